"""Designing a layout from scratch: the selection of cameras from candidate poses (`vdo design`).

Candidates. Where a camera may stand (`spots`): every rail (a [[rail]] or a rail [[mount]]) at
`[design] rail_positions` positions evenly spread in u (plus `offset_m` from the bar to the
optical centre, and its mirror below the bar, z negated); every zone [[mount]] (a tripod's floor
area and height range) at a grid of `zone_points` values along x and y times `zone_heights`
heights (`zone_grid`); every fixed [[mount]]; and every [[camera]] given by `position_m` on no
mount. From each spot a candidate aims at each *target*: the centres of the regions' boxes
(clipped to their samples), merged when closer than MERGE_TARGETS_M; with `aim_offsets_deg` also
at pan and tilt +- each offset. Each pose carries each body kind of the inventory ([[body]]: its
sensor; or [design]'s one sensor) with each lens it takes. A candidate is dropped when its body
(`vdo.scene.camera_body_points`) comes closer than `[optimize] clearance_m` to a mesh.

One judgement of all candidates. The regions are sampled at `[design] sample_spacing_mm`
(coarser than [evaluation]'s; 20 mm by default). One ray cast (`vdo.physics.visibility`) over every
(candidate, sample) pair on the scene of the meshes alone (no camera bodies), the light reaching
the samples (`vdo.physics.lighting`), and then per candidate i and sample n the mean-field information
C_i(n) = Omega w_i |det A_i| C_i (3x3, 1/m^2, `vdo.objective.camera_information`; unclipped patch)
and the soft weight w_i(n) of the objective (incidence, image edge and occlusion). Over a load
path, the candidates are also ray cast at `[design] keyframes` of its steps
(`vdo.search.loadpath.keyframe_steps`: the path's extremes first), the samples and moving meshes posed
by `vdo.geometry.keyframes.at_step`, and C_i(n) and w_i(n) are zeroed where candidate i loses sample n at
any of them (`vdo.search.loadpath.path_occlusion`, the worst case over the keyframes, as `vdo optimize`
scores it). The candidates are judged in blocks of PAIRS_PER_BLOCK (candidate, sample) pairs
(`judge_block`; a block's dense arrays are freed before the next) and only the pairs with a
non-zero weight or information are kept, sparsely (`Candidates`): 6 float64 entries, 1 float32
weight and 1 int32 sample index per kept pair, 56 bytes (a camera sees a small part of a large
specimen). Candidates that see no sample at rest (blind) are dropped. Not float32: C_i has
rank 2 with its null vector along the ray, and float32 rounding of entries ~1e15 1/m^2 leaves
~1e8 along the ray, above the prior 1/prior_sigma^2 = 1e6 that alone fixes that direction for a
sample seen once (the regularised C turned indefinite and the score NaN).

Score. The information of a set S of cameras adds: C_S(n) = sum_{i in S} C_i(n), coverage
k_S(n) = sum_{i in S} w_i(n). The set is scored by the geometric mean of sigma, inflated by the
coverage deficit:

    score(S) = exp( sum_n omega_n ln(sigma_n / 1 um) + kappa P ) um,
    P = sum_n' a_n' h(max(0, k_region(n') - k_S(n'))) / sum_n' a_n',

sigma_n the smooth sigma_max of the regularised C_S (`vdo.objective`), omega = area x importance
over the scored regions ([optimize] regions, default all) normalised to sum 1, and the coverage
penalty P over EVERY region (a design must see the whole specimen, not only the scored part),
kappa = ln(prior_sigma / 1 um) = ln 1000 (`coverage_weight`), h the views missing at a sample
smoothed (`views_short`: Huber, linear beyond half a view, so that a second view counts about as
much as a first). Why not the optimizer's power mean
(q = 8, `vdo.objective.score`): a sample no camera pair measures sits at the prior's sigma (1 mm),
(1000 / 0.3)^8 ~ 1e28 times a measured sample's term, so while any sample of the specimen is
unmeasured (one that no candidate can measure, or the part an all-round layout cannot reach yet)
the power mean is flat in every measured sigma, to float64's last digit, and the selection only
adds views (the pressure vessel: 7 designed cameras at sigma p95 2.2-8x the hand layout's, 8 mm
lenses). In the logarithm every sample counts by its ratio: a second view of an area a (sigma from
1 mm to ~1 um: ln 1000 ~ 6.9, plus kappa from P) competes with halving sigma on ~20 a of
measured area (ln 2 each), and a sample that no selection can measure adds a constant. The score
is convex in (C_S, k_S) (`vdo.design.bound`).

With `[design] target_sigma_um` sigma_t, a sample above the target costs more, quadratically in
the logarithm of its excess:

    ln(sigma_n / 1 um)  ->  ln(sigma_n / 1 um) + kappa g(max(0, ln(sigma_n / sigma_t))),

g(x) = x^2 up to x = 1 and 2x - 1 beyond (`target_excess`), so that a region's worst samples are
no longer traded for typical ones (the geometric mean alone let the steel beam's 4-camera design
leave 30 % of one end at 2.3 um p95, against a 0.3 um target). The weight is the coverage
penalty's kappa: a sample at e times the target costs as much as one view missing there; the term
is 0 at or below the target, 3.3 at twice it. Beyond e times it grows linearly in ln sigma, so an
unmeasured sample (the prior's 1 mm) adds a bounded constant and the score's exponent stays finite
for any target. It is convex (a convex increasing function of ln sigma, itself convex in C_S), so
the score stays convex and the bound holds.

It is not submodular (one camera alone gains
nothing in sigma; pairs do), so lazy evaluation's bound does not hold: every step evaluates every
feasible candidate, which the sums make cheap (`Scorer.add`: the base's log-sum corrected at each
candidate's stored entries, one vectorised pass over them). `vdo design --refine` then minimises
the optimizer's own score (`vdo optimize`), which weighs the worst samples (q = 8).

Selection. Greedy forward selection adds the feasible candidate with the lowest score, then
exchange passes replace one selected camera by the best feasible candidate while that lowers the
score. Feasible with the selected set:
* the inventory: no more cameras of a body kind than its count;
* one camera per spot: no two optical centres closer than SPOT_M (a body and its clearance);
* axis angles: two cameras that share a region (each sees at least `[optimize]
  assign_fraction` of its area with usable weight, or the area of it both see usably is at least
  that fraction of the smaller area either sees: all-round regions, `Feasibility`) keep their optical axes at least `[optimize]
  min_axis_angle_deg` apart, by default `vdo.constraints.stereo_min_angle` of the shorter lens,
  and at most `[optimize]` or that region's `max_axis_angle_deg` where set;
* clearance from the meshes (above, per candidate);
* obscuration: no obstacle hides more than `[optimize] max_obscuration` of a region the
  candidate is assigned (the area fraction it would see on a scene of the specimen alone but not
  on the whole scene: a second ray cast).
Obscuration by other camera bodies and tripods is not judged during selection; the designed
layout is judged whole (bodies and tripods included) with `vdo.state.layout_state` at [evaluation]'s sample spacing, and with
every constraint check of `vdo optimize` (`vdo.optimize.layout_checks`, constraints.json).

How many cameras. The greedy order and exchange passes per count give the best layout for every
count from `[design] min_cameras` to the inventory; `pareto.csv` holds, per count, sigma_max p95
over the scored regions (the worst region's p95, at the selection spacing, camera bodies included)
and the area fraction seen by its region's min_cameras. With `target_sigma_um` the smallest count
that meets it with full coverage is reported.

The bound. Per count, `vdo.design.bound` relaxes the selection to weights in [0, 1] (body counts
and obscuration kept, pairwise rules dropped) and certifies a lower bound on the score of every
selection of that many cameras; `design.json` (curve, bound, gap_to_bound), pareto.csv, the console
and pareto.png give the gap 1 - bound / score ([design] bound_s seconds per count).

What no selection can fix is reported naming the region and what is missing (`problems`,
`shortfalls`): an inventory below its min_cameras, no candidate that sees it (at rest or over the
keyframes), fewer candidate spots seeing it than its min_cameras, a target sigma not reached, a
region the design leaves short of its min_cameras; the best layout is written all the same.
"""

from __future__ import annotations

import logging
import math
import os
import resource
import time
import uuid
from dataclasses import dataclass, field, replace

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from vdo.design import bound
from vdo.search import loadpath
from vdo import objective
from vdo.outputs import report
from vdo.physics import usable
from vdo.model.camera import Camera
from vdo.model.pose import look_at_angles
from vdo.config.experiment import BodySpec, CameraSpec, Experiment, inside_keep_out
from vdo.constraints import stereo_min_angle
from vdo.core.errors import ConfigError
from vdo.geometry import obstacles
from vdo.geometry.keyframes import at_step, load_path_of
from vdo.physics.lighting import illuminate
from vdo.optimize import OptimizeResult, layout_checks, optimize_layout
from vdo.physics.predict import samples_for_objective, settings, view_data
from vdo.core.configure import configure
from vdo.core.progress import bar
from vdo.scene import build_scene, camera_body_points, cameras_of
from vdo.state import Geometry, layout_state, prepare
from vdo.state import bodies as bodies_of
from vdo.physics.visibility import compute_visibility
from vdo.core.tolerances import LIMIT_SLACK, TINY

log = logging.getLogger(__name__)

