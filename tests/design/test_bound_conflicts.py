"""The design bound with pairwise rules (`vdo.design.bound.relaxation` given `conflicts`): its
linear step against enumeration of every selection, the certified bound against the best
selection found by enumeration on random instances, an instance whose plain relaxation puts
more than one camera on two conflicting candidates, where the rules lift the bound to the best
selection's score (closed form), and the rules it is given (`Feasibility.placement`) against the
selection's own (`Feasibility.row`)."""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np
import pytest

from conftest import TRIPOD_ZONE

from vdo.config import experiment as config
from vdo.design import bound, hull
from vdo.design.candidates import SPOT_M, judge
from vdo.design.feasibility import Feasibility
from vdo.state import prepare

E = 0.5          # the information every sample has before any camera (the value's regulariser)


def _value(C, cover):
    """sum over samples of tr (M_n + E I)^-1, M_n the 3x3 matrix of C's six entries (xx, yy, zz,
    xy, xz, yz): A-optimality, convex in C (numpy or JAX arrays)."""
    xp = jnp if isinstance(C, jnp.ndarray) else np
    M = xp.stack([xp.stack([C[:, 0], C[:, 3], C[:, 4]], -1), xp.stack([C[:, 3], C[:, 1], C[:, 5]], -1),
                  xp.stack([C[:, 4], C[:, 5], C[:, 2]], -1)], -2) + E * xp.eye(3)
    return xp.trace(xp.linalg.inv(M), axis1=-2, axis2=-1).sum() + 0.0 * cover.sum()


def _instance(seed, K=11, N=4, p=0.35):
    """K candidates' rank-one information on N samples (some unseen), two body kinds (counts 2
    and 3), a random symmetric conflict graph with edge probability p."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(K, N, 3)) * (rng.random((K, N, 1)) > 0.3)
    info = np.concatenate([u ** 2, u[..., [0]] * u[..., [1]], u[..., [0]] * u[..., [2]],
                           u[..., [1]] * u[..., [2]]], axis=-1)
    upper = np.triu(rng.random((K, K)) < p, 1)
    return info, np.ones((K, N)), rng.integers(0, 2, K), np.array([2, 3]), upper | upper.T


def _selections(K, k, body, counts, conflict, allowed=None):
    """Every k-subset of the allowed candidates within the body counts with no conflicting pair."""
    pool = np.flatnonzero(np.ones(K, bool) if allowed is None else allowed)
    for s in itertools.combinations(pool, k):
        s = list(s)
        if all(np.sum(body[s] == b) <= c for b, c in enumerate(counts)) and not conflict[np.ix_(s, s)].any():
            yield s


def test_the_cliques_cover_every_conflict():
    rng = np.random.default_rng(4)
    upper = np.triu(rng.random((30, 30)) < 0.3, 1)
    adjacent = upper | upper.T
    covered = np.zeros_like(adjacent)
    for q in hull.cliques(adjacent):
        sub = adjacent[np.ix_(q, q)]
        assert sub[~np.eye(len(q), dtype=bool)].all()      # a clique
        covered[np.ix_(q, q)] = True
    assert not (adjacent & ~covered).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_linear_step_is_the_best_selection(seed):
    """Rules.vertex, holding the rules of two candidates only (the others held as its solutions
    take them), against every selection: its solution is one (no conflicting pair, body counts,
    k cameras, only allowed candidates) and g.s is the least over them all; its low is below."""
    info, _, body, counts, conflict = _instance(seed, K=12)
    K, k = len(body), 4
    allowed = np.ones(K, bool)
    allowed[[3, 7]] = False
    rules = hull.Rules(lambda j: conflict[j], k, allowed, body, counts)
    rules.hold([0, 5], np.inf)
    g = np.random.default_rng(seed + 10).normal(size=K)
    best = min(g[s].sum() for s in _selections(K, k, body, counts, conflict, allowed))
    s, low = rules.vertex(g, 10.0)
    assert s is not None and len(s) == k and allowed[s].all()
    assert not conflict[np.ix_(s, s)].any()
    assert all(np.sum(body[s] == b) <= c for b, c in enumerate(counts))
    assert g[s].sum() == pytest.approx(best, abs=1e-9)
    assert low <= best + 1e-9


@pytest.mark.parametrize("seed, k", [(0, 3), (1, 4), (2, 3), (3, 4)])
def test_no_selection_that_keeps_the_rules_beats_the_bound(seed, k):
    """Random instances scored by enumeration of every selection keeping the conflicts: none
    scores below the conflict-aware bound, which is at least the plain one (pairwise rules
    dropped, converged alike) and holds every candidate the relaxation weighs."""
    info, weight, body, counts, conflict = _instance(seed)
    K = len(body)
    allowed = np.ones(K, bool)
    scores = [float(_value(info[s].sum(axis=0), weight[s].sum(axis=0)))
              for s in _selections(K, k, body, counts, conflict)]
    assert len(scores) > 1
    plain = bound.relaxation(_value, info, weight, k, allowed, body, counts)
    held = bound.relaxation(_value, info, weight, k, allowed, body, counts, conflicts=lambda j: conflict[j])
    assert plain.converged and held.converged
    assert held.value <= min(scores)
    assert held.value >= plain.value * (1 - bound.REL_TOL)
    assert held.plain <= held.value <= held.relaxed
    assert held.conflicted >= np.sum(held.weights > bound.SUPPORT)


def test_the_rules_lift_the_bound_to_the_best_selection():
    """Two candidates x1, x2 that conflict inform the x axis (a each), one the y axis (b), k = 2:
    the score 1 / (a w_x + E) + 1 / (b w_y + E) + 1 / E (z unseen) falls faster in w_x than in
    w_y at w_x = w_y = 1, so the plain relaxation puts w_x = w1 + w2 > 1, which no selection can
    (both selections are {x_i, y}: w_x = w_y = 1). With the conflict the bound lies above the
    plain relaxed optimum and meets the best selection's score within REL_TOL."""
    a, b = 1.0, 10.0
    info = np.zeros((3, 1, 6))
    info[[0, 1], 0, 0], info[2, 0, 1] = a, b
    weight = np.ones((3, 1))
    conflict = np.array([[False, True, False], [True, False, False], [False, False, False]])
    best = 1 / (a + E) + 1 / (b + E) + 1 / E
    assert a / (a + E) ** 2 > b / (b + E) ** 2                # x gains more than y at w = 1
    args = (_value, info, weight, 2, np.ones(3, bool), np.zeros(3, int), np.array([3]))
    plain = bound.relaxation(*args)
    held = bound.relaxation(*args, conflicts=lambda j: conflict[j])
    assert plain.weights[:2].sum() > 1 + 0.1                  # the plain optimum breaks the rule
    assert plain.relaxed < best * (1 - 10 * bound.REL_TOL)
    assert held.value > plain.relaxed                         # above all the plain one can certify
    assert held.value <= best
    assert held.value == pytest.approx(best, rel=bound.REL_TOL)
    assert held.weights[:2].sum() == pytest.approx(1.0, abs=1e-9)


