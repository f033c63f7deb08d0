"""The one camera model: a pinhole with square pixels, its pose, projection and Jacobians.

Conventions (stated once, tested in tests/model/test_camera.py):

* World frame: right-handed, z up, metres.
* Camera frame: OpenCV, x right, y down, z forward (the optical axis).
* Pixels: (u, v) = (column, row); pixel (0, 0) is the *centre* of the top-left pixel.
* Projection: x ~ K (R X + t), K = [[f, 0, cx], [0, f, cy], [0, 0, 1]] with f = focal length / pixel
  pitch in pixels; R (world -> camera) and t = -R C for optical centre C.
* Lens distortion: Brown-Conrady as OpenCV models it, coefficients in OpenCV's order
  (k1, k2, p1, p2, k3) acting on the normalised coordinates (x, y) = (X_c/Z_c, Y_c/Z_c):
  r^2 = x^2 + y^2, x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2),
  y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y, then (u, v) = K (x_d, y_d, 1).
  Zero by default (a pinhole).
* Orientation from (pan, tilt, roll), radians, as `vdo.model.pose` states it (NumPy there, for the
  config; the same functions in JAX here): the optical axis is
  z_c = (cos tilt cos pan, cos tilt sin pan, sin tilt), pan the azimuth from world +x toward +y,
  tilt the elevation (negative looks down); with roll = 0 the image x axis is horizontal and roll
  turns the image axes about z_c. This is well defined looking straight down (tilt = -90 deg),
  where pan sets the image heading.
* Mitsuba's `perspective` sensor looks along +z with +x to the image *left* and +y up, and its film
  pixel (0, 0) is the top-left *corner*; `mitsuba_to_world` and `mitsuba_principal_offset` are the
  only place that converts (diag(-1, -1, 1) on the camera axes, half a pixel on the film).

The functions below are `jax.numpy` so they trace under jit/vmap/grad; the orientation, the
intrinsics, the projection and its point Jacobian (`rotation`, `intrinsic_matrix`, `to_camera`,
`project`, `sensitivity`) take the array module as `xp`, so that `Camera.R`, `Camera.K`,
`Camera.project` and `Camera.sensitivity` (NumPy in, NumPy out, for `vdo.dic.correlate`, the checks,
the exports) run the same arithmetic in NumPy, without a JAX dispatch per operation. `Camera`
bundles one configured camera for the rest of the program.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import jax.numpy as jnp
import numpy as np

from vdo.core.configure import require_x64
from vdo.model import pose


# --------------------------------------------------------------------------------------------
# Orientation
# --------------------------------------------------------------------------------------------
def rotation(pan, tilt, roll, xp=jnp):
    """R (world -> camera), `vdo.model.pose.rotation` in JAX by default (traceable). Shape
    (..., 3, 3). `xp`: the array module (NumPy for host callers: `Camera.R`)."""
    return pose.rotation(pan, tilt, roll, xp)


def rotation_derivatives(pan, tilt, roll):
    """dR/dpan, dR/dtilt, dR/droll in closed form, each (..., 3, 3)."""
    cp, sp, ct, st = jnp.cos(pan), jnp.sin(pan), jnp.cos(tilt), jnp.sin(tilt)
    x0, y0, z, cr, sr = pose.axes(pan, tilt, roll, jnp)
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


# --------------------------------------------------------------------------------------------
# Projection and its Jacobians
# --------------------------------------------------------------------------------------------
def intrinsic_matrix(focal_px, cx, cy, xp=jnp):
    """K for square pixels, in pixels. `xp`: the array module, as in `rotation`."""
    z, o = xp.zeros_like(focal_px), xp.ones_like(focal_px)
    return xp.stack([xp.stack([focal_px, z, cx], -1), xp.stack([z, focal_px, cy], -1),
                     xp.stack([z, z, o], -1)], -2)


def to_camera(R, t, X, xp=jnp):
    """Camera-frame coordinates R X + t, metres. `xp`: the array module (jax.numpy, or NumPy for
    NumPy callers: no JAX dispatch per operation, see `Camera.project`)."""
    return xp.einsum("...ij,...j->...i", R, X) + t


DISTORTION = ("k1", "k2", "p1", "p2", "k3")   # OpenCV's order of the coefficients


def _coefficients(distortion):
    """(k1, k2, p1, p2, k3) from a (..., 5) array or a tuple of five."""
    if isinstance(distortion, (tuple, list)):
        return tuple(distortion)
    return tuple(distortion[..., i] for i in range(5))


def distort(x, y, distortion):
    """Brown-Conrady distortion of normalised coordinates (x, y) (module docstring) -> (x_d, y_d).
    `distortion` (..., 5) in `DISTORTION` order (or a tuple of the 5), None for none. Plain
    arithmetic, so NumPy, JAX and Dr.Jit arrays all work."""
    if distortion is None:
        return x, y
    k1, k2, p1, p2, k3 = _coefficients(distortion)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


def distortion_jacobian(x, y, distortion):
    """d(x_d, y_d)/d(x, y) as the four entries (dxx, dxy, dyx, dyy), dxy = dx_d/dy:
    dx_d/dx = L + 2 x^2 L' + 2 p1 y + 6 p2 x, dx_d/dy = 2 x y L' + 2 p1 x + 2 p2 y,
    dy_d/dx = 2 x y L' + 2 p1 x + 2 p2 y, dy_d/dy = L + 2 y^2 L' + 6 p1 y + 2 p2 x, with
    L = 1 + k1 r^2 + k2 r^4 + k3 r^6 and L' = dL/d(r^2) = k1 + 2 k2 r^2 + 3 k3 r^4."""
    k1, k2, p1, p2, k3 = _coefficients(distortion)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    slope = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)
    cross = 2.0 * x * y * slope + 2.0 * p1 * x + 2.0 * p2 * y
    return (radial + 2.0 * x * x * slope + 2.0 * p1 * y + 6.0 * p2 * x, cross, cross,
            radial + 2.0 * y * y * slope + 6.0 * p1 * y + 2.0 * p2 * x)