MERGE_TARGETS_M = 0.2   # region centres closer than this share one aim point
SPOT_M = 0.2            # two optical centres closer than this are one physical spot
PAIRS_PER_BLOCK = 1_000_000  # (candidate, sample) pairs judged at once (dense arrays of one block)
ENTRY_CHUNK = 1 << 18        # stored entries per chunk of the score's sigma
ANGLE_TOL = LIMIT_SLACK       # rad: an axis angle this close to its limit meets it
TARGET_BEND = 1.0             # ln(sigma / target) where the target's term turns from square to linear
HARDWARE_CHUNK = 256          # candidates' hardware bounds tested against one camera's lines at once
PROBE = 64                   # candidates judged, evenly spread, to estimate the whole judgement
PROBE_WARM = 8               # of them judged first, untimed: their block compiles the programs
ENTRY_BYTES = 6 * 8 + 4 + 4  # one stored pair: 6 float64 information entries, float32 weight, int32 index
STORE_COPIES = 2             # the blocks' pairs and their concatenation coexist once, at the end of judging
PAIR_BYTES = 64              # working bytes per (candidate, sample) pair of a block: the ray casts'
#                              flags (whole scene, specimen alone, keyframes) and their float copies
CAMERA_BYTES = 1024          # a candidate's Camera, metadata and per-region rows (+ 9 bytes per region)
SEARCH_PASSES = 2            # exchange passes assumed per count: one that swaps, one that confirms
SHORT_SMOOTH = 0.5           # views: the coverage penalty is quadratic below this deficit, linear above (`views_short`)
GB = 1e9


