"""The stereo-pair rule of the exports (`vdo.formats.export.default_pairs`): cameras assigned a
common region are paired only when their optical axes are at most the rule's maximum apart; the
lab's --pairs overrides it. Geometry: the holed plate's two cameras moved to ±65° from the plate's
normal (axes 130° apart, both still seeing the plate) against its own ±12.5° pair."""

from __future__ import annotations

import logging
import math
import re
import shutil
from pathlib import Path

import pytest

EXPERIMENT = Path(__file__).resolve().parents[2] / "experiments" / "holed_plate" / "stereo.toml"


def _state(tmp_path, text):
    from vdo.config.experiment import load
    from vdo.state import layout_state, prepare

    folder = tmp_path / "plate"
    shutil.copytree(EXPERIMENT.parent, folder)
    text = re.sub(r"(\[evaluation\]\s*\nsample_spacing_mm = )[0-9.]+", r"\g<1>5", text, count=1)
    (folder / EXPERIMENT.name).write_text(text)
    exp = load(folder / EXPERIMENT.name)
    state = layout_state(prepare(exp), predict_fields=False)
    return exp, list(state.cameras), state.visibility, state.samples


def _axes_deg(pair):
    return math.degrees(math.acos(pair.first.optical_axis @ pair.second.optical_axis))


def test_wide_pairs_are_not_exported_unless_requested(tmp_path, caplog):
    from vdo.formats.export import default_pairs

    text = EXPERIMENT.read_text()
    exp, cams, vis, samples = _state(tmp_path, text)
    pairs = default_pairs(exp, cams, vis, samples)
    assert [(p.first.name, p.second.name) for p in pairs] == [("left", "right")]
    assert _axes_deg(pairs[0]) < 60
    r, s = 0.7, math.sin(math.radians(65))
    wide = text.replace("position_m = [-0.152, -0.686, 1.0]",
                        f"position_m = [{-r * s:.4f}, {-r * math.cos(math.radians(65)):.4f}, 1.0]")
    wide = wide.replace("position_m = [0.152, -0.686, 1.0]",
                        f"position_m = [{r * s:.4f}, {-r * math.cos(math.radians(65)):.4f}, 1.0]")
    wide = wide.replace("min_angle_deg = 15\nmax_angle_deg = 35", "min_angle_deg = 15\nmax_angle_deg = 140")
    exp, cams, vis, samples = _state(tmp_path / "wide", wide)
    with caplog.at_level(logging.INFO, logger="vdo.formats.export"):
        assert default_pairs(exp, cams, vis, samples) == []
    assert "1 stereo pair(s) not exported: optical axes more than 60 deg apart" in caplog.text
    assert "left:right 130" in caplog.text
    forced = default_pairs(exp, cams, vis, samples, requested=[("left", "right")])
    assert _axes_deg(forced[0]) == pytest.approx(130, abs=1)
