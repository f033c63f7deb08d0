"""The faces of a region of interest and their frame (`RegionFaces`). Regions are patches of a
specimen mesh chosen by selectors (`RegionSelector`: a normal cone, a box, a distance band to a
point, an axis or a mesh). A planar patch (the paper's elementary surface) has its parametric
frame (t_u, t_v): a point X = O + u t_u + v t_v, (u, v) in metres, the face normal
n = t_u x t_v. A curved patch is developed onto the plane (`vdo.model.surface`). The samples on
these faces are `vdo.meshes.samples`'.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh

from vdo.config.rig import MeshSpec, RegionSpec
from vdo.core.errors import ConfigError
from vdo.meshes.mesh import BAND_EDGE_M, Band, SceneMesh, band_distance
from vdo.model import surface

log = logging.getLogger(__name__)


NEAR_FIELDS = {"near_point_m": "a point", "near_axis_m": "an axis", "near_mesh": "mesh",
               "region_file": "the region mesh"}


@dataclass(frozen=True, eq=False)
class RegionSelector:
    """What a region selects, as predicates: the normal cone per face, the box and the distance
    band [beyond, within] per point (m). `distance(points)` is the distance to the near_* point,
    axis or surface (None without one)."""

    region: RegionSpec
    band: Band | None = None
    within: float = math.inf

    @property
    def distance(self) -> Callable[[np.ndarray], np.ndarray] | None:
        return None if self.band is None else self.band.distance

    def facing(self, normals: np.ndarray) -> np.ndarray:
        if self.region.normal is None:
            return np.ones(len(normals), dtype=bool)
        return normals @ self.region.normal >= np.cos(self.region.normal_tolerance)

    def in_box(self, points: np.ndarray) -> np.ndarray:
        return np.all((points >= self.region.box_min) & (points <= self.region.box_max), axis=1)

    def in_band(self, points: np.ndarray, slack: np.ndarray | float = 0.0) -> np.ndarray:
        """Points within [beyond - slack, within + slack] of the selector (all True without one).
        A distance is 1-Lipschitz, so a triangle of circumradius r about its centroid c has a point
        in the band only if c is in the band widened by r."""
        if self.distance is None:
            return np.ones(len(points), dtype=bool)
        d = self.distance(points)
        return (d <= self.within + slack) & (d >= self.region.beyond - slack)

    def in_banded_face(self, triangles: np.ndarray, centroids: np.ndarray,
                       radius: np.ndarray) -> np.ndarray:
        """(T,) the triangles (T, 3, 3) that hold part of the band. For a convex distance
        (`vdo.meshes.mesh.Band.least`, on a mesh split at the band's edges): least on the
        triangle < within and greatest (at a vertex) > beyond, each by more than `BAND_EDGE_M`,
        so the outer piece of a split face, whose vertices lie on the edge or beyond it, is left
        out. Otherwise (the distance to a mesh): the centroid within the band widened by the
        circumradius `radius` (the distance is 1-Lipschitz)."""
        if self.band.least is None:
            return self.in_band(centroids, radius)
        greatest = self.distance(triangles.reshape(-1, 3)).reshape(-1, 3).max(axis=1)
        return ((self.band.least(triangles) < self.within - BAND_EDGE_M)
                & (greatest > self.region.beyond + BAND_EDGE_M))

    def keep(self, points: np.ndarray) -> np.ndarray:
        """(N,) the points the region keeps of those on its selected faces: in the box and band."""
        return self.in_box(points) & self.in_band(points)


def region_selector(region: RegionSpec, meshes: list[SceneMesh], spacing: float, *,
                    mesh_specs: tuple[MeshSpec, ...], path) -> RegionSelector:
    """The `RegionSelector` of `region`: the near_mesh's surface from `meshes`, the region_file
    read in the specimen mesh's unit (its table of `mesh_specs`, the [[mesh]] tables; a file
    that cannot be read is a ConfigError at the experiment file `path`); a region file's band
    defaults to `spacing` (m)."""
    band = band_distance(region, meshes, mesh_specs=mesh_specs, path=path)
    if band is None:
        return RegionSelector(region)
    within = region.within if region.within is not None else spacing
    return RegionSelector(region, band, within)


@dataclass(frozen=True, eq=False)
class RegionFaces:
    """The faces of one region of interest and its frame (metres).

    Planar (`development` None): a point X of the face has parametric coordinates
    uv = ((X - origin) . t_u, (X - origin) . t_v), the same (u, v) that `sample_region` gives its
    samples (so a texture mapped with these uv lines up with the samples). t_u x t_v = normal
    (outward): seen from outside the face, u runs right and v up. Curved: uv is the
    `vdo.model.surface.Development`'s and `normal` the area-weighted mean normal. `selector`
    keeps the samples in the region's box and distance band."""

    faces: np.ndarray      # (T,) indices into the mesh's faces
    normal: np.ndarray     # (3,)
    t_u: np.ndarray        # (3,)
    t_v: np.ndarray        # (3,)
    origin: np.ndarray     # (3,) a point of the face's plane with uv = (0, 0)
    development: surface.Development | None = None
    selector: RegionSelector | None = None

    def uv(self, points: np.ndarray) -> np.ndarray:
        """(..., 2) parametric coordinates of points (..., 3) on the face, m."""
        if self.development is not None:
            return self.development.uv(points)
        rel = np.asarray(points, dtype=float) - self.origin
        return np.stack([rel @ self.t_u, rel @ self.t_v], axis=-1)


