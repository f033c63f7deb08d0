"""vdo's optimizer against a derivative-free baseline on the built-in experiment.

Both search the same parameters (rail u via logit, pan, tilt of every camera) and judge a layout
the same way (`vdo.search.solver.judge`): the ray cast, the lights and the predicted uncertainty are
recomputed at the layout, the score is `vdo.objective.score` there, every constraint is checked
exactly, and layouts are ranked feasible first, by score, else by fewest violations and least
total excess (`Result.rank`). vdo runs its gradient-based rounds (BFGS with frozen visibility,
refreshed between rounds); the baseline is a (1+1) evolution strategy with the 1/5 success rule
on that same ranking (a constrained ES with feasibility rules), starting from the same hand
layout with steps of one natural unit (3 deg, 0.5 in logit u), for `--budget` times vdo's wall
time (default 5: with less, the baseline is stopped before it improves much, and its final
score says little), once per seed of its random steps (`--seeds`, default 3: one run of a
stochastic search says little). Printed: the best feasible score against wall time for both,
and when each first reaches the baseline's final score, with the ratio.

Run: .venv/bin/python benchmarks/optimize.py [--config ...] [--budget 5] [--seeds 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from vdo.config import experiment as config
from vdo.core.configure import configure
from vdo.search.problem import Problem
from vdo.search.solver import judge, solve

ROOT = Path(__file__).resolve().parent.parent


def baseline(problem, seconds, theta, seed=0):
    """(1+1)-ES on `Result.rank` from θ; returns [(wall_s, best feasible score so far)]."""
    rng = np.random.default_rng(seed)
    theta = np.array(theta, dtype=float)
    start = time.perf_counter()
    incumbent = judge(problem, theta, problem.refresh(theta), 0)
    best = incumbent.score if incumbent.violations == 0 else np.inf
    trace = [(time.perf_counter() - start, best)]
    step = 1.0
    while time.perf_counter() - start < seconds:
        candidate = theta + step * problem.param.scale * rng.standard_normal(theta.size)
        result = judge(problem, candidate, problem.refresh(candidate), 0)
        if result.rank < incumbent.rank:
            theta, incumbent = candidate, result
            step *= 1.5
        else:
            step *= 1.5 ** -0.25
        if result.violations == 0:
            best = min(best, result.score)
        trace.append((time.perf_counter() - start, best))
    return trace


def best_feasible_trace(verdicts):
    """[(wall_s, best feasible score so far)] from vdo's exact judgements."""
    best, out = np.inf, []
    for v in verdicts:
        if v["violations"] == 0:
            best = min(best, v["score"])
        out.append((v["wall_s"], best))
    return out


def first_reach(trace, target):
    return next((t for t, s in trace if np.isfinite(s) and s <= target), None)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--config", default=ROOT / "experiments/beam_column/ten_cameras.toml")
    parser.add_argument("--budget", type=float, default=5.0, help="baseline time / vdo time")
    parser.add_argument("--seeds", type=int, default=3, help="baseline runs per start, one per seed")
    parser.add_argument("--rounds", type=int, default=None, help="override [optimize] rounds")
    parser.add_argument("--max-steps", type=int, default=None, help="override [optimize] max_steps")
    args = parser.parse_args()
    configure(compilation_cache=False)  # as the command line does, compile times measured cold
    exp = config.load(args.config)
    opt = dataclasses.replace(exp.optimize, starts=1)
    if args.rounds:
        opt = dataclasses.replace(opt, rounds=args.rounds)
    if args.max_steps:
        opt = dataclasses.replace(opt, max_steps=args.max_steps)
    exp = dataclasses.replace(exp, optimize=opt)
    problem = Problem(exp)
    start_verdict = judge(problem, problem.param.theta0, problem.start, 0)

    # vdo's time counts its compilation (the solver step compiles on its first call; with
    # JAX_COMPILATION_CACHE_DIR set and a previous run, it loads from the cache instead)
    t0 = time.perf_counter()
    judged_before = len(problem.run.verdicts)
    results = solve(problem)
    vdo_time = time.perf_counter() - t0
    offset = t0 - problem.run.t0   # the run's clock started when the problem was built
    solved = [dict(v, wall_s=v["wall_s"] - offset) for v in problem.run.verdicts[judged_before:]]
    vdo_trace = best_feasible_trace(solved)
    best = results[0]
    print(f"start layout        score {start_verdict.score:.5g} µm  ({start_verdict.violations} violations)")
    print(f"vdo (BFGS rounds)   {vdo_time:.1f} s, {len(problem.run.history)} accepted steps: "
          f"best score {best.score:.5g} µm with {best.violations} violations")

    feasible = next((v for v in solved if v["violations"] == 0), None)
    starts = [("hand layout", problem.param.theta0)]
    if feasible is not None:
        starts.append((f"first feasible layout of vdo (score {feasible['score']:.5g}, "
                       f"found at {feasible['wall_s']:.0f} s)", feasible["theta"]))
    print("best feasible score against wall time (s)")
    print("  vdo: " + "  ".join(f"{t:.0f}:{s:.5g}" for t, s in vdo_trace))
    for label, theta in starts:
        for seed in range(args.seeds):
            trace = baseline(problem, args.budget * vdo_time, theta, seed)
            final = trace[-1][1]
            print(f"(1+1)-ES baseline, seed {seed}, from the {label}: {trace[-1][0]:.1f} s, {len(trace) - 1} layouts, "
                  + (f"best feasible score {final:.5g}" if np.isfinite(final) else "no layout meeting every constraint"))
            print("  ES:  " + "  ".join(f"{t:.0f}:{s:.5g}" for t, s in trace[:: max(1, len(trace) // 12)]))
            if np.isfinite(final):
                t_vdo, t_base = first_reach(vdo_trace, final), first_reach(trace, final)
                print(f"  time to reach the baseline's final score {final:.5g}: vdo "
                      + ("never" if t_vdo is None else f"{t_vdo:.1f} s") + f", baseline {t_base:.1f} s"
                      + ("" if t_vdo is None else f" ({t_base / t_vdo:.1f}x)"))


if __name__ == "__main__":
    main()
