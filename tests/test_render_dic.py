"""The DIC render mode (`vdo.render.render_camera_dic`): the summed-area table's box averages
against a fine quadrature of the bilinear texture; per pixel against today's sampled mode at
high spp (within the reference's own sampling noise where the light is smooth, and below a
16-spp render's noise everywhere, penumbra and silhouettes included), with a tilted, rolled
camera and with lens distortion; the contrast and gradient energy of a frontal render against
the σ model's pixel-averaged speckle."""

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_render import down_camera, light, table  # noqa: E402

from vdo import scene  # noqa: E402
from vdo.config import experiment as config  # noqa: E402
from vdo.core.errors import ConfigError  # noqa: E402
from vdo.dic.images import SplineImage  # noqa: E402
from vdo.model.speckle import (gradient_energy_table, g_iso_lookup, normalise,  # noqa: E402
                               pattern_for, pixel_averaged_std)
from vdo.render import (SpeckleTable, build_dic_scene, build_render_scene, render_camera,  # noqa: E402
                        render_camera_dic, render_settings)
from conftest import mesh_tables, region_tables  # noqa: E402
from vdo.scene import cameras_of

FINE = 400                  # midpoints per axis of the reference quadrature of one box
QUADRATURE_TOL = 2e-5       # its error: the bilinear texture's kinks, O(1 / FINE^2) of the contrast
NOISE_RATIO = 1.5           # fast - reference within this many times the reference's own noise
REFERENCE_SPP = 256
CONTRAST_TOL = 0.01         # relative: the σ model's box-pixel contrast (same integral, exact)
TILE_TOL = 1e-4             # tiles against one: light-map interpolation within SHADE_TOLERANCE
FORM_FACTOR_TOL = 1e-5      # relative: the lit panels' Gauss-Legendre rule against the closed form
                            # (measured 1.8e-6, float32; one point a panel: 8.6e-2)
PROBE_TOL = 1e-6            # of the light scale: the probed light against a ray per panel point
                            # (measured equal to float32 rounding on the penumbra scene)
PART_TOL = 1e-4             # a footprint part's mean: float32 weights of 0.002-texel boxes (6e-5
                            # measured), against the summed-area table in float64
ENERGY_TOL = 0.02           # relative: the 64-spp reference's noise adds ~0.5 % of gradient energy


def bilinear_box_mean(pattern, x0, x1, y0, y1):
    """Midpoint rule of the texture as Mitsuba samples it (texel centres at i + ½, bilinear,
    periodic) over the box, in texels."""
    xs = x0 + (np.arange(FINE) + 0.5) / FINE * (x1 - x0)
    ys = y0 + (np.arange(FINE) + 0.5) / FINE * (y1 - y0)
    X, Y = np.meshgrid(xs, ys)
    return ndimage.map_coordinates(pattern, [Y - 0.5, X - 0.5], order=1, mode="grid-wrap").mean()


def test_summed_area_table_gives_the_box_average_of_the_bilinear_texture():
    rng = np.random.default_rng(4)
    pattern = rng.random((16, 24))
    sat = SpeckleTable.of(pattern, pad=8)
    boxes = [(1.2, 3.7, 2.1, 2.9), (-3.3, -1.0, 15.2, 18.9), (100.3, 101.0, -40.2, -39.9),
             (5.0, 5.001, 7.3, 7.301), (20.5, 27.25, 3.0, 9.5)]
    for box in boxes:
        assert sat.box_average(*box) == pytest.approx(bilinear_box_mean(pattern, *box), abs=QUADRATURE_TOL)


