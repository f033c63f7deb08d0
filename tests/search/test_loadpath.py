"""Keyframes and the load path: poses against scipy's rotations, displaced samples against a
closed-form field, and a camera that loses its region at a step known from the geometry."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import mesh_tables, write_box
from vdo.core.errors import ConfigError
from vdo.geometry.keyframes import LoadPath, Pose, at_step, read_displacements, read_poses, rotation_xyz

SHUTTER = """
[[mesh]]
name = "shutter"
file = "shutter.stl"
unit = "mm"
role = "obstacle"
"""


@pytest.mark.parametrize("angles", [(10.0, 0.0, 0.0), (0.0, -22.0, 5.0), (30.0, 40.0, -50.0)])
def test_rotation_order_matches_scipy_extrinsic_xyz(angles):
    expected = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()   # extrinsic x, y, z
    np.testing.assert_allclose(rotation_xyz(*np.radians(angles)), expected, atol=1e-14)


def test_pose_turns_about_its_pivot():
    pose = Pose(rotation_xyz(0, 0, math.pi / 2), np.array([0.0, 0.0, 0.1]), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(pose.move(np.array([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0]])),
                               [[1.0, 1.0, 0.1], [1.0, 0.0, 0.1]], atol=1e-14)


def write_csv(path, text):
    path.write_text(text.strip() + "\n")
    return path


def test_pose_file_units_and_pivot(tmp_path):
    f = write_csv(tmp_path / "poses.csv", """
