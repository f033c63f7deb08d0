"""`vdo validate`'s verdict on each ratio, without renders: the χ² interval of a ratio of standard
deviations against scipy.stats, the three verdicts (within, inconclusive, outside) on synthetic
intervals and rows, the seeds that would decide an inconclusive ratio, and the exit status and
summary line that follow (only a ratio whose joint interval lies wholly outside [0.8, 1.25] fails
the run; docs/validation.md)."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest
from scipy import stats

from small_plate import DEFAULTS
from vdo.commands import validate as command
from vdo.commands.cli import main
from vdo.dic import validate as V
from vdo.dic import verdicts

COVERAGE_DRAWS = 4000     # Monte Carlo sets: the coverage's sampling sd is sqrt(.95 .05 / 4000) = 0.0034
COVERAGE_TOLERANCE = 0.012  # 3.5 of those sds


def row(ratio: float, seeds: int, case: str = "c", axis: str = "x") -> dict:
    """One row as `run_case` writes it, reduced to what the verdict and the table read (a
    predicted σ of 1 µm)."""
    low, high = verdicts.ratio_interval(ratio, seeds)
    return {"case": case, "axis": axis, "ratio": ratio, "n_seeds": seeds,
            "ratio_ci95_low": low, "ratio_ci95_high": high, "sigma_predicted_um": 1.0,
            "sigma_expected_um": math.sqrt(2), "sigma_measured_um": ratio * math.sqrt(2), "bias_um": 0.0}


def result(*rows: dict) -> V.ValidationResult:
    cases = tuple(V.CaseResult(rows=[r], estimates=np.zeros((r["n_seeds"], 3)), setup=None,
                               info={"noise_free_ok": True}) for r in rows)
    return V.ValidationResult(spec=None, seeds=rows[0]["n_seeds"], cases=cases, wall_seconds=1.0)


# --------------------------------------------------------------------------------------------
# The interval
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seeds", [2, 10, 200])
def test_interval_bounds_are_where_the_chi2_test_rejects(seeds):
    """Each bound is the true ratio at which the χ² statistic (n − 1) r²/ρ² of the measured ratio
    r sits at the α/2 tail (scipy.stats.chi2.sf and .cdf), α = 5 %, or α/m jointly over m."""
    r, dof = 0.9, seeds - 1
    for m in (1, 32):
        low, high = verdicts.ratio_interval(r, seeds, ratios=m)
        tail = 0.05 / m / 2
        assert stats.chi2.sf(dof * r ** 2 / low ** 2, dof) == pytest.approx(tail, rel=1e-9)
        assert stats.chi2.cdf(dof * r ** 2 / high ** 2, dof) == pytest.approx(tail, rel=1e-9)
        assert low < r < high


def test_interval_textbook_values():
    """The 95 % interval of σ from n = 10 draws is [0.688 s, 1.826 s], from n = 2 [0.446 s, 31.9 s]."""
    assert verdicts.ratio_interval(1.0, 10) == pytest.approx((0.6878, 1.8256), abs=1e-4)
    assert verdicts.ratio_interval(1.0, 2) == pytest.approx((0.44615, 31.910), rel=1e-4)
    # scaling: the interval of a ratio r is r times that of 1
    assert verdicts.ratio_interval(0.7, 10) == pytest.approx(tuple(0.7 * b for b in verdicts.ratio_interval(1.0, 10)))


def test_interval_covers_the_true_ratio_95_percent_of_the_time():
    """Normal draws with a known σ (the "prediction"): the interval of s/σ holds 1 in 95 % of
    COVERAGE_DRAWS sets of 5 draws."""
    rng = np.random.default_rng(7)
    s = rng.normal(0.0, 2.0, size=(COVERAGE_DRAWS, 5)).std(axis=1, ddof=1)
    covered = [lo <= 1.0 <= hi for lo, hi in (verdicts.ratio_interval(x / 2.0, 5) for x in s)]
    assert abs(np.mean(covered) - 0.95) < COVERAGE_TOLERANCE


# --------------------------------------------------------------------------------------------
# The verdict
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("low, high, said", [
    (0.9, 1.1, "within"),
    (0.8, 1.25, "within"),            # the band's edges belong to it
    (0.7, 1.1, "inconclusive"),       # straddles the lower edge
    (1.1, 1.3, "inconclusive"),       # straddles the upper edge
    (0.3, 22.0, "inconclusive"),      # two seeds: holds the whole band
    (0.5, 0.79, "outside"),
    (1.26, 2.0, "outside"),
])
def test_verdict_of_an_interval(low, high, said):
    assert verdicts.verdict(low, high) == said


def test_rows_are_judged_jointly_and_only_outside_fails():
    """Three rows of one run (m = 3, each interval at α = 5 %/3): ratio 1.0 from 1000 seeds is
    within, 0.69 from 2 seeds (95 % interval 0.31-22: the user's report) inconclusive, 0.3 from
    60 seeds outside."""
    run = result(row(1.0, 1000, "many"), row(0.69, 2, "two"), row(0.3, 60, "bad"))
    judged = {r["case"]: r for r in run.rows}
    assert [judged[c]["verdict"] for c in ("many", "two", "bad")] == ["within", "inconclusive", "outside"]
    assert (judged["two"]["ratio_joint_low"], judged["two"]["ratio_joint_high"]) == pytest.approx(
        verdicts.ratio_interval(0.69, 2, ratios=3))
    assert judged["two"]["ratio_joint_low"] < judged["two"]["ratio_ci95_low"]       # wider
    assert judged["many"]["seeds_to_decide"] is None and judged["bad"]["seeds_to_decide"] is None
    assert run.verdicts == {"outside": 1, "inconclusive": 1, "within": 1} and not run.passed
    assert result(row(1.0, 1000), row(0.69, 2)).passed


@pytest.mark.parametrize("ratio", [0.69, 0.95, 1.2, 1.4, 0.3])
def test_seeds_to_decide_is_the_first_count_that_decides(ratio):
    n = verdicts.seeds_to_decide(ratio, ratios=32)
    assert verdicts.verdict(*verdicts.ratio_interval(ratio, n, ratios=32)) != "inconclusive"
    assert n == 2 or verdicts.verdict(*verdicts.ratio_interval(ratio, n - 1, ratios=32)) == "inconclusive"


def test_seeds_to_decide_follows_the_1_over_sqrt_n_width():
    """At hundreds of seeds the interval is r exp(±z/√(2(n − 1))) to first order, so
    n ≈ 1 + z²/(2 ln²(r/edge)) (the χ² interval's skew moves it by ~6 % at 500 seeds)."""
    z = stats.norm.ppf(1 - 0.05 / 2)
    for ratio in (0.85, 1.2):
        edge = 0.8 if ratio < 1 else 1.25
        assert verdicts.seeds_to_decide(ratio) == pytest.approx(1 + z ** 2 / (2 * math.log(ratio / edge) ** 2),
                                                         rel=0.1)
    assert verdicts.seeds_to_decide(0.8) is None       # on an edge: never decided


# --------------------------------------------------------------------------------------------
# The command: summary line and exit status
# --------------------------------------------------------------------------------------------
TOML = """
[validation]
name = "verdicts"
seeds = 2

""" + DEFAULTS + """
[[case]]
name = "stereo"
cameras = [{name = "left", polar_deg = 12.5, azimuth_deg = 180}, {name = "right", polar_deg = 12.5, azimuth_deg = 0}]
"""


@pytest.mark.parametrize("rows, status, counts", [
    ([row(0.69, 2), row(1.83, 2), row(1.0, 2)], 0, "0 OUTSIDE, 3 INCONCLUSIVE"),
    ([row(0.69, 2), row(0.2, 100)], 1, "1 OUTSIDE, 1 INCONCLUSIVE"),
    ([row(1.0, 2000)], 0, "0 OUTSIDE, 0 INCONCLUSIVE, 1 within"),
])
def test_exit_status_and_summary_line(rows, status, counts, tmp_path, monkeypatch, capsys):
    """The run fails (status 1) only on a ratio outside; the line counts every verdict and, with
    inconclusive ratios, says how many seeds would decide them."""
    path = tmp_path / "validation.toml"
    path.write_text(textwrap.dedent(TOML))
    run = result(*rows)

    def fake(spec, out, seeds=None, overwrite=False, cases=None):
        return {"rows": run.rows, "verdicts": run.verdicts, "passed": run.passed,
                "noise_free_passed": True, "wall_seconds": 1.0}

    monkeypatch.setattr(command, "validate_cases", fake)
    assert main(["validate", str(path), "--out", str(tmp_path / "run"), "--seeds", "2"]) == status
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert f"at 95% joint confidence: {counts}" in last
    opened = [r for r in run.rows if r["verdict"] == "inconclusive"]
    if opened:
        needed = sorted(command.round_up(r["seeds_to_decide"]) for r in opened)
        spread = str(needed[0]) if needed[0] == needed[-1] else f"{needed[0]}-{needed[-1]}"
        assert f"~{spread} seeds would decide" in last
        assert f"--seeds {verdicts.seeds_to_decide(1.0, ratios=len(rows))} shows a ratio of 1 within" in last
    else:
        assert "seeds" not in last
