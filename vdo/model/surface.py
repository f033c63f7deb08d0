"""Curved surfaces: the exact distance from points to a triangle mesh, and the development
(unrolling) of a patch of triangles onto the plane, which gives a curved region of interest its
surface coordinates (u, v) in metres.

Development kinds, tried in this order on the selected triangles (vertices p, face normals n,
areas A; `fit_development`):

* cylinder: the normals are perpendicular to one axis direction a (the eigenvector of the
  area-weighted scatter of the normals about their mean with the smallest eigenvalue, and
  mean n.a = 0 within FIT_ANGLE). In the plane perpendicular to a every face centroid satisfies
  p_perp = c + R n_perp: linear least squares for the axis point c and the signed radius R (R < 0
  when the normals point at the axis, the inside of a pipe), R then refined as the mean vertex
  distance from the axis. Developed exactly: u = R theta, v = (p - c).a, theta the angle about a
  from a reference direction placed in the middle of the largest angular gap (a full ring has a
  period 2 pi |R| in u).
* cone: the normals make one angle with a (|n.a| = sin alpha, alpha the half-angle), and every
  face plane passes through the apex: n.A = n.p, least squares for A. Developed exactly: the
  slant distance s = |p - A| and the developed angle psi = phi sin alpha (phi the angle about a),
  (u, v) = s (sin psi, -cos psi).
* general: least-squares conformal map (LSCM, Levy et al. 2002), solved here with scipy's sparse
  least squares, two far-apart vertices pinned, then scaled to the surface's total area and turned
  so that u runs along the map's longest extent (its principal axis).

A fit is accepted when every vertex lies within `tolerance` of the fitted surface. Every
development reports its area and angle distortion per face (`Development.distortion`): for the
affine map of a triangle from the developed plane to the surface with singular values s1 >= s2,
area ratio s1 s2 and angle distortion s1 / s2 - 1 (both exact for a triangle). A cylinder or a
cone has distortion zero up to the chord-versus-arc difference of its facets, which the samples
take into account (each sample carries the surface area of its developed cell).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from scipy.spatial import cKDTree

from vdo.core.tolerances import TINY

FIT_ANGLE = math.radians(1.0)     # a cylinder's mean |n.a| below sin of this; a cone's above
MERGE_DIGITS = 9                  # vertices equal to 1 nm (metres) are one vertex of the surface
LARGE_DISTORTION = 0.1            # warn above 10 % area or angle distortion (p95 over the area)


def face_frame(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t_u, t_v) with t_u x t_v = normal; t_v follows world z on vertical faces, else world y."""
    up = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t_v = up - normal * (up @ normal)
    t_v /= np.linalg.norm(t_v)
    return np.cross(t_v, normal), t_v