def distortion_curvature(x, y, distortion):
    """The derivatives of `distortion_jacobian`'s entries (a, b, d) = (dx_d/dx, dx_d/dy = dy_d/dx,
    dy_d/dy) along x and y, as their four distinct values (da/dx, da/dy = db/dx, db/dy = dd/dx,
    dd/dy) (the Jacobian is symmetric, so these are the third derivatives of one potential):
    da/dx = 6 x L' + 4 x^3 L'' + 6 p2, da/dy = 2 y L' + 4 x^2 y L'' + 2 p1,
    db/dy = 2 x L' + 4 x y^2 L'' + 2 p2, dd/dy = 6 y L' + 4 y^3 L'' + 6 p1, with L' as in
    `distortion_jacobian` and L'' = 2 k2 + 6 k3 r^2. For the reverse pass of `vdo.information.blocks`."""
    k1, k2, p1, p2, k3 = _coefficients(distortion)
    r2 = x * x + y * y
    slope = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)
    bend = 2.0 * k2 + 6.0 * k3 * r2
    return (x * (6.0 * slope + 4.0 * x * x * bend) + 6.0 * p2,
            y * (2.0 * slope + 4.0 * x * x * bend) + 2.0 * p1,
            x * (2.0 * slope + 4.0 * y * y * bend) + 2.0 * p2,
            y * (6.0 * slope + 4.0 * y * y * bend) + 6.0 * p1)


def image_point(K, x, y, distortion=None):
    """Pixel (u, v) of the normalised point (x, y): distortion, then K (u = f_x x_d + s y_d + c_x,
    v = f_y y_d + c_y). The one step from the camera frame to pixels: `project`, its Jacobians,
    `vdo.dic.correlate`, the visibility kernel, the objective and the field-of-view penalty all go
    through here. `K` is a (..., 3, 3) matrix or its entries (f_x, s, c_x, f_y, c_y), s None for
    no skew (for the Dr.Jit kernel and the objective's per-pair tables). Plain arithmetic
    (NumPy, JAX or Dr.Jit)."""
    if isinstance(K, tuple):
        fx, s, cx, fy, cy = K
    else:
        fx, s, cx, fy, cy = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2], K[..., 1, 1], K[..., 1, 2]
    xd, yd = distort(x, y, distortion)
    return (fx * xd + cx if s is None else fx * xd + s * yd + cx), fy * yd + cy


def project(K, R, t, X, distortion=None, xp=jnp):
    """Pixel coordinates (u, v) of world points X (..., 3) -> (..., 2), with the lens distortion
    (..., 5) in `DISTORTION` order (None: a pinhole)."""
    p = to_camera(R, t, X, xp)
    return xp.stack(image_point(K, p[..., 0] / p[..., 2], p[..., 1] / p[..., 2], distortion), axis=-1)


def _d_pixel_d_camera(K, p, distortion=None, xp=jnp):
    """d(u, v)/d(camera-frame point), (..., 2, 3), pixels per metre: the chain
    [[f_x, s], [0, f_y]] . d(x_d, y_d)/d(x, y) . (1/Z_c) [[1, 0, -x], [0, 1, -y]]."""
    zinv = 1.0 / p[..., 2]
    x, y = p[..., 0] * zinv, p[..., 1] * zinv
    zero = xp.zeros_like(zinv)
    dn = xp.stack([xp.stack([zinv, zero, -x * zinv], -1),
                   xp.stack([zero, zinv, -y * zinv], -1)], -2)           # d(x, y)/dp
    fx, s, fy = K[..., 0, 0], K[..., 0, 1], K[..., 1, 1]
    if distortion is None:
        a, b, c, d = fx, s, zero, fy
    else:
        dxx, dxy, dyx, dyy = distortion_jacobian(x, y, distortion)
        a, b = fx * dxx + s * dyx, fx * dxy + s * dyy
        c, d = fy * dyx, fy * dyy
    M = xp.stack([xp.stack([a + zero, b + zero], -1), xp.stack([c + zero, d + zero], -1)], -2)
    return M @ dn


