"""`vdo evaluate`: coverage, sensitivity and predicted uncertainty of the configured cameras on
every region of interest, written into a run folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import constraints, maps, report, vtp
from .config import Experiment
from .lighting import illuminate
from .predict import predict, speckle_model
from .runfolder import run_folder
from .scene import build_scene, camera_body, load_meshes, sample_regions
from .visibility import compute_visibility

UM = 1e6            # m -> um
MPX_PER_UM = 1e-3   # pixel/m -> mpixel/um (= pixel/mm)


def say(message: str, quiet: bool) -> None:
    if not quiet:
        print(message, flush=True)


def evaluate(exp: Experiment, out: Path, overwrite: bool = False, quiet: bool = False) -> dict:
    """Sample the regions, ray-cast every (camera, sample) pair and every light, predict the
    uncertainty, and write to `out`: layout.json, samples.vtp, summary.json, config.toml and the
    unfolded maps (coverage, sensitivity per axis, sigma_max and per axis)."""
    meshes = load_meshes(exp)
    samples = sample_regions(exp, meshes)
    say(f"{len(samples):,} samples on {len(exp.regions)} regions "
        f"({exp.evaluation.sample_spacing * 1e3:g} mm spacing)", quiet)
    cameras = exp.cameras()
    bodies = [camera_body(c) for c, spec in zip(cameras, exp.camera_specs) if spec.body]
    scene = build_scene(meshes + bodies)
    vis = compute_visibility(scene, cameras, samples, exp.evaluation.incidence_limit,
                             progress=not quiet)
    illumination = illuminate(scene, exp.lights, samples, exp.render.ambient_radiance)
    if not exp.lights and exp.render.ambient_radiance == 0:
        say("note: no [[light]] and no [render] ambient_radiance: the images would be black, so "
            "the uncertainty is not predicted (sigma = inf)", quiet)
    say("predicting the uncertainty (compiles on first use)", quiet)
    pred = predict(exp, cameras, samples, vis, illumination, speckle_model(exp))
    summary = report.summary(exp, samples, vis, pred)
    summary["axis_angles"] = constraints.angle_checks(exp, cameras, vis, samples)
    for e in summary["axis_angles"]:
        if not e["met"]:
            bound = "below the minimum" if e["constraint"] == "axis_angle" else "above the maximum"
            say(f"warning: cameras {e['cameras'][0]} and {e['cameras'][1]}: optical axes "
                f"{e['value']:.1f} deg apart, {bound} of {e['limit']:.1f} deg", quiet)

    with run_folder(out, overwrite) as tmp:
        report.write_json(tmp / "layout.json", report.layout(cameras))
        report.write_json(tmp / "summary.json", summary)
        report.write_config(tmp / "config.toml", exp)
        sigma_um = np.where(pred.measured, pred.sigma_max * UM, np.nan)
        sigma_xyz_um = np.where(pred.measured[:, None], pred.sigma_xyz * UM, np.nan)
        sens = pred.sensitivity * MPX_PER_UM
        arrays = {"normal": samples.normals, "region": samples.region.astype(np.int32),
                  "area": samples.area, "coverage": pred.coverage,
                  "patch_fraction": pred.patch_fraction, "edge_limited": pred.edge_limited,
                  "outlier": pred.outlier,
                  "irradiance": illumination.irradiance,
                  **{f"sensitivity_{a}": sens[:, k] for k, a in enumerate("xyz")},
                  "sigma_max": sigma_um,
                  **{f"sigma_{a}": sigma_xyz_um[:, k] for k, a in enumerate("xyz")}}
        arrays |= {f"visible_{name}": vis.visible[i] for i, name in enumerate(vis.camera_names)}
        arrays |= {f"usable_{name}": pred.usable[i] for i, name in enumerate(vis.camera_names)}
        vtp.write_points(tmp / "samples.vtp", samples.points, arrays)
        (tmp / "maps").mkdir()
        maps.plot_unfolded(samples, pred.coverage, tmp / "maps" / "coverage.png",
                           f"{exp.name}: number of usable views of each point", "cameras",
                           discrete=True)
        top = np.nanpercentile(sens, 99) if np.isfinite(sens).any() else 1.0
        for k, a in enumerate("xyz"):
            maps.plot_unfolded(samples, sens[:, k], tmp / "maps" / f"sensitivity_{a}.png",
                               f"{exp.name}: global sensitivity along {a.upper()}",
                               "mpixel/µm", vmin=0, vmax=top)
        if np.isfinite(sigma_um).any():
            hi = np.nanpercentile(sigma_um, 98)
            maps.plot_unfolded(samples, sigma_um, tmp / "maps" / "sigma_max.png",
                               f"{exp.name}: displacement uncertainty, worst direction "
                               "(white: < 2 usable views)", "σ_max (µm)", cmap="magma_r",
                               vmin=0, vmax=hi)
            for k, a in enumerate("xyz"):
                maps.plot_unfolded(samples, sigma_xyz_um[:, k], tmp / "maps" / f"sigma_{a}.png",
                                   f"{exp.name}: displacement uncertainty along {a.upper()}",
                                   "σ (µm)", cmap="magma_r", vmin=0, vmax=hi)
    return summary
