"""The DIC render mode's light in surface space, computed once for a camera and kept for the load
steps it holds for (docs/render.md, "The surface light map"; `vdo.rendering.dic`).

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
map serves a load step's deformed mesh (the same faces), its nodes moved with the surface, when
no vertex moved by more than MAP_REUSE_M (`map_holds`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MAP_STRIDE", "MAP_TOLERANCE", "MAP_MAX_DIVISIONS", "MAP_REUSE_M", "SurfaceLightMap", "map_holds",
           "surface_light_map"]

MAP_STRIDE = 16              # px between neighbouring nodes of a triangle's lattice in the camera
                             # of the frame that sees the triangle largest (`divisions`)
MAP_TOLERANCE = 0.03         # a sub-triangle whose nodes' light differs by at most this fraction
                             # of the camera's light scale is interpolated (as the image-space
                             # map's coarsest cells, `vdo.rendering.dic.SHADE_TOLERANCE`)
PERSPECTIVE_FACTOR = 1.0     # `divisions`: at most this many times the divisions of the frontal
                             # scale at a block's nearest vertex
DEPTH_RATIO = 1.25           # `blocks_of`: a triangle's blocks span at most this depth ratio
MAX_BLOCKS = 16              # ... and are at most this many a side
MAP_MAX_PX = 2 * MAP_STRIDE  # a sub-triangle larger than half a square of this side in the camera's
                             # image (its area x cos θ x (f / distance)²) is not interpolated
MAP_MAX_DIVISIONS = 256      # at most this many divisions of a block's side (33k nodes; a coarser
                             # lattice than the rule asks is caught by MAP_MAX_PX)
STRADDLE_DIVISIONS = 32      # ... of one that reaches behind a camera's plane (seen, if at all, at
                             # the image's edge: MAP_MAX_PX leaves it to the camera when too coarse)
MAP_REUSE_M = 20e-6          # a load step whose vertices lie within this of the geometry a map was
                             # filled on reads that map (`map_holds`); farther, a map of its own
NEAR_DEPTH_M = 0.05          # a triangle closer to a camera than this is treated as at this depth


@dataclass
class SurfaceLightMap:
    """The light on lattices over the triangles of the diffuse shapes (module docstring). The
    shapes' triangles are numbered one after another (`offset` by Mitsuba shape id, `Shape.id()`).
    Triangle t is first cut into `nc[t]`² blocks (its barycentric lattice of nc divisions: a
    triangle that recedes from a camera has blocks of about one depth each), numbered from
    `block0[t]`: the lower blocks (i, j) (corners (i, j), (i + 1, j), (i, j + 1), i + j < nc) at
    i nc - i (i - 1) / 2 + j, then the upper ones (corners (i + 1, j + 1), (i, j + 1), (i + 1, j),
    i + j < nc - 1). Block b has `n[b]` divisions a side (0: not in the map) and its lattice's
    nodes are `values[base[b]:]`, node (i, j) at base + i (n + 1) - i (i - 1) / 2 + j (NaN: not
    computed yet; +inf: a node whose light could not be computed), allocated a block at a time,
    the first time a camera's hit lies in it."""

    offset: dict                       # Mitsuba shape id -> its first triangle's number
    nc: np.ndarray                     # (T,) int64 blocks a side of each triangle
    block0: np.ndarray                 # (T,) int64 its first block
    block_tri: np.ndarray              # (B,) int64 each block's triangle, its (i, j) and whether
    block_ij: np.ndarray               # (B, 2) int64   it is an upper block
    block_upper: np.ndarray            # (B,) bool
    n: np.ndarray                      # (B,) int64 divisions of the block's sides
    area: np.ndarray                   # (B,) the block's area (m², at rest)
    base: np.ndarray                   # (B,) int64, -1: not allocated
    values: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.float32))
    used: int = 0
    computed: int = 0                  # nodes whose light was computed
    alloc_blocks: list = field(default_factory=list)   # blocks in the order of allocation

    def _allocate(self, blocks: np.ndarray) -> None:
        blocks = np.unique(blocks[self.base[blocks] < 0])
        if len(blocks) == 0:
            return
        size = (self.n[blocks] + 1) * (self.n[blocks] + 2) // 2
        self.base[blocks] = self.used + np.concatenate([[0], np.cumsum(size)[:-1]])
        need = self.used + int(size.sum())
        if need > len(self.values):
            grown = np.full(max(need, 2 * len(self.values)), np.nan, dtype=np.float32)
            grown[:self.used] = self.values[:self.used]
            self.values = grown
        self.used = need
        self.alloc_blocks.append(blocks)

    def lookup(self, dscene, si, prim_uv, scale: float, focal_px: float, tolerance: float | None = None):
        """(light, ok) at the hits `si` (Mitsuba SurfaceInteraction, n lanes) with barycentric
        coordinates `prim_uv` (Mitsuba's Point2f: p = (1 - u - v) p0 + u p1 + v p2): the
        interpolated light of each hit's sub-triangle where ok (a diffuse shape in the map, its
        front side seen, the sub-triangle at most MAP_MAX_PX² / 2 px² in a camera of focal
        length `focal_px` (px) at the hit's distance and angle, its three nodes within `tolerance` (default
        MAP_TOLERANCE) x `scale` of one another), computing the nodes not computed yet; NaN where
        not ok. Numpy (n,) float32 and bool."""
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
        return (tri, mi.Float(prim_uv.x), mi.Float(prim_uv.y), mi.Float(si.t),
                mi.Float(mi.Frame3f.cos_theta(si.wi)))

    @staticmethod
    def _cell(mi, dr, x, y, n):
        """The sub-triangle of a lattice of n (Int32) divisions holding the point of lattice
        coordinates (x, y) = n (u, v): its lower-or-upper (i, j), whether upper and the point's
        coordinates (a, b) in it (p = (1 - a - b) c0 + a c1 + b c2; lower c0 = (i, j), c1 =
        (i + 1, j), c2 = (i, j + 1); upper c0 = (i + 1, j + 1), c1 = (i, j + 1), c2 = (i + 1, j))."""
        i = dr.clip(mi.Int32(dr.floor(x)), 0, n - 1)
        j = dr.clip(mi.Int32(dr.floor(y)), 0, n - 1 - i)
        fi, fj = x - mi.Float(i), y - mi.Float(j)
        upper = (fi + fj > 1) & (i + j <= n - 2)
        return i, j, upper, dr.select(upper, 1 - fi, fi), dr.select(upper, 1 - fj, fj)

    def _block(self, mi, dr, prepared, focal_px):
        """The block of each hit of `prepare`'s arrays (UInt32), its lattice's divisions (UInt32),
        the hit's coordinates in the block (bu, bv) and where the map serves it (a diffuse front
        face whose block has a lattice, the sub-triangle small enough in the camera of focal
        length `focal_px`: an opaque Float); lazy Dr.Jit arrays."""
        tri, pu, pv, distance, cos_view = prepared
        active = tri != 0xFFFFFFFF
        nc = mi.Int32(dr.gather(mi.UInt32, self._device("nc"), tri, active))
        i1, j1, up1, bu, bv = self._cell(mi, dr, pu * mi.Float(nc), pv * mi.Float(nc), nc)
        local = dr.select(up1, nc * (nc + 1) // 2 + i1 * (nc - 1) - i1 * (i1 - 1) // 2 + j1,
                          i1 * nc - i1 * (i1 - 1) // 2 + j1)
        block = dr.gather(mi.UInt32, self._device("block0"), tri, active) + mi.UInt32(local)
        n = dr.gather(mi.UInt32, self._device("n"), block, active)
        active &= n > 0
        # the sub-triangle's area in this camera's image (px²): world area x cos θ (f / distance)²
        area = dr.gather(mi.Float, self._device("area"), block, active) / dr.square(mi.Float(n))
        active &= 2 * area * cos_view * focal_px * focal_px <= MAP_MAX_PX * MAP_MAX_PX * distance * distance
        return block, n, bu, bv, active

    def _corners(self, mi, dr, block, n, bu, bv, active):
        """The keys of the three nodes of each hit's sub-triangle (UInt32) and their weights, from
        `_block`'s arrays (the block allocated)."""
        base = mi.Int32(dr.gather(mi.UInt32, self._device("base"), block, active))
        ni = mi.Int32(n)
        i, j, upper, a, b = self._cell(mi, dr, bu * mi.Float(n), bv * mi.Float(n), ni)
        one = mi.Int32(1)
        corners = [(dr.select(upper, i + one, i), dr.select(upper, j + one, j)),
                   (dr.select(upper, i, i + one), dr.select(upper, j + one, j)),
                   (dr.select(upper, i + one, i), dr.select(upper, j, j + one))]
        keys = [mi.UInt32(base + ci * (ni + 1) - ci * (ci - 1) // 2 + cj) for ci, cj in corners]
        return keys, [1 - a - b, a, b]

    @staticmethod
    def _interpolated(dr, v, weights, active, bound):
        """(light, ok): the nodes' interpolation where they agree within `bound`, NaN elsewhere."""
        lo = dr.minimum(dr.minimum(v[0], v[1]), v[2])
        hi = dr.maximum(dr.maximum(v[0], v[1]), v[2])
        ok = active & (hi - lo <= bound)                      # False for NaN and inf
        return dr.select(ok, weights[0] * v[0] + weights[1] * v[1] + weights[2] * v[2], dr.nan), ok

    def filled(self, dscene, prepared, scale: float, focal_px: float):
        """(light, missing): `finish`'s light as lazy Dr.Jit arrays, to be evaluated with the hits,
        and where it cannot be read yet (a block without its lattice, a node not computed): where
        no hit misses one, `finish` would give the same light without computing anything (a
        camera's second render of a map already filled)."""
        import drjit as dr

        from vdo.core.backend import mitsuba

        mi = mitsuba()
        focal_px, bound = dr.opaque(mi.Float, focal_px), dr.opaque(mi.Float, MAP_TOLERANCE * scale)
        block, n, bu, bv, active = self._block(mi, dr, prepared, focal_px)
        allocated = dr.gather(mi.Bool, self._device("allocated"), block, active)
        keys, weights = self._corners(mi, dr, block, n, bu, bv, active & allocated)
        values = self._device("values")
        v = [dr.gather(mi.Float, values, key, active & allocated) for key in keys]
        missing = active & (~allocated | dr.isnan(v[0]) | dr.isnan(v[1]) | dr.isnan(v[2]))
        return self._interpolated(dr, v, weights, active & allocated, bound)[0], missing

    def finish(self, dscene, prepared, scale: float, focal_px: float, tolerance: float | None = None):
        """`lookup` from `prepare`'s arrays."""
        import drjit as dr

        from vdo.core.backend import mitsuba

        mi = mitsuba()
        _, names = _id_table(dscene, self)
        tolerance = MAP_TOLERANCE if tolerance is None else tolerance
        # the camera's numbers as opaque values: one compiled kernel for every camera
        focal_px, bound = dr.opaque(mi.Float, focal_px), dr.opaque(mi.Float, tolerance * scale)
        block, n, bu, bv, active = self._block(mi, dr, prepared, focal_px)
        hit = dr.zeros(mi.UInt32, max(len(self.n), 1))
        dr.scatter(hit, 1, block, active)
        fresh = np.flatnonzero(np.array(hit))
        if len(fresh) and (self.base[fresh] < 0).any():
            self._allocate(fresh)
        keys, weights = self._corners(mi, dr, block, n, bu, bv, active)
        values = self._device("values")
        v = [dr.gather(mi.Float, values, key, active) for key in keys]
        missing = active & (dr.isnan(v[0]) | dr.isnan(v[1]) | dr.isnan(v[2]))
        dr.eval(keys, v, weights, missing, active)
        if dr.any(missing)[0]:       # the nodes to compute: flagged by the hits that miss one
            wanted = dr.zeros(mi.UInt32, max(self.used, 1))
            for key in keys:
                dr.scatter(wanted, 1, key, missing)
            todo = np.flatnonzero((np.array(wanted)[:self.used] > 0) & np.isnan(self.values[:self.used]))
            self._compute(dscene, names, todo)
            values = self._device("values")
            v = [dr.gather(mi.Float, values, key, active) for key in keys]
        light, ok = self._interpolated(dr, v, weights, active, bound)
        dr.eval(light, ok)
        return np.array(light), np.array(ok)

    def _device(self, what: str):
        """The Dr.Jit copy of an array of the map (made again when the map changed)."""
        from vdo.core.backend import mitsuba

        mi = mitsuba()
        cache = self.__dict__.setdefault("_copies", {})
        stamp = (self.used, self.computed)
        if what in cache and cache[what][0] == stamp:
            return cache[what][1]
        if what == "values":
            out = mi.Float(self.values[:self.used] if self.used else np.full(1, np.nan, dtype=np.float32))
        elif what == "allocated":
            out = mi.Bool(np.append(self.base >= 0, False))
        elif what == "area":
            out = mi.Float(self.area.astype(np.float32))
        else:
            out = mi.UInt32(np.maximum(getattr(self, what), 0).astype(np.uint32))
        cache[what] = (stamp, out)
        return out

    def _nodes(self, keys: np.ndarray):
        """(triangle, u, v) of the nodes `keys`: the triangle's barycentric coordinates."""
        blocks = np.concatenate(self.alloc_blocks)
        blocks = blocks[np.argsort(self.base[blocks])]
        blk = blocks[np.searchsorted(self.base[blocks], keys, side="right") - 1]
        n, k = self.n[blk], keys - self.base[blk]
        c = 2 * n + 3
        i = np.floor((c - np.sqrt(np.maximum(c * c - 8.0 * k, 0.0))) / 2).astype(np.int64)
        for _ in range(2):    # rounding: offset(i) <= k < offset(i + 1), offset(i) = (i c - i²) / 2
            i = np.where(i * c - i * i > 2 * k, i - 1, i)
            i = np.where((i + 1) * c - (i + 1) * (i + 1) <= 2 * k, i + 1, i)
        j = k - (i * c - i * i) // 2
        a, b = i / n, j / n                                   # in the block
        tri = self.block_tri[blk]
        nc = self.nc[tri].astype(np.float64)
        bi, bj = self.block_ij[blk, 0], self.block_ij[blk, 1]
        up = self.block_upper[blk]
        u = np.where(up, bi + 1 - a, bi + a) / nc
        v = np.where(up, bj + 1 - b, bj + b) / nc
        return tri, u, v

    def _compute(self, dscene, names, keys: np.ndarray) -> None:
        """Shade the nodes `keys` on `dscene`'s shapes (their posed vertices)."""
        import drjit as dr

        from vdo.core.backend import mitsuba
        from vdo.rendering.shading import shade

        mi = mitsuba()
        tri, u, v = self._nodes(keys)
        starts = np.array([self.offset[name] for name, _ in names])
        owner = np.searchsorted(starts, tri, side="right") - 1
        prim = tri - starts[owner]
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
        pi.prim_uv = mi.Point2f(u.astype(np.float32), v.astype(np.float32))
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
GEOMETRY_CACHE_SHAPES = 256   # shapes whose vertices and faces are kept (`_vertices_faces`)


def _vertices_faces(shape):
    """(V (n, 3), F (T, 3)) of a Mitsuba mesh (cached per shape object)."""
    from vdo.core.backend import mitsuba

    key = id(shape)
    hit = _GEOMETRY_CACHE.get(key)
    if hit is not None and hit[0] is shape:
        return hit[1], hit[2]
    V = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    F = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
    if len(_GEOMETRY_CACHE) >= GEOMETRY_CACHE_SHAPES:   # a series' steps: older scenes' shapes go
        _GEOMETRY_CACHE.clear()
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


def _seen(tri: np.ndarray, cam):
    """(seen (T,), depths (T, 3), pixels (u, v) each (T, 3)) of the triangles `tri` (T, 3, 3) in
    the pinhole camera `cam`: seen where some corner lies in front of it and the projection's box
    overlaps the image (a triangle that reaches behind the camera's plane: wherever in front)."""
    Xc = (tri - np.asarray(cam.position, float)) @ cam.R.T      # (T, 3, 3) camera frame
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
    seen = ahead.any(1) & (~whole | ((umax >= -0.5) & (umin <= cam.width - 0.5)
                                     & (vmax >= -0.5) & (vmin <= cam.height - 0.5)))
    return seen, z, (u, v)


def _lattice_ij(nc: int):
    """(nc², 2) the (i, j) of a triangle's blocks in their order (lower, then upper) and (nc²,)
    whether each is upper."""
    lower = [(i, j) for i in range(nc) for j in range(nc - i)]
    upper = [(i, j) for i in range(nc - 1) for j in range(nc - 1 - i)]
    return np.array(lower + upper, dtype=np.int64).reshape(-1, 2), np.arange(nc * nc) >= len(lower)


def blocks_of(V: np.ndarray, F: np.ndarray, cameras):
    """(nc (T,), block corners (B, 3, 3) world, block's triangle (B,), (i, j) (B, 2), upper (B,)):
    each triangle cut into nc² blocks so that its depth varies by at most DEPTH_RATIO - 1 of the
    nearest depth over a block in every camera in front of which it lies (at most MAX_BLOCKS a
    side; a triangle that reaches behind a camera's plane: MAX_BLOCKS)."""
    tri = V[F]
    nc = np.ones(len(F), dtype=np.int64)
    for cam in cameras:
        seen, z, _ = _seen(tri, cam)
        zmin, zmax = z.min(1), z.max(1)
        want = np.where(zmin > NEAR_DEPTH_M, np.ceil((zmax - zmin) / ((DEPTH_RATIO - 1) * np.maximum(zmin, 1e-9))),
                        MAX_BLOCKS)
        nc = np.where(seen, np.maximum(nc, np.clip(want, 1, MAX_BLOCKS).astype(np.int64)), nc)
    corners, owner, ij, up = [], [], [], []
    for c in np.unique(nc):
        ts = np.flatnonzero(nc == c)
        bij, bup = _lattice_ij(int(c))
        # barycentric (u, v) of each block's three corners, in the order of `_cell`
        a0 = np.where(bup[:, None], bij + 1, bij)
        a1 = np.where(bup[:, None], bij + [0, 1], bij + [1, 0])
        a2 = np.where(bup[:, None], bij + [1, 0], bij + [0, 1])
        uv = np.stack([a0, a1, a2], axis=1) / c                        # (k, 3, 2)
        w = np.concatenate([1 - uv.sum(-1, keepdims=True), uv], axis=-1)  # (k, 3, 3) weights of p0 p1 p2
        corners.append(np.einsum("kcw,twx->tkcx", w, tri[ts]).reshape(-1, 3, 3))
        owner.append(np.repeat(ts, len(bij)))
        ij.append(np.tile(bij, (len(ts), 1)))
        up.append(np.tile(bup, len(ts)))
    order = np.argsort(np.concatenate(owner), kind="stable")
    return (nc, np.concatenate(corners)[order], np.concatenate(owner)[order],
            np.concatenate(ij)[order], np.concatenate(up)[order])


def divisions(V: np.ndarray, F: np.ndarray, cameras, stride: float = MAP_STRIDE,
              max_divisions: int = MAP_MAX_DIVISIONS) -> np.ndarray:
    """(T,) the divisions n_t of each triangle's (block's) sides, so that a sub-triangle covers
    about half a `stride` x `stride` pixel square in the camera that sees it largest: n_t =
    sqrt(2 A) / stride for A its pinhole projection's area (px²), at most PERSPECTIVE_FACTOR times
    L f / (stride z), its longest side L at the depth z of its nearest vertex (the frontal scale
    there); a triangle that reaches behind a camera's plane: L f / (stride z) for its nearest vertex
    in front (z at least NEAR_DEPTH_M), at most STRADDLE_DIVISIONS. Only the cameras whose image
    its projection overlaps count; at least 1, at most `max_divisions`; 0 where no camera sees it.
    (`lookup` leaves a sub-triangle larger than MAP_MAX_PX² / 2 in a camera's image to the camera.)"""
    tri = V[F]                                                   # (T, 3, 3)
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    n = np.zeros(len(F))
    seen_any = np.zeros(len(F), dtype=bool)
    for cam in cameras:
        seen, z, (u, v) = _seen(tri, cam)
        ahead = z > 1e-6
        whole = ahead.all(1)
        area = 0.5 * np.abs((u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0]))
        near = np.maximum(np.where(ahead, z, np.inf).min(1), NEAR_DEPTH_M)
        at_near = longest * cam.focal_px / (stride * near)    # the finest: frontal at its nearest vertex
        here = np.where(whole, np.minimum(PERSPECTIVE_FACTOR * at_near, np.sqrt(2 * area) / stride),
                        np.minimum(at_near, STRADDLE_DIVISIONS))
        n = np.where(seen, np.maximum(n, here), n)
        seen_any |= seen
    return np.where(seen_any, np.clip(np.ceil(n), 1, max_divisions), 0).astype(np.int64)


def surface_light_map(dscene, cameras, stride: float = MAP_STRIDE) -> SurfaceLightMap:
    """An empty `SurfaceLightMap` of `dscene`'s diffuse meshes for a frame seen by `cameras`
    (their blocks from `blocks_of`, the blocks' lattices from `divisions`; nodes computed when
    first needed)."""
    offset, parts = {}, []
    total = 0
    for _, (name, shape) in sorted(dscene_slots(dscene).items(), key=lambda item: item[1][0]):
        if not _diffuse(shape):
            continue
        V, F = _vertices_faces(shape)
        offset[name] = total
        nc, corners, owner, ij, up = blocks_of(V, F, cameras)
        flat = corners.reshape(-1, 3)
        n = divisions(flat, np.arange(len(flat)).reshape(-1, 3), cameras, stride)
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        parts.append((nc, owner + total, ij, up, n, area))
        total += len(F)
    if not parts:
        parts = [(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2), np.int64),
                  np.zeros(0, bool), np.zeros(0, np.int64), np.zeros(0))]
    nc, owner, ij, up, n, area = (np.concatenate(a) for a in zip(*parts))
    block0 = np.concatenate([[0], np.cumsum(nc * nc)[:-1]]).astype(np.int64)
    return SurfaceLightMap(offset, nc, block0, owner, ij, up, n, area, np.full(len(n), -1, dtype=np.int64))


def map_holds(meshes, posed, tolerance: float = MAP_REUSE_M) -> bool:
    """Whether a map filled on the scene of `meshes` serves the scene of `posed` (the same
    SceneMeshes at a load step): the same meshes, every vertex within `tolerance` (m). A rigid
    motion of a group by millimetres (the built-in's hexapod) moves the shadows over the surface
    and needs a map of its own; a specimen's micrometre deformation does not."""
    if len(meshes) != len(posed):
        return False
    for a, b in zip(meshes, posed):
        if a.name != b.name or a.vertices.shape != b.vertices.shape:
            return False
        if a.vertices is not b.vertices and np.abs(np.asarray(a.vertices) - b.vertices).max() > tolerance:
            return False
    return True
