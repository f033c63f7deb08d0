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
scores it). Stored as 6
float64 entries + 1 float32 weight per pair: candidates x samples x 52 bytes (1,666 candidates x
3,372 samples on the built-in experiment: 290 MB). Not float32: C_i has rank 2 with its null
vector along the ray, and float32 rounding of entries ~1e15 1/m^2 leaves ~1e8 along the ray,
above the prior 1/prior_sigma^2 = 1e6 that alone fixes that direction for a sample seen once
(the regularised C turned indefinite and the score NaN).

Score. The information of a set S of cameras adds: C_S(n) = sum_{i in S} C_i(n), coverage
k_S(n) = sum_{i in S} w_i(n). The set is scored as `vdo.objective.score` scores a layout:

    score(S) = ( sum_n omega_n sigma_n^q / sum_n omega_n )^(1/q) / 1 um + W P,
    P = sum_n' a_n' max(0, k_region(n') - k_S(n'))^2 / sum_n' a_n'

sigma_n the smooth sigma_max of the regularised C_S (`vdo.objective`), omega = area x importance
over the scored regions ([optimize] regions, default all), q = 8, W = 1000, and the coverage
penalty P over EVERY region (a design must see the whole specimen, not only the scored part).
This is the optimizer's own score, so selection and refinement minimise the same thing. It is not
submodular (one camera alone gains nothing in sigma; pairs do), so lazy evaluation's bound does not
hold: every step evaluates every feasible candidate, which the sums make cheap (one vectorised
pass over candidates x samples per step).

Selection. Greedy forward selection adds the feasible candidate with the lowest score, then
exchange passes replace one selected camera by the best feasible candidate while that lowers the
score. Feasible with the selected set:
* the inventory: no more cameras of a body kind than its count;
* one camera per spot: no two optical centres closer than SPOT_M (a body and its clearance);
* axis angles: two cameras that share a region (each sees at least `[optimize]
  assign_fraction` of its area with usable weight) keep their optical axes at least `[optimize]
  min_axis_angle_deg` apart, by default `vdo.constraints.stereo_min_angle` of the shorter lens,
  and at most `[optimize]` or that region's `max_axis_angle_deg` where set;
* clearance from the meshes (above, per candidate);
* obscuration: no obstacle hides more than `[optimize] max_obscuration` of a region the
  candidate is assigned (the area fraction it would see on a scene of the specimen alone but not
  on the whole scene: a second ray cast).
Obscuration by other camera bodies and tripods is not judged during selection; the designed
layout is judged whole (bodies and tripods included) with `vdo.state.layout_state` at [evaluation]'s sample spacing, and with
every constraint check of `vdo optimize` (`constraint_checks`, constraints.json).

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

import csv
import logging
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator
from scipy.spatial import cKDTree

from vdo.design import bound
from vdo.outputs import html_report
from vdo.search import loadpath
from vdo import objective
from vdo.outputs import report
from vdo.physics import usable
from vdo.model.camera import Camera, look_at_angles
from vdo.config.experiment import BodySpec, CameraSpec, Experiment, inside_floor
from vdo.constraints import stereo_min_angle
from vdo.core.errors import ConfigError
from vdo.geometry.keyframes import load_path_of
from vdo.physics.lighting import illuminate
from vdo.optimize import Problem, optimize
from vdo.physics.predict import samples_for_objective, settings, view_data
from vdo.core.progress import bar, shown
from vdo.core.runfolder import run_folder
from vdo.scene import build_scene, camera_body_points
from vdo.state import Geometry, layout_state, prepare
from vdo.physics.visibility import compute_visibility

log = logging.getLogger(__name__)

MERGE_TARGETS_M = 0.2   # region centres closer than this share one aim point
SPOT_M = 0.2            # two optical centres closer than this are one physical spot
BATCH = 256             # candidates per batch of the information and the score


