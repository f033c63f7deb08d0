"""Exposure design (`vdo.physics.exposure`): the light a camera gathers against closed forms, the
aperture against the thin lens's depth of field, and the chosen exposure and light power against
the design checks and Mitsuba's own render of the result."""

from __future__ import annotations

import dataclasses
import math
import textwrap

import numpy as np
import pytest

from conftest import write_box
from vdo.config import experiment as config
from vdo.core.errors import ConfigError
from vdo.model.optics import exposure_factor
from vdo.physics import checks
from vdo.physics.exposure import aperture_for, stop_at_least

TARGET_TOL = 0.05          # the p99 gray of the brightest region against the target (fraction of range)

TWO_LIGHTS = """
[experiment]
name = "plate, two halves, two lights"

[evaluation]
sample_spacing_mm = 40

[[mesh]]
name = "plate"
file = "plate.stl"
unit = "mm"
role = "specimen"

[[region]]
name = "left"
mesh = "plate"
normal = [0, 0, 1]
box_min_m = [-0.5, -0.5, -0.1]
box_max_m = [0.0, 0.5, 0.1]

[[region]]
name = "right"
mesh = "plate"
normal = [0, 0, 1]
box_min_m = [0.0, -0.5, -0.1]
box_max_m = [0.5, 0.5, 0.1]

[[camera]]
name = "down"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 16
position_m = [0.0, 0.0, 1.5]
pan_deg = 0
tilt_deg = -90
{camera}

[[light]]
name = "over_left"
position_m = [-0.45, 0.0, 0.3]
target_m = [-0.45, 0.0, 0.0]
size_m = [0.2, 0.2]
radiance = {left}
{left_max}

[[light]]
name = "over_right"
position_m = [0.45, 0.0, 0.3]
target_m = [0.45, 0.0, 0.0]
size_m = [0.2, 0.2]
radiance = {right}
{right_max}

[render]
spp = 4
scale = 0.5

{exposure}
"""


def _write(tmp_path, left=30.0, right=3.0, left_max="", right_max="", camera="", exposure=""):
    write_box(tmp_path / "plate.stl", [1000, 1000, 10], center=[0, 0, -5])
    path = tmp_path / "plate.toml"
    path.write_text(textwrap.dedent(TWO_LIGHTS.format(left=left, right=right, left_max=left_max,
                                                      right_max=right_max, camera=camera,
                                                      exposure=exposure)))
    return path


def _checks(exp):
    from vdo.state import layout_state, prepare
    st = layout_state(prepare(exp), predict_fields=False)
    rows = checks.design_checks(exp.camera_specs, exp.evaluation, exp.speckle, exp.sensor,
                                exp.analysis, list(st.cameras), st.samples, st.visibility.visible,
                                st.illumination.irradiance, st.geometry.speckle.pattern)
    return {r["region"]: r for r in rows}, st


def test_the_light_gathered_is_time_over_the_aperture_squared():
    assert exposure_factor(None, None, 0.01) == 1.0                       # f/8 at the reference
    assert exposure_factor(4.0, 0.02, 0.01) == pytest.approx(2.0 * 4.0)   # twice as long, 2 stops
    assert exposure_factor(16.0, None, 0.01) == pytest.approx(0.25)
    assert exposure_factor(5.6, 0.005, 0.01) == pytest.approx(0.5 * (8 / 5.6) ** 2)


@pytest.mark.parametrize("focal, pixel, near, far", [(0.1, 3.45e-6, 2.1, 2.4), (0.024, 5.86e-6, 1.0, 3.0),
                                                     (0.05, 2.2e-6, 0.6, 0.7)])
def test_the_aperture_holds_the_depth_sharp_at_both_ends(focal, pixel, near, far):
    """At N_dof focused at s, the thin lens's depth of field (`checks.depth_of_field`, its own
    formula) is exactly [near, far]."""
    n, s = aperture_for(focal, pixel, near, far)
    lo, hi = checks.depth_of_field(focal, n, s, checks.COC_PIXELS * pixel)
    assert lo == pytest.approx(near, rel=1e-9) and hi == pytest.approx(far, rel=1e-9)


