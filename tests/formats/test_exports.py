"""Calibration exports re-projected with each format's own convention, implemented here from its
documentation (docs/exports.md), against vdo's projection (with lens distortion)."""

import json
import re
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vdo.commands import cli
from vdo.config import experiment as config
from vdo.outputs import report
from vdo.core.errors import ConfigError
from vdo.commands.export import export
from vdo.scene import cameras_of

CAMERAS = """
[[camera]]
name = "left"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
position_m = [-0.5, -0.1, 1.4]
target_m = [0, 0, 0]
distortion = [-0.12, 0.03, 0.0012, -0.0008, 0.004]

[[camera]]
name = "right"
sensor_mm = [22.2, 14.8]
pixels = [640, 427]
focal_mm = 20
position_m = [0.5, 0.05, 1.3]
target_m = [0.02, 0, 0]
roll_deg = 7
principal_offset_px = [6.5, -4]
distortion = [0.08, -0.02, 0, 0, 0.003]

[[camera]]
name = "centre"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 28
position_m = [0, -0.6, 1.2]
target_m = [0, 0, 0]
distortion = [-0.05, 0, 0, 0, 0]

[[camera]]
name = "away"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
position_m = [0, 0, 1.5]
pan_deg = 0
tilt_deg = 80
"""
MM = 1e3


@pytest.fixture
def experiment(plate_experiment):
    path = plate_experiment(cameras=CAMERAS)
    exp = config.load(path)
    return path, {c.name: c for c in cameras_of(exp.camera_specs, exp.rails)}


def plate_points(n=200, seed=3):
    """World points (m) on and just above the plate's centre, seen by left, right and centre."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-0.12, 0.12, n), rng.uniform(-0.12, 0.12, n),
                            rng.uniform(0.0, 0.05, n)])


def distort_opencv(x, y, k1, k2, p1, p2, k3):
    """OpenCV's model (docs.opencv.org, calib3d): radial 1 + k1 r^2 + k2 r^4 + k3 r^6, tangential
    2 p1 x y + p2 (r^2 + 2 x^2), p1 (r^2 + 2 y^2) + 2 p2 x y."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


# --------------------------------------------------------------------------------------------
# OpenCV
# --------------------------------------------------------------------------------------------
def read_node(fs, key):
    node = fs.getNode(key)
    return node.mat() if node.isMap() else (node.string() or node.real())


def test_opencv_yaml_reprojects_with_cv2(experiment, tmp_path):
    path, cams = experiment
    written = export(path, "opencv", tmp_path / "out")
    names = sorted(p.name for p in written)
    assert names == sorted(["left.yml", "right.yml", "centre.yml", "away.yml",
                            "stereo_left_right.yml", "stereo_left_centre.yml",
                            "stereo_right_centre.yml"])      # "away" shares no view: no pair
    X = plate_points()
    for name, cam in cams.items():
        fs = cv2.FileStorage(str(tmp_path / "out" / f"{name}.yml"), cv2.FILE_STORAGE_READ)
        assert read_node(fs, "camera_name") == name
        size = int(read_node(fs, "image_width")), int(read_node(fs, "image_height"))
        assert size == (cam.width, cam.height)
        assert read_node(fs, "units") == "mm"
        rvec, _ = cv2.Rodrigues(read_node(fs, "R"))
        uv, _ = cv2.projectPoints(X * MM, rvec, read_node(fs, "t"), read_node(fs, "camera_matrix"),
                                  read_node(fs, "distortion_coefficients"))
        assert np.abs(uv[:, 0] - cam.project(X)).max() < 1e-6
    for first, second in (("left", "right"), ("left", "centre"), ("right", "centre")):
        a, b = cams[first], cams[second]
        fs = cv2.FileStorage(str(tmp_path / "out" / f"stereo_{first}_{second}.yml"), cv2.FILE_STORAGE_READ)
        assert (read_node(fs, "camera_name_1"), read_node(fs, "camera_name_2")) == (first, second)
        X1 = (X @ a.R.T + a.t) * MM                       # points in the first camera's frame, mm
        rvec, _ = cv2.Rodrigues(read_node(fs, "R"))
        uv2, _ = cv2.projectPoints(X1, rvec, read_node(fs, "T"), read_node(fs, "camera_matrix_2"),
                                   read_node(fs, "distortion_coefficients_2"))
        assert np.abs(uv2[:, 0] - b.project(X)).max() < 1e-6
        uv1, _ = cv2.projectPoints(X1, np.zeros(3), np.zeros(3), read_node(fs, "camera_matrix_1"),
                                   read_node(fs, "distortion_coefficients_1"))
        assert np.abs(uv1[:, 0] - a.project(X)).max() < 1e-6