@dataclass(frozen=True, eq=False)
class Candidates:
    """K candidate cameras judged on N samples, stored sparsely: candidate k's entries are
    `entries[indptr[k]:indptr[k + 1]]`, each a sample `index` (int32), the information `info`
    (E, 6) float64 1/m^2 (entries c00, c11, c22, c01, c02, c12 of Omega w |det A| C_i) and the
    soft weight `weight` (E,) float32 w; only pairs with a non-zero weight or information are
    stored (a candidate sees a small part of a large specimen). samples N; assigned (K, R) the
    regions each sees usably over at least assign_fraction of the area; mount (K,) names ("" for a
    [[camera]]'s own fixed position), kind (K,) "rail", "zone" or "fixed", u (K,) (rail; NaN
    otherwise), offset (K, 3) m from the rail point, body (K,) index into `bodies(exp)`, target
    (K,) index into `targets`; masked (K, R) the area fraction of each region's samples the
    candidate would see but an obstacle hides (its obscuration); path_lost (K,) the fraction of
    its usable samples at rest that the load path's keyframes take away; pruned: how many blind
    candidates (no sample in view at rest) were dropped."""

    cameras: tuple[Camera, ...]
    mount: tuple[str, ...]
    kind: tuple[str, ...]
    u: np.ndarray
    offset: np.ndarray
    body: np.ndarray
    target: np.ndarray
    targets: np.ndarray
    samples: int
    indptr: np.ndarray
    index: np.ndarray
    entry_info: np.ndarray
    entry_weight: np.ndarray
    assigned: np.ndarray
    masked: np.ndarray
    path_lost: np.ndarray
    pruned: int = 0
    dropped: dict = field(default_factory=dict)   # {mount: {reason: count}} of the poses left out

    @property
    def positions(self) -> np.ndarray:
        return np.array([c.position for c in self.cameras]).reshape(-1, 3)

    @property
    def axes(self) -> np.ndarray:
        return np.array([c.optical_axis for c in self.cameras]).reshape(-1, 3)

    @property
    def row(self) -> np.ndarray:
        """(E,) the candidate of each stored entry."""
        return np.repeat(np.arange(len(self.cameras)), np.diff(self.indptr))

    def information(self, rows) -> np.ndarray:
        """Dense (len(rows), N, 6) information of the candidates `rows` (zero where not stored)."""
        rows = np.atleast_1d(np.asarray(rows, dtype=int))
        out = np.zeros((len(rows), self.samples, 6))
        for k, i in enumerate(rows):
            s = slice(self.indptr[i], self.indptr[i + 1])
            out[k, self.index[s]] = self.entry_info[s]
        return out

    def weights(self, rows) -> np.ndarray:
        """Dense (len(rows), N) float32 soft weights of the candidates `rows`."""
        rows = np.atleast_1d(np.asarray(rows, dtype=int))
        out = np.zeros((len(rows), self.samples), np.float32)
        for k, i in enumerate(rows):
            s = slice(self.indptr[i], self.indptr[i + 1])
            out[k, self.index[s]] = self.entry_weight[s]
        return out

    @property
    def info(self) -> np.ndarray:
        """Dense (K, N, 6): every candidate's information (for small problems and tests; K x N x
        48 bytes)."""
        return self.information(range(len(self.cameras)))

    @property
    def weight(self) -> np.ndarray:
        """Dense (K, N) float32 soft weights (for small problems and tests)."""
        return self.weights(range(len(self.cameras)))

    def sums(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """(N, 6) information and (N,) weights summed over the candidates `rows`."""
        info, cover = np.zeros((self.samples, 6)), np.zeros(self.samples)
        for i in rows:
            s = slice(self.indptr[i], self.indptr[i + 1])
            info[self.index[s]] += self.entry_info[s]
            cover[self.index[s]] += self.entry_weight[s]
        return info, cover

    def usable_counts(self) -> np.ndarray:
        """(K,) how many samples each candidate sees usably (w >= USABLE_WEIGHT)."""
        use = usable.usable_views(self.entry_weight)
        return np.bincount(self.row[use], minlength=len(self.cameras))


def bodies(exp: Experiment) -> tuple[BodySpec, ...]:
    """The inventory's body kinds: the [[body]] tables, or one kind of [design]'s sensor (else
    the first [[camera]]'s) counted `inventory(exp)` times."""
    if exp.bodies:
        return exp.bodies
    d = exp.design
    width, pixels = ((d.sensor_width, d.pixels) if d.sensor_width is not None else
                     (exp.camera_specs[0].sensor_width, exp.camera_specs[0].pixels))
    return (BodySpec(name="body", sensor_width=width, pixels=tuple(pixels), count=inventory(exp),
                     lenses=()),)


def lenses(exp: Experiment, body: BodySpec | None = None) -> tuple[float, ...]:
    """The lens catalogue (m) of a body: its lenses_mm, else [design] lenses_mm, else the focal
    lengths of the [[camera]]s; without a body, every lens of every body."""
    if body is None:
        return tuple(sorted({f for b in bodies(exp) for f in lenses(exp, b)}))
    return body.lenses or exp.design.lenses or tuple(sorted({c.focal_length for c in exp.camera_specs}))


def inventory(exp: Experiment) -> int:
    """How many cameras may be placed: [design] max_cameras, else the [[body]] counts, else the
    [[camera]] count."""
    return exp.design.max_cameras or (sum(b.count for b in exp.bodies) if exp.bodies
                                      else len(exp.camera_specs))


def targets(samples) -> np.ndarray:
    """(T, 3) aim points: each region's sample centroid (area-weighted), merged greedily when
    closer than MERGE_TARGETS_M (the merged point is the area-weighted mean)."""
    out, weights = [], []
    for r in range(len(samples.region_names)):
        mask = samples.region == r
        if not mask.any():
            continue
        a = samples.area[mask]
        c = (samples.points[mask] * a[:, None]).sum(0) / a.sum()
        for k, t in enumerate(out):
            if np.linalg.norm(t - c) < MERGE_TARGETS_M:
                out[k] = (t * weights[k] + c * a.sum()) / (weights[k] + a.sum())
                weights[k] += a.sum()
                break
        else:
            out.append(c)
            weights.append(a.sum())
    return np.array(out)


def mesh_points(meshes, spacing: float = 0.01) -> np.ndarray:
    """Points on every mesh surface, at most `spacing` apart along each triangle's edges
    (vertices, and a barycentric grid per triangle), for clearance by nearest neighbour."""
    out = []
    for m in meshes:
        tri = m.vertices[m.faces]                       # (F, 3, 3)
        edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max(axis=1)
        for k in np.unique(np.ceil(edge / spacing).astype(int).clip(1, 400)):
            sel = tri[np.ceil(edge / spacing).astype(int).clip(1, 400) == k]
            i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
            keep = i + j <= k
            b = np.c_[i[keep], j[keep]] / k
            w = np.c_[1 - b.sum(1), b]                  # (G, 3)
            out.append(np.einsum("gk,fkd->fgd", w, sel).reshape(-1, 3))
    return np.vstack(out)


def zone_grid(zone, per_axis: int, heights: int) -> np.ndarray:
    """(P, 3) candidate optical centres (m) in a zone [[mount]]: `per_axis` evenly spaced values
    along x and along y (edges included; one, the middle, where the extent is zero) times `heights`
    values over its height range; over a floor polygon, the points of that grid on its bounding box
    that lie on the polygon (off its holes), and its centroid when that does."""
    lo, hi = zone.low, zone.high
    axes = [np.linspace(lo[k], hi[k], per_axis) if hi[k] > lo[k] and per_axis > 1
            else np.array([(lo[k] + hi[k]) / 2]) for k in range(2)]
    axes.append(np.linspace(lo[2], hi[2], heights) if hi[2] > lo[2] and heights > 1
                else np.array([(lo[2] + hi[2]) / 2]))
    xy = np.stack(np.meshgrid(axes[0], axes[1], indexing="ij"), -1).reshape(-1, 2)
    if zone.floor is not None:
        xy = xy[zone.inside(xy)]
        centre = zone.floor.mean(axis=0)
        xy = np.vstack([xy, centre]) if zone.inside(centre) else xy
    return np.array([[x, y, z] for x, y in xy for z in axes[2]])


def spots(exp: Experiment) -> list[tuple]:
    """Where candidates stand: (mount name, kind, u, offset (3,), optical centre (3,)) for
    `rail_positions` values of u on every rail (with `offset_m`, and its mirror below the bar),
    the `zone_grid` of every zone mount, every fixed mount, and every [[camera]] given by
    position_m on no mount."""
    d = exp.design
    heads = [d.offset] + ([d.offset * [1, 1, -1]] if d.offset[2] != 0 else [])
    grid = np.linspace(0, 1, d.rail_positions) if d.rail_positions > 1 else [0.5]
    out = [(r.name, "rail", float(u), h, exp.rail(r.name).point(u) + h)
           for r in exp.rails for u in grid for h in heads]
    zero = np.zeros(3)
    for m in exp.mounts:
        points = zone_grid(m, d.zone_points, d.zone_heights) if m.kind == "zone" else [m.position]
        out += [(m.name, m.kind, math.nan, zero, np.asarray(p, dtype=float)) for p in points]
    out += [("", "fixed", math.nan, zero, np.asarray(c.position, dtype=float))
            for c in exp.camera_specs if c.position is not None and c.mount is None]
    return out


def candidate_cameras(exp: Experiment, samples, meshes) -> tuple:
    """The candidate poses (module docstring) that keep their clearance: (cameras, mount names,
    kinds, u, offsets, body index, target index, targets, dropped), dropped = {mount: {reason:
    count}} of the candidate poses (positions, for a keep-out) left out and why."""
    aims = targets(samples)
    offsets = [(0.0, 0.0)] + [(s * a, t * a) for a in exp.design.aim_offsets for s, t in
                              ((1, 0), (-1, 0), (0, 1), (0, -1))]
    cams, rows, points = [], [], []
    kept_out: dict[str, int] = {}
    for mount, kind, u, head, p in spots(exp):
        box = int(inside_keep_out(exp.keep_outs, p)[0])
        if box >= 0:
            key = (mount or "fixed", f"positions in keep_out {exp.keep_outs[box].name!r}")
            kept_out[key] = kept_out.get(key, 0) + 1
            continue
        for t, aim in enumerate(aims):
            if np.linalg.norm(aim - p) < 1e-6:
                continue
            pan0, tilt0 = look_at_angles(p, aim)
            for dp, dt in offsets:
                for b, body in enumerate(bodies(exp)):
                    W, H = body.pixels
                    for f in lenses(exp, body):
                        c = Camera(name=f"c{len(cams)}", width=W, height=H,
                                   pixel_size=body.sensor_width / W, focal_length=f, position=p,
                                   pan=pan0 + dp, tilt=tilt0 + dt)
                        cams.append(c)
                        rows.append((mount, kind, u, head, b, t))
                        points.append(camera_body_points(f) @ c.R + p)     # x_w = R^T x_c + C
    if cams:   # one query, pruned at the clearance (an unbounded query from far away is slow)
        gap = cKDTree(mesh_points(meshes)).query(np.concatenate(points),
                                                 distance_upper_bound=exp.optimize.clearance)[0]
        clear = (gap.reshape(len(cams), -1) >= exp.optimize.clearance).all(axis=1)
        for name in dict.fromkeys(r[0] for r in rows):
            of = np.array([r[0] == name for r in rows])
            log.info("mount %s: %d candidate poses, %d dropped for clearance (closer than %g m to a "
                     "mesh)", name or "fixed", of.sum(), (of & ~clear).sum(), exp.optimize.clearance)
            if (of & ~clear).any():
                kept_out[(name or "fixed", "poses within the clearance")] = int((of & ~clear).sum())
        cams = [c for c, ok in zip(cams, clear) if ok]
        rows = [r for r, ok in zip(rows, clear) if ok]
    dropped: dict = {}
    for (name, reason), count in kept_out.items():
        dropped.setdefault(name, {})[reason] = count
        if "keep_out" in reason:
            log.info("mount %s: %d candidate %s dropped", name, count, reason)
    mount, kind, u, head, b, t = zip(*rows) if rows else ((),) * 6
    return (cams, tuple(mount), tuple(kind), np.array(u, dtype=float),
            np.array(head, dtype=float).reshape(-1, 3), np.array(b, dtype=int),
            np.array(t, dtype=int), aims, dropped)


@dataclass(frozen=True, eq=False)
class Judging:
    """What judging any block of candidates needs, built once per process (`judging`): the
    experiment, the selection geometry, the candidates (`candidate_cameras`: cameras, mount names,
    kinds, u, offsets, bodies, targets, aim points), the scene of the meshes and of the specimen
    alone, the load path's keyframe steps with each step's moved samples and scene, the light on
    the samples, the objective's samples and settings (pair terms in float64), and the (N, R)
    sparse matrix of sample areas per region."""

    exp: Experiment
    geometry: Geometry
    cams: tuple
    mount: tuple
    kind: tuple
    u: np.ndarray
    heads: np.ndarray
    body: np.ndarray
    target: np.ndarray
    aims: np.ndarray
    scene: object
    bare: object
    steps: tuple
    moved: tuple
    light: object
    smp: object
    settings: object
    region_area: object
    dropped: dict   # {mount: {reason: count}} of the poses `candidate_cameras` left out


def judging(exp: Experiment, geometry: Geometry) -> Judging:
    """The `Judging` of `exp`'s candidates on `geometry` (ray-cast scenes built, keyframes moved)."""
    samples = geometry.samples
    cams, mount, kind, u, heads, body, tg, aims, dropped = candidate_cameras(exp, samples, geometry.meshes)
    scene = build_scene(list(geometry.meshes))
    bare = build_scene([m for m in geometry.meshes if m.role == "specimen"])
    path = load_path_of(exp, list(geometry.meshes))
    steps = () if path is None else loadpath.keyframe_steps(path, exp.design.keyframes)
    moved = []
    for step in steps:      # as `vdo.search.loadpath.path_occlusion`: every keyframe, meshes moved
        g = at_step(geometry, path, step)
        moved.append((g.samples, build_scene(list(g.meshes) + bodies_of(exp, []))))
    light = illuminate(scene, exp.lights, samples, exp.render.ambient_radiance)
    R = len(samples.region_names)
    region_area = scipy.sparse.csr_matrix((samples.area, (np.arange(len(samples)), samples.region)),
                                          shape=(len(samples), R))
    return Judging(exp, geometry, tuple(cams), mount, kind, u, heads, body, tg, aims, scene, bare,
                   steps, tuple(moved), light, samples_for_objective(exp, samples),
                   replace(settings(exp), pair_dtype="float64"), region_area, dropped)


@dataclass(frozen=True, eq=False)
class Block:
    """The judgement of candidates [start, stop) (`judge_block`): per candidate the number of
    stored entries (counts), the entries (sample index int32, info (E, 6), weight (E,) float32,
    candidate by candidate, samples ascending), assigned and masked (B, R), path_lost (B,), and
    seen (B,) whether it has any entry at rest (before the load path)."""

    start: int
    counts: np.ndarray
    index: np.ndarray
    info: np.ndarray
    weight: np.ndarray
    assigned: np.ndarray
    masked: np.ndarray
    path_lost: np.ndarray
    seen: np.ndarray


def judge_block(j: Judging, start: int, stop: int) -> Block:
    """Candidates [start, stop) of `j` judged on every sample (module docstring): one ray cast on
    the whole scene, one on the specimen alone (obscuration), one per load-path keyframe; the
    information and weights of the objective; then only the non-zero pairs kept."""
    exp, samples = j.exp, j.geometry.samples
    cams = list(j.cams[start:stop])
    limit = exp.evaluation.incidence_limit
    vis = compute_visibility(j.scene, cams, samples, limit, progress=False)
    bare = compute_visibility(j.bare, cams, samples, limit, progress=False).visible
    hidden = bare & ~vis.visible
    cp = objective.CameraParams.from_cameras(cams)
    views = view_data(exp, j.smp, vis, j.light, j.geometry.speckle)
    cam, index, info, w = objective.pair_information(cp, views, j.geometry.speckle.table, j.settings)
    order = np.lexsort((index, cam))                      # candidate by candidate, samples ascending
    cam, index, info, weight = cam[order], index[order], info[order], w[order].astype(np.float32)
    kept = (weight != 0) | (info != 0).any(axis=-1)
    B, N, R = len(cams), len(samples), len(samples.region_names)
    seen = np.bincount(cam[kept], minlength=B) > 0
    at_rest = np.bincount(cam, usable.usable_views(weight), minlength=B)
    if j.steps:
        on_path = np.ones((B, N), bool)
        for moved_samples, scene in j.moved:
            on_path &= compute_visibility(scene, cams, moved_samples, limit, progress=False).visible
        on = on_path[cam, index]
        info *= on[:, None]
        weight *= on
    use = usable.usable_views(weight)
    lost = 1 - np.bincount(cam, use, minlength=B) / np.maximum(at_rest, 1)
    area = np.asarray(j.region_area.sum(axis=0)).ravel()
    region = samples.region[index]
    seen_area = np.bincount(cam * R + region, samples.area[index] * use, minlength=B * R).reshape(B, R)
    assigned = seen_area / np.maximum(area, TINY) >= exp.optimize.assign_fraction
    masked = (j.region_area.T @ hidden.T.astype(float)).T / np.maximum(
        (j.region_area.T @ bare.T.astype(float)).T, TINY)
    keep = (weight != 0) | (info != 0).any(axis=-1)
    return Block(start, np.bincount(cam[keep], minlength=B), index[keep].astype(np.int32), info[keep],
                 weight[keep], assigned, masked, lost, seen)


def block_size(samples: int) -> int:
    """Candidates per block: PAIRS_PER_BLOCK pairs (at least one candidate)."""
    return max(1, PAIRS_PER_BLOCK // max(samples, 1))


def collect(j: Judging, blocks: list[Block]) -> Candidates:
    """The `Candidates` of `j` from its blocks (in any order), blind candidates (no sample in view
    at rest) dropped."""
    blocks = sorted(blocks, key=lambda b: b.start)
    R = len(j.geometry.samples.region_names)
    cat = (lambda f, empty: np.concatenate([f(b) for b in blocks]) if blocks else empty)
    seen = cat(lambda b: b.seen, np.zeros(0, bool))
    counts = cat(lambda b: b.counts, np.zeros(0, int))
    keep = np.flatnonzero(seen)
    pick = lambda seq: tuple(seq[i] for i in keep)                        # noqa: E731
    return Candidates(
        pick(j.cams), pick(j.mount), pick(j.kind), j.u[keep], j.heads[keep], j.body[keep],
        j.target[keep], j.aims, len(j.geometry.samples),
        np.concatenate([[0], np.cumsum(counts[keep])]).astype(np.int64),
        cat(lambda b: b.index, np.zeros(0, np.int32)), cat(lambda b: b.info, np.zeros((0, 6))),
        cat(lambda b: b.weight, np.zeros(0, np.float32)),
        cat(lambda b: b.assigned, np.zeros((0, R), bool))[keep],
        cat(lambda b: b.masked, np.zeros((0, R)))[keep], cat(lambda b: b.path_lost, np.zeros(0))[keep],
        pruned=int(len(seen) - len(keep)), dropped=j.dropped)


_WORKER: dict = {}   # a Dask worker's Judging, built at its first block of a design run


def remote_block(exp: Experiment, token: str, start: int, stop: int, threads: int | None) -> Block:
    """`judge_block` on a Dask worker: the worker configures itself (`vdo.core.configure`, with
    `threads` Dr.Jit threads) and builds the run's `Judging` (selection samples at [design]
    sample_spacing_mm, candidates, scenes) at its first block of the run `token`, then keeps it.
    The candidate list is deterministic, so every worker's list is the caller's."""
    if _WORKER.get("token") != token:
        configure(threads=threads)
        _WORKER.clear()
        spacing = exp.design.sample_spacing
        geometry = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=spacing)))
        _WORKER.update(token=token, judging=judging(exp, geometry))
    return judge_block(_WORKER["judging"], start, stop)


