"""A DIC patch at the edge of the speckled surface: the clipped-patch prediction (`vdo.physics.usable`)
against correlation on renders (`vdo.dic.validate`'s renderer and correlation).

A stereo pair (25 deg apart) looks at a plate that ends 0.6 mm from the centre X0 of a nominal
6 mm patch: only 60 % of the patch square lies on the plate. vdo predicts sigma at X0 from the
samples of the plate (0.4 mm grid; the estimator sees the cut edge exactly, phi = 0.6). Correlation
measures U over the part of the patch on the plate (3.6 x 6 mm, what DIC does with a mask), from
renders of the cut plate, 160 noise seeds: measured / (sqrt 2 x predicted) must lie in
[0.8, 1.25] per axis (the sampling error of one axis is 5.6 % at 160 seeds), and the same ratio
with the unclipped patch (phi = 1) must not: the edge costs sqrt(1/0.6) = 1.29 in sigma."""

from __future__ import annotations

import math
import textwrap
from dataclasses import replace

import numpy as np
import pytest

from vdo.dic import validate as V
from vdo.geometry.plate import plate_geometry
from vdo.physics.lighting import illuminate
from vdo.physics.predict import predict
from vdo.scene import SceneMesh, SurfaceSamples, build_scene, region_faces, sample_region
from vdo.physics.visibility import compute_visibility

SEEDS = 160
L, PHI, SPACING = 6e-3, 0.6, 0.4e-3

TOML = f"""
[validation]
name = "edge"
seeds = {SEEDS}

[[case]]
name = "edge"
patch_mm = [{PHI * L * 1e3:g}, {L * 1e3:g}]
plate_margin_mm = 4
dot_mm = 0.35
texel_mm = 0.0125
tile_texels = 1024
edge_blur_mm = 0.06
focal_mm = 25
pixel_um = 5
pixels = [120, 90]
distance_mm = 500
spp = 64
displacement_um = [31, -23, 37]
cameras = [{{name = "left", polar_deg = 12.5, azimuth_deg = 180}}, {{name = "right", polar_deg = 12.5, azimuth_deg = 0}}]
seed = 21
"""


def _cut_plate(setup):
    """The case's plate with its -t_u side moved in to the patch's edge (u = 0 of the patch)."""
    g = plate_geometry(setup.case)
    verts = np.array(setup.plate.vertices, dtype=float)
    shift = setup.case.plate_margin * g["t_u"]
    verts[[0, 3]] += shift                   # plate corners p0 and p0 + ph t_v are the -t_u side
    return SceneMesh("plate", "specimen", verts, setup.plate.faces)


def _predicted_sigma(setup, clip):
    """sigma_xyz (m) at the nominal patch's centre X0 from samples of the cut plate."""
    exp = setup.experiment
    exp = replace(exp, evaluation=replace(exp.evaluation, patch_size=L, sample_spacing=SPACING))
    part = sample_region(setup.plate, exp.regions[0], SPACING, (exp.path, "edge"))
    n = len(part["points"])
    samples = SurfaceSamples(**part, region=np.zeros(n, dtype=int), region_names=("patch",),
                             region_importance=np.ones(1))
    g = plate_geometry(setup.case)
    x0 = g["origin"] + (PHI * L - L / 2) * g["t_u"] + (L / 2) * g["t_v"]
    k = int(np.argmin(np.linalg.norm(samples.points - x0, axis=1)))
    assert np.linalg.norm(samples.points[k] - x0) < 1e-9
    blockers = build_scene([setup.plate])
    vis = compute_visibility(blockers, setup.cameras, samples, exp.evaluation.incidence_limit,
                             progress=False)
    illum = illuminate(blockers, (), samples, exp.render.ambient_radiance)
    pred = predict(exp.regions, exp.evaluation, exp.speckle, exp.sensor, setup.cameras, samples, vis, illum,
                   V.speckle_model_of(setup), clip_patch=clip)
    return pred.sigma_xyz[k], pred.patch_fraction[k]


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    path = tmp_path_factory.mktemp("edge") / "edge.toml"
    path.write_text(textwrap.dedent(TOML))
    case = V.load(path).cases[0]
    setup = V.build_setup(case, path)
    setup.plate = _cut_plate(setup)
    setup.region = region_faces(setup.plate, setup.experiment.regions[0], SPACING, (path, "edge"))
    V.render_case(setup)
    res0, px_err = V.noise_free_check(setup)
    assert np.all(np.abs(px_err) < 0.02), px_err
    est = np.array([V.correlate_seed(setup, k, [r.xi for r in res0]) for k in range(SEEDS)])
    return setup, est.std(axis=0, ddof=1)


def test_patch_at_an_edge_matches_correlation_on_renders(measured):
    setup, sigma_meas = measured
    sigma_clip, phi = _predicted_sigma(setup, clip=True)
    sigma_whole, _ = _predicted_sigma(setup, clip=False)
    assert phi == pytest.approx(PHI, abs=1e-9)
    ratio = sigma_meas / (math.sqrt(2) * sigma_clip)
    print(f"edge patch: phi {phi:.2f}, measured / (sqrt2 predicted) {np.round(ratio, 3)}, "
          f"unclipped {np.round(sigma_meas / (math.sqrt(2) * sigma_whole), 3)}")
    assert np.all((ratio >= 0.8) & (ratio <= 1.25)), ratio
    np.testing.assert_allclose(sigma_clip / sigma_whole, 1 / math.sqrt(PHI), rtol=1e-6)
    unclipped = sigma_meas / (math.sqrt(2) * sigma_whole)
    assert math.sqrt(np.mean(unclipped ** 2)) > 1.2
