"""How fast does `vdo design`'s branch and bound lift its bound? (docs/design.md, "The bound").

One root for both runs: the inventory's count's relaxation with the pairwise rules
(`vdo.design.bound.relaxation`'s hull phase, as `vdo design` runs it from the greedy selection),
then the same branch and bound (`vdo.design.branch.search`, the incumbent that selection's
score) for `--seconds` twice, each from a fresh copy of the root's rules:

* "before": what the thirty-sixth stop changed, undone: a split's children one after the
  other, the adjoint over every candidate's stored pairs in candidate order, every node's hull
  converged before it is queued (`vdo.design.branch.AHEAD` infinite) (the linear step's time
  cap, `vdo.design.hull.LINEAR_S`, and the stall rule over splits stay);
* "now": as shipped: the children side by side in two threads, the allowed candidates' adjoint
  from the sample-major copy (`vdo.design.hull.linear_maps` with `rows`), nodes tightened on
  demand.

Prints each run's bound, nodes and the adjoint's time per call. The bound is certified either
way; what differs is how far it gets in the time.

Run from the repository root:
python benchmarks/design_tree.py experiments/steel_beam/design.toml [--seconds 600]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import jax
import numpy as np

from vdo.config import experiment as config
from vdo.core.configure import configure
from vdo.design import bound, branch, hull
from vdo.design.candidates import inventory, judge
from vdo.design.feasibility import Feasibility
from vdo.design.moves import greedy
from vdo.design.score import Scorer
from vdo.state import prepare

ROOT_S = 60.0       # the root's time limit, as [design] bound_s's default


class Serial:
    """`vdo.search.anytime.Beside` without the thread: fn(*args) now, its result when asked."""

    def __init__(self, fn, *args):
        self.value = fn(*args)

    def result(self):
        return self.value


def timed(pullback, seconds: list):
    def run(*args):
        t = time.perf_counter()
        out = pullback(*args)
        seconds.append(time.perf_counter() - t)
        return out
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config")
    ap.add_argument("--seconds", type=float, default=600.0, help="each run's branch and bound")
    args = ap.parse_args()
    configure()
    exp = config.load(args.config)
    d = exp.design
    coarse = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=d.sample_spacing)))
    cand = judge(exp, coarse)
    scorer, feas = Scorer(exp, coarse.samples), Feasibility(exp, cand, coarse.samples)
    k = inventory(exp)
    start, _ = greedy(cand, scorer, feas, k)
    both = jax.jit(jax.value_and_grad(scorer.value, argnums=(0, 1)))
    only = jax.jit(scorer.value)
    K, summed, every = hull.linear_maps(cand, None)
    _, _, allowed_only = hull.linear_maps(cand, None, rows=feas.alone)
    x = np.zeros(K)
    x[start] = 1.0
    incumbent = float(only(*summed(x)))

    t0 = time.perf_counter()
    plain_best, best_x, plain, _ = hull.descend(both, only, summed, allowed_only, x, k, feas.alone, feas.body,
                                                feas.counts, t0 + ROOT_S * bound.PLAIN_SHARE, bound.REL_TOL,
                                                bound.MAX_ITER)
    first = np.concatenate([start, np.flatnonzero(best_x > bound.SUPPORT)])

    def rules():
        r = hull.Rules(feas.placement, k, feas.alone, feas.body, feas.counts)
        r.hold(first, np.inf)
        return r
    root = hull.corrective(both, only, summed, allowed_only, rules(), best_x, start, plain, t0 + ROOT_S,
                           bound.INNER_SHARE * ROOT_S, bound.REL_TOL, bound.MAX_ITER)
    print(f"{k} cameras, {K:,} candidates x {cand.samples} samples: root {root.bound:.5g} "
          f"({time.perf_counter() - t0:.0f} s), incumbent {incumbent:.5g} (greedy)")
    groups = branch.classes(cand.target, cand.mount, cand.body, [c.focal_length for c in cand.cameras],
                            cand.positions)
    views = branch.Views(scorer.term, cand, None, feas.alone)
    ahead, beside = branch.AHEAD, branch.Beside
    for name, pullback, lazy, threads in (("before", every, False, False), ("now", allowed_only, True, True)):
        seconds: list = []
        branch.AHEAD = ahead if lazy else np.inf
        branch.Beside = beside if threads else Serial
        t = time.perf_counter()
        value, nodes, found, _, _ = branch.search(
            both, only, summed, timed(pullback, seconds), rules(), root, groups, incumbent,
            time.perf_counter() + args.seconds, bound.INNER_SHARE * ROOT_S, bound.REL_TOL, bound.MAX_ITER,
            views=views)
        print(f"{name:>6}: bound {value:.5g} ({nodes} nodes, {time.perf_counter() - t:.0f} s; best selection met "
              f"{found:.5g}), adjoint {1e3 * np.median(seconds):.0f} ms a call ({len(seconds)} calls)")
    branch.AHEAD, branch.Beside = ahead, beside


if __name__ == "__main__":
    main()
