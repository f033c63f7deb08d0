"""The design bound (`vdo.design.bound`): its linear step against scipy's linprog, its projection
against scipy's SLSQP, the certified bound against a closed-form relaxed optimum and against
exhaustive enumeration of every selection on a plate's candidates (two body kinds), the relaxed
optimum against scipy's SLSQP with finite differences, and `vdo design`'s outputs."""

from __future__ import annotations

import csv
import itertools
import json
from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog, minimize

from vdo.config import experiment as config
from vdo.design import bound, hull
from vdo.commands.design import design as design_run
from vdo.design.candidates import judge
from vdo.design.feasibility import Feasibility
from vdo.design.score import Scorer
from vdo.design.moves import exchange, greedy
from vdo.state import prepare

# scipy's SLSQP stops at ftol 1e-12 on these small problems; its solution agrees to about this
SLSQP_TOL = 1e-5

PLATE_DESIGN = """
[[light]]
name = "panel"
position_m = [0.3, 0.0, 1.2]
target_m = [0.0, 0.0, 0.0]
size_m = [0.6, 0.6]
radiance = 60.0

[[body]]
name = "small"
sensor_mm = [22.2, 14.8]
pixels = [300, 200]
count = 1

[[body]]
name = "large"
sensor_mm = [22.2, 14.8]
pixels = [1200, 800]
count = 2

[design]
rail_positions = 9
offset_m = [0, 0, 0]
sample_spacing_mm = 50
keyframes = 0
"""


def _polytope(rng, K=12, B=2):
    allowed = rng.random(K) > 0.2
    body = rng.integers(0, B, K)
    counts = np.array([2, 3])
    return allowed, body, counts


def _constraints(allowed, body, counts, k):
    """P as scipy constraints: sum = k, per body sum <= count, bounds [0, 1] (0 where not allowed)."""
    cons = [{"type": "eq", "fun": lambda w: w.sum() - k}]
    for b, c in enumerate(counts):
        cons.append({"type": "ineq", "fun": lambda w, b=b, c=c: c - w[body == b].sum()})
    return cons, [(0, 1) if a else (0, 0) for a in allowed]


def test_the_linear_step_is_linprogs_optimum():
    rng = np.random.default_rng(1)
    allowed, body, counts = _polytope(rng)
    for k in (1, 3, 5):
        g = rng.normal(size=len(body))
        s = hull.vertex(g, k, allowed, body, counts)
        A = np.array([(body == b).astype(float) for b in range(len(counts))])
        lp = linprog(g, A_ub=A, b_ub=counts, A_eq=np.ones((1, len(g))), b_eq=[k],
                     bounds=[(0, 1) if a else (0, 0) for a in allowed])
        assert lp.status == 0
        assert g @ s == pytest.approx(lp.fun, abs=1e-9)
        assert s.sum() == k and set(np.unique(s)) <= {0.0, 1.0}
        assert np.all(s[~allowed] == 0)
        assert all(s[body == b].sum() <= c for b, c in enumerate(counts))


def test_the_projection_is_slsqps():
    rng = np.random.default_rng(2)
    allowed, body, counts = _polytope(rng)
    for k in (2, 4):
        v = rng.normal(scale=0.8, size=len(body)) + 0.4
        w = hull.project(v, k, allowed, body, counts)
        cons, box = _constraints(allowed, body, counts, k)
        ref = minimize(lambda x: 0.5 * ((x - v) ** 2).sum(), np.full(len(v), 0.0), jac=lambda x: x - v,
                       bounds=box, constraints=cons, method="SLSQP", options={"ftol": 1e-14})
        assert ref.success
        np.testing.assert_allclose(w, ref.x, atol=SLSQP_TOL)


