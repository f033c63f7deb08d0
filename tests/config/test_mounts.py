"""Mounts beyond rails: a zone (a box a tripod can stand in) and a fixed mount. The zone map keeps
the camera inside its box for every parameter value, its derivative matches finite differences,
a rail mount behaves as a [[rail]], and bad mount input is one ConfigError line."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import PLATE_TOML, write_box
from vdo.config import experiment as config
from vdo.outputs import report
from vdo.core.errors import ConfigError
from vdo.search.parameterisation import Parameterization
from vdo.scene import cameras_of

MOUNTS = """
[[mount]]
name = "tripod"
kind = "zone"
box_min_m = [0.3, -0.4, 0.9]
box_max_m = [0.9, 0.4, 1.3]

[[mount]]
name = "wall"
kind = "fixed"
position_m = [-0.8, 0.0, 1.0]

[[mount]]
name = "beam"
kind = "rail"
control_points_m = [[-0.5, -0.8, 1.5], [0.5, -0.8, 1.5]]
"""
CAMERAS = """
[[camera]]
name = "t"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
mount = "tripod"
position_m = [0.6, 0.1, 1.0]
target_m = [0.0, 0.0, 0.0]

[[camera]]
name = "w"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
mount = "wall"
target_m = [0.0, 0.0, 0.0]

[[camera]]
name = "b"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
mount = "beam"
u = 0.5
target_m = [0.0, 0.0, 0.0]
"""


def write(tmp_path, mounts=MOUNTS, cameras=CAMERAS, extra=""):
    write_box(tmp_path / "plate.stl", [600, 600, 10], center=[0, 0, -5])
    text = PLATE_TOML.format(spacing=20, limit=75, height=1.2, extra_meshes=mounts,
                             cameras=cameras + extra)
    (tmp_path / "exp.toml").write_text(text)
    return tmp_path / "exp.toml"


def test_zone_fixed_and_rail_mounts_load_and_reload(tmp_path):
    exp = config.load(write(tmp_path))
    t, w, b = cameras_of(exp.camera_specs, exp.rails)
    np.testing.assert_allclose(t.position, [0.6, 0.1, 1.0])
    np.testing.assert_allclose(w.position, [-0.8, 0.0, 1.0])
    np.testing.assert_allclose(b.position, [0.0, -0.8, 1.5])   # middle of the rail mount
    assert exp.camera_specs[2].rail == "beam" and exp.camera_specs[0].mount == "tripod"
    report.write_config(tmp_path / "again.toml", exp)
    again = config.load(tmp_path / "again.toml")
    for c0, c1 in zip(cameras_of(exp.camera_specs, exp.rails), cameras_of(again.camera_specs, again.rails)):
        np.testing.assert_allclose(c1.position, c0.position, atol=1e-12)
        np.testing.assert_allclose(c1.R, c0.R, atol=1e-12)
    assert [m.name for m in again.mounts] == ["tripod", "wall"]


def _param(tmp_path):
    exp = config.load(write(tmp_path))
    return exp, Parameterization(exp, cameras_of(exp.camera_specs, exp.rails), np.zeros(3))


def test_zone_map_stays_inside_the_zone_for_any_parameters(tmp_path):
    exp, param = _param(tmp_path)
    idx = param.index[0]
    assert set(idx) >= {"x", "y", "z"} and not any(k in param.index[1] for k in Parameterization.MOVES)
    # θ0 puts the camera where the file does
    np.testing.assert_allclose(param.cameras_at(param.theta0)[0].position, [0.6, 0.1, 1.0], atol=1e-12)
    zone = exp.mount("tripod")
    rng = np.random.default_rng(0)
    for spread in (1.0, 10.0, 60.0):
        for _ in range(20):
            theta = param.theta0 + spread * rng.standard_normal(param.theta0.size)
            cams = param.cameras_at(theta)
            assert np.all(cams[0].position >= zone.box_min) and np.all(cams[0].position <= zone.box_max)
            np.testing.assert_allclose(cams[1].position, [-0.8, 0.0, 1.0], atol=1e-12)   # fixed


def test_zone_position_derivative_matches_finite_differences(tmp_path):
    _, param = _param(tmp_path)
    held = param.held
    theta0 = jnp.asarray(param.theta0 + 0.3)
    f = lambda th: jnp.concatenate([jnp.ravel(a) for a in param.poses(th, held)])
    jac = np.asarray(jax.jacfwd(f)(theta0))
    h = 1e-6
    fd = np.stack([(np.asarray(f(theta0.at[k].add(h))) - np.asarray(f(theta0.at[k].add(-h)))) / (2 * h)
                   for k in range(theta0.size)], axis=1)
    np.testing.assert_allclose(jac, fd, atol=1e-7, rtol=1e-6)
    # d p_x / d θ_x = (hi - lo) s (1 - s), independent of our code's form
    k = param.index[0]["x"]
    s = 1 / (1 + np.exp(-float(theta0[k])))
    assert jac[0, k] == pytest.approx(0.6 * s * (1 - s), rel=1e-9)


@pytest.mark.parametrize("mounts, cameras, field, words", [
    (MOUNTS.replace('box_max_m = [0.9, 0.4, 1.3]\n', ''), CAMERAS, 'mount "tripod".box_max_m',
     "is required for a zone mount"),
    (MOUNTS.replace("[0.9, 0.4, 1.3]", "[0.9, -0.4, 1.3]"), CAMERAS, 'mount "tripod".box_max_m',
     "no floor area"),
    (MOUNTS.replace('kind = "fixed"\nposition_m = [-0.8, 0.0, 1.0]', 'kind = "fixed"'), CAMERAS,
     'mount "wall".position_m', "is required for a fixed mount"),
    (MOUNTS.replace('kind = "zone"', 'kind = "crane"'), CAMERAS, 'mount "tripod".kind', "must be one of"),
    (MOUNTS, CAMERAS.replace('mount = "wall"', 'mount = "shelf"'), 'camera "w".mount',
     "no [[mount]] or [[rail]] named 'shelf'"),
    (MOUNTS, CAMERAS.replace("[0.6, 0.1, 1.0]", "[0.6, 0.1, 2.0]"), 'camera "t".position_m',
     "outside zone"),
])
def test_bad_mount_input_is_one_config_error_line(tmp_path, mounts, cameras, field, words):
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, mounts, cameras))
    text = str(err.value)
    assert "\n" not in text and err.value.field == field and words in text, text


R_RING = 1.5          # m, the ring's radius
RING = """
[[mount]]
name = "ring"
kind = "rail"
degree = 2
control_points_m = [[0, -1.5, 1.2], [1.5, -1.5, 1.2], [1.5, 0, 1.2], [1.5, 1.5, 1.2], [0, 1.5, 1.2],
                    [-1.5, 1.5, 1.2], [-1.5, 0, 1.2], [-1.5, -1.5, 1.2], [0, -1.5, 1.2]]
