"""Tripods as obstacles that move with their cameras ([mount.tripod], `vdo.scene.tripod`).

A wall (the specimen, its face at x = 0) is watched by camera "viewer" from 2 m away; camera
"stand" stands on a tripod in a floor zone between them. The samples the viewer loses, and the
light the tripod takes from a panel beside the viewer, are compared with a ray-cylinder test
written here (exact for a solid capped cylinder): the legs and column are prisms inscribed in
their cylinders, so a line of sight that meets the cylinder shrunk to the prism's inner radius
r cos(π/n) must be lost, and one that misses the full cylinder must be kept. The tripod's
geometry itself is checked against the [mount.tripod] numbers, and bad tripod input is one
ConfigError line."""

import dataclasses
import math

import numpy as np
import pytest

from conftest import write_box
from vdo.config import experiment as config
from vdo.config.mounts import TripodSpec
from vdo.physics import lighting
from vdo.core.errors import ConfigError
from vdo.scene import TRIPOD_SECTIONS, cameras_of, tripod_cylinders
from vdo.state import layout_state, prepare
from vdo.physics.visibility import EPSILON

TRIPOD = """
[mount.tripod]
legs = {legs}
spread_m = 0.45
leg_diameter_m = 0.04
column_diameter_m = 0.06
column_length_m = 0.3
"""

WALL_TOML = """
[experiment]
name = "wall behind a tripod"

[evaluation]
sample_spacing_mm = 10
incidence_limit_deg = 80

[[mesh]]
name = "wall"
file = "wall.stl"
unit = "mm"
role = "specimen"

[[region]]
name = "face"
mesh = "wall"
normal = [1, 0, 0]

[[mount]]
name = "floor"
kind = "zone"
box_min_m = [0.6, -0.6, 0.5]
box_max_m = [1.4, 0.6, 1.4]
{tripod}

[[light]]
name = "panel"
position_m = [2.2, -0.5, 1.0]
target_m = [0, 0, 0.5]
size_m = [0.3, 0.3]
radiance = 50

[[camera]]
name = "viewer"
sensor_mm = [22.2, 14.8]
pixels = [300, 200]
focal_mm = 24
position_m = [2.0, 0.0, 0.55]
target_m = [0.0, 0.0, 0.5]

[[camera]]
name = "stand"
sensor_mm = [22.2, 14.8]
pixels = [300, 200]
focal_mm = 24
mount = "floor"
position_m = [{x}, {y}, 0.9]
pan_deg = 180
tilt_deg = {tilt}
body = false
"""

# the prisms' radius lies in [r cos(π/n), r]; float32 rays add a few micrometres
INNER = math.cos(math.pi / TRIPOD_SECTIONS)
SLACK_M = 2e-5
MIN_LOST = 100            # samples the leg must hide from the viewer for the case to mean anything
MAX_BAND = 0.05           # fraction of the lost samples that may lie in the prism/cylinder band


def write(folder, x=1.0, y=0.1, tilt=-20.0, legs=3, tripod=True):
    write_box(folder / "wall.stl", [10, 1000, 1000], center=[-5, 0, 500])
    text = WALL_TOML.format(tripod=TRIPOD.format(legs=legs) if tripod else "", x=x, y=y, tilt=tilt)
    (folder / "exp.toml").write_text(text)
    return folder / "exp.toml"


def segment_hits_cylinder(origins, ends, top, bottom, radius):
    """(N,) bool: whether the segment origins[n] -> ends[n] meets the solid capped cylinder of
    axis top -> bottom and `radius` (the quadratic for the infinite cylinder, cut by the slab of
    the caps)."""
    axis = bottom - top
    length = np.linalg.norm(axis)
    a = axis / length
    d = ends - origins
    w = origins - top
    d_perp = d - np.outer(d @ a, a)
    w_perp = w - np.outer(w @ a, a)
    qa = np.einsum("ij,ij->i", d_perp, d_perp)
    qb = 2 * np.einsum("ij,ij->i", d_perp, w_perp)
    qc = np.einsum("ij,ij->i", w_perp, w_perp) - radius**2
    disc = qb**2 - 4 * qa * qc
    ok = disc >= 0
    root = np.sqrt(np.where(ok, disc, 0.0))
    safe = np.where(qa > 1e-300, qa, 1.0)
    t1 = np.where(qa > 1e-300, (-qb - root) / (2 * safe), np.where(qc <= 0, -np.inf, np.inf))
    t2 = np.where(qa > 1e-300, (-qb + root) / (2 * safe), np.where(qc <= 0, np.inf, -np.inf))
    s0, ds = w @ a, d @ a                      # axial coordinate along the segment: s0 + t ds
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (0.0 - s0) / ds, (length - s0) / ds
    t3 = np.where(ds != 0, np.minimum(ta, tb), np.where((s0 >= 0) & (s0 <= length), -np.inf, np.inf))
    t4 = np.where(ds != 0, np.maximum(ta, tb), np.where((s0 >= 0) & (s0 <= length), np.inf, -np.inf))
    lo = np.maximum.reduce([t1, t3, np.zeros_like(t1)])
    hi = np.minimum.reduce([t2, t4, np.ones_like(t1)])
    return ok & (lo <= hi)


