"""Fields on the unfolded specimen, laid out in first-angle projection (paper Fig. 11).

Each sample goes to the view that looks at its face: the view of the axis its normal points along.
In first-angle projection the front view (looking along +y at faces with normal -y) is in the
middle; the view from above (+z faces) is drawn *below* it, the view from below above it, the view
from the left (-x faces) to its right, the view from the right to its left, and the rear view at
the far right. Sheet coordinates of each view, from the world coordinates (x, y, z):

    front (-y): ( x, z)      top (+z): (x,  y)     bottom (-z): (x, -y)
    left  (-x): (-y, z)      right (+x): (y, z)    back (+y):  (-x, z)

so that neighbouring views share their common edges as on a drawing sheet. Each panel carries the
world directions of its sheet axes (→ right, ↑ up) and the names and outlines of its regions.

Every sample is drawn as its own surface cell: the square of side sqrt(area) around it in its
face's tangent frame (t_u, t_v), projected onto the sheet. Cells of a regular sample grid tile the
face exactly, so no sample can be lost or doubled by binning onto a raster, and no colour spills
past the face's edge.
"""

from __future__ import annotations

import math
import re
import textwrap
import weakref
from dataclasses import dataclass

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection, PolyCollection  # noqa: E402
from scipy.spatial import ConvexHull, QhullError  # noqa: E402

from vdo.scene import SurfaceSamples  # noqa: E402

# name, world axis of the face normal, sign, sheet axes as (world axis, sign) for horizontal, vertical
VIEWS = (
    ("front", 1, -1, (0, 1), (2, 1)),
    ("top", 2, +1, (0, 1), (1, 1)),
    ("bottom", 2, -1, (0, 1), (1, -1)),
    ("left", 0, -1, (1, -1), (2, 1)),
    ("right", 0, +1, (1, 1), (2, 1)),
    ("back", 1, +1, (0, -1), (2, 1)),
)
NO_VALUE = "0.78"     # grey of samples without a value (NaN); white is where there is no surface
OUTLIER_RATIO = 1.5   # a continuous scale stops at the 98th percentile when max > 1.5 x p98
MAP_HEIGHT_IN = 7.0   # height of a map figure; its width follows the unfolded specimen's aspect
MAP_MARGINS_IN = (0.1, 0.3, 0.6)   # left, bottom (the "no value" note), top (a two-line title):
                      # inches; the right margin holds the colour bar (`COLORBAR_IN`)
COLORBAR_IN = (0.15, 0.2, 0.75, 0.17)   # the colour bar's gap to the panels, its width, its tick
                      # labels' room, and a line of its label (9 pt): inches
MAX_REGION_LABELS = 40  # more regions than this: one label per region group (`region_groups`)


@dataclass(frozen=True)
class Panel:
    name: str
    x0: float
    y0: float
    width: float
    height: float


def cell_corners(samples: SurfaceSamples) -> np.ndarray:
    """(N, 4, 3) corners of each sample's surface cell: X ± (h/2) t_u ± (h/2) t_v with
    h = sqrt(area) (m), counter-clockwise seen from outside the face."""
    half = 0.5 * np.sqrt(samples.area)[:, None, None]
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)      # (4, 2)
    offsets = signs[None, :, 0:1] * samples.tangent_u[:, None, :] \
        + signs[None, :, 1:2] * samples.tangent_v[:, None, :]
    return samples.points[:, None, :] + half * offsets


def _view_of(normals: np.ndarray) -> np.ndarray:
    axis = np.argmax(np.abs(normals), axis=1)
    sign = np.sign(normals[np.arange(len(normals)), axis])
    view_of = np.empty(len(normals), dtype=int)
    for k, (_, ax, sg, _, _) in enumerate(VIEWS):
        view_of[(axis == ax) & (sign == sg)] = k
    return view_of


