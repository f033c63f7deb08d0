"""Renders: reproducible for a seed; sensor noise on the EMVA variance line; speckle dots at their
physical size; the photometric model predicts the render; shadows where the shadow map says; and
the built-in 10-camera experiment renders into a complete run folder."""

import csv
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image
from scipy import ndimage
from scipy.spatial import cKDTree

from vdo import scene
from vdo.config import experiment as config
from vdo.physics import lighting
from vdo.physics import visibility
from vdo.commands.cli import main
from vdo.render import build_render_scene, camera_sensor, expose, render_linear, scaled_camera
from vdo.commands.render import render_experiment
from vdo.model.speckle import pattern_for
from conftest import mesh_tables, region_tables
from vdo.scene import SurfaceSamples, cameras_of

ROOT = Path(__file__).resolve().parent.parent


def down_camera(name, position, pixels, pitch_um, focal_mm, body=False, target=None):
    aim = (f"target_m = {list(target)}" if target is not None else "pan_deg = 0\ntilt_deg = -90")
    return f"""
[[camera]]
name = "{name}"
sensor_width_mm = {pixels[0] * pitch_um * 1e-3}
pixels = {list(pixels)}
focal_mm = {focal_mm}
position_m = {list(position)}
{aim}
body = {str(body).lower()}
"""


def light(name, position, target, size, radiance):
    return f"""
[[light]]
name = "{name}"
position_m = {list(position)}
target_m = {list(target)}
size_m = {list(size)}
radiance = {radiance}
"""


def table(name, **values):
    def fmt(v):
        return str(v).lower() if isinstance(v, bool) else f'"{v}"' if isinstance(v, str) else repr(v)
    return f"\n[{name}]\n" + "".join(f"{k} = {fmt(v)}\n" for k, v in values.items())


def setup(exp, pattern=None):
    meshes = scene.load_meshes(**mesh_tables(exp))
    rf = scene.all_region_faces(meshes, **region_tables(exp))
    return meshes, build_render_scene(exp, meshes, rf, (), pattern)


def pixel_points(cam, z=0.0):
    """World points on the plane z = `z` seen at every pixel centre, (H*W, 3), row-major."""
    v, u = np.mgrid[: cam.height, : cam.width]
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(cam.K).T @ cam.R
    t = (z - cam.position[2]) / rays[:, 2]
    return cam.position + t[:, None] * rays


def plane_samples(points):
    n = len(points)
    return SurfaceSamples(points=points, normals=np.tile([0, 0, 1.0], (n, 1)),
                          tangent_u=np.tile([1.0, 0, 0], (n, 1)), tangent_v=np.tile([0, 1.0, 0], (n, 1)),
                          uv=points[:, :2], area=np.full(n, 1e-6), region=np.zeros(n, int),
                          region_names=("top",), region_importance=np.ones(1))


# --------------------------------------------------------------------------------------------
def test_renders_are_bit_identical_for_a_seed(plate_experiment, tmp_path):
    text = (down_camera("c", [0.0, 0.0, 1.5], (96, 64), 231.25, 24)
            + light("p", [0.5, 0.0, 1.0], [0, 0, 0], [0.3, 0.3], 20)
            + table("speckle", dot_diameter_mm=8.0, texel_mm=1.0, tile_texels=128)
            + table("render", spp=4, seed=3, exr=True, ambient_radiance=0.05))
    exp = config.load(plate_experiment(cameras=text))
    runs = []
    for k, seed in enumerate((None, None, 4)):
        out = tmp_path / f"run{k}"
        render_experiment(exp, out, seed=seed)
        runs.append([(out / "images" / f"c.{ext}").read_bytes() for ext in ("png", "exr")])
    assert runs[0] == runs[1]
    assert runs[0][0] != runs[2][0] and runs[0][1] != runs[2][1]