def test_footprint_parts_are_the_box_averages_of_the_bilinear_texture_in_every_tier():
    """`part_means` (Dr.Jit: K x K texels for small boxes, the summed-area table for the rest)
    against `SpeckleTable.box_average` (numpy, checked against quadrature above) on footprints
    from 0.001 to 40 texels, rotated and sheared, centred anywhere (the texture is periodic);
    each of DIRECT_TAPS's tiers and the table get lanes."""
    import drjit as dr

    from vdo.core.backend import mitsuba
    from vdo.rendering.footprint import DIRECT_TAPS, FOOTPRINT_SPLIT, MIN_HALF_TEXELS, part_means

    mi = mitsuba()
    rng = np.random.default_rng(7)
    pattern = rng.random((40, 56))
    table = SpeckleTable.of(pattern, pad=32)
    m = 4000
    x, y = rng.uniform(-300, 300, (2, m))
    size = np.exp(rng.uniform(np.log(1e-3), np.log(40), m))
    a = size[:, None] * rng.normal(size=(m, 2)) / np.sqrt(2)
    b = size[:, None] * rng.normal(size=(m, 2)) / np.sqrt(2)
    a, b = a * np.minimum(1, 26 / (np.abs(a) + np.abs(b)).max(axis=1))[:, None], \
        b * np.minimum(1, 26 / (np.abs(a) + np.abs(b)).max(axis=1))[:, None]      # within the pad
    means = part_means(table, mi.Float64(x), mi.Float64(y), *(mi.Float(c.astype(np.float32))
                                                                for c in (a[:, 0], a[:, 1], b[:, 0], b[:, 1])))
    dr.eval(means)
    n = FOOTPRINT_SPLIT
    a32, b32 = a.astype(np.float32).astype(float), b.astype(np.float32).astype(float)
    hx = np.maximum(0.5 * np.hypot(a32[:, 0], b32[:, 0]) / n, MIN_HALF_TEXELS)
    hy = np.maximum(0.5 * np.hypot(a32[:, 1], b32[:, 1]) / n, MIN_HALF_TEXELS)
    width = 2 * np.maximum(hx, hy)
    tiers = np.searchsorted(np.array(DIRECT_TAPS) - 2, width)       # K - 2 >= width: that tier
    assert all(np.any(tiers == k) for k in range(len(DIRECT_TAPS) + 1))
    for k, mean in enumerate(means):
        i, j = divmod(k, n)
        oi, oj = (i + 0.5) / n - 0.5, (j + 0.5) / n - 0.5
        cx, cy = x + oi * a32[:, 0] + oj * b32[:, 0], y + oi * a32[:, 1] + oj * b32[:, 1]
        expected = table.box_average(cx - hx, cx + hx, cy - hy, cy + hy)
        assert np.array(mean) == pytest.approx(expected, abs=PART_TOL)


def plate(plate_experiment, camera_text, light_text="", ambient=0.05, bar=True, dot_mm=1.5):
    text = (camera_text + light_text
            + table("speckle", dot_diameter_mm=dot_mm, texel_mm=dot_mm / 15, tile_texels=512)
            + table("render", ambient_radiance=ambient))
    files, extra = (), ""
    if bar:
        files = [("bar.stl", [20, 300, 20], [60, 0, 30])]
        extra = '[[mesh]]\nname = "bar"\nfile = "bar.stl"\nrole = "obstacle"\nunit = "mm"\n'
    return config.load(plate_experiment(cameras=text, files=files, extra_meshes=extra))


def renders(exp, spp=REFERENCE_SPP):
    meshes = scene.load_meshes(**mesh_tables(exp))
    rf = scene.all_region_faces(meshes, **region_tables(exp))
    pattern = pattern_for(exp.speckle)
    cam, spec = cameras_of(exp.camera_specs, exp.rails)[0], exp.camera_specs[0]
    fast = render_camera_dic(build_dic_scene(exp, meshes, rf, (), pattern), cam, spec=spec)
    sc = build_render_scene(exp, meshes, rf, (), pattern)
    a, b = (render_camera(sc, cam, spec, spp, seed).astype(float) for seed in (1, 2))
    return fast.astype(float), (a + b) / 2, np.std(a - b) / 2     # noise of the mean of two