def unfold(samples: SurfaceSamples, gap: float | None = None):
    """Sheet coordinates (N, 2) in metres, view index (N,), the panels, each sample's depth toward
    its viewer (larger = nearer, drawn last), and each sample's cell on the sheet (N, 4, 2).

    The panels span the samples' cells (`cell_corners`), i.e. the faces themselves, not only the
    sample centres."""
    pts = samples.points
    corners = cell_corners(samples)
    view_of = _view_of(samples.normals)
    flat = corners.reshape(-1, 3)
    lo, hi = np.minimum(flat.min(axis=0), pts.min(axis=0)), np.maximum(flat.max(axis=0), pts.max(axis=0))
    span = hi - lo
    gap = 0.08 * span.max() if gap is None else gap

    def local(k, p):
        _, _, _, (ha, hs), (va, vs) = VIEWS[k]
        h = (p[..., ha] - lo[ha]) if hs > 0 else (hi[ha] - p[..., ha])
        v = (p[..., va] - lo[va]) if vs > 0 else (hi[va] - p[..., va])
        return np.stack([h, v], axis=-1)

    Lx, Ly, Lz = span
    origin = {"front": (0.0, 0.0), "top": (0.0, -gap - Ly), "bottom": (0.0, Lz + gap),
              "left": (Lx + gap, 0.0), "right": (-gap - Ly, 0.0), "back": (Lx + 2 * gap + Ly, 0.0)}
    size = {"front": (Lx, Lz), "top": (Lx, Ly), "bottom": (Lx, Ly), "left": (Ly, Lz),
            "right": (Ly, Lz), "back": (Lx, Lz)}
    sheet = np.zeros((len(pts), 2))
    cells = np.zeros((len(pts), 4, 2))
    depth = np.zeros(len(pts))
    panels = []
    for k, (name, ax, sg, _, _) in enumerate(VIEWS):
        mask = view_of == k
        if not mask.any():
            continue
        sheet[mask] = local(k, pts[mask]) + origin[name]
        cells[mask] = local(k, corners[mask]) + origin[name]
        depth[mask] = sg * pts[mask, ax]
        panels.append(Panel(name, *origin[name], *size[name]))
    return sheet, view_of, panels, depth, cells


def axis_label(axis: tuple[int, int]) -> str:
    """'+x', '-y', ... for a sheet axis given as (world axis, sign)."""
    return ("+" if axis[1] > 0 else "−") + "xyz"[axis[0]]


