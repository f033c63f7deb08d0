"""The command line: `vdo evaluate|render|validate|optimize CONFIG --out DIR`, `vdo export`,
`vdo sweep`, `vdo report` and `vdo demo`.

Order of work, so that mistakes and interrupts cost nothing: SIGINT/SIGTERM handlers first
(`vdo.core.interrupts`), then the arguments, the output folder (`vdo.core.runfolder.check_out`) and the
config file, all before JAX, Mitsuba or matplotlib are imported (this module imports them only
inside the commands); then `vdo.core.configure.configure()` and the work. Exit status: 0 done, 1 a
check that failed (`validate`) or a worker's task that failed (one line naming it:
`vdo.core.parallel.TaskFailed`), 2 a user mistake (one line naming file and field; a path the
system refuses, too long or not permitted: one line naming it), 3 Mitsuba could not start,
130 / 143 interrupted by SIGINT / SIGTERM (one line; no output folder left).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from vdo.core import interrupts
from vdo.core.backend import BackendError
from vdo.physics.checks import print_checks
from vdo.core.errors import ConfigError
from vdo.core.parallel import TaskFailed
from vdo.core.runfolder import check_out, is_file
from vdo.core.memory import retain_freed_memory

BUILTIN = Path(__file__).resolve().parents[2] / "experiments" / "beam_column" / "ten_cameras.toml"
# per command: the module whose import is heavy (done inside `interrupts.held`)
_MODULES = {"evaluate": "vdo.commands.evaluate", "demo": "vdo.commands.evaluate",
            "render": "vdo.commands.render", "validate": "vdo.commands.validate",
            "optimize": "vdo.commands.optimize", "design": "vdo.commands.design", "export": "vdo.commands.export",
            "sweep": "vdo.commands.sweep", "report": "vdo.outputs.html_report",
            "calibrate": "vdo.commands.calibrate"}
_OWN_FOLDER = {"sweep"}     # commands whose --out is a store they check themselves (resumable)


DASK_CONNECT_S = 30.0   # --dask ADDRESS: a scheduler not reached within this long is one error line
MAX_ROWS = 40   # console rows: past this many regions, one row per region group; flagged pairs


def _grouped(regions: dict) -> dict:
    """Per region group (`vdo.outputs.maps.region_groups`): area summed, coverage and sensitivity
    area-weighted, sigma p50 the groups' median of its regions' p50 and p95 the worst p95."""
    from vdo.outputs.maps import region_groups

    names = list(regions)
    out = {}
    for group, members in region_groups(names).items():
        rs = [regions[names[k]] for k in members]
        a = np.array([r["area_m2"] for r in rs])
        avg = lambda f: float(np.dot(a, [f(r) for r in rs]) / a.sum())          # noqa: E731
        p50 = [r["sigma_max_um"]["p50"] for r in rs if r["sigma_max_um"]["p50"] is not None]
        p95 = [r["sigma_max_um"]["p95"] for r in rs if r["sigma_max_um"]["p95"] is not None]
        out[f"{group} ({len(rs)})"] = {
            "area_m2": float(a.sum()),
            **{f"seen_by_{m}_or_more": avg(lambda r: r[f"seen_by_{m}_or_more"]) for m in (1, 2, 3)},
            "sensitivity_mpx_per_um": {x: avg(lambda r: r["sensitivity_mpx_per_um"][x]) for x in "xyz"},
            "sigma_max_um": {"p50": float(np.median(p50)) if p50 else None,
                             "p95": max(p95) if len(p95) == len(rs) else None}}
    return out


def _p50_p95(sigma: dict) -> str:
    """'p50/p95' in µm to two decimals, '-' for either that is None (a group whose regions are
    partly unmeasured has a median of the measured ones and no worst p95)."""
    return "/".join("-" if sigma[k] is None else f"{sigma[k]:.2f}" for k in ("p50", "p95")).replace("-/-", "-")


def _print_summary(summary: dict) -> None:
    regions = summary["regions"]
    grouped = len(regions) > MAX_ROWS
    if grouped:
        regions = _grouped(regions)
        print(f"{len(summary['regions'])} regions in {len(regions)} groups (every region in summary.json): "
              "area-weighted coverage and sensitivity, median p50 and worst p95")
    m = None if grouped else summary.get("measured")
    print(f"{'region':<22}{'area m2':>8}{'>=1':>6}{'>=2':>6}{'>=3':>6}"
          f"{'sens x/y/z mpx/um':>21}{'bound p50/p95 um':>19}"
          + (f"{'measured p50/p95 um':>22}" if m else ""))
    for name, r in regions.items():
        sens = "/".join(f"{r['sensitivity_mpx_per_um'][a]:.1f}" for a in "xyz")
        sig = _p50_p95(r["sigma_max_um"])
        meas = ""
        if m:
            meas = f"{_p50_p95(m['regions'][name]['sigma_measured_um']):>22}"
        print(f"{name:<22}{r['area_m2']:>8.3f}" + "".join(
            f"{100 * r[f'seen_by_{m}_or_more']:>5.0f}%" for m in (1, 2, 3)) + f"{sens:>21}{sig:>19}"
            + meas)
    if m:
        from vdo.model.spline_response import INTERPOLANT_NAMES     # (jax: imported only when printed)

        print(f"measured: {m['processing']}" + (f" ({m['pairs']} pairs, {m['merge']})"
                                                 if m["pairs"] else "")
              + f", {INTERPOLANT_NAMES[m['interpolant']]}, {m['reference']} reference; bound: Cramér-Rao, "
                "one noisy image, all views")


def _load(args):
    """The command's validated input (config or validation spec), before any heavy import; for
    an experiment, its meshes and load path's files too (`_experiment`), so that a camera inside
    a mesh or a bad row stops the command before any work."""
    if args.command == "validate":
        from vdo.config import validation

        spec = validation.load(args.config)     # every field of every case: no heavy import
        from vdo.geometry.plate import check_cases

        check_cases(spec)                       # the cameras (JAX): still before any render
        if any(c.processing == "pairs" for c in spec.cases):
            from vdo.dic.validate import check_pairs

            check_pairs(spec)                   # the stereo pairs' rule at each patch: no render
        return spec
    if args.command == "calibrate":
        _calibrate_flags(args)
    exp = _experiment(args.config, getattr(args, "series", None))
    if args.command == "evaluate":
        _evaluate_flags(args, exp)
    if getattr(args, "cameras", None) is not None:
        names = [c.name for c in exp.camera_specs]
        unknown = [n for n in args.cameras if n not in names]
        if unknown or not args.cameras:
            what = f"no camera is named {unknown[0]!r}" if unknown else "names no camera"
            raise ConfigError(args.config, "--cameras", f"{what}: give names of {', '.join(names)}, "
                                                        "separated by commas")
        if args.series is not None:
            raise ConfigError(args.config, "--cameras", "renders single shots; a --series "
                                                        "renders every camera (drop one of them)")
    if getattr(args, "calibration", None):      # which camera from which file: to the run folder
        from vdo.calib.importer import imported
        exp, args.calibration_files = imported(exp, args.calibration,
                                               getattr(args, "calibration_anchor", None))
    elif getattr(args, "calibration_anchor", None):
        raise ConfigError(args.config, "--calibration-anchor", "places --calibration's files: "
                                                               "add --calibration FILE ...")
    return exp


def _experiment(path, series=None):
    """The experiment of `path`, read and checked whole: its tables, then together
    (`vdo.state.check_experiment`) its meshes (no camera inside one), its load-path
    files (every step) and a --series POSES.csv, and the lens catalogue of an optimize."""
    from vdo.config.experiment import load
    from vdo.state import check_experiment

    exp = load(path)
    if series not in (None, "load_path") and not is_file(series):
        raise ConfigError(series, "--series", "no such file: give a CSV of poses per step and "
                                              "group (see vdo.geometry.keyframes)")
    check_experiment(exp, None if series in (None, "load_path") else Path(series))
    return exp


def kind_of(path) -> str:
    """'validation', 'sweep' or 'experiment': which file `path` is, by its top tables."""
    from vdo.config.reader import read_toml

    data = read_toml(path)
    return "validation" if "validation" in data or "case" in data else \
        "sweep" if "sweep" in data else "experiment"


def check(paths) -> int:
    """`vdo check FILE...`: every up-front check of each file (an experiment, a validation or a
    sweep file; with its meshes, load-path files and cases), nothing computed; one line per
    file. Returns 0 when all pass, else 2 (the first error line is printed by `main`)."""
    for path in paths:
        kind = kind_of(path)
        if kind != "experiment":   # their cases and points build cameras (JAX, float64)
            from vdo.core.configure import configure
            configure()
        if kind == "validation":
            from vdo.dic.validate import load as load_validation
            spec = load_validation(path)
            print(f"ok: {path}: validation file, {len(spec.cases)} cases")
        elif kind == "sweep":
            from vdo.config.sweep import expand, load_sweep
            points = expand(load_sweep(path))
            print(f"ok: {path}: sweep file, {len(points)} points")
        else:
            exp = _experiment(path)
            print(f"ok: {path}: experiment {exp.name!r}, {len(exp.camera_specs)} cameras, "
                  f"{len(exp.regions)} regions, {len(exp.meshes)} meshes")
    return 0


def _evaluate_flags(args, exp) -> None:
    """`vdo evaluate`'s --workers and --dask, checked before any work: they run the load path's
    steps, so the experiment must have one."""
    if args.workers is not None and args.workers < 1:
        raise ConfigError(args.config, "--workers", f"must be at least 1 (got {args.workers}); 1 "
                                                    "judges the load path's steps in this process")
    if not exp.load_path.active:
        for flag, value in (("--workers", args.workers), ("--dask", args.dask)):
            if value is not None:
                raise ConfigError(args.config, flag, "runs the load path's steps, and the "
                                                     "experiment has no [load_path]: drop it")


def _evaluate(exp, args):
    from vdo.commands.evaluate import evaluate
    from vdo.core.parallel import blas_environment, cores, dask_client

    workers = getattr(args, "workers", None)        # `vdo demo`: neither flag
    dask = getattr(args, "dask", None)
    # Dask workers compute as this process (their OpenBLAS thread count): the same result
    with dask_client(dask, workers or cores(), DASK_CONNECT_S, prefix="vdo-evaluate-dask-",
                     env=blas_environment()) as client:
        result = evaluate(exp, Path(args.out), overwrite=args.overwrite, workers=workers, client=client,
                          calibration_files=getattr(args, "calibration_files", None))
    if not args.quiet:
        _print_summary(result.to_json())
        if result.calibration is not None:
            _print_calibration(result.calibration)
        print_checks(result.design_checks, result.negligible_views or ())
        print(f"wrote {Path(args.out).resolve()}")


def _print_calibration(cal: dict) -> None:
    """Per region, p95 of the calibration-induced displacement and strain sigma (systematic)
    beside the image noise's (random), `vdo evaluate` with a [calibration] table."""
    def show(d):
        return "-" if d["p95"] is None else f"{d['p95']:.3g}"

    print(f"calibration ({cal['images']} images, corners {cal['sigma_det_px']:g} px): p95 per region, "
          "calibration systematic, noise random per step")
    print(f"{'region':<22}{'calib u um':>12}{'noise u um':>12}{'calib strain ue':>17}{'noise strain ue':>17}")
    for name, r in cal["regions"].items():
        print(f"{name:<22}{show(r['calibration_displacement_um']):>12}{show(r['noise_displacement_um']):>12}"
              f"{show(r['calibration_strain_microstrain']):>17}{show(r['noise_strain_microstrain']):>17}")