@dataclass(frozen=True, eq=False)
class Candidates:
    """K candidate cameras judged on N samples. info (K, N, 6) float64 1/m^2 (entries c00, c11,
    c22, c01, c02, c12 of Omega w |det A| C_i); weight (K, N) float32 soft weights w;
    assigned (K, R) the regions each sees usably over at least assign_fraction of the area;
    mount (K,) names ("" for a [[camera]]'s own fixed position), kind (K,) "rail", "zone" or
    "fixed", u (K,) (rail; NaN otherwise), offset (K, 3) m from the rail point, body (K,) index
    into `bodies(exp)`, target (K,) index into `targets`; masked (K, R) the area fraction of each
    region's samples the candidate would see but an obstacle hides (its obscuration); path_lost
    (K,) the fraction of its usable samples at rest that the load path's keyframes take away."""

    cameras: tuple[Camera, ...]
    mount: tuple[str, ...]
    kind: tuple[str, ...]
    u: np.ndarray
    offset: np.ndarray
    body: np.ndarray
    target: np.ndarray
    targets: np.ndarray
    info: np.ndarray
    weight: np.ndarray
    assigned: np.ndarray
    masked: np.ndarray
    path_lost: np.ndarray

    @property
    def positions(self) -> np.ndarray:
        return np.array([c.position for c in self.cameras])

    @property
    def axes(self) -> np.ndarray:
        return np.array([c.optical_axis for c in self.cameras])


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
    that lie inside the polygon, and its centroid."""
    lo, hi = zone.low, zone.high
    axes = [np.linspace(lo[k], hi[k], per_axis) if hi[k] > lo[k] and per_axis > 1
            else np.array([(lo[k] + hi[k]) / 2]) for k in range(2)]
    axes.append(np.linspace(lo[2], hi[2], heights) if hi[2] > lo[2] and heights > 1
                else np.array([(lo[2] + hi[2]) / 2]))
    xy = np.stack(np.meshgrid(axes[0], axes[1], indexing="ij"), -1).reshape(-1, 2)
    if zone.floor is not None:
        xy = np.vstack([[p for p in xy if inside_floor(zone.floor, p)] or np.zeros((0, 2)),
                        zone.floor.mean(axis=0)])
    return np.array([[x, y, z] for x, y in xy for z in axes[2]])


def spots(exp: Experiment) -> list[tuple]:
    """Where candidates stand: (mount name, kind, u, offset (3,), optical centre (3,)) for
    `rail_positions` values of u on every rail (with `offset_m`, and its mirror below the bar),
    the `zone_grid` of every zone mount, every fixed mount, and every [[camera]] given by
    position_m on no mount."""
    d = exp.design
    heads = [d.offset] + ([d.offset * [1, 1, -1]] if d.offset[2] != 0 else [])
    grid = np.linspace(0, 1, d.rail_positions) if d.rail_positions > 1 else [0.5]
    out = [(r.name, "rail", float(u), h, exp.rail(r.name).position(u, xp=np) + h)
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
    kinds, u, offsets, body index, target index, targets)."""
    aims = targets(samples)
    offsets = [(0.0, 0.0)] + [(s * a, t * a) for a in exp.design.aim_offsets for s, t in
                              ((1, 0), (-1, 0), (0, 1), (0, -1))]
    cams, rows, points = [], [], []
    for mount, kind, u, head, p in spots(exp):
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
        cams = [c for c, ok in zip(cams, clear) if ok]
        rows = [r for r, ok in zip(rows, clear) if ok]
    mount, kind, u, head, b, t = zip(*rows) if rows else ((),) * 6
    return (cams, tuple(mount), tuple(kind), np.array(u, dtype=float),
            np.array(head, dtype=float).reshape(-1, 3), np.array(b, dtype=int),
            np.array(t, dtype=int), aims)