def hidden_by_tripod(cylinders, origins, ends, scale, slack):
    """Whether each segment meets any of the cylinders with radius r * scale + slack."""
    out = np.zeros(len(origins), dtype=bool)
    for top, bottom, radius in cylinders:
        out |= segment_hits_cylinder(origins, ends, top, bottom, radius * scale + slack)
    return out


def sight_lines(state, camera):
    """The visibility rays of `camera` (`vdo.physics.visibility`): from each sample lifted by EPSILON
    along its normal to EPSILON short of the optical centre."""
    s = state.samples
    origins = s.points + EPSILON * s.normals
    to_cam = camera.position - origins
    dist = np.linalg.norm(to_cam, axis=1, keepdims=True)
    return origins, origins + to_cam * (1 - EPSILON / dist)


def lost_and_expected(folder, **where):
    exp = config.load(write(folder, **where))
    state = layout_state(prepare(exp), predict_fields=False)
    viewer, stand = state.cameras
    vis = state.visibility
    candidate = vis.in_image[0] & vis.facing[0]
    lost = candidate & ~vis.unoccluded[0]
    cylinders = tripod_cylinders(stand, exp.mount("floor").tripod)
    origins, ends = sight_lines(state, viewer)
    surely = candidate & hidden_by_tripod(cylinders, origins, ends, INNER, -SLACK_M)
    maybe = candidate & hidden_by_tripod(cylinders, origins, ends, 1.0, SLACK_M)
    return state, lost, surely, maybe


@pytest.mark.parametrize("y", [0.1, 0.3])
def test_viewer_loses_exactly_the_samples_behind_the_legs(tmp_path, y):
    state, lost, surely, maybe = lost_and_expected(tmp_path, y=y)
    assert lost.sum() >= MIN_LOST, lost.sum()
    assert not np.any(surely & ~lost), "a line of sight through a leg was kept"
    assert not np.any(lost & ~maybe), "a line of sight clear of every cylinder was lost"
    assert (maybe & ~surely).sum() <= MAX_BAND * lost.sum()


