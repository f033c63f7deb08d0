"""σ_measured against correlation on synthesised images, over many patterns: the validation of
`vdo.model.interpolant.correlation_error` (the interpolation bias, its scatter and the noise through
the interpolant) for sharp-edged dots, fine dots and a photograph-like texture, cubic and quintic
B-splines and Keys' bicubic convolution.

Images. A pattern tile of `SUB` texels per pixel is moved by whole texels (sub-pixel shifts
d = j / SUB px along x) with its band-limited interpolant (an FFT phase ramp: the model's
texel_filter = "ideal"), blurred by the optics' MTF (`vdo.model.optics.OpticsBlur`, applied in the
Fourier domain, exact for the periodic tile), box-averaged over SUB x SUB texels per pixel, and
given independent Gaussian noise in the reference and the deformed image. A case with
`texels_per_px` (coarse texels, as a rendered texture at the cameras' own pixels) is imaged as
Mitsuba's bilinear bitmap is: the tile's N texels interpolated bilinearly (the triangle kernel,
sinc² in Fourier, its images kept over `TEXEL_IMAGES` periods), integrated over M = round(N / T)
box pixels of side N / M texels (sinc), moved by the same d = j / SUB px (a phase ramp) and
sampled: every term exact in Fourier for the periodic tile, the texel-to-pixel alignment
sweeping across the tile unless N / M is whole.

Correlation. Gauss-Newton for a translation on square subsets, the reference read at its pixel
centres with its spline gradient, the deformed image interpolated by `vdo.dic.images.SplineImage`
(the interpolant `vdo.dic.correlate` runs).

Each seed is a new pattern (and new noise). The measured RMS error over seeds, subsets and shifts
is compared with the prediction averaged over the first PREDICTION_SEEDS patterns; the 95 %
interval of the ratio comes from resampling the seeds (bootstrap).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vdo.dic.images import SplineImage
from vdo.model.optics import OpticsBlur
from vdo.model.speckle import generate_pattern, normalise
from vdo.model.interpolant import correlation_error
from vdo.model.spline_response import INTERPOLANTS

SUB = 8                  # texels per pixel
HALF = 10                # subset half-width, px (21 x 21 pixels)
STRIDE = 11              # subset centres' spacing, px
ITERATIONS = 8           # Gauss-Newton steps (converged to < 1e-8 px for these shifts)
PREDICTION_SEEDS = 4     # patterns the prediction is averaged over
BOOTSTRAP = 2000         # resamples of the seeds for the 95 % interval
TEXEL_IMAGES = 4         # periods of the texels' spectrum kept for the coarse-texel images (the
                         # bilinear kernel's sinc² times the pixel's sinc: the 5th period's
                         # weight is below 1e-3 of the base band's)


@dataclass(frozen=True)
class BiasCase:
    """One validation case: the pattern ("dots" sharp-edged, "photo" photograph-like, or
    "dots-gaussian", the sharp dots' spectrum with random phases: `gaussian_like`), its dot
    diameter in pixels, the interpolant, the optics' λN/p (0: none) and the noise in pattern stds;
    `texels_per_px` None: SUB texels per pixel with the band-limited texel interpolant, else that
    many bilinear texels per pixel (a rendered texture; may be fractional) along x, and
    `texels_per_px_y` along y when it differs (an oblique view's footprint; `dot_px` is along x);
    `strokes` as `generate_pattern`'s (per 512 x 512 texels)."""

    name: str
    pattern: str
    dot_px: float
    interpolant: str
    airy_px: float = 0.0
    noise: float = 0.0
    texels_per_px: float | None = None
    strokes: int = 0
    texels_per_px_y: float | None = None

    @property
    def texels(self) -> float:
        """Texels per pixel."""
        return SUB if self.texels_per_px is None else self.texels_per_px

    @property
    def texels_y(self) -> float:
        """Texels per pixel along y."""
        return self.texels if self.texels_per_px_y is None else self.texels_per_px_y

    def tile(self, pixels: int) -> int:
        """Texels per side of a tile imaged onto at least about `pixels` pixels per axis."""
        return int(round(pixels * max(self.texels, self.texels_y)))

    def image_px(self, tile: int) -> tuple[int, int]:
        """(M_x, M_y): the whole pixels the tile of `tile` texels is imaged onto."""
        if self.texels_per_px is None:
            return tile // SUB, tile // SUB
        return int(round(tile / self.texels)), int(round(tile / self.texels_y))


def photo_like_pattern(size: int, dot_texels: float, seed: int) -> np.ndarray:
    """A photograph-like speckle tile in [0, 1] (periodic): sprayed droplets of log-normal
    diameters (median `dot_texels`, σ_log 0.35) of varying darkness (0.55-1), ink spread by a
    Gaussian of 0.12 dot, under a smooth shading of ±8 % (a 1/k² random field), plus film grain
    (white, 2 % of the range). Not a binary pattern: what a camera photographs of a painted part."""
    rng = np.random.default_rng(seed)
    n = size
    ink = np.zeros((n, n))
    count = int(0.9 * n * n / (np.pi * (0.5 * dot_texels) ** 2))
    diam = dot_texels * np.exp(0.35 * rng.standard_normal(count))
    cx, cy = rng.uniform(0, n, count), rng.uniform(0, n, count)
    dark = rng.uniform(0.55, 1.0, count)
    for d, u, v, a in zip(diam, cx, cy, dark):
        r = 0.5 * d
        lo_x, hi_x = int(np.floor(u - r - 1)), int(np.ceil(u + r + 1))
        lo_y, hi_y = int(np.floor(v - r - 1)), int(np.ceil(v + r + 1))
        xs = np.arange(lo_x, hi_x + 1)
        ys = np.arange(lo_y, hi_y + 1)
        dist = np.hypot(xs[None, :] + 0.5 - u, ys[:, None] + 0.5 - v)
        cover = np.clip(r + 0.5 - dist, 0.0, 1.0) * a
        block = np.ix_(ys % n, xs % n)
        ink[block] = np.maximum(ink[block], cover)
    k = np.hypot(np.fft.fftfreq(n)[None, :], np.fft.fftfreq(n)[:, None])
    spread = np.exp(-2 * np.pi ** 2 * (0.12 * dot_texels) ** 2 * k ** 2)
    ink = np.real(np.fft.ifft2(np.fft.fft2(ink) * spread))
    shade = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n)))
                                 / np.maximum(k * n, 1.0) ** 2))
    shade = 1.0 + 0.08 * shade / np.abs(shade).max()
    img = (1.0 - 0.9 * ink) * shade + 0.02 * rng.standard_normal((n, n))
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def gaussian_like(f: np.ndarray, seed: int) -> np.ndarray:
    """The periodic tile `f` with its Fourier amplitudes kept and its phases drawn anew (uniform,
    Hermitian): a Gaussian field with the power spectrum of `f`, which is what the scatter term of
    `correlation_error` assumes (its fourth moments are Gaussian); normalised."""
    noise = np.fft.fft2(np.random.default_rng([seed, 7]).standard_normal(f.shape))
    g = np.fft.ifft2(np.abs(np.fft.fft2(f - f.mean())) * noise / np.maximum(np.abs(noise), 1e-300))
    return normalise(np.real(g).astype(np.float32))


