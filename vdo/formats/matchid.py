"""MatchID stereo calibration (.caldat), one file per stereo pair: `Key;value` lines.

MatchID does not publish the .caldat specification. The keys and their order follow the public
.caldat writer of pyvale (`CameraStereo.save_calibration_mid`, docs/exports.md); the meaning we
give them (an assumption, stated in docs/exports.md):

* Cam0 is the pair's first camera (the reference), Cam1 the second;
* Fx, Fy, Cx, Cy in pixels with OpenCV's pixel convention, Fs (skew) 0;
* Kappa 1..3 = k1, k2, k3 and P1, P2 = p1, p2 of OpenCV's distortion model (normalised
  coordinates);
* Tx, Ty, Tz (mm) and Theta, Phi, Psi (deg): the pose of Cam1 relative to Cam0,
  X_1 = R X_0 + T with R = Rz(Psi) Ry(Phi) Rx(Theta) (`calibration.euler_xyz_deg`) - the
  camera-to-camera transform of `cv2.stereoCalibrate`.
"""

from __future__ import annotations

from pathlib import Path

from vdo.formats.calibration import MM, StereoPair, euler_xyz_deg, file_stem


def _camera_lines(k: int, c) -> list[str]:
    k1, k2, p1, p2, k3 = c.distortion
    (fx, fs, cx), (_, fy, cy) = c.K[0], c.K[1]
    return [f"Cam{k}_Fx [pixels];{fx:.17g}", f"Cam{k}_Fy [pixels];{fy:.17g}",
            f"Cam{k}_Fs [pixels];{fs:.17g}", f"Cam{k}_Kappa 1;{k1:.17g}", f"Cam{k}_Kappa 2;{k2:.17g}",
            f"Cam{k}_Kappa 3;{k3:.17g}", f"Cam{k}_P1;{p1:.17g}", f"Cam{k}_P2;{p2:.17g}",
            f"Cam{k}_Cx [pixels];{cx:.17g}", f"Cam{k}_Cy [pixels];{cy:.17g}"]


def write(cameras, pairs: list[StereoPair], folder: Path, source) -> list[Path]:
    """Write <first>_<second>.caldat for every stereo pair into `folder`; returns the paths."""
    written = []
    for pair in pairs:
        theta, phi, psi = euler_xyz_deg(pair.R)
        T = pair.T * MM
        lines = _camera_lines(0, pair.first) + _camera_lines(1, pair.second) + [
            f"Tx [mm];{T[0]:.17g}", f"Ty [mm];{T[1]:.17g}", f"Tz [mm];{T[2]:.17g}",
            f"Theta [deg];{theta:.17g}", f"Phi [deg];{phi:.17g}", f"Psi [deg];{psi:.17g}"]
        path = Path(folder) / (f"{file_stem(pair.first.name, source)}_"
                               f"{file_stem(pair.second.name, source)}.caldat")
        path.write_text("\n".join(lines) + "\n")
        written.append(path)
    return written