@pytest.mark.parametrize("distortion", [None, [-0.12, 0.05, 0.002, -0.001, 0.0]])
def test_dic_mode_matches_the_sampled_mode_per_pixel(plate_experiment, distortion):
    """A camera 0.6 m away looking down at 50°, rolled by the look-at aim; a panel casts the
    shadow of a bar (penumbra, silhouette) on the speckled plate; an ambient sky. With lens
    distortion the sampled mode resamples a pinhole render with a cubic spline (not the box
    integral over the distorted pixel), so there the dots are 4 mm (~6 px) and the spline's
    interpolation error stays below the sampling noise."""
    cam_text = down_camera("c", [0.05, -0.3, 0.6], (240, 160), 20.0, 25, target=[0.0, 0.0, 0.0])
    if distortion is not None:
        cam_text += f"distortion = {distortion}\n"
    exp = plate(plate_experiment, cam_text, light("p", [0.5, 0.2, 0.8], [0, 0, 0], [0.3, 0.2], 20),
                dot_mm=1.5 if distortion is None else 4.0)
    fast, ref, noise = renders(exp, REFERENCE_SPP if distortion is None else 64)
    d = fast - ref
    lit = d[5:-5, 5:100]                       # left of the bar's penumbra: smooth light
    assert np.std(lit) <= NOISE_RATIO * noise
    assert abs(np.mean(lit)) <= 0.005 * ref[5:-5, 5:100].mean()     # the light level, 0.5 %
    # Everywhere, penumbra and silhouette included: below the noise of one 16-spp render.
    noise16 = noise * np.sqrt(2) * np.sqrt((REFERENCE_SPP if distortion is None else 64) / 16)
    assert np.std(d) < noise16


@pytest.mark.parametrize("focal_mm", [50, 200])
def test_dic_mode_contrast_and_gradient_energy(plate_experiment, focal_mm):
    """Straight down, a uniform sky only (ρ L everywhere), 0.2 and 0.05 mm per pixel on 0.1 mm
    texels: the image is ρ L of the box-averaged texture. Its contrast is the σ model's box-pixel
    factor (`pixel_averaged_std`, the same integral). Its gradient energy per direction (the
    cubic spline's gradient that the correlation uses) is the sampled mode's at 64 spp; the σ
    model's g_f(p / √12) (`gradient_energy_table`, the pattern's spectrum without the bilinear
    texture filter) is 1.3-1.5x both, printed here and in docs/render.md, not asserted."""
    exp = plate(plate_experiment, down_camera("c", [0.01, 0.02, 0.5], (300, 300), 20.0, focal_mm),
                ambient=1.0, bar=False)
    fast, sampled, _ = renders(exp, 64)
    sp = exp.speckle
    pattern = pattern_for(exp.speckle)
    f_hat = normalise(pattern)
    p = 0.5 / cameras_of(exp.camera_specs, exp.rails)[0].focal_px                    # m per pixel on the plate

    def albedo(image):
        return (image[10:-10, 10:-10] / exp.render.ambient_radiance - sp.black_albedo) / (
            sp.white_albedo - sp.black_albedo)

    def energy(image):
        a = albedo(image) / pattern.std()
        grid = np.stack(np.meshgrid(np.arange(a.shape[1], dtype=float),
                                    np.arange(a.shape[0], dtype=float)), -1)
        return 0.5 * np.mean(np.sum((SplineImage(a).gradient(grid) / p) ** 2, axis=-1))

    factor = pixel_averaged_std(f_hat, sp.texel, np.diag([p, p])[None])[0]
    assert albedo(fast).std() / pattern.std() == pytest.approx(factor, rel=CONTRAST_TOL)
    assert energy(fast) == pytest.approx(energy(sampled), rel=ENERGY_TOL)
    model = float(g_iso_lookup(gradient_energy_table(f_hat, sp.texel), p / np.sqrt(12)))
    print(f"gradient energy at {p * 1e3:.3f} mm/px: dic {energy(fast):.4g}, sampled "
          f"{energy(sampled):.4g}, sigma model {model:.4g} 1/m^2")


