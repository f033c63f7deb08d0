"""Glare (`vdo.physics.glare`): the satin lobe against Mitsuba's own roughplastic BSDF, and the
hot-spot check on a satin plate facing a light panel (flagged; the light moved off the mirror
direction clears it), with the hot spot where a Mitsuba render of the plate shows it."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import DOWN_CAMERA, write_plate_experiment
from conftest import region_tables
from vdo.config import experiment as config
from vdo.config.rig import LightSpec
from vdo.physics import glare
from vdo.state import layout_state, prepare

# Mitsuba evaluates its BSDF in float32
FLOAT32_RTOL = 1e-5

PANEL = """
[[light]]
name = "panel"
position_m = [{x}, 0.0, 1.2]
target_m = [0.0, 0.0, 0.0]
size_m = [0.3, 0.3]
radiance = 60.0
"""


def test_the_satin_lobe_is_mitsubas_roughplastic():
    """Mitsuba's roughplastic with no diffuse part, GGX of the same roughness and index: its
    eval (f_s cos_o) at random pairs of directions near the mirror direction."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    bsdf = mi.load_dict({"type": "roughplastic", "distribution": "ggx", "alpha": glare.SATIN_ALPHA,
                         "int_ior": glare.SATIN_IOR, "ext_ior": 1.0, "nonlinear": False,
                         "diffuse_reflectance": {"type": "rgb", "value": 0.0}})
    rng = np.random.default_rng(0)
    n = np.array([0.0, 0.0, 1.0])
    values = []
    for _ in range(12):
        wi = rng.normal(size=3)
        wi[2] = abs(wi[2])
        wi /= np.linalg.norm(wi)
        wo = wi * [-1, -1, 1] + rng.normal(scale=0.1, size=3)
        wo[2] = abs(wo[2])
        wo /= np.linalg.norm(wo)
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*map(float, wi))
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        ref = float(np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*map(float, wo))))[0, 0])
        ours = float(glare.lobe(n, wi, wo)) * wo[2]
        values.append(ours)
        assert ours == pytest.approx(ref, rel=FLOAT32_RTOL, abs=1e-7)
    assert max(values) > 1.0 > min(values)      # the pairs span the lobe's peak and its tail


def _satin_plate(folder, x):
    cams = DOWN_CAMERA.format(name="down", focal=24, u=0.5)
    path = write_plate_experiment(folder, spacing=20, cameras=cams)
    text = path.read_text().replace('role = "specimen"', 'role = "specimen"\nfinish = "satin"')
    path.write_text(text + PANEL.format(x=x))
    return config.load(path)


