"""One measure of a camera body's clearance (vdo.search.obstruction): `vdo design`'s candidate
filter (`keep_clear`) and the layout's clearance check (`clearances`) agree on every pose, and
the measure is checked against the closed-form distance from the body's mesh to a wall.

Scene: a 2 m x 2 m wall (a 10 mm thick box, its face at x = 0) and cameras in front of it at
20-120 mm, aimed along the wall, at it at an angle, and straight away from it. The distance from
a polyhedral body to a plane is attained at a vertex: min over the body's vertices of x (0 for a
body reaching through the wall)."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from vdo.model.camera import Camera
from vdo.model.pose import look_at_angles
from vdo.scene import SceneMesh, camera_body, camera_body_local
from vdo.search.obstruction import CLEARANCE_SPACING, body_points, clearances, keep_clear, surface_points

CLEARANCE = 0.05          # m, the limit both read
# The body's 400 points on its 0.085-0.10 m^2 are ~15 mm apart: no corner farther than
# CORNER_REACH from one (12-14 mm measured). The sampled clearance never reads below the exact
# distance and exceeds it by at most SAMPLED_EXCESS here (3.7 mm measured).
CORNER_REACH = 0.02       # m
SAMPLED_EXCESS = 0.01     # m


def _wall() -> SceneMesh:
    box = trimesh.creation.box(extents=(0.01, 2.0, 2.0))
    box.apply_translation((-0.005, 0.0, 0.0))
    return SceneMesh("wall", "machine", np.array(box.vertices), np.array(box.faces))


def _cameras() -> list[Camera]:
    cams = []
    for k, x in enumerate(np.linspace(0.02, 0.12, 11)):
        for aim in ((x, 1.0, 0.1), (-1.0, 0.3, 0.2), (x + 1.0, -0.2, 0.0)):
            pan, tilt = look_at_angles(np.array([x, 0.0, 0.0]), np.array(aim))
            cams.append(Camera(f"c{len(cams)}", 1200, 800, 5e-6, (0.012, 0.035)[k % 2],
                               np.array([x, 0.0, 0.0]), pan, tilt))
    return cams


def test_the_candidate_filter_and_the_layout_check_read_one_measure_of_clearance():
    wall = _wall()
    tree = cKDTree(surface_points([wall], spacing=CLEARANCE_SPACING))
    cams = _cameras()
    measured = np.array([clearances([c], tree)[0] for c in cams])
    kept = keep_clear(cams, tree, CLEARANCE)
    assert np.array_equal(kept, measured >= CLEARANCE)
    assert 0 < kept.sum() < len(cams)          # the limit falls among the poses
    # the wall's face at x = 0; a body reaching past it crosses the wall (it also holds the optical
    # centre, at x > 0): distance 0
    exact = np.array([max(camera_body(c).vertices[:, 0].min(), 0.0) for c in cams])
    assert np.all(measured >= exact - 1e-9)
    assert np.all(measured - exact <= SAMPLED_EXCESS), (measured - exact).max()


def test_body_points_lie_on_the_body_and_spread_over_it():
    for f in (0.008, 0.035, 0.1):
        pts = body_points(f)
        body = camera_body_local(f)
        assert len(pts) > 200
        lo, hi = body.bounds
        assert np.all((pts >= lo - 1e-12) & (pts <= hi + 1e-12))
        # every corner of the body has a point near it
        assert cKDTree(pts).query(np.asarray(body.vertices))[0].max() < CORNER_REACH


def test_a_body_inside_the_wall_is_not_clear():
    pan, tilt = look_at_angles(np.array([-0.01, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    cam = Camera("in", 1200, 800, 5e-6, 0.012, np.array([-0.01, 0.0, 0.0]), pan, tilt)
    tree = cKDTree(surface_points([_wall()], spacing=CLEARANCE_SPACING))
    assert not keep_clear([cam], tree, CLEARANCE)[0]
