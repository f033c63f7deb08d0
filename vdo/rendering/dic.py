"""The DIC render mode: one primary ray per pixel, the speckle averaged over the pixel's footprint
(docs/render.md, "The DIC render mode"; `vdo.render.render_images` with mode "dic")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vdo.model.camera import Camera
from vdo.model.speckle import pattern_for
from vdo.rendering.footprint import FOOTPRINT_SPLIT, SpeckleTable, part_means
from vdo.rendering.scene import (NEAR_CLIP_M, PRESAMPLE, SPECKLED_SUFFIX, build_render_scene, cell_blur,
                                 lens_sigma_px, part_blur)
from vdo.rendering.shading import shade


# --------------------------------------------------------------------------------------------
# The DIC render mode: one primary ray per pixel, the speckle averaged over the pixel's footprint
# --------------------------------------------------------------------------------------------
RENDER_MODES = ("sampled", "dic")
SHADE_STRIDE = 16            # px between the nodes of the coarsest level of the light map
SHADE_TOLERANCE = 0.03       # a light-map cell whose corner values differ by at most this fraction
                             # of the light scale (and that sees one shape) is interpolated
SHADE_ERROR = 0.002          # else its finer nodes are computed, and where they lie within this
                             # fraction of the light scale of its bilinear prediction its four
                             # halves are interpolated
CREASE_COS = float(np.cos(np.radians(1.0)))   # corners whose normals differ by more than 1°
                             # straddle a crease (a facet's edge): the cell is refined
SURFACE_FILL = 2             # at this level of the light map a cell that sees more than one surface
                             # (a silhouette or a crease passes) is not refined: each pixel takes
                             # its surface's corners' light (`_surface_fill`)
SURFACE_CORNERS = 3          # ... from at least this many of its surface's corners (not on one line)
SCALE_STRIDE = 64            # px between the nodes whose light sets the camera's light scale
SCALE_PERCENTILE = 90        # the light scale: this percentile of their light (the well-lit surfaces)
EDGE_SUPERSAMPLE = 4         # a pixel whose neighbours see another shape (a silhouette) is the
                             # mean of EDGE_SUPERSAMPLE^2 sub-pixel rays, each with its own footprint
TILE_PIXELS = 1 << 22        # pixels per tile of a DIC-mode render (fewer when memory is short)
MIN_TILE_PIXELS = 1 << 14    # below this a tile's fixed costs dominate: refuse instead
TILE_BYTES_PER_PIXEL = 320   # peak working set of a DIC tile per pixel: 280 measured on the
                             # built-in's cam1 at full size (ru_maxrss with 2^23- against
                             # 2^22-pixel tiles), plus a margin
SAMPLED_BYTES_PER_PIXEL = 80 * PRESAMPLE ** 2   # Mitsuba's film and wavefront per pixel, any
                             # spp (59 measured at 16 and 64 spp on 614k px, plus a margin), the
                             # film holding PRESAMPLE^2 cells a pixel (the lens's blur)
CELL_BYTES_PER_PIXEL = 16    # a DIC render's cell rows (PRESAMPLE float32 a pixel) and their blur
DISTORTION_BYTES_PER_PIXEL = 48   # the resampling map (H, W, 2) float64 and its spline copies
IMAGE_BYTES_PER_PIXEL = 6    # what render_images keeps per pixel and camera: float32 + 16-bit DN


@dataclass(frozen=True, eq=False)
class DicScene:
    """What the DIC render mode needs of an experiment: the render scene with white regions
    (`build_render_scene(white_regions=True)`) in Embree's robust (watertight) mode for the
    primary rays, and the same scene in its fast mode for the shadow rays (`shadows`); the
    registry ids of the speckled shapes (of `scene`), the speckle's summed-area table and tile
    size, the paint's albedos and the lights.

    Why two modes: in the fast mode a ray of the pixel lattice through an edge two triangles
    share can miss both and hit the far wall from inside (a camera level with a pipe's vertex
    row: half its middle row black, tests/test_render_dic.py); the robust mode for the shadow
    rays too cost them 30 % of CPU (200 k light nodes of cam1, 3.25 -> 4.23 s), and a shadow ray
    through an edge is one quadrature point, not a line of pixels."""

    scene: object
    shadows: object
    speckled_ids: tuple[int, ...]
    table: SpeckleTable
    tile: tuple[int, int]          # (W_t, H_t) texels of the pattern tile
    black: float
    white: float
    lights: tuple                  # per light (centre, e_u w, e_v h, normal, radiance)
    ambient: float
    light_map: object = None       # a `vdo.rendering.lightmap.SurfaceLightMap` shared by the
                                   # frame's cameras (`render_camera_dic`'s light_map), or None


def build_dic_scene(exp, meshes, region_faces, bodies=(), pattern=None, posed=None) -> DicScene:
    """The `DicScene` of `exp` (arguments as `build_render_scene`)."""
    import drjit as dr

    from vdo.core.backend import mitsuba
    from vdo.physics.lighting import panel_frame

    mi = mitsuba()
    sp = exp.speckle
    pattern = pattern_for(sp) if pattern is None else np.asarray(pattern, dtype=np.float32)
    scene = build_render_scene(exp, meshes, region_faces, bodies, pattern, posed, white_regions=True,
                               robust=True)
    shadows = build_render_scene(exp, meshes, region_faces, bodies, pattern, posed, white_regions=True)
    ids = tuple(int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in scene.shapes()
                if s.id().endswith(SPECKLED_SUFFIX))
    lights = []
    for light in exp.lights:
        n, e1, e2 = panel_frame(light)
        w, h = light.size
        lights.append((np.asarray(light.position, float), e1 * w, e2 * h, n, float(light.radiance)))
    return DicScene(scene, shadows, ids, SpeckleTable.of(pattern), (pattern.shape[1], pattern.shape[0]),
                    float(sp.black_albedo), float(sp.white_albedo), tuple(lights),
                    float(exp.render.ambient_radiance))


def available_memory() -> int:
    """Bytes this process may still allocate: MemAvailable of /proc/meminfo (Linux), else the
    physical memory (os.sysconf)."""
    import os

    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


@dataclass(frozen=True)
class RenderPlan:
    """The memory a render needs (`plan_render`): `tile_pixels` per DIC tile, `kept` bytes of
    the finished images, `working` bytes of the largest camera's render, `available` bytes."""

    mode: str
    tile_pixels: int
    kept: int
    working: int
    available: int

    @property
    def needed(self) -> int:
        return self.kept + self.working


