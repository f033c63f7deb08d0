"""`vdo evaluate` with a [calibration] table: the calibration-induced errors per region beside the
image noise's (summary.json, maps/calibration_strain.png, report.html), and with --calibration the
lab's calibration files as the cameras; without the table none of this work is done."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from vdo.config.experiment import load, parse
from vdo.scene import cameras_of

ROOT = Path(__file__).resolve().parents[2]
PLATE = ROOT / "experiments" / "holed_plate" / "stereo.toml"
CALIBRATION = """
[calibration]
poses_per_camera = 5
shared_poses = 3
detection_sigma_px = 0.05
"""
SAME = 1e-9     # relative: the same computation, or a closed-form scaling of it
FD_SCALING = 1e-4   # relative: dX/dtheta's central-difference step is FD_STEP sigma, so doubling
                    # sigma changes its O(step^2) truncation (measured 1e-5)


def plate(tmp_path: Path, extra: str = CALIBRATION) -> Path:
    """The holed-plate stereo pair at 5 mm samples with `extra` appended."""
    text = PLATE.read_text().replace('file = "meshes/', f'file = "{PLATE.parent}/meshes/')
    path = tmp_path / "plate.toml"
    path.write_text(text.replace("sample_spacing_mm = 1", "sample_spacing_mm = 5") + extra)
    return path


def test_calibration_table_is_asked_for(tmp_path):
    """Only a file with [calibration] asks for the work, and a to_dict round trip keeps that."""
    from vdo.commands.calibrate import evaluation_plan

    bare, given = load(plate(tmp_path, "")), load(plate(tmp_path))
    assert not bare.has("calibration") and given.has("calibration")
    assert not parse(bare.to_dict(), bare.path).has("calibration")
    assert parse(given.to_dict(), given.path).calibration.poses_per_camera == 5
    assert evaluation_plan(bare, None) is None          # returns before touching the geometry


def test_evaluate_gives_calibration_errors_with_imported_cameras(tmp_path, capsys):
    """`vdo evaluate CONFIG --calibration <OpenCV files>` on a file with [calibration]: the run's
    cameras are the imported ones (the lab moved the left camera 10 mm), and summary.json gives per
    region the calibration-induced displacement and strain beside the image noise's, the strain
    at the test's level the per-unit value times the level; the report shows them."""
    from vdo.formats.opencv import write
    from vdo.commands.cli import main

    config = plate(tmp_path)
    exp = load(config)
    lab = exp.with_camera("left", position_m=[-0.142, -0.686, 1.0])
    (tmp_path / "lab").mkdir()
    files = write(cameras_of(lab.camera_specs, lab.rails), [], tmp_path / "lab", config)
    out = tmp_path / "run"
    assert main(["evaluate", str(config), "--out", str(out), "--calibration", *map(str, files)]) == 0
    assert "calib strain ue" in capsys.readouterr().out
    layout = {c["name"]: c for c in json.loads((out / "layout.json").read_text())["cameras"]}
    for cam in cameras_of(lab.camera_specs, lab.rails):
        np.testing.assert_allclose(layout[cam.name]["position_m"], cam.position, atol=1e-9)
    summary = json.loads((out / "summary.json").read_text())
    cal = summary["calibration"]
    assert cal["sigma_det_px"] == 0.05 and cal["pairs"] == ["left:right"]
    front = cal["regions"]["front"]
    for key in ("calibration_displacement_um", "calibration_strain_microstrain",
                "noise_displacement_um", "noise_strain_microstrain"):
        assert 0 < front[key]["p50"] <= front[key]["p95"] < np.inf, key
    assert front["calibration_strain_microstrain"]["p95"] == pytest.approx(
        front["calibration_strain_per_unit_strain"]["p95"] * front["test_strain"] * 1e6, rel=SAME)
    assert (out / "maps" / "calibration_strain.png").is_file()
    page = (out / "report.html").read_text()
    assert "Calibration-induced errors beside the image noise" in page


def test_calibration_errors_scale_with_detection_noise(tmp_path):
    """The covariance is sigma_det^2 (J^T J)^-1 at the true cameras (noise-free corners): twice
    the detection noise gives twice every calibration-induced sigma (to the finite differences'
    truncation), and the noise columns
    are the evaluation's own strain fields (`LayoutState.strain`)."""
    from vdo.commands.calibrate import evaluation_errors, evaluation_plan
    from vdo.state import layout_state, prepare

    exp = load(plate(tmp_path))
    geometry = prepare(exp)
    planned = evaluation_plan(exp, geometry)
    state = layout_state(geometry)
    one, errors = evaluation_errors(planned, state)
    doubled = replace(exp, calibration=replace(exp.calibration, detection_sigma_px=0.1))
    two, _ = evaluation_errors(planned, replace(state, source=doubled))
    for region, r in one["regions"].items():
        for key, v in r.items():
            if key.startswith("calibration_"):
                for q in ("p50", "p95"):
                    assert two["regions"][region][key][q] == pytest.approx(2 * v[q], rel=FD_SCALING), key
    eps = state.strain[0][:, 0]
    m = state.samples.region == 0
    assert one["regions"]["front"]["noise_strain_microstrain"]["p95"] == pytest.approx(
        np.percentile(eps[m][np.isfinite(eps[m])], 95) * 1e6, rel=SAME)
    assert np.isfinite(errors.strain).any()


def test_evaluate_says_which_camera_came_from_which_calibration_file(tmp_path, capsys):
    """`vdo evaluate --calibration left.yml` (the lab's file of one camera): the console says
    which camera took its pose and intrinsics from which file and which kept the experiment's,
    summary.json's "calibration_files" maps camera -> file, and config.toml opens with the same
    lines as comments and loads again (before, none of them said a calibration file was used)."""
    from vdo.formats.opencv import write
    from vdo.commands.cli import main

    config = plate(tmp_path, "")
    exp = load(config)
    lab = exp.with_camera("left", position_m=[-0.142, -0.686, 1.0])
    (tmp_path / "lab").mkdir()
    files = write(cameras_of(lab.camera_specs, lab.rails), [], tmp_path / "lab", config)
    left = next(str(p) for p in files if Path(p).name == "left.yml")
    out = tmp_path / "run"
    assert main(["evaluate", str(config), "--out", str(out), "--calibration", left]) == 0
    lines = [f"camera left: pose and intrinsics from the calibration file {left}",
             "camera right: in no calibration file, as the experiment file gives them"]
    err = capsys.readouterr().err.splitlines()
    assert all(line in err for line in lines)
    assert json.loads((out / "summary.json").read_text())["calibration_files"] == {"left": left}
    text = (out / "config.toml").read_text()
    assert text.startswith("".join(f"# {line}\n" for line in lines))
    back = cameras_of(load(out / "config.toml").camera_specs, lab.rails)
    np.testing.assert_allclose(back[0].position, [-0.142, -0.686, 1.0], atol=1e-9)
