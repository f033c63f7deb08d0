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
    assert "1 camera pair(s) assigned a common region left out of the stereo pairs: optical axes " \
           "more than 60 deg apart ([analysis] max_pair_angle_deg; naming pairs with --pairs " \
           "FIRST:SECOND overrides)" in caplog.text
    assert "left:right 130" in caplog.text
    forced = default_pairs(exp, cams, vis, samples, requested=[("left", "right")])
    assert _axes_deg(forced[0]) == pytest.approx(130, abs=1)


def test_a_pair_closer_than_its_minimum_angle_is_exported_with_a_warning(tmp_path, caplog):
    """The plate's pair declares min_angle_deg = 15; its cameras moved to x = ±0.05 m (axes
    ~8° apart, measured here) stay the exported pair, and the warning names it with both angles."""
    from vdo.formats.export import default_pairs

    text = EXPERIMENT.read_text()
    near = text.replace("position_m = [-0.152, -0.686, 1.0]", "position_m = [-0.05, -0.686, 1.0]")
    near = near.replace("position_m = [0.152, -0.686, 1.0]", "position_m = [0.05, -0.686, 1.0]")
    exp, cams, vis, samples = _state(tmp_path, near)
    with caplog.at_level(logging.WARNING, logger="vdo.formats.export"):
        pairs = default_pairs(exp, cams, vis, samples)
    assert [(p.first.name, p.second.name) for p in pairs] == [("left", "right")]
    angle = _axes_deg(pairs[0])
    assert angle < 15
    assert f"left:right {angle:.1f} (min 15) deg; move a camera apart or name better pairs with " \
           "--pairs FIRST:SECOND" in caplog.text, caplog.text
    caplog.clear()
    exp, cams, vis, samples = _state(tmp_path / "as shipped", text)
    with caplog.at_level(logging.WARNING, logger="vdo.formats.export"):
        default_pairs(exp, cams, vis, samples)
    assert "closer than" not in caplog.text


LOOKING = """
[[camera]]
name = "{name}"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 50
rail = "overhead"
u = {u}
target_m = [{x}, 0.0, 0.0]
"""


def test_a_region_the_exported_pairs_leave_half_uncovered_is_named_with_the_pairs_to_add(
        tmp_path, plate_experiment, caplog):
    """Four 50 mm cameras over a 1 m plate, two on its left half (l1, l2), two on its right (r1,
    r2), each seeing about a quarter of it (none assigned the region, so no default pair): with
    only l1:l2 exported the export warns that region "top" is covered on its left only, with the
    fractions counted here from the ray cast, and suggests r1:r2 beside l1:l2; with both pairs it
    says nothing."""
    import numpy as np

    from vdo.commands.export import export
    from vdo.config.experiment import load
    from vdo.formats.export import PAIR_GAP, uncovered_regions
    from vdo.state import layout_state, prepare

    cams = "".join(LOOKING.format(name=n, u=u, x=x) for n, u, x in
                   (("l1", 0.30, -0.25), ("l2", 0.45, -0.25), ("r1", 0.55, 0.25), ("r2", 0.70, 0.25)))
    path = plate_experiment(spacing=25, cameras=cams)
    exp = load(path)
    state = layout_state(prepare(exp), predict_fields=False)
    vis, samples = state.visibility, state.samples
    seen = np.asarray(vis.visible, bool)
    area = samples.area / samples.area.sum()
    left, right = float(area[seen[0] & seen[1]].sum()), float(area[seen[2] & seen[3]].sum())
    assert 0.15 < left < 0.35 and 0.15 < right < 0.35 and right > PAIR_GAP   # the scene as meant

    with caplog.at_level(logging.WARNING, logger="vdo.commands.export"):
        export(path, "opencv", tmp_path / "one", pairs=[("l1", "l2")])
    warned = [r.getMessage() for r in caplog.records if "uncovered by the exported stereo" in r.getMessage()]
    assert len(warned) == 1, caplog.text
    assert f"top (100% of all regions' area): {left:.0%} of it seen by both cameras of an " \
           "exported pair" in warned[0]
    assert warned[0].endswith("e.g. --pairs l1:l2 r1:r2"), warned[0]

    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="vdo.commands.export"):
        export(path, "opencv", tmp_path / "both", pairs=[("l1", "l2"), ("r1", "r2")])
    assert "uncovered" not in caplog.text
    assert "top" in uncovered_regions(exp, list(state.cameras), vis, samples, [])   # no pair at all