# --------------------------------------------------------------------------------------------
# DICe: Teuchos ParameterList, world -> camera R (rows), T (mm), OPENCV_LENS_DISTORTION
# --------------------------------------------------------------------------------------------
def dice_cameras(path):
    root = ET.parse(path).getroot()
    top = {p.get("name"): p.get("value") for p in root.findall("Parameter")}
    assert top["xml_file_format"] == "DICe_xml_camera_system_file"
    assert top["extrinsics_relative_camera_to_camera"] == "false"
    cams = []
    for i, sub in enumerate(root.findall("ParameterList")):
        assert sub.get("name") == f"CAMERA {i}"
        p = {q.get("name"): q.get("value") for q in sub.findall("Parameter")}
        rows = {q.get("name"): q.get("value") for q in sub.find("ParameterList[@name='rotation_3x3_matrix']")}
        R = np.array([[float(v) for v in rows[f"ROW {r}"].strip("{} ").split(",")] for r in range(3)])
        cams.append((p, R))
    return cams


def dice_project(p, R, X_mm):
    """DICe's Camera: X_cam = R X + T, sensor = (x/z, y/z), OpenCV distortion, then fx, cx."""
    Xc = X_mm @ R.T + np.array([float(p[k]) for k in ("TX", "TY", "TZ")])
    x, y = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
    if p["LENS_DISTORTION_MODEL"] == "OPENCV_LENS_DISTORTION":
        x, y = distort_opencv(x, y, *(float(p[k]) for k in ("K1", "K2", "P1", "P2", "K3")))
    else:
        assert p["LENS_DISTORTION_MODEL"] == "NO_LENS_DISTORTION"
    return np.column_stack([x * float(p["FX"]) + float(p["CX"]), y * float(p["FY"]) + float(p["CY"])])


def test_dice_xml_reprojects_with_its_convention(experiment, tmp_path):
    path, cams = experiment
    written = {p.name for p in export(path, "dice", tmp_path / "out")}
    assert written == {"camera_system.xml", "left_right.xml", "left_centre.xml", "right_centre.xml"}
    X = plate_points()
    system = dice_cameras(tmp_path / "out" / "camera_system.xml")
    assert [p["CAMERA_ID"] for p, _ in system] == ["left", "right", "centre", "away"]
    for p, R in system:
        cam = cams[p["CAMERA_ID"]]
        h, w = (int(v) for v in p["IMAGE_HEIGHT_WIDTH"].strip("{} ").split(","))
        assert (w, h) == (cam.width, cam.height)
        assert np.abs(dice_project(p, R, X * MM) - cam.project(X)).max() < 1e-6
    pair = dice_cameras(tmp_path / "out" / "left_centre.xml")
    assert [p["CAMERA_ID"] for p, _ in pair] == ["left", "centre"]


# --------------------------------------------------------------------------------------------
# VIC-3D: <camera id>cx cy fx fy fs k1 k2 k3<orientation>alpha beta gamma tx ty tz</orientation>
# --------------------------------------------------------------------------------------------
def vic3d_rotation(alpha, beta, gamma):
    """DICe's eulers_to_rotation_matrix (degrees), written out element by element."""
    cx, sx, cy, sy, cz, sz = (f(np.radians(a)) for a in (alpha, beta, gamma) for f in (np.cos, np.sin))
    return np.array([[cy * cz, sx * sy * cz - cx * sz, cx * sy * cz + sx * sz],
                     [cy * sz, sx * sy * sz + cx * cz, cx * sy * sz - sx * cz],
                     [-sy, sx * cy, cx * cy]])


