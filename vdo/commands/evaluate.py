"""`vdo evaluate`: coverage, sensitivity and predicted uncertainty of the configured cameras on
every region of interest, written into a run folder."""

from __future__ import annotations

import csv
import dataclasses
import logging
from pathlib import Path

import numpy as np

from vdo.physics import checks, glare, measured
from vdo.physics.lighting import dark_lights, exposure_factors
from vdo import constraints
from vdo.outputs import html_report
from vdo.search import loadpath
from vdo.outputs import maps
from vdo.outputs import report
from vdo.physics import strain
from vdo.core import vtp
from vdo.config.experiment import Experiment
from vdo.model.spline_response import INTERPOLANT_NAMES
from vdo.core.runfolder import run_folder
from vdo.geometry.keyframes import load_path_of
from vdo.search.loadpath import LoadPathResult, evaluate_load_path
from vdo.core.progress import shown
from vdo.optimize import layout_checks
from vdo.commands.calibrate import evaluation_errors, evaluation_plan, write_evaluation_map
from vdo.calib.importer import source_lines
from vdo.state import LayoutState, layout_state, prepare

log = logging.getLogger(__name__)

UM = 1e6            # m -> um
MPX_PER_UM = 1e-3   # pixel/m -> mpixel/um (= pixel/mm)
MAX_WARNINGS = 10   # load-path warnings of each kind on the console; all of them in summary.json


def evaluate(exp: Experiment, out: Path, overwrite: bool = False, workers: int | None = None,
             client=None, calibration_files: dict | None = None) -> report.EvaluationResult:
    """Sample the regions, ray-cast every (camera, sample) pair and every light, predict the
    uncertainty, and write to `out`: layout.json, samples.vtp, summary.json, config.toml and the
    unfolded maps (coverage, sensitivity per axis, sigma_max and per axis, strain sigma per
    component for the [analysis] settings, `vdo.physics.strain`); summary.json also holds the design
    checks per camera and region (`vdo.physics.checks`); a light that lights no sample is said
    (`vdo.physics.lighting.dark_lights`). Returns the judged layout
    (`vdo.outputs.report.EvaluationResult`, whose `to_json()` is summary.json). Progress and
    warnings go to the `vdo.commands.evaluate` logger (`vdo.core.progress`). The load path's
    steps run in this process, or on `workers` >= 2 spawned processes, or on a dask.distributed
    `client`'s workers (`vdo.search.loadpath.evaluate_load_path`): the same files.
    `calibration_files`: camera -> the calibration file its pose and intrinsics came from
    (`vdo.calib.importer.imported`, `--calibration`), written as summary.json's
    "calibration_files" and a comment atop config.toml (`write_evaluation`)."""
    geometry = prepare(exp)
    samples = geometry.samples
    log.info("%s samples on %d regions (%g mm spacing)", f"{len(samples):,}", len(exp.regions),
             exp.evaluation.sample_spacing * 1e3)
    if not exp.lights and exp.render.ambient_radiance == 0:
        log.warning("note: no [[light]] and no [render] ambient_radiance: the images would be "
                    "black, so the uncertainty is not predicted (sigma = inf)")
    load_path = load_path_of(geometry.meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                             groups=exp.groups)     # its files are checked before any ray
    calibration = evaluation_plan(exp, geometry)        # None without [calibration]: no work
    state = layout_state(geometry, progress=shown(log))
    for line in dark_lights(state.illumination, exp.lights, geometry.meshes):
        log.warning("warning: %s", line)
    over_path = None
    if load_path is not None:
        log.info("load path: %d steps", len(load_path.steps))
        over_path = evaluate_load_path(geometry, load_path, progress=shown(log), rest=state,
                                       workers=workers, client=client)
        for loss in over_path.losses[:MAX_WARNINGS]:
            log.warning("warning: camera %s loses region %s at step %s (sees %.0f %% of it, "
                        "%.0f %% at rest)", loss["camera"], loss["region"], loss["step"],
                        100 * loss["fraction"], 100 * loss["rest_fraction"])
        for c in over_path.changes[:MAX_WARNINGS]:
            if c["kind"] == "sigma":
                log.warning("warning: region %s: sigma_max p95 %s at step %s, %.3g um at rest "
                            "(x%.2g; warned from x%g)", c["region"], "unmeasured" if c["value_um"] is None
                            else f"{c['value_um']:.3g} um", c["step"], c["rest_um"], c["ratio"],
                            loadpath.SIGMA_RATIO)
            else:
                log.warning("warning: region %s: area seen by its min_cameras %.0f %% at step %s, "
                            "%.0f %% at rest (warned from a drop of %.0f points)", c["region"],
                            100 * c["value"], c["step"], 100 * c["rest"], 100 * loadpath.COVERAGE_DROP)
        hidden = max(len(over_path.losses) - MAX_WARNINGS, 0) + max(len(over_path.changes) - MAX_WARNINGS, 0)
        if hidden:
            log.warning("warning: %d more load-path losses and changes in summary.json (load_path)", hidden)
    result = write_evaluation(state, out, overwrite, over_path, checked=layout_checks(state),
                              calibration=calibration, calibration_files=calibration_files)
    for line in warnings(result):
        log.warning("warning: %s", line)
    return result