def case_pattern(case: BiasCase, tile: int, seed: int) -> np.ndarray:
    """The normalised pattern tile of a case for a seed (`tile` texels per side)."""
    if case.pattern == "photo":
        return normalise(photo_like_pattern(tile, case.dot_px * case.texels, seed))
    strokes = int(round(case.strokes * tile ** 2 / 512 ** 2))
    dots = normalise(generate_pattern(tile, 1.0, case.dot_px * case.texels, 0.5, strokes, seed=seed))
    return gaussian_like(dots, seed) if case.pattern == "dots-gaussian" else dots


def case_images(f: np.ndarray, case: BiasCase):
    """image(s1, s2): the case's pixel image of the tile f moved by (s1, s2) / SUB px."""
    if case.texels_per_px is not None:
        return _bilinear_images(f, case)
    F = np.fft.fft2(f)
    k = np.fft.fftfreq(f.shape[0])
    if case.airy_px > 0:
        F = F * OpticsBlur(airy_px=case.airy_px).mtf(np.hypot(k[None, :], k[:, None]) * SUB)

    def image(s1, s2):
        g = np.real(np.fft.ifft2(F * np.exp(-2j * np.pi * (k[None, :] * s1 + k[:, None] * s2))))
        n = f.shape[0] // SUB
        return g.reshape(n, SUB, n, SUB).mean(axis=(1, 3))
    return image


def _fold(x: np.ndarray, px: np.ndarray, py: np.ndarray, mx: int, my: int) -> np.ndarray:
    """Σ over the columns of x whose frequency index is px (0 .. mx - 1) and the rows whose index
    is py (0 .. my - 1): an (my, mx) spectrum."""
    rows = np.zeros((my, x.shape[1]), dtype=x.dtype)
    np.add.at(rows, py, x)
    out = np.zeros((my, mx), dtype=x.dtype)
    np.add.at(out.T, px, rows.T)
    return out


