"""Keep-out volumes: a camera inside one, or a mount whose every position lies in one, is one
ConfigError line naming the camera's field, the keep-out and the fix; design drops the candidate
positions inside one; the optimizer's penalty is 0 exactly outside by its margin and its
gradient matches finite differences; the exact check measures the depth inside."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import PLATE_TOML, mesh_tables, region_tables, write_box
from vdo import constraints
from vdo.config import experiment as config
from vdo.config.mounts import inside_keep_out
from vdo.core.errors import ConfigError
from vdo.design.candidates import candidate_cameras
from vdo.scene import cameras_of, load_meshes, sample_regions

ZONE = """
[[mount]]
name = "ring"
kind = "zone"
box_min_m = [0.3, -0.4, 0.9]
box_max_m = [0.9, 0.4, 1.3]

[[mount]]
name = "gantry"
kind = "rail"
control_points_m = [[-0.5, -0.8, 1.5], [0.5, -0.8, 1.5]]
"""
CAMERAS = """
[[camera]]
name = "t"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
mount = "ring"
position_m = [0.6, 0.1, 1.0]
target_m = [0.0, 0.0, 0.0]

[[camera]]
name = "g"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
mount = "gantry"
u = 0.5
target_m = [0.0, 0.0, 0.0]
"""
DESIGN = """
[design]
max_cameras = 2
rail_positions = 5
offset_m = [0, 0, 0]
zone_points = 3
zone_heights = 2
"""


def write(tmp_path, keep_out, design=""):
    write_box(tmp_path / "plate.stl", [600, 600, 10], center=[0, 0, -5])
    text = PLATE_TOML.format(spacing=50, limit=75, height=1.2, extra_meshes=ZONE, cameras=CAMERAS)
    (tmp_path / "exp.toml").write_text(text + keep_out + design)
    return tmp_path / "exp.toml"


def keep_out(lo, hi, name="machine"):
    return f'\n[[keep_out]]\nname = "{name}"\nbox_min_m = {lo}\nbox_max_m = {hi}\n'


def test_a_camera_inside_a_keep_out_is_refused(tmp_path):
    path = write(tmp_path, keep_out("[0.5, 0.0, 0.9]", "[0.7, 0.2, 1.1]"))
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert err.value.field == 'camera "t".position_m'
    assert "keep_out 'machine'" in err.value.message and "move the camera out" in err.value.message


def test_a_keep_out_holding_a_zone_s_every_position_is_named(tmp_path):
    path = write(tmp_path, keep_out('[-inf, -1, 0.5]', '[inf, 1, 1.4]'))
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert err.value.field == 'camera "t".mount'
    assert "every position of zone 'ring' lies in keep_out 'machine'" in err.value.message
    assert "nowhere to stand" in err.value.message


def test_a_keep_out_holding_a_rail_is_named(tmp_path):
    path = write(tmp_path, keep_out("[-1, -1, 1.4]", "[1, -0.5, 1.6]"))
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert err.value.field == 'camera "g".rail' and "rail 'gantry'" in err.value.message


def test_design_drops_the_candidates_inside(tmp_path):
    """A keep-out over the zone's x > 0.7 half: of the 3 x 3 x 2 grid, the x = 0.9 points go
    (the grid's x values are 0.3, 0.6, 0.9), the others stay, and none inside is a candidate."""
    path = write(tmp_path, keep_out('[0.7, -inf, -inf]', '[inf, inf, inf]'), DESIGN)
    exp = config.load(path)
    meshes = load_meshes(**mesh_tables(exp))
    cams, mounts, *_, dropped = candidate_cameras(exp, sample_regions(meshes, **region_tables(exp)), meshes)
    zone = np.array([c.position for c, m in zip(cams, mounts) if m == "ring"])
    assert len(zone) and np.all(zone[:, 0] < 0.7)
    assert set(np.round(zone[:, 0], 9)) == {0.3, 0.6}
    assert not np.any(inside_keep_out(exp.keep_outs, np.array([c.position for c in cams])) >= 0)
    # counted per mount: the x = 0.9 column of the zone's grid (3 y x 2 heights), and the rail's
    # positions with x > 0.7 (none: the rail runs over x in [-0.5, 0.5])
    assert dropped["ring"]["positions in keep_out 'machine'"] == 3 * 2
    assert "gantry" not in dropped or "positions in keep_out 'machine'" not in dropped["gantry"]


def test_penalty_is_zero_outside_and_its_gradient_is_right():
    lows, highs = jnp.asarray([[0.0, 0.0, 0.0]]), jnp.asarray([[1.0, 1.0, constraints.KEEP_OUT_FAR]])
    margin = 0.005
    outside = jnp.asarray([[1.01, 0.5, 2.0], [-0.5, 0.5, 0.0]])
    assert constraints.keep_out_penalty(outside, lows, highs, margin) == 0.0
    inside = jnp.asarray([[0.9, 0.3, 5.0], [0.2, 0.95, 1.0]])
    # closed form: depths 0.1 and 0.05 (nearest faces x = 1 and y = 1)
    expected = ((0.1 + margin) / constraints.KEEP_OUT_SCALE) ** 2 + ((0.05 + margin) / constraints.KEEP_OUT_SCALE) ** 2
    assert float(constraints.keep_out_penalty(inside, lows, highs, margin)) == pytest.approx(expected, rel=1e-12)
    g = jax.grad(lambda p: constraints.keep_out_penalty(p, lows, highs, margin))(inside)
    h = 1e-6
    for c in range(2):
        for k in range(3):
            step = jnp.zeros((2, 3)).at[c, k].set(h)
            fd = (constraints.keep_out_penalty(inside + step, lows, highs, margin)
                  - constraints.keep_out_penalty(inside - step, lows, highs, margin)) / (2 * h)
            assert float(g[c, k]) == pytest.approx(float(fd), rel=1e-6, abs=1e-9)


def test_exact_check_measures_the_depth(tmp_path):
    path = write(tmp_path, keep_out("[0.5, 0.15, 0.9]", "[0.7, 0.3, 1.1]"))
    exp = config.load(path)
    entries = constraints.keep_out_checks(cameras_of(exp.camera_specs, exp.rails), exp.keep_outs)
    t = next(e for e in entries if e["cameras"] == ["t"])
    assert t["value"] == pytest.approx(-0.05) and t["met"]      # y = 0.1: 5 cm short of the box's y = 0.15
    moved = [c if c.name != "t" else type(c)(**{**c.__dict__, "position": np.array([0.6, 0.2, 1.0])})
             for c in cameras_of(exp.camera_specs, exp.rails)]
    inside = next(e for e in constraints.keep_out_checks(moved, exp.keep_outs) if e["cameras"] == ["t"])
    assert inside["value"] == pytest.approx(0.05) and not inside["met"]   # 5 cm inside (y = 0.15 face)


def test_design_drops_the_poses_whose_tripod_stands_in_a_keep_out(tmp_path):
    """The zone's cameras on tripods (feet 0.45 m out on the floor): a keep-out box on the floor
    beside the zone, away from every optical centre, takes the poses whose tripod's legs reach
    into it (by `tripod_checks`' measure, which holds none of those kept), counted per mount."""
    from vdo import constraints

    path = write(tmp_path, keep_out("[1.15, -1, -0.1]", "[2, 1, 0.2]", name="pit"), DESIGN)
    path.write_text(path.read_text().replace('box_max_m = [0.9, 0.4, 1.3]\n',
                                             'box_max_m = [0.9, 0.4, 1.3]\ntripod = {}\n', 1))
    exp = config.load(path)
    meshes = load_meshes(**mesh_tables(exp))
    cams, mounts, *_, dropped = candidate_cameras(exp, sample_regions(meshes, **region_tables(exp)), meshes)
    assert dropped["ring"]["poses with tripod legs in keep_out 'pit'"] > 0
    ring = [c for c, m in zip(cams, mounts) if m == "ring"]
    assert ring
    table = constraints.tripod_table(ring, [exp.mount("ring").tripod] * len(ring))
    checks = constraints.tripod_checks(ring, table, exp.keep_outs, clearance=0.0)
    assert all(e["met"] for e in checks)
