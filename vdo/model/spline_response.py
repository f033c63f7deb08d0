"""The responses of the interpolants a lab's correlation runs (the cubic and quintic B-splines and
Keys' cubic convolution, `INTERPOLANTS`) at frequencies ω: R_d(ω), the interpolated image of a
unit cosine moved by a sub-pixel d, its derivative, and the spline gradient D(ω) (`responses`);
and the sub-pixel positions d with their twins 1 - d (`phase_pairs`). Shared by the error model of
`vdo.model.interpolant` and the realized scatter of `vdo.model.realized_scatter`; the derivations
are in docs/theory.md, section 8a.
"""

from __future__ import annotations

import numpy as np

KEYS = "keys"               # the `order` of Keys' cubic convolution (not a B-spline: no prefilter)
KEYS_A = -0.5               # Keys' parameter a: -0.5, the one whose interpolant is exact to 2nd order
INTERPOLANTS = {"cubic": 3, "quintic": 5, "keys": KEYS}   # interpolants the lab may run: the
                            # B-splines by their order, Keys' kernel by KEYS
INTERPOLANT_NAMES = {"cubic": "cubic B-spline", "quintic": "quintic B-spline",
                     "keys": "Keys cubic (a = -0.5)"}   # how outputs name them
PHASES = 8                  # sub-pixel positions per axis over which the bias is averaged (d = j / 8)
PHASE_TWIN_TOL = 1e-12     # sub-pixel positions d and 1 - d closer than this are twins (mod 1)
_ALIAS_TERMS = 4            # |l| <= this in the Poisson sums of the spline's responses


def _by_twins(at, phases) -> np.ndarray:
    """at(phases) (P, M) for responses with R_{1-d} = conj R_d (`_SplineSpectrum`,
    `_KeysSpectrum`): computed at the phases d <= 1/2 only, their twins 1 - d in (1/2, 1) taken
    as the conjugates (3 of the 8 grid phases). Phases outside [0, 1) are computed as given."""
    d = np.atleast_1d(np.asarray(phases, dtype=np.float64))
    flip = (d > 0.5) & (d < 1.0)
    canon = np.where(flip, 1.0 - d, d)
    unique, index = np.unique(canon, return_inverse=True)
    if len(unique) == len(d):
        return at(d)
    out = at(unique)[index]
    out[flip] = np.conj(out[flip])
    return out


class _SplineSpectrum:
    """The B-spline's spectrum at the aliases of the frequencies ω (M,), computed once and shared
    by its responses: s_l = β̂(ω + 2πl) = sinc^(order+1)(ω/2π + l) for |l| <= _ALIAS_TERMS, with
    sin(π(x + l)) = ±sin(πx) (the power order + 1 is even, so the sign drops out)."""

    def __init__(self, omega: np.ndarray, order: int):
        self.l = np.arange(-_ALIAS_TERMS, _ALIAS_TERMS + 1)
        self.omega = np.asarray(omega, dtype=np.float64)
        x = self.omega[:, None] / (2 * np.pi) + self.l                      # (M, L)
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.sin(np.pi * self.omega / (2 * np.pi))[:, None] / (np.pi * x)
        v = np.where(x == 0.0, 1.0, v)
        v2 = v * v
        self.s = v2 * v2 if order == 3 else v2 * v2 * v2                    # orders 3 and 5
        self.total = self.s.sum(-1)

    def _weighted(self, s: np.ndarray, phases) -> np.ndarray:
        """Σ_l s_l exp(2πi l d) / Σ_l β̂(ω + 2πl) (P, M), as one real product (BLAS) of the
        phases' cosines and sines (2P, L) with sᵀ (L, M), one pass over s (twice as fast as
        two products s @ cos, s @ sin and a transpose); s is real, so the phase 1 - d is the
        conjugate of d (`_by_twins`)."""
        def at(d):
            angle = 2 * np.pi * np.outer(d, self.l)                         # (P, L)
            parts = np.concatenate([np.cos(angle), np.sin(angle)]) @ s.T    # (2P, M)
            parts /= self.total
            out = np.empty((len(d), s.shape[0]), dtype=np.complex128)
            out.real, out.imag = parts[:len(d)], parts[len(d):]
            return out
        return _by_twins(at, phases)

    def shift(self, phases: np.ndarray) -> np.ndarray:
        """R_d(ω) (P, M): the spline's value at n + d of the samples of exp(iωx), divided by
        exp(iω(n + d)): Σ_l β̂(ω + 2πl) exp(2πi l d) / Σ_l β̂(ω + 2πl), for every phase d."""
        return self._weighted(self.s, phases)

    def derivative(self) -> np.ndarray:
        """D(ω) (M,): the spline's derivative at the sample points of exp(iωx), divided by
        i exp(iωn): Σ_l β̂(ω + 2πl)(ω + 2πl) / Σ_l β̂(ω + 2πl) (real; ω itself for ω << π)."""
        return (self.s * (self.omega[:, None] + 2 * np.pi * self.l)).sum(-1) / self.total

    def derivative_shift(self, phases: np.ndarray) -> np.ndarray:
        """R'_d(ω) (P, M): the spline's derivative at n + d of the samples of exp(iωx), divided
        by i exp(iω(n + d)): Σ_l β̂(ω + 2πl)(ω + 2πl) exp(2πi l d) / Σ_l β̂(ω + 2πl)."""
        return self._weighted(self.s * (self.omega[:, None] + 2 * np.pi * self.l), phases)


