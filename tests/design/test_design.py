"""vdo design on a plate under a straight rail: the selection against exhaustive search over
pairs scored as whole layouts, the mirror symmetry of the best pair's score, the minimum-angle
rule, and the bad inputs (messages naming the region, the best layout still written)."""

from __future__ import annotations

import itertools
import json
import math
import re
import time
from dataclasses import replace

import numpy as np
import pytest

from conftest import DOWN_CAMERA, SLIDING_SHUTTER, TRIPOD_ZONE, load_path_tables
from vdo import objective
from vdo.config import experiment as config
from vdo.commands.design import curve_line, design as design_run
from vdo.design.budget import ENTRY_BYTES, estimate, refuse
from vdo.config.mounts import zone_grid
from vdo.design.candidates import BLIND, judge, judging, lenses, spots
from vdo.design.feasibility import STOP_MARGIN, Feasibility
from vdo.design.score import Scorer
from vdo.design.moves import exchange, greedy
from vdo.design.polish import POLISH_RTOL, figures, percentile_by_region, polish, region_table
from vdo.design.select import design_layout, problems
from vdo.core.errors import ConfigError
from vdo.geometry.keyframes import load_path_of
from vdo.physics.lighting import illuminate
from vdo.physics.predict import samples_for_objective, settings, view_data
from vdo.scene import build_scene
from vdo.state import prepare
from vdo.search.loadpath import keyframe_steps
from vdo.physics.visibility import compute_visibility

SUM_ORDER_RTOL = 1e-12   # the same float64 sums taken in another order (entries vs all samples)

# the bound on the best score (tests/design/test_bound.py checks it) and the restarts get 2 s per
# camera count here
DESIGN = """
[design]
max_cameras = {n}
rail_positions = 9
offset_m = [0, 0, 0]
sample_spacing_mm = 50
bound_s = 2
restart_s = 2
{extra}
"""


def _experiment(plate_experiment, n=2, extra="", regions="", spacing=50, cameras=None):
    path = plate_experiment(spacing=spacing, cameras=cameras)
    path.write_text(path.read_text() + regions + DESIGN.format(n=n, extra=extra))
    return config.load(path)


@pytest.fixture
def judged(plate_experiment):
    exp = _experiment(plate_experiment)
    geometry = prepare(exp)
    return exp, geometry, judge(exp, geometry)


def _own_fields(exp, geometry, cams):
    """A layout of these cameras judged from its own ray cast, not from the candidates' stored
    sums: `objective.fields` (per-sample information C, smooth coverage k, weights w) and
    sigma_n = sqrt((tr Sigma^p)^(1/p)) of Sigma = (C + I/prior^2)^-1 by numpy's eigenvalues (not
    the invariants the score uses), in sigma_unit; returns (sigma, fields, settings)."""
    scene = build_scene(list(geometry.meshes))
    smp = samples_for_objective(exp.regions, geometry.samples)
    vis = compute_visibility(scene, cams, geometry.samples, exp.evaluation.incidence_limit,
                             progress=False)
    light = illuminate(scene, exp.lights, geometry.samples, exp.render.ambient_radiance)
    views = view_data(exp.speckle, exp.sensor, smp, vis, light, geometry.speckle)
    st = replace(settings(exp.evaluation), pair_dtype="float64")
    f = objective.fields(objective.CameraParams.from_cameras(cams), smp, views,
                         geometry.speckle.table, st)
    mu = 1.0 / np.linalg.eigvalsh(np.asarray(f.information) + np.eye(3) / st.prior_sigma ** 2)
    return np.sqrt((mu ** st.eigen_power).sum(-1) ** (1.0 / st.eigen_power)) / st.sigma_unit, f, st


def _pair_score(exp, geometry, cams, coverage_weight=1.0):
    """The design's score of a layout of these cameras from `_own_fields`:
    exp(sum omega ln(sigma / sigma_unit) + coverage_weight kappa sum a h(max(0, m - k)))
    sigma_unit units, h the Huber function of half a view."""
    sigma, f, st = _own_fields(exp, geometry, cams)
    area = np.asarray(geometry.samples.area)
    omega = area * geometry.samples.region_importance[geometry.samples.region]
    need = np.array([r.min_cameras for r in exp.regions])[geometry.samples.region]
    short = np.maximum(need - np.asarray(f.coverage), 0.0)
    huber = np.where(short > 0.5, short - 0.25, short ** 2)       # s^2 / (2 x 0.5) below half a view
    kappa = math.log(st.prior_sigma / st.sigma_unit)
    cost = np.log(sigma)
    if exp.design.target_sigma_um is not None:   # the target's term: kappa g(ln sigma/sigma_t) above it
        excess = np.log(sigma * st.sigma_unit / (exp.design.target_sigma_um * 1e-6))
        x = np.maximum(excess, 0.0)
        cost = cost + kappa * np.where(x > 1, 2 * x - 1, x * x)     # square up to e times, then linear
    return float(np.exp(np.sum(omega / omega.sum() * cost)
                        + coverage_weight * kappa * np.sum(area / area.sum() * huber)))


def test_candidates_information_adds_to_the_layouts(judged):
    exp, geometry, cand = judged
    assert len(cand.cameras) == 9 * 1          # 9 rail positions x 1 target x 1 lens (24 mm)
    scorer = Scorer(exp, geometry.samples)
    for pair in [(0, 8), (2, 6), (3, 4)]:
        cams = [cand.cameras[i] for i in pair]
        assert scorer.of(cand, pair) == pytest.approx(_pair_score(exp, geometry, cams), rel=1e-4)


def test_greedy_and_exchange_find_the_best_pair_which_is_symmetric(judged):
    exp, geometry, cand = judged
    scorer, feas = Scorer(exp, geometry.samples), Feasibility(exp, cand)
    order, _ = greedy(cand, scorer, feas, 2)
    chosen, score, _ = exchange(cand, scorer, feas, order)
    feasible = [p for p in itertools.combinations(range(len(cand.cameras)), 2)
                if not feas.conflicts(p[0], p[1])]
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
    cand = judge(free, geometry)
    scorer = Scorer(free, geometry.samples)
    feas = Feasibility(free, cand)
    chosen, _, _ = exchange(cand, scorer, feas, greedy(cand, scorer, feas, 2)[0])
    angle = lambda pair: abs(math.degrees(math.atan(cand.cameras[pair[0]].position[0] / 1.5)
                                          - math.atan(cand.cameras[pair[1]].position[0] / 1.5)))
    widest = 2 * math.degrees(math.atan(1 / 1.5))
    assert angle(chosen) < widest - 1
    limit = (angle(chosen) + widest) / 2
    free.path.write_text(free.path.read_text() + f"\n[optimize]\nmin_axis_angle_deg = {limit}\n")
    exp = config.load(free.path)
    feas = Feasibility(exp, cand)
    bound, _, _ = exchange(cand, scorer, feas, greedy(cand, scorer, feas, 2)[0])
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
    result = design_run(exp, out)
    messages = " | ".join(result.problems)
    assert "region 'top' needs 3 cameras" in messages
    assert "region 'underside': no candidate pose sees it" in messages
    assert "target sigma_max p95 1e-06 um is not reached" in messages
    designed = config.load(out / "designed.toml")
    assert len(designed.camera_specs) == 2
    assert (out / "pareto.csv").read_text().startswith("cameras,")
    page = (out / "report.html").read_text()
    assert "<h2>Design</h2>" in page and "Cameras needed" in page and "Chosen cameras" in page
    assert "no candidate pose sees it" in page and "Missing from this" not in page


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
    cand = judge(exp, prepare(exp))
    for i, c in enumerate(cand.cameras):
        expected = float(np.clip(c.position[0] - 0.1, 0.0, 1.0))
        assert cand.masked[i, 0] == pytest.approx(expected, abs=0.05), c.position[0]
    feas = Feasibility(exp, cand)
    assert np.array_equal(feas.obstructed, cand.assigned[:, 0] & (cand.masked[:, 0] > 0.01))
    assert np.array_equal(feas.alone, ~feas.obstructed & cand.framed)
    scorer = Scorer(exp, prepare(exp).samples)
    chosen, _, _ = exchange(cand, scorer, feas, greedy(cand, scorer, feas, 2)[0])
    assert len(chosen) == 2 and not any(cand.assigned[i, 0] and cand.masked[i, 0] > 0.01 for i in chosen)


