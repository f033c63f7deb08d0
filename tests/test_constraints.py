"""The constraint penalties against closed forms and finite differences, and the exact checks'
verdicts at and around their limits."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vdo import constraints
from vdo.model.camera import intrinsic_matrix, rotation


def test_clearance_penalty_is_the_sum_of_hinges_over_point_pairs():
    """One body point 3 cm from one mesh point and 6 cm from another, clearance 5 cm: only the
    first pair counts, ((5 - 3) / 5)^2; two cameras' body points 1 cm apart count once."""
    body = jnp.asarray([[[0.0, 0.0, 0.0]]])
    near = jnp.asarray([[[0.03, 0.0, 0.0], [0.0, -0.06, 0.0]]])
    assert float(constraints.clearance_penalty(body, near, 0.05)) == pytest.approx((2 / 5) ** 2, rel=1e-8)
    two = jnp.asarray([[[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.01]]])
    far = jnp.full((2, 1, 3), 1e3)
    assert float(constraints.clearance_penalty(two, far, 0.05)) == pytest.approx((4 / 5) ** 2, rel=1e-8)
    assert float(constraints.clearance_penalty(body, near * 2, 0.05)) == 0.0   # 6 and 12 cm: clear


def test_clearance_penalty_gradient_matches_finite_differences_where_the_nearest_point_switches():
    """A body point between two mesh points at equal distance: a nearest-point penalty has a
    kink there; the summed one is smooth and its gradient matches central differences."""
    near = jnp.asarray([[[0.02, 0.0, 0.0], [-0.02, 0.0, 0.0], [0.0, 0.03, 0.01]]])

    def f(x):
        return constraints.clearance_penalty(x.reshape(1, 1, 3), near, 0.05)

    x0 = jnp.asarray([0.0, 0.004, -0.002])
    g = np.asarray(jax.grad(f)(x0))
    h = 1e-6
    fd = np.array([(f(x0 + h * e) - f(x0 - h * e)) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)


def test_axis_angle_penalty_is_zero_at_the_limit_and_quadratic_below():
    limit = math.radians(20.0)
    for angle, expected in [(25.0, 0.0), (20.0, 0.0),
                            (10.0, ((math.cos(math.radians(10)) - math.cos(limit)) / (1 - math.cos(limit))) ** 2)]:
        a = math.radians(angle)
        axes = jnp.asarray([[0.0, 0.0, 1.0], [math.sin(a), 0.0, math.cos(a)]])
        value = float(constraints.axis_angle_penalty(axes, np.array([[0, 1]]), [limit]))
        assert value == pytest.approx(expected, abs=1e-15)


def _strip_in_front_of_a_camera(u_range, W=1000.0, H=800.0, f=1000.0, n=400):
    """A camera at the origin and a flat strip of points at 1 m depth whose pixel u runs over
    u_range (v = H/2): camera arrays (1 camera) and the strip (1 group)."""
    K = intrinsic_matrix(jnp.asarray([f]), jnp.asarray([(W - 1) / 2]), jnp.asarray([(H - 1) / 2]))
    R = rotation(jnp.asarray([0.3]), jnp.asarray([-0.2]), jnp.asarray([0.0]))
    u = np.linspace(*u_range, n)
    x_cam = np.c_[(u - (W - 1) / 2) / f, np.zeros(n), np.ones(n)]
    X = x_cam @ np.asarray(R[0])           # world points: R^T x_cam, camera at the origin
    cams = (K, R, jnp.zeros((1, 3)), jnp.asarray([W]), jnp.asarray([H]))
    return cams, jnp.asarray(X)[None], jnp.ones((1, n)), (u[1] - u[0])


def test_in_image_fraction_matches_the_exact_fraction_where_the_edge_crosses_a_region():
    """A strip from u = 100 to 1300 px in a 1000 px wide image: (999.5 - 100) / 1200 inside."""
    cams, pts, area, spacing = _strip_in_front_of_a_camera((100.0, 1300.0))
    frac = constraints.in_image_fraction(*cams, np.array([0]), pts, area, jnp.asarray([spacing]))
    assert float(frac[0]) == pytest.approx((999.5 - 100.0) / 1200.0, abs=2e-3)
    cams, pts, area, spacing = _strip_in_front_of_a_camera((100.0, 900.0))
    whole = constraints.in_image_fraction(*cams, np.array([0]), pts, area, jnp.asarray([spacing]))
    assert float(whole[0]) == pytest.approx(1.0, abs=1e-12)


def test_fov_penalty_is_the_squared_shortfall_in_percent():
    assert float(constraints.fov_penalty(jnp.asarray([0.995]), [0.98], 0.01)) == 0.0
    assert float(constraints.fov_penalty(jnp.asarray([0.95]), [0.98], 0.01)) == pytest.approx(16.0)


def test_in_image_fraction_gradient_matches_finite_differences():
    """d fraction / d camera translation, the strip half outside: central differences."""
    cams, pts, area, spacing = _strip_in_front_of_a_camera((100.0, 1300.0))
    K, R, t, W, H = cams

    def f(shift):
        return constraints.in_image_fraction(K, R, t + shift[None], W, H, np.array([0]), pts, area,
                                             jnp.asarray([3 * spacing]))[0]

    s0 = jnp.asarray([0.01, 0.0, 0.0])
    g = np.asarray(jax.grad(f)(s0))
    h = 1e-6
    fd = np.array([(f(s0 + h * e) - f(s0 - h * e)) / (2 * h) for e in np.eye(3)])
    assert abs(g[0]) > 0.1          # moving the camera sideways moves the strip across the edge
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("kind, value, limit, met, excess", [
    ("min", 21.1, 21.1, True, 0.0), ("min", 20.0, 25.0, False, 0.2), ("max", 0.06, 0.05, False, 0.2),
    ("max", 0.05, 0.05, True, 0.0), ("range", 1.2, [0.0, 1.0], False, 0.2), ("zero", 0.1, 0.0, False, 0.1),
    ("max", 0.002, 0.0, False, 2.0),   # a zero limit: the excess is relative to 1e-3, not to 0
])
def test_check_entries_report_met_and_relative_excess(kind, value, limit, met, excess):
    e = constraints._entry("c", value, limit, "unit", kind)
    assert e["met"] is met
    assert e["excess"] == pytest.approx(excess, rel=1e-4, abs=1e-12)


def _panel_above(height=2.0, size=0.3):
    """One sample at the origin lit by a square panel `height` above it, facing down."""
    row = np.array([0, 0, height, 0, 0, -1.0, 1.0, 0, 0, size / 2, size / 2])
    return jnp.zeros((1, 3)), jnp.asarray(row)[None]


@pytest.mark.parametrize("margin", [0.0, 0.01])
def test_shadow_penalty_starts_where_the_sphere_begins_to_hide_the_panel(margin):
    """A sphere (r = 5 cm) 1 m above the sample, offset d sideways: seen from the sample it
    hides part of the 0.3 m panel 2 m up until atan(d) - atan(0.075) = (r + margin) / sqrt(1 + d^2)."""
    from scipy.optimize import brentq

    sample, panel = _panel_above()
    r = 0.05
    d_star = brentq(lambda d: math.atan(d) - math.atan(0.075) - (r + margin) / math.hypot(1, d), 0.08, 1.0)

    def pen(d, z=1.0):
        return float(constraints.shadow_penalty(jnp.asarray([[[d, 0.0, z]]]), jnp.asarray([[r]]),
                                                sample, panel, margin))

    assert pen(0.0) == pytest.approx((1 + margin / r) ** 2, rel=1e-6)   # straight under: beta = 0
    assert pen(d_star - 2e-3) > 0 and pen(d_star + 2e-3) == 0.0
    assert pen(0.0, z=-0.5) == 0.0 and pen(0.0, z=2.5) == 0.0           # behind the sample or the panel


def test_shadow_penalty_gradient_matches_finite_differences():
    sample, panel = _panel_above()

    def f(c):
        return constraints.shadow_penalty(c.reshape(1, 1, 3), jnp.asarray([[0.05]]), sample, panel, 0.01)

    c0 = jnp.asarray([0.09, 0.02, 1.1])
    g = np.asarray(jax.grad(f)(c0))
    h = 1e-7
    fd = np.array([(f(c0 + h * e) - f(c0 - h * e)) / (2 * h) for e in np.eye(3)])
    assert float(f(c0)) > 0 and np.abs(g).max() > 1
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6)


