"""The light model against closed forms: irradiance under a square panel (the configuration factor
of a rectangle, a textbook result), the inverse-square law far away, shadows, and the photometry
formulas against the sensor model."""

import math

import numpy as np
import pytest

from vdo import scene
from vdo.physics import lighting
from vdo.config.rig import LightSpec, SpeckleSpec
from vdo.scene import SceneMesh, SurfaceSamples
from vdo.model.sensor import SensorModel


def samples_at(points, normal=(0, 0, 1)):
    points = np.atleast_2d(np.asarray(points, float))
    n = len(points)
    nrm = np.tile(np.asarray(normal, float), (n, 1))
    return SurfaceSamples(points=points, normals=nrm, tangent_u=np.tile([1.0, 0, 0], (n, 1)),
                          tangent_v=np.tile([0, 1.0, 0], (n, 1)), uv=points[:, :2],
                          area=np.full(n, 1e-4), region=np.zeros(n, int), region_names=("r",),
                          region_importance=np.ones(1))


def box_mesh(name, lo, hi):
    import trimesh

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2)
    return SceneMesh(name, "obstacle", np.asarray(m.vertices), np.asarray(m.faces))


def far_away_scene():
    return scene.build_scene([box_mesh("far", [50, 50, 50], [51, 51, 51])])


def corner_factor(a, b, c):
    """View factor from a differential area to a parallel a x b rectangle at distance c with one
    corner on the area's normal (Howell, catalogue of radiation configuration factors, B-3)."""
    A, B = a / c, b / c
    return (A / math.sqrt(1 + A * A) * math.atan(B / math.sqrt(1 + A * A))
            + B / math.sqrt(1 + B * B) * math.atan(A / math.sqrt(1 + B * B))) / (2 * math.pi)


def test_irradiance_under_a_square_panel_matches_the_view_factor():
    half, height, L = 0.15, 0.4, 10.0
    light = LightSpec("p", np.array([0, 0, height]), np.array([0, 0, 0.0]), (2 * half, 2 * half), L)
    il = lighting.illuminate(far_away_scene(), [light], samples_at([[0, 0, 0]]), grid=16)
    expected = math.pi * L * 4 * corner_factor(half, half, height)      # E = π L F
    assert il.direct[0, 0] == pytest.approx(expected, rel=2e-3)
    assert il.lit[0, 0] == 1.0


def test_far_panel_follows_the_inverse_square_law_with_both_cosines():
    """A small panel far away is a point source: E = L A cos θ_s cos θ_l / r²."""
    L, size = 3.0, (0.05, 0.02)
    pos = np.array([2.0, 1.0, 3.0])
    target = np.array([0.5, 0.0, 0.0])                        # not aimed at the sample
    light = LightSpec("p", pos, target, size, L)
    X = np.array([0.0, 0.0, 0.0])
    il = lighting.illuminate(far_away_scene(), [light], samples_at([X]), ambient_radiance=0.2)
    d = pos - X
    r = np.linalg.norm(d)
    n_l = (target - pos) / np.linalg.norm(target - pos)
    expected = L * size[0] * size[1] * (d[2] / r) * (-(n_l @ d) / r) / r**2
    assert il.direct[0, 0] == pytest.approx(expected, rel=1e-3)
    assert il.irradiance[0] == pytest.approx(expected + math.pi * 0.2, rel=1e-3)


def test_back_side_and_occluded_panels_give_no_light():
    light = LightSpec("p", np.array([0, 0, 1.0]), np.array([0, 0, 0.0]), (0.2, 0.2), 1.0)
    behind = LightSpec("q", np.array([0, 0, 1.0]), np.array([0, 0, 2.0]), (0.2, 0.2), 1.0)  # faces away
    pts = [[0, 0, 0], [2.0, 0, 0]]
    blocker = scene.build_scene([box_mesh("slab", [-0.5, -0.5, 0.4], [0.5, 0.5, 0.45])])
    il = lighting.illuminate(blocker, [light, behind], samples_at(pts))
    assert il.lit[0, 0] == 0 and il.direct[0, 0] == 0          # under the slab
    assert il.lit[0, 1] > 0.99 and il.direct[0, 1] > 0          # beside it
    assert np.all(il.lit[1] == 0) and np.all(il.direct[1] == 0)
    np.testing.assert_array_equal(il.lights_reaching, [0, 1])