def judge(exp: Experiment, geometry: Geometry) -> Candidates:
    """Every candidate's information and weights on `geometry`'s samples (module docstring); with
    progress bars when the module logger passes INFO (`vdo.core.progress`)."""
    samples = geometry.samples
    R = len(samples.region_names)
    cams, mount, kind, u, heads, body, tg, aims = candidate_cameras(exp, samples, geometry.meshes)
    if not cams:
        return Candidates((), (), (), u, heads, body, tg, aims, np.zeros((0, len(samples), 6)),
                          np.zeros((0, len(samples)), np.float32), np.zeros((0, R), bool),
                          np.zeros((0, R)), np.zeros(0))
    scene = build_scene(list(geometry.meshes))
    vis = compute_visibility(scene, cams, samples, exp.evaluation.incidence_limit, progress=shown(log))
    bare = compute_visibility(build_scene([m for m in geometry.meshes if m.role == "specimen"]), cams,
                              samples, exp.evaluation.incidence_limit).visible
    hidden = bare & ~vis.visible
    path = load_path_of(exp, list(geometry.meshes))
    steps = () if path is None else loadpath.keyframe_steps(path, exp.design.keyframes)
    on_path = (np.ones((len(cams), len(samples)), bool) if not steps else
               loadpath.path_occlusion(geometry, path, cams, steps) > 0)
    light = illuminate(scene, exp.lights, samples, exp.render.ambient_radiance)
    smp = samples_for_objective(exp, samples)
    st = replace(settings(exp), pair_dtype="float64")
    K, N = len(cams), len(samples)
    info = np.zeros((K, N, 6))
    weight = np.zeros((K, N), np.float32)
    batches = range(0, K, BATCH)
    for s in bar(log, iterable=batches, desc="candidates", unit="batch", leave=False):
        part = cams[s:s + BATCH]
        pv = replace(vis, camera_names=vis.camera_names[s:s + BATCH],
                     **{k: getattr(vis, k)[s:s + BATCH] for k in
                        ("in_front", "in_image", "facing", "unoccluded")})
        cp = objective.CameraParams.from_cameras(part)
        views = view_data(exp, smp, pv, light, geometry.speckle)
        C = np.asarray(objective.camera_information(cp, smp, views, geometry.speckle.table, st))
        info[s:s + len(part)] = C[..., [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]
        w = np.asarray(objective.geometry(cp, smp, st).weight)
        weight[s:s + len(part)] = w * np.asarray(pv.unoccluded, float)
    at_rest = usable.usable_views(weight)
    info *= on_path[..., None]
    weight *= on_path
    use = usable.usable_views(weight)
    lost = 1 - use.sum(1) / np.maximum(at_rest.sum(1), 1)
    assigned, masked = np.zeros((K, R), bool), np.zeros((K, R))
    for r in range(R):
        m = samples.region == r
        a = samples.area[m]
        assigned[:, r] = (use[:, m] * a).sum(1) / a.sum() >= exp.optimize.assign_fraction
        masked[:, r] = (hidden[:, m] * a).sum(1) / np.maximum((bare[:, m] * a).sum(1), 1e-30)
    log.info("load path: %d keyframe(s) %s judged for the candidates' occlusion", len(steps), steps)
    return Candidates(tuple(cams), mount, kind, u, heads, body, tg, aims, info, weight, assigned,
                      masked, lost)


class Scorer:
    """score(S) of the module docstring for sums of candidates' information and weights."""

    def __init__(self, exp: Experiment, samples):
        st = settings(exp)
        scored = np.ones(len(samples.region_names), bool) if exp.optimize.regions is None else \
            np.isin(samples.region_names, exp.optimize.regions)
        omega = samples.area * samples.region_importance[samples.region] * scored[samples.region]
        area = samples.area / samples.area.sum()
        minimum = np.array([r.min_cameras or exp.evaluation.min_cameras for r in exp.regions])
        self.settings = st
        self.omega = jnp.asarray(omega / omega.sum())
        self.area = jnp.asarray(area)
        self.minimum = jnp.asarray(minimum[samples.region], dtype=float)
        self._batch = jax.jit(jax.vmap(self._one, in_axes=(0, 0)))

    def _one(self, info, cover):
        """info (N, 6) float64, cover (N,) -> score."""
        st = self.settings
        sigma = objective._smooth_sigma_max(tuple(info[:, k] for k in range(6)), st) / st.sigma_unit
        q = st.score_power
        top = jnp.max(sigma)
        agg = top * jnp.sum(self.omega * (sigma / top) ** q) ** (1.0 / q)
        short = jnp.maximum(self.minimum - cover, 0.0)
        return agg + st.coverage_weight * jnp.sum(self.area * short * short)

    def value(self, info, cover):
        """The score of summed information info (N, 6) float64 1/m^2 and coverage cover (N,): a
        traceable JAX function, convex in both (`vdo.design.bound`)."""
        return self._one(info, cover)

    def add(self, base_info, base_cover, info, weight) -> np.ndarray:
        """Scores of base + each candidate: base (N, 6), (N,); info (M, N, 6), weight (M, N)."""
        out = []
        for s in range(0, len(info), BATCH):
            i = jnp.asarray(base_info[None] + info[s:s + BATCH])
            c = jnp.asarray(base_cover[None] + weight[s:s + BATCH])
            out.append(np.asarray(self._batch(i, c)))
        return np.concatenate(out) if out else np.zeros(0)

    def of(self, cand: Candidates, chosen) -> float:
        chosen = list(chosen)
        i = cand.info[chosen].sum(0)
        c = cand.weight[chosen].sum(0)
        return float(self._batch(jnp.asarray(i[None]), jnp.asarray(c[None]))[0])


def min_angles(exp: Experiment, cand: Candidates) -> np.ndarray:
    """(K, K) minimum axis angle (rad) of each pair: [optimize] min_axis_angle_deg or the stereo
    rule of thumb for the shorter lens (`vdo.constraints.stereo_min_angle`)."""
    f = np.array([c.focal_length for c in cand.cameras])
    if exp.optimize.min_axis_angle is not None:
        return np.full((len(f), len(f)), exp.optimize.min_axis_angle)
    rule = {x: stereo_min_angle(x) for x in np.unique(f)}
    lo = np.minimum(f[:, None], f[None])
    return np.vectorize(rule.get)(lo)


class Feasibility:
    """Which candidates may join a selected set: no obstacle hides more than [optimize]
    max_obscuration of a region the candidate is assigned; one per spot; the minimum axis angle
    between cameras sharing a region (module docstring) and the maximum where one is set ([optimize]
    max_axis_angle_deg for every pair sharing a region, a region's max_axis_angle_deg for the
    pairs sharing that region)."""

    def __init__(self, exp: Experiment, cand: Candidates):
        p, a = cand.positions, cand.axes
        self.exclusive = np.linalg.norm(p[:, None] - p[None], axis=-1) < SPOT_M
        share = (cand.assigned.astype(int) @ cand.assigned.T.astype(int)) > 0
        angle = np.arccos(np.clip(a @ a.T, -1, 1))
        conflict = self.exclusive | (share & (angle < min_angles(exp, cand) - 1e-9))
        if exp.optimize.max_axis_angle is not None:
            conflict |= share & (angle > exp.optimize.max_axis_angle + 1e-9)
        for r, spec in enumerate(exp.regions):
            if spec.max_axis_angle is not None:
                on = cand.assigned[:, r]
                conflict |= on[:, None] & on[None] & (angle > spec.max_axis_angle + 1e-9)
        self.conflict = conflict
        self.alone = ~(cand.assigned & (cand.masked > exp.optimize.max_obscuration)).any(axis=1)
        self.body = cand.body
        self.counts = np.array([b.count for b in bodies(exp)])

    def allowed(self, chosen) -> np.ndarray:
        """(K,) True for the candidates compatible with every camera in `chosen` and whose body
        kind is not used up by `chosen`."""
        ok = self.alone.copy()
        for j in chosen:
            ok &= ~self.conflict[j]
        used = np.bincount(self.body[list(chosen)], minlength=len(self.counts))
        return ok & (used < self.counts)[self.body]


def greedy(cand: Candidates, scorer: Scorer, feas: Feasibility, n: int,
           start=()) -> tuple[list[int], list[float]]:
    """Forward selection up to n cameras from `start`: the chosen indices and the score after
    each addition (stops early when no feasible candidate is left); a progress bar when the module
    logger passes INFO."""
    chosen, scores = list(start), []
    N = cand.info.shape[1]
    for _ in bar(log, iterable=range(n - len(chosen)), desc="greedy", leave=False):
        ok = np.flatnonzero(feas.allowed(chosen))
        if ok.size == 0:
            break
        base_i = cand.info[chosen].sum(0) if chosen else np.zeros((N, 6))
        base_c = cand.weight[chosen].sum(0) if chosen else np.zeros(N)
        s = scorer.add(base_i, base_c, cand.info[ok], cand.weight[ok])
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
            s = scorer.add(cand.info[rest].sum(0),
                           cand.weight[rest].sum(0), cand.info[ok], cand.weight[ok])
            best = int(np.argmin(s))
            if s[best] < current * (1 - rtol):
                chosen[slot], current = int(ok[best]), float(s[best])
                swaps, improved = swaps + 1, True
        if not improved:
            break
    return chosen, current, swaps


def camera_specs(exp: Experiment, cand: Candidates, chosen) -> list[CameraSpec]:
    """[[camera]] entries d1, d2, ... for the chosen candidates: rail + u + offset, zone or fixed
    mount + position, or position."""
    kinds = bodies(exp)
    out = []
    for k, i in enumerate(chosen):
        c, body, mount = cand.cameras[i], kinds[cand.body[i]], cand.mount[i] or None
        on_rail = cand.kind[i] == "rail"
        out.append(CameraSpec(name=f"d{k + 1}", sensor_width=body.sensor_width,
                              pixels=tuple(body.pixels), focal_length=c.focal_length,
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


def measures(state, exp: Experiment) -> dict:
    """Of a judged layout: sigma_max p95 (um) of the worst scored region (None when a scored
    region is unmeasured) and the area fraction of all regions seen by their region's
    min_cameras usable views."""
    summary = report.state_summary(state)
    scored = exp.optimize.regions or [r.name for r in exp.regions]
    p95 = [summary["regions"][r]["sigma_max_um"]["p95"] for r in scored]
    smp = state.samples
    need = np.array([r.min_cameras or exp.evaluation.min_cameras for r in exp.regions])[smp.region]
    seen = smp.area[state.prediction.coverage >= need].sum() / smp.area.sum()
    return {"sigma_p95_um": None if any(v is None for v in p95) else max(p95),
            "coverage": float(seen)}


def problems(exp: Experiment, cand: Candidates, samples) -> list[str]:
    """What no selection can fix, each naming the region and what is missing: an inventory below
    its min_cameras; no candidate that is a usable view of it (at rest, or over the load path's
    keyframes); fewer candidate spots (optical centres SPOT_M apart) seeing it than its
    min_cameras."""
    out, n = [], inventory(exp)
    use = usable.usable_views(cand.weight) if len(cand.cameras) else np.zeros((0, len(samples)), bool)
    where = "[design] max_cameras" if exp.design.max_cameras else \
        ("the [[body]] counts" if exp.bodies else "the [[camera]] count")
    for r, spec in enumerate(exp.regions):
        need = spec.min_cameras or exp.evaluation.min_cameras
        if need > n:
            out.append(f"region {spec.name!r} needs {need} cameras (min_cameras) but the inventory "
                       f"has {n} ({where}): add {need - n} camera bod{'y' if need - n == 1 else 'ies'}")
        m = samples.region == r
        seeing = np.flatnonzero(use[:, m].any(axis=1))
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
        need = spec.min_cameras or exp.evaluation.min_cameras
        m = smp.region == r
        seen = smp.area[m & (state.prediction.coverage >= need)].sum() / smp.area[m].sum()
        if seen < 1 - 1e-9:
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
        "usable_samples_mean": float(usable.usable_views(cand.weight).sum(1).mean()),
        "load_path_lost_mean": float(cand.path_lost.mean()),
        "chosen": [{"camera": f"d{k + 1}", "body": kinds[cand.body[i]].name,
                    "focal_mm": round(cand.cameras[i].focal_length * 1e3, 6),
                    "mount": cand.mount[i] or "position", "kind": cand.kind[i],
                    "position_m": np.round(cand.cameras[i].position, 4).tolist(),
                    "regions": [r.name for k, r in enumerate(exp.regions) if cand.assigned[i, k]]}
                   for k, i in enumerate(chosen)]}


def constraint_checks(exp: Experiment) -> list[dict]:
    """Every constraint check `vdo optimize` makes (`vdo.optimize.Problem.check`: axis angles,
    clearance, obscuration, field of view, shadows), on the experiment's own cameras."""
    problem = Problem(exp)
    return problem.check(problem.start)


def design(exp: Experiment, out: Path, overwrite: bool = False, refine: bool = False) -> dict:
    """Design a layout (module docstring) and write designed.toml, layout.json, summary.json,
    candidates.csv, pareto.csv, pareto.png, design.json and report.html into `out`; with
    `refine`, also `vdo.optimize.optimize` of designed.toml into out/refine (its
    constraints.json "before" holds every constraint check of the designed layout). Progress
    and the chosen cameras: INFO lines and bars through the module logger; each problem found
    (also in the result): a warning."""
    t0 = time.perf_counter()
    d = exp.design
    n_max = inventory(exp)
    coarse = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=d.sample_spacing)))
    cand = judge(exp, coarse)
    K, N = cand.info.shape[:2]
    log.info("%s candidates x %s samples (%g mm) judged in %.0f s", f"{K:,}", f"{N:,}",
             d.sample_spacing * 1e3, time.perf_counter() - t0)
    issues = problems(exp, cand, coarse.samples)
    for msg in issues:
        log.warning(msg)
    if K == 0:
        raise ConfigError(exp.path, "design", "no candidate pose keeps its clearance: add a "
                                              "[[mount]] or [[rail]] clear of the meshes")
    scorer, feas = Scorer(exp, coarse.samples), Feasibility(exp, cand)
    order, _ = greedy(cand, scorer, feas, n_max)
    curve = []
    for n in bar(log, iterable=range(min(d.min_cameras, len(order)), len(order) + 1), desc="counts",
                 leave=False):
        chosen, score, swaps = exchange(cand, scorer, feas, order[:n])
        state = layout_state(coarse, designed(exp, cand, chosen).cameras())
        curve.append({"cameras": n, "score": score, "swaps": swaps, "chosen": chosen,
                      "lenses_mm": " ".join(f"{cand.cameras[i].focal_length * 1e3:g}" for i in chosen),
                      "bodies": " ".join(bodies(exp)[cand.body[i]].name for i in chosen),
                      **measures(state, exp)})
    relax_curve(exp, cand, scorer, feas, curve)
    best = curve[-1]
    target = None
    if d.target_sigma_um is not None:
        ok = [c for c in curve if c["sigma_p95_um"] is not None and
              c["sigma_p95_um"] <= d.target_sigma_um and c["coverage"] >= 1 - 1e-9]
        target = ok[0]["cameras"] if ok else None
        if target is None:
            reached = "unmeasured" if best["sigma_p95_um"] is None else f"{best['sigma_p95_um']:.4g} um"
            scored = ", ".join(repr(r) for r in (exp.optimize.regions or [r.name for r in exp.regions]))
            issues.append(f"target sigma_max p95 {d.target_sigma_um:g} um is not reached on "
                          f"region(s) {scored} with {len(best['chosen'])} cameras (best: {reached}; "
                          "missing: more cameras, longer lenses or closer mounts)")
            log.warning(issues[-1])
    final = designed(exp, cand, best["chosen"])
    state = layout_state(prepare(final))
    for msg in shortfalls(state, exp):
        issues.append(msg)
        log.warning(msg)
    summary = report.state_summary(state)
    checks = constraint_checks(final)
    violated = [c for c in checks if not c["met"]]
    if violated:
        log.warning("the designed layout breaks %d constraint check(s) of vdo optimize (constraints.json); "
                    "vdo design --refine (vdo optimize) starts from it", len(violated))
    stats = statistics(exp, cand, best["chosen"])
    for c in stats["chosen"]:
        log.info("%s: %s, %g mm, %s %s at %s m, sees %s", c["camera"], c["body"], c["focal_mm"], c["kind"],
                 c["mount"], c["position_m"], ", ".join(c["regions"]) or "no region whole")
    wall = time.perf_counter() - t0
    with run_folder(out, overwrite) as tmp:
        report.write_config(tmp / "designed.toml", final)
        report.write_json(tmp / "layout.json", report.layout(list(state.cameras)))
        report.write_json(tmp / "summary.json", summary)
        report.write_json(tmp / "constraints.json", {"violations": len(violated), "violated": violated,
                                                     "checks": checks})
        _write_candidates(tmp / "candidates.csv", exp, cand, best["chosen"])
        _write_curve(tmp / "pareto.csv", curve)
        _plot_curve(tmp / "pareto.png", curve, d.target_sigma_um, exp.name)
        report.write_json(tmp / "design.json", {
            "candidates": K, "samples": N, "selection_spacing_mm": d.sample_spacing * 1e3,
            "lenses_mm": [f * 1e3 for f in lenses(exp)], "inventory": n_max,
            "bodies": [{"name": b.name, "count": b.count, "pixels": list(b.pixels),
                        "sensor_width_mm": b.sensor_width * 1e3,
                        "lenses_mm": [f * 1e3 for f in lenses(exp, b)]} for b in bodies(exp)],
            "targets_m": cand.targets.tolist(), "problems": issues, "statistics": stats,
            "constraint_violations": len(violated),
            "target_sigma_um": d.target_sigma_um, "smallest_count_meeting_target": target,
            "curve": [{k: v for k, v in c.items() if k != "chosen"} for c in curve],
            "gap_to_bound": best["gap"], "bound": best["bound"],
            "wall_s": wall})
        html_report.write_report(tmp)
        refined = optimize(final, tmp / "refine") if refine else None
    return {"cameras": len(best["chosen"]), "problems": issues, "target_count": target,
            "refined": refined, "statistics": stats, "violations": len(violated),
            "curve": curve, "summary": summary, "wall_s": wall}


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
    found = [bound.relaxation(scorer.value, cand.info, cand.weight, c["cameras"], feas.alone, feas.body,
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


def _write_candidates(path, exp: Experiment, cand: Candidates, chosen):
    """One row per candidate: mount, pose, body, lens, samples it sees usably, regions assigned,
    the fraction of its view the load path takes away, selected."""
    use = usable.usable_views(cand.weight).sum(1)
    names = [b.name for b in bodies(exp)]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["candidate", "mount", "kind", "u", "x_m", "y_m", "z_m", "pan_deg", "tilt_deg",
                    "body", "focal_mm", "target", "usable_samples", "regions_assigned",
                    "load_path_lost", "selected"])
        for i, c in enumerate(cand.cameras):
            w.writerow([i, cand.mount[i], cand.kind[i], "" if math.isnan(cand.u[i]) else f"{cand.u[i]:.4f}",
                        *(f"{x:.4f}" for x in c.position),
                        f"{math.degrees(c.pan):.2f}", f"{math.degrees(c.tilt):.2f}",
                        names[cand.body[i]], f"{c.focal_length * 1e3:g}", int(cand.target[i]),
                        int(use[i]), int(cand.assigned[i].sum()), f"{cand.path_lost[i]:.3f}",
                        int(i in chosen)])


def _write_curve(path, curve):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["cameras", "score", "bound", "gap", "sigma_p95_um", "coverage", "swaps",
                    "lenses_mm", "bodies"])
        for c in curve:
            w.writerow([c["cameras"], f"{c['score']:.6g}",
                        "" if c["bound"] is None else f"{c['bound']:.6g}",
                        "" if c["gap"] is None else f"{c['gap']:.4f}",
                        "" if c["sigma_p95_um"] is None else f"{c['sigma_p95_um']:.5g}",
                        f"{c['coverage']:.4f}", c["swaps"], c["lenses_mm"], c["bodies"]])