# --------------------------------------------------------------------------------------------
# Distances
# --------------------------------------------------------------------------------------------
def point_triangle_distance(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N,) exact Euclidean distance (m) from points (N, 3) to triangles (N, 3, 3), pairwise:
    the closest point by the Voronoi regions of the triangle's vertices, edges and face
    (Ericson, Real-Time Collision Detection, sec. 5.1.5)."""
    p = np.asarray(points, float)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        closest = a + ab * v[:, None] + ac * w[:, None]                   # inside the face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    regions = [
        (d1 <= 0) & (d2 <= 0), a,                                          # vertex a
        (d3 >= 0) & (d4 <= d3), b,                                         # vertex b
        (d6 >= 0) & (d5 <= d6), c,                                         # vertex c
        (vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[:, None],         # edge ab
        (vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[:, None],         # edge ac
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + (c - b) * t_bc[:, None],  # edge bc
    ]
    done = np.zeros(len(p), dtype=bool)
    for mask, point in zip(regions[::2], regions[1::2]):
        take = mask & ~done
        closest[take] = point[take]
        done |= take
    bad = ~np.all(np.isfinite(closest), axis=1)             # a degenerate triangle: its vertices
    if bad.any():
        closest[bad] = tri[bad][np.arange(bad.sum()), np.argmin(
            np.linalg.norm(tri[bad] - p[bad, None], axis=2), axis=1)]
    return np.linalg.norm(p - closest, axis=1)


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                     chunk: int = 4096) -> np.ndarray:
    """(N,) exact distance (m) from points to the surface of a triangle mesh. The 8 triangles with
    the nearest centroids give an upper bound d0; every triangle whose centroid lies within
    d0 + r_max (r_max the largest centroid-to-vertex distance) can be closer and is checked."""
    points = np.atleast_2d(np.asarray(points, float))
    tri = np.asarray(vertices, float)[np.asarray(faces)]
    centroids = tri.mean(axis=1)
    r_max = float(np.linalg.norm(tri - centroids[:, None], axis=2).max())
    tree = cKDTree(centroids)
    out = np.empty(len(points))
    k = min(8, len(tri))
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk]
        _, near = tree.query(p, k=k)
        near = near.reshape(len(p), k)
        d0 = point_triangle_distance(np.repeat(p, k, axis=0), tri[near.ravel()]).reshape(len(p), k).min(1)
        best = d0.copy()
        for i, cand in enumerate(tree.query_ball_point(p, d0 + r_max)):
            cand = np.asarray(cand, dtype=np.int64)
            if len(cand) > k:
                best[i] = point_triangle_distance(np.repeat(p[i:i + 1], len(cand), 0), tri[cand]).min()
        out[start:start + chunk] = best
    return out


def distance_to_line(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) distance (m) from points to the infinite line through a and b."""
    d = (np.asarray(b, float) - a) / np.linalg.norm(np.asarray(b, float) - a)
    rel = np.asarray(points, float) - a
    return np.linalg.norm(rel - np.outer(rel @ d, d), axis=1)