def judge(exp: Experiment, geometry: Geometry, j: Judging | None = None, client=None,
          threads: int | None = None) -> Candidates:
    """Every candidate's information and weights on `geometry`'s samples (module docstring), in
    blocks of `block_size` candidates, stored sparsely; with progress bars when the module logger
    passes INFO (`vdo.core.progress`). With a dask.distributed `client`, the blocks are tasks on
    its workers (`remote_block`; `geometry` must then be `exp` sampled at [design]
    sample_spacing_mm, as `design` does) and come back in any order: the same result."""
    j = judging(exp, geometry) if j is None else j
    size = block_size(len(geometry.samples))
    starts = range(0, len(j.cams), size)
    if client is None:
        blocks = [judge_block(j, s, min(s + size, len(j.cams)))
                  for s in bar(log, iterable=starts, desc="candidates", unit="block", leave=False)]
    else:
        from distributed import as_completed

        token = uuid.uuid4().hex
        shared = client.scatter(exp, broadcast=True)
        futures = [client.submit(remote_block, shared, token, s, min(s + size, len(j.cams)), threads,
                                 key=f"vdo-design-{token}-{s}", pure=False) for s in starts]
        blocks = [f.result() for f in bar(log, iterable=as_completed(futures), total=len(futures),
                                          desc="candidates (dask)", unit="block", leave=False)]
    log.info("load path: %d keyframe(s) %s judged for the candidates' occlusion", len(j.steps), j.steps)
    return collect(j, blocks)


class Scorer:
    """score(S) of the module docstring for sums of candidates' information and weights:

        score(S) = exp( sum_n omega_n c(sigma_n) + kappa P ) sigma_unit,

    omega_n normalised to sum 1. Adding one candidate changes only the samples it sees, so each
    candidate's score is the base set's sums corrected at its stored entries,

        score(S + k) = exp( L + sum_{n in k} omega_n [c(sigma'_n) - c(sigma_n)]
                            + kappa (H + sum_{n in k} [h'_n - h_n]) ) sigma_unit,

    c(sigma) = ln(sigma / sigma_unit) (plus the target term of the module docstring, `cost`),
    L = sum_n omega_n c(sigma_n), h_n = a_n h(max(0, k_region(n) - k_S(n))) (`views_short`), H their
    sum and the primes after the addition: each correction is a difference of logarithms at one
    sample (no cancellation against the whole sum), and the cost follows the stored entries, not
    candidates x samples."""

    def __init__(self, exp: Experiment, samples):
        st = settings(exp)
        scored = np.ones(len(samples.region_names), bool) if exp.optimize.regions is None else \
            np.isin(samples.region_names, exp.optimize.regions)
        omega = samples.area * samples.region_importance[samples.region] * scored[samples.region]
        minimum = np.array([r.min_cameras for r in exp.regions])
        self.settings = st
        self.omega = omega / omega.sum()
        self.area = samples.area / samples.area.sum()
        self.minimum = minimum[samples.region].astype(float)
        self.kappa = coverage_weight(st)
        target = exp.design.target_sigma_um
        self.log_target = None if target is None else math.log(target * 1e-6 / st.sigma_unit)
        self._sigma = jax.jit(lambda e: objective._smooth_sigma_max(tuple(e[:, k] for k in range(6)), st)
                              / st.sigma_unit)
        self._omega, self._area, self._minimum = (jnp.asarray(x) for x in (self.omega, self.area,
                                                                           self.minimum))
        self._terms = jax.jit(self._entry_terms)

    def sigma(self, info: np.ndarray) -> np.ndarray:
        """(M,) smooth sigma_max / sigma_unit of (M, 6) information, in chunks of ENTRY_CHUNK
        (the last one padded, so one compiled size)."""
        out = np.empty(len(info))
        for s in range(0, len(info), ENTRY_CHUNK):
            part = info[s:s + ENTRY_CHUNK]
            size = ENTRY_CHUNK if len(info) > ENTRY_CHUNK else 1 << max(len(part) - 1, 1).bit_length()
            pad = np.zeros((size, 6))
            pad[:len(part)] = part
            out[s:s + len(part)] = np.asarray(self._sigma(jnp.asarray(pad)))[:len(part)]
        return out

    def cost(self, log_sigma, xp):
        """A sample's term: ln(sigma / 1 um), plus kappa g(max(0, ln(sigma / sigma_t))) with a
        target (module docstring); xp: numpy or jax.numpy."""
        if self.log_target is None:
            return log_sigma
        return log_sigma + self.kappa * target_excess(xp.maximum(log_sigma - self.log_target, 0.0), xp)

    def value(self, info, cover):
        """The score of summed information info (N, 6) float64 1/m^2 and coverage cover (N,): a
        traceable JAX function, convex in both (`vdo.design.bound`); `_score` on the host."""
        st = self.settings
        sigma = objective._smooth_sigma_max(tuple(info[:, k] for k in range(6)), st) / st.sigma_unit
        short = jnp.maximum(self._minimum - cover, 0.0)
        return jnp.exp(jnp.sum(self._omega * self.cost(jnp.log(sigma), jnp))
                       + self.kappa * jnp.sum(self._area * views_short(short, jnp)))

    def _score(self, sigma, cover) -> float:
        short = np.maximum(self.minimum - cover, 0.0)
        return float(np.exp(np.sum(self.omega * self.cost(np.log(sigma), np))
                            + self.kappa * np.sum(self.area * views_short(short, np))))

    def _entry_terms(self, index, info, weight, base_info, base_cover, base_cost, h):
        """Per entry (one chunk, jitted): omega_n (c(sigma'_n) - c(sigma_n)) after adding the
        entry's information to the base at its sample n (c = `cost`), and h'_n - h_n (class
        docstring)."""
        st = self.settings
        sig = objective._smooth_sigma_max(tuple(base_info[index, k] + info[:, k] for k in range(6)),
                                          st) / st.sigma_unit
        short = jnp.maximum(self._minimum[index] - (base_cover[index] + weight), 0.0)
        return self._omega[index] * (self.cost(jnp.log(sig), jnp) - base_cost[index]), \
            self._area[index] * views_short(short, jnp) - h[index]

    def add(self, base_info, base_cover, cand: Candidates, rows) -> np.ndarray:
        """Scores of base + each candidate of `rows`: base (N, 6), (N,)."""
        rows = np.asarray(rows, dtype=int)
        if rows.size == 0:
            return np.zeros(0)
        cost = self.cost(np.log(self.sigma(base_info)), np)
        short = np.maximum(self.minimum - base_cover, 0.0)
        h = self.area * views_short(short, np)
        base = tuple(jnp.asarray(x) for x in (base_info, base_cover, cost, h))
        dl, dh = np.zeros(len(rows)), np.zeros(len(rows))
        # the stored entries of `rows`, row after row, ENTRY_CHUNK at a time: every per-entry
        # array lives for one chunk (the stored pairs are the only thing as large as all of them)
        ends = np.cumsum(cand.indptr[rows + 1] - cand.indptr[rows])
        total = int(ends[-1])
        for s in range(0, total, ENTRY_CHUNK):
            pos = np.arange(s, min(s + ENTRY_CHUNK, total))
            owner = np.searchsorted(ends, pos, side="right")
            e = cand.indptr[rows[owner]] + pos - (ends[owner] - (cand.indptr[rows + 1] - cand.indptr[rows])[owner])
            m = len(e)
            pad = lambda x: np.concatenate([x, np.zeros((ENTRY_CHUNK - m,) + x.shape[1:], x.dtype)])  # noqa: E731
            a, b = self._terms(jnp.asarray(pad(cand.index[e])), jnp.asarray(pad(cand.entry_info[e])),
                               jnp.asarray(pad(cand.entry_weight[e].astype(float))), *base)
            dl += np.bincount(owner, np.asarray(a)[:m], minlength=len(rows))
            dh += np.bincount(owner, np.asarray(b)[:m], minlength=len(rows))
        return np.exp(np.sum(self.omega * cost) + dl + self.kappa * (h.sum() + dh))

    def of(self, cand: Candidates, chosen) -> float:
        info, cover = cand.sums(list(chosen))
        return self._score(self.sigma(info), cover)


