"""vdo design on a plate under a straight rail: the selection against exhaustive search over
pairs scored as whole layouts, the mirror symmetry of the best pair's score, the minimum-angle
rule, and the bad inputs (messages naming the region, the best layout still written)."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest

from vdo import config, design, objective
from vdo.lighting import illuminate
from vdo.predict import samples_for_objective, settings, view_data
from vdo.scene import build_scene
from vdo.state import prepare
from vdo.visibility import compute_visibility

DESIGN = """
[design]
max_cameras = {n}
rail_positions = 9
offset_m = [0, 0, 0]
sample_spacing_mm = 50
{extra}
"""


def _experiment(plate_experiment, n=2, extra="", regions="", spacing=50):
    path = plate_experiment(spacing=spacing)
    path.write_text(path.read_text() + regions + DESIGN.format(n=n, extra=extra))
    return config.load(path)


@pytest.fixture
def judged(plate_experiment):
    exp = _experiment(plate_experiment)
    geometry = prepare(exp)
    return exp, geometry, design.judge(exp, geometry)


def _pair_score(exp, geometry, cams):
    """objective.score of a layout of these cameras, computed from its own ray cast."""
    scene = build_scene(list(geometry.meshes))
    smp = samples_for_objective(exp, geometry.samples)
    vis = compute_visibility(scene, cams, geometry.samples, exp.evaluation.incidence_limit,
                             progress=False)
    light = illuminate(scene, exp.lights, geometry.samples, exp.render.ambient_radiance)
    views = view_data(exp, smp, vis, light, geometry.speckle)
    st = replace(settings(exp), pair_dtype="float64")
    return float(objective.score(objective.CameraParams.from_cameras(cams), smp, views,
                                 geometry.speckle.table, st))


def test_candidates_information_adds_to_the_layouts(judged):
    exp, geometry, cand = judged
    assert len(cand.cameras) == 9 * 1          # 9 rail positions x 1 target x 1 lens (24 mm)
    scorer = design.Scorer(exp, geometry.samples)
    for pair in [(0, 8), (2, 6), (3, 4)]:
        cams = [cand.cameras[i] for i in pair]
        assert scorer.of(cand, pair) == pytest.approx(_pair_score(exp, geometry, cams), rel=1e-4)


def test_greedy_and_exchange_find_the_best_pair_which_is_symmetric(judged):
    exp, geometry, cand = judged
    scorer, feas = design.Scorer(exp, geometry.samples), design.Feasibility(exp, cand)
    order, _ = design.greedy(cand, scorer, feas, 2)
    chosen, score, _ = design.exchange(cand, scorer, feas, order)
    feasible = [p for p in itertools.combinations(range(len(cand.cameras)), 2)
                if not feas.conflict[p[0], p[1]]]
    exhaustive = {p: _pair_score(exp, geometry, [cand.cameras[i] for i in p]) for p in feasible}
    best = min(exhaustive, key=exhaustive.get)
    assert sorted(chosen) == sorted(best)
    assert score == pytest.approx(exhaustive[best], rel=1e-4)
    # the plate is symmetric about x = 0: the mirrored pair (rail positions i -> 8 - i) scores
    # the same within the sampling's asymmetry, and is as good as any other
    mirror = tuple(sorted(8 - i for i in chosen))
    assert exhaustive[mirror] == pytest.approx(exhaustive[best], rel=1e-2)


def test_minimum_axis_angle_is_respected(plate_experiment):
    """Candidates at x = -1, -0.75, ..., 1 m on a rail 1.5 m above the plate, all aimed at its
    centre: the axes of x1 < x2 make atan(x2 / 1.5) - atan(x1 / 1.5). With a minimum angle
    between the best free pair's and the widest pair's (x = +-1: 2 atan(1 / 1.5) = 67.4 deg),
    only pairs wider than the free choice are allowed, and the selection keeps to them."""
    free = _experiment(plate_experiment)
    geometry = prepare(free)
    cand = design.judge(free, geometry)
    scorer = design.Scorer(free, geometry.samples)
    feas = design.Feasibility(free, cand)
    chosen, _, _ = design.exchange(cand, scorer, feas, design.greedy(cand, scorer, feas, 2)[0])
    angle = lambda pair: abs(math.degrees(math.atan(cand.cameras[pair[0]].position[0] / 1.5)
                                          - math.atan(cand.cameras[pair[1]].position[0] / 1.5)))
    widest = 2 * math.degrees(math.atan(1 / 1.5))
    assert angle(chosen) < widest - 1
    limit = (angle(chosen) + widest) / 2
    free.path.write_text(free.path.read_text() + f"\n[optimize]\nmin_axis_angle_deg = {limit}\n")
    exp = config.load(free.path)
    feas = design.Feasibility(exp, cand)
    bound, _, _ = design.exchange(cand, scorer, feas, design.greedy(cand, scorer, feas, 2)[0])
    assert len(bound) == 2 and angle(bound) >= limit
    a = cand.axes
    assert math.degrees(math.acos(np.clip(a[bound[0]] @ a[bound[1]], -1, 1))) == \
        pytest.approx(angle(bound), abs=1e-6)


UNDERSIDE = """
[[region]]
name = "underside"
mesh = "plate"
normal = [0, 0, -1]
"""


def test_bad_inputs_name_the_region_and_still_write_the_layout(plate_experiment, tmp_path):
    exp = _experiment(plate_experiment, n=2, regions=UNDERSIDE.replace(
        'name = "underside"', 'name = "underside"\nmin_cameras = 1'),
        extra="target_sigma_um = 1e-6")
    exp = config.load(exp.path)
    text = exp.path.read_text().replace('name = "top"\n', 'name = "top"\nmin_cameras = 3\n')
    exp.path.write_text(text)
    exp = config.load(exp.path)
    out = tmp_path / "out"
    result = design.design(exp, out, quiet=True)
    messages = " | ".join(result["problems"])
    assert "region 'top' needs 3 cameras" in messages
    assert "region 'underside': no candidate pose sees it" in messages
    assert "target sigma_max p95 1e-06 um is not reached" in messages
    designed = config.load(out / "designed.toml")
    assert len(designed.camera_specs) == 2
    assert (out / "pareto.csv").read_text().startswith("cameras,")


SLAB = """
[[mesh]]
name = "slab"
file = "slab.stl"
unit = "m"
role = "obstacle"
"""


def test_obscuration_by_an_obstacle_matches_the_shadow_geometry(plate_experiment):
    """A slab at z = 0.75 m over x in [0.3, 1.0] m between the rail (z = 1.5 m) and the plate
    (x in [-0.5, 0.5]): the ray from a camera at (c, 0, 1.5) to a plate point (p, y, 0) crosses
    z = 0.75 at x = (c + p) / 2, so the slab hides the plate points with p >= 0.6 - c, a fraction
    clip(c - 0.1, 0, 1) of the plate. Candidates hiding more than max_obscuration of a region
    they are assigned are never selected."""
    path = plate_experiment(spacing=25, extra_meshes=SLAB, files=[("slab.stl", [0.7, 2.0, 0.01],
                                                                   [0.65, 0.0, 0.75])])
    path.write_text(path.read_text() + DESIGN.format(n=2, extra="sample_spacing_mm = 25")
                    .replace("sample_spacing_mm = 50\n", ""))
    exp = config.load(path)
    cand = design.judge(exp, prepare(exp))
    for i, c in enumerate(cand.cameras):
        expected = float(np.clip(c.position[0] - 0.1, 0.0, 1.0))
        assert cand.masked[i, 0] == pytest.approx(expected, abs=0.05), c.position[0]
    feas = design.Feasibility(exp, cand)
    assert np.array_equal(feas.alone, ~(cand.assigned[:, 0] & (cand.masked[:, 0] > 0.01)))
    scorer = design.Scorer(exp, prepare(exp).samples)
    chosen, _, _ = design.exchange(cand, scorer, feas, design.greedy(cand, scorer, feas, 2)[0])
    assert len(chosen) == 2 and all(cand.masked[i, 0] <= 0.01 for i in chosen)
