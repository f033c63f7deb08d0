"""The chance scatter of a sample standard deviation: the one interval `vdo calibrate`'s Monte
Carlo check and `vdo validate`'s verdicts both read."""

from __future__ import annotations

import math


def sd_ratio_band(draws: int, ratios: int = 1, confidence: float = 0.95) -> tuple[float, float]:
    """The interval [lo, hi] that holds s / σ, s the sample standard deviation (ddof 1) of
    `draws` = n independent normal draws of standard deviation σ, with probability `confidence`
    for each of `ratios` = m such ratios at once (Bonferroni): (n − 1) s²/σ² follows χ²_{n−1}, so

        lo = √(χ²_{n−1}(q) / (n − 1)),  hi = √(χ²_{n−1}(1 − q) / (n − 1)),  q = (1 − confidence) / 2m.

    At 200 draws and m = 1: [0.90, 1.10]."""
    from scipy.stats import chi2

    dof, q = draws - 1, (1 - confidence) / 2 / ratios
    return math.sqrt(chi2.ppf(q, dof) / dof), math.sqrt(chi2.ppf(1 - q, dof) / dof)
