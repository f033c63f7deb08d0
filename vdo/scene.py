"""The physical scene: meshes in metres, regions of interest and their samples, the configured
cameras (`cameras_of`), their bodies and the tripods under them, and the Mitsuba scene built from
them.

Meshes are read with trimesh (Mitsuba has no STL loader) and handed to Mitsuba in memory, so a
user's CAD export and the built-in example take the same path.

Regions of interest are patches of a specimen mesh chosen by selectors (`RegionSelector`: a normal
cone, a box, a distance band to a point, an axis or a mesh). A planar patch (the paper's elementary
surface) is sampled on a regular grid of spacing h in its own parametric frame (t_u, t_v): a sample
at X = O + u t_u + v t_v carries the area h^2, the face normal n = t_u x t_v, and (u, v) in metres.
A curved patch is developed onto the plane (`vdo.model.surface`) and sampled on the same grid there;
each sample carries its cell's surface area, its face's normal and its own tangent frame
(`sample_region`).
"""

from __future__ import annotations

import functools

import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh

from vdo.core.backend import mitsuba
from vdo.model import surface
from vdo.model.camera import Camera
from vdo.config.experiment import UNITS, Experiment, RegionSpec, camera_positions
from vdo.config.mounts import TripodSpec
from vdo.config.schema import IMAGE_MAGIC
from vdo.core.errors import Collect, ConfigError
from vdo.core.tolerances import BARYCENTRIC_SLACK, TINY

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class SceneMesh:
    """A triangle mesh in world metres. `role` is "specimen", "obstacle" or "camera" (a camera's
    body or a part of its tripod)."""

    name: str
    role: str
    vertices: np.ndarray   # (n, 3) float64, m
    faces: np.ndarray      # (m, 3) int

    @functools.cached_property
    def trimesh(self) -> trimesh.Trimesh:
        """The mesh as trimesh, built once (its cached normals, centres and areas are shared by
        every region that selects faces of it; do not modify it)."""
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def load_meshes(exp: Experiment, errors: Collect | None = None) -> list[SceneMesh]:
    """Read every [[mesh]] of the experiment, scaled to metres, and check it: readable content,
    extents that fit the declared unit, no camera inside it (`cameras_inside`). Every mesh is
    checked and every mistake reported together (`vdo.core.errors.Collect`). Specimen faces that
    cross a region's box are split at the box (`split_at_boxes`), so a region's faces and area
    are exactly the part inside its box. With `errors`, the mistakes are kept there instead of
    raised, and the meshes that could be read are returned."""
    own = errors is None
    errors = Collect() if own else errors
    meshes = []
    for spec in exp.meshes:
        with errors.check():
            meshes.append(_load_mesh(exp, spec))
    errors.errors += cameras_inside(exp, meshes)
    if own:
        errors.raise_all()
    return meshes


def _load_mesh(exp: Experiment, spec) -> SceneMesh:
    field = f'mesh "{spec.name}".file'
    loaded = _read_mesh(spec.path, (exp.path, field))
    vertices = np.asarray(loaded.vertices, dtype=float) * spec.scale
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ConfigError(exp.path, field, f"{spec.path.name!r} has faces that refer to missing vertices")
    if not np.all(np.isfinite(vertices)):
        raise ConfigError(exp.path, field, f"{spec.path.name!r} has non-finite vertex coordinates")
    _check_extent(vertices[np.unique(faces)], spec, (exp.path, field))
    if spec.role == "specimen":
        vertices, faces = split_at_boxes(vertices, faces, [r for r in exp.regions if r.mesh == spec.name])
    return SceneMesh(spec.name, spec.role, vertices, faces)


MAX_MESH_EXTENT = 100.0      # m: a test setup larger than this is a unit mistake
NOT_MESHES = {**IMAGE_MAGIC, b"%PDF": "PDF", b"PK\x03\x04": "ZIP", b"\x1f\x8b": "gzip"}


