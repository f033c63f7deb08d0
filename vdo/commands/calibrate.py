"""`vdo calibrate CONFIG --out DIR`: the lab's calibration session rendered and calibrated
(`--plan`: how many poses, `plan_experiment`; `--montecarlo N`: N simulated calibrations against
the covariance each predicts, `montecarlo_experiment`).

Order: the session is built and checked (`vdo.calib.session.plan`: one-line errors before any
render), the target images rendered (`vdo.calib.images`), exposed with the sensor's noise, the
corners detected (`vdo.calib.detect`), the rig calibrated (`vdo.calib.solve`) and compared with
the true cameras (`vdo.calib.truth`). The run folder (atomic, `vdo.core.runfolder`):

    images/<camera>/pose_<k>.png|.tif   the target images a lab would take ([render] image_format)
    target.yml                          the target (OpenCV FileStorage: board_width, board_height,
                                        square_size in mm)
    summary.json                        per camera: the calibrated intrinsics, their sigma, the true
                                        values and the z-scores; per stereo pair: the relative
                                        pose's errors and sigmas; the reprojection rms; the
                                        detection noise used; the poses each camera saw
    contact_sheet.png                   each camera's first image
    samples.vtp                         per sample: the calibration-induced sigmas of position,
                                        displacement and strain (at the test's level and per unit;
                                        `vdo.calib.propagate`) beside the image noise's
    maps/calibration_strain.png         calibration-induced strain sigma; maps/noise_strain.png the
                                        image noise's
    config.toml                         the resolved experiment

Images are rendered at the render scale (--scale, default [render] scale): the calibration is that
of the scaled cameras (pixels of the scaled images).
"""

from __future__ import annotations

import json
import logging
import time

import numpy as np

log = logging.getLogger(__name__)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def calibrate_experiment(exp, out, scale: float | None = None, spp: int | None = None,
                         overwrite: bool = False, time_limit: float | None = None) -> dict:
    """Render, calibrate and write the run folder `out` (module docstring); returns the
    summary.json dict."""
    from vdo.calib.detect import detect_all
    from vdo.calib.images import render_session, write
    from vdo.calib.session import plan
    from vdo.calib.solve import calibrate
    from vdo.calib.truth import versus_truth
    from vdo.commands.render import contact_sheet
    from vdo.core.errors import ConfigError
    from vdo.core.runfolder import check_out, run_folder
    from vdo.outputs import report
    from vdo.calib.propagate import sample_errors
    from vdo.render import render_settings
    from vdo.state import layout_state

    started = time.perf_counter()
    scale, spp, _ = render_settings(exp, scale, spp, None)
    check_out(out, overwrite)
    planned = plan(exp, scale)
    session = planned.session
    deadline = None if time_limit is None else time.monotonic() + time_limit
    rendered = render_session(exp, session, scale, spp, deadline)
    images = rendered.exposed(exp.sensor, exp.calibration.seed, 0)
    log.info("detecting the target in %d images", len(images))
    observations, missed = detect_all(images, session.target, exp.sensor.max_dn)
    by_camera: dict = {}
    for name, k in missed:
        by_camera.setdefault(name, []).append(str(k))
    for name, poses in by_camera.items():     # one line per camera (summary.json lists them all)
        log.warning("camera %s: the target was not found in %d image(s), dropped (poses %s)",
                    name, len(poses), ", ".join(poses))
    names = [c.name for c in rendered.cameras]
    for name in names:
        if sum(o.camera == name for o in observations) < 3:
            raise ConfigError(exp.path, "calibration", f"the target was found in fewer than 3 of "
                                                       f"camera {name!r}'s images: check the lights "
                                                       "and the poses (tilt_deg, distances_m)")
    sizes = {c.name: (c.width, c.height) for c in rendered.cameras}
    log.info("calibrating %d cameras jointly from %d images", len(names), len(observations))
    cal = calibrate(names, sizes, observations, session.target, exp.calibration.detection_sigma_px)
    truth = versus_truth(cal, rendered.cameras, session.pairs)
    state = layout_state(planned.geometry, list(planned.cameras))
    samples = planned.geometry.samples
    errors = sample_errors(cal, exp, list(rendered.cameras), samples, state.visibility.visible,
                           session.pairs)
    noise_strain, noise_u = state.strain[0][:, 0], state.strain[1]
    summary = {"experiment": exp.name, "config": str(exp.path), "scale": scale, "spp": spp,
               "target": session.target.description(),
               "poses": len(session.poses),
               "views": {n: [int(k) for k in session.views[n]] for n in names},
               "missed": [[n, int(k)] for n, k in missed],
               "rms_px": cal.rms_all, "sigma_det_px": cal.sigma_det,
               "sigma_residual_px": cal.sigma_residual, **truth,
               "propagation": region_table(exp, samples, errors, noise_u, noise_strain),
               "seconds": {"render": round(rendered.seconds, 3)}}
    with run_folder(out, overwrite) as tmp:
        write(images, session, tmp, exp.sensor, exp.render.image_format, exp.render.bit_alignment)
        first = {n: images[(n, session.views[n][0])] for n in names}
        contact_sheet(first, exp.sensor.max_dn, tmp / "contact_sheet.png",
                      f"{exp.name}: calibration, first image per camera")
        report.write_config(tmp / "config.toml", exp)
        write_fields(tmp, exp, samples, errors, noise_u, noise_strain)
        summary["seconds"]["total"] = round(time.perf_counter() - started, 3)
        (tmp / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2) + "\n")
    return summary


