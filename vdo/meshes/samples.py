"""Surface samples on the regions of interest (`SurfaceSamples`). A planar patch (the paper's
elementary surface) is sampled on a regular grid of spacing h in its own parametric frame
(t_u, t_v): a sample at X = O + u t_u + v t_v carries the area h^2, the face normal
n = t_u x t_v, and (u, v) in metres. A curved patch is developed onto the plane
(`vdo.model.surface`) and sampled on the same grid there; each sample carries its cell's surface
area, its face's normal and its own tangent frame (`sample_region`). `surface_raster`: which
points of a finer grid lie on a region's surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from vdo.config.rig import MeshSpec, RegionSpec
from vdo.core.errors import ConfigError
from vdo.meshes.mesh import SceneMesh
from vdo.meshes.regions import RegionFaces, all_region_faces, region_faces
from vdo.model import surface


@dataclass(frozen=True, eq=False)
class SurfaceSamples:
    """Area-uniform samples on the regions of interest (N of them). Lengths in metres."""

    points: np.ndarray       # (N, 3)
    normals: np.ndarray      # (N, 3) outward unit normals
    tangent_u: np.ndarray    # (N, 3) unit, with tangent_v: the face's parametric frame (on a
                             # cylinder and a cone: around its axis, then along the surface)
    tangent_v: np.ndarray    # (N, 3)
    uv: np.ndarray           # (N, 2) parametric coordinates on the face, m
    area: np.ndarray         # (N,) m^2 carried by each sample
    region: np.ndarray       # (N,) index into region_names
    region_names: tuple[str, ...]
    region_importance: np.ndarray  # (R,)
    region_period: np.ndarray | None = None  # (R,) u period of a ring closed around its axis, m (0: none)
    region_cell: np.ndarray | None = None    # (R,) grid spacing in (u, v), m (None: sqrt(area))
    region_turn: np.ndarray | None = None    # (R,) developed angle of a closed cone ring, rad (0: none)

    def __len__(self):
        return len(self.points)

    def take(self, index) -> "SurfaceSamples":
        """The samples at `index` (an index or mask array), with the same regions."""
        return replace(self, points=self.points[index], normals=self.normals[index],
                       tangent_u=self.tangent_u[index], tangent_v=self.tangent_v[index],
                       uv=self.uv[index], area=self.area[index], region=self.region[index])


def edge_distance(samples: SurfaceSamples, keep: np.ndarray | None = None) -> np.ndarray:
    """(N,) each sample's distance (m) to the edge of its region's samples that `keep` (N,) bool
    holds (all of them by default; e.g. those a camera sees, whose edge is then also a silhouette
    or an occlusion's), measured on the region's sample grid (planar, or developed): half a cell
    for a sample with a grid neighbour (up, down, left or right) that is not held, else the
    distance in (u, v) to the nearest such sample plus half a cell; 0 for samples not held. A ring
    closed around its axis wraps in u (`region_period`), so its seam is no edge; a cone ring's
    seam counts as one (conservative). Lengths in the developed plane: a conformal map's area
    distortion makes them approximate."""
    from scipy.spatial import cKDTree

    keep = np.ones(len(samples), dtype=bool) if keep is None else np.asarray(keep, dtype=bool)
    out = np.zeros(len(samples))
    for r in range(len(samples.region_names)):
        idx = np.flatnonzero((samples.region == r) & keep)
        if not len(idx):
            continue
        h = float(samples.region_cell[r]) if samples.region_cell is not None else \
            float(np.sqrt(samples.area[idx].mean()))
        period = samples.region_period[r] if samples.region_period is not None else 0.0
        cells = int(round(period / h)) if period > 0 and (samples.region_turn is None
                                                          or samples.region_turn[r] == 0) else 0
        ij = np.rint(samples.uv[idx] / h - 0.5).astype(np.int64)
        low = ij.min(axis=0) - 1
        width = int(ij[:, 1].max() - low[1]) + 2
        key = lambda i, j: (i - low[0]) * width + (j - low[1])                    # noqa: E731
        have = np.sort(key(ij[:, 0], ij[:, 1]))
        edge = np.zeros(len(idx), dtype=bool)
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            i = ij[:, 0] + di
            if cells:
                i = np.mod(i - low[0], cells) + low[0]
            k = key(i, ij[:, 1] + dj)
            at = np.clip(np.searchsorted(have, k), 0, len(have) - 1)
            edge |= have[at] != k
        uv = (ij + 0.5) * h
        if not edge.any():      # a closed surface without an edge: everything is interior
            out[idx] = np.inf
            continue
        border = uv[edge]
        if cells:               # the ring's edge samples one period either side, for the wrap
            border = np.concatenate([border + [k * cells * h, 0.0] for k in (-1, 0, 1)])
        out[idx] = cKDTree(border).query(uv)[0] + h / 2
    return out


def _grid_points(uv_tri: np.ndarray, spacing: float):
    """Grid points (i + 1/2, j + 1/2) spacing inside the 2D triangles uv_tri (T, 3, 2): (triangle
    index t, barycentric l1, l2 (K, 1) each, grid index ij (K, 2))."""
    lo = np.floor(uv_tri.min(axis=1) / spacing - 0.5).astype(int)             # (T, 2)
    size = np.ceil(uv_tri.max(axis=1) / spacing - 0.5).astype(int) - lo + 1   # (T, 2)
    a, e1, e2 = uv_tri[:, 0], uv_tri[:, 1] - uv_tri[:, 0], uv_tri[:, 2] - uv_tri[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    size[np.abs(det) < 1e-18] = 0                                              # degenerate: none
    count = size.prod(axis=1)
    t = np.repeat(np.arange(len(uv_tri)), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    ij = lo[t] + np.stack([k // size[t, 1], k % size[t, 1]], axis=1)
    q = (ij + 0.5) * spacing - a[t]
    l1 = (q[:, 0] * e2[t, 1] - q[:, 1] * e2[t, 0]) / det[t]                   # barycentric (l1, l2):
    l2 = (e1[t, 0] * q[:, 1] - e1[t, 1] * q[:, 0]) / det[t]                   # q = l1 e1 + l2 e2
    tol = 1e-9  # grid points on an edge shared by two triangles must not be lost to rounding
    inside = (l1 >= -tol) & (l2 >= -tol) & (l1 + l2 <= 1 + tol)
    return t[inside], l1[inside, None], l2[inside, None], ij[inside]


def ring_spacing(period: float, spacing: float) -> float:
    """The grid spacing of a region closed around its axis: the largest h' <= h that divides the
    period 2 pi R into whole cells, so that the grid closes on itself."""
    return period / math.ceil(period / spacing - 1e-9) if period > 0 else spacing


def sample_region(mesh: SceneMesh, region: RegionSpec, spacing: float, where: tuple,
                  rf: RegionFaces | None = None, field: str = "evaluation.sample_spacing_mm") -> dict:
    """Grid samples of spacing `spacing` (m) on the faces that `region` selects (`rf`: already
    found by `region_faces`), in the region's (u, v): each stands for its cell of the grid.

    Planar: the cell's area h^2 and the face frame. Curved (developed): the grid lies in the
    developed plane; a sample on face T carries the surface area of its cell, h^2 A_T / A'_T (the
    face's area on the surface over its developed area: 1 for an exact development but for the
    chord of a facet against its arc), the face's normal n and the tangent frame t_u = the unit
    image of the developed u direction on the face (J = E D^-1, E the face's edge vectors, D the
    developed ones), projected off n, and t_v = n x t_u. A ring closed around its axis is sampled
    at `ring_spacing` and its grid index wraps at the period. Samples outside the region's box
    and distance band are dropped."""
    tm = mesh.trimesh
    rf = region_faces(mesh, region, spacing, where, tm) if rf is None else rf
    tri = tm.triangles[rf.faces]                                # (T, 3, 3)
    dev = rf.development
    if dev is not None:
        spacing = ring_spacing(dev.period, spacing)
    uv_tri = rf.uv(tri) if dev is None else dev.triangles_uv(tri)   # (T, 3, 2)
    t, l1, l2, ij = _grid_points(uv_tri, spacing)
    points = (1 - l1 - l2) * tri[t, 0] + l1 * tri[t, 1] + l2 * tri[t, 2]
    if dev is not None and dev.period > 0:
        ij[:, 0] = np.mod(ij[:, 0], round(dev.period / spacing))
    _, first = np.unique(ij, axis=0, return_index=True)        # points on shared edges once
    t, ij, pts = t[first], ij[first], points[first]
    if rf.selector is not None and (rf.selector.distance is not None or dev is not None):
        keep = rf.selector.keep(pts)
        t, ij, pts = t[keep], ij[keep], pts[keep]
    if len(pts) == 0:
        span = np.ptp(uv_tri.reshape(-1, 2), axis=0) * 1e3
        ring = (f" (on this ring {spacing * 1e3:.4g} mm, the nearest spacing that divides its "
                f"circumference)") if dev is not None and dev.period > 0 else ""
        raise ConfigError(*where, f"is smaller than the sample spacing: no grid point {spacing * 1e3:.4g} mm "
                                  f"apart{ring} falls inside it (its selected faces span {span[0]:.4g} x "
                                  f"{span[1]:.4g} mm{' developed' if dev is not None else ''}); lower {field} "
                                  "or widen the region")
    n = len(pts)
    if dev is None:
        return dict(points=pts, normals=np.tile(rf.normal, (n, 1)), tangent_u=np.tile(rf.t_u, (n, 1)),
                    tangent_v=np.tile(rf.t_v, (n, 1)), uv=(ij + 0.5) * spacing,
                    area=np.full(n, spacing**2))
    E = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=-1)      # (T, 3, 2)
    D = np.stack([uv_tri[:, 1] - uv_tri[:, 0], uv_tri[:, 2] - uv_tri[:, 0]], axis=-1)
    det = np.linalg.det(D)
    J = E @ np.linalg.inv(np.where(np.abs(det)[:, None, None] > 1e-300, D, np.eye(2)))
    normal = tm.face_normals[rf.faces]
    along = J[:, :, 0]
    if dev.kind == "cone":   # the hoop direction, J e_psi: the developed polar angle's at the face
        centre = uv_tri.mean(axis=1)                                  # (u, v) = s (sin psi, -cos psi)
        radial = centre / np.maximum(np.linalg.norm(centre, axis=1, keepdims=True), 1e-300)
        along = np.einsum("tij,tj->ti", J, np.stack([-radial[:, 1], radial[:, 0]], axis=1))
    t_u = along - normal * np.einsum("ij,ij->i", along, normal)[:, None]
    t_u /= np.linalg.norm(t_u, axis=1, keepdims=True)
    t_v = np.cross(normal, t_u)
    ratio = tm.area_faces[rf.faces] / np.maximum(np.abs(det) / 2, 1e-300)
    return dict(points=pts, normals=normal[t], tangent_u=t_u[t], tangent_v=t_v[t],
                uv=(ij + 0.5) * spacing, area=spacing**2 * ratio[t])


RASTER_MAX = 4_000_000      # fine points of one region's surface raster (4 MB of booleans)
RASTER_FINE = 8             # fine points per cell side at most


@dataclass(frozen=True, eq=False)
class SurfaceRaster:
    """Which points of a fine grid lie on a region's surface: the grid of spacing h / K in the
    region's (u, v) (fine point (m_u, m_v) at ((m + 1/2) h / K), so that cell (i, j) of the sample
    grid holds the fine points i K .. i K + K - 1 along each axis. `mask[a, b]` is fine point
    (offset[0] + a, offset[1] + b); a ring's mask is padded by `pad` wrapped columns each side, a
    closed cone's by its points near the seam continued across it (`surface.across_seam`)."""

    mask: np.ndarray        # (Nu, Nv) bool
    offset: np.ndarray      # (2,) int: the fine index of mask[0, 0]
    fine: int               # K
    cell: float             # h, m
    around: int             # cells around a cylinder ring (0: not one)
    turn: float = 0.0       # developed angle of a closed cone ring, rad, signed as u (0: not one)