def color_range(values: np.ndarray, vmin=None, vmax=None) -> tuple[float, float, str]:
    """The colour scale's limits and how they were chosen: the finite data's min and max, or the
    98th percentile when max > OUTLIER_RATIO x p98 (a few outliers would flatten the rest);
    explicit `vmin`/`vmax` win."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return (0.0 if vmin is None else vmin), (1.0 if vmax is None else vmax), "no finite value"
    dmin, dmax, p98 = float(finite.min()), float(finite.max()), float(np.percentile(finite, 98))
    how = []
    if vmin is None:
        vmin = dmin
        how.append("data min")
    else:
        how.append("set")
    if vmax is None:
        if dmax > OUTLIER_RATIO * p98 and p98 > vmin:
            vmax = p98
            how.append(f"98th pct.; max {dmax:.4g}")
        else:
            vmax = dmax
            how.append("data max")
    else:
        how.append("set")
    if vmax <= vmin:
        vmax = vmin + max(abs(vmin) * 1e-6, 1e-12)
    return float(vmin), float(vmax), " – ".join(how)


def plot_unfolded(samples: SurfaceSamples, values: np.ndarray, path, title: str, label: str,
                  discrete: bool = False, cmap: str | None = None, vmin=None, vmax=None) -> dict:
    """Draw one per-sample field on the unfolded specimen and save it as PNG.

    The colour scale runs over the data's range (`color_range`) and the colour bar states its
    limits; samples without a value (NaN) are grey. Returns each region's bounding box in the
    PNG's pixels, {name: (col0, row0, col1, row1)} with row 0 at the top."""
    values = np.asarray(values, dtype=float)
    lay = layout(samples)
    panels, cells, hulls = lay.panels, lay.cells, lay.hulls
    lo = np.array([min(p.x0 for p in panels), min(p.y0 for p in panels)])
    hi = np.array([max(p.x0 + p.width for p in panels), max(p.y0 + p.height for p in panels)])
    margin = 0.06 * max(hi - lo)
    lo, hi = lo - margin, hi + margin

    if discrete:
        finite = values[np.isfinite(values)]
        top = int(max(finite.max() if finite.size else 0, 1))
        cmap_obj = plt.get_cmap(cmap or "viridis", top + 1)
        vmin, vmax, scale = -0.5, top + 0.5, f"0 – {top}"
    else:
        cmap_obj = plt.get_cmap(cmap or "viridis")
        vmin, vmax, how = color_range(values, vmin, vmax)
        scale = f"scale {vmin:.4g} – {vmax:.4g} ({how})"
    cmap_obj = cmap_obj.with_extremes(bad=NO_VALUE)

    aspect = (hi[0] - lo[0]) / max(hi[1] - lo[1], 1e-9)
    width_in = min(4 + 6 * aspect, 18)
    dpi = 130
    # the panels' axes and the colour bar placed by hand (`MAP_MARGINS_IN`, `COLORBAR_IN`):
    # matplotlib's constrained layout drew every map twice (0.40 -> 0.28 s a map)
    left, bottom, top = MAP_MARGINS_IN
    bar_label = textwrap.fill(f"{label}; {scale}", 40)
    gap, bar_width, ticks, line = COLORBAR_IN
    right = gap + bar_width + ticks + line * (bar_label.count("\n") + 1)
    fig = plt.figure(figsize=(width_in, MAP_HEIGHT_IN), dpi=dpi)
    axes = fig.add_axes([left / width_in, bottom / MAP_HEIGHT_IN, 1 - (left + right) / width_in,
                         1 - (bottom + top) / MAP_HEIGHT_IN])
    order = lay.order                                      # nearer faces drawn last
    coll = PolyCollection(cells[order], array=np.ma.masked_invalid(values[order]), cmap=cmap_obj,
                          edgecolors="face", linewidths=0.2, antialiaseds=False)
    coll.set_clim(vmin, vmax)
    axes.add_collection(coll)
    fs = 7
    for p in panels:
        k = [v[0] for v in VIEWS].index(p.name)
        _, ax, sg, h_axis, v_axis = VIEWS[k]
        axes.text(p.x0, p.y0 + p.height + 0.01 * margin,
                  f"view from {'+' if sg > 0 else '−'}{'xyz'[ax]} ({p.name}):  "
                  f"→ {axis_label(h_axis)}   ↑ {axis_label(v_axis)}",
                  va="bottom", ha="left", fontsize=fs, color="0.2")
    # every region's outline in one collection (one artist, whatever the number of regions)
    axes.add_collection(LineCollection([np.vstack([r, r[:1]]) for rings in hulls.values() for r in rings], lw=0.6,
                                       colors="0.15", linestyles="--"))
    for text, ring in lay.labels:
        c = 0.5 * (ring.min(axis=0) + ring.max(axis=0))
        ext = ring.max(axis=0) - ring.min(axis=0)
        axes.text(*c, text, ha="center", va="center", fontsize=fs - 1.5,
                  rotation=90 if ext[1] > 1.5 * ext[0] else 0, color="0.1",
                  bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.6))
    # scale bar, bottom left
    bar = 10 ** np.floor(np.log10(0.2 * (hi[0] - lo[0])))
    axes.plot([lo[0] + 0.2 * margin, lo[0] + 0.2 * margin + bar], [lo[1] + 0.3 * margin] * 2,
              color="k", lw=1.5)
    axes.text(lo[0] + 0.2 * margin + bar / 2, lo[1] + 0.35 * margin, f"{bar:g} m", ha="center",
              va="bottom", fontsize=fs)
    axes.set_xlim(lo[0], hi[0])
    axes.set_ylim(lo[1], hi[1])
    axes.set_aspect("equal")
    axes.set_axis_off()
    chars = max(int(width_in * 72 / (0.6 * 12) * 0.8), 30)
    axes.set_title(textwrap.fill(f"{title} (first-angle projection)", chars), fontsize=12)
    height = 0.8 * (MAP_HEIGHT_IN - bottom - top)
    cax = fig.add_axes([1 - (right - gap) / width_in,
                        (bottom + 0.1 * (MAP_HEIGHT_IN - bottom - top)) / MAP_HEIGHT_IN,
                        bar_width / width_in, height / MAP_HEIGHT_IN])
    cbar = fig.colorbar(coll, cax=cax, extend="neither" if discrete else _extend(values, vmin, vmax))
    cbar.set_label(bar_label, fontsize=9)
    if discrete:
        cbar.set_ticks(range(0, int(vmax + 0.5)))
    if np.isnan(values).any():
        fig.text(0.01, 0.01, "grey: no value (not measured)", fontsize=8, color="0.3")
    fig.savefig(path, dpi=dpi)
    fig_h = fig.get_size_inches()[1] * dpi
    boxes = {}
    for name, rings in hulls.items():
        px = axes.transData.transform(np.vstack(rings))
        boxes[name] = (float(px[:, 0].min()), float(fig_h - px[:, 1].max()),
                       float(px[:, 0].max()), float(fig_h - px[:, 1].min()))
    plt.close(fig)
    return boxes


