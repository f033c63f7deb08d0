"""Subset DIC as a lab's stereo software runs it: each camera's reference and deformed images
matched in 2D with square subsets (`match_subsets`), then the cameras' matched image points
triangulated (`triangulate`); `correlate_subsets_2d` does both for 3D points.

The match of one subset. Its reference pixels are n = c + d, d ∈ [-h, h]² (side 2h + 1 =
`size_px`), c the point's image x rounded to a pixel; local coordinates ξ = n - x, so that the
warp's translation is the image motion of the point itself. With the shape function

    W(ξ; p) = ξ + (u + u_x ξ₁ + u_y ξ₂,  v + v_x ξ₁ + v_y ξ₂)        ("affine", p = (u, u_x, u_y, v, v_x, v_y))
    W(ξ; p) = ξ + (u, v)                                             ("zero", p = (u, v))

the criterion is the zero-normalised sum of squared differences (ZNSSD, insensitive to an offset
and a scale of the grey levels per subset)

    C(p) = Σ_n [ (g_n - ḡ)/Δg - (f(x + W(ξ_n; p)) - f̄)/Δf ]²,      Δ = sqrt(Σ_n (· - mean)²),

g the reference at its own pixels (no interpolation), f the deformed image's cubic B-spline
(`vdo.dic.images.SplineImage`, sampled by the compiled `vdo.dic.subset_sums.spline_sample`).
ZNCC = 1 - C / 2.

The iteration is the inverse compositional Gauss–Newton (IC-GN) of Baker and Matthews, with the
ZNSSD form of Pan, Li and Tong (2013): the steepest-descent images J_n = ∇g_n ∂W/∂p (at p = 0,
∇g the reference spline's gradient at its pixel centres) and H = Σ_n J_nᵀ J_n are computed once
per subset; each step

    Δp = -H⁻¹ Σ_n J_nᵀ [ (g_n - ḡ) - (Δg/Δf)(f_n - f̄) ],      W(·; p) ← W(·; p) ∘ W(·; Δp)⁻¹

(the warps as 3 × 3 affine matrices), until the step moves no subset pixel by more than `tol_px`:
sqrt(Δu² + Δv² + h² (Δu_x² + Δu_y² + Δv_x² + Δv_y²)) < tol_px. A subset whose warped pixels leave
the deformed image's spline window stops there, unconverged.

Triangulation: X minimises Σ_i |π_i(X) - x'_i|² over the cameras i (π_i the camera's projection,
lens distortion included), Gauss–Newton from the start with S_i = ∂x/∂X (`Camera.sensitivity`).

Every subset of a chunk of SUBSET_CHUNK runs in one XLA program (float64), the chunks on
`workers` threads. Above `vdo.dic.images`, `vdo.dic.shifts` and `vdo.dic.subset_sums`; used by
`vdo.dic.series.correlate_points` (`subset_px`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from vdo.dic.images import SPLINE_ORDER, SplineImage
from vdo.dic.subset_sums import reference_arrays, sample_box, spline_sample, window_arrays

log = logging.getLogger(__name__)

__all__ = ["SHAPE_FUNCTIONS", "SUBSET_CHUNK", "TOL_PX", "MAX_ITER", "DEFORMED_MARGIN_PX", "START_HALF",
           "SubsetMatch", "match_subsets", "triangulate", "correlate_subsets_2d"]

SHAPE_FUNCTIONS = {"zero": 2, "affine": 6}   # parameters of each shape function
SUBSET_CHUNK = 256          # subsets in one compiled program: (chunk, pixels) arrays of ~1.7 MB
TOL_PX = 1e-3               # px: a step that moves no subset pixel further than this ends the
                            # match (it is applied; the next one, ~its square, is left out)
MAX_ITER = 30               # IC-GN steps at most per subset
DEFORMED_MARGIN_PX = 8.0    # the deformed spline's window reaches this far beyond the start's
                            # subsets (plus the subset's half side for a stretch or turn)
START_HALF = 24             # px: the start's cross-correlation windows are 2 START_HALF + 1 wide
TRIANGULATION_STEPS = 10    # Gauss–Newton steps of `triangulate` at most ...
TRIANGULATION_TOL = 1e-12   # ... or until no point moves by more than this (m)


@dataclass(eq=False)
class SubsetMatch:
    """`match_subsets`' answer for K subsets of one camera: p (K, n) the shape function's
    parameters (u, u_x, u_y, v, v_x, v_y) for "affine", (u, v) for "zero" (px, and px per px);
    x (K, 2) the points' matched image positions in the deformed image, x + (u, v) (px);
    znssd (K,) the criterion at the last step's start (0: identical subsets, ZNCC = 1 - znssd / 2);
    iterations (K,); converged (K,): the last step moved no pixel by more than tol_px and no
    warped pixel left the deformed spline's window."""

    p: np.ndarray
    x: np.ndarray
    znssd: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray


