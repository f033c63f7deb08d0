"""A start for `vdo design` from an outer approximation of the score (`search`): a mixed-integer
model whose optimum is the selection that the score's tangent planes rate best.

The model. The score's logarithm F(x) = sum_n term_n(C_n(x), k_n(x)) (`vdo.design.score.Scorer.term`)
is convex in the 0/1 vector x of a selection (`vdo.design.bound`), and so is its part over any
group B of samples, F_B(x) = sum_{n in B} term_n. Each such part lies above its tangent plane at any
point x0 (a relaxation's weights or a selection):

    F_B(x) >= F_B(x0) + gamma_B . (x - x0),
    gamma_B,i = sum_{n in B} <d term_n / dC_n, C_i(n)> + d term_n / dk_n w_i(n)   (1/camera),

so the mixed-integer linear program (HiGHS through scipy's `milp`)

    min sum_B z_B   over z and the 0/1 x of a pool of candidates,
    z_B >= F_B(x0) + gamma_B . (x - x0) for every group B and every point x0 met so far,
    sum x = k,  per body kind sum x <= count,  at most one camera per clique of conflicting pool candidates,

under-estimates F at every selection of the pool, and its solution is the selection the planes
rate best. Scoring that selection and adding its planes corrects the model where it was wrong
(Kelley's cutting planes; the outer approximation of Duran and Grossmann for convex mixed-integer
programs): a selection once met is never rated below its score again, and once the model's optimum
(its dual bound) reaches the best score met, or its solution is a selection met before (the model
then rates it at its score), no selection of the pool scores lower (within MODEL_GAP). A selection
that breaks a rule the model does not hold (`search`'s `feasible`) is cut off by one row,
sum_{i in S} x_i <= k - 1. Unlike the
relaxation, whose optimum mixes selections that each see one part of the specimen well, the
model's selections are selections: on the steel beam (4 cameras, 21,340 candidates, a pool of
the relaxation's 33 weighed candidates and 150 of each body kind) its first solution is the best
layout any run has met (0.17636), where greedy and the exchange passes stop at 0.1926
(docs/design.md).

The groups are clusters of the samples (`sample_groups`): one group would leave a single plane
per point, one per sample the most rows; their number weighs the model's fidelity against the
MILP's size. The pool (`pool`): the candidates the relaxation weighs and, per body kind, those
whose linearised cost gamma_i (summed over the groups) at the relaxation's weights is lowest.
It is a start, not a bound: candidates outside the pool are not rated.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
from scipy.cluster.vq import kmeans2
from scipy.optimize import Bounds, LinearConstraint, milp

from vdo.design.hull import cliques, linear_maps
from vdo.search.anytime import Stop, until_stopped

log = logging.getLogger(__name__)

GROUPS = 10          # sample groups of the model (fewer when there are fewer samples)
POOL_PER_BODY = 150  # pool candidates of lowest linearised cost per body kind, besides those weighed
WEIGHED = 1e-6       # a weight above this puts a candidate in the pool
GROUP_SEED = 0       # k-means seed of `sample_groups` (the same groups run to run)
MODEL_GAP = 1e-3     # HiGHS's relative gap on the model's optimum (of F, a logarithm: ~0.2 % of the score)


@dataclass
class Outcome:
    """What `search` met: `chosen` the best feasible selection (indices; None: none), `score` its
    score (exp F), `model` the model's last dual bound over the pool (exp of it; -inf: none),
    `solves` the MILPs solved."""

    chosen: list | None
    score: float
    model: float
    solves: int


def sample_groups(points: np.ndarray, groups: int = GROUPS, seed: int = GROUP_SEED) -> np.ndarray:
    """(N,) labels 0..G-1 of the samples (N, 3) m: k-means clusters of their positions, G =
    min(groups, N); empty clusters are dropped and the labels renumbered."""
    points = np.asarray(points, float)
    g = min(int(groups), len(points))
    if g <= 1:
        return np.zeros(len(points), int)
    _, label = kmeans2(points, g, minit="++", seed=seed)
    return np.unique(label, return_inverse=True)[1]


def planes(term: Callable, summed, pullback, groups: np.ndarray, x0: np.ndarray):
    """The tangent planes of every group's F_B at x0 (module docstring): (gamma (K, G) 1/camera,
    rhs (G,) = F_B(x0) - gamma_B . x0, F(x0))."""
    C, c = summed(x0)
    N = len(groups)
    T, back = jax.vjp(lambda C, c: term(C, c, jnp.arange(N)), jnp.asarray(C), jnp.asarray(c))
    gC, gc = (np.asarray(a) for a in back(jnp.ones_like(T)))     # the gradient of sum_n term_n
    T = np.asarray(T)
    gamma = pullback(gC, gc, groups)
    return gamma, np.bincount(groups, T, minlength=gamma.shape[1]) - gamma.T @ x0, float(T.sum())


def pool(weights: np.ndarray, gamma: np.ndarray, allowed: np.ndarray, body: np.ndarray,
         per_body: int = POOL_PER_BODY) -> np.ndarray:
    """The pool's candidates (sorted indices): those weighed above WEIGHED, and per body kind the
    per_body allowed ones of lowest summed linearised cost gamma.sum(1)."""
    cost = gamma.sum(1)
    keep = set(np.flatnonzero(allowed & (weights > WEIGHED)).tolist())
    for b in np.unique(body):
        kind = np.flatnonzero(allowed & (body == b))
        keep |= set(kind[np.argsort(cost[kind], kind="stable")[:per_body]].tolist())
    return np.array(sorted(keep), dtype=int)


def search(term: Callable, info, weight, k: int, allowed: np.ndarray, body: np.ndarray,
           counts: np.ndarray, conflicts: Callable, feasible: Callable, groups: np.ndarray,
           points: list, seconds: float, per_body: int = POOL_PER_BODY, max_solves: int = 50,
           stop: Stop | None = None) -> Outcome:
    """The outer approximation's selections (module docstring) for k cameras. term(C (M, 6),
    cover (M,), sample (M,)) the score's logarithm per sample (JAX, convex); info, weight the
    candidates' information as `vdo.design.hull.linear_maps` takes it; allowed, body, counts as
    in `vdo.design.bound.relaxation`; conflicts(j) (K,) bool the candidates that may not join a
    selection holding j (a pair conflicts when each says so of the other); feasible(selection)
    whether a selection keeps every rule (the model holds the pairwise ones of the pool only);
    groups (N,) the samples' groups (`sample_groups`); points: (K,) weight vectors or index
    lists at which the first planes are laid, the first one the relaxation's weights (it sets
    the pool; the others are laid while `seconds` last). Stops after `seconds` wall seconds,
    max_solves MILPs, when the model's dual bound reaches the best feasible score met, or when
    its solution is a feasible selection met before; a selection `feasible` refuses is cut off.
    With `stop` (`vdo.search.anytime.Stop`), a MILP runs in a worker thread and the search ends
    with what it met once a stop is requested (Ctrl-C), the MILP left to finish on its own."""
    deadline = time.perf_counter() + seconds
    K, summed, pullback = linear_maps(info, weight)

    def vector(p):
        p = np.asarray(p)
        if p.ndim == 1 and len(p) == K and p.dtype.kind == "f":
            return p
        v = np.zeros(K)
        v[p.astype(int)] = 1.0
        return v

    first = []          # the planes at the given points, the first one always, the others in time
    for p in points:
        if first and time.perf_counter() > deadline:
            break
        first.append(planes(term, summed, pullback, groups, vector(p)))
    chosen = pool(vector(points[0]), first[0][0], allowed, body, per_body)
    P, G = len(chosen), first[0][0].shape[1]
    among = np.array([np.asarray(conflicts(j), bool)[chosen] for j in chosen])
    adjacent = among & among.T
    np.fill_diagonal(adjacent, False)
    fixed = [np.r_[np.ones(P), np.zeros(G)][None]] + \
        [np.r_[(body[chosen] == b).astype(float), np.zeros(G)][None] for b in range(len(counts))] + \
        [np.r_[np.isin(np.arange(P), q).astype(float), np.zeros(G)][None] for q in cliques(adjacent)]
    fixed_lo = np.r_[k, np.zeros(len(fixed) - 1)]
    fixed_hi = np.r_[k, counts, np.ones(len(fixed) - 1 - len(counts))]
    cut_rows, cut_lo = [], []

    def lay(gamma, rhs):
        cut_rows.append(np.hstack([-gamma[chosen].T, np.eye(G)]))
        cut_lo.append(rhs)
    for gamma, rhs, _ in first:
        lay(gamma, rhs)
    best, best_score, model, solves = None, math.inf, -math.inf, 0
    met = set()
    while solves < max_solves and time.perf_counter() < deadline:
        A = scipy.sparse.csr_matrix(np.vstack(cut_rows + fixed))
        lo = np.concatenate(cut_lo + [fixed_lo])
        hi = np.concatenate([np.full(sum(len(r) for r in cut_lo), np.inf), fixed_hi])
        def solve():
            return milp(np.r_[np.zeros(P), np.ones(G)], constraints=LinearConstraint(A, lo, hi),
                        integrality=np.r_[np.ones(P), np.zeros(G)],
                        bounds=Bounds(np.r_[np.zeros(P), np.full(G, -np.inf)], np.r_[np.ones(P), np.full(G, np.inf)]),
                        options={"time_limit": max(deadline - time.perf_counter(), 1.0), "mip_rel_gap": MODEL_GAP})
        done, res = (True, solve()) if stop is None else until_stopped(stop, solve)
        if not done:
            break
        solves += 1
        low = getattr(res, "mip_dual_bound", None)
        if low is not None and np.isfinite(low) and res.status in (0, 1):
            model = max(model, math.exp(low))
        if res.x is None:
            break
        taken = res.x[:P] > 0.5
        selection = np.sort(chosen[taken])
        key = tuple(selection.tolist())
        if not feasible(list(key)):     # a rule the model does not hold: that selection is cut off
            fixed.append(np.r_[taken.astype(float), np.zeros(G)][None])
            fixed_lo, fixed_hi = np.r_[fixed_lo, 0.0], np.r_[fixed_hi, k - 1]
            log.debug("outer approximation: solve %d, selection %s breaks a rule: cut off", solves, list(key))
            continue
        if key in met:      # its planes are laid, so the model rates it at its score: nothing in
            break           # the pool rates lower (within MODEL_GAP), and the next solve is this one
        met.add(key)
        gamma, rhs, value = planes(term, summed, pullback, groups, vector(selection))
        lay(gamma, rhs)
        score = math.exp(value)
        if score < best_score:
            best, best_score = list(key), score
        log.debug("outer approximation: solve %d, model %.5g, selection %s scores %.5g", solves,
                  math.exp(res.fun), list(key), score)
        if model >= best_score:
            break
    return Outcome(best, best_score, model, solves)
