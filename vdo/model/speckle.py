"""Speckle patterns and their gradient energy under Gaussian blur.

A pattern is a float32 image in [0, 1] (1 = white paint, 0 = black) of square texels of side h
[m]. `normalise` gives f̂ = (f - mean) / std (zero mean, unit variance). From its power spectrum
|F(k)|² (k in cycles/m, DC left out, normalised so that Σ_k |F(k)|² = var f̂ = 1) we tabulate

    g_f(l)          = ½ <|∇(G_l ⋆ f̂)|²>
                    = Σ_k w(k) exp(-(2π|k| l)²),                 w(k) = ½ |2πk|² |F(k)|²

    G(l_par, l_perp) = <(∂_e (G_{l_par, l_perp} ⋆ f̂))²>            (orientation-averaged)
                    = Σ_k w(k) e^(-min(α,β)) [I0e(γ) - sgn(α-β) I1e(γ)]

with α = (2π|k| l_par)², β = (2π|k| l_perp)², γ = |α - β| / 2, I0e/I1e the exponentially scaled
modified Bessel functions, all energies in 1/m². l is the standard deviation [m] of the Gaussian
blur; G_{l_par, l_perp} has std l_par along the unit direction e and l_perp across it.

Derivation of G. The blur multiplies F(k) by exp(-2π²(l_par² k_e² + l_perp² k_⊥²)); the directional
derivative multiplies it by 2πi k·e. With θ the angle between k and e, the energy of one k is
|2πk|² |F(k)|² cos²θ exp(-α cos²θ - β sin²θ). For a pattern that is isotropic on average, the
mean over θ with cos²θ = (1 + cos 2θ)/2, sin²θ = (1 - cos 2θ)/2, z = (α - β)/2 is

    <cos²θ e^(-α cos²θ - β sin²θ)>_θ = ½ e^(-(α+β)/2) [I0(z) - I1(z)]
                                     = ½ e^(-min(α,β)) [I0e(|z|) - sgn(z) I1e(|z|)]

(<e^(-z cos φ)> = I0(z), <cos φ e^(-z cos φ)> = -I1(z); I0 is even, I1 odd). Hence the formula
above: the minus sign holds for l_par >= l_perp, a plus sign for l_par < l_perp. For an isotropic
pattern <(∂_e f)²> = ½ <|∇f|²>, so G(l, l) = g_f(l) exactly: g_f is the energy per direction, the
quantity that enters the gradient tensor T = <∇f ∇fᵀ>.

`gradient_energy_table` evaluates both sums on a radially binned spectrum and stores them on a
log-spaced grid of l; `g_iso_lookup` and `g_aniso_lookup` interpolate log g linearly in log l
(bilinearly for G), in `jax.numpy`, so they work under `jax.jit` and `jax.grad`.
"""

from __future__ import annotations

import hashlib
import math
import numbers
import os
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft
import scipy.sparse
from scipy.special import i0e, i1e, j0

__all__ = [
    "GradientEnergyTable",
    "generate_pattern",
    "load_pattern",
    "normalise",
    "gradient_energy_table",
    "g_iso_lookup",
    "g_aniso_lookup",
    "pixel_averaged_std",
    "interpolation_error",
]

MIN_DOT_TEXELS = 3.0  # smallest dot diameter, in texels, that anti-aliasing renders as a round dot
STROKE_LENGTH_DOTS = (3.0, 8.0)  # stroke length range, in dot diameters
STROKE_SEGMENTS = 48  # polyline segments per stroke
_STAMP_CHUNK = 1 << 21  # texel evaluations per vectorised stamping batch
_LOW_K_RADIUS = 32.0  # below this radius (in units of 1/(N h)) each |k| is its own spectral bin
_BINS_PER_E_FOLD = 64  # above it, log-spaced bins of relative width 1/64