def _moves(rng, n, length):
    """n random translations (3,) of norm at most `length`, half of them exactly `length`."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * np.where(np.arange(n) % 2 == 0, length, rng.uniform(0, length, n))[:, None]


# (name, clearance m, how far the bodies may move m, trials)
LOCAL_CASES = [("tight", 0.05, 0.1, 40), ("wide", 0.1, 0.3, 40)]


@pytest.mark.parametrize("name, clearance, move, trials", LOCAL_CASES)
def test_local_clearance_and_shadow_sets_give_the_full_penalties_for_moves_within_reach(
        name, clearance, move, trials):
    """The point set `points_near` keeps around a body, and the (camera, sample) pairs
    `shadow_pairs` keeps around its spheres, give the same penalties as every point and every
    pair for any move of the bodies up to `move`, on a floor of points and samples lit by a panel
    above, with bodies placed across the light's rays; the sets are much smaller than the full
    ones, and the moves do make both penalties nonzero (else the equality would prove nothing)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(1)
    g = np.linspace(-1, 1, 41)
    floor = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)   # 5 cm apart
    sample_pts, panel_row = _panel_above(height=2.0, size=0.4)
    samples = floor[::3]
    panels = np.tile(np.asarray(panel_row[0]), (len(samples), 1))
    local = np.array([[0.0, 0.0, 0.0], [0.04, 0.03, 0.05], [-0.04, -0.03, 0.1]])
    anchors = np.array([[0.1, 0.0, 0.12], [0.3, -0.2, 0.9], [-0.5, 0.4, 1.3]])   # near the floor, in the light
    radii = np.full((3, 3), 0.04)
    body0 = anchors[:, None, :] + local
    tree = cKDTree(floor)
    kept = [constraints.points_near(floor, b, clearance + move, tree) for b in body0]
    # the other way to the same sets: a tree of the anchors
    assert all(np.array_equal(k, constraints.points_near(floor, b, clearance + move))
               for k, b in zip(kept, body0))
    pairs = constraints.shadow_pairs(body0, radii, samples, panels, 0.005, move)
    assert max(len(k) for k in kept) < len(floor) / 4 and len(pairs) < 3 * len(samples) / 2
    near_kept = jnp.asarray(constraints.padded_points(kept))
    near_all = jnp.asarray(np.broadcast_to(floor, (3, *floor.shape)))
    nonzero = [0, 0]
    for d in _moves(rng, trials, move):
        body = jnp.asarray(body0 + d)
        full = float(constraints.clearance_penalty(body, near_all, clearance))
        assert float(constraints.clearance_penalty(body, near_kept, clearance)) == pytest.approx(full, rel=1e-12, abs=1e-15)
        full_shadow = float(constraints.shadow_penalty(body, jnp.asarray(radii), jnp.asarray(samples),
                                                       jnp.asarray(panels), 0.005))
        cheap = float(constraints.shadow_penalty(body, jnp.asarray(radii), jnp.asarray(samples), jnp.asarray(panels),
                                                 0.005, jnp.asarray(pairs), jnp.ones(len(pairs))))
        assert cheap == pytest.approx(full_shadow, rel=1e-12, abs=1e-15)
        nonzero[0] += full > 0
        nonzero[1] += full_shadow > 0
    assert min(nonzero) > 0