def keys_kernel(x, a: float | None = None, derivative: bool = False, xp=np) -> np.ndarray:
    """Keys' cubic convolution kernel k(x) (a = KEYS_A unless given; support |x| < 2), or k'(x):

        k(x) = (a + 2)|x|³ - (a + 3)|x|² + 1          |x| <= 1
               a|x|³ - 5a|x|² + 8a|x| - 4a            1 < |x| < 2

    k(0) = 1, k(±1) = k(±2) = 0: the interpolant f(x) = Σ_m f_m k(x - m) passes through its
    samples, with no prefilter; k' is continuous (k'(±1) = ±a from both pieces). xp: numpy or
    jax.numpy."""
    a = KEYS_A if a is None else float(a)
    x = xp.asarray(x, dtype=xp.float64)
    t = xp.abs(x)
    if derivative:
        inner = 3 * (a + 2) * t * t - 2 * (a + 3) * t
        outer = 3 * a * t * t - 10 * a * t + 8 * a
        return xp.sign(x) * xp.where(t <= 1.0, inner, xp.where(t < 2.0, outer, 0.0))
    inner = ((a + 2) * t - (a + 3)) * t * t + 1.0
    outer = ((a * t - 5 * a) * t + 8 * a) * t - 4 * a
    return xp.where(t <= 1.0, inner, xp.where(t < 2.0, outer, 0.0))


class _KeysSpectrum:
    """Keys' kernel's responses at the frequencies ω (M,), the interface of `_SplineSpectrum`.
    The interpolant of the samples exp(iωm) at x = n + d (0 <= d < 1) sums the four taps
    m = n + j, j = -1 .. 2:

        f(n + d)  = Σ_j exp(iω(n + j)) k(d - j)
        R_d(ω)  = f(n + d) / exp(iω(n + d))        = Σ_j k(d - j) exp(iω(j - d))
        R'_d(ω) = f'(n + d) / (i exp(iω(n + d)))   = -i Σ_j k'(d - j) exp(iω(j - d))
        D(ω)    = R'_0(ω) = -2 k'(1) sin ω = sin ω  (a = -0.5: the central difference)

    k is even and k' odd, so R_{1-d} = conj R_d and R'_{1-d} = conj R'_d (`phase_pairs`)."""

    TAPS = np.arange(-1, 3)

    def __init__(self, omega: np.ndarray):
        self.omega = np.asarray(omega, dtype=np.float64)

    def _sum(self, phases, derivative: bool) -> np.ndarray:
        def at(d):
            taps = keys_kernel(d[:, None] - self.TAPS, derivative=derivative)      # (P, 4)
            ramp = np.exp(1j * np.outer(self.TAPS, self.omega))                    # (4, M)
            out = (taps @ ramp) * np.exp(-1j * np.outer(d, self.omega))            # (P, M)
            return -1j * out if derivative else out
        return _by_twins(at, phases)

    def shift(self, phases: np.ndarray) -> np.ndarray:
        """R_d(ω) (P, M) for every phase d."""
        return self._sum(phases, False)

    def derivative(self) -> np.ndarray:
        """D(ω) (M,): the derivative response at the sample points (real)."""
        return self._sum(np.zeros(1), True)[0].real

    def derivative_shift(self, phases: np.ndarray) -> np.ndarray:
        """R'_d(ω) (P, M) for every phase d."""
        return self._sum(phases, True)


def responses(omega: np.ndarray, order):
    """The interpolant's responses at ω: `_KeysSpectrum` for KEYS, else `_SplineSpectrum`."""
    return _KeysSpectrum(omega) if order == KEYS else _SplineSpectrum(omega, order)


def phase_pairs(px: np.ndarray, py: np.ndarray) -> list[tuple]:
    """The sub-pixel positions (p₁, p₂) to compute, each with its twin and the count it stands
    for. The spline is symmetric, so the responses at 1 - d are the conjugates of those at d
    (R₁₋d = conj R_d, the same for R'): at (1 - d₁, 1 - d₂) E is conj E, the bias is -b and the
    noise and scatter terms are equal. Where both grids hold 1 - d for every d (mod 1, within
    `PHASE_TWIN_TOL`), one of each twin pair is computed and counted twice (about half the work);
    otherwise every pair once."""
    def twin_index(grid):
        out = []
        for d in grid:
            j = np.nonzero(np.abs(((1.0 - d) - grid + 0.5) % 1.0 - 0.5) < PHASE_TWIN_TOL)[0]
            if j.size == 0:
                return None
            out.append(int(j[0]))
        return out

    t1, t2 = twin_index(px), twin_index(py)
    if t1 is None or t2 is None:
        return [(p1, p2, None, 1) for p1 in range(px.size) for p2 in range(py.size)]
    pairs, done = [], set()
    for p1 in range(px.size):
        for p2 in range(py.size):
            if (p1, p2) in done:
                continue
            twin = (t1[p1], t2[p2])
            done.update({(p1, p2), twin})
            pairs.append((p1, p2, None, 1) if twin == (p1, p2) else (p1, p2, twin, 2))
    return pairs
