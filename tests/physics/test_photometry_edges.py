"""photometry.csv reads a region's rendered pixels only where its 3 x 3 window stays on the region:
a strip of speckle on a bright plate, rendered at a quarter of the camera's pixels (9 mm pixels,
a 100 mm strip 11 px wide), has its brightness and contrast as predicted (the sky's uniform light
on an open plate), where the windows that reach the bright plate beside it raise both; and the
edge distance it uses is the closed-form distance to the strip's sides."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from conftest import DOWN_CAMERA, write_plate_experiment
from test_photometry import LIGHTS as SCENE   # 6 mm dots, an ambient light alone, 4 spp

STRIP = """
[[region]]
name = "strip"
mesh = "plate"
normal = [0, 0, 1]
box_min_m = [-0.4, -0.05, -1]
box_max_m = [0.4, 0.05, 1]
"""


@pytest.fixture(scope="module")
def strip(tmp_path_factory):
    folder = tmp_path_factory.mktemp("strip")
    path = write_plate_experiment(folder, spacing=10, cameras=DOWN_CAMERA.format(name="down", focal=24, u=0.5) + SCENE)
    text = path.read_text()
    text = text[:text.index("[[region]]")] + STRIP + "\n" + text[text.index("[[rail]]"):]
    path.write_text(text.replace('role = "specimen"', 'role = "specimen"\nalbedo = 0.95'))
    return path


def test_edge_distance_is_the_distance_to_the_strips_sides(strip):
    from vdo.config.experiment import load
    from vdo.meshes.samples import edge_distance
    from vdo.state import prepare

    samples = prepare(load(strip)).samples
    x, y = samples.points[:, 0], samples.points[:, 1]
    closed = np.minimum.reduce([x + 0.4, 0.4 - x, y + 0.05, 0.05 - y])
    h = float(samples.region_cell[0])
    assert np.abs(edge_distance(samples) - closed).max() <= h / 2 + 1e-9
    # a sample left out of `keep` makes an edge: its neighbours are half a cell from it
    keep = np.ones(len(samples), dtype=bool)
    middle = int(np.argmax(closed))
    keep[middle] = False
    near = np.linalg.norm(samples.points - samples.points[middle], axis=1) < 1.01 * h
    d = edge_distance(samples, keep)
    assert d[middle] == 0 and np.allclose(d[near & keep], h / 2)


def test_the_strips_window_stays_on_it(strip, tmp_path):
    from vdo.commands.render import render_experiment
    from vdo.config.experiment import load

    render_experiment(load(strip), tmp_path / "run", scale=0.25)
    row = next(csv.DictReader((tmp_path / "run" / "photometry.csv").open()))
    assert 0 < int(row["n_interior"]) < int(row["n_samples"])
    assert float(row["b_render_dn"]) == pytest.approx(float(row["b_predicted_dn"]), rel=0.02)
    assert float(row["c_render_dn"]) == pytest.approx(float(row["c_render_predicted_dn"]), rel=0.05)