def region_groups(names) -> dict[str, list[int]]:
    """Regions grouped by name with a trailing index removed ("front_012" and "front_013" ->
    "front"; a name without one is its own group): {group: region indices}, in first-seen order."""
    out: dict[str, list[int]] = {}
    for r, name in enumerate(names):
        out.setdefault(re.sub(r"[_\-. ]*\d+$", "", name) or name, []).append(r)
    return out


@dataclass(frozen=True, eq=False)
class MapLayout:
    """What every map of one set of samples shares (`layout`): the unfolded cells (N, 4, 2) and
    depth (N,) of `unfold`, the drawing order (nearer faces last), the panels, each region's
    outlines on the sheet (the convex hull of its cells in each view it spans: a curved region's
    several) and the labels to draw: (text, ring), one per
    region up to MAX_REGION_LABELS regions, else one per region group (`region_groups`, its
    name and region count, over the union of its members' rings)."""

    cells: np.ndarray
    depth: np.ndarray
    order: np.ndarray
    panels: list
    hulls: dict
    labels: list


_LAYOUTS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def layout(samples: SurfaceSamples) -> MapLayout:
    """The `MapLayout` of `samples`, computed once per samples object (every map of an evaluation
    shares it)."""
    if samples in _LAYOUTS:
        return _LAYOUTS[samples]
    _, view_of, panels, depth, cells = unfold(samples)
    hulls = {}
    for r, name in enumerate(samples.region_names):
        rings = []
        for k in np.unique(view_of[samples.region == r]):   # a curved region spans several views
            corners = cells[(samples.region == r) & (view_of == k)].reshape(-1, 2)
            try:
                rings.append(corners[ConvexHull(corners).vertices])
            except QhullError:                             # degenerate (a line of samples)
                rings.append(corners[[np.argmin(corners[:, 0]), np.argmax(corners[:, 0])]])
        if rings:
            hulls[name] = rings
    if len(hulls) <= MAX_REGION_LABELS:       # each region named once, in the view it fills most
        labels = [(name, max(rings, key=_ring_area)) for name, rings in hulls.items()]
    else:
        labels = []
        names = list(samples.region_names)
        for group, members in region_groups(names).items():
            rings = [ring for r in members if names[r] in hulls for ring in hulls[names[r]]]
            if rings:   # a group spread over several views is labelled in each view it fills
                for view in _views_of_rings(rings, panels):
                    labels.append((f"{group} ({len(members)})", np.vstack(view)))
    out = MapLayout(cells, depth, np.argsort(depth, kind="stable"), panels, hulls, labels)
    _LAYOUTS[samples] = out
    return out


