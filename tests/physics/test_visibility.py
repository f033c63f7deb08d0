"""Visibility against closed-form answers: a camera's frustum on a plane, the incidence-angle
circle, the shadow of a bar, and camera bodies as obstacles."""

import numpy as np
import pytest

from conftest import DOWN_CAMERA, raycast
from vdo.physics import visibility
from vdo.scene import cameras_of

H = 1.5          # camera height above the plate (m)
CELL = 0.01      # sample spacing (m)


def run(path):
    exp, samples, _, _, vis = raycast(path)
    return exp, samples, vis


def assert_matches_away_from_edges(got, expected, distance_to_edge):
    """`got` equals the analytic `expected` for every sample more than one cell from an edge."""
    clear = distance_to_edge > CELL
    assert clear.sum() > 0.8 * len(got)
    mismatches = np.flatnonzero(clear & (got != expected))
    assert mismatches.size == 0, f"{mismatches.size} samples differ from the closed form"


def test_frustum_on_a_plane(plate_experiment):
    """Looking straight down with pan = 0, the image's rows run along world x: the footprint is
    |x| <= H (sensor height / 2) / f (all of the plate along y)."""
    exp, samples, vis = run(plate_experiment(height=H))
    half_x = H * (14.8 / 2) / 24
    x = samples.points[:, 0]
    assert_matches_away_from_edges(vis.in_image[0], np.abs(x) <= half_x, np.abs(np.abs(x) - half_x))
    np.testing.assert_array_equal(vis.visible[0], vis.in_image[0])      # nothing else in the way
    assert vis.visible[0].mean() == pytest.approx(2 * half_x, abs=CELL)  # plate is 1 m wide


def test_incidence_limit_is_a_circle(plate_experiment):
    """From height H, the incidence angle at radius r is atan(r / H): visible iff r < H tan(limit)."""
    cams = DOWN_CAMERA.format(name="wide", focal=8, u=0.5)
    exp, samples, vis = run(plate_experiment(height=H, limit=25, cameras=cams))
    r = np.hypot(samples.points[:, 0], samples.points[:, 1])
    r_max = H * np.tan(np.radians(25))
    assert vis.in_image[0].all()
    assert_matches_away_from_edges(vis.visible[0], r < r_max, np.abs(r - r_max))
    np.testing.assert_allclose(visibility.incidence_angles(cameras_of(exp.camera_specs, exp.rails)[0], samples), np.arctan2(r, H),
                               atol=1e-12)


def test_shadow_of_a_bar(plate_experiment):
    """A 50 mm square bar along y at x = 0.2, z = 0.5 hides the strip between the projections of
    its section's corners from the optical centre: x' = x H / (H - z)."""
    extra = '[[mesh]]\nname = "bar"\nfile = "bar.stl"\nunit = "mm"\nrole = "obstacle"\n'
    cams = DOWN_CAMERA.format(name="wide", focal=8, u=0.5)
    path = plate_experiment(height=H, cameras=cams, extra_meshes=extra,
                            files=[("bar.stl", [50, 2000, 50], [200, 0, 500])])
    exp, samples, vis = run(path)
    corners = [(x, z) for x in (0.175, 0.225) for z in (0.475, 0.525)]
    shadow = [x * H / (H - z) for x, z in corners]
    lo, hi = min(shadow), max(shadow)
    x = samples.points[:, 0]
    hidden = (x > lo) & (x < hi)
    assert_matches_away_from_edges(~vis.unoccluded[0], hidden,
                                   np.minimum(np.abs(x - lo), np.abs(x - hi)))
    assert vis.facing[0].all() and vis.in_image[0].all()


def test_other_camera_bodies_occlude_and_own_body_does_not(plate_experiment):
    """Camera `high` looks down past camera `low` (1 m lower, same axis): `low`'s body hides the
    plate around the axis from `high`; neither camera is hidden by its own body."""
    extra_rail = '[[rail]]\nname = "lower"\ncontrol_points_m = [[-1.0, 0.0, 0.5], [1.0, 0.0, 0.5]]\n'
    cams = (DOWN_CAMERA.format(name="high", focal=8, u=0.5)
            + DOWN_CAMERA.format(name="low", focal=8, u=0.5).replace('"overhead"', '"lower"'))
    exp, samples, vis = run(plate_experiment(height=H, cameras=extra_rail + cams))
    r = np.hypot(samples.points[:, 0], samples.points[:, 1])
    high, low = vis.visible
    assert not high[r < 0.03].any()               # body of `low` is in the way
    assert high[r > 0.3].all()                    # the body shadow is small (about 0.13 m)
    near = r < 0.3
    assert low[near & vis.in_image[1]].all()      # own body never hides
