"""Floor zones of any simple shape: an L-shaped floor and a ring around the specimen (a floor
polygon with a hole). Point-in-floor is checked against matplotlib's own Path.contains_points;
a camera in the hole, a self-crossing floor and a hole outside the floor are one ConfigError
line each; design's candidate grid stands only on the ring; the optimizer's floor depth is the
signed distance to the ring (matplotlib's sign, the edges sampled densely), its penalty's gradient
is finite differences', and `vdo optimize` moves two cameras over the ring and keeps them on it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.path import Path as MplPath
from scipy.spatial import cKDTree

from conftest import PLATE_TOML, write_box
from vdo import constraints
from vdo.config import experiment as config
from vdo.config.mounts import inside_floor
from vdo.core.errors import ConfigError
from vdo.config.mounts import zone_grid
from vdo.search.parameterisation import Parameterization
from vdo.search.problem import CLEARANCE_MARGIN
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


def test_the_floor_depth_is_the_signed_distance_to_the_ring(tmp_path):
    zone = config.load(write(tmp_path)).mount("ring")
    starts, ends = constraints.floor_edges(zone)
    assert len(starts) == 8
    points = np.random.default_rng(5).uniform(-2.5, 2.5, size=(400, 2))
    depth = np.asarray(constraints.floor_depth(jnp.asarray(points), jnp.asarray(starts), jnp.asarray(ends)))
    on = MplPath(np.array(OUTER)).contains_points(points) & ~MplPath(np.array(HOLE)).contains_points(points)
    assert 100 < on.sum() < 350 and np.array_equal(depth < 0, on)
    t = np.linspace(0.0, 1.0, 40001)[:, None]          # every 0.1 mm of the 4 m and 2 m edges
    boundary = np.concatenate([a + t * (b - a) for a, b in zip(starts, ends)])
    np.testing.assert_allclose(np.abs(depth), cKDTree(boundary).query(points)[0], atol=1e-4)


@pytest.mark.parametrize("xy", [[1.003, 0.3], [0.9, -0.2], [1.8, 1.998], [-2.05, 0.4]])
def test_the_floor_penalty_gradient_is_central_differences(tmp_path, xy):
    """Points within the margin of the hole's edge, in the hole, within the margin of the outline
    and off it: the penalty is positive and its JAX gradient equals central differences."""
    zone = config.load(write(tmp_path)).mount("ring")
    floors = ((jnp.asarray([1]), *(jnp.asarray(a) for a in constraints.floor_edges(zone))),)
    positions = jnp.asarray([[1.5, 0.0, 1.2], [*xy, 1.2]])
    f = lambda p: constraints.floor_penalty(p, floors, CLEARANCE_MARGIN)
    assert float(f(positions)) > 0
    assert float(f(positions.at[1].set(jnp.asarray([1.5, 0.5, 1.2])))) == 0.0   # well on the ring
    g = np.asarray(jax.grad(f)(positions))
    h = 1e-7
    for k in range(2):
        step = np.zeros((2, 3))
        step[1, k] = h
        fd = (float(f(positions + step)) - float(f(positions - step))) / (2 * h)
        assert g[1, k] == pytest.approx(fd, rel=1e-5, abs=1e-6)
    assert np.all(g[0] == 0) and g[1, 2] == 0


def test_optimize_moves_two_cameras_over_the_ring_and_keeps_them_on_it(tmp_path):
    """Two tripod cameras on the ring, 1.5 m either side of the plate: nearer is sharper, so the
    score pulls them toward the hole, where the floor penalty holds them; each moves (its x and y are free parameters), ends on the
    floor (the file's own point-in-floor test, and the optimized layout loads again) with a
    met floor check, and the score falls."""
    from vdo.commands.optimize import optimize

    second = CAMERA.format(position="position_m = [-1.5, 0.0, 1.2]").replace('name = "t"', 'name = "t2"')
    path = write(tmp_path, extra=second + '\n[render]\nambient_radiance = 1.0\n\n[optimize]\n'
                 'free = ["u", "pan", "tilt"]\nstarts = 1\nrounds = 2\nmax_steps = 20\n')
    exp = config.load(path)
    param = Parameterization(exp, cameras_of(exp.camera_specs, exp.rails), np.zeros(3))
    assert all({"x", "y", "z"} <= set(idx) for idx in param.index)
    result = optimize(exp, tmp_path / "run")
    assert result.violations == 0, result.violated
    assert result.score_after_um < result.score_before_um
    after = config.load(tmp_path / "run" / "optimized.toml")
    zone = after.mount("ring")
    moved = [np.linalg.norm(np.subtract(a.position, b.position))
             for a, b in zip(after.camera_specs, exp.camera_specs)]
    assert min(moved) > 0.01, moved
    for spec in after.camera_specs:
        assert inside_floor(zone.floor, spec.position[:2], holes=zone.floor_holes)
    import json
    floor = [e for e in json.loads((tmp_path / "run" / "constraints.json").read_text())["after"]
             if e["constraint"] == "floor"]
    assert sorted(e["cameras"][0] for e in floor) == ["t", "t2"] and all(e["met"] for e in floor)
    # the floor, not the score, stopped them: both stand at the hole's edge (x = +-1 m), within
    # twice the penalty's margin of it
    edge = [abs(s.position[0]) - 1.0 for s in after.camera_specs]
    assert all(0.0 <= e < 2 * CLEARANCE_MARGIN for e in edge), edge