def test_moving_the_tripod_camera_moves_what_it_hides(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    _, lost_a, _, _ = lost_and_expected(tmp_path / "a", y=0.1)
    _, lost_b, surely_b, maybe_b = lost_and_expected(tmp_path / "b", y=0.3)
    moved = lost_a ^ lost_b
    assert moved.sum() >= MIN_LOST, "the tripod's shadow in the viewer did not move with the camera"
    assert not np.any(surely_b & ~lost_b) and not np.any(lost_b & ~maybe_b)


def test_tripod_shadows_the_light_where_the_shadow_rays_cross_it(tmp_path):
    exp = config.load(write(tmp_path))
    state = layout_state(prepare(exp), predict_fields=False)
    bare = layout_state(prepare(exp), [state.cameras[0]], predict_fields=False)   # stand gone
    light = exp.lights[0]
    panel, _ = lighting.panel_points(light)
    n_l, _, _ = lighting.panel_frame(light)
    s = state.samples
    cylinders = tripod_cylinders(state.cameras[1], exp.mount("floor").tripod)
    origins = np.repeat(s.points + lighting.EPSILON * s.normals, len(panel), axis=0)
    target = np.tile(panel, (len(s), 1))
    to_panel = target - origins
    dist = np.linalg.norm(to_panel, axis=1, keepdims=True)
    ends = origins + to_panel * (1 - lighting.EPSILON / dist)
    d = target - np.repeat(s.points, len(panel), axis=0)         # sample -> panel point
    facing = (np.einsum("ij,ij->i", d, np.repeat(s.normals, len(panel), axis=0)) > 0) & (d @ n_l < 0)
    lit_bare = bare.illumination.lit[0]
    # without the tripod nothing hides the panel from the wall
    np.testing.assert_allclose(lit_bare, facing.reshape(len(s), -1).mean(axis=1), atol=1e-12)
    clear_most = facing & ~hidden_by_tripod(cylinders, origins, ends, INNER, -SLACK_M)
    clear_least = facing & ~hidden_by_tripod(cylinders, origins, ends, 1.0, SLACK_M)
    most = clear_most.reshape(len(s), -1).mean(axis=1)
    least = clear_least.reshape(len(s), -1).mean(axis=1)
    lit = state.illumination.lit[0]
    assert np.all(lit <= most + 1e-12) and np.all(lit >= least - 1e-12)
    assert (lit < lit_bare - 0.05).sum() >= MIN_LOST, "the tripod casts no shadow on the wall"


@pytest.mark.parametrize("tilt", [20.0, 0.0, -20.0, -50.0])
def test_a_camera_is_not_hidden_by_its_own_tripod(tmp_path, tilt):
    exp = config.load(write(tmp_path, tilt=tilt))
    state = layout_state(prepare(exp), predict_fields=False)
    stand = state.cameras[1]
    cylinders = tripod_cylinders(stand, exp.mount("floor").tripod)
    # its own lines of sight miss its own cylinders (geometry, not an exception in the ray cast)
    origins, ends = sight_lines(state, stand)
    assert not np.any(hidden_by_tripod(cylinders, origins, ends, 1.0, 0.0))
    bare = config.load(write(tmp_path, tilt=tilt, tripod=False))
    seen_bare = layout_state(prepare(bare), predict_fields=False).visibility.visible[1]
    assert seen_bare.sum() > 0
    np.testing.assert_array_equal(state.visibility.visible[1], seen_bare)


@pytest.mark.parametrize("legs", [3, 5])
def test_tripod_geometry_follows_the_mount_table(tmp_path, legs):
    exp = config.load(write(tmp_path, legs=legs))
    spec = exp.mount("floor").tripod
    stand = cameras_of(exp.camera_specs, exp.rails)[1]
    parts = tripod_cylinders(stand, spec)
    assert len(parts) == legs + 1
    top = parts[0][0]
    assert top[2] < stand.position[2] - spec.head           # the top casting is under the camera
    feet = np.array([bottom for _, bottom, _ in parts[:legs]])
    np.testing.assert_allclose(feet[:, 2], spec.floor_z, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(feet[:, :2] - top[:2], axis=1), spec.spread, rtol=1e-12)
    azimuths = np.degrees(np.arctan2(*(feet[:, :2] - top[:2]).T[::-1]))
    expected = np.degrees(stand.pan + spec.azimuth) + 360.0 * np.arange(legs) / legs
    np.testing.assert_allclose((azimuths - expected + 180) % 360 - 180, 0, atol=1e-9)
    column_top, column_bottom, column_radius = parts[-1]
    np.testing.assert_allclose(column_top - column_bottom, [0, 0, spec.column_length], atol=1e-12)
    assert column_radius == pytest.approx(0.03) and parts[0][2] == pytest.approx(0.02)
    # the tripod moves with the camera
    moved = tripod_cylinders(stand.with_pose(stand.position + [0.1, -0.2, 0.05], stand.pan, stand.tilt), spec)
    np.testing.assert_allclose(moved[0][0] - top, [0.1, -0.2, 0.05], atol=1e-12)


def test_tripod_table_round_trips(tmp_path):
    import tomllib

    import tomli_w

    exp = config.load(write(tmp_path))
    again = config.parse(tomllib.loads(tomli_w.dumps(exp.to_dict())), exp.path)
    assert again.mount("floor").tripod == exp.mount("floor").tripod
    assert dataclasses.asdict(exp.mount("floor").tripod)["leg_diameter"] == pytest.approx(0.04)
    text = tmp_path / "defaults.toml"
    text.write_text(write(tmp_path).read_text().replace(TRIPOD.format(legs=3), "tripod = {}\n"))
    assert config.load(text).mount("floor").tripod == TripodSpec()


@pytest.mark.parametrize("old, new, field, words", [
    ("legs = 3", "legs = 2", 'mount "floor".tripod.legs', "integer >= 3"),
    ("spread_m = 0.45", "spread_m = 0", 'mount "floor".tripod.spread_m', "positive"),
    ("leg_diameter_m = 0.04", "leg_diameter_m = -0.04", 'mount "floor".tripod.leg_diameter_m', "positive"),
    ("column_diameter_m = 0.06", "column_diameter_m = 0.0", 'mount "floor".tripod.column_diameter_m',
     "positive"),
    ("legs = 3", "legz = 3", 'mount "floor".tripod.legz', "did you mean 'legs'"),
    ("legs = 3", "legs = 3\nfloor_z_m = 0.45", 'mount "floor".tripod.floor_z_m', "no room"),
    ('kind = "zone"\nbox_min_m = [0.6, -0.6, 0.5]\nbox_max_m = [1.4, 0.6, 1.4]',
     'kind = "fixed"\nposition_m = [1.0, 0.1, 0.9]', 'mount "floor".tripod', "only a zone mount"),
    # trial 4: a floor-wide keep-out (for the cameras of a rail) also holds every tripod foot
    ("column_length_m = 0.3", 'column_length_m = 0.3\n[[keep_out]]\nname = "below"\nbox_min_m = [-inf, -inf, -inf]\n'
     "box_max_m = [inf, inf, 0.05]", 'mount "floor".tripod.floor_z_m', "end the keep-out below the floor"),
])
def test_bad_tripod_input_is_one_config_error_line(tmp_path, old, new, field, words):
    path = write(tmp_path)
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    with pytest.raises(ConfigError) as err:
        config.load(path)
    message = str(err.value)
    assert "\n" not in message and err.value.field == field and words in message, message


MAX_LEG_BRIGHTNESS = 0.3     # a leg pixel's mean radiance against the wall's without the tripod
MIN_LEG_PIXELS = 50


def test_render_shows_the_other_cameras_tripod(tmp_path):
    """The viewer's render is dark where its pixel rays meet the stand's tripod (the cylinders
    shrunk by one pixel's footprint, so that the whole pixel is on the leg)."""
    from vdo.render import build_render_scene, camera_sensor, render_linear
    from vdo.state import bodies

    exp = config.load(write(tmp_path))
    geometry = prepare(exp)
    viewer, stand = cameras_of(exp.camera_specs, exp.rails)
    images = []
    for cams in ([viewer, stand], [viewer]):
        sc = build_render_scene(exp, list(geometry.meshes), list(geometry.region_faces), bodies(exp, cams))
        images.append(render_linear(sc, camera_sensor(viewer, exp.camera_specs[0], 4, jitter=False), 0))
    with_tripod, without = images
    v, u = np.mgrid[0:viewer.height, 0:viewer.width]
    rays = np.stack([(u.ravel() - viewer.principal_point[0]) / viewer.focal_px,
                     (v.ravel() - viewer.principal_point[1]) / viewer.focal_px,
                     np.ones(u.size)], axis=1) @ viewer.R          # camera -> world directions
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    origins = np.broadcast_to(viewer.position, rays.shape)
    ends = origins + 5.0 * rays
    footprint = 1.5 * np.linalg.norm(stand.position - viewer.position) / viewer.focal_px
    on_leg = np.zeros(u.size, dtype=bool)
    for top, bottom, radius in tripod_cylinders(stand, exp.mount("floor").tripod):
        if radius * INNER > footprint:
            on_leg |= segment_hits_cylinder(origins, ends, top, bottom, radius * INNER - footprint)
    t_wall = -viewer.position[0] / rays[:, 0]                   # where each ray meets x = 0
    wall = viewer.position + t_wall[:, None] * rays
    behind = (t_wall > 0) & (np.abs(wall[:, 1]) < 0.5) & (wall[:, 2] > 0) & (wall[:, 2] < 1)
    on_leg = (on_leg & behind).reshape(u.shape)                 # a leg in front of the wall
    assert on_leg.sum() >= MIN_LEG_PIXELS
    assert with_tripod[on_leg].mean() < MAX_LEG_BRIGHTNESS * without[on_leg].mean()
    assert with_tripod[~on_leg].mean() == pytest.approx(without[~on_leg].mean(), rel=0.1)


def test_prisms_are_closed_outward_and_inscribed():
    """A leg's prism: watertight, normals outward (positive volume), of the inscribed n-gon's
    volume (n/2) r² sin(2π/n) L, its vertices on the cylinder."""
    import trimesh

    from vdo.scene import prism

    top, bottom, radius = np.array([0.1, 0.2, 1.4]), np.array([0.5, -0.1, 0.0]), 0.015
    vertices, faces = prism(top, bottom, radius)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    n, length = TRIPOD_SECTIONS, np.linalg.norm(top - bottom)
    assert mesh.volume == pytest.approx(n / 2 * radius**2 * math.sin(2 * math.pi / n) * length, rel=1e-9)
    axis = (top - bottom) / length
    rel = vertices[:2 * n] - bottom
    np.testing.assert_allclose(np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1), radius, rtol=1e-12)