def _ring_area(ring: np.ndarray) -> float:
    """The area a closed ring (M, 2) encloses (the shoelace formula; 0 for fewer than 3 points)."""
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def _views_of_rings(rings, panels) -> list[list[np.ndarray]]:
    """The rings split by the panel that holds each one's centre (in panel order)."""
    out = {}
    for ring in rings:
        c = ring.mean(axis=0)
        k = next((i for i, p in enumerate(panels) if p.x0 - 1e-9 <= c[0] <= p.x0 + p.width + 1e-9
                  and p.y0 - 1e-9 <= c[1] <= p.y0 + p.height + 1e-9), -1)
        out.setdefault(k, []).append(ring)
    return [out[k] for k in sorted(out)]


def _extend(values: np.ndarray, vmin: float, vmax: float) -> str:
    finite = values[np.isfinite(values)]
    below = bool(finite.size and finite.min() < vmin)
    above = bool(finite.size and finite.max() > vmax)
    return {(False, False): "neither", (True, False): "min", (False, True): "max",
            (True, True): "both"}[(below, above)]


# --------------------------------------------------------------------------------------------
# Curved regions drawn developed
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DevelopedOutline:
    """A curved region's lines in its developed plane (m): `outline` the edges of the union of
    its samples' grid cells (the sampled surface's edge), `holes` its mesh's free edges (holes and
    open ends that the region's faces border), `seam` the lines where a closed ring was cut open
    to be developed (a cylinder's u = 0 and u = period, a cone's rays at psi = 0 and psi = turn;
    None when the region is not closed)."""

    outline: np.ndarray      # (E, 2, 2)
    holes: np.ndarray        # (F, 2, 2)
    seam: np.ndarray | None  # (S, 2, 2)


