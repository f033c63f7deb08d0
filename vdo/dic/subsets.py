"""Many square subsets at once: `correlate_subsets`, the subset (pairs) correlation of a
full-field grid, and its answer `SubsetResult`.

Subset k is the Q4(1, 1) patch of side `size` centred on points[k], correlated as
`vdo.dic.correlate.correlate(..., ImageReference(references), model=Q4(1, 1))` correlates it:
the same modified Gauss–Newton steps (each camera's reference pixel centres on the subset, J from
the reference spline's gradient there, brightness and contrast per camera solved alongside), here
vectorised over chunks of SUBSET_CHUNK subsets: the per-camera normal matrices M_i (14 × 14) are
summed once, only the residual's sums are formed per step (one compiled program per camera,
`vdo.dic.subset_sums`, on one window of B-spline coefficients per image,
`vdo.dic.images.SplineImage.around` all the subsets), and the step is the batched scaled eigen
pseudo-inverse. The subsets it cannot batch (an image's margin, a corner behind a camera, lens
distortion, a sample that left the deformed window) are handed to `correlate` itself
(`SubsetResult.one_by_one`).

Above `vdo.dic.correlate` (which it calls), `vdo.dic.subset_sums`, `vdo.dic.patch` and
`vdo.dic.images`; used by `vdo.dic.series`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from vdo.core.tolerances import LIMIT_SLACK
from vdo.dic.correlate import ImageReference, Q4, Solver, correlate
from vdo.dic.images import SPLINE_ORDER, SplineImage
from vdo.dic.patch import Patch
from vdo.dic.subset_sums import (BOX_PAD, padded, reference_arrays, residual_sums, sample_box, subset_setup,
                                 window_arrays)
from vdo.model.camera import image_point

log = logging.getLogger(__name__)

__all__ = ["SUBSET_CHUNK", "DEFORMED_MARGIN_PX", "SubsetResult", "correlate_subsets"]


SUBSET_CHUNK = 64       # subsets solved together: (chunk, pixels, 14) arrays of a few MB
DEFORMED_MARGIN_PX = 8.0    # the deformed images' splines reach this far beyond the starting
                            # subsets (`WindowedImage`'s margin); a subset that moves further is
                            # handed to `correlate`


@dataclass(eq=False)
class SubsetResult:
    """`correlate_subsets`' answer for P subsets and n cameras: U (P, 4, 3) the Q4(1, 1) node
    displacements (m, world frame, node order of `Q4`), b, c (P, n) the brightness and contrast,
    iterations (P,), converged (P,), one_by_one (P,): the subsets solved by `correlate` itself
    (one that meets an image's margin, a corner behind a camera, a camera with lens distortion,
    a sample that left the deformed spline's window). `centre` is U at the subset centre, the
    mean of the four nodes."""

    U: np.ndarray
    b: np.ndarray
    c: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    one_by_one: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        return self.U.mean(axis=1)


def correlate_subsets(cameras: Sequence, references: Sequence, deformed: Sequence, points, tangent_u,
                      tangent_v, size: float, U0=None, *, solver: Solver = Solver(),
                      order: int = SPLINE_ORDER, margin_px: float = 3.0, workers: int = 1) -> SubsetResult:
    """Subset k, for every k at once, as `correlate(cameras, deformed, patch_k,
    ImageReference(references), model=Q4(1, 1), U0=U0[k], solver=solver, order=order)` solves it,
    with patch_k the square of side `size` (m) centred on points[k] (P, 3) in the plane of
    (tangent_u[k], tangent_v[k]) (P, 3) each, U0 (P, 3) or (P, 4, 3) (default 0).

    The same Gauss–Newton iteration, step for step and point for point, vectorised over the
    points: each camera's integration points are its reference pixel centres on the patch seen
    by every camera `margin_px` inside its image (`vdo.dic.patch.pixel_points`); J = [c_i ∇g_i s_i N, -1, -g_i]
    with ∇g_i the reference spline's gradient at its pixel centres (the B-spline's derivative
    stencil there), so that per camera M_i = Σ_p j_p j_pᵀ, j = [∇g s ⊗ N, 1, g] (14 × 14), is
    summed once and H = Σ_i D_i M_i D_i, D_i = diag(c_i 1₁₂, -1, -1), at every step; per step
    only the sums t_i = Σ_p f(P_i(X + N U)) j_p are formed (the residual's right-hand side is
    t_i - M_i[:, 12:14] (b_i, c_i)), one compiled program per camera over the chunk's pixels
    (`vdo.dic.subset_sums.residual_sums`), on the B-spline coefficients of one window per image
    (`SplineImage.around` all the subsets). The step is `correlate`'s scaled eigen
    pseudo-inverse (`vdo.dic.correlate._pinv_solve`), batched; a subset stops when max |ΔU| <
    `solver.tol`, as `correlate` stops.
    Subsets that `correlate` would treat otherwise (SubsetResult.one_by_one) are solved by it.
    `workers` threads share the chunks of SUBSET_CHUNK subsets (NumPy, SciPy and XLA release
    the GIL in the heavy calls)."""
    cameras = list(cameras)
    nc = len(cameras)
    if nc == 0 or len(references) != nc or len(deformed) != nc:
        raise ValueError("correlate_subsets: expected one reference and one deformed image per camera")
    points, t_u, t_v = (np.asarray(a, dtype=float).reshape(-1, 3) for a in (points, tangent_u, tangent_v))
    n_pts = len(points)
    if len(t_u) != n_pts or len(t_v) != n_pts:
        raise ValueError("correlate_subsets: expected one tangent_u and one tangent_v per point")
    if not (np.all(np.abs(np.linalg.norm(t_u, axis=1) - 1) <= LIMIT_SLACK)
            and np.all(np.abs(np.linalg.norm(t_v, axis=1) - 1) <= LIMIT_SLACK)
            and np.all(np.abs(np.einsum("ka,ka->k", t_u, t_v)) <= LIMIT_SLACK)):
        raise ValueError("correlate_subsets: every (tangent_u, tangent_v) must be orthonormal")
    if not size > 0:
        raise ValueError(f"correlate_subsets: expected a positive subset size, got {size!r}")
    U0 = np.zeros((n_pts, 3)) if U0 is None else np.asarray(U0, dtype=float)
    U0 = np.broadcast_to(U0.reshape(n_pts, -1, 3), (n_pts, 4, 3)).copy()
    half = size / 2
    origin = points - half * t_u - half * t_v
    corners = _corners(origin, t_u, t_v, size)

    def splines(i):
        """Camera i's reference and deformed splines, each on one window around the subsets."""
        cam = cameras[i]
        ref, dfm = np.asarray(references[i]), np.asarray(deformed[i])   # the windows become float64
        on_image = lambda X: np.clip(cam.project(X), 0, [cam.width - 1, cam.height - 1])  # noqa: E731
        spline = SplineImage.around(dfm, on_image(corners + U0), 1.0 + DEFORMED_MARGIN_PX, order)
        return (_Reference.of(ref, SplineImage.around(ref, on_image(corners), 1.0, order)),
                _Deformed.of(spline, cam))

    from concurrent.futures import ThreadPoolExecutor

    threads = min(int(workers), nc)
    if threads > 1:                   # SciPy's filters release the GIL
        with ThreadPoolExecutor(threads) as pool:
            refs, defs = zip(*pool.map(splines, range(nc)))
    else:
        refs, defs = zip(*map(splines, range(nc)))
    shape = (n_pts,)
    out = SubsetResult(U=U0.copy(), b=np.zeros((n_pts, nc)), c=np.zeros((n_pts, nc)),
                       iterations=np.zeros(shape, int), converged=np.zeros(shape, bool),
                       one_by_one=np.zeros(shape, bool))
    chunks = [np.arange(k, min(k + SUBSET_CHUNK, n_pts)) for k in range(0, n_pts, SUBSET_CHUNK)]
    geometry = (origin, t_u, t_v, size)
    boxes = [_subset_boxes(cam, cameras, geometry, np.arange(n_pts), margin_px) for cam in cameras]
    # a camera's boxes padded to one size (the largest of the subsets it solves, rounded up to
    # BOX_PAD): one compiled program per camera and call, whatever the chunk
    solved = ~np.any([odd for _, _, odd in boxes], axis=0)
    sizes = [tuple(-(-int((hi - lo)[solved, a].max(initial=0) + 1) // BOX_PAD) * BOX_PAD for a in (0, 1))
             for lo, hi, _ in boxes]

    def run(k):
        per_camera = [(lo[k], hi[k], odd[k], n) for (lo, hi, odd), n in zip(boxes, sizes)]
        _solve_subsets(cameras, refs, defs, geometry, k, per_camera, U0[k], solver, out)
        return len(k)

    from vdo.core.parallel import run_chunks

    run_chunks(run, chunks, workers, log, n_pts, "subsets", "subset")
    for k in np.flatnonzero(out.one_by_one):
        patch = Patch(origin=origin[k], t_u=t_u[k], t_v=t_v[k], size=(size, size))
        res = correlate(cameras, deformed, patch, ImageReference(references), model=Q4(1, 1),
                        U0=U0[k], solver=solver, order=order)
        out.U[k], out.b[k], out.c[k] = res.U, res.b, res.c
        out.iterations[k], out.converged[k] = res.iterations, res.converged
    return out


@dataclass(frozen=True)
class _Reference:
    """A reference image as `vdo.dic.subset_sums.subset_setup` reads it: the image and its
    spline's gradients at the pixel centres on the spline's window
    (`vdo.dic.subset_sums.reference_arrays`), the window's corner pixel (u, v) and where the
    spline is the whole image's (`SplineImage.valid`)."""

    image: jax.Array
    gradient_u: jax.Array
    gradient_v: jax.Array
    window: np.ndarray
    valid: np.ndarray

    @classmethod
    def of(cls, image: np.ndarray, spline: SplineImage) -> "_Reference":
        return cls(*reference_arrays(image, spline), window=spline.origin.copy(),
                   valid=np.array(spline.valid))


@dataclass(frozen=True)
class _Deformed:
    """A deformed image's spline as `vdo.dic.subset_sums.residual_sums` reads it: the window's
    coefficients (`vdo.dic.subset_sums.window_arrays`: one compiled program for windows of about
    one size), the window's corner `origin` (u, v), the camera's k = (f_x, s, c_x, f_y, c_y), and
    `valid` = (u0, u1, v0, v1), where a sample is the whole image's spline and its taps lie in the
    window (`vdo.dic.subset_sums.sample_box`)."""

    coeffs: jax.Array
    origin: np.ndarray
    k: np.ndarray
    valid: np.ndarray
    order: object

    @classmethod
    def of(cls, spline: SplineImage, cam) -> "_Deformed":
        K = cam.K
        return cls(coeffs=window_arrays(spline, (spline.coeffs,))[0], origin=spline.origin.copy(),
                   k=np.array([K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]]),
                   valid=sample_box(spline), order=spline.order)


def _subset_boxes(cam, cameras, geometry, k, margin_px):
    """The box of pixels that `pixel_points` scans for each of the subsets k in camera `cam`
    (the bounding box of its corners' projections, +1 px, clipped to the image): lo, hi (K, 2)
    (u, v); and (K,) the subsets left to `correlate` whatever their pixels (a corner behind the
    camera, where `pixel_points` scans the whole image; one that meets an image's margin; a camera
    with lens distortion). `vdo.dic.subset_sums.subset_setup` finds the pixels in the box."""
    origin, t_u, t_v, size = *(a[k] for a in geometry[:3]), geometry[3]
    normal = np.cross(t_u, t_v)
    corners = _corners(origin, t_u, t_v, size)
    cam_xyz = corners @ cam.R.T + cam.t
    behind = ~np.all(cam_xyz[..., 2] > 0, axis=1)
    px = cam_xyz @ cam.K.T
    px = px[..., :2] / np.where(behind[:, None, None], 1.0, px[..., 2:])
    lo = np.maximum(np.floor(px.min(axis=1)) - 1, 0)
    hi = np.minimum(np.ceil(px.max(axis=1)) + 1, [cam.width - 1, cam.height - 1])
    lo = np.where(behind[:, None], 0, lo)
    hi = np.where(behind[:, None], lo, hi)
    # `vdo.dic.patch._visible` in every camera. Each of its conditions holds on a convex part
    # of the plane (in front; |cos| >= min_cos is |(X - C)·n| = const >= min_cos |X - C|, a disc;
    # inside the image margin, for a pinhole): where all four corners pass with LIMIT_SLACK to spare, every pixel
    # does. The other subsets go to `correlate` (a pixel centre exactly on the integer margin is
    # in or out by the rounding of `pixel_points`' own arithmetic).
    edge = np.zeros(len(k), bool)
    for other in cameras:
        edge |= ~_visible_margin(other, corners, normal, margin_px, LIMIT_SLACK).all(axis=1)
        edge |= other.distortion_array is not None
    return lo, hi, behind | edge


def _corners(origin, t_u, t_v, size):
    """The corners (K, 4, 3) of the squares origin + [0, size]² in (t_u, t_v), in Q4 node order."""
    return origin[:, None, :] + np.array([0.0, size, 0.0, size])[None, :, None] * t_u[:, None, :] \
        + np.array([0.0, 0.0, size, size])[None, :, None] * t_v[:, None, :]


def _visible_margin(cam, X, normal, margin_px, slack, min_cos: float = 0.05):
    """`vdo.dic.patch._visible` for points X (K, M, 3) on planes of normals (K, 3), each
    condition met with `slack` (pixels, cos) to spare."""
    ray = X - np.asarray(cam.position, dtype=float)
    cos = np.abs(np.einsum("kma,ka->km", ray, normal)) / np.sqrt(np.sum(ray * ray, axis=-1))
    pc = X @ cam.R.T + cam.t
    x, y = image_point(cam.K, pc[..., 0] / pc[..., 2], pc[..., 1] / pc[..., 2], cam.distortion_array)
    m = margin_px + slack
    return ((pc[..., 2] > 0) & (cos >= min_cos + slack) & (x >= m) & (x <= cam.width - 1 - m)
            & (y >= m) & (y <= cam.height - 1 - m))


def _solve_subsets(cameras, refs, defs, geometry, k, boxes, U0, solver, out):
    """`correlate_subsets` on the subsets k, given per camera their pixel boxes lo, hi, the ones
    left to `correlate` (`_subset_boxes` of the subsets k) and the padded box size (n_u, n_v) (as
    large as any box but those left to `correlate`): writes out.U[k], b, c, iterations, converged,
    one_by_one. The per-pixel work is `vdo.dic.subset_sums`' compiled programs, on the chunk padded
    to SUBSET_CHUNK subsets and (n_u, n_v) pixels a box (weight 0)."""
    nu, ndof = 12, 12 + 2 * len(cameras)
    size = geometry[3]
    cams = []
    one_by_one = np.zeros(len(k), bool)
    origin, t_u, t_v = (padded(a[k], (SUBSET_CHUNK,)) for a in geometry[:3])
    corners = _corners(origin, t_u, t_v, size)                  # world frame, padded
    for cam, ref, dfm, (lo, hi, odd, (n_u, n_v)) in zip(cameras, refs, defs, boxes):
        camera = (np.linalg.inv(cam.K).T @ cam.R, np.asarray(cam.position, dtype=float), cam.R, cam.t, dfm.k,
                  np.array([cam.width, cam.height], dtype=float))
        Xc, N, w, g, G, M, count, covered = subset_setup(
            padded(lo, (SUBSET_CHUNK,)), padded(hi, (SUBSET_CHUNK,)), origin, t_u, t_v, size, camera, ref.image,
            ref.gradient_u, ref.gradient_v, ref.window, ref.valid, n_u=n_u, n_v=n_v)
        one_by_one |= odd | (np.asarray(count)[:len(k)] < 4) | ~np.asarray(covered)[:len(k)]
        cams.append(dict(cam=cam, dfm=dfm, Xc=Xc, N=N, w=w, g=g, G=G, M=np.asarray(M)[:len(k)],
                         corners=jnp.asarray(corners @ cam.R.T + cam.t)))

    p = np.zeros((len(k), ndof))
    p[:, :nu] = U0.reshape(len(k), nu)
    act = np.flatnonzero(~one_by_one)

    def sums(idx):
        """Per camera the sums t = Σ w f j (len(idx), 14) of the subsets idx at their current U
        (`vdo.dic.subset_sums.residual_sums`); and (len(idx),) whether every pixel lies where
        the deformed spline is the whole image's: where the four displaced corners do (the
        pixels' N are convex weights, so their positions lie in the corners' hull, and so do
        their pinhole images). The program runs on the whole padded chunk, the other subsets at
        weight 0: one compiled shape."""
        on = np.zeros(SUBSET_CHUNK)
        on[idx] = 1.0
        U = padded(p[:, :nu].reshape(-1, 4, 3), (SUBSET_CHUNK,))
        ts, inside = [], np.ones(len(idx), bool)
        for c in cams:
            d = c["dfm"]
            t, ok = residual_sums(d.coeffs, d.origin, d.k, c["cam"].R, c["Xc"], c["N"], U, c["w"], on,
                                  c["g"], c["G"], c["corners"], d.valid, order=d.order)
            ts.append(np.asarray(t)[idx])
            inside &= np.asarray(ok)[idx]
        return ts, inside

    # Initial b, c: least squares of f on [1, g] at U0 (`correlate`'s lstsq, normal equations):
    # t[12:14] = (Σ w f, Σ w g f). The first step samples f at the same U: these sums serve it too.
    ts, inside = sums(act)
    for i, c in enumerate(cams):
        p[act, nu + 2 * i: nu + 2 * i + 2] = np.linalg.solve(c["M"][act][:, 12:, 12:],
                                                             ts[i][:, 12:, None])[..., 0]
    one_by_one[act[~inside]] = True
    act, ts = act[inside], [t[inside] for t in ts]

    iterations = np.full(len(k), solver.max_iter)
    converged = np.zeros(len(k), bool)
    inside = np.ones(len(act), bool)
    for it in range(1, solver.max_iter + 1):
        if not len(act):
            break
        if it > 1:
            ts, inside = sums(act)
        H = np.zeros((len(act), ndof, ndof))
        rhs = np.zeros((len(act), ndof))
        for i, c in enumerate(cams):
            ib = nu + 2 * i
            b, cc = p[act, ib], p[act, ib + 1]
            M = c["M"][act]
            s = ts[i] - M[:, :, 12] * b[:, None] - M[:, :, 13] * cc[:, None]     # Σ w (f - b - c g) j
            D = np.concatenate([np.repeat(cc[:, None], nu, 1), -np.ones((len(act), 2))], 1)
            sel = np.r_[0:nu, ib, ib + 1]
            H[:, sel[:, None], sel[None, :]] += D[:, :, None] * M * D[:, None, :]
            rhs[:, sel] -= D * s
        dp = _pinv_solve_many(H, rhs, solver.rcond, nu)
        p[act] += dp
        done = np.max(np.abs(dp[:, :nu]), axis=1) < solver.tol
        converged[act[done]] = True
        iterations[act[done]] = it
        one_by_one[act[~inside]] = True      # a sample outside the window: `correlate` redoes it
        act = act[~done & inside]

    out.U[k] = p[:, :nu].reshape(-1, 4, 3)
    out.b[k], out.c[k] = p[:, nu::2], p[:, nu + 1::2]
    out.iterations[k], out.converged[k], out.one_by_one[k] = iterations, converged, one_by_one


def _pinv_solve_many(H, rhs, rcond, nu):
    """`vdo.dic.correlate._pinv_solve`(H_k) @ rhs_k for a stack H (K, n, n), rhs (K, n): the same
    scaling (one scale for the U dofs, Jacobi for the rest) and the same dropped eigen-directions."""
    diag = np.clip(np.diagonal(H, axis1=1, axis2=2), 0, None)
    d = np.sqrt(diag)
    d[:, :nu] = np.sqrt(diag[:, :nu].mean(axis=1))[:, None]
    d = np.where(d > 0, d, 1.0)
    Hs = H / d[:, :, None] / d[:, None, :]
    lam, V = np.linalg.eigh(0.5 * (Hs + np.swapaxes(Hs, 1, 2)))
    keep = lam > rcond * lam.max(axis=1, keepdims=True)
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    y = np.einsum("kji,kj->ki", V, rhs / d) * inv
    return np.einsum("kij,kj->ki", V, y) / d
