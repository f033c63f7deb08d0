"""`vdo optimize` over a load path: a shutter slides over the plate during the test. The layout
optimised at rest moves camera `a` where the shutter hides the plate at step 2; optimised over the
path (`[optimize] load_path`, the default when the experiment has a `[load_path]`), it keeps the
plate seen by both cameras at every step. Both are judged at every step by
`vdo.search.loadpath.evaluate_load_path` (summary_after.json), which knows nothing of the optimizer.

Geometry (metres): the 0.6 m plate at z = 0; cameras on the rail at z = 1.2, `b` fixed at x = -0.6,
`a` free from x = 0.3 (a 41-degree stereo angle; the score gains from a wider one, so the rest
optimum moves `a` outward, to x = 0.77 when measured; over the path it stops short of the
shutter's shadow, at x = 0.34). The 1.5 m shutter, at z = 0.9, spans x >= 0.35 at step 2. The ray from
the rail point x_c to the plate point x_p crosses z = 0.9 at x_p + 0.75 (x_c - x_p): the shutter
hides part of the plate from x_c > 0.37 and all of it from x_c > 0.57; b's rays cross at x <= -0.37.
"""

import json

import numpy as np
import pytest

from conftest import PLATE_TOML, SLIDING_SHUTTER, aimed_camera, load_path_tables, write_box
from vdo.config import experiment as config
from vdo.search import loadpath
from vdo.model.pose import look_at_angles
from vdo.geometry.keyframes import load_path_of
from vdo.search.loadpath import keyframe_steps, path_occlusion
from vdo.commands.optimize import optimize
from vdo.state import prepare
from vdo.scene import cameras_of

SHUTTER_EDGE = 0.35   # m: the shutter's near edge at step 2
RAIL_HEIGHT, SHUTTER_HEIGHT = 1.2, 0.9

SETTINGS = """
[render]
ambient_radiance = 1.0

[optimize]
cameras = ["a"]
starts = 1
rounds = 2
max_steps = 20
load_path = {over_path}
"""


def experiment(tmp_path, over_path: bool):
    write_box(tmp_path / "plate.stl", [600, 600, 10], center=[0, 0, -5])
    # at rest far out at +x; step 2 brings its near edge to SHUTTER_EDGE
    write_box(tmp_path / "shutter.stl", [1500, 1500, 10],
              center=[(SHUTTER_EDGE + 0.75 + 3.0) * 1e3, 0, SHUTTER_HEIGHT * 1e3])
    rows = ["step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg",
            "1,slide,-1500,0,0,0,0,0", "2,slide,-3000,0,0,0,0,0", "3,slide,0,0,0,0,0,0"]
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    cams = aimed_camera("a", 0.65) + aimed_camera("b", 0.2)
    text = PLATE_TOML.format(spacing=50, limit=75, height=RAIL_HEIGHT, extra_meshes=SLIDING_SHUTTER,
                             cameras=cams + SETTINGS.format(over_path=str(over_path).lower()))
    path = tmp_path / "exp.toml"
    path.write_text(text)
    return config.load(path)


def test_path_occlusion_hides_the_views_the_geometry_says(tmp_path):
    """path_occlusion against the closed form of the module docstring, for a camera at x = 0.2
    (sees the whole plate at every step) and one at x = 0.5 (at step 2 the shutter hides the
    plate points whose ray crosses z = 0.9 beyond the edge, x_p > -0.1)."""
    exp = experiment(tmp_path, True)
    geometry = prepare(exp)
    load_path = load_path_of(geometry.meshes, **load_path_tables(exp))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    near, far = (cam.with_pose([x, 0.0, RAIL_HEIGHT], *look_at_angles([x, 0.0, RAIL_HEIGHT], [0, 0, 0]))
                 for x in (0.2, 0.5))
    every = path_occlusion(geometry, load_path, [near, far], fraction=1.0)
    most = path_occlusion(geometry, load_path, [near, far], fraction=0.6)
    assert every[0].all() and most.all()       # 2 of 3 steps >= 0.6: the far camera still counts
    x_p = geometry.samples.points[:, 0]
    crossing = x_p + SHUTTER_HEIGHT / RAIL_HEIGHT * (0.5 - x_p)
    assert np.all(every[1] == (crossing < SHUTTER_EDGE))   # hidden where the ray meets the shutter
    assert 0.3 < every[1].mean() < 0.5
    assert keyframe_steps(load_path, 1) == (2,)            # the extreme of the slide


@pytest.mark.parametrize("over_path, loses", [(False, True), (True, False)], ids=["rest", "path"])
def test_rest_optimum_loses_the_plate_and_the_path_optimum_keeps_it(tmp_path, over_path, loses):
    exp = experiment(tmp_path, over_path)
    out = tmp_path / "run"
    optimize(exp, out)
    after = json.loads((out / "summary_after.json").read_text())["load_path"]
    geometry = prepare(exp)   # the hand layout, judged over the path as `vdo evaluate` does
    before = loadpath.summary(loadpath.evaluate_load_path(geometry, load_path_of(geometry.meshes,
                                                                                 **load_path_tables(exp))))
    moves = {row.split(",")[0]: row.split(",") for row in (out / "moves.csv").read_text().splitlines()}
    x_after = float(moves["a"][13])
    print(f"load_path={over_path}: camera a x = {x_after:.3f} m; covered at the worst step "
          f"{after['regions']['top']['covered_fraction_min']:.3f}; losses {after['losses']}")
    assert before["regions"]["top"]["covered_fraction_min"] > 0.99 and not before["losses"]
    if loses:
        assert after["regions"]["top"]["covered_fraction_min"] < 0.5
        assert [(x["camera"], x["step"]) for x in after["losses"]] == [("a", 2)]
    else:
        assert after["regions"]["top"]["covered_fraction_min"] > 0.99 and not after["losses"]
    scores = json.loads((out / "optimizer.json").read_text())
    assert scores["score_after"]["score_um"] < scores["score_before"]["score_um"]   # it did move