def _plot_curve(path, curve, target, name):
    """Top: sigma_max p95 and coverage per camera count; bottom: the design's score and the
    relaxation's bound on any selection's score per count (`relax_curve`)."""
    fig, (ax, low) = plt.subplots(2, 1, figsize=(6, 6.5), layout="constrained", sharex=True,
                                  height_ratios=(3, 2))
    n = [c["cameras"] for c in curve]
    s = [np.nan if c["sigma_p95_um"] is None else c["sigma_p95_um"] for c in curve]
    ax.semilogy(n, s, "o-", label="σ_max p95, worst scored region")
    if target is not None:
        ax.axhline(target, ls="--", color="k", lw=0.8, label=f"target {target:g} µm")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("σ_max p95 (µm)")
    ax2 = ax.twinx()
    ax2.plot(n, [100 * c["coverage"] for c in curve], "s:", color="C1", label="coverage")
    ax2.set_ylabel("area seen by its min_cameras (%)")
    ax2.set_ylim(0, 105)
    ax.set_title(f"{name}: cameras needed")
    lines = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    ax.legend(lines, [ln.get_label() for ln in lines], fontsize=8, loc="center right")
    low.semilogy(n, [c["score"] for c in curve], "o-", label="design's score")
    bounds = [np.nan if c["bound"] is None or c["bound"] <= 0 else c["bound"] for c in curve]
    if not np.all(np.isnan(bounds)):
        low.semilogy(n, bounds, "v--", color="C2", label="bound: no selection scores lower")
    low.set_xlabel("cameras")
    low.set_ylabel("score")
    low.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)