def test_stops_are_thirds_of_a_stop_within_the_lens_range():
    assert stop_at_least(1.0, 2.8, 16) == 2.83
    assert stop_at_least(8.0, 2.8, 16) == 8.0
    assert stop_at_least(8.1, 2.8, 16) == 8.98
    assert stop_at_least(40.0, 2.8, 16) == 16


def test_exposure_and_light_power_clear_the_exposure_checks(tmp_path):
    """The right half gets a tenth of the light: with only the camera's time free the left half
    reaches the target and the right half stays under-exposed (said so); with the lights free
    too, both halves come inside the exposure window. Judged by the design checks (the whole
    pattern's gray levels) and by Mitsuba's render of the result."""
    from vdo.rendering.scene import noise_free_dn
    from vdo.render import render_images
    from vdo.state import with_exposure

    maxes = dict(left_max="max_radiance = 60", right_max="max_radiance = 60")
    only_time = config.load(_write(tmp_path, **maxes, exposure='[exposure]\nfree = ["time"]'))
    before, _ = _checks(only_time)
    timed, plan = with_exposure(only_time)
    rows, _ = _checks(timed)
    assert rows["left"]["exposure"]["p99_gray_fraction"] == pytest.approx(
        timed.exposure.target_gray, abs=TARGET_TOL)
    assert any("under-exposed" in f for f in rows["right"]["flags"])
    assert any("right stays at" in p for p in plan.problems)
    assert plan.radiance == {"over_left": 30.0, "over_right": 3.0}

    free = config.load(_write(tmp_path, **maxes, exposure='[exposure]\nfree = ["time", "lights"]'))
    lit, plan = with_exposure(free)
    rows, st = _checks(lit)
    for region in ("left", "right"):
        e = rows[region]["exposure"]
        assert checks.EXPOSURE[0] <= e["p99_gray_fraction"] <= checks.EXPOSURE[1], (region, e)
        assert not any(f["check"] == "exposure" for f in rows[region]["findings"])
    assert plan.problems == ()
    assert plan.radiance["over_right"] > 3.0 * 3          # the dim light was raised
    brightest = max(rows[r]["exposure"]["p99_gray_fraction"] for r in rows)
    assert brightest == pytest.approx(lit.exposure.target_gray, abs=TARGET_TOL)
    # Mitsuba's render of the result: each half's 99th percentile gray inside the window
    result = render_images(lit)
    cam = result.state.cameras[0]
    clean = noise_free_dn(result.linear[cam.name], lit.sensor) / lit.sensor.max_dn
    uv = np.rint(cam.project(st.samples.points)).astype(int)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    for k, region in enumerate(st.samples.region_names):
        pick = inside & (st.samples.region == k)
        p99 = np.percentile(clean[uv[pick, 1], uv[pick, 0]], 99)
        assert checks.EXPOSURE[0] <= p99 <= checks.EXPOSURE[1], (region, p99)


def test_the_aperture_keeps_the_plate_sharp(tmp_path):
    """A camera looking at the plate obliquely sees depths [near, far]: the chosen f-number is a
    third stop at or above the thin lens's need, and the design check of depth of field passes;
    the written exposure time gives back the plan's light factor k."""
    from vdo.state import with_exposure

    path = _write(tmp_path, left=30.0, right=30.0,
                  exposure='[exposure]\nfree = ["aperture", "time"]\nmax_ms = 1000')
    text = path.read_text().replace('position_m = [0.0, 0.0, 1.5]\npan_deg = 0\ntilt_deg = -90',
                                    'position_m = [-1.2, 0.0, 1.2]\ntarget_m = [0.0, 0.0, 0.0]')
    text = text.replace("focal_mm = 16", "focal_mm = 75")
    path.write_text(text)
    exp, plan = with_exposure(config.load(path))
    (cam,) = plan.cameras
    need, _ = aperture_for(0.075, 22.2e-3 / 600, *cam.depth_m)
    assert exp.exposure.f_numbers[0] < need < exp.exposure.f_numbers[1]
    assert need <= cam.f_number <= exp.exposure.f_numbers[1]
    rows, _ = _checks(exp)
    assert rows and all(r["depth_of_field"] is not None for r in rows.values())
    assert not any(f["check"] == "depth of field" for r in rows.values() for f in r["findings"])
    # t = t_ref k (N / 8)^2: the written time gives back the plan's k
    spec = exp.camera_specs[0]
    assert exposure_factor(spec.f_number, spec.exposure_time, exp.sensor.exposure_ms * 1e-3) == \
        pytest.approx(cam.gathered)