weights = [1, 0.7071067811865476, 1, 0.7071067811865476, 1, 0.7071067811865476, 1, 0.7071067811865476, 1]
knots = [0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 4]
"""
RING_CAMERA = CAMERAS.replace('mount = "beam"', 'mount = "ring"')


def test_a_cad_circle_with_its_knots_is_a_circle(tmp_path):
    """Trial 4: the CAD form of a circle (9 control points on a square, degree 2, corner weights
    1/sqrt(2), double interior knots) read with uniform knots gave radii of 1.50-1.78 m. With its
    `knots` every point lies at R_RING from the centre, in NumPy (the config's point) and in JAX
    (the optimizer's Rail); u = 0 and u = 1 are the same point, u = 1/4 a quarter turn on."""
    exp = config.load(write(tmp_path, MOUNTS + RING, RING_CAMERA))
    ring = next(r for r in exp.rails if r.name == "ring")
    u = np.linspace(0, 1, 1001)
    pts = ring.point(u)
    np.testing.assert_allclose(np.linalg.norm(pts[:, :2], axis=1), R_RING, rtol=1e-12)
    np.testing.assert_allclose(pts[:, 2], 1.2, atol=1e-12)
    np.testing.assert_allclose(ring.point(np.array([0.0, 0.25, 1.0])), [[0, -1.5, 1.2], [1.5, 0, 1.2], [0, -1.5, 1.2]],
                               atol=1e-12)
    param = Parameterization(exp, cameras_of(exp.camera_specs, exp.rails), np.zeros(3))
    jax_pts = np.asarray(param.rails[2].position(jnp.asarray(u)))
    np.testing.assert_allclose(jax_pts, pts, atol=1e-12)
    uniform = dataclasses.replace(ring, knots=None).point(u)      # what the trial got
    assert np.ptp(np.linalg.norm(uniform[:, :2], axis=1)) > 0.1
    report.write_config(tmp_path / "again.toml", exp)
    again = next(r for r in config.load(tmp_path / "again.toml").rails if r.name == "ring")
    np.testing.assert_allclose(again.point(u), pts, atol=1e-12)


SEAM_STEP = 0.05     # how far past the ring's seam (u = 1 = 0) the camera is moved, in u


def test_a_camera_goes_round_a_closed_rail_past_its_seam(tmp_path):
    """On a closed rail (the CAD circle: its last control point is its first) the optimizer's u
    is θ mod 1, not a sigmoid that stops short of the ends: a camera at u = 0.98 moved by
    SEAM_STEP stands at the config's own point C(0.03) (NumPy, `RailSpec.point`), the map's
    derivative across the seam matches central differences, and `u` reads 0.03. The open beam
    keeps its sigmoid. `vdo design` offers the ring's u = 0 once (not again at u = 1)."""
    from vdo.design.candidates import spots

    exp = config.load(write(tmp_path, MOUNTS + RING, RING_CAMERA.replace("u = 0.5", "u = 0.98")
                            + CAMERAS.split("[[camera]]")[3].replace('name = "b"', '[[camera]]\nname = "o"')
                            + "\n[design]\nrail_positions = 5\n"))
    ring = next(r for r in exp.rails if r.name == "ring")
    param = Parameterization(exp, cameras_of(exp.camera_specs, exp.rails), np.zeros(3))
    assert param.periodic == [False, False, True, False] and ring.closed
    k = param.index[2]["u"]
    assert param.theta0[k] == pytest.approx(0.98)
    theta = param.theta0.copy()
    theta[k] += SEAM_STEP
    np.testing.assert_allclose(param.cameras_at(theta)[2].position, ring.point(0.03), atol=1e-9)
    assert param.u(theta)[2] == pytest.approx(0.03) and param.u(theta)[3] == 0.5
    pos = lambda z: param.poses(jnp.asarray(theta).at[k].set(z), param.held)[0][2]
    h = 1e-6
    for z in (1.0 - 1e-3, 1.0 + 1e-3):                      # either side of the seam
        fd = (np.asarray(pos(z + h)) - np.asarray(pos(z - h))) / (2 * h)
        np.testing.assert_allclose(np.asarray(jax.jacfwd(pos)(z)), fd, rtol=1e-5, atol=1e-8)
    by_rail = {}
    for mount, kind, u, *_ in spots(exp):
        by_rail.setdefault(mount, []).append(u)
    assert sorted(set(by_rail["ring"])) == [0.0, 0.25, 0.5, 0.75]          # each u with its heads
    assert sorted(set(by_rail["beam"])) == [0.0, 0.25, 0.5, 0.75, 1.0]


@pytest.mark.parametrize("knots, words", [
    ("[0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4]", "must hold n + degree + 1 = 12 values"),
    ("[0, 0, 0, 1, 1, 2, 2, 3, 3, 2, 4, 4]", "must be non-decreasing"),
    ("[0, 0, 1, 1, 1, 2, 2, 3, 3, 4, 4, 4]", "must be clamped"),
    ("[0, 0, 0, 1, 1, 1, 2, 3, 3, 4, 4, 4]", "more than the degree 2"),
])
def test_bad_knots_are_one_config_error_line(tmp_path, knots, words):
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, MOUNTS + RING.replace("[0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 4]", knots),
                          RING_CAMERA))
    text = str(err.value)
    assert "\n" not in text and err.value.field == 'mount "ring".knots' and words in text, text