def _compose(p, dp, affine: bool):
    """The parameters of W(·; p) ∘ W(·; dp)⁻¹, (K, n), written out: as 2 × 3 affine matrices
    A = [[1 + u_x, u_y, u], [v_x, 1 + v_y, v]] the product A(p) A(dp)⁻¹ (XLA makes a batched 3 × 3
    product or inverse a library call that costs more than the arithmetic)."""
    if not affine:
        return p - dp
    a, b, c, d, e, f = 1 + p[:, 1], p[:, 2], p[:, 0], p[:, 4], 1 + p[:, 5], p[:, 3]
    a2, b2, c2, d2, e2, f2 = 1 + dp[:, 1], dp[:, 2], dp[:, 0], dp[:, 4], 1 + dp[:, 5], dp[:, 3]
    det = a2 * e2 - b2 * d2
    i00, i01, i02 = e2 / det, -b2 / det, (b2 * f2 - c2 * e2) / det
    i10, i11, i12 = -d2 / det, a2 / det, (c2 * d2 - a2 * f2) / det
    return jnp.stack([a * i02 + b * i12 + c, a * i00 + b * i10 - 1, a * i01 + b * i11,
                      d * i02 + e * i12 + f, d * i00 + e * i10, d * i01 + e * i11 - 1], -1)


