"""The scripting API (docs/api.md): checked edits in the file's names and units, a layout state
that carries the experiment it was judged with, the differentiable fields of the mount variables."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

import vdo
from vdo.config.experiment import parse
from vdo.config.reader import read_toml
from vdo.scene import cameras_of

ROOT = Path(__file__).resolve().parent.parent
BEAM = ROOT / "experiments" / "beam_column" / "ten_cameras.toml"
STEEL = ROOT / "experiments" / "steel_beam" / "four_point_bending.toml"
AT_CENTRE_PX = 1e-6     # px: a point on the optical axis projects this close to the principal point


@pytest.fixture(scope="module")
def beam():
    return vdo.prepare(vdo.load(BEAM).with_settings(evaluation={"sample_spacing_mm": 40}))


@pytest.fixture(scope="module")
def steel():
    return vdo.prepare(vdo.load(STEEL).with_settings(evaluation={"sample_spacing_mm": 40}))


def _opencv_pixel(cam, X):
    """X (3,) projected by OpenCV's pinhole model (an independent projection)."""
    rvec, _ = cv2.Rodrigues(cam.R)
    uv, _ = cv2.projectPoints(np.asarray(X, float)[None], rvec, cam.t, cam.K, None)
    return uv.reshape(2)


def test_edit_in_file_units_equals_the_file(beam, tmp_path):
    """with_camera(u=, focal_mm=, pan_deg=, tilt_deg=) gives the cameras of a file that says the same."""
    exp = beam.experiment
    edited = exp.with_camera("cam2", u=0.3, focal_mm=50, pan_deg=-20, tilt_deg=10)
    text = BEAM.read_text()
    data = read_toml(BEAM)
    entry = next(c for c in data["camera"] if c["name"] == "cam2")
    for key in ("target_m", "pan_deg", "tilt_deg"):
        entry.pop(key, None)
    entry.update(u=0.3, focal_mm=50, pan_deg=-20, tilt_deg=10)
    from_file = parse(data, BEAM).with_settings(evaluation={"sample_spacing_mm": 40})
    assert text   # the shipped file itself is unchanged
    for a, b in zip(cameras_of(edited.camera_specs, edited.rails), cameras_of(from_file.camera_specs, from_file.rails)):
        np.testing.assert_allclose(a.K, b.K, rtol=1e-12)
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.position, b.position, atol=1e-12)
    cam = cameras_of(edited.camera_specs, edited.rails)[1]
    assert cam.focal_length == pytest.approx(0.050) and math.degrees(cam.pan) == pytest.approx(-20)


@pytest.mark.parametrize("which,camera,move", [
    ("beam", "cam2", dict(u=0.3)),                                # slide along a rail
    ("steel", "left", dict(position_m=[-0.3, -1.4, 0.8])),        # step within a tripod zone
])
def test_a_move_reaims_at_the_aim_point(which, camera, move, beam, steel):
    """After a move the camera looks at the point of its old optical axis at the depth of the
    regions' centroid (vdo optimize's rule), checked with OpenCV's projection."""
    geometry = beam if which == "beam" else steel
    exp = geometry.experiment
    if which == "steel":   # aim it by pan and tilt first (the file aims it at a target)
        exp = exp.with_camera(camera, pan_deg=75.0, tilt_deg=8.0)
    c = [s.name for s in exp.camera_specs].index(camera)
    old = cameras_of(exp.camera_specs, exp.rails)[c]
    moved = exp.with_camera(camera, centre=geometry.centre, **move)
    new = cameras_of(moved.camera_specs, moved.rails)[c]
    depth = float((geometry.centre - old.position) @ old.optical_axis)
    aim = old.position + depth * old.optical_axis
    np.testing.assert_allclose(_opencv_pixel(old, aim), old.principal_point, atol=AT_CENTRE_PX)
    assert np.linalg.norm(new.position - old.position) > 0.01
    np.testing.assert_allclose(_opencv_pixel(new, aim), new.principal_point, atol=AT_CENTRE_PX)
    assert new.roll == pytest.approx(old.roll)


