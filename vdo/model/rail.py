"""Camera rails: NURBS curves in world space, evaluated in JAX so that d(position)/du exists.

A rail is a clamped B-spline of degree p >= 1 with control points P_i (metres) and weights w_i
(all 1 for a plain B-spline, i.e. a polyline when p = 1). Its knot vector is clamped, uniform on
[0, 1] or the user's mapped onto [0, 1] (a CAD circle's double knots), so u = 0 is the first
control point and u = 1 the last:

    C(u) = sum_i N_{i,p}(u) w_i P_i / sum_i N_{i,p}(u) w_i

evaluated with de Boor's algorithm on homogeneous points (w P, w).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from vdo.model.nurbs import de_boor, homogeneous, is_closed, knot_vector


@dataclass(frozen=True, eq=False)
class Rail:
    """A NURBS rail. `control_points` (n, 3) in metres, `weights` (n,), `degree` p with 1 <= p < n,
    `knots` (n + p + 1, clamped; None: uniform)."""

    name: str
    control_points: np.ndarray
    degree: int = 1
    weights: np.ndarray | None = None
    knots_given: np.ndarray | None = None

    def __post_init__(self):
        pts = np.asarray(self.control_points, dtype=float)
        n = len(pts)
        if pts.ndim != 2 or pts.shape[1] != 3 or n < 2:
            raise ValueError("control_points must be an (n >= 2, 3) array")
        if not 1 <= self.degree < n:
            raise ValueError(f"degree must be in [1, {n - 1}] for {n} control points")
        w = np.ones(n) if self.weights is None else np.asarray(self.weights, dtype=float)
        if w.shape != (n,) or np.any(w <= 0):
            raise ValueError("weights must be n positive numbers")
        object.__setattr__(self, "control_points", pts)
        object.__setattr__(self, "weights", w)

    @property
    def closed(self) -> bool:
        """A ring: u and u + 1 are the same place (`vdo.model.nurbs.is_closed`)."""
        return is_closed(self.control_points)

    @property
    def knots(self) -> np.ndarray:
        """The knot vector on [0, 1] (n + p + 1 values; `vdo.model.nurbs.knot_vector`)."""
        return knot_vector(len(self.control_points), self.degree, self.knots_given)

    def position(self, u, xp=jnp):
        """C(u) in metres, for scalar or array u in [0, 1] (shape u.shape + (3,)). JAX-traceable;
        `xp` = NumPy evaluates on the host without a JAX dispatch per operation."""
        u = xp.asarray(u, dtype=xp.float64)
        return de_boor(xp.asarray(self.knots), xp.asarray(self._homogeneous), self.degree, u, xp)

    def tangent(self, u):
        """dC/du in metres per unit of u (forward-mode derivative of `position`)."""
        u = jnp.asarray(u, dtype=jnp.float64)
        return jnp.vectorize(lambda s: jax.jvp(self._point, (s,), (jnp.ones_like(s),))[1],
                             signature="()->(3)")(u)

    def _point(self, u):
        return de_boor(jnp.asarray(self.knots), jnp.asarray(self._homogeneous), self.degree, u, jnp)

    @property
    def _homogeneous(self) -> np.ndarray:
        """(n, 4): the control points times their weights, and the weights."""
        return homogeneous(self.control_points, self.weights)

    def arc_length(self, u: float) -> float:
        """Length along the rail from u = 0 to u, in metres: 16-point Gauss-Legendre quadrature of
        |dC/du| on each knot span (the speed may jump at a knot), the spans clipped to [0, u], all
        in one compiled call per rail."""
        nodes, weights = np.polynomial.legendre.leggauss(16)
        knots = np.unique(self.knots)
        a, b = np.clip(knots[:-1], 0.0, u), np.clip(knots[1:], 0.0, u)
        grid = 0.5 * (b - a)[:, None] * nodes + 0.5 * (a + b)[:, None]   # (spans, 16)
        speed = np.linalg.norm(np.asarray(_speeds(self.knots, self._homogeneous, self.degree, grid)), axis=-1)
        return float(np.sum(0.5 * (b - a) * (speed @ weights)))


@functools.partial(jax.jit, static_argnums=2)
def _speeds(knots, homogeneous, p: int, u):
    """dC/du at every u: one compiled program for all rails of the same size and degree."""
    point = lambda s: de_boor(knots, homogeneous, p, s, jnp)
    return jnp.vectorize(lambda s: jax.jvp(point, (s,), (jnp.ones_like(s),))[1], signature="()->(3)")(u)
