"""A band around a point or an axis given as if in millimetres is refused in one line before any
work: within_m more than ten times the mesh's size (the band cuts nothing off it), or a point far
from the mesh; an axis through the mesh given by far points is still a band. The plate is 1 m x
1 m x 10 mm: its bounding box's diagonal is sqrt(2 + 1e-4) m."""

from __future__ import annotations

import math

import pytest

from conftest import write_plate_experiment
from vdo.core.errors import ConfigError

SIZE = math.sqrt(2 + 1e-4)


def with_band(tmp_path, band: str):
    path = write_plate_experiment(tmp_path)
    path.write_text(path.read_text().replace('normal = [0, 0, 1]', 'normal = [0, 0, 1]\n' + band))
    return path


def test_within_in_millimetres(tmp_path):
    from vdo.config.experiment import load
    from vdo.state import prepare

    path = with_band(tmp_path, "near_point_m = [0, 0, 0]\nwithin_m = 150")
    with pytest.raises(ConfigError, match=rf'region "top": within_m = 150 m is more than 10 times the size of '
                                          rf"mesh 'plate' \({SIZE:.3g} m across\).*divide them by 1000"):
        prepare(load(path))


def test_point_in_millimetres(tmp_path):
    from vdo.config.experiment import load
    from vdo.state import prepare

    path = with_band(tmp_path, "near_point_m = [200, 300, 0]\nwithin_m = 0.1")
    far = math.hypot(200 - 0.5, 300 - 0.5)          # to the box's corner (0.5, 0.5) in its plane
    with pytest.raises(ConfigError, match=rf"near_point_m lies {far:.4g} m from mesh 'plate'"):
        prepare(load(path))


def test_an_axis_through_the_mesh_from_far_points_is_a_band(tmp_path):
    from vdo.config.experiment import load
    from vdo.state import prepare

    path = with_band(tmp_path, "near_axis_m = [[0, 0, -50], [0, 0, 50]]\nwithin_m = 0.3")
    samples = prepare(load(path)).samples
    assert len(samples) and (samples.points[:, :2] ** 2).sum(axis=1).max() <= 0.3 ** 2
