"""What of a sample's views and of its DIC patch is usable: one definition shared by the coverage
counts, the uncertainty and the summaries.

Usable view. Camera i is a *usable view* of sample X when its soft weight (`vdo.objective`: ray
cast x in front x incidence ramp x image-edge ramp) reaches

    w_i(X) >= USABLE_WEIGHT = 0.5,

the middle of each soft ramp: with the default ramps, at least 5 px inside the image edge and 5 deg
inside the incidence limit, and not occluded. A view below it contributes nothing to the reported
uncertainty, is not counted in `coverage` and not in the summaries' "seen by" fractions, so a sample
counted as seen by >= 2 cameras has the information of >= 2 views of weight >= 0.5 (its sigma is
finite unless the two rays are parallel), and a sample at the image edge with a tiny weight is
counted as unseen rather than reported with a meaningless sigma of metres. (The optimizer's score
keeps the smooth weights, which it needs for gradients.)

Patch clipped to the usable surface. The DIC patch (subset or element) of side L (`[evaluation]
patch_mm`, area Omega = L^2) centred at X lies on the speckled surface only in part near a hole, a
region's boundary or an occlusion boundary. The information of camera i over the patch is the
integral of its per-area information over the part of the square that camera i sees usably, so

    C(X) = sum_i Omega_i(X) w_i(X) |det A_i| C_i,     Omega_i(X) = phi_i(X) Omega,

with phi_i(X) in [0, 1] the fraction of the patch square on samples of X's region that are usable
views of camera i (0 when camera i is not a usable view of X itself). Far from edges phi_i = 1 and
C is the unclipped model; where only a fraction phi of the square is usable by every camera,
sigma grows as 1 / sqrt(phi).

Estimator. The samples of a region lie on a regular grid of spacing h in the face coordinates
(u, v) (`vdo.scene.sample_region`); each stands for the cell of side h centred on it, and the cells
tile the sampled surface. phi_i(X) is the area of the square's overlap with the cells of the
region's samples that camera i sees usably, divided by L^2:

    phi_i(X) = sum_j o(X, j) [w_ij >= USABLE_WEIGHT] / L^2,
    o(X, j)  = prod_{a = u, v} clip((L + h)/2 - |x_a - y_a|, 0, min(L, h))

the neighbours j found with a KD-tree (Chebyshev radius (L + h)/2) in the region's (u, v). The
overlaps of all cells sum to L^2 away from edges, so phi = 1 there exactly. Error: an edge is
resolved to the cells, i.e. to within h/2 of its true position, so phi is off by at most
h/(2L) per edge crossing the square (a straight edge; a curved hole edge alternates signs along
it, and averages better). Measured on the holed plate (1 mm cells, 10 mm patch, 30 mm hole)
against the exact area of the square off the disc: sigma / (sigma_far / sqrt(phi_exact)) - 1
has median +0.2 % and 95 % of the samples within 1.7 % (`experiments/holed_plate/
edge_profile.py`; `tests/physics/test_edges.py` holds it to 2.5 %). When L <= h the patch is one cell and only a whole missing or hidden cell
clips it: sample more finely than the patch to see edges.

Flags (per sample, from `flags`):

* ``edge_limited``: the patch fraction usable by >= 2 cameras, phi_2(X) (the square's overlap with
  the cells of samples of the region that have >= 2 usable views, over L^2), is below
  EDGE_FRACTION = 0.5: the measurement rests on less than half its nominal patch;
* ``outlier``: sigma_max above OUTLIER_FACTOR = 3 times the median sigma_max of the measured samples
  of its region (near-parallel views, edge-limited patches, grazing views): a value that is
  measured, but far from the rest of its region.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from vdo.model.surface import CellIndex, across_seam, across_seam_grid
from vdo.scene import SurfaceSamples

USABLE_WEIGHT = 0.5    # a view counts when its soft weight w_i >= this
EDGE_FRACTION = 0.5    # edge-limited: less than this fraction of the patch usable by >= 2 views
OUTLIER_FACTOR = 3.0   # outlier: sigma_max above this multiple of its region's median
FINE_PATCH_CELLS = 2.0  # a patch at most this many cells wide is clipped on the surface itself


def usable_views(weights: np.ndarray) -> np.ndarray:
    """(C, N) bool: camera i is a usable view of sample n, w_in >= USABLE_WEIGHT."""
    return np.asarray(weights) >= USABLE_WEIGHT


def raster_overlap(samples: SurfaceSamples, region: int, patch_size: float,
                   raster) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, cols, values) of the overlap of the patches of region `region`'s samples with its
    cells, from the surface itself (`vdo.scene.SurfaceRaster`, fine points of spacing h / K):
    o(n, j) = #(fine points of the patch square of sample n in cell j that lie on the surface)
    / #(fine points of the whole square). The patch spans cells i - 1 .. i + 1 (L <= 2 h); the
    counts come from the raster's summed-area table. Error: an edge is resolved to h / K."""
    L, K, h = float(patch_size), raster.fine, raster.cell
    idx = np.flatnonzero(samples.region == region)
    ij = np.round(samples.uv[idx] / h - 0.5).astype(np.int64)
    S = np.zeros((raster.mask.shape[0] + 1, raster.mask.shape[1] + 1), dtype=np.int64)
    S[1:, 1:] = raster.mask.cumsum(axis=0).cumsum(axis=1)

    def count(a0, a1, b0, b1):
        """On-surface fine points in [a0, a1) x [b0, b1) (fine indices), per sample."""
        a0, a1 = (np.clip(x - raster.offset[0], 0, raster.mask.shape[0]) for x in (a0, a1))
        b0, b1 = (np.clip(x - raster.offset[1], 0, raster.mask.shape[1]) for x in (b0, b1))
        a1, b1 = np.maximum(a1, a0), np.maximum(b1, b0)
        return S[a1, b1] - S[a0, b1] - S[a1, b0] + S[a0, b0]

    half = L * K / (2 * h)                              # the patch's half side in fine spacings
    centre = ij * K + K / 2                             # fine coordinate of the cell centres
    lo = np.ceil(centre - half - 0.5 - 1e-9).astype(np.int64)
    hi = np.ceil(centre + half - 0.5 - 1e-9).astype(np.int64)
    whole = np.prod(hi - lo, axis=1).astype(float)
    lookup = CellIndex(ij)
    if raster.turn:      # a closed cone's cells continue across its seam (a cell's own row first)
        seam, owner = across_seam_grid(ij, h, raster.turn, 2 * h)
        lookup = CellIndex(np.concatenate([ij, seam.reshape(-1, 2)]),
                           np.concatenate([np.arange(len(ij)), owner]))
    rows, cols, vals = [], [], []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            other = ij + [di, dj]
            a0, a1 = np.maximum(lo[:, 0], other[:, 0] * K), np.minimum(hi[:, 0], other[:, 0] * K + K)
            b0, b1 = np.maximum(lo[:, 1], other[:, 1] * K), np.minimum(hi[:, 1], other[:, 1] * K + K)
            c = count(a0, a1, b0, b1)
            if raster.around:
                other[:, 0] = np.mod(other[:, 0], raster.around)
            j = lookup.find(other)
            ok = (c > 0) & (j >= 0)
            rows.append(idx[ok])
            cols.append(idx[j[ok]])
            vals.append(c[ok] / whole[ok])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)


