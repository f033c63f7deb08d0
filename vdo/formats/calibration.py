"""What the calibration exports share: stereo pairs, the pose of one camera relative to another,
Euler angles, the length unit and safe file names.

vdo's cameras (`vdo.camera`): x ~ K (R X + t) with R world -> camera (OpenCV axes: x right, y down,
z forward), t = -R C, world metres, pixel (0, 0) the centre of the top-left pixel, lens distortion
(k1, k2, p1, p2, k3) in OpenCV's order. The exports write lengths in millimetres (`MM` per metre),
the unit of DIC software.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import ConfigError

MM = 1e3   # millimetres per metre: the exports' length unit
_SAFE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")


def file_stem(name: str, source) -> str:
    """A camera name as part of a file name: letters, digits, '_', '.', '-', not starting with
    '.', at most 64 characters; anything else is a ConfigError (names never become paths unchecked)."""
    if not _SAFE.fullmatch(name):
        raise ConfigError(source, f'camera "{name}".name',
                          "cannot name an export file: use letters, digits, '_', '.' or '-' "
                          "(at most 64, not starting with '.')")
    return name


@dataclass(frozen=True)
class StereoPair:
    """Cameras `first` (the reference) and `second`; X_2 = R X_1 + T (camera frames, metres)."""

    first: Camera
    second: Camera

    @property
    def R(self) -> np.ndarray:
        """R_2 R_1^T: camera 1 axes -> camera 2 axes."""
        return self.second.R @ self.first.R.T

    @property
    def T(self) -> np.ndarray:
        """t_2 - R t_1 (m), so that X_2 = R X_1 + T for any point (X_i = R_i X + t_i)."""
        return self.second.t - self.R @ self.first.t

    @property
    def stem(self) -> str:
        return f"{self.first.name}_{self.second.name}"


def euler_xyz_deg(R: np.ndarray) -> tuple[float, float, float]:
    """(a, b, c) in degrees with R = Rz(c) Ry(b) Rx(a) (rotations about the fixed x, then y, then z
    axis): a = atan2(R21, R22), b = atan2(-R20, sqrt(R00^2 + R10^2)), c = atan2(R10, R00);
    b in [-90, 90] deg (at b = +-90 deg, c = 0 and a takes the rest)."""
    R = np.asarray(R, dtype=float)
    sy = math.hypot(R[0, 0], R[1, 0])
    if sy > 1e-12:
        a, b, c = math.atan2(R[2, 1], R[2, 2]), math.atan2(-R[2, 0], sy), math.atan2(R[1, 0], R[0, 0])
    else:
        a, b, c = math.atan2(-R[1, 2], R[1, 1]), math.atan2(-R[2, 0], sy), 0.0
    return math.degrees(a), math.degrees(b), math.degrees(c)


def in_image(camera: Camera, X: np.ndarray) -> np.ndarray:
    """(N,) True where the point lies in front of the camera and its (distorted) image falls
    inside the pixel area [-0.5, W - 0.5] x [-0.5, H - 0.5]."""
    front = (np.asarray(X) @ camera.R[2] + camera.t[2]) > 0
    uv = camera.project(X)
    inside = ((uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width - 0.5)
              & (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height - 0.5))
    return front & inside


def stereo_pairs(cameras: list[Camera], points: np.ndarray, requested, source) -> list[StereoPair]:
    """The stereo pairs to export. Two cameras share a field of view when at least one of
    `points` (the regions' surface samples, m) lies in both images (`in_image`; occlusion not
    considered). `requested`: (first, second) name tuples, each checked (known names, two
    different cameras, a shared field of view, else a ConfigError naming them); None: every pair
    i < j in the cameras' order that shares a field of view."""
    by_name = {c.name: c for c in cameras}
    seen = {c.name: in_image(c, points) for c in cameras}
    if requested is None:
        return [StereoPair(a, b) for i, a in enumerate(cameras) for b in cameras[i + 1:]
                if (seen[a.name] & seen[b.name]).any()]
    pairs = []
    for first, second in requested:
        for name in (first, second):
            if name not in by_name:
                raise ConfigError(source, "--pairs", f"no camera named {name!r} (cameras: "
                                                     f"{', '.join(by_name)})")
        if first == second:
            raise ConfigError(source, "--pairs", f"{first}:{second} pairs a camera with itself")
        if not (seen[first] & seen[second]).any():
            raise ConfigError(source, "--pairs", f"cameras {first!r} and {second!r} share no field "
                                                 "of view (no region point lies in both images); "
                                                 "pair cameras that look at a common region")
        pairs.append(StereoPair(by_name[first], by_name[second]))
    return pairs