def _read_mesh(path, where) -> trimesh.Trimesh:
    """The triangles of an STL, OBJ or PLY file; ConfigError saying what is wrong with the file."""
    name, fmt = path.name, path.suffix.lstrip(".").upper()
    data = path.read_bytes()
    if not data:
        raise ConfigError(*where, f"{name!r} is empty (0 bytes)")
    for magic, kind in NOT_MESHES.items():
        if data.startswith(magic):
            raise ConfigError(*where, f"{name!r} is a {kind} file, not an {fmt} mesh")
    if fmt == "STL":
        count = int.from_bytes(data[80:84], "little") if len(data) >= 84 else 0
        binary = len(data) >= 84 and len(data) == 84 + 50 * count
        if not binary and not data.lstrip()[:5].lower() == b"solid":
            if len(data) < 84:
                raise ConfigError(*where, f"{name!r} is neither ASCII STL (which starts with 'solid') "
                                          f"nor binary STL (84-byte header; the file has {len(data)} bytes)")
            raise ConfigError(*where, f"{name!r} is not a valid binary STL: its header announces {count} "
                                      f"triangles ({84 + 50 * count} bytes) but the file has {len(data)} "
                                      "bytes (truncated or not an STL)")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except ModuleNotFoundError:       # trimesh's text fallback for content it cannot parse
        raise ConfigError(*where, f"cannot read {name!r} as {fmt}: the content is not a valid "
                                  f"{fmt} mesh") from None
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ConfigError(*where, f"cannot read {name!r} as a mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ConfigError(*where, f"{name!r} holds no triangles")
    return loaded


def _check_extent(vertices: np.ndarray, spec, where) -> None:
    """ConfigError when the mesh spans more than MAX_MESH_EXTENT metres, with the likely cause:
    a stray vertex far from the others, or a length unit that is not the file's."""
    extent = float(np.ptp(vertices, axis=0).max())
    if extent <= MAX_MESH_EXTENT:
        return
    centre = np.median(vertices, axis=0)
    far = np.linalg.norm(vertices - centre, axis=1)
    core = float(np.ptp(vertices[far <= np.quantile(far, 0.99)], axis=0).max())
    if core <= MAX_MESH_EXTENT:
        worst = vertices[np.argmax(far)]
        raise ConfigError(*where, f"a vertex of {spec.path.name!r} lies at {np.round(worst, 3).tolist()} m, "
                                  f"far from the rest of the mesh (which spans {core:.3g} m): a corrupt "
                                  "vertex? fix the file")
    hints = [f'is the mesh in {unit}? set unit = "{unit}"' for unit in ("mm", "cm", "in")
             if UNITS[unit] < spec.scale and extent * UNITS[unit] / spec.scale <= MAX_MESH_EXTENT]
    raise ConfigError(*where, f"{spec.path.name!r} spans {extent:.4g} m with unit = \"{spec.unit}\" "
                              f"(at most {MAX_MESH_EXTENT:g} m expected)"
                      + (f"; {hints[0]}" if hints else "; check the file's unit"))


INSIDE_TURN_RAD = (0.3141, 0.2718, 0.1414)   # rad: the rays of `inside_mesh`, turned off the axes
INSIDE_MIN_RAYS = 8       # of the 14 rays, at least this many must be clear for a point to be inside
INSIDE_ON_SURFACE_M = 1e-6   # m: a ray that starts this close to a triangle starts on the surface
INSIDE_CHUNK = 200_000    # (ray, triangle) pairs per block of `inside_mesh`


def inside_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(P,) bool: whether each point lies inside the closed surface (`vertices` (n, 3) m, `faces`
    (m, 3)), by the even-odd rule, whatever the faces' winding. From each point 14 rays (the axes
    and the diagonals, turned by `INSIDE_TURN_RAD` so that they do not run along a CAD model's
    edges) are intersected with every triangle (Möller-Trumbore: o + t d = (1 - u - v) a + u b
    + v c, t > 0, u, v, 1 - u - v >= 0). A ray that passes within `BARYCENTRIC_SLACK` of a
    triangle's edge, or starts on the surface (|t| <= `INSIDE_ON_SURFACE_M`), is ambiguous and not counted;
    a point is inside when at least `INSIDE_MIN_RAYS` rays are clear and every clear one crosses
    the surface an odd number of times (through a hole of an open mesh a ray crosses an even
    number: such a point is not called inside)."""
    from scipy.spatial.transform import Rotation

    points = np.atleast_2d(np.asarray(points, dtype=float))
    dirs = np.array(list(np.ndindex(3, 3, 3)), dtype=float) - 1.0
    dirs = dirs[np.isin(np.count_nonzero(dirs, axis=1), (1, 3))]       # 6 axes + 8 diagonals
    dirs = Rotation.from_euler("xyz", INSIDE_TURN_RAD).apply(dirs / np.linalg.norm(dirs, axis=1)[:, None])
    a, b, c = (np.asarray(vertices, dtype=float)[faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    out = np.zeros(len(points), dtype=bool)
    step = max(1, INSIDE_CHUNK // len(dirs))
    for p, point in enumerate(points):
        crossings = np.zeros(len(dirs), dtype=int)
        ambiguous = np.zeros(len(dirs), dtype=bool)
        for lo in range(0, len(faces), step):
            s_ = slice(lo, lo + step)
            pvec = np.cross(dirs[:, None, :], e2[None, s_])                   # (R, T, 3)
            det = np.einsum("tk,rtk->rt", e1[s_], pvec)
            ok = np.abs(det) > TINY
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            tvec = point - a[s_]                                              # (T, 3)
            u = np.einsum("tk,rtk->rt", tvec, pvec) * inv
            qvec = np.cross(tvec, e1[s_])                                     # (T, 3)
            v = np.einsum("rk,tk->rt", dirs, qvec) * inv
            t = np.einsum("tk,tk->t", e2[s_], qvec)[None, :] * inv
            w = 1.0 - u - v
            within = ok & (u >= -BARYCENTRIC_SLACK) & (v >= -BARYCENTRIC_SLACK) & (w >= -BARYCENTRIC_SLACK)
            edge = within & (np.minimum(np.minimum(u, v), w) <= BARYCENTRIC_SLACK)
            on_surface = within & (np.abs(t) <= INSIDE_ON_SURFACE_M)
            ambiguous |= ((edge & (t > -INSIDE_ON_SURFACE_M)) | on_surface).any(axis=1)
            crossings += (within & (t > INSIDE_ON_SURFACE_M)).sum(axis=1)
        clear = ~ambiguous
        out[p] = clear.sum() >= INSIDE_MIN_RAYS and bool(np.all(crossings[clear] % 2 == 1))
    return out


def cameras_inside(exp: Experiment, meshes: list[SceneMesh]) -> list[ConfigError]:
    """One `ConfigError` per (camera, mesh) whose optical centre lies inside the mesh
    (`inside_mesh`), naming the camera's field that places it and the fix; only the cameras
    within a mesh's bounding box are tested against it."""
    if not exp.camera_specs:
        return []
    positions = np.array(camera_positions(exp))
    errors = []
    for mesh in meshes:
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        near = np.flatnonzero(np.all((positions >= lo) & (positions <= hi), axis=1))
        if not len(near):
            continue
        for i in near[inside_mesh(positions[near], mesh.vertices, mesh.faces)]:
            spec = exp.camera_specs[i]
            fixed = spec.mount is not None and exp.mount(spec.mount).kind == "fixed"
            field, fix = (("u", "move it out along its rail (u) or off it (offset_m)") if spec.rail else
                          ("mount", "stand it on a mount outside the mesh") if fixed else
                          ("position_m", "move it out of the mesh"))
            errors.append(ConfigError(exp.path, f'camera "{spec.name}".{field}',
                                      f"its optical centre {np.round(positions[i], 4).tolist()} m lies "
                                      f"inside mesh {mesh.name!r}: {fix}"))
    return errors