def plan_render(cameras, mode: str, available: int | None = None) -> RenderPlan:
    """The memory of rendering `cameras` (already scaled) in `mode`, before anything is rendered:
    every finished image is kept (IMAGE_BYTES_PER_PIXEL per pixel); one camera renders at a time,
    the sampled mode with its whole film (SAMPLED_BYTES_PER_PIXEL, plus
    DISTORTION_BYTES_PER_PIXEL for a distorted camera), the DIC mode in tiles of TILE_PIXELS
    (TILE_BYTES_PER_PIXEL each) and its cell rows (CELL_BYTES_PER_PIXEL a pixel of the camera),
    split into smaller tiles (down to MIN_TILE_PIXELS) when that does not fit in `available` bytes
    (default `available_memory`). Raises MemoryError with the
    bytes it would need when even that does not fit."""
    available = available_memory() if available is None else int(available)
    kept = sum(c.width * c.height for c in cameras) * IMAGE_BYTES_PER_PIXEL
    tile = TILE_PIXELS
    if mode == "dic":
        cells = max((c.width * c.height for c in cameras), default=0) * CELL_BYTES_PER_PIXEL
        room = available - kept - cells
        while tile > MIN_TILE_PIXELS and tile * TILE_BYTES_PER_PIXEL > room:
            tile //= 2
        working = tile * TILE_BYTES_PER_PIXEL + cells
    else:
        working = max((c.width * c.height * (SAMPLED_BYTES_PER_PIXEL
                                             + (DISTORTION_BYTES_PER_PIXEL if c.distorted else 0))
                       for c in cameras), default=0)
    plan = RenderPlan(mode, tile, kept, working, available)
    if plan.needed > available:
        raise MemoryError(f"the render needs {plan.needed / 2 ** 30:.2f} GiB ({kept / 2 ** 30:.2f} GiB "
                          f"of images, {working / 2 ** 30:.2f} GiB to render one camera); "
                          f"{available / 2 ** 30:.2f} GiB available")
    return plan


