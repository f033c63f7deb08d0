"""A lab's own calibration as the experiment's cameras: the files vdo exports (`vdo.formats`:
OpenCV, VIC-3D, DICe, MatchID) read back into vdo `Camera`s.

Each file gives, per camera, K (pixels), the distortion and the pose of the camera in the
calibration's frame (world -> camera for OpenCV, DICe and VIC-3D; for MatchID, the second camera
relative to the first, whose frame is then the calibration frame). `frame` (4 x 4) places that
frame in the experiment's CAD frame: X_cad = frame[:3, :3] X_cal + frame[:3, 3] (metres). The
sensor's pixel size comes from the experiment's camera of the same name (calibration files
hold pixels, not millimetres), and a file whose image size disagrees with that camera's is
refused (`ConfigError`). vdo models square pixels without skew: fx and fy must agree within
`SQUARE_PIXELS`.

`vdo evaluate CONFIG --calibration FILE ...` (`imported`, `with_imported`): the files' cameras
replace the experiment's cameras of the same names (placed by position and angles: off their rail
or mount), the format told by the file (`format_of`); the calibration frame is the CAD frame (vdo's
exports), except a MatchID file's, which is its first camera's: it is placed at that camera's
configured pose. Which camera came from which file is said on the console and in the run folder
(`source_lines`; summary.json's "calibration_files").
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from vdo.core.errors import ConfigError
from vdo.core.runfolder import is_file
from vdo.formats.calibration import MM
from vdo.scene import cameras_of

log = logging.getLogger(__name__)
SQUARE_PIXELS = 1e-9     # relative difference of fx and fy accepted as square pixels
FORMATS = ("opencv", "vic3d", "dice", "matchid")


def euler_matrix(a: float, b: float, c: float) -> np.ndarray:
    """R = Rz(c) Ry(b) Rx(a), degrees (the inverse of `vdo.formats.calibration.euler_xyz_deg`)."""
    a, b, c = (math.radians(v) for v in (a, b, c))
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    Rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def angles(R: np.ndarray) -> tuple[float, float, float]:
    """(pan, tilt, roll) in radians of the world -> camera rotation R (`vdo.model.camera`'s
    convention: z_c = (cos t cos p, cos t sin p, sin t), x_c = cos r x0 + sin r y0)."""
    z = R[2]
    tilt = math.asin(max(-1.0, min(1.0, z[2])))
    pan = math.atan2(z[1], z[0])
    x0 = np.array([math.sin(pan), -math.cos(pan), 0.0])
    y0 = np.cross(z, x0)
    roll = math.atan2(R[0] @ y0, R[0] @ x0)
    return pan, tilt, roll


def as_camera(base, K, distortion, R, t, size, frame: np.ndarray, path, name):
    """The experiment's camera `base` with the calibrated K, distortion and pose (world -> camera
    R, t in metres in the calibration frame), placed in the CAD frame by `frame`."""
    if tuple(size) != (base.width, base.height):
        raise ConfigError(path, f'camera "{name}".image size',
                          f"is {size[0]} x {size[1]} px but the experiment's camera has "
                          f"{base.width} x {base.height}: import the calibration of this sensor "
                          "(or fix [[camera]] pixels)")
    fx, fy = K[0, 0], K[1, 1]
    if abs(fx - fy) > SQUARE_PIXELS * fx or abs(K[0, 1]) > SQUARE_PIXELS * fx:
        raise ConfigError(path, f'camera "{name}".fx', f"fx = {fx:.6g} and fy = {fy:.6g} (skew "
                                                       f"{K[0, 1]:.3g}): vdo models square pixels "
                                                       "without skew")
    Rf, tf = frame[:3, :3], frame[:3, 3]
    R_world = R @ Rf.T                      # X_cam = R X_cal + t, X_cal = Rf^T (X_cad - tf)
    C = Rf @ (-R.T @ t) + tf
    pan, tilt, roll = angles(R_world)
    return replace(base, focal_length=fx * base.pixel_size, position=C, pan=pan, tilt=tilt, roll=roll,
                   principal_offset_px=(K[0, 2] - (base.width - 1) / 2, K[1, 2] - (base.height - 1) / 2),
                   distortion=tuple(float(d) for d in distortion))


def _opencv(path: Path):
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        for key in ("camera_name", "image_width", "image_height", "camera_matrix",
                    "distortion_coefficients", "R", "t"):
            if fs.getNode(key).empty():
                raise ConfigError(path, key, "is missing: give the camera's file as vdo export "
                                             "(opencv) writes it (docs/exports.md)")
        name = fs.getNode("camera_name").string()
        size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
        K, d = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()
        R, t = fs.getNode("R").mat(), fs.getNode("t").mat().ravel() / MM
    finally:
        fs.release()
    return [(name, K, d, R, t, size)]


def _numbers(text: str) -> list[float]:
    return [float(x) for x in text.replace("{", " ").replace("}", " ").replace(",", " ").split()]


def _dice(path: Path):
    import xml.etree.ElementTree as ET

    out = []
    for cam in ET.parse(path).getroot().iter("ParameterList"):
        if not (cam.get("name") or "").startswith("CAMERA "):
            continue
        p = {e.get("name"): e.get("value") for e in cam.findall("Parameter")}
        rows = {e.get("name"): _numbers(e.get("value")) for e in cam.iter("Parameter")
                if (e.get("name") or "").startswith("ROW ")}
        h, w = (int(v) for v in _numbers(p["IMAGE_HEIGHT_WIDTH"]))
        K = np.array([[float(p["FX"]), 0, float(p["CX"])], [0, float(p["FY"]), float(p["CY"])], [0, 0, 1]])
        d = [float(p[k]) for k in ("K1", "K2", "P1", "P2", "K3")]
        R = np.array([rows[f"ROW {r}"] for r in range(3)])
        t = np.array([float(p[k]) for k in ("TX", "TY", "TZ")]) / MM
        out.append((p["CAMERA_ID"], K, d, R, t, (w, h)))
    return out


def _vic3d(path: Path):
    text = path.read_text()
    head = re.search(r"camera 0: (\S+) \((\d+) x (\d+) pixels\); camera 1: (\S+) \((\d+) x (\d+) pixels\)", text)
    if head is None:
        raise ConfigError(path, "", "is not a VIC-3D calibration written by vdo (no camera names "
                                    "and sizes in its header)")
    out = []
    for i, m in enumerate(re.finditer(r'<camera id="\d+">([^<]*)<orientation>([^<]*)</orientation>', text)):
        cx, cy, fx, fy, fs, k1, k2, k3 = _numbers(m.group(1))
        alpha, beta, gamma, tx, ty, tz = _numbers(m.group(2))
        K = np.array([[fx, fs, cx], [0, fy, cy], [0, 0, 1]])
        name, w, h = head.group(1 + 3 * i), int(head.group(2 + 3 * i)), int(head.group(3 + 3 * i))
        out.append((name, K, [k1, k2, 0.0, 0.0, k3], euler_matrix(alpha, beta, gamma),
                    np.array([tx, ty, tz]) / MM, (w, h)))
    return out


def _matchid(path: Path, bases: dict):
    values = {}
    for line in path.read_text().splitlines():
        if ";" in line:
            key, value = line.split(";", 1)
            values[key.strip()] = float(value)
    names = path.stem.split("_", 1) if path.stem.count("_") == 1 else None
    if names is None or any(n not in bases for n in names):
        raise ConfigError(path, "file name", "must be <first>_<second>.caldat with the two cameras' names")
    out = []
    for k, name in enumerate(names):
        v = {key.split("_", 1)[1].split(" [")[0]: val for key, val in values.items() if key.startswith(f"Cam{k}_")}
        K = np.array([[v["Fx"], v["Fs"], v["Cx"]], [0, v["Fy"], v["Cy"]], [0, 0, 1]])
        d = [v["Kappa 1"], v["Kappa 2"], v["P1"], v["P2"], v["Kappa 3"]]
        if k == 0:
            R, t = np.eye(3), np.zeros(3)
        else:
            R = euler_matrix(values["Theta [deg]"], values["Phi [deg]"], values["Psi [deg]"])
            t = np.array([values["Tx [mm]"], values["Ty [mm]"], values["Tz [mm]"]]) / MM
        base = bases[name]
        out.append((name, K, d, R, t, (base.width, base.height)))
    return out


def _read(path: Path, fmt: str, bases: dict) -> list:
    """The file's entries (name, K, distortion, R, t, size); a file that is missing or lacks a
    value raises the one-line `ConfigError` naming it."""
    import xml.etree.ElementTree as ET

    import cv2

    existing(path)
    try:
        return {"opencv": _opencv, "dice": _dice, "vic3d": _vic3d}[fmt](path) if fmt != "matchid" \
            else _matchid(path, bases)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, ET.ParseError, cv2.error,
            UnicodeDecodeError) as exc:
        if isinstance(exc, ConfigError):
            raise
        what = f"no value {exc.args[0]!r}" if isinstance(exc, KeyError) else \
            (str(exc).strip().splitlines() or [type(exc).__name__])[-1]
        raise ConfigError(path, fmt, f"cannot be read in the {fmt} format ({what}): give the "
                                     "file as vdo export writes it (docs/exports.md)") from None


def existing(path: Path) -> None:
    """Refuse (one line) a calibration file that is not there."""
    if not is_file(path):
        raise ConfigError(path, "--calibration", "no such file: give a calibration file written by "
                                                 "vdo export or the lab's software (docs/calibration.md)")


def format_of(path) -> str:
    """The format of calibration file `path` (`FORMATS`) by its name and, for XML, its content:
    .yml/.yaml OpenCV (one camera's file; not a stereo_ file), .caldat MatchID, .xml DICe (a
    ParameterList) or VIC-3D."""
    path = Path(path)
    existing(path)
    suffix = path.suffix.lower()
    if suffix in (".yml", ".yaml"):
        if path.name.startswith("stereo_"):
            raise ConfigError(path, "--calibration", "is an OpenCV stereo file: give the cameras' "
                                                     "own <camera>.yml files instead")
        return "opencv"
    if suffix == ".caldat":
        return "matchid"
    if suffix == ".xml":
        head = path.read_text(errors="replace")[:4096]
        return "dice" if "ParameterList" in head else "vic3d"
    raise ConfigError(path, "--calibration", "is not a calibration file vdo reads: give OpenCV "
                                             ".yml, MatchID .caldat, DICe or VIC-3D .xml")


def import_cameras(path, fmt: str, cameras, frame: np.ndarray | None = None) -> list:
    """The cameras of the calibration file `path` in format `fmt` (`FORMATS`) as vdo Cameras,
    each based on the experiment's camera of the same name in `cameras` (module docstring)."""
    path = Path(path)
    if fmt not in FORMATS:
        raise ConfigError(path, "format", f"must be one of {', '.join(FORMATS)} (got {fmt!r})")
    bases = {c.name: c for c in cameras}
    frame = np.eye(4) if frame is None else np.asarray(frame, dtype=float)
    entries = _read(path, fmt, bases)
    out = []
    for name, K, d, R, t, size in entries:
        if name not in bases:
            raise ConfigError(path, f'camera "{name}"', f"is not a [[camera]] of the experiment "
                                                        f"({', '.join(bases)})")
        out.append(as_camera(bases[name], np.asarray(K, dtype=float), d, np.asarray(R, dtype=float),
                             np.asarray(t, dtype=float), size, frame, path, name))
    return out