def split_at_boxes(vertices: np.ndarray, faces: np.ndarray, regions) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with every triangle that crosses a face plane of a region box split along it.

    A plane x_k = c of a region's box is used only where it crosses a triangle that the region
    could select (its normal within the tolerance, overlapping the box); it then splits every
    triangle of the mesh that it crosses (one vertex alone on one side -> 3 triangles, a vertex on
    the plane -> 2), with one new vertex per cut edge, so a closed mesh stays closed and the
    surface is unchanged. Afterwards each triangle lies on one side of every such plane."""
    eps = 1e-9 * max(1.0, float(np.abs(vertices).max()))   # splitting keeps the extent
    done = set()   # planes already split at: no triangle crosses them any more (the pieces of
    # a later split lie inside their triangle), so regions that share a plane test it once
    for region in regions:
        planes = [(k, float(c)) for k in range(3) for c in (region.box_min[k], region.box_max[k])
                  if np.isfinite(c) and (k, float(c)) not in done]
        tri = None   # the triangles and what the region could select of them, until a split
        for k, c in planes:
            if tri is None:
                tri = vertices[faces]
                normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
                length = np.linalg.norm(normals, axis=1)
                facing = (np.ones(len(tri), dtype=bool) if region.normal is None else
                          normals @ region.normal >= np.cos(region.normal_tolerance) * np.maximum(length, 1e-300))
                selectable = facing & np.all((tri.max(axis=1) >= region.box_min)
                                             & (tri.min(axis=1) <= region.box_max), axis=1)
            offset = tri[..., k] - c
            side = np.sign(np.where(np.abs(offset) < eps, 0.0, offset))
            crossing = (side.max(axis=1) > 0) & (side.min(axis=1) < 0)
            if np.any(crossing & selectable):
                log.info("region %r: %d faces split at its box plane %s = %g m", region.name,
                         int(crossing.sum()), "xyz"[k], c)
                vertices, faces = _split_plane(vertices, faces, side, crossing, k, c)
                done.add((k, c))
                tri = None
            elif not crossing.any():
                done.add((k, c))
    return vertices, faces


def _split_plane(vertices, faces, side, crossing, k, c):
    new_vertices, cache, out = [vertices], {}, [faces[~crossing]]
    count = len(vertices)

    def cut(a, b):
        nonlocal count
        key = (min(a, b), max(a, b))
        if key not in cache:
            p, q = vertices[key[0]], vertices[key[1]]
            point = p + (q - p) * ((c - p[k]) / (q[k] - p[k]))
            point[k] = c
            new_vertices.append(point[None])
            cache[key], count = count, count + 1
        return cache[key]

    pieces = []
    for f, s in zip(faces[crossing], side[crossing]):
        zero = np.flatnonzero(s == 0)
        if len(zero):                                   # a vertex on the plane: 2 triangles
            r = int(zero[0])
            a, b, d = f[r], f[(r + 1) % 3], f[(r + 2) % 3]
            p = cut(b, d)
            pieces += [(a, b, p), (a, p, d)]
        else:                                           # one vertex alone on its side: 3
            r = next(i for i in range(3) if s[i] != s[(i + 1) % 3] and s[i] != s[(i + 2) % 3])
            a, b, d = f[r], f[(r + 1) % 3], f[(r + 2) % 3]
            p, q = cut(a, b), cut(a, d)
            pieces += [(a, p, q), (p, b, d), (p, d, q)]
    out.append(np.array(pieces, dtype=np.int64).reshape(-1, 3))
    return np.concatenate(new_vertices), np.concatenate(out)


# --------------------------------------------------------------------------------------------
# Surface samples on the regions of interest
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SurfaceSamples:
    """Area-uniform samples on the regions of interest (N of them). Lengths in metres."""

    points: np.ndarray       # (N, 3)
    normals: np.ndarray      # (N, 3) outward unit normals
    tangent_u: np.ndarray    # (N, 3) unit, with tangent_v: the face's parametric frame
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


NEAR_FIELDS = {"near_point_m": "a point", "near_axis_m": "an axis", "near_mesh": "mesh",
               "region_file": "the region mesh"}


@dataclass(frozen=True, eq=False)
class RegionSelector:
    """What a region selects, as predicates: the normal cone per face, the box and the distance
    band [beyond, within] per point (m). `distance(points)` is the distance to the near_* point,
    axis or surface (None without one)."""

    region: RegionSpec
    distance: Callable[[np.ndarray], np.ndarray] | None = None
    within: float = math.inf

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

    def keep(self, points: np.ndarray) -> np.ndarray:
        """(N,) the points the region keeps of those on its selected faces: in the box and band."""
        return self.in_box(points) & self.in_band(points)


def region_selector(exp: Experiment, region: RegionSpec, meshes: list[SceneMesh],
                    spacing: float) -> RegionSelector:
    """The `RegionSelector` of `region`: the near_mesh's surface from `meshes`, the region_file
    read in the specimen mesh's unit; a region file's band defaults to `spacing` (m)."""
    field = f'region "{region.name}".region_file'
    if region.near_point is not None:
        distance = lambda x: np.linalg.norm(x - region.near_point, axis=1)
    elif region.near_axis is not None:
        distance = lambda x: surface.distance_to_line(x, *region.near_axis)
    elif region.near_mesh is not None:
        other = next(m for m in meshes if m.name == region.near_mesh)
        distance = lambda x: surface.distance_to_mesh(x, other.vertices, other.faces)
    elif region.region_file is not None:
        scale = next(m.scale for m in exp.meshes if m.name == region.mesh)
        loaded = _read_mesh(region.region_file, (exp.path, field))
        v, f = np.asarray(loaded.vertices, float) * scale, np.asarray(loaded.faces)
        distance = lambda x: surface.distance_to_mesh(x, v, f)
    else:
        return RegionSelector(region)
    within = region.within if region.within is not None else spacing
    return RegionSelector(region, distance, within)


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
        best = float(np.degrees(np.arccos(np.clip((tm.face_normals @ region.normal).max(), -1, 1))))
        raise ConfigError(*where, f"selects no face of mesh {mesh.name!r}: the closest face normal is "
                                  f"{best:.1f} deg from normal (tolerance "
                                  f"{np.degrees(region.normal_tolerance):g} deg); check normal, "
                                  "normal_tolerance_deg, box_min_m and box_max_m (metres, world frame)")
    raise ConfigError(*where, f"selects no face of mesh {mesh.name!r}: check box_min_m and box_max_m "
                              "(metres, world frame)")


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
        selector = region_selector(None, region, [], spacing)
    centroids = tm.triangles_center
    radius = np.linalg.norm(tm.triangles - centroids[:, None], axis=2).max(axis=1)
    chosen = selector.facing(tm.face_normals) & selector.in_box(centroids) & (tm.area_faces > 0)
    if selector.distance is not None and chosen.any():
        chosen[chosen] = selector.in_band(centroids[chosen], radius[chosen])
    faces = np.flatnonzero(chosen)
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
                  rf: RegionFaces | None = None) -> dict:
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
        raise ConfigError(*where, f"is smaller than the sample spacing ({spacing * 1e3:g} mm)")
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
    t_u = J[:, :, 0] - normal * np.einsum("ij,ij->i", J[:, :, 0], normal)[:, None]
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


def all_region_faces(exp: Experiment, meshes: list[SceneMesh],
                     spacing: float | None = None) -> list[RegionFaces]:
    """`region_faces` for every region of the experiment, in config order."""
    spacing = exp.evaluation.sample_spacing if spacing is None else spacing
    by_name = {m.name: m for m in meshes}
    return [region_faces(by_name[r.mesh], r, spacing, (exp.path, f'region "{r.name}"'),
                         selector=region_selector(exp, r, meshes, spacing))
            for r in exp.regions]


MAX_SAMPLES = 2_000_000     # surface samples: ~1 GB of visibility and uncertainty arrays for 10 cameras


def check_sample_count(exp: Experiment, meshes: list[SceneMesh], faces: list[RegionFaces],
                       spacing: float) -> None:
    """ConfigError before sampling when the regions' area A would give more than MAX_SAMPLES
    samples at spacing h (N = A / h^2), with the smallest spacing that fits."""
    area = sum(float(m.trimesh.area_faces[rf.faces].sum()) for m, rf in zip(meshes, faces))
    count = area / spacing**2
    if count > MAX_SAMPLES:
        fits = math.ceil(math.sqrt(area / MAX_SAMPLES) * 1e4) / 10
        raise ConfigError(exp.path, "evaluation.sample_spacing_mm",
                          f"= {spacing * 1e3:g} mm gives about {count:,.0f} samples on the regions' "
                          f"{area:.3g} m² (at most {MAX_SAMPLES:,}): raise sample_spacing_mm to "
                          f"{fits:g} or more")


def sample_regions(exp: Experiment, meshes: list[SceneMesh], spacing: float | None = None,
                   faces: list[RegionFaces] | None = None) -> SurfaceSamples:
    """Samples on every region of the experiment, at `spacing` (m; default from the config), on
    the regions' `faces` (`all_region_faces` at that spacing; found here when not given)."""
    spacing = exp.evaluation.sample_spacing if spacing is None else spacing
    by_name = {m.name: m for m in meshes}
    faces = all_region_faces(exp, meshes, spacing) if faces is None else faces
    check_sample_count(exp, [by_name[r.mesh] for r in exp.regions], faces, spacing)
    parts = []
    for index, (region, rf) in enumerate(zip(exp.regions, faces)):
        part = sample_region(by_name[region.mesh], region, spacing,
                             (exp.path, f'region "{region.name}"'), rf)
        part["region"] = np.full(len(part["points"]), index)
        parts.append(part)
    merged = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    period = np.array([0.0 if rf.development is None else rf.development.period for rf in faces])
    return SurfaceSamples(**merged, region_names=tuple(r.name for r in exp.regions),
                          region_importance=np.array([r.importance for r in exp.regions]),
                          region_period=period,
                          region_cell=np.array([spacing if rf.development is None else
                                                ring_spacing(rf.development.period, spacing)
                                                for rf in faces]),
                          region_turn=np.array([0.0 if rf.development is None else
                                                rf.development.flip * rf.development.turn for rf in faces]))


