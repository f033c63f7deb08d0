"""`vdo validate`'s verdict on each measured/predicted ratio (`vdo.dic.validate`): its interval
from the seed count, at a confidence held jointly over the run's ratios (Bonferroni), against the
requirement `BAND`: "within", "outside" (the run fails) or "inconclusive" (too few seeds to tell,
with the seeds that would decide it)."""

from __future__ import annotations

from vdo.core.stats import sd_ratio_band

BAND = (0.8, 1.25)       # the requirement on every ratio (`verdict`, `ValidationResult.passed`)
CONFIDENCE = 0.95        # each row's interval (ratio_ci95_*), and the run's joint level (`judge`)
SEEDS_HINT_MAX = 10 ** 7  # `seeds_to_decide` searches no further (a ratio on a band edge never decides)
VERDICTS = ("outside", "inconclusive", "within")


# --------------------------------------------------------------------------------------------
def ratio_interval(ratio: float, seeds: int, confidence: float = CONFIDENCE,
                   ratios: int = 1) -> tuple[float, float]:
    """The `confidence` interval of the true ratio σ/σ_e from `ratio` = s/σ_e, s the standard
    deviation (ddof 1) of n = `seeds` normal draws and σ_e the prediction (exact): s/σ lies in
    `vdo.core.stats.sd_ratio_band` [lo, hi], so

        σ/σ_e ∈ [ratio / hi,  ratio / lo]  = [ratio √((n − 1)/χ²_{n−1}(1 − α/2)), ratio √((n − 1)/χ²_{n−1}(α/2))],

    α = (1 − confidence) / `ratios`: with `ratios` = m > 1 the m intervals of a run hold their true
    ratios together with probability ≥ `confidence` (Bonferroni)."""
    lo, hi = sd_ratio_band(seeds, ratios, confidence)
    return ratio / hi, ratio / lo


def verdict(low: float, high: float) -> str:
    """A ratio's verdict from its interval [low, high] (`ratio_interval`) and `BAND` [b0, b1]:
    "within" when b0 <= low and high <= b1, "outside" when high < b0 or low > b1 (the seeds
    reject every ratio in the band), else "inconclusive" (the interval holds a band edge: the
    seeds cannot tell)."""
    if BAND[0] <= low and high <= BAND[1]:
        return "within"
    if high < BAND[0] or low > BAND[1]:
        return "outside"
    return "inconclusive"


def seeds_to_decide(ratio: float, confidence: float = CONFIDENCE, ratios: int = 1) -> int | None:
    """The fewest seeds n at which the interval about the same `ratio` (`ratio_interval`, the same
    `confidence` and `ratios`) no longer holds a band edge, i.e. its `verdict` is "within" or
    "outside"; None past SEEDS_HINT_MAX (a ratio on an edge is never decided). To first order
    the interval is ratio · exp(±z/√(2(n − 1))) (z the normal quantile of 1 − α/2), so
    n ≈ 1 + z²/(2 ln²(ratio/edge)); the χ² interval is skewed (~6 % in n at 500 seeds, far more
    at a few), so n is searched on it (doubling, then bisection: it shrinks about `ratio` as n
    grows)."""

    def decided(n: int) -> bool:
        return verdict(*ratio_interval(ratio, n, confidence, ratios)) != "inconclusive"

    high = 2
    while not decided(high):
        if high >= SEEDS_HINT_MAX:
            return None
        high *= 2
    low = high // 2           # undecided (1: no interval below 2 seeds)
    while high - low > 1:
        mid = (low + high) // 2
        low, high = (low, mid) if decided(mid) else (mid, high)
    return high


def judge(row: dict, ratios: int) -> dict:
    """`row` (one ratio of `run_case`) with the run's verdict on it: its interval at joint
    `CONFIDENCE` over the run's `ratios` ratios (`ratio_interval`; ratio_joint_low/high), its
    `verdict`, and for an inconclusive one `seeds_to_decide` (else None)."""
    low, high = ratio_interval(row["ratio"], row["n_seeds"], ratios=ratios)
    said = verdict(low, high)
    return {**row, "ratio_joint_low": low, "ratio_joint_high": high, "verdict": said,
            "seeds_to_decide": seeds_to_decide(row["ratio"], ratios=ratios)
            if said == "inconclusive" else None}