def views_short(short, xp):
    """The coverage penalty's cost of `short` views missing at a sample (module docstring): the
    Huber function, s^2 / (2 SHORT_SMOOTH) up to SHORT_SMOOTH views, s - SHORT_SMOOTH / 2 beyond:
    convex and smooth (the bound's gradient steps), and as linear as that allows, so that a
    sample's second view lowers it about as much as its first (a squared deficit rewarded the
    first view three times the second and spread two cameras over disjoint views). xp: numpy or
    jax.numpy."""
    return xp.where(short > SHORT_SMOOTH, short - SHORT_SMOOTH / 2, short * short / (2 * SHORT_SMOOTH))


def target_excess(x, xp):
    """g(x) of the target's term (module docstring) for x = max(0, ln(sigma / sigma_t)) >= 0: x^2
    up to TARGET_BEND and linear beyond (slope 2 TARGET_BEND): convex, increasing, smooth."""
    return xp.where(x > TARGET_BEND, 2 * TARGET_BEND * x - TARGET_BEND ** 2, x * x)


def coverage_weight(st: objective.Settings) -> float:
    """kappa of the score (module docstring): ln(prior_sigma / sigma_unit), so that a sample's
    whole area one camera short of its region's min_cameras raises the score's logarithm as much
    as a sample of the same weight going from a 1 um to an unmeasured sigma (the prior, 1 mm)."""
    return math.log(st.prior_sigma / st.sigma_unit)


def min_angles(exp: Experiment, cand: Candidates, j: int) -> np.ndarray:
    """(K,) minimum axis angle (rad) of candidate j with each candidate: [optimize]
    min_axis_angle_deg or the stereo rule of thumb for the shorter lens
    (`vdo.constraints.stereo_min_angle`)."""
    f = np.array([c.focal_length for c in cand.cameras])
    if exp.optimize.min_axis_angle is not None:
        return np.full(len(f), exp.optimize.min_axis_angle)
    lens = np.unique(f)
    rule = np.array([stereo_min_angle(x) for x in lens])
    return rule[np.searchsorted(lens, np.minimum(f, f[j]))]


class Feasibility:
    """Which candidates may join a selected set: no obstacle hides more than [optimize]
    max_obscuration of a region the candidate is assigned; one per spot; the minimum axis angle
    between cameras sharing a region (module docstring) and the maximum where one is set ([optimize]
    max_axis_angle_deg for every pair sharing a region, a region's max_axis_angle_deg for the
    pairs sharing that region). Two candidates share a region when both are assigned it or, with
    the `samples` the candidates were judged on, when the area of it that both see usably is at
    least [optimize] assign_fraction of the smaller area either sees (`vdo.constraints.sharing`'s
    rule: around a closed surface no candidate is assigned it, yet neighbours see the same part).
    With the `samples`, two candidates also conflict when one's hardware (body, and tripod on a
    zone with a [mount.tripod]; `vdo.geometry.obstacles`) hides more than [optimize]
    max_obscuration of the area of a region the other is assigned that the other sees usably (a
    camera on a tripod in front of another's lens). A candidate's conflicts with all others (K,)
    are found when it is first selected and kept (never a K x K matrix)."""

    def __init__(self, exp: Experiment, cand: Candidates, samples=None):
        self.exp, self.cand = exp, cand
        self._seen = self._region_area = self._alone = self._sight = None
        if samples is not None:       # (K, N) usable views; (N, R) sample areas; (K, R) area seen
            use = usable.usable_views(cand.entry_weight)
            # the usable entries as sight lines: candidate, sample, its area (`hides`)
            self._sight = (cand.row[use], cand.index[use], samples.area[cand.index[use]])
            self._seen = scipy.sparse.csr_matrix(
                (np.ones(int(use.sum())), self._sight[:2]), shape=(len(cand.cameras), cand.samples))
            self._region_area = scipy.sparse.csr_matrix(
                (samples.area, (np.arange(len(samples)), samples.region)),
                shape=(len(samples), len(samples.region_names)))
            self._alone = (self._seen @ self._region_area).toarray()
        self.positions, self.axes = cand.positions, cand.axes
        self.limited = [(r, spec.max_axis_angle) for r, spec in enumerate(exp.regions)
                        if spec.max_axis_angle is not None]
        self.alone = ~(cand.assigned & (cand.masked > exp.optimize.max_obscuration)).any(axis=1)
        self.body = cand.body
        self.counts = np.array([b.count for b in bodies(exp)])
        self._rows: dict[int, np.ndarray] = {}
        self._samples = samples
        self._tripods = {m.name: m.tripod for m in exp.mounts}     # rails stand on no tripod
        self._hardware: dict[int, obstacles.Hardware] = {}
        self._bounds = None   # every candidate's hardware bounding sphere: (centres (K, 3), radii (K,))

    def row(self, j: int) -> np.ndarray:
        """(K,) True where a candidate conflicts with candidate j."""
        if j not in self._rows:
            cand, opt = self.cand, self.exp.optimize
            exclusive = np.linalg.norm(self.positions - self.positions[j], axis=1) < SPOT_M
            shared = self.shared(j)
            share = shared.any(axis=1)
            angle = np.arccos(np.clip(self.axes @ self.axes[j], -1, 1))
            conflict = exclusive | (share & (angle < min_angles(self.exp, cand, j) - ANGLE_TOL))
            if opt.max_axis_angle is not None:
                conflict |= share & (angle > opt.max_axis_angle + ANGLE_TOL)
            for r, top in self.limited:
                conflict |= shared[:, r] & (angle > top + ANGLE_TOL)
            if self._samples is not None:
                conflict |= self.hides(j)
            self._rows[j] = conflict
        return self._rows[j]

    def hardware(self, k: int) -> obstacles.Hardware:
        """Candidate k's body and tripod (`vdo.geometry.obstacles.hardware`)."""
        if k not in self._hardware:
            self._hardware[k] = obstacles.hardware(self.cand.cameras[k], self._tripods.get(self.cand.mount[k]))
        return self._hardware[k]

    def hides(self, j: int) -> np.ndarray:
        """(K,) True where candidate j's hardware hides more than max_obscuration of an assigned
        region's usable area from a candidate, or that candidate's hardware hides as much from j
        (class docstring)."""
        cand, smp, limit = self.cand, self._samples, self.exp.optimize.max_obscuration
        K, R = cand.assigned.shape
        rows, index, area = self._sight
        # j's hardware in front of every other candidate's lines of sight
        lost = obstacles.hidden(self.positions[rows], smp.points[index], self.hardware(j)) & (rows != j)
        hidden = np.bincount(rows[lost] * R + smp.region[index[lost]], weights=area[lost],
                             minlength=K * R).reshape(K, R)
        frac = hidden / np.maximum(self._alone, TINY)
        out = (cand.assigned & (frac > limit)).any(axis=1)
        # every other candidate's hardware in front of j's lines of sight
        mine = rows == j
        lines = (self.positions[j], smp.points[index[mine]])
        seen = np.bincount(smp.region[index[mine]], weights=area[mine], minlength=R)
        mine_assigned = cand.assigned[j]
        if self._bounds is None:
            every = [self.hardware(k) for k in range(K)]
            self._bounds = (np.array([h.bound_centre for h in every]), np.array([h.bound_radius for h in every]))
        near = np.zeros(K, dtype=bool)
        for lo in range(0, K, HARDWARE_CHUNK):   # (chunk, lines) distances from each bounding centre
            centre, radius = (b[lo:lo + HARDWARE_CHUNK] for b in self._bounds)
            d = obstacles.point_segment_distance(centre[:, None], lines[0], lines[1][None])
            near[lo:lo + HARDWARE_CHUNK] = (d < radius[:, None]).any(axis=1) if d.size else False
        for k in np.flatnonzero(near & ~out):
            if k == j:
                continue
            lost = obstacles.hidden(np.broadcast_to(lines[0], lines[1].shape), lines[1], self.hardware(k))
            if lost.any():
                part = np.bincount(smp.region[index[mine]][lost], weights=area[mine][lost], minlength=R)
                out[k] = bool((mine_assigned & (part > limit * np.maximum(seen, TINY))).any())
        return out

    def shared(self, j: int) -> np.ndarray:
        """(K, R) True where a candidate shares region r with candidate j (class docstring)."""
        out = self.cand.assigned & self.cand.assigned[j]
        if self._seen is None:
            return out
        mine = np.asarray(self._seen[j].todense()).ravel()
        common = (self._seen @ self._region_area.multiply(mine[:, None]).tocsr()).toarray()
        smaller = np.minimum(self._alone, self._alone[j])
        return out | ((smaller > 0) & (common >= self.exp.optimize.assign_fraction * smaller))

    def conflicts(self, i: int, j: int) -> bool:
        return bool(self.row(j)[i])

    def allowed(self, chosen) -> np.ndarray:
        """(K,) True for the candidates compatible with every camera in `chosen` and whose body
        kind is not used up by `chosen`."""
        ok = self.alone.copy()
        for j in chosen:
            ok &= ~self.row(j)
        used = np.bincount(self.body[list(chosen)], minlength=len(self.counts))
        return ok & (used < self.counts)[self.body]