@pytest.mark.parametrize("edit, field", [
    (dict(exposure="[exposure]\nf_number_range = [16, 2.8]"), "exposure.f_number_range"),
    (dict(exposure='[exposure]\nfree = ["lights"]'), "exposure.free"),
    (dict(exposure='[exposure]\nfree = ["shutter"]'), "exposure.free"),
    (dict(exposure="[exposure]\nmax_ms = 0"), "exposure.max_ms"),
    (dict(exposure="[exposure]\nblur_px = 0"), "exposure.blur_px"),
    (dict(exposure="[load_path]\nstep_s = 0.5"), "load_path.step_s"),
    (dict(camera="exposure_ms = -5"), 'camera "down".exposure_ms'),
    (dict(left_max="max_radiance = 10"), 'light "over_left".max_radiance'),
])
def test_bad_exposure_settings_are_one_line(tmp_path, edit, field):
    with pytest.raises(ConfigError) as err:
        config.load(_write(tmp_path, **edit))
    message = str(err.value)
    assert field in message and "\n" not in message, message


SLIDE_MM = 20.0   # the plate slides along x by this much per step of the load path


def test_the_exposure_keeps_the_image_motion_within_blur_px(tmp_path):
    """The plate slides 20 mm per step, a step every 0.5 s, under a camera looking straight down
    from Z = 1.5 m: every point of the plate crosses the image at f_px v / Z pixels per second (a
    fronto-parallel plane in translation, exactly). Under dim light the exposure the time wants
    is longer than blur_px allows, so the plan sets blur_px / speed, and says so for the region
    left dark; at rest (no step_s) the same file gets [exposure] max_ms."""
    from vdo.state import with_exposure

    (tmp_path / "poses.csv").write_text("step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n" + "".join(
        f"{k},plate,{SLIDE_MM * k},0,0,0,0,0\n" for k in (1, 2, 3)))
    step_s, blur = 0.5, 0.1
    moving = '[exposure]\nfree = ["time"]\nblur_px = 0.1\n\n[load_path]\nposes = "poses.csv"\nstep_s = 0.5'
    exp, plan = with_exposure(config.load(_write(tmp_path, left=0.5, right=0.5, exposure=moving)))
    (cam,) = plan.cameras
    f_px = 0.016 / (22.2e-3 / 600)
    speed = f_px * (SLIDE_MM * 1e-3 / step_s) / 1.5
    assert cam.image_speed == pytest.approx(speed, rel=1e-6)
    assert cam.max_s == pytest.approx(blur / speed, rel=1e-6)
    assert cam.exposure_s == pytest.approx(cam.max_s, rel=1e-9)       # the limit binds
    assert exp.camera_specs[0].exposure_time == pytest.approx(blur / speed, rel=1e-6)
    assert any("blur_px" in p and "px/s" in p for p in plan.problems), plan.problems
    still, plan_still = with_exposure(config.load(_write(
        tmp_path, left=0.5, right=0.5, exposure="[exposure]\nfree = [\"time\"]\nblur_px = 0.1")))
    assert plan_still.cameras[0].exposure_s == pytest.approx(still.exposure.max_time)
    assert plan_still.cameras[0].image_speed == 0.0


