"""The renders' machinery, whose public face is `vdo.render`: the Mitsuba scene, the sensor and
the exposure of one camera (`scene`), and the DIC render mode (`dic`: one primary ray per pixel,
the speckle averaged over the pixel's footprint; `shading`: the light each hit reflects;
`lightmap`: that light in surface space, shared by a frame's cameras and load steps)."""