def _pairs(names):
    """--pairs FIRST:SECOND ... as (first, second) tuples, or None."""
    return None if names is None else [tuple(p.split(":", 1)) for p in names]


def _render(exp, args):
    from vdo.commands.render import render_experiment

    if args.series is not None:
        from vdo.commands.series import render_series

        poses = None if args.series == "load_path" else args.series
        summary = render_series(exp, Path(args.out), poses, scale=args.scale, spp=args.spp,
                                seed=args.seed, overwrite=args.overwrite, pairs=_pairs(args.pairs))
        if not args.quiet:
            print(f"rendered {len(summary['steps'])} steps x {len(summary['cameras'])} cameras in "
                  f"{summary['total_seconds']:.1f} s; wrote {Path(args.out).resolve()}")
        return
    summary = render_experiment(exp, Path(args.out), scale=args.scale, spp=args.spp, seed=args.seed,
                                overwrite=args.overwrite, pairs=_pairs(args.pairs), only=args.cameras)
    if not args.quiet:
        print(f"rendered {len(summary['cameras'])} cameras in {summary['total_seconds']:.1f} s; "
              f"wrote {Path(args.out).resolve()} (see contact_sheet.png)")


def _validate(spec, args):
    from vdo.commands.validate import print_table, validate_cases, verdict_line

    summary = validate_cases(spec, Path(args.out), seeds=args.seeds, overwrite=args.overwrite)
    if not args.quiet:
        print_table(summary["rows"])
        print(f"{verdict_line(summary)}; {summary['wall_seconds']:.0f} s; wrote {Path(args.out).resolve()}")
    return 0 if summary["passed"] and summary["noise_free_passed"] else 1


