"""The design bound's splits on a sample's views (`vdo.design.branch.Views`, `relaxation` with
`term`): the floor of a sample seen at most once against every selection, the linear step under
view-count rules against enumeration, and the branch and bound on instances where each camera
measures two directions of three (one view leaves a sample unmeasured), against the best
selection found by enumeration."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from test_bound_branch import assert_open_nodes_hold
from test_bound_conflicts import _selections

from vdo.design import bound, hull, branch

E = 0.05         # the information every sample has before any camera (a view measures two directions of three)
A = 0.05         # a sample's term: A tr (M_n + E I)^-1


def _term(C, cover, sample):
    """A tr (M + E I)^-1 per sample, M the 3x3 matrix of C's six entries (xx, yy, zz, xy, xz,
    yz): convex and non-increasing in C (numpy or JAX arrays; cover and sample unused)."""
    xp = jnp if isinstance(C, jnp.ndarray) else np
    M = xp.stack([xp.stack([C[:, 0], C[:, 3], C[:, 4]], -1), xp.stack([C[:, 3], C[:, 1], C[:, 5]], -1),
                  xp.stack([C[:, 4], C[:, 5], C[:, 2]], -1)], -2) + E * xp.eye(3)
    return A * xp.trace(xp.linalg.inv(M), axis1=-2, axis2=-1) + 0.0 * cover


def _value(C, cover):
    """exp(sum_n term_n): the score `term` decomposes."""
    xp = jnp if isinstance(C, jnp.ndarray) else np
    return xp.exp(xp.sum(_term(C, cover, xp.arange(C.shape[0]))))


def _instance(seed, K=12, N=6, p=0.25, see=0.5):
    """K candidates seeing each of N samples with probability `see`, each view the projector
    across a random ray (rank two) times a random strength; two body kinds (counts 2 and 3), a
    random symmetric conflict graph with edge probability p."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(K, N, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    P = np.eye(3) - d[..., :, None] * d[..., None, :]
    P *= (rng.random((K, N, 1, 1)) < see) * rng.uniform(0.5, 2.0, (K, N, 1, 1))
    info = np.stack([P[..., 0, 0], P[..., 1, 1], P[..., 2, 2], P[..., 0, 1], P[..., 0, 2], P[..., 1, 2]], -1)
    upper = np.triu(rng.random((K, K)) < p, 1)
    return info, (info != 0).any(-1).astype(float), rng.integers(0, 2, K), np.array([2, 3]), upper | upper.T


def _scores(info, weight, body, counts, conflict, k):
    return {tuple(s): float(_value(info[s].sum(0), weight[s].sum(0)))
            for s in _selections(len(body), k, body, counts, conflict)}


@pytest.mark.parametrize("seed", [0, 3])
def test_a_sample_seen_at_most_once_keeps_its_floor(seed):
    """`Views.alone(n)` is at most sample n's term in every selection of which at most one
    camera sees n, and equals it for the best such single camera; `viewers` and `count` agree
    with the information stored."""
    info, weight, body, counts, conflict = _instance(seed)
    K, N = info.shape[:2]
    views = branch.Views(_term, info, weight, np.ones(K, bool))
    for n in range(N):
        seers = views.viewers(n)
        assert np.array_equal(seers, np.flatnonzero((info[:, n] != 0).any(-1)))
        singles = [float(_term(info[[i], n], weight[[i], n], np.array([n]))[0]) for i in seers]
        alone = views.alone(n)
        assert alone == pytest.approx(min(singles + [float(_term(np.zeros((1, 6)), np.zeros(1), [n])[0])]))
        for s in _selections(K, 3, body, counts, conflict):
            assert views.count(s)[n] == np.isin(s, seers).sum()
            if views.count(s)[n] <= 1:
                assert float(_term(info[s, n].sum(0)[None], weight[s, n].sum(0)[None], [n])[0]) >= alone - 1e-12


@pytest.mark.parametrize("seed", [0, 1])
def test_the_linear_step_keeps_view_counts(seed):
    """Rules.vertex under a node with view rules (at most one camera of one group, at least two
    of another) against every selection that keeps them and the conflicts."""
    info, weight, body, counts, conflict = _instance(seed)
    K, k = len(body), 3
    views = branch.Views(_term, info, weight, np.ones(K, bool))
    few, many = views.viewers(0), views.viewers(1)
    node = hull.Node(between=((few, 0, 1), (many, 2, k)))
    rules = hull.Rules(lambda j: conflict[j], k, np.ones(K, bool), body, counts)
    rules.hold([int(many[0])], np.inf)
    g = np.random.default_rng(seed + 30).normal(size=K)
    keeps = [s for s in _selections(K, k, body, counts, conflict) if node.keeps(s, k)]
    assert keeps and len(keeps) < sum(1 for _ in _selections(K, k, body, counts, conflict))
    s, low = rules.vertex(g, 10.0, node)
    assert s is not None and node.keeps(s, k) and not conflict[np.ix_(s, s)].any()
    assert g[s].sum() == pytest.approx(min(g[x].sum() for x in keeps), abs=1e-9)
    assert low <= g[s].sum() + 1e-9
    never = hull.Node(between=((many, 0, 1), (many, 2, k)))
    assert rules.vertex(g, 10.0, never) == (None, np.inf)


@pytest.mark.parametrize("seed", [0, 3, 5])
def test_splitting_on_views_closes_the_gap(seed):
    """Where the hull mixes selections that see a sample once with others that see it more
    often, three nodes split on views lift the bound above three nodes split on candidates
    alone, never above any selection, and the whole tree closes on the best selection."""
    info, weight, body, counts, conflict = _instance(seed)
    K, k = len(body), 3
    scores = _scores(info, weight, body, counts, conflict, k)
    best = min(scores.values())
    start = list(max(scores, key=scores.get))
    args = (_value, info, weight, k, np.ones(K, bool), body, counts)
    rules = dict(start=start, conflicts=lambda j: conflict[j])
    hull = bound.relaxation(*args, **rules)
    spots = bound.relaxation(*args, **rules, branch_s=60.0, branch_nodes=3)
    split = bound.relaxation(*args, **rules, branch_s=60.0, branch_nodes=3, term=_term)
    tree = bound.relaxation(*args, **rules, branch_s=60.0, term=_term)
    assert hull.value < best * (1 - 0.2)               # a gap to close
    assert spots.value < split.value <= best * (1 + 1e-12)
    assert tree.value <= best * (1 + 1e-12)
    assert tree.value == pytest.approx(best, rel=bound.REL_TOL)
    assert scores[tuple(tree.found[0])] == pytest.approx(best)


@pytest.mark.parametrize("seed", [0, 3])
def test_every_selection_below_the_incumbent_lies_in_an_open_node_split_on_views(seed):
    """After a few nodes split on views, each selection scoring below the incumbent keeps the
    rules of an open node whose bound is at most its score."""
    info, weight, body, counts, conflict = _instance(seed)
    K, k = len(body), 3
    scores = _scores(info, weight, body, counts, conflict, k)
    start = list(max(scores, key=scores.get))
    tree = bound.relaxation(_value, info, weight, k, np.ones(K, bool), body, counts, start=start,
                            conflicts=lambda j: conflict[j], branch_s=60.0, branch_nodes=4, term=_term)
    assert any(node.between for node, _ in tree.leaves)
    assert_open_nodes_hold(tree, scores, k)
