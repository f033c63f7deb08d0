"""`vdo design`'s random restarts against exhaustive search: the shipped holed plate's design
problem (215 candidates on a rail and tripods, two cameras), where greedy selection and exchange
passes stop at a local minimum of single swaps; and Ctrl-C in its branch and bound, which ends
the search and still returns the best layout met."""

from __future__ import annotations

import math

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from vdo.config.experiment import load
from vdo.design.candidates import judge, judging
from vdo.design.feasibility import Feasibility
from vdo.design.score import Scorer
from vdo.design.moves import RESTART_PATIENCE, exchange, greedy, restarts
from vdo.state import prepare

ROOT = Path(__file__).resolve().parents[2]
SAME_SCORE_RTOL = 1e-9      # mirror-image pairs score the same to float64 rounding
LOCAL_MINIMUM = 1.2         # greedy + exchange end this much above the best pair (measured: 1.57x)
TREE_SPACING_MM = 8         # the branch and bound's test: design samples every 8 mm (the file's 5):
                            # 315 samples, greedy + exchange still 1.15x above the best pair


def plate(spacing_mm: float | None = None):
    """The shipped holed plate's design problem, at its own design sample spacing or `spacing_mm`:
    (experiment, candidates, scorer, feasibility)."""
    exp = load(ROOT / "experiments" / "holed_plate" / "design.toml")
    if spacing_mm is not None:
        exp = replace(exp, design=replace(exp.design, sample_spacing=spacing_mm * 1e-3))
    coarse = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=exp.design.sample_spacing)))
    cand = judge(exp, coarse, judging(exp, coarse))
    return exp, cand, Scorer(exp, coarse.samples), Feasibility(exp, cand, coarse.samples)


@pytest.fixture(scope="module")
def plate_design():
    return plate()[1:]


@pytest.fixture(scope="module")
def coarse_plate():
    return plate(TREE_SPACING_MM)


def exhaustive_best_pair(cand, scorer, feas):
    """The lowest score of every feasible pair: each allowed first camera with every camera
    allowed beside it (scored together in one `Scorer.add`)."""
    best, pair = np.inf, None
    for i in np.flatnonzero(feas.allowed([])):
        ok = np.flatnonzero(feas.allowed([int(i)]))
        ok = ok[ok > i]
        if ok.size:
            s = scorer.add(*cand.sums([int(i)]), cand, ok)
            j = int(np.argmin(s))
            if s[j] < best:
                best, pair = float(s[j]), (int(i), int(ok[j]))
    return best, pair


def test_restarts_leave_the_local_minimum_and_reach_the_best_pair(plate_design):
    cand, scorer, feas = plate_design
    best, pair = exhaustive_best_pair(cand, scorer, feas)
    order, _ = greedy(cand, scorer, feas, 2)
    _, local, _ = exchange(cand, scorer, feas, order)
    assert local > LOCAL_MINIMUM * best          # the single-swap search alone is stuck
    t0 = time.perf_counter()
    chosen, score, starts = restarts(cand, scorer, feas, None, 2, 120.0, np.random.default_rng(0))
    assert score == pytest.approx(best, rel=SAME_SCORE_RTOL), (chosen, pair)
    assert scorer.of(cand, chosen) == pytest.approx(score, rel=SAME_SCORE_RTOL)
    assert not feas.conflicts(*chosen) and feas.alone[chosen].all()
    # nothing better to find: RESTART_PATIENCE fruitless starts end it long before its 120 s
    assert starts >= RESTART_PATIENCE and time.perf_counter() - t0 < 60


@pytest.mark.parametrize("outer_on", [False, True])
def test_the_branch_and_bounds_best_selection_is_a_start_and_closes_the_gap(coarse_plate, monkeypatch, outer_on):
    """With the restarts off, `vdo design` on the holed plate (design samples every
    TREE_SPACING_MM) still writes the best pair of the
    exhaustive search: its branch and bound closes on it (the bound is its score within
    REL_TOL; about 20 s with XLA's optimisations off). With the outer approximation off,
    the best selection the tree met replaces the count's (greedy, exchange and the rounding stop
    above it), said as "branched" in the curve; as shipped, the outer approximation's selection
    (`vdo.design.outer`) is that pair already ("outer")."""
    from vdo.core.configure import configure
    from vdo.design import bound, outer
    from vdo.design.select import design_layout
    configure()
    if not outer_on:
        monkeypatch.setattr(outer, "search", lambda *a, **k: outer.Outcome(None, math.inf, -math.inf, 0))
    exp, cand, scorer, feas = coarse_plate
    best, pair = exhaustive_best_pair(cand, scorer, feas)
    result = design_layout(replace(exp, design=replace(exp.design, restart_seconds=0.0)))
    top = result.curve[-1]
    assert top["cameras"] == 2 and not top.get("restarted")
    assert top["outer"] if outer_on else (top["branched"] and not top["outer"])
    assert top["score"] == pytest.approx(best, rel=SAME_SCORE_RTOL)
    assert scorer.of(cand, top["chosen"]) == pytest.approx(best, rel=SAME_SCORE_RTOL)
    assert best * (1 - bound.REL_TOL) <= top["bound"] <= best * (1 + 1e-12)


def test_ctrl_c_in_the_branch_and_bound_writes_the_best_layout_so_far(coarse_plate, monkeypatch):
    """SIGINT while the branch and bound makes its first children (`vdo.design.branch.search`,
    an hour of it would be lost otherwise): the tree ends after that split, the outer
    approximation and the restarts (300 s asked) are not started, and `design_layout` still
    judges and returns the best layout met (the rounding's and the tree's selections tried),
    its bound still below the exhaustive best pair and the interruption named among its
    problems."""
    import os
    import signal

    from vdo.core.configure import configure
    from vdo.design import branch
    from vdo.design.select import design_layout
    configure()
    exp, cand, scorer, feas = coarse_plate
    best, _ = exhaustive_best_pair(cand, scorer, feas)
    real, sent = branch.corrective, []

    def corrective(*args, **kwargs):
        if not sent:
            sent.append(time.perf_counter())
            os.kill(os.getpid(), signal.SIGINT)
        return real(*args, **kwargs)
    monkeypatch.setattr(branch, "corrective", corrective)
    result = design_layout(replace(exp, design=replace(exp.design, restart_seconds=300.0, branch_seconds=600.0)))
    top = result.curve[-1]
    assert sent and time.perf_counter() - sent[0] < 60
    assert any("interrupted" in p for p in result.problems)
    assert top["bound_nodes"] <= 1 + branch.SPLIT_SAMPLES + 1       # the root and one split's children
    assert "restarts" not in top and not top.get("outer")
    assert top["bound"] <= best * (1 + 1e-12) <= top["score"] * (1 + 1e-12)
