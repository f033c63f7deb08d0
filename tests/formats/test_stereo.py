"""Stereo-pair rules: the maximum axis angle (penalty against its closed form and finite
differences, the optimizer held inside [min, max], `evaluate` warning of a 3 deg pair), per-camera
lens catalogues, and the config's one-line errors."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import PLATE_TOML, aimed_camera, write_box
from vdo import constraints
from vdo.config import experiment as config
from vdo.config import procedure
from vdo.core.errors import ConfigError
from vdo.commands.evaluate import evaluate
from vdo.commands.optimize import optimize
from vdo.scene import cameras_of

TAIL = """
[render]
ambient_radiance = 1.0
{render}

[optimize]
starts = 1
rounds = 2
max_steps = 25
{optimize}

{pairs}
"""


def write(tmp_path, u=(0.45, 0.55), pairs="", optimize_extra="", camera_extra=("", ""), render=""):
    write_box(tmp_path / "plate.stl", [600, 600, 10], center=[0, 0, -5])
    cams = "".join(aimed_camera(n, x, e) for n, x, e in zip("ab", u, camera_extra))
    text = PLATE_TOML.format(spacing=20, limit=75, height=1.2, extra_meshes="",
                             cameras=cams + TAIL.format(optimize=optimize_extra, pairs=pairs,
                                                              render=render))
    path = tmp_path / "exp.toml"
    path.write_text(text)
    return path


def test_max_angle_penalty_is_zero_inside_and_quadratic_above():
    low, high = math.radians(15), math.radians(35)
    pairs = np.array([[0, 1]])
    for angle in (15.0, 25.0, 35.0, 50.0):
        a = math.radians(angle)
        axes = jnp.asarray([[0.0, 0.0, 1.0], [math.sin(a), 0.0, math.cos(a)]])
        value = float(constraints.axis_angle_penalty(axes, pairs, [low], [high]))
        over = max(0.0, math.cos(high) - math.cos(a)) / (1 - math.cos(high))
        assert value == pytest.approx(over ** 2, abs=1e-15)
    # no maximum (inf): the minimum term alone
    axes = jnp.asarray([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    assert float(constraints.axis_angle_penalty(axes, pairs, [low], [math.inf])) == 0.0

    def f(t):
        return constraints.axis_angle_penalty(
            jnp.stack([jnp.array([0.0, 0.0, 1.0]), jnp.stack([jnp.sin(t), 0.0, jnp.cos(t)])]),
            pairs, [low], [high])

    t0, h = math.radians(41.0), 1e-6
    assert float(jax.grad(f)(t0)) == pytest.approx((float(f(t0 + h)) - float(f(t0 - h))) / (2 * h), rel=1e-6)


def test_declared_pair_limits_and_defaults(tmp_path):
    """A declared pair without angles: the rule of thumb (24 mm: 21.1 deg) and that + 20 deg;
    with angles: its own; the global maximum applies to the other shared pairs."""
    exp = config.load(write(tmp_path, pairs='[[stereo_pair]]\ncameras = ["a", "b"]'))
    cams = cameras_of(exp.camera_specs, exp.rails)
    pairs, low, high = constraints.angle_limits(exp.regions, exp.optimize, exp.stereo_pairs, cams,
                                                np.zeros((2, 1), dtype=bool))
    assert pairs.tolist() == [[0, 1]]
    assert math.degrees(low[0]) == pytest.approx(math.degrees(constraints.stereo_min_angle(0.024)))
    assert math.degrees(high[0] - low[0]) == pytest.approx(procedure.STEREO_SPAN_DEG)
    exp = config.load(write(tmp_path, optimize_extra="max_axis_angle_deg = 40",
                            pairs='[[stereo_pair]]\ncameras = ["b", "a"]\nmin_angle_deg = 15\nmax_angle_deg = 35'))
    both = np.ones((2, 1), dtype=bool)          # both cameras assigned the one region
    _, low, high = constraints.angle_limits(exp.regions, exp.optimize, exp.stereo_pairs, cameras_of(exp.camera_specs, exp.rails),
                                            both)
    assert np.degrees([low[0], high[0]]) == pytest.approx([15, 35])
    exp = config.load(write(tmp_path, optimize_extra="max_axis_angle_deg = 40"))
    _, _, high = constraints.angle_limits(exp.regions, exp.optimize, exp.stereo_pairs, cameras_of(exp.camera_specs, exp.rails), both)
    assert math.degrees(high[0]) == pytest.approx(40)
    # a region's own maximum applies to the pairs sharing it, the least of the limits wins
    path = write(tmp_path, optimize_extra="max_axis_angle_deg = 40")
    path.write_text(path.read_text().replace('normal = [0, 0, 1]', 'normal = [0, 0, 1]\nmax_axis_angle_deg = 30'))
    exp = config.load(path)
    assert exp.regions[0].max_axis_angle == pytest.approx(math.radians(30))
    _, _, high = constraints.angle_limits(exp.regions, exp.optimize, exp.stereo_pairs, cameras_of(exp.camera_specs, exp.rails), both)
    assert math.degrees(high[0]) == pytest.approx(30)
    _, _, high = constraints.angle_limits(exp.regions, exp.optimize, exp.stereo_pairs, cameras_of(exp.camera_specs, exp.rails),
                                          np.array([[True], [False]]))
    assert len(high) == 0                         # no common region: no pair


@pytest.mark.parametrize("kwargs, field", [
    (dict(pairs='[[stereo_pair]]\ncameras = ["a", "b"]\nmin_angle_deg = 20\nmax_angle_deg = 10'),
     "stereo_pair[0].max_angle_deg"),
    (dict(optimize_extra="min_axis_angle_deg = 20\nmax_axis_angle_deg = 5"), "optimize.max_axis_angle_deg"),
    (dict(pairs='[[stereo_pair]]\ncameras = ["a", "zz"]'), "stereo_pair[0].cameras"),
    (dict(pairs='[[stereo_pair]]\ncameras = ["a", "a"]'), "stereo_pair[0].cameras"),
    (dict(camera_extra=("lenses_mm = [24, -35]", "")), 'camera "a".lenses_mm'),
    (dict(render='bit_alignment = "lsb"'), "render.bit_alignment"),
])
def test_bad_input_is_one_line_naming_the_field(tmp_path, kwargs, field):
    path = write(tmp_path, **kwargs)
    with pytest.raises(ConfigError) as info:
        config.load(path)
    assert info.value.field == field
    assert "\n" not in str(info.value)


def test_camera_lens_catalogue_is_read_and_satisfies_a_free_lens(tmp_path):
    path = write(tmp_path, camera_extra=("lenses_mm = [35, 24, 50]", ""),
                 optimize_extra='free = ["u", "pan", "tilt", "lens"]')
    exp = config.load(path)
    assert exp.camera_specs[0].lenses == pytest.approx((0.024, 0.035, 0.05))
    assert exp.camera_specs[1].lenses == ()
    assert config.parse(exp.to_dict(), path).camera_specs[0].lenses == exp.camera_specs[0].lenses


def test_evaluate_warns_of_a_3_degree_pair(tmp_path, caplog):
    """Cameras 6 cm apart at 1.2 m, both aimed at the plate centre: 2.9 deg between their axes,
    below the 24 mm rule of thumb (21.1 deg): evaluate says so (a warning of the vdo.commands.evaluate
    logger) and summary.json records it."""
    result = evaluate(config.load(write(tmp_path, u=(0.485, 0.515))), tmp_path / "run")
    out = caplog.text
    assert "warning: axis_angle not met: a and b: 2.864 deg, limit 21.11" in out
    entry = [e for e in result.axis_angles if e["constraint"] == "axis_angle"][0]
    assert not entry["met"] and entry["value"] == pytest.approx(2 * math.degrees(math.atan(0.03 / 1.2)), rel=1e-6)
    saved = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert saved["axis_angles"][0]["value"] == pytest.approx(entry["value"])


@pytest.mark.slow
def test_optimizer_keeps_a_declared_pair_within_its_maximum(tmp_path):
    """A stereo pair 18 deg apart, declared [10, 20] deg: the score (out-of-plane sigma) pulls
    the cameras apart; the maximum stops them at 20 deg (0.5 deg inside, the penalty's margin)."""
    pairs = '[[stereo_pair]]\ncameras = ["a", "b"]\nmin_angle_deg = 10\nmax_angle_deg = 20'
    half = math.tan(math.radians(9)) * 1.2 / 2.0       # rail x in [-1, 1]: u = 0.5 +- x / 2
    exp = config.load(write(tmp_path, u=(0.5 - half, 0.5 + half), pairs=pairs))
    result = optimize(exp, tmp_path / "run")
    after = json.loads((tmp_path / "run" / "constraints.json").read_text())["after"]
    top = [e for e in after if e["constraint"] == "axis_angle_max"][0]
    assert top["limit"] == pytest.approx(20) and top["met"], top
    assert result.violations == 0, result.violated
    before = json.loads((tmp_path / "run" / "constraints.json").read_text())["before"]
    start = [e for e in before if e["constraint"] == "axis_angle_max"][0]["value"]
    assert start == pytest.approx(18, abs=0.05)
    print(f"stereo pair: {start:.2f} deg -> {top['value']:.2f} deg (max 20)")