def warnings(result: report.EvaluationResult) -> list[str]:
    """What is wrong with the layout, one line each: a camera that sees no region usefully, and
    every constraint check it breaks (`vdo.optimize.layout_checks`), worst first."""
    out = [f"camera {name} sees no region (no usable view of any sample: aimed away, blocked "
           "or out of range?)" for name in result.cameras_seeing_nothing]
    broken = sorted((c for c in result.constraints["checks"] if not c["met"]),
                    key=lambda c: -c["excess"])
    for c in broken:
        if c["constraint"] == "no_shadow_from_cameras":
            out.append(_shadow_line(c))
            continue
        who = " and ".join(c.get("cameras", [])) or "the layout"
        where = f" on region {c['region']}" if "region" in c else ""
        out.append(f"{c['constraint']} not met: {who}{where}: {_shown(c['value'])} {c['unit']}, "
                   f"limit {_shown(c['limit'])}")
    return out


def _shadow_line(c: dict) -> str:
    """A "no_shadow_from_cameras" check that fails, in words: how much of the region loses light,
    and (`vdo.search.obstruction.light_shadowers`) which camera bodies hide which lights."""
    head = (f"no_shadow_from_cameras not met on region {c['region']}: {100 * c['value']:.3g} % of its area "
            f"loses light to camera bodies (limit {100 * c['limit']:.3g} %)")
    if not c.get("cameras"):
        return head
    lights = ", ".join(repr(name) for name in c.get("lights", []))
    bodies = " and ".join(c["cameras"])
    return (f"{head}: {bodies} stand{'s' if len(c['cameras']) == 1 else ''} between the region and "
            f"light{'s' if len(c.get('lights', [])) > 1 else ''} {lights}; move "
            f"{'that camera' if len(c['cameras']) == 1 else 'those cameras'} or the "
            f"light{'s' if len(c.get('lights', [])) > 1 else ''}")


def _shown(value) -> str:
    """A check's value or limit ([low, high] for a range) with 4 significant digits."""
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(f"{v:.4g}" for v in value) + "]"
    return f"{value:.4g}"