def _nothing_selected(mesh: SceneMesh, region: RegionSpec, selector: RegionSelector, tm, where):
    """ConfigError naming what the selection would need: the box misses the mesh, no face faces
    the normal, or the distance band holds no face (with the distances the faces have)."""
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    hint = ""
    if np.any(region.box_min > hi) or np.any(region.box_max < lo):
        hint = (f"; the box misses the mesh, which spans {np.round(lo, 3).tolist()} to "
                f"{np.round(hi, 3).tolist()} m")
        size = np.where(np.isfinite(region.box_max - region.box_min), region.box_max - region.box_min, 0)
        if np.ptp(mesh.vertices, axis=0).max() > 100 * max(size.max(), 1e-9):
            hint += ": is the mesh's unit right (unit = \"mm\" for a CAD export in mm)?"
        raise ConfigError(*where, f"selects no face of mesh {mesh.name!r}: check normal, "
                                  f"box_min_m and box_max_m (metres, world frame){hint}")
    near = region.near
    if near is not None:
        ok = selector.facing(tm.face_normals) & selector.in_box(tm.triangles_center)
        if ok.any():
            d = selector.distance(tm.triangles_center[ok])
            limited = [w for w, on in (("box", np.isfinite(region.box_min).any() or np.isfinite(region.box_max).any()),
                                       ("normal cone", region.normal is not None)) if on]
            within = f" (in the {' and '.join(limited)})" if limited else ""
            raise ConfigError(*where, f"selects no face of mesh {mesh.name!r}: its faces{within} "
                                      f"lie {d.min():.4g} to {d.max():.4g} m from "
                                      f"{NEAR_FIELDS[near]} ({near}); set within_m / beyond_m to "
                                      "include some of that range")
    if region.normal is not None:
        in_box = selector.in_box(tm.triangles_center)
        facing = selector.facing(tm.face_normals)
        scope = in_box if in_box.any() else np.ones(len(in_box), dtype=bool)
        best = float(np.degrees(np.arccos(np.clip((tm.face_normals[scope] @ region.normal).max(), -1, 1))))
        outside = ""
        if facing.any() and in_box.any():   # the faces that face it are all outside the box
            c = tm.triangles_center[facing]
            outside = (f"; the faces that face it lie outside the box, between "
                       f"{np.round(c.min(axis=0), 3).tolist()} and {np.round(c.max(axis=0), 3).tolist()} m")
        raise ConfigError(*where, f"selects no face of mesh {mesh.name!r}: the closest face normal "
                                  f"{'in the box ' if in_box.any() else ''}is {best:.1f} deg from normal "
                                  f"(tolerance {np.degrees(region.normal_tolerance):g} deg){outside}; check "
                                  "normal, normal_tolerance_deg, box_min_m and box_max_m (metres, world frame)")
    raise ConfigError(*where, f"selects no face of mesh {mesh.name!r}: check box_min_m and box_max_m "
                              "(metres, world frame)")


BAND_SCALE = 10.0   # a distance band wider than this many times its mesh's size cuts nothing off it


def _band_in_metres(mesh: SceneMesh, region: RegionSpec, where) -> None:
    """ConfigError when a region's band around a point or an axis is given as if in millimetres:
    within_m larger than BAND_SCALE times the mesh's size (the diagonal of its bounding box: the
    band then cuts nothing off it), or the point (the axis line) farther than that from the mesh's
    bounding box (its centre less the half-diagonal); both fields are metres, like every `_m`."""
    if region.near not in ("near_point_m", "near_axis_m"):
        return
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    size = float(np.linalg.norm(hi - lo))
    if region.near == "near_point_m":      # the point's distance to the mesh's bounding box
        far = float(np.linalg.norm(np.maximum(np.maximum(lo - region.near_point, region.near_point - hi), 0.0)))
    else:                                   # the line's distance to the box's centre, less its half-diagonal
        a, b = np.asarray(region.near_axis, dtype=float)
        e, c = (b - a) / max(float(np.linalg.norm(b - a)), 1e-300), (lo + hi) / 2 - a
        far = max(float(np.linalg.norm(c - (c @ e) * e)) - size / 2, 0.0)
    hint = (f"the near_* fields and within_m / beyond_m are metres (values in mm? divide them by 1000)")
    if region.within is not None and region.within > BAND_SCALE * size:
        raise ConfigError(*where, f"within_m = {region.within:g} m is more than {BAND_SCALE:g} times the size "
                                  f"of mesh {mesh.name!r} ({size:.3g} m across): the band cuts nothing "
                                  f"off it; {hint}")
    if far > BAND_SCALE * size:
        raise ConfigError(*where, f"{region.near} lies {far:.4g} m from mesh {mesh.name!r} ({size:.3g} m "
                                  f"across, spanning {np.round(lo, 3).tolist()} to {np.round(hi, 3).tolist()} m); "
                                  f"{hint}")


