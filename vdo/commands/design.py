"""`vdo design` as a command: the selection of `vdo.design.select` (`design_layout`) and its run
folder (`write_design`): designed.toml, layout.json, summary.json, constraints.json,
candidates.csv, pareto.csv, pareto.png, design.json, report.html and, with refine, the
`vdo optimize` folder refine/."""

from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

from vdo.commands.optimize import write_optimization
from vdo.config.experiment import Experiment
from vdo.core.runfolder import run_folder
from vdo.design.budget import GB
from vdo.design.candidates import Candidates, bodies, lenses
from vdo.design.select import DesignResult, design_layout
from vdo.outputs import html_report, report


def block_store(out: Path) -> Path:
    """Where `vdo design --out OUT` keeps its judged candidate blocks until OUT is written: the
    hidden folder .OUT.vdo-design-blocks beside OUT, so that a run interrupted before OUT
    appears (it is written whole or not at all) resumes from them when started again with the
    same OUT (`vdo.design.candidates.BlockStore`)."""
    out = Path(out).expanduser().resolve()
    return out.parent / f".{out.name}.vdo-design-blocks"


def design(exp: Experiment, out: Path, overwrite: bool = False, refine: bool = False,
           memory_limit: float | None = None, time_limit: float | None = None, client=None,
           threads: int | None = None) -> DesignResult:
    """Design a layout (`vdo.design.select.design_layout`, the arguments as there) and write its
    run folder into `out` (`write_design`). Resumable: the judged candidate blocks are kept in
    `block_store(out)` until the run folder is written, and a run started again with the same
    experiment and `out` after an interruption judges only the blocks not kept there. Returns
    the `DesignResult`."""
    store = block_store(out)
    result = design_layout(exp, refine=refine, memory_limit=memory_limit, time_limit=time_limit,
                           client=client, threads=threads, store=store)
    write_design(result, out, overwrite)
    shutil.rmtree(store, ignore_errors=True)
    return result


def write_design(result: DesignResult, out: Path, overwrite: bool = False) -> None:
    """The run folder of `vdo design` from its result (atomic, `vdo.core.runfolder`): designed.toml,
    layout.json, summary.json, constraints.json (every constraint check of `vdo optimize`),
    candidates.csv, pareto.csv, pareto.png, design.json (candidates, inventory, the curve and its
    bound, problems, statistics, the estimate against what was measured), report.html and, when
    the result was refined, refine/ (`vdo.commands.optimize.write_optimization`)."""
    rec = result.record
    exp, cand, est, curve = rec.experiment, rec.candidates, rec.estimate, result.curve
    d = exp.design
    best = curve[-1]
    violated = [c for c in rec.checks if not c["met"]]
    with run_folder(out, overwrite) as tmp:
        report.write_config(tmp / "designed.toml", rec.designed)
        report.write_json(tmp / "layout.json", report.layout(list(rec.cameras)))
        report.write_json(tmp / "summary.json", result.summary.to_json())
        report.write_json(tmp / "constraints.json", {"violations": len(violated), "violated": violated,
                                                     "checks": rec.checks})
        write_candidates(tmp / "candidates.csv", exp, cand, best["chosen"])
        write_curve(tmp / "pareto.csv", curve)
        plot_curve(tmp / "pareto.png", curve, d.target_sigma_um, exp.name)
        report.write_json(tmp / "design.json", {
            "candidates": len(cand.cameras), "samples": cand.samples,
            "selection_spacing_mm": d.sample_spacing * 1e3,
            "lenses_mm": [f * 1e3 for f in lenses(exp)], "inventory": rec.inventory,
            "bodies": [{"name": b.name, "count": b.count, "pixels": list(b.pixels),
                        "sensor_width_mm": b.sensor_width * 1e3,
                        "lenses_mm": [f * 1e3 for f in lenses(exp, b)]} for b in bodies(exp)],
            "targets_m": cand.targets.tolist(), "problems": result.problems, "statistics": result.statistics,
            "dropped_per_mount": cand.dropped, "exposure": result.exposure,
            "constraint_violations": result.violations,
            "target_sigma_um": d.target_sigma_um, "smallest_count_meeting_target": result.target_count,
            "coverage_weight": d.coverage_weight,
            "curve": [{k: v for k, v in c.items() if k != "chosen"} for c in curve],
            "gap_to_bound": best["gap"], "bound": best["bound"],
            "wall_s": result.wall_s,
            "estimate": {"candidates": est.candidates, "samples": est.samples, "probed": est.probed,
                         "entries": est.entries, "memory_gb": est.memory_bytes / GB,
                         "judge_s": est.judge_s, "search_s": est.search_s},
            "measured": {"candidates": len(cand.cameras) + cand.pruned, "blind_pruned": cand.pruned,
                         "entries": int(cand.index.size), "peak_memory_gb": rec.peak_memory_bytes / GB,
                         "peak_memory_gb_with_final_judgement": rec.final_peak_memory_bytes / GB,
                         "judge_s": rec.judge_s, "search_s": rec.search_s}})
        html_report.write_report(tmp)
        if result.refined is not None:
            write_optimization(result.refined, tmp / "refine")