FRAME_GRID = 400        # plate points per side for the in-image fraction by direct projection
FRAME_BORDER = 0.03    # |fraction - threshold| below this: the 10 mm samples may fall either way


def test_a_candidate_frames_every_region_it_sees_over_half_of(plate_experiment):
    """`Candidates.framed` against the pinhole projection of a dense grid on the plate (1 m x 1 m
    at z = 0, every point facing every candidate above it): f the fraction of the plate whose
    projection u = f_px x_c / z_c + c_x (and v) lies in [-0.5, W - 0.5] x [-0.5, H - 0.5]; a
    candidate seeing the plate over f >= assign_fraction must hold 1 - max_obscuration of it in
    its image, so framed = not (0.5 <= f < 0.99) (8 mm lenses frame all of it, 24 mm ones part).
    Candidates within FRAME_BORDER of either threshold (but the whole plate, f = 1) are not
    judged (the 10 mm samples resolve the edge to about that); the rest must agree, both kinds
    present. The field-of-view check of the designed layout holds."""
    path = plate_experiment(spacing=10)
    path.write_text(path.read_text() + DESIGN.format(n=2, extra="sample_spacing_mm = 10\nlenses_mm = [8, 24]")
                    .replace("sample_spacing_mm = 50\n", ""))
    exp = config.load(path)
    cand = judge(exp, prepare(exp))
    g = (np.arange(FRAME_GRID) + 0.5) / FRAME_GRID - 0.5
    X = np.stack([*np.meshgrid(g, g, indexing="ij"), np.zeros((FRAME_GRID, FRAME_GRID))], -1).reshape(-1, 3)
    claim, full = exp.optimize.assign_fraction, 1 - exp.optimize.max_obscuration
    judged = []
    for i, c in enumerate(cand.cameras):
        p = (X - c.position) @ c.R.T
        u = c.focal_px * p[:, 0] / p[:, 2] + (c.width - 1) / 2
        v = c.focal_px * p[:, 1] / p[:, 2] + (c.height - 1) / 2
        f = float(np.mean((p[:, 2] > 0) & (u >= -0.5) & (u <= c.width - 0.5) & (v >= -0.5)
                          & (v <= c.height - 0.5)))
        if abs(f - claim) < FRAME_BORDER or (f < 1 and abs(f - full) < FRAME_BORDER):
            continue
        judged.append(not (claim <= f < full))
        assert bool(cand.framed[i]) == judged[-1], (c.position, f)
    assert len(set(judged)) == 2, judged
    out = path.parent / "designed"
    design_run(exp, out)
    checks = json.loads((out / "constraints.json").read_text())["checks"]
    assert all(e["met"] for e in checks if e["constraint"] == "field_of_view")
    dropped = json.loads((out / "design.json").read_text())["dropped_per_mount"]
    unframed = sum(1 - bool(x) for x in cand.framed)
    left_out = sum(n for reasons in dropped.values() for why, n in reasons.items() if "field of view" in why)
    assert left_out == unframed > 0


ZONE = """
[[mount]]
name = "stand"
kind = "zone"
box_min_m = [-1.0, -0.3, 1.2]
box_max_m = [1.0, 0.3, 1.6]
"""

ON_ZONE = """
[[camera]]
name = "reference"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
mount = "stand"
target_m = [0, 0, 0]
"""


def test_zone_candidates_stand_on_the_grid_and_the_design_loads(plate_experiment, tmp_path):
    """A zone above the plate and no rail positions: the candidates stand on the zone's grid
    (zone_points along x and y x zone_heights), designed.toml places the cameras in the zone, and a
    floor polygon keeps the grid points inside it (and its centroid)."""
    exp = _experiment(plate_experiment, n=2, cameras=ZONE + ON_ZONE,
                      extra="zone_points = 3\nzone_heights = 2\nkeyframes = 0")
    exp = replace(exp, rails=())
    found = spots(exp)
    grid = np.array([p for *_, p in found])
    expected = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-0.3, 0, 0.3) for z in (1.2, 1.6)])
    assert sorted(map(tuple, grid)) == sorted(map(tuple, expected))
    assert {k for _, k, *_ in found} == {"zone"}
    out = tmp_path / "out"
    result = design_run(exp, out)
    again = config.load(out / "designed.toml")
    assert [c.mount for c in again.camera_specs] == ["stand", "stand"]
    for c in again.camera_specs:
        assert any(np.allclose(c.position, p) for p in expected)
    assert result.statistics["per_mount_kind"]["zone"] == len(judge(exp, prepare(exp)).cameras)
    # the DesignResult is what the folder holds: summary.json byte for byte, design.json's figures
    assert (out / "summary.json").read_text() == json.dumps(result.summary.to_json(), indent=2) + "\n"
    written = json.loads((out / "design.json").read_text())
    assert (written["problems"], written["constraint_violations"]) == (result.problems, result.violations)
    assert written["coverage_weight"] == exp.design.coverage_weight == 1.0
    assert [c["score"] for c in written["curve"]] == [c["score"] for c in result.curve]
    assert result.cameras == len(again.camera_specs) == result.curve[-1]["cameras"]
    assert result.refined is None
    # each designed camera carries the lenses the design chose from, so that --refine's lens
    # choice (even with another [optimize] catalogue) keeps to them: no lens outside a catalogue
    assert all(c.lenses == lenses(exp) for c in again.camera_specs)
    free = replace(again, optimize=replace(again.optimize, free=("pan", "tilt", "lens"), lenses=(0.5,)))
    assert config.lens_catalogue_errors(free) == []
    assert json.loads(json.dumps(result.to_json()))["summary"] == json.loads((out / "summary.json").read_text())
    # a triangle floor: of the 3 x 3 grid on its bounding box, the points inside it, and its centroid
    floor = replace(exp.mounts[0], floor=np.array([[-1.0, -0.3], [1.0, -0.3], [-1.0, 0.3]]),
                    height=(1.2, 1.2))
    pts = zone_grid(floor, 3, 2)
    inside = [(-1, -0.3), (0, -0.3), (1, -0.3), (-1, 0), (0, 0), (-1, 0.3)]
    assert sorted(map(tuple, np.round(pts[:, :2], 9))) == sorted(inside + [(round(-1 / 3, 9), -0.1)])
    assert np.all(pts[:, 2] == 1.2)


BODIES = """
[[body]]
name = "small"
sensor_mm = [22.2, 14.8]
pixels = [300, 200]
count = {small}

[[body]]
name = "large"
sensor_mm = [22.2, 14.8]
pixels = [1200, 800]
count = {large}
"""


def test_the_inventory_counts_are_respected(plate_experiment):
    """Two body kinds of one sensor size, 300 x 200 and 1200 x 800 pixels, one of each: every
    candidate carries one of them; once a kind is used its candidates are no longer allowed; the
    selected pair is the best of all feasible mixed pairs (exhaustive), and its score from the
    candidates equals the design's score of those two cameras ray cast anew (`_pair_score`)."""
    exp = _experiment(plate_experiment, n=2, regions=BODIES.format(small=1, large=1))
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    assert len(cand.cameras) == 9 * 2                  # 9 rail positions x 2 bodies x 1 lens
    assert [(c.width, c.height) for c in cand.cameras] == [(300, 200), (1200, 800)] * 9
    scorer, feas = Scorer(exp, geometry.samples), Feasibility(exp, cand)
    assert not np.any(feas.allowed([0]) & (cand.body == 0))
    assert not np.any(feas.allowed([1]) & (cand.body == 1))
    pick, score, _ = exchange(cand, scorer, feas, greedy(cand, scorer, feas, 2)[0])
    assert sorted(cand.body[pick]) == [0, 1]
    mixed = [p for p in itertools.combinations(range(len(cand.cameras)), 2)
             if cand.body[p[0]] != cand.body[p[1]] and not feas.conflicts(*p)]
    best = min(mixed, key=lambda p: scorer.of(cand, p))
    assert sorted(pick) == sorted(best)
    cams = [cand.cameras[i] for i in pick]
    assert score == pytest.approx(_pair_score(exp, geometry, cams), rel=1e-4)