def anchor_frame(paths, bases: dict, anchor: str) -> np.ndarray:
    """The calibration frame placed so that camera `anchor` stands at its CAD pose: with the
    file's R_cal, t_cal (calibration frame -> camera) and the experiment's R_cad, t_cad, the
    frame X_cad = R_f X_cal + t_f has R_f = R_cad^T R_cal and t_f = R_cad^T (t_cal - t_cad)
    (then R_cad X_cad + t_cad = R_cal X_cal + t_cal for every point). One line naming
    --calibration-anchor when no file holds that camera."""
    if anchor not in bases:
        raise ConfigError("--calibration-anchor", "", f"no camera of the experiment is named "
                                                      f"{anchor!r}: give one of {', '.join(bases)}")
    for p in paths:
        for cam in import_cameras(Path(p), format_of(Path(p)), bases.values()):
            if cam.name == anchor:
                cad = bases[anchor]
                frame = np.eye(4)
                frame[:3, :3] = cad.R.T @ cam.R
                frame[:3, 3] = cad.R.T @ (cam.t - cad.t)
                return frame
    raise ConfigError("--calibration-anchor", "", f"camera {anchor!r} is in none of the "
                                                  "calibration files: name a camera they hold")


def with_imported(exp, paths, anchor: str | None = None):
    """The experiment of `imported`."""
    return imported(exp, paths, anchor)[0]


