"""Tests for vdo.model.sensor: the EMVA 1288 noise model, saturation, determinism, JAX, image files."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

from vdo.model.sensor import SensorModel, save_image

SHAPE = (256, 256)
FILLS = (0.05, 0.2, 0.4, 0.6, 0.75, 0.9)  # fraction of full well (mean electrons)


def _flat_pair(sensor: SensorModel, fill: float, seed: int):
    """Two independent exposures of a flat field at `fill` of the full well."""
    linear = np.full(SHAPE, fill * sensor.saturation_linear())
    a = sensor.expose(linear, np.random.default_rng(seed)).astype(np.float64)
    b = sensor.expose(linear, np.random.default_rng(seed + 10_000)).astype(np.float64)
    return linear, a, b


def _photon_transfer(sensor: SensorModel, seed0: int):
    """EMVA photon transfer: per level, measured mean, measured variance, model mean, model var."""
    rows = []
    for i, fill in enumerate(FILLS):
        linear, a, b = _flat_pair(sensor, fill, seed0 + i)
        mean = 0.5 * (a.mean() + b.mean())
        var = np.var(a - b) / 2.0  # difference of two frames removes fixed structure
        mu_model = float(sensor.mean_dn(fill * sensor.saturation_linear()))
        rows.append((mean, var, mu_model, float(sensor.variance_dn(mu_model))))
    return np.array(rows)


@pytest.mark.parametrize("bits", [10, 12, 16])
def test_photon_transfer_matches_model(bits):
    sensor = SensorModel(bit_depth=bits)
    pt = _photon_transfer(sensor, seed0=100 * bits)
    mean, var, mu_model, var_model = pt.T
    # 0.5 DN as asked; at 16 bit the standard error of the mean itself exceeds that (1.2 DN at
    # 90 % fill), so there the bound is 5 standard errors.
    tol = np.maximum(0.5, 5.0 * np.sqrt(var_model / (2 * np.prod(SHAPE))))
    assert np.all(np.abs(mean - mu_model) < tol), mean - mu_model
    rel = np.abs(var / var_model - 1.0)
    assert rel.max() < 0.05, rel
    slope, intercept = np.polyfit(mean, var, 1)
    assert slope == pytest.approx(sensor.gain, rel=0.05)


def test_photon_transfer_explicit_parameters():
    sensor = SensorModel(
        quantum_efficiency=0.45,
        full_well_e=10_000,
        read_noise_e=12.0,
        bit_depth=12,
        gain_dn_per_e=0.3,
        offset_dn=64,
        photons_per_unit=5_000,
    )
    pt = _photon_transfer(sensor, seed0=7)
    mean, var, mu_model, var_model = pt.T
    assert np.all(np.abs(mean - mu_model) < 0.5)
    assert np.abs(var / var_model - 1.0).max() < 0.05
    assert np.polyfit(mean, var, 1)[0] == pytest.approx(0.3, rel=0.05)


def test_defaults():
    s = SensorModel()
    assert s.offset == 32.0 and s.max_dn == 4095
    assert s.gain == pytest.approx((4095 - 32) / 20000)
    # linear 1.0 -> 70 % of the full well; full well -> top DN
    assert float(s.mean_dn(1.0)) == pytest.approx(32 + 0.7 * (4095 - 32))
    assert float(s.mean_dn(s.saturation_linear())) == pytest.approx(4095)
    assert s.saturation_linear() == pytest.approx(1 / 0.7)
    # None fields are re-derived when another field changes
    s16 = dataclasses.replace(s, bit_depth=16)
    assert s16.offset == 512.0
    assert float(s16.mean_dn(s16.saturation_linear())) == pytest.approx(65535)


@pytest.mark.parametrize("bits", [8, 12, 16])
def test_saturation_gives_top_dn_and_no_noise(bits):
    s = SensorModel(bit_depth=bits)
    for factor in (1.2, 3.0, 1e6):
        linear = np.full((64, 64), factor * s.saturation_linear())
        a = s.expose(linear, np.random.default_rng(1))
        b = s.expose(linear, np.random.default_rng(2))
        assert np.all(a == s.max_dn) and np.all(b == s.max_dn)
        assert np.var(a.astype(float) - b.astype(float)) == 0.0
    assert np.all(s.expose(np.full((4, 4), np.inf), np.random.default_rng(0)) == s.max_dn)


def test_saturation_at_full_well_dn_when_gain_is_low():
    s = SensorModel(bit_depth=12, gain_dn_per_e=0.1, offset_dn=32)  # full well -> 2032 DN
    dn = s.expose(np.full((64, 64), 2.0 * s.saturation_linear()), np.random.default_rng(3))
    assert np.all(dn == 2032)


def test_dark_image_and_negative_input():
    s = SensorModel()
    dark = s.expose(np.zeros(SHAPE), np.random.default_rng(4)).astype(float)
    assert dark.mean() == pytest.approx(s.offset, abs=0.05)
    assert dark.var() == pytest.approx(float(s.variance_dn(s.offset)), rel=0.05)
    neg = s.expose(-np.ones((8, 8)), np.random.default_rng(4))
    assert neg.min() >= 0 and abs(neg.mean() - s.offset) < 5
    with pytest.raises(ValueError, match="NaN"):
        s.expose(np.array([[np.nan]]), np.random.default_rng(0))
    with pytest.raises(TypeError, match="Generator"):
        s.expose(np.zeros((2, 2)), 42)


def test_determinism():
    s = SensorModel()
    linear = np.random.default_rng(0).uniform(0.0, 1.2, size=(128, 96))
    a = s.expose(linear, np.random.default_rng(123))
    b = s.expose(linear, np.random.default_rng(123))
    c = s.expose(linear, np.random.default_rng(124))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.shape == linear.shape


def test_the_same_image_on_any_number_of_threads(monkeypatch):
    """An image of several blocks (`EXPOSE_BLOCK_PIXELS`, each its own stream): the same counts
    on 1 and on 3 threads, and blocks whose noise is not a copy of one another's."""
    from vdo.core import backend
    from vdo.model import sensor as sensor_module

    s = SensorModel()
    linear = np.full((3 * sensor_module.EXPOSE_BLOCK_PIXELS // 512 + 7, 512), 0.5)
    images = []
    for threads in (1, 3):
        monkeypatch.setattr(backend, "cpu_threads", lambda threads=threads: threads)
        images.append(s.expose(linear, np.random.default_rng(5)))
    assert np.array_equal(images[0], images[1])
    block = sensor_module.EXPOSE_BLOCK_PIXELS
    flat = images[0].reshape(-1).astype(float)
    assert not np.array_equal(flat[:block], flat[block:2 * block])
    assert abs(np.corrcoef(flat[:block], flat[block:2 * block])[0, 1]) < 0.01


@pytest.mark.parametrize(
    "bits, dtype", [(8, np.uint8), (10, np.uint16), (12, np.uint16), (16, np.uint16)]
)
def test_dtype_and_range(bits, dtype):
    s = SensorModel(bit_depth=bits)
    linear = np.linspace(-0.1, 2.0 * s.saturation_linear(), 200 * 50).reshape(200, 50)
    dn = s.expose(linear, np.random.default_rng(bits))
    assert dn.dtype == dtype
    assert dn.min() >= 0 and dn.max() == 2**bits - 1


def test_jax_jit_and_grad_agree_with_numpy():
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    s = SensorModel(read_noise_e=4.0)
    x = np.linspace(0.0, 1.4, 37)
    mean_np = s.mean_dn(x)
    sigma_np = s.noise_sigma_dn(x)
    mean_jx = jax.jit(s.mean_dn)(jnp.asarray(x))
    sigma_jx = jax.jit(s.noise_sigma_dn)(jnp.asarray(x))
    var_jx = jax.jit(s.variance_dn)(jnp.asarray(mean_np))
    np.testing.assert_allclose(np.asarray(mean_jx), mean_np, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(sigma_jx), sigma_np, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(var_jx), s.variance_dn(mean_np), rtol=1e-6)
    np.testing.assert_allclose(sigma_np, np.sqrt(s.variance_dn(s.mean_dn(x))))
    # d sigma / d linear = K * K QE p / (2 sigma)
    g = jax.grad(lambda v: s.noise_sigma_dn(v))(0.5)
    kqp = s.gain * s.quantum_efficiency * s.photon_scale
    assert float(g) == pytest.approx(s.gain * kqp / (2 * s.noise_sigma_dn(0.5)), rel=1e-5)
    # the sensor is hashable, so it can be a static argument
    f = jax.jit(lambda sensor, v: sensor.noise_sigma_dn(v), static_argnums=0)
    np.testing.assert_allclose(np.asarray(f(s, jnp.asarray(x))), sigma_np, rtol=1e-6)


def test_model_formulas_scalar():
    s = SensorModel(gain_dn_per_e=0.25, offset_dn=10, read_noise_e=8, quantum_efficiency=0.5,
                    photons_per_unit=1000)
    assert s.mean_dn(2.0) == pytest.approx(0.25 * 0.5 * 1000 * 2 + 10)
    assert s.variance_dn(260.0) == pytest.approx(0.25 * 250 + 0.25**2 * 64 + 1 / 12)
    assert s.variance_dn(0.0) == pytest.approx(0.25**2 * 64 + 1 / 12)  # below offset: no shot term
    assert s.saturation_linear() == pytest.approx(20000 / (0.5 * 1000))


def _read(path):
    from PIL import Image

    with Image.open(path) as im:
        return im.mode, np.asarray(im).copy()


@pytest.mark.parametrize(
    "name, bits, dtype, modes",
    [
        ("img.png", 12, np.uint16, ("I;16", "I")),
        ("img16.png", 16, np.uint16, ("I;16", "I")),
        ("img.png", 8, np.uint8, ("L",)),
        ("img.tif", 12, np.uint16, ("I;16", "I;16B", "I")),
        ("img.TIFF", 16, np.uint16, ("I;16", "I;16B", "I")),
        ("img8.tiff", 8, np.uint8, ("L",)),
    ],
)
def test_save_image_round_trip(tmp_path, name, bits, dtype, modes):
    rng = np.random.default_rng(5)
    dn = rng.integers(0, 2**bits, size=(37, 53)).astype(dtype)
    dn[0, 0], dn[-1, -1] = 0, 2**bits - 1
    out = save_image(tmp_path / name, dn, bits, alignment="raw")
    assert out == tmp_path / name
    mode, back = _read(out)
    assert mode in modes
    assert back.shape == dn.shape
    assert np.array_equal(back.astype(np.int64), dn.astype(np.int64))  # values kept, not rescaled
    assert os.listdir(tmp_path) == [name]  # no temporary file left behind


def test_save_image_from_exposure_and_overwrite(tmp_path):
    s = SensorModel()
    dn = s.expose(np.full((32, 32), 0.5), np.random.default_rng(0))
    p = tmp_path / "cam0.png"
    save_image(p, np.zeros((32, 32), np.uint16), 12)
    save_image(str(p), dn, s.bit_depth, alignment="raw")  # replaces the earlier file
    assert np.array_equal(_read(p)[1], dn)


def test_save_image_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="outside 0..4095"):
        save_image(tmp_path / "a.png", np.full((4, 4), 4096, np.uint16), 12)
    with pytest.raises(ValueError, match="outside 0..255"):
        save_image(tmp_path / "a.png", np.full((4, 4), 300, np.uint16), 8)
    with pytest.raises(TypeError, match="integer"):
        save_image(tmp_path / "a.png", np.zeros((4, 4)), 12)
    with pytest.raises(ValueError, match="2-D"):
        save_image(tmp_path / "a.png", np.zeros((4, 4, 3), np.uint8), 8)
    with pytest.raises(ValueError, match=r"\.png"):
        save_image(tmp_path / "a.jpg", np.zeros((4, 4), np.uint8), 8)
    with pytest.raises(ValueError, match="bit_depth"):
        save_image(tmp_path / "a.png", np.zeros((4, 4), np.uint8), 7)
    with pytest.raises(ValueError, match="alignment"):
        save_image(tmp_path / "a.png", np.zeros((4, 4), np.uint16), 12, alignment="lsb")
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    "field, value",
    [
        ("quantum_efficiency", 0.0),
        ("quantum_efficiency", 1.5),
        ("quantum_efficiency", "high"),
        ("full_well_e", 0),
        ("full_well_e", float("inf")),
        ("read_noise_e", -1.0),
        ("read_noise_e", float("nan")),
        ("bit_depth", 7),
        ("bit_depth", 17),
        ("bit_depth", 12.0),
        ("bit_depth", True),
        ("bit_depth", None),
        ("full_well_e", None),
        ("gain_dn_per_e", 0.0),
        ("gain_dn_per_e", -0.2),
        ("offset_dn", -1),
        ("offset_dn", 4095),
        ("photons_per_unit", 0),
        ("photons_per_unit", -5.0),
    ],
)
def test_bad_fields_raise_value_error_naming_field(field, value):
    with pytest.raises(ValueError, match=field):
        SensorModel(**{field: value})