def test_the_run_in_3d_draws_each_tripod(tmp_path):
    """`vdo.outputs.view3d.load` (report.html, view3d_*.png) draws one mesh per tripod, at the camera's
    pose in the run's config.toml."""
    from vdo.outputs import report
    from vdo.outputs import view3d
    from vdo.scene import tripods

    exp = config.load(write(tmp_path))
    run = tmp_path / "run"
    run.mkdir()
    report.write_config(run / "config.toml", exp)
    drawn = {name: (v, f) for name, _, v, f in view3d.load(run).meshes}
    assert set(drawn) == {"wall", "tripod:stand"}
    parts = tripods(cameras_of(exp.camera_specs, exp.rails), camera_specs=exp.camera_specs, mounts=exp.mounts)
    vertices, faces = drawn["tripod:stand"]
    np.testing.assert_allclose(vertices, np.vstack([p.vertices for p in parts]), atol=1e-9)
    assert len(faces) == sum(len(p.faces) for p in parts) and faces.max() == len(vertices) - 1


# --------------------------------------------------------------------------------------------
# Tripods in the constraints: out of the keep-outs, apart from one another
# --------------------------------------------------------------------------------------------
def two_tripods(folder, keep_out=""):
    """The wall scene with the viewer on the floor zone too: two tripods 0.6 m apart."""
    text = write(folder, legs=4).read_text().replace(
        'position_m = [2.0, 0.0, 0.55]\ntarget_m = [0.0, 0.0, 0.5]',
        'mount = "floor"\nposition_m = [1.2, -0.5, 0.9]\ntarget_m = [0.0, 0.0, 0.5]')
    (folder / "exp.toml").write_text(text + keep_out)
    return config.load(folder / "exp.toml")


