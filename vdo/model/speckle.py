"""Speckle patterns and their gradient energy under Gaussian blur (what an interpolating
correlation measures on them: `vdo.model.interpolant`).

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

from vdo.core.memo import Memo, digest

__all__ = [
    "GradientEnergyTable",
    "generate_pattern",
    "load_pattern",
    "normalise",
    "gradient_energy_table",
    "g_iso_lookup",
    "g_aniso_lookup",
    "pixel_averaged_std",
    "blocked_spectrum",
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


def blocked_spectrum(pattern_normalised, texel_m: float, texel_filter: bool, block: int | None = None):
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
    w, ku, kv = blocked_spectrum(pattern_normalised, texel_m, texel_filter=True)
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


TABLE_MEMO_SIZE = 16      # gradient-energy tables kept per process (~0.15 MB each at n = 96)
PATTERN_MEMO_SIZE = 8     # generated tiles kept per process (4 MB each at 1024 texels)
_TABLES = Memo(TABLE_MEMO_SIZE)
_PATTERNS = Memo(PATTERN_MEMO_SIZE)


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
    and G over ~n²/2 × 500 Bessel terms (G(i, j) and G(j, i) share them): ~0.2 s, so the last
    `TABLE_MEMO_SIZE` tables are kept per process by the tile's values and the arguments.
    """
    f = np.asarray(pattern_normalised, dtype=np.float64)
    if f.ndim != 2 or min(f.shape) < 8:
        raise ValueError(f"pattern_normalised: expected a 2-D image at least 8x8, got shape {f.shape}")
    if not np.all(np.isfinite(f)):
        raise ValueError("pattern_normalised: expected finite values")
    h = _positive_real("texel_m", texel_m)
    n = _integer("n", n, 8)
    l_min = None if l_min is None else _positive_real("l_min", l_min)
    l_max = None if l_max is None else _positive_real("l_max", l_max)
    return _TABLES.get_or((digest(f), h, n, l_min, l_max), lambda: _table(f, h, n, l_min, l_max))


def _table(f: np.ndarray, h: float, n: int, l_min: float | None,
           l_max: float | None) -> GradientEnergyTable:
    """`gradient_energy_table` of a checked tile f̂ with texel h [m]."""
    k2, w, p = _radial_spectrum(f, h)
    if w.size == 0:
        raise ValueError("pattern_normalised: expected a non-constant image (no gradient energy)")
    extent = min(f.shape) * h
    lo = 0.25 * h if l_min is None else l_min
    hi = min(130.0 * _acf_half_width(k2, p, extent, h), 0.5 * extent) if l_max is None else l_max
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
    """The [0, 1] pattern tile of a `vdo.config.rig.SpeckleSpec`: the user's image when it names one,
    else a generated tile of `tile_texels` texels of `texel` metres (read-only: the last
    `PATTERN_MEMO_SIZE` generated tiles are kept per process, ~0.1 s each to draw at 1024²)."""
    if spec.image is not None:
        return load_pattern(spec.image)
    args = (spec.tile_texels, spec.texel, spec.dot_diameter, spec.coverage, spec.strokes, spec.seed)
    return _PATTERNS.get_or(args, lambda: _read_only(generate_pattern(*args)))


def _read_only(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a