def test_a_camera_with_a_target_keeps_it(steel):
    exp = steel.experiment
    moved = steel.with_camera("left", position_m=[-0.3, -1.4, 0.8])
    new = cameras_of(moved.camera_specs, moved.rails)[0]
    target = exp.camera_specs[0].target
    np.testing.assert_allclose(_opencv_pixel(new, target), new.principal_point, atol=AT_CENTRE_PX)


@pytest.mark.parametrize("fields,field,fix", [
    (dict(u=1.3), 'camera "cam2".u', "runs from 0 to 1"),
    (dict(focal_mm=-50), 'camera "cam2".focal_mm', "positive"),
    (dict(pan_deg=-400), 'camera "cam2".pan_deg', "[-360.0, 360.0]"),
    (dict(tilt_deg=1000), 'camera "cam2".tilt_deg', "[-360.0, 360.0]"),
    (dict(focal=0.05), 'camera "cam2".focal', "did you mean 'focal_mm'"),
    (dict(u=0.3), 'camera "cam2"', "pass centre=geometry.centre"),
])
def test_bad_edits_are_one_line(beam, fields, field, fix):
    with pytest.raises(vdo.ConfigError) as err:
        beam.experiment.with_camera("cam2", **fields)
    text = str(err.value)
    assert "\n" not in text and err.value.field == field and fix in text


def test_bad_edits_outside_a_zone_and_unknown_camera(steel):
    with pytest.raises(vdo.ConfigError) as err:
        steel.with_camera("left", position_m=[-0.2, -1.3, 10.7])
    assert err.value.field == 'camera "left".position_m' and "outside zone 'tripod_left'" in str(err.value)
    with pytest.raises(vdo.ConfigError) as err:
        steel.with_camera("middle", focal_mm=12)
    assert "cameras: left, right" in str(err.value)


def test_the_file_refuses_an_angle_beyond_360(tmp_path):
    data = read_toml(BEAM)
    data["camera"][1] |= {"pan_deg": 400.0}
    with pytest.raises(vdo.ConfigError) as err:
        parse(data, BEAM)
    assert err.value.field == 'camera "cam2".pan_deg'


def test_with_settings_is_checked(beam):
    exp = beam.experiment.with_settings(sensor={"read_noise_e": 3.0}, evaluation={"patch_mm": 12})
    assert exp.sensor.read_noise_e == 3.0 and exp.evaluation.patch_size == pytest.approx(0.012)
    assert exp.evaluation.sample_spacing == pytest.approx(0.04)   # the other keys are kept
    with pytest.raises(vdo.ConfigError) as err:
        beam.experiment.with_settings(evaluation={"sample_spacing_mm": -1})
    assert err.value.field == "evaluation.sample_spacing_mm"
    with pytest.raises(vdo.ConfigError) as err:
        beam.experiment.with_settings(camera={"u": 1})
    assert "with_camera" in str(err.value)


# ---- one source of truth for a state ------------------------------------------------------
def test_a_batch_of_reparsed_variants_judges_each_variant(beam):
    """The first silent trap: a geometry prepared once, variants re-parsed from the file with
    another lens. Each state judges the variant's cameras, and its numbers equal those of a
    geometry prepared from the variant itself (an independent preparation)."""
    base = beam.experiment
    data = base.to_dict()
    for entry in data["camera"]:
        entry["focal_mm"] = 50.0
    variant = parse(data, BEAM)   # re-parsed: another object than the geometry's experiment
    state = vdo.layout_state(beam, variant)
    assert state.experiment is variant
    assert all(c.focal_length == pytest.approx(0.050) for c in state.cameras)
    alone = vdo.layout_state(vdo.prepare(variant))
    np.testing.assert_array_equal(state.prediction.sigma_max, alone.prediction.sigma_max)
    default = vdo.layout_state(beam)   # the geometry's own experiment: its 35 mm-class lenses
    assert not np.array_equal(default.prediction.sigma_max, state.prediction.sigma_max)


def test_a_geometry_from_another_experiment_is_refused(beam, steel):
    finer = beam.experiment.with_settings(evaluation={"sample_spacing_mm": 20})
    with pytest.raises(vdo.ConfigError) as err:
        vdo.layout_state(beam, finer)
    assert err.value.field == "evaluation.sample_spacing_mm" and "vdo.prepare(exp)" in str(err.value)
    with pytest.raises(vdo.ConfigError) as err:
        vdo.layout_state(beam, steel.experiment)
    assert err.value.field.startswith("mesh") and "\n" not in str(err.value)