def sensitivity(K, R, t, X, distortion=None, xp=jnp):
    """s = dx/dX (..., 2, 3) in pixel/m (paper eq. 4, with the distortion's Jacobian D):
    s = [[f_x, s], [0, f_y]] D (1 / Z_c) [[1, 0, -X_c/Z_c], [0, 1, -Y_c/Z_c]] R."""
    return _d_pixel_d_camera(K, to_camera(R, t, X, xp), distortion, xp) @ R


def undistort(x_d, y_d, distortion, iterations: int = 20):
    """The normalised (x, y) whose distortion is (x_d, y_d): Newton's method on `distort` with
    `distortion_jacobian`, from (x_d, y_d) (NumPy arrays), a fixed number of steps (it converges
    quadratically where the distortion does not fold the image; checked against
    cv2.undistortPoints to 1e-6 px in tests/model/test_distortion.py)."""
    x, y = np.array(x_d, dtype=float), np.array(y_d, dtype=float)
    for _ in range(iterations):
        fx, fy = distort(x, y, distortion)
        rx, ry = fx - x_d, fy - y_d
        a, b, c, d = distortion_jacobian(x, y, distortion)
        det = a * d - b * c
        x, y = x - (d * rx - b * ry) / det, y - (a * ry - c * rx) / det
    return x, y


PARAMETERS = ("x", "y", "z", "pan", "tilt", "roll", "focal_px")


def parameter_jacobian(focal_px, cx, cy, position, pan, tilt, roll, X, distortion=None):
    """dx/d(camera parameters) at world points X, (..., 2, 7), columns in `PARAMETERS` order:
    optical centre (pixel/m), pan/tilt/roll (pixel/rad), focal length in pixels (pixel/pixel).

    With p = R (X - C): dx/dC = -J R, dx/dθ = J (dR/dθ)(X - C), du/df = x_d, dv/df = y_d (the
    distorted normalised coordinates), where J = d(u, v)/dp (`_d_pixel_d_camera`)."""
    R = rotation(pan, tilt, roll)
    K = intrinsic_matrix(focal_px, cx, cy)
    rel = X - position
    p = jnp.einsum("...ij,...j->...i", R, rel)
    J = _d_pixel_d_camera(K, p, distortion)
    columns = [-(J @ R)]
    for dR in rotation_derivatives(pan, tilt, roll):
        columns.append((J @ jnp.einsum("...ij,...j->...i", dR, rel))[..., None])
    columns.append(jnp.stack(distort(p[..., 0] / p[..., 2], p[..., 1] / p[..., 2], distortion),
                             -1)[..., None])
    return jnp.concatenate(columns, axis=-1)


# --------------------------------------------------------------------------------------------
# One configured camera
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Camera:
    """A camera: sensor, lens and pose. Lengths in metres, angles in radians.

    `principal_offset_px` shifts the principal point from the image centre ((W-1)/2, (H-1)/2).
    `distortion` holds the lens distortion (k1, k2, p1, p2, k3) in OpenCV's order (module
    docstring); all zero is a pinhole."""

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
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def distorted(self) -> bool:
        return any(c != 0.0 for c in self.distortion)

    def __post_init__(self):
        require_x64()  # K, R and the projections below are float64 JAX computations

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
        return intrinsic_matrix(np.float64(self.focal_px), np.float64(cx), np.float64(cy), xp=np)

    @cached_property
    def R(self) -> np.ndarray:
        return rotation(np.float64(self.pan), np.float64(self.tilt), np.float64(self.roll), xp=np)

    @cached_property
    def t(self) -> np.ndarray:
        return -self.R @ np.asarray(self.position, dtype=float)

    @property
    def optical_axis(self) -> np.ndarray:
        return self.R[2]

    @property
    def distortion_array(self) -> np.ndarray | None:
        """The distortion as a (5,) array, or None for a pinhole (the projection's argument)."""
        return np.asarray(self.distortion, dtype=float) if self.distorted else None

    def project(self, X) -> np.ndarray:
        return project(self.K, self.R, self.t, np.asarray(X, dtype=np.float64),
                       self.distortion_array, xp=np)

    def sensitivity(self, X) -> np.ndarray:
        return sensitivity(self.K, self.R, self.t, np.asarray(X, dtype=np.float64),
                           self.distortion_array, xp=np)

    def undistorted_pixels(self, uv) -> np.ndarray:
        """Where the pixels uv (..., 2) of this camera's (distorted) image lie in the image of the
        same camera without distortion (same K): K (undistort(K^-1 uv)), pixels."""
        uv = np.asarray(uv, dtype=float)
        (fx, s, cx), (_, fy, cy) = self.K[0], self.K[1]
        yd = (uv[..., 1] - cy) / fy
        x, y = undistort((uv[..., 0] - cx - s * yd) / fx, yd, np.asarray(self.distortion, dtype=float))
        return np.stack(image_point(self.K, x, y), axis=-1)

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
