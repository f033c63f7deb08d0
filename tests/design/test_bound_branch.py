"""The design bound's branch and bound (`vdo.design.bound.relaxation` with `branch_s`): the
linear step under a node's branching rules against enumeration, and the bound against the best
selection found by enumeration on random instances, where the branching lifts it above the
hull's and, given the time, to the best selection's score."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from test_bound_conflicts import _instance, _selections, _value

from vdo.design import bound, hull, branch


@pytest.mark.parametrize("seed", [0, 1])
def test_the_linear_step_keeps_a_nodes_rules(seed):
    """Rules.vertex under a node (two candidates left out, at least one camera of each of two
    groups) against every selection keeping the conflicts and those rules: its solution is one
    and g.s the least; a node no selection keeps is answered with an infinite low."""
    info, _, body, counts, conflict = _instance(seed, K=12)
    K, k = len(body), 4
    allowed = np.ones(K, bool)
    out = np.zeros(K, bool)
    out[[2, 9]] = True
    into = (np.array([0, 1, 4]), np.array([4, 6, 10, 11]))
    node = hull.Node(out=out, into=into)
    rules = hull.Rules(lambda j: conflict[j], k, allowed, body, counts)
    rules.hold([1], np.inf)     # the others enter as the solutions take them
    g = np.random.default_rng(seed + 20).normal(size=K)
    keeps = [s for s in _selections(K, k, body, counts, conflict, ~out)
             if all(np.isin(q, s).any() for q in into)]
    assert keeps
    s, low = rules.vertex(g, 10.0, node)
    assert s is not None and not out[s].any() and all(np.isin(q, s).any() for q in into)
    assert not conflict[np.ix_(s, s)].any()
    assert g[s].sum() == pytest.approx(min(g[x].sum() for x in keeps), abs=1e-9)
    assert low <= g[s].sum() + 1e-9
    empty = hull.Node(out=np.arange(K) >= 3, into=(np.array([5]),))   # a group wholly left out
    assert rules.vertex(g, 10.0, empty) == (None, np.inf)


@pytest.mark.parametrize("seed, k", [(0, 3), (2, 3), (3, 4)])
def test_branching_lifts_the_bound_to_the_best_selection(seed, k):
    """Random instances where the hull's bound lies well below the best selection (the
    relaxation's integrality gap): with branching it stays below every selection keeping the
    conflicts, rises above the hull's, and closes on the best one within REL_TOL."""
    info, weight, body, counts, conflict = _instance(seed, K=12)
    K = len(body)
    allowed = np.ones(K, bool)
    scores = {tuple(s): float(_value(info[s].sum(axis=0), weight[s].sum(axis=0)))
              for s in _selections(K, k, body, counts, conflict)}
    best = min(scores.values())
    start = list(max(scores, key=scores.get))          # the worst selection: the incumbent to beat
    args = (_value, info, weight, k, allowed, body, counts)
    hull = bound.relaxation(*args, start=start, conflicts=lambda j: conflict[j])
    tree = bound.relaxation(*args, start=start, conflicts=lambda j: conflict[j], branch_s=60.0,
                            groups=np.arange(K) // 3)
    assert hull.value < best * (1 - 0.05)              # a gap to close
    assert tree.value <= best * (1 + 1e-12)
    assert tree.value == pytest.approx(best, rel=bound.REL_TOL)
    assert tree.nodes > 1
    assert scores[tuple(tree.found[0])] == pytest.approx(best)      # the best selection found


@pytest.mark.parametrize("seed, k", [(0, 3), (3, 4)])
def test_every_selection_below_the_incumbent_lies_in_an_open_node(seed, k):
    """The tree after a few nodes, against every selection keeping the conflicts: each one
    that scores below the incumbent keeps the branching rules of an open node whose bound is
    at most its score (so the least of the open nodes' bounds bounds it), and the bound
    reported is the least of those and the incumbent (or a closed node's, within REL_TOL of it)."""
    info, weight, body, counts, conflict = _instance(seed, K=12)
    K = len(body)
    scores = {tuple(s): float(_value(info[s].sum(axis=0), weight[s].sum(axis=0)))
              for s in _selections(K, k, body, counts, conflict)}
    start = list(max(scores, key=scores.get))
    tree = bound.relaxation(_value, info, weight, k, np.ones(K, bool), body, counts, start=start,
                            conflicts=lambda j: conflict[j], branch_s=60.0, branch_nodes=5,
                            groups=np.arange(K) // 3)
    incumbent = min(scores[tuple(s)] for s in tree.found)
    assert tree.leaves
    least = min([incumbent] + [b for _, b in tree.leaves])     # a closed node may lie REL_TOL under the incumbent
    assert least * (1 - bound.REL_TOL) <= tree.value <= least
    for s, score in scores.items():
        if score >= incumbent * (1 - bound.REL_TOL):
            continue
        within = [b for node, b in tree.leaves
                  if (node.out is None or not node.out[list(s)].any()) and all(np.isin(q, s).any() for q in node.into)]
        assert within and min(within) <= score * (1 + 1e-12), s


def test_a_spot_holds_every_candidate_at_one_optical_centre():
    """`spots`: candidates whose optical centres agree to the millimetre share a group, others
    do not."""
    p = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0002], [0.0, 0.0, 1.5], [2.0, -1.0, 1.0], [0.0, 0.0, 1.5]])
    g = branch.spots(p)
    assert g[0] == g[1] and g[2] == g[4]
    assert len({g[0], g[2], g[3]}) == 3