def write_candidates(path, exp: Experiment, cand: Candidates, chosen):
    """One row per candidate: mount, pose, body, lens, samples it sees usably, regions assigned,
    the fraction of its view the load path takes away, selected."""
    use = cand.usable_counts()
    names = [b.name for b in bodies(exp)]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["candidate", "mount", "kind", "u", "x_m", "y_m", "z_m", "pan_deg", "tilt_deg",
                    "body", "focal_mm", "target", "usable_samples", "regions_assigned",
                    "load_path_lost", "selected"])
        for i, c in enumerate(cand.cameras):
            w.writerow([i, cand.mount[i], cand.kind[i], "" if math.isnan(cand.u[i]) else f"{cand.u[i]:.4f}",
                        *(f"{x:.4f}" for x in c.position),
                        f"{math.degrees(c.pan):.2f}", f"{math.degrees(c.tilt):.2f}",
                        names[cand.body[i]], f"{c.focal_length * 1e3:g}", int(cand.target[i]),
                        int(use[i]), int(cand.assigned[i].sum()), f"{cand.path_lost[i]:.3f}",
                        int(i in chosen)])


def write_curve(path, curve):
    """pareto.csv: per camera count its score, bound and gap, sigma_max p95 (µm; overall and per
    scored region), coverage, swaps (exchange, then polish), lenses, bodies, the measurable
    area's figures and sigma_max p95 over the area every count measures (`common_p95`); with [design] score = "measured" then σ_measured p95 (µm; the worst scored
    region, then per region)."""
    regions = list(curve[0]["sigma_p95_by_region_um"]) if curve else []
    meas = bool(curve) and "sigma_measured_p95_um" in curve[0]    # [design] score = "measured"
    show = lambda v: "" if v is None else f"{v:.5g}"
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["cameras", "score", "bound", "gap", "sigma_p95_um", "coverage", "swaps", "polish_swaps",
                    "lenses_mm", "bodies", "measurable_fraction", "coverage_of_measurable",
                    "sigma_p95_measurable_um", "common_fraction", "sigma_p95_common_um"]
                   + [f"sigma_p95_um_{r}" for r in regions]
                   + (["sigma_measured_p95_um"] + [f"sigma_measured_p95_um_{r}" for r in regions]
                      if meas else []))
        for c in curve:
            w.writerow([c["cameras"], f"{c['score']:.6g}",
                        "" if c["bound"] is None else f"{c['bound']:.6g}",
                        "" if c["gap"] is None else f"{c['gap']:.4f}",
                        show(c["sigma_p95_um"]), f"{c['coverage']:.4f}", c["swaps"], c["polish_swaps"],
                        c["lenses_mm"], c["bodies"], f"{c['measurable_fraction']:.4f}",
                        f"{c['coverage_of_measurable']:.4f}", show(c["sigma_p95_measurable_um"]),
                        f"{c['common_fraction']:.4f}", show(c["sigma_p95_common_um"])]
                       + [show(c["sigma_p95_by_region_um"][r]) for r in regions]
                       + ([show(c["sigma_measured_p95_um"])]
                          + [show(c["sigma_measured_p95_by_region_um"][r]) for r in regions]
                          if meas else []))


