"""DICe camera-system XML (`xml_file_format` = DICe_xml_camera_system_file): a Teuchos
ParameterList as DICe's `Camera_System::read_camera_system_file` reads it.

Every camera is a sublist "CAMERA i" (i = 0, 1, ...) with CAMERA_ID (vdo's name),
IMAGE_HEIGHT_WIDTH "{h, w}", CX, CY, FX, FY (pixels), the distortion K1, K2, K3, P1, P2 with
LENS_DISTORTION_MODEL = OPENCV_LENS_DISTORTION (NO_LENS_DISTORTION for a pinhole), TX, TY, TZ
(mm) and the sublist rotation_3x3_matrix with "ROW 0..2" = "{R_i0, R_i1, R_i2}". The extrinsics
are world -> camera for every camera (extrinsics_relative_camera_to_camera = false):
X_cam = R X_world + T, DICe's `world_cam_trans`; the world is vdo's (z up), in mm.

Files: camera_system.xml with every camera (only when there are at most 8: DICe's reader stops
with "too many cameras" from the 9th), and <first>_<second>.xml per stereo pair (DICe's stereo
correlation uses cameras 0 and 1).
"""

from __future__ import annotations

import logging
from pathlib import Path
from xml.sax.saxutils import quoteattr

from vdo.formats.calibration import MM, StereoPair, file_stem

log = logging.getLogger(__name__)
MAX_CAMERAS = 8   # DICe's reader throws on reaching index 9 of its 10 slots: CAMERA 0..7 load


def _param(name: str, kind: str, value) -> str:
    text = f"{value:.17g}" if kind == "double" else str(value)
    return f"<Parameter name={quoteattr(name)} type={quoteattr(kind)} value={quoteattr(text)} />"


def _camera(i: int, c) -> list[str]:
    k1, k2, p1, p2, k3 = c.distortion
    (fx, _, cx), (_, fy, cy) = c.K[0], c.K[1]
    T = c.t * MM
    model = "OPENCV_LENS_DISTORTION" if c.distorted else "NO_LENS_DISTORTION"
    lines = [f'  <ParameterList name="CAMERA {i}">',
             "    " + _param("CAMERA_ID", "string", c.name),
             "    " + _param("IMAGE_HEIGHT_WIDTH", "string", f"{{ {c.height}, {c.width} }}"),
             "    " + _param("LENS_DISTORTION_MODEL", "string", model)]
    for key, value in (("CX", cx), ("CY", cy), ("FX", fx), ("FY", fy), ("K1", k1), ("K2", k2),
                       ("K3", k3), ("P1", p1), ("P2", p2), ("TX", T[0]), ("TY", T[1]), ("TZ", T[2])):
        lines.append("    " + _param(key, "double", value))
    lines.append('    <ParameterList name="rotation_3x3_matrix">')
    for r, row in enumerate(c.R):
        values = ", ".join(f"{v:.17g}" for v in row)
        lines.append("      " + _param(f"ROW {r}", "string", f"{{ {values} }}"))
    lines += ["    </ParameterList>", "  </ParameterList>"]
    return lines


def system_xml(cameras) -> str:
    """The camera-system file for `cameras` (in this order: CAMERA 0, 1, ...)."""
    lines = ['<?xml version="1.0" encoding="utf-8"?>', "<ParameterList>",
             "  <!-- written by vdo: world -> camera extrinsics, X_cam = R X_world + T, mm; "
             "pixel (0, 0) is the centre of the top-left pixel -->",
             "  " + _param("xml_file_format", "string", "DICe_xml_camera_system_file"),
             "  " + _param("system_type_3D", "string", "OPENCV"),
             "  " + _param("extrinsics_relative_camera_to_camera", "bool", "false")]
    for i, c in enumerate(cameras):
        lines += _camera(i, c)
    return "\n".join(lines + ["</ParameterList>"]) + "\n"


def write(cameras, pairs: list[StereoPair], folder: Path, source) -> list[Path]:
    """Write camera_system.xml (at most `MAX_CAMERAS` cameras) and <first>_<second>.xml per
    stereo pair into `folder`; returns the paths."""
    folder = Path(folder)
    written = []
    for c in cameras:
        file_stem(c.name, source)
    if len(cameras) <= MAX_CAMERAS:
        written.append(folder / "camera_system.xml")
        written[-1].write_text(system_xml(cameras))
    else:
        log.warning("DICe: %d cameras; DICe reads at most %d per camera-system file, so only the "
                    "per-pair files are written", len(cameras), MAX_CAMERAS)
    for pair in pairs:
        path = folder / f"{file_stem(pair.first.name, source)}_{file_stem(pair.second.name, source)}.xml"
        path.write_text(system_xml([pair.first, pair.second]))
        written.append(path)
    return written
