"""Mean-field DIC uncertainty of a multi-camera layout, and the scalar score the optimizer minimises.

Pure `jax.numpy` (float64, or float32 per pair: `Settings.pair_dtype`), differentiable with respect to
every camera parameter but the pixel counts (width, height). docs/theory.md
and the paper's sec. 5.3-5.4 give the model; this module implements it with the paper's loose
notation made exact. Notation, per camera i and surface sample X (normal n, unit tangents t_u, t_v with
t_u x t_v = n, surface coordinates xi in metres along them):

sensitivity   s_i = dx_i/dX = (f / Z_c) D [[1, 0, -X_c/Z_c], [0, 1, -Y_c/Z_c]] R_i  (2x3, pixel/m)
              (D the lens distortion's Jacobian, I for a pinhole: "Lens distortion" below)
footprint     A_i = s_i [t_u t_v]                                               (2x2, pixel/m)
              A A^T = sum_k a_k^2 v_k v_k^T, v_k in the image; a_k = pixels per metre of surface
              along e_k; the pixel blur (Gaussian, std kappa pixels) is std l_k = kappa / a_k (m)
              on the surface along e_k.
gradient      T_i = c_i^2 sum_k G(l_k, l_other) / a_k^2 v_k v_k^T                (gray^2/pixel^2)
tensor        G(l_par, l_perp) = <(d_e (G_blur * f_hat))^2> (1/m^2) is the directional gradient
              energy of the normalised speckle f_hat under an anisotropic Gaussian blur (std l_par
              along e, l_perp across), G(l, l) = g_f(l) (`vdo.model.speckle`).
information   C_i = (1/sigma_i)^2 s_i^T T_i s_i                         (3x3, 1/m^2 per pixel)
per sample    C = Omega sum_i w_i |det A_i| C_i                                       (1/m^2)
              |det A_i| = a_1 a_2 is the pixel density (pixel/m^2), Omega the DIC patch area (m^2),
              w_i in [0, 1] the camera's soft usable weight (below).
covariance    Sigma = C^-1 (m^2): the Cramer-Rao bound for ONE noisy image against a perfect
              reference. When both images are noisy the measured variance is about 2x (sigma x sqrt 2);
              spline correlation on sampled images loses a further 10-15 %.
sensitivity   S_k = sqrt(sum_i w_i |s_i[:, k]|^2) (pixel/m) per world axis k (paper sec. 5.2).
(global)

Numerical care (all derivatives stay finite):

* T as a matrix function of M = A A^T, with no SVD/eigh: the exact spectral formula with the
  eigenvalue gap floored, finite and differentiable also where a_1 = a_2 (a fronto-parallel view);
  `vdo.information.tensor` gives the formula and its error (O(gap_eps^2)).
* lam_max(Sigma) for the score uses the trace p-norm (tr Sigma^p)^(1/p) (`Settings.eigen_power`
  p, default 8), computed from the invariants of C by Newton's identities: smooth everywhere, and between lam_max and
  3^(1/p) lam_max (at most +7 % in sigma for p = 8, only when Sigma is isotropic; +0.05 % for a
  stereo pair whose out-of-plane variance is twice the in-plane one). The report (`fields`) uses the
  exact eigenvalues.
* Rank deficiency: with fewer than two usable views C has rank <= 2 and the out-of-plane variance is
  infinite. `fields` reports +inf in every sigma field where C has rank < 3 (smallest eigenvalue
  <= `rank_rtol` x largest, or C = 0) and flags `measured = False`. The score instead regularises:
  C_reg = C + I / prior_sigma^2, a Gaussian prior of std `prior_sigma` (default 1 mm) on each
  displacement component, so an unmeasured sample costs sigma ~ prior_sigma, finite and smooth.

Soft weights, w_i = occlusion x in_front x w_incidence x w_image, with the C^2 quintic smoothstep
S(t) = 6t^5 - 15t^4 + 10t^3 on [0, 1] (0 below, 1 above): exactly 0 where the view is unusable,
exactly 1 well inside, and a finite gradient everywhere (S' = 0 at both ends).

* w_incidence = S((cos theta - cos theta_lim) / (cos(theta_lim - ramp) - cos theta_lim)), with
  cos theta = n . (P - X)/|P - X|: 0 at the incidence limit, 1 at `ramp` radians inside it. Written in
  cos theta, not theta, because d acos / dx is infinite at normal incidence.
* w_image = S((u + 1/2)/m) S((W - 1/2 - u)/m) S((v + 1/2)/m) S((H - 1/2 - v)/m): 0 at the image
  edge, 1 at `image_margin_px` = m pixels inside it (pixel centres are integers, the image spans
  [-1/2, W - 1/2]).
* in_front: Z_c > `near` (a hard gate; beyond it the projection is safe-guarded, and near it the
  image weight is already 0 because the projection leaves the image).
* occlusion: the ray cast's 0/1 (or fractional) visibility, a constant.

Score (dimensionless, in units of `sigma_unit`, default micrometres):

    score = Sbar / sigma_unit + coverage_weight * P
    Sbar  = ( sum_n omega_n sigma_n^q / sum_n omega_n )^(1/q)          (m; weighted power mean)
    P     = sum_n omega_n max(0, k_region(n) - sum_i w_i)^2 / sum_n omega_n   (cameras^2)

with sigma_n the smooth sqrt(lam_max) of the regularised Sigma, omega_n = area_n x
importance[region_n], q = `score_power` (default 8: a smooth maximum, between the mean and the
max; 1 % of the area at sigma_max alone gives 0.56 sigma_max) and k the per-region minimum camera
count (2 by default, 3 on the joint). With the default coverage_weight = 1000 a sample one camera
short costs as much as an unmeasured one (prior_sigma / sigma_unit = 1000).

Lens distortion (`CameraParams.distortion`, Brown-Conrady as `vdo.model.camera` models it). The pixel is
u = f x_d + c_x, v = f y_d + c_y with (x_d, y_d) = `vdo.model.camera.distort`(X_c/Z_c, Y_c/Z_c), and the
sensitivity carries D = d(x_d, y_d)/d(x, y) = [[a, b], [b, d]] (`vdo.model.camera.distortion_jacobian`;
symmetric), so s = (f/Z_c) D E R with E R the pinhole rows; the soft image weight reads the
distorted pixel. In the reverse pass D (g_s0, g_s1) feeds the pinhole chain, and D's own
dependence on (x, y) enters through its four distinct derivatives
(`vdo.model.camera.distortion_curvature`). The coefficients are constants (gradient 0). With
distortion None the camera table has 17 columns and the programs are the pinhole ones exactly
(bit-identical to a build without distortion, and as fast); with coefficients it has 22.

The machinery is `vdo.information` (floor 6), and its modules say how it is computed and why:
`inputs` (`CameraParams`, `Samples`, `Settings`), `projection` (s, A and w per pair), `tensor`
(A -> T, the energies G), `views` ("Sparse pairs": `ViewData`, the camera-major list of the
pairs that can have w > 0, refreshed when the cameras move past its margins) and `blocks` (the
per-pair block summed per sample, in chunks: "Reverse pass", the hand-written gradient; "How it
runs on XLA:CPU"; "Precision", the float32 per-pair work of `Settings.pair_dtype`, with the
per-sample sums, the score and the reports (`fields`, `information`, `camera_information`)
always float64). This module re-exports their public names.

Inputs are pytrees (equinox Modules) of arrays: `CameraParams` (C cameras), `Samples` (N samples,
R regions), `ViewData` (per-pair constants for the P selected pairs), an `energy` G (a `vdo.model.speckle.GradientEnergyTable`,
or any jax-traceable callable G(l_par, l_perp) -> 1/m^2, e.g. `GaussianFieldEnergy`) and `Settings`
(static). Everything is jit-compiled with `equinox.filter_jit`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from vdo.information.blocks import materialise, pair_inputs, pair_terms, per_sample, sample_sums
from vdo.information.inputs import KAPPA_BOX, CameraParams, Samples, Settings
from vdo.information.projection import pairs, smoothstep
from vdo.information.tensor import GaussianFieldEnergy, TableEnergy, gradient_tensor
from vdo.information.views import PAIR_HEADROOM, ViewData, bucket

__all__ = [
    "smooth_sigma_max",
    "CameraParams",
    "Samples",
    "ViewData",
    "Settings",
    "TableEnergy",
    "GaussianFieldEnergy",
    "Geometry",
    "Fields",
    "geometry",
    "gradient_tensor",
    "camera_information",
    "information",
    "score",
    "score_and_grad",
    "fields",
    "smoothstep",
    "KAPPA_BOX",
    "PAIR_HEADROOM",
    "bucket",
]


def _per_pair_dense(x, vd: ViewData, c, n):
    """Scatter a (B, block) per-pair array into (C, N) (zeros where not listed)."""
    return jnp.zeros((c, n)).at[vd.camera, vd.sample].add(x.reshape(-1).astype(jnp.float64))


def _sym_full(e):
    """6 entries (c00, c11, c22, c01, c02, c12: `vdo.information.blocks`' order) -> (..., 3, 3)."""
    c00, c11, c22, c01, c02, c12 = e
    return jnp.stack([jnp.stack([c00, c01, c02], -1), jnp.stack([c01, c11, c12], -1),
                      jnp.stack([c02, c12, c22], -1)], -2)


def smooth_sigma_max(ent, st: Settings, keep=lambda x: x):
    """sqrt of the trace p-norm (tr Sigma^p)^(1/p) of Sigma_reg = (C + I/prior^2)^-1 (m), from the
    invariants of C alone (no inverse, no eigen-decomposition): with e1, e2, e3 the elementary
    symmetric functions of C's eigenvalues nu, Sigma's eigenvalues mu = 1/nu have
    E1 = e2/e3, E2 = e1/e3, E3 = 1/e3; scaled to sum 1 (mu' = mu/E1) their power sums follow
    Newton's identities p_k = p_(k-1) - E2' p_(k-2) + E3' p_(k-3) with E2' = e1 e3/e2^2,
    E3' = e3^2/e2^3 (all in [0, 1/3]), and (tr Sigma^p)^(1/p) = E1 p_p^(1/p). C is first scaled
    by its trace so that nothing under- or overflows."""
    prior = 1.0 / st.prior_sigma ** 2
    c00, c11, c22 = ent[0] + prior, ent[1] + prior, ent[2] + prior
    c01, c02, c12 = ent[3:]
    tc = c00 + c11 + c22
    c00, c11, c22, c01, c02, c12 = keep(tuple(x / tc for x in (c00, c11, c22, c01, c02, c12)))
    m00 = c11 * c22 - c12 * c12
    m11 = c00 * c22 - c02 * c02
    m22 = c00 * c11 - c01 * c01
    e2 = m00 + m11 + m22
    e3 = c00 * m00 + c01 * (c02 * c12 - c01 * c22) + c02 * (c01 * c12 - c02 * c11)
    e2, e3 = keep((e2, e3))
    E2 = e3 / (e2 * e2)  # e1 = 1 after scaling
    E3 = e3 * e3 / (e2 * e2 * e2)
    E2, E3 = keep((E2, E3))
    p = [1.0, 1.0, 1.0 - 2.0 * E2]  # p_0 is unused (index shift), p_1, p_2
    p.append(p[2] - E2 + 3.0 * E3)  # p_3
    for k in range(4, st.eigen_power + 1):
        p.append(keep(p[k - 1] - E2 * p[k - 2] + E3 * p[k - 3]))
    lam = (e2 / e3) * p[st.eigen_power] ** (1.0 / st.eigen_power) / tc
    return jnp.sqrt(lam)


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------
class Geometry(eqx.Module):
    """Per (camera, sample) geometry: pixel (C, N, 2), sensitivity s (C, N, 2, 3) pixel/m,
    footprint A (C, N, 2, 2) pixel/m, weight w (C, N) (occlusion not applied)."""

    pixel: jax.Array
    sensitivity: jax.Array
    footprint: jax.Array
    weight: jax.Array


@eqx.filter_jit
def geometry(cameras: CameraParams, samples: Samples, settings: Settings = Settings()) -> Geometry:
    """Projection, sensitivity s = dx/dX, footprint A = s [t_u t_v] and soft weight per pair
    (dense: every camera with every sample)."""
    geo = pairs(cameras, samples, settings)
    s0, s1, A, u, v, w = geo.s0, geo.s1, geo.A, geo.u, geo.v, geo.w
    s = jnp.stack([jnp.stack(s0, -1), jnp.stack(s1, -1)], -2)
    A = jnp.stack([jnp.stack(A[:2], -1), jnp.stack(A[2:], -1)], -2)
    return Geometry(jnp.stack([u, v], -1), s, A, w)


@eqx.filter_jit
def camera_information(cameras: CameraParams, samples: Samples, views: ViewData, energy,
                       settings: Settings = Settings()):
    """Each camera's contribution Omega w_i |det A_i| C_i to the sample information, (C, N, 3, 3)
    in 1/m^2 (C_i = sigma_i^-2 s_i^T T_i s_i per pixel; rank 2, null vector along the ray); zero
    for pairs not listed in `views`."""
    ent, _, _ = pair_terms(cameras, views, energy, settings)
    c, n = cameras.position.shape[0], samples.points.shape[0]
    return _sym_full(tuple(_per_pair_dense(e, views, c, n) for e in ent))


def pair_information(cameras: CameraParams, views: ViewData, energy,
                     settings: Settings = Settings()) -> tuple[np.ndarray, ...]:
    """The listed pairs of `views` alone (padding dropped), in numpy: camera and sample indices
    (P,), the 6 entries (c00, c11, c22, c01, c02, c12) of Omega w_i |det A_i| C_i (P, 6) in 1/m^2
    and the soft weight w_i (P,) with the occlusion applied: what `camera_information` and
    `geometry(...).weight` x occlusion give at these pairs (zero at every other pair), without
    the (C, N) arrays."""
    ent, w = _pair_entries(cameras, views, energy, settings)
    real = np.asarray(views.occlusion).reshape(-1) > 0
    return (np.asarray(views.camera).reshape(-1)[real], np.asarray(views.sample).reshape(-1)[real],
            np.stack([np.asarray(e, dtype=np.float64).reshape(-1) for e in ent], -1)[real],
            np.asarray(w, dtype=np.float64).reshape(-1)[real])


@eqx.filter_jit
def _pair_entries(cameras, views, energy, settings):
    """`pair_terms`' entries and weights as one compiled program (`pair_information`: run op by
    op, its ~100 operations each compiled and dispatched alone)."""
    ent, w, _ = pair_terms(cameras, views, energy, settings)
    return ent, w


@eqx.filter_jit
def information(cameras: CameraParams, samples: Samples, views: ViewData, energy,
                settings: Settings = Settings()):
    """C = Omega sum_i w_i |det A_i| C_i per sample, (N, 3, 3) in 1/m^2 (no regularisation)."""
    ent, _, _ = pair_terms(cameras, views, energy, settings)
    n = samples.points.shape[0]
    return _sym_full(tuple(per_sample(e, views.sample, n) for e in ent))


def _score(cameras, samples, views, energy, settings):
    ctab, geometry, occ, kc, one = pair_inputs(cameras, views, settings,
                                                jnp.dtype(settings.pair_dtype))
    n = samples.points.shape[0]
    sample = views.sample.reshape(occ.shape)
    sums = sample_sums(ctab, geometry, occ, kc, one, sample, jax.lax.stop_gradient(energy),
                        settings, views.chunk, n)
    # materialised, so that the backward delivers each of the 7 per-sample cotangents once
    # (XLA:CPU otherwise fuses them into one loop that re-derives the per-sample chain per row)
    ones = jax.lax.stop_gradient(samples.area / samples.area)  # runtime 1.0 per sample
    keep = lambda x: materialise(x, ones)
    *ent, cov = keep(sums)
    sigma = smooth_sigma_max(ent, settings, keep) / settings.sigma_unit
    omega = samples.area * samples.importance[samples.region]
    omega = omega / omega.sum()
    q = settings.score_power
    top = jax.lax.stop_gradient(jnp.max(sigma))  # exact homogeneity: value and gradient unchanged
    ratio = sigma / top
    power = jax.lax.integer_pow(ratio, int(q)) if float(q).is_integer() else ratio ** q
    agg = top * jnp.sum(omega * power) ** (1.0 / q)
    short = jnp.maximum(samples.min_cameras[samples.region] - cov, 0.0)
    penalty = jnp.sum(omega * short * short)
    return agg + settings.coverage_weight * penalty


@eqx.filter_jit
def score(cameras: CameraParams, samples: Samples, views: ViewData, energy,
          settings: Settings = Settings()):
    """Scalar score to minimise (dimensionless; uncertainty in units of settings.sigma_unit):
    weighted power mean of the smooth sigma_max plus the coverage penalty (module docstring)."""
    return _score(cameras, samples, views, energy, settings)


@eqx.filter_jit
def score_and_grad(cameras: CameraParams, samples: Samples, views: ViewData, energy,
                   settings: Settings = Settings()):
    """(score, d score / d cameras) with the gradient a `CameraParams` of the same shapes."""
    return jax.value_and_grad(_score)(cameras, samples, views, energy, settings)


class Fields(eqx.Module):
    """Per-sample report fields (N leading axis). Sigmas in m, one noisy image (x sqrt 2 for two).

    sensitivity       (N, 3) global sensitivity per world axis, pixel/m (x 1e-3: mpixel/um)
    sigma_max         (N,) sqrt(lam_max(Sigma)), +inf where not measured
    sigma_xyz         (N, 3) sqrt(diag Sigma), +inf where not measured
    sigma_max_smooth  (N,) the regularised smooth value the score uses (finite)
    coverage          (N,) sum_i w_i, the smooth count of usable cameras
    measured          (N,) C has full rank (>= 2 usable, non-parallel views)
    weights           (C, N) w_i including occlusion (0 for pairs not listed in the ViewData)
    information       (N, 3, 3) C in 1/m^2
    """

    sensitivity: jax.Array
    sigma_max: jax.Array
    sigma_xyz: jax.Array
    sigma_max_smooth: jax.Array
    coverage: jax.Array
    measured: jax.Array
    weights: jax.Array
    information: jax.Array


@eqx.filter_jit
def fields(cameras: CameraParams, samples: Samples, views: ViewData, energy,
           settings: Settings = Settings()) -> Fields:
    """All report fields (exact eigenvalues, not for differentiation)."""
    ent, w, geo = pair_terms(cameras, views, energy, settings)
    s0, s1 = geo.s0, geo.s1
    c, n = cameras.position.shape[0], samples.points.shape[0]
    ent = tuple(per_sample(e, views.sample, n) for e in ent)
    sens = jnp.stack([jnp.sqrt(per_sample(w * (s0[k] ** 2 + s1[k] ** 2), views.sample, n))
                      for k in range(3)], -1)
    C = _sym_full(ent)
    tc = jnp.trace(C, axis1=-2, axis2=-1)
    scale = jnp.where(tc > 0, tc, 1.0)
    lam, V = jnp.linalg.eigh(C / scale[:, None, None])
    measured = (tc > 0) & (lam[:, 0] > settings.rank_rtol * lam[:, 2])
    lam_safe = jnp.where(measured[:, None], lam, 1.0)
    var_axis = jnp.einsum("nkj,nj->nk", V * V, 1.0 / lam_safe) / scale[:, None]
    inf = jnp.inf
    sigma_max = jnp.where(measured, jnp.sqrt(1.0 / (lam_safe[:, 0] * scale)), inf)
    sigma_xyz = jnp.where(measured[:, None], jnp.sqrt(var_axis), inf)
    return Fields(sensitivity=sens, sigma_max=sigma_max, sigma_xyz=sigma_xyz,
                  sigma_max_smooth=smooth_sigma_max(ent, settings),
                  coverage=per_sample(w, views.sample, n), measured=measured,
                  weights=_per_pair_dense(w, views, c, n), information=C)


class SampleFields(eqx.Module):
    """Per-sample fields as differentiable functions of the cameras (`sample_fields`), for a
    user's own objective. N samples, R regions; sigmas for one noisy image (x sqrt 2 for two).

    information  (N, 3, 3) 1/m^2: C = Omega sum_i w_i |det A_i| C_i (no regularisation)
    sigma_xyz    (N, 3) m: sqrt(diag Sigma_reg), Sigma_reg = (C + I/prior_sigma^2)^-1: finite
                 everywhere (about prior_sigma, 1 mm, along a direction no camera measures)
    sigma_max    (N,) m: the score's smooth sqrt(lam_max(Sigma_reg)) (trace p-norm, at most
                 3^(1/2p) above the exact value: module docstring)
    coverage     (N,) cameras: sum_i w_i, the smooth count of usable views (the soft weights w
                 of the module docstring; with occlusion frozen by the `ViewData`)
    area         (N,) m^2, region (N,) int in [0, R), importance (R,), min_cameras (R,): the
                 samples' constants (`Samples`), for weighting
    """

    information: jax.Array
    sigma_xyz: jax.Array
    sigma_max: jax.Array
    coverage: jax.Array
    area: jax.Array
    region: jax.Array
    importance: jax.Array
    min_cameras: jax.Array


def sample_fields(cameras: CameraParams, samples: Samples, views: ViewData, energy,
                  settings: Settings = Settings()) -> SampleFields:
    """`SampleFields` of `cameras`: the per-sample sums of the score (the same pair work and
    hand-written reverse pass, `settings.pair_dtype` per pair), so that `jax.grad` of any
    function of them w.r.t. the cameras' position, pan, tilt, roll, focal_px, cx, cy works and
    costs about one score gradient. Traceable (use inside `jax.jit`, `jax.grad`)."""
    ctab, geometry, occ, kc, one = pair_inputs(cameras, views, settings,
                                                jnp.dtype(settings.pair_dtype))
    n = samples.points.shape[0]
    *ent, cov = sample_sums(ctab, geometry, occ, kc, one, views.sample.reshape(occ.shape),
                             jax.lax.stop_gradient(energy), settings, views.chunk, n)
    C = _sym_full(ent)
    reg = C + jnp.eye(3) / settings.prior_sigma ** 2
    tc = jnp.trace(reg, axis1=-2, axis2=-1)   # scaled to trace 1 before the inverse
    sigma_xyz = jnp.sqrt(jnp.diagonal(jnp.linalg.inv(reg / tc[:, None, None]), axis1=-2, axis2=-1)
                         / tc[:, None])
    return SampleFields(information=C, sigma_xyz=sigma_xyz, sigma_max=smooth_sigma_max(ent, settings),
                        coverage=cov, area=samples.area, region=samples.region,
                        importance=samples.importance, min_cameras=samples.min_cameras)
