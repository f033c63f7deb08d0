"""The renders' machinery, whose public face is `vdo.render`: the Mitsuba scene, the sensor and
the exposure of one camera (`scene`), and the DIC render mode (`dic`: one primary ray per pixel,
the speckle averaged over the pixel's footprint, `footprint`; `shading`: the light each hit
reflects; `lightmap`: that light in surface space, kept for a camera over the load steps it holds
for)."""
