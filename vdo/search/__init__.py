"""The optimizer's pieces: reachability of the regions from the mounts, the load path judged per
step and obscuration of the lights. The entry point is `vdo.optimize`; the constraints are
`vdo.constraints`."""
