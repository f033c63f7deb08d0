"""A VIC-3D-style calibration XML, one file per stereo pair.

Correlated Solutions does not publish the format. We write the `<calibration>` block of a VIC-3D
project file as DICe's reader of VIC-3D files parses it (`Camera_System::read_camera_system_file`,
"old" VIC-3D layout, docs/exports.md):

    <camera id="i">cx cy fx fy fs k1 k2 k3<orientation>alpha beta gamma tx ty tz</orientation>
    </camera>

with the intrinsics in pixels (fs the skew, 0 here), and the orientation world -> camera
(X_cam = R X_world + T, T = (tx, ty, tz) in mm, vdo's world) with
R = Rz(gamma) Ry(beta) Rx(alpha), angles in degrees (DICe's `eulers_to_rotation_matrix`,
`calibration.euler_xyz_deg`). Camera 0 is the pair's first camera.

Distortion, our assumption: k1, k2, k3 are the radial coefficients of r^2, r^4, r^6 on the
normalised coordinates (OpenCV's radial terms). The file has no tangential terms: a camera
with p1 or p2 != 0 is refused. DICe reads VIC-3D's k1, k2 as k1 r + k2 r^2 and drops k3
(marked unconfirmed in its source), so DICe and this file agree only without distortion.
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

from vdo.core.errors import ConfigError
from vdo.formats.calibration import MM, StereoPair, euler_xyz_deg, file_stem


def _camera(i: int, c) -> str:
    k1, k2, _, _, k3 = c.distortion
    (fx, fs, cx), (_, fy, cy) = c.K[0], c.K[1]
    alpha, beta, gamma = euler_xyz_deg(c.R)
    T = c.t * MM
    intrinsics = " ".join(f"{v:.17g}" for v in (cx, cy, fx, fy, fs, k1, k2, k3))
    orientation = " ".join(f"{v:.17g}" for v in (alpha, beta, gamma, *T))
    return (f'  <camera id="{i}">{intrinsics}<orientation>{orientation}</orientation>\n'
            f"  </camera>")


def pair_xml(pair: StereoPair) -> str:
    a, b = pair.first, pair.second
    return "\n".join([
        '<?xml version="1.0" encoding="UTF-8"?>', "<!DOCTYPE vpml>",
        "<!-- written by vdo: VIC-3D-style calibration, world -> camera, mm, degrees; "
        "R = Rz(gamma) Ry(beta) Rx(alpha); pixel (0, 0) is the centre of the top-left pixel -->",
        f"<!-- camera 0: {a.name} ({a.width} x {a.height} pixels); "
        f"camera 1: {b.name} ({b.width} x {b.height} pixels) -->",
        f"<project name={quoteattr(pair.stem)}>",
        ' <calibration lri="calibration">',
        _camera(0, a), _camera(1, b),
        " </calibration>", "</project>"]) + "\n"


def write(cameras, pairs: list[StereoPair], folder: Path, source) -> list[Path]:
    """Write <first>_<second>.xml per stereo pair into `folder` (nothing when a camera of a pair
    has tangential distortion: ConfigError); returns the paths."""
    for c in (c for pair in pairs for c in (pair.first, pair.second)):
        if c.distortion[2] != 0.0 or c.distortion[3] != 0.0:
            raise ConfigError(source, f'camera "{c.name}".distortion',
                              "VIC-3D's calibration holds no tangential terms: set p1 = p2 = 0 "
                              "or export another format (opencv, dice, matchid)")
    written = []
    for pair in pairs:
        path = Path(folder) / (f"{file_stem(pair.first.name, source)}_"
                               f"{file_stem(pair.second.name, source)}.xml")
        path.write_text(pair_xml(pair))
        written.append(path)
    return written