def render_camera_dic(dscene: DicScene, camera: Camera, progress=None,
                      tile_pixels: int = TILE_PIXELS, spec=None, light_map=None) -> np.ndarray:
    """One camera's (H, W) float32 linear image in the DIC render mode, in tiles of at most
    `tile_pixels` pixels (whole rows; `plan_render` chooses). Per pixel (u, v) of the (distorted) image:

    * one primary ray through the pinhole pixel p = `Camera.undistorted_pixels`(u, v), with ray
      differentials through p + ∂p/∂u and p + ∂p/∂v (central differences over ±½ px): Mitsuba's
      `compute_uv_partials` gives the footprint's sides a = ∂(x, y)/∂u, b = ∂(x, y)/∂v in texels;
    * on a speckled region, the albedo ρ = ρ_b + (ρ_w - ρ_b) f̄ with f̄ the mean of the bilinear
      texture over the footprint parallelogram c + [-½, ½] a + [-½, ½] b, cut into
      FOOTPRINT_SPLIT^2 parts, each replaced by the axis-aligned box of the same second moments
      (half-widths ½ |(a_x, b_x)| / n and ½ |(a_y, b_y)| / n), averaged exactly (`vdo.rendering.footprint.part_means`:
      from the few texels a small box reads, else the `SpeckleTable`; exact for a footprint
      aligned with the texture axes);
    * the light reaching the hit (`vdo.rendering.shading.shade`: each panel probed by shadow
      rays at some of its points, a lit panel by a Gauss rule, a partly shadowed one by midpoints
      with shadow rays where the probes disagree, the ambient sky by BSDF-sampled directions)
      from an adaptive light map per tile (`_light_map`: nodes every SHADE_STRIDE pixels,
      refined a level at a time where the bilinear prediction misses, a crease or another shape
      passes, silhouettes and creases filled from their own surface at SURFACE_FILL px;
      tolerances in units of the camera's light scale, `_light_scale`);
    * value = emitted radiance seen + ρ × light (white regions: the BSDF's own albedo elsewhere);
      a silhouette pixel (a 4-neighbour sees another shape) is the mean of EDGE_SUPERSAMPLE^2
      sub-pixel values (`_supersampled`).

    With the camera's `spec` (a CameraSpec), the lens's in-focus diffraction
    (`vdo.rendering.scene.lens_sigma_px`: the f/8 that σ_measured assumes for a camera without
    f_number; a camera with one is refused in this mode) acts before the pixels integrate, as in a
    camera: each pixel's value is kept on its FOOTPRINT_SPLIT^2 cells (the speckle's albedo of
    each part of the footprint, the pixel's light and emission; a silhouette pixel's mean on all),
    the cells blurred and each pixel their mean (along the rows in each tile,
    `vdo.rendering.scene.part_blur`, and across them once the tiles are done, `cell_blur`).
    `light_map`: the frame's `vdo.rendering.lightmap.SurfaceLightMap` (`surface_light_map` of
    the frame's cameras, this one among them), from which the light map's nodes take the light
    where its lattice's nodes agree (the nodes it lacks are computed into it); None: a map of this
    camera alone; False: every node computed (no surface map).
    `progress`: called with the number of rows done after each tile."""
    from dataclasses import replace

    from vdo.rendering.lightmap import surface_light_map

    if light_map is None:
        light_map = surface_light_map(dscene, [camera])
    dscene = replace(dscene, light_map=light_map or None)
    s = SHADE_STRIDE
    rows = max(1, tile_pixels // camera.width)
    rows = rows // s * s if rows >= s else rows           # tiles share the light map's lattice
    sigma, n = lens_sigma_px(camera, spec), FOOTPRINT_SPLIT
    out = np.empty(((n if sigma > 0 else 1) * camera.height, camera.width), dtype=np.float32)
    scale = _light_scale(dscene, camera)
    k = n if sigma > 0 else 1
    for r0 in range(0, camera.height, rows):
        r1 = min(camera.height, r0 + rows)
        hits = _tile_hits(dscene, camera, r0, r1, scale, cells=sigma > 0)
        out[k * r0:k * r1] = _tile_image(dscene, camera, hits, scale, sigma)
        if progress is not None:
            progress(r1 - r0)
    return cell_blur(out, sigma, n, axis=0) if sigma > 0 else out


def _pixel_grid(u, v) -> np.ndarray:
    return np.stack(np.broadcast_arrays(u[None, :], v[:, None]), axis=-1).reshape(-1, 2)


def _rays(camera: Camera, grid, step: float = 1.0, differentials: bool = True):
    """Mitsuba ray differentials for the (distorted) pixels `grid` ((n, 2) array, or a pair of
    Dr.Jit Floats (u, v)): from the near-clip plane through the pinhole pixel p =
    `Camera.undistorted_pixels`(u, v) and, as differentials, through p + ∂p/∂u and p + ∂p/∂v
    for a step of `step` pixels (central differences over ±step/2 for a distorted camera);
    without `differentials`, the rays alone."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    # The camera's numbers enter the kernels as values read from one array (not literals), so that
    # every camera and tile runs the same compiled kernels: the world direction of a homogeneous
    # pixel M = R^T K^-1, then the centre.
    numbers = mi.Float(np.concatenate([(camera.R.T @ np.linalg.inv(camera.K)).ravel(),
                                       camera.position]).astype(np.float32))
    number = [dr.gather(mi.Float, numbers, mi.UInt32(k)) for k in range(12)]
    M = [number[3 * k:3 * k + 3] for k in range(3)]

    def direction(x, y):
        return mi.Vector3f(*(M[k][0] * x + M[k][1] * y + M[k][2] for k in range(3)))

    if camera.distorted and not differentials:
        p = camera.undistorted_pixels(grid)
        px, py = (mi.Float(np.ascontiguousarray(p[:, k], dtype=np.float32)) for k in range(2))
    elif camera.distorted:
        at = camera.undistorted_pixels
        du, dv = np.array([step / 2, 0.0]), np.array([0.0, step / 2])
        p, pu, pv = at(grid), at(grid + du) - at(grid - du), at(grid + dv) - at(grid - dv)
        px, py, pux, puy, pvx, pvy = (mi.Float(np.ascontiguousarray(a[:, k], dtype=np.float32))
                                      for a in (p, pu, pv) for k in range(2))
    else:
        if isinstance(grid, np.ndarray):
            px, py = (mi.Float(np.ascontiguousarray(grid[:, k], dtype=np.float32)) for k in range(2))
        else:
            px, py = grid
        pux, puy, pvx, pvy = step, 0.0, 0.0, step
    # Each ray starts on the near-clip plane (the camera frame's z = NEAR_CLIP_M, as Mitsuba's
    # perspective sensor), so that a camera's own body around its centre is not hit.
    o = mi.Point3f(*number[9:])
    if not differentials:
        d = direction(px, py)
        return mi.Ray3f(o + NEAR_CLIP_M * d, dr.normalize(d))
    d, d_x, d_y = direction(px, py), direction(px + pux, py + puy), direction(px + pvx, py + pvy)
    ray = mi.RayDifferential3f(o + NEAR_CLIP_M * d, dr.normalize(d))
    ray.o_x, ray.o_y = o + NEAR_CLIP_M * d_x, o + NEAR_CLIP_M * d_y
    ray.d_x, ray.d_y = d_x, d_y
    ray.has_differentials = True
    return ray


def _footprint_albedo(dscene: DicScene, si, cells: bool = False):
    """ρ at each hit (Dr.Jit Float): the footprint-averaged speckle albedo on the speckled
    shapes (`render_camera_dic`), 1 elsewhere; with `cells`, the list of the FOOTPRINT_SPLIT^2
    parts' own, part (i, j) (i along ∂/∂u, j along ∂/∂v) at i FOOTPRINT_SPLIT + j.

    Evaluates the hits' texture coordinates, their partials and the parts' means, with whatever
    the caller has scheduled (`dr.schedule`) in the same kernel."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    wt, ht = dscene.tile
    shape = _shape_ids(si)
    speckled = mi.Bool(False)
    for sid in dscene.speckled_ids:
        speckled |= shape == sid
    speckled &= si.is_valid()
    means = part_means(dscene.table, mi.Float64(si.uv.x) * wt, mi.Float64(si.uv.y) * ht,
                        *(c * s for c, s in ((si.duv_dx.x, wt), (si.duv_dx.y, ht),
                                             (si.duv_dy.x, wt), (si.duv_dy.y, ht))), active=speckled)

    black, white = (dr.opaque(mi.Float, v) for v in (dscene.black, dscene.white))

    def albedo(f):
        return dr.select(speckled, black + (white - black) * f, 1.0)
    n = FOOTPRINT_SPLIT
    return [albedo(f) for f in means] if cells else albedo(sum(means[1:], means[0]) / (n * n))


def _shape_ids(si):
    """The registry id of the shape each hit sees (Dr.Jit UInt32; 0 for a miss)."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    return dr.reinterpret_array(mitsuba().UInt32, si.shape)


def _cast(dscene: DicScene, camera: Camera, grid, step: float = 1.0, barycentric: bool = False,
          partials: bool = True):
    """Primary hits (with uv partials over a footprint of `step` pixels; without `partials`, to be
    shaded only: fewer values to trace) of the pixels `grid` (`_rays`), traced in Embree's coherent
    mode: neighbouring lanes are neighbouring pixels. On cam1 of the built-in the traversal took
    0.3 s instead of 1.3 s for 24 M rays, with the same hits except where two surfaces tie on a
    shared edge (the other one taken at ~600 pixels)."""
    from vdo.core.backend import mitsuba

    mi = mitsuba()
    ray = _rays(camera, grid, step, differentials=partials)
    if barycentric:          # and the hits' barycentric coordinates (Mitsuba's prim_uv)
        pi = dscene.scene.ray_intersect_preliminary(ray, True)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All)
        if partials:
            si.compute_uv_partials(ray)
        return si, pi.prim_uv
    si = dscene.scene.ray_intersect(ray, mi.RayFlags.All, True)
    if partials:
        si.compute_uv_partials(ray)
    return si


def _shaded(dscene: DicScene, camera: Camera, grid):
    """(`shade` at the primary hits of the pixels `grid`, the hits): cast without ray
    differentials or uv partials, which the shading does not read."""
    si = _cast(dscene, camera, grid, partials=False)
    return shade(dscene, si), si


def _light_scale(dscene: DicScene, camera: Camera) -> float:
    """The camera's light scale: the SCALE_PERCENTILE-th percentile of the light (`shade`) at
    the pixels every SCALE_STRIDE px; the light map's tolerances are fractions of it."""
    xs = np.arange(SCALE_STRIDE // 2, camera.width, SCALE_STRIDE, dtype=float)
    ys = np.arange(SCALE_STRIDE // 2, camera.height, SCALE_STRIDE, dtype=float)
    light, _ = _shaded(dscene, camera, _pixel_grid(xs if len(xs) else np.zeros(1), ys if len(ys) else np.zeros(1)))
    lit = light[light > 0]
    return float(np.percentile(lit, SCALE_PERCENTILE)) if len(lit) else 1.0


@dataclass(frozen=True, eq=False)
class _TileHits:
    """What a tile's primary rays give (`_tile_hits`), numpy arrays over its h x W pixels (views
    of Dr.Jit's arrays where they can be: a view keeps its array)."""

    r0: int                     # its first row
    nodes: "_LightNodes"        # its light map's lattice: the pixels' shape ids and shading
                                # normals, and their light where known (the surface light map)
    emitted: np.ndarray         # (h W,) float32 the radiance emitted towards the camera
    rho: list                   # per footprint part (or one: the whole footprint) (h W,) float32


def _tile_hits(dscene: DicScene, camera: Camera, r0: int, r1: int, scale: float,
               cells: bool) -> _TileHits:
    """The primary rays of rows r0 .. r1 - 1 (one Dr.Jit kernel: the hits, their albedo, with
    `cells` per footprint part, and what the surface light map needs), and the map's light."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    W, h = camera.width, r1 - r0
    u, v = np.arange(W, dtype=float), np.arange(r0, r1, dtype=float)
    index = dr.arange(mi.UInt32, W * h)
    width = dr.opaque(mi.UInt32, W)
    pixel = (mi.Float(index % width), mi.Float(index // width + dr.opaque(mi.UInt32, r0)))
    grid = _pixel_grid(u, v) if camera.distorted else pixel
    mapped = dscene.light_map is not None
    si, prim_uv = _cast(dscene, camera, grid, barycentric=True) if mapped else (_cast(dscene, camera, grid), None)
    emitted = mi.luminance(si.emitter(dscene.scene).eval(si))
    ids = _shape_ids(si)
    prepared = dscene.light_map.prepare(dscene, si, prim_uv) if mapped else ()
    # the map's light read in the same kernel where it can be (every node it needs computed)
    filled = dscene.light_map.filled(dscene, prepared, scale, camera.focal_px) if mapped else ()
    dr.schedule(emitted, ids, si.sh_frame.n, *prepared, *filled)   # one kernel with the albedo's
    rho = _footprint_albedo(dscene, si, cells=cells)
    rho = rho if cells else [rho]
    dr.eval(*rho)
    nodes = _LightNodes.lattice(np.asarray(ids).reshape(h, W),
                                (np.asarray(si.sh_frame.n[k]).reshape(h, W) for k in range(3)))
    tile = nodes.I[:h, :W]
    del si, prim_uv
    if mapped:         # the frame's surface light map where its nodes agree (NaN elsewhere)
        light, missing = filled
        if dr.any(missing)[0]:                    # nodes to compute first: the map's own lookup
            light = dscene.light_map.finish(dscene, prepared, scale, camera.focal_px)[0]
        nodes.L[:h, :W] = np.asarray(light).reshape(h, W)
    nodes.L[:h, :W][tile == 0] = 0.0                   # a pixel that sees nothing has no light
    return _TileHits(r0, nodes, np.asarray(emitted), [np.asarray(part) for part in rho])


def _tile_image(dscene: DicScene, camera: Camera, hits: _TileHits, scale: float,
                sigma: float = 0.0) -> np.ndarray:
    """The tile's rows of `render_camera_dic`'s image from its `hits`, (h, W) float32; with a
    lens blur `sigma` (px) > 0, their FOOTPRINT_SPLIT rows of cells each, blurred along the rows
    and each pixel the mean of its cells along them (`part_blur`): (FOOTPRINT_SPLIT h, W)."""
    h, W = hits.nodes.tile
    ids = hits.nodes.I[:h, :W]
    light = _light_map(dscene, camera, hits.r0, hits.nodes, scale).ravel()
    edges = np.flatnonzero(_silhouette(ids))
    edge_value = (_supersampled(dscene, camera, hits.r0, edges, ids, light.reshape(h, W))
                  if len(edges) else None)
    light, emitted = light.reshape(h, W), hits.emitted.reshape(h, W)
    rho = [part.reshape(h, W) for part in hits.rho]         # part i n + j: cell i along the row

    def value(k: int, rows: slice) -> np.ndarray:
        """Part k's value on `rows`: emitted + ρ L, a silhouette pixel's own mean on all parts."""
        out = np.multiply(rho[k][rows], light[rows])
        out += emitted[rows]
        if edge_value is not None:
            at = slice(*np.searchsorted(edges, (rows.start * W, rows.stop * W)))
            out.ravel()[edges[at] - rows.start * W] = edge_value[at]
        return out
    return part_blur(value, (h, W), sigma, FOOTPRINT_SPLIT) if sigma > 0 else value(0, slice(0, h))


def _light_map(dscene: DicScene, camera: Camera, r0: int, nodes: "_LightNodes",
               scale: float) -> np.ndarray:
    """(h, W) the light (`shade`) at each pixel of the tile whose rows start at r0 and whose
    pixels' shape ids, normals and light where already known are `nodes` (`_tile_hits`),
    from an adaptive light map (tolerances in units of the camera's light `scale`). Level s has
    nodes every s pixels (s = SHADE_STRIDE, SHADE_STRIDE / 2, ..., 1; the lattice may reach past
    the last row and column). A cell of level s whose pixels and corners see one shape, with the
    corners' normals within CREASE_COS of one another (no crease), is interpolated bilinearly
    from its corners when they differ by at most SHADE_TOLERANCE; otherwise the five nodes of
    level s / 2 in it are computed, and when they lie within SHADE_ERROR of the cell's bilinear
    prediction (on the same surface) its four halves are interpolated from their corners; the
    rest (shadow edges, creases, another shape) go down a level, to the pixels themselves at
    s = 1; but at s = SURFACE_FILL a cell that sees more than one surface takes `_surface_fill`
    (a silhouette's or a crease's pixels from their own surface's corners). Nodes and cells are
    held by their pixel (row y, column x) on one lattice for all levels.

    The light already known at some pixels (the frame's surface light map; 0 where the pixel
    sees nothing): those pixels keep it, a coarsest cell whose pixels all have it is done, and a
    node at such a pixel takes it."""
    h, W = nodes.tile
    ids = nodes.I[:h, :W]
    s = SHADE_STRIDE
    ncy, ncx = -(-h // s), -(-W // s)          # cells of s x s pixels covering the tile
    # The least and greatest shape id in each cell of each level (a min/max pyramid).
    lo_ids = {1: np.pad(ids, ((0, ncy * s - h), (0, ncx * s - W)), mode="edge")}
    hi_ids = {1: lo_ids[1]}
    k = 1
    while k < s:
        for pyr, op in ((lo_ids, np.minimum), (hi_ids, np.maximum)):
            q = pyr[k]
            pyr[2 * k] = op(op(q[::2, ::2], q[1::2, ::2]), op(q[::2, 1::2], q[1::2, 1::2]))
        k *= 2
    out = np.empty((ncy * s, ncx * s), dtype=np.float32)
    known = np.isfinite(nodes.L[:h, :W])        # (the nodes computed below were not known)
    done = np.pad(known, ((0, ncy * s - h), (0, ncx * s - W))).reshape(ncy, s, ncx, s).all(axis=(1, 3))
    y, x = (a.ravel() * s for a in np.nonzero(~done))
    corners = np.unique(np.concatenate([(y + dy) * nodes.L.shape[1] + x + dx
                                        for dy in (0, s) for dx in (0, s)]))
    nodes.compute(dscene, camera, r0, *np.divmod(corners, nodes.L.shape[1]), scale)

    def finish():
        return np.where(known, nodes.L[:h, :W], out[:h, :W])
    while True:
        if s == 1:                                   # the nodes are the pixels themselves
            out[y, x] = nodes.L[y, x]
            return finish()
        corners = [(y, x), (y, x + s), (y + s, x), (y + s, x + s)]
        c00, c01, c10, c11 = (nodes.L[c] for c in corners)
        lo_id = lo_ids[s][y // s, x // s]
        one = (lo_id == hi_ids[s][y // s, x // s]) & nodes.same(corners, lo_id, corners[0])
        lo = np.minimum(np.minimum(c00, c01), np.minimum(c10, c11))
        hi = np.maximum(np.maximum(c00, c01), np.maximum(c10, c11))
        smooth = one & (hi - lo <= SHADE_TOLERANCE * scale)
        _fill(out, y[smooth], x[smooth], s, c00[smooth], c01[smooth], c10[smooth], c11[smooth])
        rest = ~smooth
        if s == SURFACE_FILL:                        # silhouettes and creases: no further
            edge = rest & ~one
            _surface_fill(dscene, camera, r0, out, nodes, y[edge], x[edge], s, lo_ids[1], scale)
            rest &= one
        y, x, one, c00, c01, c10, c11, lo_id = (a[rest] for a in (y, x, one, c00, c01, c10, c11, lo_id))
        if len(y) == 0:
            return finish()
        # The next level: the five new nodes of each remaining cell are computed.
        m = s // 2
        new = [(y + m, x + m), (y, x + m), (y + s, x + m), (y + m, x), (y + m, x + s)]
        fresh = np.unique(np.concatenate([j * nodes.L.shape[1] + i for j, i in new]))
        nodes.compute(dscene, camera, r0, *np.divmod(fresh, nodes.L.shape[1]), scale)
        predicted = [(c00 + c01 + c10 + c11) / 4, (c00 + c01) / 2, (c10 + c11) / 2,
                     (c00 + c10) / 2, (c01 + c11) / 2]
        err = np.max([np.abs(nodes.L[n] - p) for n, p in zip(new, predicted)], axis=0)
        fine = one & (err <= SHADE_ERROR * scale) & nodes.same(new, lo_id, (y, x))
        children = [(y + dy, x + dx) for dy in (0, m) for dx in (0, m)]
        for j, i in children:
            jf, i_f = j[fine], i[fine]
            _fill(out, jf, i_f, m, *(nodes.L[c] for c in ((jf, i_f), (jf, i_f + m), (jf + m, i_f),
                                                        (jf + m, i_f + m))))
        y = np.concatenate([j[~fine] for j, _ in children])
        x = np.concatenate([i[~fine] for _, i in children])
        s = m


def _surface_fill(dscene: DicScene, camera: Camera, r0: int, out: np.ndarray, nodes: "_LightNodes",
                  y: np.ndarray, x: np.ndarray, s: int, ids: np.ndarray, scale: float) -> None:
    """Write into `out` the pixels of the level-s cells (y, x) that see more than one surface (a
    silhouette or a crease passes): each pixel (y + a, x + b) takes the light of the cell's
    corners on its own surface (shape id as in `ids`, padded like `out`; normal within CREASE_COS
    of the pixel's, `nodes.normal`), with the bilinear weights (1 - a/s or a/s, 1 - b/s or
    b/s) renormalised over them (their mean where those weights are 0), when at least
    SURFACE_CORNERS such corners (three of a square's corners are not on one line: the light's
    slope is bounded both ways) agree within SHADE_ERROR x `scale`; the other pixels are computed
    themselves (thin features, a surface with fewer corners, a shadow edge). The light on one
    surface varies smoothly between shadow edges, and a pixel is at most s / √2 px from a corner.
    Measured on the built-in's cam1 at full size: 22 % fewer nodes; the image within 0.0012 of
    the light map refined to the pixels (25 pixels above 0.001, of 24 M) with SURFACE_CORNERS = 3,
    within 0.0056 with 2 (a steep light on a dark face next to a silhouette)."""
    if len(y) == 0:
        return
    corners = [(y, x), (y, x + s), (y + s, x), (y + s, x + s)]
    L = np.stack([nodes.L[c] for c in corners], axis=1)              # (m, 4)
    I = np.stack([nodes.I[c] for c in corners], axis=1)
    N = np.stack([nodes.normal(*c) for c in corners], axis=1)        # (m, 4, 3)
    todo_y, todo_x = [], []
    for a in range(s):
        for b in range(s):
            py, px = y + a, x + b
            if a == b == 0:                          # the corner (y, x) is this pixel's node
                out[py, px] = nodes.L[py, px]
                continue
            match = (I == ids[py, px][:, None]) & (np.einsum("mkc,mc->mk", N, nodes.normal(py, px)) >= CREASE_COS)
            count = match.sum(axis=1)
            spread = np.where(match, L, -np.inf).max(axis=1) - np.where(match, L, np.inf).min(axis=1)
            ok = (count >= SURFACE_CORNERS) & (spread <= SHADE_ERROR * scale)
            fy, fx = a / s, b / s
            w = np.array([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx])[None, :] * match
            total = w.sum(axis=1)
            w = np.where(total[:, None] > 0, w, match)
            value = np.sum(w * np.where(match, L, 0.0), axis=1) / np.maximum(w.sum(axis=1), 1e-300)
            out[py[ok], px[ok]] = value[ok]
            todo_y.append(py[~ok])
            todo_x.append(px[~ok])
    py, px = np.concatenate(todo_y), np.concatenate(todo_x)
    h, W = nodes.tile
    inside = (py < h) & (px < W)                     # past the tile: not part of the image
    py, px = py[inside], px[inside]
    nodes.compute(dscene, camera, r0, py, px, scale)
    out[py, px] = nodes.L[py, px]


@dataclass
class _LightNodes:
    """The nodes of the light map on the tile's pixel lattice (one row and column of nodes past
    the tile's, and the lattice may reach further): light L (NaN where not known yet), shape id I
    and shading normal N; at the tile's pixels the tile's own shape ids and normals, and the light
    where given."""

    L: np.ndarray
    I: np.ndarray
    N: np.ndarray              # the normals of the nodes past the tile's pixels (0 elsewhere)
    tile: tuple[int, int]      # (h, W): the nodes at the tile's pixels
    tile_normals: tuple = ()   # their normals' components, each (h, W) (views of the hits')

    @classmethod
    def lattice(cls, ids: np.ndarray, tile_normals: tuple) -> "_LightNodes":
        """The lattice of the tile whose pixels see the shapes `ids` (h, W) with shading normals
        `tile_normals` (three (h, W) components): every SHADE_STRIDE-th node of each level
        covers it; no light known yet."""
        h, W = ids.shape
        s = SHADE_STRIDE
        ny, nx = -(-h // s) * s + 1, -(-W // s) * s + 1
        I = np.zeros((ny, nx), dtype=np.uint32)
        I[:h, :W] = ids
        return cls(np.full((ny, nx), np.nan, dtype=np.float32), I, np.zeros((ny, nx, 3), dtype=np.float32),
                   (h, W), tuple(tile_normals))

    def normal(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(m, 3) the shading normals of the nodes (y, x): (0, 0, 1) where they see nothing (the
        sky is one "surface")."""
        out = self.N[y, x]
        h, W = self.tile
        inside = np.flatnonzero((y < h) & (x < W))
        if len(inside):
            yi, xi = y[inside], x[inside]
            for k, component in enumerate(self.tile_normals):
                out[inside, k] = component[yi, xi]
        out[self.I[y, x] == 0] = (0.0, 0.0, 1.0)
        return out

    def same(self, at, shape_id: np.ndarray, base) -> np.ndarray:
        """Whether the nodes `at` (a list of (y, x) index pairs) all see `shape_id` with normals
        within CREASE_COS of the node `base`'s."""
        ok = np.ones(len(shape_id), dtype=bool)
        n0 = self.normal(*base)
        for j, i in at:
            ok &= (self.I[j, i] == shape_id) & (np.einsum("ij,ij->i", self.normal(j, i), n0) >= CREASE_COS)
        return ok

    def compute(self, dscene: DicScene, camera: Camera, r0: int, y: np.ndarray, x: np.ndarray,
                scale: float = 1.0) -> None:
        """The light of the nodes (y, x), the pixels (x, r0 + y), where not known yet: cast (one
        batch) and shaded, from the frame's surface light map where it holds (at the tile's
        pixels it did not when the tile was cast: there it is shaded); the cast gives the shape
        and normal of the nodes past the tile's pixels."""
        import drjit as dr

        todo = np.isnan(self.L[y, x])
        y, x = y[todo], x[todo]
        if len(y) == 0:
            return
        grid = np.column_stack([x.astype(float), r0 + y.astype(float)])
        mapped = dscene.light_map is not None
        si, prim_uv = (_cast(dscene, camera, grid, barycentric=True, partials=False) if mapped
                       else (_cast(dscene, camera, grid, partials=False), None))
        dr.eval(si, prim_uv)                  # once: the lookup, the shading and the reads below
        h, W = self.tile
        beyond = (y >= h) | (x >= W)          # the map failed at the tile's pixels when it was cast
        light = _mapped_light(dscene, camera, si, prim_uv, scale, beyond if mapped else None)
        shape = np.array(_shape_ids(si))
        normal = np.empty((len(shape), 3), dtype=np.float32)
        for k in range(3):
            normal[:, k] = np.asarray(si.sh_frame.n[k])
        self.I[y, x], self.N[y, x], self.L[y, x] = shape, normal, light


def _mapped_light(dscene: DicScene, camera: Camera, si, prim_uv, scale: float, where=None) -> np.ndarray:
    """The light (`shade`) at the hits `si`: from the frame's surface light map (`dscene.light_map`,
    `vdo.rendering.lightmap`) at the hits `where` (a bool array; None: nowhere) when its lattice's
    nodes agree (tolerance in units of the camera's light `scale`), computed at the hits
    themselves elsewhere."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()

    def hits(lanes):
        return mi.UInt32(lanes.astype(np.uint32))
    light = np.full(dr.width(si), np.nan)
    tried = np.flatnonzero(where) if where is not None else np.zeros(0, dtype=np.int64)
    if len(tried):
        value, ok = dscene.light_map.lookup(dscene, dr.gather(type(si), si, hits(tried)),
                                            dr.gather(type(prim_uv), prim_uv, hits(tried)), scale, camera.focal_px)
        light[tried[ok]] = value[ok]
    rest = np.flatnonzero(np.isnan(light))
    if len(rest):
        light[rest] = shade(dscene, dr.gather(type(si), si, hits(rest)))
    return light


def _fill(out: np.ndarray, y: np.ndarray, x: np.ndarray, s: int, c00, c01, c10, c11) -> None:
    """Write into `out` (a whole number of level-s cells a side) the pixels of the level-s cells
    whose top-left pixels are (y, x), bilinear between their corners' values c00 (y, x), c01
    (y, x + s), c10 (y + s, x) and c11 (y + s, x + s)."""
    if len(y) == 0:
        return
    t = (np.arange(s) / s).astype(np.float32)
    fy, fx = t[None, :, None], t[None, None, :]
    c00, c01, c10, c11 = (np.asarray(c, dtype=np.float32)[:, None, None] for c in (c00, c01, c10, c11))
    top = c00 + fx * (c01 - c00)
    value = top + fy * (c10 + fx * (c11 - c10) - top)
    H, W = out.shape
    out.reshape(H // s, s, W // s, s)[y // s, :, x // s, :] = value


def _silhouette(ids: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels with a 4-neighbour (within the tile) that sees another shape."""
    out = np.zeros(ids.shape, dtype=bool)
    dy, dx = ids[1:] != ids[:-1], ids[:, 1:] != ids[:, :-1]
    out[1:] |= dy
    out[:-1] |= dy
    out[:, 1:] |= dx
    out[:, :-1] |= dx
    return out


def _supersampled(dscene: DicScene, camera: Camera, r0: int, pixels: np.ndarray, ids: np.ndarray,
                  light: np.ndarray) -> np.ndarray:
    """(n,) the mean of EDGE_SUPERSAMPLE^2 sub-pixel values of the tile's flat `pixels` (tile rows
    from r0; stratum centres, each ray with the footprint of its stratum and its albedo). A
    sub-pixel ray takes the light (`light`, (h, W), the light map) of the nearest pixel of the 3 x 3
    around its pixel that sees its shape: the light is smooth on one surface over a pixel, and the
    map is computed at each pixel where the shape changes. A ray whose shape no pixel around sees
    (a feature thinner than a pixel) is shaded itself."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    h, W = ids.shape
    k = EDGE_SUPERSAMPLE
    mid = (np.arange(k) + 0.5) / k - 0.5
    offsets = np.stack(np.meshgrid(mid, mid), -1).reshape(-1, 2)
    py, px = pixels // W, pixels % W
    grid = np.column_stack([px, py + r0]).astype(float)
    sub = (grid[:, None, :] + offsets[None]).reshape(-1, 2)
    si = _cast(dscene, camera, sub, 1.0 / k)
    value = mi.luminance(si.emitter(dscene.scene).eval(si)) * 1.0
    sub_ids = _shape_ids(si)
    dr.schedule(value, sub_ids)
    rho = _footprint_albedo(dscene, si)
    dr.eval(rho)
    del si
    sub_ids = np.array(sub_ids).reshape(len(pixels), k * k)
    sub_light = np.full(sub_ids.shape, np.nan)
    # The 3 x 3 neighbours, nearest first, each as seen from the sub-ray's own pixel.
    ring = sorted(((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)), key=lambda d: d[0] ** 2 + d[1] ** 2)
    for dy, dx in ring:
        y, x = np.clip(py + dy, 0, h - 1), np.clip(px + dx, 0, W - 1)
        take = np.isnan(sub_light) & (ids[y, x][:, None] == sub_ids)
        sub_light[take] = np.broadcast_to(light[y, x][:, None], sub_ids.shape)[take]
    alone = np.flatnonzero(np.isnan(sub_light).ravel())
    if len(alone):
        sub_light.ravel()[alone] = _shaded(dscene, camera, sub[alone])[0]
    total = np.array(value, dtype=np.float64) + np.array(rho, dtype=np.float64) * sub_light.ravel()
    return total.reshape(len(pixels), k * k).mean(axis=1)