def test_non_positive_lens_in_the_catalogue_is_refused(tmp_path):
    extra = '\n[optimize]\nfree = ["u", "pan", "tilt", "lens"]\nlenses_mm = [16, 0, 35]\n'
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, extra=extra))
    assert err.value.field == "optimize.lenses_mm" and "each > 0" in str(err.value)


def test_optimized_zone_camera_stays_in_its_zone_and_reloads(tmp_path):
    """A short optimization of the tripod camera alone: it ends inside its zone, and the written
    layout (mount + position) loads again with the same pose."""
    from vdo.commands.optimize import optimize

    extra = '\n[render]\nambient_radiance = 1.0\n\n[optimize]\ncameras = ["t"]\nstarts = 1\nrounds = 1\nmax_steps = 6\n'
    exp = config.load(write(tmp_path, extra=extra))
    exp = dataclasses.replace(exp, optimize=dataclasses.replace(exp.optimize, min_axis_angle=0.0))
    out = tmp_path / "run"
    optimize(exp, out)
    again = config.load(out / "optimized.toml")
    zone = again.mount("tripod")
    cam = cameras_of(again.camera_specs, again.rails)[0]
    assert again.camera_specs[0].mount == "tripod"
    assert np.all(cam.position >= zone.box_min) and np.all(cam.position <= zone.box_max)


FLOOR = """
[[mount]]
name = "corner"
kind = "zone"
floor_m = [[0.4, -0.6], [1.0, -0.5], [1.1, 0.2], [0.6, 0.5], [0.3, 0.0]]
height_m = [0.9, 1.4]
"""
FLOOR_CAMERA = CAMERAS.replace('mount = "tripod"\nposition_m = [0.6, 0.1, 1.0]',
                               'mount = "corner"\nposition_m = [0.7, -0.1, 1.1]')


