"""`vdo evaluate` says what is wrong with a hand layout: the optimizer's constraint checks
(`vdo.optimize.layout_checks`), a camera that sees no region and a light that lights no sample, checked against closed forms
and trimesh's exact distances; `vdo check` and `vdo render --cameras` refuse bad names in one
line before any work."""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from conftest import DOWN_CAMERA
from vdo.commands import cli
from vdo.commands.evaluate import evaluate
from vdo.config.experiment import load
from vdo.model.camera import Camera
from vdo.scene import camera_body, cameras_of

ROOT = Path(__file__).resolve().parents[2]
PLATE = ROOT / "experiments" / "holed_plate" / "stereo.toml"
CLEARANCE_SAMPLING_M = 0.02   # the check measures to points 15 mm apart and 400 body points


def _plate(tmp_path: Path, left_position, right_target) -> Path:
    """The holed-plate stereo pair at 5 mm samples, the left camera moved and the right one
    re-aimed."""
    text = PLATE.read_text().replace('file = "meshes/', f'file = "{PLATE.parent}/meshes/')
    text = text.replace("sample_spacing_mm = 1", "sample_spacing_mm = 5")
    text = text.replace("position_m = [-0.152, -0.686, 1.0]", f"position_m = {list(left_position)}")
    text = text.replace('''position_m = [0.152, -0.686, 1.0]
target_m = [0, -0.0025, 1.0]''', f'''position_m = [0.152, -0.686, 1.0]
target_m = {list(right_target)}''')
    path = tmp_path / "plate.toml"
    path.write_text(text)
    return path


def _axis(position, target) -> np.ndarray:
    d = np.asarray(target, float) - np.asarray(position, float)
    return d / np.linalg.norm(d)


def test_evaluate_reports_clearance_axis_angle_and_a_blind_camera(tmp_path, caplog):
    left = (-0.06, -0.10, 1.0)            # 0.1 m in front of the plate: inside the 50 mm clearance?
    away = (0.6, -1.5, 1.0)               # the right camera looks away from the plate
    exp = load(_plate(tmp_path, left, away))
    with caplog.at_level(logging.WARNING, logger="vdo"):
        result = evaluate(exp, tmp_path / "run")
    assert result.cameras_seeing_nothing == ["right"]
    assert any("camera right sees no region" in r.getMessage() for r in caplog.records)

    checks = json.loads((tmp_path / "run" / "constraints.json").read_text())
    assert checks == result.constraints
    by = {(c["constraint"], tuple(c.get("cameras", ()))): c for c in checks["checks"]}

    # the axis angle of the [[stereo_pair]]: the closed form from positions and targets
    angle = by[("axis_angle", ("left", "right"))]["value"]
    target = (0, -0.0025, 1.0)
    expected = math.degrees(math.acos(np.clip(_axis(left, target) @ _axis((0.152, -0.686, 1.0), away),
                                              -1, 1)))
    assert angle == pytest.approx(expected, abs=1e-6)
    assert by[("axis_angle_max", ("left", "right"))]["met"] == (expected <= 35 + 1e-6)

    # the clearance of the left camera: trimesh's exact distance from its body to the meshes
    cam = next(c for c in cameras_of(exp.camera_specs, exp.rails) if c.name == "left")
    body = camera_body(cam)
    points = trimesh.sample.sample_surface_even(
        trimesh.Trimesh(body.vertices, body.faces, process=False), 300, seed=1)[0]
    exact = min(trimesh.proximity.closest_point_naive(
        trimesh.load(m.path, force="mesh").apply_scale(m.scale), points)[1].min() for m in exp.meshes)
    clearance = by[("clearance", ("left",))]
    assert clearance["value"] == pytest.approx(exact, abs=CLEARANCE_SAMPLING_M)
    assert clearance["met"] == (clearance["value"] >= exp.optimize.clearance)
    warned = [r.getMessage() for r in caplog.records if "not met" in r.getMessage()]
    assert len(warned) == checks["violations"] and checks["violations"] >= 1


def test_check_and_render_cameras_refuse_in_one_line(tmp_path, capsys):
    assert cli.main(["check", str(PLATE), str(ROOT / "experiments" / "beam_column" / "sweep.toml")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"ok: {PLATE}: experiment") and "2 cameras" in out[0]
    assert out[1].endswith("sweep file, 24 points")

    bad = tmp_path / "bad.toml"
    bad.write_text(PLATE.read_text().replace('file = "meshes/', f'file = "{PLATE.parent}/meshes/')
                   .replace("focal_mm = 25", "focal_mm = -25", 1))
    assert cli.main(["check", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "focal_mm" in err[0] and str(bad) in err[0]

    assert cli.main(["render", str(PLATE), "--out", str(tmp_path / "r"), "--cameras", "left,nobody"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {PLATE}: --cameras: no camera is named 'nobody': give names of left, "
                   "right, separated by commas"]
    assert not (tmp_path / "r").exists()


def test_render_only_the_named_cameras(tmp_path):
    """`--cameras left` renders the left camera alone, pixel for pixel as in a render of both
    (same seed per camera; the right camera stays in the scene as a body)."""
    from vdo.render import render_images

    exp = load(PLATE)
    one = render_images(exp, scale=0.05, spp=2, seed=1, only=["left"])
    both = render_images(exp, scale=0.05, spp=2, seed=1)
    assert list(one.images) == ["left"] and [c.name for c in one.cameras] == ["left"]
    assert np.array_equal(one.images["left"], both.images["left"])
    assert isinstance(one.cameras[0], Camera)


CRATE = '[[mesh]]\nname = "crate"\nfile = "crate.stl"\nunit = "mm"\nrole = "obstacle"\n'


def _light(name, position, target) -> str:
    return (f'\n[[light]]\nname = "{name}"\nposition_m = {list(position)}\ntarget_m = {list(target)}\n'
            "size_m = [0.2, 0.2]\nradiance = 20\n")


def test_evaluate_says_a_light_that_lights_no_sample(plate_experiment, tmp_path, caplog):
    """Three panels over the plate (top face at z = 0) and a closed crate floating above it
    (z 0.2 to 0.4 m): 'over' faces the plate and lights it (not named); 'boxed' stands inside the
    crate facing down, every sight line to it blocked by the crate's floor (named with the
    crate); 'skyward' faces up, away from every sample (named, no mesh)."""
    lights = (_light("over", [-0.3, 0.0, 1.0], [0, 0, 0]) + _light("boxed", [0.3, 0.3, 0.3], [0.3, 0.3, 0])
              + _light("skyward", [0.0, 0.0, 1.0], [0, 0, 2]))
    path = plate_experiment(spacing=50, files=[("crate.stl", [300, 300, 200], [300, 300, 300])],
                            extra_meshes=CRATE,
                            cameras=DOWN_CAMERA.format(name="down", focal=24, u=0.5) + lights)
    with caplog.at_level(logging.WARNING, logger="vdo"):
        evaluate(load(path), tmp_path / "run")
    said = sorted(r.getMessage() for r in caplog.records if "lights no region sample" in r.getMessage())
    assert said == [
        "warning: light 'boxed' lights no region sample (its centre is inside mesh 'crate'): move it "
        "(position_m) out of the mesh",
        "warning: light 'skyward' lights no region sample (it faces away from them, or something "
        "blocks it): aim it at the regions (target_m) or move it (position_m)"], said
