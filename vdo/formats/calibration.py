"""What the calibration exports share: stereo pairs, the pose of one camera relative to another,
Euler angles, the length unit and safe file names.

vdo's cameras (`vdo.model.camera`): x ~ K (R X + t) with R world -> camera (OpenCV axes: x right, y down,
z forward), t = -R C, world metres, pixel (0, 0) the centre of the top-left pixel, lens distortion
(k1, k2, p1, p2, k3) in OpenCV's order. The exports write lengths in millimetres (`MM` per metre),
the unit of DIC software.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from vdo.model.camera import Camera
from vdo.config.schema import NAME_PATTERN
from vdo.core.errors import ConfigError

MM = 1e3   # millimetres per metre: the exports' length unit
_SAFE = re.compile(NAME_PATTERN)     # the names the config accepts (`vdo.config.schema`)


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


def stereo_pairs(cameras: list[Camera], visible: np.ndarray, assigned: np.ndarray, requested,
                 source) -> list[StereoPair]:
    """The stereo pairs to export. `visible` (C, N): which camera sees which surface sample (the
    ray cast, `vdo.physics.visibility`); `assigned` (C, R): the regions each camera is assigned
    (`vdo.constraints.assignments`). None requested: the pairs i < j, in the cameras' order,
    assigned a common region (`vdo.constraints.shared_pairs`, the pairs whose stereo angle the
    optimizer constrains). `requested`: (first, second) name tuples, each checked: known names,
    two different cameras that both see at least one sample, else a ConfigError naming them."""
    from vdo.constraints import shared_pairs

    if requested is None:
        return [StereoPair(cameras[i], cameras[j]) for i, j in shared_pairs(assigned)]
    index = {c.name: i for i, c in enumerate(cameras)}
    pairs = []
    for first, second in requested:
        for name in (first, second):
            if name not in index:
                raise ConfigError(source, "--pairs", f"no camera named {name!r} (cameras: "
                                                     f"{', '.join(index)})")
        if first == second:
            raise ConfigError(source, "--pairs", f"{first}:{second} pairs a camera with itself")
        i, j = index[first], index[second]
        if not (visible[i] & visible[j]).any():
            raise ConfigError(source, "--pairs", f"cameras {first!r} and {second!r} share no field "
                                                 "of view (no region point is seen by both); pair "
                                                 "cameras that look at a common region")
        pairs.append(StereoPair(cameras[i], cameras[j]))
    return pairs
