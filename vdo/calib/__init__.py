"""Calibration: the lab's calibration session planned, rendered, calibrated (OpenCV detection, a
joint bundle adjustment) and its uncertainty carried into displacement and strain
(docs/calibration.md)."""
