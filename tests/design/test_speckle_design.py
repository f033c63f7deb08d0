"""`vdo speckle` (`vdo.design.pattern`) on a plate seen by a 24 mm and a 50 mm lens: the printed
file's physical scale and scale bar and the tile's dot sizes measured with OpenCV, the chosen
pattern used by an experiment (its speckle model from the written tile reproduces the design's
sigma), and a print resolution too coarse for the dots (one line)."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from PIL import Image

from conftest import DOWN_CAMERA, write_plate_experiment
from vdo.commands.cli import main
from vdo.config import experiment as config
from vdo.design import pattern
from vdo.outputs import report
from vdo.physics.predict import predict, speckle_model
from vdo.state import layout_state, prepare

LIGHT = """
[[light]]
name = "panel"
position_m = [0.3, 0.0, 1.2]
target_m = [0.0, 0.0, 0.0]
size_m = [0.6, 0.6]
radiance = 60.0

[design]
sample_spacing_mm = 50
"""

# a dot's radius from the distance transform of the tile thresholded at 0.5: within a texel of
# D / 2, 2 % for the dots of these tests (>= 50 texels in radius)
DOT_RADIUS_RTOL = 0.02


def _plate(folder, extra=""):
    cams = (DOWN_CAMERA.format(name="wide", focal=24, u=0.45)
            + DOWN_CAMERA.format(name="long", focal=50, u=0.55))
    path = write_plate_experiment(folder, spacing=50, cameras=cams)
    path.write_text(path.read_text() + LIGHT + extra)
    return path


@pytest.fixture(scope="module")
def designed(tmp_path_factory):
    folder = tmp_path_factory.mktemp("speckle")
    path = _plate(folder)
    out = folder / "out"
    assert main(["speckle", str(path), "--out", str(out), "--quiet"]) == 0
    return path, out, json.loads((out / "speckle.json").read_text())


def test_the_print_is_at_physical_scale_with_a_ten_mm_bar(designed):
    path, out, data = designed
    r = data["regions"]["top"]
    with Image.open(out / "top.png") as im:
        dpi = im.info["dpi"][0]
        img = np.asarray(im.convert("L"))
    assert dpi == pytest.approx(600, rel=1e-3)
    side = r["tile_texels"] * r["print_repeats"]
    assert img.shape[1] == side                              # one printer dot per texel
    assert side * r["texel_mm"] >= pattern.SHEET_MM
    margin = img[side:] < 128                                # below the tiles: the bar and the text
    n, labels, stats, _ = cv2.connectedComponentsWithStats(margin.astype(np.uint8), connectivity=8)
    widest = stats[1:, cv2.CC_STAT_WIDTH].max()
    assert widest == pytest.approx(pattern.SCALE_BAR_MM / pattern.MM_PER_INCH * 600, abs=2)


def test_the_tiles_dots_have_the_designed_sizes(designed):
    """OpenCV's exact Euclidean distance transform of the thresholded tile's black: its local
    maxima are the dot centres (overlapping dots included) with the value of their radius, so
    they gather at D / 2 of each designed size D (in texels), and nowhere in between."""
    path, out, data = designed
    r = data["regions"]["top"]
    black = (np.asarray(Image.open(out / "top_tile.png").convert("L")) < 128).astype(np.uint8)
    dt = cv2.distanceTransform(black, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    peak = (dt == cv2.dilate(dt, np.ones((5, 5), np.uint8))) & (dt > 3)
    values = dt[peak]
    radii = [d / 2 / r["texel_mm"] for d in r["dots_mm"]]
    for radius in radii:
        near = values[np.abs(values / radius - 1) < 0.05]
        assert len(near) >= 20
        assert np.median(near) == pytest.approx(radius, rel=DOT_RADIUS_RTOL)
    if len(radii) == 2:   # between the two sizes: only where dots overlap, far fewer centres
        between = values[(values > 1.1 * radii[0]) & (values < 0.9 * radii[1])]
        assert len(between) < len(values[np.abs(values / radii[0] - 1) < 0.05])


def test_the_written_pattern_is_used_by_an_experiment(designed):
    """The region's [speckle] snippet in the experiment: its speckle model (read from the tile
    PNG) predicts the sigma the design reported for it."""
    path, out, data = designed
    snippet = (out / "top.toml").read_text().replace('image = "top_tile.png"',
                                                     f'image = "{out / "top_tile.png"}"')
    used = path.with_name("used.toml")
    used.write_text(path.read_text() + snippet)
    exp = config.load(used)
    assert exp.speckle.image is not None
    exp = replace(exp, evaluation=replace(exp.evaluation, sample_spacing=exp.design.sample_spacing))
    geometry = prepare(exp)
    model = speckle_model(exp.speckle)
    state = layout_state(geometry, predict_fields=False)
    pred = predict(exp.regions, exp.evaluation, exp.speckle, exp.sensor, list(state.cameras), state.samples,
                   state.visibility, state.illumination, model, overlap=geometry.overlap)
    p95 = report.summary(exp, state.samples, state.visibility, pred)["regions"]["top"]["sigma_max_um"]["p95"]
    # the PNG holds 8-bit grays of the float tile: sigma within a fraction of a percent
    assert p95 == pytest.approx(data["regions"]["top"]["sigma_p95_um"], rel=5e-3)


def test_the_choice_has_the_fewest_flags_then_the_lowest_sigma(designed):
    _, _, data = designed
    r = data["regions"]["top"]
    ranks = [(len(c["flags"]["top"]), c["sigma_p95_um"]["top"]) for c in data["candidates"]]
    assert (len(r["flags"]), r["sigma_p95_um"]) == min(ranks)
    # the footprints differ by more than 5/3: a two-size mix is among the candidates
    fp = data["footprints_mm_per_px"]["top"]
    assert max(fp.values()) / min(fp.values()) > 5 / 3
    assert any(len(c["dots_mm"]) == 2 for c in data["candidates"])


def test_a_print_resolution_too_coarse_for_the_dots_is_one_line(tmp_path, capsys):
    path = _plate(tmp_path)
    path.write_text(path.read_text().replace("[design]", "[speckle]\nprint_dpi = 10\n\n[design]"))
    assert main(["speckle", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "speckle.print_dpi" in err[0] and "dpi or more" in err[0] and str(path) in err[0]
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
