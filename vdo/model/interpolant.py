"""What an interpolating correlation measures on a speckle pattern: the interpolation floor
(`interpolation_error`) and the per-footprint error model of a translation's correlation
(`correlation_error`: the bias over sub-pixel positions, its patch-to-patch scatter and the noise
through the interpolant, against the Cramér-Rao bound), for the cubic and quintic B-splines and
Keys' cubic convolution (`INTERPOLANTS`). The pattern's spectrum comes from
`vdo.model.speckle.blocked_spectrum`; the derivations are in docs/theory.md, section 8a.
"""

from __future__ import annotations

import math
import hashlib
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.sparse

from vdo.model.speckle import blocked_spectrum


INTERPOLATION_ORDER = 3        # the cubic B-spline of `vdo.dic.images.SplineImage`
TEXEL_IMAGES = 2               # texel-grid images k + m / h, |m| <= this, per axis


def interpolation_error(pattern_normalised, texel_m: float, pixel_sides,
                        order: int = INTERPOLATION_ORDER, phase=(0.5, 0.5),
                        optics=None) -> np.ndarray:
    """RMS error (K,) of the image-correlation interpolation on the box-pixel image of the
    normalised pattern f̂ (variance 1 before averaging), for K pixel footprints `pixel_sides`
    (K, 2, 2) m (as `pixel_averaged_std`): the difference between the B-spline interpolant of the
    image of the pattern moved by `phase` pixels, read at the pixel centres moved back, and the
    image of the unmoved pattern read at the pixel centres. A correlation that interpolates the
    deformed image (`vdo.dic.correlate`) sees this error as a fixed, motion-dependent gray-level
    pattern: not noise, a bias.

    The rendered texture is the texel samples (spectrum F(k), periodic in k with period 1/h)
    filtered by bilinear interpolation (sinc²(k_u h) sinc²(k_v h)), so it has energy at every
    k + m/h; the box pixel multiplies by sinc(k.a_1) sinc(k.a_2); sampling at the pixel centres
    aliases whatever lies above the pixel Nyquist frequency, which no interpolation can undo.
    With ω_j = 2π k.a_j and K_d(ω) the interpolant's shift response (`_SplineSpectrum.shift`:
    K_d(ω) = Σ_l β̂(ω + 2πl) exp(2πi l d) / Σ_l β̂(ω + 2πl), β̂(ω) = sinc^(order+1)(ω / 2π), |l| <= _ALIAS_TERMS),

        err² = Σ_k Σ_m |F(k)|² sinc⁴(k'_u h) sinc⁴(k'_v h) sinc²(k'.a_1) sinc²(k'.a_2)
               |K_d1(ω_1) K_d2(ω_2) - 1|²,      k' = k + m / h, |m_u|, |m_v| <= TEXEL_IMAGES

    (checked against map_coordinates on supersampled box-pixel images, tests/model/test_speckle.py).
    The half-pixel phase is the worst: about the largest error over sub-pixel motions. The
    spectrum is summed over blocks of side // 64 frequencies (`blocked_spectrum`; 0.3 % off the
    full sum for the built-in 1024-texel tile): one FFT of the tile per call, then about 0.02 s
    per footprint; pass all footprints at once. `optics`: K `vdo.model.optics.OpticsBlur` (None
    entries or None: no lens blur), whose MTF²(|q|) multiplies each term (q = (k'.a_1, k'.a_2)
    cycles per pixel)."""
    f = np.asarray(pattern_normalised)
    w, ku, kv = blocked_spectrum(f, texel_m, texel_filter=False, block=max(1, min(f.shape) // 64))
    m = np.arange(-TEXEL_IMAGES, TEXEL_IMAGES + 1) / texel_m
    shape = (m.size, m.size, ku.size)                                  # (m_u, m_v, blocks)
    qu = np.broadcast_to(ku[None, None, :] + m[:, None, None], shape).reshape(-1, ku.size)
    qv = np.broadcast_to(kv[None, None, :] + m[None, :, None], shape).reshape(-1, kv.size)
    weight = w * (np.sinc(qu * texel_m) * np.sinc(qv * texel_m)) ** 4
    keep = weight.sum(axis=1) >= 1e-6 * w.sum()           # far texel images: < 1e-6 of the variance
    qu, qv, weight = qu[keep], qv[keep], weight[keep]
    sides = np.asarray(pixel_sides, dtype=np.float64).reshape(-1, 2, 2)
    optics = [None] * len(sides) if optics is None else list(optics)
    out = np.empty(len(sides))
    for i, (a, opt) in enumerate(zip(sides, optics)):
        k1, k2 = qu * a[0, 0] + qv * a[1, 0], qu * a[0, 1] + qv * a[1, 1]
        box = (np.sinc(k1) * np.sinc(k2)) ** 2
        if opt is not None:
            box = box * opt.mtf(np.hypot(k1, k2)) ** 2
        K = (_responses(2 * np.pi * k1.ravel(), order).shift(np.array([phase[0]]))[0]
             * _responses(2 * np.pi * k2.ravel(), order).shift(np.array([phase[1]]))[0]).reshape(k1.shape)
        out[i] = math.sqrt(float(np.sum(weight * box * np.abs(K - 1.0) ** 2)))
    return out


# --------------------------------------------------------------------------------------------
# What an interpolating correlation measures: noise through the interpolant, and its bias
# --------------------------------------------------------------------------------------------
KEYS = "keys"               # the `order` of Keys' cubic convolution (not a B-spline: no prefilter)
KEYS_A = -0.5               # Keys' parameter a: -0.5, the one whose interpolant is exact to 2nd order
INTERPOLANTS = {"cubic": 3, "quintic": 5, "keys": KEYS}   # interpolants the lab may run: the
                            # B-splines by their order, Keys' kernel by KEYS
INTERPOLANT_NAMES = {"cubic": "cubic B-spline", "quintic": "quintic B-spline",
                     "keys": "Keys cubic (a = -0.5)"}   # how outputs name them
PHASES = 8                  # sub-pixel positions per axis over which the bias is averaged (d = j / 8)
PHASE_TWIN_TOL = 1e-12     # sub-pixel positions d and 1 - d closer than this are twins (mod 1)
FOLD_BINS = 32              # bins per axis of the folded pixel spectrum (scatter of the bias)
PHASE_CHUNK = 8             # sub-pixel positions computed together (`correlation_error`: (8, M) arrays)
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
        """Σ_l s_l exp(2πi l d) / Σ_l β̂(ω + 2πl) (P, M), as two real products (BLAS); s is
        real, so the phase 1 - d is the conjugate of d (`_by_twins`)."""
        def at(d):
            angle = 2 * np.pi * np.outer(self.l, d)                         # (L, P)
            return ((s @ np.cos(angle)) + 1j * (s @ np.sin(angle))).T / self.total
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


def keys_kernel(x, a: float | None = None, derivative: bool = False) -> np.ndarray:
    """Keys' cubic convolution kernel k(x) (a = KEYS_A unless given; support |x| < 2), or k'(x):

        k(x) = (a + 2)|x|³ - (a + 3)|x|² + 1          |x| <= 1
               a|x|³ - 5a|x|² + 8a|x| - 4a            1 < |x| < 2

    k(0) = 1, k(±1) = k(±2) = 0: the interpolant f(x) = Σ_m f_m k(x - m) passes through its
    samples, with no prefilter; k' is continuous (k'(±1) = ±a from both pieces)."""
    a = KEYS_A if a is None else float(a)
    x = np.asarray(x, dtype=np.float64)
    t = np.abs(x)
    if derivative:
        inner = 3 * (a + 2) * t * t - 2 * (a + 3) * t
        outer = 3 * a * t * t - 10 * a * t + 8 * a
        return np.sign(x) * np.where(t <= 1.0, inner, np.where(t < 2.0, outer, 0.0))
    inner = ((a + 2) * t - (a + 3)) * t * t + 1.0
    outer = ((a * t - 5 * a) * t + 8 * a) * t - 4 * a
    return np.where(t <= 1.0, inner, np.where(t < 2.0, outer, 0.0))


class _KeysSpectrum:
    """Keys' kernel's responses at the frequencies ω (M,), the interface of `_SplineSpectrum`.
    The interpolant of the samples exp(iωm) at x = n + d (0 <= d < 1) sums the four taps
    m = n + j, j = -1 .. 2:

        f(n + d)  = Σ_j exp(iω(n + j)) k(d - j)
        R_d(ω)  = f(n + d) / exp(iω(n + d))        = Σ_j k(d - j) exp(iω(j - d))
        R'_d(ω) = f'(n + d) / (i exp(iω(n + d)))   = -i Σ_j k'(d - j) exp(iω(j - d))
        D(ω)    = R'_0(ω) = -2 k'(1) sin ω = sin ω  (a = -0.5: the central difference)

    k is even and k' odd, so R_{1-d} = conj R_d and R'_{1-d} = conj R'_d (`_phase_pairs`)."""

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


def _responses(omega: np.ndarray, order):
    """The interpolant's responses at ω: `_KeysSpectrum` for KEYS, else `_SplineSpectrum`."""
    return _KeysSpectrum(omega) if order == KEYS else _SplineSpectrum(omega, order)


@dataclass(frozen=True, eq=False)
class CorrelationError:
    """What a B-spline interpolating correlation of a translation measures on K footprints, per
    unit-variance pattern f̂ (`correlation_error`); image axes (x, y), pixels.

    gradient  (K, 2, 2) H₁ = <∇f ∇fᵀ> per pixel, ∇ the spline's derivative at the pixel centres
    noise     (K, 2, 2) mean over sub-pixel positions of H₁⁻¹ N_d H₁⁻¹: the noise covariance for
              a noise std σ (in units of the pattern's std) and P pixels is σ² noise / P (px²)
    bias      (K, 2, 2) mean over sub-pixel positions of b(d) b(d)ᵀ: the systematic bias (px²)
    scatter   (K, 2, 2) mean over sub-pixel positions of H₁⁻¹ V_d H₁⁻¹: the bias's variation from
              patch to patch of the pattern is scatter / P (px²)
    bound     (K, 2, 2) (Σ_k w |2πq|² q̂ q̂ᵀ)⁻¹: the Cramér-Rao bound of one noisy image with the
              true gradient (σ² bound / P), for the ratio
    bound_sharp (K, 2, 2) the same without the optics' MTF (the image the bound of
              `vdo.objective` describes)
    phases    ((n₁,), (n₂,)) the sub-pixel positions d₁, d₂ averaged over
    bias_curve (K, n₁, n₂, 2) b(d₁, d₂) in px
    """

    gradient: np.ndarray
    noise: np.ndarray
    bias: np.ndarray
    scatter: np.ndarray
    bound: np.ndarray
    bound_sharp: np.ndarray
    phases: tuple
    bias_curve: np.ndarray

    def covariance(self, sigma, pixels) -> np.ndarray:
        """(K, 2, 2) px²: σ² noise / P + scatter / P + bias, σ (K,) or scalar in pattern stds."""
        s2 = np.asarray(sigma, dtype=float) ** 2 * np.ones(len(self.noise))
        p = np.asarray(pixels, dtype=float) * np.ones(len(self.noise))
        return (s2[:, None, None] * self.noise + self.scatter) / p[:, None, None] + self.bias

    def ratio(self, sigma, pixels, sharp: bool = False) -> np.ndarray:
        """(K, 2) per image axis: sqrt(measured variance / the bound's σ² bound / P); `sharp`:
        against the bound of the image without the optics (`bound_sharp`)."""
        s2 = np.asarray(sigma, dtype=float) ** 2 * np.ones(len(self.noise))
        p = np.asarray(pixels, dtype=float) * np.ones(len(self.noise))
        crb = s2[:, None] * np.diagonal(self.bound_sharp if sharp else self.bound,
                                        axis1=1, axis2=2) / p[:, None]
        return np.sqrt(np.diagonal(self.covariance(sigma, pixels), axis1=1, axis2=2) / crb)


MODEL_CACHE_SIZE = 4096      # footprints whose `correlation_error` terms are kept (about 2 kB each)
_MODEL_CACHE: dict = {}      # (pattern digest, settings, footprint, optics) -> that footprint's terms


def _phase_pairs(px: np.ndarray, py: np.ndarray) -> list[tuple]:
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


def correlation_error(pattern_normalised, texel_m: float, pixel_sides, order: int | str = 3,
                      optics=None, noisy_reference: bool = True,
                      texel_filter: str = "bilinear", phases=None,
                      fourth_moments: bool = True) -> CorrelationError:
    """The error of an interpolating correlation of a translation (`order`: 3 or 5, the B-spline;
    KEYS, Keys' cubic convolution, `_KeysSpectrum`) on the
    box-pixel image of the pattern f̂ at K footprints `pixel_sides` (K, 2, 2) m (as
    `pixel_averaged_std`), after the optics' MTF (`optics`: K `vdo.model.optics.OpticsBlur`, or
    None for none). The correlation (`vdo.dic.correlate`) reads the reference at its pixel centres
    n with the spline's gradient there, and interpolates the deformed image at n + u; d = frac(u).

    Every pattern frequency k (cycles/m, with its texel images k + m/h as `interpolation_error`)
    lands in the image at q_j = k.a_j cycles per pixel, ω = 2πq, with the weight
    w(k) = |F(k)|² T(k) sinc²(q₁) sinc²(q₂) MTF²(|q|) (T the texel filter: bilinear sinc⁴ per axis,
    box sinc²). With R_d(ω) the interpolant's shift response (the interpolated over the true value,
    `_SplineSpectrum.shift`, `_KeysSpectrum.shift`), D(ω) its derivative response (`.derivative`),
    E = R_{d₁}(ω₁) R_{d₂}(ω₂) - 1 the interpolation error and ω̄ the frequency folded into
    [-π, π) (where the sampled noise lives), over a patch of P pixels and for a pattern with
    independent random phases:

        H₁  = Σ_k w D Dᵀ                          (gradient per pixel)
        b(d) = -H₁⁻¹ Σ_k w D Im E                   (the systematic bias, px)
        N_d = Σ_k w D Dᵀ (|R_{d₁}(ω̄₁) R_{d₂}(ω̄₂)|² + r)   (r = 1: a noisy reference)
        V_d = ∫ [S_DD(q̄) S_EE(q̄) + Re S_DE(q̄) S_DE(q̄)ᵀ] dq̄   (Gaussian fourth moments)

    with S_DD, S_EE, S_DE the folded spectra (Σ of w DDᵀ, w|E|², w i D Ē over the k that fold to
    q̄, binned FOLD_BINS² over the unit cell). Then û - u = b(d) + noise + scatter with
    Cov = σ² H₁⁻¹ N_d H₁⁻¹ / P + H₁⁻¹ V_d H₁⁻¹ / P: the mean over d on a PHASES² grid is returned
    (docs/theory.md, "What the lab measures"); `phases` = (d₁ values, d₂ values) replaces that
    grid (e.g. ([0, 1/8, ...], [0]) for shifts along x only).
    V_d holds for a Gaussian field; a real pattern's fourth cumulant changes it (binary dots at
    50 % fill are platykurtic: less scatter). With `fourth_moments` (the default) the scatter is
    scaled per image axis a by kappa_a of `cumulant_factor`, the realized over the Gaussian
    scatter on the image of this tile at the rectangular footprint of the same pixel sides
    (|a_1| along image x, |a_2| along y, snapped; the footprint's shear and its orientation to
    the texel grid left out): scatter_ab <- sqrt(kappa_a kappa_b) scatter_ab (px²; kappa about 1
    for a Gaussian field, about 0.6 on y for 2 px binary dots; tests/physics/test_measured.py).
    `texel_filter`: "bilinear" (Mitsuba's bitmap), "box" (nearest texel) or "ideal" (the texels'
    band-limited interpolant: no texel filter, no texel images).
    Each footprint's terms are kept (`MODEL_CACHE_SIZE` of them, keyed by the pattern's digest, the
    settings, the footprint and the optics), so the design checks and σ_measured, which meet the
    same footprints, compute them once per process; the factor is kept per canonical footprint
    and snapped optics (`cumulant_factor`: about 0.3 s for each new one, in memory and on disk)."""
    if order not in INTERPOLANTS.values():
        raise ValueError(f"order: expected one of {list(INTERPOLANTS.values())}, got {order!r}")
    f = np.asarray(pattern_normalised)
    w, ku, kv = blocked_spectrum(f, texel_m, texel_filter=False, block=max(1, min(f.shape) // 256))
    m = np.arange(-TEXEL_IMAGES, TEXEL_IMAGES + 1) / texel_m
    shape = (m.size, m.size, ku.size)
    qu = np.broadcast_to(ku[None, None, :] + m[:, None, None], shape).reshape(-1)
    qv = np.broadcast_to(kv[None, None, :] + m[None, :, None], shape).reshape(-1)
    if texel_filter == "ideal":     # the texels' band-limited (trigonometric) interpolant
        m = np.zeros(1)
        shape = (1, 1, ku.size)
        qu, qv = ku, kv
    power = {"bilinear": 4, "box": 2, "ideal": 0}[texel_filter]
    weight = np.broadcast_to(w, shape).reshape(-1) * (np.sinc(qu * texel_m) * np.sinc(qv * texel_m)) ** power
    keep = weight >= 1e-9 * w.sum()
    qu, qv, weight = qu[keep], qv[keep], weight[keep]
    sides = np.asarray(pixel_sides, dtype=np.float64).reshape(-1, 2, 2)
    optics = [None] * len(sides) if optics is None else list(optics)
    grid = np.arange(PHASES) / PHASES
    px, py = (grid, grid) if phases is None else (np.atleast_1d(np.asarray(p, dtype=float))
                                                  for p in phases)
    out = {k: np.empty((len(sides), 2, 2))
           for k in ("gradient", "noise", "bias", "scatter", "bound", "bound_sharp")}
    curves = np.empty((len(sides), px.size, py.size, 2))
    r = 1.0 if noisy_reference else 0.0
    pairs = _phase_pairs(px, py)
    common = (hashlib.blake2b(np.ascontiguousarray(f, dtype=np.float64).tobytes(),
                              digest_size=16).hexdigest(), float(texel_m), order, noisy_reference,
              texel_filter, px.tobytes(), py.tobytes(), fourth_moments)
    for i, (a, opt) in enumerate(zip(sides, optics)):
        key = common + (a.tobytes(), opt)
        if key in _MODEL_CACHE:
            for name, value in _MODEL_CACHE[key].items():
                (curves if name == "bias_curve" else out[name])[i] = value
            continue
        q1, q2 = qu * a[0, 0] + qv * a[1, 0], qu * a[0, 1] + qv * a[1, 1]
        wk = weight * (np.sinc(q1) * np.sinc(q2)) ** 2
        qn = np.stack([q1, q2]) / np.maximum(np.hypot(q1, q2), 1e-300)
        out["bound_sharp"][i] = np.linalg.inv(np.einsum("m,am,bm->ab", wk * (2 * np.pi) ** 2
                                                        * (q1 ** 2 + q2 ** 2), qn, qn))
        if opt is not None:
            wk = wk * opt.mtf(np.hypot(q1, q2)) ** 2
        big = wk >= 1e-9 * wk.sum()
        q1, q2, wk = q1[big], q2[big], wk[big]
        om1, om2 = 2 * np.pi * q1, 2 * np.pi * q2
        sp1, sp2 = _responses(om1, order), _responses(om2, order)
        D = np.stack([sp1.derivative(), sp2.derivative()])                             # (2, M)
        H1 = np.einsum("m,am,bm->ab", wk, D, D)
        qn = np.stack([q1, q2]) / np.maximum(np.hypot(q1, q2), 1e-300)
        out["bound"][i] = np.linalg.inv(np.einsum("m,am,bm->ab", wk * (om1 ** 2 + om2 ** 2), qn, qn))
        R1, R2 = sp1.shift(px), sp2.shift(py)
        G1, G2 = sp1.derivative_shift(px), sp2.derivative_shift(py)
        fold1, fold2 = (q1 + 0.5) % 1.0 - 0.5, (q2 + 0.5) % 1.0 - 0.5
        A1 = np.abs(_responses(2 * np.pi * fold1, order).shift(px)) ** 2
        A2 = np.abs(_responses(2 * np.pi * fold2, order).shift(py)) ** 2
        nb = FOLD_BINS * FOLD_BINS

        def bin_of(f1, f2):
            return (np.minimum((f1 + 0.5) * FOLD_BINS, FOLD_BINS - 1).astype(np.int64) * FOLD_BINS
                    + np.minimum((f2 + 0.5) * FOLD_BINS, FOLD_BINS - 1).astype(np.int64))

        # The spectrum is one-sided (k stands for ±k): half of each weight at +q̄, half at -q̄,
        # where a real field's cross-spectrum is the conjugate (D odd, E(-q) = conj E(q)).
        plus, minus = bin_of(fold1, fold2), bin_of(-fold1, -fold2)

        # binning as sparse (nb, M) matrices: even and odd parts of the two half weights
        cols = np.arange(q1.size)
        Bp, Bm = (scipy.sparse.csr_matrix((np.full(q1.size, 0.5), (rows, cols)), shape=(nb, q1.size))
                  for rows in (plus, minus))
        even, odd = Bp + Bm, Bp - Bm
        Dw = D * wk                                                              # (2, M)
        wDD = (Dw[:, None, :] * D[None, :, :]).reshape(4, -1)                    # (4, M)
        s_dd = (even @ wDD.T).T.reshape(2, 2, nb)
        noise = np.zeros((2, 2))
        bias = np.zeros((2, 2))
        scatter = np.zeros((2, 2))
        # the sub-pixel positions PHASE_CHUNK at a time, as (c, M) arrays
        for s in range(0, len(pairs), PHASE_CHUNK):
            part = pairs[s:s + PHASE_CHUNK]
            i1, i2 = (np.array([p[k] for p in part]) for k in (0, 1))
            count = np.array([p[3] for p in part], dtype=float)
            R1c, R2c = R1[i1], R2[i2]
            E = R1c * R2c - 1.0
            # the Jacobian the iteration meets: Σ ∇ref ∇(interpolated deformed)ᵀ at n + d
            Hd = np.stack([(G1[i1] * R2c).real @ Dw.T, (R1c * G2[i2]).real @ Dw.T], -1)  # (c, a, b)
            Hi = np.linalg.inv(Hd)
            b = -np.einsum("cab,cb->ca", Hi, E.imag @ Dw.T)
            for k, (p1, p2, twin, _) in enumerate(part):
                curves[i, p1, p2] = b[k]
                if twin is not None:
                    curves[i, twin[0], twin[1]] = -b[k]
            bias += np.einsum("c,ca,cb->ab", count, b, b)
            Nd = ((A1[i1] * A2[i2] + r) @ wDD.T).reshape(-1, 2, 2)
            noise += np.einsum("c,cab,cbd,ced->ae", count, Hi, Nd, Hi)
            s_ee = (even @ (wk * (E.real ** 2 + E.imag ** 2)).T).T                # (c, nb)
            # i D conj(E), (2, c, nb): real part even, imaginary part odd in q̄
            re, im = ((B @ (Dw[:, None, :] * x).reshape(-1, x.shape[-1]).T).T.reshape(2, -1, nb)
                      for B, x in ((even, E.imag), (odd, E.real)))
            V = nb * (np.einsum("abq,cq->cab", s_dd, s_ee)
                      + np.einsum("acq,bcq->cab", re, re) - np.einsum("acq,bcq->cab", im, im))
            scatter += np.einsum("c,cab,cbd,ced->ae", count, Hi, V, Hi)
        n_ph = px.size * py.size
        out["gradient"][i], out["noise"][i] = H1, noise / n_ph
        kappa = np.ones(2) if not fourth_moments else np.sqrt(cumulant_factor(
            f, texel_m, np.linalg.norm(a, axis=0), order, (px, py), opt, texel_filter,
            digest=common[0]).kappa)
        out["bias"][i], out["scatter"][i] = bias / n_ph, kappa[:, None] * scatter * kappa / n_ph
        if len(_MODEL_CACHE) >= MODEL_CACHE_SIZE:
            _MODEL_CACHE.pop(next(iter(_MODEL_CACHE)))          # the oldest entry first
        _MODEL_CACHE[key] = {**{k: v[i].copy() for k, v in out.items()}, "bias_curve": curves[i].copy()}
    return CorrelationError(phases=(px, py), bias_curve=curves, **out)


# --------------------------------------------------------------------------------------------
# The scatter's fourth moments, from the realized pattern
# --------------------------------------------------------------------------------------------
SCATTER_LAGS = 21           # half-width (px) of the Bartlett window over which the realized
                            # autocovariances of g = ∇f e_d are summed (`cumulant_factor`): the
                            # variance of a 21 x 21 px patch's sum, the validation's subsets
LAG_FRACTION = 4            # ... and at most a quarter of the canonical image's side: the tile's
                            # sampling error of the factor stays about 0.1 at 64 px (its first-
                            # order biases, O(L² / M²), are removed)
SCALE_STEPS = 16            # canonical pixel sides per octave of texels per pixel (4.4 % steps)
CUMULANT_PHASES = 4         # sub-pixel positions per axis at most over which the factor is taken
OPTICS_STEP = 0.25          # px: the optics' λN/p and defocus blur snapped to this for the factor
CUMULANT_MAX_PIXELS = 512  # the canonical image's side at most (px): a finer footprint (more
                            # than 512 pixels over the tile, i.e. fewer than N / 512 texels per
                            # pixel) takes the factor at 512 (cost grows as M² log M: 0.3 s at
                            # 512, 2-3 s at 1024, 60 s at 4,500; below about 1.5 texels per pixel
                            # the model's x is off by 13-54 % with or without the factor,
                            # docs/theory.md)
CUMULANT_CACHE_SIZE = 1024  # (pattern, settings, canonical side, snapped optics) factors kept
FACTOR_VERSION = 2          # part of the on-disk key: raise it when the factor's formula changes
_CUMULANT_CACHE: dict = {}


@dataclass(frozen=True)
class CumulantFactor:
    """The realized scatter over its Gaussian part at a canonical footprint (`cumulant_factor`).

    kappa     (2,) per image axis: Σ_d [H⁻¹ V_real H⁻¹]_aa / Σ_d [H⁻¹ V_gauss H⁻¹]_aa
    gaussian  (2, 2) mean over the sub-pixel positions of H⁻¹ V_gauss H⁻¹ on the realized image:
              the Gaussian formula's scatter (px², for a unit-variance pattern), summed over the
              same lag window (checks against `correlation_error`'s analytic term)
    pixels    (M_x, M_y), the canonical image's pixels along x and y over the tile (its pixel:
              N h / M_x by N h / M_y)
    """

    kappa: np.ndarray
    gaussian: np.ndarray
    pixels: int


def _fold(x: np.ndarray, j: np.ndarray, m: int, axis: int) -> np.ndarray:
    """Σ over the frequencies j ≡ p (mod m) of x along `axis` (j sorted ascending, consecutive
    integers): the spectrum of the samples at m pixels per tile, p = 0 .. m - 1 (FFT order)."""
    x = np.moveaxis(x, axis, 0)
    out = np.zeros((m,) + x.shape[1:], dtype=x.dtype)
    t, p = 0, int(j[0] % m)
    while t < x.shape[0]:                        # runs of consecutive p, each added as a slice
        run = min(m - p, x.shape[0] - t)
        out[p:p + run] += x[t:t + run]
        t, p = t + run, 0
    return np.moveaxis(out, 0, axis)


def _lag_window(mx: int, my: int) -> np.ndarray:
    """The Bartlett window (1 - |l₁|/L₁)(1 - |l₂|/L₂), |l_a| < L_a = min(SCATTER_LAGS,
    M_a // LAG_FRACTION), on the M_y x M_x periodic lag grid (FFT order)."""
    def axis(m):
        lag = max(1, min(SCATTER_LAGS, m // LAG_FRACTION))
        return np.clip(1.0 - np.abs(np.fft.fftfreq(m, 1.0 / m)) / lag, 0.0, None)
    return axis(my)[:, None] * axis(mx)[None, :]


def cumulant_factor(pattern_normalised, texel_m: float, side_m, order=3, phases=None,
                    optics=None, texel_filter: str = "bilinear",
                    digest: str | None = None) -> CumulantFactor:
    """How far the scatter of the bias departs from its Gaussian fourth moments on this pattern:
    the scatter computed on the realized image of the tile, over the same computed with Isserlis'
    theorem from the same image's second moments, at the canonical footprint: rectangular pixels
    of sides N h / M_x along x and N h / M_y along y (M_a = round(N h / side_a), `side_m` a side
    in metres or (x, y) sides, each snapped to SCALE_STEPS per octave of texels per pixel), so
    that the tile holds M_x x M_y whole pixels and the image is periodic.

    The image's spectrum at pixel frequency p is the sum of its pattern frequencies j ≡ p (mod M)
    per axis (j cycles per tile, q_a = j_a / M_a cycles per pixel, ω = 2πq):
    c_j T(j/N) sinc(q₁) sinc(q₂) MTF(|q|)
    (c_j the tile's DFT / N², T the texel filter's amplitude on its base band; the texel images
    are left out). The interpolant's response is R_d(ω) = exp(-iωd) P_d(ω̄), P_d periodic (the
    discrete interpolation), so the moved image folds c_j exp(-iω.d) and the interpolation error
    field is ê_d = P_d(ω̄₁) P_d(ω̄₂) fold(c exp(-iω.d)) - fold(c); the reference's spline gradient
    ∇̂_a = i D(ω̄_a) fold(c). Per pixel g(n) = ∇f(n) e_d(n) - <∇f e_d> (`correlation_error`'s
    û - u = -H_d⁻¹ Σ_n g(n); the mean is its random-phase expectation, Σ_j |c_j|² (-i D) E, so
    that V_real is unbiased), with C_xy(l) = <x(n) y(n + l)> over the tile and w(l) the Bartlett
    window of half-width L = min(SCATTER_LAGS, M // LAG_FRACTION) px (`_lag_window`):

        V_real  = Σ_l w(l) C_gg(l)                                    (every moment)
        V_gauss = Σ_l w(l) [C_∇∇(l) C_ee(l) + C_∇e(l) C_e∇(l)ᵀ]       (Isserlis: Gaussian)
                  - (Σw / M²) Σ_k C_∇e(k) [C_∇e(k) + C_∇e(-k)]ᵀ    (the products' own bias)

    and kappa_a = Σ_d [H⁻¹ V_real H⁻¹]_aa / Σ_d [H⁻¹ V_gauss H⁻¹]_aa, H = <∇f ∇fᵀ>, over at most
    CUMULANT_PHASES of the given sub-pixel positions and their twins 1 - d per axis (`phases` as
    `correlation_error`; the set is the same for d and 1 - d, as the Gaussian term is). kappa is
    1 in expectation for a Gaussian field (binary dots are platykurtic: kappa < 1 on the axis
    across the shift). The texel filter's images (m ≠ 0) are left out of the realized image; the
    optics' λN/p and defocus are snapped to OPTICS_STEP; M is at most CUMULANT_MAX_PIXELS (a finer
    footprint takes the factor at that M). Cost: the tile's FFT, one N x N product per x phase and
    six M x M FFTs per phase pair (0.3 s at M = 512); kept per pattern, settings, canonical side
    and snapped optics in memory (CUMULANT_CACHE_SIZE) and in vdo's cache folder
    (`scatter-factors/`, one small file each, keyed with FACTOR_VERSION), so that later runs and
    other processes read it; `digest`: the tile's, when the caller has it."""
    f = np.asarray(pattern_normalised, dtype=np.float64)
    n = f.shape[0]
    if f.shape != (n, n):
        raise ValueError(f"cumulant_factor: a square tile, got {f.shape}")
    grid = np.arange(PHASES) / PHASES
    px, py = (grid, grid) if phases is None else (np.atleast_1d(np.asarray(p, dtype=float))
                                                  for p in phases)
    px, py = (np.unique(np.concatenate([p % 1.0, (1.0 - p) % 1.0])) for p in (px, py))   # + twins
    px, py = (p[::-(-p.size // CUMULANT_PHASES)] for p in (px, py))
    sides = np.broadcast_to(np.asarray(side_m, dtype=float), (2,))
    steps = [round(math.log2(side / texel_m) * SCALE_STEPS) for side in sides]
    mx, my = (min(CUMULANT_MAX_PIXELS, max(8, int(round(n / 2.0 ** (k / SCALE_STEPS)))))
              for k in steps)
    if optics is not None:
        optics = type(optics)(**{k: OPTICS_STEP * round(getattr(optics, k) / OPTICS_STEP)
                                 for k in ("airy_px", "defocus_px")})     # the MTF's parameters
    if digest is None:
        digest = hashlib.blake2b(np.ascontiguousarray(f).tobytes(), digest_size=16).hexdigest()
    key = (digest, float(texel_m), mx, my, order, optics, texel_filter, px.tobytes(), py.tobytes())
    if key in _CUMULANT_CACHE:
        return _CUMULANT_CACHE[key]
    stored = _stored_factor(key)
    if stored is not None:
        _keep(key, stored)
        return stored
    j = np.arange(-(n // 2), n - n // 2)                            # cycles per tile, ascending
    c = np.fft.fftshift(np.fft.fft2(f)) / n ** 2                     # rows: y (v), columns: x (u)
    qx, qy = j / mx, j / my                                          # cycles per pixel
    texel = {"bilinear": np.sinc(j / n) ** 2, "box": np.sinc(j / n), "ideal": np.ones(n)}[texel_filter]
    c = c * (np.sinc(qy) * texel)[:, None] * (np.sinc(qx) * texel)[None, :]
    if optics is not None:
        c = c * optics.mtf(np.hypot(qy[:, None], qx[None, :]))
    omega_x, omega_y = 2 * np.pi * qx, 2 * np.pi * qy
    folded_x, folded_y = (2 * np.pi * np.fft.fftfreq(m) for m in (mx, my))   # ω̄, FFT order
    sp_x, sp_y = _responses(folded_x, order), _responses(folded_y, order)
    D_x, D_y = sp_x.derivative(), sp_y.derivative()
    # P_d(ω̄) = R_d(ω̄) exp(iω̄d), per axis and phase
    P1 = sp_x.shift(px) * np.exp(1j * np.outer(px, folded_x))
    P2 = sp_y.shift(py) * np.exp(1j * np.outer(py, folded_y))
    image = _fold(_fold(c, j, mx, 1), j, my, 0)                        # (M_y, M_x), Î
    npix, half = mx * my, mx // 2 + 1
    # real fields through their half spectra: x(n) = Σ_p X̂(p) exp(2πi p.n / M), rfft2(x) = M² X̂
    twice = np.where((np.arange(half) > 0) & (2 * np.arange(half) != mx), 2.0, 1.0)  # rfft columns

    def field(coef):
        return scipy.fft.irfft2(npix * coef[:, :half], s=(my, mx))

    def corr(a_hat, b_hat):            # C_ab(l) = <a(n) b(n + l)>, from the rfft2s of a and b
        return scipy.fft.irfft2(np.conj(a_hat) * b_hat, s=(my, mx)) / npix

    def reversed_(x):                  # x(-l) on the periodic lag grid
        return np.roll(x[::-1, ::-1], 1, axis=(0, 1))

    w = _lag_window(mx, my)
    w_hat = scipy.fft.rfft2(w).real * twice / npix ** 2    # Σ_l w C_ab = Σ_p ŵ conj(â) b̂ / M⁴
    grad_coef = [1j * D_x[None, :] * image, 1j * D_y[:, None] * image]   # ∇_x (columns), ∇_y
    grad = np.stack([field(x) for x in grad_coef])
    grad_hat = [npix * x[:, :half] for x in grad_coef]
    c_dd = [[corr(grad_hat[a], grad_hat[b]) for b in range(2)] for a in range(2)]
    H = np.einsum("an,bn->ab", grad.reshape(2, -1), grad.reshape(2, -1)) / npix
    Hi = np.linalg.inv(H)
    real, gauss = np.zeros((2, 2)), np.zeros((2, 2))
    # the pattern's expected <g> (random phases: the diagonal j = j' of Σ_p conj ∇̂ ê)
    power = np.abs(c) ** 2
    full_x, full_y = _responses(omega_x, order), _responses(omega_y, order)
    dx_full, dy_full = full_x.derivative(), full_y.derivative()
    r1_full, r2_full = full_x.shift(px), full_y.shift(py)
    pairs = _phase_pairs(px, py)
    for p1 in sorted({p[0] for p in pairs}):
        moved_x = _fold(c * np.exp(-1j * omega_x * px[p1])[None, :], j, mx, 1)   # (N, M_x)
        mean_x, mean_y = power @ (dx_full * r1_full[p1]), power @ r1_full[p1]       # (N,) per j₂
        for _, p2, _, count in (p for p in pairs if p[0] == p1):
            if px[p1] % 1.0 == 0.0 and py[p2] % 1.0 == 0.0:
                continue                         # whole pixels: no interpolation error, V = 0
            moved = _fold(moved_x * np.exp(-1j * omega_y * py[p2])[:, None], j, my, 0)
            e_coef = P1[p1][None, :] * P2[p2][:, None] * moved - image
            e, e_hat = field(e_coef), npix * e_coef[:, :half]
            g = grad * e
            g[0] -= np.real(-1j * np.sum(r2_full[p2] * mean_x))           # <g> = the bias's H b
            g[1] -= np.real(-1j * np.sum(dy_full * r2_full[p2] * mean_y))
            g_hat = scipy.fft.rfft2(g)
            c_ee = corr(e_hat, e_hat)
            c_de = [corr(grad_hat[a], e_hat) for a in range(2)]         # <∇_a(n) e(n + l)>
            c_ed = [reversed_(x) for x in c_de]                         # <e(n) ∇_a(n + l)>
            v_real = np.array([[np.sum(w_hat * (np.conj(g_hat[a]) * g_hat[b]).real)
                                for b in range(2)] for a in range(2)])
            # minus the products' own bias, (Σw / M²) Σ_k C_∇e(k) [C_∇e(k) + C_∇e(-k)]
            v_gauss = np.array([[np.sum(w * (c_dd[a][b] * c_ee + c_de[a] * c_ed[b]))
                                 - w.sum() / npix * np.sum(c_de[a] * (c_de[b] + c_ed[b]))
                                 for b in range(2)] for a in range(2)])
            real += count * Hi @ v_real @ Hi
            gauss += count * Hi @ v_gauss @ Hi
    out = CumulantFactor(np.diagonal(real) / np.diagonal(gauss), gauss / (px.size * py.size),
                         (mx, my))
    _keep(key, out)
    _store_factor(key, out)
    return out


def _keep(key: tuple, factor: CumulantFactor) -> None:
    if len(_CUMULANT_CACHE) >= CUMULANT_CACHE_SIZE:
        _CUMULANT_CACHE.pop(next(iter(_CUMULANT_CACHE)))          # the oldest entry first
    _CUMULANT_CACHE[key] = factor


def _factor_path(key: tuple):
    """The factor's file in vdo's cache folder (`vdo.core.configure.cache_dir`), named by a digest
    of its key and FACTOR_VERSION."""
    from vdo.core.configure import cache_dir

    name = hashlib.blake2b(repr((FACTOR_VERSION,) + key).encode(), digest_size=20).hexdigest()
    return cache_dir() / "scatter-factors" / f"{name}.npz"


def _stored_factor(key: tuple) -> CumulantFactor | None:
    """The factor kept on disk by an earlier process, or None (absent or unreadable)."""
    path = _factor_path(key)
    try:
        with np.load(path) as z:
            return CumulantFactor(z["kappa"].copy(), z["gaussian"].copy(),
                                  tuple(int(v) for v in z["pixels"]))
    except (OSError, KeyError, ValueError):
        return None


def _store_factor(key: tuple, factor: CumulantFactor) -> None:
    """Keep the factor on disk for later processes (written whole, then renamed: a reader never
    meets half a file); a folder that cannot be written only costs the recomputation."""
    import os
    import tempfile
    from pathlib import Path

    path = _factor_path(key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = tempfile.NamedTemporaryFile(dir=path.parent, suffix=".part", delete=False)
    except OSError:
        return
    try:
        with tmp:
            np.savez(tmp, kappa=factor.kappa, gaussian=factor.gaussian, pixels=factor.pixels)
        os.replace(tmp.name, path)
    except BaseException as err:              # Ctrl-C included: no half-written file is left
        Path(tmp.name).unlink(missing_ok=True)
        if not isinstance(err, OSError):
            raise
