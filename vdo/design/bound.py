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
takes candidates by increasing g_i while their body kind has room, until k are taken (`vertex`).
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
(`Rules.vertex`, scipy's HiGHS), whose dual bound (a lower bound on its optimum, whatever its
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
vertex); the projection onto P is exact (`project`: w_i = clip(v_i - lambda - mu_b(i), 0, 1),
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
Then, with pairwise rules, over H: fully corrective Frank-Wolfe (`_hull`). The iterate is a
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

Branching. What is left is the integrality gap of H itself: its optimum mixes whole selections
(on the steel beam each selection of the mix scores 0.30 to 10^9 alone), and no inequality that
the selections keep removes a mix. A branch and bound does (`_branch`, `[design] branch_s` for
the inventory's count): a node is the hull phase over the selections that keep the rules and
the node's own, none of the candidates it left out and at least one camera in each group it
requires (`Node`; two more kinds of rows in `Rules.vertex`, whose candidates not held enter as
the lowest-g few of each body kind and each set of groups they belong to). Every selection
lies in one of a node's two children (none of a set S of candidates / at least one of S), so
the least bound over the open nodes, and over the best selection found (`found`: every
selection the MILP returns keeps the rules, so f there bounds the minimum from above and
closes the nodes whose bound reaches it), bounds every selection; a child's bound is at least
its parent's. S is the spot (`spots`: every pose, body and lens at one optical centre) whose
weights at the node's iterate sum farthest from a whole number, else the candidate weighted
farthest from 0 and 1. Best first: the node of least bound is split, each child certified by
the hull phase from the parent's selections that keep its rules (NODE_INNER_S of re-weighting
at most), so the bound rises monotonically; it stops at its time, when the bound has risen by
less than STALL in STALL_S, or when every node is closed (the best selection found is then the
best of all). Measured (2026-12-06, 2 cores shared with two other jobs): on the built-in (10
cameras) 49 nodes in 260 s lifted 0.05142 to 0.05192, gap 5.8 -> 4.9 %; on the steel beam
(4 cameras) 13 nodes in 240 s lifted 0.15559 to 0.15575: there each child moves the bound by
0.01-0.05 %, the mix spreading over other spots at almost no cost.

Branching on views. A camera measures a point in two directions of three, so a sample seen by
one camera is unmeasured (the prior's sigma), by two or more measured. The hull's optimum mixes
selections that see a sample once with others that see it two or more times: at the mix's
summed information the sample reads measured, while a part of the mix leaves it unmeasured
(on the steel beam the root's mix weighs selections that leave one end of the beam to a single
camera, each scoring 1e8-1e10 alone). Given the score's per-sample terms (`term`, score =
exp(sum_n term_n), each convex and non-increasing in the sample's information and coverage),
a node is first split on the samples n_1..n_m (`Views.split`, SPLIT_SAMPLES at most) that its
mix sees both ways and whose term it underrates most (the mix of the selections' own terms
less the term at the mix): every selection either sees all of them with two cameras or more
(one child: a row of the linear step per sample, at least two of the candidates that see it),
or n_j is the first it sees with at most one (child j: the rows of n_1..n_{j-1}, at most one
candidate of n_j's, and n_j's term at least `Views.alone(n_j)`, the least term one camera or
none can give it; the node's function takes max(term_n, floor_n) per sample, `_floored`,
convex and equal to the score at the node's selections). These partition the node's
selections, so the bound stays valid. The floor lifts child j's bound at once: on the steel
beam an unmeasured sample costs 1.2-1.3x the score, so child j is certified at the parent's
iterate alone (`_once`: one gradient and one linear step), kept open without its own hull
until it is the least open bound, and mostly closed by the incumbent. When no sample is mixed,
the split falls back to spots, and once a split on views lifts its node's bound by less than
VIEWS_LIFT (the mix found other selections that see those samples twice at little cost) the
tree splits on spots alone. Measured on the steel beam (4 cameras, 2 loaded cores): two
splits on views lift the hull's 0.15562 to 0.15710 (+0.95 %, against +0.1 % for the first four
spot splits), after which the mix sees every sample twice and the splits go back to spots; what
separates the bound from the designs there is then the Jensen gap of the measured samples'
sigma (the target's term is quadratic in ln sigma), which no split on views removes. On random
instances where each view has rank two (tests/design/test_bound_views.py, seeds 0, 3, 5) three
nodes split on views lift the hull's bound by 2.48, 2.55 and 0.64 against 0.09, 0.16 and 0.08
for three split on candidates, and the tree closes on the best selection.

The gap of a design with score s to the bound b is reported as 1 - b / s: no selection of that
many cameras can lower the score by more than that fraction.
"""

from __future__ import annotations

import heapq
import logging
import time
from dataclasses import dataclass, replace
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
from scipy.optimize import Bounds, LinearConstraint, milp

from vdo.design.candidates import ENTRY_CHUNK

log = logging.getLogger(__name__)

REL_TOL = 1e-3        # stop when (best value - bound) <= REL_TOL * bound
MAX_ITER = 2000       # gradient steps at most per camera count
BISECTIONS = 60       # bisection steps of the projection's multipliers (to 2^-60 of their range)
ROUNDING = 1e-12      # relative rounding allowed in the backtracking test of the score
DOUBLINGS = 60        # backtracking doublings of the Lipschitz estimate at most per step
SHRINK = 0.9          # the Lipschitz estimate's shrink after an accepted step (backtracking doubles it)
SPARSE_ROWS = 8       # sums over the weighted candidates' own entries when fewer than 1 / this of all
SUPPORT = 1e-4        # the first phase's best iterate names the candidates it weighs above this to the rules
PLAIN_SHARE = 0.5     # with pairwise rules the first phase stops at this share of the time limit at most
INNER_SHARE = 0.05    # one re-weighting of the hull phase's selections: this share of the time limit at most
INNER_TOL = 0.5       # ... and stops at INNER_TOL * rel_tol (of its own certificate)
MIP_GAP = 1e-9        # HiGHS's relative gap in the selection oracle (the certificate takes its dual bound)
NODE_INNER_S = 1.0     # the branch and bound's nodes: one re-weighting of their selections at most this long
STALL_S = 60.0         # the branch and bound stops when the bound rose by less than STALL (relative) in STALL_S
STALL = 5e-4
SPLIT_SAMPLES = 16     # a split on views names at most this many samples (`Views.split`)
VIEWS_LIFT = 1e-3      # ... and the tree splits on candidates alone once one lifts its bound by less (relative)
BRANCH_LOG_S = 30.0    # a progress line of the branch and bound at most this often


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
    with branching (`_branch`), nodes made (0: none), value the least bound over the open nodes
    and the best selection found (it may then exceed relaxed), found those selections, best first,
    and leaves the open nodes as (Node, bound)."""

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

    def gap(self, score: float) -> float:
        """1 - value / score: the largest fraction by which any selection of `cameras` cameras
        could lower `score` (0 when the design meets the bound)."""
        return max(0.0, 1.0 - self.value / score)


def vertex(g: np.ndarray, k: int, allowed: np.ndarray, body: np.ndarray,
           counts: np.ndarray) -> np.ndarray:
    """argmin of g.s over P = {s in [0, 1]^K, s_i = 0 where not allowed, sum s = k, per body kind
    b sum_{body_i = b} s_i <= counts[b]}: the 0/1 vector of the candidates taken by increasing g
    while their body kind has room, until k are taken (greedy is exact on a matroid's base
    polytope)."""
    s = np.zeros(len(g))
    room = np.array(counts, dtype=int)
    taken = 0
    for i in np.flatnonzero(allowed)[np.argsort(g[allowed], kind="stable")]:
        if taken == k:
            break
        if room[body[i]] > 0:
            s[i], room[body[i]], taken = 1.0, room[body[i]] - 1, taken + 1
    return s


def largest(allowed: np.ndarray, body: np.ndarray, counts: np.ndarray) -> int:
    """The most candidates a selection may hold: per body kind, min(count, allowed candidates)."""
    return int(sum(min(int(c), int((allowed & (body == b)).sum())) for b, c in enumerate(counts)))


def project(v: np.ndarray, k: int, allowed: np.ndarray, body: np.ndarray,
            counts: np.ndarray) -> np.ndarray:
    """The Euclidean projection of v onto P (`vertex`), k <= `largest(...)`: from the KKT
    conditions w_i = clip(v_i - lambda - mu_b(i), 0, 1) on the allowed candidates (0 elsewhere),
    mu_b >= 0 the smallest that brings body kind b's sum to at most counts[b], lambda the one that
    brings the total to k. At a given lambda body kind b holds min(counts[b], S_b(lambda)),
    S_b(lambda) = sum_b clip(v_i - lambda, 0, 1), a total non-increasing in lambda: lambda by
    bisection on that total, then every capped kind's mu_b by bisection at once (`BISECTIONS`
    steps each, all kinds in one array)."""
    idx = np.flatnonzero(allowed)
    w = np.zeros(len(v))
    if idx.size == 0:
        return w
    x, b = np.asarray(v, dtype=float)[idx], np.asarray(body)[idx]
    cap = np.asarray(counts, dtype=float)
    kinds = len(cap)

    def held(shift):
        """sum over each body kind of clip(x - shift, 0, 1); shift a scalar or one per kind."""
        return np.bincount(b, np.clip(x - shift, 0.0, 1.0), minlength=kinds)

    lo, hi = float(x.min()) - 1.0, float(x.max())   # at lo every entry clips to 1, at hi to 0
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.minimum(held(mid), cap).sum() > k else (lo, mid)
    lam = hi
    over = held(lam) > cap
    mu_lo, mu_hi = np.zeros(kinds), np.where(over, float(x.max() - x.min()) + 2.0, 0.0)
    if over.any():                  # mu_b beyond the span clips every entry of kind b to 0
        for _ in range(BISECTIONS):
            mid = 0.5 * (mu_lo + mu_hi)
            above = held(lam + mid[b]) > cap
            mu_lo, mu_hi = np.where(above, mid, mu_lo), np.where(above, mu_hi, mid)
    w[idx] = np.clip(x - lam - mu_hi[b], 0.0, 1.0)
    return w


def linear_maps(info, weight):
    """(K, summed, pullback) for candidates given densely, info (K, N, 6) and weight (K, N), or
    stored sparsely (`info` a `vdo.design.candidates.Candidates`: indptr, index, entry_info,
    entry_weight; `weight` None): summed(w) = (sum_k w_k C_k (N, 6), sum_k w_k w_k,n (N,)) and its
    adjoint pullback(gC, gc) = (sum_n C_k,n : gC_n + w_k,n gc_n)_k (K,). The sparse form costs
    the stored entries, not K x N."""
    if weight is None:
        K, N = len(info.indptr) - 1, info.samples
        owner, idx, ei, ew = info.row, info.index, info.entry_info, info.entry_weight
        chunks = [slice(lo, lo + ENTRY_CHUNK) for lo in range(0, len(idx), ENTRY_CHUNK)]

        def summed(w):
            w = np.asarray(w, float)
            rows = np.flatnonzero(w)
            if len(rows) * SPARSE_ROWS < K:   # few candidates weighted (a vertex): their entries only
                return info.sums(rows, w[rows])
            C, c = np.zeros((N, 6)), np.zeros(N)
            for part in chunks:          # ENTRY_CHUNK entries at a time
                we, i = w[owner[part]], idx[part]
                for col in range(6):
                    C[:, col] += np.bincount(i, we * ei[part, col], minlength=N)
                c += np.bincount(i, we * ew[part], minlength=N)
            return C, c

        def pullback(gC, gc):
            gC, gc = np.asarray(gC), np.asarray(gc)
            out = np.zeros(K)
            for part in chunks:
                i = idx[part]
                out += np.bincount(owner[part], np.einsum("ec,ec->e", ei[part], gC[i]) + ew[part] * gc[i],
                                   minlength=K)
            return out
        return K, summed, pullback
    weight = np.asarray(weight, dtype=float)

    def summed(w):
        nz = np.flatnonzero(w)
        return np.tensordot(w[nz], info[nz], axes=1), w[nz] @ weight[nz]

    def pullback(gC, gc):
        return np.tensordot(info, np.asarray(gC), axes=([1, 2], [0, 1])) + weight @ np.asarray(gc)
    return info.shape[0], summed, pullback


def cliques(adjacent: np.ndarray) -> list[np.ndarray]:
    """Cliques of the graph `adjacent` (n, n) symmetric bool, False on the diagonal, that cover
    every edge: from each edge no clique holds yet, the clique grown by the common neighbour of
    most neighbours while one is left."""
    degree = adjacent.sum(axis=1)
    left = np.triu(adjacent, 1)
    out = []
    for i, j in zip(*np.nonzero(left)):
        if not left[i, j]:
            continue
        members, common = [i, j], adjacent[i] & adjacent[j]
        while common.any():
            m = np.flatnonzero(common)[np.argmax(degree[common])]
            members.append(m)
            common &= adjacent[m]
        q = np.array(members)
        left[np.ix_(q, q)] = False
        out.append(q)
    return out


class Rules:
    """The pairwise rules of a selection over the candidates asked so far (`held`), for the linear
    step over the selections that keep them: conflicts(j) (K,) bool, True where a candidate may
    not join a selection holding j; a pair conflicts when each says so of the other (a selection
    adds its cameras in some order). Every clique of that graph holds at most one camera of a
    selection (`cliques`); a candidate not held keeps the body counts alone."""

    def __init__(self, conflicts: Callable, k: int, allowed: np.ndarray, body: np.ndarray,
                 counts: np.ndarray):
        self.conflicts, self.k, self.allowed, self.body, self.counts = conflicts, k, allowed, body, counts
        self.held = np.zeros(0, dtype=int)
        self._rows: list[np.ndarray] = []
        self._cliques: list[np.ndarray] = []

    def hold(self, candidates, deadline: float) -> None:
        """Adds the rules of `candidates` (indices, in that order; those not allowed are left
        out) until the deadline (time.perf_counter()) passes: holding fewer keeps the bound valid."""
        held = set(self.held.tolist())
        new = [j for j in dict.fromkeys(np.asarray(candidates, dtype=int).tolist())
               if self.allowed[j] and j not in held]
        rows = []
        for j in new:
            if time.perf_counter() > deadline:
                break
            rows.append(np.asarray(self.conflicts(j), dtype=bool))
        if not rows:
            return
        self._rows += rows
        self.held = np.concatenate([self.held, new[:len(rows)]]).astype(int)
        among = np.array([r[self.held] for r in self._rows])
        adjacent = among & among.T
        np.fill_diagonal(adjacent, False)
        self._cliques = cliques(adjacent)

    def vertex(self, g: np.ndarray, seconds: float, node: Node | None = None) -> tuple[np.ndarray | None, float]:
        """(s, low): low <= g.s for every 0/1 s of k allowed candidates within the body counts
        with at most one camera in each clique of the held candidates, and with a `node`'s
        branching rules (none of its `out` candidates, between lo and hi cameras in each of its
        groups, `Node.limits`) (HiGHS's dual bound of that MILP; -inf where it gives none, +inf
        where no such s exists); s the indices of its solution when all are held (a selection
        that keeps the rules), else None. The candidates not held enter only as the min(count,
        k) of lowest g of each body kind and each set of groups they belong to (or none; any
        solution's others of a kind and set can be swapped for them at no cost, the rows they
        enter being the same); a solution that takes one is solved again with its rules held,
        until none is taken or `seconds` have passed."""
        k, body, counts = self.k, self.body, self.counts
        node = node or Node()
        limits = node.limits(k)
        into = [q for q, _, _ in limits]
        deadline = time.perf_counter() + seconds
        while True:
            free = self.allowed.copy()
            if node.out is not None:
                free &= ~node.out
            usable = free[self.held]          # held candidates a node's branching leaves out: 0
            free[self.held] = False
            rest = np.flatnonzero(free)
            inside = np.zeros((len(rest), len(into)), bool)   # which groups each is in
            for q, group in enumerate(into):
                inside[:, q] = np.isin(rest, group)
            pattern = np.unique(inside, axis=0, return_inverse=True)[1].ravel() if len(rest) else rest
            extra = []
            for p in np.unique(pattern):        # the candidates that enter the same rows
                for b, c in enumerate(counts):
                    idx = rest[(pattern == p) & (body[rest] == b)]
                    n = min(int(c), k, len(idx))
                    extra.append(idx[np.argpartition(g[idx], n - 1)[:n]] if n else idx[:0])
            V = np.concatenate([self.held, *extra]).astype(int)
            rows = [np.arange(len(V))] + [np.flatnonzero(body[V] == b) for b in range(len(counts))] + \
                self._cliques + [np.flatnonzero(np.isin(V, group)) for group in into]
            A = scipy.sparse.csr_matrix((np.ones(sum(len(r) for r in rows)),
                                         (np.repeat(np.arange(len(rows)), [len(r) for r in rows]),
                                          np.concatenate(rows))), shape=(len(rows), len(V)))
            top = np.concatenate([[k], counts, np.ones(len(self._cliques)), [hi for _, _, hi in limits]])
            low_rows = np.concatenate([[k], np.zeros(len(counts) + len(self._cliques)), [lo for _, lo, _ in limits]])
            upper = np.concatenate([usable, np.ones(len(V) - len(self.held), bool)]).astype(float)
            res = milp(g[V], constraints=LinearConstraint(A, low_rows, top), integrality=np.ones(len(V)),
                       bounds=Bounds(0, upper), options={"mip_rel_gap": MIP_GAP,
                                                         "time_limit": max(deadline - time.perf_counter(), 0.0)})
            if res.status == 2:       # infeasible: no selection keeps the node's rules
                return None, np.inf
            low = getattr(res, "mip_dual_bound", None)
            low = -np.inf if low is None or not np.isfinite(low) or res.status not in (0, 1) else float(low)
            if res.x is None:
                return None, low
            taken = np.sort(V[res.x > 0.5])
            new = np.setdiff1d(taken, self.held)
            if not len(new):
                return taken, low
            held = len(self.held)
            self.hold(new, deadline)
            if len(self.held) == held:
                return None, low


def _descend(both, only, summed, pullback, x, k, allowed, body, counts, deadline, rel_tol, max_iter):
    """Accelerated projected gradient over P from x, a point of P (module docstring), until the
    best value and the certificate agree to rel_tol, max_iter steps or the deadline
    (time.perf_counter()): (best value, its iterate, the best certificate (>= 0), steps)."""
    fx = float(only(*summed(x)))
    y, t, lipschitz = x.copy(), 1.0, 1.0
    best, best_x, bound, it = fx, x, 0.0, 0   # the score is >= 0: 0 bounds it before any step
    for it in range(1, max_iter + 1):
        fy, (gC, gc) = both(*summed(y))
        fy = float(fy)
        g = pullback(gC, gc)
        bound = max(bound, fy + float(g @ (vertex(g, k, allowed, body, counts) - y)))
        if best - bound <= rel_tol * abs(bound) or time.perf_counter() > deadline:
            break
        for _ in range(DOUBLINGS):   # backtracking: the quadratic model at y bounds f at the step
            xn = project(y - g / lipschitz, k, allowed, body, counts)
            fn, d = float(only(*summed(xn))), xn - y
            if fn <= fy + float(g @ d) + 0.5 * lipschitz * float(d @ d) + ROUNDING * abs(fy):
                break
            lipschitz *= 2.0
            if time.perf_counter() > deadline:   # each try is a pass over every entry
                break
        if time.perf_counter() > deadline:      # the bound found so far stands
            break
        if fn > fx:   # restart the momentum from the last accepted iterate
            y, t = x.copy(), 1.0
            continue
        tn = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
        y = np.clip(xn + (t - 1.0) / tn * (xn - x), 0.0, 1.0)   # w >= 0 keeps every C_n >= 0
        x, fx, t = xn, fn, tn
        if fx < best:
            best, best_x = fx, x
        lipschitz *= SHRINK
    return best, best_x, bound, it


@dataclass
class Hull:
    """The state of the fully corrective Frank-Wolfe over a hull (`_hull`): best: f at the best
    iterate in the hull (inf: none), best_x that iterate (None: none), bound the best
    certificate, steps made; chosen the selections of the last iterate and lam their weights
    (summing to 1), x that iterate (K,)."""

    best: float
    best_x: np.ndarray | None
    bound: float
    steps: int
    chosen: list
    lam: np.ndarray
    x: np.ndarray


def _hull(both, only, summed, pullback, rules: Rules, point, start, bound, deadline, inner_s,
          rel_tol, max_iter, node: Node | None = None, stop_above: float = np.inf) -> Hull:
    """Fully corrective Frank-Wolfe over the hull of the selections that keep `rules` (and the
    `node`'s branching rules; module docstring): the certificate at `point` (the first phase's
    best iterate, of P, or a parent node's iterate), then at each iterate, a convex combination
    of the selections found by `Rules.vertex` (and `start`: a list of (selection, weight) that
    keep the rules, or one selection, or None), its weights re-optimised over them all after each
    new one (`_descend` over their simplex, inner_s seconds at most); `bound` the certificate
    so far. Stops when the best iterate and the certificate agree to rel_tol, the certificate
    reaches `stop_above`, no selection keeps the rules (the certificate is then inf) or at the
    deadline; the oracle may run inner_s past the deadline, so that the last iterate is
    certified."""
    K = len(point)
    chosen, sums, lam = [], [], np.zeros(0)

    def add(selection, weight):
        v = np.zeros(K)
        v[selection] = 1.0
        chosen.append(selection)
        sums.append(summed(v))
        return np.append(lam, weight)

    if start is not None and len(start) and not isinstance(start[0], tuple):
        start = [(start, 1.0)]
    for selection, weight in start or []:
        lam = add(np.sort(np.asarray(selection, dtype=int)), weight)
    if lam.size:
        lam = lam / lam.sum()
    x, C, inside = point, summed(point), False
    best, best_x, steps = np.inf, None, 0
    while steps < max_iter:
        steps += 1
        fx, (gC, gc) = both(*C)
        fx = float(fx)
        g = pullback(gC, gc)
        s, low = rules.vertex(g, max(deadline - time.perf_counter(), inner_s), node)
        bound = max(bound, fx + low - float(g @ x))
        if inside and fx < best:
            best, best_x = fx, x
        if best - bound <= rel_tol * abs(bound) or bound >= stop_above or s is None \
                or time.perf_counter() > deadline:
            break
        if not any(np.array_equal(s, v) for v in chosen):
            lam = add(s, 0.0 if lam.size else 1.0)
        m = len(chosen)          # the weights of the selections: the same descent over a simplex
        _, inner_sum, inner_pull = linear_maps(np.stack([c for c, _ in sums]), np.stack([c for _, c in sums]))
        _, lam, _, _ = _descend(both, only, inner_sum, inner_pull, lam, 1, np.ones(m, bool), np.zeros(m, int),
                                np.ones(1, int), min(deadline, time.perf_counter() + inner_s),
                                INNER_TOL * rel_tol, max_iter)
        keep = np.flatnonzero(lam > 0)     # the projection clips unused selections to 0
        chosen, sums, lam = [chosen[i] for i in keep], [sums[i] for i in keep], lam[keep]
        x = np.zeros(K)
        for weight, v in zip(lam, chosen):
            x[v] += weight
        C, inside = tuple(sum(w * c[part] for w, c in zip(lam, sums)) for part in (0, 1)), True
    return Hull(best, best_x, bound, steps, chosen, lam, x)


def _floor(node: Node, samples: int) -> np.ndarray:
    """(samples,) each sample's least term in the node's selections (-inf where none is known)."""
    floor = np.full(samples, -np.inf)
    for n, value in node.floor:
        floor[n] = max(floor[n], value)
    return floor


@dataclass(frozen=True)
class Node:
    """The branching rules of a node of the branch and bound (`_branch`): `out` (K,) bool, the
    candidates none of its selections holds (None: none), `into` the groups (index arrays) in
    each of which its selections hold at least one camera, `views` (group, lo, hi): between lo
    and hi cameras of the group (the candidates that see one sample, `Views`), and `floor`
    (sample, value): that sample's term of the score is at least value in every selection of
    the node (`Views.alone`)."""

    out: np.ndarray | None = None
    into: tuple = ()
    views: tuple = ()
    floor: tuple = ()

    def limits(self, k: int) -> list:
        """Every group rule as (group, lo, hi): `into`'s as (group, 1, k), then `views`."""
        return [(np.asarray(q, dtype=int), 1, k) for q in self.into] + \
            [(np.asarray(q, dtype=int), lo, hi) for q, lo, hi in self.views]

    def keeps(self, selection, k: int) -> bool:
        """Whether a selection (indices) keeps the node's rules."""
        v = np.asarray(selection, dtype=int)
        return (self.out is None or not self.out[v].any()) and \
            all(lo <= np.isin(v, q).sum() <= hi for q, lo, hi in self.limits(k))


class Views:
    """Which candidates see each sample, for the branch and bound's splits on a sample's views
    (module docstring, "Branching on views"). term(info (M, 6), cover (M,), sample (M,)) -> (M,)
    the score's logarithm per sample (`vdo.design.score.Scorer.term`: score = exp(sum_n
    term_n), each term convex and non-increasing in the sample's information and coverage);
    info and weight as `relaxation`'s (dense, or the sparse `Candidates` and None); allowed the
    candidates a selection may hold. A candidate sees sample n when it stores an entry there
    (or, dense, a non-zero information or weight): the others add nothing at n."""

    def __init__(self, term: Callable, info, weight, allowed: np.ndarray):
        if weight is None:
            self.owner, self.sample, self.indptr = info.row, info.index, info.indptr
            self.info, self.weight = info.entry_info, info.entry_weight
            self.samples = info.samples
        else:
            info, weight = np.asarray(info, float), np.asarray(weight, float)
            self.owner, self.sample = np.nonzero((info != 0).any(axis=2) | (weight != 0))
            self.indptr = np.searchsorted(self.owner, np.arange(info.shape[0] + 1))
            self.info, self.weight = info[self.owner, self.sample], weight[self.owner, self.sample]
            self.samples = info.shape[1]
        self.allowed = np.asarray(allowed, bool)
        self.K = len(self.allowed)
        self._term = jax.jit(term)
        self._all = np.arange(self.samples)

    def terms(self, info: np.ndarray, cover: np.ndarray) -> np.ndarray:
        """(N,) every sample's term at summed information (N, 6) and coverage (N,)."""
        return np.asarray(self._term(info, cover, self._all))

    def count(self, selection) -> np.ndarray:
        """(N,) how many cameras of a selection (indices) see each sample."""
        seen = [self.sample[self.indptr[i]:self.indptr[i + 1]] for i in np.asarray(selection, dtype=int)]
        return np.bincount(np.concatenate(seen), minlength=self.samples) if seen else np.zeros(self.samples, int)

    def viewers(self, n: int) -> np.ndarray:
        """The allowed candidates that see sample n (sorted indices)."""
        at = self.owner[self.sample == n]
        return np.unique(at[self.allowed[at]])

    def alone(self, n: int) -> float:
        """The least term sample n can have in a selection of which at most one camera sees it:
        min(term(0, 0), min_i term(C_i(n), w_i(n))) over the allowed candidates i that see it
        (a lower bound on its term in every such selection, the term being exact there)."""
        e = np.flatnonzero((self.sample == n) & self.allowed[self.owner])
        info = np.concatenate([np.zeros((1, 6)), self.info[e]])
        cover = np.concatenate([[0.0], np.asarray(self.weight[e], float)])
        return float(np.min(np.asarray(self._term(info, cover, np.full(len(info), n)))))

    def split(self, h: Hull, summed, floor: np.ndarray) -> list[int] | None:
        """The samples to branch on at a hull's iterate, most underrated first (at most
        SPLIT_SAMPLES), or None: those that some of its selections see with at most one camera
        and others with two or more, and whose term the mix underrates, sum_s lam_s term_n(s) >
        max(term_n(x), floor_n) (the relaxation evaluates the mix's summed information x, the
        selections their own)."""
        if len(h.chosen) < 2:
            return None
        counts = np.array([self.count(v) for v in h.chosen])
        mixed = (counts <= 1).any(axis=0) & (counts >= 2).any(axis=0)
        if not mixed.any():
            return None
        mix = np.zeros(self.samples)
        for lam, v in zip(h.lam, h.chosen):
            w = np.zeros(self.K)
            w[v] = 1.0
            mix += lam * self.terms(*summed(w))
        under = mix - np.maximum(self.terms(*summed(h.x)), floor)
        under[~mixed] = -np.inf
        order = np.argsort(-under)[:SPLIT_SAMPLES]
        order = order[under[order] > 0]
        return [int(n) for n in order] if len(order) else None


def spots(positions: np.ndarray, digits: int = 3) -> np.ndarray:
    """(K,) the group of each candidate for the branching (`_branch`): the candidates whose
    optical centres agree to `digits` decimals of a metre (one spot: every pose, body and lens
    there)."""
    return np.unique(np.round(np.asarray(positions, float), digits), axis=0, return_inverse=True)[1].ravel()


def _fractional(x: np.ndarray, groups: np.ndarray, node: Node, tol: float):
    """The branching set at the iterate x: the group whose weight sum lies farthest from a whole
    number (beyond tol) among those the node has not branched on, else the candidate weighted
    farthest from 0 and 1 (its own group); None when every weight is within tol of 0 or 1."""
    done = {tuple(q) for q in node.into}
    sums = np.bincount(groups, x, minlength=int(groups.max()) + 1)
    off = np.abs(sums - np.round(sums))
    for q in np.argsort(-off):
        if off[q] <= tol:
            break
        members = np.flatnonzero(groups == q)
        if node.out is not None:
            members = members[~node.out[members]]
        if tuple(members) not in done:
            return members
    off = np.minimum(x, 1.0 - x)
    i = int(np.argmax(off))
    return None if off[i] <= tol else np.array([i])


def _branch(both, only, summed, pullback, rules: Rules, root: Hull, groups: np.ndarray, incumbent: float,
            deadline: float, inner_s: float, rel_tol: float, max_iter: int, max_nodes: int | None = None,
            views: Views | None = None, floored=None):
    """Branch and bound over the hull's selections (module docstring, "Branching"), best first:
    each open node's certificate bounds every selection keeping the rules and its branching
    rules; the node of lowest bound is split on the set S of `_fractional` (none of S / at
    least one of S: every selection lies in one child), each child certified by `_hull` from
    its parent's selections that keep its rules, and a child whose bound reaches the incumbent
    (f at the best selection found, each a point of the hull) within rel_tol is closed. Returns
    (the least of the incumbent, the closed nodes' bounds and the open nodes' bounds: a lower
    bound on f over every selection keeping the rules; nodes made (at most max_nodes); the incumbent; the selections found, best first
    (at most 8); the open nodes as (Node, bound))."""
    K = len(root.x)
    found: dict = {}

    def seen(h: Hull):
        nonlocal incumbent
        for v in h.chosen:
            key = tuple(int(i) for i in v)
            if key not in found:
                w = np.zeros(K)
                w[list(key)] = 1.0
                found[key] = float(only(*summed(w)))
                incumbent = min(incumbent, found[key])

    seen(root)
    # an open node: (bound, order, Node, its Hull, or None while only its parent's iterate
    # certifies it (`_once`), then the parent's Hull)
    heap, order, nodes, closed = [(root.bound, 0, Node(), root, None)], 1, 1, np.inf
    shown = since = time.perf_counter()
    risen = root.bound
    on_views = views is not None          # splits on views first (module docstring)

    def settle(child: Node, bound: float, c: Hull | None, parent: Hull | None):
        """Keeps a child open (its bound below the incumbent) or closes it."""
        nonlocal order, closed
        if bound < incumbent * (1 - rel_tol):
            heapq.heappush(heap, (bound, order, child, c, parent))
            order += 1
        else:           # closed: its selections score at least this (within rel_tol of the incumbent)
            closed = min(closed, bound)

    def solve(child: Node, parent: Hull, low: float) -> Hull:
        nonlocal nodes
        keep = [(v, w) for v, w in zip(parent.chosen, parent.lam) if child.keeps(v, rules.k)]
        fb, fo = (both, only) if not child.floor else floored(_floor(child, views.samples))
        c = _hull(fb, fo, summed, pullback, rules, parent.x, keep or None, low, deadline,
                  min(inner_s, NODE_INNER_S), rel_tol, max_iter, node=child, stop_above=incumbent)
        nodes += 1
        seen(c)
        return c

    while heap and time.perf_counter() < deadline and (max_nodes is None or nodes < max_nodes):
        low, _, node, h, parent = heap[0]
        if low >= incumbent * (1 - rel_tol):
            break
        if h is None:           # certified by its parent's iterate alone so far: its own hull now
            heapq.heappop(heap)
            c = solve(node, parent, low)
            settle(node, max(c.bound, low), c, None)
            continue
        split = views.split(h, summed, _floor(node, views.samples)) if on_views else None
        pick = None if split is not None else _fractional(h.x, groups, node, 1e-6)
        if split is None and pick is None:        # an integral iterate not certified: hull's steps ran out of time
            break
        now = time.perf_counter()
        if now > since + STALL_S:           # stalled: the bound rose by less than STALL in STALL_S
            if low < risen * (1 + STALL):
                break
            since, risen = now, low
        heapq.heappop(heap)
        if now > shown + BRANCH_LOG_S:
            shown = now
            log.info("branch and bound: %d nodes, %d open, bound %.5g, best selection found %.5g", nodes,
                     len(heap) + 1, low, incumbent)
        if split is not None:
            # samples n_1..n_m: every one seen by two cameras or more (solved now), or n_j the
            # first seen by at most one (its term at least `alone`; certified from h's iterate,
            # `_once`, and solved only when it is the least open bound)
            seers = [views.viewers(n) for n in split]
            many = tuple((q, 2, rules.k) for q in seers)
            for j, n in enumerate(split):
                child = replace(node, views=node.views + many[:j] + ((seers[j], 0, 1),),
                                floor=node.floor + ((n, views.alone(n)),))
                once = _once(floored(_floor(child, views.samples)), summed, pullback, rules, h.x, child, inner_s)
                nodes += 1
                if np.isfinite(once):
                    settle(child, max(once, low), None, h)
            child = replace(node, views=node.views + many)
            c = solve(child, h, low)
            settle(child, max(c.bound, low), c, None)
            if c.bound < low * (1 + VIEWS_LIFT):      # the mix moved at little cost: candidates from now on
                on_views = False
            continue
        out = np.zeros(K, bool) if node.out is None else node.out.copy()
        out[pick] = True
        for child in (replace(node, out=out), replace(node, into=node.into + (pick,))):
            c = solve(child, h, low)
            settle(child, max(c.bound, low), c, None)
    value = min([incumbent, closed] + [n[0] for n in heap])
    best = sorted(found, key=found.get)[:8]
    return value, nodes, incumbent, [np.array(v) for v in best], [(n[2], n[0]) for n in heap]


def _once(at, summed, pullback, rules: Rules, x: np.ndarray, node: Node, seconds: float) -> float:
    """A node's certificate at one point x (its parent's iterate), without its own hull: f(x) +
    min g.(s - x) over the selections that keep the node's rules (`Rules.vertex`), f and g the
    node's (value, gradient) `at`; inf when no selection keeps them."""
    fx, (gC, gc) = at[0](*summed(x))
    g = pullback(gC, gc)
    _, low = rules.vertex(g, seconds, node)
    return float(fx) + low - float(g @ x)


def _floored(term: Callable, samples: int):
    """floor (samples,) -> (value and gradient, value) of exp(sum_n max(term_n, floor_n)), jitted
    once: the score of a node whose selections keep each sample's term at or above its floor
    (`Node.floor`): convex (a maximum of convex functions) and equal to the score at each of
    those selections, so its minimum over their hull bounds their scores."""
    every = jnp.arange(samples)

    def value(info, cover, floor):
        return jnp.exp(jnp.sum(jnp.maximum(term(info, cover, every), floor)))
    both, only = jax.jit(jax.value_and_grad(value, argnums=(0, 1))), jax.jit(value)

    def at(floor):
        f = jnp.asarray(floor)
        return (lambda C, c: both(C, c, f)), (lambda C, c: only(C, c, f))
    return at


def relaxation(value: Callable, info, weight, k: int, allowed: np.ndarray,
               body: np.ndarray, counts: np.ndarray, start=None, conflicts: Callable | None = None,
               rel_tol: float = REL_TOL, max_iter: int = MAX_ITER, time_limit: float = 60.0,
               groups: np.ndarray | None = None, branch_s: float = 0.0,
               branch_nodes: int | None = None, term: Callable | None = None) -> Bound:
    """The certified bound of the relaxation for k cameras (module docstring). value(C (N, 6),
    k (N,)) -> score: a JAX function convex in its arguments (`vdo.design.score.Scorer.value`);
    info (K, N, 6) float64 1/m^2 and weight (K, N) the candidates' information and soft weights
    (or info the sparsely stored `Candidates` and weight None, `linear_maps`);
    allowed (K,) the candidates a selection may hold at all; body (K,) their body kind, counts
    its inventory; start: indices of a feasible selection (the design's), else the vertex of the
    first candidates; conflicts: j -> (K,) bool, the candidates that may not join a selection
    holding j (`vdo.design.feasibility.Feasibility.placement`), whose rules the bound then holds
    (`Rules`; None: the pairwise rules dropped); time_limit in wall seconds. With conflicts and
    branch_s > 0, a branch and bound follows for branch_s wall seconds more (`_branch`; groups
    (K,) the sets it branches on first, default none: candidates alone; branch_nodes: at most
    that many nodes, else as many as the time allows; term: the score's logarithm per sample,
    value = exp(sum_n term_n) (`Views`), with which it splits first on how many cameras see a
    sample). k is cut to `largest(...)` (no selection holds more)."""
    t0 = time.perf_counter()
    k = min(int(k), largest(allowed, body, counts))
    K, summed, pullback = linear_maps(info, weight)
    both = jax.jit(jax.value_and_grad(value, argnums=(0, 1)))
    only = jax.jit(value)

    x = np.zeros(K)
    if start is not None and len(start):
        x[list(start)] = 1.0
    else:
        x = vertex(-np.ones(K), k, allowed, body, counts)
    first = t0 + time_limit * (1.0 if conflicts is None else PLAIN_SHARE)
    best, best_x, plain, it = _descend(both, only, summed, pullback, x, k, allowed, body, counts, first,
                                       rel_tol, max_iter)
    bound, held, nodes, found, leaves = plain, 0, 0, [], []
    if conflicts is not None and time.perf_counter() < t0 + time_limit:
        rules = Rules(conflicts, k, allowed, body, counts)
        weighed = np.flatnonzero(best_x > SUPPORT)
        rules.hold(np.concatenate([np.asarray(start if start is not None else [], dtype=int),
                                   weighed[np.argsort(-best_x[weighed])]]), t0 + time_limit)
        h = _hull(both, only, summed, pullback, rules, best_x, start, plain,
                  t0 + time_limit, INNER_SHARE * time_limit, rel_tol, max_iter)
        bound, steps = h.bound, h.steps
        it, held = it + steps, len(rules.held)
        if h.best_x is not None:
            best, best_x = h.best, h.best_x
        if branch_s > 0 and np.isfinite(h.bound):
            incumbent = float(only(*summed(x))) if start is not None and len(start) else np.inf
            views = floored = None
            if term is not None:
                views = Views(term, info, weight, allowed)
                floored = _floored(term, views.samples)
            bound, nodes, _, found, leaves = _branch(
                both, only, summed, pullback, rules, h, np.arange(K) if groups is None else np.asarray(groups),
                incumbent, time.perf_counter() + branch_s, INNER_SHARE * time_limit, rel_tol, max_iter,
                max_nodes=branch_nodes, views=views, floored=floored)
            bound, held = max(bound, h.bound), len(rules.held)
    return Bound(cameras=k, value=float(bound), plain=float(plain), relaxed=float(best), weights=best_x,
                 iterations=it, converged=best - bound <= rel_tol * abs(bound),
                 seconds=time.perf_counter() - t0, conflicted=held, nodes=nodes, found=found, leaves=leaves)