@pytest.mark.parametrize("which", ["beam", "steel"])
def test_write_evaluation_writes_the_cameras_it_judged(which, beam, steel, tmp_path):
    """The second silent trap: a state of edited cameras (another lens, a moved camera) written by
    write_evaluation. Its config.toml, read back and judged afresh, gives the layout.json cameras
    and the summary.json numbers."""
    import dataclasses
    import json
    geometry = beam if which == "beam" else steel
    cams = cameras_of(geometry.experiment.camera_specs, geometry.experiment.rails)
    cams[0] = dataclasses.replace(cams[0], focal_length=cams[0].focal_length * 1.5)
    cams[1] = cams[1].with_pose(cams[1].position + np.array([0.02, 0.0, 0.03]), cams[1].pan + 0.05,
                                cams[1].tilt)
    state = vdo.layout_state(geometry, cams)
    result = vdo.write_evaluation(state, tmp_path / "run")
    again = vdo.load(tmp_path / "run" / "config.toml")
    layout = json.loads((tmp_path / "run" / "layout.json").read_text())
    for cam, written in zip(cameras_of(again.camera_specs, again.rails), cams):
        np.testing.assert_allclose(cam.K, written.K, rtol=1e-10)
        np.testing.assert_allclose(cam.R, written.R, atol=1e-10)
        np.testing.assert_allclose(cam.position, written.position, atol=1e-10)
    for cam, written in zip(cameras_of(again.camera_specs, again.rails), layout["cameras"]):   # config.toml agrees with layout.json
        assert cam.name == written["name"]
        np.testing.assert_allclose(cam.K, written["K"], rtol=1e-10)
        np.testing.assert_allclose(cam.R, written["R"], atol=1e-10)
        np.testing.assert_allclose(cam.t, written["t"], atol=1e-10)
    fresh = vdo.summary(vdo.layout_state(vdo.prepare(again)))
    written = json.loads((tmp_path / "run" / "summary.json").read_text())
    for name, region in fresh["regions"].items():
        assert written["regions"][name]["sigma_max_um"]["p95"] == pytest.approx(
            region["sigma_max_um"]["p95"], rel=1e-9, nan_ok=True)
    assert result.regions.keys() == fresh["regions"].keys()


# ---- a script's own objective, with gradients -------------------------------------------------
FD_STEP = 1e-6       # central differences in θ (logit, rad) and in mm: O(h^2) truncation ~1e-6 relative
GRAD_RTOL = 1e-4     # max |AD - FD| / max |FD|, as tests/test_objective.py holds the score's gradient


def _masked_objective(mask):
    """Area-weighted mean out-of-plane σ (µm) over the samples in `mask` + a coverage shortfall term."""
    import jax.numpy as jnp

    def out_of_plane(f):
        w = f.area * mask
        short = jnp.maximum(f.min_cameras[f.region] - f.coverage, 0.0)
        return (jnp.sum(w * f.sigma_xyz[:, 2]) / jnp.sum(w) * 1e6
                + 10.0 * jnp.sum(f.area * short ** 2) / jnp.sum(f.area))
    return out_of_plane


@pytest.mark.parametrize("path", [BEAM.parent / "three_cameras.toml", STEEL])
def test_gradient_of_a_user_objective_matches_finite_differences(path):
    import jax
    import jax.numpy as jnp
    from vdo.search.mountmodel import MountModel
    model = MountModel(vdo.load(path).with_settings(evaluation={"sample_spacing_mm": 40}), float64=True)
    theta, focal = jnp.asarray(model.theta0), jnp.asarray(model.focal0_mm)
    first = model.fields(theta)
    assert first.sigma_xyz.shape == (first.area.shape[0], 3) and first.information.shape[1:] == (3, 3)
    # the fields at the configured layout are the report's: information as vdo.physics.predict's first pass
    mask = jnp.asarray(np.asarray(first.sigma_max) < 100e-6, dtype=float)   # well measured at the start
    objective = _masked_objective(mask)
    J = jax.jit(lambda t, f: objective(model.fields(t, f)))
    g_theta, g_focal = jax.jit(jax.grad(lambda t, f: objective(model.fields(t, f)), argnums=(0, 1)))(theta, focal)
    fd_theta = np.array([(J(theta + e, focal) - J(theta - e, focal)) / (2 * FD_STEP)
                         for e in FD_STEP * np.eye(len(theta))])
    fd_focal = np.array([(J(theta, focal + e) - J(theta, focal - e)) / (2 * FD_STEP)
                         for e in FD_STEP * np.eye(len(focal))])
    assert np.max(np.abs(fd_theta)) > 0 and np.max(np.abs(fd_focal)) > 0
    assert np.max(np.abs(np.asarray(g_theta) - fd_theta)) < GRAD_RTOL * np.max(np.abs(fd_theta))
    assert np.max(np.abs(np.asarray(g_focal) - fd_focal)) < GRAD_RTOL * np.max(np.abs(fd_focal))
    assert len(model.names) == len(theta) and all("." in n for n in model.names)


