"""A camera's u off a rail whose ends meet (a ring) or nearly meet is refused with what to write:
on a closed rail, the same place within [0, 1]; on one whose last control point misses its first
by 2 mm, that it is open and how to close it. Both for a [[rail]] and a rail [[mount]]."""

from __future__ import annotations

import pytest

from conftest import write_plate_experiment
from vdo.core.errors import ConfigError

SQUARE = [[2, -2, 1.5], [2, 2, 1.5], [-2, 2, 1.5], [-2, -2, 1.5]]


def ring(table: str, last) -> str:
    points = ", ".join(str(p) for p in SQUARE + [last])
    kind = 'kind = "rail"\n' if table == "mount" else ""
    return f"""
[[{table}]]
name = "ring"
{kind}control_points_m = [{points}]

[[camera]]
name = "cam"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
{'mount' if table == 'mount' else 'rail'} = "ring"
u = 1.25
target_m = [0.0, 0.0, 0.0]
"""


@pytest.mark.parametrize("table", ["rail", "mount"])
def test_off_a_closed_ring_names_the_same_place(tmp_path, table):
    from vdo.config.experiment import load

    path = write_plate_experiment(tmp_path, cameras=ring(table, SQUARE[0]))
    with pytest.raises(ConfigError, match=r"camera \"cam\"\.u: = 1\.25 is off rail .*'ring'.*the rail is closed"
                                          r".*so u = 1\.25 is the place u = 0\.25: write that"):
        load(path)
    # the place it names loads
    path.write_text(path.read_text().replace("u = 1.25", "u = 0.25"))
    exp = load(path)
    assert exp.camera_specs[0].u == 0.25


@pytest.mark.parametrize("table", ["rail", "mount"])
def test_off_a_ring_that_misses_its_start_by_2_mm_says_it_is_open(tmp_path, table):
    from vdo.config.experiment import load

    path = write_plate_experiment(tmp_path, cameras=ring(table, [2, -1.998, 1.5]))
    with pytest.raises(ConfigError, match=r"its ends are 2 mm apart, so it is open, not a ring: to close it, "
                                          r"make its last control point exactly its first"):
        load(path)


def test_off_an_open_bar_says_the_range_alone(tmp_path):
    from vdo.config.experiment import load

    path = write_plate_experiment(tmp_path)
    path.write_text(path.read_text().replace("u = 0.5", "u = 1.3"))
    with pytest.raises(ConfigError) as info:
        load(path)
    assert str(info.value).endswith("is off rail 'overhead': the rail parameter runs from 0 to 1")