def test_the_bound_meets_the_closed_form_optimum():
    """One sample, three candidates each informing one axis with the same magnitude a, the value
    tr (C + e I)^-1 (A-optimality, convex): by symmetry and convexity the relaxed optimum puts
    k/3 on each, value 3 / (a k / 3 + e). The certified bound lies below it and within REL_TOL."""
    a, e = 4.0, 0.5
    info = np.zeros((3, 1, 6))
    info[[0, 1, 2], 0, [0, 1, 2]] = a
    weight = np.ones((3, 1))

    def value(C, cover):
        M = jnp.array([[C[0, 0], C[0, 3], C[0, 4]], [C[0, 3], C[0, 1], C[0, 5]],
                       [C[0, 4], C[0, 5], C[0, 2]]]) + e * jnp.eye(3)
        return jnp.trace(jnp.linalg.inv(M)) + 0.0 * cover.sum()

    for k in (1, 2):
        b = bound.relaxation(value, info, weight, k, np.ones(3, bool), np.zeros(3, int),
                             np.array([3]), start=list(range(k)))
        exact = 3.0 / (a * k / 3.0 + e)
        assert b.converged
        assert b.value <= exact + 1e-12
        assert b.relaxed >= exact - 1e-12
        assert b.value == pytest.approx(exact, rel=bound.REL_TOL)
        np.testing.assert_allclose(b.weights, k / 3.0, atol=1e-2)


@pytest.fixture(scope="module")
def plate(tmp_path_factory):
    from conftest import write_plate_experiment

    path = write_plate_experiment(tmp_path_factory.mktemp("plate"), spacing=50)
    path.write_text(path.read_text() + PLATE_DESIGN)
    exp = config.load(path)
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    return exp, geometry, cand, Scorer(exp, geometry.samples), Feasibility(exp, cand)


@pytest.mark.parametrize("k, aimed", [(2, False), (3, False), (2, True)])
def test_no_selection_beats_the_bound(plate, k, aimed):
    """Every k-subset of the candidates within the body counts (pairwise rules ignored: a superset
    of the selections the design may make), scored whole: none scores below the bound; the
    design's own greedy + exchange selection scores at or above its best. `aimed`: with a
    [design] target_sigma_um at the median sigma of a pair, whose term keeps the score convex."""
    exp, geometry, cand, scorer, feas = plate
    if aimed:
        sigma = scorer.sigma(cand.sums([0, 17])[0]) * scorer.settings.sigma_unit
        measured = sigma[sigma < 0.1 * scorer.settings.prior_sigma]
        assert measured.size > 10
        exp = replace(exp, design=replace(exp.design, target_sigma_um=float(np.median(measured)) * 1e6))
        scorer = Scorer(exp, geometry.samples)
        assert scorer.log_target is not None
    K = len(cand.cameras)
    assert K == 18 and sorted(np.bincount(cand.body)) == [9, 9]
    b = bound.relaxation(scorer.value, cand.info, cand.weight, k, feas.alone, feas.body, feas.counts)
    assert b.converged
    best = min(scorer.of(cand, s) for s in itertools.combinations(np.flatnonzero(feas.alone), k)
               if all(np.sum(cand.body[list(s)] == j) <= c for j, c in enumerate(feas.counts)))
    assert b.value <= best
    assert b.value <= b.relaxed <= best * (1 + 1e-9)
    chosen, score, _ = exchange(cand, scorer, feas, greedy(cand, scorer, feas, k)[0])
    assert score >= best * (1 - 1e-9)
    assert 0 <= b.gap(score) < 1


def test_the_relaxed_optimum_is_slsqps(plate):
    """The relaxation solved by scipy's SLSQP with finite-difference gradients (no JAX gradient):
    its optimum lies between the certified bound and the best iterate (to SLSQP's tolerance)."""
    exp, geometry, cand, scorer, feas = plate
    k = 3
    b = bound.relaxation(scorer.value, cand.info, cand.weight, k, feas.alone, feas.body, feas.counts)
    weight = cand.weight.astype(float)

    def f(w):
        return float(scorer.value(jnp.tensordot(w, cand.info, axes=1), w @ weight))

    cons, box = _constraints(feas.alone, feas.body, feas.counts, k)
    start = np.where(feas.alone, k / feas.alone.sum(), 0.0)
    ref = minimize(f, start, bounds=box, constraints=cons, method="SLSQP",
                   options={"ftol": 1e-12, "maxiter": 500})
    assert ref.success
    assert b.value <= ref.fun * (1 + SLSQP_TOL)
    assert ref.fun <= b.relaxed * (1 + SLSQP_TOL)
    assert b.relaxed == pytest.approx(ref.fun, rel=2 * bound.REL_TOL)


