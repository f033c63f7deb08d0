"""Design checks: each flag tripped by a config made to trip it, and the numbers against closed
forms (footprint of a frontal pinhole, thin-lens depth of field, exposure from the sensor model)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import DOWN_CAMERA
from vdo.physics import checks
from vdo.physics.lighting import illuminate
from vdo.model.speckle import pattern_for

CAMERA = DOWN_CAMERA.format(name="down", focal=24, u=0.5) + """{lens}

[speckle]
dot_diameter_mm = {dot}
texel_mm = {texel}
tile_texels = 256

[render]
ambient_radiance = {ambient}
"""


def _rows(plate_experiment, dot=9.0, ambient=1.0, lens="", texel=1.0):
    from conftest import raycast
    path = plate_experiment(spacing=50, cameras=CAMERA.format(dot=dot, ambient=ambient, lens=lens, texel=texel))
    exp, samples, cams, scene, vis = raycast(path)
    illum = illuminate(scene, exp.lights, samples, exp.render.ambient_radiance)
    rows = checks.design_checks(exp.camera_specs, exp.evaluation, exp.speckle, exp.sensor,
                                exp.analysis, cams, samples, vis.visible, illum.irradiance,
                                pattern_for(exp.speckle))
    assert [r["region"] for r in rows] == ["top"]
    return rows[0], exp


def test_a_good_design_has_no_flag_and_closed_form_numbers(plate_experiment):
    # 11 mm dots of 3.66 mm texels: edges soft at the 2.3 mm pixel (interpolation error 1.9x the
    # sensor noise, under the flag)
    row, exp = _rows(plate_experiment, dot=11.0, texel=3.66, lens="f_number = 8\nfocus_m = 1.5")
    assert row["flags"] == [] and row["severity"] is None
    pixel = 22.2e-3 / 600
    assert row["mm_per_px"] == pytest.approx(1.5 * pixel / 24e-3 * 1e3, rel=0.02)  # frontal: Z p / f
    assert row["speckle_px"] == pytest.approx(11e-3 / (1.5 * pixel / 24e-3), rel=0.02)
    assert row["standoff_m"] == pytest.approx(1.5, rel=0.1)
    # the plate (1 m) fills the image's width: 1 m / (W mm/px) columns of the 600 x 400 image
    cols = 1.0 / (row["mm_per_px"] * 1e-3)
    assert row["fov_fill"] == pytest.approx(min(cols, 600) * min(cols, 400) / (600 * 400), rel=0.1)
    # exposure: white paint at E = pi L -> linear 0.8 -> 56 % of the full well, gain maps full
    # well to the top DN: the brightest percentile is 0.56 of (max - offset) + offset
    s = exp.sensor
    assert row["exposure"]["p99_gray_fraction"] == pytest.approx(
        s.mean_dn(0.8) / s.max_dn, rel=0.01)
    near, far = row["depth_of_field"]["near_m"], row["depth_of_field"]["far_m"]
    assert far is None and near < 1.5


def test_speckle_flags(plate_experiment):
    small, _ = _rows(plate_experiment, dot=3.0)
    large, _ = _rows(plate_experiment, dot=20.0)
    assert any("speckle dots" in f for f in small["flags"]) and small["speckle_px"] < 3
    assert any("speckle dots" in f for f in large["flags"]) and large["speckle_px"] > 5


def test_interpolation_floor(plate_experiment):
    """9 mm dots of 1 mm texels have edges sharp at the 2.3 mm pixel: the interpolation error
    (`vdo.model.interpolant.interpolation_error`, checked in test_speckle.py) is several times the sensor
    noise; 11 mm dots of 3.66 mm texels are soft at the pixel scale. The gray levels from the
    sensor model: linear 0.8 (white) and 0.05 (black) at E = π L, L = 1. The measured/noise ratio
    is `correlation_error`'s (checked against correlation in test_measured.py) at the same σ and
    patch: the sharp pattern's is larger, and only it is flagged."""
    from vdo.model.optics import optics_blur
    from vdo.model.speckle import normalise
    from vdo.model.interpolant import correlation_error, interpolation_error

    sharp, exp = _rows(plate_experiment)
    soft, _ = _rows(plate_experiment, dot=11.0, texel=3.66)
    assert sharp["interpolation"]["ratio"] > checks.INTERPOLATION_NOISE
    assert soft["interpolation"]["ratio"] < checks.INTERPOLATION_NOISE
    s, f = exp.sensor, pattern_for(exp.speckle)
    p = sharp["mm_per_px"] * 1e-3                      # frontal view: a square pixel
    e = interpolation_error(normalise(f), exp.speckle.texel, np.diag([p, p]))[0]
    contrast = (s.mean_dn(0.8) - s.mean_dn(0.05)) * f.std()
    assert sharp["interpolation"]["error_dn"] == pytest.approx(e * contrast, rel=0.03)
    mean = s.mean_dn(0.05 + 0.75 * f.mean())
    noise = math.sqrt(s.variance_dn(mean))
    assert sharp["interpolation"]["noise_dn"] == pytest.approx(noise, rel=0.03)
    # the measured/noise ratio at the frontal footprint, f/8 assumed (no f_number), 10 mm patch
    m = sharp["interpolation"]["measured"]
    assert sharp["interpolation"]["optics"]["f_number_assumed"]
    lens = optics_blur(22.2e-3 / 600, 24e-3, None, None)
    model = correlation_error(normalise(f), exp.speckle.texel, np.diag([p, p])[None], optics=[lens])
    sigma, pixels = noise / contrast, (10e-3 / p) ** 2
    total = np.diagonal(model.covariance(sigma, pixels)[0])
    expected = np.sqrt(total / (sigma ** 2 / pixels * np.diagonal(model.noise[0])))
    assert m["measured_over_noise"] == pytest.approx(expected, rel=0.03)
    assert max(m["measured_over_noise"]) > max(soft["interpolation"]["measured"]["measured_over_noise"])
    flagged = [f for f in sharp["findings"] if f["check"] == "interpolation"]
    assert flagged and flagged[0]["severity"] in ("warn", "advice")
    assert not any(f["check"] == "interpolation" for f in soft["findings"])