def _percentiles(x: np.ndarray, scale: float) -> dict:
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return {"p50": None, "p95": None}
    return {"p50": float(np.percentile(x, 50) * scale), "p95": float(np.percentile(x, 95) * scale)}


def region_table(exp, samples, errors, noise_u, noise_strain) -> dict:
    """Per region, p50/p95 over its samples: the calibration-induced position sigma (mm),
    displacement sigma at the test's level (um) and per unit displacement (um/mm), strain sigma at
    the test's level and per unit strain (microstrain), beside the image noise's displacement and
    strain sigma (one image pair: random, per load step)."""
    out = {}
    for k, name in enumerate(samples.region_names):
        m = samples.region == k
        out[name] = {
            "calibration_position_mm": _percentiles(errors.position[m], 1e3),
            "calibration_displacement_um": _percentiles(errors.displacement[m], 1e6),
            "calibration_displacement_um_per_mm": _percentiles(errors.per_unit_displacement[m], 1e3),
            "calibration_strain_microstrain": _percentiles(errors.strain[m], 1e6),
            "calibration_strain_per_unit_strain": _percentiles(errors.per_unit_strain[m], 1.0),
            "noise_displacement_um": _percentiles(noise_u[m], 1e6),
            "noise_strain_microstrain": _percentiles(noise_strain[m], 1e6),
            "test_strain": exp.calibration.strain,
            "test_displacement_mm": exp.calibration.displacement * 1e3}
    return out


def write_fields(folder, exp, samples, errors, noise_u, noise_strain) -> None:
    """samples.vtp (calibration and image-noise sigmas per sample) and maps/ (calibration strain
    sigma beside the image noise's)."""
    from vdo.core import vtp
    from vdo.outputs import maps

    (folder / "maps").mkdir()
    arrays = {"calib_position_sigma": errors.position, "calib_displacement_sigma": errors.displacement,
              "calib_displacement_per_unit": errors.per_unit_displacement,
              "calib_strain_sigma": errors.strain, "calib_strain_per_unit": errors.per_unit_strain,
              "calib_pair": errors.pair.astype(np.int32), "noise_displacement_sigma": noise_u,
              "noise_strain_sigma": noise_strain, "region": samples.region.astype(np.int32),
              "normal": samples.normals, "tangent_u": samples.tangent_u, "tangent_v": samples.tangent_v,
              "area": samples.area}                 # the sample cells `vdo report` draws
    vtp.write_points(folder / "samples.vtp", samples.points, arrays)
    level = exp.calibration.strain
    for name, values, title in (
            ("calibration_strain.png", errors.strain * 1e6,
             f"calibration-induced strain sigma at strain {level:g} (microstrain, systematic)"),
            ("noise_strain.png", np.where(np.isfinite(noise_strain), noise_strain, np.nan) * 1e6,
             "image-noise strain sigma (microstrain, random per step)")):
        maps.plot_unfolded(samples, values, folder / "maps" / name, f"{exp.name}: {title}", "microstrain")


