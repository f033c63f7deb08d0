"""Unfolded maps: every sample of a regular grid drawn (no white cell), nothing drawn past a
region's outline, and colour scales from the data's range."""

import textwrap

import numpy as np
import pytest
from PIL import Image

from conftest import write_box
from conftest import mesh_tables, region_tables
from vdo import scene
from vdo.config import experiment as config
from vdo.outputs import maps

PLATE = """
[experiment]
name = "vertical plate"
[evaluation]
sample_spacing_mm = 2
[[mesh]]
name = "plate"
file = "plate.stl"
unit = "mm"
role = "specimen"
[[region]]
name = "gauge_face"
mesh = "plate"
normal = [0, -1, 0]
[[region]]
name = "side_face"
mesh = "plate"
normal = [1, 0, 0]
[[rail]]
name = "r"
control_points_m = [[-1.0, -1.0, 0.1], [1.0, -1.0, 0.1]]
[[camera]]
name = "c"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
rail = "r"
u = 0.5
pan_deg = 90
tilt_deg = 0
"""


@pytest.fixture
def plate_samples(tmp_path):
    """A 60 x 20 x 300 mm upright plate sampled on a 2 mm grid by vdo's own sampler: sample centres
    sit on exact multiples of the spacing from the lowest one, where binning by floor((x - x_min) /
    spacing) put two samples in one raster cell and left its neighbour white."""
    write_box(tmp_path / "plate.stl", [60, 20, 300], center=[0, 0, 150])
    (tmp_path / "plate.toml").write_text(textwrap.dedent(PLATE))
    exp = config.load(tmp_path / "plate.toml")
    return scene.sample_regions(scene.load_meshes(**mesh_tables(exp)), **region_tables(exp))


def _inside_and_ring(boxes, name, shape, inset=3, outset=4):
    c0, r0, c1, r1 = boxes[name]
    inner = (slice(int(np.ceil(r0)) + inset, int(np.floor(r1)) - inset),
             slice(int(np.ceil(c0)) + inset, int(np.floor(c1)) - inset))
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    near = ((rows >= r0 - outset - 3) & (rows <= r1 + outset + 3)
            & (cols >= c0 - outset - 3) & (cols <= c1 + outset + 3))
    far = (rows < r0 - outset) | (rows > r1 + outset) | (cols < c0 - outset) | (cols > c1 + outset)
    return inner, near & far


@pytest.mark.parametrize("discrete", [True, False])
def test_every_sample_of_a_regular_grid_is_drawn(plate_samples, tmp_path, discrete):
    s = plate_samples
    assert len(s) == 30 * 150 + 10 * 150    # 60 x 300 mm face and 20 x 300 mm side at 2 mm
    values = np.full(len(s), 2.0) if discrete else 1.7 + 0.1 * s.points[:, 2]
    path = tmp_path / "map.png"
    boxes = maps.plot_unfolded(s, values, path, "plate " * 30, "cameras", discrete=discrete)
    rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    band = rgb[: rgb.shape[0] // 6]                 # the title (wrapped): clear of both edges
    assert (band < 200).any() and (band[:, :3] >= 250).all() and (band[:, -3:] >= 250).all()
    for name in ("gauge_face", "side_face"):
        inner, ring = _inside_and_ring(boxes, name, rgb.shape)
        cells = rgb[inner]
        assert cells.shape[0] > 100 and cells.shape[1] > 3
        white = np.all(cells >= 250, axis=-1)
        grey = np.all(np.abs(cells - 199) <= 2, axis=-1)          # NO_VALUE = 0.78 grey
        assert white.sum() == 0, f"{white.sum()} white pixels inside {name}"
        assert grey.sum() == 0
        # a band 4-7 px outside the outline: background (white) or text, never the field's colours
        band = rgb[ring]
        coloured = (band.max(axis=-1) - band.min(axis=-1)) > 40   # saturated = a colormap colour
        assert coloured.sum() == 0, f"{coloured.sum()} coloured pixels outside {name}"


def test_missing_values_grey_and_scale_from_data(plate_samples, tmp_path):
    s = plate_samples
    values = 1.7 + 0.1 * s.points[:, 2]
    values[::97] = np.nan
    values[5] = 40.0                                               # one outlier
    vmin, vmax, how = maps.color_range(values)
    finite = values[np.isfinite(values)]
    assert vmin == finite.min() and vmax == pytest.approx(np.percentile(finite, 98))
    assert "max 40" in how
    vmin, vmax, how = maps.color_range(np.array([1.71, 1.9, 2.35]))
    assert (vmin, vmax, how) == (1.71, 2.35, "data min – data max")
    path = tmp_path / "map.png"
    boxes = maps.plot_unfolded(s, values, path, "sigma", "σ (µm)")
    rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    inner, _ = _inside_and_ring(boxes, "gauge_face", rgb.shape, inset=1)
    grey = np.all(np.abs(rgb[inner] - 199) <= 2, axis=-1)
    # each missing sample is a 2 mm cell of about 1.8 x 1.8 px at this scale: some grey drawn
    assert grey.sum() >= 0.5 * np.isnan(values[s.region == 0]).sum()
