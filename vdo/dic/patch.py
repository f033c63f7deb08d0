"""The planar patch a correlation integrates over and the points it integrates at.

* `Patch`: the rectangle X(ξ) = origin + ξ1 t_u + ξ2 t_v, ξ in [0, size] (metres), the face
  coordinates (u, v) of `vdo.scene.RegionFaces.uv`.
* `footprint`: a camera's pixel footprint A = ∂x/∂ξ on it (pixel/m).
* `integration_points`: a cell-centred ξ grid seen by every camera (about one point per pixel of
  the best camera), and `pixel_points`: the rays of one camera's pixel centres met on the patch;
  both keep only the points every camera sees in front of it, not at grazing incidence and
  `margin_px` inside its image.
* `q4_shape_functions`: the bilinear shape functions of an nx × ny element mesh of the patch.

The geometry under `vdo.dic.correlate` and `vdo.dic.subsets`; with `vdo.dic.images`, the lowest
module of `vdo.dic`: it imports nothing of the package.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["Patch", "footprint", "integration_points", "pixel_points", "q4_shape_functions"]


@dataclass(frozen=True, eq=False)
class Patch:
    """Planar rectangle X(ξ) = origin + ξ1 t_u + ξ2 t_v, ξ in [0, size[0]] × [0, size[1]] (metres).
    t_u and t_v are orthonormal (checked)."""

    origin: np.ndarray
    t_u: np.ndarray
    t_v: np.ndarray
    size: np.ndarray

    def __post_init__(self):
        for name in ("origin", "t_u", "t_v"):
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise ValueError(f"Patch.{name}: expected 3 finite numbers, got {a!r}")
            object.__setattr__(self, name, a)
        s = np.asarray(self.size, dtype=float)
        if s.shape != (2,) or not np.all(s > 0):
            raise ValueError(f"Patch.size: expected 2 positive lengths, got {s!r}")
        object.__setattr__(self, "size", s)
        if abs(np.linalg.norm(self.t_u) - 1) > 1e-9 or abs(np.linalg.norm(self.t_v) - 1) > 1e-9 \
                or abs(self.t_u @ self.t_v) > 1e-9:
            raise ValueError("Patch: t_u and t_v must be orthonormal")

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.t_u, self.t_v)

    @property
    def tangents(self) -> np.ndarray:
        """[t_u t_v] as a (3, 2) matrix: dX = tangents @ dξ."""
        return np.stack([self.t_u, self.t_v], axis=1)

    def points(self, xi) -> np.ndarray:
        xi = np.asarray(xi, dtype=float)
        return self.origin + xi[..., :1] * self.t_u + xi[..., 1:2] * self.t_v


def footprint(camera, patch: Patch, X) -> np.ndarray:
    """The camera's pixel footprint on the patch, A = ∂x/∂ξ = (∂x/∂X) [t_u t_v] (..., 2, 2) pixel/m,
    at points X (..., 3) of the patch (`Camera.sensitivity` times `Patch.tangents`): |det A| is
    the number of that camera's pixels per m² of the patch."""
    return camera.sensitivity(X) @ patch.tangents


def integration_points(patch: Patch, cameras: Sequence, spacing: float | None = None,
                       density: float = 1.0, margin_px: float = 3.0, min_cos: float = 0.05):
    """Cell-centred grid ξ (N, 2) on the patch and its cell area, keeping the points that every
    camera sees in front of it, not at grazing incidence (|cos| >= min_cos), and at least
    `margin_px` inside its image. The default spacing is 1 / (density × the best camera's largest
    linear pixel density sqrt|det A| over a 9 × 9 probe of the patch): about one point per pixel
    of the best camera at density 1. Returns (xi, cell_area)."""
    if spacing is None:
        g = (np.arange(9) + 0.5) / 9
        probe = np.stack(np.meshgrid(g * patch.size[0], g * patch.size[1], indexing="xy"), -1)
        probe = probe.reshape(-1, 2)
        Xp = patch.points(probe)
        best = 0.0
        for cam in cameras:
            ok = _visible(cam, patch, Xp, margin_px, min_cos)
            if ok.any():
                best = max(best, float(np.sqrt(np.abs(np.linalg.det(footprint(cam, patch, Xp[ok])))).max()))
        if best == 0.0:
            raise ValueError("integration_points: no camera sees the patch")
        spacing = 1.0 / (density * best)
    n = np.maximum(1, np.ceil(patch.size / spacing).astype(int))
    h = patch.size / n
    xi = np.stack(np.meshgrid((np.arange(n[0]) + 0.5) * h[0], (np.arange(n[1]) + 0.5) * h[1],
                              indexing="xy"), -1).reshape(-1, 2)
    X = patch.points(xi)
    keep = np.ones(len(xi), dtype=bool)
    for cam in cameras:
        keep &= _visible(cam, patch, X, margin_px, min_cos)
    return xi[keep], float(h[0] * h[1])


