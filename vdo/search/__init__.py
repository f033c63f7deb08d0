"""The optimizer's pieces: the parameter vector and the camera specs it maps to
(parameterisation), the problem and its penalties (problem), the rounds and starts (solver, bfgs,
anytime), reachability of the regions from the mounts, the load path judged per step and
obscuration of the lights. The entry point is `vdo.optimize`; the constraints are
`vdo.constraints`."""