def patch_overlap(samples: SurfaceSamples, patch_size: float, rasters=None) -> scipy.sparse.csr_matrix:
    """(N, N) sparse: entry (n, j) = o(X_n, j) / L^2, the fraction of the patch square of side
    `patch_size` L (m) centred at sample n covered by the cell of sample j of the same region
    (module docstring). The cell side h is each region's grid spacing (`region_cell`; else
    sqrt(area), planar cells). A ring closed around its axis wraps in u at its period. With
    `rasters` (one `vdo.scene.SurfaceRaster` or None per region), a region whose patch is at most
    FINE_PATCH_CELLS cells wide takes its overlaps from its surface (`raster_overlap`)."""
    L = float(patch_size)
    rows, cols, vals = [], [], []
    periods = samples.region_period if samples.region_period is not None else \
        np.zeros(len(samples.region_names))
    turns = samples.region_turn if samples.region_turn is not None else np.zeros(len(samples.region_names))
    for r in np.unique(samples.region):
        if rasters is not None and rasters[r] is not None and L <= FINE_PATCH_CELLS * rasters[r].cell:
            for out, part in zip((rows, cols, vals), raster_overlap(samples, r, L, rasters[r])):
                out.append(part)
            continue
        idx = np.flatnonzero(samples.region == r)
        uv = np.asarray(samples.uv[idx], dtype=float)
        period = float(periods[r])
        h = float(np.sqrt(np.median(samples.area[idx]))) if samples.region_cell is None \
            else float(samples.region_cell[r])
        owner, cells = np.arange(len(idx)), uv      # the cells: a closed cone's continue across its seam
        if turns[r] != 0:
            ghost, image = across_seam(uv, float(turns[r]), L + h)
            owner, cells = np.concatenate([owner, ghost]), np.concatenate([uv, image])
        if period > 0:        # a ring: u wraps at the period
            uv = uv - [0.0, uv[:, 1].min()]
            cells = uv
            box = [period, 2 * (float(uv[:, 1].max()) + L + h) + 1.0]
            tree = cKDTree(np.mod(uv, box), boxsize=box)
        else:
            tree = cKDTree(cells)
        # cells overlapping the square: centres within (L + h)/2 in the max norm (minus rounding)
        pairs = tree.query_ball_point(np.mod(uv, box) if period > 0 else uv,
                                      r=(L + h) / 2 * (1 - 1e-12), p=np.inf)
        counts = np.fromiter((len(p) for p in pairs), dtype=np.int64, count=len(pairs))
        a = np.repeat(np.arange(len(idx)), counts)
        b = np.concatenate([np.asarray(p, dtype=np.int64) for p in pairs]) if len(pairs) else a
        d = np.abs(uv[a] - cells[b])                                 # (K, 2)
        if period > 0:
            d[:, 0] = np.minimum(d[:, 0], period - d[:, 0])
        overlap = np.clip((L + h) / 2 - d, 0.0, min(L, h))         # 1D overlap per axis
        rows.append(idx[a])
        cols.append(idx[owner[b]])
        vals.append(overlap.prod(axis=1) / L ** 2)
    n = len(samples)
    return scipy.sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                   shape=(n, n))


