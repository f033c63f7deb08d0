"""The design bound's branch and bound (`vdo.design.bound.relaxation` with `branch_s`): the
linear step under a node's branching rules against enumeration, and the bound against the best
selection found by enumeration on random instances, where the branching lifts it above the
hull's and, given the time, to the best selection's score."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from test_bound_conflicts import _instance, _selections, _value

from vdo.design import bound, hull, branch
from vdo.search.anytime import Beside


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


def test_a_linear_step_reads_the_rules_held_when_it_began(monkeypatch):
    """The branch and bound runs two nodes' linear steps side by side (`vdo.search.anytime.Beside`), so
    another thread may hold more candidates while a step builds its rows. Here a hold of every
    candidate lands in the middle of a step (from `hull._alike`, which runs between the step's
    reading of the held candidates and its rows): the step's answer is still a selection with
    no conflicting pair and the least g.s over them all (enumeration), as when nothing
    intervenes; its rows and its candidates came from one state."""
    info, _, body, counts, conflict = _instance(5, K=14, p=0.3)
    K, k = len(body), 3
    rules = hull.Rules(lambda j: conflict[j], k, np.ones(K, bool), body, counts)
    rules.hold([0], np.inf)
    alike, meddled = hull._alike, []

    def meddle(inside):
        if not meddled:
            meddled.append(1)
            rules.hold(np.arange(K), np.inf)      # "another thread"
        return alike(inside)
    monkeypatch.setattr(hull, "_alike", meddle)
    every = list(_selections(K, k, body, counts, conflict))
    for g in np.random.default_rng(7).normal(size=(4, K)):
        meddled.clear()
        rules._rows, rules._state = rules._rows[:1], (rules.held[:1], [])     # one held again
        s, low = rules.vertex(g, 30.0)
        best = min(g[x].sum() for x in every)
        assert meddled and len(rules.held) == K
        assert s is not None and not conflict[np.ix_(s, s)].any()
        assert g[s].sum() == pytest.approx(best, abs=1e-9) and low <= best + 1e-9


def test_a_side_thread_hands_back_its_result_and_its_error():
    assert Beside(lambda a, b: a + b, 2, 3).result() == 5

    def fails():
        raise ValueError("in the side thread")
    with pytest.raises(ValueError, match="side thread"):
        Beside(fails).result()


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


@pytest.mark.parametrize("seed, k, families", [(0, 3, 1), (3, 4, 1), (0, 3, 3), (3, 4, 3)])
def test_every_selection_below_the_incumbent_lies_in_an_open_node(seed, k, families):
    """The tree after a few nodes, against every selection keeping the conflicts: each one
    that scores below the incumbent keeps the branching rules of an open node whose bound is
    at most its score (so the least of the open nodes' bounds bounds it), and the bound
    reported is the least of those and the incumbent (or a closed node's, within REL_TOL of it).
    With three families of classes (`_families`) the splits count cameras (at most t / at
    least t + 1 of a class, t >= 1 among them)."""
    info, weight, body, counts, conflict = _instance(seed, K=12)
    K = len(body)
    scores = {tuple(s): float(_value(info[s].sum(axis=0), weight[s].sum(axis=0)))
              for s in _selections(K, k, body, counts, conflict)}
    start = list(max(scores, key=scores.get))
    tree = bound.relaxation(_value, info, weight, k, np.ones(K, bool), body, counts, start=start,
                            conflicts=lambda j: conflict[j], branch_s=60.0, branch_nodes=5,
                            groups=_families(K, families))
    assert tree.leaves
    assert_open_nodes_hold(tree, scores, k)


def assert_open_nodes_hold(tree, scores: dict, k: int) -> None:
    """Every enumerated selection (`scores`: selection -> score) scoring below the incumbent
    (the best of the tree's found selections) keeps the rules of an open node (`tree.leaves`)
    whose bound is at most its score, and the bound reported is the least of those bounds and
    the incumbent (a closed node's may lie REL_TOL under the incumbent)."""
    incumbent = min(scores[tuple(s)] for s in tree.found)
    least = min([incumbent] + [b for _, b in tree.leaves])
    assert least * (1 - bound.REL_TOL) <= tree.value <= least
    for s, score in scores.items():
        if score >= incumbent * (1 - bound.REL_TOL):
            continue
        within = [b for node, b in tree.leaves if node.keeps(list(s), k)]
        assert within and min(within) <= score * (1 + 1e-12), s


def _families(K: int, n: int) -> np.ndarray:
    """(n, K) families of classes for the branching, coarse to fine: halves, then sixths, then
    triples of the candidates (n = 1: the triples alone)."""
    rows = [np.arange(K) // (K // 2), np.arange(K) // (K // 6), np.arange(K) // 3]
    return np.stack(rows[-n:])


@pytest.mark.parametrize("seed, k", [(0, 3), (2, 3), (3, 4)])
def test_branching_on_classes_closes_on_the_best_selection(seed, k, monkeypatch):
    """With three families of classes (halves, sixths, triples of the candidates), whose sums at
    the hull's iterate exceed one: the tree splits on counts above none / some (recorded from
    `hull.Node`'s `between` rows of the children it certifies), stays below every selection,
    and closes on the best one within REL_TOL."""
    info, weight, body, counts, conflict = _instance(seed, K=12)
    K = len(body)
    scores = {tuple(s): float(_value(info[s].sum(axis=0), weight[s].sum(axis=0)))
              for s in _selections(K, k, body, counts, conflict)}
    best = min(scores.values())
    start = list(max(scores, key=scores.get))
    rows = []
    corrective = branch.corrective

    def recording(*args, node=None, **kw):
        if node is not None:
            rows.extend(node.between)
        return corrective(*args, node=node, **kw)
    monkeypatch.setattr(branch, "corrective", recording)
    tree = bound.relaxation(_value, info, weight, k, np.ones(K, bool), body, counts, start=start,
                            conflicts=lambda j: conflict[j], branch_s=60.0, groups=_families(K, 3))
    assert any(hi < k and hi >= 1 or lo >= 2 for _, lo, hi in rows)       # a count above none / some
    assert tree.value <= best * (1 + 1e-12)
    assert tree.value == pytest.approx(best, rel=bound.REL_TOL)
    assert scores[tuple(tree.found[0])] == pytest.approx(best)


def test_a_root_without_a_certificate_still_branches(monkeypatch):
    """On a loaded machine the relaxation's phases can end before any certificate (the bound then
    reads 0, the score's trivial floor; seen in a reduced `vdo design` of the steel beam): the
    tree starts from there, its pseudo-costs (lifts relative to the node's bound) pass over a
    node of bound 0, and it still closes on the best selection."""
    info, weight, body, counts, conflict = _instance(0, K=12)
    K, k = len(body), 3
    scores = {tuple(s): float(_value(info[s].sum(axis=0), weight[s].sum(axis=0)))
              for s in _selections(K, k, body, counts, conflict)}
    best = min(scores.values())
    corrective = bound.corrective
    monkeypatch.setattr(bound, "corrective", lambda *a, **kw: replace(corrective(*a, **kw), bound=0.0))
    tree = bound.relaxation(_value, info, weight, k, np.ones(K, bool), body, counts,
                            start=list(max(scores, key=scores.get)), conflicts=lambda j: conflict[j],
                            branch_s=60.0, groups=_families(K, 3))
    assert tree.nodes > 1
    assert tree.value <= best * (1 + 1e-12)
    assert tree.value == pytest.approx(best, rel=bound.REL_TOL)


@pytest.mark.parametrize("t", [0, 1, 2])
def test_a_split_on_a_class_partitions_the_nodes_selections(t):
    """`branch._children` of a node that already holds rules (one candidate left out, at least
    one of a group, one to three of another): every selection of 4 of 10 candidates that keeps
    the node's rules keeps exactly one child's, the one its count in the class says."""
    K, k = 10, 4
    out = np.zeros(K, bool)
    out[9] = True
    node = hull.Node(out=out, into=(np.array([0, 5]),), between=((np.array([1, 2, 3, 6]), 1, 3),))
    group = np.array([2, 3, 4, 7, 8])
    low, high = branch._children(node, group, t, k, K)
    kept = 0
    for s in itertools.combinations(range(K), k):
        if not node.keeps(s, k):
            continue
        kept += 1
        held = np.isin(s, group).sum()
        assert (low.keeps(s, k), high.keeps(s, k)) == (held <= t, held > t), s
    assert kept > 20


def test_the_split_family_is_the_untried_then_the_one_that_lifted_most():
    """`branch._pick` on a mix of two selections of 2 of 8 candidates, {0, 4} and {1, 5}, each
    at weight 1/2, with three families: halves (0-3 / 4-7, whose sums are whole), F1 ({0, 1},
    {2, 3}, {4}, {5}, {6, 7}: {4} and {5} hold 1/2) and F2 ({0}, {1}, {2, 3, 4}, {5, 6, 7}: all
    1/2). The family split on holds a fractional class: the first not split on yet, then the one
    whose splits lifted fastest (the pseudo-costs `lifts`: lifts and seconds); with no fractional class,
    the candidate weighted farthest from 0 and 1."""
    K = 8
    chosen = [np.array([0, 4]), np.array([1, 5])]
    x = np.zeros(K)
    x[[0, 1, 4, 5]] = 0.5
    h = hull.Hull(best=1.0, best_x=x, bound=1.0, steps=1, chosen=chosen, lam=np.array([0.5, 0.5]), x=x)
    fams = np.stack([np.arange(K) // 4, [0, 0, 1, 1, 2, 3, 4, 4], [0, 1, 2, 2, 2, 3, 3, 3]])
    summed = lambda w: (np.asarray(w, float), None)        # noqa: E731
    value = lambda w, _: float(w @ np.arange(K))           # noqa: E731
    pick = lambda lifts: branch._pick(h, fams, hull.Node(), value, summed, 1e-9, np.array(lifts, float))  # noqa: E731
    f, S, t = pick(np.zeros((3, 2)))
    assert f == 1 and t == 0 and set(S) in ({4}, {5})      # halves are whole; F1 untried, first
    assert pick([[0, 0], [0.01, 2], [0, 0]])[0] == 2       # F2 not split on yet
    assert pick([[0, 0], [0.01, 2], [0.03, 1]])[0] == 2    # F2 lifted faster
    assert pick([[0, 0], [0.01, 2], [0.03, 10]])[0] == 1   # ... and slower
    assert pick([[0, 0], [0.05, 1], [0.03, 1]])[0] == 1
    single = np.zeros(K)
    single[0] = 0.7
    alone = hull.Hull(best=1.0, best_x=single, bound=1.0, steps=1, chosen=chosen[:1], lam=np.ones(1), x=single)
    f, S, t = branch._pick(alone, fams[1:2], hull.Node(), value, summed, 1e-9, np.zeros((1, 2)))
    assert f == 0 and set(S) == {0, 1} and t == 0
    single[1] = 0.3                                        # one class of all: its sum is whole
    f, S, t = branch._pick(alone, np.zeros((1, K), int), hull.Node(), value, summed, 1e-9, np.zeros((1, 2)))
    assert (f, list(S), t) == (-1, [0], 0)


def test_classes_label_aim_mount_body_lens_and_spot():
    """`classes`: five rows, coarse to fine; candidates share a class when they share every
    attribute of its row, and each row refines the one before."""
    target = np.array([0, 0, 0, 1, 1, 0])
    mount = np.array(["a", "a", "b", "a", "a", "a"])
    body = np.array([0, 1, 0, 0, 0, 0])
    focal = np.array([0.008, 0.008, 0.008, 0.008, 0.035, 0.035])
    pos = np.array([[0, 0, 1], [0, 0, 1], [1, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1.0004]], float)
    c = branch.classes(target, mount, body, focal, pos)
    assert c.shape == (5, 6)
    same = lambda row, i, j: c[row, i] == c[row, j]  # noqa: E731
    assert same(0, 0, 2) and not same(0, 0, 3)                   # aim point
    assert same(1, 0, 1) and not same(1, 0, 2)                   # ... and mount
    assert not same(2, 0, 1) and same(2, 0, 5)                   # ... and body
    assert not same(3, 0, 5) and same(3, 3, 3)                   # ... and lens
    assert same(4, 0, 3) and same(4, 0, 5) and not same(4, 0, 2)   # spot: the optical centre, to the mm
    for row in range(1, 4):         # finer: one class of a row lies in one class of the row before
        assert all(len(set(c[row - 1, c[row] == q])) == 1 for q in set(c[row]))


def test_a_spot_holds_every_candidate_at_one_optical_centre():
    """`spots`: candidates whose optical centres agree to the millimetre share a group, others
    do not."""
    p = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0002], [0.0, 0.0, 1.5], [2.0, -1.0, 1.0], [0.0, 0.0, 1.5]])
    g = branch.spots(p)
    assert g[0] == g[1] and g[2] == g[4]
    assert len({g[0], g[2], g[3]}) == 3


@pytest.mark.parametrize("columns", [0, 5, 64, 70])
def test_rows_alike_share_a_label(columns):
    """hull._alike (the linear step's groups of candidates that enter the same rows) against
    numpy's unique rows: one label per distinct row, across a 64-bit word's edge too."""
    rng = np.random.default_rng(columns)
    base = rng.random((7, columns)) < 0.5
    rows = base[rng.integers(0, 7, size=200)]
    label = hull._alike(rows)
    expect = np.unique(rows, axis=0, return_inverse=True)[1].ravel() if columns else np.zeros(200, int)
    assert len(np.unique(label)) == len(np.unique(expect))
    same = label[:, None] == label[None, :]
    assert (same == (expect[:, None] == expect[None, :])).all()