def imported(exp, paths, anchor: str | None = None) -> tuple:
    """(the experiment `exp` with its cameras replaced by those of the calibration files `paths`
    (module docstring), camera name -> the file it came from, as given, in the experiment's
    camera order); the specs keep everything but the lens and pose (body, aperture, focus).
    `anchor`: a camera's name; the files' common frame is placed so that this camera stands at
    its CAD pose (`anchor_frame`: a lab's calibration in its own frame, e.g. its first camera's).
    Logs `source_lines` (INFO)."""
    bases = {c.name: c for c in cameras_of(exp.camera_specs, exp.rails)}
    specs = {s.name: s for s in exp.camera_specs}
    common = None if anchor is None else anchor_frame(paths, bases, anchor)
    sources = {}
    for p in paths:
        path = Path(p)
        fmt = format_of(path)
        frame = common
        if fmt == "matchid" and common is None:
            first = path.stem.split("_", 1)[0]
            if first in bases:
                frame = np.eye(4)
                frame[:3, :3], frame[:3, 3] = bases[first].R.T, bases[first].position
        for cam in import_cameras(path, fmt, bases.values(), frame):
            specs[cam.name] = replace(
                specs[cam.name], focal_length=cam.focal_length, rail=None, mount=None, u=None,
                offset=np.zeros(3), position=np.asarray(cam.position, dtype=float), target=None,
                pan=cam.pan, tilt=cam.tilt, roll=cam.roll, principal_offset_px=tuple(
                    float(v) for v in cam.principal_offset_px), distortion=cam.distortion)
            sources[cam.name] = str(p)
    sources = {s.name: sources[s.name] for s in exp.camera_specs if s.name in sources}
    for line in source_lines(sources, [s.name for s in exp.camera_specs]):
        log.info("%s", line)
    return exp.with_cameras([specs[s.name] for s in exp.camera_specs]), sources


def source_lines(sources: dict, cameras) -> list[str]:
    """Which cameras took their pose and intrinsics from which calibration file (`sources`:
    camera -> file, `imported`), one line per file, then one for the `cameras` (names) in no
    file, which keep the experiment's: the console's lines and config.toml's comment."""
    by_file: dict[str, list[str]] = {}
    for name, path in sources.items():
        by_file.setdefault(path, []).append(name)
    plural = lambda names: ("camera " if len(names) == 1 else "cameras ") + ", ".join(names)
    lines = [f"{plural(names)}: pose and intrinsics from the calibration file {path}"
             for path, names in by_file.items()]
    rest = [n for n in cameras if n not in sources]
    if rest:
        lines.append(f"{plural(rest)}: in no calibration file, as the experiment file gives them")
    return lines