def test_the_constraints_read_the_legs_of_the_tripod_mesh(tmp_path):
    """`tripod_legs` (NumPy and JAX) gives the legs `tripod_cylinders` builds the mesh from."""
    import jax.numpy as jnp

    from vdo import constraints

    exp = two_tripods(tmp_path)
    cams = cameras_of(exp.camera_specs, exp.rails)
    table = constraints.tripod_table(cams, constraints.tripods_of(cams, exp.camera_specs, exp.mounts))
    assert table["has"].tolist() == [True, True]
    pos, axes, pans = (np.array([getattr(c, a) for c in cams], float) for a in ("position", "optical_axis", "pan"))
    for xp in (np, jnp):
        top, feet = constraints.tripod_legs(xp.asarray(pos), xp.asarray(axes), xp.asarray(pans),
                                            {k: xp.asarray(v) for k, v in table.items()}, xp=xp)
        for c, cam in enumerate(cams):
            legs = tripod_cylinders(cam, exp.mount("floor").tripod)[:4]
            np.testing.assert_allclose(np.asarray(top[c]), legs[0][0], atol=1e-12)
            np.testing.assert_allclose(np.asarray(feet[c]), [foot for _, foot, _ in legs], atol=1e-12)
            assert table["radius"][c] == pytest.approx(legs[0][2])


def test_segment_distance_against_dense_sampling():
    """`segment_distance` against the least distance between 2001 points on each segment, on
    random, parallel, touching and end-to-end segments."""
    from vdo.geometry.obstacles import segment_distance

    rng = np.random.default_rng(5)
    cases = [tuple(rng.normal(size=(4, 3))) for _ in range(30)]
    p0, p1 = np.zeros(3), np.array([1.0, 0, 0])
    cases += [(p0, p1, p0 + [0.3, 0.2, 0], p1 + [0.3, 0.2, 0]),        # parallel, overlapping
              (p0, p1, [1.5, 0.1, 0.0], [2.5, 0.1, 0.0]),               # parallel, end to end
              (p0, p1, [0.5, -1, 0.0], [0.5, 1, 0.0]),                  # crossing: 0
              (p0, p0, [0.0, 1.0, 0.0], [1.0, 1.0, 0.0])]               # a point and a segment
    s = np.linspace(0, 1, 2001)[:, None]
    for a, b, c, d in cases:
        a, b, c, d = (np.asarray(x, float) for x in (a, b, c, d))
        P, Q = a + s * (b - a), c + s * (d - c)
        brute = np.sqrt(((P[:, None] - Q[None]) ** 2).sum(-1)).min()
        step = (np.linalg.norm(b - a) + np.linalg.norm(d - c)) / 2000
        assert segment_distance(a, b, c, d) <= brute + 1e-12
        assert segment_distance(a, b, c, d) >= brute - step


