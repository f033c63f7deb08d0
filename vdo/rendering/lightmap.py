"""The DIC render mode's light in surface space, shared by the cameras of a frame and by the load
steps (docs/render.md, "The surface light map"; `vdo.rendering.dic`).

The light a diffuse surface reflects (`vdo.rendering.shading.shade`: the panels and the ambient
sky) does not depend on the camera that sees it: the BSDF is f = ρ / π on the front side, so the
camera enters only through which side it sees. `SurfaceLightMap` holds that light on a lattice per
triangle of every diffuse shape: triangle t is cut into n_t² sub-triangles by the nodes of
barycentric coordinates (i / n_t, j / n_t), i + j <= n_t, with n_t chosen once per frame from its
cameras (`divisions`: MAP_STRIDE pixels of the finest footprint any of them has there). A node's
light is computed the first time a camera needs it and kept; the light at a point of the
triangle is then the linear interpolation of its sub-triangle's three nodes, taken where they
agree within a tolerance of the camera's light scale (`lookup`; elsewhere, a shadow's edge or a
penumbra, the light is computed at the point itself). Glossy shapes (satin paint, metal) and
back faces are always computed, per camera.

The lattice follows the mesh (triangle and barycentric coordinates), not the world: the same
map serves a load step's deformed mesh (the same faces), its nodes moved with the surface."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MAP_STRIDE", "MAP_TOLERANCE", "MAP_MAX_DIVISIONS", "SurfaceLightMap", "surface_light_map"]

MAP_STRIDE = 16              # px between neighbouring nodes of a triangle's lattice in the camera
                             # of the frame that sees the triangle largest (`divisions`)
MAP_TOLERANCE = 0.03         # a sub-triangle whose nodes' light differs by at most this fraction
                             # of the camera's light scale is interpolated (as the image-space
                             # map's coarsest cells, `vdo.rendering.dic.SHADE_TOLERANCE`)
PERSPECTIVE_FACTOR = 2.0     # `divisions`: at most this many times the divisions that the
                             # triangle's projected area asks for
MAP_MAX_PX = 2 * MAP_STRIDE  # a sub-triangle whose side may span more pixels than this in the
                             # camera (frontal bound: side x f / distance) is not interpolated
MAP_MAX_DIVISIONS = 2048     # at most this many divisions of a triangle's side
NEAR_DEPTH_M = 0.05          # a triangle closer to a camera than this is treated as at this depth


@dataclass
class SurfaceLightMap:
    """The light on a lattice per triangle of the diffuse shapes (module docstring). The shapes'
    triangles are numbered one after another (`offset` by Mitsuba shape id, `Shape.id()`);
    triangle t has `n[t]` divisions a side (0: not in the map) and its lattice's nodes are
    `values[base[t]:]` (NaN: not computed yet; +inf: a node whose light could not be computed),
    allocated a triangle at a time, the first time a camera's hit lies on it: node (i, j) of a
    lattice of n divisions at base + i (n + 1) - i (i - 1) / 2 + j."""

    offset: dict                       # Mitsuba shape id -> its first triangle's number
    n: np.ndarray                      # (T,) int64
    longest: np.ndarray                # (T,) the triangle's longest side (m, at rest)
    base: np.ndarray                   # (T,) int64, -1: not allocated
    values: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.float32))
    used: int = 0
    computed: int = 0                  # nodes whose light was computed
    alloc_tris: list = field(default_factory=list)   # triangles in the order of allocation

    @property
    def node_count(self) -> int:
        return self.computed

    def _allocate(self, tris: np.ndarray) -> None:
        tris = np.unique(tris[self.base[tris] < 0])
        if len(tris) == 0:
            return
        size = (self.n[tris] + 1) * (self.n[tris] + 2) // 2
        self.base[tris] = self.used + np.concatenate([[0], np.cumsum(size)[:-1]])
        need = self.used + int(size.sum())
        if need > len(self.values):
            grown = np.full(max(need, 2 * len(self.values)), np.nan, dtype=np.float32)
            grown[:self.used] = self.values[:self.used]
            self.values = grown
        self.used = need
        self.alloc_tris.append(tris)

    def lookup(self, dscene, si, prim_uv, scale: float, focal_px: float, tolerance: float | None = None):
        """(light, ok) at the hits `si` (Mitsuba SurfaceInteraction, n lanes) with barycentric
        coordinates `prim_uv` (Mitsuba's Point2f: p = (1 - u - v) p0 + u p1 + v p2): the
        interpolated light of each hit's sub-triangle where ok (a diffuse shape in the map, its
        front side seen, the sub-triangle's sides at most MAP_MAX_PX in a camera of focal length
        `focal_px` (px) at the hit's distance, its three nodes within `tolerance` x `scale` of one
        another), computing the nodes not computed yet; NaN where not ok. Numpy (n,) float32 and
        bool."""
        return self.finish(dscene, self.prepare(dscene, si, prim_uv), scale, focal_px, tolerance)

    def prepare(self, dscene, si, prim_uv) -> tuple:
        """What `finish` needs of the hits (Dr.Jit arrays, to be evaluated with the hits, whose
        other fields are then not kept): the map's triangle number, the barycentric coordinates
        and the distance from the ray's origin, the triangle 0xFFFFFFFF where not in the map
        (another shape, a miss, a back face)."""
        import drjit as dr

        from vdo.core.backend import mitsuba

        mi = mitsuba()
        table, _ = _id_table(dscene, self)
        sid = dr.reinterpret_array(mi.UInt32, si.shape)
        inside = sid < dr.width(table)
        off = dr.gather(mi.UInt32, table, sid, inside)
        active = inside & si.is_valid() & (mi.Frame3f.cos_theta(si.wi) > 0) & (off > 0)
        tri = dr.select(active, off - 1 + si.prim_index, 0xFFFFFFFF)
        return tri, mi.Float(prim_uv.x), mi.Float(prim_uv.y), mi.Float(si.t)

    def finish(self, dscene, prepared, scale: float, focal_px: float, tolerance: float | None = None):
        """`lookup` from `prepare`'s arrays."""
        import drjit as dr

        from vdo.core.backend import mitsuba

        mi = mitsuba()
        _, names = _id_table(dscene, self)
        tri, pu, pv, distance = prepared
        tolerance = MAP_TOLERANCE if tolerance is None else tolerance
        active = tri != 0xFFFFFFFF
        n = dr.gather(mi.UInt32, self._device("n"), tri, active)
        active &= n > 0
        side = dr.gather(mi.Float, self._device("longest"), tri, active) / mi.Float(n)
        active &= side * focal_px <= MAP_MAX_PX * distance
        hit = dr.zeros(mi.UInt32, max(len(self.n), 1))
        dr.scatter(hit, 1, tri, active)
        fresh = np.flatnonzero(np.array(hit))
        if len(fresh) and (self.base[fresh] < 0).any():
            self._allocate(fresh)
        base = dr.gather(mi.UInt32, self._device("base"), tri, active)
        nf = mi.Float(n)
        x, y = pu * nf, pv * nf
        ni = mi.Int32(n)
        i = dr.clip(mi.Int32(dr.floor(x)), 0, ni - 1)
        j = dr.clip(mi.Int32(dr.floor(y)), 0, ni - 1 - i)
        fi, fj = x - mi.Float(i), y - mi.Float(j)
        upper = (fi + fj > 1) & (i + j <= ni - 2)
        one = mi.Int32(1)
        corners = [(dr.select(upper, i + one, i), dr.select(upper, j + one, j)),
                   (dr.select(upper, i, i + one), dr.select(upper, j + one, j)),
                   (dr.select(upper, i + one, i), dr.select(upper, j, j + one))]
        weights = [dr.select(upper, fi + fj - 1, 1 - fi - fj), dr.select(upper, 1 - fj, fi),
                   dr.select(upper, 1 - fi, fj)]
        keys = [mi.UInt32(mi.Int32(base) + a * (ni + 1) - a * (a - 1) // 2 + b) for a, b in corners]
        values = self._device("values")
        v = [dr.gather(mi.Float, values, key, active) for key in keys]
        missing = active & (dr.isnan(v[0]) | dr.isnan(v[1]) | dr.isnan(v[2]))
        dr.eval(keys, v, weights, missing)
        lanes = dr.compress(missing)
        if dr.width(lanes):
            todo = np.unique(np.concatenate([np.array(dr.gather(mi.UInt32, key, lanes)) for key in keys]))
            todo = todo[np.isnan(self.values[todo])].astype(np.int64)
            self._compute(dscene, names, todo)
            values = self._device("values")
            v = [dr.gather(mi.Float, values, key, active) for key in keys]
        lo = dr.minimum(dr.minimum(v[0], v[1]), v[2])
        hi = dr.maximum(dr.maximum(v[0], v[1]), v[2])
        ok = active & (hi - lo <= tolerance * scale)          # False for NaN and inf
        light = dr.select(ok, weights[0] * v[0] + weights[1] * v[1] + weights[2] * v[2], dr.nan)
        dr.eval(light, ok)
        return np.array(light), np.array(ok)

    def _device(self, what: str):
        """The Dr.Jit copy of `n`, `base` or `values` (made again when they changed)."""
        from vdo.core.backend import mitsuba

        mi = mitsuba()
        cache = self.__dict__.setdefault("_copies", {})
        stamp = (self.used, self.computed)
        if what in cache and cache[what][0] == stamp:
            return cache[what][1]
        if what == "n":
            out = mi.UInt32(self.n.astype(np.uint32))
        elif what == "longest":
            out = mi.Float(self.longest.astype(np.float32))
        elif what == "base":
            out = mi.UInt32(np.maximum(self.base, 0).astype(np.uint32))
        else:
            out = mi.Float(self.values[:max(self.used, 1)])
        cache[what] = (stamp, out)
        return out

    def _nodes(self, keys: np.ndarray):
        """(triangle, i, j) of the nodes `keys`."""
        tris = np.concatenate(self.alloc_tris)
        order = np.argsort(self.base[tris])
        tris = tris[order]
        t = tris[np.searchsorted(self.base[tris], keys, side="right") - 1]
        n, k = self.n[t], keys - self.base[t]
        b = 2 * n + 3
        i = np.floor((b - np.sqrt(np.maximum(b * b - 8.0 * k, 0.0))) / 2).astype(np.int64)
        for _ in range(2):    # rounding: offset(i) <= k < offset(i + 1)
            i = np.where(i * b - i * i > 2 * k, i - 1, i)
            i = np.where((i + 1) * b - (i + 1) * (i + 1) <= 2 * k, i + 1, i)
        j = k - (i * b - i * i) // 2
        return t, i, j

    def _compute(self, dscene, names, keys: np.ndarray) -> None:
        """Shade the nodes `keys` on `dscene`'s shapes (their posed vertices)."""
        import drjit as dr

        from vdo.core.backend import mitsuba
        from vdo.rendering.shading import shade

        mi = mitsuba()
        tri, i, j = self._nodes(keys)
        starts = np.array([self.offset[name] for name, _ in names])
        owner = np.searchsorted(starts, tri, side="right") - 1
        prim = tri - starts[owner]
        n = self.n[tri].astype(np.float64)
        m = len(keys)
        normal = np.empty((m, 3))
        for k, (_, shape) in enumerate(names):
            at = np.flatnonzero(owner == k)
            if len(at):
                V, F = _vertices_faces(shape)
                p = V[F[prim[at]]]
                nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
                normal[at] = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        pi = dr.zeros(mi.PreliminaryIntersection3f, m)
        pi.t = mi.Float(np.ones(m, dtype=np.float32))
        pi.prim_uv = mi.Point2f((i / n).astype(np.float32), (j / n).astype(np.float32))
        pi.prim_index = mi.UInt32(prim.astype(np.uint32))
        pi.shape = dr.gather(mi.ShapePtr, mi.ShapePtr([shape for _, shape in names]),
                             mi.UInt32(owner.astype(np.uint32)))
        pi.valid = mi.Bool(True)
        # the ray comes along -n to the point (t = 1): the node is seen from its front side
        ray = mi.Ray3f(mi.Point3f(0.0, 0.0, 0.0),
                       mi.Vector3f(*(np.ascontiguousarray(-normal[:, k], dtype=np.float32) for k in range(3))))
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All)
        light = shade(dscene, si)
        good = np.array(si.is_valid() & (mi.Frame3f.cos_theta(si.wi) > 0))
        self.values[keys] = np.where(good, light, np.inf).astype(np.float32)
        self.computed += m


def _id_table(dscene, light_map):
    """(UInt32 table: registry id -> 1 + the map's number of the shape's first triangle, 0 where
    the shape is not in the map; [(Mitsuba shape id, shape)] of the map's shapes in the order of
    their first triangles) for `dscene`'s scene (cached on it)."""
    cached = getattr(dscene, "_id_table", None)
    if cached is not None and cached[0] is light_map:
        return cached[1], cached[2]
    from vdo.core.backend import mitsuba

    slots = dscene_slots(dscene)
    table = np.zeros(max(slots) + 1, dtype=np.uint32)
    names = []
    for sid, (name, shape) in slots.items():
        if name in light_map.offset:
            table[sid] = light_map.offset[name] + 1
            names.append((name, shape))
    names.sort(key=lambda item: light_map.offset[item[0]])
    out = (mitsuba().UInt32(table), names)
    object.__setattr__(dscene, "_id_table", (light_map, *out))
    return out


_GEOMETRY_CACHE: dict = {}


def _vertices_faces(shape):
    """(V (n, 3), F (T, 3)) of a Mitsuba mesh (cached per shape object)."""
    from vdo.core.backend import mitsuba

    key = id(shape)
    hit = _GEOMETRY_CACHE.get(key)
    if hit is not None and hit[0] is shape:
        return hit[1], hit[2]
    V = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    F = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
    _GEOMETRY_CACHE[key] = (shape, V, F)
    return V, F


def dscene_slots(dscene) -> dict:
    """Registry id (the UInt32 of a ShapePtr) -> (Mitsuba shape id, the shape) of `dscene.scene`."""
    slots = getattr(dscene, "_slots", None)
    if slots is not None:
        return slots
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    slots = {int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]): (s.id(), s) for s in dscene.scene.shapes()}
    object.__setattr__(dscene, "_slots", slots)
    return slots


