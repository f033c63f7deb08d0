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
its parent's. S is a class of candidates (below, "Branching on classes"), else the candidate
weighted farthest from 0 and 1. Best first: the node of least bound is split, each child certified by
the hull phase from the parent's selections that keep its rules (NODE_INNER_S of re-weighting
at most), so the bound rises monotonically; it stops at its time, when the bound has risen by
less than STALL in STALL_S and STALL_SPLITS splits (a split on classes may take 20-50 s a node on
the steel beam), or when every node is closed (the best selection found is then the
best of all). A split's two children (on views: the child solved now and the others' one-step
certificates) are worked on side by side in two threads (`vdo.search.anytime.Beside`; HiGHS
and NumPy's kernels release the GIL, `Rules` hands each linear step a matching pair of held
candidates and cliques):
on the steel beam's first 40 nodes 142.6 -> 105.2 s, the same bound (0.16049), 2 cores.
Measured (2026-12-06, 2 cores shared with two other jobs): on the built-in (10
cameras) 49 nodes in 260 s lifted 0.05142 to 0.05192, gap 5.8 -> 4.9 %; on the steel beam
(4 cameras) 13 nodes in 240 s lifted 0.15559 to 0.15575: there each child moves the bound by
0.01-0.05 %, the mix spreading over other spots at almost no cost.

Tightening on demand. The bound is the least over the open nodes, so a node's hull needs to
be certified only as far as that least bound can rise before the node is split: a node's
hull (`corrective`) stops once its bound is AHEAD above the least other open bound (`Hull.above`),
and when it becomes the least itself it is tightened from where it stopped, before it is split
(its selections, weights and iterate kept); two such nodes are tightened side by side. The
bound over the open nodes stays valid at every step (each certificate holds for its node's
selections, whatever its convergence); what is saved are the late Frank-Wolfe steps on nodes
whose bounds stay above the tree's.

Branching on classes. A spot is one optical centre, and the mix moves to the next one at almost
no cost; what separates its selections is coarser. On the steel beam the root's mix weighs
selections that favour one end of the beam with their mirror images: cameras on the left
aimed at the right end's centre, or at the left's, from one height or another. So the
candidates are grouped in families of classes, coarse to fine (`classes`): by aim point; aim
point and mount; those and body kind; those and lens; spot. A node whose iterate holds a
fractional t + f (0 < f < 1) cameras of a class S splits into at most t cameras of S / at
least t + 1 (t = 0: none / some, as before; `_children`; every selection keeps exactly one).
Which family lifts most depends on the experiment, so the tree learns it as it goes
(pseudo-costs, as MILP solvers rank their branching variables): each family is split on once,
coarse to fine, and then the family whose splits lifted the least child's bound fastest (its
relative lifts over the seconds its children took, the tree having a time limit). In that
family, of its PICK_PER_FAMILY most fractional classes, the one that leaves the mix worst off:
the larger of the node's function at the mix of its selections on each side (re-weighted to
sum 1), the smaller side taken (`_pick`; the hull's certificate at the parent's iterate is the
same for every split, so it cannot rank them). Measured on the steel beam's root (4 cameras,
the hull at 0.15563, each child solved alone): a split on an aim point lifts the least child by
0.58 %, on aim point, mount and body by 1.41 %, against 0.01-0.1 % for a spot. 300 s of
branching from the same hull (2 loaded cores): the steel beam 0.15777 on spots, 0.16097 on
classes; the built-in (10 cameras on rails, where spots lift most) 0.05202 on spots, 0.05189
on classes ranked by the mix alone, 0.05200 with the pseudo-costs.

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
the split falls back to classes, and once a split on views lifts its node's bound by less than
VIEWS_LIFT (the mix found other selections that see those samples twice at little cost) the
tree splits on classes alone. Measured on the steel beam (4 cameras, 2 loaded cores): two
splits on views lift the hull's 0.15562 to 0.15710 (+0.95 %, against +0.1 % for the first four
spot splits), after which the mix sees every sample twice; what is left is the Jensen gap of
the measured samples' sigma (the target's term is quadratic in ln sigma, and the mix's
selections each favour one end), which the splits on classes take back in part. On random
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
from vdo.search.anytime import Beside

