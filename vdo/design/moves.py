"""Searching the selections of k candidates (`vdo design`): moves on a candidate set, scored by
`vdo.design.score.Scorer` under the rules of `vdo.design.feasibility.Feasibility`.

* `greedy`: forward selection, the candidate of lowest score added while one is feasible;
* `exchange`: swap passes (`swap_options` per slot), one selected camera replaced by the best feasible candidate while
  the score drops (a local minimum of single swaps);
* `rounded`: a start from the relaxation's weights (`vdo.design.bound`);
* `restarts`: random starts drawn from those weights, each taken down by exchange passes over a
  pool of candidates.

`vdo.design.select` runs them per camera count, with the polish and the judgement."""

from __future__ import annotations

import logging
import math
import time
from typing import Callable

import numpy as np

from vdo.core.progress import bar
from vdo.design.candidates import Candidates
from vdo.design.feasibility import Feasibility
from vdo.design.score import Scorer

log = logging.getLogger(__name__)

_clock = time.perf_counter      # the restarts' clock

ROUNDING_RTOL = 1e-6        # the relaxation's rounded start replaces a count's selection when it scores this much lower
RESTART_SPREAD = 0.1        # share of a restart's draw spread evenly over the candidates (the rest
                            # follows the relaxation's weights): starts away from the relaxation too
RESTART_SEED = 0            # the restarts' random stream (a design is repeatable)
RESTART_PATIENCE = 16       # the restarts stop after this many starts in a row find nothing better
RESTART_POOL = 1024         # candidates a restart's exchange passes choose from (drawn as its start;
                            # the best restart's selection is then exchanged over all candidates)


def greedy(cand: Candidates, scorer: Scorer, feas: Feasibility, n: int,
           start=()) -> tuple[list[int], list[float]]:
    """Forward selection up to n cameras from `start`: the chosen indices and the score after
    each addition (stops early when no feasible candidate is left); a progress bar when the module
    logger passes INFO."""
    chosen, scores = list(start), []
    for _ in bar(log, iterable=range(n - len(chosen)), desc="greedy", leave=False):
        ok = np.flatnonzero(feas.allowed(chosen))
        if ok.size == 0:
            break
        s = scorer.add(*cand.sums(chosen), cand, ok)
        best = int(np.argmin(s))
        chosen.append(int(ok[best]))
        scores.append(float(s[best]))
    return chosen, scores


def swap_options(feas: Feasibility, chosen: list, pool: np.ndarray | None = None):
    """For each slot of `chosen` (a list the caller may change between slots): (slot, the other
    selected cameras, the feasible candidates with them that are not selected, of `pool` (indices)
    when given); slots with none are skipped."""
    for slot in range(len(chosen)):
        rest = chosen[:slot] + chosen[slot + 1:]
        ok = np.flatnonzero(feas.allowed(rest))
        ok = ok[~np.isin(ok, chosen)]
        if pool is not None:
            ok = ok[np.isin(ok, pool)]
        if ok.size:
            yield slot, rest, ok


def exchange(cand: Candidates, scorer: Scorer, feas: Feasibility, chosen, max_passes: int = 5,
             rtol: float = 1e-6, pool: np.ndarray | None = None) -> tuple[list[int], float, int]:
    """Swap passes: replace one selected camera by the best feasible candidate (of `pool`, indices,
    when given) while the score drops by more than rtol (relative). Returns (chosen, score, swaps
    made)."""
    chosen = list(chosen)
    current, swaps = scorer.of(cand, chosen), 0
    for _ in range(max_passes):
        improved = False
        for slot, rest, ok in swap_options(feas, chosen, pool):
            s = scorer.add(*cand.sums(rest), cand, ok)
            best = int(np.argmin(s))
            if s[best] < current * (1 - rtol):
                chosen[slot], current = int(ok[best]), float(s[best])
                swaps, improved = swaps + 1, True
        if not improved:
            break
    return chosen, current, swaps


def rounded(cand: Candidates, scorer: Scorer, feas: Feasibility, weights: np.ndarray,
            k: int) -> list[int]:
    """A feasible selection of k cameras from the relaxation's weights (`vdo.design.bound.Bound`):
    the candidates by decreasing weight, each taken while it is feasible with those taken, then
    `greedy` to k when the weighted ones run out."""
    chosen: list[int] = []
    for i in np.argsort(-np.asarray(weights)):
        if len(chosen) == k or weights[i] <= 0:
            break
        if feas.allowed(chosen)[i]:
            chosen.append(int(i))
    if len(chosen) < k:
        chosen, _ = greedy(cand, scorer, feas, k, start=chosen)
    return chosen


def restarts(cand: Candidates, scorer: Scorer, feas: Feasibility, weights: np.ndarray | None,
             k: int, seconds: float, rng: np.random.Generator,
             stop: Callable[[], bool] | None = None) -> tuple[list[int], float, int]:
    """Random restarts for k cameras for about `seconds` (at least one start; fewer when
    RESTART_PATIENCE starts in a row find nothing better than the best so far): each start draws
    feasible candidates one at a time, candidate i (not yet drawn, feasible with those drawn)
    with probability proportional to (1 - RESTART_SPREAD) w_i / sum(w) + RESTART_SPREAD / K
    (w: the relaxation's weights; uniform without them; K candidates), up to k (`greedy` fills
    the rest when the draws run out of feasible candidates), then `exchange` to a local minimum
    of single swaps among RESTART_POOL candidates drawn the same way (a pass over all of them
    costs K / RESTART_POOL times as much); no start after `stop()` is True. Returns the best
    (chosen, score) and the number of starts; the caller exchanges the best over all candidates."""
    K = len(cand.cameras)
    w = np.zeros(K) if weights is None else np.clip(np.asarray(weights, dtype=float), 0.0, None)
    p = (1.0 - RESTART_SPREAD) * w / w.sum() + RESTART_SPREAD / K if w.sum() > 0 else np.full(K, 1.0 / K)
    best, best_score, starts, since = [], math.inf, 0, 0
    until = _clock() + seconds
    while starts == 0 or (_clock() < until and since < RESTART_PATIENCE and not (stop is not None and stop())):
        starts, since = starts + 1, since + 1
        chosen: list[int] = []
        while len(chosen) < k:
            q = np.where(feas.allowed(chosen), p, 0.0)
            q[chosen] = 0.0
            if q.sum() <= 0:
                break
            chosen.append(int(rng.choice(K, p=q / q.sum())))
        if len(chosen) < k:
            chosen, _ = greedy(cand, scorer, feas, k, start=chosen)
        pool = rng.choice(K, size=min(K, RESTART_POOL), replace=False, p=p)
        chosen, score, _ = exchange(cand, scorer, feas, chosen, pool=np.union1d(pool, chosen))
        if score < best_score * (1 - ROUNDING_RTOL):
            best, best_score, since = chosen, score, 0
    return best, best_score, starts
