"""NURBS curves without JAX: the knot vector (clamped uniform, or a user's clamped one on [0, 1])
and de Boor's algorithm on
homogeneous control points, for any array module `xp` (NumPy here and in the config; `jax.numpy`
in `vdo.model.rail`, which differentiates them).

    C(u) = sum_i N_{i,p}(u) w_i P_i / sum_i N_{i,p}(u) w_i
"""

from __future__ import annotations

import numpy as np

CLOSED_TOL_M = 1e-9     # m: a rail whose last control point is its first within this is closed


def is_closed(control_points) -> bool:
    """Whether a clamped curve through these control points (n, 3) closes on itself: C(0) = P_0
    and C(1) = P_(n-1) coincide within CLOSED_TOL_M (a ring rail, as a CAD circle or a polyline
    whose last point is its first). Its u is then periodic: u and u + 1 are the same place."""
    pts = np.asarray(control_points, dtype=float)
    return bool(np.linalg.norm(pts[-1] - pts[0]) <= CLOSED_TOL_M)


NEARLY_CLOSED = 0.05    # a rail whose ends are apart by at most this fraction of its control polygon's
                        # length, but more than CLOSED_TOL_M, looks like a ring and is not one


def off_rail_hint(control_points, u: float) -> str:
    """What to tell a user whose camera's u lies outside [0, 1], by the rail's ends: on a closed
    rail the same place within [0, 1]; on one whose ends nearly meet (NEARLY_CLOSED), that it is
    open and how to close it; otherwise nothing."""
    pts = np.asarray(control_points, dtype=float)
    gap = float(np.linalg.norm(pts[-1] - pts[0]))
    length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
    if gap <= CLOSED_TOL_M:
        return (f"; the rail is closed (its last control point is its first), so u = {u:g} is the "
                f"place u = {u % 1.0:g}: write that")
    if gap <= NEARLY_CLOSED * length:
        return (f"; its ends are {gap * 1e3:.3g} mm apart, so it is open, not a ring: to close it, "
                "make its last control point exactly its first (a closed rail's u wraps in vdo optimize)")
    return ""


def clamped_knots(n: int, p: int) -> np.ndarray:
    """Clamped uniform knot vector on [0, 1] for n control points of degree p (n + p + 1 values)."""
    interior = np.arange(1, n - p) / (n - p)
    return np.concatenate([np.zeros(p + 1), interior, np.ones(p + 1)])


def knot_vector(n: int, p: int, knots=None) -> np.ndarray:
    """The knot vector of n control points of degree p: `knots` (n + p + 1 non-decreasing values,
    clamped: the first p + 1 equal, the last p + 1 equal) mapped onto [0, 1], so that u = 0 is
    the first control point and u = 1 the last; `clamped_knots` without them."""
    if knots is None:
        return clamped_knots(n, p)
    k = np.asarray(knots, dtype=float)
    return (k - k[0]) / (k[-1] - k[0])


def homogeneous(control_points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n, 4): the control points times their weights, and the weights."""
    return np.hstack([control_points * weights[:, None], weights[:, None]])


def point(control_points, degree: int, weights, u, knots=None) -> np.ndarray:
    """C(u) in metres (u.shape + (3,)) on the host, NumPy only (`knot_vector` of `knots`)."""
    pts = np.asarray(control_points, dtype=float)
    w = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=float)
    return de_boor(knot_vector(len(pts), degree, knots), homogeneous(pts, w), degree,
                   np.asarray(u, dtype=float))


def de_boor(knots, homogeneous, p: int, u, xp=np):
    """C(u) (u.shape + (3,)) by de Boor's algorithm on the homogeneous control points (n, 4),
    degree p, for every u at once; `xp` the array module."""
    n = homogeneous.shape[0]
    span = xp.clip(xp.searchsorted(knots, u, side="right") - 1, p, n - 1)
    d = [homogeneous[span - p + j] for j in range(p + 1)]
    for r in range(1, p + 1):
        for j in range(p, r - 1, -1):
            lo = knots[span - p + j]
            hi = knots[span + 1 + j - r]
            alpha = ((u - lo) / xp.where(hi > lo, hi - lo, 1.0))[..., None]
            d[j] = (1.0 - alpha) * d[j - 1] + alpha * d[j]
    return d[p][..., :3] / d[p][..., 3:]
