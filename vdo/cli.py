"""The command line: `vdo evaluate CONFIG --out DIR`, `vdo render CONFIG --out DIR`,
`vdo export CONFIG_OR_RUN --format F --out DIR` and `vdo demo`."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .backend import BackendError
from .errors import ConfigError
from .memory import retain_freed_memory

BUILTIN = Path(__file__).resolve().parent.parent / "experiments" / "beam_column" / "ten_cameras.toml"


def _print_summary(summary: dict) -> None:
    print(f"{'region':<22}{'area m2':>8}{'>=1':>6}{'>=2':>6}{'>=3':>6}"
          f"{'sens x/y/z mpx/um':>21}{'sigma p50/p95 um':>19}")
    for name, r in summary["regions"].items():
        sens = "/".join(f"{r['sensitivity_mpx_per_um'][a]:.1f}" for a in "xyz")
        sig = r["sigma_max_um"]
        sig = "-" if sig["p50"] is None else f"{sig['p50']:.2f}/{sig['p95']:.2f}"
        print(f"{name:<22}{r['area_m2']:>8.3f}" + "".join(
            f"{100 * r[f'seen_by_{m}_or_more']:>5.0f}%" for m in (1, 2, 3)) + f"{sens:>21}{sig:>19}")


def _evaluate(config_path, out, overwrite, quiet):
    from .config import load
    from .evaluate import evaluate

    exp = load(config_path)
    summary = evaluate(exp, Path(out), overwrite=overwrite, quiet=quiet)
    if not quiet:
        _print_summary(summary)
        from .checks import print_checks
        print_checks(summary["design_checks"])
        print(f"wrote {Path(out).resolve()}")


def _render(args):
    from .config import load
    from .render import render_experiment

    exp = load(args.config)
    if args.series is not None:
        from .series import render_series

        poses = None if args.series == "load_path" else args.series
        summary = render_series(exp, Path(args.out), poses, scale=args.scale, spp=args.spp,
                                seed=args.seed, overwrite=args.overwrite, quiet=args.quiet)
        if not args.quiet:
            print(f"rendered {len(summary['steps'])} steps x {len(summary['cameras'])} cameras in "
                  f"{summary['total_seconds']:.1f} s; wrote {Path(args.out).resolve()}")
        return
    summary = render_experiment(exp, Path(args.out), scale=args.scale, spp=args.spp, seed=args.seed,
                                overwrite=args.overwrite, quiet=args.quiet)
    if not args.quiet:
        print(f"rendered {len(summary['cameras'])} cameras in {summary['total_seconds']:.1f} s; "
              f"wrote {Path(args.out).resolve()} (see contact_sheet.png)")


def _validate(args):
    from .validate import load, print_table, validate

    spec = load(args.config)
    summary = validate(spec, Path(args.out), seeds=args.seeds, overwrite=args.overwrite,
                       quiet=args.quiet)
    if not args.quiet:
        print_table(summary["rows"])
        print(f"{'all ratios in [0.8, 1.25]' if summary['passed'] else 'SOME RATIOS OUTSIDE [0.8, 1.25]'}"
              f"; noise-free check {'passed' if summary['noise_free_passed'] else 'FAILED'}; "
              f"{summary['wall_seconds']:.0f} s; wrote {Path(args.out).resolve()}")
    return 0 if summary["passed"] and summary["noise_free_passed"] else 1


def _optimize(args) -> None:
    from .config import load
    from .optimize import optimize

    result = optimize(load(args.config), Path(args.out), overwrite=args.overwrite, quiet=args.quiet)
    if not args.quiet:
        before, after = result["joint_p95_um"]
        if before is not None and after is not None:
            print(f"joint sigma_max p95: {before:.3f} -> {after:.3f} um")
        for entry in result["violated"]:
            print(f"violated: {entry['constraint']} {entry.get('cameras', '')} "
                  f"{entry.get('region', '')}: {entry['value']:.4g} (limit {entry['limit']})")
        print(f"wrote {Path(args.out).resolve()}")


def _design(args) -> None:
    from .config import load
    from .design import design

    result = design(load(args.config), Path(args.out), overwrite=args.overwrite, quiet=args.quiet,
                    refine=args.refine)
    for message in result["problems"]:
        print(f"warning: {message}", file=sys.stderr)
    if not args.quiet:
        for c in result["curve"]:
            p95 = "unmeasured" if c["sigma_p95_um"] is None else f"{c['sigma_p95_um']:.3f} um"
            print(f"{c['cameras']:3d} cameras: sigma_max p95 {p95}, coverage {100 * c['coverage']:.1f} %")
        if result["target_count"] is not None:
            print(f"smallest count meeting the target: {result['target_count']}")
        if result["refined"] is not None:
            before, after = result["refined"]["joint_p95_um"]
            print(f"refined: joint sigma_max p95 {before} -> {after} um, "
                  f"{result['refined']['violations']} constraint violation(s)")
        print(f"wrote {Path(args.out).resolve()} ({result['wall_s']:.0f} s)")


def _export(args) -> None:
    from .formats.export import export

    pairs = None if args.pairs is None else [tuple(p.split(":", 1)) for p in args.pairs]
    for path in export(args.source, args.format, args.out, pairs, overwrite=args.overwrite):
        print(f"wrote {path}")
def _sweep(args) -> int:
    from .sweep import load_sweep, sweep

    result = sweep(load_sweep(args.sweep), args.out, workers=args.workers, dask=args.dask,
                   quiet=args.quiet)
    for r in [r for r in result["rows"] if r["status"] == "failed"][:5]:
        print(f"point {r['index']} failed: {r['error']}", file=sys.stderr)
    print(f"{result['points']} points: {result['done']} done ({result['reused']} stored before), "
          f"{result['failed']} failed; wrote {result['results']}")
    return 1 if result["failed"] else 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="vdo", description="Virtual design of multi-camera DIC tests")
    sub = parser.add_subparsers(dest="command", required=True)
    ev = sub.add_parser("evaluate", help="coverage of the regions of interest by the cameras")
    ev.add_argument("config", help="experiment TOML file")
    ev.add_argument("--out", required=True, help="output folder (created; must be new or empty)")
    ev.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    ev.add_argument("--quiet", action="store_true")
    rd = sub.add_parser("render", help="photo-realistic noisy images of every camera")
    rd.add_argument("config", help="experiment TOML file")
    rd.add_argument("--out", required=True, help="output folder (created; must be new or empty)")
    rd.add_argument("--scale", type=float, default=None, help="image size relative to the sensor "
                                                              "(default: [render] scale)")
    rd.add_argument("--spp", type=int, default=None, help="samples per pixel (default: [render] spp)")
    rd.add_argument("--seed", type=int, default=None, help="random seed (default: [render] seed)")
    rd.add_argument("--series", nargs="?", const="load_path", default=None, metavar="POSES.csv",
                    help="render a reference and deformed image series over the load path: the "
                         "experiment's [load_path], or the poses per step and group (or mesh) of "
                         "POSES.csv (see vdo.keyframes)")
    rd.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    rd.add_argument("--quiet", action="store_true")
    va = sub.add_parser("validate", help="predicted vs measured (correlation) uncertainty on renders")
    va.add_argument("config", help="validation TOML file (e.g. experiments/validation.toml)")
    va.add_argument("--out", required=True, help="output folder (created; must be new or empty)")
    va.add_argument("--seeds", type=int, default=None,
                    help="noise seeds per case (default: [validation] seeds)")
    va.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    va.add_argument("--quiet", action="store_true")
    op = sub.add_parser("optimize", help="move the cameras along their rails under the constraints")
    op.add_argument("config", help="experiment TOML file (its [optimize] table says what moves)")
    op.add_argument("--out", required=True, help="output folder (created; must be new or empty)")
    op.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    op.add_argument("--quiet", action="store_true")
    de = sub.add_parser("design", help="choose camera poses and lenses from scratch (docs/design.md)")
    de.add_argument("config", help="experiment TOML file (its [design] table says what to choose from)")
    de.add_argument("--out", required=True, help="output folder (created; must be new or empty)")
    de.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    de.add_argument("--quiet", action="store_true")
    de.add_argument("--refine", action="store_true", help="then run vdo optimize on the design (refine/)")
    ex = sub.add_parser("export", help="calibration files for DIC software (docs/exports.md)")
    ex.add_argument("source", help="experiment TOML file or run folder (with layout.json)")
    ex.add_argument("--format", required=True, help="opencv, matchid, dice or vic3d")
    ex.add_argument("--out", required=True, help="output folder (created; must be new or empty)")
    ex.add_argument("--pairs", nargs="+", metavar="FIRST:SECOND", default=None,
                    help="stereo pairs (default: every pair that shares a field of view)")
    ex.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    rp = sub.add_parser("report", help="write RUN_DIR/report.html (3D view, tables, figures)")
    rp.add_argument("run_dir", help="a run folder written by vdo")
    sw = sub.add_parser("sweep", help="evaluate or optimize many variants of an experiment")
    sw.add_argument("sweep", help="sweep TOML file (base experiments, axes, action)")
    sw.add_argument("--out", required=True, help="sweep folder: new, or an earlier run's to resume")
    sw.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core)")
    sw.add_argument("--dask", default=None, help="Dask scheduler address, or 'local' for a LocalCluster")
    sw.add_argument("--quiet", action="store_true")
    demo = sub.add_parser("demo", help="evaluate the built-in 10-camera beam-column experiment")
    demo.add_argument("--out", default=None, help="output folder (default: runs/demo-TIMESTAMP)")
    args = parser.parse_args(argv)
    retain_freed_memory()  # before the first JAX computation (`vdo.memory`)
    started = time.perf_counter()
    try:
        if args.command == "evaluate":
            _evaluate(args.config, args.out, args.overwrite, args.quiet)
        elif args.command == "render":
            _render(args)
        elif args.command == "validate":
            return _validate(args)
        elif args.command == "optimize":
            _optimize(args)
        elif args.command == "design":
            _design(args)
        elif args.command == "export":
            _export(args)
        elif args.command == "report":
            from .html_report import write_report

            if not Path(args.run_dir).is_dir():
                raise ConfigError(args.run_dir, "RUN_DIR", "is not a folder; give a run folder")
            print(f"wrote {write_report(args.run_dir).resolve()}")
        elif args.command == "sweep":
            return _sweep(args)
        elif args.command == "demo":
            if not BUILTIN.is_file():
                raise ConfigError(BUILTIN, "", "the built-in experiment is not here; run vdo demo "
                                               "from a checkout of the vdo repository")
            out = args.out or Path("runs") / time.strftime("demo-%Y%m%d-%H%M%S")
            _evaluate(BUILTIN, out, False, False)
            print(f"demo finished in {time.perf_counter() - started:.0f} s; open "
                  f"{Path(out).resolve() / 'maps' / 'coverage.png'} and samples.vtp in ParaView")
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except BackendError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