def greedy(cand: Candidates, scorer: Scorer, feas: Feasibility, n: int,
           start=()) -> tuple[list[int], list[float]]:
    """Forward selection up to n cameras from `start`: the chosen indices and the score after
    each addition (stops early when no feasible candidate is left); a progress bar when the module
    logger passes INFO."""
    chosen, scores = list(start), []
    for _ in bar(log, iterable=range(n - len(chosen)), desc="greedy", leave=False):
        ok = np.flatnonzero(feas.allowed(chosen))
        if ok.size == 0:
            break
        s = scorer.add(*cand.sums(chosen), cand, ok)
        best = int(np.argmin(s))
        chosen.append(int(ok[best]))
        scores.append(float(s[best]))
    return chosen, scores


def exchange(cand: Candidates, scorer: Scorer, feas: Feasibility, chosen, max_passes: int = 5,
             rtol: float = 1e-6) -> tuple[list[int], float, int]:
    """Swap passes: replace one selected camera by the best feasible candidate while the score
    drops by more than rtol (relative). Returns (chosen, score, swaps made)."""
    chosen = list(chosen)
    current, swaps = scorer.of(cand, chosen), 0
    for _ in range(max_passes):
        improved = False
        for slot in range(len(chosen)):
            rest = chosen[:slot] + chosen[slot + 1:]
            ok = np.flatnonzero(feas.allowed(rest))
            ok = ok[~np.isin(ok, chosen)]
            if ok.size == 0:
                continue
            s = scorer.add(*cand.sums(rest), cand, ok)
            best = int(np.argmin(s))
            if s[best] < current * (1 - rtol):
                chosen[slot], current = int(ok[best]), float(s[best])
                swaps, improved = swaps + 1, True
        if not improved:
            break
    return chosen, current, swaps


@dataclass(frozen=True)
class Estimate:
    """What judging and selecting will take, estimated before the work (`estimate`): candidates
    K, samples N, candidates probed P, stored pairs E (the probe's mean per candidate x K), peak
    memory (bytes: the process so far, the stored pairs STORE_COPIES times, one block's working
    arrays, the candidates' cameras), judging time (the probe's time per candidate x K) and search
    time (the score's time per stored pair, timed on the probe's pairs, x E x the score passes:
    greedy's n_max plus SEARCH_PASSES exchange passes of every count's cameras), seconds."""

    candidates: int
    samples: int
    probed: int
    entries: int
    memory_bytes: float
    fixed_bytes: float
    judge_s: float
    search_s: float

    def line(self) -> str:
        return (f"design estimate: {self.candidates:,} candidates x {self.samples:,} samples, about "
                f"{self.entries:,} stored pairs (from {self.probed} probed candidates): "
                f"{self.memory_bytes / GB:.1f} GB peak, {self.judge_s:.0f} s judging + "
                f"{self.search_s:.0f} s search")


def peak_rss() -> float:
    """The process's peak resident memory so far (bytes; Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0


def available_memory() -> float:
    """Bytes this process may still use: MemAvailable of /proc/meminfo plus what it holds now
    (its peak so far); the physical memory where /proc is missing."""
    try:
        with open("/proc/meminfo") as fh:
            free = next(int(line.split()[1]) * 1024 for line in fh if line.startswith("MemAvailable:"))
    except (OSError, StopIteration):
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    return free + peak_rss()


def score_passes(exp: Experiment) -> int:
    """How many times the search scores every candidate: greedy's n_max steps plus SEARCH_PASSES
    exchange passes over each count's cameras (count = min_cameras .. n_max)."""
    n = inventory(exp)
    return n + SEARCH_PASSES * sum(range(min(exp.design.min_cameras, n), n + 1))


def estimate(exp: Experiment, j: Judging, scorer: Scorer) -> Estimate:
    """Judge PROBE candidates evenly spread over `j`'s list and time the score on their pairs;
    scale to all candidates (the `Estimate` fields)."""
    K, N = len(j.cams), len(j.geometry.samples)
    pick = np.unique(np.linspace(0, K - 1, min(K, PROBE)).astype(int)) if K else np.zeros(0, int)
    probe = replace(j, cams=tuple(j.cams[i] for i in pick), mount=tuple(j.mount[i] for i in pick),
                    kind=tuple(j.kind[i] for i in pick), u=j.u[pick], heads=j.heads[pick],
                    body=j.body[pick], target=j.target[pick])
    warm = min(len(pick), PROBE_WARM)      # the first few compile the programs: not timed
    first = judge_block(probe, 0, warm) if warm else None
    t0 = time.perf_counter()
    rest = judge_block(probe, warm, len(pick)) if len(pick) > warm else None
    judge_s = (time.perf_counter() - t0) / max(len(pick) - warm, 1) * K if rest is not None else 0.0
    block = first if rest is None else replace(
        rest, start=0, counts=np.concatenate([first.counts, rest.counts]),
        index=np.concatenate([first.index, rest.index]), info=np.concatenate([first.info, rest.info]),
        weight=np.concatenate([first.weight, rest.weight]),
        assigned=np.concatenate([first.assigned, rest.assigned]),
        masked=np.concatenate([first.masked, rest.masked]),
        path_lost=np.concatenate([first.path_lost, rest.path_lost]),
        seen=np.concatenate([first.seen, rest.seen]))
    per = float(block.counts.sum()) / len(pick) if len(pick) else 0.0
    entries = int(round(per * K))
    search_s = 0.0
    sample = collect(probe, [block]) if block is not None else None
    if sample is not None and sample.index.size:
        rows = np.arange(len(sample.cameras))
        zero = (np.zeros((N, 6)), np.zeros(N))
        scorer.add(*zero, sample, rows[:1])                                  # compiles
        t0 = time.perf_counter()
        scorer.add(*zero, sample, rows)
        chunks = math.ceil(sample.index.size / ENTRY_CHUNK)    # a chunk costs the same, full or padded
        search_s = (time.perf_counter() - t0) / (chunks * ENTRY_CHUNK) * entries * score_passes(exp)
    fixed = peak_rss() + block_size(N) * N * PAIR_BYTES + K * CAMERA_BYTES
    memory = fixed + STORE_COPIES * entries * ENTRY_BYTES
    return Estimate(K, N, len(pick), entries, memory, fixed, judge_s, search_s)


def refuse(exp: Experiment, est: Estimate, memory_limit: float, time_limit: float | None) -> None:
    """ConfigError naming the [design] sample_spacing_mm and the candidate count that would fit
    when `est` needs more than `memory_limit` bytes or (with one) `time_limit` seconds. The stored
    pairs and both times grow as candidates x samples, samples as 1 / spacing^2."""
    over = []
    if est.memory_bytes > memory_limit:
        room = memory_limit - est.fixed_bytes
        if room <= 0:
            raise ConfigError(exp.path, "design", (
                f"{est.line()}; but only {memory_limit / GB:.1f} GB is available and this process, one "
                f"block of candidates and the {est.candidates:,} candidates' cameras already take "
                f"{est.fixed_bytes / GB:.1f} GB: free memory, or far fewer candidates (zone_points, "
                "zone_heights, rail_positions, lenses_mm, aim_offsets_deg)"))
        over.append(((est.memory_bytes - est.fixed_bytes) / room, f"{memory_limit / GB:.1f} GB of memory"))
    total = est.judge_s + est.search_s
    if time_limit is not None and total > time_limit:
        over.append((total / time_limit, f"the time limit of {time_limit:g} s"))
    if not over:
        return
    ratio, what = max(over)
    spacing = math.ceil(exp.design.sample_spacing * 1e3 * math.sqrt(ratio))
    raise ConfigError(exp.path, "design.sample_spacing_mm", (
        f"{est.line()}: more than {' and '.join(w for _, w in over)}; a sample_spacing_mm of {spacing} "
        f"or more, or at most {int(est.candidates / ratio):,} candidates (fewer zone_points, "
        "zone_heights, rail_positions, lenses_mm or aim_offsets_deg), fits"))