def test_photometry_formulas_follow_the_sensor_model():
    sensor = SensorModel()
    sp = SpeckleSpec(white_albedo=0.8, black_albedo=0.1)
    E = np.array([0.0, 1.0, 2.5])
    il = lighting.Illumination(("a",), lit=np.ones((1, 3)), direct=E[None], ambient=0.0)
    pho = lighting.photometry(il, sp, sensor, pattern_mean=0.6, pattern_std=0.45, n_cameras=2)
    mean_rho = 0.1 + 0.7 * 0.6
    assert pho.contrast.shape == pho.noise.shape == pho.brightness.shape == (2, 3)
    lin = mean_rho * E / np.pi
    np.testing.assert_allclose(pho.brightness[1], sensor.mean_dn(lin))
    np.testing.assert_allclose(pho.noise[0], np.sqrt(sensor.variance_dn(sensor.mean_dn(lin))))
    # contrast = DN per unit linear x (ρ_w - ρ_b) std(f) E / π; a white-minus-black step halves it
    dn_per_unit = sensor.mean_dn(1.0) - sensor.mean_dn(0.0)
    np.testing.assert_allclose(pho.contrast[0], dn_per_unit * 0.7 * 0.45 * E / np.pi)
    assert pho.noise[0, 0] > 0 and pho.contrast[0, 0] == 0


@pytest.mark.parametrize("case, blocker_lo, blocker_hi, shaded_min", [
    # a small box between the panel and part of the samples: those samples lose light
    ("half shaded", [-0.3, -0.3, 0.18], [0.0, 0.3, 0.22], 10),
    # a box beside the light paths: nothing changes, and nothing needs casting again
    ("clear", [2.0, 2.0, 0.1], [2.2, 2.2, 0.3], 0),
    # a box below the samples' plane: no sky ray can meet it, nothing is cast again
    ("below", [-0.3, -0.3, -0.5], [0.3, 0.3, -0.4], 0),
])
def test_relight_equals_a_full_cast_with_the_added_occluder(case, blocker_lo, blocker_hi, shaded_min):
    """`relight` (cast again only the samples an added occluder may shade) against `illuminate` of
    the whole scene with it: the same lit fractions, irradiance and sky fractions, for samples
    shaded and not."""
    light = LightSpec("p", np.array([0, 0, 0.5]), np.array([0, 0, 0.0]), (0.3, 0.3), 5.0)
    xs = np.linspace(-0.4, 0.4, 21)
    grid = samples_at(np.array([[x, y, 0.0] for x in xs for y in xs]))
    base = [box_mesh("far", [50, 50, 50], [51, 51, 51])]
    blocker = box_mesh("blocker", blocker_lo, blocker_hi)
    unobstructed = lighting.illuminate(scene.build_scene(base), [light], grid, ambient_radiance=1.0)
    full = lighting.illuminate(scene.build_scene(base + [blocker]), [light], grid, ambient_radiance=1.0)
    fast = lighting.relight(scene.build_scene(base + [blocker]), [light], grid, unobstructed,
                            [blocker.vertices])
    np.testing.assert_array_equal(fast.lit, full.lit)
    np.testing.assert_allclose(fast.direct, full.direct, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(fast.sky, full.sky)     # the sky hidden by the occluder too
    assert int((full.lit < unobstructed.lit).sum()) >= shaded_min, case



SKY_MEAN_RTOL = 0.01   # mean of 64 points' sky fractions against the closed form
SKY_POINT_RTOL = 0.06  # one point: its 12 x 12 grid's error at the wall's top edge


@pytest.mark.parametrize("d_over_h", [0.2, 1.0, 3.0])
def test_sky_beside_a_long_wall_follows_the_two_dimensional_view_factor(d_over_h):
    """Floor points at distance d from a long wall of height h see the wall over the
    cosine-weighted fraction F = (1 - d / sqrt(d^2 + h^2)) / 2 (an infinitely long strip's view
    factor, (sin φ_2 - sin φ_1) / 2 with φ from the normal: the wall's foot at 90°, its top at
    atan(d / h)), so the sky fraction is S = 1 - F and the ambient irradiance π L_amb S; a point
    on the far side of a vertical face (normal away from the wall) keeps S = 1."""
    h = 1.0
    d = d_over_h * h
    wall = box_mesh("wall", [d, -200.0, -0.1], [d + 0.05, 200.0, h])
    sc = scene.build_scene([wall])
    points = np.column_stack([np.zeros(64), np.linspace(-0.5, 0.5, 64), np.zeros(64)])
    il = lighting.illuminate(sc, [], samples_at(points), ambient_radiance=2.0)
    expected = 1.0 - (1.0 - d / math.hypot(d, h)) / 2
    assert il.sky.mean() == pytest.approx(expected, rel=SKY_MEAN_RTOL)
    np.testing.assert_allclose(il.sky, expected, rtol=SKY_POINT_RTOL)
    np.testing.assert_allclose(il.irradiance, 2.0 * math.pi * il.sky, rtol=1e-12)
    away = lighting.illuminate(sc, [], samples_at([[d - 0.01, 0.0, 0.5]], normal=(-1, 0, 0)), 2.0)
    assert away.sky[0] == 1.0