def curve_line(c: dict, scored=None) -> str:
    """One count of the camera-count curve for the console: sigma_max p95 of the worst scored
    region, or, while a scored region has no measured sample, over the area that is measured
    with the unmeasured regions named; then the coverage (of all the regions' area and of what
    the candidate spots can measure); σ_measured p95 of the worst scored region beside the bound
    when the design scores it; and the worst scored region's p95 over the area every count
    measures (`vdo.design.select.common_p95`), where the counts compare."""
    by = c["sigma_p95_by_region_um"]
    scored = list(by) if scored is None else list(scored)
    if c["sigma_p95_um"] is not None:
        worst = max((r for r in scored if by.get(r) is not None), key=lambda r: by[r], default=None)
        sigma = f"sigma_max p95 {c['sigma_p95_um']:.3f} um" + (f" (worst: {worst})" if worst else "")
    else:
        none = [r for r in scored if by.get(r) is None]
        over = c["sigma_p95_measurable_um"]
        sigma = ("no region measured" if over is None else
                 f"sigma_max p95 {over:.3f} um over the measured area") + \
            f" ({', '.join(none)}: none of it measured)"
    if "sigma_measured_p95_um" in c:      # [design] score = "measured"
        m = c["sigma_measured_p95_um"]
        sigma += ", sigma_measured p95 " + ("unserved" if m is None else f"{m:.3f} um")
    common = c.get("sigma_p95_common_um")
    if common is not None:
        sigma += f"; {common:.3f} um over the {100 * c['common_fraction']:.0f} % every count measures"
    return (f"{c['cameras']:3d} cameras: {sigma}, coverage {100 * c['coverage']:.1f} % "
            f"({100 * c['coverage_of_measurable']:.1f} % of the measurable)")


def uncompared(curve, sigma: str = "sigma_max") -> str | None:
    """Why the counts of `curve` get no figure over the area every count measures (each count's
    "sigma_p95_common_um" None, `vdo.design.select.common_p95`): they share no measured area
    ("common_fraction" 0), or that area holds no scored region's sample; None when a count has
    the figure. `sigma` names the figure (the console's "sigma_max", the figure's "σ_max"): the
    console's line and pareto.png's legend entry in place of the missing curve."""
    if not curve or "sigma_p95_common_um" not in curve[0] \
            or any(c["sigma_p95_common_um"] is not None for c in curve):
        return None
    share = curve[0]["common_fraction"]
    why = ("the camera counts share no measured area" if share == 0 else
           f"the area every camera count measures ({100 * share:.1f} % of the regions) holds no "
           "sample of a scored region")
    return f"{why}: their {sigma} p95 over a common area is not compared"