def test_design_reports_the_gap(plate, tmp_path):
    """design.json, pareto.csv and the figure carry the bound; the bound is below the design's
    score at every count and the gap is 1 - bound / score."""
    exp = plate[0]
    out = tmp_path / "design"
    result = design_run(exp, out)
    data = json.loads((out / "design.json").read_text())
    assert data["gap_to_bound"] == pytest.approx(1 - data["bound"] / result.curve[-1]["score"])
    rows = list(csv.DictReader(open(out / "pareto.csv")))
    assert [int(r["cameras"]) for r in rows] == [c["cameras"] for c in data["curve"]]
    for r in rows:
        assert float(r["bound"]) <= float(r["score"])
        assert float(r["gap"]) == pytest.approx(1 - float(r["bound"]) / float(r["score"]), abs=1e-4)
    assert (out / "pareto.png").is_file()


def test_a_bound_for_more_cameras_bounds_fewer(plate):
    """The best pair scores at least the bound of three cameras (adding one never raises the
    score): exhaustive over the pairs within the body counts."""
    exp, geometry, cand, scorer, feas = plate
    three = bound.relaxation(scorer.value, cand.info, cand.weight, 3, feas.alone, feas.body, feas.counts)
    pairs = [p for p in itertools.combinations(np.flatnonzero(feas.alone), 2)
             if all(np.sum(cand.body[list(p)] == j) <= c for j, c in enumerate(feas.counts))]
    assert three.value <= min(scorer.of(cand, p) for p in pairs)


def test_sparse_and_dense_candidates_give_one_relaxation(plate, monkeypatch):
    """The relaxation's linear map on the stored entries (`linear_maps` of the sparse
    `Candidates`, in chunks of 37 entries, and over a vertex's few candidates alone) and its
    adjoint equal those on the dense (K, N, 6) arrays, and so does the bound. The adjoint of a
    part of the candidates (`rows`, from the sample-major copy) equals the dense one there and
    is 0 elsewhere."""
    exp, geometry, cand, scorer, feas = plate
    monkeypatch.setattr(hull, "ENTRY_CHUNK", 37)
    K, summed, pullback = hull.linear_maps(cand, None)
    Kd, summed_d, pullback_d = hull.linear_maps(cand.info, cand.weight)
    rng = np.random.default_rng(0)
    vertex = np.zeros(K)
    vertex[[0, K // 2]] = [1.0, 0.5]
    assert 2 * hull.SPARSE_ROWS < K
    for w in (rng.random(K), vertex):
        for a, b in zip(summed(w), summed_d(w)):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    gC, gc = rng.normal(size=(cand.samples, 6)), rng.normal(size=cand.samples)
    np.testing.assert_allclose(pullback(gC, gc), pullback_d(gC, gc), rtol=1e-9)
    part = rng.random(K) < 0.5
    assert 0 < part.sum() < K
    _, _, pullback_part = hull.linear_maps(cand, None, rows=part)
    dense = pullback_d(gC, gc)
    np.testing.assert_allclose(pullback_part(gC, gc)[part], dense[part], rtol=1e-9, atol=1e-12 * np.abs(dense).max())
    assert not pullback_part(gC, gc)[~part].any()
    sparse = bound.relaxation(scorer.value, cand, None, 2, feas.alone, feas.body, feas.counts)
    dense = bound.relaxation(scorer.value, cand.info, cand.weight, 2, feas.alone, feas.body, feas.counts)
    assert sparse.value == pytest.approx(dense.value, rel=1e-9)


def test_the_time_limit_holds_inside_the_backtracking(plate, monkeypatch):
    """A clock that advances one second at each reading and a 2.5 s limit: the relaxation stops
    after at most three projections (each backtracking try is a pass over every stored entry, so
    the limit is read between tries, not only between steps), and the bound it returns still
    bounds the best selection it found."""
    exp, geometry, cand, scorer, feas = plate
    clock, projected = iter(range(10 ** 6)), []
    project = hull.project
    monkeypatch.setattr(hull.time, "perf_counter", lambda: float(next(clock)))
    monkeypatch.setattr(hull, "project", lambda *a: projected.append(1) or project(*a))
    b = bound.relaxation(scorer.value, cand, None, 2, feas.alone, feas.body, feas.counts, time_limit=2.5)
    assert len(projected) <= 3 and b.value <= b.relaxed