def print_summary(summary: dict) -> None:
    """The console table: per camera views, rms, f and c with sigma and error; per pair the
    relative pose's errors."""
    print(f"target {summary['target']['columns']} x {summary['target']['rows']} corners, pitch "
          f"{summary['target']['pitch_mm']:.3g} mm; {summary['poses']} poses; reprojection rms "
          f"{summary['rms_px']:.3f} px; detection sigma {summary['sigma_det_px']:.3f} px")
    print(f"{'camera':<14}{'views':>6}{'rms px':>8}{'fx (sigma, error) px':>30}{'cx (sigma, error) px':>28}")
    for name, c in summary["cameras"].items():
        fx, cx = c["fx"], c["cx"]
        print(f"{name:<14}{c['views']:>6}{c['rms_px']:>8.3f}"
              f"{fx['value']:>12.2f} ({fx['sigma']:.2f}, {fx['error']:+.2f})"
              f"{cx['value']:>11.2f} ({cx['sigma']:.2f}, {cx['error']:+.2f})")
    for pair, p in summary["pairs"].items():
        rot = max(abs(x) for x in p["rotation_error_deg"])
        print(f"pair {pair}: rotation error {rot:.4f} deg, baseline error {p['baseline_error_mm']:+.4f} mm")
    print(f"{'region':<18}{'calib u um (/mm)':>20}{'noise u um':>12}{'calib strain ue (/unit)':>26}"
          f"{'noise strain ue':>17}   (p95; calibration systematic, noise random)")
    for name, r in summary["propagation"].items():
        def show(d):
            return "-" if d["p95"] is None else f"{d['p95']:.3g}"
        print(f"{name:<18}{show(r['calibration_displacement_um']):>11} ({show(r['calibration_displacement_um_per_mm'])})"
              f"{show(r['noise_displacement_um']):>12}"
              f"{show(r['calibration_strain_microstrain']):>15} ({show(r['calibration_strain_per_unit_strain'])})"
              f"{show(r['noise_strain_microstrain']):>17}")


def plan_experiment(exp, out, overwrite: bool = False) -> dict:
    """`vdo calibrate --plan`: the planner's curve and choice (`vdo.calib.planner`) into the run
    folder `out`: plan.json (counts, images, strain sigma p95, the chosen count and its poses:
    centres and front normals in metres) and plan.png (the diminishing-returns curve)."""
    from dataclasses import replace

    from vdo.calib.planner import plan_session, plot
    from vdo.calib.session import plan, stereo_names
    from vdo.core.runfolder import check_out, run_folder
    from vdo.scene import cameras_of
    from vdo.state import layout_state, prepare

    check_out(out, overwrite)
    geometry = prepare(exp)
    state = layout_state(geometry, predict_fields=False)
    pairs = stereo_names(exp, tuple(cameras_of(exp.camera_specs, exp.rails)), geometry, state.visibility)
    plan(exp, 1.0, geometry, pairs=pairs)        # the configured session's checks first
    p = plan_session(exp, state.visibility, geometry, pairs)
    result = {"experiment": exp.name, "poses_per_camera": list(p.counts), "images": list(p.images),
              "strain_sigma_p95": list(p.strain_p95), "target_strain_error": p.target,
              "sigma_det_px": p.sigma_det, "chosen_poses_per_camera": p.chosen}
    if p.chosen is not None:
        spec = exp.calibration
        share = spec.shared_poses / max(1, spec.poses_per_camera)
        chosen = plan(exp, 1.0, geometry, replace(spec, poses_per_camera=p.chosen,
                                                  shared_poses=max(1, round(share * p.chosen))),
                      pairs)
        s = chosen.session
        result["chosen_session"] = {
            "pitch_mm": s.target.pitch * 1e3,
            "pose_centres_m": [pose.world(s.target.centre[None])[0].tolist() for pose in s.poses],
            "pose_normals": [pose.front.tolist() for pose in s.poses],
            "views": {n: list(v) for n, v in s.views.items()}}
    with run_folder(out, overwrite) as tmp:
        plot(p, tmp / "plan.png", f"{exp.name}: calibration session plan")
        (tmp / "plan.json").write_text(json.dumps(_jsonable(result), indent=2) + "\n")
    return result


