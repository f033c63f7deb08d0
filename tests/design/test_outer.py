"""The outer approximation's start (`vdo.design.outer`) against enumeration on random instances
whose views have rank two (one view leaves a sample unmeasured): the tangent planes of each sample
group never exceed the group's part of the score at any selection, the search ends on the best
selection of its pool that keeps the rules, and its model's dual bound never passes that best."""

from __future__ import annotations

import numpy as np
import pytest

from test_bound_conflicts import _selections
from test_bound_views import _instance, _term, _value

from vdo.design import outer
from vdo.design.hull import linear_maps

PLANE_SLACK = 1e-9     # float64 rounding allowed where a plane touches the score

def _best(info, weight, body, counts, conflict, k, keeps=lambda s: True):
    scores = {tuple(s): float(_value(info[s].sum(0), weight[s].sum(0)))
              for s in _selections(len(body), k, body, counts, conflict) if keeps(s)}
    best = min(scores, key=scores.get)
    return list(best), scores[best]

@pytest.mark.parametrize("seed", [0, 2])
def test_the_planes_stay_below_every_selection(seed):
    """At a fractional point and at a selection, each group's plane lies at or below the group's
    sum of terms at every selection (convexity), and touches it at a selection where it is laid."""
    info, weight, body, counts, conflict = _instance(seed)
    K, N = info.shape[:2]
    groups = outer.sample_groups(np.random.default_rng(seed).normal(size=(N, 3)), 3)
    _, summed, pullback = linear_maps(info, weight)
    x0 = np.random.default_rng(seed + 1).random(K)
    x0 *= 3 / x0.sum()
    laid = next(iter(_selections(K, 3, body, counts, conflict)))      # a selection: the planes touch there
    touched = 0
    for point in (x0, np.isin(np.arange(K), laid).astype(float)):
        gamma, rhs, total = outer.planes(_term, summed, pullback, groups, point)
        assert total == pytest.approx(float(np.sum(_term(*summed(point), np.arange(N)))))
        for s in _selections(K, 3, body, counts, conflict):
            x = np.isin(np.arange(K), s).astype(float)
            part = np.bincount(groups, np.asarray(_term(*summed(x), np.arange(N))), minlength=gamma.shape[1])
            assert np.all(rhs + gamma.T @ x <= part + PLANE_SLACK * np.abs(part).max())
            if np.array_equal(x, point):
                np.testing.assert_allclose(rhs + gamma.T @ x, part, rtol=1e-9, atol=1e-12)
                touched += 1
    assert touched == 1

@pytest.mark.parametrize("seed", [0, 1, 3])
def test_the_search_ends_on_the_best_selection(seed):
    """With every candidate in the pool and time to spare, the search returns the best selection
    of enumeration (k = 3, body counts 2 and 3, random conflicts), the model's dual bound is at
    most its score, and a rule the model does not hold (`feasible`) is kept."""
    info, weight, body, counts, conflict = _instance(seed)
    K, N = info.shape[:2]
    groups = outer.sample_groups(np.random.default_rng(seed).normal(size=(N, 3)), 3)
    best, score = _best(info, weight, body, counts, conflict, 3)
    start = np.full(K, 3 / K)
    o = outer.search(_term, info, weight, 3, np.ones(K, bool), body, counts, lambda j: conflict[j],
                     lambda s: True, groups, [start], 60.0, per_body=K)
    assert o.chosen == sorted(best) and o.score == pytest.approx(score, rel=1e-9)
    assert o.model <= score * (1 + 1e-9)
    # a rule beyond the pairwise ones: the best selection's first camera may not be taken
    banned = best[0]
    best2, score2 = _best(info, weight, body, counts, conflict, 3, keeps=lambda s: banned not in s)
    o2 = outer.search(_term, info, weight, 3, np.ones(K, bool), body, counts, lambda j: conflict[j],
                      lambda s: banned not in s, groups, [start], 60.0, per_body=K, max_solves=200)
    assert o2.chosen is not None and banned not in o2.chosen
    assert o2.score == pytest.approx(score2, rel=1e-9)

def test_the_pool_holds_the_weighed_and_the_cheapest_of_each_kind():
    """`pool`: every candidate weighed above WEIGHED, and per body kind the per_body allowed ones
    of lowest summed cost; a candidate not allowed never."""
    rng = np.random.default_rng(5)
    K = 40
    body = rng.integers(0, 2, K)
    allowed = rng.random(K) < 0.8
    weights = np.where(rng.random(K) < 0.1, 0.5, 0.0)
    gamma = rng.normal(size=(K, 3))
    got = outer.pool(weights, gamma, allowed, body, per_body=4)
    cost = gamma.sum(1)
    want = set(np.flatnonzero(allowed & (weights > outer.WEIGHED)))
    for b in (0, 1):
        kind = np.flatnonzero(allowed & (body == b))
        want |= set(kind[np.argsort(cost[kind])[:4]])
    assert set(got.tolist()) == want and allowed[got].all()

def test_sample_groups_cluster_apart_points():
    """Two clouds of samples far apart never share a group; fewer samples than groups: one each."""
    rng = np.random.default_rng(0)
    points = np.vstack([rng.normal(size=(30, 3)) * 0.01, rng.normal(size=(30, 3)) * 0.01 + 5.0])
    labels = outer.sample_groups(points, 2)
    assert len(set(labels[:30])) == 1 and len(set(labels[30:])) == 1 and labels[0] != labels[30]
    assert sorted(outer.sample_groups(points[:3], 10).tolist()) == [0, 1, 2]


@pytest.mark.parametrize("seed", range(4))
def test_admits_finds_an_order_when_one_exists(seed):
    """`Feasibility.admits` against every order of every 3-subset: true exactly when some order
    adds each camera while `allowed` by those before (one-way conflicts, body counts, cameras
    not allowed alone)."""
    import itertools

    from vdo.design.feasibility import Feasibility

    class Rules:
        allowed, admits = Feasibility.allowed, Feasibility.admits

        def __init__(self, rng, K=7):
            self.rows = rng.random((K, K)) < 0.25
            np.fill_diagonal(self.rows, False)
            self.alone = rng.random(K) < 0.9
            self.body, self.counts = rng.integers(0, 2, K), np.array([2, 2])

        def row(self, j):
            return self.rows[j]

    rules = Rules(np.random.default_rng(seed))
    for s in itertools.combinations(range(7), 3):
        ordered = any(all(rules.allowed(list(p[:m]))[p[m]] for m in range(3))
                      for p in itertools.permutations(s))
        assert rules.admits(list(s)) == ordered