def _bilinear_images(f: np.ndarray, case: BiasCase):
    """The bilinear texels' box-pixel image (module docstring): with c_j the tile's DFT / N² and
    j over TEXEL_IMAGES periods, pixel frequency p ≡ j (mod M_a) per axis carries
    Σ_j c_(j mod N) sinc²(j / N) sinc(j_a / M_a) MTF(|q|) exp(-2πi Σ_a j_a s_a / M_a)
    (q_a = j_a / M_a cycles per pixel, s in px)."""
    n = f.shape[0]
    mx, my = case.image_px(n)
    j = np.fft.fftfreq(n * TEXEL_IMAGES, 1.0 / (n * TEXEL_IMAGES))        # cycles per tile
    texel = np.sinc(j / n) ** 2
    idx = (j % n).astype(int)
    F = ((np.fft.fft2(f) / n ** 2)[np.ix_(idx, idx)] * (texel * np.sinc(j / my))[:, None]
         * (texel * np.sinc(j / mx))[None, :])
    if case.airy_px > 0:
        F = F * OpticsBlur(airy_px=case.airy_px).mtf(np.hypot(j[None, :] / mx, j[:, None] / my))
    px, py = (j % mx).astype(int), (j % my).astype(int)

    def image(s1, s2):
        moved = F * np.exp(-2j * np.pi * (j[None, :] * s1 / mx + j[:, None] * s2 / my) / SUB)
        return np.real(np.fft.ifft2(_fold(moved, px, py, mx, my))) * mx * my
    return image


def measure(f: np.ndarray, case: BiasCase, shifts, rng) -> np.ndarray:
    """Errors (n, 2) px of the subset correlations of the pattern f over `shifts` (texels)."""
    order = INTERPOLANTS[case.interpolant]
    image = case_images(f, case)
    ref = image(0, 0)
    rows, cols = ref.shape
    offsets = np.stack(np.meshgrid(np.arange(-HALF, HALF + 1), np.arange(-HALF, HALF + 1)), -1)
    errors = []
    for s1, s2 in shifts:
        u = np.array([s1, s2], dtype=float) / SUB
        r_img = ref + case.noise * rng.standard_normal(ref.shape)
        d_img = image(s1, s2) + case.noise * rng.standard_normal(ref.shape)
        reference, deformed = SplineImage(r_img, order=order), SplineImage(d_img, order=order)
        for cx in range(HALF + 2, cols - HALF - 2, STRIDE):
            for cy in range(HALF + 2, rows - HALF - 2, STRIDE):
                x = (offsets + [cx, cy]).reshape(-1, 2).astype(float)
                value, J = reference.value_and_gradient(x)
                est = u.copy()
                for _ in range(ITERATIONS):
                    est -= np.linalg.solve(J.T @ J, J.T @ (deformed(x + est) - value))
                errors.append(est - u)
    return np.array(errors)


def predict(f: np.ndarray, case: BiasCase) -> tuple[np.ndarray, np.ndarray]:
    """(σ_measured (2,) px, the bound σ (2,) px) for the case's subsets on pattern f, RMS over
    the shifts d = j / SUB along x."""
    optics = [OpticsBlur(airy_px=case.airy_px)] if case.airy_px > 0 else None
    n = f.shape[0]
    mx, my = case.image_px(n)
    model = correlation_error(f, 1.0, np.diag([n / mx, n / my])[None],          # in texels
                              order=INTERPOLANTS[case.interpolant], optics=optics,
                              texel_filter="ideal" if case.texels_per_px is None else "bilinear",
                              phases=(np.arange(SUB) / SUB, [0.0]))
    p = (2 * HALF + 1) ** 2
    measured = np.sqrt(np.diagonal(model.covariance(case.noise, p)[0]))
    bound = np.sqrt(case.noise ** 2 * np.diagonal(model.bound[0]) / p)
    return measured, bound


@dataclass(frozen=True)
class BiasRow:
    """One case's result: measured and predicted σ (px, per axis x, y), their ratio with its 95 %
    interval over seeds, and the bound's ratio (measured / (√2 bound) when noisy; None without
    noise)."""

    case: BiasCase
    seeds: int
    samples: int
    measured_px: np.ndarray
    predicted_px: np.ndarray
    ratio: np.ndarray
    ratio_95: np.ndarray          # (2, 2): [axis][low, high]
    bound_ratio: np.ndarray | None