@pytest.mark.parametrize("mode", ["sampled", "dic"])
def test_the_run_folder_says_which_mode_made_the_images(plate_experiment, tmp_path, monkeypatch, mode):
    """render.json records the mode, and spp and the integrator only where they were used (the
    sampled mode; the dic mode has one ray per pixel); the contact sheet's title names the mode."""
    import vdo.commands.render as command

    text = (down_camera("c", [0.0, 0.0, 1.5], (48, 32), 462.5, 24)
            + table("speckle", dot_diameter_mm=8.0, texel_mm=1.0, tile_texels=128)
            + table("render", spp=4, mode=mode, ambient_radiance=0.5))
    exp = config.load(plate_experiment(cameras=text))
    titles = []
    sheet = command.contact_sheet
    monkeypatch.setattr(command, "contact_sheet", lambda *a, **k: (titles.append(a[3]), sheet(*a, **k)))
    render_experiment(exp, tmp_path / "run")
    written = json.loads((tmp_path / "run" / "render.json").read_text())
    assert written["mode"] == mode
    if mode == "sampled":
        assert (written["spp"], written["integrator"]) == (4, "direct")
        assert titles == [f"{exp.name}: sampled mode, scale 1, 4 spp"]
    else:
        assert "spp" not in written and "integrator" not in written
        assert titles == [f"{exp.name}: dic mode, scale 1"]


def test_flat_field_noise_follows_the_emva_variance_line(plate_experiment):
    """A white plane under a uniform sky (no texture, no panel): radiance ρ L_amb everywhere. At
    each exposure, two independent noise draws: var((A - B)) / 2 is the temporal variance (the
    render's own Monte Carlo pattern cancels), which must lie on K μ + K² σ_r² + 1/12."""
    exp = config.load(plate_experiment(cameras=down_camera("c", [0, 0, 1.5], (128, 96), 185, 50)))
    exp = replace(exp, render=replace(exp.render, ambient_radiance=1.0))
    sensor = exp.sensor
    _, sc = setup(exp, pattern=np.ones((16, 16), np.float32))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    base = render_linear(sc, camera_sensor(cam, exp.camera_specs[0], 4), 0)   # = 0.8 x 1.0
    assert base.mean() == pytest.approx(exp.speckle.white_albedo, rel=2e-3)
    means, variances = [], []
    for k, level in enumerate((0.1, 0.3, 0.5, 0.8)):
        linear = base * (level / exp.speckle.white_albedo)     # ambient L = level / ρ
        a = expose(linear, sensor, 11, 2 * k).astype(float)
        b = expose(linear, sensor, 11, 2 * k + 1).astype(float)
        means.append(0.5 * (a.mean() + b.mean()))
        variances.append(np.var(a - b) / 2)
        assert means[-1] == pytest.approx(sensor.mean_dn(level), rel=5e-3)
    means, variances = np.array(means), np.array(variances)
    np.testing.assert_allclose(variances, sensor.variance_dn(means), rtol=0.05)
    slope, intercept = np.polyfit(means - sensor.offset, variances, 1)
    assert slope == pytest.approx(sensor.gain, rel=0.05)


def test_rendered_dots_have_the_configured_size(plate_experiment):
    """Straight down from Z = 0.5 m with f = 5000 px: 0.1 mm per pixel, 2 mm dots = 20 px."""
    Z, f_px = 0.5, 5000.0
    text = (down_camera("c", [0.1, 0.1, Z], (400, 400), 5.0, 25.0)
            + table("speckle", dot_diameter_mm=2.0, coverage=0.05, strokes=0, texel_mm=0.1,
                    tile_texels=512, seed=5)
            + table("render", ambient_radiance=1.0))
    exp = config.load(plate_experiment(cameras=text))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    assert cam.focal_px == pytest.approx(f_px)
    _, sc = setup(exp)
    image = render_linear(sc, camera_sensor(cam, exp.camera_specs[0], 4), 0)
    sp = exp.speckle
    dark = image < 0.5 * (sp.white_albedo + sp.black_albedo)
    labels, n = ndimage.label(dark)
    sizes = ndimage.sum_labels(dark, labels, np.arange(1, n + 1))
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    keep = np.setdiff1d(np.arange(1, n + 1), edge)
    areas = sizes[keep - 1]
    single = areas[areas < 1.5 * np.median(areas)]            # drop overlapping dots
    assert len(single) >= 15
    diameter_mm = 2 * np.sqrt(single / np.pi) * (Z / f_px) * 1e3
    assert np.mean(diameter_mm) == pytest.approx(2.0, rel=0.02)


