"""The DIC render mode's surface light map (`vdo.rendering.lightmap`): its interpolated light
against the light computed at every pixel and against closed forms (a panel's form factor, an
open sky); renders with it against renders without it (every light-map node computed for the
camera) on the built-in experiment and on the curved pressure vessel; one map shared by the
cameras of a frame (the same images in any order, fewer nodes for the second camera) and by a
load step whose surface moved by micrometres. Against Mitsuba's own sampled renders: the DIC
mode renders with a map by default, so tests/test_render_dic.py's per-pixel comparisons with
256-spp renders hold for it too."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_render import down_camera, light, table  # noqa: E402
from test_render_dic import penumbra_plate, plate, rectangle_form_factor  # noqa: E402

from conftest import mesh_tables, region_tables  # noqa: E402
from vdo import scene  # noqa: E402
from vdo.config import experiment as config  # noqa: E402
from vdo.render import build_dic_scene, render_camera_dic, scaled_camera, surface_light_map  # noqa: E402
from vdo.scene import cameras_of  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
FORM_TOL = 3e-3          # relative: the map's linear interpolation of a panel's form factor (measured 1.75e-3)
SKY_RTOL = 1e-5          # an open sky: the same light at every node, interpolated exactly
RENDER_STD_TOL = 5e-4    # a render with the map against one without, std of the difference
                         # (linear radiance; the DIC mode's own error against 256-spp renders is
                         # 0.0007-0.0023 on the built-in's windows, a 16-spp render's 0.002-0.003)
RENDER_MAX_TOL = 0.03    # ... and the largest difference (a shadow edge's pixel)
SKY_STD_TOL = 2.5e-3     # the same on the pressure vessel's shell, lit mostly by its sky (ambient 1.2,
                         # 64 directions a point, both maps interpolate that quadrature): measured
                         # 0.0016 there, where against the mean of two 256-spp renders the map errs
                         # 0.00800, the render without it 0.00805 and a 16-spp render 0.0131
ORDER_TOL = 1e-5         # two orders of rendering a frame's cameras (float32 sums of ~100 terms)
STEP_TOL = 1e-3          # of the light scale: a load step's surface moved by micrometres, the map
                         # of step 0 against the map of the step itself


def dic_scene(exp, posed=None):
    meshes = scene.load_meshes(**mesh_tables(exp))
    full = cameras_of(exp.camera_specs, exp.rails)
    bodies = [scene.camera_body(c) for c, s in zip(full, exp.camera_specs) if s.body]
    faces = scene.all_region_faces(meshes, **region_tables(exp))
    return build_dic_scene(exp, meshes, faces, bodies, None, posed(meshes) if posed else None), full


def every_pixel(ds, cam, light_map):
    """(exact light at every pixel, the map's light (NaN where not ok), the camera's light scale)."""
    from vdo.rendering import dic, shading

    v, u = np.mgrid[: cam.height, : cam.width]
    grid = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    mapped = replace(ds, light_map=light_map)
    si, prim_uv = dic._cast(mapped, cam, grid, barycentric=True)
    scale = dic._light_scale(ds, cam)
    value, ok = light_map.lookup(mapped, si, prim_uv, scale, cam.focal_px)
    exact = shading.shade(ds, si)
    return exact, np.where(ok, value, np.nan), scale


def test_the_surface_map_follows_the_light_computed_at_every_pixel(plate_experiment):
    """The map's light against `vdo.rendering.shading.shade` at every pixel of a plate at 50°
    with a panel's penumbra, a bar's shadow and silhouette and a 12-sided prism (creases): every
    pixel it interpolates within MAP_TOLERANCE x the light scale, on average within SHADE_ERROR x
    it; it interpolates most pixels; and the whole render within RENDER_STD_TOL of the render
    without the map (every node of the camera's light map computed)."""
    from vdo.rendering import dic, lightmap

    exp = penumbra_plate(plate_experiment)
    ds, (cam,) = dic_scene(exp)
    light_map = surface_light_map(ds, [cam])
    exact, mapped, scale = every_pixel(ds, cam, light_map)
    ok = np.isfinite(mapped)
    err = np.abs(mapped[ok] - exact[ok])
    print(f"surface map: {ok.mean():.3f} of the pixels, max {err.max() / scale:.2e}, mean "
          f"{err.mean() / scale:.2e} of the light scale; {light_map.computed} nodes")
    assert ok.mean() > 0.6        # measured 0.73: the rest is sky, penumbra and shadow edges
    assert err.max() <= lightmap.MAP_TOLERANCE * scale
    assert err.mean() <= dic.SHADE_ERROR * scale
    with_map = render_camera_dic(ds, cam, light_map=light_map).astype(float)
    without = render_camera_dic(ds, cam, light_map=False).astype(float)
    d = with_map - without
    print(f"render with the map - without: std {d.std():.2e}, max {np.abs(d).max():.2e}")
    assert d.std() <= RENDER_STD_TOL and np.abs(d).max() <= RENDER_MAX_TOL


def test_the_maps_light_read_in_the_render_kernel_is_its_lookup(plate_experiment):
    """`SurfaceLightMap.filled` (the map's light scheduled in a tile's kernel, `render_camera_dic`)
    against `finish` (the lookup that computes the nodes it lacks) on the penumbra plate: on a
    fresh map every hit the map serves is `missing` and none has light; on a map filled from
    half the image, the other half's new blocks and nodes are missing; once the whole image
    was looked up, none is missing and the light is the lookup's, NaN where it is NaN."""
    import drjit as dr

    from vdo.core.backend import mitsuba
    from vdo.rendering import dic

    mi = mitsuba()
    exp = penumbra_plate(plate_experiment)
    ds, (cam,) = dic_scene(exp)
    light_map = surface_light_map(ds, [cam])
    mapped = replace(ds, light_map=light_map)
    v, u = np.mgrid[: cam.height, : cam.width]
    grid = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    si, prim_uv = dic._cast(mapped, cam, grid, barycentric=True)
    prepared = light_map.prepare(mapped, si, prim_uv)
    dr.eval(prepared)
    scale = dic._light_scale(ds, cam)

    def filled():
        light, missing = light_map.filled(mapped, prepared, scale, cam.focal_px)
        dr.eval(light, missing)
        return np.array(light), np.array(missing)
    served = np.array(prepared[0]) != 0xFFFFFFFF
    light, missing = filled()
    assert missing.any() and not missing[~served].any() and not np.isfinite(light).any()
    top = np.arange(len(grid)) < len(grid) // 2
    light_map.finish(mapped, tuple(dr.gather(type(a), a, dr.compress(mi.Bool(top))) for a in prepared),
                     scale, cam.focal_px)
    light, missing = filled()
    assert missing[~top].any() and not missing[top].any()
    value, ok = light_map.finish(mapped, prepared, scale, cam.focal_px)
    light, missing = filled()
    assert not missing.any()
    assert np.array_equal(np.isfinite(light), ok) and ok.mean() > 0.5
    assert light[ok] == pytest.approx(value[ok], rel=1e-6)


def test_the_surface_map_gives_a_panels_closed_form_and_an_open_sky(plate_experiment):
    """A white Lambertian plate under a parallel panel (no sky): the map's light is L F, F the
    form factor to the rectangle (closed form), within FORM_TOL at every pixel; under an open sky
    alone (no panel) it is the ambient radiance, to SKY_RTOL."""
    height, size, radiance = 0.5, (0.3, 0.2), 20.0
    cam_text = down_camera("c", [0.6, -0.1, 0.3], (64, 48), 20.0, 12, target=[0.05, 0.02, 0.0])
    exp = plate(plate_experiment, cam_text, light("p", [0.0, 0.0, height], [0.0, 0.0, 0.0], list(size),
                                                  radiance), ambient=0.0, bar=False)
    ds, (cam,) = dic_scene(exp)
    light_map = surface_light_map(ds, [cam])
    _, mapped, _ = every_pixel(ds, cam, light_map)
    ok = np.isfinite(mapped)
    from vdo.rendering import dic

    v, u = np.mgrid[: cam.height, : cam.width]
    si = dic._cast(ds, cam, np.column_stack([u.ravel(), v.ravel()]).astype(float))
    p = np.column_stack([np.array(si.p[k], dtype=float) for k in range(3)])
    centre, e1, e2, normal, L = ds.lights[0]
    d = p - centre
    s1, s2 = d @ e1 / np.linalg.norm(e1), d @ e2 / np.linalg.norm(e2)
    w, h = np.linalg.norm(e1), np.linalg.norm(e2)
    x1, x2, y1, y2 = -w / 2 - s1, w / 2 - s1, -h / 2 - s2, h / 2 - s2
    F = sum(sign * rectangle_form_factor(a, b, height) for a, b, sign in
            ((x2, y2, 1), (x1, y2, -1), (x2, y1, -1), (x1, y1, 1)))
    rel = np.abs(mapped[ok] / (L * F[ok]) - 1)
    print(f"map against the form factor: {ok.mean():.3f} of the pixels, max {rel.max():.2e}, "
          f"{light_map.computed} nodes")
    assert ok.mean() > 0.5 and rel.max() < FORM_TOL

    ambient = 0.05
    exp = plate(plate_experiment, down_camera("c", [0.1, -0.05, 0.8], (32, 24), 20.0, 12),
                ambient=ambient, bar=False)
    ds, (cam,) = dic_scene(exp)
    _, mapped, _ = every_pixel(ds, cam, surface_light_map(ds, [cam]))
    assert np.isfinite(mapped).all() and np.allclose(mapped, ambient, rtol=SKY_RTOL)


def window(camera, width, height, at):
    """The camera's window of width x height pixels whose top-left pixel is `at` (same pose and
    focal length: a full-size render's pixels)."""
    cx, cy = camera.principal_point
    return replace(camera, width=width, height=height,
                   principal_offset_px=(cx - at[0] - (width - 1) / 2, cy - at[1] - (height - 1) / 2),
                   position=np.asarray(camera.position, dtype=float))


@pytest.mark.parametrize("config_path, camera, at, std_tol", [
    ("experiments/beam_column/ten_cameras.toml", 0, (2800, 1850), RENDER_STD_TOL),   # the joint's speckle
    ("experiments/beam_column/ten_cameras.toml", 0, (500, 3000), RENDER_STD_TOL),    # a shadow, dark parts
    ("experiments/pressure_vessel/all_round.toml", 0, (1100, 900), SKY_STD_TOL)])    # the curved shell
def test_renders_with_the_surface_map_match_the_renders_without(config_path, camera, at, std_tol):
    """Windows of full-size cameras of the built-in experiment and of the curved pressure vessel
    (300 x 200 px, the map laid out for the whole camera) with the map against the render
    without it (every node of the camera's light map computed): within RENDER_STD_TOL per pixel
    (std; SKY_STD_TOL on the sky-lit shell) and RENDER_MAX_TOL at most."""
    exp = config.load(ROOT / config_path)
    ds, full = dic_scene(exp)
    spec = exp.camera_specs[camera]
    light_map = surface_light_map(ds, [full[camera]])
    cam = window(full[camera], 300, 200, at)
    with_map = render_camera_dic(ds, cam, spec=spec, light_map=light_map).astype(float)
    without = render_camera_dic(ds, cam, spec=spec, light_map=False).astype(float)
    d = with_map - without
    print(f"{config_path} {cam.name} at {at}: with the map - without: std {d.std():.2e}, max "
          f"{np.abs(d).max():.2e} (image std {without.std():.3f}); {light_map.computed} nodes")
    assert light_map.computed > 0
    assert d.std() <= std_tol and np.abs(d).max() <= RENDER_MAX_TOL


def test_one_map_serves_the_cameras_of_a_frame_in_any_order(plate_experiment):
    """Two cameras of the plate with a panel and a bar sharing one map: the same images whichever
    renders first (a node's light does not depend on the camera that asked for it), and the second
    camera computes fewer nodes than it does alone (they see the same plate)."""
    cams_text = (down_camera("a", [0.05, -0.3, 0.6], (160, 120), 20.0, 25, target=[0.0, 0.0, 0.0])
                 + down_camera("b", [-0.2, 0.25, 0.7], (160, 120), 20.0, 25, target=[0.02, 0.0, 0.0]))
    exp = plate(plate_experiment, cams_text, light("p", [0.5, 0.2, 0.8], [0, 0, 0], [0.3, 0.2], 20))
    ds, cams = dic_scene(exp)
    first = surface_light_map(ds, cams)
    a0 = render_camera_dic(ds, cams[0], light_map=first)
    alone = first.computed
    b0 = render_camera_dic(ds, cams[1], light_map=first)
    second_shared = first.computed - alone
    other = surface_light_map(ds, cams)
    b1 = render_camera_dic(ds, cams[1], light_map=other)
    second_alone = other.computed
    a1 = render_camera_dic(ds, cams[0], light_map=other)
    print(f"nodes: first camera {alone}, the second after it {second_shared}, alone {second_alone}")
    # the same up to float32 sums of the shadow rays (Dr.Jit's scatter-add), whose batches differ
    assert np.abs(a0 - a1).max() <= ORDER_TOL and np.abs(b0 - b1).max() <= ORDER_TOL
    assert second_shared < 0.5 * second_alone


def test_a_load_steps_micrometres_leave_the_map_of_step_0_valid(plate_experiment):
    """The plate bent by up to 20 µm (a load step; the bar and the panel stay): the map of the
    rest geometry (its lattices follow the mesh, so its nodes move with the surface) against a map
    computed on the bent plate, at every pixel both interpolate: within STEP_TOL of the light
    scale; and the renders with either map within RENDER_STD_TOL."""
    exp = plate(plate_experiment, down_camera("c", [0.05, -0.3, 0.6], (160, 120), 20.0, 25,
                                              target=[0.0, 0.0, 0.0]),
                light("p", [0.5, 0.2, 0.8], [0, 0, 0], [0.3, 0.2], 20))

    def bent(meshes):
        out = []
        for m in meshes:
            if m.role == "specimen":
                x = m.vertices[:, 0]
                m = replace(m, vertices=m.vertices + np.column_stack(
                    [0 * x, 0 * x, 20e-6 * (x - x.min()) / max(np.ptp(x), 1e-9)]))
            out.append(m)
        return out

    rest, (cam,) = dic_scene(exp)
    moved, _ = dic_scene(exp, bent)
    frame = surface_light_map(rest, [cam])
    render_camera_dic(rest, cam, light_map=frame)                   # step 0 fills the map
    computed = frame.computed
    _, shared, scale = every_pixel(moved, cam, frame)
    fresh_map = surface_light_map(moved, [cam])
    _, fresh, _ = every_pixel(moved, cam, fresh_map)
    both = np.isfinite(shared) & np.isfinite(fresh)
    err = np.abs(shared[both] - fresh[both])
    print(f"step map against its own: {both.mean():.3f} of the pixels, max {err.max() / scale:.2e} of the "
          f"light scale; the step computed {frame.computed - computed} new nodes")
    assert both.mean() > 0.5 and err.max() <= STEP_TOL * scale
    d = (render_camera_dic(moved, cam, light_map=frame).astype(float)
         - render_camera_dic(moved, cam, light_map=fresh_map))
    assert d.std() <= RENDER_STD_TOL


def test_a_step_that_moves_a_group_by_millimetres_gets_a_map_of_its_own():
    """`map_holds`: the same meshes within MAP_REUSE_M serve one map; a vertex moved farther (a
    rigid motion of the built-in's hexapod by millimetres) or another mesh does not."""
    from vdo.render import map_holds
    from vdo.rendering.lightmap import MAP_REUSE_M
    from vdo.scene import SceneMesh

    v = np.random.default_rng(1).random((10, 3))
    f = np.array([[0, 1, 2], [3, 4, 5]])
    rest = [SceneMesh("a", "specimen", v, f), SceneMesh("b", "obstacle", v + 1, f)]
    near = [replace(rest[0], vertices=v + 0.9 * MAP_REUSE_M), rest[1]]
    far = [replace(rest[0], vertices=v + [0.005, 0.0, 0.0]), rest[1]]
    assert map_holds(rest, rest) and map_holds(rest, near)
    assert not map_holds(rest, far) and not map_holds(rest, rest[:1])
    assert not map_holds(rest, [rest[0], replace(rest[1], name="c")])