# --------------------------------------------------------------------------------------------
# Argument checks
# --------------------------------------------------------------------------------------------
def _positive_real(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(value) \
            or value <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return float(value)


def _integer(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


# --------------------------------------------------------------------------------------------
# Pattern generation
# --------------------------------------------------------------------------------------------
def _stamp_capsules(black: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float) -> None:
    """black = max(black, coverage of the capsules (segments a->b, `radius`)), periodic wrap.

    Positions in texels, texel (i, j) has its centre at (x, y) = (j + 0.5, i + 0.5). The coverage
    of a texel is clip(radius + 0.5 - d, 0, 1) with d the distance from its centre to the segment:
    the exact area fraction for a straight edge, a close approximation for curved ones. The max of
    these ramps over segments is the ramp of the distance to their union, so polylines join cleanly.
    """
    n = black.shape[0]
    flat_black = black.reshape(-1)
    d = b - a
    length2 = np.einsum("ij,ij->i", d, d)
    half = int(np.ceil(0.5 * np.sqrt(length2.max(initial=0.0)) + radius + 1.0))
    offsets = np.arange(-half, half + 1)
    width = offsets.size
    chunk = max(1, _STAMP_CHUNK // (width * width))
    inv_len2 = np.divide(1.0, length2, out=np.zeros_like(length2), where=length2 > 0)
    for s in range(0, a.shape[0], chunk):
        sl = slice(s, s + chunk)
        mid = 0.5 * (a[sl] + b[sl])
        ix = np.floor(mid[:, 0]).astype(np.int64)[:, None] + offsets  # (m, W)
        iy = np.floor(mid[:, 1]).astype(np.int64)[:, None] + offsets
        rx = (ix + 0.5 - a[sl, 0:1])[:, None, :]  # (m, 1, W)
        ry = (iy + 0.5 - a[sl, 1:2])[:, :, None]  # (m, W, 1)
        dx = d[sl, 0][:, None, None]
        dy = d[sl, 1][:, None, None]
        t = np.clip((rx * dx + ry * dy) * inv_len2[sl][:, None, None], 0.0, 1.0)
        dist = np.hypot(rx - t * dx, ry - t * dy)
        cov = np.clip(radius + 0.5 - dist, 0.0, 1.0)
        flat = (iy % n)[:, :, None] * n + (ix % n)[:, None, :]
        hit = cov > 0
        np.maximum.at(flat_black, flat[hit], cov[hit].astype(black.dtype))


def _stroke_polyline(rng: np.random.Generator, n: int, dot_px: float) -> np.ndarray:
    """Vertices (STROKE_SEGMENTS + 1, 2) of one random curved stroke, in texels (not wrapped)."""
    start = rng.uniform(0.0, n, size=2)
    length = dot_px * rng.uniform(*STROKE_LENGTH_DOTS)
    heading = rng.uniform(0.0, 2.0 * np.pi)
    bend, s_bend = rng.uniform(-0.5 * np.pi, 0.5 * np.pi, size=2)  # arc and S-shaped turning
    t = (np.arange(STROKE_SEGMENTS) + 0.5) / STROKE_SEGMENTS
    theta = heading + bend * t + s_bend * np.sin(2.0 * np.pi * t)
    steps = (length / STROKE_SEGMENTS) * np.stack([np.cos(theta), np.sin(theta)], axis=1)
    return start + np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])


def generate_pattern(size_px: int, texel_m: float, dot_diameter_m: float, coverage: float = 0.5,
                     strokes: int = 0, seed: int = 0) -> np.ndarray:
    """A seamless (periodic in both axes) speckle tile: black dots and strokes on white.

    Returns a (size_px, size_px) float32 image in [0, 1], 1 = white paint, 0 = black; each texel is
    `texel_m` metres. First `strokes` random curved black bands (width dot_diameter_m / 2, length
    3-8 dot diameters) are painted, then black discs of diameter `dot_diameter_m` at uniformly
    random centres, in batches, until the black area fraction reaches `coverage` (within about one
    dot's area; if the strokes alone exceed it, no dots are added). Everything wraps around the
    edges, so the tile repeats without a seam. Edges are anti-aliased (texel value = 1 - covered
    area fraction; the disc radius is reduced by the ramp's curvature bias so that each dot's black
    area is π d²/4). Deterministic for a `seed` (`numpy.random.default_rng(seed)`).

    Raises ValueError (naming the argument) unless size_px >= 16, texel_m > 0,
    3 texels <= dot_diameter_m <= size_px * texel_m / 4, 0 < coverage < 1, strokes >= 0, seed >= 0.
    """
    n = _integer("size_px", size_px, 16)
    texel = _positive_real("texel_m", texel_m)
    dot = _positive_real("dot_diameter_m", dot_diameter_m)
    dot_px = dot / texel
    if dot_px < MIN_DOT_TEXELS * (1 - 1e-9):
        raise ValueError(f"dot_diameter_m: expected at least {MIN_DOT_TEXELS:g} texels "
                         f"(>= {MIN_DOT_TEXELS * texel:g} m for texel_m = {texel:g}), got {dot!r}")
    if dot_px > n / 4:
        raise ValueError(f"dot_diameter_m: expected at most a quarter of the tile "
                         f"(<= {n * texel / 4:g} m = size_px * texel_m / 4), got {dot!r}")
    if isinstance(coverage, bool) or not isinstance(coverage, numbers.Real) \
            or not 0.0 < coverage < 1.0:
        raise ValueError(f"coverage: expected a black area fraction 0 < coverage < 1, got {coverage!r}")
    coverage = float(coverage)
    n_strokes = _integer("strokes", strokes, 0)
    rng = np.random.default_rng(_integer("seed", seed, 0))

    black = np.zeros((n, n), dtype=np.float32)
    for _ in range(n_strokes):
        v = _stroke_polyline(rng, n, dot_px)
        _stamp_capsules(black, v[:-1], v[1:], 0.25 * dot_px)

    # Dots: a Boolean model, each new dot lands on white with probability (1 - black fraction), so
    # reaching `coverage` from c takes about ln((1 - c) / (1 - coverage)) * area / dot_area dots.
    radius = 0.5 * dot_px
    radius_eff = np.sqrt(radius * radius - 1.0 / 12.0)  # ramp area = π (r_eff² + 1/12) = π r²
    dots_per_unit_log = n * n / (np.pi * radius * radius)
    for _ in range(100):
        c = float(black.mean(dtype=np.float64))
        deficit = np.log((1.0 - c) / (1.0 - coverage)) * dots_per_unit_log
        if deficit < 0.5:
            break
        last = deficit < 20
        count = int(round(deficit)) if last else int(0.9 * deficit)
        centres = rng.uniform(0.0, n, size=(count, 2))
        _stamp_capsules(black, centres, centres, radius_eff)
        if last:
            break
    return np.subtract(1.0, black, dtype=np.float32)


# --------------------------------------------------------------------------------------------
# Reading and normalising
# --------------------------------------------------------------------------------------------
def load_pattern(path) -> np.ndarray:
    """Read a PNG/TIFF/JPEG image as a float32 grey image in [0, 1] (first frame of a stack).

    8-bit data are divided by 255, 16-bit by 65535 (Pillow mode "I" is taken as 16-bit when its
    values fit, else divided by its maximum); float images are used as they are if in [0, 1], else
    divided by their maximum. Colour is converted to luma 0.299 R + 0.587 G + 0.114 B; alpha and
    palette are resolved by Pillow's conversion to RGB (alpha is dropped).
    """
    from PIL import Image

    with Image.open(path) as img:
        img.seek(0)
        mode = img.mode
        if mode.startswith("I;16"):
            grey = np.asarray(img, dtype=np.float64) / 65535.0
        elif mode == "I":
            grey = np.asarray(img, dtype=np.float64)
            top = grey.max(initial=0.0)
            grey = grey / (65535.0 if top <= 65535 else top)
        elif mode == "F":
            grey = np.asarray(img, dtype=np.float64)
            top = grey.max(initial=0.0)
            if top > 1.0:
                grey = grey / top
        elif mode == "L":
            grey = np.asarray(img, dtype=np.float64) / 255.0
        elif mode == "1":
            grey = np.asarray(img.convert("L"), dtype=np.float64) / 255.0
        else:
            rgb = np.asarray(img.convert("RGB"), dtype=np.float64) / 255.0
            grey = rgb @ np.array([0.299, 0.587, 0.114])
    if grey.ndim != 2:
        raise ValueError(f"path: expected a single-channel or colour image, got shape {grey.shape}")
    return np.clip(grey, 0.0, 1.0).astype(np.float32)


def normalise(pattern) -> np.ndarray:
    """f̂ = (f - mean f) / std f: the pattern with zero mean and unit variance (float64, 2-D)."""
    f = np.asarray(pattern, dtype=np.float64)
    if f.ndim != 2 or min(f.shape) < 2:
        raise ValueError(f"pattern: expected a 2-D image, got shape {f.shape}")
    if not np.all(np.isfinite(f)):
        raise ValueError("pattern: expected finite values")
    f = f - f.mean()
    std = f.std()
    if not std > 0:
        raise ValueError("pattern: expected a non-constant image (its variance is 0)")
    return f / std


# --------------------------------------------------------------------------------------------
# Gradient-energy table
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GradientEnergyTable:
    """g_f and G tabulated over blur widths.

    log_l:   (n,) blur standard deviations l [m] on a log-spaced (geometric) grid. The values are
             l itself, not log l; the name says how the grid is spaced.
    g_iso:   (n,) g_f(l) = ½ <|∇(G_l ⋆ f̂)|²>   [1/m²].
    g_aniso: (n, n) G(l_par = log_l[i], l_perp = log_l[j]) = <(∂_e (G ⋆ f̂))²>   [1/m²];
             its diagonal equals g_iso.

    Registered as a JAX pytree (the three arrays are leaves), so a table can be passed into a
    jitted function as well as closed over.
    """

    log_l: np.ndarray
    g_iso: np.ndarray
    g_aniso: np.ndarray

    def __post_init__(self):
        arrays = (self.log_l, self.g_iso, self.g_aniso)
        if not all(isinstance(a, np.ndarray) for a in arrays):
            return  # JAX rebuilds the pytree with tracers or placeholders; nothing to check
        n = self.log_l.shape[0]
        if self.log_l.ndim != 1 or n < 2 or self.g_iso.shape != (n,) or self.g_aniso.shape != (n, n):
            raise ValueError("GradientEnergyTable: expected log_l (n,), g_iso (n,), g_aniso (n, n), n >= 2")
        steps = np.diff(np.log(self.log_l))
        if not (np.all(steps > 0) and np.allclose(steps, steps[0], rtol=1e-6)):
            raise ValueError("GradientEnergyTable.log_l: expected an increasing geometric grid")


jax.tree_util.register_dataclass(
    GradientEnergyTable, data_fields=["log_l", "g_iso", "g_aniso"], meta_fields=[])


def _radial_spectrum(f: np.ndarray, texel_m: float):
    """Radially binned spectrum of f: per bin (k2, w, p) with
    w = Σ ½ |2πk|² |F(k)|² [1/m²], k2 = w-weighted mean of |k|² [1/m²], p = Σ |F(k)|².

    |F(k)|² = |DFT(f)|² / N_total², so Σ_k |F(k)|² = mean f² (Parseval). Bins: every distinct |k|
    below _LOW_K_RADIUS / (N h) (N = the larger side) is a bin of its own; above, log-spaced bins
    of relative width 1/_BINS_PER_E_FOLD. Since k2 is the w-weighted mean, the error of
    Σ w exp(-c k2) is second order in the bin width: about 1e-4 relative for g_f.
    """
    ny, nx = f.shape
    spec = scipy.fft.rfft2(f, workers=os.cpu_count() or 1)
    power = (spec.real ** 2 + spec.imag ** 2) / float(nx * ny) ** 2
    power[:, 1:(nx + 1) // 2] *= 2.0  # the half spectrum: columns with a conjugate twin count twice
    power[0, 0] = 0.0  # DC
    kx = np.arange(power.shape[1]) / (nx * texel_m)
    ky = np.fft.fftfreq(ny, d=texel_m)
    k2 = ky[:, None] ** 2 + kx[None, :] ** 2
    unit2 = (max(nx, ny) * texel_m) ** -2  # (1 / (N h))²
    rho2 = k2 / unit2
    low = rho2 < _LOW_K_RADIUS ** 2
    ids = np.empty(k2.shape, dtype=np.int64)
    low_keys, low_ids = np.unique(np.round(rho2[low], 6), return_inverse=True)
    ids[low] = low_ids
    high = ~low
    ids[high] = low_keys.size + np.floor(
        0.5 * _BINS_PER_E_FOLD * np.log(rho2[high] / _LOW_K_RADIUS ** 2)).astype(np.int64)
    ids = ids.ravel()
    w_k = (2.0 * np.pi ** 2) * k2 * power  # ½ |2πk|² |F|²
    w = np.bincount(ids, weights=w_k.ravel())
    wk2 = np.bincount(ids, weights=(w_k * k2).ravel())
    p = np.bincount(ids, weights=power.ravel())
    keep = w > 0
    return wk2[keep] / w[keep], w[keep], p[keep]


def _blocked_spectrum(pattern_normalised, texel_m: float, texel_filter: bool, block: int | None = None):
    """The tile's one-sided power spectrum |F(k)|² (DC left out, Σ = var f̂), times the bilinear
    texel filter sinc⁴(k_u h) sinc⁴(k_v h) when `texel_filter`, summed over blocks of b x b
    frequencies (b = side // 256, at least 1) each placed at its weight's centroid: (w, k_u, k_v)
    flat arrays, k in cycles/m (`pixel_averaged_std`)."""
    f = np.asarray(pattern_normalised, dtype=np.float64)
    ny, nx = f.shape
    spec = scipy.fft.rfft2(f, workers=os.cpu_count() or 1)
    power = (spec.real ** 2 + spec.imag ** 2) / float(nx * ny) ** 2
    power[:, 1:(nx + 1) // 2] *= 2.0
    power[0, 0] = 0.0
    ku = np.broadcast_to((np.arange(power.shape[1]) / (nx * texel_m))[None, :], power.shape)
    kv = np.broadcast_to(np.fft.fftfreq(ny, d=texel_m)[:, None], power.shape)   # rows: v
    weight = power * (np.sinc(ku * texel_m) * np.sinc(kv * texel_m)) ** 4 if texel_filter else power
    b = max(1, min(ny, nx) // 256) if block is None else block
    if b > 1 and ny % (2 * b) == 0:     # blocks never straddle the jump from +k to -k rows
        cols = -(-weight.shape[1] // b) * b

        def blocks(x):
            x = np.pad(x, ((0, 0), (0, cols - x.shape[1])))
            return x.reshape(ny // b, b, cols // b, b).sum(axis=(1, 3)).ravel()

        w = blocks(weight)
        ok = w > 0
        return w[ok], blocks(weight * ku)[ok] / w[ok], blocks(weight * kv)[ok] / w[ok]
    return weight.ravel(), ku.ravel(), kv.ravel()


def pixel_averaged_std(pattern_normalised, texel_m: float, pixel_sides) -> np.ndarray:
    """Standard deviation of f̂ averaged over a camera pixel, as rendered: (K,) for K pixel
    footprints, the pattern's variance being 1 before averaging.

    `pixel_sides` (K, 2, 2) [m]: columns a_1, a_2 are the surface displacements (u, v) of one
    pixel step along image x and y, A^-1 for the footprint A = dx/dξ (pixel/m). The box pixel is
    the parallelogram spanned by a_1, a_2, whose indicator has the Fourier transform
    sinc(k.a_1) sinc(k.a_2) (k in cycles/m, sinc x = sin(πx)/(πx)); the texture is interpolated
    bilinearly between texel centres (Mitsuba's bitmap), a triangle of width 2h per axis,
    sinc²(k_u h) sinc²(k_v h). So

        std² = Σ_k |F(k)|² sinc²(k.a_1) sinc²(k.a_2) sinc⁴(k_u h) sinc⁴(k_v h),

    over the tile's discrete spectrum (DC left out, Σ |F|² = var f̂). The aliases of the texel
    grid (k + m/h) are left out: bilinear interpolation keeps their weight below
    sinc⁴(1/2) = 16 % at the texel Nyquist frequency, and a pixel wider than a few texels
    suppresses them further. Used to predict the contrast of rendered pixels (the photometry
    table of `vdo render`): pixel values vary by c std, not by c.

    For speed the spectrum is summed over blocks of b x b frequencies (b = side // 256, at least
    1), each at its weight's centroid: the sinc factors vary little over a block (16 cycles/m for
    a 1024-texel tile of 0.25 mm), and the centroid makes the error second order (2e-4 relative
    against the full sum for footprints of 0.1-9 mm, `tests/physics/test_photometry.py`)."""
    w, ku, kv = _blocked_spectrum(pattern_normalised, texel_m, texel_filter=True)
    sides = np.asarray(pixel_sides, dtype=np.float64).reshape(-1, 2, 2)
    out = np.empty(len(sides))
    for i, a in enumerate(sides):
        h = np.sinc(ku * a[0, 0] + kv * a[1, 0]) * np.sinc(ku * a[0, 1] + kv * a[1, 1])
        out[i] = math.sqrt(float(np.sum(w * h * h)))
    return out


def _acf_half_width(k2: np.ndarray, p: np.ndarray, extent: float, texel: float) -> float:
    """Half-width at half maximum [m] of the radially averaged autocorrelation
    ACF(r) = Σ |F(k)|² J0(2π|k| r) / Σ |F(k)|²; about 0.385 dot diameters for dots at 50 % coverage."""
    k = np.sqrt(k2)
    r = np.geomspace(0.25 * texel, 0.5 * extent, 256)
    acf = (p[None, :] * j0(2.0 * np.pi * r[:, None] * k[None, :])).sum(axis=1) / p.sum()
    below = np.nonzero(acf < 0.5)[0]
    return float(r[below[0]] if below.size else r[-1])


def gradient_energy_table(pattern_normalised, texel_m: float, n: int = 96, *,
                          l_min: float | None = None, l_max: float | None = None) -> GradientEnergyTable:
    """Tabulate g_f(l) and G(l_par, l_perp) (module docstring) for a normalised pattern f̂.

    pattern_normalised: 2-D array, normally `normalise(...)`'s output; it is used as given (the DC
        term is dropped, the energies scale with its variance). Periodic tiles give exact spectra;
        a non-periodic image adds a small edge-leakage term.
    texel_m: texel side h [m].
    n: grid points (>= 8), log-spaced from l_min to l_max.
    l_min: smallest blur width [m]; default h / 4 (g_f is flat below: f̂ holds nothing finer than h).
    l_max: largest blur width [m]; default 130 half-widths at half maximum of the autocorrelation
        (about 50 dot diameters for a dot pattern), at most half the image's shorter side. Pass
        l_max = 50 * dot_diameter_m to fix it.

    The spectrum is binned once (see `_radial_spectrum`), then g_f is a sum over ~500 bins per l
    and G over ~n²/2 × 500 Bessel terms (G(i, j) and G(j, i) share them).
    """
    f = np.asarray(pattern_normalised, dtype=np.float64)
    if f.ndim != 2 or min(f.shape) < 8:
        raise ValueError(f"pattern_normalised: expected a 2-D image at least 8x8, got shape {f.shape}")
    if not np.all(np.isfinite(f)):
        raise ValueError("pattern_normalised: expected finite values")
    h = _positive_real("texel_m", texel_m)
    n = _integer("n", n, 8)
    k2, w, p = _radial_spectrum(f, h)
    if w.size == 0:
        raise ValueError("pattern_normalised: expected a non-constant image (no gradient energy)")
    extent = min(f.shape) * h
    lo = 0.25 * h if l_min is None else _positive_real("l_min", l_min)
    hi = min(130.0 * _acf_half_width(k2, p, extent, h), 0.5 * extent) if l_max is None \
        else _positive_real("l_max", l_max)
    if not hi > lo:
        raise ValueError(f"l_max: expected > l_min = {lo:g} m, got {hi:g} m")
    ls = np.geomspace(lo, hi, n)

    c = 4.0 * np.pi ** 2 * k2  # α = c l²
    damp = w[None, :] * np.exp(-np.outer(ls ** 2, c))  # (n, bins): w e^(-α)
    g_iso = damp.sum(axis=1)

    # Pairs i <= j (l_i <= l_j): min(α, β) belongs to l_i, γ = c (l_j² - l_i²) / 2.
    # S_A = Σ w e^(-α_i) I0e(γ), S_B = Σ w e^(-α_i) I1e(γ);
    # G(l_par = l_i, l_perp = l_j) = S_A + S_B  (l_par <= l_perp),  G(l_j, l_i) = S_A - S_B.
    iu, ju = np.triu_indices(n)
    s_a = np.empty(iu.size)
    s_b = np.empty(iu.size)
    block = max(1, (1 << 21) // c.size)
    for s in range(0, iu.size, block):
        i, j = iu[s:s + block], ju[s:s + block]
        gamma = (0.5 * (ls[j] ** 2 - ls[i] ** 2))[:, None] * c[None, :]
        s_a[s:s + block] = np.einsum("pb,pb->p", damp[i], i0e(gamma))
        s_b[s:s + block] = np.einsum("pb,pb->p", damp[i], i1e(gamma))
    g_aniso = np.empty((n, n))
    g_aniso[iu, ju] = s_a + s_b
    g_aniso[ju, iu] = s_a - s_b
    g_aniso[np.arange(n), np.arange(n)] = g_iso
    tiny = np.finfo(np.float64).tiny  # log-log interpolation needs g > 0
    arrays = (ls, np.maximum(g_iso, tiny), np.maximum(g_aniso, tiny))
    for a in arrays:
        a.setflags(write=False)
    return GradientEnergyTable(*arrays)


# --------------------------------------------------------------------------------------------
# Lookups (jax.numpy: usable under jit / grad / vmap)
# --------------------------------------------------------------------------------------------
def _grid_position(table: GradientEnergyTable, l):
    """Index i and fraction t of log l on the table's log-uniform grid, l clamped to the grid."""
    grid = jnp.asarray(table.log_l)
    size = grid.shape[0]
    log_lo, log_hi = jnp.log(grid[0]), jnp.log(grid[-1])
    l = jnp.clip(jnp.asarray(l, dtype=grid.dtype), grid[0], grid[-1])
    u = jnp.clip((jnp.log(l) - log_lo) / ((log_hi - log_lo) / (size - 1)), 0.0, size - 1.0)
    i = jnp.clip(jnp.floor(u), 0, size - 2).astype(jnp.int32)
    return i, u - i


def g_iso_lookup(table: GradientEnergyTable, l):
    """g_f(l) [1/m²] for blur widths l [m] (any shape): log g linear in log l between grid points.

    l outside [log_l[0], log_l[-1]] is clamped to the grid (value of the end point, zero
    derivative); l <= 0 gives g_f at the smallest grid width.
    """
    log_g = jnp.log(jnp.asarray(table.g_iso))
    i, t = _grid_position(table, l)
    return jnp.exp((1.0 - t) * log_g[i] + t * log_g[i + 1])


def g_aniso_lookup(table: GradientEnergyTable, l_par, l_perp):
    """G(l_par, l_perp) [1/m²]: energy of the derivative along e for blur std l_par [m] along e
    and l_perp [m] across it (arrays broadcast together). Bilinear in (log l_par, log l_perp) on
    log G; each width is clamped to the grid as in `g_iso_lookup`.
    """
    log_g = jnp.log(jnp.asarray(table.g_aniso))
    l_par, l_perp = jnp.broadcast_arrays(jnp.asarray(l_par), jnp.asarray(l_perp))
    i, s = _grid_position(table, l_par)
    j, t = _grid_position(table, l_perp)
    value = ((1.0 - s) * (1.0 - t) * log_g[i, j] + s * (1.0 - t) * log_g[i + 1, j]
             + (1.0 - s) * t * log_g[i, j + 1] + s * t * log_g[i + 1, j + 1])
    return jnp.exp(value)


def pattern_for(spec) -> np.ndarray:
    """The [0, 1] pattern tile of a `vdo.config.experiment.SpeckleSpec`: the user's image when it names one,
    else a generated tile of `tile_texels` texels of `texel` metres."""
    if spec.image is not None:
        return load_pattern(spec.image)
    return generate_pattern(spec.tile_texels, spec.texel, spec.dot_diameter, spec.coverage,
                            spec.strokes, spec.seed)


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
    spectrum is summed over blocks of side // 64 frequencies (`_blocked_spectrum`; 0.3 % off the
    full sum for the built-in 1024-texel tile): one FFT of the tile per call, then about 0.02 s
    per footprint; pass all footprints at once. `optics`: K `vdo.model.optics.OpticsBlur` (None
    entries or None: no lens blur), whose MTF²(|q|) multiplies each term (q = (k'.a_1, k'.a_2)
    cycles per pixel)."""
    f = np.asarray(pattern_normalised)
    w, ku, kv = _blocked_spectrum(f, texel_m, texel_filter=False, block=max(1, min(f.shape) // 64))
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
                      texel_filter: str = "bilinear", phases=None) -> CorrelationError:
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
    `texel_filter`: "bilinear" (Mitsuba's bitmap), "box" (nearest texel) or "ideal" (the texels'
    band-limited interpolant: no texel filter, no texel images).
    Each footprint's terms are kept (`MODEL_CACHE_SIZE` of them, keyed by the pattern's digest, the
    settings, the footprint and the optics), so the design checks and σ_measured, which meet the
    same footprints, compute them once per process."""
    if order not in INTERPOLANTS.values():
        raise ValueError(f"order: expected one of {list(INTERPOLANTS.values())}, got {order!r}")
    f = np.asarray(pattern_normalised)
    w, ku, kv = _blocked_spectrum(f, texel_m, texel_filter=False, block=max(1, min(f.shape) // 256))
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
              texel_filter, px.tobytes(), py.tobytes())
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
        out["bias"][i], out["scatter"][i] = bias / n_ph, scatter / n_ph
        if len(_MODEL_CACHE) >= MODEL_CACHE_SIZE:
            _MODEL_CACHE.pop(next(iter(_MODEL_CACHE)))          # the oldest entry first
        _MODEL_CACHE[key] = {**{k: v[i].copy() for k, v in out.items()}, "bias_curve": curves[i].copy()}
    return CorrelationError(phases=(px, py), bias_curve=curves, **out)
