"""The per-pixel work of `vdo.dic.subsets.correlate_subsets`, compiled: once per subset its
pixels, what the steps read of them and its normal matrix (`subset_setup`, with `normal_sums`)
and, at every Gauss–Newton step, the B-spline samples of the deformed image with the sums the
step needs (`residual_sums`), one XLA program (JAX, float64) each.

Why compiled. A step samples ~840 pixels per subset and camera. SciPy's `map_coordinates` takes
~60 ns a sample on this access pattern and the NumPy arithmetic around it as much again, in
temporaries as large as the chunk; the same B-spline sum as one XLA program takes 8-12 ns
(`benchmarks/sampler.py`), and the projection and the sums fuse with it.

The sums, per subset k and camera (p its pixels, w_p ∈ {0, 1} the pixel's weight, g_p the
reference grey level, G_p = ∇g s (1 × 3, grey level per metre), N_p the Q4(1, 1) shape
functions, f_p the deformed image at the pixel's displaced position):

    M = Σ_p w_p j_p j_pᵀ,   j_p = [N_p ⊗ G_p, 1, g_p]        (14 × 14, once)
    t = Σ_p w_p f_p j_p                                       (14, every step)

so that the step's right-hand side Σ_p w_p (f_p - b - c g_p) j_p is t - M[:, 12:14] (b, c).

Shapes. XLA compiles one program per shape: the caller pads a chunk's pixel boxes to multiples of
BOX_PAD a side (weight 0) and the image windows to multiples of WINDOW_PAD (never read: a sample
is only taken where the caller's `valid` box says its taps lie in the window).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from vdo.dic.images import bspline
from vdo.model.camera import image_point
from vdo.model.spline_response import KEYS, keys_kernel

__all__ = ["WINDOW_PAD", "BOX_PAD", "padded", "window_arrays", "reference_arrays", "sample_box",
           "normal_sums", "residual_sums", "spline_sample", "subset_setup"]

BOX_PAD = 2             # a camera's pixel boxes are padded to multiples of this per side (calls
                        # with boxes of about one size then share a program)
WINDOW_PAD = 512        # a coefficient window's sides are padded to multiples of this (the
                        # cameras' windows of a call then share a size, hence one program)


def padded(a: np.ndarray, shape) -> np.ndarray:
    """`a` zero-padded at the end of its leading axes to `shape`."""
    out = np.zeros(tuple(shape) + a.shape[len(shape):], dtype=a.dtype)
    out[tuple(slice(0, n) for n in a.shape[:len(shape)])] = a
    return out


def window_arrays(spline, arrays) -> list:
    """`arrays` of a `vdo.dic.images.SplineImage`'s window shape, zero-padded to multiples of
    WINDOW_PAD a side (windows of about one size share a compiled program), as JAX arrays."""
    h, w = spline.shape
    size = (-(-h // WINDOW_PAD) * WINDOW_PAD, -(-w // WINDOW_PAD) * WINDOW_PAD)
    return [jnp.asarray(padded(a, size)) for a in arrays]


def reference_arrays(image, spline) -> list:
    """The reference image and its spline's gradients at the pixel centres
    (`SplineImage.pixel_gradients`) on the spline's window (`window_arrays`)."""
    (c0, r0), (h, w) = spline.origin.astype(int), spline.shape
    pixels = np.asarray(np.asarray(image)[r0:r0 + h, c0:c0 + w], dtype=np.float64)
    return window_arrays(spline, (pixels, *spline.pixel_gradients()))


def sample_box(spline) -> np.ndarray:
    """(u0, u1, v0, v1): where a sample of the spline's window is the whole image's spline and its
    kernel's taps lie in the window (`spline_sample`'s `valid` box): the spline's own valid part
    less the kernel's half-width + 1 px from the window's edges."""
    H, W = spline.shape
    half = (3 if spline.order == KEYS else spline.order) // 2 + 2
    (u0, v0), (u1, v1) = spline.origin + half, spline.origin + [W - 1 - half, H - 1 - half]
    s0, s1, t0, t1 = spline.valid
    return np.array([max(u0, s0), min(u1, s1), max(v0, t0), min(v1, t1)])


def _rotate(X, R):
    """X Rᵀ for points X (..., 3) and a 3 × 3 R, as three fused sums (XLA makes a (..., 3) × (3, 3)
    product a library call that costs more than the arithmetic)."""
    return jnp.stack([X[..., 0] * R[i, 0] + X[..., 1] * R[i, 1] + X[..., 2] * R[i, 2] for i in range(3)], -1)


