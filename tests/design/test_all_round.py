"""`vdo design` around a cylinder: the closed-form answer of an all-round selection. Six cameras
chosen from two rings of twelve spots around a vertical cylinder (every 30 deg, a near ring at
0.8 m and a far one at 1.6 m from the axis) must stand 60 deg apart (equal spacing: the only
six-of-twelve set that gives every point of the wall two views within the 75 deg incidence limit,
where six neighbouring spots leave the back bare) and on the near ring (the same coverage, twice
the pixels per millimetre: a quarter of the sigma). The cylinder's bottom face, which no spot sees, keeps
samples at the prior's sigma (1 mm): the score must still tell the rings apart (a power mean
dominated by those samples did not)."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest
import trimesh

from vdo.config import experiment as config
from vdo.design.candidates import judge
from vdo.design.feasibility import Feasibility
from vdo.design.score import Scorer
from vdo.design.moves import exchange, greedy
from vdo.state import layout_state, prepare
from vdo.scene import cameras_of

RADIUS, HEIGHT = 0.1, 0.3
NEAR, FAR, SPOTS = 0.8, 1.6, 12
ANGLE_TOL_DEG = 1.0     # spot angles come from atan2 of float64 positions

CAMERA = """
[[camera]]
name = "{name}"
sensor_mm = [22.2, 14.8]
pixels = [1200, 800]
focal_mm = 25
position_m = [{x:.6f}, {y:.6f}, 0.0]
target_m = [0, 0, 0]
"""


def write_cylinder(tmp_path):
    """The cylinder (axis z, centred at the origin) with two regions, the wall and the bottom
    face, and the far ring's spots listed before the near ring's (a selection blind to
    precision takes the first of equal scores)."""
    trimesh.creation.cylinder(radius=RADIUS, height=HEIGHT, sections=128).export(tmp_path / "cyl.stl")
    cams = "".join(CAMERA.format(name=f"{ring}{k}", x=d * math.cos(math.radians(30 * k)),
                                 y=d * math.sin(math.radians(30 * k)))
                   for ring, d in (("far", FAR), ("near", NEAR)) for k in range(SPOTS))
    text = textwrap.dedent("""
        [experiment]
        name = "cylinder seen all round"
        [evaluation]
        sample_spacing_mm = 20
        incidence_limit_deg = 75
        [render]
        ambient_radiance = 20
        [[mesh]]
        name = "cyl"
        file = "cyl.stl"
        role = "specimen"
        [[region]]
        name = "wall"
        mesh = "cyl"
        near_axis_m = [[0, 0, 0], [0, 0, 1]]
        within_m = 0.11
        box_min_m = [-1, -1, -0.149]
        box_max_m = [1, 1, 0.149]
        [[region]]
        name = "bottom"
        mesh = "cyl"
        normal = [0, 0, -1]
        [design]
        max_cameras = 6
        sample_spacing_mm = 20
        bound_s = 0
        [optimize]
        min_axis_angle_deg = 20
        """) + cams
    path = tmp_path / "cyl.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def selection(tmp_path_factory):
    exp = config.load(write_cylinder(tmp_path_factory.mktemp("allround")))
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    scorer, feas = Scorer(exp, geometry.samples), Feasibility(exp, cand, geometry.samples)
    order, _ = greedy(cand, scorer, feas, 6)
    chosen, score, _ = exchange(cand, scorer, feas, order)
    return exp, geometry, cand, scorer, chosen, score


def _wall(exp, geometry, cams):
    """Of a layout on the wall: area fraction seen by two usable views and sigma_max p95 (um;
    unmeasured samples at infinity)."""
    pred = layout_state(geometry, cams).prediction
    smp = geometry.samples
    wall = smp.region == list(smp.region_names).index("wall")
    covered = smp.area[wall & (pred.coverage >= 2)].sum() / smp.area[wall].sum()
    sigma = np.where(pred.measured[wall], pred.sigma_max[wall] * 1e6, np.inf)
    return covered, np.percentile(sigma, 95, method="inverted_cdf")


def test_six_cameras_around_a_cylinder_stand_equally_spaced_on_the_near_ring(selection):
    exp, geometry, cand, scorer, chosen, score = selection
    pos = cand.positions[chosen]
    radius = np.hypot(pos[:, 0], pos[:, 1])
    np.testing.assert_allclose(radius, NEAR, rtol=1e-6)
    angle = np.sort(np.degrees(np.arctan2(pos[:, 1], pos[:, 0])) % 360)
    np.testing.assert_allclose(np.diff(np.r_[angle, angle[0] + 360]), 60, atol=ANGLE_TOL_DEG)


def test_equal_spacing_beats_a_cluster_and_the_far_ring_in_coverage_and_sigma(selection):
    exp, geometry, cand, scorer, chosen, score = selection
    by_name = {c.name: c for c in cameras_of(exp.camera_specs, exp.rails)}
    designed = [cand.cameras[i] for i in chosen]
    cluster = [by_name[f"near{k}"] for k in range(6)]                 # 0..150 deg: one side
    far = [by_name[f"far{k}"] for k in range(0, SPOTS, 2)]           # equally spaced, far
    cover, sigma = _wall(exp, geometry, designed)
    cover_cluster, sigma_cluster = _wall(exp, geometry, cluster)
    cover_far, sigma_far = _wall(exp, geometry, far)
    assert cover == pytest.approx(1.0) and cover_far == pytest.approx(1.0)
    assert cover_cluster < 0.75                 # the back (beyond 150 + 75 deg) seen once or never
    assert sigma < sigma_cluster                # inf: the cluster leaves samples unmeasured
    # twice the distance, the same lens: sigma ~ (mm per pixel) / sqrt(pixels in a patch) ~ d^2,
    # four times (incidence and perspective differ a little between the rings)
    assert sigma_far / sigma == pytest.approx(4, rel=0.2)


def test_neighbours_around_the_cylinder_share_it_and_keep_their_axis_angle(selection):
    """No candidate sees half the wall (assign_fraction 0.5), so none is assigned it; yet of the
    arc of half-width ~70 deg one near spot sees, its neighbour 30 deg away sees (140 - 30) / 140
    = 79 %: they share the wall, and with a 40 deg minimum axis angle they conflict; spots 90 deg
    apart (36 % in common) or opposite (nothing) do not."""
    from dataclasses import replace

    exp, geometry, cand, scorer, chosen, score = selection
    assert not cand.assigned[:, 0].any()
    strict = replace(exp, optimize=replace(exp.optimize, min_axis_angle=math.radians(40)))
    feas = Feasibility(strict, cand, geometry.samples)
    index = {c: i for i, c in enumerate(cand.cameras)}
    near = [index[c] for c in cand.cameras if np.hypot(*c.position[:2]) < (NEAR + FAR) / 2]
    near.sort(key=lambda i: np.degrees(np.arctan2(cand.positions[i, 1], cand.positions[i, 0])) % 360)
    assert feas.conflicts(near[1], near[0]) and feas.conflicts(near[11], near[0])
    assert not feas.conflicts(near[3], near[0]) and not feas.conflicts(near[6], near[0])
    assert not Feasibility(strict, cand).conflicts(near[1], near[0])    # assigned alone: no pair