@pytest.mark.parametrize("extra, field, message", [
    ("[design]\nsensor_width_mm = 22.2\npixels = [600, 400]\n", "design.sensor_width_mm", "not both"),
    ("[design]\nmax_cameras = 5\n", "design.max_cameras", "more than the 3 [[body]] bodies"),
    ('[[body]]\nname = "x"\nsensor_mm = [22.2, 1]\npixels = [600, 400]\ncount = 1\n', "sensor_mm",
     "non-square"),
])
def test_bad_inventories_are_refused(plate_experiment, extra, field, message):
    path = plate_experiment()
    path.write_text(path.read_text() + BODIES.format(small=1, large=2) + extra)
    with pytest.raises(ConfigError, match=rf"{re.escape(field)}.*{re.escape(message)}"):
        config.load(path)


def test_candidates_lose_what_the_load_path_hides(plate_experiment):
    """A 1.2 m shutter at z = 0.75 m slides in -x by 0.5 m per step (steps 1-7) from x = 3 m. One
    keyframe: the step farthest from rest, 7, where it spans x in [-1.1, 0.1]. The ray from a
    candidate at (c, 0, 1.5) to a plate point (p, y, 0) crosses z = 0.75 at x = (c + p) / 2, so the
    candidate loses the samples with (c + p) / 2 < 0.1 and keeps the others (as at rest)."""
    path = plate_experiment(spacing=50, extra_meshes=SLIDING_SHUTTER,
                            files=[("shutter.stl", [1200, 1200, 10], [3000, 0, 750])])
    rows = ["step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg"]
    (path.parent / "poses.csv").write_text(
        "\n".join(rows + [f"{k},slide,{-500 * k},0,0,0,0,0" for k in range(1, 8)]) + "\n")
    path.write_text(path.read_text() + DESIGN.format(n=2, extra="keyframes = 1"))
    exp = config.load(path)
    lp = load_path_of(None, **load_path_tables(exp))
    assert keyframe_steps(lp, 1) == (7,)            # the farthest from rest
    assert keyframe_steps(lp, 2) == (1, 7)          # then the other extreme of the slide
    geometry = prepare(exp)
    moving = judge(exp, geometry)
    still = judge(replace(exp, design=replace(exp.design, keyframes=0)), geometry)
    x = geometry.samples.points[:, 0]
    for i, c in enumerate(moving.cameras):
        cross = (c.position[0] + x) / 2
        hidden, clear = cross < 0.1 - 0.02, cross > 0.1 + 0.02
        assert np.all(moving.weight[i, hidden] == 0) and np.all(moving.info[i, hidden] == 0)
        np.testing.assert_array_equal(moving.weight[i, clear], still.weight[i, clear])
    assert np.all(still.path_lost == 0) and moving.path_lost.max() > 0.5


def test_too_few_spots_for_a_region_are_named(plate_experiment):
    """Two rail positions (x = -1 and +1 m) for a region that needs 3 cameras out of an inventory
    of 3: the region is named with the 2 spots that see it."""
    exp = _experiment(plate_experiment, n=3)
    exp = replace(exp, design=replace(exp.design, rail_positions=2),
                  regions=(replace(exp.regions[0], min_cameras=3),))
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    assert sorted(c.position[0] for c in cand.cameras) == [-1.0, 1.0]
    assert problems(exp, cand, geometry.samples) == [
        "region 'top' needs 3 cameras (min_cameras) but only 2 candidate spot(s) see it: add a "
        "mount in view of it"]


def test_the_curve_is_over_the_measurable_area_with_sigma_per_region(plate_experiment, tmp_path):
    """The plate's underside faces away from the rail above it: no candidate sees it, so the
    worst-region sigma is None at every count, while the curve over the measurable area (the top:
    half the regions' area, the two faces being equal) has a sigma from two cameras on, the top's
    own, and counts the coverage of that area alone."""
    exp = _experiment(plate_experiment, n=2, regions='\n[[region]]\nname = "under"\nmesh = "plate"\n'
                                                     'normal = [0, 0, -1]\n[render]\nambient_radiance = 20\n')
    result = design_run(exp, tmp_path / "out")
    for c in result.curve:
        assert c["sigma_p95_um"] is None
        assert c["measurable_fraction"] == pytest.approx(0.5, abs=1e-9)
        assert c["sigma_p95_by_region_um"]["under"] is None
        assert c["sigma_p95_measurable_um"] == c["sigma_p95_by_region_um"]["top"]
        assert (c["sigma_p95_measurable_um"] is not None) == (c["cameras"] >= 2)   # two views measure
        assert c["coverage_of_measurable"] == pytest.approx(2 * c["coverage"], abs=1e-9)
    text = (tmp_path / "out" / "pareto.csv").read_text().splitlines()
    assert text[0].endswith("sigma_p95_um_top,sigma_p95_um_under")
    # the console names the unmeasured region and gives sigma over the measured area
    for c in result.curve:
        line = curve_line(c, ["top", "under"])
        assert "under: none of it measured" in line
        if c["sigma_p95_measurable_um"] is not None:
            assert f"sigma_max p95 {c['sigma_p95_measurable_um']:.3f} um over the measured area" in line
        assert f"coverage {100 * c['coverage']:.1f} % ({100 * c['coverage_of_measurable']:.1f} %" in line


def test_sparse_scores_equal_whole_sums_and_blocks_equal_one_judgement(judged, monkeypatch):
    """Scorer.add corrects the base's sums at a candidate's stored entries only: equal to
    Scorer.of, which sums every sample (checked against `_pair_score` above), for every
    candidate added to every base pair; judging in blocks of 2 candidates stores the same entries
    as one block."""
    exp, geometry, cand = judged
    scorer = Scorer(exp, geometry.samples)
    K = len(cand.cameras)
    for base in [(), (0,), (1, 7)]:
        rows = np.array([k for k in range(K) if k not in base])
        fast = scorer.add(*cand.sums(list(base)), cand, rows)
        whole = [scorer.of(cand, list(base) + [k]) for k in rows]
        np.testing.assert_allclose(fast, whole, rtol=SUM_ORDER_RTOL)
        with monkeypatch.context() as m:                         # chunks that cut candidates' rows
            m.setattr("vdo.design.score.ENTRY_CHUNK", 37)
            np.testing.assert_allclose(scorer.add(*cand.sums(list(base)), cand, rows), whole,
                                       rtol=SUM_ORDER_RTOL)
    assert cand.index.size < K * len(geometry.samples)          # only the pairs in view are stored
    monkeypatch.setattr("vdo.design.candidates.PAIRS_PER_BLOCK", 2 * len(geometry.samples))
    small = judge(exp, geometry)
    for name in ("indptr", "index", "entry_info", "entry_weight", "assigned", "masked", "path_lost"):
        np.testing.assert_array_equal(getattr(small, name), getattr(cand, name), err_msg=name)


def test_the_target_term_matches_its_closed_form_and_the_sparse_sums(plate_experiment):
    """With [design] target_sigma_um at the median sigma of one pair's measured samples (a lit
    plate), the score equals `_pair_score`'s independent computation with the term
    kappa g(max(0, ln(sigma / sigma_t))) added per sample (g: square up to 1, then linear), rises above the score without a target, and
    Scorer.add still equals Scorer.of for every candidate added to a base."""
    exp = _experiment(plate_experiment, regions="\n[render]\nambient_radiance = 20\n")
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    plain = Scorer(exp, geometry.samples)
    sigma = plain.sigma(cand.sums([2, 6])[0]) * plain.settings.sigma_unit
    measured = sigma[sigma < 0.1 * plain.settings.prior_sigma]
    assert measured.size > 50
    aimed = replace(exp, design=replace(exp.design, target_sigma_um=float(np.median(measured)) * 1e6))
    scorer = Scorer(aimed, geometry.samples)
    for pair in [(0, 8), (2, 6), (3, 4)]:
        cams = [cand.cameras[i] for i in pair]
        assert scorer.of(cand, pair) == pytest.approx(_pair_score(aimed, geometry, cams), rel=1e-4)
        assert scorer.of(cand, pair) >= plain.of(cand, pair)
    assert scorer.of(cand, (2, 6)) > 1.01 * plain.of(cand, (2, 6))
    for base in [(), (1, 7)]:
        rows = np.array([k for k in range(len(cand.cameras)) if k not in base])
        np.testing.assert_allclose(scorer.add(*cand.sums(list(base)), cand, rows),
                                   [scorer.of(cand, list(base) + [k]) for k in rows], rtol=SUM_ORDER_RTOL)


