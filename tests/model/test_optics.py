"""Tests for vdo.model.optics: each MTF against a numerical transform of its point-spread function,
the Gaussian fit of the Airy core by least squares, and the circle of confusion against the depth
of field of vdo.physics.checks (a formula written independently)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import optimize
from scipy.special import j1

from vdo.model.optics import (AIRY_GAUSS, DEFAULT_F_NUMBER, OpticsBlur, circle_of_confusion, defocus_mtf,
                              diffraction_mtf, gaussian_mtf, optics_blur, working_f_number)
from vdo.physics.checks import depth_of_field

GRID = 1024            # samples per side of the numerical transforms
MTF_TOL = 5e-3         # numerical MTF vs closed form: discretisation of the PSF/pupil on GRID
CELL_BLUR_TOL = 2e-3      # the sampled Gaussian kernel against the continuous one (measured ~4e-4)


def _radial_mtf(psf: np.ndarray, step: float, q_max: float):
    """(q, |FFT(psf)| / FFT(psf)(0)) along the first axis at the transform's own frequencies
    0 <= q <= q_max (cycles per unit)."""
    otf = np.abs(np.fft.fft2(np.fft.ifftshift(psf)))
    otf /= otf[0, 0]
    freqs = np.fft.fftfreq(psf.shape[0], d=step)
    keep = (freqs >= 0) & (freqs <= q_max)
    return freqs[keep], otf[0, keep]


def test_diffraction_mtf_is_the_pupils_autocorrelation():
    # The OTF of an incoherent aberration-free system is the autocorrelation of the pupil; with
    # the pupil of radius 1/(2 λ N) in frequency units, its cut-off is 1/(λN). Numerically: the
    # pupil's indicator on a grid, autocorrelated by FFT.
    lam_n = 1.0
    step = 4.0 / GRID / lam_n                     # frequency step, the grid spans ±2/(λN)
    f = (np.arange(GRID) - GRID // 2) * step
    pupil = (np.hypot(f[:, None], f[None, :]) <= 0.5 / lam_n).astype(float)
    auto = np.real(np.fft.ifft2(np.abs(np.fft.fft2(pupil)) ** 2))
    auto = np.fft.fftshift(auto) / auto.max()
    q = f[GRID // 2:GRID // 2 + int(1.0 / lam_n / step)]
    numeric = auto[GRID // 2, GRID // 2:GRID // 2 + q.size]
    assert np.max(np.abs(numeric - diffraction_mtf(q, 1.0, lam_n))) < MTF_TOL


def test_defocus_mtf_is_the_transform_of_a_disc():
    c = 1.0
    step = 16.0 * c / GRID
    x = (np.arange(GRID) - GRID // 2) * step
    r = np.hypot(x[:, None], x[None, :])
    sub = 8                                   # area-weighted edge: supersample the disc's rim
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    disc = np.zeros_like(r)
    for dy in offs:
        for dx in offs:
            disc += np.hypot(x[:, None] + dx * step, x[None, :] + dy * step) <= 0.5 * c
    q, numeric = _radial_mtf(disc, step, 3.0 / c)
    numeric = numeric / np.abs(np.sinc(q * step))     # the rim's supersampling box of one step
    assert np.max(np.abs(numeric - np.abs(defocus_mtf(q, c)))) < MTF_TOL
    # and the disc's std per axis is c / 4
    std = np.sqrt(np.sum(disc * x[None, :] ** 2) / disc.sum())
    assert std == pytest.approx(c / 4, rel=MTF_TOL)


def test_airy_core_is_fit_by_a_gaussian_of_042_lambda_n():
    # Least-squares fit of a Gaussian to the Airy intensity (2 J1(πr/λN) / (πr/λN))² within its
    # first zero (1.22 λN): the fitted σ is 0.42 λN to two digits.
    r = np.linspace(1e-6, 1.22, 400)
    x = np.pi * r
    airy = (2 * j1(x) / x) ** 2
    (sigma,), _ = optimize.curve_fit(lambda r, s: np.exp(-r * r / (2 * s * s)), r, airy, p0=[0.4])
    assert sigma == pytest.approx(AIRY_GAUSS, abs=0.01)


def test_gaussian_mtf_is_the_transform_of_a_sampled_gaussian():
    sigma = 1.0
    step = 16.0 * sigma / GRID * 4
    x = (np.arange(GRID) - GRID // 2) * step
    psf = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * sigma ** 2))
    q, numeric = _radial_mtf(psf, step, 0.6 / sigma)
    assert np.max(np.abs(numeric - gaussian_mtf(q, sigma))) < MTF_TOL


@pytest.mark.parametrize("focal,n,focus", [(0.035, 8.0, 1.2), (0.012, 4.0, 0.6)])
def test_circle_of_confusion_equals_the_limit_at_the_depth_of_field(focal, n, focus):
    coc = 8.6e-6
    near, far = depth_of_field(focal, n, focus, coc)
    assert circle_of_confusion(focal, n, focus, near) == pytest.approx(coc, rel=1e-9)
    assert circle_of_confusion(focal, n, focus, far) == pytest.approx(coc, rel=1e-9)
    assert circle_of_confusion(focal, n, focus, focus) == 0.0


def test_optics_blur_in_pixels():
    pitch, focal, focus = 4.3e-6, 0.035, 1.0
    blur = optics_blur(pitch, focal, 8.0, focus, depth=1.1, wavelength=0.55e-6)
    n_w = working_f_number(8.0, focal, focus)
    assert n_w == pytest.approx(8.0 * focus / (focus - focal))     # N (1 + m), m = f / (s - f)
    assert blur.airy_px == pytest.approx(0.55e-6 * n_w / pitch)
    assert blur.defocus_px == pytest.approx(circle_of_confusion(focal, 8.0, focus, 1.1) / pitch)
    assert blur.sigma_px == pytest.approx(np.hypot(0.42 * blur.airy_px, blur.defocus_px / 4))
    assumed = optics_blur(pitch, focal, None, None)
    assert assumed.assumed and assumed.defocus_px == 0.0 and assumed.f_number == 8.0
    # the product MTF: zero at and beyond the diffraction cut-off
    assert float(blur.mtf(1.0 / blur.airy_px)) == pytest.approx(0.0, abs=1e-12)
    assert float(OpticsBlur().mtf(0.7)) == 1.0


def test_renders_blur_by_the_diffraction_of_the_cameras_f_number():
    # The lens's Gaussian is the Airy core's, 0.42 λ N_w / p pixels; a camera without f_number
    # gets the assumed f/8 in focus; no spec, no blur.
    from types import SimpleNamespace

    from vdo.render import lens_sigma_px

    camera = SimpleNamespace(pixel_size=3.45e-6, focal_length=0.05)
    n_w = 11.0 * (1 + 0.05 / (1.5 - 0.05))
    assert lens_sigma_px(camera, SimpleNamespace(f_number=11.0, focus_distance=1.5)) == pytest.approx(
        AIRY_GAUSS * 0.55e-6 * n_w / 3.45e-6, rel=1e-12)
    assert lens_sigma_px(camera, SimpleNamespace(f_number=None, focus_distance=None)) == pytest.approx(
        AIRY_GAUSS * 0.55e-6 * DEFAULT_F_NUMBER / 3.45e-6, rel=1e-12)
    assert lens_sigma_px(camera, None) == 0.0


@pytest.mark.parametrize("frequency", [0.2, 0.35, 0.75, 0.9])
def test_the_lens_blurs_before_the_pixels_integrate(frequency):
    """A grating of `frequency` cycles per pixel on the cells of the pixels (2 x 2 a pixel):
    `cell_blur` on both axes gives each pixel the grating blurred by the lens's Gaussian at its
    own frequency, then averaged over the pixel's cells, in closed form
    exp(-2 π² σ² f²) sin(π f) / (n sin(π f / n)) sin(2 π f k + φ); above the pixels' Nyquist
    frequency (0.75, 0.9; the cells carry gratings below 1 cycle per pixel) that is the aliased
    grating a lens leaves, far below what a blur of the sampled image would leave,
    exp(-2 π² σ² f_alias²) at the folded frequency."""
    from vdo.render import cell_blur

    n, sigma, phase = 2, 0.5, 0.3
    x = (np.arange(400 * n) + 0.5) / n - 0.5                     # cell centres, pixel units
    cells = np.broadcast_to(np.sin(2 * np.pi * frequency * x + phase), (8 * n, len(x)))
    out = cell_blur(cell_blur(cells, sigma, n, axis=1), sigma, n, axis=0)
    k = np.arange(400)
    gain = np.exp(-2 * np.pi ** 2 * sigma ** 2 * frequency ** 2) * np.sin(np.pi * frequency) \
        / (n * np.sin(np.pi * frequency / n))
    expected = gain * np.sin(2 * np.pi * frequency * k + phase)
    assert out.shape == (8, 400)
    assert np.abs(out[4, 20:-20] - expected[20:-20]).max() < CELL_BLUR_TOL
    if frequency > 0.5:
        folded = abs(frequency - round(frequency))
        after = np.sinc(frequency) * np.exp(-2 * np.pi ** 2 * sigma ** 2 * folded ** 2)
        assert abs(gain) < abs(after) / 3



CELL_BLUR_SCIPY_TOL = 1e-6       # float32 sums in another order (measured 2.4e-7)


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("shape, sigma, n, axis", [((40, 60), 0.5, 2, 0), ((40, 60), 0.5, 2, 1),
                                                   ((6, 10), 1.3, 2, 1), ((2, 4), 1.3, 2, 0),
                                                   ((30, 33), 0.3, 3, 0), ((4, 6, 8), 2.0, 2, 2)])
def test_cell_blur_is_scipys_gaussian_then_the_pixels_mean(shape, sigma, n, axis, threads, monkeypatch):
    """`cell_blur` computes only the pixels: it equals SciPy's `gaussian_filter1d` of the cells
    (std n sigma cells, "nearest" beyond the ends) followed by each pixel's mean of its n cells,
    in the middle and at both ends, also where the kernel is longer than the image; on one
    thread and cut into strips for three (every image counted as large enough)."""
    from scipy import ndimage

    from vdo.core import backend
    from vdo.render import cell_blur
    from vdo.rendering import scene

    monkeypatch.setattr(backend, "cpu_threads", lambda: threads)
    monkeypatch.setattr(scene, "BLUR_THREAD_CELLS", 1)

    cells = np.random.default_rng(7).random(shape).astype(np.float32)
    blurred = ndimage.gaussian_filter1d(cells.astype(float), n * sigma, axis=axis, mode="nearest")
    expected = np.mean([np.take(blurred, np.arange(m, shape[axis], n), axis=axis) for m in range(n)], axis=0)
    out = cell_blur(cells, sigma, n, axis)
    assert out.dtype == np.float32 and out.shape == expected.shape
    assert np.abs(out - expected).max() < CELL_BLUR_SCIPY_TOL


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("h, W, sigma, n", [(5, 40, 0.5, 2), (3, 2, 1.3, 2), (9, 11, 0.7, 3), (4, 30, 2.5, 2)])
def test_part_blur_is_the_cell_blur_of_the_laid_out_cells(h, W, sigma, n, threads, monkeypatch):
    """`part_blur` (the DIC mode's rows: a pixel's n x n cells as n² separate images) equals
    `cell_blur` along the rows of the cells laid out (pixel row y's cell row j at n y + j, cell i
    of pixel x at n x + i), borders and kernels longer than the row included."""
    from vdo.core import backend
    from vdo.render import cell_blur
    from vdo.rendering import scene

    monkeypatch.setattr(backend, "cpu_threads", lambda: threads)
    monkeypatch.setattr(scene, "BLUR_THREAD_CELLS", 1)
    rng = np.random.default_rng(3)
    parts = [rng.random((h, W)).astype(np.float32) for _ in range(n * n)]
    cells = np.empty((h, n, W, n), dtype=np.float32)
    for k, part in enumerate(parts):
        cells[:, k % n, :, k // n] = part
    expected = cell_blur(cells.reshape(h * n, W * n), sigma, n, axis=1)
    out = scene.part_blur(lambda k, rows: parts[k][rows], (h, W), sigma, n)
    assert out.dtype == np.float32 and out.shape == expected.shape
    assert np.abs(out - expected).max() < CELL_BLUR_SCIPY_TOL