def patch_normal_spread(overlap: scipy.sparse.csr_matrix, normals: np.ndarray) -> np.ndarray:
    """(N,) the largest angle (rad) between a sample's normal and the normals of the cells its
    patch overlaps: 0 on a planar region, about L / R on a surface of radius of curvature R."""
    coo = overlap.tocoo()
    cos = np.einsum("ij,ij->i", normals[coo.row], normals[coo.col])
    lowest = np.ones(overlap.shape[0])
    np.minimum.at(lowest, coo.row, cos)
    return np.arccos(np.clip(lowest, -1.0, 1.0))


def surface_patch_information(overlap: scipy.sparse.csr_matrix, usable: np.ndarray,
                              per_camera: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(len(rows), 3, 3) information (1/m^2) of the patches of samples `rows` summed over the
    patch's own surface points: C(X_n) = sum_i [i usable at n] sum_j o(n, j) [i usable at j] P_ij,
    with P_ij (`per_camera` (C, N, 3, 3): Omega w |det A| C_i of camera i at sample j, whole patch)
    the per-area information of cell j (its own normal, frame and view) times Omega, and o(n, j)
    the fraction of the patch on cell j (`patch_overlap`). On a plane with a uniform view this is
    the clipped model Omega phi_i w |det A_i| C_i; on a curved surface each cell keeps its own
    normal."""
    use = np.asarray(usable, dtype=bool)
    sub = overlap[rows]
    out = np.zeros((len(rows), 9))
    for i in range(use.shape[0]):
        if use[i, rows].any():
            out += use[i, rows, None] * (sub @ (use[i, :, None] * per_camera[i].reshape(-1, 9)))
    return out.reshape(-1, 3, 3)


def patch_fractions(overlap: scipy.sparse.csr_matrix, usable: np.ndarray) -> np.ndarray:
    """(C, N) phi_i(X_n): the fraction of the patch at sample n on cells that camera i sees
    usably, 0 where camera i is not a usable view of n itself (module docstring)."""
    usable = np.asarray(usable, dtype=bool)
    phi = np.asarray((overlap @ usable.T.astype(float)).T)
    return np.where(usable, np.minimum(phi, 1.0), 0.0)


def flags(overlap: scipy.sparse.csr_matrix, usable: np.ndarray, sigma_max: np.ndarray,
          measured: np.ndarray, region: np.ndarray) -> dict[str, np.ndarray]:
    """Per sample: ``coverage`` (int, usable views), ``patch_fraction`` phi_2 (the fraction of the
    patch usable by >= 2 views), ``edge_limited`` (phi_2 < EDGE_FRACTION) and ``outlier``
    (measured, sigma_max > OUTLIER_FACTOR x its region's median over measured samples)."""
    coverage = np.asarray(usable).sum(axis=0)
    phi2 = np.minimum(np.asarray(overlap @ (coverage >= 2).astype(float)), 1.0)
    phi2 = np.where(coverage >= 2, phi2, 0.0)
    outlier = np.zeros(len(sigma_max), dtype=bool)
    for r in np.unique(region):
        m = (region == r) & measured
        if m.any():
            outlier[m] = sigma_max[m] > OUTLIER_FACTOR * np.median(sigma_max[m])
    return {"coverage": coverage.astype(np.int32), "patch_fraction": phi2,
            "edge_limited": measured & (phi2 < EDGE_FRACTION), "outlier": outlier}
