"""Where things are at a step: keyframes (rigid poses of mesh groups, nodal displacements) of the
load path. The scene itself is `vdo.scene`."""
