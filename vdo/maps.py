"""Fields on the unfolded specimen, laid out in first-angle projection (paper Fig. 11).

Each sample goes to the view that looks at its face: the view of the axis its normal points along.
In first-angle projection the front view (looking along +y at faces with normal -y) is in the
middle; the view from above (+z faces) is drawn *below* it, the view from below above it, the view
from the left (-x faces) to its right, the view from the right to its left, and the rear view at
the far right. Sheet coordinates of each view, from the world coordinates (x, y, z):

    front (-y): ( x, z)      top (+z): (x,  y)     bottom (-z): (x, -y)
    left  (-x): (-y, z)      right (+x): (y, z)    back (+y):  (-x, z)

so that neighbouring views share their common edges as on a drawing sheet.
"""

from __future__ import annotations

from dataclasses import dataclass

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .scene import SurfaceSamples  # noqa: E402

# name, world axis of the face normal, sign, sheet axes as (world axis, sign) for horizontal, vertical
VIEWS = (
    ("front", 1, -1, (0, 1), (2, 1)),
    ("top", 2, +1, (0, 1), (1, 1)),
    ("bottom", 2, -1, (0, 1), (1, -1)),
    ("left", 0, -1, (1, -1), (2, 1)),
    ("right", 0, +1, (1, 1), (2, 1)),
    ("back", 1, +1, (0, -1), (2, 1)),
)


@dataclass(frozen=True)
class Panel:
    name: str
    x0: float
    y0: float
    width: float
    height: float


def unfold(samples: SurfaceSamples, gap: float | None = None):
    """Sheet coordinates (N, 2) in metres, view index (N,), the panels, and each sample's depth
    toward its viewer (larger = nearer, drawn last)."""
    pts, normals = samples.points, samples.normals
    view_of = np.empty(len(pts), dtype=int)
    axis = np.argmax(np.abs(normals), axis=1)
    sign = np.sign(normals[np.arange(len(pts)), axis])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = hi - lo
    gap = 0.08 * span.max() if gap is None else gap
    for k, (_, ax, sg, _, _) in enumerate(VIEWS):
        view_of[(axis == ax) & (sign == sg)] = k

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
    depth = np.zeros(len(pts))
    panels = []
    for k, (name, ax, sg, _, _) in enumerate(VIEWS):
        mask = view_of == k
        if not mask.any():
            continue
        sheet[mask] = local(k, pts[mask]) + origin[name]
        depth[mask] = sg * pts[mask, ax]
        panels.append(Panel(name, *origin[name], *size[name]))
    return sheet, view_of, panels, depth


def plot_unfolded(samples: SurfaceSamples, values: np.ndarray, path, title: str, label: str,
                  discrete: bool = False, cmap: str | None = None, vmin=None, vmax=None) -> None:
    """Draw one per-sample field on the unfolded specimen and save it as PNG."""
    values = np.asarray(values, dtype=float)
    sheet, _, panels, depth = unfold(samples)
    cell = float(np.sqrt(np.median(samples.area)))
    lo = np.array([min(p.x0 for p in panels), min(p.y0 for p in panels)])
    hi = np.array([max(p.x0 + p.width for p in panels), max(p.y0 + p.height for p in panels)])
    shape = np.ceil((hi - lo) / cell).astype(int) + 1
    canvas = np.full((shape[1], shape[0]), np.nan)
    order = np.argsort(depth, kind="stable")              # nearer faces drawn last
    ij = np.floor((sheet[order] - lo) / cell).astype(int)
    canvas[ij[:, 1], ij[:, 0]] = values[order]

    finite = values[np.isfinite(values)]
    if discrete:
        top = int(max(finite.max() if finite.size else 0, 1))
        cmap_obj = plt.get_cmap(cmap or "viridis", top + 1)
        vmin, vmax = -0.5, top + 0.5
    else:
        cmap_obj = plt.get_cmap(cmap or "viridis")
    cmap_obj = cmap_obj.with_extremes(bad="white")
    aspect = (hi[0] - lo[0]) / max(hi[1] - lo[1], 1e-9)
    fig, axes = plt.subplots(figsize=(min(4 + 6 * aspect, 18), 7), layout="constrained")
    image = axes.imshow(canvas, origin="lower", cmap=cmap_obj, vmin=vmin, vmax=vmax,
                        extent=(lo[0], lo[0] + shape[0] * cell, lo[1], lo[1] + shape[1] * cell),
                        interpolation="nearest")
    for p in panels:
        axes.add_patch(plt.Rectangle((p.x0, p.y0), p.width, p.height, fill=False, lw=0.6,
                                     ec="0.5", ls="--"))
        axes.text(p.x0, p.y0 + p.height, f" {p.name}", va="bottom", ha="left", fontsize=8,
                  color="0.3")
    axes.set_title(title)
    axes.set_xlabel("sheet coordinate (m), first-angle projection")
    axes.set_aspect("equal")
    bar = fig.colorbar(image, ax=axes, shrink=0.8, label=label)
    if discrete:
        bar.set_ticks(range(0, int(vmax + 0.5)))
    fig.savefig(path, dpi=130)
    plt.close(fig)