def test_a_tripod_foot_in_a_keep_out_is_a_broken_check_and_a_penalty_the_gradient_leaves(tmp_path):
    """A keep-out box 0.2 m square and 0.05 m high around one foot of the "stand" tripod, 0.08 m
    of it on one side in x: its check is broken by the foot's horizontal depth, 0.08 m (a foot leaves the box across the
    floor; the leg above it lies less deep); the penalty is positive, and its JAX gradient in the
    camera's position matches central differences and moves the foot out across the floor. The
    two tripods' clearance check equals the least distance between their legs' sampled axes
    minus both radii."""
    import jax
    import jax.numpy as jnp

    from vdo import constraints
    from vdo.core.configure import configure

    configure()                                  # float64 JAX, as the commands run it
    exp = two_tripods(tmp_path)
    cams = cameras_of(exp.camera_specs, exp.rails)
    foot = tripod_cylinders(cams[1], exp.mount("floor").tripod)[1][1]
    box = (f'\n[[keep_out]]\nname = "pit"\nbox_min_m = [{foot[0] - 0.08}, {foot[1] - 0.1}, -1.0]\n'
           f"box_max_m = [{foot[0] + 0.12}, {foot[1] + 0.1}, 0.05]\n")
    exp = two_tripods(tmp_path, box)
    table = constraints.tripod_table(cams, constraints.tripods_of(cams, exp.camera_specs, exp.mounts))
    checks = constraints.tripod_checks(cams, table, exp.keep_outs, clearance=0.05)
    pit = {e["cameras"][0]: e for e in checks if e["constraint"] == "tripod_keep_out"}
    assert pit["stand"]["value"] == pytest.approx(0.08, abs=1e-9) and not pit["stand"]["met"]
    assert pit["viewer"]["met"]
    apart = next(e for e in checks if e["constraint"] == "tripod_clearance")
    pos, axes, pans = (np.array([getattr(c, a) for c in cams], float) for a in ("position", "optical_axis", "pan"))
    top, feet = constraints.tripod_legs(pos, axes, pans, table, xp=np)
    s = np.linspace(0, 1, 1001)[:, None]
    legs = [[top[c] + s * (f - top[c]) for f in feet[c]] for c in range(2)]
    brute = min(np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1)).min() for a in legs[0] for b in legs[1])
    assert apart["value"] == pytest.approx(brute - 2 * table["radius"][0], abs=2e-3)
    lows, highs = (jnp.asarray(np.array([getattr(k, a) for k in exp.keep_outs])) for a in ("box_min", "box_max"))
    tab = {k: jnp.asarray(v) for k, v in table.items()}

    def penalty(p):
        return constraints.tripod_penalty(*constraints.tripod_legs(p, jnp.asarray(axes), jnp.asarray(pans), tab),
                                          tab, lows, highs, 0.05, 0.01)

    P = jnp.asarray(pos)
    assert float(penalty(P)) > 0
    grad = np.asarray(jax.grad(penalty)(P))
    for k in range(3):
        h = np.zeros_like(pos)
        h[1, k] = 1e-6
        fd = (float(penalty(P + h)) - float(penalty(P - h))) / 2e-6
        assert grad[1, k] == pytest.approx(fd, rel=1e-4, abs=1e-6)
    assert np.linalg.norm(grad[1, :2]) > 0 and abs(grad[0]).max() == 0   # across the floor; the viewer untouched
    step = -grad[1, :2] / np.linalg.norm(grad[1, :2])
    assert float(penalty(P.at[1, :2].add(0.01 * step))) < float(penalty(P))   # a descent direction
    assert float(penalty(P.at[1, :2].add(0.1 * step))) < 1e-3 * float(penalty(P))  # past the box's 0.08 m