log = logging.getLogger(__name__)

NODE_INNER_S = 1.0     # the branch and bound's nodes: one re-weighting of their selections at most this long
STALL_S = 60.0         # the branch and bound stops when the bound rose by less than STALL (relative) in STALL_S
STALL = 5e-4
STALL_SPLITS = 8       # ... and in STALL_SPLITS splits (not nodes: a split on views makes up to SPLIT_SAMPLES + 1)
SPLIT_SAMPLES = 16     # a split on views names at most this many samples (`Views.split`)
VIEWS_LIFT = 1e-3      # ... and the tree splits on classes alone once one lifts its bound by less (relative)
AHEAD = 1e-3           # a node's hull stops once its bound is this far (relative) above the least other open one
PICK_PER_FAMILY = 3    # a split on classes weighs this many classes of each family (`_pick`)
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


def classes(target: np.ndarray, mount, body: np.ndarray, focal: np.ndarray,
            positions: np.ndarray) -> np.ndarray:
    """(5, K) the classes of candidates the branching counts (`search`, module docstring
    "Branching on classes"), coarse to fine, one row of labels each: the aim point (`target`),
    the aim point and the mount, those and the body kind, those and the lens (`focal`), and the
    spot (`spots`)."""
    lens = np.round(np.asarray(focal, float), 6)
    return np.stack([_label(target), _label(target, mount), _label(target, mount, body),
                     _label(target, mount, body, lens), spots(positions)])


def _label(*columns) -> np.ndarray:
    """(K,) one label per distinct combination of the columns' values (each (K,))."""
    codes = [np.unique(np.asarray(c), return_inverse=True)[1].ravel() for c in columns]
    return np.unique(np.stack(codes, axis=1), axis=0, return_inverse=True)[1].ravel()


def _pick(h: Hull, families: np.ndarray, node: Node, value: Callable, summed, tol: float,
          lifts: np.ndarray):
    """The branching set at a node's hull h: (family, S, t), every selection holding at most t
    cameras of S or at least t + 1 (module docstring, "Branching on classes"). Of each family of
    classes (rows of `families`, labels), the PICK_PER_FAMILY classes whose weights at h's
    iterate sum farthest from a whole number (beyond tol), t the sum rounded down. The family:
    the first (coarse to fine) not split on yet, else the one whose splits lifted their node's
    bound fastest (`lifts` (F, 2): the relative lifts of the least child's bound over the
    node's, and the seconds their children took, each summed so far: a pseudo-cost per
    second). In it, the class whose split leaves the mix worst off: the larger of the
    node's function `value` at the mix of h's selections on each side (re-weighted to sum 1),
    the smaller of the two sides taken. Else the candidate weighted farthest from 0 and 1
    (family -1, t = 0); None when every weight is within tol of 0 or 1."""
    x, K = h.x, len(h.x)
    per, named = [], set()
    for f, labels in enumerate(families):
        ids, inv = np.unique(labels, return_inverse=True)
        sums = np.bincount(inv, x, minlength=len(ids))
        off = np.abs(sums - np.round(sums))
        options = []
        for q in np.argsort(-off)[:PICK_PER_FAMILY]:
            if off[q] <= tol:
                break
            members = np.flatnonzero(inv == q)
            if node.out is not None:
                members = members[~node.out[members]]
            if tuple(members) not in named:
                named.add(tuple(members))
                options.append((members, int(np.floor(sums[q] + tol))))
        if options:
            per.append((f, options))
    if not per:
        off = np.minimum(x, 1.0 - x)
        i = int(np.argmax(off))
        return None if off[i] <= tol else (-1, np.array([i]), 0)
    untried = [p for p in per if lifts[p[0], 1] == 0]
    f, options = untried[0] if untried else max(per, key=lambda p: lifts[p[0], 0] / lifts[p[0], 1])
    if len(options) == 1 or len(h.chosen) < 2:
        return (f, *options[0])

    def side(keep):
        lam = np.where(keep, h.lam, 0.0)
        if lam.sum() <= 0:
            return np.inf
        mix = np.zeros(K)
        for weight, v in zip(lam / lam.sum(), h.chosen):
            mix[v] += weight
        return float(value(*summed(mix)))

    def worse_off(option):
        members, t = option
        held = np.array([np.isin(v, members).sum() for v in h.chosen])
        return min(side(held <= t), side(held > t))
    return (f, *max(options, key=worse_off))


