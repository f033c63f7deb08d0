"""`vdo optimize` as a command: the search of `vdo.optimize` (`optimize_layout`) and its run folder
(`write_optimization`): optimized.toml, layout.json, summary_before/after.json, constraints.json,
optimizer.json, history.csv, convergence.png, moves.csv and report.html."""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path

import matplotlib.pyplot as plt

from vdo.config.experiment import Experiment
from vdo.core.runfolder import run_folder
from vdo.optimize import DEFAULT_TIME_LIMIT, OptimizeResult, optimize_layout, run_labels
from vdo.outputs import html_report, report
from vdo.search.anytime import Stop
from vdo.search.problem import PENALTIES

log = logging.getLogger(__name__)


def optimize(exp: Experiment, out: Path, overwrite: bool = False,
             time_limit: float = DEFAULT_TIME_LIMIT, stop: Stop | None = None,
             objective=None, started: float | None = None) -> OptimizeResult:
    """Optimize the layout (`vdo.optimize.optimize_layout`: `time_limit`, `stop`, `objective` and
    `started` as there) and write its run folder into `out` (`write_optimization`), whatever
    ended the search. Returns the `OptimizeResult`."""
    result = optimize_layout(exp, time_limit=time_limit, stop=stop, objective=objective, started=started)
    write_optimization(result, out, overwrite)
    return result


def write_optimization(result: OptimizeResult, out: Path, overwrite: bool = False) -> None:
    """The run folder of `vdo optimize` from its result: optimized.toml, layout.json,
    summary_before/after.json, constraints.json, optimizer.json (how the search ended, start-up
    and search seconds, rounds, starts, scores, the regions whose σ rose while the score fell:
    `vdo.optimize.precision_traded`), history.csv, convergence.png, moves.csv and
    report.html (atomic, `vdo.core.runfolder`)."""
    log.info("writing %s", out)
    record = result.record
    with run_folder(out, overwrite) as tmp:
        report.write_config(tmp / "optimized.toml", result.optimized)
        report.write_json(tmp / "layout.json", report.layout(result.cameras))
        report.write_json(tmp / "summary_before.json", result.before.to_json())
        report.write_json(tmp / "summary_after.json", result.after.to_json())
        report.write_json(tmp / "constraints.json", {
            "violations": result.violations,
            "violated": result.violated,
            "after": result.checks_after, "before": result.checks_before})
        time_limit = record.time_limit_s
        report.write_json(tmp / "optimizer.json", {
            "status": result.status, "converged": result.status == "converged",
            "time_limit_s": time_limit if math.isfinite(time_limit) else None,
            "search_wall_s": record.history[-1]["wall_s"] if record.history else 0.0,
            "startup_s": result.startup_s, "search_s": result.search_s, "reason": result.reason,
            "rounds": record.rounds, "starts": record.starts, "accepted_steps": len(record.history),
            "layouts_judged": len(record.verdicts), "best_start": record.best_start,
            "score_before": record.score_before, "score_after": record.score_after,
            "reachability": result.reachability, "exposure": result.exposure,
            "precision_traded": result.precision_traded})
        write_history(tmp / "history.csv", record.history)
        plot_history(tmp / "convergence.png", record.history, record.verdicts, result.optimized.name)
        write_moves(tmp / "moves.csv", result)
        html_report.write_report(tmp)


def write_history(path, history):
    """history.csv: one row per accepted solver step (step, start, round, wall_s, score and each
    penalty of `vdo.search.problem.PENALTIES`)."""
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, ["step", "start", "round", "wall_s", "score", *PENALTIES])
        writer.writeheader()
        for i, row in enumerate(history):
            writer.writerow({"step": i, **row})


def plot_history(path, history, verdicts, name):
    """Score (log scale when it spans more than a factor 10) at every accepted solver step (thin
    line) and the exact score of each judged layout (markers: filled where it meets every
    constraint; each round's end, and the checkpoints within rounds), per start and lens trial
    (the solves after the lens screening); layouts judged without a solve (the screening) as
    crosses. The legend stands beside the axes."""
    fig, ax = plt.subplots(figsize=(9.5, 4), layout="constrained")
    solved = sorted({h["start"] for h in history})
    screened = [r for r in verdicts if r["start"] not in solved]
    labels = run_labels(history, verdicts)
    for s in solved:
        rows = [h for h in history if h["start"] == s]
        what = labels[s]
        line, = ax.plot([h["wall_s"] for h in rows], [h["score"] for h in rows], lw=0.6, alpha=0.5,
                        label=f"{what}: accepted steps")
        for feasible in (True, False):
            v = [r for r in verdicts if r["start"] == s and (r["violations"] == 0) == feasible]
            ax.plot([r["wall_s"] for r in v], [r["score"] for r in v], "o", ms=6,
                    color=line.get_color(), mfc=line.get_color() if feasible else "white",
                    label=f"{what}: judged layout, {'feasible' if feasible else 'violates a constraint'}")
    if screened:
        ax.plot([r["wall_s"] for r in screened], [r["score"] for r in screened], "x", color="0.4",
                label="lens options screened at the best layout")
    scores = [r["score"] for r in verdicts] + [h["score"] for h in history]
    if scores and max(scores) > 10 * min(scores):   # e.g. from unmeasured points to a few µm
        ax.set_yscale("log")
    ax.set_xlabel("wall time (s)")
    ax.set_ylabel("score (smooth σ_max, µm, + coverage)")
    ax.set_title(f"{name}: convergence")
    if verdicts:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))     # beside the points
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_moves(path, result: OptimizeResult):
    """moves.csv, per camera (`vdo.optimize.CameraMove`): its mount (rail or zone), rail position
    (mm along the bar), pan, tilt (deg), focal length (mm) and optical centre (m), before (the
    hand layout) and after (the best layout)."""
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["camera", "mount", "rail_position_mm_before", "rail_position_mm_after",
                         "pan_deg_before", "pan_deg_after", "tilt_deg_before", "tilt_deg_after",
                         "focal_mm_before", "focal_mm_after", "x_m_before", "y_m_before", "z_m_before",
                         "x_m_after", "y_m_after", "z_m_after"])
        for move in result.moves:
            a, b = move.before, move.after
            along = ["" if m is None else f"{m * 1e3:.1f}" for m in (move.rail_before_m, move.rail_after_m)]
            writer.writerow([a.name, move.mount, *along,
                             f"{math.degrees(a.pan):.2f}", f"{math.degrees(b.pan):.2f}",
                             f"{math.degrees(a.tilt):.2f}", f"{math.degrees(b.tilt):.2f}",
                             f"{a.focal_length * 1e3:g}", f"{b.focal_length * 1e3:g}",
                             *(f"{v:.4f}" for v in (*a.position, *b.position))])