step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg
1,top,10,0,0,0,0,90
2,top,0,0,0,0,0,0
""")
    poses = read_poses(f, {"top": ("a",)}, {"top": np.zeros(3)})
    np.testing.assert_allclose(poses[(1, "top")].move(np.array([1.0, 0, 0])), [0.01, 1.0, 0], atol=1e-12)
    np.testing.assert_allclose(poses[(2, "top")].rotation, np.eye(3))


@pytest.mark.parametrize("text, where, words", [
    ("step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n1,platform,0,0,0,0,0,0", "row 2", "neither a [[group]] nor a [[mesh]]"),
    ("step,group,x_mm,y_mm,rx_deg,ry_deg,rz_deg\n1,top,0,0,0,0,0", "column z", "z_<unit>"),
    ("step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n1,top,0,abc,0,0,0,0", "row 2", "expected a number"),
    ("step,group,x_mm,y_mm,z_mm,rx_rad,ry_rad,rz_rad\n1,top,0,0,0,0,0,20", "row 2", "in degrees"),
    ("step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n1.5,top,0,0,0,0,0,0", "row 2", "whole number"),
    ("step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n1,top,0,0,0,0,0,0\n1,top,0,0,0,0,0,0", "row 3", "second pose"),
])
def test_bad_pose_files_name_the_row_and_the_fix(tmp_path, text, where, words):
    f = write_csv(tmp_path / "poses.csv", text)
    with pytest.raises(ConfigError) as info:
        read_poses(f, {"top": ("a",)}, {"top": np.zeros(3)})
    assert str(f) in str(info.value) and where in str(info.value) and words in str(info.value)


def test_bad_row_is_named_by_its_line_in_the_file(tmp_path):
    """Comment and blank lines (the shipped CSVs open with a comment) count: the row a message
    names is the line an editor or a spreadsheet shows, found here by searching the text."""
    text = ("# a comment line, as the shipped load paths have\n"
            "step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n"
            "1,top,0,0,0,0,0,0\n"
            "\n"
            "# another comment\n"
            "2,top,0,nan,0,0,0,0\n")
    f = tmp_path / "poses.csv"
    f.write_text(text)
    line = text.splitlines().index("2,top,0,nan,0,0,0,0") + 1
    with pytest.raises(ConfigError, match=rf"row {line}: column y_mm: nan is not finite"):
        read_poses(f, {"top": ("a",)}, {"top": np.zeros(3)})
    d = tmp_path / "disp.csv"
    d.write_text("# comment\nstep,x_m,y_m,z_m,ux_mm,uy_mm,uz_mm\n1,0,0,0,0,0,0\n1,5,5,5,0,0,0\n")
    with pytest.raises(ConfigError, match=r"row 4: node \[5.0, 5.0, 5.0\] m"):
        read_displacements(d, np.zeros((1, 3)), "plate")


def test_node_positions_in_millimetres_under_metre_columns_name_the_columns(tmp_path):
    """A vertex at (0.1, 0.2, 0.3) m written in mm under x_m columns: the message names the unit
    slip and the columns; under x_mm columns the same row moves that vertex by its 5 mm."""
    vertices = np.array([[0.1, 0.2, 0.3], [1.0, 1.0, 1.0]])
    f = tmp_path / "disp.csv"
    f.write_text("step,x_m,y_m,z_m,ux_mm,uy_mm,uz_mm\n1,100,200,300,0,0,5\n")
    with pytest.raises(ConfigError, match=r"row 2: .*at 0\.001 times it is a vertex: the positions are in mm, "
                                          r"so name their columns x_mm, y_mm, z_mm \(not _m\)"):
        read_displacements(f, vertices, "plate")
    f.write_text("step,x_mm,y_mm,z_mm,ux_mm,uy_mm,uz_mm\n1,100,200,300,0,0,5\n")
    np.testing.assert_allclose(read_displacements(f, vertices, "plate")[1], [[0, 0, 0.005], [0, 0, 0]])


def test_radians_in_degree_columns_are_warned(tmp_path, caplog):
    f = write_csv(tmp_path / "poses.csv", "step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n"
                                          "1,top,0,0,0,0.05,0,0\n2,top,0,0,0,0.1,0,-0.12")
    with caplog.at_level(logging.WARNING, logger="vdo"):
        read_poses(f, {"top": ("a",)}, {"top": np.zeros(3)})
    assert "rx_rad" in caplog.text


def test_deformed_plate_samples_follow_a_linear_field(plate_experiment, tmp_path):
    from vdo.config import experiment as config
    from vdo.state import prepare

    geometry = prepare(config.load(plate_experiment(spacing=100)))
    plate = geometry.meshes[0]
    a = 0.02                                                      # uz = a x (a tilt)
    rows = ["step,x_m,y_m,z_m,ux_mm,uy_mm,uz_mm"]
    rows += [f"3,{float(x)!r},{float(y)!r},{float(z)!r},0,0,{float(a * x * 1e3)!r}" for x, y, z in plate.vertices]
    f = write_csv(tmp_path / "disp.csv", "\n".join(rows))
    u = read_displacements(f, plate.vertices, "plate")
    lp = LoadPath(steps=(3,), groups={}, poses={}, deformed_mesh="plate", displacements=u)
    moved = at_step(geometry, lp, 3, regions=geometry.experiment.regions)
    rest = geometry.samples.points
    np.testing.assert_allclose(moved.samples.points[:, 2] - rest[:, 2], a * rest[:, 0], atol=1e-12)
    np.testing.assert_allclose(moved.meshes[0].vertices[:, 2] - plate.vertices[:, 2],
                               a * plate.vertices[:, 0], atol=1e-12)

    bad = write_csv(tmp_path / "bad.csv", "step,x_m,y_m,z_m,ux_mm,uy_mm,uz_mm\n1,0.2,0.2,0,0,0,1")
    with pytest.raises(ConfigError, match=r"row 2.*nearest vertex of mesh 'plate'"):
        read_displacements(bad, plate.vertices, "plate")


def test_camera_loses_the_region_at_the_step_the_geometry_says(plate_experiment, tmp_path):
    """A 1.2 m shutter at z = 0.75 slides in -x by 0.5 m per step from x = 3 m. The camera at
    (0, 0, 1.5) looks down at the 1 m plate: its rays cross z = 0.75 at x/2, |x/2| <= 0.25. The
    shutter's near edge is at 2.4 - 0.5 k: at step 4 (0.4) it hides nothing; at step 5 (-0.1) it
    hides every plate point with x > -0.2, 70 % of the plate: the camera loses it at step 5."""
    from vdo.config import experiment as config
    from vdo.search.loadpath import evaluate_load_path
    from vdo.state import prepare

    write_box(tmp_path / "shutter.stl", [1200, 1200, 10], [3000, 0, 750])
    exp = config.load(plate_experiment(spacing=50, extra_meshes=SHUTTER))
    geometry = prepare(exp)
    steps = tuple(range(1, 8))
    poses = {(k, "slide"): Pose(np.eye(3), np.array([-0.5 * k, 0.0, 0.0]), np.zeros(3)) for k in steps}
    lp = LoadPath(steps=steps, groups={"slide": ("shutter",)}, poses=poses)
    result = evaluate_load_path(geometry, lp)
    assert [(x["camera"], x["region"], x["step"]) for x in result.losses] == [("down", "top", 5)]
    seen = result.seen_fraction[:, 0, 0]
    assert seen[0] >= 0.85 and np.all(seen[1:5] == seen[0])         # rest and steps 1-4 unchanged
    # Step 5: the shutter hides x > -0.2; the camera's footprint already cut y to +-0.46 m.
    assert seen[5] == pytest.approx(seen[0] * 0.3, abs=0.05)
    assert np.all(result.worst_coverage[geometry.samples.points[:, 0] > 0] == 0)


def test_a_path_that_returns_to_a_pose_is_judged_as_each_of_its_steps(plate_experiment, tmp_path):
    """The shutter of the test above slides in and back out (-2.5 m, 0: the identity, -2.5 m
    again), then turns about its own centre. Steps that repeat a geometry share its key (the
    identity has the rest key), and the judgement of every step equals a layout state computed
    at that step on its own."""
    from vdo.config import experiment as config
    from vdo.geometry.keyframes import at_step
    from vdo.search.loadpath import evaluate_load_path
    from vdo.state import layout_state, prepare

    write_box(tmp_path / "shutter.stl", [1200, 1200, 10], [3000, 0, 750])
    exp = config.load(plate_experiment(spacing=50, extra_meshes=SHUTTER))
    geometry = prepare(exp)
    slide = lambda x: Pose(np.eye(3), np.array([x, 0.0, 0.0]), np.zeros(3))
    turn = Pose(rotation_xyz(0.0, 0.0, 0.3), np.zeros(3), np.array([3.0, 0.0, 0.75]))
    poses = {(1, "slide"): slide(-2.5), (2, "slide"): slide(0.0), (3, "slide"): slide(-2.5),
             (4, "slide"): turn}
    lp = LoadPath(steps=(1, 2, 3, 4), groups={"slide": ("shutter",)}, poses=poses)
    keys = [lp.step_key(k) for k in lp.steps]
    assert keys[1] == () and keys[0] == keys[2] and len({keys[0], keys[3], ()}) == 3
    result = evaluate_load_path(geometry, lp)
    assert result.seen_fraction[1, 0, 0] < 0.9 * result.seen_fraction[0, 0, 0]   # step 1 hides
    for index, step in enumerate(lp.steps, start=1):
        alone = layout_state(at_step(geometry, lp, step, regions=exp.regions), strain_fields=False).prediction
        np.testing.assert_array_equal(result.coverage[index], alone.coverage)
        np.testing.assert_allclose(result.sigma_max[index], np.where(alone.measured, alone.sigma_max, np.inf),
                                   rtol=1e-12)


def test_evaluate_over_the_load_path_names_the_loss_and_writes_the_worst_case(plate_experiment,
                                                                              tmp_path, capsys):
    """`vdo evaluate` on the shutter scene with a [load_path]: the warning, summary.json's loss,
    load_path.csv, the worst-case arrays and maps."""
    import json

    from vdo.commands import cli
    from vdo.core.vtp import read_points

    write_box(tmp_path / "shutter.stl", [1200, 1200, 10], [3000, 0, 750])
    rows = ["step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg"]
    rows += [f"{k},slide,{-500 * k},0,0,0,0,0" for k in range(1, 8)]
    write_csv(tmp_path / "poses.csv", "\n".join(rows))
    extra = SHUTTER + '\n[[group]]\nname = "slide"\nmeshes = ["shutter"]\n\n[load_path]\nposes = "poses.csv"\n'
    config = plate_experiment(spacing=100, extra_meshes=extra)
    out = tmp_path / "run"
    assert cli.main(["evaluate", str(config), "--out", str(out)]) == 0
    assert "warning: camera down loses region top at step 5" in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert [(x["camera"], x["step"]) for x in summary["load_path"]["losses"]] == [("down", 5)]
    assert summary["load_path"]["steps"] == 7
    table = (out / "load_path.csv").read_text().splitlines()
    assert table[0] == "step,region,covered_fraction,sigma_max_p95_um" and len(table) == 1 + 8
    points, arrays = read_points(out / "samples.vtp")
    hidden = points[:, 0] > 0
    assert np.all(arrays["coverage_worst"][hidden] == 0)
    assert np.all(arrays["worst_step"][hidden] >= 0)
    assert (out / "load_path.png").is_file() and (out / "maps" / "coverage_worst.png").is_file()


def test_every_kth_step_and_the_last_are_judged():
    """[load_path] every = k keeps every k-th step of the files and the last one, after every row
    was checked."""
    from vdo.config.experiment import load
    from vdo.geometry.keyframes import check_load_path

    path = Path(__file__).resolve().parents[2] / "experiments" / "beam_column" / "ten_cameras.toml"
    exp = load(path)
    steps = lambda e: check_load_path(**mesh_tables(e), load_path_spec=e.load_path, groups=e.groups).steps
    every = steps(exp)
    for k in (1, 4, 7):
        kept = steps(exp.with_settings(load_path={"every": k}))
        assert kept == tuple(sorted(set(every[::k]) | {every[-1]}))
    assert len(steps(exp.with_settings(load_path={"every": 100}))) == 2
