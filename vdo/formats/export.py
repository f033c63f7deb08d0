"""`vdo export SOURCE --format F --out DIR`: the cameras of an experiment or of a run folder as
calibration files for DIC software.

SOURCE is an experiment TOML (its cameras resolved as `vdo evaluate` does) or a run folder with
layout.json (cameras at that run's pose and image scale). The stereo pairs are the cameras
assigned a common region with optical axes at most the pair rule's maximum apart
(`default_pairs`); for a run folder the scene comes from its
config.toml. Which camera sees which sample comes from the ray cast (`vdo.physics.visibility`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from vdo.model.camera import Camera
from vdo.core.errors import ConfigError
from vdo.formats import dice
from vdo.formats import matchid
from vdo.formats import opencv
from vdo.formats import vic3d
from vdo.formats.calibration import stereo_pairs

log = logging.getLogger(__name__)
FORMATS = {"opencv": opencv.write, "matchid": matchid.write, "dice": dice.write, "vic3d": vic3d.write}


def default_pairs(exp, cameras, vis, samples, requested=None, source=None) -> list:
    """The stereo pairs of a layout: cameras assigned a common region whose optical axes are at
    most [analysis] max_pair_angle_deg apart (default `vdo.physics.measured`'s 60°: beyond it
    stereo matching fails on foreshortening; dropped pairs are logged), or the `requested`
    (first, second) names, the lab's override, each checked to share a field of view
    (`stereo_pairs`; errors name `source`, default the experiment file)."""
    from vdo.constraints import assignments
    from vdo.physics.measured import DEFAULT_MAX_PAIR_ANGLE_DEG

    if requested is not None:
        return stereo_pairs(cameras, vis.visible, None, requested, source or exp.path)
    pairs = stereo_pairs(cameras, vis.visible,
                         assignments(vis, samples, exp.optimize.assign_fraction), None, exp.path)
    limit = exp.analysis.max_pair_angle if exp.analysis.max_pair_angle is not None \
        else math.radians(DEFAULT_MAX_PAIR_ANGLE_DEG)
    kept, dropped = [], []
    for pair in pairs:
        angle = math.acos(float(np.clip(pair.first.optical_axis @ pair.second.optical_axis, -1, 1)))
        if angle <= limit:
            kept.append(pair)
        else:
            dropped.append(f"{pair.first.name}:{pair.second.name} {math.degrees(angle):.0f}")
    if dropped:       # one line, however many pairs (45 of them on a 10-camera rig)
        log.info("%d stereo pair(s) not exported: optical axes more than %.0f deg apart "
                 "([analysis] max_pair_angle_deg; --pairs overrides): %s", len(dropped),
                 math.degrees(limit), ", ".join(dropped))
    return kept


def write_all(cameras, pairs, folder: Path, source) -> dict[str, list[Path]]:
    """Every format into folder/<format>/ (as `vdo render` writes them beside its images). A
    format that cannot hold these cameras (VIC-3D with tangential distortion, the pair formats
    without a pair) is skipped with a warning. Returns the written paths per format."""
    written = {}
    for fmt, write in FORMATS.items():
        if fmt in ("matchid", "vic3d") and not pairs:
            log.warning("%s: no stereo pair (no two cameras assigned a common region); "
                        "no stereo calibration written", fmt)
            continue
        (Path(folder) / fmt).mkdir(parents=True)
        try:
            written[fmt] = write(cameras, pairs, Path(folder) / fmt, source)
        except ConfigError as exc:
            if fmt != "vic3d":
                raise
            log.warning("vic3d calibration not written: %s", exc.message)
            (Path(folder) / fmt).rmdir()
    return written


def camera_from_layout(entry: dict, path) -> Camera:
    """A `Camera` from one layout.json entry (`vdo.outputs.report.layout`), rebuilt from its pose fields
    and checked against the K, R, t stored beside them (1e-9 relative), so that a hand-edited
    layout.json cannot export a calibration that differs from its own matrices."""
    name = str(entry.get("name", "?"))
    try:
        K = np.asarray(entry["K"], dtype=float)
        width, height = int(entry["width"]), int(entry["height"])
        cam = Camera(name=name, width=width, height=height, pixel_size=entry["pixel_um"] * 1e-6,
                     focal_length=entry["focal_mm"] * 1e-3,
                     position=np.asarray(entry["position_m"], dtype=float),
                     pan=math.radians(entry["pan_deg"]), tilt=math.radians(entry["tilt_deg"]),
                     roll=math.radians(entry["roll_deg"]),
                     principal_offset_px=(K[0, 2] - (width - 1) / 2, K[1, 2] - (height - 1) / 2),
                     distortion=tuple(float(k) for k in entry.get("distortion", [0.0] * 5)))
        stored = [np.asarray(entry[key], dtype=float) for key in ("K", "R", "t")]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise ConfigError(path, f'camera "{name}"', f"is not a vdo layout entry ({exc!r})") from None
    if len(cam.distortion) != 5:
        raise ConfigError(path, f'camera "{name}".distortion', "must hold 5 numbers (k1, k2, p1, p2, k3)")
    for key, mine, theirs in zip("KRt", (cam.K, cam.R, cam.t), stored):
        if mine.shape != theirs.shape or not np.allclose(mine, theirs, rtol=1e-9,
                                                         atol=1e-9 * np.abs(theirs).max()):
            raise ConfigError(path, f'camera "{name}".{key}', "does not match the camera's pose "
                                                              "fields (was layout.json edited?)")
    return cam
