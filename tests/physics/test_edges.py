"""Usable views and the DIC patch clipped at edges (`vdo.physics.usable`), on the holed-plate experiment
(experiments/holed_plate, meshes rebuilt here by its make_meshes.py) and on synthetic grids.

Checked against things vdo does not compute: the exact area of a square clipped by a straight
edge (closed form) and by a disc (fine point sampling of the geometry), and sigma's 1/sqrt(area)
law that follows from the information being additive over the patch's pixels."""

from __future__ import annotations

import dataclasses
import json
import runpy
import shutil
from pathlib import Path

import numpy as np
import pytest

from vdo import objective
from vdo.config import experiment as config
from vdo.physics import usable
from vdo.commands.evaluate import evaluate
from vdo.physics.predict import predict, samples_for_objective, settings, view_data
from vdo.scene import SurfaceSamples
from vdo.state import layout_state, prepare

HOLED = Path(__file__).resolve().parents[2] / "experiments" / "holed_plate"
HOLE_CENTRE, HOLE_RADIUS = np.array([0.0, 1.0]), 0.015     # (x, z), m


def _grid(n_u, n_v, h, keep=None):
    """SurfaceSamples on an n_u x n_v grid of spacing h in one region (uv = cell centres)."""
    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    uv = (np.stack([i.ravel(), j.ravel()], 1) + 0.5) * h
    if keep is not None:
        uv = uv[keep(uv)]
    n = len(uv)
    pts = np.c_[uv, np.zeros(n)]
    return SurfaceSamples(points=pts, normals=np.tile([0.0, 0.0, 1.0], (n, 1)),
                          tangent_u=np.tile([1.0, 0.0, 0.0], (n, 1)),
                          tangent_v=np.tile([0.0, 1.0, 0.0], (n, 1)), uv=uv,
                          area=np.full(n, h * h), region=np.zeros(n, dtype=int),
                          region_names=("r",), region_importance=np.ones(1))


def test_patch_fraction_is_one_inside_and_the_clipped_area_at_a_straight_edge():
    """A surface that ends at u = 40 mm (cells of 1 mm): a 10 mm square centred d from the edge
    keeps clip(1/2 + d/L, 0, 1) of its area (closed form); the estimator resolves the edge to the
    cells, so it is within h / (2 L) = 5 % of it, and exactly 1 inside."""
    h, L = 1e-3, 10e-3
    s = _grid(40, 60, h)
    overlap = usable.patch_overlap(s, L)
    phi = usable.patch_fractions(overlap, np.ones((1, len(s)), dtype=bool))[0]
    u, v = s.uv[:, 0], s.uv[:, 1]
    inner = (u > L / 2 + h) & (u < 0.04 - L / 2 - h) & (v > L / 2 + h) & (v < 0.06 - L / 2 - h)
    np.testing.assert_allclose(phi[inner], 1.0, atol=1e-12)
    band = (u > 0.02) & (v > L) & (v < 0.06 - L)       # near the edge u = 40 mm only
    d = 0.04 - u[band]
    exact = np.clip(0.5 + d / L, 0, 1)
    err = np.abs(phi[band] - exact)
    assert err.max() <= h / (2 * L) + 1e-12, err.max()
    assert (exact < 1).sum() > 100


def test_patch_fraction_follows_the_usable_views_per_camera():
    """Camera 1 sees only u < 20 mm (an occlusion boundary): its fraction drops there like at a
    surface edge while camera 0's stays 1; a view unusable at the sample itself gives 0."""
    h, L = 1e-3, 6e-3
    s = _grid(40, 30, h)
    use = np.ones((2, len(s)), dtype=bool)
    use[1] = s.uv[:, 0] < 0.02
    phi = usable.patch_fractions(usable.patch_overlap(s, L), use)
    mid = (s.uv[:, 1] > L) & (s.uv[:, 1] < 0.03 - L)
    at = mid & np.isclose(s.uv[:, 0], 0.0195)          # the last seen column: 0.5 mm from it
    assert np.allclose(phi[0, at], 1.0)
    assert np.allclose(phi[1, at], 0.5 + 0.0005 / L)   # exact here: the boundary is a cell edge
    assert np.all(phi[1, ~use[1]] == 0)


def _holed_fraction_exact(centres_uv_to_xz, L, n=400):
    """Exact fraction (to 1/n^2 point sampling) of each L-square lying off the hole's disc."""
    a = (np.arange(n) + 0.5) / n - 0.5
    gx, gz = np.meshgrid(a * L, a * L, indexing="ij")
    out = []
    for x, z in centres_uv_to_xz:
        r = np.hypot(x + gx - HOLE_CENTRE[0], z + gz - HOLE_CENTRE[1])
        out.append(np.mean(r >= HOLE_RADIUS))
    return np.array(out)


@pytest.fixture(scope="module")
def holed(tmp_path_factory):
    """The holed-plate experiment with its meshes rebuilt in a temporary folder, ray-cast."""
    root = tmp_path_factory.mktemp("holed")
    shutil.copy(HOLED / "stereo.toml", root / "stereo.toml")
    runpy.run_path(str(HOLED / "make_meshes.py"))["main"](root / "meshes")
    exp = config.load(root / "stereo.toml")
    geometry = prepare(exp)
    state = layout_state(geometry, predict_fields=False)
    samples, cams, sp = geometry.samples, list(state.cameras), geometry.speckle
    vis, illum = state.visibility, state.illumination
    return dict(root=root, exp=exp, samples=samples, cams=cams, vis=vis, illum=illum, speckle=sp,
                clipped=predict(exp.regions, exp.evaluation, exp.speckle, exp.sensor, cams, samples, vis,
                                illum, sp),
                whole=predict(exp.regions, exp.evaluation, exp.speckle, exp.sensor, cams, samples, vis, illum,
                              sp, clip_patch=False))


