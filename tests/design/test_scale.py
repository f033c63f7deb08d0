"""Scale: the generated large experiment of benchmarks/scale_case.py at reduced size; costs that
follow the work (region boxes sharing planes split once, maps of hundreds of regions labelled by
group) checked against closed forms."""

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from conftest import mesh_tables, region_tables
from vdo import scene
from vdo.config import experiment as config
from vdo.outputs import maps

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from scale_case import HALF_W, Z_HI, Z_LO, write_case  # noqa: E402

# binary STL stores float32 vertices (0.9 m is 0.89999998): cut planes between them leave slivers
# about 1e-7 m wide, ~5e-6 of a 67 mm segment's area
STL_AREA_REL = 1e-5


@pytest.fixture(scope="module")
def girder(tmp_path_factory):
    """A 2 m girder cut into 4 faces x 30 segments = 120 regions, 4 cameras, 40 mm samples."""
    path = write_case(tmp_path_factory.mktemp("girder"), length_m=2.0, segments=30, cameras=4,
                      spacing_mm=40)
    exp = config.load(path)
    meshes = scene.load_meshes(**mesh_tables(exp))
    return exp, meshes, scene.sample_regions(meshes, **region_tables(exp))


def test_region_areas_with_shared_planes(girder):
    """Neighbouring regions share their box planes (each plane split at once): the area of every
    region's faces is its face's width times the segment length (closed form), the girder stays
    closed and its area unchanged."""
    exp, meshes, _ = girder
    assert len(exp.regions) == 120
    seg = 2.0 / 30
    width = {"front": Z_HI - Z_LO, "back": Z_HI - Z_LO, "top": 2 * HALF_W, "bottom": 2 * HALF_W}
    g = next(m for m in meshes if m.name == "girder")
    for spec in exp.regions:
        faces = scene.region_faces(g, spec, 0.04, (exp.path, "region")).faces
        area = g.trimesh.area_faces[faces].sum()
        assert area == pytest.approx(seg * width[spec.name.split("_")[0]], rel=STL_AREA_REL), spec.name
    mesh = trimesh.Trimesh(g.vertices, g.faces)
    assert mesh.is_watertight
    assert mesh.area == pytest.approx(trimesh.load(exp.meshes[0].path).area, rel=1e-12)   # as read


def test_map_of_many_regions_labels_groups(girder, tmp_path):
    """Past MAX_REGION_LABELS regions, one label per region group (its name and count) in each view
    it fills, every region still outlined and its pixel box returned inside the image."""
    exp, _, samples = girder
    assert maps.region_groups(["front_000", "front_001", "joint", "back-12"]) == \
        {"front": [0, 1], "joint": [2], "back": [3]}
    lay = maps.layout(samples)
    assert lay is maps.layout(samples)                      # shared by every map of these samples
    assert len(lay.hulls) == 120
    assert sorted(t for t, _ in lay.labels) == ["back (30)", "bottom (30)", "front (30)", "top (30)"]
    path = tmp_path / "map.png"
    boxes = maps.plot_unfolded(samples, samples.points[:, 0], path, "x", "m")
    h, w = np.asarray(Image.open(path)).shape[:2]
    assert len(boxes) == 120
    for c0, r0, c1, r1 in boxes.values():
        assert 0 <= c0 < c1 <= w and 0 <= r0 < r1 <= h


def test_load_path_changes_that_matter_are_named_with_their_thresholds():
    """The issue's cases: sigma p95 2.06 -> 8.94 um with coverage still whole, a face losing 26 %
    of its coverage; below the thresholds (x1.4, 4 points) nothing; unmeasured at a step: x inf."""
    from vdo.search import loadpath

    steps = ("rest", 1, 2)
    p95 = np.array([[2.06, 1.0, 1.0, 3.0], [2.0, 1.0, 1.4, np.nan], [8.94, 1.0, 1.2, 3.0]]) * 1e-6
    covered = np.array([[1.0, 1.0, 1.0, 1.0], [1.0, 0.74, 0.96, 1.0], [1.0, 0.9, 0.97, 1.0]])
    got = loadpath.region_changes(("root", "bottom", "calm", "lost"), steps, covered, p95)
    assert [(c["region"], c["kind"], c["step"]) for c in got] == [
        ("root", "sigma", 2), ("bottom", "coverage", 1), ("lost", "sigma", 1)]
    assert got[0]["ratio"] == pytest.approx(8.94 / 2.06) and got[1]["drop"] == pytest.approx(0.26)
    assert got[2]["ratio"] == np.inf and got[2]["value_um"] is None
    assert 1.4 < loadpath.SIGMA_RATIO and 0.04 < loadpath.COVERAGE_DROP


def test_console_summary_of_many_regions_is_per_group(capsys):
    """Past MAX_ROWS regions the console table has one row per region group: areas summed,
    coverage area-weighted, the worst p95 (hand-computed here)."""
    from vdo.commands import cli

    def region(area, seen, p95):
        return {"area_m2": area, "seen_by_1_or_more": seen, "seen_by_2_or_more": seen,
                "seen_by_3_or_more": 0.0, "sensitivity_mpx_per_um": {"x": 1.0, "y": 2.0, "z": 3.0},
                "sigma_max_um": {"p50": p95 / 2, "p95": p95}}

    regions = {f"front_{k:03d}": region(0.1, 1.0, 1.0 + k / 100) for k in range(30)}
    regions |= {f"top_{k:03d}": region(0.3 if k else 0.6, 0.0 if k else 1.0, 2.0) for k in range(20)}
    unmeasured = {"p50": None, "p95": None}     # a group partly unmeasured: its median, no worst p95
    regions |= {f"bottom_{k:03d}": region(0.1, 1.0, 1.0) if k else {**region(0.1, 0.0, 1.0), "sigma_max_um": unmeasured}
                for k in range(3)}
    regions |= {f"back_{k:03d}": {**region(0.1, 0.0, 1.0), "sigma_max_um": unmeasured} for k in range(2)}
    cli._print_summary({"regions": regions})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("55 regions in 4 groups") and len(lines) == 6
    front, top, bottom, back = (line.split() for line in lines[2:])
    assert front[:3] == ["front", "(30)", "3.000"] and front[-1].endswith("/1.29")
    assert top[:4] == ["top", "(20)", "6.300", f"{100 * 0.6 / 6.3:.0f}%"]
    assert bottom[:2] == ["bottom", "(3)"] and bottom[-1] == "0.50/-" and back[-1] == "-"
