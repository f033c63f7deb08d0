"""From the footprint to the gradient tensor: what a camera's pixels see of the speckle's gradient.

With A the footprint (pixel/m, `vdo.information.projection`) and A A^T = sum_k a_k^2 v_k v_k^T
(a_k pixels per metre of surface along e_k, v_k in the image), the pixel blur (Gaussian, std
kappa pixels) is std l_k = kappa / a_k (m) on the surface along e_k, and

    T / c^2 = sum_k G(l_k, l_other) / a_k^2 v_k v_k^T                          (1/pixel^2)

with G(l_par, l_perp) = <(d_e (G_blur * f_hat))^2> (1/m^2) the directional gradient energy of
the normalised speckle under an anisotropic Gaussian blur (std l_par along e, l_perp across):
a `TableEnergy` (`vdo.model.speckle.GradientEnergyTable`, bilinear in log-log), the closed form
`GaussianFieldEnergy`, or any jax-traceable G(l_par, l_perp). `phis_of` reads the table by hand
(one gather for G(l_1, l_2) and G(l_2, l_1), `_packed_table`) and gives its Jacobian for the
reverse pass of `vdo.information.blocks`.

Numerical care (all derivatives stay finite; `vdo.objective`'s docstring has the rest):

* T as a matrix function of M = A A^T, with no SVD/eigh. With m = tr M / 2, h = (M00 - M11)/2,
  the eigenvalues are m +- gap, gap = sqrt(h^2 + M01^2). We use
  gap_eps = sqrt(h^2 + M01^2 + (eps m)^2), lam1 = m + gap_eps, lam2 = det M / lam1 and
  T/c^2 = (phi1 + phi2)/2 I + (phi1 - phi2)/(lam1 - lam2) (M - m I),  phi_k = G(l_k, l_other)/lam_k.
  This is the exact spectral formula with the gap floored: both coefficients are even functions of
  the gap, so the floor changes T by O(eps^2) (eps = 1e-4 -> 1e-8 relative), the difference
  quotient never divides by zero (a fronto-parallel view, a_1 = a_2 exactly, is fine) and the sqrt
  is never evaluated at 0.

Above `vdo.information.inputs` (`KAPPA_BOX`); below `blocks`. `vdo.objective` re-exports
`gradient_tensor`, `TableEnergy` and `GaussianFieldEnergy`."""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from vdo.information.inputs import KAPPA_BOX
from vdo.model.speckle import GradientEnergyTable, g_aniso_lookup


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


def phis_of(energy, lam1, lam2, kappa, jacobian=False):
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


def spectrum(A, gap_eps) -> _Spectrum:
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


def tensor_from(sp: _Spectrum, phi1, phi2):
    """T / c^2 = (phi1 + phi2)/2 I + (phi1 - phi2)/(lam1 - lam2) (M - m I) as (T00, T01, T11)
    (1/pixel^2), with alpha, beta and lam1 - lam2."""
    alpha = 0.5 * (phi1 + phi2)
    D = sp.lam1 - sp.lam2
    beta = (phi1 - phi2) / D
    return (alpha + beta * sp.h, beta * sp.M01, alpha - beta * sp.h), beta, D


def _tensor(A, energy, kappa, gap_eps):
    """T / c^2 = sum_k G(l_k, l_other)/a_k^2 v_k v_k^T as (T00, T01, T11) (1/pixel^2), and |det A|,
    by the floored-gap spectral formula (module docstring). A = (A00, A01, A10, A11)."""
    sp = spectrum(A, gap_eps)
    T, _, _ = tensor_from(sp, *phis_of(energy, sp.lam1, sp.lam2, kappa)[0])
    return T, jnp.abs(sp.det)


@eqx.filter_jit
def gradient_tensor(footprint, energy, kappa: float = KAPPA_BOX, gap_eps: float = 1e-4):
    """T / c^2 = sum_k G(kappa/a_k, kappa/a_other)/a_k^2 v_k v_k^T (..., 2, 2) in 1/pixel^2 for
    footprints A (..., 2, 2) in pixel/m; differentiable also where a_1 = a_2."""
    A = (footprint[..., 0, 0], footprint[..., 0, 1], footprint[..., 1, 0], footprint[..., 1, 1])
    (t00, t01, t11), _ = _tensor(A, energy, kappa, gap_eps)
    return jnp.stack([jnp.stack([t00, t01], -1), jnp.stack([t01, t11], -1)], -2)
