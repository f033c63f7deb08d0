"""The polish of a selection on the figure the camera-count curve reports (`polish`): each scored
region's σ_max p95 over its samples seen by two usable views or more, the worst of them, and the
area seen by min_cameras (`Figures`, `figures`), from the candidates' stored sums.

The selection's score is smooth and averages over samples; the worst region's p95 is what a user
reads, and two selections the score rates nearly equal can differ by a third in it (the steel
beam: 0.398 -> 0.279 µm). So after the exchange passes (`vdo.design.moves.exchange`) the curve's
selections go through swap passes on that figure that keep the area seen by min_cameras
(`vdo.design.select` keeps the polished layout when its judgement reads no worse)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vdo.core.tolerances import LIMIT_SLACK
from vdo.design.candidates import Candidates
from vdo.design.feasibility import Feasibility
from vdo.design.moves import swap_options
from vdo.design.score import Scorer

POLISH_SHORTLIST = 128      # candidates per slot that the polish judges: those of lowest score
POLISH_BLOCK = 16           # candidates whose (N, 6) sums are formed together in the polish
POLISH_PASSES = 3           # most passes over the slots
POLISH_RTOL = 1e-3          # a polish swap lowers the worst region's p95 by more than this (relative)
POLISH_PERCENTILE = 95.0    # the curve's figure: each region's σ_max p95


@dataclass(frozen=True)
class Figures:
    """What the curve reports of a selection, from the candidates' sums (bodies not judged):
    `worst_p95` the worst scored region's σ_max p95 in units of sigma_unit over its samples
    seen by ≥ 2 usable views (inf where a scored region has none) and `coverage` the area
    fraction seen by its region's min_cameras usable views."""

    worst_p95: np.ndarray
    coverage: np.ndarray


def region_table(region: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(R, L) int: the indices of the samples where `keep`, one row per region that has any (in
    region order), padded with -1 to the longest row L."""
    idx = np.flatnonzero(keep)
    names, counts = np.unique(region[idx], return_counts=True)
    table = np.full((len(names), counts.max() if len(names) else 0), -1)
    order = idx[np.argsort(region[idx], kind="stable")]
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for r, (first, n) in enumerate(zip(start, counts)):
        table[r, :n] = order[first:first + n]
    return table


def percentile_by_region(values: np.ndarray, table: np.ndarray, q: float) -> np.ndarray:
    """(M, R) the q-th percentile of `values` (M, N) over each row of `table` (`region_table`),
    NaN values ignored (numpy's linear interpolation between order statistics, index
    q / 100 (n - 1) among the n finite ones); NaN where a region has none. One sort of an
    (M, R, L) array instead of a percentile call per region."""
    v = np.sort(np.where(table >= 0, values[:, np.maximum(table, 0)], np.nan), axis=2)  # NaN last
    n = np.sum(~np.isnan(v), axis=2)
    pos = q / 100.0 * np.maximum(n - 1, 0)
    lo = np.floor(pos).astype(int)
    hi = np.minimum(lo + 1, np.maximum(n - 1, 0))
    a = np.take_along_axis(v, lo[..., None], 2)[..., 0]
    b = np.take_along_axis(v, hi[..., None], 2)[..., 0]
    return np.where(n > 0, a + (pos - lo) * (b - a), np.nan)


def figures(cand: Candidates, scorer: Scorer, samples, rest, rows) -> Figures:
    """`Figures` (M,) of the selections `rest` + each candidate of `rows` (M,): the sums of
    `rest` plus one candidate's stored entries, σ from `Scorer.sigma`, POLISH_BLOCK candidates
    at a time."""
    info0, _ = cand.sums(rest)
    count0, use = cand.usable_sums(rest), cand.usable_entries
    table = region_table(samples.region, scorer.omega > 0)
    need, area = scorer.minimum, scorer.area
    rows = np.asarray(rows, dtype=int)
    worst, coverage = np.empty(len(rows)), np.empty(len(rows))
    for s in range(0, len(rows), POLISH_BLOCK):
        part = rows[s:s + POLISH_BLOCK]
        info = np.broadcast_to(info0, (len(part),) + info0.shape).copy()
        count = np.broadcast_to(count0, (len(part), cand.samples)).copy()
        for k, i in enumerate(part):
            e = slice(cand.indptr[i], cand.indptr[i + 1])
            info[k, cand.index[e]] += cand.entry_info[e]
            count[k, cand.index[e]] += use[e]
        sigma = scorer.sigma(info.reshape(-1, 6)).reshape(len(part), -1)
        p95 = percentile_by_region(np.where(count >= 2, sigma, np.nan), table, POLISH_PERCENTILE)
        worst[s:s + len(part)] = np.where(np.isnan(p95).any(1), np.inf,    # a region unmeasured: inf
                                          np.max(np.where(np.isnan(p95), -np.inf, p95), 1))
        coverage[s:s + len(part)] = (area * (count >= need)).sum(1)
    return Figures(worst, coverage)


def polish(cand: Candidates, scorer: Scorer, feas: Feasibility, samples, chosen,
           rtol: float = POLISH_RTOL) -> tuple[list[int], int]:
    """Swap passes on the figures the curve reports (`Figures`), after `exchange`: replace one
    selected camera by a feasible candidate when that lowers the worst scored region's σ_max
    p95 by more than `rtol` (relative) without lowering the area seen by min_cameras. The score
    is smooth and averages over samples; the worst region's p95 is what a user reads, and a
    swap that the score rates equal can halve it. Per slot the POLISH_SHORTLIST candidates of
    lowest score are judged. Returns (chosen, swaps made)."""
    chosen, swaps = list(chosen), 0
    here = figures(cand, scorer, samples, chosen[1:], chosen[:1])
    worst, cover = float(here.worst_p95[0]), float(here.coverage[0])
    for _ in range(POLISH_PASSES):
        improved = False
        for slot, rest, ok in swap_options(feas, chosen):
            top = ok[np.argsort(scorer.add(*cand.sums(rest), cand, ok))[:POLISH_SHORTLIST]]
            f = figures(cand, scorer, samples, rest, top)
            better = (f.coverage >= cover - LIMIT_SLACK) & (f.worst_p95 < worst * (1 - rtol))
            if better.any():
                k = int(np.argmin(np.where(better, f.worst_p95, np.inf)))
                chosen[slot], worst, cover = int(top[k]), float(f.worst_p95[k]), float(f.coverage[k])
                swaps, improved = swaps + 1, True
        if not improved:
            break
    return chosen, swaps