def _weights(t, order):
    """The kernel's weights of the taps floor(x) - (n - 1)/2 .. floor(x) + (n + 1)/2 (n = 3 for
    Keys), for t = x - floor(x): a list of arrays shaped like t. Cubic B-spline in closed form,
    (1 - t)³/6, (3t³ - 6t² + 4)/6, (-3t³ + 3t² + 3t + 1)/6, t³/6; other odd orders by
    `vdo.dic.images.bspline`; Keys' kernel by `vdo.model.spline_response.keys_kernel`."""
    if order == 3:
        s, t2 = 1.0 - t, t * t
        t3 = t2 * t
        return [s * s * s / 6, (3 * t3 - 6 * t2 + 4) / 6, (-3 * t3 + 3 * t2 + 3 * t + 1) / 6, t3 / 6]
    n = 3 if order == KEYS else order
    taps = range(-(n - 1) // 2, (n + 1) // 2 + 1)
    if order == KEYS:
        return [keys_kernel(t - j, xp=jnp) for j in taps]
    return [bspline(t - j, order, xp=jnp) for j in taps]


def spline_sample(coeffs, rows, cols, order):
    """Σ_a Σ_b β(v - r_a) β(u - c_b) C[r_a, c_b] over the kernel's taps (`_weights`) at window
    coordinates (rows, cols): what `scipy.ndimage.map_coordinates(coeffs, [rows, cols],
    prefilter=False)` sums where every tap lies in the window (the caller's `valid` box). The
    positions are clamped so that the others read some coefficient; their weight is 0."""
    H, W = coeffs.shape
    n = 3 if order == KEYS else order
    lo = (n - 1) // 2
    rows = jnp.clip(rows, lo, H - 1 - (n + 1) // 2)
    cols = jnp.clip(cols, lo, W - 1 - (n + 1) // 2)
    fr, fc = jnp.floor(rows), jnp.floor(cols)
    wr, wc = _weights(rows - fr, order), _weights(cols - fc, order)
    base = (fr.astype(jnp.int32) - lo) * W + fc.astype(jnp.int32) - lo
    flat = coeffs.reshape(-1)
    out = 0.0
    for a in range(n + 1):
        row = 0.0
        for b in range(n + 1):
            row = row + wc[b] * flat[base + (a * W + b)]
        out = out + wr[a] * row
    return out


@jax.jit
def normal_sums(N, w, G, g):
    """M = Σ_p w_p j_p j_pᵀ (K, 14, 14) of the module docstring, for N (K, P, 4), w (K, P),
    G (K, P, 3), g (K, P)."""
    K, P = w.shape
    ju = ((N * w[..., None])[..., :, None] * G[..., None, :]).reshape(K, P, 12)
    j = jnp.concatenate([ju, w[..., None], (w * g)[..., None]], axis=-1)
    return jnp.einsum("kpi,kpj->kij", j, j)


@partial(jax.jit, static_argnames="order")
def residual_sums(coeffs, origin, k, R, Xc, N, U, w, active, g, G, corners, valid, *, order):
    """One step's sums of one camera for the K subsets where `active` (K,) is 1 (0 elsewhere):
    t = Σ_p w_p f_p j_p (K, 14) (module docstring), f_p the deformed image's spline (coefficients
    `coeffs` (H, W), window corner `origin` = (u, v) in the image) at the pinhole image of
    R (X_p + N_p U) + t, given Xc = R X_p + t (K, P, 3) and the Q4 node displacements U (K, 4, 3)
    (m); and (K,) whether the four displaced corners (camera frame before the displacement,
    `corners` (K, 4, 3)) project inside `valid` = (u0, u1, v0, v1), where every pixel's taps lie
    in the window and the window's spline is the whole image's. k = (f_x, s, c_x, f_y, c_y)
    (pixels)."""
    URt = U @ R.T                                                   # (K, 4, 3): small
    pc = Xc + sum(N[..., a:a + 1] * URt[:, None, a, :] for a in range(4))
    u, v = image_point(tuple(k), pc[..., 0] / pc[..., 2], pc[..., 1] / pc[..., 2])
    w = w * active[:, None]
    on = w > 0                       # padding pixels sit at the camera centre: 0 / 0
    rows, cols = jnp.where(on, v - origin[1], 0.0), jnp.where(on, u - origin[0], 0.0)
    wf = jnp.where(on, w * spline_sample(coeffs, rows, cols, order), 0.0)
    K = w.shape[0]
    tU = jnp.einsum("kpa,kpj->kaj", N, wf[..., None] * G).reshape(K, 12)
    t = jnp.concatenate([tU, wf.sum(1)[:, None], (wf * g).sum(1)[:, None]], axis=1)
    q = corners + URt
    qu, qv = image_point(tuple(k), q[..., 0] / q[..., 2], q[..., 1] / q[..., 2])
    inside = jnp.all((qu >= valid[0]) & (qu <= valid[1]) & (qv >= valid[2]) & (qv <= valid[3]), axis=1)
    return t, inside


@partial(jax.jit, static_argnames=("n_u", "n_v"))
def subset_setup(lo, hi, origin, t_u, t_v, size, camera, image, gradient_u, gradient_v, window, valid, *,
                 n_u, n_v):
    """Each subset's pixels, as `vdo.dic.patch.pixel_points` finds them, and everything the steps
    read of them, for K subsets of one camera: the pixel centres (u, v) of the box lo .. hi (K, 2)
    (clipped to the image) in an n_u × n_v grid; of these, the pixels whose ray meets the
    subset's square origin + [0, size]² in (t_u, t_v) (K, 3 each) in front of the camera, w = 1
    (0 for the others), where the ray C + λ d (d = Rᵀ K⁻¹ q, q = (u, v, 1)) meets the plane:
    λ = (o - C)·n / d·n and ξ_a = (C - o)·t_a + λ d·t_a.

    camera = (Kinv_R (3, 3) with q Kinv_R = dᵀ, C (3,), R (3, 3), t (3,), k (5,) =
    (f_x, s, c_x, f_y, c_y), (width, height)); `image`, `gradient_u`, `gradient_v`: the reference
    image and its spline's gradient at the pixel centres on the reference window whose corner
    pixel is `window` (u, v); `valid` (u0, u1, v0, v1): where that spline is the whole image's.

    Returns Xc = R X + t (K, P, 3), N (K, P, 4) the Q4(1, 1) shape functions at ξ / size, w (K, P),
    g (K, P) the reference grey level, G = ∇g s (K, P, 3) (s = ∂x/∂X of a pinhole: ∂u/∂p =
    [f_x, s, -(f_x x + s y)/z] / z, ∂v/∂p = [0, f_y, -f_y y / z] / z, times R), M (K, 14, 14)
    (`normal_sums`), the pixel count (K,) and (K,) whether every pixel lies in `valid`."""
    Kinv_R, C, R, t, k, (width, height) = camera
    du, dv = (a.ravel() for a in jnp.meshgrid(jnp.arange(n_u), jnp.arange(n_v), indexing="xy"))
    U, V = lo[:, :1] + du, lo[:, 1:] + dv
    ok = (U <= hi[:, :1]) & (V <= hi[:, 1:])
    u, v = jnp.minimum(U, width - 1), jnp.minimum(V, height - 1)
    normal = jnp.cross(t_u, t_v)
    rows = jnp.stack([t_u, t_v, normal], 1) @ Kinv_R.T                # d·t_u, d·t_v, d·n per q
    lin = lambda r: r[:, 0:1] * u + r[:, 1:2] * v + r[:, 2:3]         # noqa: E731
    dn = lin(rows[:, 2])
    dn_safe = jnp.where(dn == 0, 1.0, dn)
    lam = jnp.einsum("ka,ka->k", origin - C, normal)[:, None] / dn_safe
    ok &= (dn != 0) & jnp.isfinite(lam) & (lam > 0)
    lam = jnp.where(ok, lam, 0.0)
    co = C - origin
    xi0 = jnp.where(ok, jnp.einsum("ka,ka->k", co, t_u)[:, None] + lam * lin(rows[:, 0]), 0.0)
    xi1 = jnp.where(ok, jnp.einsum("ka,ka->k", co, t_v)[:, None] + lam * lin(rows[:, 1]), 0.0)
    ok &= (xi0 >= 0) & (xi0 <= size) & (xi1 >= 0) & (xi1 <= size)
    X = origin[:, None, :] + xi0[..., None] * t_u[:, None, :] + xi1[..., None] * t_v[:, None, :]
    w = ok.astype(jnp.float64)
    covered = jnp.all((u >= valid[0]) & (u <= valid[1]) & (v >= valid[2]) & (v <= valid[3]) | ~ok, axis=1)
    h, wd = image.shape
    cu = jnp.clip(u - window[0], 0, wd - 1).astype(jnp.int32)
    cv = jnp.clip(v - window[1], 0, h - 1).astype(jnp.int32)
    g, gu, gv = image[cv, cu], gradient_u[cv, cu], gradient_v[cv, cu]
    a, b = xi0 / size, xi1 / size
    N = jnp.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b], -1)
    pc = _rotate(X, R) + t
    fx, sk, fy = k[0], k[1], k[3]
    zi = 1.0 / pc[..., 2]
    ga = gu * fx * zi
    gb = (gu * sk + gv * fy) * zi
    gc = -(ga * pc[..., 0] + gb * pc[..., 1]) * zi
    G = jnp.where(ok[..., None], _rotate(jnp.stack([ga, gb, gc], -1), R.T), 0.0)     # (∇g s_p) R
    return pc, N, w, g, G, normal_sums(N, w, G, g), w.sum(1), covered