def test_in_image_fraction_of_a_distorted_camera_counts_what_opencv_projects_inside():
    """A barrel-distorted camera before a plane wider than its view: with a ramp of 1e-3 px the
    smooth fraction is the fraction of points that cv2.projectPoints puts on the sensor."""
    cv2 = pytest.importorskip("cv2")
    W, H, f = 1000, 800, 900.0
    dist = np.array([-0.25, 0.06, 0.002, -0.001, 0.0])           # k1, k2, p1, p2, k3
    K = np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    x, y = np.meshgrid(np.linspace(-0.8, 0.8, 61), np.linspace(-0.6, 0.6, 47))
    X = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 1.0)])
    uv = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    exact = np.mean((uv[:, 0] >= -0.5) & (uv[:, 0] <= W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= H - 0.5))
    assert 0.3 < exact < 0.95                                      # the edges cross the plane
    frac = constraints.in_image_fraction(
        jnp.asarray(K)[None], jnp.eye(3)[None], jnp.zeros((1, 3)), jnp.asarray([W]), jnp.asarray([H]),
        np.array([0]), jnp.asarray(X)[None], jnp.ones((1, len(X))), jnp.asarray([1e-3]), jnp.asarray(dist)[None])
    assert float(frac[0]) == pytest.approx(exact, abs=0.5 / len(X))