def test_photometry_predicts_the_render(plate_experiment):
    """One panel lights a speckled plane seen straight down at 1 mm per pixel; the image spans one
    128 mm tile of 12 mm dots exactly. Per pixel the model gives b and c from the irradiance at the
    pixel's surface point; the render's mean DN and its contrast (std after dividing out the
    panel's shading) agree with them."""
    Z = 0.5
    text = (down_camera("c", [0, 0, Z], (128, 128), 10.0, 5.0)
            + light("p", [0.4, 0.0, 0.5], [0, 0, 0], [0.3, 0.3], 15)
            + table("speckle", dot_diameter_mm=12.0, coverage=0.5, strokes=0, texel_mm=0.5,
                    tile_texels=256, seed=2))
    exp = config.load(plate_experiment(cameras=text))
    meshes, sc = setup(exp)
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    linear = render_linear(sc, camera_sensor(cam, exp.camera_specs[0], 16), 0)
    pattern = pattern_for(exp.speckle)
    pts = plane_samples(pixel_points(cam))
    illum = lighting.illuminate(scene.build_scene(meshes), exp.lights, pts, grid=16)
    pho = lighting.photometry(illum, exp.speckle, exp.sensor, *lighting.pattern_stats(pattern), 1)
    sensor = exp.sensor
    dn = sensor.mean_dn(linear.astype(float)).ravel()
    assert dn.max() < sensor.max_dn                                   # no clipping
    b_pred = pho.brightness[0]
    assert dn.mean() == pytest.approx(b_pred.mean(), rel=0.02)       # +0.96 %: dots vs shading
    # Divide out the panel's shading (so the few dots under the bright side do not count double):
    # the mean level then agrees to about 0.01 %.
    shading = (b_pred - sensor.offset) / (b_pred - sensor.offset).mean()
    assert np.mean((dn - sensor.offset) / shading) == pytest.approx(
        np.mean(b_pred - sensor.offset), rel=2e-3)
    c_render = np.std((dn - sensor.offset) / shading)
    # Photometry's c is the unblurred paint's; each 1 mm pixel averages the bilinearly interpolated
    # 0.5 mm texels: weights (1, 7, 7, 1)/16 per axis (the tent integrated over the pixel).
    k = np.array([1.0, 7.0, 7.0, 1.0]) / 16
    blurred = ndimage.convolve1d(ndimage.convolve1d(pattern.astype(float), k, 0, mode="wrap"),
                                 k, 1, mode="wrap")
    blur = blurred.std() / pattern.std()                              # about 0.968
    assert c_render == pytest.approx(pho.contrast[0].mean() * blur, rel=0.01)
    assert c_render == pytest.approx(pho.contrast[0].mean(), rel=0.05)