def test_findings_carry_a_severity_worst_first(plate_experiment):
    row, _ = _rows(plate_experiment, dot=3.0, ambient=2.0, lens="f_number = 1.4\nfocus_m = 1.0")
    severities = [f["severity"] for f in row["findings"]]
    assert severities[0] == "fail" and row["severity"] == "fail"
    assert severities == sorted(severities, key=checks.SEVERITIES.index)
    assert {f["check"] for f in row["findings"]} >= {"depth of field", "exposure", "speckle"}
    assert row["flags"] == [f["message"] for f in row["findings"]]
    assert checks.count_findings([row])["fail"] == severities.count("fail")


def test_depth_of_field_flag(plate_experiment):
    row, _ = _rows(plate_experiment, lens="f_number = 1.4\nfocus_m = 1.0")
    assert any("out of focus" in f for f in row["flags"])
    d = row["depth_of_field"]
    # thin-lens closed form with c = 2 pixel pitches
    c, f, N, s = 2 * 22.2e-3 / 600, 24e-3, 1.4, 1.0
    assert d["far_m"] == pytest.approx(s * f * f / (f * f - N * c * (s - f)), rel=1e-9)
    assert d["near_m"] == pytest.approx(s * f * f / (f * f + N * c * (s - f)), rel=1e-9)
    assert row["depth_max_m"] > d["far_m"]


def test_exposure_flags(plate_experiment):
    dark, _ = _rows(plate_experiment, ambient=0.2)
    bright, _ = _rows(plate_experiment, ambient=2.0)
    assert any("under-exposed" in f for f in dark["flags"])
    assert dark["exposure"]["p99_gray_fraction"] < 0.25
    assert any("saturating" in f for f in bright["flags"])
    assert bright["exposure"]["saturated_fraction"] > 0.3


def test_depth_of_field_limits_bracket_the_focus():
    near, far = checks.depth_of_field(0.05, 8.0, 2.0, 10e-6)
    assert near < 2.0 < far
    # beyond the hyperfocal distance H = f^2 / (N c) + f the far limit is infinite
    H = 0.05 ** 2 / (8.0 * 10e-6) + 0.05
    assert math.isinf(checks.depth_of_field(0.05, 8.0, 1.01 * H, 10e-6)[1])
    assert np.isfinite(checks.depth_of_field(0.05, 8.0, 0.99 * H, 10e-6)[1])


