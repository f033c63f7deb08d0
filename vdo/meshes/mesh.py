"""The scene's triangle meshes (`SceneMesh`, world metres): the [[mesh]] files read and checked
(readable content, extents that fit the declared unit, no camera inside a mesh: `inside_mesh`, by
the even-odd rule; faces wound against their neighbours said in a warning: `faces_against`),
and a specimen's faces split at its regions' boxes (`split_at_boxes`) and at the edges of their
distance bands (`split_at_bands`).

Meshes are read with trimesh (Mitsuba has no STL loader) and handed to Mitsuba in memory
(`vdo.scene.mitsuba_mesh`), so a user's CAD export and the built-in example take the same path.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh

from vdo.config.experiment import camera_positions
from vdo.config.mounts import MountSpec, RailSpec
from vdo.config.rig import UNITS, CameraSpec, MeshSpec, RegionSpec
from vdo.config.schema import IMAGE_MAGIC
from vdo.core.errors import Collect, ConfigError
from vdo.core.tolerances import BARYCENTRIC_SLACK, TINY
from vdo.model import surface

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


def load_meshes(*, mesh_specs: tuple[MeshSpec, ...], regions: tuple[RegionSpec, ...],
                camera_specs: tuple[CameraSpec, ...], rails: tuple[RailSpec, ...],
                mounts: tuple[MountSpec, ...], path, errors: Collect | None = None) -> list[SceneMesh]:
    """Read every mesh of `mesh_specs` (an experiment's [[mesh]] tables), scaled to metres, and
    check it: readable content, extents that fit the declared unit, a consistent winding (else a
    warning naming the mesh, its file and the faces wound against the rest), no camera of `camera_specs`
    (placed by `rails` and `mounts`) inside it (`cameras_inside`). Every mesh is checked and every
    mistake reported together (`vdo.core.errors.Collect`), each naming the experiment file
    `path`. Specimen faces that cross a box of one of `regions` are split at the box
    (`split_at_boxes`), and those that cross the edge of a region's distance band at that edge
    (`split_at_bands`), so a region's faces and area are exactly the part inside its box and
    band. With
    `errors`, the mistakes are kept there instead of raised, and the meshes that could be read
    are returned."""
    own = errors is None
    errors = Collect() if own else errors
    meshes = []
    for spec in mesh_specs:
        with errors.check():
            meshes.append(_load_mesh(spec, regions=regions, path=path))
    errors.errors += cameras_inside(meshes, camera_specs=camera_specs, rails=rails, mounts=mounts,
                                    path=path)
    if own:
        errors.raise_all()
    with errors.check():
        meshes = split_at_bands(meshes, regions=regions, mesh_specs=mesh_specs, path=path)
    return meshes


def _load_mesh(spec: MeshSpec, *, regions: tuple[RegionSpec, ...], path) -> SceneMesh:
    field = f'mesh "{spec.name}".file'
    loaded = read_mesh(spec.path, (path, field))
    vertices = np.asarray(loaded.vertices, dtype=float) * spec.scale
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ConfigError(path, field, f"{spec.path.name!r} has faces that refer to missing vertices")
    if not np.all(np.isfinite(vertices)):
        raise ConfigError(path, field, f"{spec.path.name!r} has non-finite vertex coordinates")
    _check_extent(vertices[np.unique(faces)], spec, (path, field))
    against = faces_against(vertices, faces)
    if against != 0:
        log.warning("mesh %r (%s): %s wound against their neighbours (their normals point the "
                    "other way: the renders draw them dark and a region's normal selector and area "
                    "take them wrong): fix the winding in the file (e.g. trimesh's repair.fix_winding)",
                    spec.name, spec.path.name, "some faces" if against is None else f"{against} face(s)")
    if spec.role == "specimen":
        vertices, faces = split_at_boxes(vertices, faces, [r for r in regions if r.mesh == spec.name])
    return SceneMesh(spec.name, spec.role, vertices, faces)


def faces_against(vertices: np.ndarray, faces: np.ndarray) -> int | None:
    """How many of the faces (`vertices` (n, 3) m, `faces` (m, 3)) are wound against their
    neighbours: 0 when trimesh finds the winding consistent (vertices merged first: an STL's
    triangles share none); else, per connected patch of faces, the smaller of the two classes
    that a consistent winding tells apart (two faces sharing an edge are in one class when they
    run it in opposite directions); None when no winding is consistent (a one-sided surface such
    as a Moebius strip)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    merged = trimesh.Trimesh(vertices, faces, process=True)
    if merged.is_winding_consistent:
        return 0
    tri, pairs, shared = merged.faces, merged.face_adjacency, merged.face_adjacency_edges

    def forward(side):   # whether that face of each pair runs the shared edge from its first vertex
        corners = tri[pairs[:, side]]
        at = [np.argmax(corners == shared[:, k, None], axis=1) for k in (0, 1)]
        return (at[1] - at[0]) % 3 == 1

    same = forward(0) == forward(1)                      # the pair runs the edge the same way
    n, a, b = len(tri), pairs[:, 0], pairs[:, 1]
    # faces twice over (f: as wound, f + n: flipped); a pair ties a face to its neighbour as wound
    # when they run the edge in opposite directions, to its flipped copy when the same way
    cross = np.where(same, n, 0)
    twice = coo_matrix((np.ones(2 * len(a)), (np.concatenate([a, a + n]),
                                               np.concatenate([b + cross, b + n - cross]))),
                       shape=(2 * n, 2 * n))
    label = connected_components(twice, directed=False)[1]
    if np.any(label[:n] == label[n:]):
        return None
    patches = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)[1]
    first = np.full(patches.max() + 1, n)
    np.minimum.at(first, patches, np.arange(n))          # a face of each patch: its class is "one"
    one = label[:n] == label[first[patches]]
    size, ones = np.bincount(patches), np.bincount(patches, weights=one)
    return int(np.minimum(ones, size - ones).sum())