def test_sigma_near_the_hole_follows_one_over_sqrt_of_the_clipped_area(holed):
    """sigma(clipped) / sigma(whole patch) = 1 / sqrt(phi) with phi the exact area fraction of the
    10 mm square off the 30 mm hole, within the estimator's resolution (h / 2L per edge: 5 % in
    phi, 2.5 % in sigma; measured below), for samples within 8 mm of the hole's edge and well
    inside the image."""
    s, c, w = holed["samples"], holed["clipped"], holed["whole"]
    xz = s.points[:, [0, 2]]
    d = np.hypot(*(xz - HOLE_CENTRE).T) - HOLE_RADIUS
    near = (d < 0.008) & c.measured & w.measured
    assert near.sum() > 500
    phi_exact = _holed_fraction_exact(xz[near], holed["exp"].evaluation.patch_size)
    ratio = c.sigma_max[near] / w.sigma_max[near]
    model = 1 / np.sqrt(phi_exact)
    rel = ratio / model - 1
    assert np.abs(rel).max() < 0.025, np.abs(rel).max()
    assert np.abs(np.mean(rel)) < 0.005          # no bias: the cell edges straddle the circle
    assert ratio.max() > 1.25                    # the hole's edge matters: ~1.3 at the rim
    far = (d > 0.012) & (np.abs(xz[:, 0]) < 0.04) & (np.abs(xz[:, 1] - 1.0) < 0.08) & c.measured
    np.testing.assert_allclose(c.sigma_max[far], w.sigma_max[far], rtol=1e-9)


def test_usable_views_counts_sigma_and_summary_agree(holed, tmp_path):
    """The region reaches past the images' top and bottom edges (the issue's case): samples there
    have small soft weights. With one definition of a usable view (w >= 0.5): coverage counts
    them, sigma is finite exactly where >= 2 usable non-parallel views exist, no such sample's
    sigma exceeds OUTLIER_FACTOR x its region's median without a flag, and the summary's max is
    the max over the measured samples. Before (soft weights alone) the same samples gave a max
    sigma of metres."""
    exp, s, cams, vis, illum, sp = (holed[k] for k in ("exp", "samples", "cams", "vis", "illum",
                                                        "speckle"))
    smp = samples_for_objective(exp.regions, s)
    raw = objective.fields(objective.CameraParams.from_cameras(cams), smp,
                           view_data(exp.speckle, exp.sensor, smp, vis, illum, sp), sp.table,
                           settings(exp.evaluation))
    w = np.asarray(raw.weights)
    edge = ((w > 0) & (w < usable.USABLE_WEIGHT)).any(axis=0)
    assert edge.sum() > 20
    old_max = np.max(np.asarray(raw.sigma_max)[np.asarray(raw.measured)])
    pred = holed["clipped"]
    assert not pred.measured[edge & ((w >= usable.USABLE_WEIGHT).sum(0) < 2)].any()
    assert np.all(np.isfinite(pred.sigma_max[pred.measured]))
    np.testing.assert_array_equal(pred.coverage, (w >= usable.USABLE_WEIGHT).sum(0))

    # the written run at 2 mm (4x fewer samples than the fixture: the same edges, a quarter of
    # the maps and report to draw)
    coarse = dataclasses.replace(exp, evaluation=dataclasses.replace(exp.evaluation,
                                                                     sample_spacing=2e-3))
    result = evaluate(coarse, tmp_path / "run")
    from vtk import vtkXMLPolyDataReader
    from vtk.util.numpy_support import vtk_to_numpy
    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(tmp_path / "run" / "samples.vtp"))
    reader.Update()
    arr = lambda name: vtk_to_numpy(reader.GetOutput().GetPointData().GetArray(name))
    sigma, cov, outlier, edge_lim = arr("sigma_max"), arr("coverage"), arr("outlier"), arr("edge_limited")
    finite = np.isfinite(sigma)
    assert np.all(cov[finite] >= 2)
    median = np.median(sigma[finite])
    high = finite & (sigma > usable.OUTLIER_FACTOR * median)
    assert np.all(outlier[high] == 1)
    reg = result.regions["front"]
    assert reg.sigma_max_um.max == pytest.approx(sigma[finite].max(), rel=1e-9)
    plain = finite & (outlier == 0) & (edge_lim == 0)
    assert reg.sigma_max_um.max_unflagged == pytest.approx(sigma[plain].max(), rel=1e-9)
    assert reg.n_outliers == int(outlier.sum()) and reg.n_edge_limited == int(edge_lim.sum())
    assert reg.seen_by_2_or_more == pytest.approx(np.mean(cov >= 2), rel=1e-9)
    assert reg.sigma_max_um.max < old_max * 1e6 / 10
    print(f"holed plate summary max: soft weights {old_max * 1e6:.3g} um -> usable views "
          f"{reg.sigma_max_um.max:.3g} um (unflagged {reg.sigma_max_um.max_unflagged:.3g})")
    (tmp_path / "summary.txt").write_text(json.dumps(reg.to_json()))
