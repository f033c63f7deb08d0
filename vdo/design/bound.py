"""A certified lower bound on the best score any selection of k cameras can reach (`vdo design`).

The relaxation. Give each candidate i a weight w_i in [0, 1] instead of a yes/no, with sum_i w_i =
k and, per body kind b, sum_{i of kind b} w_i <= count_b (the inventory). The per-sample
information and coverage of `vdo.design.candidates` are linear in w:

    C_n(w) = sum_i w_i C_i(n)   (3x3, 1/m^2),      k_n(w) = sum_i w_i w_i(n),

and the score of `vdo.design.score.Scorer` is convex in (C, k):

* sigma_n = sqrt((tr Sigma_n^p)^(1/p)), Sigma_n = (C_n + I/prior^2)^-1, equals
  c Phi(C_n)^(-1/2) with Phi(M) = (tr M^-p / 3)^(-1/p) Kiefer's information function, concave and
  positive on positive definite M; so ln sigma_n = ln c - ln Phi(C_n) / 2 is convex in C_n (ln of
  a concave positive function is concave);
* the coverage penalty kappa sum_n a_n max(0, m_n - k_n)^2 is convex in k_n;
* the score exp(sum_n omega_n ln sigma_n + kappa penalty), omega_n >= 0, is exp (convex and
  non-decreasing) of a non-negative sum of convex functions: convex.

So f(w) = score(C(w), k(w)) is convex on the polytope P of the weights, and every selection of k
cameras that `vdo design` may choose is a vertex of P. Hence min_P f <= the score of every
feasible k-selection (the first phase, below; the pairwise rules of the selection dropped).

The certificate. For any w >= 0 (where f is convex and differentiable), with g = df/dw, and any
set S of weights,

    min_S f >= f(w) + min_{s in S} g.(s - w)      (the Frank-Wolfe duality gap's bound),

since f(s) >= f(w) + g.(s - w) for every s (convexity); w need not lie in S. Over P the linear
minimisation is exact and cheap: P is the base polytope of a truncated partition matroid, so s
takes candidates by increasing g_i while their body kind has room, until k are taken (`vdo.design.hull.vertex`).
The best of these over the iterates (and 0: the score, an exponential, is positive) is a
certified lower bound, whatever the convergence; it meets the relaxed optimum as the iterate
reaches it.

The pairwise rules. Given `conflicts` (`vdo.design.feasibility.Feasibility.placement`: one spot,
the axis angles, the tripods' legs), the bound also holds the rules between two cameras. Let H
be the convex hull of the 0/1 selections of k allowed candidates within the body counts with no
conflicting pair (a pair conflicts when each conflicts with the other). A selection of the
design adds its cameras one at a time, each allowed by those before it, so it holds no
conflicting pair and is a point of H; H lies in P, so

    min_P f  <=  min_H f  <=  the score of every feasible k-selection,

and the certificate with S = H is f(w) - g.w + min g.s over those 0/1 selections: a MILP
(`vdo.design.hull.Rules.vertex`, scipy's HiGHS), whose dual bound (a lower bound on its optimum, whatever its
own gap) keeps the certificate valid. Its variables are the candidates whose rules it holds and,
per body kind, the min(count, k) others of lowest g (only the body counts constrain the others,
so any solution's others of a kind can be swapped for those at no cost); its rows sum = k, the
body counts, and one clique inequality, at most one camera, per clique of the conflict graph
among the held candidates (`cliques` covers every edge: the candidates at one spot, the tripods
over one floor point). The rules held start with the candidates the first phase's best iterate
weighs above SUPPORT and the design's selection; a solution that takes a candidate not held is
solved again with its rules held, until it takes none: then it is a selection that keeps the
rules (every pair of it held), a vertex of H. Holding fewer candidates' rules only drops
conflicts, which enlarges H: the bound stays valid. The hardware rule of `Feasibility.row` (one
camera's body or tripod hiding another's region) is left out: 0.5-2 s a candidate against 50 ms
for the others, and on the steel beam (4 cameras) it moved the hull's optimum by nothing
(0.1556-0.1557 with or without; its rules cost 138 s).

The iterates. First, over P: accelerated projected gradient (FISTA with backtracking on the
Lipschitz estimate and a restart when the value rises) from the design's own selection (a
vertex); the projection onto P is exact (`vdo.design.hull.project`: w_i = clip(v_i - lambda - mu_b(i), 0, 1),
the multipliers found by bisection). g comes from JAX on the per-sample function, g_i = sum_n
<dF/dC_n, C_i(n)> + dF/dk_n w_i(n). Measured on the built-in experiment with the earlier
power-mean score (1,666 candidates x 3,372 samples, 10 cameras, 60 s wall on a loaded 2-core
machine): Frank-Wolfe with exact line search reached f = 0.092 and a bound of 0.028, the
accelerated gradient f = 0.080 and a bound of 0.050 (after 300 s: f = 0.073, bound 0.065); a
conic solver would need one 3x3 linear matrix inequality and a power cone per sample, and the
score's smooth sigma_max (a trace p-norm) has no compact conic form. It stops when the best
value and the bound agree to REL_TOL, after MAX_ITER steps or at the time limit (PLAIN_SHARE of
it with pairwise rules); its certificate, `Bound.plain`, bounds every k cameras within the body
counts, which a bound for fewer cameras needs (`vdo.design.select.relax_curve`).
Then, with pairwise rules, over H: fully corrective Frank-Wolfe (`vdo.design.hull.corrective`). The iterate is a
convex combination of the selections the MILP has returned (and the design's); after each new
one their weights are optimised again by the same accelerated gradient over their simplex (P
with k = 1 and one body kind), INNER_SHARE of the time limit at most, and the selections left
at weight 0 are dropped. The iterates stay in H, so f at them bounds min_H f from above
(`Bound.relaxed`), and the loop stops when that and the certificate agree to REL_TOL. Measured
on the steel beam (4 cameras, 420 samples, a loaded 2-core machine, XLA's optimisations off for
both): Frank-Wolfe with pairwise steps and a line search reached f = 0.15605 and a bound of
0.15516 in 120 s, the fully corrective one f = 0.15574 and 0.15559 in 55 s. There the MILP
takes 7-20 ms a call (100-150 candidates held, 130-210 cliques), the LP with the same clique
rows 4-10 ms and gave the same value on every call compared (its solutions 0/1): the MILP's
solutions are selections whatever the graph, which keeps the iterates in H. The inner descent
to INNER_TOL = 0.5 of REL_TOL took the built-in's 10 cameras to the same bound in 32 s against
44-49 s at 0.1.

What the rules lift. On the steel beam the relaxed optimum over P (0.1531) puts 1.44 cameras
over one floor point (0.68 + 0.31 + 0.30 + 0.15 on four candidates at [1.5, -1.2], two heights,
every two of them a tripod conflict), no pair of them above 1: inequalities on pairs, w_i + w_j
<= 1, would lift nothing; the clique of that floor point does, to min_H f in [0.15562, 0.15574]
(+1.7 %). On the
built-in (10 cameras, rails, no tripods) min_P f = 0.05140 and min_H f <= 0.05146 (+0.1 %):
what separates the bound from a design there is the integrality gap of H itself, the
fractional mix of whole selections. The bound over the curve took 129 s with the rules
against 176 s without on the steel beam, 210 s against 153 s on the built-in (docs/design.md,
"The bound holds the pairwise rules").

Branching (`vdo.design.branch`) lifts the bound of the inventory's count further: what is left
after the hull phase is the integrality gap of H itself, which splitting the selections into
nodes (at most t / at least t + 1 cameras of a class of candidates: aim point, mount, body,
lens, spot; a sample's views) takes back in part.

The gap of a design with score s to the bound b is reported as 1 - b / s: no selection of that
many cameras can lower the score by more than that fraction.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import jax
import numpy as np

from vdo.design.branch import Views, search
from vdo.design.hull import Rules, corrective, descend, largest, linear_maps, vertex

REL_TOL = 1e-3        # stop when (best value - bound) <= REL_TOL * bound
MAX_ITER = 2000       # gradient steps at most per camera count
SUPPORT = 1e-4        # the first phase's best iterate names the candidates it weighs above this to the rules
PLAIN_SHARE = 0.5     # with pairwise rules the first phase stops at this share of the time limit at most
INNER_SHARE = 0.05    # one re-weighting of the hull phase's selections: this share of the time limit at most


@dataclass(frozen=True)
class Bound:
    """The relaxation for k cameras. value: certified lower bound on the score of every selection
    of k cameras within the body counts that keeps the pairwise rules the relaxation was given
    (the best certificate over the iterates, and 0); plain: the certificate of the first phase,
    over P alone: it bounds every k cameras within the body counts, pairwise rules or not (<=
    value); relaxed: f at the best iterate (>= the relaxed optimum >= value; with pairwise rules,
    an iterate of the hull phase when it made one); weights (K,) that iterate; iterations made
    (gradient steps, then the hull phase's); converged: (relaxed - value) <= REL_TOL * value;
    seconds: wall time; conflicted: the candidates whose pairwise rules the bound holds (0: none);
    with branching (`vdo.design.branch.search`), nodes made (0: none), value the least bound over the open nodes
    and the best selection found (it may then exceed relaxed), found those selections, best first,
    and leaves the open nodes as (Node, bound); mix the selections of the hull phase's last
    iterate (index arrays; empty without pairwise rules), whose planes shape the outer
    approximation's model (`vdo.design.outer`)."""

    cameras: int
    value: float
    plain: float
    relaxed: float
    weights: np.ndarray
    iterations: int
    converged: bool
    seconds: float
    conflicted: int
    nodes: int = 0
    found: list = None
    leaves: list = None
    mix: list = ()

    def gap(self, score: float) -> float:
        """1 - value / score: the largest fraction by which any selection of `cameras` cameras
        could lower `score` (0 when the design meets the bound)."""
        return max(0.0, 1.0 - self.value / score)


def relaxation(value: Callable, info, weight, k: int, allowed: np.ndarray,
               body: np.ndarray, counts: np.ndarray, start=None, conflicts: Callable | None = None,
               rel_tol: float = REL_TOL, max_iter: int = MAX_ITER, time_limit: float = 60.0,
               groups: np.ndarray | None = None, branch_s: float = 0.0,
               branch_nodes: int | None = None, term: Callable | None = None,
               stop: Callable[[], bool] | None = None) -> Bound:
    """The certified bound of the relaxation for k cameras (module docstring). value(C (N, 6),
    k (N,)) -> score: a JAX function convex in its arguments (`vdo.design.score.Scorer.value`);
    info (K, N, 6) float64 1/m^2 and weight (K, N) the candidates' information and soft weights
    (or info the sparsely stored `Candidates` and weight None, `vdo.design.hull.linear_maps`);
    allowed (K,) the candidates a selection may hold at all; body (K,) their body kind, counts
    its inventory; start: indices of a feasible selection (the design's), else the vertex of the
    first candidates; conflicts: j -> (K,) bool, the candidates that may not join a selection
    holding j (`vdo.design.feasibility.Feasibility.placement`), whose rules the bound then holds
    (`vdo.design.hull.Rules`; None: the pairwise rules dropped); time_limit in wall seconds. With conflicts and
    branch_s > 0, a branch and bound follows for branch_s wall seconds more (`vdo.design.branch.search`; groups
    (K,) the classes of candidates it counts, or (F, K) F families of them
    (`vdo.design.branch.classes`), default none: candidates alone; branch_nodes: at most
    that many nodes, else as many as the time allows; term: the score's logarithm per sample,
    value = exp(sum_n term_n) (`vdo.design.branch.Views`), with which it splits first on how many cameras see a
    sample); stop: `stop()` True ends the branch and bound early (`vdo.search.anytime.Stop`: its
    bound so far stands). k is cut to `largest(...)` (no selection holds more)."""
    t0 = time.perf_counter()
    k = min(int(k), largest(allowed, body, counts))
    K, summed, pullback = linear_maps(info, weight, rows=allowed if weight is None else None)
    both = jax.jit(jax.value_and_grad(value, argnums=(0, 1)))
    only = jax.jit(value)

    x = np.zeros(K)
    if start is not None and len(start):
        x[list(start)] = 1.0
    else:
        x = vertex(-np.ones(K), k, allowed, body, counts)
    first = t0 + time_limit * (1.0 if conflicts is None else PLAIN_SHARE)
    best, best_x, plain, it = descend(both, only, summed, pullback, x, k, allowed, body, counts, first,
                                       rel_tol, max_iter)
    bound, held, nodes, found, leaves, mix = plain, 0, 0, [], [], []
    if conflicts is not None and time.perf_counter() < t0 + time_limit:
        rules = Rules(conflicts, k, allowed, body, counts)
        weighed = np.flatnonzero(best_x > SUPPORT)
        rules.hold(np.concatenate([np.asarray(start if start is not None else [], dtype=int),
                                   weighed[np.argsort(-best_x[weighed])]]), t0 + time_limit)
        h = corrective(both, only, summed, pullback, rules, best_x, start, plain,
                  t0 + time_limit, INNER_SHARE * time_limit, rel_tol, max_iter)
        bound, steps, mix = h.bound, h.steps, list(h.chosen)
        it, held = it + steps, len(rules.held)
        if h.best_x is not None:
            best, best_x = h.best, h.best_x
        if branch_s > 0 and np.isfinite(h.bound):
            incumbent = float(only(*summed(x))) if start is not None and len(start) else np.inf
            bound, nodes, _, found, leaves = search(
                both, only, summed, pullback, rules, h, np.arange(K) if groups is None else np.asarray(groups),
                incumbent, time.perf_counter() + branch_s, INNER_SHARE * time_limit, rel_tol, max_iter,
                max_nodes=branch_nodes, views=None if term is None else Views(term, info, weight, allowed),
                stop=stop)
            bound, held = max(bound, h.bound), len(rules.held)
    return Bound(cameras=k, value=float(bound), plain=float(plain), relaxed=float(best), weights=best_x,
                 iterations=it, converged=best - bound <= rel_tol * abs(bound),
                 seconds=time.perf_counter() - t0, conflicted=held, nodes=nodes, found=found, leaves=leaves,
                 mix=mix)