@pytest.mark.parametrize("bad,says", [
    (lambda f: float(f.sigma_max[0]), "is not JAX-traceable"),
    (lambda f: np.asarray(f.sigma_max).mean(), "is not JAX-traceable"),
    (lambda f: f.sigma_max * 2, "returns shape (4,)"),
    ("sigma", "must be a function"),
])
def test_a_bad_user_objective_is_refused_in_one_line(bad, says, tmp_path):
    exp = vdo.load(BEAM.parent / "three_cameras.toml")
    with pytest.raises(vdo.ConfigError) as err:
        vdo.optimize_experiment(exp, tmp_path / "never", objective=bad)
    assert says in str(err.value) and "\n" not in str(err.value)
    assert not (tmp_path / "never").exists()


# ---- regions and results for scripts ----------------------------------------------------------
@pytest.mark.parametrize("which", ["beam", "steel"])
def test_region_stats_are_the_summary_numbers(which, beam, steel, tmp_path):
    import csv
    from vdo.core.table import write_csv
    geometry = beam if which == "beam" else steel
    state = vdo.layout_state(geometry)
    summary = vdo.summary(state)
    rows = state.regions()
    assert [r.region for r in rows] == list(summary["regions"])
    for r in rows:
        s = summary["regions"][r.region]
        assert r.area_m2 == pytest.approx(s["area_m2"], rel=1e-12)
        assert r.seen_by_2_or_more == pytest.approx(s["seen_by_2_or_more"], abs=1e-12)
        assert r.measured_fraction == pytest.approx(1 - s["unmeasured_fraction"], abs=1e-12)
        for mine, theirs in ((r.sigma_max_um_p95, s["sigma_max_um"]["p95"]),
                             (r.sigma_max_um_max, s["sigma_max_um"]["max"]),
                             (r.sigma_z_um_p95, s["sigma_axis_um"]["z"]["p95"])):
            assert (mine is None and theirs is None) or mine == pytest.approx(theirs, rel=1e-12)
        mask = state.region_mask(r.region)   # covered: an independent count over the samples
        need = r.min_cameras
        area = geometry.samples.area
        assert r.covered_fraction == pytest.approx(
            area[mask & (state.prediction.coverage >= need)].sum() / area[mask].sum())
    path = write_csv(tmp_path / "regions.csv", rows)
    with open(path) as fh:
        back = list(csv.DictReader(fh))
    assert [b["region"] for b in back] == [r.region for r in rows]
    assert float(back[0]["area_m2"]) == pytest.approx(rows[0].area_m2, rel=1e-12)
    with pytest.raises(vdo.ConfigError) as err:
        state.region_mask("nowhere")
    assert "regions: " in str(err.value)