_SCORED = {"bound": "sigma_max", "measured": "sigma_measured max"}   # [optimize] score, as printed


def _optimize(exp, args) -> None:
    from vdo.commands.optimize import optimize

    result = optimize(exp, Path(args.out), overwrite=args.overwrite, time_limit=args.time_limit,
                      started=args.started)   # the limit counts the whole command
    if not args.quiet:
        print(f"search: {result.status} (start-up {result.startup_s:.0f} s, search "
              f"{result.search_s:.0f} s); score (smooth {_SCORED[exp.optimize.score]} percentile) "
              f"{result.score_before_um:.4g} -> {result.score_after_um:.4g} um")
        if result.reason:
            print(result.reason)
        for name, r in result.score_regions_um.items():   # the regions the score counts
            if r["scored"] and r["sigma_smooth_um"] is not None:
                # the score's views and the final layout's evaluation (summary_after.json) differ
                # by the area seen twice with a view under the usable weight (grazing, at the
                # image's edge): the score keeps it at a finite sigma, the evaluation does not
                final = result.after.regions[name].unmeasured_fraction if name in result.after.regions else None
                print(f"  {name}: smooth sigma_max {r['sigma_smooth_um']:.4g} um"
                      + (f" ({100 * r['unmeasured_fraction']:.1f} % of the area unmeasured in the score's "
                         "views, counted as 1 mm" + ("" if final is None else
                                                      f"; {100 * final:.1f} % in summary_after.json") + ")"
                         if r["unmeasured_fraction"] > 0 or (final or 0) > 0 else "")
                      + (f", coverage shortfall {r['coverage_um']:.3g} um" if r["coverage_um"] > 1e-3 else ""))
        before, after = result.worst_p95_um
        show = lambda v: "unmeasured" if v is None else f"{v:.3f} um"
        print(f"sigma_max p95 of the worst scored region: {show(before)} -> {show(after)}")
        for entry in result.violated:
            print(f"violated: {entry['constraint']} {entry.get('cameras', '')} "
                  f"{entry.get('region', '')}: {entry['value']:.4g} (limit {entry['limit']})")
        print(f"wrote {Path(args.out).resolve()}")