def test_a_satin_plate_facing_a_panel_is_flagged_and_moving_the_light_clears_it(tmp_path):
    """Camera straight above the plate's centre at 1.5 m. Panel at x = 0.3 m, 1.2 m high: its
    mirror point on the plate is x = 0.3 x 1.5 / 2.7 = 0.167 m, inside the plate: flagged, with
    the hottest sample there. Panel at x = -1.2 m: mirror point x = -0.667 m, off the plate:
    cleared. The matte plate under the first panel: no row (only satin regions are checked)."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    facing = _satin_plate(tmp_path / "a", 0.3)
    state = layout_state(prepare(facing), predict_fields=False)
    rows = glare.hot_spots(facing.meshes, facing.regions, facing.lights, facing.speckle,
                           facing.sensor, list(state.cameras), state.samples,
                           state.visibility.visible, state.illumination)
    assert len(rows) == 1 and rows[0]["flags"]
    assert rows[0]["hot_spot_fraction"] > glare.HOT_SPOT_FRACTION
    smp = state.samples
    Ls = glare.specular_radiance(facing.lights, state.illumination.lit, smp.points, smp.normals,
                                 [state.cameras[0].position])[0]
    hottest = smp.points[np.argmax(Ls)]
    assert hottest[0] == pytest.approx(0.3 * 1.5 / 2.7, abs=0.03)   # the mirror point, to a sample
    assert abs(hottest[1]) <= 0.03

    moved = _satin_plate(tmp_path / "b", -1.2)
    state = layout_state(prepare(moved), predict_fields=False)
    rows = glare.hot_spots(moved.meshes, moved.regions, moved.lights, moved.speckle, moved.sensor,
                           list(state.cameras), state.samples, state.visibility.visible,
                           state.illumination)
    assert len(rows) == 1 and not rows[0]["flags"]
    assert rows[0]["hot_spot_fraction"] <= glare.HOT_SPOT_FRACTION

    matte = config.load(write_plate_experiment(tmp_path / "a", spacing=20))
    assert glare.satin_samples(matte.meshes, matte.regions, state.samples).sum() == 0


# the render integrates each panel with one light sample per pixel sample (RENDER_SPP stratified
# samples) over a lobe narrower than the panel: a few percent
RENDER_RTOL = 0.05
RENDER_SPP = 256


def test_a_mitsuba_render_shows_the_predicted_hot_spot(tmp_path):
    """The satin plate with (almost) no diffuse paint rendered by Mitsuba (render.py's satin
    roughplastic, the panel an area emitter): the brightest pixel is where the predicted
    specular radiance peaks, and its value is the predicted peak."""
    from vdo import scene
    from vdo.render import build_render_scene, render_camera, scaled_camera

    exp = _satin_plate(tmp_path, 0.3)
    text = exp.path.read_text() + "\n[speckle]\nwhite_albedo = 0.001\nblack_albedo = 0.0\n"
    exp.path.write_text(text.replace("spacing_mm = 20", "spacing_mm = 5"))
    exp = config.load(exp.path)
    geometry = prepare(exp)
    state = layout_state(geometry, predict_fields=False)
    cam = scaled_camera(state.cameras[0], 0.25)
    smp = state.samples
    Ls = glare.specular_radiance(exp.lights, state.illumination.lit, smp.points, smp.normals,
                                 [cam.position])[0]
    meshes = list(geometry.meshes)
    sc = build_render_scene(exp, meshes, scene.all_region_faces(meshes, **region_tables(exp)), ())
    image = render_camera(sc, cam, exp.camera_specs[0], RENDER_SPP, seed=1, jitter=False)
    peak = np.unravel_index(np.argmax(image), image.shape)
    u, v = np.asarray(cam.project(smp.points[np.argmax(Ls)][None]))[0]
    assert image.max() == pytest.approx(Ls.max(), rel=RENDER_RTOL)
    assert np.hypot(peak[1] + 0.5 - u, peak[0] + 0.5 - v) <= 3


LIGHT_ZONE = """
[[mount]]
name = "light_stand"
kind = "rail"
control_points_m = [[-1.2, 0.0, 1.2], [0.3, 0.0, 1.2]]

[exposure]
free = ["light_positions"]
"""


def test_the_exposure_step_moves_a_light_off_the_mirror_direction(tmp_path):
    """The panel over the satin plate at x = 0.3 m (flagged, above) may stand anywhere on a rail
    from x = -1.2 to 0.3 m at its height: with "light_positions" free the exposure step moves it
    where the hot-spot check (`glare.hot_spots`, run on the result) no longer flags the plate,
    still facing its target."""
    from vdo.state import with_exposure

    path = write_plate_experiment(tmp_path, spacing=20, cameras=DOWN_CAMERA.format(name="down", focal=24, u=0.5))
    text = path.read_text().replace('role = "specimen"', 'role = "specimen"\nfinish = "satin"')
    path.write_text(text + PANEL.format(x=0.3) + 'mount = "light_stand"\n' + LIGHT_ZONE)
    exp = config.load(path)
    assert len(exp.light_places(exp.lights[0])) > 1
    placed, plan = with_exposure(exp)
    assert plan.moved == ("panel",)
    (light,) = placed.lights
    assert light.position[0] < 0.3 and light.position[1:] == pytest.approx([0.0, 1.2])
    assert any(np.allclose(light.position, p) for p in exp.light_places(exp.lights[0]))
    assert np.array_equal(light.target, exp.lights[0].target)
    state = layout_state(prepare(placed), predict_fields=False)
    rows = glare.hot_spots(placed.meshes, placed.regions, placed.lights, placed.speckle,
                           placed.sensor, list(state.cameras), state.samples,
                           state.visibility.visible, state.illumination)
    assert len(rows) == 1 and not rows[0]["flags"], rows
    assert plan.to_json()["light_positions_m"]["panel"] == pytest.approx(list(light.position))


@pytest.mark.parametrize("edit, field, words", [
    ('mount = "nowhere"', 'light "panel".mount', "no rail or zone"),
    ('mount = "fixed_stand"', 'light "panel".mount', "no rail or zone"),
    ('mount = "boxed"', 'light "panel".mount', "keep_out"),
    ('mount = "overhead"', 'camera "down".rail', "'overhead' carries the [[light]] 'panel'"),
    ("", "exposure.free", "light_positions"),
])
def test_a_light_mount_that_cannot_be_used_is_one_line(tmp_path, edit, field, words):
    path = write_plate_experiment(tmp_path, spacing=20)
    extra = """