MC_SAMPLES = 8        # samples per rig whose triangulated displacement and strain the Monte Carlo checks


def montecarlo_rigs(exp, planned) -> tuple[dict, list[tuple]]:
    """The rigs `vdo calibrate --montecarlo` checks: each stereo pair of the session and, with
    more than two cameras calibrated together, the whole rig; each rig's names start with its
    group's reference camera (`vdo.calib.propagate.rig`), read from one calibration of the
    noise-free corners. Returns (rig -> its label, "a:b" or "all"; the rigs)."""
    from vdo.calib import propagate as prop
    from vdo.calib.solve import calibrate, simulate

    cams = list(planned.cameras)
    names = [c.name for c in cams]
    obs = simulate(cams, planned.session, 0.0, np.random.default_rng(exp.calibration.seed))
    reference = calibrate(names, {c.name: (c.width, c.height) for c in cams}, obs,
                          planned.session.target, 1.0).reference
    labels = {}
    for a, b in planned.session.pairs:
        if reference[a] == reference[b]:
            labels[prop.reference_first(reference, a, b)] = f"{a}:{b}"
    group = [n for n in names if reference[n] == reference[names[0]]]
    if len(group) > 2 and len(group) == len(names):
        labels[tuple(group)] = "all"
    return labels, list(labels)