def _speckle(exp, args) -> None:
    from vdo.commands.speckle import speckle

    result = speckle(exp, Path(args.out), overwrite=args.overwrite)
    for region, r in result["regions"].items():
        s = "unmeasured" if r["sigma_p95_um"] is None else f"{r['sigma_p95_um']:.3f} um"
        print(f"{region}: dots {' + '.join(f'{d:g}' for d in r['dots_mm'])} mm, sigma_max p95 {s}, "
              f"{len(r['flags'])} flagged checks; print {args.out}/{r['files'][0]}")


def _design(exp, args) -> None:
    from vdo.core.parallel import cores, dask_client
    from vdo.commands.design import curve_line, design, uncompared

    workers = args.workers or cores()
    # the candidates judged on Dask workers (spawned processes for "local")
    with dask_client(args.dask, workers, DASK_CONNECT_S, prefix="vdo-design-dask-") as client:
        result = design(exp, Path(args.out), overwrite=args.overwrite, refine=args.refine,   # logs its problems
                        memory_limit=None if args.memory_gb is None else args.memory_gb * 1e9,
                        time_limit=args.time_limit, client=client,
                        threads=max(1, cores() // workers) if args.dask == "local" else None)
    if not args.quiet:
        for c in result.curve:
            print(curve_line(c, exp.optimize.regions or [r.name for r in exp.regions]))
        missing = uncompared(result.curve)       # no figure over the area every count measures
        if missing is not None:
            print(missing)
        if result.target_count is not None:
            print(f"smallest count meeting the target: {result.target_count}")
        if result.refined is not None:
            before, after = (("unmeasured" if v is None else f"{v:.3f} um") for v in result.refined.worst_p95_um)
            print(f"refined: sigma_max p95 of the worst scored region {before} "
                  f"({result.violations} constraint violation(s)) -> {after} "
                  f"({result.refined.violations})")
        print(f"wrote {Path(args.out).resolve()} ({result.wall_s:.0f} s)")


def _export(_, args) -> None:
    from vdo.commands.export import export

    pairs = _pairs(args.pairs)
    for path in export(args.source, args.format, args.out, pairs, overwrite=args.overwrite):
        print(f"wrote {path}")


def _report(_, args) -> None:
    from vdo.outputs.html_report import EXPECTED, write_report

    if not Path(args.run_dir).is_dir():
        raise ConfigError(args.run_dir, "RUN_DIR", "is not a folder; give a run folder")
    if not any((Path(args.run_dir) / f).is_file() for files in EXPECTED.values() for f in files):
        raise ConfigError(args.run_dir, "RUN_DIR", "holds none of the files a vdo run writes "
                                                   "(summary.json, layout.json, ...): give the --out "
                                                   "folder of a vdo command")
    print(f"wrote {write_report(args.run_dir).resolve()}")


def _sweep(_, args) -> int:
    from vdo.commands.sweep import sweep
    from vdo.config.sweep import load_sweep

    result = sweep(load_sweep(args.sweep), args.out, workers=args.workers, dask=args.dask,
                   max_points=args.max_points)
    for r in [r for r in result["rows"] if r["status"] == "failed"][:5]:
        print(f"point {r['index']} failed: {r['error']}", file=sys.stderr)
    pending = f", {result['pending']} pending (run it again to finish)" if result["pending"] else ""
    print(f"{result['points']} points: {result['done']} done ({result['reused']} stored before), "
          f"{result['failed']} failed{pending}; wrote {result['results']}")
    return 1 if result["failed"] else 0


def _calibrate_flags(args) -> None:
    """`vdo calibrate`'s flags that go together, checked before the experiment is read."""
    if args.montecarlo is None:
        for flag, value in (("--workers", args.workers), ("--dask", args.dask)):
            if value is not None:
                raise ConfigError(args.config, flag, "runs the --montecarlo trials: add "
                                                     "--montecarlo N or drop it")
        return
    if args.plan:
        raise ConfigError(args.config, "--montecarlo", "and --plan are two different runs: give "
                                                       "one of them")
    if args.montecarlo < 2:
        raise ConfigError(args.config, "--montecarlo", f"needs at least 2 calibrations (got "
                                                       f"{args.montecarlo}): the scatter is a sample "
                                                       "standard deviation; 50 or more make a check")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(args.config, "--workers", f"must be at least 1 (got {args.workers}); 1 "
                                                    "runs the calibrations in this process")


def _calibrate(exp, args) -> int | None:
    from vdo.commands.calibrate import calibrate_experiment, plan_experiment, print_summary

    if args.montecarlo is not None:
        from vdo.commands.calibrate import montecarlo_experiment, print_montecarlo
        from vdo.core.parallel import blas_environment, cores, dask_client

        workers = args.workers or cores()
        env = blas_environment()      # Dask workers compute as this process: the same result
        try:
            with dask_client(args.dask, workers, prefix="vdo-montecarlo-dask-", env=env) as client:
                summary = montecarlo_experiment(exp, Path(args.out), args.montecarlo, workers=workers,
                                                client=client, overwrite=args.overwrite,
                                                time_limit=args.time_limit)
        except TimeoutError as exc:      # --time-limit: one line, no output folder
            print(f"error: {exc} (--time-limit {args.time_limit:g} s); nothing written", file=sys.stderr)
            return 1
        if not args.quiet:
            print_montecarlo(summary)
            print(f"wrote {Path(args.out).resolve()}")
        return
    if args.plan:
        result = plan_experiment(exp, Path(args.out), overwrite=args.overwrite)
        if not args.quiet:
            for n, k, e in zip(result["poses_per_camera"], result["images"], result["strain_sigma_p95"]):
                print(f"{n:>4} poses per camera, {k:>5} images: calibration strain sigma p95 {e:.3g}")
            chosen = result["chosen_poses_per_camera"]
            print(f"target {result['target_strain_error']:g}: " + (
                f"{chosen} poses per camera" if chosen else "not reached by any session tried"))
            print(f"wrote {Path(args.out).resolve()}")
        return
    summary = calibrate_experiment(exp, Path(args.out), scale=args.scale, spp=args.spp,
                                   overwrite=args.overwrite, time_limit=args.time_limit)
    if not args.quiet:
        print_summary(summary)
        print(f"wrote {Path(args.out).resolve()}")


def _command(sub, name: str, help: str, config_help: str) -> argparse.ArgumentParser:
    """A subcommand with the arguments most share: CONFIG, --out, --overwrite and --quiet."""
    parser = sub.add_parser(name, help=help)
    parser.add_argument("config", help=config_help)
    parser.add_argument("--out", required=True, help="output folder (created; must be new or empty)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    parser.add_argument("--quiet", action="store_true")
    return parser


def _calibrate_parser(sub) -> None:
    ca = _command(sub, "calibrate", "render the calibration session, calibrate it, "
                                          "and carry its uncertainty into strain (docs/calibration.md)",
                  "experiment TOML file (its [calibration] table)")
    ca.add_argument("--scale", type=float, default=None, help="image size relative to the sensor "
                                                              "(default: [render] scale)")
    ca.add_argument("--spp", type=int, default=None, help="samples per pixel (default: [render] spp)")
    ca.add_argument("--plan", action="store_true", help="choose the number of poses that reaches "
                                                        "[calibration] target_strain_error (plan.png)")
    ca.add_argument("--montecarlo", type=int, default=None, metavar="N",
                    help="N calibrations of simulated corners against the covariance each predicts "
                         "(montecarlo.json, montecarlo.png)")
    ca.add_argument("--workers", type=int, default=None,
                    help="--montecarlo: worker processes (default: one per core; 1: this process)")
    ca.add_argument("--dask", default=None, metavar="ADDRESS",
                    help="--montecarlo: on a Dask scheduler's workers, or 'local' for a LocalCluster "
                         "of --workers processes")
    ca.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                    help="stop the renders (or the --montecarlo calibrations) after this long "
                         "(no output folder)")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vdo", description="Virtual design of multi-camera DIC tests")
    sub = parser.add_subparsers(dest="command", required=True)
    ev = _command(sub, "evaluate", "coverage of the regions of interest by the cameras",
                                   "experiment TOML file")
    ev.add_argument("--calibration", nargs="+", metavar="FILE", default=None,
                    help="a lab's calibration files (OpenCV .yml, MatchID .caldat, DICe or VIC-3D "
                         ".xml): their cameras replace the experiment's of the same names "
                         "(docs/calibration.md)")
    ev.add_argument("--calibration-anchor", default=None, metavar="CAMERA",
                    help="the calibration files share a frame of their own (a lab's, e.g. its "
                         "first camera's): place it so that CAMERA stands at its pose in the "
                         "experiment file (default: the files' frame is the CAD frame)")
    ev.add_argument("--workers", type=int, default=None,
                    help="judge the load path's steps on this many spawned processes (default: "
                         "this process; with --dask local: the LocalCluster's, default one per core)")
    ev.add_argument("--dask", default=None, metavar="ADDRESS",
                    help="judge the load path's steps on a Dask scheduler's workers, or 'local' "
                         "for a LocalCluster of --workers processes")
    rd = _command(sub, "render", "photo-realistic noisy images of every camera", "experiment TOML file")
    rd.add_argument("--scale", type=float, default=None, help="image size relative to the sensor "
                                                              "(default: [render] scale)")
    rd.add_argument("--spp", type=int, default=None, help="samples per pixel (default: [render] spp)")
    rd.add_argument("--seed", type=int, default=None, help="random seed (default: [render] seed)")
    rd.add_argument("--series", nargs="?", const="load_path", default=None, metavar="POSES.csv",
                    help="render a reference and deformed image series over the load path: the "
                         "experiment's [load_path], or the poses per step and group (or mesh) of "
                         "POSES.csv (see vdo.geometry.keyframes)")
    rd.add_argument("--pairs", nargs="+", metavar="FIRST:SECOND", default=None,
                    help="stereo pairs of the calibration files (default: cameras assigned a "
                         "common region); each must share a field of view")
    rd.add_argument("--cameras", type=lambda t: [n.strip() for n in t.split(",") if n.strip()],
                    default=None, metavar="A,B", help="render only these cameras (the others stay "
                                                      "in the scene as bodies)")
    va = _command(sub, "validate", "predicted vs measured (correlation) uncertainty on renders",
                                   "validation TOML file (e.g. experiments/validation.toml)")
    va.add_argument("--seeds", type=int, default=None,
                    help="noise seeds per case (default: [validation] seeds)")
    op = _command(sub, "optimize", "move the cameras along their rails under the constraints",
                                   "experiment TOML file (its [optimize] table says what moves)")
    op.add_argument("--time-limit", type=float, default=900.0, metavar="SECONDS",
                    help="end the search after this long and write the best layout so far (default 900)")
    de = _command(sub, "design", "choose camera poses and lenses from scratch (docs/design.md)",
                                 "experiment TOML file (its [design] table says what to choose from)")
    de.add_argument("--refine", action="store_true", help="then run vdo optimize on the design (refine/)")
    de.add_argument("--memory-gb", type=float, default=None, metavar="GB",
                    help="refuse, before the work, a design estimated to need more (default: the "
                         "memory available)")
    de.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                    help="refuse, before the work, a design whose judging is estimated to take longer; "
                         "the selection stops at the limit (the inventory's count first)")
    de.add_argument("--dask", default=None, help="judge the candidates on a Dask scheduler's workers "
                                                 "(its address), or 'local' for a LocalCluster")
    de.add_argument("--workers", type=int, default=None,
                    help="LocalCluster worker processes (default: one per core)")
    _command(sub, "speckle", "design the speckle per region; print-ready files (docs/speckle.md)",
                             "experiment TOML file (its cameras and [speckle] print_dpi)")
    ex = sub.add_parser("export", help="calibration files for DIC software (docs/exports.md)")
    ex.add_argument("source", help="experiment TOML file or run folder (with layout.json)")
    ex.add_argument("--format", required=True, help="opencv, matchid, dice or vic3d")
    ex.add_argument("--out", required=True, help="output folder (created; must be new or empty)")
    ex.add_argument("--pairs", nargs="+", metavar="FIRST:SECOND", default=None,
                    help="stereo pairs (default: cameras assigned a common region, optical "
                         "axes at most [analysis] max_pair_angle_deg apart); each must share a "
                         "field of view")
    ex.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    rp = sub.add_parser("report", help="write RUN_DIR/report.html (3D view, tables, figures)")
    rp.add_argument("run_dir", help="a run folder written by vdo")
    sw = sub.add_parser("sweep", help="evaluate or optimize many variants of an experiment")
    sw.add_argument("sweep", help="sweep TOML file (base experiments, axes, action)")
    sw.add_argument("--out", required=True, help="sweep folder: new, or an earlier run's to resume")
    sw.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core)")
    sw.add_argument("--dask", default=None, help="Dask scheduler address, or 'local' for a LocalCluster")
    sw.add_argument("--max-points", type=int, default=None, metavar="N",
                    help="run at most N of the points still to run (a trial; run again without it "
                         "to finish: stored points are kept)")
    sw.add_argument("--quiet", action="store_true")
    ck = sub.add_parser("check", help="validate experiment, validation or sweep files without computing")
    ck.add_argument("files", nargs="+", help="TOML files")
    _calibrate_parser(sub)
    demo = sub.add_parser("demo", help="evaluate the built-in 10-camera beam-column experiment")
    demo.add_argument("--out", default=None, help="output folder (default: runs/demo-TIMESTAMP)")
    return parser