def test_the_settings_are_written_and_read_back(tmp_path):
    """designed.toml / optimized.toml carry the settings: written with `report.write_config` and
    read again, every camera's f-number, focus and time and every light's radiance are the
    plan's, and the experiment judges the same light gathered."""
    from vdo.outputs.report import write_config
    from vdo.physics.lighting import exposure_factors
    from vdo.state import with_exposure

    exp, plan = with_exposure(config.load(_write(
        tmp_path, left_max="max_radiance = 60", right_max="max_radiance = 60",
        exposure='[exposure]\nfree = ["aperture", "time", "lights"]')))
    write_config(tmp_path / "designed.toml", exp)
    again = config.load(tmp_path / "designed.toml")
    for spec, cam in zip(again.camera_specs, plan.cameras):
        assert spec.f_number == pytest.approx(cam.f_number)
        assert spec.focus_distance == pytest.approx(cam.focus_m)
        assert spec.exposure_time == pytest.approx(cam.exposure_s)
    assert {lt.name: lt.radiance for lt in again.lights} == pytest.approx(plan.radiance)
    assert exposure_factors(again.camera_specs, again.sensor) == \
        pytest.approx([c.gathered for c in plan.cameras])


def test_the_stop_is_where_the_measured_uncertainty_is_least(tmp_path):
    """Fine speckle (2 mm dots at 1.1 mm per 6 µm pixel) aliases at a wide aperture; a smaller one
    blurs it by diffraction and gathers less light. The chosen stop is the one where the summed
    σ_measured² of the camera's regions is least, each stop judged through the camera's own
    settings as `vdo evaluate` judges them (`vdo.physics.measured.region_floors`: its f-number,
    focus and the exposure time the plan would set), and it is not the widest stop here."""
    from vdo.physics import measured
    from vdo.physics.exposure import THIRD_STOP
    from vdo.physics.lighting import exposure_factors
    from vdo.state import layout_state, prepare, with_exposure

    path = _write(tmp_path, left=30.0, right=30.0, exposure='[exposure]\nfree = ["aperture", "time"]\n'
                  "max_ms = 1000")
    path.write_text(path.read_text().replace("sensor_mm = [22.2, 14.8]", "sensor_mm = [3.6, 2.4]")
                    .replace("focal_mm = 16", "focal_mm = 8")
                    + "\n[speckle]\ndot_diameter_mm = 2.0\ntexel_mm = 0.25\ntile_texels = 512\n")
    exp = config.load(path)
    chosen, plan = with_exposure(exp)
    (cam,) = plan.cameras
    first = stop_at_least(aperture_for(0.008, 6e-6, *cam.depth_m)[0], *exp.exposure.f_numbers)
    stops = [first] + [round(THIRD_STOP ** j, 2) for j in range(round(6 * math.log2(first)) + 3, 40, 3)
                       if round(THIRD_STOP ** j, 2) <= exp.exposure.f_numbers[1]]     # whole stops up
    base = layout_state(prepare(exp), predict_fields=False)
    totals = {}
    for stop in stops:    # the time follows the stop (max_ms is never reached): k stays the plan's
        t = exp.sensor.exposure_ms * 1e-3 * cam.gathered * (stop / 8) ** 2
        spec = dataclasses.replace(chosen.camera_specs[0], f_number=stop, exposure_time=t)
        assert exposure_factors([spec], exp.sensor)[0] == pytest.approx(cam.gathered)
        floors = measured.region_floors((spec,), exp.evaluation, exp.speckle, exp.sensor, exp.analysis,
                                        list(base.cameras), base.samples, base.visibility.visible,
                                        base.illumination, base.geometry.speckle)
        total = 0.0
        for *_, floor, _ in floors:
            model, j = floor["model"]
            n = len(model.bias)
            cov = model.covariance(np.full(n, floor["noise_rel"]), np.full(n, floor["patch_pixels"]))
            total += float(np.trace(cov[j]))
        totals[stop] = total
    best = min(totals, key=totals.get)
    assert cam.f_number == pytest.approx(best, abs=0.01), totals
    assert cam.f_number > stops[0]
