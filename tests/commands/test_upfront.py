"""Every case of a validation file, every point of a sweep and every step of a load path is checked
before any heavy work: one bad case deep in a long list stops the command in one line naming the
file, the case and the field, and the heavy work (JAX/Mitsuba set-up, rendering, the sweep's
points) is never reached: the functions that start it are replaced by ones that fail the test."""

from __future__ import annotations

import shutil
import textwrap
from pathlib import Path

import pytest

from vdo.commands.cli import main

ROOT = Path(__file__).resolve().parents[2]


class Reached(AssertionError):
    pass


def forbid(monkeypatch, module, name):
    def heavy(*args, **kwargs):
        raise Reached(f"{module}.{name} was reached before the bad input was refused")

    monkeypatch.setattr(f"{module}.{name}", heavy)


@pytest.fixture
def no_work(monkeypatch):
    """The commands call vdo.core.configure.configure() (JAX, Dr.Jit) right after loading their
    input, before importing their heavy module; and validate's cases start in run_case."""
    forbid(monkeypatch, "vdo.core.configure", "configure")
    forbid(monkeypatch, "vdo.dic.validate", "run_case")
    forbid(monkeypatch, "vdo.dic.validate", "render_case")


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    return err


# --------------------------------------------------------------------------------------------
# A validation file: 12 cases, the 11th bad
# --------------------------------------------------------------------------------------------
VALIDATION_HEAD = """
[validation]
name = "long"
seeds = 50

[defaults]
patch_mm = [6, 5]
plate_margin_mm = 4
dot_mm = 0.35
texel_mm = 0.0125
tile_texels = 1024
focal_mm = 25
pixel_um = 5
pixels = [120, 90]
distance_mm = 500
displacement_um = [31, -23, 37]
"""

CASE = """
[[case]]
name = "c{k}"
cameras = [{{polar_deg = {a}, azimuth_deg = 180}}, {{polar_deg = {a}, azimuth_deg = 0}}]
seed = {k}
"""


@pytest.mark.parametrize("bad, field, words", [
    ("polar_deg = 95", 'case "c11".cameras[1].polar_deg', "95"),
    ("dot_mm = -1", 'case "c11".dot_mm', "positive"),
    ("strain_microstrain = [2000, -1000, 500]\nsubset_mm = 2\nstep_mm = 1\nstrain_window = 6",
     'case "c11".strain_window', "larger than the patch"),
])
def test_validation_file_bad_case_deep_in_the_list(tmp_path, capsys, no_work, bad, field, words):
    cases = [CASE.format(k=k, a=5 + k) for k in range(1, 13)]
    if bad.startswith("polar_deg"):
        cases[10] = cases[10].replace("polar_deg = 16, azimuth_deg = 0", bad)
    else:
        cases[10] += bad + "\n"
    path = tmp_path / "long.toml"
    path.write_text(textwrap.dedent(VALIDATION_HEAD) + "".join(cases))
    assert main(["validate", str(path), "--out", str(tmp_path / "out")]) == 2
    err = one_line(capsys)
    assert err.startswith(f"error: {path.resolve()}: {field}: ") and words in err, err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# A sweep: 12 points, the last three bad