def test_vic3d_xml_reprojects_with_its_convention(experiment, tmp_path):
    path, cams = experiment
    written = export(path, "vic3d", tmp_path / "out", pairs=[("right", "centre")])
    assert [p.name for p in written] == ["right_centre.xml"]
    text = written[0].read_text()
    # the line layout DICe's VIC-3D reader tokenises (separators ' \t<>"'): 18 tokens per camera
    lines = [line for line in text.splitlines() if line.strip().startswith("<camera")]
    for line in lines:
        tokens = [t for t in re.split(r'[ \t<>"]+', line) if t]
        assert tokens[0] == "camera" and tokens[11] == "orientation" and len(tokens) >= 18
    root = ET.fromstring(text.split("?>", 1)[1].replace("<!DOCTYPE vpml>", ""))
    X = plate_points()
    for element, name in zip(root.find("calibration").findall("camera"), ("right", "centre")):
        cx, cy, fx, fy, fs, k1, k2, k3 = (float(v) for v in element.text.split())
        alpha, beta, gamma, tx, ty, tz = (float(v) for v in element.find("orientation").text.split())
        Xc = (X * MM) @ vic3d_rotation(alpha, beta, gamma).T + np.array([tx, ty, tz])
        x, y = distort_opencv(Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2], k1, k2, 0, 0, k3)
        uv = np.column_stack([fx * x + fs * y + cx, fy * y + cy])
        assert np.abs(uv - cams[name].project(X)).max() < 1e-6


def test_vic3d_refuses_tangential_distortion(experiment, tmp_path):
    path, _ = experiment
    with pytest.raises(ConfigError, match='camera "left".distortion.*tangential'):
        export(path, "vic3d", tmp_path / "out", pairs=[("left", "right")])
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# MatchID .caldat: Cam0 reference, X1 = R X0 + T, R = Rz(Psi) Ry(Phi) Rx(Theta), mm, degrees
# --------------------------------------------------------------------------------------------
def test_matchid_caldat_fields(experiment, tmp_path):
    path, cams = experiment
    written = export(path, "matchid", tmp_path / "out", pairs=[("left", "right")])
    assert [p.name for p in written] == ["left_right.caldat"]
    fields = dict(line.split(";") for line in written[0].read_text().splitlines())
    assert len(fields) == 26
    f = {k: float(v) for k, v in fields.items()}
    a, b = cams["left"], cams["right"]
    X = plate_points()
    X0 = (X @ a.R.T + a.t) * MM                           # first camera's frame, mm
    R = Rotation.from_euler("xyz", [f["Theta [deg]"], f["Phi [deg]"], f["Psi [deg]"]],
                            degrees=True).as_matrix()
    X1 = X0 @ R.T + np.array([f["Tx [mm]"], f["Ty [mm]"], f["Tz [mm]"]])
    for k, Xk, cam in ((0, X0, a), (1, X1, b)):
        K = np.array([[f[f"Cam{k}_Fx [pixels]"], f[f"Cam{k}_Fs [pixels]"], f[f"Cam{k}_Cx [pixels]"]],
                      [0, f[f"Cam{k}_Fy [pixels]"], f[f"Cam{k}_Cy [pixels]"]], [0, 0, 1]])
        dist = np.array([f[f"Cam{k}_Kappa 1"], f[f"Cam{k}_Kappa 2"], f[f"Cam{k}_P1"], f[f"Cam{k}_P2"],
                         f[f"Cam{k}_Kappa 3"]])
        uv, _ = cv2.projectPoints(Xk, np.zeros(3), np.zeros(3), K, dist)
        assert np.abs(uv[:, 0] - cam.project(X)).max() < 1e-6


