"""How far can valid inequalities lift `vdo design`'s bound? (docs/design.md, "The bound").

The bound's first phase (`vdo.design.bound.relaxation` without `conflicts`, as run here) is the
minimum of the convex score f over the polytope P of weights (body counts kept, pairwise rules
dropped); `vdo design` then holds the spot, axis-angle and tripod rules (the bound's hull phase).
Any constraint that every feasible selection meets (clique inequalities over conflicting
candidates, the spot rule, the axis angles) keeps the convex hull H of the feasible selections,
so the best bound they can give is min_H f, and

    min_P f  <=  min_H f  <=  f(h)   for every h in H.

This script solves the relaxation for the inventory's count, keeps the candidates it weighs
(weight > SUPPORT), and runs Frank-Wolfe over the hull of the feasible selections of those
candidates (their pairwise conflicts from `vdo.design.feasibility.Feasibility`, the body counts):
each step's linear minimisation is a selection found by scipy's MILP, the step length an exact
line search. Its last iterate h is a convex combination of feasible selections, so f(h) caps what
any valid inequality can give: a design scoring s keeps a gap of at least 1 - f(h) / s.

Run from the repository root:
python benchmarks/design_gap.py experiments/steel_beam/design.toml [--seconds 300] [--steps 300]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import jax
import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp, minimize_scalar

from vdo.config import experiment as config
from vdo.core.configure import configure
from vdo.design import bound, hull
from vdo.design.candidates import inventory, judge
from vdo.design.feasibility import Feasibility
from vdo.design.score import Scorer
from vdo.state import prepare

SUPPORT = 1e-4      # candidates weighted above this by the relaxed optimum are the hull's
LINE_TOL = 1e-9     # the exact line search's tolerance on the step length (of 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config")
    ap.add_argument("--seconds", type=float, default=300.0, help="the relaxation's time limit")
    ap.add_argument("--steps", type=int, default=300, help="Frank-Wolfe steps over the hull")
    args = ap.parse_args()
    configure()
    exp = config.load(args.config)
    coarse = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=exp.design.sample_spacing)))
    cand = judge(exp, coarse)
    scorer, feas = Scorer(exp, coarse.samples), Feasibility(exp, cand, coarse.samples)
    k = inventory(exp)
    t0 = time.perf_counter()
    b = bound.relaxation(scorer.value, cand, None, k, feas.alone, feas.body, feas.counts,
                         time_limit=args.seconds)
    print(f"{k} cameras: bound {b.value:.5g}, relaxed {b.relaxed:.5g} ({b.iterations} steps, "
          f"{'converged' if b.converged else 'time limit'}, {time.perf_counter() - t0:.0f} s)")

    sup = np.flatnonzero(b.weights > SUPPORT)
    n = len(sup)
    conflict = np.array([feas.row(j)[sup] for j in sup])
    conflict |= conflict.T
    pairs = [(p, q) for p in range(n) for q in range(p + 1, n) if conflict[p, q]]
    rows = [LinearConstraint(np.ones((1, n)), k, k),
            LinearConstraint(np.array([feas.body[sup] == kind for kind in range(len(feas.counts))], float),
                             0, feas.counts)]
    if pairs:
        edge = np.zeros((len(pairs), n))
        edge[np.arange(len(pairs)), [p for p, _ in pairs]] = 1
        edge[np.arange(len(pairs)), [q for _, q in pairs]] = 1
        rows.append(LinearConstraint(edge, 0, 1))
    print(f"support: {n} candidates (weight > {SUPPORT:g}), {len(pairs)} conflicting pairs among them")

    K, summed, pullback = hull.linear_maps(cand, None)
    value_grad, value = jax.jit(jax.value_and_grad(scorer.value, argnums=(0, 1))), jax.jit(scorer.value)

    def full(x):
        w = np.zeros(K)
        w[sup] = x
        return summed(w)

    def f(x):
        return float(value(*full(x)))

    def gradient(x):
        _, (gC, gc) = value_grad(*full(x))
        return pullback(gC, gc)[sup]

    def selection(g):
        """argmin g.s over the feasible selections of the support (0/1, scipy's MILP)."""
        r = milp(g, constraints=rows, integrality=np.ones(n), bounds=Bounds(0, 1))
        return np.round(r.x)

    x = selection(gradient(b.weights[sup]))
    for _ in range(args.steps):
        s = selection(gradient(x))
        step = minimize_scalar(lambda a: f(x + a * (s - x)), bounds=(0.0, 1.0), method="bounded",
                               options={"xatol": LINE_TOL}).x
        x = x + step * (s - x)
    print(f"a point of the feasible selections' hull: f = {f(x):.5g} after {args.steps} Frank-Wolfe "
          "steps; no valid inequality lifts the bound above it")


if __name__ == "__main__":
    main()
