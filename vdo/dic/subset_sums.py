"""The per-pixel sums of `vdo.dic.subsets.correlate_subsets`, compiled: each subset's normal
matrix once (`normal_sums`) and, at every Gauss–Newton step, the B-spline samples of the deformed
image with the sums the step needs (`residual_sums`), one XLA program (JAX, float64) each.

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

Shapes. XLA compiles one program per shape: the caller pads the pixels of a chunk's boxes to a
multiple of PIXEL_PAD (weight 0) and the coefficient window to a multiple of WINDOW_PAD (never
read: a sample is only taken where the caller's `valid` box says its taps lie in the window).
"""

from __future__ import annotations

from functools import partial
from math import comb, factorial

import jax
import jax.numpy as jnp
import numpy as np

from vdo.model.camera import image_point
from vdo.model.spline_response import KEYS, KEYS_A

__all__ = ["PIXEL_PAD", "WINDOW_PAD", "padded", "normal_sums", "residual_sums"]

PIXEL_PAD = 64          # a chunk's pixels per box are padded to a multiple of this
WINDOW_PAD = 512        # a coefficient window's sides are padded to multiples of this (the
                        # cameras' windows of a call then share a size, hence one program)


def padded(a: np.ndarray, shape) -> np.ndarray:
    """`a` zero-padded at the end of its leading axes to `shape`."""
    out = np.zeros(tuple(shape) + a.shape[len(shape):], dtype=a.dtype)
    out[tuple(slice(0, n) for n in a.shape[:len(shape)])] = a
    return out


def _weights(t, order):
    """The kernel's weights of the taps floor(x) - (n - 1)/2 .. floor(x) + (n + 1)/2 (n = 3 for
    Keys), for t = x - floor(x): a list of arrays shaped like t. Cubic B-spline in closed form,
    (1 - t)³/6, (3t³ - 6t² + 4)/6, (-3t³ + 3t² + 3t + 1)/6, t³/6; other odd orders by
    β_n(x) = Σ_j (-1)^j C(n+1, j) (x + (n+1)/2 - j)_+^n / n! (`vdo.dic.images`); Keys' kernel
    (`vdo.model.spline_response.keys_kernel`, a = KEYS_A)."""
    if order == 3:
        s, t2 = 1.0 - t, t * t
        t3 = t2 * t
        return [s * s * s / 6, (3 * t3 - 6 * t2 + 4) / 6, (-3 * t3 + 3 * t2 + 3 * t + 1) / 6, t3 / 6]
    n = 3 if order == KEYS else order
    out = []
    for j in range(-(n - 1) // 2, (n + 1) // 2 + 1):
        x = t - j
        if order == KEYS:
            a, ax = KEYS_A, jnp.abs(x)
            out.append(jnp.where(ax <= 1.0, ((a + 2) * ax - (a + 3)) * ax * ax + 1.0,
                                 jnp.where(ax < 2.0, ((a * ax - 5 * a) * ax + 8 * a) * ax - 4 * a, 0.0)))
        else:
            total = 0.0
            for i in range(n + 2):
                total = total + (-1) ** i * comb(n + 1, i) * jnp.maximum(x + (n + 1) / 2 - i, 0.0) ** n
            out.append(total / factorial(n))
    return out


def _sample(coeffs, rows, cols, order):
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
    """One step's sums of one camera for the K subsets where `active` (K,) is 1 (0 elsewhere): t = Σ_p w_p f_p j_p (K, 14) (module
    docstring), f_p the deformed image's spline (coefficients `coeffs` (H, W), window corner
    `origin` = (u, v) in the image) at the pinhole image of R (X_p + N_p U) + t, given
    Xc = R X_p + t (K, P, 3) and the Q4 node displacements U (K, 4, 3) (m); and (K,) whether the
    four displaced corners (camera frame before the displacement, `corners` (K, 4, 3)) project
    inside `valid` = (u0, u1, v0, v1), where every pixel's taps lie in the window and the window's
    spline is the whole image's. k = (f_x, s, c_x, f_y, c_y) (pixels)."""
    URt = U @ R.T
    pc = Xc + N @ URt
    u, v = image_point(tuple(k), pc[..., 0] / pc[..., 2], pc[..., 1] / pc[..., 2])
    w = w * active[:, None]
    on = w > 0                       # padding pixels sit at the camera centre: 0 / 0
    rows, cols = jnp.where(on, v - origin[1], 0.0), jnp.where(on, u - origin[0], 0.0)
    wf = jnp.where(on, w * _sample(coeffs, rows, cols, order), 0.0)
    K = w.shape[0]
    tU = jnp.einsum("kpa,kpj->kaj", N, wf[..., None] * G).reshape(K, 12)
    t = jnp.concatenate([tU, wf.sum(1)[:, None], (wf * g).sum(1)[:, None]], axis=1)
    q = corners + URt
    qu, qv = image_point(tuple(k), q[..., 0] / q[..., 2], q[..., 1] / q[..., 2])
    inside = jnp.all((qu >= valid[0]) & (qu <= valid[1]) & (qv >= valid[2]) & (qv <= valid[3]), axis=1)
    return t, inside