MAX_MESH_EXTENT = 100.0      # m: a test setup larger than this is a unit mistake
NOT_MESHES = {**IMAGE_MAGIC, b"%PDF": "PDF", b"PK\x03\x04": "ZIP", b"\x1f\x8b": "gzip"}


def read_mesh(path, where) -> trimesh.Trimesh:
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


def cameras_inside(meshes: list[SceneMesh], *, camera_specs: tuple[CameraSpec, ...],
                   rails: tuple[RailSpec, ...], mounts: tuple[MountSpec, ...],
                   path) -> list[ConfigError]:
    """One `ConfigError` (at the experiment file `path`) per (camera of `camera_specs`, mesh)
    whose optical centre (on its rail of `rails`, `camera_positions`) lies inside the mesh
    (`inside_mesh`), naming the camera's field that places it (a fixed mount of `mounts`: its
    `mount`) and the fix; only the cameras within a mesh's bounding box are tested against it."""
    if not camera_specs:
        return []
    positions = np.array(camera_positions(camera_specs, rails))
    errors = []
    for mesh in meshes:
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        near = np.flatnonzero(np.all((positions >= lo) & (positions <= hi), axis=1))
        if not len(near):
            continue
        for i in near[inside_mesh(positions[near], mesh.vertices, mesh.faces)]:
            spec = camera_specs[i]
            fixed = spec.mount is not None and next(
                m for m in mounts if m.name == spec.mount).kind == "fixed"
            field, fix = (("u", "move it out along its rail (u) or off it (offset_m)") if spec.rail else
                          ("mount", "stand it on a mount outside the mesh") if fixed else
                          ("position_m", "move it out of the mesh"))
            errors.append(ConfigError(path, f'camera "{spec.name}".{field}',
                                      f"its optical centre {np.round(positions[i], 4).tolist()} m lies "
                                      f"inside mesh {mesh.name!r}: {fix}"))
    return errors