def montecarlo_experiment(exp, out, trials: int, workers: int | None = None, client=None,
                          overwrite: bool = False, time_limit: float | None = None) -> dict:
    """`vdo calibrate --montecarlo N`: N calibrations of the experiment's planned session
    (`vdo.calib.session.plan` at full size) from corners simulated with independent
    N(0, sigma_det^2) noise, sigma_det = [calibration] detection_sigma_px (default
    `vdo.calib.planner.DEFAULT_SIGMA_DET_PX`), on `workers` local processes or the workers of a
    Dask `client` (`vdo.calib.montecarlo.run`: the same result wherever it runs). Per rig
    (`montecarlo_rigs`) the observed scatter over the predicted sigma of every parameter, of the
    displacement and strain of the test's motion at up to MC_SAMPLES samples seen by the rig, and
    sqrt(NEES), beside the 95 % interval of one ratio and of all the rig's parameter ratios at
    once (Bonferroni, `ratio_interval`). The run folder `out`: montecarlo.json, montecarlo.png
    (the ratios per parameter in the intervals' bands), config.toml. Returns the json dict."""
    from vdo.calib import montecarlo as mc
    from vdo.calib import propagate as prop
    from vdo.calib.planner import DEFAULT_SIGMA_DET_PX
    from vdo.calib.session import plan
    from vdo.core.runfolder import check_out, run_folder
    from vdo.outputs import report

    check_out(out, overwrite)
    deadline = None if time_limit is None else time.monotonic() + time_limit
    planned = plan(exp, 1.0)
    from vdo.core.errors import ConfigError

    labels, rigs = montecarlo_rigs(exp, planned)
    if not rigs:
        raise ConfigError(exp.path, "stereo_pair", "no stereo pair is calibrated together (no "
                                                   "shared pose): raise [calibration] shared_poses")
    by_name = {c.name: c for c in planned.cameras}
    samples = planned.geometry.samples
    points, motions = {}, {}
    for r in list(rigs):
        points[r], motions[r] = prop.probe(exp, samples, [by_name[n] for n in r], MC_SAMPLES)
        if len(points[r]) == 0:
            log.warning("rig %s sees no region sample in every image: left out", labels[r])
            rigs.remove(r)
    if not rigs:        # e.g. all round: no region sample lies in every image of the whole rig
        raise ConfigError(exp.path, "stereo_pair", f"no rig of the session ({', '.join(labels.values())}) "
                                                   "sees a region sample in all its cameras' images: "
                                                   "name stereo pairs that share a view of a region")
    given = exp.calibration.detection_sigma_px
    sigma = given or DEFAULT_SIGMA_DET_PX
    log.info("Monte Carlo: %d calibrations of %d poses, corners sigma %g px, rigs %s", trials,
             len(planned.session.poses), sigma, ", ".join(labels[r] for r in rigs))
    result = mc.run(list(planned.cameras), planned.session, rigs, points, motions, trials,
                    exp.calibration.seed, sigma_det=sigma, deadline=deadline, workers=workers,
                    client=client)
    one = mc.ratio_interval(trials)
    summary = {"experiment": exp.name, "config": str(exp.path), "trials": trials,
               "seed": exp.calibration.seed, "sigma_det_px": sigma,
               "sigma_det_from": "detection_sigma_px" if given else "default (no detection_sigma_px)",
               "poses": len(planned.session.poses), "confidence": 0.95, "interval_one_ratio": list(one),
               "workers": "dask" if client is not None else (workers or 1),
               "seconds": round(result.seconds, 3), "rigs": {}}
    for r in result.rigs:
        every = mc.ratio_interval(trials, len(r.parameters))
        ratio = r.ratio
        summary["rigs"][labels[r.names]] = {
            "cameras": list(r.names),
            "parameters": {name: {"predicted": p, "observed": o, "ratio": q}
                           for name, p, o, q in zip(r.parameters, r.predicted, r.observed, ratio)},
            "ratio_median": float(np.median(ratio)), "ratio_min": float(ratio.min()),
            "ratio_max": float(ratio.max()),
            "outside_one_ratio_interval": int(np.sum((ratio < one[0]) | (ratio > one[1]))),
            "interval_all_ratios": list(every),
            "all_inside": bool(np.all((ratio >= every[0]) & (ratio <= every[1]))),
            "sqrt_nees": float(np.sqrt(r.nees)), "displacement_ratio": r.displacement_ratio,
            "strain_ratio": r.strain_ratio, "samples": int(len(r.strain_predicted))}
    with run_folder(out, overwrite) as tmp:
        plot_montecarlo(summary, tmp / "montecarlo.png", f"{exp.name}: {trials} calibrations, "
                                                         f"corners sigma {sigma:g} px")
        report.write_config(tmp / "config.toml", exp)
        (tmp / "montecarlo.json").write_text(json.dumps(_jsonable(summary), indent=2) + "\n")
    return summary


def plot_montecarlo(summary: dict, path, title: str) -> None:
    """montecarlo.png: per rig, each parameter's ratio observed / predicted sigma (dots), then
    sqrt(NEES), the displacement and the strain ratio (diamonds), in the bands of the 95 %
    interval of one ratio (dark) and of all the rig's parameter ratios at once (light)."""
    import matplotlib.pyplot as plt

    rigs = summary["rigs"]
    one = summary["interval_one_ratio"]
    widest = max(len(r["parameters"]) for r in rigs.values())
    fig, axes = plt.subplots(len(rigs), 1, figsize=(max(8.0, 0.22 * widest + 3), 3.2 * len(rigs)),
                             squeeze=False, constrained_layout=True)
    for ax, (label, r) in zip(axes[:, 0], rigs.items()):
        names = list(r["parameters"])
        ratios = [p["ratio"] for p in r["parameters"].values()]
        extra = {"sqrt(NEES)": r["sqrt_nees"], "displacement": r["displacement_ratio"],
                 "strain": r["strain_ratio"]}
        x = np.arange(len(names))
        x_extra = len(names) + 1 + np.arange(len(extra))
        ax.axhspan(*r["interval_all_ratios"], color="C0", alpha=0.12,
                   label=f"95 % of all {len(names)} ratios at once")
        ax.axhspan(*one, color="C0", alpha=0.25, label="95 % of one ratio")
        ax.axhline(1.0, color="k", lw=0.8)
        ax.plot(x, ratios, "o", color="C3", ms=4, label="parameter")
        ax.plot(x_extra, list(extra.values()), "D", color="C2", ms=5)
        ax.set_xticks(list(x) + list(x_extra), names + list(extra), rotation=90, fontsize=7)
        ax.set_ylabel("observed / predicted sigma")
        ax.set_title(f"rig {label}", fontsize=9)
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_montecarlo(summary: dict) -> None:
    """The console lines of `vdo calibrate --montecarlo`: per rig the parameter ratios' median
    and range, whether all lie in their Bonferroni interval, sqrt(NEES), displacement and strain."""
    low, high = summary["interval_one_ratio"]
    print(f"{summary['trials']} calibrations, corners sigma {summary['sigma_det_px']:g} px, "
          f"{summary['seconds']:.1f} s; 95 % interval of one ratio [{low:.3f}, {high:.3f}]")
    for label, r in summary["rigs"].items():
        lo, hi = r["interval_all_ratios"]
        print(f"rig {label}: {len(r['parameters'])} parameters, ratio median {r['ratio_median']:.3f} "
              f"({r['ratio_min']:.3f}-{r['ratio_max']:.3f}), all inside [{lo:.3f}, {hi:.3f}]: "
              f"{'yes' if r['all_inside'] else 'no'}; sqrt(NEES) {r['sqrt_nees']:.3f}, "
              f"displacement {r['displacement_ratio']:.3f}, strain {r['strain_ratio']:.3f}")


