"""Rendered against predicted contrast (photometry.csv) at full and reduced render scale, and the
pixel-averaged speckle statistics behind it, against a direct box filter of the texture."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from scipy import ndimage

from conftest import DOWN_CAMERA
from vdo.config import experiment as config
from vdo.commands.render import render_experiment
from vdo.model.speckle import generate_pattern, normalise, pixel_averaged_std


@pytest.mark.parametrize("side_texels, skew", [(4, 0.0), (16, 0.0), (8, 0.5)])
def test_pixel_averaged_std_matches_a_direct_box_average(side_texels, skew):
    """Upsample the pattern 4x bilinearly (texel centres kept, as Mitsuba interpolates), average
    it over a box pixel (a sheared parallelogram for skew > 0) by brute force, sample at pixel
    centres: its std is the spectral formula's (within 1 %: the brute force's own sub-texel
    grid and the texel-grid aliases the formula leaves out)."""
    texel = 1e-4
    f = normalise(generate_pattern(256, texel, 8 * texel, seed=4))
    up = 4
    fine = ndimage.zoom(f, up, order=1, mode="grid-wrap", grid_mode=True)
    n = side_texels * up
    kernel = np.zeros((n, n + int(skew * n)))
    for row in range(n):                   # a parallelogram: each row shifted by skew x row
        start = int(round(skew * row))
        kernel[row, start:start + n] = 1.0
    box = ndimage.convolve(fine, kernel / kernel.sum(), mode="wrap")
    direct = box.std()
    a = side_texels * texel
    sides = np.array([[[a, skew * a], [0.0, a]]])       # columns: pixel x step, pixel y step (u, v)
    assert pixel_averaged_std(f, texel, sides)[0] == pytest.approx(direct, rel=0.01)


def test_block_summed_spectrum_matches_the_full_sum():
    """A 1024-texel tile is summed over 4 x 4 frequency blocks: within 5e-4 of the full sum over
    every frequency, for parallelogram footprints of 0.1 to 9 mm."""
    from vdo.config.rig import SpeckleSpec
    from vdo.model.speckle import pattern_for

    sp = SpeckleSpec()
    f = normalise(pattern_for(sp))
    rng = np.random.default_rng(0)
    sides = rng.uniform(0.1e-3, 3e-3, size=(12, 2, 2)) * rng.choice([1, 3], size=(12, 1, 1))
    fast = pixel_averaged_std(f, sp.texel, sides)
    n = f.shape[0]
    power = np.abs(np.fft.fft2(f)) ** 2 / float(n * n) ** 2
    power[0, 0] = 0.0
    k = np.fft.fftfreq(n, d=sp.texel)
    ku, kv = k[None, :], k[:, None]
    w = power * (np.sinc(ku * sp.texel) * np.sinc(kv * sp.texel)) ** 4
    full = [np.sqrt(np.sum(w * (np.sinc(ku * a[0, 0] + kv * a[1, 0]) * np.sinc(ku * a[0, 1] + kv * a[1, 1])) ** 2))
            for a in sides]
    np.testing.assert_allclose(fast, full, rtol=5e-4)


LIGHTS = """
[speckle]
dot_diameter_mm = 6
texel_mm = 0.75
strokes = 0