@pytest.mark.parametrize("weight", [0.25, 4.0])
def test_the_coverage_weight_scales_the_coverage_term_only(plate_experiment, weight):
    """[design] coverage_weight multiplies the coverage term's kappa and nothing else (the
    target's term keeps the default kappa): with a target at the median sigma of a pair, the
    score equals `_pair_score`'s independent computation with coverage_weight x kappa for pairs
    and for one camera alone (every sample at least a view short), and ln(score / default
    score) is (weight - 1) times the default's coverage term, read from `_pair_score`."""
    exp = _experiment(plate_experiment, regions="\n[render]\nambient_radiance = 20\n")   # lit
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    sigma = Scorer(exp, geometry.samples).sigma(cand.sums([2, 6])[0]) * settings(exp.evaluation).sigma_unit
    target = float(np.median(sigma[sigma < 0.1 * settings(exp.evaluation).prior_sigma])) * 1e6
    aimed = replace(exp, design=replace(exp.design, target_sigma_um=target))
    plain = Scorer(aimed, geometry.samples)
    weighted = Scorer(replace(aimed, design=replace(aimed.design, coverage_weight=weight)), geometry.samples)
    for chosen in [(2, 6), (0, 8), (3,)]:
        cams = [cand.cameras[i] for i in chosen]
        mine = _pair_score(aimed, geometry, cams, coverage_weight=weight)
        default = _pair_score(aimed, geometry, cams)
        assert weighted.of(cand, chosen) == pytest.approx(mine, rel=1e-4)
        assert plain.of(cand, chosen) == pytest.approx(default, rel=1e-4)
        coverage_term = (math.log(_pair_score(aimed, geometry, cams, coverage_weight=2.0)) - math.log(default))
        assert math.log(weighted.of(cand, chosen) / plain.of(cand, chosen)) == pytest.approx(
            (weight - 1) * coverage_term, rel=1e-3, abs=1e-9)
    assert math.log(plain.of(cand, (3,))) - math.log(_pair_score(
        replace(aimed, design=replace(aimed.design, target_sigma_um=None)), geometry, [cand.cameras[3]])) > 0


def test_a_coverage_weight_of_zero_is_refused_in_one_line(plate_experiment):
    from vdo.core.errors import ConfigError

    path = plate_experiment()
    path.write_text(path.read_text() + DESIGN.format(n=2, extra="coverage_weight = 0"))
    with pytest.raises(ConfigError, match=r"coverage_weight.*> 0|coverage_weight.*positive"):
        config.load(path)