def evaluation_plan(exp, geometry):
    """`vdo evaluate`'s calibration session (`vdo.calib.session.plan` at scale 1) when the file
    has a [calibration] table, else None and no work; built and checked before the ray cast, so
    that a session that cannot calibrate stops evaluate in one line before its heavy work."""
    if not exp.has("calibration"):
        return None
    from vdo.calib.session import plan

    return plan(exp, 1.0, geometry)


def evaluation_errors(planned, state) -> tuple[dict, object]:
    """The calibration-induced errors `vdo evaluate` gives beside the image noise: the planned
    session's corners simulated without noise at the true cameras, calibrated with
    sigma_det = [calibration] detection_sigma_px (default `vdo.calib.planner.DEFAULT_SIGMA_DET_PX`),
    the covariance sigma_det^2 (J^T J)^-1 carried into every sample seen by a calibrated pair
    (`vdo.calib.propagate.sample_errors`). Returns (summary.json's "calibration": the session, the
    detection noise and per region `region_table`, the `SampleErrors`)."""
    from vdo.calib.planner import DEFAULT_SIGMA_DET_PX
    from vdo.calib.propagate import sample_errors
    from vdo.calib.solve import calibrate, simulate

    exp, samples = state.experiment, state.samples
    cams = list(planned.cameras)
    session = planned.session
    given = exp.calibration.detection_sigma_px
    sigma = given or DEFAULT_SIGMA_DET_PX
    obs = simulate(cams, session, 0.0, np.random.default_rng(exp.calibration.seed))
    cal = calibrate([c.name for c in cams], {c.name: (c.width, c.height) for c in cams}, obs,
                    session.target, sigma)
    errors = sample_errors(cal, exp, cams, samples, state.visibility.visible, session.pairs)
    eps, sigma_dic = state.strain
    out = {"sigma_det_px": sigma,
           "sigma_det_from": "detection_sigma_px" if given else "default (no detection_sigma_px)",
           "target": session.target.description(), "poses": len(session.poses),
           "images": sum(len(v) for v in session.views.values()),
           "pairs": [f"{a}:{b}" for a, b in errors.pairs],
           "regions": region_table(exp, samples, errors, sigma_dic, eps[:, 0])}
    return out, errors


def write_evaluation_map(folder, exp, samples, errors) -> None:
    """maps/calibration_strain.png of `vdo evaluate`: the calibration-induced strain sigma at the
    test's strain (systematic), when any sample is seen by a calibrated pair."""
    from vdo.outputs import maps

    if np.isfinite(errors.strain).any():
        maps.plot_unfolded(samples, errors.strain * 1e6, folder / "maps" / "calibration_strain.png",
                           f"{exp.name}: calibration-induced strain sigma at strain "
                           f"{exp.calibration.strain:g} (microstrain, systematic)", "microstrain")