ROUND_CAMERA = """
[[camera]]
name = "c{deg}"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 16
position_m = [{x:.6f}, {y:.6f}, 0.0]
target_m = [0, 0, 0]
"""


def test_cameras_around_a_cylinder_share_it_with_their_neighbours_only(tmp_path):
    """Three cameras 1 m from the axis of a cylinder (r = 0.1 m) at 0, 60 and 180 deg, incidence
    limit 75 deg: each sees an arc of half-width alpha (closed form below, ~70 deg), 39 % of the
    wall, so none is assigned it (assign_fraction 0.5) and the optimizer formed no pair. Of the
    arc one sees, its neighbour at 60 deg sees (2 alpha - 60) / (2 alpha) ~ 57 %: they share the
    wall (one pair, its axis angle checked); at 120 and 180 deg apart, 14 % and nothing: no pair."""
    import textwrap

    import trimesh

    from vdo.config import experiment as config
    from vdo.state import layout_state, prepare

    radius, distance, limit = 0.1, 1.0, math.radians(75)
    trimesh.creation.cylinder(radius=radius, height=0.3, sections=128).export(tmp_path / "cyl.stl")
    cams = "".join(ROUND_CAMERA.format(deg=d, x=distance * math.cos(math.radians(d)),
                                       y=distance * math.sin(math.radians(d))) for d in (0, 60, 180))
    (tmp_path / "cyl.toml").write_text(textwrap.dedent("""
        [experiment]
        name = "three around a cylinder"
        [evaluation]
        sample_spacing_mm = 10
        incidence_limit_deg = 75
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
        """) + cams)
    exp = config.load(tmp_path / "cyl.toml")
    state = layout_state(prepare(exp))
    smp, vis = state.samples, state.visibility
    # alpha: the wall point at angle psi from a camera is seen at incidence
    # acos((D cos psi - r) / |D - r n|), n = (cos psi, sin psi); 75 deg at psi = alpha
    psi = np.linspace(0, math.pi / 2, 200001)
    incidence = np.arccos((distance * np.cos(psi) - radius)
                          / np.hypot(distance - radius * np.cos(psi), radius * np.sin(psi)))
    alpha = math.degrees(psi[np.searchsorted(incidence, limit)])
    assert not constraints.assignments(vis, smp, exp.optimize.assign_fraction).any()
    shared = constraints.sharing(vis, smp, exp.optimize.assign_fraction)
    assert shared[0, 1, 0] and shared[1, 0, 0]
    assert not shared[0, 2, 0] and not shared[1, 2, 0]
    seen = np.asarray(vis.visible, dtype=float) * smp.area
    fraction = (seen[0] @ np.asarray(vis.visible[1], dtype=float)) / seen[0].sum()
    assert fraction == pytest.approx((2 * alpha - 60) / (2 * alpha), abs=0.05)
    pairs, low, _ = constraints.angle_limits(exp.regions, exp.optimize, exp.stereo_pairs, list(state.cameras),
                                             constraints.assignments(vis, smp, 0.5), shared)
    np.testing.assert_array_equal(pairs, [[0, 1]])
    assert low[0] == pytest.approx(constraints.stereo_min_angle(0.016))