def test_shadow_of_a_bar_is_where_the_shadow_map_puts_it(plate_experiment):
    """A 0.1 m panel 1 m above the plate, a 120 mm bar 0.2 m above it: the samples the shadow map
    marks unlit are dark in the render, the lit ones as bright as predicted (away from penumbrae)."""
    text = (down_camera("c", [0.0, -1.0, 1.2], (300, 200), 74.0, 24, target=[0, 0, 0])
            + light("p", [0, 0, 1.0], [0, 0, 0], [0.1, 0.1], 40))
    bar = '[[mesh]]\nname = "bar"\nfile = "bar.stl"\nunit = "mm"\nrole = "obstacle"\n'
    path = plate_experiment(cameras=text, extra_meshes=bar,
                            files=[("bar.stl", [1000, 120, 20], [0, 0, 200])])
    exp = config.load(path)
    meshes, sc = setup(exp, pattern=np.ones((16, 16), np.float32))
    samples = scene.sample_regions(meshes, **region_tables(exp))
    blockers = scene.build_scene(meshes)
    illum = lighting.illuminate(blockers, exp.lights, samples)
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    vis = visibility.compute_visibility(blockers, [cam], samples, exp.evaluation.incidence_limit,
                                        progress=False)
    linear = render_linear(sc, camera_sensor(cam, exp.camera_specs[0], 16), 0)
    lit = illum.lit[0]
    seen = vis.visible[0]
    edges = cKDTree(samples.points[((lit > 0) & (lit < 1)) | ~seen])   # penumbrae, hidden parts
    far = (edges.query(samples.points)[0] > 0.015) & (np.abs(samples.points[:, :2]).max(1) < 0.48)
    umbra, full = seen & far & (lit == 0), seen & far & (lit == 1)
    assert umbra.sum() > 200 and full.sum() > 1000
    uv = np.rint(cam.project(samples.points)).astype(int)
    value = linear[uv[:, 1].clip(0, cam.height - 1), uv[:, 0].clip(0, cam.width - 1)]
    predicted = exp.speckle.white_albedo * illum.irradiance / np.pi
    assert np.all(value[umbra] < 0.02 * np.median(predicted[full]))
    rel = np.abs(value[full] / predicted[full] - 1)
    assert np.median(rel) < 0.02 and rel.max() < 0.15


def test_builtin_experiment_renders_a_complete_run_folder(tmp_path):
    exp = config.load(ROOT / "experiments/beam_column/ten_cameras.toml")
    out = tmp_path / "run"
    summary = render_experiment(exp, out, scale=0.05, spp=2)
    names = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    calibration = {n for n in names if n.startswith("calibration/")}
    names -= calibration
    cams = [c.name for c in exp.camera_specs]
    assert {f"calibration/opencv/{c}.yml" for c in cams} <= calibration
    assert {n.split("/")[1] for n in calibration} == {"opencv", "matchid", "dice", "vic3d"}
    assert {f"images/{c}.png" for c in cams} | {"layout.json", "contact_sheet.png", "photometry.csv",
                                                 "shadows.vtp", "maps/shadows.png", "config.toml",
                                                 "render.json", "report.html"} == names
    layout = json.loads((out / "layout.json").read_text())
    full = cameras_of(exp.camera_specs, exp.rails)
    for entry, cam in zip(layout["cameras"], full):
        small = scaled_camera(cam, 0.05)
        assert (entry["width"], entry["height"]) == (small.width, small.height) == (
            round(cam.width * 0.05), round(cam.height * 0.05))
        assert entry["K"][0][0] == pytest.approx(cam.focal_px * small.width / cam.width)
        fs = cv2.FileStorage(str(out / "calibration" / "opencv" / f"{cam.name}.yml"), cv2.FILE_STORAGE_READ)
        np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), entry["K"])   # the images' K
        with Image.open(out / "images" / f"{cam.name}.png") as im:
            assert im.size == (small.width, small.height) and im.mode.startswith("I")
            assert np.asarray(im).std() > 50           # speckled, lit, not flat
    with open(out / "photometry.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(cams) * len(exp.regions)
    seen = [r for r in rows if int(r["n_samples"]) > 0]
    assert len(seen) > 20 and all(float(r["b_predicted_dn"]) > 0 for r in seen)
    assert set(summary["lights"]) == {lt.name for lt in exp.lights}
    with Image.open(out / "contact_sheet.png") as im:
        assert im.size[0] > 800


def test_cli_render_reports_config_errors(tmp_path, capsys):
    assert main(["render", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "file not found" in capsys.readouterr().err