[render]
ambient_radiance = 1.0
spp = 4
"""


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    """A 1 m plate seen from 1.5 m by one 600 x 400 camera (2.3 mm pixels on the plate, 6 mm
    dots), lit by a uniform sky only (no Monte Carlo noise on an open Lambertian plate),
    rendered at scale 1 and 0.25."""
    from conftest import PLATE_TOML, write_box

    root = tmp_path_factory.mktemp("photometry")
    write_box(root / "plate.stl", [1000, 1000, 10], center=[0, 0, -5])
    text = PLATE_TOML.format(spacing=10, limit=75, height=1.5, extra_meshes="",
                             cameras=DOWN_CAMERA.format(name="down", focal=24, u=0.5) + LIGHTS)
    (root / "plate.toml").write_text(text)
    exp = config.load(root / "plate.toml")
    out = {}
    for scale in (1.0, 0.25):
        folder = root / f"scale{scale}"
        render_experiment(exp, folder, scale=scale)
        out[scale] = next(csv.DictReader((folder / "photometry.csv").open()))
    return out


def test_rendered_contrast_matches_the_prediction_at_every_scale(renders):
    """The rendered contrast is the paint's c times the std of the rendered pixel average
    (render_factor: the box pixel plus the Monte Carlo term of 4 spp), within 5 %, at scale 1
    and 0.25; against the paint's c alone it is more than 10 % lower: the pixel averages the
    speckle, 4x wider pixels more (pixel_factor down by > 20 %)."""
    for scale, row in renders.items():
        c_render = float(row["c_render_dn"])
        assert c_render == pytest.approx(float(row["c_render_predicted_dn"]), rel=0.05), (scale, row)
        assert float(row["b_render_dn"]) == pytest.approx(float(row["b_predicted_dn"]), rel=0.02)
        assert c_render < 0.9 * float(row["c_predicted_dn"])
    full, quarter = (float(renders[s]["pixel_factor"]) for s in (1.0, 0.25))
    assert quarter < 0.8 * full
    ratio = lambda s: float(renders[s]["c_render_dn"]) / float(renders[s]["c_predicted_dn"])
    assert ratio(0.25) < 0.8 * ratio(1.0)


NOZZLE_TOML = """
[experiment]
name = "nozzle on a floor"

[evaluation]
sample_spacing_mm = 4
incidence_limit_deg = 80

[render]
ambient_radiance = 1.0
mode = "dic"

[speckle]
dot_diameter_mm = 1.5
strokes = 0

[[mesh]]
name = "floor"
file = "floor.stl"
unit = "mm"
role = "obstacle"

[[mesh]]
name = "nozzle"
file = "nozzle.stl"
unit = "mm"
role = "specimen"

[[region]]
name = "wall"
mesh = "nozzle"
near_axis_m = [[0, 0, 0], [0, 0, 1]]
within_m = 0.09
box_min_m = [-1, -1, 0.06]
box_max_m = [1, 1, 0.24]