def test_numpy_scalars_are_normalised():
    s = SensorModel(
        quantum_efficiency=np.float32(0.5), bit_depth=np.int64(10), offset_dn=np.int32(16)
    )
    assert type(s.quantum_efficiency) is float and type(s.bit_depth) is int
    assert type(s.offset_dn) is float
    assert hash(s) == hash(SensorModel(quantum_efficiency=0.5, bit_depth=10, offset_dn=16))


@pytest.mark.parametrize("name, bits", [("a.png", 12), ("a.tif", 10), ("b.png", 16), ("c.png", 8)])
def test_save_image_msb_alignment_read_by_opencv(tmp_path, name, bits):
    """The default "msb" alignment puts a 12-bit count in the top bits of the 16-bit file
    (count x 16), as OpenCV reads it back; 16- and 8-bit images are stored as they are."""
    import cv2

    rng = np.random.default_rng(7)
    dn = rng.integers(0, 2**bits, size=(21, 34)).astype(np.uint16 if bits > 8 else np.uint8)
    dn[0, 0] = 2**bits - 1
    back = cv2.imread(str(save_image(tmp_path / name, dn, bits)), cv2.IMREAD_UNCHANGED)
    shift = 16 - bits if bits > 8 else 0
    assert back.dtype == (np.uint16 if bits > 8 else np.uint8)
    np.testing.assert_array_equal(back.astype(np.int64), dn.astype(np.int64) << shift)
    if bits > 8:
        assert back.max() == 65536 - 2**shift     # full scale: 65520 for 12-bit data