def write_evaluation(state: LayoutState, out: Path, overwrite: bool = False,
                     over_path: LoadPathResult | None = None,
                     checked: list[dict] | None = None, calibration=None,
                     calibration_files: dict | None = None) -> report.EvaluationResult:
    """Write a judged layout into the run folder `out` (see `evaluate`); returns it
    (`vdo.outputs.report.EvaluationResult`: summary.json is its `to_json()`).
    With `over_path` (`vdo.search.loadpath`) also the load path: load_path.csv, load_path.png, the worst
    case over the steps in samples.vtp (coverage_worst, sigma_max_worst, worst_step) and in
    maps/coverage_worst.png, maps/sigma_max_worst.png, and summary.json's "load_path".
    `checked`, the constraint checks of the layout (`vdo.optimize.layout_checks`), go into
    constraints.json and summary.json's "constraints" (None: not judged). `calibration`, the
    planned calibration session (`vdo.commands.calibrate.evaluation_plan`), adds summary.json's
    "calibration" (per region the calibration-induced errors beside the image noise's) and
    maps/calibration_strain.png. `calibration_files` (camera -> file, `vdo.calib.importer.imported`)
    is summary.json's "calibration_files" and config.toml's opening comment
    (`vdo.calib.importer.source_lines`)."""
    exp, samples, cameras = state.experiment, state.samples, state.cameras
    vis, illumination, pred = state.visibility, state.illumination, state.prediction
    eps, sigma_dic = state.strain
    angles = constraints.angle_checks(exp.regions, exp.optimize, exp.stereo_pairs, list(cameras),
                                      vis, samples)
    negligible = checks.negligible_views(vis.camera_names, samples, vis.visible, pred.usable)
    design_checks = checks.design_checks(exp.camera_specs, exp.evaluation, exp.speckle, exp.sensor,
                                         exp.analysis, list(cameras), samples, vis.visible,
                                         illumination.irradiance, state.geometry.speckle.pattern,
                                         leave_out={(n["camera"], n["region"]) for n in negligible})
    judged = None
    if checked is not None:
        judged = {"violations": sum(not c["met"] for c in checked), "checks": checked}
    hot = glare.hot_spots(exp.meshes, exp.regions, exp.lights, exp.speckle, exp.sensor,
                          list(cameras), samples, vis.visible, illumination,
                          exposure_factors(exp.camera_specs, exp.sensor))
    for row in hot:
        for flag in row["flags"]:
            log.warning("camera %s: %s", row["camera"], flag)
    meas = state.measured
    calibration_summary = None
    if calibration is not None:
        calibration_summary, calibration_errors = evaluation_errors(calibration, state)
    result = dataclasses.replace(
        report.state_evaluation(state),
        axis_angles=angles, design_checks=design_checks, negligible_views=negligible,
        cameras_seeing_nothing=[name for i, name in enumerate(vis.camera_names) if not pred.usable[i].any()],
        constraints=judged, glare=hot,
        measured=measured.summary(exp.analysis, meas, samples, pred, eps),
        load_path=None if over_path is None else loadpath.summary(over_path),
        calibration=calibration_summary, calibration_files=calibration_files)
    with run_folder(out, overwrite) as tmp:
        if judged is not None:
            report.write_json(tmp / "constraints.json", judged)
        report.write_json(tmp / "layout.json", report.layout(cameras))
        report.write_json(tmp / "summary.json", result.to_json())
        report.write_config(tmp / "config.toml", exp, comment=None if calibration_files is None
                            else source_lines(calibration_files, vis.camera_names))
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
        arrays |= {f"sigma_strain_{c}": np.where(np.isfinite(eps[:, k]), eps[:, k] * 1e6, np.nan)
                   for k, c in enumerate(strain.STRAIN_COMPONENTS)}
        arrays["sigma_dic_max"] = np.where(np.isfinite(sigma_dic), sigma_dic * UM, np.nan)
        arrays["sigma_measured_max"] = np.where(np.isfinite(meas.sigma_max), meas.sigma_max * UM, np.nan)
        arrays |= {f"sigma_measured_{a}": np.where(np.isfinite(meas.sigma_xyz[:, k]),
                                                   meas.sigma_xyz[:, k] * UM, np.nan)
                   for k, a in enumerate("xyz")}
        arrays["sigma_measured_ratio"] = np.where(np.isfinite(meas.ratio), meas.ratio, np.nan)
        if meas.pairs:
            arrays["stereo_pair"] = meas.pair.astype(np.int32)
        arrays["tangent_u"], arrays["tangent_v"] = samples.tangent_u, samples.tangent_v
        arrays |= {f"visible_{name}": vis.visible[i] for i, name in enumerate(vis.camera_names)}
        arrays |= {f"usable_{name}": pred.usable[i] for i, name in enumerate(vis.camera_names)}
        if over_path is not None:
            worst_sigma = over_path.worst_sigma
            arrays |= {"coverage_worst": over_path.worst_coverage.astype(np.int32),
                       "sigma_max_worst": np.where(np.isfinite(worst_sigma), worst_sigma * UM, np.nan),
                       "worst_step": over_path.worst_step_index.astype(np.int32)}
        vtp.write_points(tmp / "samples.vtp", samples.points, arrays)
        (tmp / "maps").mkdir()
        maps.plot_unfolded(samples, pred.coverage, tmp / "maps" / "coverage.png",
                           f"{exp.name}: number of usable views of each point", "cameras",
                           discrete=True)
        for k, a in enumerate("xyz"):
            maps.plot_unfolded(samples, sens[:, k], tmp / "maps" / f"sensitivity_{a}.png",
                               f"{exp.name}: global sensitivity along {a.upper()}",
                               "mpixel/µm")
        if np.isfinite(sigma_um).any():
            maps.plot_unfolded(samples, sigma_um, tmp / "maps" / "sigma_max.png",
                               f"{exp.name}: displacement uncertainty, worst direction "
                               "(grey: < 2 usable views)", "σ_max (µm)", cmap="magma_r")
            for k, a in enumerate("xyz"):
                maps.plot_unfolded(samples, sigma_xyz_um[:, k], tmp / "maps" / f"sigma_{a}.png",
                                   f"{exp.name}: displacement uncertainty along {a.upper()}",
                                   "σ (µm)", cmap="magma_r")
            maps.plot_unfolded(samples, arrays["sigma_measured_max"],
                               tmp / "maps" / "sigma_measured_max.png",
                               f"{exp.name}: measured displacement error, worst direction "
                               f"({exp.analysis.processing}, {INTERPOLANT_NAMES[exp.analysis.interpolant]})",
                               "σ_measured (µm)", cmap="magma_r")
            eps_ue = np.where(np.isfinite(eps), eps * 1e6, np.nan)
            for k, c in enumerate(strain.STRAIN_COMPONENTS):
                maps.plot_unfolded(samples, eps_ue[:, k], tmp / "maps" / f"sigma_strain_{c}.png",
                                   f"{exp.name}: strain uncertainty ε_{c} (face frame, "
                                   f"{exp.analysis.method} DIC)", "σ (µε)", cmap="magma_r")
        meshes, developed = {m.name: m for m in state.geometry.meshes}, {}
        for r, (region, faces) in enumerate(zip(exp.regions, state.geometry.region_faces)):
            if faces.development is not None:
                mesh = meshes[region.mesh]
                developed[region.name] = maps.plot_developed(
                    samples, r, faces, mesh.vertices, mesh.faces, sigma_um, pred.usable,
                    vis.camera_names, tmp / "maps" / f"developed_{region.name}.png",
                    f"{exp.name}: region {region.name!r} developed, σ_max and the usable views",
                    "σ_max (µm)")
        if calibration is not None:
            write_evaluation_map(tmp, exp, samples, calibration_errors)
        if developed:
            result = dataclasses.replace(result, developed=developed)
            report.write_json(tmp / "summary.json", result.to_json())
        if over_path is not None:
            _write_load_path(tmp, exp, samples, over_path)
        html_report.write_report(tmp)
    return result


def _write_load_path(tmp: Path, exp: Experiment, samples, result: LoadPathResult) -> None:
    """The load-path files of `write_evaluation`."""
    rows = loadpath.table(result)
    with open(tmp / "load_path.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    loadpath.plot(result, tmp / "load_path.png",
                  f"{exp.name}: coverage and σ_max p95 over the load path")
    maps.plot_unfolded(samples, result.worst_coverage, tmp / "maps" / "coverage_worst.png",
                       f"{exp.name}: fewest usable views of each point over the load path",
                       "cameras", discrete=True)
    worst = np.where(np.isfinite(result.worst_sigma), result.worst_sigma * UM, np.nan)
    if np.isfinite(worst).any():
        maps.plot_unfolded(samples, worst, tmp / "maps" / "sigma_max_worst.png",
                           f"{exp.name}: largest σ_max of each point over the load path "
                           "(grey: < 2 usable views at some step)", "σ_max (µm)", cmap="magma_r")