# --------------------------------------------------------------------------------------------
# The cameras
# --------------------------------------------------------------------------------------------
def cameras_of(exp: Experiment) -> list[Camera]:
    """The configured cameras of `exp` (`vdo.model.camera.Camera`), in [[camera]] order: optical
    centres from rails and positions (`camera_positions`), aimed at target_m or by pan and tilt
    (`CameraSpec.angles`), pixel pitch = sensor width / pixel columns."""
    out = []
    for spec, position in zip(exp.camera_specs, camera_positions(exp)):
        pan, tilt = spec.angles(position)
        width, height = spec.pixels
        out.append(Camera(name=spec.name, width=width, height=height,
                          pixel_size=spec.sensor_width / width, focal_length=spec.focal_length,
                          position=position, pan=pan, tilt=tilt, roll=spec.roll,
                          principal_offset_px=spec.principal_offset_px, distortion=spec.distortion))
    return out


# --------------------------------------------------------------------------------------------
# Camera bodies as obstacles
# --------------------------------------------------------------------------------------------
BODY_SIZE = (0.14, 0.10, 0.08)   # width, height, depth of a DSLR body, m
LENS_DIAMETER = 0.075            # m


def lens_length(focal_length: float) -> float:
    """Length of the lens barrel (m): 1.2 x the focal length, within [4, 15] cm."""
    return float(np.clip(focal_length * 1.2, 0.04, 0.15))


