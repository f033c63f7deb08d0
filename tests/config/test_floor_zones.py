"""Floor zones of any simple shape: an L-shaped floor and a ring around the specimen (a floor
polygon with a hole). Point-in-floor is checked against matplotlib's own Path.contains_points;
a camera in the hole, a self-crossing floor and a hole outside the floor are one ConfigError
line each; design's candidate grid stands only on the ring; optimize says it moves cameras over
convex floors only."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.path import Path as MplPath

from conftest import PLATE_TOML, write_box
from vdo.config import experiment as config
from vdo.config.mounts import inside_floor
from vdo.core.errors import ConfigError
from vdo.config.mounts import zone_grid
from vdo.search.parameterisation import Parameterization
from vdo.scene import cameras_of

OUTER = [[-2.0, -2.0], [2.0, -2.0], [2.0, 2.0], [-2.0, 2.0]]
HOLE = [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]
L_SHAPE = [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]]

RING = """
[[mount]]
name = "ring"
kind = "zone"
floor_m = {outer}
floor_holes_m = [{hole}]
height_m = [1.0, 1.5]

[mount.tripod]
"""
CAMERA = """
[[camera]]
name = "t"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
mount = "ring"
{position}
target_m = [0.0, 0.0, 0.0]
"""


def write(tmp_path, position="position_m = [1.5, 0.0, 1.2]", outer=OUTER, hole=HOLE, extra=""):
    write_box(tmp_path / "plate.stl", [600, 600, 10], center=[0, 0, -5])
    mounts = RING.format(outer=outer, hole=hole)
    text = PLATE_TOML.format(spacing=50, limit=75, height=1.2, extra_meshes=mounts,
                             cameras=CAMERA.format(position=position))
    (tmp_path / "exp.toml").write_text(text + extra)
    return tmp_path / "exp.toml"


def test_point_in_floor_matches_matplotlib():
    rng = np.random.default_rng(3)
    points = rng.uniform(-2.5, 2.5, size=(2000, 2))
    outer, hole, ell = (np.array(p, float) for p in (OUTER, HOLE, L_SHAPE))
    ring = MplPath(outer).contains_points(points) & ~MplPath(hole).contains_points(points)
    ours = np.array([inside_floor(outer, p, holes=(hole,)) for p in points])
    assert ring.sum() > 500 and np.array_equal(ours, ring)
    ours = np.array([inside_floor(ell, p) for p in points])
    assert np.array_equal(ours, MplPath(ell).contains_points(points))


def test_a_ring_zone_loads_and_the_hole_is_off_it(tmp_path):
    exp = config.load(write(tmp_path))
    assert cameras_of(exp.camera_specs, exp.rails)[0].position.tolist() == pytest.approx([1.5, 0.0, 1.2])
    assert not exp.mount("ring").convex
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, position="position_m = [0.5, 0.0, 1.2]"))
    assert err.value.field == 'camera "t".position_m' and "in hole 0 of the floor of zone 'ring'" in err.value.message
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, position=""))
    assert err.value.field == 'camera "t".position_m' and "centroid" in err.value.message


@pytest.mark.parametrize("outer,hole,field,words", [
    ([[0, 0], [3, 2], [3, 0], [0, 1]], [[2.5, 0.6], [2.9, 0.6], [2.9, 0.9]], "floor_m", "two of its edges cross"),
    (OUTER, [[1.5, 1.5], [3, 1.5], [3, 3], [1.5, 3]], "floor_holes_m", "must lie inside floor_m"),
])
def test_bad_floors_are_named(tmp_path, outer, hole, field, words):
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, outer=outer, hole=hole))
    assert err.value.field == f'mount "ring".{field}' and words in err.value.message


def test_design_candidates_stand_on_the_ring(tmp_path):
    exp = config.load(write(tmp_path, extra="\n[design]\nmax_cameras = 2\nzone_points = 9\nzone_heights = 1\n"))
    grid = zone_grid(exp.mount("ring"), exp.design.zone_points, exp.design.zone_heights)
    xs = np.linspace(-2, 2, 9)
    expected = [(x, y) for x in xs for y in xs if max(abs(x), abs(y)) >= 1.0]   # hole edges count as floor
    assert sorted(map(tuple, np.round(grid[:, :2], 9))) == sorted(expected)


def test_optimize_says_it_needs_convex_floors(tmp_path):
    exp = config.load(write(tmp_path, extra='\n[optimize]\nfree = ["u", "pan", "tilt"]\n'))
    with pytest.raises(ConfigError) as err:
        Parameterization(exp, cameras_of(exp.camera_specs, exp.rails), np.zeros(3))
    assert err.value.field == 'mount "ring".floor_m' and "convex floors only" in err.value.message


@pytest.mark.parametrize("moving, named", [
    ("", "cameras 't', 't2' move over"),            # every camera moves: one line names both
    ('cameras = ["t2"]\n', "camera 't2' moves over"),   # only the moving one is named
])
def test_optimize_refuses_a_ring_once_per_mount(tmp_path, monkeypatch, capsys, moving, named):
    """Two cameras on one ring: `vdo optimize` says it once for the mount, naming the cameras it
    would move on it, not once per camera."""
    from vdo.commands.cli import main

    second = CAMERA.format(position="position_m = [-1.5, 0.0, 1.2]").replace('name = "t"', 'name = "t2"')
    path = write(tmp_path, extra=second + f'\n[optimize]\nfree = ["u", "pan", "tilt"]\n{moving}')
    monkeypatch.setattr("vdo.state.load_meshes", lambda *a, **k: pytest.fail("a mesh was read"))
    assert main(["optimize", str(path), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.count('mount "ring".floor_m') == 1 and named in err, err


def test_vdo_optimize_refuses_a_ring_before_reading_a_mesh(tmp_path, monkeypatch, capsys):
    """The command line refuses the file with the same line before any mesh is read (`vdo check`,
    evaluate and design take the ring whole)."""
    from vdo.commands.cli import main

    path = write(tmp_path, extra='\n[optimize]\nfree = ["u", "pan", "tilt"]\n')

    def no_meshes(*args, **kwargs):
        raise AssertionError("a mesh was read before the refusal")

    monkeypatch.setattr("vdo.state.load_meshes", no_meshes)
    assert main(["optimize", str(path), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and 'mount "ring".floor_m' in err and "convex floors only" in err
    assert not (tmp_path / "run").exists()
