"""How far the scatter of a correlation's interpolation bias departs from its Gaussian fourth
moments on a real pattern (`cumulant_factor`): the scatter computed on the realized image of the
pattern tile over its Isserlis (Gaussian) part from the same image, per image axis, kept in memory
and in vdo's cache folder. `vdo.model.interpolant.correlation_error` scales its analytic scatter
by it; the derivation and its validation are in docs/theory.md, "The scatter from the realized
pattern".
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft

from vdo.core.memo import Memo, digest as array_digest
from vdo.model.spline_response import PHASES, phase_pairs, responses

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
_CUMULANT_CACHE = Memo(CUMULANT_CACHE_SIZE)


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
    integers): the spectrum of the samples at m pixels per tile, p = 0 .. m - 1 (FFT order). Runs
    of consecutive p are added as slices along `axis` in place (no transposed copy of x)."""
    shape = list(x.shape)
    shape[axis] = m
    out = np.zeros(shape, dtype=x.dtype)
    cut = lambda a, b: (slice(None),) * axis + (slice(a, b),)  # noqa: E731
    t, p = 0, int(j[0] % m)
    while t < x.shape[axis]:
        run = min(m - p, x.shape[axis] - t)
        out[cut(p, p + run)] += x[cut(t, t + run)]
        t, p = t + run, 0
    return out


def _real_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b for a real matrix a and a complex b, as two real products (numpy's mixed-type matmul
    casts a to complex and leaves BLAS: 1.35 s against 0.02 s for a 4096² tile's power)."""
    return a @ b.real + 1j * (a @ b.imag)


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
        digest = array_digest(f)
    key = (digest, float(texel_m), mx, my, order, optics, texel_filter, px.tobytes(), py.tobytes())
    if key in _CUMULANT_CACHE:
        return _CUMULANT_CACHE[key]
    stored = _stored_factor(key)
    if stored is not None:
        _CUMULANT_CACHE.put(key, stored)
        return stored
    j = np.arange(-(n // 2), n - n // 2)                            # cycles per tile, ascending
    c = np.fft.fftshift(scipy.fft.fft2(f))          # / N² below; rows: y (v), columns: x (u)
    qx, qy = j / mx, j / my                                          # cycles per pixel
    texel = {"bilinear": np.sinc(j / n) ** 2, "box": np.sinc(j / n), "ideal": np.ones(n)}[texel_filter]
    c *= (np.sinc(qy) * texel / n ** 2)[:, None]       # in place: the tile's spectrum is N² wide
    c *= (np.sinc(qx) * texel)[None, :]
    if optics is not None:
        c *= optics.mtf(np.hypot(qy[:, None], qx[None, :]))
    omega_x, omega_y = 2 * np.pi * qx, 2 * np.pi * qy
    folded_x, folded_y = (2 * np.pi * np.fft.fftfreq(m) for m in (mx, my))   # ω̄, FFT order
    sp_x, sp_y = responses(folded_x, order), responses(folded_y, order)
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
    full_x, full_y = responses(omega_x, order), responses(omega_y, order)
    dx_full, dy_full = full_x.derivative(), full_y.derivative()
    r1_full, r2_full = full_x.shift(px), full_y.shift(py)
    pairs = phase_pairs(px, py)
    firsts = sorted({p[0] for p in pairs})
    means = _real_matmul(power, np.stack([v for p1 in firsts
                                          for v in (dx_full * r1_full[p1], r1_full[p1])], axis=1))
    for k, p1 in enumerate(firsts):
        moved_x = _fold(c * np.exp(-1j * omega_x * px[p1])[None, :], j, mx, 1)   # (N, M_x)
        mean_x, mean_y = means[:, 2 * k], means[:, 2 * k + 1]                    # (N,) per j₂
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
    _CUMULANT_CACHE.put(key, out)
    _store_factor(key, out)
    return out


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