def log_ticks(ax) -> None:
    """Plain labels on a log axis at 1, 2 and 5 per decade, and at every digit where the data
    span less than a decade (matplotlib's default labels two ticks of a 0.43-0.86 µm curve)."""
    lo, hi = ax.get_ylim()
    subs = tuple(range(1, 10)) if hi / max(lo, 1e-300) < 10 else (1.0, 2.0, 5.0)
    ax.yaxis.set_major_locator(LogLocator(subs=subs))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _: f"{y:.3g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def plot_curve(path, curve, target, name):
    """pareto.png: `curve_figure` saved at `path`."""
    fig = curve_figure(curve, target, name)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def curve_figure(curve, target, name):
    """Top: sigma_max p95 (and σ_measured p95 when the design scores it) and coverage per camera
    count, and σ_max p95 over the area every count measures, or where no count has it, why
    (`uncompared`, a legend entry without a curve); bottom: the design's score and the
    relaxation's bound on any selection's score per count (`relax_curve`)."""
    fig, (ax, low) = plt.subplots(2, 1, figsize=(9, 6.5), layout="constrained", sharex=True,
                                  height_ratios=(3, 2))
    n = [c["cameras"] for c in curve]
    s = [np.nan if c["sigma_p95_um"] is None else c["sigma_p95_um"] for c in curve]
    ax.semilogy(n, s, "o-", label="σ_max p95, worst scored region")
    if curve and "sigma_measured_p95_um" in curve[0]:     # [design] score = "measured"
        ax.semilogy(n, [np.nan if c["sigma_measured_p95_um"] is None else c["sigma_measured_p95_um"]
                        for c in curve], "D-", color="C3",
                    label="σ_measured p95, worst scored region (scored)")
    ax.semilogy(n, [np.nan if c["sigma_p95_measurable_um"] is None else c["sigma_p95_measurable_um"]
                    for c in curve], "x-", color="C0", alpha=0.45, lw=0.8,
                label="σ_max p95 over the measured area")
    missing = uncompared(curve, "σ_max")
    if curve and "sigma_p95_common_um" in curve[0] and missing is None:
        ax.semilogy(n, [np.nan if c["sigma_p95_common_um"] is None else c["sigma_p95_common_um"] for c in curve],
                    "P-", color="k", lw=1.4,
                    label=f"σ_max p95 over the {100 * curve[0]['common_fraction']:.0f} % every count measures")
    for c in curve:     # a count that leaves a region unmeasured says so under its point
        none = [r for r, v in c["sigma_p95_by_region_um"].items() if v is None]
        if none:
            ax.annotate("unmeasured:\n" + "\n".join(none), (c["cameras"], 0.97),
                        xycoords=("data", "axes fraction"), ha="center", va="top", fontsize=7,
                        color="0.3", bbox=dict(boxstyle="round", fc="white", ec="0.7", lw=0.5))
    for k, r in enumerate(curve[0]["sigma_p95_by_region_um"] if curve else ()):
        ax.semilogy(n, [np.nan if c["sigma_p95_by_region_um"][r] is None else c["sigma_p95_by_region_um"][r]
                        for c in curve], ".--", lw=0.8, color=f"C{k + 2}", label=f"{r} (measurable area)")
    if target is not None:
        ax.axhline(target, ls="--", color="k", lw=0.8, label=f"target {target:g} µm")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    log_ticks(ax)
    ax.set_ylabel("σ_max p95 (µm)")
    ax2 = ax.twinx()
    ax2.plot(n, [100 * c["coverage"] for c in curve], "s:", color="C1", label="coverage")
    if curve:
        ax2.plot(n, [100 * c["coverage_of_measurable"] for c in curve], "^:", color="C1", alpha=0.6,
                 label=f"coverage of the measurable {100 * curve[0]['measurable_fraction']:.0f} %")
    ax2.set_ylabel("area seen by its min_cameras (%)")
    ax2.set_ylim(0, 105)
    ax.set_title(f"{name}: cameras needed")
    lines = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    if missing is not None:     # said in the legend, with no mark: nothing is drawn for it
        lines.append(Line2D([], [], linestyle="none", label=missing))
    ax.legend(lines, [ln.get_label() for ln in lines], fontsize=7, loc="upper left",
              bbox_to_anchor=(1.12, 1.0))                               # beside the curves, not on them
    low.semilogy(n, [c["score"] for c in curve], "o-", label="design's score")
    bounds = [np.nan if c["bound"] is None or c["bound"] <= 0 else c["bound"] for c in curve]
    if not np.all(np.isnan(bounds)):
        low.semilogy(n, bounds, "v--", color="C2", label="bound: no selection scores lower")
    low.set_xlabel("cameras")
    low.set_ylabel("score")
    low.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.12, 1.0))
    return fig
