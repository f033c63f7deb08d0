"""`vdo export SOURCE --format F --out DIR`: the cameras of an experiment or of a run folder as
calibration files for DIC software.

SOURCE is an experiment TOML (its cameras resolved as `vdo evaluate` does) or a run folder with
layout.json (cameras at that run's pose and image scale). The stereo pairs are the cameras
assigned a common region (`calibration.stereo_pairs`); for a run folder the scene comes from its
config.toml. Which camera sees which sample comes from the ray cast (`vdo.visibility`).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import ConfigError
from . import dice, matchid, opencv, vic3d
from .calibration import stereo_pairs

log = logging.getLogger(__name__)
FORMATS = {"opencv": opencv.write, "matchid": matchid.write, "dice": dice.write, "vic3d": vic3d.write}


def default_pairs(exp, cameras, vis, samples, requested=None, source=None) -> list:
    """The stereo pairs of a layout: cameras assigned a common region, or the `requested`
    (first, second) names, each checked to share a field of view (`stereo_pairs`; errors name
    `source`, default the experiment file)."""
    from ..constraints import assignments

    if requested is not None:
        return stereo_pairs(cameras, vis.visible, None, requested, source or exp.path)
    return stereo_pairs(cameras, vis.visible,
                        assignments(vis, samples, exp.optimize.assign_fraction), None, exp.path)


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
    """A `Camera` from one layout.json entry (`vdo.report.layout`), rebuilt from its pose fields
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


def _sources(source: Path):
    """(experiment, cameras, the file to name in errors): the cameras of an experiment TOML, or
    of a run folder's layout.json with the experiment of its config.toml."""
    from .. import config

    if source.is_dir():
        layout = source / "layout.json"
        if not layout.is_file():
            raise ConfigError(source, "", "is a folder without layout.json: give an experiment "
                                          "TOML or a vdo run folder")
        try:
            entries = json.loads(layout.read_text())["cameras"]
        except (ValueError, KeyError, TypeError) as exc:
            raise ConfigError(layout, "cameras", f"cannot read the camera list ({exc})") from None
        cameras = [camera_from_layout(e, layout) for e in entries]
        if not (source / "config.toml").is_file():
            raise ConfigError(source, "config.toml", "missing: the run's experiment is needed to "
                                                     "find which cameras share a field of view")
        return config.load(source / "config.toml"), cameras, layout
    if source.is_file():
        exp = config.load(source)
        return exp, exp.cameras(), source
    raise ConfigError(source, "", "does not exist: give an experiment TOML or a run folder")


def export(source, fmt: str, out, pairs=None, overwrite: bool = False) -> list[Path]:
    """Write the `fmt` calibration files of `source`'s cameras into the run folder `out`
    (atomically, `vdo.runfolder`). `pairs`: (first, second) camera names, or None for the pairs
    assigned a common region (`default_pairs`). Returns the written paths (inside `out`)."""
    from ..runfolder import run_folder

    source = Path(source)
    if fmt not in FORMATS:
        raise ConfigError(source, "--format", f"unknown format {fmt!r}; choose one of "
                                              f"{', '.join(FORMATS)}")
    from ..state import layout_state, prepare

    exp, cameras, errors_in = _sources(source)
    state = layout_state(prepare(exp), cameras, predict_fields=False)
    vis, samples = state.visibility, state.samples
    chosen = default_pairs(exp, cameras, vis, samples, pairs, errors_in)
    if not chosen and fmt in ("matchid", "vic3d"):
        raise ConfigError(errors_in, "--format", f"{fmt} files describe stereo pairs, and no two "
                                                 "cameras are assigned a common region: name the "
                                                 "pairs with --pairs")
    with run_folder(out, overwrite) as tmp:
        names = [p.name for p in FORMATS[fmt](cameras, chosen, tmp, errors_in)]
    return [Path(out).resolve() / n for n in names]