def _selectable(triangles: np.ndarray, region) -> np.ndarray:
    """(T,) the triangles (T, 3, 3) that `region` could select: its normal within the tolerance
    (when it has one) and overlapping its box."""
    out = np.all((triangles.max(axis=1) >= region.box_min) & (triangles.min(axis=1) <= region.box_max), axis=1)
    if region.normal is not None:
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        length = np.linalg.norm(normals, axis=1)
        out &= normals @ region.normal >= np.cos(region.normal_tolerance) * np.maximum(length, 1e-300)
    return out


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
                selectable = _selectable(tri, region)
            offset = tri[..., k] - c
            side = np.sign(np.where(np.abs(offset) < eps, 0.0, offset))
            crossing = (side.max(axis=1) > 0) & (side.min(axis=1) < 0)
            if np.any(crossing & selectable):
                sharing = [r.name for r in regions if c in (float(r.box_min[k]), float(r.box_max[k]))]
                log.info("%d mesh faces split at the plane %s = %g m (a box face of region %s), so that "
                         "regions end there exactly", int(crossing.sum()), "xyz"[k], c,
                         ", ".join(repr(n) for n in sharing))
                vertices, faces = _split_plane(vertices, faces, side, crossing, k, c)
                done.add((k, c))
                tri = None
            elif not crossing.any():
                done.add((k, c))
    return vertices, faces


BAND_EDGE_M = 1e-9          # m: a vertex this close to a distance band's edge lies on it (the
                            # band's cuts place theirs to ~1e-13 m of it, `BAND_BISECTIONS`)
BAND_BISECTIONS = 48        # bisection steps of a band's cut along an edge (2^-48 of the edge)


@dataclass(frozen=True, eq=False)
class Band:
    """The distance that a region's band is measured in: `distance(points (N, 3))` -> (N,) m,
    and for a convex distance (to a point or a line) `least(triangles (T, 3, 3))` -> (T,) its
    least value on each triangle, exact (None for the distance to a mesh). A convex distance is
    greatest on a triangle at a vertex, so a triangle holds part of the band [beyond, within]
    exactly when least < within and its greatest vertex distance > beyond."""

    distance: Callable[[np.ndarray], np.ndarray]
    least: Callable[[np.ndarray], np.ndarray] | None = None


def band_distance(region: RegionSpec, meshes: list[SceneMesh], *, mesh_specs: tuple[MeshSpec, ...],
                  path) -> Band | None:
    """The `Band` of `region`'s near_point_m, near_axis_m, near_mesh (one of `meshes`) or
    region_file (read in the unit of the region's mesh in `mesh_specs`; a file that cannot be
    read is a ConfigError at the experiment file `path`); None without one."""
    if region.near_point is not None:
        point = region.near_point
        return Band(lambda x: np.linalg.norm(x - point, axis=1),
                    lambda t: surface.point_triangle_distance(np.broadcast_to(point, (len(t), 3)), t))
    if region.near_axis is not None:
        ends = region.near_axis
        return Band(lambda x: surface.distance_to_line(x, *ends),
                    lambda t: surface.line_triangle_distance(t, *ends))
    if region.near_mesh is not None:
        other = next(m for m in meshes if m.name == region.near_mesh)
        return Band(lambda x: surface.distance_to_mesh(x, other.vertices, other.faces))
    if region.region_file is not None:
        scale = next(m.scale for m in mesh_specs if m.name == region.mesh)
        loaded = read_mesh(region.region_file, (path, f'region "{region.name}".region_file'))
        v, f = np.asarray(loaded.vertices, float) * scale, np.asarray(loaded.faces)
        return Band(lambda x: surface.distance_to_mesh(x, v, f))
    return None