def _visible(cam, patch, X, margin_px, min_cos):
    """(N,) whether camera `cam` sees the points X (N, 3) of the patch: in front of it, the ray
    at |cos| >= min_cos to the patch's normal, and at least `margin_px` inside its image."""
    pc = X @ cam.R.T + cam.t
    ray = X - np.asarray(cam.position, dtype=float)
    cos = np.abs(ray @ patch.normal) / np.linalg.norm(ray, axis=-1)
    ok = (pc[:, 2] > 0) & (cos >= min_cos)
    x = cam.project(X)
    ok &= (x[:, 0] >= margin_px) & (x[:, 0] <= cam.width - 1 - margin_px)
    ok &= (x[:, 1] >= margin_px) & (x[:, 1] <= cam.height - 1 - margin_px)
    return ok


def q4_shape_functions(xi, size, nx: int, ny: int):
    """Bilinear shape functions of an nx × ny mesh of [0, size]: a (N, nodes) CSR matrix; node index
    j * (nx + 1) + i with i along ξ1. Points outside are extrapolated from the nearest element."""
    from scipy import sparse

    xi = np.asarray(xi, dtype=float)
    ex, ey = size[0] / nx, size[1] / ny
    ie = np.clip(np.floor(xi[:, 0] / ex).astype(int), 0, nx - 1)
    je = np.clip(np.floor(xi[:, 1] / ey).astype(int), 0, ny - 1)
    a = xi[:, 0] / ex - ie
    b = xi[:, 1] / ey - je
    n0 = je * (nx + 1) + ie
    cols = np.stack([n0, n0 + 1, n0 + nx + 1, n0 + nx + 2], 1)
    vals = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b], 1)
    rows = np.repeat(np.arange(len(xi)), 4)
    return sparse.csr_matrix((vals.ravel(), (rows, cols.ravel())),
                             shape=(len(xi), (nx + 1) * (ny + 1)))


def pixel_points(patch: Patch, cameras: Sequence, index: int, margin_px: float = 3.0,
                 min_cos: float = 0.05):
    """Integration points at the pixel centres of camera `index`: the face coordinates ξ (N, 2) where
    the rays of its pixels meet the patch, keeping those inside the patch and seen by every camera
    (as in `integration_points`). Each stands for exactly one pixel of that camera."""
    cam = cameras[index]
    # Only the pixels of the patch's bounding box (its corners' pinhole projections, +1 px):
    # a planar rectangle in front of the camera projects into their convex hull.
    corners = patch.points(np.array([[0, 0], [patch.size[0], 0], [0, patch.size[1]], patch.size]))
    cam_xyz = corners @ cam.R.T + cam.t
    cols, rows = np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float)
    if np.all(cam_xyz[:, 2] > 0):
        px = cam_xyz @ cam.K.T
        px = px[:, :2] / px[:, 2:]
        lo, hi = np.floor(px.min(axis=0)) - 1, np.ceil(px.max(axis=0)) + 1
        cols = cols[(cols >= lo[0]) & (cols <= hi[0])]
        rows = rows[(rows >= lo[1]) & (rows <= hi[1])]
    u, v = np.meshgrid(cols, rows, indexing="xy")
    f, (cx, cy) = cam.focal_px, cam.principal_point
    d = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], -1).reshape(-1, 3) @ cam.R
    C = np.asarray(cam.position, dtype=float)
    n = patch.normal
    dn = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = ((patch.origin - C) @ n) / dn
    ok = np.isfinite(lam) & (lam > 0)
    rel = C + np.where(ok, lam, 0.0)[:, None] * d - patch.origin
    xi = np.stack([rel @ patch.t_u, rel @ patch.t_v], -1)
    ok &= np.all((xi >= 0) & (xi <= patch.size), axis=1)
    xi = xi[ok]
    X = patch.points(xi)
    keep = np.ones(len(xi), dtype=bool)
    for other in cameras:
        keep &= _visible(other, patch, X, margin_px, min_cos)
    return xi[keep]
