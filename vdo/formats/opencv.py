"""OpenCV FileStorage YAML: one file per camera and one per stereo pair, readable with
`cv2.FileStorage(path, cv2.FILE_STORAGE_READ)`.

<camera>.yml: camera_name, image_width, image_height, camera_matrix (3x3, pixels),
distortion_coefficients (1x5: k1, k2, p1, p2, k3), R (3x3, world -> camera), t (3x1, mm),
units. `cv2.projectPoints(X_mm, cv2.Rodrigues(R)[0], t, camera_matrix, distortion_coefficients)`
gives the pixel of the world point X (mm).

stereo_<first>_<second>.yml: the two cameras' names, image sizes, camera matrices and distortions
(suffix _1 for the first, the reference, _2 for the second) and R, T between them in
`cv2.stereoCalibrate`'s convention, X_2 = R X_1 + T (T in mm).

The numbers are written with 17 significant digits (they read back to the same doubles).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vdo.model.camera import Camera
from vdo.formats.calibration import MM, StereoPair, file_stem


def _matrix(key: str, M) -> str:
    M = np.atleast_2d(np.asarray(M, dtype=float))
    data = ", ".join(f"{v:.17g}" for v in M.ravel())
    return (f"{key}: !!opencv-matrix\n   rows: {M.shape[0]}\n   cols: {M.shape[1]}\n   dt: d\n"
            f"   data: [ {data} ]\n")


def _write(path: Path, scalars: dict, matrices: dict) -> None:
    text = "%YAML:1.0\n---\n"
    for key, value in scalars.items():
        text += f'{key}: "{value}"\n' if isinstance(value, str) else f"{key}: {value}\n"
    for key, value in matrices.items():
        text += _matrix(key, value)
    Path(path).write_text(text)


def write(cameras: list[Camera], pairs: list[StereoPair], folder: Path, source) -> list[Path]:
    """Write <camera>.yml for every camera and stereo_<first>_<second>.yml for every pair into
    `folder`; returns the paths."""
    folder = Path(folder)
    written = []
    for c in cameras:
        path = folder / f"{file_stem(c.name, source)}.yml"
        _write(path, {"camera_name": c.name, "image_width": c.width, "image_height": c.height,
                      "units": "mm"},
               {"camera_matrix": c.K, "distortion_coefficients": np.array(c.distortion)[None],
                "R": c.R, "t": (c.t * MM)[:, None]})
        written.append(path)
    for pair in pairs:
        a, b = pair.first, pair.second
        path = folder / f"stereo_{file_stem(a.name, source)}_{file_stem(b.name, source)}.yml"
        _write(path, {"camera_name_1": a.name, "camera_name_2": b.name, "image_width_1": a.width,
                      "image_height_1": a.height, "image_width_2": b.width,
                      "image_height_2": b.height, "units": "mm"},
               {"camera_matrix_1": a.K, "distortion_coefficients_1": np.array(a.distortion)[None],
                "camera_matrix_2": b.K, "distortion_coefficients_2": np.array(b.distortion)[None],
                "R": pair.R, "T": (pair.T * MM)[:, None]})
        written.append(path)
    return written