def camera_specs(exp: Experiment, cand: Candidates, chosen) -> list[CameraSpec]:
    """[[camera]] entries d1, d2, ... for the chosen candidates: rail + u + offset, zone or fixed
    mount + position, or position; each with its body's lens catalogue (`lenses`) as lenses_mm,
    so that `--refine` chooses among the lenses the design chose from."""
    kinds = bodies(exp)
    out = []
    for k, i in enumerate(chosen):
        c, body, mount = cand.cameras[i], kinds[cand.body[i]], cand.mount[i] or None
        on_rail = cand.kind[i] == "rail"
        out.append(CameraSpec(name=f"d{k + 1}", sensor_width=body.sensor_width,
                              pixels=tuple(body.pixels), focal_length=c.focal_length,
                              lenses=lenses(exp, body),   # what the design chose from: --refine too
                              rail=mount if on_rail else None, mount=None if on_rail else mount,
                              u=float(cand.u[i]) if on_rail else None,
                              offset=np.array(cand.offset[i]),
                              position=None if on_rail else np.asarray(c.position),
                              pan=c.pan, tilt=c.tilt))
    return out


def designed(exp: Experiment, cand: Candidates, chosen) -> Experiment:
    """The experiment with the chosen cameras (stereo pairs and [optimize] cameras, which name the
    hand layout's cameras, dropped)."""
    return replace(exp.with_cameras(camera_specs(exp, cand, chosen)), stereo_pairs=(),
                   optimize=replace(exp.optimize, cameras=None))


def measurable(exp: Experiment, cand: Candidates, samples) -> np.ndarray:
    """(N,) the samples that some selection of candidates could measure: usable views from at
    least their region's min_cameras distinct spots (optical centres SPOT_M apart) among all
    candidates."""
    need = np.array([r.min_cameras for r in exp.regions])[samples.region]
    if not len(cand.cameras):
        return np.zeros(len(samples), dtype=bool)
    spot = np.unique(np.round(cand.positions / SPOT_M), axis=0, return_inverse=True)[1].ravel()
    owner = np.repeat(np.arange(len(cand.cameras)), np.diff(cand.indptr))
    use = usable.usable_views(cand.entry_weight)
    pairs = np.unique(spot[owner[use]].astype(np.int64) * len(samples) + cand.index[use])
    return np.bincount(pairs % len(samples), minlength=len(samples)) >= need


def measures(state, exp: Experiment, can_measure: np.ndarray | None = None) -> dict:
    """Of a judged layout: sigma_max p95 (um) of the worst scored region (None when a scored
    region is unmeasured), the area fraction of all regions seen by their region's min_cameras
    usable views, and over the area that can be measured at all (`can_measure`, `measurable`;
    default everywhere): that area's fraction, the fraction of it seen by min_cameras, sigma_max
    p95 per region over its measured samples there (None for a region with none), and the worst
    of those (None only when no region has one)."""
    judged = report.state_evaluation(state)
    scored = exp.optimize.regions or [r.name for r in exp.regions]
    p95 = [judged.regions[r].sigma_max_um.p95 for r in scored]
    smp, pred = state.samples, state.prediction
    need = np.array([r.min_cameras for r in exp.regions])[smp.region]
    covered = pred.coverage >= need
    seen = smp.area[covered].sum() / smp.area.sum()
    can = np.ones(len(smp), dtype=bool) if can_measure is None else np.asarray(can_measure, bool)
    by_region = {}
    for r, name in enumerate(smp.region_names):
        m = (smp.region == r) & can & pred.measured
        by_region[name] = float(np.percentile(pred.sigma_max[m] * 1e6, 95)) if m.any() else None
    values = [by_region[r] for r in scored if by_region[r] is not None]
    area = float(smp.area[can].sum())
    return {"sigma_p95_um": None if any(v is None for v in p95) else max(p95),
            "coverage": float(seen),
            "measurable_fraction": area / float(smp.area.sum()),
            "coverage_of_measurable": float(smp.area[can & covered].sum() / area) if area > 0 else 0.0,
            "sigma_p95_measurable_um": max(values) if values else None,
            "sigma_p95_by_region_um": by_region}


def problems(exp: Experiment, cand: Candidates, samples) -> list[str]:
    """What no selection can fix, each naming the region and what is missing: an inventory below
    its min_cameras; no candidate that is a usable view of it (at rest, or over the load path's
    keyframes); fewer candidate spots (optical centres SPOT_M apart) seeing it than its
    min_cameras."""
    out, n = [], inventory(exp)
    use = usable.usable_views(cand.entry_weight)
    owner, region = cand.row[use], samples.region[cand.index[use]]
    where = "[design] max_cameras" if exp.design.max_cameras else \
        ("the [[body]] counts" if exp.bodies else "the [[camera]] count")
    for r, spec in enumerate(exp.regions):
        need = spec.min_cameras
        if need > n:
            out.append(f"region {spec.name!r} needs {need} cameras (min_cameras) but the inventory "
                       f"has {n} ({where}): add {need - n} camera bod{'y' if need - n == 1 else 'ies'}")
        seeing = np.unique(owner[region == r])
        if seeing.size == 0:
            moving = " over the load path's keyframes" if np.any(cand.path_lost > 0) else ""
            out.append(f"region {spec.name!r}: no candidate pose sees it{moving}: add a mount "
                       "([[mount]] or [[rail]]) in view of it, or more [design] rail_positions, "
                       "zone_points or aim_offsets_deg")
            continue
        spots_seen = _distinct(cand.positions[seeing])
        if 0 < spots_seen < need <= n:
            out.append(f"region {spec.name!r} needs {need} cameras (min_cameras) but only "
                       f"{spots_seen} candidate spot(s) see it: add a mount in view of it")
    return out


def _distinct(points: np.ndarray) -> int:
    """How many of `points` are SPOT_M apart (greedy clustering)."""
    left, count = np.asarray(points), 0
    while len(left):
        left = left[np.linalg.norm(left - left[0], axis=1) >= SPOT_M]
        count += 1
    return count


def shortfalls(state, exp: Experiment) -> list[str]:
    """Regions the designed layout leaves short of their min_cameras, each named with the area
    fraction seen by that many usable views."""
    out, smp = [], state.samples
    for r, spec in enumerate(exp.regions):
        need = spec.min_cameras
        m = smp.region == r
        seen = smp.area[m & (state.prediction.coverage >= need)].sum() / smp.area[m].sum()
        if seen < 1 - LIMIT_SLACK:
            out.append(f"region {spec.name!r}: the design sees {100 * seen:.1f} % of it by its "
                       f"min_cameras = {need} usable views (missing: more cameras or a mount in "
                       "view of the rest)")
    return out


def statistics(exp: Experiment, cand: Candidates, chosen) -> dict:
    """Candidate statistics for design.json and the report: counts per mount kind, body, lens
    and region (candidates assigned it), the load path's mean loss, and the chosen cameras."""
    kinds = bodies(exp)
    f = np.array([c.focal_length for c in cand.cameras])
    return {
        "per_mount_kind": {k: int(sum(x == k for x in cand.kind)) for k in ("rail", "zone", "fixed")},
        "per_body": {b.name: int((cand.body == i).sum()) for i, b in enumerate(kinds)},
        "per_lens_mm": {f"{x * 1e3:g}": int((f == x).sum()) for x in np.unique(f)},
        "per_region_assigned": {r.name: int(cand.assigned[:, k].sum())
                                for k, r in enumerate(exp.regions)},
        "usable_samples_mean": float(cand.usable_counts().mean()) if len(cand.cameras) else 0.0,
        "blind_pruned": cand.pruned,
        "load_path_lost_mean": float(cand.path_lost.mean()),
        "chosen": [{"camera": f"d{k + 1}", "body": kinds[cand.body[i]].name,
                    "focal_mm": round(cand.cameras[i].focal_length * 1e3, 6),
                    "mount": cand.mount[i] or "position", "kind": cand.kind[i],
                    "position_m": np.round(cand.cameras[i].position, 4).tolist(),
                    "regions": [r.name for k, r in enumerate(exp.regions) if cand.assigned[i, k]]}
                   for k, i in enumerate(chosen)]}