def test_a_dark_pair_is_flagged_under_exposed_and_not_interpolated(plate_experiment):
    # no light at all: zero contrast, so no interpolation figure (it would be 0/0) and no warning
    # from numpy; the exposure check says why
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        row, _ = _rows(plate_experiment, ambient=0.0)
    assert row["interpolation"] is None
    assert [f["check"] for f in row["findings"]] == ["exposure"]
    assert row["findings"][0]["message"].startswith("under-exposed")
    assert math.isnan(checks._measured_over_noise(row))


def test_a_camera_that_sees_a_sliver_at_its_image_edge_is_left_out_and_counted(plate_experiment, tmp_path, capsys):
    """Camera `down` sees the whole plate; `edge`, above the floor past the plate's end looking
    down, holds a strip of it at its image border, where the frame's ramp leaves no usable view (under
    NEGLIGIBLE_VIEW of the area, counted here from the prediction's usable views): `vdo evaluate`
    leaves `edge` out of the design checks, lists it in summary.json's negligible_views and says so
    in one line; `down` stays checked, and without the cut `edge` would have had its row."""
    import json

    from conftest import aimed_camera
    from vdo.commands.cli import main

    edge = aimed_camera("edge", 1.0).replace("target_m = [0.0, 0.0, 0.0]", "target_m = [0.95, 0.0, 0.0]")
    cams = DOWN_CAMERA.format(name="down", focal=24, u=0.5) + edge + "\n[render]\nambient_radiance = 1.0\n"
    path = plate_experiment(spacing=25, cameras=cams)
    assert main(["evaluate", str(path), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert [(r["camera"], r["region"]) for r in summary["design_checks"]] == [("down", "top")]
    left = summary["negligible_views"]
    assert [(n["camera"], n["region"]) for n in left] == [("edge", "top")]
    assert left[0]["usable_fraction"] == pytest.approx(summary["regions"]["top"]["cameras"].get("edge", 0.0), abs=1e-4)
    assert left[0]["usable_fraction"] < checks.NEGLIGIBLE_VIEW
    assert ("1 pair(s) left out as negligible (usable view under 1 % of the region: summary.json "
            "negligible_views)") in out, out

    # the strip is seen (the ray cast): without the cut the table would hold its row
    from conftest import raycast
    exp, samples, cams_, scene, vis = raycast(path)
    illum = illuminate(scene, exp.lights, samples, exp.render.ambient_radiance)
    rows = checks.design_checks(exp.camera_specs, exp.evaluation, exp.speckle, exp.sensor, exp.analysis,
                                cams_, samples, vis.visible, illum.irradiance, pattern_for(exp.speckle))
    assert [r["camera"] for r in rows] == ["down", "edge"]


def test_the_console_counts_pairs_by_worst_finding_and_lists_only_the_above_advice_ones(plate_experiment, capsys):
    """Three real rows: a failing one (f/1.4 focused at 1 m, over-lit, fine dots), an advice-only
    one (coarse dots) and a clean one. The head line counts pairs by their worst finding; the table
    holds the failing pair, not the advice-only one (which stays in summary.json)."""
    failing, _ = _rows(plate_experiment, dot=3.0, ambient=2.0, lens="f_number = 1.4\nfocus_m = 1.0")
    clean, _ = _rows(plate_experiment, dot=11.0, texel=3.66, lens="f_number = 8\nfocus_m = 1.5")
    advice = dict(clean, camera="coarse",
                  findings=[{"severity": "advice", "check": "speckle", "message": "speckle dots 9 px"}],
                  severity="advice")
    assert failing["severity"] == "fail" and not clean["findings"]
    rows = [dict(failing, camera="sharp"), advice, dict(clean, camera="good")]
    checks.print_checks(rows)
    out = capsys.readouterr().out.splitlines()
    n_fail = checks.count_findings([failing])
    assert out[0].startswith("design checks on 3 camera-region pairs, by worst finding: 1 fail, 0 warn, "
                             "1 advice only, 1 clean; findings: "
                             f"{n_fail['fail']} fail, {n_fail['warn']} warn, {n_fail['advice'] + 1} advice"), out[0]
    table = out[2:]
    assert len(table) == 1 and table[0].startswith("FAIL    sharp"), out