[[camera]]
name = "front"
sensor_mm = [2.07, 1.38]
pixels = [600, 400]
focal_mm = 8
position_m = [0.7, 0, 0.15]
target_m = [0, 0, 0.15]
body = false
"""
WALL_SKY = 0.5            # a vertical wall over an endless floor sees half its cosine-weighted sky
CURVED_RTOL = 0.05        # rendered against predicted contrast on the curved wall (sampling of ~2000 windows)


def test_curved_wall_beside_a_floor_renders_the_predicted_light_and_contrast(tmp_path):
    """A cylinder (r = 80 mm, a nozzle) standing on a 40 m floor, seen from the side by a camera
    with 3.45 µm pixels (its f/8 diffraction 0.54 px) under a uniform sky: the wall's normals are
    horizontal, so the floor hides half of each sample's cosine-weighted sky (closed form,
    WALL_SKY) and the render (Mitsuba's) is half as bright as the open sky would make it; the
    light model must say so, and the rendered contrast (with the predicted light divided out)
    must be the paint's times the rms of the rendered pixel's factor over the region, whose
    footprints stretch towards the silhouette. Without the sky's occlusion, the lens and the
    per-sample footprints the prediction was 2.3x the render (901 against 392 DN)."""
    import trimesh

    from conftest import write_box
    from vdo.model.speckle import pattern_for

    write_box(tmp_path / "floor.stl", [40000, 40000, 10], center=[0, 0, -5])
    trimesh.creation.cylinder(radius=80, height=300, sections=256).apply_translation(
        [0, 0, 150]).export(tmp_path / "nozzle.stl")
    (tmp_path / "nozzle.toml").write_text(NOZZLE_TOML)
    exp = config.load(tmp_path / "nozzle.toml")
    render_experiment(exp, tmp_path / "run")
    row = next(csv.DictReader((tmp_path / "run" / "photometry.csv").open()))
    sp, sensor = exp.speckle, exp.sensor
    mean_rho = sp.black_albedo + (sp.white_albedo - sp.black_albedo) * pattern_for(sp).mean()
    closed_form = sensor.mean_dn(mean_rho * np.pi * 1.0 * WALL_SKY / np.pi)
    assert int(row["n_samples"]) > 1000
    assert float(row["b_render_dn"]) == pytest.approx(closed_form, rel=0.02)
    assert float(row["b_predicted_dn"]) == pytest.approx(closed_form, rel=0.02)
    assert float(row["c_render_dn"]) == pytest.approx(float(row["c_render_predicted_dn"]), rel=CURVED_RTOL)


def test_a_row_off_its_predicted_contrast_is_warned_of():
    """`vdo render` warns of a row whose rendered contrast is further than PHOTOMETRY_TOLERANCE
    from its prediction, naming the camera, the region and both numbers (the pressure vessel's
    nozzle before the sky's occlusion entered the light model: 793 against 1122 DN)."""
    from vdo.render import PHOTOMETRY_TOLERANCE, photometry_warnings

    rows = [{"camera": "t210", "region": "nozzle", "n_samples": 508, "c_render_dn": 793.0,
             "c_render_predicted_dn": 1122.0},
            {"camera": "t210", "region": "shell", "n_samples": 6773,
             "c_render_dn": 1000.0 * (1 + 0.9 * PHOTOMETRY_TOLERANCE), "c_render_predicted_dn": 1000.0},
            {"camera": "overhead", "region": "nozzle", "n_samples": 0}]
    lines = photometry_warnings(rows)
    assert len(lines) == 1 and "\n" not in lines[0]
    assert all(word in lines[0] for word in ("t210/nozzle", "793", "1122", "-29 %"))


SAMPLING_RTOL = 0.07        # rendered against predicted contrast with the light's sampling noise
SAMPLING_SHARE = 0.3        # the light's sampling noise is at least this share of the prediction


def test_the_sampled_modes_light_noise_is_predicted(tmp_path):
    """Trial 4 rendered a pipe at 1/10 scale and 4 spp: every row's contrast read 19-48 % above
    the prediction, which left out the light's own sampling (one panel point and one sky
    direction a sample, a Bernoulli where a panel or the sky is partly hidden). Here the plate
    is half walled in (the sky half hidden along the wall) and a bar shades part of a panel: at
    4 spp the rendered contrast (Mitsuba's own render) is the prediction with
    `c_light_sampling_dn` within SAMPLING_RTOL, and without that term it would be more than
    15 % off (the term is at least SAMPLING_SHARE of the prediction)."""
    from conftest import write_plate_experiment

    walls = ('[[mesh]]\nname = "wall"\nfile = "wall.stl"\nunit = "mm"\nrole = "obstacle"\n'
             '[[mesh]]\nname = "bar"\nfile = "bar.stl"\nunit = "mm"\nrole = "obstacle"\n')
    light = ('[[light]]\nname = "p"\nposition_m = [0.6, 0.0, 1.0]\ntarget_m = [0.0, 0.0, 0.0]\n'
             'size_m = [0.4, 0.4]\nradiance = 2\n')
    path = write_plate_experiment(tmp_path, cameras=DOWN_CAMERA.format(name="down", focal=16, u=0.5)
                                  + light + LIGHTS, extra_meshes=walls,
                                  files=[("wall.stl", [1000, 20, 800], [0, 520, 400]),
                                         ("bar.stl", [20, 1000, 20], [350, 0, 500])])
    exp = config.load(path)
    render_experiment(exp, tmp_path / "run", scale=0.25)
    row = next(csv.DictReader((tmp_path / "run" / "photometry.csv").open()))
    c_render, predicted = float(row["c_render_dn"]), float(row["c_render_predicted_dn"])
    light = float(row["c_light_sampling_dn"])
    assert c_render == pytest.approx(predicted, rel=SAMPLING_RTOL), row
    assert light >= SAMPLING_SHARE * predicted, row
    assert c_render > 1.15 * np.sqrt(predicted ** 2 - light ** 2), row
