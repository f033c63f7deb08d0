"""report.html: opens in headless Chromium without console errors, draws a non-blank 3D view,
switches fields; the 3D geometry it reads back agrees with OpenCV and VTK; an interrupted run
folder gives a report that lists what is missing."""

import json
import shutil
import subprocess
import textwrap

import cv2
import numpy as np
import pytest
import trimesh
from PIL import Image

from conftest import DOWN_CAMERA, PLATE_TOML, write_box
from vdo.outputs import view3d
from conftest import mesh_tables, region_tables
from vdo.core import vtp
from vdo.commands.cli import main
from vdo.outputs.html_report import write_report

CHROMIUM = shutil.which("chromium")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A two-camera plate evaluated at 25 mm spacing (1,600 samples); evaluate writes the report."""
    folder = tmp_path_factory.mktemp("report")
    write_box(folder / "plate.stl", [1000, 1000, 10], center=[0, 0, -5])
    cams = DOWN_CAMERA.format(name="a", focal=24, u=0.4) + DOWN_CAMERA.format(name="b", focal=35, u=0.6)
    (folder / "plate.toml").write_text(textwrap.dedent(PLATE_TOML.format(
        spacing=25, limit=75, height=1.5, cameras=cams, extra_meshes="")))
    out = folder / "run"
    assert main(["evaluate", str(folder / "plate.toml"), "--out", str(out), "--quiet"]) == 0
    return out


def chromium(url: str, tmp_path, name: str):
    """Open `url` in headless Chromium: (console lines, the DOM after the scripts ran, a
    1200 x 1000 screenshot as an RGB float array)."""
    shot = tmp_path / f"{name}.png"
    args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
            "--enable-logging=stderr", "--v=0", "--hide-scrollbars", "--window-size=1200,1000",
            "--virtual-time-budget=8000", "--dump-dom", f"--screenshot={shot}", url]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=90, cwd=tmp_path)
    console = [line for line in proc.stderr.splitlines() if "CONSOLE" in line]
    return console, proc.stdout, np.asarray(Image.open(shot).convert("RGB")).astype(float)


def test_report_is_self_contained(run):
    page = (run / "report.html").read_text()
    assert "<script src=" not in page and 'src="http' not in page     # nothing fetched
    assert "Plotly.newPlot" in page and 'class="missing"' not in page
    assert "<td>top</td>" in page                                       # the region table
    assert (run / "maps" / "view3d_coverage.png").is_file()


def test_interrupted_run_says_what_is_missing(run, tmp_path):
    cut = tmp_path / "cut"
    shutil.copytree(run, cut)
    (cut / "report.html").unlink()
    (cut / "layout.json").unlink()
    data = (cut / "samples.vtp").read_bytes()
    (cut / "samples.vtp").write_bytes(data[: len(data) // 2])         # cut short
    page = write_report(cut).read_text()
    assert "Missing from this evaluate run folder" in page
    assert "layout.json (no camera is drawn)" in page and "samples.vtp unreadable" in page
    (cut / "extra.json").write_text("{not json")
    assert "extra.json unreadable" in write_report(cut).read_text()
    (cut / "extra.json").unlink()
    (cut / "summary.json").unlink()
    (cut / "samples.vtp").unlink()
    assert main(["report", str(cut)]) == 0
    assert main(["report", str(tmp_path / "nowhere")]) == 2
    page = (cut / "report.html").read_text()
    assert "summary.json (no region table)" in page and "samples.vtp (no field is drawn)" in page


def _png(path):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2, 2))
    ax.plot([0, 1], [1, 0])
    fig.savefig(path)
    plt.close(fig)


def test_optimize_and_sweep_folders(run, tmp_path):
    opt = tmp_path / "opt"
    opt.mkdir()
    shutil.copy(run / "config.toml", opt / "optimized.toml")
    shutil.copy(run / "layout.json", opt / "layout.json")
    before = json.loads((run / "summary.json").read_text())
    after = json.loads((run / "summary.json").read_text())
    after["regions"]["top"]["seen_by_2_or_more"] = 0.987654
    (opt / "summary_before.json").write_text(json.dumps(before))
    (opt / "summary_after.json").write_text(json.dumps(after))
    (opt / "constraints.json").write_text(json.dumps({"violations": 0, "violated": [],
                                                      "after": [{"constraint": "axis_angle",
                                                                 "value": 31.5, "met": True}]}))
    _png(opt / "convergence.png")
    page = write_report(opt).read_text()
    assert 'class="missing"' not in page and "Before and after optimizing" in page
    assert "0.9877" in page and "axis_angle" in page and "<h2>Cameras</h2>" in page
    assert page.count("<img alt=") == 1 and 'alt="convergence.png"' in page
    assert '"text":["a","b"]' in page and "<td>a</td>" in page       # cameras: 3D and table
    (opt / "convergence.png").unlink()
    assert "convergence.png (no convergence figure)" in write_report(opt).read_text()

    sweep = tmp_path / "sweep"
    (sweep / "figures").mkdir(parents=True)
    (sweep / "results.csv").write_text("variant,focal_mm,joint_p95_um\nv1,24,0.31\nv2,35,0.27\n")
    _png(sweep / "figures" / "p95_vs_focal.png")
    page = write_report(sweep).read_text()
    assert "results.csv (2 rows)" in page and "<td>v2</td>" in page and "<td>0.27</td>" in page
    assert 'alt="figures/p95_vs_focal.png"' in page and 'class="missing"' not in page


def test_frustum_corners_project_to_the_image_corners_in_opencv(run):
    layout = json.loads((run / "layout.json").read_text())
    for cam in layout["cameras"]:
        K, R, t = (np.array(cam[k], dtype=float) for k in ("K", "R", "t"))
        centre, corners = view3d.frustum(K, R, t, cam["width"], cam["height"], 0.7)
        px, _ = cv2.projectPoints(corners, cv2.Rodrigues(R)[0], t, K, None)
        w, h = cam["width"], cam["height"]
        expected = [[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]]
        np.testing.assert_allclose(px[:, 0], expected, atol=1e-6)
        np.testing.assert_allclose((R @ corners.T).T[:, 2] + t[2], 0.7, atol=1e-9)   # depth
        np.testing.assert_allclose(R @ centre + t, 0, atol=1e-9)


def test_cells_from_the_run_folder_are_the_samplers(run):
    """The 3D view rebuilds each sample's cell from samples.vtp: it matches the cell of the sample
    as vdo's sampler made it, up to the lift off the face; the static figure shows it."""
    from vdo import scene
    from vdo.config import experiment as config
    from vdo.outputs import maps

    sc = view3d.load(run)
    exp = config.load(run / "config.toml")
    samples = scene.sample_regions(scene.load_meshes(**mesh_tables(exp)), **region_tables(exp))
    lift = 0.1 * np.sqrt(samples.area)[:, None, None] * samples.normals[:, None, :]
    np.testing.assert_allclose(view3d.cells(sc), maps.cell_corners(samples) + lift, atol=1e-12)
    assert [c[0] for c in sc.cameras] == ["a", "b"] and sc.unreadable == []
    rgb = np.asarray(Image.open(run / "maps" / "view3d_coverage.png").convert("RGB")).astype(int)
    coloured = (rgb.max(axis=-1) - rgb.min(axis=-1)) > 60        # viridis, not grey axes
    assert coloured.mean() > 0.02