def subcommands() -> tuple[str, ...]:
    """The names of vdo's subcommands (`vdo NAME ...`), in the order of `vdo --help`."""
    action = next(a for a in _parser()._actions if isinstance(a, argparse._SubParsersAction))
    return tuple(action.choices)


def _run(args) -> int:
    started = args.started = time.perf_counter()
    if args.command == "demo":
        if not BUILTIN.is_file():
            raise ConfigError(BUILTIN, "", "the built-in experiment is not here; run vdo demo "
                                           "from a checkout of the vdo repository")
        args.config, args.overwrite, args.quiet = BUILTIN, False, False
        args.out = args.out or Path("runs") / time.strftime("demo-%Y%m%d-%H%M%S")
    if getattr(args, "out", None) is not None and args.command not in _OWN_FOLDER:
        check_out(args.out, getattr(args, "overwrite", False))
    if "jax" not in sys.modules:  # float64 from JAX's first import, should loading the config need it
        os.environ["JAX_ENABLE_X64"] = "1"
    # before loading the config, whose checks may run JAX: threads that allocate before it keep
    # their own malloc arenas (`vdo.core.memory`; measured: 10 M page faults, 20 s of system time in
    # the built-in `vdo optimize` when this came after the load)
    retain_freed_memory()
    if args.command == "check":
        return check(args.files)
    with interrupts.held():  # heavy imports (`vdo.core.interrupts`)
        loaded = _load(args) if hasattr(args, "config") else None
        from vdo.core.configure import configure

        configure()
        if args.command in _MODULES:
            importlib.import_module(_MODULES[args.command])
    handler = {"evaluate": _evaluate, "demo": _evaluate, "render": _render, "validate": _validate,
               "optimize": _optimize, "design": _design, "speckle": _speckle, "export": _export, "report": _report,
               "sweep": _sweep, "calibrate": _calibrate}[args.command]
    status = handler(loaded, args) or 0
    if args.command == "demo":
        print(f"demo finished in {time.perf_counter() - started:.0f} s; open "
              f"{Path(args.out).resolve() / 'report.html'} in a browser")
    return status


