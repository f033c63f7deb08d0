"""The branch and bound of the design bound (`vdo.design.bound.relaxation` with `branch_s`).

Branching. What is left is the integrality gap of H itself: its optimum mixes whole selections
(on the steel beam each selection of the mix scores 0.30 to 10^9 alone), and no inequality that
the selections keep removes a mix. A branch and bound does (`search`, `[design] branch_s` for
the inventory's count): a node is the hull phase over the selections that keep the rules and
the node's own, none of the candidates it left out and at least one camera in each group it
requires (`vdo.design.hull.Node`; two more kinds of rows in `vdo.design.hull.Rules.vertex`, whose candidates not held enter as
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
none can give it; the node's function takes max(term_n, floor_n) per sample, `Views.floored`,
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
"""

from __future__ import annotations

import heapq
import logging
import time
from dataclasses import replace
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from vdo.design.hull import Hull, Node, Rules, corrective

log = logging.getLogger(__name__)

NODE_INNER_S = 1.0     # the branch and bound's nodes: one re-weighting of their selections at most this long
STALL_S = 60.0         # the branch and bound stops when the bound rose by less than STALL (relative) in STALL_S
STALL = 5e-4
SPLIT_SAMPLES = 16     # a split on views names at most this many samples (`Views.split`)
VIEWS_LIFT = 1e-3      # ... and the tree splits on candidates alone once one lifts its bound by less (relative)
BRANCH_LOG_S = 30.0    # a progress line of the branch and bound at most this often


def _floor(node: Node, samples: int) -> np.ndarray:
    """(samples,) each sample's least term in the node's selections (-inf where none is known)."""
    floor = np.full(samples, -np.inf)
    for n, value in node.floor:
        floor[n] = max(floor[n], value)
    return floor


class Views:
    """Which candidates see each sample, for the branch and bound's splits on a sample's views
    (module docstring, "Branching on views"). term(info (M, 6), cover (M,), sample (M,)) -> (M,)
    the score's logarithm per sample (`vdo.design.score.Scorer.term`: score = exp(sum_n
    term_n), each term convex and non-increasing in the sample's information and coverage);
    info and weight as `vdo.design.bound.relaxation`'s (dense, or the sparse `Candidates` and None); allowed the
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
        every = jnp.arange(self.samples)

        def value(info, cover, floor):
            return jnp.exp(jnp.sum(jnp.maximum(term(info, cover, every), floor)))
        self._floored = jax.jit(jax.value_and_grad(value, argnums=(0, 1))), jax.jit(value)

    def floored(self, floor: np.ndarray):
        """(value and gradient, value) of exp(sum_n max(term_n, floor_n)) at summed information
        and coverage, floor (N,): the score of a node whose selections keep each sample's term
        at or above its floor (`Node.floor`), convex (a maximum of convex functions) and equal
        to the score at each of those selections, so its minimum over their hull bounds their
        scores (jitted once)."""
        both, only = self._floored
        f = jnp.asarray(floor)
        return (lambda C, c: both(C, c, f)), (lambda C, c: only(C, c, f))

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
    """(K,) the group of each candidate for the branching (`search`): the candidates whose
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


def search(both, only, summed, pullback, rules: Rules, root: Hull, groups: np.ndarray, incumbent: float,
            deadline: float, inner_s: float, rel_tol: float, max_iter: int, max_nodes: int | None = None,
            views: Views | None = None):
    """Branch and bound over the hull's selections (module docstring, "Branching"), best first:
    each open node's certificate bounds every selection keeping the rules and its branching
    rules; the node of lowest bound is split on the set S of `_fractional` (none of S / at
    least one of S: every selection lies in one child), each child certified by `corrective` from
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
        fb, fo = (both, only) if not child.floor else views.floored(_floor(child, views.samples))
        c = corrective(fb, fo, summed, pullback, rules, parent.x, keep or None, low, deadline,
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
                once = _once(views.floored(_floor(child, views.samples)), summed, pullback, rules, h.x, child, inner_s)
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
