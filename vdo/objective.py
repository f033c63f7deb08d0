"""Mean-field DIC uncertainty of a multi-camera layout, and the scalar score the optimizer minimises.

Pure `jax.numpy` (float64, or float32 per pair: "Precision" below), differentiable with respect to
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

* T as a matrix function of M = A A^T, with no SVD/eigh. With m = tr M / 2, h = (M00 - M11)/2,
  the eigenvalues are m +- gap, gap = sqrt(h^2 + M01^2). We use
  gap_eps = sqrt(h^2 + M01^2 + (eps m)^2), lam1 = m + gap_eps, lam2 = det M / lam1 and
  T/c^2 = (phi1 + phi2)/2 I + (phi1 - phi2)/(lam1 - lam2) (M - m I),  phi_k = G(l_k, l_other)/lam_k.
  This is the exact spectral formula with the gap floored: both coefficients are even functions of
  the gap, so the floor changes T by O(eps^2) (eps = 1e-4 -> 1e-8 relative), the difference
  quotient never divides by zero (a fronto-parallel view, a_1 = a_2 exactly, is fine) and the sqrt
  is never evaluated at 0.
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

Sparse pairs (`ViewData`). Most (camera, sample) pairs have w = 0 exactly (occluded, behind, outside
the image, beyond the incidence limit), so the per-pair work runs over a list of P selected pairs only
and is summed per sample with `jax.ops.segment_sum`. The list is laid out camera-major in blocks of
`block` pairs that all belong to one camera (each camera's list padded to whole blocks, the block
count padded to a bucket so that a changing P seldom recompiles): the camera parameters are then
broadcast per block and their gradient is a row sum, not a scatter into C slots (which XLA:CPU
serialises: 40 ms for 10 cameras x 317k pairs against < 1 ms). Padding pairs have occlusion 0,
hence weight and gradient exactly 0. The list carries its pairs' sample geometry (point, normal,
t_u, t_v), copied once when it is built: gathering it from the samples on every call cost ~10 ms.
`ViewData.from_dense` builds the list from (C, N) arrays: without cameras it keeps every pair
with occlusion > 0 (exact for any camera parameters); given the cameras it also drops the pairs
that are behind the camera, outside the image extended by `margin_px`, or beyond the incidence
limit plus `margin_angle` at those cameras. A dropped pair has w = 0 and a zero gradient there, so
value and gradient stay exact as long as no camera moves so far that a dropped pair crosses into
its image or incidence range: refresh the selection when the cameras move by more than the margins
(the optimizer does so between inner solves, with visibility).

Reverse pass (`_block_vjp`). The score's gradient with respect to the cameras is written out by
hand for the per-pair block: for per-pair cotangents Q (the symmetric 3x3 of the 6 entries, off-
diagonals halved) and c_w, L = k tr(T Y) + c_w w with Y = S Q S^T, so dL/dk = tr(T Y),
dL/dT = k Y, dL/dS = 2 k T S Q, then back through T = alpha I + beta (M - m I), the floored-gap
eigenvalues, the footprint, the soft weights and the projection to the camera, summed over each
camera-major block. For the rotation only its skew part is summed: R stays a rotation (dR = W R,
W skew), so dL/dR counts through the 3 entries of M - M^T, M = dL/dR R^T, and the block's dL/dR
is returned as S R with S = (M - M^T)/2 (the same derivative along every rotation, hence the same
pan, tilt and roll gradients). Width and height are pixel counts, not differentiated. Only the
cameras are differentiated: samples, view data and the energy are constants (zero cotangents).

How it runs on XLA:CPU (`_sample_sums`, measured on 10 cameras x 100k samples, 2 cores;
figures in `benchmarks/README.md`). Both passes go over the pair list in chunks of `ViewData.chunk`
blocks (~32k pairs, `lax.map`), the reverse pass recomputing the forward. Within a chunk, values
used by several later steps are materialised (`_keep`): XLA:CPU duplicates cheap elementwise
producers into every consumer fusion, so without it each of the ~20 loops that end in a camera
column re-derived the forward chain (5,000 operations per pair in the reverse pass, 2,100 with
it). Materialising costs memory traffic, hence the chunks, which keep it in cache. Other facts
behind the code: reading an array with a stride (the columns of a (pairs, 7) gather of the
per-sample cotangents) stops vectorisation, so each of the 7 is gathered on its own (1.2x on
value + gradient); the block sums are one batched dot with ones (separate row sums: ~15 %
slower); a variadic `lax.reduce` compiles to scalar code (~7x slower); gathers inside the
per-pair chain (a sample-major layout) stop vectorisation (~4x slower forward). Each call's
temporaries (~130 MB before the chunks) come from malloc, and glibc maps and unmaps blocks that
large on every call: `vdo.core.memory.retain_freed_memory` keeps them in the heap instead (58 -> 47
ms per value + gradient).

Precision (`Settings.pair_dtype`). The per-pair work (projection, footprint, spectrum, table
lookup, weights and their reverse) can run in float32: f32 exp/log are ~5x faster than f64 on
XLA:CPU and AVX2 holds 8 f32 lanes against 4. The 6 entries k S^T T S (and their reverse,
Y and dL/dS) are assembled in float64 from the rounded S in either case, so that each pair's
matrix keeps the ray as its null vector to f64 precision: float32 rounding of the entries
leaves ~1e-7 |C_i| along the ray, far above the prior 1/prior_sigma^2 that alone fixes that
direction for a sample seen by one camera (it made sigma NaN there). Per-sample sums and the
score are float64. Measured on 10 cameras x 100k samples: value within ~4e-8 and gradient
within ~1e-5 (max |diff| / max |g|) of float64. The default stays float64 (the finite-
difference tests need it); `vdo.physics.predict.settings`, and so the optimizer, uses float32; the reports
(`fields`, `information`, `camera_information`) always run float64.

Inputs are pytrees (equinox Modules) of arrays: `CameraParams` (C cameras), `Samples` (N samples,
R regions), `ViewData` (per-pair constants for the P selected pairs), an `energy` G (a `vdo.model.speckle.GradientEnergyTable`,
or any jax-traceable callable G(l_par, l_perp) -> 1/m^2, e.g. `GaussianFieldEnergy`) and `Settings`
(static). Everything is jit-compiled with `equinox.filter_jit`.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from vdo.model.camera import distort, distortion_curvature, distortion_jacobian, image_point, rotation
from vdo.core.configure import require_x64
from vdo.model.speckle import GradientEnergyTable, g_aniso_lookup
from vdo.core.tolerances import IN_FRONT_M

__all__ = [
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
]

KAPPA_BOX = 1.0 / math.sqrt(12.0)  # std of a box pixel, in pixels (docs/theory.md)
PAIR_HEADROOM = 1.25   # `ViewData.from_dense` with sizes: the first list's blocks x this, for later layouts


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------
class CameraParams(eqx.Module):
    """C cameras as arrays. position (C, 3) m; pan, tilt, roll (C,) rad (`vdo.model.camera` convention);
    focal_px, cx, cy (C,) pixels; width, height (C,) pixel counts (floats; constants: the score's
    gradient with respect to them is 0); distortion (C, 5) the Brown-Conrady coefficients in
    `vdo.model.camera.DISTORTION` order (constants), or None for pinholes (the programs then hold no
    distortion arithmetic at all: module docstring, "Lens distortion")."""

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


def bucket(n: int) -> int:
    """n rounded up to 2^k x {1, 1.125, ..., 1.875} (at most 12.5 % more): few distinct sizes."""
    if n <= 16:
        return max(n, 1)
    step = 1 << (n.bit_length() - 4)
    return -(-n // step) * step


class ViewData(eqx.Module):
    """Per-pair constants for P selected (camera, sample) pairs (module docstring, "Sparse pairs"):
    camera, sample (P,) int32 indices; occlusion (P,) in [0, 1] from the ray cast (1 = seen);
    contrast c in DN (image = b + c f_hat); noise sigma in DN rms per pixel; geometry
    (12, B, block) the pairs' sample point, normal, t_u and t_v (m, unit), copied from the
    `Samples` it was built with (the per-pair work reads them contiguously instead of gathering
    them per call).

    Layout: P = B x `block`; the pairs of block b (P[b*block:(b+1)*block]) all belong to one camera
    and are sorted by sample; padding pairs have occlusion 0 (and contrast 0, noise 1). The block
    count B is a multiple of `chunk`, the blocks per chunk of both passes. Build it with
    `from_dense`, and score it with the same samples. Pairs not listed have weight 0."""

    camera: jax.Array
    sample: jax.Array
    occlusion: jax.Array
    contrast: jax.Array
    noise: jax.Array
    geometry: jax.Array
    block: int = eqx.field(static=True, default=1)
    chunk: int = eqx.field(static=True, default=1)

    @classmethod
    def from_dense(cls, occlusion, contrast, noise, samples: "Samples",
                   cameras: "CameraParams | None" = None, settings: "Settings | None" = None, *,
                   margin_px: float = 64.0, margin_angle: float = math.radians(3.0),
                   block: int = 1024, chunk_pairs: int = 32768, sizes: dict | None = None) -> "ViewData":
        """Select the pairs that can have w > 0 from (C, N) arrays (contrast, noise broadcast)
        for the N `samples`.

        Without `cameras`: every pair with occlusion > 0 (exact for any camera parameters). With
        them: also in front (Z_c > near), inside the image grown by `margin_px` on every side,
        and incidence below `settings.incidence_limit + margin_angle`: exact at these cameras and
        while they move less than the margins (refresh after larger moves). `block` is the
        most pairs per block, `chunk_pairs` about the pairs per chunk of both passes.

        `sizes` (a dict kept with the samples, e.g. `vdo.state.Geometry.sizes`) fixes the block
        count per block size across calls, so that the lists of new camera layouts keep one
        shape and the programs that read them compile once: the first list sets it to its
        blocks x `PAIR_HEADROOM` (whole chunks); a longer list raises it (one new shape).
        Without it the count is `bucket`ed (a new bucket, a new compile)."""
        occ = np.asarray(occlusion, dtype=np.float64)
        if occ.ndim != 2 or occ.shape[1] != samples.points.shape[0]:
            raise ValueError(f"ViewData.from_dense: occlusion must be (C, N) with N = "
                             f"{samples.points.shape[0]} samples, got {occ.shape}")
        contrast = np.broadcast_to(np.asarray(contrast, dtype=np.float64), occ.shape)
        noise = np.broadcast_to(np.asarray(noise, dtype=np.float64), occ.shape)
        keep = occ > 0
        if cameras is not None:
            keep &= _candidates(cameras, samples, settings or Settings(), margin_px, margin_angle)
        return cls._from_pairs(*np.nonzero(keep), occ, contrast, noise,
                               np.asarray(_sample_table(samples)), block, chunk_pairs, sizes)

    @classmethod
    def _from_pairs(cls, cam, smp, occ, contrast, noise, table, block, chunk_pairs, sizes=None):
        """cam, smp (K,) sorted by camera then sample (np.nonzero order); dense (C, N) values;
        table (N, 12) the sample columns (`_sample_table`)."""
        n_cameras = occ.shape[0]
        counts = np.bincount(cam, minlength=n_cameras)
        most = int(counts.max()) if counts.size else 0
        L = block if most >= block else max(8, 1 << max(most - 1, 0).bit_length())
        blocks = -(-counts // L)  # per camera
        if sizes is not None and ("blocks", L) in sizes and sizes[("blocks", L)][0] >= blocks.sum():
            n_blocks, chunk = sizes[("blocks", L)]
        else:
            n_blocks = bucket(int(blocks.sum())) if sizes is None else \
                max(1, math.ceil(PAIR_HEADROOM * int(blocks.sum())))
            chunk = max(1, min(chunk_pairs // L, n_blocks))
            n_blocks = -(-n_blocks // chunk) * chunk
            if sizes is not None:
                sizes[("blocks", L)] = (n_blocks, chunk)
        block_cam = np.zeros(n_blocks, dtype=np.int32)
        block_cam[:blocks.sum()] = np.repeat(np.arange(n_cameras), blocks)
        first_pair = np.cumsum(counts) - counts
        first_slot = (np.cumsum(blocks) - blocks) * L
        dest = first_slot[cam] + np.arange(cam.size) - first_pair[cam]
        P = n_blocks * L
        out_s = np.zeros(P, dtype=np.int32)
        out_o, out_c, out_n = np.zeros(P), np.zeros(P), np.ones(P)
        out_s[dest] = smp
        out_o[dest], out_c[dest], out_n[dest] = occ[cam, smp], contrast[cam, smp], noise[cam, smp]
        return cls(jnp.asarray(np.repeat(block_cam, L)), jnp.asarray(out_s), jnp.asarray(out_o),
                   jnp.asarray(out_c), jnp.asarray(out_n),
                   jnp.asarray(table[out_s].T.reshape(12, n_blocks, L)), L, chunk)

    @property
    def n_blocks(self) -> int:
        """B, the number of blocks (pairs = B x `block`)."""
        return self.camera.shape[0] // self.block

    def padded(self, n_blocks: int, chunk: int | None = None) -> "ViewData":
        """This list with padding blocks up to `n_blocks` (>= `n_blocks`, a multiple of `chunk`,
        the result's blocks per chunk, default this list's):
        occlusion 0, hence weight and gradient exactly 0; a real sample's geometry (finite). The
        same values from every program, with the shapes of a larger list: callers fix the size
        so that new layouts reuse one compiled program (`vdo.optimize`, `vdo.physics.predict`)."""
        L, B, chunk = self.block, self.n_blocks, chunk or self.chunk
        if n_blocks < B or n_blocks % chunk:
            raise ValueError(f"ViewData.padded: {n_blocks} blocks must be >= {B} and a multiple of "
                             f"the chunk {chunk}")
        extra = (n_blocks - B) * L   # on the host: an XLA concatenate would compile per shape
        fill = lambda a, value: jnp.asarray(np.concatenate(  # noqa: E731
            [np.asarray(a), np.full(extra, value, np.asarray(a).dtype)]))
        table = np.asarray(self.geometry)
        geometry = jnp.asarray(np.concatenate([table, np.broadcast_to(
            table[:, :1, :1], (12, n_blocks - B, L))], axis=1))
        return ViewData(fill(self.camera, 0), fill(self.sample, 0), fill(self.occlusion, 0.0),
                        fill(self.contrast, 0.0), fill(self.noise, 1.0), geometry, L, chunk)

    @property
    def n_pairs(self) -> int:
        """Number of listed pairs with occlusion > 0 (not counting the padding)."""
        return int(np.count_nonzero(np.asarray(self.occlusion)))


def _candidates(cameras, samples, st, margin_px, margin_angle):
    """(C, N) bool, numpy: in front, inside the image + margin_px, incidence < limit + margin."""
    R = rotation(*(np.asarray(a) for a in (cameras.pan, cameras.tilt, cameras.roll)), xp=np)
    d = np.asarray(samples.points)[None] - np.asarray(cameras.position)[:, None]  # (C, N, 3)
    p = np.einsum("cab,cnb->acn", R, d)
    front = p[2] > st.near
    z = np.where(front, p[2], 1.0)
    f = np.asarray(cameras.focal_px)[:, None]
    dist = (None if cameras.distortion is None else
            tuple(np.asarray(cameras.distortion)[:, k, None] for k in range(5)))
    u, v = image_point((f, None, np.asarray(cameras.cx)[:, None], f, np.asarray(cameras.cy)[:, None]),
                       p[0] / z, p[1] / z, dist)
    W, H = np.asarray(cameras.width)[:, None], np.asarray(cameras.height)[:, None]
    lo = -0.5 - margin_px
    inside = (u > lo) & (u < W - 1 - lo) & (v > lo) & (v < H - 1 - lo)
    cos_lim = math.cos(min(st.incidence_limit + margin_angle, math.pi))
    nd = -np.einsum("nk,cnk->cn", np.asarray(samples.normals), d)
    facing = nd > cos_lim * np.sqrt(np.einsum("cnk,cnk->cn", d, d))
    return front & inside & facing


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
                       lookup in `score` and `score_and_grad` (module docstring, "Precision");
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


class TableEnergy(eqx.Module):
    """G(l_par, l_perp) from a `vdo.model.speckle.GradientEnergyTable` (bilinear in log-log), 1/m^2."""

    table: GradientEnergyTable

    def __call__(self, l_par, l_perp):
        return g_aniso_lookup(self.table, l_par, l_perp)


class GaussianFieldEnergy(eqx.Module):
    """Closed-form G for a Gaussian random field: white noise smoothed by a Gaussian of std
    `correlation_length` = s (m), normalised to unit variance (autocorrelation exp(-r^2 / 4 s^2)).
    Blurring adds covariances, so

        G(l_par, l_perp) = s^2 / (2 (s^2 + l_par^2)^(3/2) (s^2 + l_perp^2)^(1/2))     (1/m^2),

    G(0, 0) = 1/(2 s^2). Smooth in both arguments: a reference for tests and derivations."""

    correlation_length: float

    def __call__(self, l_par, l_perp):
        s2 = self.correlation_length ** 2
        a, b = s2 + l_par * l_par, s2 + l_perp * l_perp
        return s2 / (2.0 * a * jnp.sqrt(a * b))


# --------------------------------------------------------------------------------------------
# Component helpers: 3-vectors as tuples of broadcastable arrays, so XLA fuses everything
# --------------------------------------------------------------------------------------------
def smoothstep(t):
    """C^2 step: 0 for t <= 0, 6t^5 - 15t^4 + 10t^3 on [0, 1], 1 for t >= 1."""
    t = jnp.clip(t, 0.0, 1.0)
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def _smoothstep_grad(t):
    """d smoothstep / dt = 30 t^2 (1 - t)^2 on [0, 1], 0 outside."""
    t = jnp.clip(t, 0.0, 1.0)
    return 30.0 * (t * (1.0 - t)) ** 2


def _weight_scales(st):
    """(cos theta_lim, 1 / (cos(theta_lim - ramp) - cos theta_lim), 1 / image_margin_px): the
    smoothstep arguments of the soft weights are t_inc = (cos theta - cos theta_lim) x the
    second and t_img = (distance to the image edge) x the third."""
    c_lim, c_full = math.cos(st.incidence_limit), math.cos(st.incidence_limit - st.incidence_ramp)
    return c_lim, 1.0 / (c_full - c_lim), 1.0 / st.image_margin_px


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


# Per-camera quantities, columns of the (C, 17) camera table: R (row-major), position, intrinsics;
# with lens distortion 5 more (C, 22): the coefficients in `vdo.model.camera.DISTORTION` order.
_R, _POS, _F, _CX, _CY, _W, _H = slice(0, 9), slice(9, 12), 12, 13, 14, 15, 16
_PINHOLE_COLUMNS, _DIST = 17, slice(17, 22)


def _camera_table(cam: CameraParams):
    """(C, 17): R = rotation (rows x_c, y_c, z_c) row-major, position, f, cx, cy, W, H (the
    pixel counts W, H not differentiated); (C, 22) with the distortion coefficients (constants)
    when `cam.distortion` is not None."""
    R = rotation(cam.pan, cam.tilt, cam.roll)
    c = R.shape[0]
    W, H = jax.lax.stop_gradient((cam.width, cam.height))
    columns = [R.reshape(c, 9), cam.position, jnp.stack([cam.focal_px, cam.cx, cam.cy, W, H], -1)]
    if cam.distortion is not None:
        columns.append(jax.lax.stop_gradient(jnp.asarray(cam.distortion, dtype=R.dtype)))
    return jnp.concatenate(columns, -1)


def _sample_table(smp: Samples):
    """(N, 12): point, normal, t_u, t_v."""
    return jnp.concatenate([smp.points, smp.normals, smp.tangent_u, smp.tangent_v], -1)


def _split(table, shape_of):
    """Columns of a (K, m) table as m arrays reshaped by shape_of (broadcastable components)."""
    return [shape_of(table[:, k]) for k in range(table.shape[1])]


class _Geo(NamedTuple):
    """Per-pair geometry and its intermediates (broadcastable arrays; 3-vectors as tuples)."""

    d: tuple      # X - P, m
    p: tuple      # R d, camera frame, m
    front: jax.Array
    iz: jax.Array  # 1 / Z_c (1 where not in front), 1/m
    xn: jax.Array  # X_c / Z_c
    yn: jax.Array
    u: jax.Array   # pixel
    v: jax.Array
    g: jax.Array   # f / Z_c, pixel/m
    lens: tuple | None  # with distortion: (coefficients, x_d, y_d, D's entries (a, b, d)), else None
    s0: tuple      # sensitivity rows, pixel/m
    s1: tuple
    A: tuple       # footprint A00, A01, A10, A11, pixel/m
    rd: jax.Array  # 1 / |d|
    cos_inc: jax.Array
    t_inc: jax.Array  # smoothstep arguments: incidence, then the 4 image edges
    t_img: tuple
    w: jax.Array   # soft weight (occlusion not included)


def _pairs_from(cq, sq, st: Settings) -> _Geo:
    """Per-pair geometry from broadcastable components: cq the 17 camera columns (22 with the
    lens distortion), sq the 12 sample columns (module docstring for the formulas)."""
    R = [cq[3 * a:3 * a + 3] for a in range(3)]
    P, f, cx, cy, W, H = cq[9:12], cq[_F], cq[_CX], cq[_CY], cq[_W], cq[_H]
    X, nrm, tu, tv = sq[0:3], sq[3:6], sq[6:9], sq[9:12]
    d = tuple(X[k] - P[k] for k in range(3))  # camera centre -> point
    p = tuple(_dot(R[a], d) for a in range(3))
    front = p[2] > st.near
    iz = 1.0 / jnp.where(front, p[2], 1.0)  # safe depth: the weight is 0 where not in front
    xn, yn = p[0] * iz, p[1] * iz
    g = f * iz
    if len(cq) == _PINHOLE_COLUMNS:
        lens = None
        u, v = image_point((f, None, cx, f, cy), xn, yn)
        s0 = tuple(g * (R[0][b] - xn * R[2][b]) for b in range(3))
        s1 = tuple(g * (R[1][b] - yn * R[2][b]) for b in range(3))
    else:  # s = g D [[1, 0, -x], [0, 1, -y]] R with D = d(x_d, y_d)/d(x, y) = [[a, b], [b, d]]
        coefficients = tuple(cq[_DIST])
        xd, yd = distort(xn, yn, coefficients)
        jxx, jxy, _, jyy = distortion_jacobian(xn, yn, coefficients)
        lens = (coefficients, xd, yd, (jxx, jxy, jyy))
        u, v = image_point((f, None, cx, f, cy), xd, yd)   # (x_d, y_d): distorted above
        e0 = tuple(R[0][b] - xn * R[2][b] for b in range(3))
        e1 = tuple(R[1][b] - yn * R[2][b] for b in range(3))
        s0 = tuple(g * (jxx * e0[b] + jxy * e1[b]) for b in range(3))
        s1 = tuple(g * (jxy * e0[b] + jyy * e1[b]) for b in range(3))
    A = (_dot(s0, tu), _dot(s0, tv), _dot(s1, tu), _dot(s1, tv))

    dd = _dot(d, d)
    rd = jax.lax.rsqrt(jnp.maximum(dd, jnp.finfo(dd.dtype).tiny))
    cos_inc = -_dot(nrm, d) * rd
    c_lim, inc_scale, m = _weight_scales(st)
    t_inc = (cos_inc - c_lim) * inc_scale
    t_img = ((u + 0.5) * m, (W - 0.5 - u) * m, (v + 0.5) * m, (H - 0.5 - v) * m)
    w_img = smoothstep(t_img[0]) * smoothstep(t_img[1]) * smoothstep(t_img[2]) * smoothstep(t_img[3])
    w = jnp.where(front, smoothstep(t_inc) * w_img, 0.0)
    return _Geo(d, p, front, iz, xn, yn, u, v, g, lens, s0, s1, A, rd, cos_inc, t_inc, t_img, w)


def _pairs(cam: CameraParams, smp: Samples, st: Settings) -> _Geo:
    """Dense (C, N) geometry (every camera with every sample)."""
    cq = _split(_camera_table(cam), lambda x: x[:, None])
    sq = _split(_sample_table(smp), lambda x: x[None, :])
    return _pairs_from(cq, sq, st)


def _packed_table(table: GradientEnergyTable):
    """Bilinear coefficients of log G on each table cell (i, j), for both G(l_i, l_j) and
    G(l_j, l_i): ((n-1)^2, 8) rows [a0, a1, a2, a3] (G) and the same for G^T, with
    log G = a0 + s a1 + t (a2 + s a3) at fractions s, t: one gather serves both lookups."""
    lg = jnp.log(jnp.asarray(table.g_aniso))

    def coef(g):
        c0, c1, c2, c3 = g[:-1, :-1], g[1:, :-1], g[:-1, 1:], g[1:, 1:]
        return jnp.stack([c0, c1 - c0, c2 - c0, c3 - c2 - c1 + c0], -1)

    n = lg.shape[0]
    return jnp.concatenate([coef(lg), coef(lg.T)], -1).reshape((n - 1) * (n - 1), 8)


def _phis(energy, lam1, lam2, kappa, jacobian=False):
    """phi_k = G(l_k, l_other) / lam_k with l_k = kappa / sqrt(lam_k) (lam in pixel^2/m^2,
    phi in 1/pixel^2), in the dtype of lam; with `jacobian` also d phi_i / d lam_j as
    (j11, j12, j21, j22) (1/pixel^2 per pixel^2/m^2), else None."""
    table = energy.table if isinstance(energy, TableEnergy) else energy
    if not isinstance(table, GradientEnergyTable):
        def fun(a, b):
            la, lb = kappa * jax.lax.rsqrt(a), kappa * jax.lax.rsqrt(b)
            return energy(la, lb) / a, energy(lb, la) / b
        if not jacobian:
            return fun(lam1, lam2), None
        one, zero = jnp.ones_like(lam1), jnp.zeros_like(lam1)  # two forward-mode passes
        phis, (j11, j21) = jax.jvp(fun, (lam1, lam2), (one, zero))
        _, (j12, j22) = jax.jvp(fun, (lam1, lam2), (zero, one))
        return phis, (j11, j12, j21, j22)
    # bilinear in (log l_par, log l_perp) on log G as `vdo.model.speckle.g_aniso_lookup` (same clamping):
    # u = c0 - log(lam)/2 per grid step, clamped to the grid; s, t the fractions in the cell
    dt = lam1.dtype
    grid = jnp.asarray(table.log_l)
    n = grid.shape[0]
    log_lo = jnp.log(grid[0])
    inv_step = (n - 1) / (jnp.log(grid[-1]) - log_lo)
    ll1, ll2 = jnp.log(lam1), jnp.log(lam2)
    c0 = ((math.log(kappa) - log_lo) * inv_step).astype(dt)
    half = (0.5 * inv_step).astype(dt)
    x1, x2 = c0 - half * ll1, c0 - half * ll2
    u1, u2 = jnp.clip(x1, 0.0, n - 1.0), jnp.clip(x2, 0.0, n - 1.0)
    i = jnp.clip(jnp.floor(u1), 0, n - 2)
    j = jnp.clip(jnp.floor(u2), 0, n - 2)
    s, t = u1 - i, u2 - j
    idx = (i * (n - 1) + j).astype(jnp.int32)
    cf = jnp.take(_packed_table(table).astype(dt), idx.reshape(-1), axis=0, mode="clip")
    cf = [cf[:, k].reshape(idx.shape) for k in range(8)]
    log_g12 = cf[0] + s * cf[1] + t * (cf[2] + s * cf[3])
    log_g21 = cf[4] + s * cf[5] + t * (cf[6] + s * cf[7])
    phi1, phi2 = jnp.exp(log_g12 - ll1), jnp.exp(log_g21 - ll2)
    if not jacobian:
        return (phi1, phi2), None
    # by hand (one table gather, not one per forward-mode pass): d s / d lam1 = -half / lam1
    # inside the grid and 0 where clamped, likewise t and lam2
    ds = jnp.where((x1 > 0.0) & (x1 < n - 1.0), -half / lam1, 0.0)
    dt_ = jnp.where((x2 > 0.0) & (x2 < n - 1.0), -half / lam2, 0.0)
    j11 = phi1 * ((cf[1] + t * cf[3]) * ds - 1.0 / lam1)
    j12 = phi1 * (cf[2] + s * cf[3]) * dt_
    j21 = phi2 * (cf[5] + t * cf[7]) * ds
    j22 = phi2 * ((cf[6] + s * cf[7]) * dt_ - 1.0 / lam2)
    return (phi1, phi2), (j11, j12, j21, j22)


class _Spectrum(NamedTuple):
    """Eigenvalues of M = A A^T by the floored-gap formula (module docstring), with the
    intermediates the hand-written reverse pass needs. Units: pixel^2/m^2."""

    M01: jax.Array
    det: jax.Array   # det A (pixel^2/m^2)
    m_raw: jax.Array  # tr M / 2 before the tiny floor
    m: jax.Array
    h: jax.Array     # (M00 - M11) / 2
    gap: jax.Array
    lam1: jax.Array
    q: jax.Array     # det^2 / lam1
    lam2: jax.Array


def _spectrum(A, gap_eps) -> _Spectrum:
    A00, A01, A10, A11 = A
    M00 = A00 * A00 + A01 * A01
    M11 = A10 * A10 + A11 * A11
    M01 = A00 * A10 + A01 * A11
    det = A00 * A11 - A01 * A10
    m_raw = 0.5 * (M00 + M11)
    m = jnp.maximum(m_raw, jnp.finfo(M00.dtype).tiny)
    h = 0.5 * (M00 - M11)
    gap = jnp.sqrt(h * h + M01 * M01 + (gap_eps * m) ** 2)
    lam1 = m + gap
    q = det * det / lam1
    lam2 = jnp.maximum(q, 1e-12 * lam1)  # stable small eigenvalue; edge-on floor
    return _Spectrum(M01, det, m_raw, m, h, gap, lam1, q, lam2)


def _tensor_from(sp: _Spectrum, phi1, phi2):
    """T / c^2 = (phi1 + phi2)/2 I + (phi1 - phi2)/(lam1 - lam2) (M - m I) as (T00, T01, T11)
    (1/pixel^2), with alpha, beta and lam1 - lam2."""
    alpha = 0.5 * (phi1 + phi2)
    D = sp.lam1 - sp.lam2
    beta = (phi1 - phi2) / D
    return (alpha + beta * sp.h, beta * sp.M01, alpha - beta * sp.h), beta, D


def _tensor(A, energy, kappa, gap_eps):
    """T / c^2 = sum_k G(l_k, l_other)/a_k^2 v_k v_k^T as (T00, T01, T11) (1/pixel^2), and |det A|,
    by the floored-gap spectral formula (module docstring). A = (A00, A01, A10, A11)."""
    sp = _spectrum(A, gap_eps)
    T, _, _ = _tensor_from(sp, *_phis(energy, sp.lam1, sp.lam2, kappa)[0])
    return T, jnp.abs(sp.det)


# --------------------------------------------------------------------------------------------
# The per-pair block: Omega w |det A| C_i (6 entries) and w, with a hand-written reverse pass
# --------------------------------------------------------------------------------------------
@jax.custom_jvp
def _keep(x, one):
    """x, materialised: the identity x / one with `one` a per-element runtime 1.0 (an array, as
    XLA rewrites a division by a broadcast scalar into a multiplication). XLA:CPU duplicates cheap
    elementwise producers into every consumer fusion but not divisions, so this stores x once
    (forward) and, by the JVP rule, its cotangent once (backward); with a single consumer it is
    fused all the same. `lax.optimization_barrier` does not do this on CPU (it is removed before
    fusion). Where it pays: module docstring, "How it runs on XLA:CPU"."""
    return jax.tree.map(lambda a: a / one, x)


@_keep.defjvp
def _keep_jvp(primals, tangents):
    x, one = primals
    tx, _ = tangents
    return _keep(x, one), jax.tree.map(lambda a: a / one, tx)


_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))  # order of the 6 unique entries


def _f64(x):
    return jax.tree.map(lambda a: a.astype(jnp.float64), x)


def _block_columns(ctab, dtype):
    """(B, 17) camera rows (22 with distortion) -> as many (B, 1) columns in the pair dtype."""
    return [ctab[:, k].astype(dtype)[:, None] for k in range(ctab.shape[1])]


def _block_forward(cq, sq, occ, kc, one, energy, st, jacobian=False):
    """Per pair, from broadcastable components (cq the 17 camera columns, sq the 12 sample
    columns, occlusion, kc = Omega c^2 / sigma^2 in m^2, `one` a runtime 1.0 for `_keep`): ent,
    the 6 entries of k S^T T S in _SYM order (1/m^2, float64), with
    k = Omega w |det A| c^2/sigma^2 = kc w |det A|, and w (occlusion included); and the
    intermediates (geometry, spectrum, phis, T, beta, lam1 - lam2, k, and with `jacobian` the
    table lookup's d phi_i / d lam_j, else None)."""
    keep = lambda x: _keep(x, one)
    geo = _pairs_from(cq, sq, st)
    w = geo.w * occ
    s0, s1, A, w = keep((geo.s0, geo.s1, geo.A, w))
    geo = geo._replace(s0=s0, s1=s1, A=A)
    sp = _spectrum(geo.A, st.gap_eps)
    phis, jac = _phis(energy, sp.lam1, sp.lam2, st.kappa, jacobian)
    T, beta, D = _tensor_from(sp, *phis)
    *T, absdet = keep(T + (jnp.abs(sp.det),))
    # rooted at a divide: XLA:CPU materialises k once instead of re-deriving the weight chain
    # in every consumer fusion
    k = keep(kc * w * absdet)
    # the assembly k S^T T S runs in float64 whatever the pair dtype: each pair's matrix then
    # has the ray as its null vector to float64 precision (float32 rounding of the 6 entries
    # would leave an error ~1e-7 |C_i| along the ray, far above the prior 1/prior_sigma^2 that
    # alone measures that direction for a sample seen by one camera)
    s0, s1, (T00, T01, T11), k = _f64((geo.s0, geo.s1, tuple(T), k))
    k00, k01, k11 = k * T00, k * T01, k * T11
    ent = tuple(k00 * s0[a] * s0[b] + k11 * s1[a] * s1[b] + k01 * (s0[a] * s1[b] + s1[a] * s0[b])
                for a, b in _SYM)
    return ent, w, (geo, sp, phis, tuple(T), beta, D, k, jac)


@functools.partial(jax.custom_vjp, nondiff_argnums=(7, 8, 9))
def _sample_sums(ctab, geometry, occ, kc, one, sample, energy, st, chunk, n):
    """Per-sample sums over the listed pairs of ent (6 entries) and of w: 7 arrays (n,) (float64).

    ctab (B, 17) (22 with distortion) is the camera row of each block (float64); geometry the
    12 sample columns, occ, kc, one and sample (B, block) per pair, in the pair dtype; B a
    multiple of `chunk`. The per-pair work (`_block_forward`) runs over chunks of `chunk` blocks
    (`_chunked`).
    Differentiable with respect to ctab only (the other inputs are constants), by the
    hand-written `_block_vjp`, which recomputes the forward chunk by chunk."""
    dt = occ.dtype

    def forward(ctab, geometry, occ, kc, one):
        ent, w, _ = _block_forward(_block_columns(ctab, dt), geometry, occ, kc, one, energy, st)
        return ent, w

    ent, w = _chunked(forward, (ctab, geometry, occ, kc, one), chunk)
    return tuple(_per_sample(x, sample, n) for x in ent + (w,))


def _sample_sums_fwd(ctab, geometry, occ, kc, one, sample, energy, st, chunk, n):
    sums = _sample_sums(ctab, geometry, occ, kc, one, sample, energy, st, chunk, n)
    return sums, (ctab, geometry, occ, kc, one, sample, energy)


def _sample_sums_bwd(st, chunk, n, res, ct):
    ctab, geometry, occ, kc, one, sample, energy = res
    dt = occ.dtype

    def reverse(ctab, geometry, occ, kc, one, sample):
        c = [jnp.take(x, sample, mode="clip") for x in ct]
        return _block_vjp(ctab, geometry, occ, kc, one, tuple(c[:6]), c[6].astype(dt), energy, st)

    g = _chunked(reverse, (ctab, geometry, occ, kc, one, sample), chunk)
    return g, None, None, None, None, None, None


_sample_sums.defvjp(_sample_sums_fwd, _sample_sums_bwd)


def _chunked(fun, args, chunk):
    """fun(*args) for arrays whose leading axis is the B blocks, evaluated on chunks of `chunk`
    blocks in sequence (`lax.map`): the intermediates it materialises then stay in cache
    (measured 1.1-1.3x faster than one pass over all blocks)."""
    B = jax.tree.leaves(args)[0].shape[0]
    out = jax.lax.map(lambda x: fun(*x),
                      jax.tree.map(lambda x: x.reshape((B // chunk, chunk) + x.shape[1:]), args))
    return jax.tree.map(lambda x: x.reshape((B,) + x.shape[2:]), out)


def _block_vjp(ctab, sq, occ, kc, one, c_ent, c_w, energy, st):
    """Cotangent of the (B, 17) (or 22) block camera rows ctab for per-pair cotangents c_ent
    (6, float64) of ent and c_w of w, written out by hand (module docstring, "Reverse pass").

    With Q the symmetric 3x3 of c_ent (off-diagonals halved), L = k tr(T Y) + c_w w with
    Y = S Q S^T: dL/dk = tr(T Y), dL/dT = k Y (dL/dT01 = 2 k Y01), dL/ds0 = 2k (T00 Q s0 + T01 Q s1)
    and dL/ds1 likewise; then back through the spectrum, the footprint, the weights and the
    projection to the camera columns, summed over each block (one camera per block): for R
    (9 columns) its rotation part only, R's skew cotangent S R; position, f, cx, cy; width and
    height are pixel counts, not differentiated (0). The
    forward is recomputed, with the table lookup's Jacobian d phi_i / d lam_j.

    Values used by several later steps are materialised (`_keep`), and `_sample_sums` runs this
    on chunks that fit in cache (module docstring, "How it runs on XLA:CPU")."""
    keep = lambda x: _keep(x, one)
    cq = _block_columns(ctab, sq[0].dtype)
    _, w, (geo, sp, _, T, beta, D, k, jac) = _block_forward(cq, sq, occ, kc, one, energy, st,
                                                            jacobian=True)
    xn, yn, iz, g, p, d, rd, cos_inc, t_inc, t_img = keep(
        (geo.xn, geo.yn, geo.iz, geo.g, geo.p, geo.d, geo.rd, geo.cos_inc, geo.t_inc, geo.t_img))
    geo = geo._replace(xn=xn, yn=yn, iz=iz, g=g, p=p, d=d, rd=rd, cos_inc=cos_inc, t_inc=t_inc,
                       t_img=t_img)
    j11, j12, j21, j22 = jac
    s0, s1, (T00, T01, T11), k = _f64((geo.s0, geo.s1, T, k))
    c00, c11, c22, c01, c02, c12 = c_ent
    Q = ((c00, 0.5 * c01, 0.5 * c02), (0.5 * c01, c11, 0.5 * c12), (0.5 * c02, 0.5 * c12, c22))
    q0 = tuple(_dot(Q[a], s0) for a in range(3))
    q1 = tuple(_dot(Q[a], s1) for a in range(3))
    Y00, Y11, Y01 = _dot(s0, q0), _dot(s1, q1), _dot(s0, q1)
    tau = T00 * Y00 + T11 * Y11 + 2.0 * T01 * Y01  # dL/dk
    g_s0 = [2.0 * k * (T00 * q0[b] + T01 * q1[b]) for b in range(3)]
    g_s1 = [2.0 * k * (T11 * q1[b] + T01 * q0[b]) for b in range(3)]
    g_T00, g_T11, g_T01 = k * Y00, k * Y11, 2.0 * k * Y01
    # from here on in the pair dtype
    dt = sq[0].dtype
    tau, g_s0, g_s1, g_T00, g_T11, g_T01, c_w = keep(jax.tree.map(
        lambda a: a.astype(dt), (tau, g_s0, g_s1, g_T00, g_T11, g_T01, c_w)))
    absdet = jnp.abs(sp.det)
    g_w = c_w + tau * kc * absdet
    g_absdet = tau * kc * w
    # T = alpha I + beta (M - m I), alpha = (phi1 + phi2)/2, beta = (phi1 - phi2)/D
    g_alpha = g_T00 + g_T11
    g_beta = (g_T00 - g_T11) * sp.h + g_T01 * sp.M01
    g_h = (g_T00 - g_T11) * beta
    g_M01 = g_T01 * beta
    g_phi1 = 0.5 * g_alpha + g_beta / D
    g_phi2 = 0.5 * g_alpha - g_beta / D
    g_D = -g_beta * beta / D
    g_lam1 = g_D + g_phi1 * j11 + g_phi2 * j21
    g_lam2 = -g_D + g_phi1 * j12 + g_phi2 * j22
    # lam2 = max(det^2 / lam1, 1e-12 lam1), lam1 = m + gap, gap = sqrt(h^2 + M01^2 + (eps m)^2)
    unfloored = sp.q > 1e-12 * sp.lam1
    g_q = jnp.where(unfloored, g_lam2, 0.0)
    g_lam1 = g_lam1 + jnp.where(unfloored, 0.0, 1e-12 * g_lam2) - g_q * sp.q / sp.lam1
    g_det = g_q * 2.0 * sp.det / sp.lam1 + g_absdet * jnp.sign(sp.det)
    g_gap = g_lam1 / sp.gap
    g_h = g_h + g_gap * sp.h
    g_M01 = g_M01 + g_gap * sp.M01
    g_m = jnp.where(sp.m_raw > jnp.finfo(sp.m.dtype).tiny,
                    g_lam1 + g_gap * (st.gap_eps ** 2) * sp.m, 0.0)
    g_M00 = 0.5 * (g_m + g_h)
    g_M11 = 0.5 * (g_m - g_h)
    A00, A01, A10, A11 = geo.A
    g_A = (2.0 * A00 * g_M00 + A10 * g_M01 + A11 * g_det,
           2.0 * A01 * g_M00 + A11 * g_M01 - A10 * g_det,
           2.0 * A10 * g_M11 + A00 * g_M01 - A01 * g_det,
           2.0 * A11 * g_M11 + A01 * g_M01 + A00 * g_det)
    tu, tv = sq[6:9], sq[9:12]
    g_A = keep(g_A)
    g_s0, g_s1 = keep(([g_s0[b] + g_A[0] * tu[b] + g_A[1] * tv[b] for b in range(3)],
                       [g_s1[b] + g_A[2] * tu[b] + g_A[3] * tv[b] for b in range(3)]))
    # weights: w = [front] S(t_inc) S(t_1) S(t_2) S(t_3) S(t_4) occ, S' = 30 t^2 (1 - t)^2
    g_raw = jnp.where(geo.front, g_w * occ, 0.0)
    ts = (geo.t_inc,) + geo.t_img
    S = keep([smoothstep(t) for t in ts])
    dS = keep([_smoothstep_grad(t) for t in ts])
    prod = lambda xs: functools.reduce(lambda a, b: a * b, xs)
    g_t = keep([g_raw * dS[i] * prod(S[:i] + S[i + 1:]) for i in range(5)])
    _, inc_scale, mg = _weight_scales(st)
    g_cos = g_t[0] * inc_scale
    g_u, g_v = mg * (g_t[1] - g_t[2]), mg * (g_t[3] - g_t[4])
    # projection: s0 = g (R0 - xn R2), s1 = g (R1 - yn R2), g = f iz, u = f xn + cx, v = f yn + cy
    R = [cq[3 * a:3 * a + 3] for a in range(3)]
    f = cq[_F]
    if geo.lens is not None:
        # s0 = g (a e0 + b e1), s1 = g (b e0 + d e1), e0 = R0 - xn R2, e1 = R1 - yn R2, D = [[a, b],
        # [b, d]] a function of (xn, yn), u = f x_d + cx, v = f y_d + cy: the pinhole chain below
        # with the cotangents D (g_s0, g_s1) of e0/g, e1/g, plus D's and (x_d, y_d)'s own
        # dependence on (xn, yn) (`vdo.model.camera.distortion_curvature`)
        coefficients, xd, yd, (jxx, jxy, jyy) = geo.lens
        e0 = [R[0][b] - geo.xn * R[2][b] for b in range(3)]
        e1 = [R[1][b] - geo.yn * R[2][b] for b in range(3)]
        g_jxx, g_jyy = geo.g * _dot(g_s0, e0), geo.g * _dot(g_s1, e1)
        g_jxy = geo.g * (_dot(g_s0, e1) + _dot(g_s1, e0))
        g_s0, g_s1 = ([jxx * g_s0[b] + jxy * g_s1[b] for b in range(3)],
                      [jxy * g_s0[b] + jyy * g_s1[b] for b in range(3)])
        d_xxx, d_xxy, d_xyy, d_yyy = distortion_curvature(geo.xn, geo.yn, coefficients)
        g_xd, g_yd = f * g_u, f * g_v
        lens_xn = jxx * g_xd + jxy * g_yd + g_jxx * d_xxx + g_jxy * d_xxy + g_jyy * d_xyy
        lens_yn = jxy * g_xd + jyy * g_yd + g_jxx * d_xxy + g_jxy * d_xyy + g_jyy * d_yyy
        lens_f = g_u * xd + g_v * yd
    g_e0 = [geo.g * x for x in g_s0]
    g_e1 = [geo.g * x for x in g_s1]
    g_g = (_dot(g_s0, [R[0][b] - geo.xn * R[2][b] for b in range(3)])
           + _dot(g_s1, [R[1][b] - geo.yn * R[2][b] for b in range(3)]))
    h = [[_dot(g_e, R[c]) for c in range(3)] for g_e in (g_e0, g_e1)]  # camera-frame components
    if geo.lens is None:
        g_xn = f * g_u - h[0][2]
        g_yn = f * g_v - h[1][2]
        g_f = g_u * geo.xn + g_v * geo.yn + g_g * geo.iz
    else:
        g_xn = lens_xn - h[0][2]
        g_yn = lens_yn - h[1][2]
        g_f = lens_f + g_g * geo.iz
    g_iz = g_g * f + g_xn * geo.p[0] + g_yn * geo.p[1]
    g_p = keep((g_xn * geo.iz, g_yn * geo.iz, jnp.where(geo.front, -g_iz * geo.iz * geo.iz, 0.0)))
    # cos_inc = -n.d / |d|, p = R d, d = X - P
    nrm = sq[3:6]
    g_d = [g_cos * geo.rd * (-nrm[b] - geo.cos_inc * geo.rd * geo.d[b]) + _dot(g_p, [R[a][b] for a in range(3)])
           for b in range(3)]
    # rotation: R stays a rotation (dR = W R, W skew), so only the skew part of M = dL/dR R^T
    # counts; M_ac = h_a[c] + g_p[a] p[c] with h_a the camera-frame components of the cotangent
    # of row a of R (h_2 = -(xn h_0 + yn h_1)), and per pair we keep M_ac - M_ca
    h.append([-(geo.xn * h[0][c] + geo.yn * h[1][c]) for c in range(3)])
    M = lambda a, c: h[a][c] + g_p[a] * geo.p[c]
    cols = [M(0, 1) - M(1, 0), M(0, 2) - M(2, 0), M(1, 2) - M(2, 1)] + [-x for x in g_d] + [
        g_f, g_u, g_v]
    # the block sums as one batched dot with ones (float64 accumulation): value + gradient ~15 %
    # faster than with separate row sums
    cols = jnp.stack(jnp.broadcast_arrays(*cols), 1)  # (blocks, 9, block)
    sums = jnp.einsum("gkl,l->gk", cols, jnp.ones(cols.shape[-1], cols.dtype),
                      preferred_element_type=ctab.dtype)
    # dL/dR of the block as S R, S = (M - M^T)/2 summed: the same dL for every rotation of R
    u01, u02, u12 = sums[:, 0], sums[:, 1], sums[:, 2]
    zero = jnp.zeros_like(u01)
    S = 0.5 * jnp.stack([jnp.stack([zero, u01, u02], -1), jnp.stack([-u01, zero, u12], -1),
                         jnp.stack([-u02, -u12, zero], -1)], -2)
    g_R = jnp.einsum("gab,gbc->gac", S, ctab[:, _R].reshape(-1, 3, 3)).reshape(-1, 9)
    # W, H and the distortion coefficients: constants
    constants = jnp.zeros((sums.shape[0], ctab.shape[1] - _W), sums.dtype)
    return jnp.concatenate([g_R, sums[:, 3:], constants], -1)


def _pair_inputs(cam, vd: ViewData, st, dt):
    """The per-pair inputs: the camera row of each block (B, 17, or 22 with distortion) (float64)
    and, as (B, block)
    arrays in dtype dt, the 12 sample columns of the pairs' geometry, the occlusion,
    kc = Omega c^2 / sigma^2 (m^2) and a runtime 1.0 (`_keep`)."""
    L = vd.block
    B = vd.camera.shape[0] // L
    occ, cn, nz = (jax.lax.stop_gradient(x).reshape(B, L)
                   for x in (vd.occlusion, vd.contrast, vd.noise))
    kc = st.patch_area * cn * cn / (nz * nz)  # m^2
    one = (nz / nz).astype(dt)  # 1.0 (noise > 0) per pair, unknown to XLA
    ctab = _camera_table(cam)[vd.camera.reshape(B, L)[:, 0]]
    geometry = [x.astype(dt) for x in jax.lax.stop_gradient(vd.geometry)]
    return ctab, geometry, occ.astype(dt), kc.astype(dt), one


def _pair_terms(cam, vd: ViewData, energy, st):
    """Per listed pair, as (B, block) arrays of the camera-major list, for the reports (float64
    whatever `st.pair_dtype`; not differentiated): ent, w and the geometry (`_block_forward`)."""
    ctab, geometry, occ, kc, one = _pair_inputs(cam, vd, st, jnp.float64)
    ent, w, (geo, *_) = _block_forward(_block_columns(ctab, jnp.float64), geometry, occ, kc, one,
                                       energy, st)
    return ent, w, geo


def _per_sample(x, sample, n):
    """Sum a per-pair array over the pairs of each sample (`sample` its indices, same shape),
    in float64: (n,)."""
    return jax.ops.segment_sum(x.reshape(-1).astype(jnp.float64), sample.reshape(-1), n)


def _per_pair_dense(x, vd: ViewData, c, n):
    """Scatter a (B, block) per-pair array into (C, N) (zeros where not listed)."""
    return jnp.zeros((c, n)).at[vd.camera, vd.sample].add(x.reshape(-1).astype(jnp.float64))


def _sym_full(e):
    """6 entries (_SYM order) -> (..., 3, 3)."""
    c00, c11, c22, c01, c02, c12 = e
    return jnp.stack([jnp.stack([c00, c01, c02], -1), jnp.stack([c01, c11, c12], -1),
                      jnp.stack([c02, c12, c22], -1)], -2)



def _smooth_sigma_max(ent, st: Settings, keep=lambda x: x):
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
    geo = _pairs(cameras, samples, settings)
    s0, s1, A, u, v, w = geo.s0, geo.s1, geo.A, geo.u, geo.v, geo.w
    s = jnp.stack([jnp.stack(s0, -1), jnp.stack(s1, -1)], -2)
    A = jnp.stack([jnp.stack(A[:2], -1), jnp.stack(A[2:], -1)], -2)
    return Geometry(jnp.stack([u, v], -1), s, A, w)


@eqx.filter_jit
def gradient_tensor(footprint, energy, kappa: float = KAPPA_BOX, gap_eps: float = 1e-4):
    """T / c^2 = sum_k G(kappa/a_k, kappa/a_other)/a_k^2 v_k v_k^T (..., 2, 2) in 1/pixel^2 for
    footprints A (..., 2, 2) in pixel/m; differentiable also where a_1 = a_2."""
    A = (footprint[..., 0, 0], footprint[..., 0, 1], footprint[..., 1, 0], footprint[..., 1, 1])
    (t00, t01, t11), _ = _tensor(A, energy, kappa, gap_eps)
    return jnp.stack([jnp.stack([t00, t01], -1), jnp.stack([t01, t11], -1)], -2)


@eqx.filter_jit
def camera_information(cameras: CameraParams, samples: Samples, views: ViewData, energy,
                       settings: Settings = Settings()):
    """Each camera's contribution Omega w_i |det A_i| C_i to the sample information, (C, N, 3, 3)
    in 1/m^2 (C_i = sigma_i^-2 s_i^T T_i s_i per pixel; rank 2, null vector along the ray); zero
    for pairs not listed in `views`."""
    ent, _, _ = _pair_terms(cameras, views, energy, settings)
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
    """`_pair_terms`' entries and weights as one compiled program (`pair_information`: run op by
    op, its ~100 operations each compiled and dispatched alone)."""
    ent, w, _ = _pair_terms(cameras, views, energy, settings)
    return ent, w


@eqx.filter_jit
def information(cameras: CameraParams, samples: Samples, views: ViewData, energy,
                settings: Settings = Settings()):
    """C = Omega sum_i w_i |det A_i| C_i per sample, (N, 3, 3) in 1/m^2 (no regularisation)."""
    ent, _, _ = _pair_terms(cameras, views, energy, settings)
    n = samples.points.shape[0]
    return _sym_full(tuple(_per_sample(e, views.sample, n) for e in ent))


def _score(cameras, samples, views, energy, settings):
    ctab, geometry, occ, kc, one = _pair_inputs(cameras, views, settings,
                                                jnp.dtype(settings.pair_dtype))
    n = samples.points.shape[0]
    sample = views.sample.reshape(occ.shape)
    sums = _sample_sums(ctab, geometry, occ, kc, one, sample, jax.lax.stop_gradient(energy),
                        settings, views.chunk, n)
    # materialised, so that the backward delivers each of the 7 per-sample cotangents once
    # (XLA:CPU otherwise fuses them into one loop that re-derives the per-sample chain per row)
    ones = jax.lax.stop_gradient(samples.area / samples.area)  # runtime 1.0 per sample
    keep = lambda x: _keep(x, ones)
    *ent, cov = keep(sums)
    sigma = _smooth_sigma_max(ent, settings, keep) / settings.sigma_unit
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
    ent, w, geo = _pair_terms(cameras, views, energy, settings)
    s0, s1 = geo.s0, geo.s1
    c, n = cameras.position.shape[0], samples.points.shape[0]
    ent = tuple(_per_sample(e, views.sample, n) for e in ent)
    sens = jnp.stack([jnp.sqrt(_per_sample(w * (s0[k] ** 2 + s1[k] ** 2), views.sample, n))
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
                  sigma_max_smooth=_smooth_sigma_max(ent, settings),
                  coverage=_per_sample(w, views.sample, n), measured=measured,
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
    ctab, geometry, occ, kc, one = _pair_inputs(cameras, views, settings,
                                                jnp.dtype(settings.pair_dtype))
    n = samples.points.shape[0]
    *ent, cov = _sample_sums(ctab, geometry, occ, kc, one, views.sample.reshape(occ.shape),
                             jax.lax.stop_gradient(energy), settings, views.chunk, n)
    C = _sym_full(ent)
    reg = C + jnp.eye(3) / settings.prior_sigma ** 2
    tc = jnp.trace(reg, axis1=-2, axis2=-1)   # scaled to trace 1 before the inverse
    sigma_xyz = jnp.sqrt(jnp.diagonal(jnp.linalg.inv(reg / tc[:, None, None]), axis1=-2, axis2=-1)
                         / tc[:, None])
    return SampleFields(information=C, sigma_xyz=sigma_xyz, sigma_max=_smooth_sigma_max(ent, settings),
                        coverage=cov, area=samples.area, region=samples.region,
                        importance=samples.importance, min_cameras=samples.min_cameras)
