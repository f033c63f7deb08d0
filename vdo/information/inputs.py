"""What the mean-field information is computed from, as equinox Modules (pytrees whose arrays
`equinox.filter_jit` traces): the cameras (`CameraParams`, C cameras as arrays), the surface
samples (`Samples`, N samples in R regions) and the static `Settings` (hashable: changing one
recompiles); `KAPPA_BOX`, the blur std of a box pixel. Lengths in metres, angles in radians,
image quantities in pixels. `vdo.objective` re-exports all four.

The bottom of `vdo.information`: it imports `vdo.core` only (`CameraParams.from_cameras` reads
`vdo.model.camera.Camera` objects by their attributes)."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from vdo.core.configure import require_x64
from vdo.core.tolerances import IN_FRONT_M

KAPPA_BOX = 1.0 / math.sqrt(12.0)  # std of a box pixel, in pixels (docs/theory.md)


class CameraParams(eqx.Module):
    """C cameras as arrays. position (C, 3) m; pan, tilt, roll (C,) rad (`vdo.model.camera` convention);
    focal_px, cx, cy (C,) pixels; width, height (C,) pixel counts (floats; constants: the score's
    gradient with respect to them is 0); distortion (C, 5) the Brown-Conrady coefficients in
    `vdo.model.camera.DISTORTION` order (constants), or None for pinholes (the programs then hold no
    distortion arithmetic at all: `vdo.objective`'s docstring, "Lens distortion")."""

    position: jax.Array
    pan: jax.Array
    tilt: jax.Array
    roll: jax.Array
    focal_px: jax.Array
    cx: jax.Array
    cy: jax.Array
    width: jax.Array
    height: jax.Array
    distortion: jax.Array | None = None

    def __check_init__(self):
        require_x64()  # float64 inputs would silently become float32

    @classmethod
    def from_cameras(cls, cameras) -> "CameraParams":
        """Stack `vdo.model.camera.Camera` objects (distortion None unless one of them is distorted)."""
        f = lambda get: jnp.asarray(np.array([get(c) for c in cameras], dtype=np.float64))
        distorted = any(c.distorted for c in cameras)
        return cls(position=f(lambda c: np.asarray(c.position, dtype=float)),
                   pan=f(lambda c: c.pan), tilt=f(lambda c: c.tilt), roll=f(lambda c: c.roll),
                   focal_px=f(lambda c: c.focal_px), cx=f(lambda c: c.principal_point[0]),
                   cy=f(lambda c: c.principal_point[1]), width=f(lambda c: c.width),
                   height=f(lambda c: c.height),
                   distortion=f(lambda c: c.distortion) if distorted else None)


class Samples(eqx.Module):
    """N surface samples. points, normals, tangent_u, tangent_v (N, 3) (unit, t_u x t_v = n);
    area (N,) m^2; region (N,) int in [0, R); per region: importance (R,) (weight in the score) and
    min_cameras (R,) (coverage requirement, e.g. 2, or 3 on the joint)."""

    points: jax.Array
    normals: jax.Array
    tangent_u: jax.Array
    tangent_v: jax.Array
    area: jax.Array
    region: jax.Array
    importance: jax.Array
    min_cameras: jax.Array


class Settings(eqx.Module):
    """Static settings (all hashable; changing one recompiles).

    kappa              pixel blur std in pixels (1/sqrt 12: box pixel)
    patch_area         Omega, the DIC patch (subset/element) area, m^2
    incidence_limit    theta_lim, rad: weight 0 at and beyond it
    incidence_ramp     rad: weight reaches 1 at theta_lim - ramp
    image_margin_px    px: weight 0 at the image edge, 1 this far inside
    near               m: in front means Z_c > near
    prior_sigma        m: regularising prior std for the score (C + I/prior_sigma^2)
    sigma_unit         m: unit of the score's uncertainty term (1e-6: micrometres)
    score_power        q of the weighted power mean over samples
    eigen_power        p >= 2 of the trace p-norm that smooths lam_max(Sigma)
    coverage_weight    weight of the coverage penalty (per camera^2 of deficit, area fraction)
    gap_eps            relative floor of the eigenvalue gap of A A^T (error O(gap_eps^2))
    rank_rtol          `fields`: eigenvalue ratio below which C counts as rank deficient
    pair_dtype         "float64" or "float32": dtype of the per-pair geometry, tensor and table
                       lookup in `score` and `score_and_grad` (`vdo.information.blocks`, "Precision");
                       the assembly of each pair's 3x3, the per-sample sums and the score are
                       float64 either way, and the reports (`fields`, `information`,
                       `camera_information`) always run float64
    """

    kappa: float = eqx.field(static=True, default=KAPPA_BOX)
    patch_area: float = eqx.field(static=True, default=1e-4)
    incidence_limit: float = eqx.field(static=True, default=math.radians(70.0))
    incidence_ramp: float = eqx.field(static=True, default=math.radians(10.0))
    image_margin_px: float = eqx.field(static=True, default=10.0)
    near: float = eqx.field(static=True, default=IN_FRONT_M)
    prior_sigma: float = eqx.field(static=True, default=1e-3)
    sigma_unit: float = eqx.field(static=True, default=1e-6)
    score_power: float = eqx.field(static=True, default=8.0)
    eigen_power: int = eqx.field(static=True, default=8)
    coverage_weight: float = eqx.field(static=True, default=1e3)
    gap_eps: float = eqx.field(static=True, default=1e-4)
    rank_rtol: float = eqx.field(static=True, default=1e-10)
    pair_dtype: str = eqx.field(static=True, default="float64")