def design_layout(exp: Experiment, refine: bool = False, memory_limit: float | None = None,
                  time_limit: float | None = None, client=None, threads: int | None = None) -> DesignResult:
    """Design a layout (module docstring); returns the `DesignResult` that `vdo.commands.design`
    writes as designed.toml, layout.json, summary.json, constraints.json, candidates.csv,
    pareto.csv, pareto.png, design.json and report.html (this function writes nothing). With
    `refine`, also `vdo.optimize.optimize_layout` of the designed layout (`DesignResult.refined`,
    written into out/refine; its constraints.json "before" holds every constraint check of the
    designed layout). Before the work, the time and memory it will take are estimated
    (`estimate`, one INFO line) and a problem that needs more than `memory_limit` bytes (default:
    `available_memory`) or `time_limit` seconds is refused (`refuse`: ConfigError naming the
    spacing and the candidate count that fit). With a dask.distributed `client` the candidates
    are judged on its workers (`judge`; `threads` Dr.Jit threads each). Progress and the chosen
    cameras: INFO lines and bars through the module logger; each problem found (also in the
    result): a warning."""
    t0 = time.perf_counter()
    d = exp.design
    n_max = inventory(exp)
    coarse = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=d.sample_spacing)))
    j = judging(exp, coarse)
    scorer = Scorer(exp, coarse.samples)
    est = estimate(exp, j, scorer)
    log.info(est.line())
    refuse(exp, est, available_memory() if memory_limit is None else memory_limit, time_limit)
    t_judge = time.perf_counter()
    cand = judge(exp, coarse, j, client=client, threads=threads)
    K, N = len(cand.cameras), cand.samples
    judged_s = time.perf_counter() - t_judge
    log.info("%s candidates x %s samples (%g mm) judged in %.0f s", f"{K:,}", f"{N:,}",
             d.sample_spacing * 1e3, time.perf_counter() - t0)
    issues = problems(exp, cand, coarse.samples)
    for msg in issues:
        log.warning(msg)
    if K == 0:
        raise ConfigError(exp.path, "design", (
            f"none of the {cand.pruned} candidate poses that keep their clearance sees a sample: add "
            "a [[mount]] or [[rail]] in view of the regions") if cand.pruned else (
            "no candidate pose keeps its clearance: add a [[mount]] or [[rail]] clear of the meshes"))
    feas = Feasibility(exp, cand, coarse.samples)
    can_measure = measurable(exp, cand, coarse.samples)
    log.info("%.0f %% of the regions' area can be measured from the candidate spots (%d+ views); "
             "the camera-count curve is over that area", 100 * coarse.samples.area[can_measure].sum()
             / coarse.samples.area.sum(), exp.evaluation.min_cameras)
    t_search = time.perf_counter()
    order, _ = greedy(cand, scorer, feas, n_max)
    curve = []
    for n in bar(log, iterable=range(min(d.min_cameras, len(order)), len(order) + 1), desc="counts",
                 leave=False):
        chosen, score, swaps = exchange(cand, scorer, feas, order[:n])
        state = layout_state(coarse, cameras_of(designed(exp, cand, chosen)))
        curve.append({"cameras": n, "score": score, "swaps": swaps, "chosen": chosen,
                      "lenses_mm": " ".join(f"{cand.cameras[i].focal_length * 1e3:g}" for i in chosen),
                      "bodies": " ".join(bodies(exp)[cand.body[i]].name for i in chosen),
                      **measures(state, exp, can_measure)})
    relax_curve(exp, cand, scorer, feas, curve)
    searched_s = time.perf_counter() - t_search
    search_peak = peak_rss()      # what the estimate covers: judging and selection
    best = curve[-1]
    target = None
    if d.target_sigma_um is not None:
        ok = [c for c in curve if c["sigma_p95_um"] is not None and
              c["sigma_p95_um"] <= d.target_sigma_um and c["coverage"] >= 1 - LIMIT_SLACK]
        target = ok[0]["cameras"] if ok else None
        sharp = [c for c in curve if c["sigma_p95_um"] is not None and c["sigma_p95_um"] <= d.target_sigma_um]
        scored = ", ".join(repr(r) for r in (exp.optimize.regions or [r.name for r in exp.regions]))
        if target is None and sharp:     # sigma is met, the coverage of every region is not
            issues.append(f"target sigma_max p95 {d.target_sigma_um:g} um is reached on region(s) "
                          f"{scored} from {sharp[0]['cameras']} cameras ({sharp[0]['sigma_p95_um']:.4g} um), "
                          f"but no count sees every region by its min_cameras (at most "
                          f"{100 * max(c['coverage'] for c in curve):.1f} % of the area; the region(s) "
                          "short are named below)")
            log.warning(issues[-1])
        elif target is None:
            reached = "unmeasured" if best["sigma_p95_um"] is None else f"{best['sigma_p95_um']:.4g} um"
            issues.append(f"target sigma_max p95 {d.target_sigma_um:g} um is not reached on "
                          f"region(s) {scored} with {len(best['chosen'])} cameras (best: {reached}; "
                          "missing: more cameras, longer lenses or closer mounts)")
            log.warning(issues[-1])
    final = designed(exp, cand, best["chosen"])
    state = layout_state(prepare(final))
    for msg in shortfalls(state, exp):
        issues.append(msg)
        log.warning(msg)
    summary = report.state_evaluation(state)
    checks = layout_checks(state)
    violated = [c for c in checks if not c["met"]]
    if violated:
        log.warning("the designed layout breaks %d constraint check(s) of vdo optimize (constraints.json); "
                    "vdo design --refine (vdo optimize) starts from it", len(violated))
    stats = statistics(exp, cand, best["chosen"])
    for c in stats["chosen"]:
        log.info("%s: %s, %g mm, %s %s at %s m, sees %s", c["camera"], c["body"], c["focal_mm"], c["kind"],
                 c["mount"], c["position_m"], ", ".join(c["regions"]) or "no region whole")
    wall = time.perf_counter() - t0
    final_peak = peak_rss()       # before the refinement, as the figures above
    refined = optimize_layout(final) if refine else None
    return DesignResult(cameras=len(best["chosen"]), problems=issues, target_count=target,
                        refined=refined, statistics=stats, violations=len(violated), curve=curve,
                        summary=summary, wall_s=wall,
                        record=DesignRecord(experiment=exp, designed=final, cameras=tuple(state.cameras),
                                            checks=checks, candidates=cand, inventory=n_max,
                                            estimate=est, judge_s=judged_s, search_s=searched_s,
                                            peak_memory_bytes=search_peak,
                                            final_peak_memory_bytes=final_peak))


@dataclass(frozen=True)
class DesignResult:
    """What `design` returns: the designed layout's camera count, the problems found (the
    warnings, in words), the smallest count meeting [design] target_sigma_um, the camera-count
    curve (pareto.csv's rows, with each count's chosen candidates), the designed layout judged as
    `vdo evaluate` judges it (`summary`: summary.json is its `to_json()`) and, with `refine`, the
    `vdo.optimize.OptimizeResult` of optimizing it; `record`: the rest of what `vdo.commands.design`
    writes (`DesignRecord`)."""

    cameras: int                           # cameras of the designed layout
    problems: list[str]                    # design.json "problems"
    target_count: int | None               # smallest count meeting the target (None: none, or no target)
    refined: OptimizeResult | None         # out/refine (None without refine)
    statistics: dict                       # design.json "statistics" (`statistics`)
    violations: int                        # constraint checks the designed layout breaks
    curve: list[dict]                      # per camera count: score, bound, σ p95 (µm), coverage, chosen, ...
    summary: report.EvaluationResult       # the designed layout judged whole
    wall_s: float                          # s, the whole design
    record: DesignRecord                   # what the run folder is written from

    def to_json(self) -> dict:
        """The fields as a JSON dict, `summary` and `refined` as their `to_json()`."""
        return {"cameras": self.cameras, "problems": self.problems, "target_count": self.target_count,
                "refined": None if self.refined is None else self.refined.to_json(),
                "statistics": self.statistics, "violations": self.violations, "curve": self.curve,
                "summary": self.summary.to_json(), "wall_s": self.wall_s}


@dataclass(frozen=True)
class DesignRecord:
    """What the run folder of `vdo design` holds besides `DesignResult`'s figures: the experiment
    designed for, the designed one (designed.toml) and its cameras (layout.json), every
    constraint check of the designed layout (constraints.json), the judged candidates
    (candidates.csv), the inventory, the up-front estimate and the measured seconds (judging,
    selection) and peak resident memory (bytes: of judging and selection, and with the final
    judgement) of design.json."""

    experiment: Experiment
    designed: Experiment
    cameras: tuple[Camera, ...]
    checks: list[dict]
    candidates: Candidates
    inventory: int                          # cameras the inventory holds
    estimate: Estimate
    judge_s: float                          # s, judging the candidates
    search_s: float                         # s, selection and bounds
    peak_memory_bytes: float                # peak resident memory of judging and selection
    final_peak_memory_bytes: float          # the same, the final judgement included


def relax_curve(exp: Experiment, cand: Candidates, scorer: Scorer, feas: Feasibility, curve) -> None:
    """Adds to each count of `curve` the certified lower bound on the score of any selection of
    that many cameras (`vdo.design.bound.relaxation`, body counts and obscuration kept, pairwise
    rules dropped; [design] bound_s wall seconds per count): "bound", "gap" (1 - bound / score)
    and "bound_converged"; None where bound_s = 0. The score never rises when a camera is added,
    so the best k-camera score is at least the best (k+1)-camera score: each count's bound is the
    largest of its own and those of larger counts (while the relaxation's count grows). Logs each
    gap."""
    seconds = exp.design.bound_seconds
    if seconds <= 0:
        for c in curve:
            c.update(bound=None, gap=None, bound_converged=None)
        return
    found = [bound.relaxation(scorer.value, cand, None, c["cameras"], feas.alone, feas.body,
                              feas.counts, start=c["chosen"], time_limit=seconds)
             for c in bar(log, iterable=curve, desc="bound", leave=False)]
    value, later = [b.value for b in found], 0.0
    for i in reversed(range(len(found))):
        # adding a camera never raises the score, so a bound for k + 1 cameras (uncut) bounds k
        value[i] = max(value[i], later)
        later = value[i] if i == 0 or found[i].cameras > found[i - 1].cameras else 0.0
    for c, b, v in zip(curve, found, value):
        c.update(bound=v, gap=max(0.0, 1.0 - v / c["score"]), bound_converged=b.converged)
        log.info("%d cameras: score %.4g, no selection below %.4g (relaxation bound): gap %.1f %% "
                 "(%d steps, %s)", c["cameras"], c["score"], v, 100 * c["gap"], b.iterations,
                 "converged" if b.converged else f"time limit {seconds:g} s")