def test_floor_polygon_zone_keeps_the_camera_over_the_polygon(tmp_path):
    """A pentagon floor zone: θ0 reproduces the configured position (mean value coordinates),
    any θ stays over the polygon (half-plane test) and within the heights, and the derivative
    matches finite differences."""
    from vdo.config.mounts import inside_floor

    exp = config.load(write(tmp_path, MOUNTS + FLOOR, FLOOR_CAMERA))
    param = Parameterization(exp, cameras_of(exp.camera_specs, exp.rails), np.zeros(3))
    idx = param.index[0]
    assert {"w1", "w2", "w3", "w4", "z"} <= set(idx)
    np.testing.assert_allclose(param.cameras_at(param.theta0)[0].position, [0.7, -0.1, 1.1], atol=1e-6)
    zone = exp.mount("corner")
    rng = np.random.default_rng(1)
    for spread in (1.0, 10.0, 60.0):
        for _ in range(20):
            p = param.cameras_at(param.theta0 + spread * rng.standard_normal(param.theta0.size))[0].position
            assert inside_floor(zone.floor, p[:2]) and 0.9 <= p[2] <= 1.4
    held = param.held
    f = lambda th: jnp.ravel(param.poses(th, held)[0])
    theta0 = jnp.asarray(param.theta0 + 0.2)
    jac = np.asarray(jax.jacfwd(f)(theta0))
    h = 1e-6
    fd = np.stack([(np.asarray(f(theta0.at[k].add(h))) - np.asarray(f(theta0.at[k].add(-h)))) / (2 * h)
                   for k in range(theta0.size)], axis=1)
    np.testing.assert_allclose(jac, fd, atol=1e-7, rtol=1e-6)
    report.write_config(tmp_path / "again.toml", exp)   # the polygon survives a round trip
    np.testing.assert_allclose(config.load(tmp_path / "again.toml").mount("corner").floor, zone.floor)


@pytest.mark.parametrize("floor, camera_pos, field, words", [
    ("[[0.4, -0.6], [0.7, -0.3], [1.0, 0.0]]", "[0.7, -0.3, 1.1]", "floor_m", "no floor area"),
    # a floor whose edges cross (a concave one is a zone now: tests/config/test_floor_zones.py)
    ("[[0.4, -0.6], [1.0, 0.4], [1.0, -0.6], [0.4, 0.2]]", "[0.6, 0.0, 1.1]", "floor_m", "edges cross"),
    # a symmetric bow-tie: its signed area is 0, yet the reason is the crossing, not the area
    ("[[0.4, 0.4], [1.0, -0.6], [0.4, -0.6], [1.0, 0.4]]", "[0.6, 0.0, 1.1]", "floor_m", "edges cross"),
    # repeated corners: no area, and no crossing
    ("[[0.4, -0.6], [1.0, 0.4], [1.0, 0.4], [0.4, -0.6]]", "[0.6, 0.0, 1.1]", "floor_m", "no floor area"),
    # in the bounding box, not over the floor
    ("[[0.4, -0.6], [1.0, -0.5], [1.1, 0.2]]", "[0.5, 0.1, 1.1]", "position_m", "off the floor polygon of zone"),
])
def test_bad_floor_zone_is_one_config_error_line(tmp_path, floor, camera_pos, field, words):
    mounts = MOUNTS + FLOOR.replace("[[0.4, -0.6], [1.0, -0.5], [1.1, 0.2], [0.6, 0.5], [0.3, 0.0]]", floor)
    cams = CAMERAS.replace('mount = "tripod"\nposition_m = [0.6, 0.1, 1.0]',
                           f'mount = "corner"\nposition_m = {camera_pos}')
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, mounts, cams))
    assert "\n" not in str(err.value) and err.value.field.endswith(field) and words in str(err.value), str(err.value)


def test_a_light_on_a_rail_mount_a_camera_uses_names_the_field_and_the_light(tmp_path):
    """Trial 4: a camera on a rail [[mount]] (`mount = ...`, read as a rail) that also carries a
    light was told about its `rail`, a field it does not have, and the light went unnamed."""
    light = ('\n[[light]]\nname = "front"\nmount = "beam"\nposition_m = [0.2, -0.8, 1.5]\n'
             'target_m = [0, 0, 0]\nsize_m = [0.2, 0.2]\nradiance = 10\n')
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, extra=light))
    assert err.value.field == 'camera "b".mount', str(err.value)
    assert "'beam' carries the [[light]] 'front'" in err.value.message