def split_at_bands(meshes: list[SceneMesh], *, regions: tuple[RegionSpec, ...],
                   mesh_specs: tuple[MeshSpec, ...], path) -> list[SceneMesh]:
    """`meshes` with every specimen triangle that a region could select (its normal within the
    tolerance, overlapping the box) and whose vertices lie on both sides of an edge of the
    region's distance band (within_m, and beyond_m when > 0) split along it, like
    `split_at_boxes`: the cut on each crossed edge found by bisection of the distance along it,
    so each piece lies on one side of the band's edge (its vertices there or on it, to
    `BAND_EDGE_M`). A region then holds the part of a large face that lies in its band, not the
    whole face (a flange beside a nozzle's wall, a fan of long triangles). Only a convex
    distance (to a point or an axis: `Band.least`) is split at; a band around a mesh keeps the
    faces that may reach into it."""
    out = []
    for mesh in meshes:
        vertices, faces = mesh.vertices, mesh.faces
        for region in regions:
            convex = region.near_point is not None or region.near_axis is not None   # `Band.least`
            if mesh.role != "specimen" or region.mesh != mesh.name or region.within is None or not convex:
                continue
            band = band_distance(region, meshes, mesh_specs=mesh_specs, path=path)
            distance = band.distance
            for level in (region.within, region.beyond):
                if level <= 0:
                    continue
                offset = distance(vertices) - level
                side = np.sign(np.where(np.abs(offset) <= BAND_EDGE_M, 0.0, offset))[faces]
                crossing = (side.max(axis=1) > 0) & (side.min(axis=1) < 0) & _selectable(vertices[faces], region)
                if not crossing.any():
                    continue
                log.info("%d faces of mesh %r split at %g m from region %r's %s, so that the region "
                         "ends there exactly", int(crossing.sum()), mesh.name, level, region.name,
                         region.near.removesuffix("_m").replace("_", " "))

                def at(p, q, level=level, distance=distance):
                    lo, hi = np.zeros(len(p)), np.ones(len(p))
                    below = distance(p) < level          # which end lies below the level
                    for _ in range(BAND_BISECTIONS):
                        mid = 0.5 * (lo + hi)
                        under = distance(p + (q - p) * mid[:, None]) < level
                        lo, hi = np.where(under == below, mid, lo), np.where(under == below, hi, mid)
                    return p + (q - p) * (0.5 * (lo + hi))[:, None]
                vertices, faces = _split(vertices, faces, side, crossing, at)
        out.append(mesh if vertices is mesh.vertices else SceneMesh(mesh.name, mesh.role, vertices, faces))
    return out


def _split_plane(vertices, faces, side, crossing, k, c):
    """`_split` at the plane x_k = c (the cut points on it exactly)."""
    def at(p, q):
        point = p + (q - p) * ((c - p[:, k]) / (q[:, k] - p[:, k]))[:, None]
        point[:, k] = c
        return point
    return _split(vertices, faces, side, crossing, at)


def _split(vertices, faces, side, crossing, at):
    """The mesh with each `crossing` triangle cut where its edges change `side` (per face vertex
    -1, 0 or 1; a vertex at 0 lies on the cut): one vertex alone on its side -> 3 triangles, a
    vertex on the cut -> 2. `at(p, q)` (E, 3) gives the cut points of the edges p -> q (E, 3);
    each cut edge gets one new vertex, shared by the triangles on both sides of it, so a closed
    mesh stays closed."""
    edges = []
    for f, s in zip(faces[crossing], side[crossing]):
        zero = np.flatnonzero(s == 0)
        if len(zero):
            r = int(zero[0])
            edges.append((f[(r + 1) % 3], f[(r + 2) % 3]))
        else:
            r = next(i for i in range(3) if s[i] != s[(i + 1) % 3] and s[i] != s[(i + 2) % 3])
            edges += [(f[r], f[(r + 1) % 3]), (f[r], f[(r + 2) % 3])]
    keys = sorted({(min(a, b), max(a, b)) for a, b in edges})
    cache = {key: len(vertices) + n for n, key in enumerate(keys)}
    ends = np.array(keys, dtype=np.int64).reshape(-1, 2)
    new_vertices = [vertices, at(vertices[ends[:, 0]], vertices[ends[:, 1]])]
    out = [faces[~crossing]]

    def cut(a, b):
        return cache[(min(a, b), max(a, b))]

    pieces = []
    for f, s in zip(faces[crossing], side[crossing]):
        zero = np.flatnonzero(s == 0)
        if len(zero):                                   # a vertex on the cut: 2 triangles
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
