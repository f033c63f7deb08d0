"""`vdo evaluate` writes a complete run folder that other tools read back."""

import json

import cv2
import numpy as np
import pytest
import trimesh

from conftest import DOWN_CAMERA, read_vtp, write_plate_experiment
from vdo.config import experiment as config
from vdo.commands.cli import main
from vdo.outputs.maps import unfold
from vdo.core.runfolder import run_folder
from vdo.model.surface import face_frame
from vdo.scene import SurfaceSamples, cameras_of


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One `vdo evaluate` run shared by the tests that read it (none of them writes into it)."""
    cams = DOWN_CAMERA.format(name="a", focal=24, u=0.4) + DOWN_CAMERA.format(name="b", focal=35, u=0.6)
    folder = tmp_path_factory.mktemp("outputs")
    path = write_plate_experiment(folder, cameras=cams)
    out = folder / "run"
    assert main(["evaluate", str(path), "--out", str(out), "--quiet"]) == 0
    return path, out


def test_run_folder_contents(run):
    _, out = run
    names = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert names == ["config.toml", "constraints.json", "layout.json", "maps/coverage.png", "maps/sensitivity_x.png",
                     "maps/sensitivity_y.png", "maps/sensitivity_z.png", "maps/view3d_coverage.png",
                     "report.html", "samples.vtp", "summary.json"]


def test_samples_vtp_reads_in_vtk_and_agrees_with_summary(run):
    _, out = run
    points, n_verts, arrays = read_vtp(out / "samples.vtp")
    assert n_verts == len(points) == 10_000
    assert {"normal", "region", "area", "coverage", "visible_a", "visible_b", "sensitivity_x",
            "sensitivity_y", "sensitivity_z", "sigma_max", "sigma_x", "sigma_y", "sigma_z"} <= set(arrays)
    # coverage counts the usable views (vdo.physics.usable), each of them a view the ray cast found clear
    np.testing.assert_array_equal(arrays["coverage"], arrays["usable_a"] + arrays["usable_b"])
    assert np.all(arrays["usable_a"] <= arrays["visible_a"]) and np.all(arrays["usable_b"] <= arrays["visible_b"])
    summary = json.loads((out / "summary.json").read_text())
    top = summary["regions"]["top"]
    area = arrays["area"]
    assert top["area_m2"] == pytest.approx(area.sum())
    assert top["seen_by_2_or_more"] == pytest.approx(area[arrays["coverage"] >= 2].sum() / area.sum())
    assert summary["settings"]["incidence_limit_deg"] == 75


def test_layout_reprojects_visible_samples_with_opencv(run):
    """Points a camera sees project inside its image through layout.json's K, R, t (OpenCV)."""
    _, out = run
    points, _, arrays = read_vtp(out / "samples.vtp")
    layout = json.loads((out / "layout.json").read_text())
    for cam in layout["cameras"]:
        K, R, t = (np.array(cam[k], dtype=float) for k in ("K", "R", "t"))
        seen = arrays[f"visible_{cam['name']}"].astype(bool)
        uv, _ = cv2.projectPoints(points[seen], cv2.Rodrigues(R)[0], t, K, np.zeros(5))
        uv = uv[:, 0]
        assert seen.sum() > 1000
        assert (uv[:, 0] >= -0.5).all() and (uv[:, 0] <= cam["width"] - 0.5).all()
        assert (uv[:, 1] >= -0.5).all() and (uv[:, 1] <= cam["height"] - 0.5).all()


def test_resolved_config_reloads_to_the_same_cameras(run):
    path, out = run
    original, resolved = config.load(path), config.load(out / "config.toml")
    for a, b in zip(cameras_of(original.camera_specs, original.rails), cameras_of(resolved.camera_specs, resolved.rails)):
        np.testing.assert_allclose(a.K, b.K)
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)


def test_existing_output_folder_is_not_overwritten(run, capsys):
    path, out = run
    assert main(["evaluate", str(path), "--out", str(out), "--quiet"]) == 2
    assert "exists and is not empty" in capsys.readouterr().err


def test_failed_run_leaves_nothing(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with run_folder(out) as tmp:
            (tmp / "half.json").write_text("{")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_first_angle_unfolding_of_a_box():
    """Each face of a box lands in its view, views do not overlap, and the top view sits below
    the front view (first-angle projection)."""
    box = trimesh.creation.box(extents=[2.0, 1.0, 0.5])
    pts, face = trimesh.sample.sample_surface(box, 3000, seed=1)
    normals = box.face_normals[face]
    tu, tv = np.array([face_frame(n) for n in normals]).transpose(1, 0, 2)
    samples = SurfaceSamples(points=pts, normals=normals, tangent_u=tu, tangent_v=tv,
                             uv=pts[:, :2], area=np.full(len(pts), 1e-3), region=np.zeros(len(pts), int),
                             region_names=("box",), region_importance=np.ones(1))
    sheet, view, panels, _, _ = unfold(samples)
    names = [p.name for p in panels]
    assert sorted(names) == sorted(["front", "top", "bottom", "left", "right", "back"])
    for k, p in enumerate(panels):
        mine = sheet[view == ["front", "top", "bottom", "left", "right", "back"].index(p.name)]
        assert (mine[:, 0] >= p.x0 - 1e-9).all() and (mine[:, 0] <= p.x0 + p.width + 1e-9).all()
        assert (mine[:, 1] >= p.y0 - 1e-9).all() and (mine[:, 1] <= p.y0 + p.height + 1e-9).all()
        for q in panels[k + 1:]:
            overlap_x = min(p.x0 + p.width, q.x0 + q.width) - max(p.x0, q.x0)
            overlap_y = min(p.y0 + p.height, q.y0 + q.height) - max(p.y0, q.y0)
            assert min(overlap_x, overlap_y) <= 0
    by = {p.name: p for p in panels}
    assert by["top"].y0 + by["top"].height < by["front"].y0         # plan view below the elevation
    assert by["left"].x0 > by["front"].x0 + by["front"].width       # left view to the right
    # panels span the samples' cells (side sqrt(area) = 3.2 cm) around points on the faces
    cell = np.sqrt(1e-3)
    assert 2.0 <= by["front"].width <= 2.0 + cell and 1.0 <= by["top"].height <= 1.0 + cell