def surface_raster(mesh: SceneMesh, rf: RegionFaces, spacing: float, pad_cells: int = 2) -> SurfaceRaster:
    """The `SurfaceRaster` of a region from its own triangles (not from its samples): the fine
    points inside its (developed) triangles, and in its box and distance band, as `sample_region`
    decides for a sample. K = RASTER_FINE, fewer when the region would exceed RASTER_MAX."""
    tm = mesh.trimesh
    tri = tm.triangles[rf.faces]
    dev = rf.development
    h = ring_spacing(dev.period, spacing) if dev is not None else spacing
    uv_tri = rf.uv(tri) if dev is None else dev.triangles_uv(tri)
    cells = float(tm.area_faces[rf.faces].sum()) / h ** 2
    fine = int(max(2, min(RASTER_FINE, math.floor(math.sqrt(RASTER_MAX / max(cells, 1.0))))))
    t, l1, l2, m = _grid_points(uv_tri, h / fine)
    if rf.selector is not None and (rf.selector.distance is not None or dev is not None):
        points = (1 - l1 - l2) * tri[t, 0] + l1 * tri[t, 1] + l2 * tri[t, 2]
        m = m[rf.selector.keep(points)]
    around = int(round(dev.period / h)) if dev is not None and dev.period > 0 else 0
    if around:
        m[:, 0] = np.mod(m[:, 0], around * fine)
        pad = pad_cells * fine
        m = np.concatenate([m, m[m[:, 0] < pad] + [around * fine, 0],
                            m[m[:, 0] >= around * fine - pad] - [around * fine, 0]])
    turn = dev.flip * dev.turn if dev is not None else 0.0
    if turn:
        m = np.concatenate([m, surface.across_seam_grid(m, h / fine, turn, pad_cells * h)[0].astype(m.dtype)])
    lo = m.min(axis=0)
    mask = np.zeros(tuple(m.max(axis=0) - lo + 1), dtype=bool)
    mask[m[:, 0] - lo[0], m[:, 1] - lo[1]] = True
    return SurfaceRaster(mask, lo, fine, h, around, turn)