def line_triangle_distance(tri: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T,) least distance (m) from the triangles (T, 3, 3) to the infinite line through a and b:
    0 where the line pierces a triangle (its barycentric coordinates on the triangle's plane all
    >= 0), else the least over its three edges. The distance to a line is convex, so on a
    triangle the line does not pierce it is least on the boundary (a plane parallel to the line
    holds its least value along a line that leaves the triangle through an edge). An edge p + s e
    (s in [0, 1]) is at distance |w + s e| off the line's direction u (w = p - a, both with
    their u part removed), least at s = -w.e / |e|^2 clipped to [0, 1]."""
    tri = np.asarray(tri, float)
    a = np.asarray(a, float)
    u = (np.asarray(b, float) - a) / np.linalg.norm(np.asarray(b, float) - a)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(u, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > TINY * np.maximum(np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), TINY)
    det = np.where(ok, det, 1.0)
    w = a - tri[:, 0]
    beta = np.einsum("ij,ij->i", w, h) / det
    q = np.cross(w, e1)
    gamma = (q @ u) / det
    pierced = ok & (beta >= 0) & (gamma >= 0) & (beta + gamma <= 1)
    off = lambda x: x - np.outer(x @ u, u)                  # the part across the line
    least = np.full(len(tri), np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        w_i, e = off(tri[:, i] - a), off(tri[:, j] - tri[:, i])
        s = np.clip(-np.einsum("ij,ij->i", w_i, e) / np.maximum(np.einsum("ij,ij->i", e, e), TINY), 0.0, 1.0)
        least = np.minimum(least, np.linalg.norm(w_i + s[:, None] * e, axis=1))
    return np.where(pierced, 0.0, least)


# --------------------------------------------------------------------------------------------
# Developments
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Distortion:
    """Area-weighted distortion of a development over its faces: area ratio surface / developed
    (1 = none) and angle distortion s1 / s2 - 1 (0 = conformal), p95 of the deviation each."""

    area_p95: float     # p95 of |area ratio - 1|
    angle_p95: float    # p95 of s1 / s2 - 1

    @property
    def large(self) -> bool:
        return max(self.area_p95, self.angle_p95) > LARGE_DISTORTION


@dataclass(frozen=True, eq=False)
class Development:
    """The map from a region's surface to the plane, (u, v) in metres.

    kind "cylinder": axis point `centre`, unit `axis`, reference direction `e1` (theta = 0),
    `e2` = axis x e1, signed `radius`; kind "cone": `centre` is the apex, `half_angle` alpha;
    kind "general": `faces_uv` (T, 3, 2), the developed corners of the region's faces `faces`
    (indices into the mesh) and the mesh triangles `triangles` (T, 3, 3) to locate points.
    `period` is the u period of a full cylinder ring (m; 0 when the region is not closed around
    its axis); `turn` the developed angle of a full cone ring, 2 pi sin alpha (rad; 0 when not
    closed): the ring continues across its seam rotated by +-turn about the apex (`across_seam`)."""

    kind: str
    centre: np.ndarray | None = None
    axis: np.ndarray | None = None
    e1: np.ndarray | None = None
    e2: np.ndarray | None = None
    radius: float = 0.0
    half_angle: float = 0.0
    period: float = 0.0
    turn: float = 0.0
    triangles: np.ndarray | None = None
    faces_uv: np.ndarray | None = None
    distortion: Distortion | None = None
    flip: float = 1.0         # -1 mirrors u, so that t_u x t_v is the outward normal

    def _angle(self, points: np.ndarray) -> np.ndarray:
        rel = np.asarray(points, float) - self.centre
        return np.mod(np.arctan2(rel @ self.e2, rel @ self.e1), 2 * np.pi)

    def uv(self, points: np.ndarray) -> np.ndarray:
        """(..., 2) developed coordinates of points (..., 3) on the surface, m."""
        pts = np.asarray(points, float)
        shape = pts.shape[:-1]
        pts = pts.reshape(-1, 3)
        if self.kind == "cylinder":
            out = np.stack([self.flip * self.radius * self._angle(pts),
                            (pts - self.centre) @ self.axis], axis=-1)
        elif self.kind == "cone":
            s = np.linalg.norm(pts - self.centre, axis=1)
            psi = self._angle(pts) * math.sin(self.half_angle)
            out = np.stack([self.flip * s * np.sin(psi), -s * np.cos(psi)], axis=-1)
        else:
            out = self._general_uv(pts)
        return out.reshape(*shape, 2)

    def triangles_uv(self, tri: np.ndarray) -> np.ndarray:
        """(T, 3, 2) developed corners of triangles (T, 3, 3), each triangle kept in one piece
        across a ring's seam (its corners' angles unwrapped to within pi of its first corner's)."""
        if self.kind == "general":
            return self.faces_uv
        uv = self.uv(tri)
        if self.kind == "cylinder":
            theta = self._angle(tri.reshape(-1, 3)).reshape(tri.shape[:2])
            wrap = np.round((theta - theta[:, :1]) / (2 * np.pi))
            uv[..., 0] -= self.flip * self.radius * 2 * np.pi * wrap
        elif self.kind == "cone":
            phi = self._angle(tri.reshape(-1, 3)).reshape(tri.shape[:2])
            phi = phi - 2 * np.pi * np.round((phi - phi[:, :1]) / (2 * np.pi))
            s = np.linalg.norm(tri - self.centre, axis=2)
            psi = phi * math.sin(self.half_angle)
            uv = np.stack([self.flip * s * np.sin(psi), -s * np.cos(psi)], axis=-1)
        return uv

    def _general_uv(self, pts: np.ndarray) -> np.ndarray:
        """A point's developed coordinates by the barycentric coordinates on its nearest face."""
        centroids = self.triangles.mean(axis=1)
        _, idx = cKDTree(centroids).query(pts, k=min(8, len(centroids)))
        idx = idx.reshape(len(pts), -1)
        d = np.stack([point_triangle_distance(pts, self.triangles[idx[:, k]])
                      for k in range(idx.shape[1])], axis=1)
        face = idx[np.arange(len(pts)), np.argmin(d, axis=1)]
        tri = self.triangles[face]
        e1, e2, q = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], pts - tri[:, 0]
        g = np.stack([np.stack([np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2)], -1),
                      np.stack([np.einsum("ij,ij->i", e1, e2), np.einsum("ij,ij->i", e2, e2)], -1)], -2)
        rhs = np.stack([np.einsum("ij,ij->i", e1, q), np.einsum("ij,ij->i", e2, q)], -1)
        l12 = np.linalg.solve(g, rhs[..., None])[..., 0]
        uv = self.faces_uv[face]
        return uv[:, 0] + l12[:, :1] * (uv[:, 1] - uv[:, 0]) + l12[:, 1:] * (uv[:, 2] - uv[:, 0])