[[mount]]
name = "fixed_stand"
kind = "fixed"
position_m = [0.5, 0.5, 1.5]

[[mount]]
name = "boxed"
kind = "zone"
box_min_m = [1.0, 1.0, 1.0]
box_max_m = [1.2, 1.2, 1.2]

[[keep_out]]
name = "cage"
box_min_m = [0.9, 0.9, 0.9]
box_max_m = [1.3, 1.3, 1.3]
"""
    path.write_text(path.read_text() + PANEL.format(x=0.3) + edit + "\n" + extra + LIGHT_ZONE)
    with pytest.raises(config.ConfigError) as err:
        config.load(path)
    message = str(err.value)
    assert field in message and words in message and "\n" not in message, message


def test_two_panels_on_one_mount_do_not_stand_in_one_place(tmp_path):
    """Two identical panels on the same rail, both best at the same point alone: the second takes
    another point, its centre at least a panel's diagonal from the first's."""
    from vdo.state import with_exposure

    second = PANEL.replace('name = "panel"', 'name = "panel2"').format(x=0.2)
    path = write_plate_experiment(tmp_path, spacing=20)
    path.write_text(path.read_text() + PANEL.format(x=0.3) + 'mount = "light_stand"\n'
                    + second + 'mount = "light_stand"\n' + LIGHT_ZONE)
    placed, plan = with_exposure(config.load(path))
    a, b = (np.asarray(lt.position) for lt in placed.lights)
    assert np.linalg.norm(a - b) >= np.hypot(0.3, 0.3) - 1e-9
    places = placed.light_places(placed.lights[0])
    assert all(any(np.allclose(p, q) for q in places) for p in (a, b))


def test_the_panel_hides_what_mitsubas_ray_cast_hides(tmp_path):
    """`panel_hides` (sight lines against the panel's rectangle) against Mitsuba: the plate seen
    from above with and without a 0.3 m square, 1 mm thin box where a horizontal panel would
    stand; the area fraction of the samples seen without it and lost with it. The two differ
    only at the shadow's edge, by samples (20 mm apart) the box's 1 mm thickness or the edge
    itself decides."""
    from conftest import raycast
    from vdo.physics.exposure import panel_hides

    centre = (0.1, 0.05, 0.9)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    bare = write_plate_experiment(tmp_path / "a", spacing=20)
    boxed = write_plate_experiment(tmp_path / "b", spacing=20, files=[
        ("panel.stl", [300, 300, 1], [1000 * c for c in centre])], extra_meshes=(
        '[[mesh]]\nname = "panel"\nfile = "panel.stl"\nunit = "mm"\nrole = "obstacle"\n'))
    exp, samples, cams, _, seen = raycast(bare)
    _, _, _, _, behind = raycast(boxed)
    before = np.asarray(seen.visible[0])
    lost = before & ~np.asarray(behind.visible[0])
    mitsuba = samples.area[lost].sum() / samples.area[before].sum()
    light = LightSpec(name="p", position=np.array(centre), target=np.array([0.1, 0.05, 0.0]),
                             size=(0.3, 0.3), radiance=1.0)
    ours = panel_hides(light, cams[0].position, samples.points[before], samples.area[before])
    assert 0.2 < mitsuba < 0.6                              # the shadow falls on the plate in part
    assert ours == pytest.approx(mitsuba, abs=PANEL_EDGE_TOL)


PANEL_EDGE_TOL = 0.02   # area fraction: the shadow's edge, 2.5 x the panel's 1.2 m perimeter over 20 mm samples


def test_a_mount_wholly_in_a_cameras_view_keeps_the_light_where_it_was(tmp_path):
    """A rail 0.6 m under the camera, over the plate's middle: every place hides the plate from
    it, so the panel stays put and the plan says why."""
    from vdo.state import with_exposure

    path = write_plate_experiment(tmp_path, spacing=20)
    path.write_text(path.read_text() + PANEL.format(x=0.3) + 'mount = "in_view"\n' + """
[[mount]]
name = "in_view"
kind = "rail"
control_points_m = [[-0.1, 0.0, 0.9], [0.1, 0.0, 0.9]]

[exposure]
free = ["light_positions"]
""")
    exp = config.load(path)
    placed, plan = with_exposure(exp)
    assert plan.moved == ()
    assert np.array_equal(placed.lights[0].position, exp.lights[0].position)
    assert any("stands in a camera's view" in p for p in plan.problems), plan.problems
