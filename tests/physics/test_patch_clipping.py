"""A DIC patch no larger than the sample spacing is clipped by the surface itself: on the holed
plate (experiments/holed_plate) with a 2 mm patch at 2 mm spacing, each sample's sigma near the
hole grows as 1 / sqrt(psi), psi the exact fraction of its patch square off the hole (computed
here on a 200 x 200 grid of the square against the circle), and the samples within half a patch
of the edge average 1.15-1.4x the sigma far from it. The cell-based overlap (from the
neighbouring samples) cannot see it: at this spacing each patch is its own cell."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from vdo.config import experiment as config
from vdo.physics import usable
from vdo.state import layout_state, prepare

HERE = Path(__file__).resolve().parents[2] / "experiments" / "holed_plate"
HOLE_RADIUS, HOLE_Z = 0.015, 1.0
RASTER_RTOL = 0.03     # sigma vs 1/sqrt(psi): the raster resolves the edge to h / K = 0.25 mm


@pytest.fixture(scope="module")
def holed_plate():
    exp = config.load(HERE / "stereo.toml")
    exp = replace(exp, evaluation=replace(exp.evaluation, sample_spacing=0.002, patch_size=0.002))
    geometry = prepare(exp)
    return (geometry, layout_state(geometry, strain_fields=False).prediction,
            layout_state(geometry, strain_fields=False, clip_patch=False).prediction)


def test_small_patch_is_clipped_by_the_hole(holed_plate):
    geometry, clipped, whole = holed_plate
    s = geometry.samples
    L = geometry.experiment.evaluation.patch_size
    d = np.hypot(s.points[:, 0], s.points[:, 2] - HOLE_Z) - HOLE_RADIUS
    near = np.flatnonzero((d >= 0) & (d <= L / 2) & clipped.measured)
    far = (d > 0.02) & (d < 0.04) & clipped.measured
    assert len(near) > 20 and far.sum() > 500
    q = (np.arange(200) + 0.5) / 200 * L - L / 2
    U, V = np.meshgrid(q, q, indexing="ij")
    psi = np.array([np.mean(np.hypot(s.points[n, 0] + U, s.points[n, 2] - HOLE_Z + V) >= HOLE_RADIUS)
                    for n in near])
    ratio = clipped.sigma_max[near] / whole.sigma_max[near]
    np.testing.assert_allclose(ratio, 1 / np.sqrt(psi), rtol=RASTER_RTOL)
    edge = np.mean(clipped.sigma_max[near]) / np.median(clipped.sigma_max[far])
    assert 1.15 <= edge <= 1.4


def test_cell_overlap_alone_does_not_see_the_hole(holed_plate):
    geometry, clipped, _ = holed_plate
    s = geometry.samples
    overlap = usable.patch_overlap(s, geometry.experiment.evaluation.patch_size)   # no rasters
    phi = usable.patch_fractions(overlap, clipped.usable)
    d = np.hypot(s.points[:, 0], s.points[:, 2] - HOLE_Z) - HOLE_RADIUS
    near = (d >= 0) & (d <= 0.001) & clipped.measured
    assert np.all(phi[:, near][clipped.usable[:, near]] == pytest.approx(1.0))