class _OnceForMeshes(logging.Filter):
    """Each line of `vdo.meshes` (faces split at a region's box plane, a region's development
    distortion) once per command: the geometry is read again by the up-front checks, the
    evaluation and the figures, and says the same each time."""

    def __init__(self):
        super().__init__()
        self.said: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.name.startswith("vdo.meshes"):
            return True
        text = record.getMessage()
        if text in self.said:
            return False
        self.said.add(text)
        return True


@contextmanager
def _log_to_stderr(quiet: bool):
    """Show the `vdo` logger's records on stderr while the command runs: warnings with --quiet,
    information otherwise; each line above the progress bars (`vdo.core.progress.AboveBars`)."""
    from vdo.core.progress import AboveBars

    handler = AboveBars(sys.stderr)
    handler.setFormatter(logging.Formatter("%(message)s"))
    handler.addFilter(_OnceForMeshes())
    logger = logging.getLogger("vdo")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def main(argv=None) -> int:
    """Run one command; returns the exit status (module docstring). Called without `argv` it is
    the program (``vdo ...``, ``python -m vdo``): after an interrupt it ends the process at once,
    instead of waiting seconds for Dr.Jit's threads to finish the render they were given."""
    restore = interrupts.install()
    try:
        args = _parser().parse_args(argv)
        # `vdo check` says one line per file: the meshes' information lines (faces split at a
        # region's box) are for the commands that compute; its warnings still show
        with _log_to_stderr(getattr(args, "quiet", False) or args.command == "check"):
            return _run(args)
    except BaseException as exc:
        stop = interrupts.interruption(exc)
        if stop is not None:
            interrupts.acknowledge()
            print(stop.message, file=sys.stderr)
            if argv is None:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(stop.exit_code)
            return stop.exit_code
        if isinstance(exc, ConfigError):
            for error in getattr(exc, "errors", (exc,)):   # `ConfigErrors`: every one, a line each
                print(f"error: {error}", file=sys.stderr)
            return 2
        if isinstance(exc, BackendError):
            print(f"error: {exc}", file=sys.stderr)
            return 3
        if isinstance(exc, TaskFailed):     # a worker's task: one line (its traceback at DEBUG)
            print(f"error: {exc}", file=sys.stderr)
            return 1
        if isinstance(exc, OSError) and exc.filename is not None:   # a path the system refuses
            print(f"error: {exc.filename}: {exc.strerror or exc}; check the path (its length, its "
                  "permissions, the space left)", file=sys.stderr)
            return 2
        raise
    finally:
        restore()


if __name__ == "__main__":
    sys.exit(main())