def developed_outline(samples: SurfaceSamples, region: int, faces, mesh_vertices: np.ndarray,
                      mesh_faces: np.ndarray) -> DevelopedOutline:
    """The `DevelopedOutline` of region `region` (its `vdo.scene.RegionFaces` `faces`, whose
    development gives the map) on a mesh (vertices (V, 3) m, faces (F, 3)). Cell edges: a side of
    the square cell (i, j) (uv = (i + 1/2, j + 1/2) h) not shared with another cell of the region
    (a cylinder ring's neighbours across the seam count; along a cone ring's seam, where the
    square cells meet turned, no cell edge within a cell of the seam is drawn: the seam's rays are).
    Free edges: edges used by one face of the whole mesh (corners merged to 1 nm), of the region's
    faces, developed with their face."""
    from vdo.model.surface import merged
    from vdo.scene import ring_spacing

    mask = samples.region == region
    dev = faces.development
    period = float(dev.period) if dev is not None else 0.0
    h = float(samples.region_cell[region]) if samples.region_cell is not None else \
        float(np.sqrt(np.median(samples.area[mask])))
    h = ring_spacing(period, h) if period else h
    ij = np.round(samples.uv[mask] / h - 0.5).astype(np.int64)
    n_around = int(round(period / h)) if period else 0
    cells = {tuple(c) for c in ij}
    turn = dev.flip * dev.turn if dev is not None else 0.0
    lines = []
    for (i, j) in cells:
        for di, dj, a, b in ((1, 0, (1, 0), (1, 1)), (-1, 0, (0, 0), (0, 1)),
                             (0, 1, (0, 1), (1, 1)), (0, -1, (0, 0), (1, 0))):
            k = (i + di) % n_around if n_around else i + di
            if (k, j + dj) not in cells:
                lines.append([[(i + a[0]) * h, (j + a[1]) * h], [(i + b[0]) * h, (j + b[1]) * h]])
    lines = np.array(lines).reshape(-1, 2, 2)
    if turn:
        mid = lines.mean(axis=1)
        s_mid = np.hypot(mid[:, 0], mid[:, 1])
        psi = np.mod(np.arctan2(math.copysign(1.0, turn) * mid[:, 0], -mid[:, 1]) + math.pi - abs(turn) / 2,
                     2 * math.pi) - math.pi + abs(turn) / 2
        lines = lines[np.minimum(np.abs(psi), np.abs(abs(turn) - psi)) * s_mid >= h]
    tri_all = np.asarray(mesh_vertices, float)[np.asarray(mesh_faces)]
    _, f_all = merged(tri_all)
    edges = np.sort(np.stack([f_all[:, [0, 1]], f_all[:, [1, 2]], f_all[:, [2, 0]]], axis=1), axis=2)
    keys, counts = np.unique(edges.reshape(-1, 2), axis=0, return_counts=True)
    free = {tuple(k) for k in keys[counts == 1]}
    uv_tri = dev.triangles_uv(tri_all[faces.faces]) if dev is not None else faces.uv(tri_all[faces.faces])
    holes = []
    for t, face in enumerate(faces.faces):
        for a, b in ((0, 1), (1, 2), (2, 0)):
            if tuple(sorted((f_all[face, a], f_all[face, b]))) in free:
                holes.append(uv_tri[t, [a, b]])
    holes = np.array(holes).reshape(-1, 2, 2)
    if period:
        holes[..., 0] = np.mod(holes[..., 0], period)
        wrapped = np.abs(holes[:, 0, 0] - holes[:, 1, 0]) > period / 2
        holes = holes[~wrapped]
    uv = samples.uv[mask]
    seam = None
    if period:
        v0, v1 = uv[:, 1].min() - h / 2, uv[:, 1].max() + h / 2
        seam = np.array([[[0.0, v0], [0.0, v1]], [[period, v0], [period, v1]]])
    elif turn:
        s0, s1 = np.hypot(uv[:, 0], uv[:, 1]).min() - h / 2, np.hypot(uv[:, 0], uv[:, 1]).max() + h / 2
        rays = [np.array([np.sign(turn) * math.sin(a), -math.cos(a)]) for a in (0.0, abs(turn))]
        seam = np.array([[s0 * r, s1 * r] for r in rays])
    return DevelopedOutline(lines, holes, seam)