def region_faces(mesh: SceneMesh, region: RegionSpec, spacing: float, where: tuple,
                 tm: trimesh.Trimesh | None = None, selector: RegionSelector | None = None) -> RegionFaces:
    """The faces that `region` selects on `mesh` and their frame; ConfigError (at `where`) when
    none is selected. A selection whose faces are coplanar (tolerance max(spacing / 4, 0.1 mm))
    is a planar face; otherwise it must be one connected piece of surface, developed by
    `vdo.model.surface.fit_development` (same tolerance for the fit). `selector`: the region's
    `RegionSelector` (needed for near_mesh and region_file; built here for the others)."""
    tm = mesh.trimesh if tm is None else tm
    if selector is None:
        if region.near_mesh is not None or region.region_file is not None:
            raise ValueError("a region that selects by a mesh needs its RegionSelector")
        selector = region_selector(region, [], spacing, mesh_specs=(), path=None)
    centroids = tm.triangles_center
    radius = np.linalg.norm(tm.triangles - centroids[:, None], axis=2).max(axis=1)
    chosen = selector.facing(tm.face_normals) & selector.in_box(centroids) & (tm.area_faces > 0)
    if selector.distance is not None and chosen.any():
        chosen[chosen] = selector.in_banded_face(tm.triangles[chosen], centroids[chosen], radius[chosen])
    faces = np.flatnonzero(chosen)
    _band_in_metres(mesh, region, where)
    if len(faces) == 0:
        _nothing_selected(mesh, region, selector, tm, where)
    normal = np.average(tm.face_normals[faces], axis=0, weights=tm.area_faces[faces])
    normal /= max(np.linalg.norm(normal), 1e-300)
    tri = tm.triangles[faces]                                   # (T, 3, 3)
    tolerance = max(0.25 * spacing, 1e-4)
    depth = tri.reshape(-1, 3) @ normal
    if np.ptp(depth) <= tolerance and np.linalg.norm(normal) > 0.5:
        t_u, t_v = surface.face_frame(normal)
        flat = tri.reshape(-1, 3)
        ou, ov = (flat @ t_u).min(), (flat @ t_v).min()
        origin = ou * t_u + ov * t_v + depth.mean() * normal
        return RegionFaces(faces=faces, normal=normal, t_u=t_u, t_v=t_v, origin=origin, selector=selector)
    vertices, merged_faces = surface.merged(tri)
    pieces = surface.components(merged_faces, len(vertices))
    count = int(pieces.max()) + 1
    if count > 1:
        raise ConfigError(*where, f"selects faces that are not coplanar (depth spread "
                                  f"{np.ptp(depth) * 1e3:.1f} mm) and not one connected surface "
                                  f"({count} separate pieces): a region must be one planar face or "
                                  "one connected curved patch; narrow its box, normal_tolerance_deg "
                                  "or distance band")
    dev = surface.fit_development(tri, tm.face_normals[faces], tm.area_faces[faces], tolerance)
    if dev.distortion.large:
        log.warning("%s: %s: developed with distortion %.0f %% in area and %.0f %% in angle (p95 "
                    "over its surface; samples carry their true area, but its maps are distorted "
                    "by as much): split it into flatter regions", where[0], where[1],
                    100 * dev.distortion.area_p95, 100 * dev.distortion.angle_p95)
    t_u, t_v = surface.face_frame(normal) if np.linalg.norm(normal) > 0.5 else (np.eye(3)[0], np.eye(3)[1])
    return RegionFaces(faces=faces, normal=normal, t_u=t_u, t_v=t_v, origin=tri.reshape(-1, 3).mean(0),
                       development=dev, selector=selector)


def all_region_faces(meshes: list[SceneMesh], *, mesh_specs: tuple[MeshSpec, ...],
                     regions: tuple[RegionSpec, ...], spacing: float, path) -> list[RegionFaces]:
    """`region_faces` for every region of `regions` (an experiment's [[region]] tables), in
    config order, on `meshes` (read from `mesh_specs`, its [[mesh]] tables), at sample `spacing`
    (m; the experiment's is `evaluation.sample_spacing`); errors name the experiment file
    `path`."""
    by_name = {m.name: m for m in meshes}
    return [region_faces(by_name[r.mesh], r, spacing, (path, f'region "{r.name}"'),
                         selector=region_selector(r, meshes, spacing, mesh_specs=mesh_specs, path=path))
            for r in regions]