def test_stored_pairs_equal_the_dense_information_and_weights(judged):
    """The stored entries (`objective.pair_information` on the listed pairs) equal the dense
    (candidates, samples) arrays of `objective.camera_information` and `objective.geometry`'s
    weight times the ray cast's occlusion, zero wherever nothing is stored."""
    exp, geometry, cand = judged
    cams = list(cand.cameras)
    vis = compute_visibility(build_scene(list(geometry.meshes)), cams, geometry.samples,
                             exp.evaluation.incidence_limit, progress=False)
    smp = samples_for_objective(exp.regions, geometry.samples)
    light = illuminate(build_scene(list(geometry.meshes)), exp.lights, geometry.samples,
                       exp.render.ambient_radiance)
    st = replace(settings(exp.evaluation), pair_dtype="float64")
    cp = objective.CameraParams.from_cameras(cams)
    views = view_data(exp.speckle, exp.sensor, smp, vis, light, geometry.speckle)
    C = np.asarray(objective.camera_information(cp, smp, views, geometry.speckle.table, st))
    dense = C[..., [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]
    w = np.asarray(objective.geometry(cp, smp, st).weight) * vis.unoccluded
    np.testing.assert_allclose(cand.info, dense, rtol=SUM_ORDER_RTOL, atol=SUM_ORDER_RTOL * np.abs(dense).max())
    np.testing.assert_allclose(cand.weight, w.astype(np.float32), rtol=0, atol=0)


SCALING_TOL = 0.15   # stored pairs grow as 1 / spacing^2 only up to the regions' edges


def test_estimate_against_the_judgement_and_the_refusal_names_a_spacing_that_fits(plate_experiment):
    """Fewer candidates than PROBE: the estimate judges them all, so its stored pairs are the
    judgement's and its stored bytes the arrays' own. A memory limit a quarter of the way from the
    fixed part to the estimate is refused naming a spacing (at least 2x coarser) and a candidate
    count; the estimate at that spacing fits within SCALING_TOL. A time limit half the judging's
    estimate: a spacing sqrt(2) coarser; one that the judging fits but not the search is not
    refused (the selection stops at the limit)."""
    exp = _experiment(plate_experiment)
    geometry = prepare(exp)
    j = judging(exp, geometry)
    est = estimate(exp, j, Scorer(exp, geometry.samples))
    cand = judge(exp, geometry, j)
    assert est.probed == len(j.cams) and est.entries == cand.index.size
    assert est.entries * ENTRY_BYTES == \
        cand.index.nbytes + cand.entry_info.nbytes + cand.entry_weight.nbytes
    room = 0.25 * (est.memory_bytes - est.fixed_bytes)
    with pytest.raises(ConfigError) as err:
        refuse(exp, est, est.fixed_bytes + room, None)
    msg = str(err.value)
    assert "design.sample_spacing_mm" in msg and "\n" not in msg
    spacing = int(re.search(r"sample_spacing_mm of (\d+) or more", msg)[1])
    assert spacing >= 2 * 50 and f"at most {int(est.candidates / 4):,} candidates" in msg
    coarse = replace(exp, design=replace(exp.design, sample_spacing=spacing / 1e3))
    g2 = prepare(replace(coarse, evaluation=replace(coarse.evaluation, sample_spacing=spacing / 1e3)))
    est2 = estimate(coarse, judging(coarse, g2), Scorer(coarse, g2.samples))
    assert est2.memory_bytes - est2.fixed_bytes <= room * (1 + SCALING_TOL)
    with pytest.raises(ConfigError, match=rf"sample_spacing_mm of {math.ceil(50 * math.sqrt(2))} or more"):
        refuse(exp, est, math.inf, est.judge_s / 2)
    refuse(exp, est, est.memory_bytes, est.judge_s)     # what fits is not refused
    assert est.search_s > 0
    refuse(exp, est, math.inf, est.judge_s + est.search_s / 2)


def test_the_estimate_judges_one_block_of_the_size_the_judging_uses(plate_experiment, monkeypatch):
    """Judging a block (ray casts, Dr.Jit's and JAX's arrays) takes memory that grows with the
    block, so the estimate's peak is measured after judging one block as large as the judging's:
    blocks of 3 candidates here (of 9), the probe PROBE_WARM = 1 candidate then 3."""
    from vdo.design import budget, candidates

    exp = _experiment(plate_experiment)
    geometry = prepare(exp)
    j = judging(exp, geometry)
    monkeypatch.setattr(candidates, "PAIRS_PER_BLOCK", 3 * len(geometry.samples))
    monkeypatch.setattr(budget, "PROBE", 2)
    monkeypatch.setattr(budget, "PROBE_WARM", 1)
    sizes = {"estimate": [], "judge": []}
    real = candidates.judge_block

    def recorded(where):
        def block(jj, start, stop):
            sizes[where].append(stop - start)
            return real(jj, start, stop)
        return block

    monkeypatch.setattr(budget, "judge_block", recorded("estimate"))
    est = estimate(exp, j, Scorer(exp, geometry.samples))
    monkeypatch.setattr(candidates, "judge_block", recorded("judge"))
    judge(exp, geometry, j)
    assert sizes == {"estimate": [1, 3], "judge": [3, 3, 3]} and est.probed == 4


def test_design_refused_on_the_command_line_in_one_line(plate_experiment, tmp_path, capsys):
    """`vdo design --memory-gb` below the estimate: exit 2, one line naming the file and the
    field, no traceback, no output folder."""
    from vdo.commands.cli import main

    exp = _experiment(plate_experiment)
    out = tmp_path / "out"
    assert main(["design", str(exp.path), "--out", str(out), "--memory-gb", "0.01", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0] and str(exp.path) in err[0]
    assert "design" in err[0] and "GB" in err[0]
    assert not out.exists()


def test_candidates_judged_on_a_two_worker_local_cluster_equal_the_local_run(plate_experiment, tmp_path,
                                                                             monkeypatch):
    """Blocks of 3 candidates as tasks on a dask.distributed LocalCluster of 2 spawned worker
    processes: the same stored pairs, regions and obscuration as the local judgement, and the same
    selection."""
    from distributed import Client, LocalCluster

    exp = _experiment(plate_experiment)          # [evaluation] and [design] spacing both 50 mm
    geometry = prepare(exp)
    monkeypatch.setattr("vdo.design.candidates.PAIRS_PER_BLOCK", 3 * len(geometry.samples))
    local = judge(exp, geometry)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      local_directory=str(tmp_path / "dask")) as cluster, Client(cluster) as client:
        remote = judge(exp, geometry, client=client, threads=1)
    for name in ("indptr", "index", "entry_info", "entry_weight", "assigned", "masked", "path_lost"):
        np.testing.assert_array_equal(getattr(remote, name), getattr(local, name), err_msg=name)
    picks = []
    for cand in (local, remote):
        scorer, feas = Scorer(exp, geometry.samples), Feasibility(exp, cand)
        picks.append(exchange(cand, scorer, feas, greedy(cand, scorer, feas, 2)[0])[0])
    assert picks[0] == picks[1]


def test_sparse_scores_when_a_candidate_sees_the_worst_samples(judged):
    """A base of every candidate but one leaves its worst samples to the one left out: the score
    of adding it (the base's log-sum corrected at the samples it sees) equals Scorer.of's sum over
    every sample."""
    exp, geometry, cand = judged
    scorer = Scorer(exp, geometry.samples)
    K = len(cand.cameras)
    for k in range(K):
        base = [i for i in range(K) if i != k]
        fast = scorer.add(*cand.sums(base), cand, [k])[0]
        assert fast == pytest.approx(scorer.of(cand, base + [k]), rel=SUM_ORDER_RTOL)


def test_design_on_the_command_line_with_a_local_dask_cluster(plate_experiment, tmp_path):
    """`vdo design --dask local --workers 2` (docs/scale.md) writes the layout of the local run."""
    from vdo.commands.cli import main

    exp = _experiment(plate_experiment)
    local, remote = tmp_path / "local", tmp_path / "dask"
    assert main(["design", str(exp.path), "--out", str(local), "--quiet"]) == 0
    assert main(["design", str(exp.path), "--out", str(remote), "--quiet", "--dask", "local",
                 "--workers", "2"]) == 0
    assert (remote / "layout.json").read_text() == (local / "layout.json").read_text()


def test_a_target_met_in_sigma_but_not_in_coverage_says_so(plate_experiment, tmp_path):
    """Only the top is scored ([optimize] regions) and the underside, which no candidate sees, is
    never covered: a target every count's sigma meets is reported as met on sigma, with the
    coverage that keeps the count from being named, not as 'not reached'."""
    exp = _experiment(plate_experiment, n=2, extra="target_sigma_um = 1000",
                      regions='\n[[region]]\nname = "under"\nmesh = "plate"\nnormal = [0, 0, -1]\n'
                              '[render]\nambient_radiance = 20\n[optimize]\nregions = ["top"]\n')
    result = design_run(exp, tmp_path / "out")
    assert result.target_count is None
    met = [p for p in result.problems if p.startswith("target sigma_max p95 1000 um")]
    assert len(met) == 1 and "is reached on region(s) 'top' from 2 cameras" in met[0]
    assert f"at most {100 * max(c['coverage'] for c in result.curve):.1f} % of the area" in met[0]


def test_a_camera_body_under_another_on_the_same_spot_is_a_conflict(plate_experiment):
    """Candidates at two heights over each rail position (offset 0.3 m up and down): the lower
    camera's body sits in the upper one's view of the plate. `Feasibility.hides` must call a
    pair a conflict exactly when Mitsuba's ray test, from the one camera's optical centre to the
    samples it sees usably, against the other camera's body mesh, hides more than
    max_obscuration of a region the first is assigned (either way round)."""
    from vdo.core.backend import mitsuba
    from vdo.scene import camera_body

    path = plate_experiment(spacing=50)
    path.write_text(path.read_text() + "\n[render]\nambient_radiance = 20\n"
                    + DESIGN.format(n=2, extra="").replace("offset_m = [0, 0, 0]", "offset_m = [0, 0, 0.3]"))
    exp = config.load(path)
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    feas = Feasibility(exp, cand, geometry.samples)
    smp, limit, mi = geometry.samples, exp.optimize.max_obscuration, mitsuba()
    use = cand.entry_weight >= 0.5
    R = len(smp.region_names)

    def hides(j, k):
        """Does camera j's body hide more than the limit of a region assigned to k? (ray test)"""
        mine = use & (cand.row == k)
        X = smp.points[cand.index[mine]]
        C = cand.cameras[k].position
        d = X - C
        length = np.linalg.norm(d, axis=1)
        ray = mi.Ray3f(mi.Point3f(*np.tile(C, (len(X), 1)).T), mi.Vector3f(*(d / length[:, None]).T))
        ray.maxt = mi.Float(length)
        lost = np.asarray(build_scene([camera_body(cand.cameras[j])]).ray_test(ray), dtype=bool)
        region, area = smp.region[cand.index[mine]], smp.area[cand.index[mine]]
        frac = np.bincount(region[lost], area[lost], minlength=R) / np.maximum(
            np.bincount(region, area, minlength=R), 1e-30)
        return bool((cand.assigned[k] & (frac > limit)).any())

    heights = np.round(cand.positions[:, 2], 3)
    assert len(np.unique(heights)) == 2
    checked = conflicts = 0
    for j in range(0, len(cand.cameras), 3):
        row = feas.hides(j)
        for k in range(len(cand.cameras)):
            if k != j:
                expected = hides(j, k) or hides(k, j)
                assert row[k] == expected, (j, k)
                checked, conflicts = checked + 1, conflicts + expected
    assert conflicts >= 2 and checked > 20        # both answers occur


def _layout_figures(exp, geometry, cams):
    """The polish's figures of a layout from `_own_fields` (not the candidates' sums): usable
    views w >= 0.5 counted per sample, then the worst scored region's p95 of the smooth sigma
    over the samples seen by >= 2 views (units of sigma_unit) and the area fraction seen by
    min_cameras."""
    sigma, f, _ = _own_fields(exp, geometry, cams)
    count = (np.asarray(f.weights) >= 0.5).sum(0)
    region, area = geometry.samples.region, np.asarray(geometry.samples.area)
    need = np.array([r.min_cameras for r in exp.regions])[region]
    seen = [(region == r) & (count >= 2) for r in range(len(exp.regions))]
    p95 = [np.percentile(sigma[m], 95) if m.any() else np.inf for m in seen]
    return max(p95), float(area[count >= need].sum() / area.sum())


def test_the_polish_reads_its_figures_right_and_no_single_swap_beats_it(plate_experiment):
    """`figures` (the candidates' sums, vectorised) equals `_layout_figures` (each layout's own
    ray cast) for every candidate added to a pair; the polished triple's worst p95 is no higher
    than the exchange's at no less coverage, and no feasible single swap, judged by
    `_layout_figures`, lowers it further (by the polish's relative step) at the same coverage."""
    exp = _experiment(plate_experiment, n=3, regions="\n[render]\nambient_radiance = 20\n")
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    scorer, feas = Scorer(exp, geometry.samples), Feasibility(exp, cand, geometry.samples)
    own = lambda rows: _layout_figures(exp, geometry, [cand.cameras[i] for i in rows])  # noqa: E731
    K = len(cand.cameras)
    rows = [k for k in range(K) if k not in (1, 7)]
    fig = figures(cand, scorer, geometry.samples, [1, 7], rows)
    for k, row in enumerate(rows):
        worst, cover = own([1, 7, row])
        assert fig.worst_p95[k] == pytest.approx(worst, rel=1e-4)
        assert fig.coverage[k] == pytest.approx(cover, abs=1e-12)
    order, _ = greedy(cand, scorer, feas, 3)
    chosen, _, _ = exchange(cand, scorer, feas, order)
    for start in (chosen, [3, 4, 5]):            # the design's triple, and three bunched cameras
        polished, swaps = polish(cand, scorer, feas, geometry.samples, list(start))
        (w0, c0), (w1, c1) = own(start), own(polished)
        assert w1 <= w0 and c1 >= c0 - 1e-12
        assert (swaps > 0) == (polished != list(start))
        _no_swap_beats(polished, w1, c1, own, feas)
    assert swaps > 0 and w1 < 0.5 * w0           # the bunched triple spreads: its p95 halves at least


def _no_swap_beats(polished, w1, c1, own, feas):
    for slot in range(3):
        rest = polished[:slot] + polished[slot + 1:]
        for k in np.flatnonzero(feas.allowed(rest)):
            if k in polished:
                continue
            w, c = own(rest + [int(k)])
            assert not (c >= c1 - 1e-12 and w < w1 * (1 - POLISH_RTOL)), (rest, k, w, w1)


def test_the_polish_percentiles_are_numpys_per_region():
    """`percentile_by_region` (one sort of a padded table) against np.nanpercentile region by
    region: NaN values ignored, a region left without values NaN, a region not kept absent."""
    import warnings

    rng = np.random.default_rng(0)
    region = rng.integers(0, 7, 500)
    keep = (rng.random(500) > 0.2) & (region != 3)
    values = rng.random((5, 500))
    values[rng.random((5, 500)) < 0.3] = np.nan
    values[2, region == 5] = np.nan
    got = percentile_by_region(values, region_table(region, keep), 95.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # the all-NaN region
        want = np.stack([np.nanpercentile(values[:, keep & (region == r)], 95, axis=1)
                         for r in np.unique(region[keep])], 1)
    np.testing.assert_allclose(got, want, rtol=1e-12)     # NaN where both are NaN
    assert np.isnan(got[2, list(np.unique(region[keep])).index(5)])


def test_refine_starts_from_the_design_and_says_both_ends(plate_experiment, tmp_path, capsys):
    """`vdo design --refine` (README's command table): `vdo optimize` runs from the designed layout
    into out/refine; its 'before' is the design's own judgement (summary.json's worst scored
    region), and the console line gives both ends with the constraint violations of each, as
    design.json, refine/summary_*.json and refine/constraints.json hold them."""
    from vdo.commands.cli import main

    exp = _experiment(plate_experiment, n=2)
    exp.path.write_text(exp.path.read_text() + "\n[render]\nambient_radiance = 20\n"
                        "[optimize]\nstarts = 1\nrounds = 1\nmax_steps = 5\n")
    out = tmp_path / "out"
    assert main(["design", str(exp.path), "--out", str(out), "--refine"]) == 0
    line = [s for s in capsys.readouterr().out.splitlines() if s.startswith("refined:")]
    design = json.loads((out / "design.json").read_text())
    refined = json.loads((out / "refine" / "constraints.json").read_text())

    def worst(summary):
        return max(r["sigma_max_um"]["p95"] for r in json.loads(summary.read_text())["regions"].values())

    before, after = worst(out / "refine" / "summary_before.json"), worst(out / "refine" / "summary_after.json")
    assert before == pytest.approx(worst(out / "summary.json"), rel=SUM_ORDER_RTOL)
    assert line == [f"refined: sigma_max p95 of the worst scored region {before:.3f} um "
                    f"({design['constraint_violations']} constraint violation(s)) -> {after:.3f} um "
                    f"({refined['violations']})"]
    assert config.load(out / "refine" / "optimized.toml").camera_specs


def test_refine_keeps_to_the_time_limit(plate_experiment, monkeypatch):
    """`vdo design --refine --time-limit T`: the refinement's optimize gets what is left of T
    (trial 4: it ran with optimize's own 900 s default after a 240 s design), at least
    REFINE_MIN_S; without a limit, optimize's default."""
    from vdo.design import select

    given = []

    def record(exp, **kwargs):
        given.append(kwargs.get("time_limit"))
        return "refined"

    monkeypatch.setattr(select, "optimize_layout", record)
    exp = _experiment(plate_experiment, n=2)
    t0 = time.perf_counter()
    assert design_layout(exp, refine=True, time_limit=120.0).refined == "refined"
    spent = time.perf_counter() - t0
    assert select.REFINE_MIN_S <= given[0] <= max(select.REFINE_MIN_S, 120.0 - spent + 1.0)
    assert design_layout(exp, refine=True).refined == "refined" and given[1] is None


def test_the_selection_stops_at_the_time_limit_with_the_inventory_searched_first(plate_experiment, monkeypatch):
    """The design's clock jumps past the time limit once the first camera count is searched: the
    result is the inventory's layout (as without a limit), the curve holds that count alone, the
    skipped counts are named in `problems`, and no bound is computed (no time left)."""
    from vdo.design import select

    exp = _experiment(plate_experiment, extra="min_cameras = 1")
    free = design_layout(exp)
    assert len(free.curve) >= 2
    real, jumped = select._clock, {"s": 0.0}

    def exchange(*args, **kwargs):
        out = real_exchange(*args, **kwargs)
        jumped["s"] = 1e6                    # the first count took "a million seconds"
        return out

    real_exchange = select.exchange
    monkeypatch.setattr(select, "exchange", exchange)
    monkeypatch.setattr(select, "_clock", lambda: real() + jumped["s"])
    cut = design_layout(exp, time_limit=1e5)
    assert [c["cameras"] for c in cut.curve] == [free.curve[-1]["cameras"]]
    assert cut.curve[0]["chosen"] == free.curve[-1]["chosen"] and cut.cameras == free.cameras
    assert cut.curve[0]["bound"] is None
    skipped = [c["cameras"] for c in free.curve[:-1]]
    assert any(f"counts {min(skipped)}..{max(skipped)} were searched" in p for p in cut.problems)


@pytest.mark.parametrize("limit", ["0", "-5"])
def test_a_time_limit_that_is_not_positive_is_one_line(plate_experiment, tmp_path, capsys, limit):
    """`vdo design --time-limit 0 | -5`: exit 2, one line naming the option and the fix, no
    traceback, no output folder (it divided by zero or took a square root of a negative)."""
    from vdo.commands.cli import main

    exp = _experiment(plate_experiment)
    out = tmp_path / "out"
    assert main(["design", str(exp.path), "--out", str(out), "--time-limit", limit, "--quiet"]) == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line.startswith("error")]
    assert len(err) == 1 and "--time-limit: must be a positive number of seconds" in err[0]
    assert not out.exists()


def test_with_the_aperture_free_candidates_that_no_stop_holds_sharp_are_left_out(plate_experiment):
    """"aperture" in [exposure] free: a candidate is left out when no focus distance holds the depth
    of its usable samples in its assigned regions within the thin lens's depth of field
    (`checks.depth_of_field`, circle of confusion 2 pixels) a third of a stop below the largest
    stop. Judged here by a scan of focus distances, that stop set to the median of what the
    candidates need (so that both kinds are present); candidates within 2 % of it are not judged."""
    from vdo.physics.checks import COC_PIXELS, depth_of_field

    path = plate_experiment(spacing=50)
    path.write_text(path.read_text() + DESIGN.format(n=2, extra="lenses_mm = [24, 50]")
                    + '\n[exposure]\nfree = ["aperture"]\n')
    exp = config.load(path)
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    samples = geometry.samples
    use = cand.usable_entries
    rows, index = cand.row[use], cand.index[use]
    keep = cand.assigned[rows, samples.region[index]]

    def sharp_at(k, stop):
        pts = samples.points[index[keep & (rows == k)]]
        if not len(pts):
            return True
        c = cand.cameras[k]
        z = (pts - c.position) @ c.optical_axis
        for s in np.linspace(z.min(), z.max(), 400):
            near, far = depth_of_field(c.focal_length, stop, s, COC_PIXELS * c.pixel_size)
            if near <= z.min() and z.max() <= far:
                return True
        return False

    def need(k):     # the smallest stop that holds candidate k sharp, by bisection on sharp_at
        lo, hi = 0.1, 1e4
        for _ in range(40):
            mid = math.sqrt(lo * hi)
            lo, hi = (lo, mid) if sharp_at(k, mid) else (mid, hi)
        return hi

    needs = np.array([need(k) for k in range(len(cand.cameras))])
    top = float(np.median(needs))
    exp = replace(exp, exposure=replace(exp.exposure, f_numbers=(0.5, top * STOP_MARGIN)))
    feas = Feasibility(exp, cand, samples)
    judged = np.abs(needs / top - 1) > 0.02
    framed = ~feas.obstructed & cand.framed
    expected = (needs > top) & framed
    assert np.array_equal(feas.blurred[judged], expected[judged])
    assert feas.blurred.any() and (framed & ~feas.blurred).any()
    assert not feas.alone[feas.blurred].any()
    left = feas.left_out()
    assert sum(n for reasons in left.values() for why, n in reasons.items()
               if "depth of field" in why) == int(feas.blurred.sum())


def test_the_relaxation_is_rounded_by_weight_into_a_feasible_selection(judged):
    """`rounded`: the candidates by decreasing weight, each kept while feasible with those kept
    (`Feasibility.conflicts`), then greedy to k. A heavy candidate that conflicts with a heavier
    one is skipped; with no weight left, greedy completes the selection. The rounded start of
    the whole design is judged in `vdo design`'s log on the built-in (docs/design.md)."""
    from vdo.design.moves import rounded

    exp, geometry, cand = judged
    scorer, feas = Scorer(exp, geometry.samples), Feasibility(exp, cand)
    K = len(cand.cameras)
    usable = [k for k in range(K) if feas.alone[k]]        # the others no selection may hold
    free = [(a, b) for a, b in itertools.combinations(usable, 2) if not feas.conflicts(a, b)]
    assert free
    a, b = free[0]
    w = np.full(K, 0.01)
    w[a], w[b] = 0.9, 0.8
    assert rounded(cand, scorer, feas, w, 2) == [a, b]
    clash = next((c for c in usable if c not in (a, b) and feas.conflicts(a, c)), None)
    if clash is not None:             # heavier than b but in conflict with a: skipped
        w[clash] = 0.85
        assert rounded(cand, scorer, feas, w, 2) == [a, b]
    w = np.zeros(K)
    w[a] = 1.0
    chosen = rounded(cand, scorer, feas, w, 2)
    greedy_pick, _ = greedy(cand, scorer, feas, 2, start=[a])
    assert chosen == greedy_pick and chosen[0] == a
    assert not any(feas.conflicts(x, y) for x, y in itertools.combinations(chosen, 2))


def test_a_chosen_camera_is_told_what_part_of_each_region_it_sees():
    """`seen_fractions`: the area fraction of each region a camera views usably (on an all-round
    rig a useful camera sees no region whole), against the hand count on four samples."""
    from types import SimpleNamespace

    from vdo.design.measures import seen_fractions

    samples = SimpleNamespace(region=np.array([0, 0, 1, 1]), area=np.array([1.0, 3.0, 2.0, 2.0]),
                              region_names=("bend", "leg"))
    usable = np.array([[True, False, True, True], [False, True, False, False]])
    state = SimpleNamespace(samples=samples, prediction=SimpleNamespace(usable=usable),
                            cameras=(SimpleNamespace(name="d1"), SimpleNamespace(name="d2")))
    assert seen_fractions(state) == {"d1": {"bend": 0.25, "leg": 1.0}, "d2": {"bend": 0.75, "leg": 0.0}}


def test_the_curve_compares_the_counts_on_the_area_every_count_measures():
    """`common_p95`: each count's sigma_max p95 over the samples that every count measures (its
    own figure is over a different area at each count), against numpy's percentile on that
    area; the private arrays leave the curve."""
    from types import SimpleNamespace

    from vdo.design.measures import common_p95

    rng = np.random.default_rng(3)
    n = 400
    samples = SimpleNamespace(region=np.repeat([0, 1], n // 2), area=np.full(n, 1e-4),
                              region_names=("a", "b"))
    measured = [rng.random(n) < p for p in (0.5, 0.7, 0.9)]
    sigma = [rng.uniform(1e-7, 1e-6, n) for _ in measured]
    curve = [{"cameras": k + 2, "_measured": m, "_sigma_max": s} for k, (m, s) in enumerate(zip(measured, sigma))]
    exp = SimpleNamespace(optimize=SimpleNamespace(regions=None), regions=(SimpleNamespace(name="a"),
                                                                              SimpleNamespace(name="b")))
    common_p95(exp, samples, curve)
    both = measured[0] & measured[1] & measured[2]
    for c, s in zip(curve, sigma):
        worst = max(np.percentile(s[both & (samples.region == r)] * 1e6, 95) for r in (0, 1))
        assert c["sigma_p95_common_um"] == pytest.approx(worst, rel=1e-12)
        assert c["common_fraction"] == pytest.approx(both.mean(), rel=1e-12)
        assert "_measured" not in c and "_sigma_max" not in c


PIT = """
[[mount]]
name = "pit"
kind = "fixed"
position_m = [0.0, 0.0, -1.0]
"""


def test_blind_candidates_get_their_console_line(plate_experiment, caplog):
    """A fixed mount under the plate sees only its underside, which holds no sample: its
    candidates are blind, dropped, and said in one console line for the mount with their count
    (as design.json's dropped_per_mount has it); the rail above, whose candidates all see the
    plate, gets no such line."""
    exp = _experiment(plate_experiment, n=2, cameras=PIT + DOWN_CAMERA.format(name="down", focal=24, u=0.5))
    with caplog.at_level("INFO", logger="vdo.design.select"):
        result = design_layout(exp)
    blind = [r.getMessage() for r in caplog.records if "blind" in r.getMessage()]
    count = result.record.candidates.dropped["pit"][BLIND]
    assert count > 0 and blind == [f"mount pit: {count} candidate(s) left out: {BLIND}"], blind


def test_a_smaller_count_sharper_in_every_scored_region_is_named():
    """`sharper_smaller_count`: of a curve 2, 3, 4 cameras with 4 written, the 3 has the lower
    σ p95 in both scored regions (the 2 too, but the largest such count is named), with its p95
    per region and coverage against the written one's; a count sharper in one region only, or a
    curve whose written count is the sharpest, says nothing."""
    from types import SimpleNamespace

    from vdo.design.measures import sharper_smaller_count

    exp = SimpleNamespace(optimize=SimpleNamespace(regions=None), design=SimpleNamespace(score="bound"),
                          regions=(SimpleNamespace(name="dome"), SimpleNamespace(name="ring")))
    row = lambda n, cov, dome, ring: {"cameras": n, "coverage": cov,
                                      "sigma_p95_by_region_um": {"dome": dome, "ring": ring}}
    curve = [row(2, 0.80, 0.70, 0.40), row(3, 0.990, 0.587, 0.488), row(4, 0.997, 0.861, 0.534)]
    line = sharper_smaller_count(exp, curve, curve[-1])
    assert line.startswith("3 cameras reach a lower sigma_max p95 than the 4 written to designed.toml "
                           "in every scored region (dome 0.587 against 0.861 um, ring 0.488 against "
                           "0.534 um) at coverage 99.0 % against 99.7 %"), line
    assert "[design] max_cameras = 3" in line
    one_region = [row(3, 0.99, 0.587, 0.60), row(4, 0.997, 0.861, 0.534)]
    assert sharper_smaller_count(exp, one_region, one_region[-1]) is None
    sharpest = [row(3, 0.99, 0.9, 0.6), row(4, 0.997, 0.861, 0.534)]
    assert sharper_smaller_count(exp, sharpest, sharpest[-1]) is None
    unmeasured = [row(3, 0.99, None, 0.4), row(4, 0.997, 0.861, 0.534)]   # a region lost is not sharper
    assert sharper_smaller_count(exp, unmeasured, unmeasured[-1]) is None


def test_the_design_names_a_sharper_smaller_count_and_still_writes_the_inventorys(plate_experiment, tmp_path,
                                                                                monkeypatch):
    """On the plate, counts 1 and 2 (one camera measures nothing): the design says nothing of a
    sharper smaller count. With the 1-camera count's σ p95 made lower than the 2's (the count's
    figures replaced after its judgement), the line is in `problems` and design.json, and the
    written layout is still the inventory's 2 cameras."""
    import json

    from vdo.design import select

    exp = _experiment(plate_experiment, extra="min_cameras = 1",
                      regions="\n[render]\nambient_radiance = 20\n")
    plain = design_run(exp, tmp_path / "plain")
    assert [c["cameras"] for c in plain.curve] == [1, 2] and plain.curve[0]["sigma_p95_by_region_um"]["top"] is None
    assert not [p for p in plain.problems if "written to designed.toml" in p]

    real = select._count

    def sharper_one(*args, **kwargs):
        c = real(*args, **kwargs)
        if c["cameras"] == 1:
            c["sigma_p95_by_region_um"] = {"top": 1e-3}
        return c

    monkeypatch.setattr(select, "_count", sharper_one)
    result = design_run(exp, tmp_path / "out")
    said = [p for p in result.problems if "written to designed.toml" in p]
    assert len(said) == 1 and said[0].startswith("1 cameras reach a lower sigma_max p95 than the 2"), result.problems
    assert said[0] in json.loads((tmp_path / "out" / "design.json").read_text())["problems"]
    assert result.cameras == 2 and len(json.loads((tmp_path / "out" / "layout.json").read_text())["cameras"]) == 2


@pytest.mark.parametrize("lo, hi, at_least", [(0.43, 0.86, 3), (0.05, 40.0, 4)])
def test_the_curves_log_axis_labels_enough_ticks(lo, hi, at_least):
    """`log_ticks` on a σ axis: a curve spanning less than a decade (0.43-0.86 µm, where
    matplotlib labelled two ticks) gets a label at every digit inside it; one spanning three
    decades at 1, 2 and 5 per decade; the labels are the tick values."""
    import matplotlib.pyplot as plt

    from vdo.commands.design import log_ticks

    fig, ax = plt.subplots()
    ax.semilogy([1, 2, 3], [lo, (lo * hi) ** 0.5, hi])
    log_ticks(ax)
    fig.canvas.draw()
    y0, y1 = ax.get_ylim()
    shown = [(t.get_loc(), t.label1.get_text()) for t in ax.yaxis.get_major_ticks()
             if y0 <= t.get_loc() <= y1 and t.label1.get_text()]
    plt.close(fig)
    assert len(shown) >= at_least, shown
    assert all(float(text) == pytest.approx(loc, rel=1e-2) for loc, text in shown)


def test_a_smaller_count_sharper_only_for_measuring_less_is_not_named():
    """The pressure vessel's case: 3 cameras have a lower σ p95 than the 7 written in every
    region over each one's own measured area (34 % against 87 % seen), but a higher one over the
    area every count measures (0.928 against 0.864 µm): not named. Lower there too: named."""
    from types import SimpleNamespace

    from vdo.design.measures import sharper_smaller_count

    exp = SimpleNamespace(design=SimpleNamespace(score="bound"), optimize=SimpleNamespace(regions=None),
                          regions=(SimpleNamespace(name="nozzle"), SimpleNamespace(name="shell")))
    written = dict(cameras=7, coverage=0.87, sigma_p95_common_um=0.864,
                   sigma_p95_by_region_um={"nozzle": 1.522, "shell": 1.492})
    three = dict(cameras=3, coverage=0.34, sigma_p95_common_um=0.928,
                 sigma_p95_by_region_um={"nozzle": 0.786, "shell": 0.951})
    assert sharper_smaller_count(exp, [written, three], written) is None
    three["sigma_p95_common_um"] = 0.80
    said = sharper_smaller_count(exp, [written, three], written)
    assert said.startswith("3 cameras reach a lower sigma_max p95 than the 7") and "nozzle 0.786 against 1.522" in said


def _curve_counts(common_um, common_fraction):
    """A camera-count curve of two counts as `vdo design` returns it, region "a" only, with each
    count's σ_max p95 over the area every count measures (`common_um`, None: none) and that
    area's share (`common_fraction`)."""
    return [{"cameras": k, "score": 1.0 / k, "bound": None, "sigma_p95_um": 2.0 / k,
             "sigma_p95_by_region_um": {"a": 2.0 / k}, "sigma_p95_measurable_um": 2.0 / k,
             "coverage": 0.5, "coverage_of_measurable": 0.8, "measurable_fraction": 0.6,
             "sigma_p95_common_um": u, "common_fraction": common_fraction}
            for k, u in zip((2, 3), common_um)]


def test_counts_that_share_no_measured_area_say_so_instead_of_a_0_percent_curve(tmp_path, monkeypatch,
                                                                              capsys):
    """Trial 4: every count's common_fraction 0, so no count has a σ_max p95 over the area every
    count measures; pareto.png's legend said "σ_max p95 over the 0 % every count measures" for
    a curve with no point, and the console nothing. Now the console prints one line saying why,
    the legend says the same with no curve drawn; counts that share an area keep their curve."""
    from types import SimpleNamespace

    import matplotlib.pyplot as plt

    from vdo.commands import cli
    from vdo.commands import design as command
    from vdo.commands.design import curve_figure, uncompared

    line = "the camera counts share no measured area: their sigma_max p95 over a common area is not compared"
    apart = _curve_counts((None, None), 0.0)
    assert uncompared(apart) == line
    fig = curve_figure(apart, None, "tee")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "the camera counts share no measured area: their σ_max p95 over a common area is not " \
           "compared" in labels
    assert not any("every count measures" in t for t in labels)
    assert not any("every count measures" in ln.get_label() for ln in fig.axes[0].get_lines())
    plt.close(fig)

    shared = _curve_counts((1.5, 1.2), 0.4)
    assert uncompared(shared) is None
    fig = curve_figure(shared, None, "tee")
    assert "σ_max p95 over the 40 % every count measures" in \
        [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    plt.close(fig)
    assert uncompared(_curve_counts((None, None), 0.25)) == (
        "the area every camera count measures (25.0 % of the regions) holds no sample of a scored "
        "region: their sigma_max p95 over a common area is not compared")

    result = SimpleNamespace(curve=apart, target_count=None, refined=None, wall_s=1.0)
    monkeypatch.setattr(command, "design", lambda *a, **k: result)
    exp = SimpleNamespace(optimize=SimpleNamespace(regions=None), regions=[SimpleNamespace(name="a")])
    cli._design(exp, SimpleNamespace(workers=1, dask=None, out=tmp_path / "o", overwrite=False,
                                     refine=False, memory_gb=None, time_limit=None, quiet=False))
    printed = capsys.readouterr().out.splitlines()
    assert printed[2] == line and sum(line == p for p in printed) == 1


def test_two_tripods_never_share_their_legs(plate_experiment):
    """The steel beam's design put two tripods over one floor point at 1.1 and 0.5 m (their feet
    shared), which its own judgement then failed ("tripod_clearance"). The selection's rule is
    that check's measure: for every two tripod candidates, a conflict exactly where the
    designed layout's `tripod_checks` would fail; two heights over one floor point always
    conflict (the same feet); tripods whose footprints (spread + leg radius) lie more than the
    clearance apart in plan never do."""
    from vdo.constraints import tripod_checks, tripod_table, tripods_of

    path = plate_experiment(spacing=50, extra_meshes=TRIPOD_ZONE)
    path.write_text(path.read_text() + DESIGN.format(n=2, extra="zone_points = 3\nzone_heights = 2"))
    exp = config.load(path)
    cand = judge(exp, prepare(exp))
    feas = Feasibility(exp, cand)
    on = np.flatnonzero(np.array(cand.mount) == "floor")
    assert len(on) >= 12
    clearance, reach = exp.optimize.clearance, 0.45 + 0.02
    seen = {"same point": 0, "far": 0, "measured": 0}
    for a in on:
        row = feas.tripods_touch(int(a))
        for b in on[on > a]:
            pa, pb = cand.cameras[a].position, cand.cameras[b].position
            pair = [cand.cameras[a], cand.cameras[b]]
            table = tripod_table(pair, [exp.mount("floor").tripod] * 2)
            check = tripod_checks(pair, table, [], clearance)[0]
            assert row[b] == (not check["met"]), (pa, pb, check)
            if np.allclose(pa[:2], pb[:2]):
                seen["same point"] += 1
                assert row[b] and feas.row(int(a))[b]            # the selection's own rule
            elif np.linalg.norm(pa[:2] - pb[:2]) > 2 * reach + clearance + 0.3:   # the top's offset
                seen["far"] += 1
                assert not row[b]
            seen["measured"] += 1
    assert min(seen.values()) > 0, seen