# ---- sweeps from Python -----------------------------------------------------------------------
def test_a_python_sweep_of_variants_runs_and_resumes(tmp_path):
    """Variants built in code through the sweep engine (one local worker): each row holds the
    numbers of its own experiment judged in this process, and a second call reuses every point."""
    import csv
    from vdo.commands.sweep import sweep_variants
    base = vdo.load(BEAM.parent / "three_cameras.toml").with_settings(evaluation={"sample_spacing_mm": 40})
    variants = []
    for focal in (25, 50):
        exp = base
        for spec in base.camera_specs:
            exp = exp.with_camera(spec.name, focal_mm=focal)
        variants.append(({"focal_mm": focal}, exp))
    first = sweep_variants(variants, tmp_path / "sweep", workers=1)
    assert (first["points"], first["done"], first["computed"]) == (2, 2, 2)
    for (values, exp), row in zip(variants, first["rows"]):
        assert row["focal_mm"] == values["focal_mm"]
        mine = vdo.layout_state(vdo.prepare(exp)).region_stats("joint_top")
        assert row["joint_top.sigma_p95_um"] == pytest.approx(mine.sigma_max_um_p95, rel=1e-9)
    again = sweep_variants(variants, tmp_path / "sweep", workers=1)
    assert (again["computed"], again["reused"]) == (0, 2)
    with open(tmp_path / "sweep" / "results.csv") as fh:
        assert [r["status"] for r in csv.DictReader(fh)] == ["done", "done"]
    with pytest.raises(vdo.ConfigError) as err:
        sweep_variants([({"a": 1}, base), ({"b": 2}, base)], tmp_path / "bad")
    assert "same keys" in str(err.value)


# ---- compilation made predictable ----------------------------------------------------------------
_COMPILES = {"on": False, "n": 0}


def _count(name, secs, **kw):
    if _COMPILES["on"] and name in ("/jax/core/compile/backend_compile_duration",
                                    "/jax/compilation_cache/cache_retrieval_time_sec"):
        _COMPILES["n"] += 1


@pytest.mark.parametrize("which,camera,moves", [
    ("beam", "cam1", [dict(u=float(u)) for u in np.linspace(0.05, 0.95, 50)[:8]]),
    ("steel", "left", [dict(position_m=[x, -1.3, 0.7]) for x in np.linspace(-1.0, -0.2, 5)]),
])
def test_new_camera_positions_compile_nothing_after_warm_up(which, camera, moves, steel):
    """After `vdo.warm_up`, layouts never judged before (a camera at new rail or zone positions)
    run no JAX compilation and load nothing from the compilation cache (at 10 mm spacing on the
    beam, the bucketed pair lists recompiled at new positions)."""
    import jax
    exp = vdo.load(BEAM.parent / "three_cameras.toml") if which == "beam" else steel.experiment
    geometry = vdo.prepare(exp.with_settings(evaluation={"sample_spacing_mm": 10 if which == "beam" else 20}))
    jax.monitoring.register_event_duration_secs_listener(_count)
    assert vdo.warm_up(geometry, geometry.with_camera(camera, **moves[0])) > 0
    _COMPILES.update(on=True, n=0)
    try:
        for move in moves[1:]:
            vdo.layout_state(geometry, geometry.with_camera(camera, **move))
    finally:
        _COMPILES["on"] = False
    assert _COMPILES["n"] == 0


def test_fixed_pair_list_sizes_leave_the_fields_unchanged(beam):
    """The padded lists (Geometry.sizes) give the fields of the bucketed ones, and a layout that
    sees nothing (no pair) still works after a layout that set the sizes."""
    from vdo import objective
    from vdo.physics.predict import samples_for_objective, settings, view_data
    state = vdo.layout_state(beam)
    exp, samples = beam.experiment, beam.samples
    smp = samples_for_objective(exp.regions, samples)
    cams = objective.CameraParams.from_cameras(state.cameras)
    sizes: dict = {}
    fixed = view_data(exp.speckle, exp.sensor, smp, state.visibility, state.illumination, beam.speckle,
                      sizes=sizes)
    plain = view_data(exp.speckle, exp.sensor, smp, state.visibility, state.illumination, beam.speckle)
    assert sizes and fixed.n_blocks >= plain.n_blocks - plain.chunk
    a = objective.fields(cams, smp, fixed, beam.speckle.table, settings(exp.evaluation))
    b = objective.fields(cams, smp, plain, beam.speckle.table, settings(exp.evaluation))
    np.testing.assert_allclose(np.asarray(a.information), np.asarray(b.information), rtol=1e-12, atol=0)
    empty = objective.ViewData.from_dense(np.zeros((len(state.cameras), len(samples))), 1.0, 1.0, smp,
                                          sizes=sizes)
    assert empty.n_pairs == 0 and empty.n_blocks >= 1
