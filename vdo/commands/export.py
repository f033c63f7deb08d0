"""`vdo export CONFIG_OR_RUN --format F --out DIR`: calibration files for DIC software from an
experiment TOML or a run folder's layout.json (the formats: `vdo.formats`)."""
from __future__ import annotations

import json
import logging
from pathlib import Path

from vdo.core.errors import ConfigError
from vdo.formats.export import FORMATS, camera_from_layout, default_pairs, no_pair_message, uncovered_regions
from vdo.scene import cameras_of

log = logging.getLogger(__name__)


RUN_EXPERIMENTS = ("config.toml", "optimized.toml", "designed.toml")   # a run folder's experiment:
# the resolved config (`vdo evaluate`, `vdo render`, ...), else the layout `vdo optimize` or
# `vdo design` wrote (its cameras are the layout.json's)


def sources(source: Path):
    """(experiment, cameras, the file to name in errors): the cameras of an experiment TOML, or
    of a run folder's layout.json with the experiment of the first of RUN_EXPERIMENTS it holds."""
    from vdo.config import experiment as config

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
        found = [source / name for name in RUN_EXPERIMENTS if (source / name).is_file()]
        if not found:
            raise ConfigError(source, RUN_EXPERIMENTS[0], "missing (and no " + " or ".join(RUN_EXPERIMENTS[1:])
                              + "): the run's experiment is needed to find which cameras share a "
                                "field of view; export the experiment TOML instead")
        return config.load(found[0]), cameras, layout
    if source.is_file():
        exp = config.load(source)
        return exp, cameras_of(exp.camera_specs, exp.rails), source
    raise ConfigError(source, "", "does not exist: give an experiment TOML or a run folder")


def export(source, fmt: str, out, pairs=None, overwrite: bool = False) -> list[Path]:
    """Write the `fmt` calibration files of `source`'s cameras into the run folder `out`
    (atomically, `vdo.core.runfolder`). `pairs`: (first, second) camera names, or None for the pairs
    assigned a common region (`default_pairs`); a region that the chosen pairs leave partly
    uncovered is named in a warning with the --pairs that would cover it (`uncovered_regions`).
    Returns the written paths (inside `out`)."""
    from vdo.core.runfolder import run_folder

    source = Path(source)
    if fmt not in FORMATS:
        raise ConfigError(source, "--format", f"unknown format {fmt!r}; choose one of "
                                              f"{', '.join(FORMATS)}")
    from vdo.state import layout_state, prepare

    exp, cameras, errors_in = sources(source)
    state = layout_state(prepare(exp), cameras, predict_fields=False)
    vis, samples = state.visibility, state.samples
    chosen = default_pairs(exp, cameras, vis, samples, pairs, errors_in)
    if not chosen and fmt in ("matchid", "vic3d"):
        raise ConfigError(errors_in, "--format", f"{fmt} files describe stereo pairs, and "
                                                 + no_pair_message(exp, cameras, vis, samples))
    uncovered = uncovered_regions(exp, cameras, vis, samples, chosen)
    if uncovered:
        log.warning(uncovered)
    with run_folder(out, overwrite) as tmp:
        names = [p.name for p in FORMATS[fmt](cameras, chosen, tmp, errors_in)]
    return [Path(out).resolve() / n for n in names]
