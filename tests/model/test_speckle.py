"""Tests for vdo.model.speckle: pattern generation, loading, and the gradient-energy tables.

The energies are checked against direct measurements on blurred images: the normalised pattern is
blurred in the spatial domain (scipy.ndimage.gaussian_filter, mode="wrap") and differentiated
spectrally (multiply the FFT by 2πik). A spectral derivative is exact for a periodic sampled image;
central differences have the transfer function sin(2πkh)/h instead of 2πk, which underestimates the
energy by about (2πkh)²/3: 13 % at a blur of 1 texel, still 0.5 % at 10 texels, so they are only
used as a cross-check at large blur. Blurs below 1 texel are not compared: the sampled Gaussian
kernel of gaussian_filter is then no longer the continuous Gaussian of the formula (aliasing).
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image
from scipy import ndimage
from scipy.interpolate import RegularGridInterpolator

from vdo.model.interpolant import interpolation_error
from vdo.model.speckle import (GradientEnergyTable, g_aniso_lookup, g_iso_lookup, generate_pattern,
                               gradient_energy_table, load_pattern, normalise)

H = 1e-4  # texel [m]
N = 1024  # tile side [texels]
DOT = 8 * H  # dot diameter [m]


@pytest.fixture(scope="module")
def patterns():
    """Two independent normalised 50 %-coverage tiles with strokes, and their tables."""
    out = []
    for seed in (1, 2):
        f = normalise(generate_pattern(N, H, DOT, 0.5, 40, seed))
        out.append((f, gradient_energy_table(f, H)))
    return out


def _spectral_gradient(b: np.ndarray):
    """(∂b/∂x, ∂b/∂y) of a periodic image by FFT; x along axis 1, y along axis 0, texel H."""
    k = np.fft.fftfreq(b.shape[0], d=H)
    spec = np.fft.fft2(b)
    gx = np.fft.ifft2(spec * (2j * np.pi * k[None, :])).real
    gy = np.fft.ifft2(spec * (2j * np.pi * k[:, None])).real
    return gx, gy


def _direct_g_iso(f: np.ndarray, l: float) -> float:
    """½ <|∇(G_l ⋆ f)|²> measured on the blurred image [1/m²]."""
    gx, gy = _spectral_gradient(ndimage.gaussian_filter(f, l / H, mode="wrap", truncate=6.0))
    return 0.5 * float(np.mean(gx ** 2 + gy ** 2))


def _direct_g_aniso(f: np.ndarray, l_par: float, l_perp: float) -> float:
    """<(∂_e (G ⋆ f))²> with std l_par along e, l_perp across, averaged over e = x and e = y."""
    bx = ndimage.gaussian_filter(f, (l_perp / H, l_par / H), mode="wrap", truncate=6.0)
    by = ndimage.gaussian_filter(f, (l_par / H, l_perp / H), mode="wrap", truncate=6.0)
    gx, _ = _spectral_gradient(bx)
    _, gy = _spectral_gradient(by)
    return 0.5 * float(np.mean(gx ** 2) + np.mean(gy ** 2))


def _grid_index(table: GradientEnergyTable, l: float) -> int:
    return int(np.argmin(np.abs(np.log(table.log_l / l))))


# --------------------------------------------------------------------------------------------
# Pattern generation
# --------------------------------------------------------------------------------------------
def test_pattern_range_dtype_and_determinism():
    a = generate_pattern(256, H, 5 * H, 0.5, 10, 7)
    b = generate_pattern(256, H, 5 * H, 0.5, 10, 7)
    c = generate_pattern(256, H, 5 * H, 0.5, 10, 8)
    assert a.shape == (256, 256) and a.dtype == np.float32
    assert a.min() >= 0.0 and a.max() <= 1.0
    assert np.array_equal(a, b)
    assert np.mean(np.abs(a - c) > 0.5) > 0.3  # independent tiles differ at about half the texels
    # anti-aliased: edge texels take intermediate values
    assert np.mean((a > 0.05) & (a < 0.95)) > 0.05


@pytest.mark.parametrize("coverage, strokes", [(0.2, 0), (0.5, 0), (0.7, 0), (0.5, 30), (0.3, 60)])
def test_coverage(coverage, strokes):
    p = generate_pattern(512, H, 6 * H, coverage, strokes, 3)
    assert abs(float(np.mean(1.0 - p)) - coverage) < 0.01


@pytest.mark.parametrize("dot_texels", [3.0, 6.0, 12.3])
def test_dot_diameter(dot_texels):
    """Isolated dots (low coverage, no strokes) have the configured equivalent diameter."""
    p = generate_pattern(1024, H, dot_texels * H, 0.03, 0, 11)
    black = 1.0 - p.astype(np.float64)
    labels, count = ndimage.label(black > 0, structure=np.ones((3, 3)))
    index = np.arange(1, count + 1)
    texels = ndimage.sum_labels(np.ones_like(black), labels, index)
    area = ndimage.sum_labels(black, labels, index)  # black area incl. anti-aliased edge [texel²]
    core = ndimage.sum_labels(black > 0.5, labels, index)  # texels at least half black
    on_edge = np.zeros(count + 1, dtype=bool)
    for edge in (labels[0], labels[-1], labels[:, 0], labels[:, -1]):
        on_edge[edge] = True
    single = (texels < 1.3 * np.median(texels)) & ~on_edge[1:]  # merged dots are larger
    assert single.sum() > 100
    d_area = np.sqrt(4.0 * area[single] / np.pi).mean() * H
    d_core = np.sqrt(4.0 * core[single] / np.pi).mean() * H
    assert d_area == pytest.approx(dot_texels * H, rel=0.05)
    assert d_core == pytest.approx(dot_texels * H, rel=0.05)


def test_seamless():
    """The difference across the wrap seam is like that between any two neighbouring rows/columns."""
    p = generate_pattern(512, H, 6 * H, 0.5, 40, 5).astype(np.float64)
    for q in (p, p.T):
        steps = np.mean((q[:, 1:] - q[:, :-1]) ** 2, axis=0)  # per column pair, interior
        seam = np.mean((q[:, 0] - q[:, -1]) ** 2)
        assert steps.min() <= seam <= steps.max()
        assert abs(seam - steps.mean()) < 4.0 * steps.std()
        # an unrelated column (what a non-periodic tile has at its edge) is far off
        assert np.mean((q[:, 0] - q[:, 256]) ** 2) > steps.max() * 2
    # the 2x2 tiling has the same local gradient energy at its seams as elsewhere
    t = np.tile(p, (2, 2))
    gx = np.diff(t, axis=1) ** 2
    seam_cols = gx[:, [511]].mean()
    interior = gx[:, 100:400].mean(axis=0)
    assert interior.min() <= seam_cols <= interior.max()


@pytest.mark.parametrize("kwargs, name", [
    (dict(size_px=0), "size_px"),
    (dict(size_px=64.5), "size_px"),
    (dict(texel_m=0.0), "texel_m"),
    (dict(texel_m=-1e-4), "texel_m"),
    (dict(dot_diameter_m=2 * H), "dot_diameter_m"),
    (dict(dot_diameter_m=-1.0), "dot_diameter_m"),
    (dict(dot_diameter_m=100 * H), "dot_diameter_m"),
    (dict(coverage=0.0), "coverage"),
    (dict(coverage=1.0), "coverage"),
    (dict(coverage=float("nan")), "coverage"),
    (dict(strokes=-1), "strokes"),
    (dict(seed=-3), "seed"),
])
def test_bad_arguments(kwargs, name):
    args = dict(size_px=128, texel_m=H, dot_diameter_m=5 * H, coverage=0.5, strokes=0, seed=0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        generate_pattern(**args)


def test_bad_table_arguments():
    f = normalise(np.random.default_rng(0).standard_normal((64, 64)))
    with pytest.raises(ValueError, match="texel_m"):
        gradient_energy_table(f, 0.0)
    with pytest.raises(ValueError, match="pattern_normalised"):
        gradient_energy_table(np.zeros(64), H)
    with pytest.raises(ValueError, match="l_max"):
        gradient_energy_table(f, H, l_min=1e-3, l_max=1e-4)
    with pytest.raises(ValueError, match="pattern"):
        normalise(np.ones((8, 8)))


# --------------------------------------------------------------------------------------------
# Loading and normalising
# --------------------------------------------------------------------------------------------
def test_load_pattern(tmp_path):
    rng = np.random.default_rng(0)
    grey8 = rng.integers(0, 256, (40, 50), dtype=np.uint8)
    Image.fromarray(grey8).save(tmp_path / "g8.png")
    np.testing.assert_allclose(load_pattern(tmp_path / "g8.png"), grey8 / 255.0, atol=1e-6)

    grey16 = rng.integers(0, 65536, (40, 50)).astype(np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")
    Image.fromarray(grey16).save(tmp_path / "g16.tif")
    for name in ("g16.png", "g16.tif"):
        got = load_pattern(tmp_path / name)
        assert got.dtype == np.float32 and got.shape == (40, 50)
        np.testing.assert_allclose(got, grey16 / 65535.0, atol=1e-6)

    rgb = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "c.png")
    luma = (0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]) / 255.0
    np.testing.assert_allclose(load_pattern(tmp_path / "c.png"), luma, atol=1e-6)

    Image.fromarray(grey8).save(tmp_path / "g.jpg", quality=95)
    assert np.abs(load_pattern(tmp_path / "g.jpg") - grey8 / 255.0).mean() < 0.05


def test_normalise():
    p = generate_pattern(128, H, 5 * H, 0.4, 5, 1)
    f = normalise(p)
    assert abs(f.mean()) < 1e-12 and f.std() == pytest.approx(1.0, abs=1e-12)


# --------------------------------------------------------------------------------------------
# Gradient-energy tables against direct measurements
# --------------------------------------------------------------------------------------------
def test_table_grid(patterns):
    _, table = patterns[0]
    assert 64 <= table.log_l.size <= 128
    assert table.log_l[0] == pytest.approx(H / 4)
    assert 30 * DOT < table.log_l[-1] < 70 * DOT  # about 50 dot diameters
    steps = np.diff(np.log(table.log_l))
    np.testing.assert_allclose(steps, steps[0], rtol=1e-9)
    assert np.all(np.diff(table.g_iso) < 0)  # more blur, less gradient energy


@pytest.mark.parametrize("texels", [1.0, 1.5, 2.0, 3.0, 5.0, 7.0, 10.0])
def test_g_iso_against_blurred_image(patterns, texels):
    f, table = patterns[0]
    i = _grid_index(table, texels * H)
    l = table.log_l[i]
    direct = _direct_g_iso(f, l)
    assert table.g_iso[i] == pytest.approx(direct, rel=0.02)
    # between grid points, through the log-log interpolation
    l_mid = texels * H * 1.03
    assert float(g_iso_lookup(table, l_mid)) == pytest.approx(_direct_g_iso(f, l_mid), rel=0.02)


@pytest.mark.parametrize("texels", [8.0, 12.0])
def test_g_iso_against_central_differences(patterns, texels):
    """Independent of any FFT: central differences, accurate to ~(2πkh)²/3 at large blur."""
    f, table = patterns[0]
    b = ndimage.gaussian_filter(f, texels, mode="wrap", truncate=6.0)
    gx = (np.roll(b, -1, axis=1) - np.roll(b, 1, axis=1)) / (2 * H)
    gy = (np.roll(b, -1, axis=0) - np.roll(b, 1, axis=0)) / (2 * H)
    direct = 0.5 * float(np.mean(gx ** 2 + gy ** 2))
    assert float(g_iso_lookup(table, texels * H)) == pytest.approx(direct, rel=0.02)


def test_g_aniso_diagonal_is_g_iso(patterns):
    _, table = patterns[0]
    np.testing.assert_allclose(np.diag(table.g_aniso), table.g_iso, rtol=1e-12)
    l = jnp.asarray(table.log_l[::7])
    np.testing.assert_allclose(g_aniso_lookup(table, l, l), g_iso_lookup(table, l), rtol=1e-9)
    # between grid points the bilinear cell also uses off-diagonal corners: equal to ~0.2 %
    l = l[:-1] * 1.03
    np.testing.assert_allclose(g_aniso_lookup(table, l, l), g_iso_lookup(table, l), rtol=5e-3)


@pytest.mark.parametrize("l_par, l_perp", [
    (2.0, 6.0), (6.0, 2.0), (1.5, 10.0), (10.0, 1.5), (3.0, 4.0), (4.0, 3.0), (1.2, 3.0)])
def test_g_aniso_against_blurred_image(patterns, l_par, l_perp):
    """G = <(∂_e f)²> (no factor ½) for blur l_par along e; both orders l_par < l_perp and >."""
    measured, predicted = [], []
    for f, table in patterns:
        i, j = _grid_index(table, l_par * H), _grid_index(table, l_perp * H)
        measured.append(_direct_g_aniso(f, table.log_l[i], table.log_l[j]))
        predicted.append(table.g_aniso[i, j])
    assert np.mean(predicted) == pytest.approx(np.mean(measured), rel=0.02)


def test_g_aniso_limits(patterns):
    """Blur along e lowers G more than the same blur across e; G decreases in both widths."""
    _, table = patterns[0]
    g = table.g_aniso
    i, j = 20, 50
    assert g[j, i] < g[i, j]
    assert np.all(np.diff(g, axis=0) < 0) and np.all(np.diff(g, axis=1) < 0)


# --------------------------------------------------------------------------------------------
# Lookups: jit, interpolation, gradients, clamping
# --------------------------------------------------------------------------------------------
def test_lookups_under_jit_match_numpy(patterns):
    _, table = patterns[0]
    rng = np.random.default_rng(4)
    lo, hi = table.log_l[0], table.log_l[-1]
    l = np.exp(rng.uniform(np.log(lo), np.log(hi), (3, 5)))
    lq = np.exp(rng.uniform(np.log(lo), np.log(hi), (3, 5)))
    iso = jax.jit(lambda x: g_iso_lookup(table, x))(jnp.asarray(l))
    ref = np.exp(np.interp(np.log(l), np.log(table.log_l), np.log(table.g_iso)))
    assert iso.shape == (3, 5)
    np.testing.assert_allclose(np.asarray(iso), ref, rtol=1e-10)

    aniso = jax.jit(g_aniso_lookup)(table, jnp.asarray(l), jnp.asarray(lq))  # table as a pytree
    axis = np.log(table.log_l)
    interp = RegularGridInterpolator((axis, axis), np.log(table.g_aniso))
    ref2 = np.exp(interp(np.stack([np.log(l), np.log(lq)], axis=-1)))
    np.testing.assert_allclose(np.asarray(aniso), ref2, rtol=1e-10)
    # broadcasting a scalar against an array
    assert g_aniso_lookup(table, l[0, 0], jnp.asarray(lq)).shape == (3, 5)


def test_lookup_gradients_match_finite_differences(patterns):
    _, table = patterns[0]
    for l in (0.7 * H, 2.3 * H, 17.0 * H):
        grad = float(jax.jit(jax.grad(lambda x: g_iso_lookup(table, x)))(l))
        step = l * 1e-7
        fd = float(g_iso_lookup(table, l + step) - g_iso_lookup(table, l - step)) / (2 * step)
        assert grad == pytest.approx(fd, rel=1e-5)
        assert grad < 0
        gp, gq = jax.grad(lambda a, b: g_aniso_lookup(table, a, b), argnums=(0, 1))(l, 3.1 * H)
        fdp = float(g_aniso_lookup(table, l + step, 3.1 * H) - g_aniso_lookup(table, l - step, 3.1 * H)) / (2 * step)
        assert float(gp) == pytest.approx(fdp, rel=1e-5)
        assert float(gq) < 0


def test_lookup_clamps_outside_grid(patterns):
    _, table = patterns[0]
    lo, hi = table.log_l[0], table.log_l[-1]
    assert float(g_iso_lookup(table, lo / 10)) == pytest.approx(table.g_iso[0], rel=1e-12)
    assert float(g_iso_lookup(table, 0.0)) == pytest.approx(table.g_iso[0], rel=1e-12)
    assert float(g_iso_lookup(table, hi * 10)) == pytest.approx(table.g_iso[-1], rel=1e-12)
    assert float(g_aniso_lookup(table, hi * 10, lo / 10)) == pytest.approx(table.g_aniso[-1, 0], rel=1e-12)
    assert float(jax.grad(lambda x: g_iso_lookup(table, x))(hi * 10)) == 0.0
    assert np.isfinite(float(jax.grad(lambda x: g_iso_lookup(table, x))(0.0)))


def test_white_noise_closed_form():
    f = normalise(np.random.default_rng(0).standard_normal((2048, 2048)))
    table = gradient_energy_table(f, H, l_max=400 * H)
    # white noise: |F(k)|² = 1/N² is flat with N² modes per 1/h² of k-plane, so for l >> h
    # g_f(l) = h² ∫ ½|2πk|² e^(-(2π|k|l)²) d²k = h² / (8π l⁴)
    l = 20 * H
    assert float(g_iso_lookup(table, l)) == pytest.approx(H ** 2 / (8 * np.pi * l ** 4), rel=0.02)


@pytest.mark.parametrize("shape", [(301, 200), (128, 257)])
def test_g_iso_non_square_odd_image(shape):
    """Odd and non-square images (load_pattern input): the binned table equals the full 2-D sum
    ½ Σ_k |2πk|² e^(-(2π|k|l)²) |F(k)|² over every FFT mode."""
    f = normalise(ndimage.gaussian_filter(np.random.default_rng(1).standard_normal(shape), 2.0,
                                          mode="wrap"))
    table = gradient_energy_table(f, H, n=64, l_max=40 * H)
    ky, kx = np.fft.fftfreq(shape[0], d=H), np.fft.fftfreq(shape[1], d=H)
    k2 = ky[:, None] ** 2 + kx[None, :] ** 2
    power = np.abs(np.fft.fft2(f)) ** 2 / f.size ** 2
    assert power.sum() == pytest.approx(1.0)
    for i in range(0, 64, 9):
        l = table.log_l[i]
        full = 0.5 * np.sum(4 * np.pi ** 2 * k2 * np.exp(-4 * np.pi ** 2 * k2 * l ** 2) * power)
        assert table.g_iso[i] == pytest.approx(full, rel=1e-3)


# --------------------------------------------------------------------------------------------
# Interpolation error of the box-pixel image (the correlation's floor, vdo.physics.checks)
# --------------------------------------------------------------------------------------------
INTERPOLATION_REL = 0.02       # spectral sum against the images (midpoint box, 16 x 16 points)


def _box_image(f, texel, pixels, shift, sub=16):
    """The image of the periodic bilinear texture f (texel centres at (j + ½) h) seen by square
    pixels tiling the tile `pixels` times per side, the texture moved by `shift` pixels: each
    pixel the mean of sub x sub midpoints (scipy map_coordinates, order 1, grid-wrap)."""
    p = f.shape[0] * texel / pixels
    o = (np.arange(sub) + 0.5) / sub - 0.5
    centres = np.arange(pixels)
    u = (centres[None, :, None, None] + o[None, None, None, :] - shift[0]) * p
    v = (centres[:, None, None, None] + o[None, None, :, None] - shift[1]) * p
    u, v = np.broadcast_arrays(u, v)
    values = ndimage.map_coordinates(f, [v / texel - 0.5, u / texel - 0.5], order=1, mode="grid-wrap")
    return values.reshape(pixels, pixels, -1).mean(-1), p


@pytest.mark.parametrize("pixels,phase", [(100, (0.5, 0.0)), (100, (0.5, 0.5)), (40, (0.25, 0.5))])
def test_interpolation_error_against_spline_on_box_images(pixels, phase):
    """The RMS difference between scipy's cubic B-spline (periodic) through the image of the
    texture moved by `phase` pixels, read at the pixel centres moved by `phase`, and the image of
    the unmoved texture: the spectral sum of `interpolation_error` (8-texel dots: 3.1 px at 100
    pixels per tile, 1.25 px at 40)."""
    f = normalise(generate_pattern(256, H, DOT, 0.5, 10, 3)).astype(np.float64)
    still, p = _box_image(f, H, pixels, (0.0, 0.0))
    moved, _ = _box_image(f, H, pixels, phase)
    coeffs = ndimage.spline_filter(moved, order=3, mode="grid-wrap")
    rows, cols = np.meshgrid(np.arange(pixels) + phase[1], np.arange(pixels) + phase[0], indexing="ij")
    read = ndimage.map_coordinates(coeffs, [rows, cols], order=3, prefilter=False, mode="grid-wrap")
    measured = float(np.sqrt(np.mean((read - still) ** 2)))
    predicted = interpolation_error(f, H, np.diag([p, p]), phase=phase)[0]
    assert measured > 0.01
    assert predicted == pytest.approx(measured, rel=INTERPOLATION_REL)


# --------------------------------------------------------------------------------------------
# Keys' cubic convolution: the model's responses against interpolating a sampled sinusoid
# --------------------------------------------------------------------------------------------
KEYS_RESPONSE_TOL = 1e-12     # closed-form sums of 4 taps against the same sums done term by term
KEYS_FD_STEP = 1e-6           # px: central differences of the interpolant for its derivative
KEYS_FD_TOL = 1e-7            # their truncation and rounding error (per unit amplitude)


def _keys_reference(x):
    """Keys' kernel for a = -1/2 written out (Keys 1981, eq. 15): 3/2|x|³ - 5/2|x|² + 1 on
    [0, 1], -1/2|x|³ + 5/2|x|² - 4|x| + 2 on (1, 2), 0 beyond."""
    t = np.abs(x)
    return np.piecewise(t, [t <= 1, (t > 1) & (t < 2)],
                        [lambda t: 1.5 * t ** 3 - 2.5 * t ** 2 + 1,
                         lambda t: -0.5 * t ** 3 + 2.5 * t ** 2 - 4 * t + 2, 0.0])


def test_keys_responses_are_the_interpolated_sinusoid():
    """Interpolate the samples exp(iωm), m = -8 .. 16, at x = n + d with the kernel written out
    here, for frequencies below and above Nyquist: f(x) / exp(iωx) is R_d(ω), the derivative
    (central differences of f) over i exp(iωx) is R'_d(ω), and at d = 0 the derivative response
    is sin ω (the kernel's k'(±1) = ∓1/2: the central difference)."""
    from vdo.model.spline_response import _KeysSpectrum

    omega = np.array([0.05, 0.7, 2.0, 3.1, 4.4, 9.0])
    phases = np.array([0.0, 0.125, 0.5, 0.8])
    m = np.arange(-8, 17)
    n = 4
    spec = _KeysSpectrum(omega)
    R, Rp = spec.shift(phases), spec.derivative_shift(phases)
    for p, d in enumerate(phases):
        x = n + d
        f = lambda x: (np.exp(1j * omega[:, None] * m) * _keys_reference(x - m)).sum(-1)
        assert np.allclose(f(x) / np.exp(1j * omega * x), R[p], atol=KEYS_RESPONSE_TOL)
        fd = (f(x + KEYS_FD_STEP) - f(x - KEYS_FD_STEP)) / (2 * KEYS_FD_STEP)
        assert np.allclose(fd / (1j * np.exp(1j * omega * x)), Rp[p], atol=KEYS_FD_TOL)
    assert np.allclose(spec.derivative(), np.sin(omega), atol=KEYS_RESPONSE_TOL)
    assert np.allclose(R[0], 1.0, atol=KEYS_RESPONSE_TOL)           # it passes through its samples
    # third-order accurate: the error at a low frequency falls as ω³ (Keys' a = -1/2)
    low = _KeysSpectrum(np.array([0.1, 0.2])).shift(np.array([0.5]))[0]
    ratio = abs(low[1] - 1) / abs(low[0] - 1)
    assert 7.0 < ratio < 17.0, ratio      # 2³ = 8 (odd-order term) .. 2⁴ = 16


def test_keys_correlation_error_is_symmetric_and_worse_than_the_cubic_spline():
    """The twin rule of `_phase_pairs` holds for Keys' kernel (R_{1-d} = conj R_d): the phases
    d and 1 - d, computed apart (grids without twins), give opposite biases and equal noise; and on
    4 px sharp dots its bias is several times the cubic B-spline's (the kernel's stronger
    attenuation off the grid)."""
    from vdo.model.interpolant import correlation_error
    from vdo.model.spline_response import KEYS

    f = normalise(generate_pattern(256, 1.0, 32.0, 0.5, 0, seed=2))
    low, high = np.array([0.125, 0.25, 0.375]), np.array([0.875, 0.75, 0.625])
    a, b = (correlation_error(f, 1.0 / 8, np.eye(2)[None], order=KEYS, texel_filter="ideal",
                              phases=(p, [0.0])) for p in (low, high))
    ba, bb = a.bias_curve[0, :, 0, 0], b.bias_curve[0, :, 0, 0]
    assert np.abs(ba).min() > 1e-3 and np.allclose(ba, -bb, rtol=1e-9)
    assert np.allclose(a.noise, b.noise, rtol=1e-9) and np.allclose(a.scatter, b.scatter, rtol=1e-9)
    grid = np.arange(8) / 8
    keys = correlation_error(f, 1.0 / 8, np.eye(2)[None], order=KEYS, texel_filter="ideal",
                             phases=(grid, [0.0]))
    cubic = correlation_error(f, 1.0 / 8, np.eye(2)[None], order=3, texel_filter="ideal",
                              phases=(grid, [0.0]))
    assert np.sqrt(keys.bias[0, 0, 0]) > 3 * np.sqrt(cubic.bias[0, 0, 0])
