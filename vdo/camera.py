"""The one camera model: a pinhole with square pixels, its pose, projection and Jacobians.

Conventions (stated once, tested in tests/test_camera.py):

* World frame: right-handed, z up, metres.
* Camera frame: OpenCV, x right, y down, z forward (the optical axis).
* Pixels: (u, v) = (column, row); pixel (0, 0) is the *centre* of the top-left pixel.
* Projection: x ~ K (R X + t), K = [[f, 0, cx], [0, f, cy], [0, 0, 1]] with f = focal length / pixel
  pitch in pixels; R (world -> camera) and t = -R C for optical centre C.
* Orientation from (pan, tilt, roll), radians: the optical axis is
  z_c = (cos tilt cos pan, cos tilt sin pan, sin tilt), i.e. pan is the azimuth from world +x toward
  +y and tilt the elevation (negative looks down). With roll = 0 the image x axis is horizontal,
  x_0 = (sin pan, -cos pan, 0), and y_0 = z_c x x_0 points down the image. Roll turns the image
  axes about z_c: x_c = cos(roll) x_0 + sin(roll) y_0, y_c = -sin(roll) x_0 + cos(roll) y_0.
  This is well defined looking straight down (tilt = -90 deg), where pan sets the image heading.
* Mitsuba's `perspective` sensor looks along +z with +x to the image *left* and +y up, and its film
  pixel (0, 0) is the top-left *corner*; `mitsuba_to_world` and `mitsuba_principal_offset` are the
  only place that converts (diag(-1, -1, 1) on the camera axes, half a pixel on the film).

The functions below are pure `jax.numpy` so they trace under jit/vmap/grad; `Camera` bundles one
configured camera for the rest of the program.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)


# --------------------------------------------------------------------------------------------
# Orientation
# --------------------------------------------------------------------------------------------
def _axes(pan, tilt, roll):
    cp, sp, ct, st = jnp.cos(pan), jnp.sin(pan), jnp.cos(tilt), jnp.sin(tilt)
    cr, sr = jnp.cos(roll), jnp.sin(roll)
    z = jnp.stack([ct * cp, ct * sp, st], axis=-1)
    x0 = jnp.stack([sp, -cp, jnp.zeros_like(sp)], axis=-1)
    y0 = jnp.stack([st * cp, st * sp, -ct], axis=-1)
    return x0, y0, z, cr[..., None], sr[..., None]


def rotation(pan, tilt, roll):
    """R (world -> camera), rows x_c, y_c, z_c as in the module docstring. Shape (..., 3, 3)."""
    x0, y0, z, cr, sr = _axes(pan, tilt, roll)
    return jnp.stack([cr * x0 + sr * y0, -sr * x0 + cr * y0, z], axis=-2)


_rotation_jit = jax.jit(rotation)


def rotation_derivatives(pan, tilt, roll):
    """dR/dpan, dR/dtilt, dR/droll in closed form, each (..., 3, 3)."""
    cp, sp, ct, st = jnp.cos(pan), jnp.sin(pan), jnp.cos(tilt), jnp.sin(tilt)
    x0, y0, z, cr, sr = _axes(pan, tilt, roll)
    zero = jnp.zeros_like(sp)
    dz_dp = jnp.stack([-ct * sp, ct * cp, zero], -1)
    dz_dt = jnp.stack([-st * cp, -st * sp, ct], -1)
    dx0_dp = jnp.stack([cp, sp, zero], -1)
    dy0_dp = jnp.stack([-st * sp, st * cp, zero], -1)
    dy0_dt = jnp.stack([ct * cp, ct * sp, st], -1)
    x = cr * x0 + sr * y0
    y = -sr * x0 + cr * y0
    d_pan = jnp.stack([cr * dx0_dp + sr * dy0_dp, -sr * dx0_dp + cr * dy0_dp, dz_dp], -2)
    d_tilt = jnp.stack([sr * dy0_dt, cr * dy0_dt, dz_dt], -2)
    d_roll = jnp.stack([y, -x, jnp.zeros_like(z)], -2)
    return d_pan, d_tilt, d_roll


def look_at_angles(position, target):
    """(pan, tilt) in radians that point the optical axis from `position` at `target`."""
    d = np.asarray(target, dtype=float) - np.asarray(position, dtype=float)
    return float(np.arctan2(d[1], d[0])), float(np.arctan2(d[2], np.hypot(d[0], d[1])))


# --------------------------------------------------------------------------------------------
# Projection and its Jacobians
# --------------------------------------------------------------------------------------------
def intrinsic_matrix(focal_px, cx, cy):
    """K for square pixels, in pixels."""
    z, o = jnp.zeros_like(focal_px), jnp.ones_like(focal_px)
    return jnp.stack([jnp.stack([focal_px, z, cx], -1), jnp.stack([z, focal_px, cy], -1),
                      jnp.stack([z, z, o], -1)], -2)


def to_camera(R, t, X):
    """Camera-frame coordinates R X + t, metres."""
    return jnp.einsum("...ij,...j->...i", R, X) + t


def project(K, R, t, X):
    """Pixel coordinates (u, v) of world points X (..., 3) -> (..., 2)."""
    p = to_camera(R, t, X)
    uvw = jnp.einsum("...ij,...j->...i", K, p)
    return uvw[..., :2] / uvw[..., 2:3]


def _d_pixel_d_camera(K, p):
    """d(u, v)/d(camera-frame point), (..., 2, 3), pixels per metre."""
    fx, fy = K[..., 0, 0], K[..., 1, 1]
    zinv = 1.0 / p[..., 2]
    xz, yz = p[..., 0] * zinv, p[..., 1] * zinv
    zero = jnp.zeros_like(zinv)
    return jnp.stack([jnp.stack([fx * zinv, zero, -fx * xz * zinv], -1),
                      jnp.stack([zero, fy * zinv, -fy * yz * zinv], -1)], -2)


def sensitivity(K, R, t, X):
    """s = dx/dX (..., 2, 3) in pixel/m (paper eq. 4):
    s = (f / Z_c) [[1, 0, -X_c/Z_c], [0, 1, -Y_c/Z_c]] R."""
    return _d_pixel_d_camera(K, to_camera(R, t, X)) @ R


PARAMETERS = ("x", "y", "z", "pan", "tilt", "roll", "focal_px")


def parameter_jacobian(focal_px, cx, cy, position, pan, tilt, roll, X):
    """dx/d(camera parameters) at world points X, (..., 2, 7), columns in `PARAMETERS` order:
    optical centre (pixel/m), pan/tilt/roll (pixel/rad), focal length in pixels (pixel/pixel).

    With p = R (X - C): dx/dC = -J R, dx/dθ = J (dR/dθ)(X - C), du/df = X_c/Z_c, dv/df = Y_c/Z_c,
    where J = d(u, v)/dp."""
    R = rotation(pan, tilt, roll)
    K = intrinsic_matrix(focal_px, cx, cy)
    rel = X - position
    p = jnp.einsum("...ij,...j->...i", R, rel)
    J = _d_pixel_d_camera(K, p)
    columns = [-(J @ R)]
    for dR in rotation_derivatives(pan, tilt, roll):
        columns.append((J @ jnp.einsum("...ij,...j->...i", dR, rel))[..., None])
    columns.append((p[..., :2] / p[..., 2:3])[..., None])
    return jnp.concatenate(columns, axis=-1)


# --------------------------------------------------------------------------------------------
# One configured camera
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Camera:
    """A camera: sensor, lens and pose. Lengths in metres, angles in radians.

    `principal_offset_px` shifts the principal point from the image centre ((W-1)/2, (H-1)/2)."""

    name: str
    width: int
    height: int
    pixel_size: float
    focal_length: float
    position: np.ndarray
    pan: float
    tilt: float
    roll: float = 0.0
    principal_offset_px: tuple[float, float] = (0.0, 0.0)

    @property
    def focal_px(self) -> float:
        return self.focal_length / self.pixel_size

    @property
    def principal_point(self) -> tuple[float, float]:
        return ((self.width - 1) / 2 + self.principal_offset_px[0],
                (self.height - 1) / 2 + self.principal_offset_px[1])

    @cached_property
    def K(self) -> np.ndarray:
        cx, cy = self.principal_point
        return np.asarray(intrinsic_matrix(jnp.float64(self.focal_px), jnp.float64(cx), jnp.float64(cy)))

    @cached_property
    def R(self) -> np.ndarray:
        # one compiled call: eager, the ~20 operations cost ~15 ms per camera under load
        return np.asarray(_rotation_jit(jnp.float64(self.pan), jnp.float64(self.tilt), jnp.float64(self.roll)))

    @cached_property
    def t(self) -> np.ndarray:
        return -self.R @ np.asarray(self.position, dtype=float)

    @property
    def optical_axis(self) -> np.ndarray:
        return self.R[2]

    def project(self, X) -> np.ndarray:
        return np.asarray(project(self.K, self.R, self.t, jnp.asarray(X, dtype=jnp.float64)))

    def sensitivity(self, X) -> np.ndarray:
        return np.asarray(sensitivity(self.K, self.R, self.t, jnp.asarray(X, dtype=jnp.float64)))

    def with_pose(self, position, pan, tilt, roll=None) -> "Camera":
        return replace(self, position=np.asarray(position, dtype=float), pan=float(pan),
                       tilt=float(tilt), roll=self.roll if roll is None else float(roll))

    # -- Mitsuba conversion: the one place where its conventions enter -----------------------
    def mitsuba_to_world(self) -> np.ndarray:
        """4x4 camera-to-world matrix for Mitsuba's sensor: columns -x_c, -y_c, z_c, C."""
        M = np.eye(4)
        M[:3, :3] = self.R.T @ np.diag([-1.0, -1.0, 1.0])
        M[:3, 3] = self.position
        return M

    def mitsuba_fov_deg(self) -> float:
        """Horizontal field of view (fov_axis = 'x') across the film's full width."""
        return float(np.degrees(2 * np.arctan(self.width / (2 * self.focal_px))))

    def mitsuba_principal_offset(self) -> tuple[float, float]:
        """Mitsuba's principal_point_offset_x/y: shift of the principal point from the film centre
        as a fraction of the film size. OpenCV's cx = (W - 1)/2 + dx is Mitsuba's W/2 + dx on its
        corner-origin film; Mitsuba's sign on this offset is opposite to the image axes (checked
        against renders in tests/test_render_alignment.py)."""
        dx, dy = self.principal_offset_px
        return -dx / self.width, -dy / self.height