def test_bad_render_settings_name_the_field_and_the_fix(plate_experiment):
    exp = plate(plate_experiment, down_camera("c", [0, 0, 0.5], (64, 48), 20.0, 25), bar=False)
    for kwargs, field in (({"mode": "fast"}, "mode"), ({"scale": 0.0}, "--scale"),
                          ({"spp": 0}, "--spp"), ({"scale": -1.0}, "--scale")):
        with pytest.raises(ConfigError, match=field) as err:
            render_settings(exp, **kwargs)
        assert "\n" not in str(err.value) and "must" in str(err.value)
    text = (down_camera("c", [0, 0, 0.5], (64, 48), 20.0, 25) + "f_number = 8\nfocus_m = 0.5\n"
            + table("render", mode="dic"))
    exp = config.load(plate_experiment(cameras=text))
    with pytest.raises(ConfigError, match="f_number.*depth of field"):
        render_settings(exp)
    (Path(exp.path).parent / "bad.toml").write_text(Path(exp.path).read_text().replace(
        'mode = "dic"', 'mode = "fast"'))
    with pytest.raises(ConfigError, match="mode.*sampled, dic"):
        config.load(Path(exp.path).parent / "bad.toml")


def test_a_render_that_does_not_fit_is_split_or_refused_before_rendering(plate_experiment, monkeypatch):
    """The plan is made from the cameras alone (bytes per pixel measured, `vdo.render`): the DIC
    mode splits its tiles to fit, and a render whose images alone do not fit is refused with the
    size it needs, naming [render] scale."""
    from vdo.render import CELL_BYTES_PER_PIXEL, IMAGE_BYTES_PER_PIXEL, MIN_TILE_PIXELS, TILE_PIXELS, \
        plan_render, render_images, scaled_camera

    exp = plate(plate_experiment, down_camera("c", [0, 0, 0.5], (6000, 4000), 3.45, 25), bar=False)
    cams = cameras_of(exp.camera_specs, exp.rails)
    kept = 6000 * 4000 * IMAGE_BYTES_PER_PIXEL
    roomy = plan_render(cams, "dic", available=8 * 2 ** 30)
    assert roomy.tile_pixels == TILE_PIXELS and roomy.kept == kept
    cells = 6000 * 4000 * CELL_BYTES_PER_PIXEL          # the lens's cells of the whole camera
    tight = plan_render(cams, "dic", available=kept + cells + 20 * 2 ** 20)
    assert MIN_TILE_PIXELS <= tight.tile_pixels < TILE_PIXELS and tight.needed <= tight.available
    with pytest.raises(MemoryError, match=r"needs 0\.\d+ GiB"):
        plan_render(cams, "dic", available=kept // 2)
    with pytest.raises(MemoryError):
        plan_render(cams, "sampled", available=kept + 20 * 2 ** 20)
    # Through render_images: refused before any geometry work, one line naming the field.
    monkeypatch.setattr("vdo.rendering.dic.available_memory", lambda: kept)
    with pytest.raises(ConfigError, match=r"\[render\] scale.*GiB.*lower scale") as err:
        render_images(exp, scale=1.0)
    assert "\n" not in str(err.value)
    monkeypatch.undo()
    # Tiles: the same image in 1 tile or in tiles of 16 rows (light-map nodes restart per tile).
    small = scaled_camera(cams[0], 0.04)
    meshes = scene.load_meshes(**mesh_tables(exp))
    ds = build_dic_scene(exp, meshes, scene.all_region_faces(meshes, **region_tables(exp)))
    whole = render_camera_dic(ds, small)
    tiled = render_camera_dic(ds, small, tile_pixels=16 * small.width)
    assert np.abs(tiled - whole).max() <= TILE_TOL * whole.max()




def penumbra_plate(plate_experiment):
    """The plate at 50° to a 320 x 240 camera, lit by a panel whose penumbra crosses it, with a
    bar (a shadow and a silhouette) and a 12-sided prism lying on it (creases every 30°, each
    facet lit differently): the light maps' hard case. Returns the loaded experiment."""
    import trimesh

    cam_text = down_camera("c", [0.05, -0.3, 0.6], (320, 240), 20.0, 25, target=[0.0, 0.0, 0.0])
    path = plate_experiment(
        cameras=cam_text + light("p", [0.5, 0.2, 0.8], [0, 0, 0], [0.3, 0.2], 20)
        + table("speckle", dot_diameter_mm=1.5, texel_mm=0.1, tile_texels=512)
        + table("render", ambient_radiance=0.05),
        files=[("bar.stl", [20, 300, 20], [60, 0, 30])],
        extra_meshes='[[mesh]]\nname = "bar"\nfile = "bar.stl"\nrole = "obstacle"\nunit = "mm"\n'
                     '[[mesh]]\nname = "prism"\nfile = "prism.stl"\nrole = "obstacle"\nunit = "mm"\n')
    prism = trimesh.creation.cylinder(radius=40, height=300, sections=12)
    prism.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    prism.apply_translation([-60, 0, 40])
    prism.export(Path(path).parent / "prism.stl")
    return config.load(path)


def test_the_adaptive_light_map_follows_the_light_computed_at_every_pixel(plate_experiment):
    """The light map (`vdo.rendering.dic._light_map`: nodes every SHADE_STRIDE px, refined where
    the light bends, the shape changes or a crease passes) against `vdo.rendering.shading.shade` cast at every pixel,
    on a plate at 50° with a panel's penumbra, a bar's silhouette and a 12-sided prism lying on
    the plate (creases every 30°, each facet lit differently). Every pixel within the map's
    acceptance bound SHADE_TOLERANCE x the light scale; the mean error within SHADE_ERROR x it."""
    from vdo.rendering import dic, shading

    exp = penumbra_plate(plate_experiment)
    meshes = scene.load_meshes(**mesh_tables(exp))
    ds = build_dic_scene(exp, meshes, scene.all_region_faces(meshes, **region_tables(exp)))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    v, u = np.mgrid[: cam.height, : cam.width]
    grid = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    si = dic._cast(ds, cam, grid)
    ids = np.array(dic._shape_ids(si)).reshape(cam.height, cam.width)
    exact = shading.shade(ds, si).reshape(cam.height, cam.width)
    scale = dic._light_scale(ds, cam)
    normals = (np.array(si.sh_frame.n[k]).reshape(cam.height, cam.width) for k in range(3))
    mapped = dic._light_map(ds, cam, 0, dic._LightNodes.lattice(ids, normals), scale)
    err = np.abs(mapped - exact)
    assert len(np.unique(ids)) >= 3                       # plate, bar, prism
    assert err.max() <= dic.SHADE_TOLERANCE * scale
    assert err.mean() <= dic.SHADE_ERROR * scale
    print(f"light map against every pixel: max {err.max() / scale:.2e}, mean {err.mean() / scale:.2e} "
          f"of the light scale")
    # The probes (`PROBE_GRID`): the light with a shadow ray for every panel point, every pixel.
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(shading, "PROBE_GRID", tuple(range(shading.LIGHT_POINTS)))
        every_ray = shading.shade(ds, si).reshape(cam.height, cam.width)
    shaded = (every_ray > 0.05 * scale) & (every_ray < 0.95 * every_ray.max())
    assert shaded.sum() > 100               # neither dark nor fully lit: shadow edges and shading
    assert np.abs(exact - every_ray).max() <= PROBE_TOL * scale


def rectangle_form_factor(a, b, c):
    """The form factor from a differential area to a parallel rectangle a x b at distance c with
    one corner straight above it (Howell's catalogue, C-12): (1 / 2π) [A / √(1 + A²) atan(B /
    √(1 + A²)) + B / √(1 + B²) atan(A / √(1 + B²))], A = a / c, B = b / c; signed with a and b
    so that rectangles add up."""
    A, B = np.abs(a) / c, np.abs(b) / c
    F = (A / np.sqrt(1 + A * A) * np.arctan(B / np.sqrt(1 + A * A))
         + B / np.sqrt(1 + B * B) * np.arctan(A / np.sqrt(1 + B * B))) / (2 * np.pi)
    return np.sign(a) * np.sign(b) * F


def test_a_lit_panel_gives_the_closed_form_irradiance(plate_experiment):
    """A white Lambertian plate under a parallel panel of radiance L, nothing between them: the
    light each hit reflects (`vdo.rendering.shading.shade`) is L F, F the differential-area form
    factor to the rectangle (four corner rectangles of the closed form, signed), at every pixel,
    within FORM_FACTOR_TOL of it; every panel there is lit, so this is the lit panels' quadrature."""
    from vdo.rendering import dic, shading

    height, size, radiance = 0.5, (0.3, 0.2), 20.0
    cam_text = down_camera("c", [0.6, -0.1, 0.3], (64, 48), 20.0, 12, target=[0.05, 0.02, 0.0])
    exp = plate(plate_experiment, cam_text, light("p", [0.0, 0.0, height], [0.0, 0.0, 0.0], list(size),
                                                  radiance), ambient=0.0, bar=False)
    meshes = scene.load_meshes(**mesh_tables(exp))
    ds = build_dic_scene(exp, meshes, scene.all_region_faces(meshes, **region_tables(exp)))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    v, u = np.mgrid[: cam.height, : cam.width]
    si = dic._cast(ds, cam, np.column_stack([u.ravel(), v.ravel()]).astype(float))
    p = np.column_stack([np.array(si.p[k], dtype=float) for k in range(3)])
    assert np.all(np.array(si.is_valid())) and np.allclose(p[:, 2], 0.0, atol=1e-6)
    centre, e1, e2, normal, L = ds.lights[0]
    assert np.allclose(normal, [0, 0, -1])
    d = p - centre                          # the point in the panel's frame
    s1, s2 = d @ e1 / np.linalg.norm(e1), d @ e2 / np.linalg.norm(e2)
    w, h = np.linalg.norm(e1), np.linalg.norm(e2)
    x1, x2, y1, y2 = -w / 2 - s1, w / 2 - s1, -h / 2 - s2, h / 2 - s2
    F = sum(sign * rectangle_form_factor(a, b, height) for a, b, sign in
            ((x2, y2, 1), (x1, y2, -1), (x2, y1, -1), (x1, y1, 1)))
    light_value = shading.shade(ds, si)
    assert np.abs(light_value / (L * F) - 1).max() < FORM_FACTOR_TOL


def test_an_open_sky_gives_the_ambient_radiance_times_the_albedo(plate_experiment):
    """No light, an ambient sky of radiance L_amb and nothing above a white Lambertian plate:
    every one of the AMBIENT_POINTS^2 ambient directions escapes, and the light each hit reflects
    is L_amb ρ = L_amb exactly (the cosine-weighted hemisphere's integral of ρ / π cosθ)."""
    from vdo.rendering import dic, shading

    ambient = 0.05
    exp = plate(plate_experiment, down_camera("c", [0.1, -0.05, 0.8], (32, 24), 20.0, 12),
                ambient=ambient, bar=False)
    meshes = scene.load_meshes(**mesh_tables(exp))
    ds = build_dic_scene(exp, meshes, scene.all_region_faces(meshes, **region_tables(exp)))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    v, u = np.mgrid[: cam.height, : cam.width]
    si = dic._cast(ds, cam, np.column_stack([u.ravel(), v.ravel()]).astype(float))
    assert np.all(np.array(si.is_valid()))
    assert np.allclose(shading.shade(ds, si), ambient, rtol=1e-5)


PIPE_RADIUS_MM, PIPE_AXIS_MM = 160.0, 1200.0   # a pipe along x; a camera level with its axis
EDGE_ROW_RATIO = 0.9        # the edge row's darkest pixel against its neighbour rows' darkest


def faceted_pipe(path, facets=96, cells=120, length_mm=3000.0):
    """A closed ring of `facets` flat strips (open ends), a triangle soup as a CAD export writes
    it, with a vertex row at (y, z) = (-R, axis height): the side a camera at y < 0 sees edge-on."""
    import trimesh

    phi = 2 * np.pi * np.arange(facets + 1) / facets
    X, P = np.meshgrid(np.linspace(-length_mm / 2, length_mm / 2, cells + 1), phi, indexing="ij")
    grid = np.stack([X, -PIPE_RADIUS_MM * np.cos(P), PIPE_AXIS_MM + PIPE_RADIUS_MM * np.sin(P)], -1)
    a, b, c, d = grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]
    tri = np.concatenate([np.stack([a, b, c], -2), np.stack([a, c, d], -2)]).reshape(-1, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = tri.mean(axis=1) * [0, 1, 1] - [0, 0, PIPE_AXIS_MM]
    flip = np.einsum("ij,ij->i", normal, outward) < 0
    tri[flip] = tri[flip][:, ::-1]
    trimesh.Trimesh(tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3), process=False).export(path)