# --------------------------------------------------------------------------------------------
def test_sweep_bad_point_deep_in_the_list(plate_experiment, tmp_path, capsys, monkeypatch):
    from conftest import CAMERAS, HEIGHT

    for name in ("_run_local", "_run_dask", "plot"):
        forbid(monkeypatch, "vdo.commands.sweep", name)
    plate_experiment(spacing=25, height=HEIGHT, cameras=CAMERAS)
    path = tmp_path / "sweep.toml"
    path.write_text(textwrap.dedent("""
        [sweep]
        experiment = "plate.toml"
        [[axis]]
        path = "camera.*.focal_mm"
        values = [16, 24, 35, -5]
        [[axis]]
        path = "speckle.dot_diameter_mm"
        values = [2, 3, 4]
        """))
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = one_line(capsys)
    assert err.startswith(f"error: {path.resolve()}: point 9 (plate.toml: camera.*.focal_mm = -5, "
                          "speckle.dot_diameter_mm = 2): "), err
    assert 'plate.toml: camera "left".focal_mm: must be positive (got -5)' in err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# A load path: the built-in beam-column's, one row deep in one of its CSV files made bad
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def beam_column(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lp") / "beam_column"
    shutil.copytree(ROOT / "experiments" / "beam_column", folder,
                    ignore=shutil.ignore_patterns("*.py", "sweep.toml"))
    return folder


def spoil(folder: Path, file: str, line: int, column: int, value: str) -> None:
    """Set one cell of a CSV (1-based line of the file, counting its comment line)."""
    path = folder / file
    lines = path.read_text().splitlines()
    cells = lines[line - 1].split(",")
    cells[column] = value
    lines[line - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("command", [["evaluate"], ["optimize"], ["render", "--series"], ["design"]])
@pytest.mark.parametrize("file, line, column, value, words", [
    ("load_path_platform.csv", 24, 5, "400", "column rx_deg|rotation 400.0 deg is more than a full turn"),
    ("load_path_specimen.csv", 180, 1, "0.5", "mm from the nearest vertex of mesh 'specimen'"),
])
def test_load_path_bad_step_deep_in_the_list(beam_column, tmp_path, capsys, no_work, command,
                                             file, line, column, value, words):
    import re

    folder = tmp_path / "bc"
    shutil.copytree(beam_column, folder)
    original = (folder / file).read_text().splitlines()
    assert len(original) > line, "the shipped load path is shorter than this test assumes"
    spoil(folder, file, line, column, value)
    config = folder / ("design.toml" if command == ["design"] else "ten_cameras.toml")
    assert main([command[0], str(config), *command[1:], "--out", str(tmp_path / "out")]) == 2
    err = one_line(capsys)
    # the row named is the line spoiled: the file's line number, its comment line counted
    assert err.startswith(f"error: {folder / file}: row {line}: "), err
    assert re.search(words, err), err
    assert not (tmp_path / "out").exists()


def test_series_poses_file_bad_step(beam_column, tmp_path, capsys, no_work):
    poses = tmp_path / "poses.csv"
    rows = ["step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg"]
    rows += [f"{k},platform,{k},0,0,0,0,0" for k in range(1, 40)]
    rows[35] = "35,plattform,1,0,0,0,0,0"
    poses.write_text("\n".join(rows) + "\n")
    assert main(["render", str(beam_column / "ten_cameras.toml"), "--series", str(poses), "--out",
                 str(tmp_path / "out")]) == 2
    err = one_line(capsys)
    assert err.startswith(f"error: {poses}: row 36: group 'plattform' is neither a [[group]] "), err


# --------------------------------------------------------------------------------------------
# Several geometric mistakes in one file: all of them, one line each, before any work
# --------------------------------------------------------------------------------------------
def test_geometric_mistakes_are_reported_together(plate_experiment, tmp_path, capsys, no_work):
    """A camera inside the plate, a displacement file without step 2 of the pose file, and a
    lens outside the [optimize] catalogue: every command that loads the file (and `vdo check`)
    prints the three, one line each naming the file, the field and the fix, and exits 2
    before the heavy work (`no_work`)."""
    from conftest import DOWN_CAMERA

    inside = DOWN_CAMERA.format(name="buried", focal=24, u=0.5).replace(
        'rail = "overhead"\nu = 0.5', "position_m = [0.1, 0.1, -0.005]")
    cams = (DOWN_CAMERA.format(name="down", focal=24, u=0.5) + inside
            + '\n[optimize]\nfree = ["u", "pan", "tilt", "lens"]\nlenses_mm = [28, 50]\n'
            + '\n[load_path]\nposes = "poses.csv"\ndisplacements = "u.csv"\ndeformed_mesh = "plate"\n')
    path = plate_experiment(cameras=cams)
    (path.parent / "poses.csv").write_text("step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n"
                                           + "".join(f"{k},plate,0,0,{k},0,0,0\n" for k in (1, 2, 3)))
    (path.parent / "u.csv").write_text("step,x_m,y_m,z_m,ux_mm,uy_mm,uz_mm\n"
                                       + "".join(f"{k},0.5,0.5,0,0,0,0.1\n" for k in (1, 3)))
    for command in (["check"], ["evaluate"], ["optimize"], ["render", "--series"]):
        out = [] if command == ["check"] else ["--out", str(tmp_path / "out")]
        assert main([command[0], str(path), *command[1:], *out]) == 2, command
        lines = capsys.readouterr().err.strip().splitlines()
        assert lines == [
            f"error: {path.resolve()}: camera \"buried\".position_m: its optical centre [0.1, 0.1, -0.005] m "
            "lies inside mesh 'plate': move it out of the mesh",
            f"error: {path.parent / 'u.csv'}: step: has no displacements at step 2, which the pose file "
            "'poses.csv' has (the specimen would stand undeformed there): add those steps (zeros where "
            "it does not deform), or drop them from the pose file",
            f"error: {path.resolve()}: camera \"down\".focal_mm: 24 mm is not in the lens catalogue "
            "([optimize] lenses_mm = [28, 50]) that \"lens\" in [optimize] free chooses from, so the "
            "optimized layout could keep a lens the catalogue does not list: add 24 to [optimize] "
            "lenses_mm, or start from a lens of the catalogue",
            f"error: {path.resolve()}: camera \"buried\".focal_mm: 24 mm is not in the lens catalogue "
            "([optimize] lenses_mm = [28, 50]) that \"lens\" in [optimize] free chooses from, so the "
            "optimized layout could keep a lens the catalogue does not list: add 24 to [optimize] "
            "lenses_mm, or start from a lens of the catalogue"], command
        assert not (tmp_path / "out").exists()


def test_check_reports_every_region_that_selects_nothing(plate_experiment, capsys, no_work):
    """`vdo check` reads the regions' selections too (the evaluation would refuse the file two
    seconds in): two regions whose boxes miss the plate, one line each naming the region, and
    exit 2; nothing computed (`no_work`)."""
    path = plate_experiment()
    with open(path, "a") as f:
        for name, corner in (("nowhere", 5.0), ("elsewhere", -7.0)):
            f.write(f'\n[[region]]\nname = "{name}"\nmesh = "plate"\n'
                    f"box_min_m = [{corner}, {corner}, {corner}]\nbox_max_m = [{corner + 1}, {corner + 1}, {corner + 1}]\n")
    assert main(["check", str(path)]) == 2
    lines = [line for line in capsys.readouterr().err.strip().splitlines() if line.startswith("error:")]
    assert len(lines) == 2, lines
    for line, name in zip(lines, ("nowhere", "elsewhere")):
        assert f'region "{name}": selects no face of mesh \'plate\'' in line and "box" in line, line


def test_the_meshes_lines_are_said_once_per_command():
    """The geometry is read by the up-front checks, the evaluation and the figures: its lines
    (`vdo.meshes`) reach the console once each; other lines as often as they come."""
    import logging

    from vdo.commands.cli import _OnceForMeshes

    once = _OnceForMeshes()

    def record(name, text):
        return logging.LogRecord(name, logging.INFO, __file__, 1, text, None, None)

    split = "152 mesh faces split at the plane x = 0.59 m (a box face of region 'shell'), so that regions end there exactly"
    said = [once.filter(record("vdo.meshes.mesh", split)) for _ in range(3)]
    said += [once.filter(record("vdo.meshes.mesh", split.replace("0.59", "-0.59")))]
    said += [once.filter(record("vdo.commands.evaluate", "step 1 of 4")) for _ in range(2)]
    assert said == [True, False, False, True, True, True]


@pytest.mark.parametrize("second, overlaps", [
    ('normal = [0, 0, 1]', True),                                       # the same top face again
    ('normal = [0, 0, 1]\nnear_point_m = [0, 0, 0]\nbeyond_m = 0.2\nwithin_m = 5', False),   # a band beside it
])
def test_two_regions_keeping_the_same_surface_are_said(plate_experiment, caplog, second, overlaps):
    """Two regions of one mesh that keep the same surface count it twice: said at the door; two
    that a distance band splits between them (faces cut by the band shared, no surface twice)
    are not."""
    import logging

    from vdo.config import experiment as config
    from vdo.state import check_experiment

    path = plate_experiment()
    text = path.read_text()
    first = 'normal = [0, 0, 1]\nnear_point_m = [0, 0, 0]\nwithin_m = 0.2' if not overlaps else 'normal = [0, 0, 1]'
    text = text.replace('normal = [0, 0, 1]', first, 1)
    path.write_text(text + f'\n[[region]]\nname = "again"\nmesh = "plate"\n{second}\n')
    with caplog.at_level(logging.WARNING, logger="vdo"):
        check_experiment(config.load(path))
    assert ("counts twice" in caplog.text) == overlaps, caplog.text


@pytest.mark.parametrize("down_mm, said", [(15.0, True), (10.5, False)])
def test_a_mesh_driven_into_the_specimen_is_said(plate_experiment, caplog, down_mm, said):
    """A 100 x 100 x 20 mm platen 10 mm above the 10 mm plate, driven down by the load path: at
    15 mm its underside lies 5 mm inside the plate (said, with the step and the depth), at
    10.5 mm 0.5 mm (a press's contact, below PENETRATION_M: not said)."""
    import logging

    from vdo.config import experiment as config
    from vdo.state import check_experiment

    path = plate_experiment(files=[("platen.stl", [100, 100, 20], [0, 0, 20])],
                            extra_meshes='[[mesh]]\nname = "platen"\nfile = "platen.stl"\nrole = "obstacle"\nunit = "mm"\n')
    (path.parent / "poses.csv").write_text("step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n"
                                           f"1,platen,0,0,-5,0,0,0\n2,platen,0,0,{-down_mm},0,0,0\n")
    path.write_text(path.read_text() + '\n[load_path]\nposes = "poses.csv"\n')
    with caplog.at_level(logging.WARNING, logger="vdo"):
        check_experiment(config.load(path))
    assert ("at step 2 of the load path mesh 'platen' reaches 5.0 mm inside specimen 'plate'" in caplog.text) == said, caplog.text
    assert ("inside specimen" in caplog.text) == said


def test_check_says_one_line_and_the_warnings(plate_experiment, capsys, no_work):
    """`vdo check` on the shipped pressure vessel, whose regions split faces (five information
    lines in the other commands): the one ok line on stdout, nothing on stderr. Its warnings
    still reach the console: a second region on the plate's top warns that two regions keep the
    same surface."""
    from pathlib import Path

    vessel = Path(__file__).resolve().parents[2] / "experiments" / "pressure_vessel" / "all_round.toml"
    assert main(["check", str(vessel)]) == 0
    out, err = capsys.readouterr()
    assert out.count("\n") == 1 and out.startswith(f"ok: {vessel}") and err == "", (out, err)
    path = plate_experiment()
    with open(path, "a") as f:
        f.write('\n[[region]]\nname = "again"\nmesh = "plate"\nnormal = [0, 0, 1]\n')
    assert main(["check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("ok: ") and "'top'" in err and "'again'" in err, (out, err)


def test_a_rail_under_the_floor_is_said(plate_experiment, capsys, no_work):
    """Trial 4: a ring rail dipped under the floor and design put cameras there, unsaid. A rail
    that runs below every mesh (the plate's underside, z = -0.01 m, is the lowest) is warned
    with its stretches of u: the polyline (-1, 0, 1.5) -> (0, 0, -1) -> (1, 0, 1.5) is under
    z = -0.02 m where -1 + 5 |u - 0.5| < -0.02 (u in [0.304, 0.696], sampled every 1/512); a rail
    above it is not."""
    path = plate_experiment()
    text = path.read_text()
    assert main(["check", str(path)]) == 0
    assert "runs below every mesh" not in capsys.readouterr().err
    path.write_text(text.replace("control_points_m = [[-1.0, 0.0, 1.5], [1.0, 0.0, 1.5]]",
                                 "control_points_m = [[-1.0, 0.0, 1.5], [0.0, 0.0, -1.0], [1.0, 0.0, 1.5]]\ndegree = 1"))
    assert main(["check", str(path)]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "runs below every mesh" in line]
    assert len(err) == 1 and "rail 'overhead'" in err[0] and "for u in [0.30, 0.70], down to z = -1.000 m" in err[0], err


def test_validate_given_an_experiment_says_which_file_it_reads(plate_experiment, capsys, no_work):
    """Trial 4: `vdo validate EXPERIMENT` said "experiment: unknown field". One line: the file is
    an experiment, and validate reads a validation file."""
    path = plate_experiment()
    assert main(["validate", str(path), "--out", str(path.parent / "v")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {path}: is an experiment file; vdo validate "
                                               "reads a validation file"), err
    assert not (path.parent / "v").exists()
