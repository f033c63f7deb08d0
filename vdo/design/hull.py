"""The hull phase of the design bound (`vdo.design.bound`, whose docstring has the formulas):
the polytope P of the candidates' weights (`vertex`, its linear step; `project`, the Euclidean
projection; `linear_maps`, the per-sample sums and their adjoint), the accelerated projected
gradient over it (`descend`), the pairwise rules and a branch and bound node's rules in the
linear step over the selections that keep them (`Rules`, a MILP; `Node`), and the fully
corrective Frank-Wolfe over their hull (`corrective`)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse
from scipy.optimize import Bounds, LinearConstraint, milp

from vdo.design.candidates import ENTRY_CHUNK

BISECTIONS = 60       # bisection steps of the projection's multipliers (to 2^-60 of their range)
ROUNDING = 1e-12      # relative rounding allowed in the backtracking test of the score
DOUBLINGS = 60        # backtracking doublings of the Lipschitz estimate at most per step
SHRINK = 0.9          # the Lipschitz estimate's shrink after an accepted step (backtracking doubles it)
SAMPLE_MAJOR_BYTES = 6 * 8 + 4 + 4   # a stored pair's copy in `linear_maps`'s sample-major order (information, weight, owner)
SPARSE_ROWS = 8       # sums over the weighted candidates' own entries when fewer than 1 / this of all
INNER_TOL = 0.5       # ... and stops at INNER_TOL * rel_tol (of its own certificate)
LINEAR_S = 30.0       # one linear step's MILP at most this long (its dual bound still certifies, its incumbent is the step)
MIP_GAP = 1e-9        # HiGHS's relative gap in the selection oracle (the certificate takes its dual bound)


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


def linear_maps(info, weight, rows: np.ndarray | None = None):
    """(K, summed, pullback) for candidates given densely, info (K, N, 6) and weight (K, N), or
    stored sparsely (`info` a `vdo.design.candidates.Candidates`: indptr, index, entry_info,
    entry_weight; `weight` None): summed(w) = (sum_k w_k C_k (N, 6), sum_k w_k w_k,n (N,)) and its
    adjoint pullback(gC, gc) = (sum_n C_k,n : gC_n + w_k,n gc_n)_k (K,); pullback(gC, gc, groups),
    groups (N,) labels 0..G-1 of the samples, gives the adjoint of each group's samples apart, (K,
    G), in one pass. The sparse form costs the stored entries, not K x N. With `rows` (K,) bool
    (sparse form), pullback(gC, gc) gives the adjoint of those candidates only (0 for the others:
    the bound's linear steps never take a candidate that is not allowed) from a copy of their
    stored pairs ordered by sample (SAMPLE_MAJOR_BYTES per pair, made here): per sample one
    matrix-vector product over its contiguous pairs, then one sum per candidate, where the
    candidate-major pass gathers gC at every pair (on the steel beam's 7.5 M pairs, 5.6 M of
    allowed candidates: 190 -> 80 ms a call)."""
    if weight is None:
        K, N = len(info.indptr) - 1, info.samples
        owner, idx, ei, ew = info.row, info.index, info.entry_info, info.entry_weight
        chunks = [slice(lo, lo + ENTRY_CHUNK) for lo in range(0, len(idx), ENTRY_CHUNK)]
        if rows is not None:
            keep = np.flatnonzero(np.asarray(rows, bool)[owner])
            by = keep[np.argsort(idx[keep], kind="stable")]
            del keep
            by_info, by_weight = np.take(ei, by, axis=0), np.take(ew, by)
            by_owner = owner[by].astype(np.int32)
            starts = np.searchsorted(idx[by], np.arange(N + 1))
            del by

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

        def pullback(gC, gc, groups=None):
            gC, gc = np.asarray(gC), np.asarray(gc)
            if rows is not None and groups is None:
                values = np.empty(len(by_owner))
                for n in range(N):
                    part = slice(starts[n], starts[n + 1])
                    np.dot(by_info[part], gC[n], out=values[part])
                    values[part] += by_weight[part] * gc[n]
                return np.bincount(by_owner, values, minlength=K)
            G = 1 if groups is None else int(np.max(groups)) + 1
            out = np.zeros(K * G)
            for part in chunks:
                i = idx[part]
                where = owner[part] if groups is None else owner[part] * G + groups[i]
                out += np.bincount(where, np.einsum("ec,ec->e", ei[part], gC[i]) + ew[part] * gc[i],
                                   minlength=K * G)
            return out if groups is None else out.reshape(K, G)
        return K, summed, pullback
    weight = np.asarray(weight, dtype=float)

    def summed(w):
        nz = np.flatnonzero(w)
        return np.tensordot(w[nz], info[nz], axes=1), w[nz] @ weight[nz]

    def pullback(gC, gc, groups=None):
        if groups is None:
            return np.tensordot(info, np.asarray(gC), axes=([1, 2], [0, 1])) + weight @ np.asarray(gc)
        return np.stack([pullback(np.asarray(gC) * (groups == b)[:, None], np.asarray(gc) * (groups == b))
                         for b in range(int(np.max(groups)) + 1)], 1)
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


@dataclass(frozen=True)
class Node:
    """The branching rules of a node of the branch and bound (`vdo.design.branch.search`): `out` (K,) bool, the
    candidates none of its selections holds (None: none), `into` the groups (index arrays) in
    each of which its selections hold at least one camera, `between` (group, lo, hi): between lo
    and hi cameras of the group (the candidates that see one sample, `vdo.design.branch.Views`;
    a class of candidates, `vdo.design.branch.classes`), and `floor` (sample, value): that
    sample's term of the score is at least value in every selection of the node
    (`vdo.design.branch.Views.alone`)."""

    out: np.ndarray | None = None
    into: tuple = ()
    between: tuple = ()
    floor: tuple = ()

    def limits(self, k: int) -> list:
        """Every group rule as (group, lo, hi): `into`'s as (group, 1, k), then `between`."""
        return [(np.asarray(q, dtype=int), 1, k) for q in self.into] + \
            [(np.asarray(q, dtype=int), lo, hi) for q, lo, hi in self.between]

    def keeps(self, selection, k: int) -> bool:
        """Whether a selection (indices) keeps the node's rules."""
        v = np.asarray(selection, dtype=int)
        return (self.out is None or not self.out[v].any()) and \
            all(lo <= np.isin(v, q).sum() <= hi for q, lo, hi in self.limits(k))


class Rules:
    """The pairwise rules of a selection over the candidates asked so far (`held`), for the linear
    step over the selections that keep them: conflicts(j) (K,) bool, True where a candidate may
    not join a selection holding j; a pair conflicts when each says so of the other (a selection
    adds its cameras in some order). Every clique of that graph holds at most one camera of a
    selection (`cliques`); a candidate not held keeps the body counts alone."""

    def __init__(self, conflicts: Callable, k: int, allowed: np.ndarray, body: np.ndarray,
                 counts: np.ndarray):
        self.conflicts, self.k, self.allowed, self.body, self.counts = conflicts, k, allowed, body, counts
        self._rows: list[np.ndarray] = []
        # (held candidates, the cliques among them as positions in that array), replaced whole so
        # that a linear step in another thread (`vdo.design.branch.search`) reads a matching pair
        self._state: tuple[np.ndarray, list[np.ndarray]] = (np.zeros(0, dtype=int), [])
        self._lock = threading.Lock()

    @property
    def held(self) -> np.ndarray:
        """The candidates whose rules are held, in the order they were added."""
        return self._state[0]

    def hold(self, candidates, deadline: float) -> None:
        """Adds the rules of `candidates` (indices, in that order; those not allowed are left
        out) until the deadline (time.perf_counter()) passes: holding fewer keeps the bound valid.
        One thread at a time."""
        with self._lock:
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
            now = np.concatenate([self.held, new[:len(rows)]]).astype(int)
            among = np.array([r[now] for r in self._rows])
            adjacent = among & among.T
            np.fill_diagonal(adjacent, False)
            self._state = (now, cliques(adjacent))

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
            held, clique = self._state
            free = self.allowed.copy()
            if node.out is not None:
                free &= ~node.out
            usable = free[held]          # held candidates a node's branching leaves out: 0
            free[held] = False
            rest = np.flatnonzero(free)
            inside = np.zeros((len(rest), len(into)), bool)   # which groups each is in
            for q, group in enumerate(into):
                inside[:, q] = np.isin(rest, group)
            # the candidates that enter the same rows (groups and body kind): the lowest-g
            # min(count, k) of each
            key = _alike(inside) * len(counts) + body[rest]
            order = np.lexsort((g[rest], key))            # by rows and body kind, then by g
            ranked, place = key[order], np.arange(len(order))
            rank = place - np.maximum.accumulate(np.where(np.r_[True, ranked[1:] != ranked[:-1]], place, 0))
            extra = rest[order[rank < np.minimum(np.asarray(counts)[body[rest[order]]], k)]]
            V = np.concatenate([held, extra]).astype(int)
            rows = [np.arange(len(V))] + [np.flatnonzero(body[V] == b) for b in range(len(counts))] + \
                clique + [np.flatnonzero(np.isin(V, group)) for group in into]
            A = scipy.sparse.csr_matrix((np.ones(sum(len(r) for r in rows)),
                                         (np.repeat(np.arange(len(rows)), [len(r) for r in rows]),
                                          np.concatenate(rows))), shape=(len(rows), len(V)))
            top = np.concatenate([[k], counts, np.ones(len(clique)), [hi for _, _, hi in limits]])
            low_rows = np.concatenate([[k], np.zeros(len(counts) + len(clique)), [lo for _, lo, _ in limits]])
            upper = np.concatenate([usable, np.ones(len(V) - len(held), bool)]).astype(float)
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
            new = np.setdiff1d(taken, held)
            if not len(new):
                return taken, low
            self.hold(new, deadline)
            if not np.isin(new, self.held).any():     # the deadline passed before any was held
                return None, low


def _alike(inside: np.ndarray) -> np.ndarray:
    """(R,) one label per distinct row of `inside` (R, Q) bool: the rows packed into 64-bit words
    and sorted as integers (np.unique over bool rows compares them as bytes, 80 of the 220 ms
    of a linear step of the steel beam's tree)."""
    if inside.shape[1] == 0:
        return np.zeros(len(inside), dtype=int)
    packed = np.packbits(inside, axis=1)
    words = np.ascontiguousarray(np.pad(packed, ((0, 0), (0, -packed.shape[1] % 8)))).view(np.uint64)
    order = np.lexsort(words.T[::-1])
    ranked = words[order]
    step = np.r_[True, (ranked[1:] != ranked[:-1]).any(axis=1)]
    label = np.empty(len(words), dtype=int)
    label[order] = np.cumsum(step) - 1
    return label


def descend(both, only, summed, pullback, x, k, allowed, body, counts, deadline, rel_tol, max_iter):
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
    """The state of the fully corrective Frank-Wolfe over a hull (`corrective`): best: f at the best
    iterate in the hull (inf: none), best_x that iterate (None: none), bound the best
    certificate, steps made; chosen the selections of the last iterate and lam their weights
    (summing to 1), x that iterate (K,); above: it stopped because the bound reached
    `stop_above` before the best iterate and the bound agreed (a branch and bound node's hull,
    to be tightened later from this state, `vdo.design.branch.search`)."""

    best: float
    best_x: np.ndarray | None
    bound: float
    steps: int
    chosen: list
    lam: np.ndarray
    x: np.ndarray
    above: bool = False


def corrective(both, only, summed, pullback, rules: Rules, point, start, bound, deadline, inner_s,
          rel_tol, max_iter, node: Node | None = None, stop_above: float = np.inf,
               stop: Callable[[], bool] | None = None) -> Hull:
    """Fully corrective Frank-Wolfe over the hull of the selections that keep `rules` (and the
    `node`'s branching rules; module docstring): the certificate at `point` (the first phase's
    best iterate, of P, or a parent node's iterate), then at each iterate, a convex combination
    of the selections found by `Rules.vertex` (and `start`: a list of (selection, weight) that
    keep the rules, or one selection, or None), its weights re-optimised over them all after each
    new one (`descend` over their simplex, inner_s seconds at most); `bound` the certificate
    so far. Stops when the best iterate and the certificate agree to rel_tol, the certificate
    reaches `stop_above`, no selection keeps the rules (the certificate is then inf) or at the
    deadline or once `stop()` is True; the oracle may run inner_s past the deadline, so that the
    last iterate is certified."""
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
    best, best_x, steps, above = np.inf, None, 0, False
    while steps < max_iter:
        steps += 1
        fx, (gC, gc) = both(*C)
        fx = float(fx)
        g = pullback(gC, gc)
        s, low = rules.vertex(g, min(max(deadline - time.perf_counter(), inner_s), LINEAR_S), node)
        bound = max(bound, fx + low - float(g @ x))
        if inside and fx < best:
            best, best_x = fx, x
        if best - bound <= rel_tol * abs(bound) or s is None or time.perf_counter() > deadline \
                or (stop is not None and stop()):
            break
        if bound >= stop_above:
            above = True
            break
        if not any(np.array_equal(s, v) for v in chosen):
            lam = add(s, 0.0 if lam.size else 1.0)
        m = len(chosen)          # the weights of the selections: the same descent over a simplex
        _, inner_sum, inner_pull = linear_maps(np.stack([c for c, _ in sums]), np.stack([c for _, c in sums]))
        _, lam, _, _ = descend(both, only, inner_sum, inner_pull, lam, 1, np.ones(m, bool), np.zeros(m, int),
                                np.ones(1, int), min(deadline, time.perf_counter() + inner_s),
                                INNER_TOL * rel_tol, max_iter)
        keep = np.flatnonzero(lam > 0)     # the projection clips unused selections to 0
        chosen, sums, lam = [chosen[i] for i in keep], [sums[i] for i in keep], lam[keep]
        x = np.zeros(K)
        for weight, v in zip(lam, chosen):
            x[v] += weight
        C, inside = tuple(sum(w * c[part] for w, c in zip(lam, sums)) for part in (0, 1)), True
    return Hull(best, best_x, bound, steps, chosen, lam, x, above)