def _children(node: Node, group: np.ndarray, t: int, k: int, K: int) -> tuple[Node, Node]:
    """A node's two children split on a class `group` (indices) at count t: at most t cameras of
    it / at least t + 1 (t = 0: none of it, left out of the linear step / at least one), so that
    each of the node's selections keeps the rules of exactly one."""
    if t == 0:
        out = np.zeros(K, bool) if node.out is None else node.out.copy()
        out[group] = True
        return replace(node, out=out), replace(node, into=node.into + (group,))
    return (replace(node, between=node.between + ((group, 0, t),)),
            replace(node, between=node.between + ((group, t + 1, k),)))


def search(both, only, summed, pullback, rules: Rules, root: Hull, groups: np.ndarray, incumbent: float,
            deadline: float, inner_s: float, rel_tol: float, max_iter: int, max_nodes: int | None = None,
            views: Views | None = None, stop: Callable[[], bool] | None = None):
    """Branch and bound over the hull's selections (module docstring, "Branching"), best first:
    each open node's certificate bounds every selection keeping the rules and its branching
    rules; the node of lowest bound is split on a sample's views (`views`, `Views.split`) or on
    the set S and count t of `_pick` among the classes `groups` ((K,) labels, or (F, K): F
    families of them, `classes`): at most t cameras of S / at least t + 1 (t = 0: none of S / at
    least one; every selection lies in one child), each child certified by `corrective` from
    its parent's selections that keep its rules, and a child whose bound reaches the incumbent
    (f at the best selection found, each a point of the hull) within rel_tol is closed. Returns
    (the least of the incumbent, the closed nodes' bounds and the open nodes' bounds: a lower
    bound on f over every selection keeping the rules; nodes made (at most max_nodes); the incumbent; the selections found, best first
    (at most 8); the open nodes as (Node, bound)). `stop()` True ends it as its time does (a
    node's hull in the making stops at its next step; `vdo.search.anytime.Stop`)."""
    K = len(root.x)
    families = np.atleast_2d(np.asarray(groups))
    lifts = np.zeros((len(families), 2))      # per family: its splits' relative lifts and their seconds, summed
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
    # an open node: (bound, order, Node, its Hull (`Hull.above`: to be tightened before it is
    # split), or None while only its parent's iterate certifies it (`_once`), then the parent's Hull)
    heap, order, nodes, closed = [(root.bound, 0, Node(), root, None)], 1, 1, np.inf
    shown = since = time.perf_counter()
    risen, splits, splits_then = root.bound, 0, 0
    on_views = views is not None          # splits on views first (module docstring)

    def settle(child: Node, bound: float, c: Hull | None, parent: Hull | None):
        """Keeps a child open (its bound below the incumbent) or closes it."""
        nonlocal order, closed
        if bound < incumbent * (1 - rel_tol):
            heapq.heappush(heap, (bound, order, child, c, parent))
            order += 1
        else:           # closed: its selections score at least this (within rel_tol of the incumbent)
            closed = min(closed, bound)

    def ceiling() -> float:
        """Where a node worked on now may stop (module docstring, "Tightening on demand"): a
        little above the least other open bound, or at the incumbent."""
        return min(incumbent, heap[0][0] * (1 + AHEAD)) if heap else incumbent

    def solve(child: Node, point: np.ndarray, start: list, low: float, above: float) -> Hull:
        """A node's hull from `point` and `start` ((selection, weight) pairs) until it converges
        or its bound reaches `above` (in a worker thread: `Rules` and the jitted functions are
        shared)."""
        fb, fo = (both, only) if not child.floor else views.floored(_floor(child, views.samples))
        return corrective(fb, fo, summed, pullback, rules, point, start or None, low, deadline,
                          min(inner_s, NODE_INNER_S), rel_tol, max_iter, node=child, stop_above=above,
                          stop=stop)

    def child_of(child: Node, parent: Hull, low: float, above: float) -> Hull:
        """A child's own hull, from its parent's iterate and the parent's selections it keeps."""
        keep = [(v, w) for v, w in zip(parent.chosen, parent.lam) if child.keeps(v, rules.k)]
        return solve(child, parent.x, keep, low, above)

    def again(node: Node, h: Hull | None, parent: Hull | None, low: float, above: float) -> Hull:
        """An open node's hull made (certified by its parent's iterate so far) or tightened."""
        if h is None:
            return child_of(node, parent, low, above)
        return solve(node, h.x, list(zip(h.chosen, h.lam)), low, above)

    def solved(c: Hull) -> Hull:
        nonlocal nodes
        nodes += 1
        seen(c)
        return c

    def waiting(entry) -> bool:
        """An open node whose hull is still to be made or tightened before it can be split."""
        return entry[3] is None or entry[3].above

    while heap and time.perf_counter() < deadline and (max_nodes is None or nodes < max_nodes) \
            and not (stop is not None and stop()):
        low, _, node, h, parent = heap[0]
        if low >= incumbent * (1 - rel_tol):
            break
        if waiting(heap[0]):    # its own hull now, or tightened; the next one beside it when it waits too
            work = [heapq.heappop(heap)]
            if heap and waiting(heap[0]) and heap[0][0] < incumbent * (1 - rel_tol):
                work.append(heapq.heappop(heap))
            above = ceiling()
            side = Beside(again, *work[1][2:], work[1][0], above).result if len(work) > 1 else None
            results = [again(*work[0][2:], work[0][0], above)] + ([side()] if side else [])
            for (low, _, node, h, _), c in zip(work, results):
                if h is None:
                    solved(c)
                else:
                    seen(c)
                settle(node, max(c.bound, low), c, None)
            continue
        split = views.split(h, summed, _floor(node, views.samples)) if on_views else None
        pick = None if split is not None else _pick(
            h, families, node, only if not node.floor else views.floored(_floor(node, views.samples))[1], summed,
            1e-6, lifts)
        if split is None and pick is None:        # an integral iterate not certified: hull's steps ran out of time
            break
        now = time.perf_counter()
        if now > since + STALL_S and splits >= splits_then + STALL_SPLITS:     # stalled: the bound rose
            if low < risen * (1 + STALL):                                # by less than STALL in both
                break
            since, risen, splits_then = now, low, splits
        heapq.heappop(heap)
        splits += 1
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
            child = replace(node, between=node.between + many)
            hull_of = Beside(child_of, child, h, low, ceiling()).result     # its hull in a second thread, the others here
            for j, n in enumerate(split):
                child = replace(node, between=node.between + many[:j] + ((seers[j], 0, 1),),
                                floor=node.floor + ((n, views.alone(n)),))
                once = _once(views.floored(_floor(child, views.samples)), summed, pullback, rules, h.x, child, inner_s)
                nodes += 1
                if np.isfinite(once):
                    settle(child, max(once, low), None, h)
            child = replace(node, between=node.between + many)
            c = solved(hull_of())
            settle(child, max(c.bound, low), c, None)
            if c.bound < low * (1 + VIEWS_LIFT):      # the mix moved at little cost: candidates from now on
                on_views = False
            continue
        family, group, t = pick
        least, began = np.inf, time.perf_counter()
        first, second = _children(node, group, t, rules.k, K)
        above = ceiling()
        hull_of = Beside(child_of, second, h, low, above).result        # the two children's hulls side by side
        for child, c in ((first, child_of(first, h, low, above)), (second, hull_of())):
            c = solved(c)
            settle(child, max(c.bound, low), c, None)
            least = min(least, max(c.bound, low))
        if family >= 0 and np.isfinite(least) and low > 0:     # bound 0: no certificate yet, no relative lift
            lifts[family] += (least / low - 1.0, time.perf_counter() - began)
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
