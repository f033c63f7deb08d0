"""vdo's optimizer against a derivative-free baseline on the built-in experiment.

Both search the same parameters (rail u via logit, pan, tilt of every camera) and judge a layout
the same way: the ray cast, the lights and the predicted uncertainty are recomputed at the layout
(`Problem.refresh`), the score is `vdo.objective.score` there, and a layout counts only when it
meets every constraint (`Problem.check`). vdo runs its gradient-based rounds (BFGS with frozen
visibility, refreshed between rounds); the baseline is a (1+1) evolution strategy with the 1/5
success rule, starting from the same hand layout with steps of one natural unit (3 deg, 0.5 in
logit u), for `--budget` times vdo's wall time. Printed: the best feasible score against wall time
for both, and the time each needs to reach the baseline's final score.

Run: .venv/bin/python benchmarks/optimize.py [--config ...] [--budget 1.5]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from vdo import config
from vdo.optimize import Problem, solve

ROOT = Path(__file__).resolve().parent.parent


def feasible_score(problem, theta):
    state = problem.refresh(theta)
    violations = sum(not e["met"] for e in problem.check(state))
    return problem.exact_score(state), violations


def baseline(problem, seconds, seed=0):
    rng = np.random.default_rng(seed)
    theta = problem.param.theta0.copy()
    score, violations = feasible_score(problem, theta)
    best = score if violations == 0 else np.inf     # only layouts meeting every constraint count
    start = time.perf_counter()
    trace = [(0.0, best)]
    step = 1.0
    while time.perf_counter() - start < seconds:
        candidate = theta + step * problem.param.scale * rng.standard_normal(theta.size)
        score, violations = feasible_score(problem, candidate)
        if violations == 0 and score < best:
            theta, best = candidate, score
            step *= 1.5
        else:
            step *= 1.5 ** -0.25
        trace.append((time.perf_counter() - start, best))
    return trace


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--config", default=ROOT / "experiments/beam_column/ten_cameras.toml")
    parser.add_argument("--budget", type=float, default=1.5, help="baseline time / vdo time")
    parser.add_argument("--rounds", type=int, default=None, help="override [optimize] rounds")
    parser.add_argument("--max-steps", type=int, default=None, help="override [optimize] max_steps")
    args = parser.parse_args()
    exp = config.load(args.config)
    opt = dataclasses.replace(exp.optimize, starts=1)
    if args.rounds:
        opt = dataclasses.replace(opt, rounds=args.rounds)
    if args.max_steps:
        opt = dataclasses.replace(opt, max_steps=args.max_steps)
    exp = dataclasses.replace(exp, optimize=opt)
    problem = Problem(exp)
    score0, v0 = feasible_score(problem, problem.param.theta0)

    # warm the JIT caches outside the timing (both methods reuse the compiled objective)
    problem.value_and_grad(problem.param.theta0, problem.start.views, 1.0)
    problem.history.clear()

    start = time.perf_counter()
    results = solve(problem)
    vdo_time = time.perf_counter() - start
    vdo_score = results[0].score if results[0].violations == 0 else np.inf
    print(f"start layout        score {score0:.5g}  ({v0} violations)")
    print(f"vdo (BFGS rounds)   score {vdo_score:.5g} in {vdo_time:.1f} s, "
          f"{len(problem.history)} objective evaluations, {results[0].violations} violations")

    trace = baseline(problem, args.budget * vdo_time)
    base_final = trace[-1][1]
    reach = next((t for t, s in trace if np.isfinite(s) and s <= vdo_score), None)
    print(f"(1+1)-ES baseline   score {base_final:.5g} after {trace[-1][0]:.1f} s, {len(trace) - 1} layouts")
    print(f"baseline reaches vdo's score: {'never' if reach is None else f'after {reach:.1f} s'}")
    if not (np.isfinite(vdo_score) or np.isfinite(base_final)):
        print("neither method found a layout that meets every constraint")
    else:
        print(f"vdo reaches the baseline's final score: {'yes' if vdo_score <= base_final else 'no'}, "
              f"in {vdo_time:.1f} s vs {trace[-1][0]:.1f} s")
    print("time_s  baseline_best")
    for t, s in trace[:: max(1, len(trace) // 12)]:
        print(f"{t:6.1f}  {s:.5g}")


if __name__ == "__main__":
    main()