def across_seam(uv: np.ndarray, turn: float, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the points of a closed cone ring near its seam lie when the development is continued
    across the seam: (indices (M,) into uv, their images (M, 2) m). The developed ring is the
    sector psi in [0, |turn|] about the apex (the origin of (u, v) = s (sin psi, -cos psi), u
    mirrored when turn < 0); a point within `reach` (m, along its circle) of the start edge
    reappears at psi + |turn|, one within `reach` of the end edge at psi - |turn|. The images keep
    at least half the gap 2 pi - |turn| away from the sector's other edge, so that a cone whose
    development nearly closes (half-angle near 90 deg) does not overlap itself."""
    uv = np.asarray(uv, float)
    sign, theta = math.copysign(1.0, turn), abs(turn)
    s = np.hypot(uv[:, 0], uv[:, 1])
    half_gap = (2 * math.pi - theta) / 2
    psi = np.mod(np.arctan2(sign * uv[:, 0], -uv[:, 1]) + half_gap, 2 * math.pi) - half_gap
    band = np.minimum(reach / np.maximum(s, 1e-300), half_gap)
    start = np.flatnonzero(psi < band)
    end = np.flatnonzero(theta - psi < band)
    idx = np.concatenate([start, end])
    moved = np.concatenate([psi[start] + theta, psi[end] - theta])
    return idx, np.stack([sign * s[idx] * np.sin(moved), -s[idx] * np.cos(moved)], axis=-1)


class CellIndex:
    """Integer grid cells (M, 2) -> a value per cell (default: the cell's row), looked up for many
    cells at once on sorted 64-bit keys (no Python loop); a cell listed twice keeps its first
    value. Cell indices must lie within +-2^31."""

    def __init__(self, cells, values=None):
        cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        values = np.arange(len(cells)) if values is None else np.asarray(values, dtype=np.int64)
        self._keys, first = np.unique(_cell_keys(cells), return_index=True)
        self._values = values[first]

    def find(self, cells) -> np.ndarray:
        """(K,) the value of each of `cells` (K, 2), -1 where a cell is not in the index."""
        q = _cell_keys(np.asarray(cells, dtype=np.int64).reshape(-1, 2))
        if self._keys.size == 0:
            return np.full(len(q), -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self._keys, q), self._keys.size - 1)
        return np.where(self._keys[pos] == q, self._values[pos], -1)


def _cell_keys(cells: np.ndarray) -> np.ndarray:
    """One int64 per cell (i, j): i * 2^32 + (j + 2^31), ordered as (i, j)."""
    return cells[:, 0] * (1 << 32) + (cells[:, 1] + (1 << 31))


def across_seam_grid(cells: np.ndarray, step: float, turn: float, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The grid version of `across_seam`: of the grid points beside a closed cone ring's seam (integer
    indices, point (i + 1/2) step), the ones that continue the cells `cells` (M, 2) across it,
    each with the index into `cells` of the cell it continues: (grid points (G, 2), owners (G,)).
    Pulled, not pushed: each grid point next to a pushed image is taken back across the seam and
    kept when it lands in a cell, so that the turned grid leaves no holes."""
    cells = np.asarray(cells, np.int64)
    _, image = across_seam((cells + 0.5) * step, turn, reach)
    near = np.round(image / step - 0.5).astype(np.int64)
    ring = np.array([[di, dj] for di in (-1, 0, 1) for dj in (-1, 0, 1)])
    grid = np.unique((near[:, None, :] + ring[None]).reshape(-1, 2), axis=0)
    back_idx, back = across_seam((grid + 0.5) * step, turn, 2 * reach)
    landed = np.round(back / step - 0.5).astype(np.int64)
    index = CellIndex(cells)
    owner = index.find(landed)
    keep = (owner >= 0) & (index.find(grid[back_idx]) < 0)
    return grid[back_idx][keep], owner[keep]


def face_distortion(tri: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle (area ratio surface / developed, angle distortion s1 / s2 - 1) of the affine
    map from the developed triangle uv (T, 3, 2) to the surface triangle tri (T, 3, 3)."""
    E = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=-1)          # (T, 3, 2)
    D = np.stack([uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], axis=-1)              # (T, 2, 2)
    det = np.linalg.det(D)
    ok = np.abs(det) > 1e-300
    J = np.zeros_like(E)
    J[ok] = E[ok] @ np.linalg.inv(D[ok])
    s = np.linalg.svd(J, compute_uv=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ok, s[:, 0] * s[:, 1], np.inf), np.where(ok, s[:, 0] / s[:, 1] - 1, np.inf)


def distortion_of(tri: np.ndarray, uv: np.ndarray) -> Distortion:
    """`Distortion` (area-weighted p95) of the developed triangles uv of surface triangles tri."""
    area_ratio, angle = face_distortion(tri, uv)
    weight = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)

    def p95(x):
        order = np.argsort(x)
        cum = np.cumsum(weight[order])
        return float(x[order][np.searchsorted(cum, 0.95 * cum[-1])])

    return Distortion(p95(np.abs(area_ratio - 1)), p95(angle))


def _axis_of(normals: np.ndarray, areas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(axis, eigenvalues ascending) of the area-weighted scatter of the normals about their mean."""
    w = areas / areas.sum()
    mean = w @ normals
    rel = normals - mean
    lam, vec = np.linalg.eigh((rel * w[:, None]).T @ rel)
    return vec[:, 0], lam


def _frame(axis: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e1 = reference - axis * (reference @ axis)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def _gap_reference(angles: np.ndarray, e1: np.ndarray, e2: np.ndarray, widest: float):
    """(reference direction in the middle of the largest gap of `angles`, closed?): a region is
    closed around its axis when no gap between its vertices' angles exceeds 1.5 x the widest
    angle a single face spans."""
    a = np.sort(np.mod(angles, 2 * np.pi))
    gaps = np.diff(np.r_[a, a[0] + 2 * np.pi])
    k = int(np.argmax(gaps))
    mid = a[k] + gaps[k] / 2
    closed = gaps[k] <= 1.5 * widest
    return math.cos(mid) * e1 + math.sin(mid) * e2, closed


def _orient(dev: Development, tri: np.ndarray, normals: np.ndarray) -> Development:
    """`dev` with u mirrored when the developed faces are wound against their normals (so that
    t_u x t_v = n)."""
    uv = dev.triangles_uv(tri)
    d = np.stack([uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], axis=1)
    det2 = d[:, 0, 0] * d[:, 1, 1] - d[:, 0, 1] * d[:, 1, 0]
    if np.sum(np.sign(det2)) < 0:
        dev = Development(**{**dev.__dict__, "flip": -dev.flip})
        if dev.kind == "general":
            dev = Development(**{**dev.__dict__, "faces_uv": dev.faces_uv * [-1.0, 1.0], "flip": 1.0})
    return dev


def _canonical(axis: np.ndarray) -> np.ndarray:
    """The axis direction with v increasing upward: its z component positive (else x, else y)."""
    for k in (2, 0, 1):
        if abs(axis[k]) > 1e-6:
            return axis if axis[k] > 0 else -axis
    return axis


def fit_cylinder(tri: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 tolerance: float) -> Development | None:
    """The cylinder through the triangles (module docstring), or None when they are not on one
    (a vertex farther than `tolerance` from it, or the normals not perpendicular to one axis).
    The axis points up (`_canonical`), so that a map's v runs up a vertical cylinder."""
    axis, lam = _axis_of(normals, areas)
    axis = _canonical(axis)
    w = areas / areas.sum()
    if abs(w @ (normals @ axis)) > math.sin(FIT_ANGLE) or lam[1] < 1e-8:
        return None
    e1, e2 = _frame(axis, np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, 0])
    cen = tri.mean(axis=1)
    n2 = np.stack([normals @ e1, normals @ e2], axis=1)
    p2 = np.stack([cen @ e1, cen @ e2], axis=1)
    # p2 = c + R n2 per face: unknowns (c1, c2, R)
    A = np.zeros((2 * len(p2), 3))
    A[0::2, 0], A[1::2, 1] = 1.0, 1.0
    A[:, 2] = n2.ravel()
    sol, *_ = np.linalg.lstsq(A * np.repeat(np.sqrt(w), 2)[:, None], p2.ravel() * np.repeat(np.sqrt(w), 2),
                              rcond=None)
    c2, signed = sol[:2], sol[2]
    verts = tri.reshape(-1, 3)
    r = np.linalg.norm(np.stack([verts @ e1, verts @ e2], axis=1) - c2, axis=1)
    radius = float(r.max())     # a tessellation's vertices lie on the surface, its facets and the
    # points where a region's box or band cuts them inside it (a chord's sagitta)
    if abs(signed) < 1e-12 or np.abs(r - radius).max() > tolerance:
        return None
    centre = c2[0] * e1 + c2[1] * e2
    rel = verts - centre
    angles = np.arctan2(rel @ e2, rel @ e1)
    corner = np.arctan2((tri - centre) @ e2, (tri - centre) @ e1)
    spread = np.abs(np.angle(np.exp(1j * (corner[:, :, None] - corner[:, None, :])))).max()
    reference, closed = _gap_reference(angles, e1, e2, float(spread))
    e1, e2 = _frame(axis, reference)
    dev = Development("cylinder", centre=centre, axis=axis, e1=e1, e2=e2,
                      radius=math.copysign(radius, signed),
                      period=2 * math.pi * radius if closed else 0.0)
    dev = _orient(dev, tri, normals)
    return Development(**{**dev.__dict__, "distortion": distortion_of(tri, dev.triangles_uv(tri))})


def fit_cone(tri: np.ndarray, normals: np.ndarray, areas: np.ndarray,
             tolerance: float) -> Development | None:
    """The cone through the triangles (module docstring), or None."""
    axis, lam = _axis_of(normals, areas)
    w = areas / areas.sum()
    along = normals @ axis
    if abs(w @ along) <= math.sin(FIT_ANGLE) or lam[1] < 1e-8:
        return None
    if w @ along < 0:
        axis = -axis
    cen = tri.mean(axis=1)
    sw = np.sqrt(w)[:, None]
    apex, *_ = np.linalg.lstsq(normals * sw, np.einsum("ij,ij->i", normals, cen) * sw[:, 0], rcond=None)
    # the axis points from the apex into the cone
    verts = tri.reshape(-1, 3)
    rel = verts - apex
    if np.mean(rel @ axis) < 0:
        axis = -axis
    s = np.linalg.norm(rel, axis=1)
    beta = np.arccos(np.clip((rel @ axis) / np.maximum(s, 1e-300), -1, 1))
    alpha = float(np.average(beta, weights=s))
    if not 1e-3 < alpha < math.pi / 2 - 1e-3 or np.abs(s * np.sin(beta - alpha)).max() > tolerance:
        return None
    e1, e2 = _frame(axis, np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, 0])
    corner = np.arctan2((tri - apex) @ e2, (tri - apex) @ e1)
    spread = np.abs(np.angle(np.exp(1j * (corner[:, :, None] - corner[:, None, :])))).max()
    reference, closed = _gap_reference(np.arctan2(rel @ e2, rel @ e1), e1, e2, float(spread))
    e1, e2 = _frame(axis, reference)
    dev = Development("cone", centre=apex, axis=axis, e1=e1, e2=e2, half_angle=alpha,
                      turn=2 * math.pi * math.sin(alpha) if closed else 0.0)
    dev = _orient(dev, tri, normals)
    return Development(**{**dev.__dict__, "distortion": distortion_of(tri, dev.triangles_uv(tri))})


def merged(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3), faces (T, 3)) of a triangle soup with equal corners (to 1 nm) merged."""
    key = np.round(tri.reshape(-1, 3), MERGE_DIGITS)
    vertices, inverse = np.unique(key, axis=0, return_inverse=True)
    return vertices, inverse.reshape(-1, 3)


def components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(T,) label of the edge-connected piece each face belongs to."""
    t = np.repeat(np.arange(len(faces)), 3)
    inc = scipy.sparse.csr_matrix((np.ones(len(t)), (t, faces.ravel())), shape=(len(faces), n_vertices))
    _, labels = scipy.sparse.csgraph.connected_components(inc @ inc.T, directed=False)
    return labels


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The patch's distinct edges (E, 2) (vertex pairs, smaller index first) and how many faces
    use each (E,)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)