def _diffuse(shape) -> bool:
    from vdo.core.backend import mitsuba

    mi = mitsuba()
    flags = shape.bsdf().flags()
    return (shape.is_mesh() and hasattr(shape, "faces_buffer") and not shape.is_emitter()
            and not mi.has_flag(flags, mi.BSDFFlags.Glossy)
            and not mi.has_flag(flags, mi.BSDFFlags.Delta)
            and not mi.has_flag(flags, mi.BSDFFlags.Transmission))


def divisions(V: np.ndarray, F: np.ndarray, cameras, stride: float = MAP_STRIDE,
              max_divisions: int = MAP_MAX_DIVISIONS) -> np.ndarray:
    """(T,) the divisions n_t of each triangle's sides, so that a sub-triangle covers about half
    a `stride` x `stride` pixel square where the camera that sees it largest sees it largest:
    n_t = L f / (stride z) for its longest side L at the depth z of its nearest vertex (at least
    NEAR_DEPTH_M; f the focal length in px), the frontal scale there, but at most
    PERSPECTIVE_FACTOR sqrt(2 A) / stride for A its pinhole projection's area (px²) (a triangle
    that recedes far is not resolved at its near end's scale everywhere: `lookup` leaves a
    sub-triangle larger than MAP_MAX_PX in the image to the camera's own light map), in the cameras
    whose image its projection overlaps; at least 1, at most `max_divisions`; 0 where no camera
    sees it."""
    tri = V[F]                                                   # (T, 3, 3)
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    n = np.zeros(len(F))
    seen_any = np.zeros(len(F), dtype=bool)
    for cam in cameras:
        Xc = (tri - np.asarray(cam.position, float)) @ cam.R.T  # (T, 3, 3) camera frame
        z = Xc[..., 2]
        ahead = z > 1e-6
        K = cam.K
        safe = np.where(ahead, z, 1.0)
        u = K[0, 0] * Xc[..., 0] / safe + K[0, 2]
        v = K[1, 1] * Xc[..., 1] / safe + K[1, 2]
        big = 1e30
        umin, umax = np.where(ahead, u, big).min(1), np.where(ahead, u, -big).max(1)
        vmin, vmax = np.where(ahead, v, big).min(1), np.where(ahead, v, -big).max(1)
        whole = ahead.all(1)
        # a triangle that reaches behind the camera's plane may cover any part of the image
        seen = ahead.any(1) & (~whole | ((umax >= -0.5) & (umin <= cam.width - 0.5)
                                         & (vmax >= -0.5) & (vmin <= cam.height - 0.5)))
        area = 0.5 * np.abs((u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0]))
        near = np.maximum(np.where(ahead, z, np.inf).min(1), NEAR_DEPTH_M)
        at_near = longest * cam.focal_px / (stride * near)    # the finest: frontal at its nearest vertex
        here = np.where(whole, np.minimum(at_near, PERSPECTIVE_FACTOR * np.sqrt(2 * area) / stride), at_near)
        n = np.where(seen, np.maximum(n, here), n)
        seen_any |= seen
    return np.where(seen_any, np.clip(np.ceil(n), 1, max_divisions), 0).astype(np.int64)


def surface_light_map(dscene, cameras, stride: float = MAP_STRIDE) -> SurfaceLightMap:
    """An empty `SurfaceLightMap` of `dscene`'s diffuse meshes for a frame seen by `cameras`
    (their lattices from `divisions`; nodes computed when first needed)."""
    offset, ns, longest = {}, [], []
    total = 0
    for _, (name, shape) in sorted(dscene_slots(dscene).items(), key=lambda item: item[1][0]):
        if not _diffuse(shape):
            continue
        V, F = _vertices_faces(shape)
        offset[name] = total
        ns.append(divisions(V, F, cameras, stride))
        tri = V[F]
        longest.append(np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1))
        total += len(F)
    n = np.concatenate(ns) if ns else np.zeros(0, dtype=np.int64)
    longest = np.concatenate(longest) if longest else np.zeros(0)
    return SurfaceLightMap(offset, n, longest, np.full(len(n), -1, dtype=np.int64))
