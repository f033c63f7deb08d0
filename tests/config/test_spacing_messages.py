"""A region narrower than the sample spacing is refused in one line that names the spacing's own
field (`[evaluation]` or, in `vdo design`, `[design]` sample_spacing_mm), the region's extent and
the fix."""

from __future__ import annotations

import re
from dataclasses import replace

import pytest

from conftest import write_plate_experiment
from vdo.core.errors import ConfigError

STRIP = """
[[region]]
name = "strip"
mesh = "plate"
normal = [0, 0, 1]
box_min_m = [-0.5, 0.2, -1]
box_max_m = [0.5, 0.205, 1]
"""


def strip_experiment(tmp_path, spacing_mm):
    path = write_plate_experiment(tmp_path, spacing=spacing_mm)
    text = path.read_text()
    start = text.index("[[region]]")
    end = text.index("[[rail]]")
    path.write_text(text[:start] + STRIP + "\n" + text[end:])
    return path


@pytest.mark.parametrize("field", ["evaluation.sample_spacing_mm", "design.sample_spacing_mm"])
def test_a_strip_narrower_than_the_spacing_names_the_field_and_its_width(tmp_path, field):
    from vdo.config.experiment import load
    from vdo.state import prepare

    exp = load(strip_experiment(tmp_path, spacing_mm=100))
    with pytest.raises(ConfigError) as info:
        if field == "evaluation.sample_spacing_mm":
            prepare(exp)
        else:   # as vdo design samples: its own spacing written over the evaluation's
            prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=0.1)), spacing_field=field)
    message = str(info.value)
    assert 'region "strip"' in message and f"lower {field}" in message and "100 mm apart" in message
    # the strip is the box's 5 mm across the 1000 mm plate (faces split at the box)
    width, length = sorted(float(v) for v in re.search(r"span ([\d.]+) x ([\d.]+) mm", message).groups())
    assert width == pytest.approx(5.0, rel=1e-6) and length == pytest.approx(1000.0, rel=1e-6)
    # at a spacing below the strip's width the same region samples
    samples = prepare(load(strip_experiment(tmp_path, spacing_mm=2))).samples
    assert len(samples) > 0
