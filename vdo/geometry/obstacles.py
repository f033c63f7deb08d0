"""A camera's own hardware as an obstacle to the other cameras' sight lines, in closed form.

The body is the union of spheres of `vdo.scene.camera_body_spheres` and, for a camera on a zone
mount with a `[mount.tripod]`, the tripod's legs and column are capsules around the axes of
`vdo.scene.tripod_cylinders` (the cylinders that the scene meshes as prisms). A sight line from a
camera's optical centre C to a surface point X is hidden when the segment CX passes within a
sphere's radius of its centre, or within a capsule's radius of its axis segment (the capsule's
rounded ends overshoot a cylinder by at most its radius, 1–2 cm). `vdo design` uses this to keep
a selected camera out of another's view (`vdo.design.feasibility.Feasibility`); the layout's own
ray cast against the meshes stays the judge (`constraints.json`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vdo.core.tolerances import TINY
from vdo.scene import camera_body_spheres, tripod_cylinders


@dataclass(frozen=True)
class Hardware:
    """One camera's body spheres (centres (S, 3), radii (S,)) and tripod capsules (axis ends
    tops, bottoms (Q, 3), radii widths (Q,)), world frame, metres; `bound_centre` and
    `bound_radius` enclose them all."""

    centres: np.ndarray
    radii: np.ndarray
    tops: np.ndarray
    bottoms: np.ndarray
    widths: np.ndarray
    bound_centre: np.ndarray
    bound_radius: float


def hardware(camera, tripod=None) -> Hardware:
    """The `Hardware` of `camera` (a `vdo.model.camera.Camera`), on `tripod` (a
    `TripodSpec`, or None): body spheres X_world = X_cam R + C (X_cam from
    `camera_body_spheres`), the tripod's `tripod_cylinders` as capsules."""
    local, radii = camera_body_spheres(camera.focal_length)
    centres = local @ camera.R + np.asarray(camera.position, float)
    parts = tripod_cylinders(camera, tripod) if tripod is not None else []
    tops = np.array([p[0] for p in parts]).reshape(-1, 3)
    bottoms = np.array([p[1] for p in parts]).reshape(-1, 3)
    widths = np.array([p[2] for p in parts], dtype=float)
    ends = np.vstack([centres, tops, bottoms])
    middle = 0.5 * (ends.min(axis=0) + ends.max(axis=0))
    reach = np.concatenate([np.linalg.norm(centres - middle, axis=1) + radii,
                            np.linalg.norm(tops - middle, axis=1) + widths,
                            np.linalg.norm(bottoms - middle, axis=1) + widths])
    return Hardware(centres, np.asarray(radii, float), tops, bottoms, widths, middle, float(reach.max()))


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (m) from points p to segments ab (broadcast over the leading axes, last axis 3):
    |a + t (b - a) - p| with t = clip((p - a).(b - a) / |b - a|^2, 0, 1)."""
    d = b - a
    t = np.clip(np.einsum("...i,...i->...", p - a, d) / np.maximum(np.einsum("...i,...i->...", d, d), TINY), 0, 1)
    return np.linalg.norm(a + t[..., None] * d - p, axis=-1)


def segment_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Distance (m) between segments a0a1 and b0b1 (broadcast, last axis 3): the closest points
    a0 + s d1, b0 + t d2 minimise the distance over s, t in [0, 1] (the unconstrained minimum,
    s then t clamped, s recomputed where t was clamped); parallel segments take s = 0."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    b = np.einsum("...i,...i->...", d1, d2)
    c = np.einsum("...i,...i->...", d1, r)
    f = np.einsum("...i,...i->...", d2, r)
    denom = a * e - b * b
    s = np.where(denom > TINY * np.maximum(a * e, TINY), np.clip((b * f - c * e) / np.maximum(denom, TINY), 0, 1), 0.0)
    t = (b * s + f) / np.maximum(e, TINY)
    s = np.where(t < 0, np.clip(-c / np.maximum(a, TINY), 0, 1), np.where(t > 1, np.clip((b - c) / np.maximum(a, TINY), 0, 1), s))
    t = np.clip(t, 0, 1)
    return np.linalg.norm(a0 + s[..., None] * d1 - b0 - t[..., None] * d2, axis=-1)


LINES_CHUNK = 1 << 16    # sight lines tested at once: the distance arrays of a chunk (lines x
#                          spheres or capsules x 3 float64) stay tens of MB, whatever the count


def hidden(starts: np.ndarray, ends: np.ndarray, hw: Hardware) -> np.ndarray:
    """(M,) True where the sight line starts -> ends (M, 3) passes through the hardware `hw`,
    LINES_CHUNK lines at a time (a design's feasibility tests every stored sight line: millions)."""
    starts, ends = np.asarray(starts, float), np.asarray(ends, float)
    out = np.zeros(len(starts), dtype=bool)
    for lo in range(0, len(starts), LINES_CHUNK):
        a, b = starts[lo:lo + LINES_CHUNK], ends[lo:lo + LINES_CHUNK]
        near = np.flatnonzero(point_segment_distance(hw.bound_centre, a, b) < hw.bound_radius)
        if near.size == 0:
            continue
        s, e = a[near, None], b[near, None]
        hit = (point_segment_distance(hw.centres[None], s, e) < hw.radii[None]).any(axis=1)
        if len(hw.widths):
            hit |= (segment_distance(s, e, hw.tops[None], hw.bottoms[None]) < hw.widths[None]).any(axis=1)
        out[lo + near] = hit
    return out
