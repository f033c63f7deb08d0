"""A camera's pose without a camera: its orientation from (pan, tilt, roll) and the aim rules, in
NumPy only, so that the experiment file (`vdo.config`) can aim and re-aim cameras without JAX.

Orientation (the conventions of `vdo.model.camera`, radians): the optical axis is
z_c = (cos tilt cos pan, cos tilt sin pan, sin tilt), pan the azimuth from world +x toward +y and
tilt the elevation (negative looks down). With roll = 0 the image x axis is horizontal,
x_0 = (sin pan, -cos pan, 0), and y_0 = z_c x x_0 points down the image; roll turns the image axes
about z_c: x_c = cos(roll) x_0 + sin(roll) y_0, y_c = -sin(roll) x_0 + cos(roll) y_0. R (world ->
camera) has rows x_c, y_c, z_c.

The functions that take `xp` (the array module: NumPy here, `jax.numpy` in `vdo.model.camera`,
which traces them) are plain arithmetic on it.
"""

from __future__ import annotations

import math

import numpy as np

MIN_AIM_DEPTH = 0.1   # m: the least depth of an aim point along the optical axis (`aim_point`)
VERTICAL_COS = 1e-3   # |cos tilt| below this: the axis is vertical, its heading undefined (`holds_aim`)


def optical_axis(pan, tilt, xp=np):
    """z_c = (cos tilt cos pan, cos tilt sin pan, sin tilt), the unit optical axis (..., 3)."""
    ct = xp.cos(tilt)
    return xp.stack([ct * xp.cos(pan), ct * xp.sin(pan), xp.sin(tilt)], axis=-1)


def axes(pan, tilt, roll, xp=np):
    """(x_0, y_0, z_c, cos roll, sin roll): the image axes before roll and the optical axis, each
    (..., 3), and the roll's cosine and sine as (..., 1) (the parts of `rotation` and of its
    derivatives in `vdo.model.camera.rotation_derivatives`)."""
    cp, sp, ct, st = xp.cos(pan), xp.sin(pan), xp.cos(tilt), xp.sin(tilt)
    x0 = xp.stack([sp, -cp, xp.zeros_like(sp)], axis=-1)
    y0 = xp.stack([st * cp, st * sp, -ct], axis=-1)
    return x0, y0, optical_axis(pan, tilt, xp), xp.cos(roll)[..., None], xp.sin(roll)[..., None]


def rotation(pan, tilt, roll, xp=np):
    """R (world -> camera), rows x_c, y_c, z_c as in the module docstring. Shape (..., 3, 3)."""
    x0, y0, z, cr, sr = axes(pan, tilt, roll, xp)
    return xp.stack([cr * x0 + sr * y0, -sr * x0 + cr * y0, z], axis=-2)


def look_at_angles(position, target) -> tuple[float, float]:
    """(pan, tilt) in radians that point the optical axis from `position` at `target` (m):
    pan = atan2(d_y, d_x), tilt = atan2(d_z, |d_xy|) for d = target - position."""
    d = np.asarray(target, dtype=float) - np.asarray(position, dtype=float)
    return float(np.arctan2(d[1], d[0])), float(np.arctan2(d[2], np.hypot(d[0], d[1])))


def aim_point(position, pan: float, tilt: float, centre) -> np.ndarray:
    """The point a camera at `position` (m) looking along (pan, tilt) keeps in the middle of its
    image when it moves on its mount (the rule of `vdo optimize`): the point of its optical axis z
    at the depth of `centre` (m, the regions' centroid), a = P + max((centre - P) . z,
    MIN_AIM_DEPTH) z, in metres."""
    position = np.asarray(position, dtype=float)
    z = optical_axis(float(pan), float(tilt))
    depth = max(float((np.asarray(centre, dtype=float) - position) @ z), MIN_AIM_DEPTH)
    return position + depth * z


def holds_aim(tilt: float) -> bool:
    """Whether a moved camera of this tilt (rad) re-aims at its `aim_point`: its axis is not
    vertical (|cos tilt| > VERTICAL_COS; vertical, the heading is undefined and pan, tilt and roll
    stay as they are)."""
    return abs(math.cos(tilt)) > VERTICAL_COS