def test_vtp_read_back_equals_vtk(run):
    from vtk import vtkXMLPolyDataReader
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(run / "samples.vtp"))
    reader.Update()
    pd = reader.GetOutput().GetPointData()
    ref = {pd.GetArrayName(i): vtk_to_numpy(pd.GetArray(i)) for i in range(pd.GetNumberOfArrays())}
    points, arrays = vtp.read_points(run / "samples.vtp")
    np.testing.assert_array_equal(points, vtk_to_numpy(reader.GetOutput().GetPoints().GetData()))
    assert set(arrays) == set(ref)
    for name, values in ref.items():
        np.testing.assert_array_equal(arrays[name], values)


def test_decimate_keeps_the_shape():
    sphere = trimesh.creation.icosphere(subdivisions=5)                 # 20,480 faces
    v, f = view3d.decimate(sphere.vertices, sphere.faces, 3000)
    assert 500 < len(f) <= 3000
    radius = np.linalg.norm(v, axis=1)
    assert np.abs(radius - 1).max() < 0.05
    np.testing.assert_allclose(np.ptp(v, axis=0), 2.0, rtol=0.05)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (as root: apt-get install -y "
                                             "chromium, or run scripts/setup.sh)")
def test_report_in_headless_chromium(run, tmp_path):
    url = (run / "report.html").as_uri()
    shots = {}
    for field in ("coverage", "sensitivity_x"):
        console, dom, shots[field] = chromium(f"{url}#field={field}", tmp_path, field)
        errors = [c for c in console if any(w in c.lower() for w in ("error", "uncaught",
                                                                      "exception", "failed"))]
        assert errors == []
        assert f'data-field="{field}"' in dom                   # the page's script ran to the end
    plot = (slice(200, 880), slice(100, 900))                   # the 3D view, left of the bar
    area = shots["coverage"][plot]
    background = np.all(area >= 245, axis=-1)
    assert area.std() > 20 and (~background).mean() > 0.05      # not blank
    diff = np.abs(shots["coverage"][plot] - shots["sensitivity_x"][plot]).max(axis=-1) > 30
    assert diff.mean() > 0.01                                   # the field changed the colours


@pytest.mark.parametrize("files, kind", [(["series.json", "config.toml"], "series"),
                                         (["target.yml", "summary.json"], "calibrate"),
                                         (["render.json"], "render"), (["summary.json"], "evaluate")])
def test_a_series_or_calibrate_folder_is_reported_as_what_it_is(tmp_path, files, kind):
    """`vdo render --series` and `vdo calibrate` folders are their own kinds: the report does not
    call a complete one an interrupted evaluate or render run."""
    from vdo.outputs.html_report import EXPECTED, kind_of

    for f in files:
        (tmp_path / f).write_text("{}")
    assert kind_of(tmp_path) == kind
    assert set(files) <= set(EXPECTED[kind]) or kind == "evaluate"


def test_a_folder_no_run_wrote_is_refused(tmp_path, capsys):
    """`vdo report` on a folder that no vdo command wrote (trial 4: an empty report, exit 0): one
    line, exit 2, nothing written; one file of a run is enough to report it."""
    from vdo.commands.cli import main

    (tmp_path / "notes.txt").write_text("mine")
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {tmp_path}: RUN_DIR: holds none of the files a vdo run writes "
                   "(summary.json, layout.json, ...): give the --out folder of a vdo command"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]
    (tmp_path / "render.json").write_text("{}")
    assert main(["report", str(tmp_path)]) == 0 and (tmp_path / "report.html").is_file()
