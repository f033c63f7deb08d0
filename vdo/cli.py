"""The command line: `vdo evaluate CONFIG --out DIR`, `vdo render CONFIG --out DIR` and `vdo demo`."""

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
        print(f"wrote {Path(out).resolve()}")


def _render(args):
    from .config import load
    from .render import render_experiment

    exp = load(args.config)
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

    result = optimize(load(args.config), Path(args.out), overwrite=args.overwrite, quiet=args.quiet,
                      time_limit=args.time_limit)
    if not args.quiet:
        print(f"search: {result['status']}; score (smooth sigma_max percentile) "
              f"{result['score_before']:.4g} -> {result['score_after']:.4g} um")
        for name, r in result["score_regions_um"].items():   # the regions the score counts
            if r["scored"] and r["sigma_smooth_um"] is not None:
                print(f"  {name}: smooth sigma_max {r['sigma_smooth_um']:.4g} um"
                      + (f" ({100 * r['unmeasured_fraction']:.1f} % of the area unmeasured, counted "
                         "as 1 mm)" if r["unmeasured_fraction"] > 0 else "")
                      + (f", coverage shortfall {r['coverage_um']:.3g} um" if r["coverage_um"] > 1e-3 else ""))
        before, after = result["joint_p95_um"]
        if before is not None and after is not None:
            print(f"joint sigma_max p95: {before:.3f} -> {after:.3f} um")
        for entry in result["violated"]:
            print(f"violated: {entry['constraint']} {entry.get('cameras', '')} "
                  f"{entry.get('region', '')}: {entry['value']:.4g} (limit {entry['limit']})")
        print(f"wrote {Path(args.out).resolve()}")


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
    op.add_argument("--time-limit", type=float, default=900.0, metavar="SECONDS",
                    help="end the search after this long and write the best layout so far (default 900)")
    op.add_argument("--quiet", action="store_true")
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
