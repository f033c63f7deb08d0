"""`vdo evaluate`: coverage of the regions of interest by the configured cameras, into a run folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import maps, report, vtp
from .config import Experiment
from .runfolder import run_folder
from .scene import build_scene, camera_body, load_meshes, sample_regions
from .visibility import compute_visibility


def say(message: str, quiet: bool) -> None:
    if not quiet:
        print(message, flush=True)


def evaluate(exp: Experiment, out: Path, overwrite: bool = False, quiet: bool = False) -> dict:
    """Sample the regions, ray-cast every (camera, sample) pair and write the outputs to `out`:
    layout.json, samples.vtp, summary.json, config.toml and maps/coverage.png."""
    meshes = load_meshes(exp)
    samples = sample_regions(exp, meshes)
    say(f"{len(samples):,} samples on {len(exp.regions)} regions "
        f"({exp.evaluation.sample_spacing * 1e3:g} mm spacing)", quiet)
    cameras = exp.cameras()
    bodies = [camera_body(c) for c, spec in zip(cameras, exp.camera_specs) if spec.body]
    scene = build_scene(meshes + bodies)
    vis = compute_visibility(scene, cameras, samples, exp.evaluation.incidence_limit,
                             progress=not quiet)
    summary = report.coverage_summary(exp, samples, vis)
    with run_folder(out, overwrite) as tmp:
        report.write_json(tmp / "layout.json", report.layout(cameras))
        report.write_json(tmp / "summary.json", summary)
        report.write_config(tmp / "config.toml", exp)
        arrays = {"normal": samples.normals, "region": samples.region.astype(np.int32),
                  "area": samples.area, "coverage": vis.coverage.astype(np.int32)}
        arrays |= {f"visible_{name}": vis.visible[i] for i, name in enumerate(vis.camera_names)}
        vtp.write_points(tmp / "samples.vtp", samples.points, arrays)
        (tmp / "maps").mkdir()
        maps.plot_unfolded(samples, vis.coverage, tmp / "maps" / "coverage.png",
                           f"{exp.name}: number of cameras that see each point", "cameras",
                           discrete=True)
    return summary