def boundary_loops(faces: np.ndarray, n_vertices: int) -> list[np.ndarray]:
    """The vertex indices of each boundary loop of a merged patch (`merged`): the edges that one
    face alone uses, grouped by connection."""
    unique, count = _edges(faces)
    rim = unique[count == 1]
    if len(rim) == 0:
        return []
    graph = scipy.sparse.csr_matrix((np.ones(len(rim)), (rim[:, 0], rim[:, 1])), shape=(n_vertices, n_vertices))
    _, label = scipy.sparse.csgraph.connected_components(graph, directed=False)
    on = np.unique(rim)
    return [on[label[on] == k] for k in np.unique(label[on])]


def cut_ring(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A patch with the topology of a ring (two boundary loops, Euler characteristic
    V - E + F = 0: a tube, a knuckle band, a band around a hole) cut open into a strip, so that
    a map of it to the plane need not close on itself (the LSCM of a ring squeezes it into an
    annulus). The seam is the half-plane theta = pi about the axis through the first loop's
    centroid, normal to its best-fit plane (the axis a tube's end, a band's rim or a hole's edge
    turns about): each face whose corners' angles theta span more than pi takes copies of its
    corners at theta < 0. Other patches, or a cut that does not leave one boundary loop, are
    returned as they are."""
    loops = boundary_loops(faces, len(vertices))
    if len(loops) != 2 or len(vertices) - len(_edges(faces)[0]) + len(faces) != 0:
        return vertices, faces
    rim = vertices[loops[0]]
    centre = rim.mean(axis=0)
    axis = np.linalg.svd(rim - centre)[2][-1]
    e1 = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, 0]
    e2 = np.cross(axis, e1)
    rel = vertices - centre
    theta = np.arctan2(rel @ e2, rel @ e1)
    corner = theta[faces]
    crossing = corner.max(axis=1) - corner.min(axis=1) > np.pi
    copy = crossing[:, None] & (corner < 0)
    if not copy.any():
        return vertices, faces
    moved = np.unique(faces[copy])
    index = np.full(len(vertices), -1)
    index[moved] = len(vertices) + np.arange(len(moved))
    cut = faces.copy()
    cut[copy] = index[faces[copy]]
    out = np.concatenate([vertices, vertices[moved]])
    if len(boundary_loops(cut, len(out))) != 1:
        return vertices, faces
    return out, cut


def lscm(tri: np.ndarray) -> Development:
    """The least-squares conformal map of a connected patch of triangles (module docstring).

    Each face, in its own orthonormal 2D frame with corners (x_j, y_j), contributes
    |sum_j W_j U_j|^2 / (2 A) with W_j = (x_{j+2} - x_{j+1}) + i (y_{j+2} - y_{j+1}) and U_j = u_j
    + i v_j; the two vertices farthest apart are pinned at (0, 0) and (d, 0), the remaining
    vertices solve the real least-squares system, the map is scaled so that its developed
    area equals the surface area and turned so that u runs along its longest extent (the
    principal axis of the faces' developed centroids, area-weighted, pointing from the first pin
    to the second): the pins alone would set u along a diagonal of a band (a pipe bend's
    intrados: 17-34 degrees off its length), and the samples' strain frames (t_u, t_v) follow u.
    A ring (`cut_ring`) is also mapped cut open into a strip, and the map of the two with the
    smaller distortion (p95 of the area's, then the angle's) is kept: a tube or a knuckle band
    opens into a strip (a tube with a lip: 984 % -> 3 % in area), a wide band around a small
    hole stays whole (cut open: 9 % -> 44 %)."""
    vertices, faces = merged(tri)
    best = _conformal(tri, vertices, faces)
    opened = cut_ring(vertices, faces)
    if opened[0] is not vertices:
        other = _conformal(tri, *opened)
        key = lambda d: (d.distortion.area_p95, d.distortion.angle_p95)
        best = other if key(other) < key(best) else best
    return best


def _conformal(tri: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> Development:
    """`lscm` of the triangles `tri` on the patch (vertices, faces) (merged, or cut open)."""
    p = vertices[faces]
    e1 = p[:, 1] - p[:, 0]
    n = np.cross(e1, p[:, 2] - p[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    keep = area2 > 1e-300
    ex = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-300)
    ey = np.cross(n / np.maximum(area2, 1e-300)[:, None], ex)
    x = np.einsum("tkj,tj->tk", p - p[:, :1], ex)
    y = np.einsum("tkj,tj->tk", p - p[:, :1], ey)
    W = (np.roll(x, -2, axis=1) - np.roll(x, -1, axis=1)) + 1j * (np.roll(y, -2, axis=1) - np.roll(y, -1, axis=1))
    W = W[keep] / np.sqrt(area2[keep])[:, None]
    rows = np.repeat(np.arange(keep.sum()), 3)
    cols = faces[keep].ravel()
    V = len(vertices)
    Mr = scipy.sparse.csr_matrix((W.real.ravel(), (rows, cols)), shape=(keep.sum(), V))
    Mi = scipy.sparse.csr_matrix((W.imag.ravel(), (rows, cols)), shape=(keep.sum(), V))
    A = scipy.sparse.bmat([[Mr, -Mi], [Mi, Mr]]).tocsc()
    # pins: the two vertices farthest apart (from the farthest from the first vertex, twice)
    i = int(np.argmax(np.linalg.norm(vertices - vertices[0], axis=1)))
    j = int(np.argmax(np.linalg.norm(vertices - vertices[i], axis=1)))
    d = float(np.linalg.norm(vertices[j] - vertices[i]))
    pinned = np.zeros(2 * V, dtype=bool)
    pinned[[i, j, V + i, V + j]] = True
    values = np.zeros(2 * V)
    values[j] = d
    free = ~pinned
    solution = scipy.sparse.linalg.lsqr(A[:, free], -A[:, pinned] @ values[pinned],
                                        atol=1e-12, btol=1e-12, iter_lim=20 * V)[0]
    values[free] = solution
    uv = np.stack([values[:V], values[V:]], axis=1)
    faces_uv = uv[faces]
    d2 = np.stack([faces_uv[:, 1] - faces_uv[:, 0], faces_uv[:, 2] - faces_uv[:, 0]], axis=1)
    area_uv = np.abs(d2[:, 0, 0] * d2[:, 1, 1] - d2[:, 0, 1] * d2[:, 1, 0]).sum()
    faces_uv = faces_uv * math.sqrt(area2.sum() / max(area_uv, 1e-300))
    # Turn the map so that u runs along its longest extent: the principal axis e of the faces'
    # developed centroids (area-weighted second moments), from the first pin towards the second.
    weight = area2 / area2.sum()
    centroid = faces_uv.mean(axis=1)
    mean = weight @ centroid
    spread = np.einsum("t,ti,tj->ij", weight, centroid - mean, centroid - mean)
    e = np.linalg.eigh(spread)[1][:, -1]
    e = e if e @ (uv[j] - uv[i]) >= 0 else -e
    faces_uv = faces_uv @ np.array([[e[0], -e[1]], [e[1], e[0]]])      # a rotation: (u, v) -> (u.e, u x e)
    normals = n / np.maximum(area2, 1e-300)[:, None]
    dev = _orient(Development("general", triangles=np.asarray(tri, float), faces_uv=faces_uv), tri, normals)
    return Development(**{**dev.__dict__, "distortion": distortion_of(tri, dev.faces_uv)})


def fit_development(tri: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                    tolerance: float) -> Development:
    """The development of a connected, curved patch of triangles: a cylinder or a cone when the
    triangles lie on one within `tolerance` (m), else the LSCM (module docstring)."""
    return fit_cylinder(tri, normals, areas, tolerance) or fit_cone(tri, normals, areas, tolerance) \
        or lscm(tri)