def _cholesky(H):
    """The Cholesky factor L (lists of (K,) arrays, L[i][j] for j <= i) of the symmetric
    matrices H (lists, H[i][j] for j <= i), written out for small n: NaN where H is not
    positive definite (a subset without texture)."""
    n = len(H)
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        L[j][j] = jnp.sqrt(H[j][j] - sum(L[j][k] ** 2 for k in range(j)))
        for i in range(j + 1, n):
            L[i][j] = (H[i][j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    return L


def _solve(L, b):
    """x with L Lᵀ x = b (b a list of (K,) arrays), by substitution."""
    n = len(L)
    y = []
    for i in range(n):
        y.append((b[i] - sum(L[i][k] * y[k] for k in range(i))) / L[i][i])
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(L[k][i] * x[k] for k in range(i + 1, n))) / L[i][i]
    return x


@partial(jax.jit, static_argnames=("half", "affine", "order", "max_iter"))
def _icgn(image, grad_u, grad_v, ref_origin, coeffs, dfm_origin, valid, x, p0, tol, *,
          half, affine, order, max_iter):
    """The IC-GN of the module docstring for K subsets at once: reference window arrays `image`,
    `grad_u`, `grad_v` with corner pixel `ref_origin` (u, v) (int); the deformed spline's
    coefficients `coeffs` on the window with corner `dfm_origin` (u, v), where a sample is the
    whole image's inside `valid` = (u0, u1, v0, v1); the points' images x (K, 2) and the start
    p0 (K, n). Returns p, znssd (at the last step's start: e = (g - ḡ) - (Δg/Δf)(f - f̄) is
    Δg times the ZNSSD's residual), iterations, converged. H and its Cholesky factor are summed
    and written out entry by entry (as batched products and factorisations XLA calls a library
    per subset)."""
    d = jnp.arange(-half, half + 1, dtype=jnp.float64)
    d1, d2 = (a.ravel() for a in jnp.meshgrid(d, d, indexing="xy"))
    c = jnp.round(x)
    n1, n2 = c[:, :1] + d1, c[:, 1:] + d2                              # (K, P) reference pixels
    xi1, xi2 = n1 - x[:, :1], n2 - x[:, 1:]
    corner = (c - half - ref_origin).astype(jnp.int32)                   # (u, v) in the window
    side = 2 * half + 1

    def block(a):
        """The subsets' reference pixels of a window array (K, P), row by row (contiguous
        slices: cheaper than a gather per pixel)."""
        return jax.vmap(lambda q: jax.lax.dynamic_slice(a, (q[1], q[0]), (side, side)))(corner).reshape(len(c), -1)

    g, gu, gv = (block(a) for a in (image, grad_u, grad_v))
    J = [gu, gu * xi1, gu * xi2, gv, gv * xi1, gv * xi2] if affine else [gu, gv]
    L = _cholesky([[jnp.sum(J[i] * J[j], axis=1) for j in range(i + 1)] for i in range(len(J))])
    gc = g - g.mean(axis=1, keepdims=True)
    dg = jnp.sqrt(jnp.sum(gc * gc, axis=1))
    x1, x2 = x[:, :1] + xi1, x[:, 1:] + xi2

    def sampled(p):
        """f at the warped pixels (K, P), centred, its Δf (K,), and whether all lie in `valid`."""
        if affine:
            pu = x1 + p[:, 0:1] + p[:, 1:2] * xi1 + p[:, 2:3] * xi2
            pv = x2 + p[:, 3:4] + p[:, 4:5] * xi1 + p[:, 5:6] * xi2
        else:
            pu, pv = x1 + p[:, 0:1], x2 + p[:, 1:2]
        inside = jnp.all((pu >= valid[0]) & (pu <= valid[1]) & (pv >= valid[2]) & (pv <= valid[3]), axis=1)
        f = spline_sample(coeffs, pv - dfm_origin[1], pu - dfm_origin[0], order)
        fc = f - f.mean(axis=1, keepdims=True)
        return fc, jnp.sqrt(jnp.sum(fc * fc, axis=1)), inside

    scale = [1.0, half, half, 1.0, half, half] if affine else [1.0, 1.0]

    def step(state):
        it, p, done, iters, ok, znssd = state
        fc, df, inside = sampled(p)
        e = gc - (dg / jnp.where(df > 0, df, 1.0))[:, None] * fc
        dp = jnp.stack([-v for v in _solve(L, [jnp.sum(Ji * e, axis=1) for Ji in J])], -1)
        moving = ~done & inside & (df > 0)
        p = jnp.where(moving[:, None], _compose(p, dp, affine), p)
        small = jnp.sqrt(sum((dp[:, i] * s) ** 2 for i, s in enumerate(scale))) < tol
        iters = jnp.where(moving, it + 1, iters)
        ok = ok | (moving & small)
        znssd = jnp.where(moving, jnp.sum(e * e, axis=1) / jnp.where(dg > 0, dg * dg, 1.0), znssd)
        done = done | ~inside | (df == 0) | small
        return it + 1, p, done, iters, ok, znssd

    K = x.shape[0]
    state = (0, p0, jnp.zeros(K, bool), jnp.zeros(K, jnp.int32), jnp.zeros(K, bool), jnp.full(K, jnp.nan))
    _, p, _, iters, ok, znssd = jax.lax.while_loop(lambda s: (s[0] < max_iter) & ~jnp.all(s[2]), step, state)
    return p, znssd, iters, ok


def match_subsets(reference, deformed, points, start=None, *, size_px: int = 29,
                  shape_function: str = "affine", tol_px: float = TOL_PX, max_iter: int = MAX_ITER,
                  workers: int = 1) -> SubsetMatch:
    """Match the square subsets of side `size_px` (odd, ≥ 5) centred on the image points
    `points` (K, 2) (u, v) px of the gray image `reference` in the gray image `deformed` (same
    shape), by IC-GN on the ZNSSD (module docstring), from the image motion `start` (K, 2) px
    (default 0; the affine terms start at 0). `workers` threads share the chunks of
    SUBSET_CHUNK subsets. A subset whose reference pixels leave the image is not matched
    (converged False, p = the start)."""
    if shape_function not in SHAPE_FUNCTIONS:
        raise ValueError(f"shape_function: expected one of {', '.join(SHAPE_FUNCTIONS)}, got "
                         f"{shape_function!r}")
    if int(size_px) != size_px or size_px < 5 or size_px % 2 == 0:
        raise ValueError(f"size_px: expected an odd whole number of pixels >= 5, got {size_px!r}")
    if not tol_px > 0 or int(max_iter) < 1:
        raise ValueError(f"tol_px > 0 and max_iter >= 1 expected, got {tol_px!r} and {max_iter!r}")
    ref, dfm = np.asarray(reference), np.asarray(deformed)     # the windows become float64
    if ref.ndim != 2 or ref.shape != dfm.shape:
        raise ValueError(f"match_subsets: expected two gray images of one shape, got {ref.shape} "
                         f"and {dfm.shape}")
    x = np.asarray(points, dtype=float).reshape(-1, 2)
    K, half, affine = len(x), int(size_px) // 2, shape_function == "affine"
    n = SHAPE_FUNCTIONS[shape_function]
    p0 = np.zeros((K, n))
    if start is not None:
        p0[:, [0, n // 2]] = np.asarray(start, dtype=float).reshape(K, 2)
    H, W = ref.shape
    c = np.rint(x)
    whole = np.all(np.isfinite(x), axis=1) & (c[:, 0] - half >= 0) & (c[:, 1] - half >= 0) \
        & (c[:, 0] + half <= W - 1) & (c[:, 1] + half <= H - 1)
    out = SubsetMatch(p=p0.copy(), x=x + p0[:, [0, n // 2]], znssd=np.full(K, np.nan),
                      iterations=np.zeros(K, int), converged=np.zeros(K, bool))
    idx = np.flatnonzero(whole)
    if not len(idx):
        return out
    box = np.concatenate([c[idx] - half, c[idx] + half])
    ref_spline = SplineImage.around(ref, box, 0.0, SPLINE_ORDER)
    ref_arrays = reference_arrays(ref, ref_spline)
    moved = x[idx] + p0[idx][:, [0, n // 2]]
    dfm_spline = SplineImage.around(dfm, np.concatenate([moved - half, moved + half]),
                                    DEFORMED_MARGIN_PX + half, SPLINE_ORDER)
    coeffs, = window_arrays(dfm_spline, (dfm_spline.coeffs,))
    valid = sample_box(dfm_spline)
    chunks = [idx[k:k + SUBSET_CHUNK] for k in range(0, len(idx), SUBSET_CHUNK)]

    def run(k):
        """The subsets k, padded to SUBSET_CHUNK with copies of the first (one compiled shape)."""
        fill = np.concatenate([k, np.full(SUBSET_CHUNK - len(k), k[0])])
        p, znssd, iters, ok = _icgn(*ref_arrays, ref_spline.origin, coeffs, dfm_spline.origin, valid,
                                    jnp.asarray(x[fill]), jnp.asarray(p0[fill]), float(tol_px),
                                    half=half, affine=affine, order=SPLINE_ORDER, max_iter=int(max_iter))
        m = len(k)
        out.p[k], out.znssd[k] = np.asarray(p)[:m], np.asarray(znssd)[:m]
        out.iterations[k], out.converged[k] = np.asarray(iters)[:m], np.asarray(ok)[:m]
        return m

    from vdo.core.parallel import run_chunks

    run_chunks(run, chunks, workers, log, len(idx), "subsets", "subset")
    out.x = x + out.p[:, [0, n // 2]]
    return out


def triangulate(cameras, image_points, X0) -> tuple[np.ndarray, np.ndarray]:
    """The world points X (K, 3) m whose images in `cameras` (two or more) are closest to
    `image_points` (C, K, 2) px in the least-squares sense (module docstring), from X0 (K, 3);
    and the RMS reprojection residual per point (K,) px."""
    x = np.asarray(image_points, dtype=float)
    X = np.array(X0, dtype=float).reshape(-1, 3)
    if len(cameras) < 2 or x.shape != (len(cameras), len(X), 2):
        raise ValueError(f"triangulate: expected image points (cameras >= 2, {len(X)}, 2), got {x.shape}")
    for _ in range(TRIANGULATION_STEPS):
        r = np.concatenate([x[i] - cam.project(X) for i, cam in enumerate(cameras)], axis=1)
        S = np.concatenate([np.asarray(cam.sensitivity(X)) for cam in cameras], axis=1)
        dX = np.linalg.solve(np.einsum("kai,kaj->kij", S, S), np.einsum("kai,ka->ki", S, r)[..., None])[..., 0]
        X += dX
        if np.max(np.abs(dX), initial=0.0) < TRIANGULATION_TOL:
            break
    r = np.stack([x[i] - cam.project(X) for i, cam in enumerate(cameras)])
    return X, np.sqrt(np.mean(np.sum(r * r, axis=-1), axis=0))


def correlate_subsets_2d(cameras, references, deformed, points, U0=None, *, size_px: int = 29,
                         shape_function: str = "affine", tol_px: float = TOL_PX,
                         max_iter: int = MAX_ITER, start_half: int = START_HALF, workers: int = 1):
    """The displacement (N, 3) m of the world points `points` (N, 3) that subset DIC measures:
    in each camera the subset of `size_px` pixels around the point's image matched from the
    camera's reference to its deformed image (`match_subsets`), the matched points triangulated
    (`triangulate`). Each camera starts from the image motion of U0 (N, 3) m where its row is
    finite, elsewhere from its own shift (`vdo.dic.shifts.image_shifts` of windows 2 `start_half`
    + 1 px wide, the peak refined to a fraction of a pixel; 0 where the window leaves the image). The cameras run side by
    side on `workers` threads. Returns (U, converged (N,): every camera's match converged and
    the triangulated point finite, matches: the cameras' `SubsetMatch`es); U is U0 (0 where not
    given) where not converged."""
    from vdo.dic.shifts import image_shifts

    X = np.asarray(points, dtype=float).reshape(-1, 3)
    U0 = np.full_like(X, np.nan) if U0 is None else np.asarray(U0, dtype=float).reshape(-1, 3)
    given = np.all(np.isfinite(U0), axis=1)
    if len(cameras) < 2 or len(references) != len(cameras) or len(deformed) != len(cameras):
        raise ValueError("correlate_subsets_2d: expected two or more cameras, one reference and one "
                         "deformed image each")

    def match(i):
        cam, h = cameras[i], start_half
        x = cam.project(X)
        start = np.zeros_like(x)
        start[given] = cam.project(X[given] + U0[given]) - x[given]
        c = np.rint(x).astype(int)
        inside = ~given & np.all(np.isfinite(x), axis=1) & (c[:, 0] >= h) & (c[:, 1] >= h) \
            & (c[:, 0] <= cam.width - 1 - h) & (c[:, 1] <= cam.height - 1 - h)
        start[inside] = image_shifts(references[i], deformed[i], c[inside], h, subpixel=True)
        return match_subsets(references[i], deformed[i], x, start, size_px=size_px,
                             shape_function=shape_function, tol_px=tol_px, max_iter=max_iter,
                             workers=max(1, workers // len(cameras)))

    if workers > 1:        # the cameras side by side (their starts and splines' prefilters too)
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(int(workers), len(cameras))) as pool:
            matches = list(pool.map(match, range(len(cameras))))
    else:
        matches = [match(i) for i in range(len(cameras))]
    moved, _ = triangulate(cameras, np.stack([m.x for m in matches]), np.where(given[:, None], X + U0, X))
    converged = np.all([m.converged for m in matches], axis=0) & np.all(np.isfinite(moved), axis=1)
    return np.where(converged[:, None], moved - X, np.where(given[:, None], U0, 0.0)), converged, matches
