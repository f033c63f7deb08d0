"""Named tolerances: every comparison that needs slack names its reason here, once.

Lengths are in metres, angles in radians; relative tolerances are fractions. A module that needs
a tolerance of its own kind (a solver's stopping rule, a unit conversion) keeps it beside its
code, with a comment; what two modules share is defined here.
"""

IN_FRONT_M = 1e-3
"""A point is in front of a camera when its depth along the optical axis, Z_c, exceeds this (m).
The one threshold of the hard ray cast (`vdo.physics.visibility`), the smooth weights
(`vdo.objective`) and the field-of-view check (`vdo.constraints`)."""

RAY_OFFSET_M = 1e-4
"""Rays start this far off a surface and stop this short of their end (m): a camera's centre
for visibility rays, a light panel for shadow rays. Far below a sample spacing, far above the
float32 resolution of Mitsuba's intersections at metre scale (~1e-7 m)."""

LIMIT_SLACK = 1e-9
"""Slack when a computed quantity is compared with a limit it may equal after rounding (angles
in rad, counts, lengths in m): `x <= limit + LIMIT_SLACK`."""

CHECK_MET_REL = 1e-6
"""A constraint check is met within this fraction of its limit's scale (`vdo.constraints`)."""

BARYCENTRIC_SLACK = 1e-6
"""A point is inside a triangle when its barycentric coordinates are >= -BARYCENTRIC_SLACK
and sum to <= 1 + BARYCENTRIC_SLACK."""

TINY = 1e-30
"""Floor of a denominator that is zero only when its numerator is (an empty area, a zero
weight): x / max(d, TINY)."""

SMOOTH_SQRT = 1e-12
"""Added under a square root that JAX differentiates (m^2 or rad^2): sqrt(x + SMOOTH_SQRT) has a
finite gradient at x = 0."""

SIZE_TOLERANCE = 1e-6
"""Relative: a size may exceed the side it must fit in by this fraction and still fit (`fits`).
Sides are sums of float coordinates (a patch of side w measured back as 0.005999999999999998 m
for 6 mm), so an equal size must not be refused; 1e-6 is far above float64 rounding (1e-16
relative) and far below any size a user chooses (a micrometre per metre)."""


def fits(size: float, side: float) -> bool:
    """Whether a size (m) fits in a side (m): size <= side (1 + SIZE_TOLERANCE), so that sizes
    equal up to rounding fit."""
    return size <= side * (1.0 + SIZE_TOLERANCE)