@functools.lru_cache(maxsize=64)
def _body_arrays(focal_length: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of `camera_body_local`, built once per focal length (read-only)."""
    length = lens_length(focal_length)
    lens = trimesh.creation.cylinder(radius=LENS_DIAMETER / 2, height=length, sections=24)
    lens.apply_translation([0, 0, -length / 2])
    body = trimesh.creation.box(extents=BODY_SIZE)
    body.apply_translation([0, 0, -length - BODY_SIZE[2] / 2])
    mesh = trimesh.util.concatenate([lens, body])
    vertices, faces = np.array(mesh.vertices), np.array(mesh.faces)
    vertices.setflags(write=False)
    faces.setflags(write=False)
    return vertices, faces


def camera_body_local(focal_length: float) -> trimesh.Trimesh:
    """The body in the camera's own OpenCV frame (z forward): a lens barrel over z in [-L, 0] and
    a DSLR-sized box behind it. Everything lies behind the optical centre (the lens front), so a
    ray that reaches the camera's own optical centre from its field of view never crosses it."""
    vertices, faces = _body_arrays(float(focal_length))
    return trimesh.Trimesh(vertices.copy(), faces.copy(), process=False)


def camera_body_points(focal_length: float) -> np.ndarray:
    """(B, 3) points on the body's outline in the camera frame, for clearance: the rims of the
    lens barrel and the corners and face centres of the box."""
    length = lens_length(focal_length)
    a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = np.c_[np.cos(a), np.sin(a), np.zeros(8)] * (LENS_DIAMETER / 2)
    w, h, d = BODY_SIZE
    corners = np.array([[x, y, z] for x in (-w / 2, w / 2) for y in (-h / 2, h / 2)
                        for z in (-length, -length - d)])
    faces = np.array([[0, 0, -length - d], [w / 2, 0, -length - d / 2], [-w / 2, 0, -length - d / 2],
                      [0, h / 2, -length - d / 2], [0, -h / 2, -length - d / 2]])
    return np.vstack([ring, ring - [0, 0, length], corners, faces])


def camera_body_spheres(focal_length: float) -> tuple[np.ndarray, np.ndarray]:
    """Spheres whose union covers the body (camera frame): centres (10, 3) and radii (10,) m;
    two along the lens barrel and one around each eighth of the box (overshoot ~1.5 cm), a smooth
    stand-in for the mesh in the shadow penalty."""
    length = lens_length(focal_length)
    w, h, d = BODY_SIZE
    quarter = length / 4
    lens = np.array([[0, 0, -quarter], [0, 0, -3 * quarter]])
    box = np.array([[x * w / 4, y * h / 4, -length - d / 2 + z * d / 4]
                    for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    radii = [float(np.hypot(LENS_DIAMETER / 2, quarter))] * 2 + [0.25 * float(np.sqrt(w * w + h * h + d * d))] * 8
    return np.vstack([lens, box]), np.array(radii)


def camera_body(camera: Camera) -> SceneMesh:
    """`camera_body_local` placed at the camera's pose, as an obstacle for the other cameras:
    X_world = R^T X_cam + C."""
    vertices, faces = _body_arrays(float(camera.focal_length))
    return SceneMesh(f"camera:{camera.name}", "camera", vertices @ camera.R + camera.position,
                     faces.copy())


# --------------------------------------------------------------------------------------------
# Tripods as obstacles
# --------------------------------------------------------------------------------------------
TRIPOD_SECTIONS = 24     # sides of the prisms that stand for the legs' and column's cylinders


def tripod_cylinders(camera: Camera, spec: TripodSpec) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The tripod under `camera` as cylinders (top (3,), bottom (3,), radius), metres, world frame:
    the legs first, then the centre column; [] when the top casting is not above the floor.

    The body's centre is B = C - (L + d/2) z_c (`camera_body_local`: lens length L, body depth d,
    optical centre C, optical axis z_c); the top casting is T = B - (h_body/2 + head_m) e_z. Leg k
    (k = 0 .. legs-1) runs from T to the foot T_floor + spread_m (cos φ_k, sin φ_k, 0), with
    T_floor = T with z = floor_z_m and φ_k = pan + azimuth_deg + 2πk/legs; the column runs from T
    down by min(column_length_m, T_z - floor_z_m). Everything hangs below the top casting, inside
    the cone of the legs, so a camera that looks up, level, or down less steeply than its legs
    lean sees past its own tripod (tests/test_tripods.py)."""
    length = lens_length(camera.focal_length)
    body_centre = np.asarray(camera.position, float) - (length + BODY_SIZE[2] / 2) * camera.optical_axis
    top = body_centre - np.array([0.0, 0.0, BODY_SIZE[1] / 2 + spec.head])
    height = top[2] - spec.floor_z
    if height <= 0:
        return []
    below = np.array([top[0], top[1], spec.floor_z])
    angles = camera.pan + spec.azimuth + 2 * np.pi * np.arange(spec.legs) / spec.legs
    feet = below + spec.spread * np.c_[np.cos(angles), np.sin(angles), np.zeros(spec.legs)]
    legs = [(top, foot, spec.leg_diameter / 2) for foot in feet]
    column = top - np.array([0.0, 0.0, min(spec.column_length, height)])
    return legs + [(top, column, spec.column_diameter / 2)]


def _prism_faces(sections: int) -> np.ndarray:
    """Triangles of a closed prism whose vertices are `sections` points of the bottom ring, the
    same of the top ring, then the bottom and top centres; wound counter-clockwise seen from
    outside (outward normals, as the renderer's one-sided BSDFs need)."""
    k = np.arange(sections)
    nxt = (k + 1) % sections
    bottom, top = 2 * sections, 2 * sections + 1
    side = np.concatenate([np.c_[k, nxt, sections + nxt], np.c_[k, sections + nxt, sections + k]])
    caps = np.concatenate([np.c_[np.full(sections, bottom), nxt, k],
                           np.c_[np.full(sections, top), sections + k, sections + nxt]])
    return np.concatenate([side, caps])


PRISM_FACES = _prism_faces(TRIPOD_SECTIONS)


def prism(top: np.ndarray, bottom: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the closed TRIPOD_SECTIONS-sided prism inscribed in the cylinder of
    axis bottom -> top and `radius` (m): ring vertices bottom + r (cos α_j e_1 + sin α_j e_2)
    (+ the axis for the top ring), e_1, e_2 unit and perpendicular to the axis."""
    bottom, axis = np.asarray(bottom, float), np.asarray(top, float) - np.asarray(bottom, float)
    a = axis / np.linalg.norm(axis)
    e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    angle = 2 * np.pi * np.arange(TRIPOD_SECTIONS) / TRIPOD_SECTIONS
    ring = bottom + radius * (np.cos(angle)[:, None] * e1 + np.sin(angle)[:, None] * e2)
    return np.vstack([ring, ring + axis, bottom, bottom + axis]), PRISM_FACES


def tripod(camera: Camera, spec: TripodSpec) -> list[SceneMesh]:
    """`tripod_cylinders` as closed prisms of TRIPOD_SECTIONS sides inscribed in the cylinders
    (`prism`: radius short by at most r (1 - cos(π / TRIPOD_SECTIONS)), under 1 %), one obstacle
    mesh each (so that `vdo.physics.lighting.relight` bounds each part alone)."""
    return [SceneMesh(f"tripod:{camera.name}:{k}", "camera", *prism(top, bottom, radius))
            for k, (top, bottom, radius) in enumerate(tripod_cylinders(camera, spec))]


def tripods(exp: Experiment, cameras) -> list[SceneMesh]:
    """The `tripod` parts of every camera of `cameras` that the experiment lists on a zone
    [[mount]] with a [mount.tripod], built where the camera stands."""
    mounts = {spec.name: spec.mount for spec in exp.camera_specs}
    specs = {m.name: m.tripod for m in exp.mounts if m.tripod is not None}
    return [part for c in cameras if mounts.get(c.name) in specs
            for part in tripod(c, specs[mounts[c.name]])]


# --------------------------------------------------------------------------------------------
# Mitsuba
# --------------------------------------------------------------------------------------------
def mitsuba_mesh(mesh: SceneMesh, bsdf=None, uv: np.ndarray | None = None):
    """An in-memory `mi.Mesh` with the same vertices and faces, an optional BSDF (a loaded
    Mitsuba BSDF or a dict) and optional per-vertex texture coordinates uv (n, 2)."""
    mi = mitsuba()
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    out = mi.Mesh(mesh.name, len(mesh.vertices), len(mesh.faces), props=props,
                  has_vertex_texcoords=uv is not None)
    params = mi.traverse(out)
    params["vertex_positions"] = np.ascontiguousarray(mesh.vertices, dtype=np.float32).ravel()
    params["faces"] = np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel()
    if uv is not None:
        params["vertex_texcoords"] = np.ascontiguousarray(uv, dtype=np.float32).ravel()
    params.update()
    return out


def build_scene(meshes: list[SceneMesh]):
    """A Mitsuba scene holding the meshes as shapes, for ray casting."""
    mi = mitsuba()
    scene = {"type": "scene"}
    for i, mesh in enumerate(meshes):
        scene[f"shape_{i:03d}"] = mitsuba_mesh(mesh)
    return mi.load_dict(scene)
