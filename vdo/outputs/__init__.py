"""What a person reads: the summary, the unfolded maps, 3D views and the self-contained HTML report.
Calibration and mesh file formats are in `vdo.formats`."""