DESIGN = """
[design]
max_cameras = 2
rail_positions = 9
offset_m = [0, 0, 0]
sample_spacing_mm = 50
zone_points = 3
zone_heights = 2
"""


def test_the_bound_holds_rules_the_selection_keeps(plate_experiment):
    """Tripods in a floor zone (two heights over each floor point) and the plate's rails:
    `placement`, the rules the design's bound holds, is symmetric and within `row`, the
    selection's own (so a pair it holds can be in no selection, whichever camera comes first),
    and holds the tripods' conflicts and those of one spot (some of each among the candidates
    taken)."""
    path = plate_experiment(spacing=50, extra_meshes=TRIPOD_ZONE)
    path.write_text(path.read_text() + DESIGN)
    exp = config.load(path)
    geometry = prepare(exp)
    cand = judge(exp, geometry)
    feas = Feasibility(exp, cand, geometry.samples)
    some = np.flatnonzero(feas.alone)[::max(1, int(feas.alone.sum()) // 24)]
    placed = np.array([feas.placement(int(j))[some] for j in some])
    rows = np.array([feas.row(int(j))[some] for j in some])
    assert (placed == placed.T).all()
    assert not (placed & ~rows).any()
    tripods = np.array([feas.tripods_touch(int(j))[some] for j in some])
    spot = np.linalg.norm(cand.positions[some][:, None] - cand.positions[some][None], axis=-1) < SPOT_M
    assert placed[tripods].all() and placed[spot].all()
    assert tripods.sum() > 0 and (spot & ~np.eye(len(some), dtype=bool)).sum() > 0