MAX_SAMPLES = 2_000_000     # surface samples: ~1 GB of visibility and uncertainty arrays for 10 cameras


def check_sample_count(meshes: list[SceneMesh], faces: list[RegionFaces], spacing: float, *,
                       path, field: str = "evaluation.sample_spacing_mm") -> None:
    """ConfigError (at the experiment file `path`, its `field`, the spacing's) before
    sampling when the regions' area A would give more than MAX_SAMPLES samples at spacing h
    (N = A / h^2), with the smallest spacing that fits."""
    area = sum(float(m.trimesh.area_faces[rf.faces].sum()) for m, rf in zip(meshes, faces))
    count = area / spacing**2
    if count > MAX_SAMPLES:
        fits = math.ceil(math.sqrt(area / MAX_SAMPLES) * 1e4) / 10
        raise ConfigError(path, field,
                          f"= {spacing * 1e3:g} mm gives about {count:,.0f} samples on the regions' "
                          f"{area:.3g} m² (at most {MAX_SAMPLES:,}): raise sample_spacing_mm to "
                          f"{fits:g} or more")


def sample_regions(meshes: list[SceneMesh], *, mesh_specs: tuple[MeshSpec, ...],
                   regions: tuple[RegionSpec, ...], spacing: float, path,
                   faces: list[RegionFaces] | None = None,
                   field: str = "evaluation.sample_spacing_mm") -> SurfaceSamples:
    """Samples on every region of `regions` (an experiment's [[region]] tables) at `spacing` (m;
    the experiment's is `evaluation.sample_spacing`), on the regions' `faces` (`all_region_faces`
    at that spacing, with `mesh_specs`, its [[mesh]] tables; found here when not given); errors
    name the experiment file `path`."""
    by_name = {m.name: m for m in meshes}
    faces = all_region_faces(meshes, mesh_specs=mesh_specs, regions=regions, spacing=spacing,
                             path=path) if faces is None else faces
    check_sample_count([by_name[r.mesh] for r in regions], faces, spacing, path=path, field=field)
    parts = []
    for index, (region, rf) in enumerate(zip(regions, faces)):
        part = sample_region(by_name[region.mesh], region, spacing,
                             (path, f'region "{region.name}"'), rf, field=field)
        part["region"] = np.full(len(part["points"]), index)
        parts.append(part)
    merged = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    period = np.array([0.0 if rf.development is None else rf.development.period for rf in faces])
    return SurfaceSamples(**merged, region_names=tuple(r.name for r in regions),
                          region_importance=np.array([r.importance for r in regions]),
                          region_period=period,
                          region_cell=np.array([spacing if rf.development is None else
                                                ring_spacing(rf.development.period, spacing)
                                                for rf in faces]),
                          region_turn=np.array([0.0 if rf.development is None else
                                                rf.development.flip * rf.development.turn for rf in faces]))