def run_case(case: BiasCase, seeds: int, pixels: int = 64, first_seed: int = 0) -> BiasRow:
    """The case over `seeds` patterns of images of `pixels` x `pixels` (module docstring)."""
    tile = case.tile(pixels)
    shifts = [(j, 0) for j in range(SUB)]
    per_seed, preds, bounds = [], [], []
    for s in range(first_seed, first_seed + seeds):
        f = case_pattern(case, tile, s)
        per_seed.append(np.mean(measure(f, case, shifts, np.random.default_rng([s, 1])) ** 2, axis=0))
        if len(preds) < PREDICTION_SEEDS:
            m, b = predict(f, case)
            preds.append(m ** 2)
            bounds.append(b ** 2)
    ms = np.array(per_seed)                                                   # (seeds, 2)
    predicted = np.sqrt(np.mean(preds, axis=0))
    measured = np.sqrt(ms.mean(axis=0))
    rng = np.random.default_rng(12345)
    boot = ms[rng.integers(0, seeds, size=(BOOTSTRAP, seeds))].mean(axis=1)    # (B, 2)
    low, high = np.sqrt(np.percentile(boot, [2.5, 97.5], axis=0)) / predicted
    bound = np.sqrt(np.mean(bounds, axis=0))
    n = int(np.prod([(m - 2 * HALF - 4 + STRIDE - 1) // STRIDE for m in case.image_px(tile)])) \
        * SUB * seeds
    return BiasRow(case, seeds, n, measured, predicted, measured / predicted,
                   np.stack([low, high], axis=1),
                   measured / (np.sqrt(2.0) * bound) if case.noise > 0 else None)


DEFAULT_CASES = (
    BiasCase("sharp 4 px dots, cubic", "dots", 4.0, "cubic", 0.0, 0.02),
    BiasCase("sharp 4 px dots, quintic", "dots", 4.0, "quintic", 0.0, 0.02),
    BiasCase("fine 1.5 px dots, cubic", "dots", 1.5, "cubic", 0.0, 0.02),
    BiasCase("fine 2 px dots, quintic", "dots", 2.0, "quintic", 0.0, 0.02),
    BiasCase("4 px dots at f/8 (λN/p = 1.28), cubic", "dots", 4.0, "cubic", 1.28, 0.02),
    BiasCase("photo-like 4 px, cubic", "photo", 4.0, "cubic", 0.0, 0.02),
    BiasCase("photo-like 4 px, quintic", "photo", 4.0, "quintic", 0.0, 0.02),
    BiasCase("sharp 4 px dots, keys", "dots", 4.0, "keys", 0.0, 0.02),
    BiasCase("fine 2 px dots, keys", "dots", 2.0, "keys", 0.0, 0.02),
    BiasCase("4 px dots at f/8 (λN/p = 1.28), keys", "dots", 4.0, "keys", 1.28, 0.02),
    BiasCase("photo-like 4 px, keys", "photo", 4.0, "keys", 0.0, 0.02),
    # coarse bilinear texels, as a rendered texture at the cameras' own pixels
    BiasCase("4 px dots and strokes, 2 texels/px, cubic", "dots", 4.0, "cubic", 0.0, 0.02, 2.0, 3),
    BiasCase("3.6 px dots, 2.2 texels/px, cubic", "dots", 3.6, "cubic", 0.0, 0.02, 2.2),
    BiasCase("5 px dots, 1.6 texels/px, cubic", "dots", 5.0, "cubic", 0.0, 0.02, 1.6),
    BiasCase("2.5 px dots, 2 texels/px, quintic", "dots", 2.5, "quintic", 0.0, 0.02, 2.0),
    BiasCase("2 px dots, 3 texels/px, cubic", "dots", 2.0, "cubic", 0.0, 0.02, 3.0),
    BiasCase("4 px dots, 2 texels/px, keys", "dots", 4.0, "keys", 0.0, 0.02, 2.0),
    BiasCase("4 px dots, 2 texels/px, f/8 (λN/p = 1.28), cubic", "dots", 4.0, "cubic", 1.28, 0.02, 2.0),
    # an oblique view: pixels three times longer on the surface along one image axis
    BiasCase("4 px dots, 2.5 x 7.5 texels/px (oblique, 3:1), cubic", "dots", 4.0, "cubic", 0.0, 0.02,
             2.5, 0, 7.5),
    BiasCase("1.3 px dots, 7.5 x 2.5 texels/px (oblique, 3:1), cubic", "dots", 1.33, "cubic", 0.0,
             0.02, 7.5, 0, 2.5),
)