def test_a_camera_level_with_an_edge_sees_the_near_wall(plate_experiment, tmp_path):
    """A camera level with a faceted pipe's axis: its middle pixel row (the principal point's)
    runs exactly along the edge between two facets. Every primary ray that hits the pipe must hit
    its near side (y < 0: the far wall is hidden by the near one, a closed form), and the DIC
    render's edge row is no darker than its neighbours (a leaked ray saw the far wall from inside,
    in the dark). In Embree's fast mode half of that row's 64 pixels were black (0); in its robust
    mode (`vdo.rendering.dic.DicScene`) none.
    161 rows: (161 - 1) is a multiple of the light map's SHADE_STRIDE, a tile size that crashed."""
    from vdo.rendering import dic

    faceted_pipe(tmp_path / "pipe.stl")
    axis_m = PIPE_AXIS_MM / 1000
    text = (down_camera("c", [0.0, -1.5, axis_m], (64, 161), 34.472, 12, target=[0.0, 0.0, axis_m])
            + light("p", [0.3, -1.0, 1.2], [0, 0, 0.6], [0.3, 0.2], 20) + table("render", ambient_radiance=0.5))
    extra = '[[mesh]]\nname = "pipe"\nfile = "pipe.stl"\nrole = "specimen"\nunit = "mm"\n'
    exp = config.load(plate_experiment(cameras=text, extra_meshes=extra))
    meshes = scene.load_meshes(**mesh_tables(exp))
    ds = build_dic_scene(exp, meshes, scene.all_region_faces(meshes, **region_tables(exp)))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    middle = cam.height // 2
    assert cam.K[1, 2] == middle                            # the middle row's centres lie on the edge
    v, u = np.mgrid[: cam.height, : cam.width]
    si = dic._cast(ds, cam, np.column_stack([u.ravel(), v.ravel()]).astype(float))
    y = np.array(si.p[1]).reshape(cam.height, cam.width)
    on_pipe = np.array(si.is_valid()).reshape(cam.height, cam.width)
    assert on_pipe[middle].all() and not np.any(y[on_pipe] > 0)
    image = render_camera_dic(ds, cam)
    assert image[middle].min() >= EDGE_ROW_RATIO * min(image[middle - 1].min(), image[middle + 1].min())
