"""Files for other programs: calibration exports for DIC software.

`calibration` holds what every format shares (stereo pairs, relative poses, angles, units, file
names); `opencv`, `matchid`, `dice` and `vic3d` each write one format from `vdo.model.camera.Camera`
objects; `export` is `vdo export` (cameras from an experiment TOML or a run folder's layout.json).
Each format's conventions and their public sources: docs/exports.md.
"""