def plot_developed(samples: SurfaceSamples, region: int, faces, mesh_vertices, mesh_faces,
                   values: np.ndarray, usable: np.ndarray, camera_names, path, title: str,
                   label: str, cmap: str = "magma_r") -> dict:
    """One curved region drawn developed and saved as PNG: the field `values` (N,) on each
    sample's square cell in (u, v) (exact for a cylinder or a cone; a parameterisation otherwise,
    its distortion in the title), the region's outline (black), its hole and free edges (blue),
    a ring's seam (dotted), and one small panel per camera that sees part of it (usable views
    `usable` (C, N)) with the cells it sees. Returns {"kind", "area_distortion",
    "angle_distortion", "cameras": {name: fraction of the region's area seen}}."""
    from matplotlib.collections import LineCollection

    mask = samples.region == region
    dev = faces.development
    outline = developed_outline(samples, region, faces, mesh_vertices, mesh_faces)
    h = float(samples.region_cell[region]) if samples.region_cell is not None else \
        float(np.sqrt(np.median(samples.area[mask])))
    uv = samples.uv[mask]
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float) * h / 2
    cells = uv[:, None, :] + square[None]
    vals = np.asarray(values, float)[mask]
    seen = np.asarray(usable, bool)[:, mask]
    area = samples.area[mask]
    shown = [i for i in range(len(camera_names)) if seen[i].any()]
    lo, hi = cells.reshape(-1, 2).min(0), cells.reshape(-1, 2).max(0)
    ext = hi - lo
    ncols = max(len(shown), 1)
    fig = plt.figure(figsize=(max(8, min(18, 2.2 * ncols)), 8), layout="constrained", dpi=120)
    grid = fig.add_gridspec(2, ncols, height_ratios=[3, 1.2])
    main = fig.add_subplot(grid[0, :])
    main.set_anchor("C")
    vmin, vmax, how = color_range(vals)
    coll = PolyCollection(cells, array=np.ma.masked_invalid(vals),
                          cmap=plt.get_cmap(cmap).with_extremes(bad=NO_VALUE),
                          edgecolors="face", linewidths=0.2, antialiaseds=False)
    coll.set_clim(vmin, vmax)
    main.add_collection(coll)

    def lines(ax, width):
        ax.add_collection(LineCollection(outline.outline, colors="k", linewidths=width))
        if len(outline.holes):
            ax.add_collection(LineCollection(outline.holes, colors="tab:blue", linewidths=1.6 * width))
        if outline.seam is not None:
            ax.add_collection(LineCollection(outline.seam, colors="0.3", linestyles=":", linewidths=width))
        ax.set_xlim(lo[0] - 0.02 * ext.max(), hi[0] + 0.02 * ext.max())
        ax.set_ylim(lo[1] - 0.02 * ext.max(), hi[1] + 0.02 * ext.max())
        ax.set_aspect("equal")

    lines(main, 0.8)
    main.set_xlabel("u (m, developed" + (", R θ)" if dev is not None and dev.kind == "cylinder" else ")"))
    main.set_ylabel("v (m)")
    kind = dev.kind if dev is not None else "plane"
    dist = dev.distortion if dev is not None else None
    how_dev = {"cylinder": f"cylinder R = {abs(dev.radius):.4g} m, developed exactly" if dev is not None else "",
               "cone": f"cone half-angle {np.degrees(dev.half_angle):.3g}°, developed exactly"
               if dev is not None else "",
               "general": "least-squares conformal map", "plane": "planar"}[kind]
    if dist is not None:
        how_dev += f"; area distortion p95 {100 * dist.area_p95:.2g} %, angle {100 * dist.angle_p95:.2g} %"
        if dist.large:
            how_dev += " (LARGE: distances on this map are off by as much)"
    main.set_title("\n".join(textwrap.fill(part, 110) for part in (title, how_dev)), fontsize=10)
    cbar = fig.colorbar(coll, ax=main, shrink=0.8, panchor=False)    # the map stays centred
    cbar.set_label(f"{label}; scale {vmin:.4g} – {vmax:.4g} ({how})", fontsize=8)
    fig.text(0.01, 0.005, "black: region outline   blue: hole / free edges"
             + ("   dotted: the ring's seam (the map continues across it)" if outline.seam is not None
                else ""), fontsize=8, color="0.3")
    fractions = {}
    for col, i in enumerate(shown):
        ax = fig.add_subplot(grid[1, col])
        colors = np.where(seen[i], 0.25, 0.9)
        ax.add_collection(PolyCollection(cells, array=colors, cmap="Greens_r", clim=(0, 1),
                                         edgecolors="face", linewidths=0.1, antialiaseds=False))
        lines(ax, 0.4)
        fractions[camera_names[i]] = float(area[seen[i]].sum() / area.sum())
        ax.set_title(f"{camera_names[i]}: {100 * fractions[camera_names[i]]:.0f} %", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.savefig(path)
    plt.close(fig)
    return {"kind": kind, "area_distortion": None if dist is None else dist.area_p95,
            "angle_distortion": None if dist is None else dist.angle_p95, "cameras": fractions}