# --------------------------------------------------------------------------------------------
# Run folders and bad input
# --------------------------------------------------------------------------------------------
def run_folder(path, tmp_path):
    """A run folder as vdo writes one: layout.json and the resolved config.toml."""
    exp = config.load(path)
    run = tmp_path / "run"
    run.mkdir()
    report.write_json(run / "layout.json", report.layout(cameras_of(exp.camera_specs, exp.rails)))
    report.write_config(run / "config.toml", exp)
    return run


def test_run_folder_exports_what_its_config_exports(experiment, tmp_path):
    path, _ = experiment
    run = run_folder(path, tmp_path)
    from_run = export(run, "dice", tmp_path / "a")
    from_config = export(path, "dice", tmp_path / "b")
    assert [p.name for p in from_run] == [p.name for p in from_config]
    number = re.compile(r"-?\d+\.?\d*(?:e[-+]?\d+)?")
    for p, q in zip(from_run, from_config):     # the same file up to the last digit (the pose
        a, b = p.read_text(), q.read_text()      # goes through degrees and micrometres)
        assert number.sub("#", a) == number.sub("#", b)
        np.testing.assert_allclose([float(x) for x in number.findall(a)],
                                   [float(x) for x in number.findall(b)], rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("name", ["optimized.toml", "designed.toml"])
def test_an_optimize_or_design_folder_exports_its_layout(experiment, tmp_path, name):
    """`vdo optimize` and `vdo design` write their layout as optimized.toml / designed.toml, not
    config.toml: the folder exports what that file exports."""
    path, _ = experiment
    run = run_folder(path, tmp_path)
    (run / "config.toml").rename(run / name)
    from_run = export(run, "opencv", tmp_path / "a")
    from_config = export(path, "opencv", tmp_path / "b")
    assert [p.name for p in from_run] == [p.name for p in from_config]
    (run / name).unlink()
    with pytest.raises(ConfigError, match="config.toml: missing .*optimized.toml or designed.toml"):
        export(run, "opencv", tmp_path / "c")


def test_edited_layout_is_refused(experiment, tmp_path):
    path, _ = experiment
    run = run_folder(path, tmp_path)
    layout = json.loads((run / "layout.json").read_text())
    layout["cameras"][1]["t"][0] += 0.01
    (run / "layout.json").write_text(json.dumps(layout))
    with pytest.raises(ConfigError, match='camera "right".t'):
        export(run, "opencv", tmp_path / "out")


def test_pair_without_shared_view_is_one_clear_line(experiment, tmp_path, capsys):
    path, _ = experiment
    code = cli.main(["export", str(path), "--format", "matchid", "--out", str(tmp_path / "o"),
                     "--pairs", "left:away"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "'left' and 'away' share no field of view" in err and "--pairs" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("args,message", [
    (["--format", "vicon"], "unknown format 'vicon'"),
    (["--format", "opencv", "--pairs", "left:nobody"], "no camera named 'nobody'"),
])
def test_bad_export_arguments(experiment, tmp_path, capsys, args, message):
    path, _ = experiment
    code = cli.main(["export", str(path), "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and message in err


def test_unsafe_camera_name_is_refused(plate_experiment, tmp_path):
    path = plate_experiment(cameras=CAMERAS.replace('name = "away"', 'name = "../away"'))
    with pytest.raises(ConfigError, match="names output files"):       # refused at load
        export(path, "opencv", tmp_path / "out")
    # a run folder's layout.json is not checked by the config: the export refuses the name itself
    import json

    from vdo.config import experiment as config
    from vdo.outputs import report

    run = tmp_path / "run"
    run.mkdir()
    exp = config.load(plate_experiment(cameras=CAMERAS))
    report.write_config(run / "config.toml", exp)
    layout = report.layout(cameras_of(exp.camera_specs, exp.rails))
    layout["cameras"][0]["name"] = "../away"
    (run / "layout.json").write_text(json.dumps(layout))
    with pytest.raises(ConfigError, match="cannot name an export file"):
        export(run, "opencv", tmp_path / "out2")
    assert not (tmp_path / "away.yml").exists() and not (tmp_path / "out2").exists()


def test_write_all_skips_what_a_format_cannot_hold(experiment, tmp_path, caplog):
    """`vdo render`'s calibration folder: VIC-3D is left out (with a warning) when a paired camera
    has tangential distortion; the other formats are written."""
    from vdo.formats.calibration import StereoPair
    from vdo.formats.export import write_all

    path, cams = experiment
    written = write_all(list(cams.values()), [StereoPair(cams["left"], cams["right"])],
                        tmp_path / "calibration", path, no_pair="")
    assert set(written) == {"opencv", "matchid", "dice"}
    assert sorted(p.name for p in (tmp_path / "calibration").iterdir()) == ["dice", "matchid", "opencv"]
    assert "vic3d calibration not written" in caplog.text and "tangential" in caplog.text


@pytest.fixture
def unpaired(experiment):
    """The plate's cameras with [optimize] assign_fraction = 0.99: only 'right' (all of the plate)
    is assigned it, 'left' (94 %) and 'centre' (81 %) are not, so no pair is assigned a common
    region (as an all-round rig's cameras, each seeing less than half of a region)."""
    path, cams = experiment
    path.write_text(path.read_text() + "\n[optimize]\nassign_fraction = 0.99\n")
    return path, cams


def test_no_default_pair_names_the_flag_and_a_pair(unpaired, tmp_path, capsys):
    """No default pair: the one-line error says why and names the fix, --pairs with the two
    cameras (axes within 60 deg) that see the most of the plate together, computed here from the
    ray cast; that pair then exports."""
    from conftest import raycast

    path, _ = unpaired
    exp, samples, cams, _, vis = raycast(path)
    seen = np.asarray(vis.visible, dtype=float) * samples.area
    together = seen @ np.asarray(vis.visible, dtype=float).T / samples.area.sum()
    assert np.sum(together.diagonal() >= exp.optimize.assign_fraction) == 1
    axes = np.array([c.optical_axis for c in cams])
    ok = np.degrees(np.arccos(np.clip(axes @ axes.T, -1, 1))) <= 60
    best = max(((i, j) for i in range(len(cams)) for j in range(i + 1, len(cams)) if ok[i, j]),
               key=lambda p: together[p])
    pair = f"{cams[best[0]].name}:{cams[best[1]].name}"

    code = cli.main(["export", str(path), "--format", "matchid", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and not (tmp_path / "o").exists()
    assert "no two cameras are assigned a common region" in err and "assign_fraction = 0.99" in err
    assert f"--pairs FIRST:SECOND, e.g. --pairs {pair} (together they see " \
           f"{together[best]:.0%} of region 'top'" in err
    assert cli.main(["export", str(path), "--format", "matchid", "--out", str(tmp_path / "o"),
                     "--pairs", pair]) == 0


def test_render_without_a_pair_says_how_to_name_one(unpaired, tmp_path, caplog):
    """`vdo render`'s calibration folder without a default pair: one warning for matchid and
    vic3d, with the fix; with no two cameras within max_pair_angle_deg sharing a view, the fix is
    to move them."""
    from conftest import raycast
    from vdo.formats.export import default_pairs, no_pair_message, write_all

    path, cams = unpaired
    exp, samples, cameras, _, vis = raycast(path)
    assert default_pairs(exp, cameras, vis, samples) == []
    message = no_pair_message(exp, cameras, vis, samples)
    written = write_all(list(cams.values()), [], tmp_path / "calibration", path, no_pair=message)
    assert set(written) == {"opencv", "dice"}
    lines = [r.getMessage() for r in caplog.records if "no stereo calibration" in r.getMessage()]
    assert lines == [f"matchid, vic3d: no stereo calibration written: {message}"]
    assert "--pairs FIRST:SECOND, e.g. --pairs " in message

    path.write_text(path.read_text() + "\n[analysis]\nmax_pair_angle_deg = 1\n")
    exp, samples, cameras, _, vis = raycast(path)
    assert no_pair_message(exp, cameras, vis, samples).endswith(
        "at most 1 deg apart, and no two such cameras see a point of a region together: move the "
        "cameras so that two share a view, then name them with --pairs FIRST:SECOND")
