"""Where cameras may stand and the one judgement of all candidates (`vdo design`): the
`Candidates` that `vdo.design.select` chooses from.

Candidates. Where a camera may stand (`spots`): every rail (a [[rail]] or a rail [[mount]]) at
`[design] rail_positions` positions evenly spread in u (plus `offset_m` from the bar to the
optical centre, and its mirror below the bar, z negated); every zone [[mount]] (a tripod's floor
area and height range) at a grid of `zone_points` values along x and y times `zone_heights`
heights (`zone_grid`); every fixed [[mount]]; and every [[camera]] given by `position_m` on no
mount. From each spot a candidate aims at each *target*: the centres of the regions' boxes
(clipped to their samples), merged when closer than MERGE_TARGETS_M; with `aim_offsets_deg` also
at pan and tilt +- each offset. Each pose carries each body kind of the inventory ([[body]]: its
sensor; or [design]'s one sensor) with each lens it takes. A candidate is dropped when its body
comes closer than `[optimize] clearance_m` to a mesh, by the measure of the layout's clearance
check (`vdo.search.obstruction.keep_clear`).

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
scores it). With `[design] score = "measured"` each candidate's sensor noise is multiplied by √κ
(`inflation`), κ its measured error over the bound at its median footprint in each region
(`vdo.physics.measured.noise_inflation`), so that C_i(n) is divided by κ. The candidates are judged in blocks of PAIRS_PER_BLOCK (candidate, sample) pairs
(`judge_block`; a block's dense arrays are freed before the next) and only the pairs with a
non-zero weight or information are kept, sparsely (`Candidates`): 6 float64 entries, 1 float32
weight and 1 int32 sample index per kept pair, 56 bytes (a camera sees a small part of a large
specimen). Candidates that see no sample at rest (blind) are dropped. Not float32: C_i has
rank 2 with its null vector along the ray, and float32 rounding of entries ~1e15 1/m^2 leaves
~1e8 along the ray, above the prior 1/prior_sigma^2 = 1e6 that alone fixes that direction for a
sample seen once (the regularised C turned indefinite and the score NaN).

Resumable. With a `BlockStore` (`vdo design` keeps one beside its output folder), each judged
block is written to disk as it comes (`KEY/START.npz`, atomically), KEY a digest of what the
judgement reads: the experiment, the size and time of every file it names, the block size and
vdo's version. A run interrupted after some blocks, started again with the same experiment and
output folder, loads those blocks (bit for bit what was judged) and judges only the others, so it
ends with the layout of an uninterrupted run; the store is removed once the run folder is written.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import mmap
import os
import uuid
from functools import cached_property
from dataclasses import dataclass, field, fields, replace
from importlib import metadata
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from vdo.search import loadpath
from vdo import constraints, objective
from vdo.physics import measured, usable
from vdo.model.camera import Camera
from vdo.model.pose import look_at_angles
from vdo.config.experiment import Experiment
from vdo.config.rig import BodySpec, CameraSpec
from vdo.config.mounts import inside_keep_out, zone_grid
from vdo.geometry.keyframes import at_step, load_path_of
from vdo.physics.lighting import illuminate
from vdo.physics.predict import samples_for_objective, settings, view_data
from vdo.core.configure import configure
from vdo.core.progress import bar
from vdo.scene import build_scene
from vdo.search.obstruction import CLEARANCE_SPACING, keep_clear, surface_points
from vdo.state import Geometry, prepare
from vdo.state import bodies as bodies_of
from vdo.physics.visibility import compute_visibility
from vdo.core.tolerances import TINY

log = logging.getLogger(__name__)

MERGE_TARGETS_M = 0.2   # region centres closer than this share one aim point
SPOT_M = 0.2            # two optical centres closer than this are one physical spot
BLIND = "blind (no sample in view at rest)"   # why a blind candidate is dropped (dropped_per_mount)
PAIRS_PER_BLOCK = 1_000_000  # (candidate, sample) pairs judged at once (dense arrays of one block)
ENTRY_CHUNK = 1 << 18        # stored entries per chunk of a pass over them (score, bound, tables):
                             # a pass's per-entry temporaries live for one chunk, not for all pairs
# [design] score = "measured": each candidate's footprint reduced to its singular values on 1/8-octave
# steps (`vdo.physics.measured.noise_inflation`'s lattice): the built-in beam-column's 1,666
# candidates meet 350 correlation models (6,642 on the optimizer's lattice), sqrt(kappa) within
# 4.4 % of the exact footprint's (p95; 9 % at most) on 80 candidate footprints
KAPPA_OCTAVE = 1.0 / 8
KAPPA_LATTICE = (KAPPA_OCTAVE, None)


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
    candidate would see but an obstacle hides (its obscuration); framed (K,) whether every region
    it sees over at least assign_fraction of its area (`vdo.constraints.assignments`) lies in its
    image over at least 1 - max_obscuration of the area facing it (the field-of-view check of
    `vdo.constraints.check`); path_lost (K,) the fraction of its usable samples at rest that the
    load path's keyframes take away; pruned: how many blind candidates (no sample in view at
    rest) were dropped."""

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
    framed: np.ndarray
    path_lost: np.ndarray
    pruned: int = 0
    dropped: dict = field(default_factory=dict)   # {mount: {reason: count}} of the poses left out

    @property
    def positions(self) -> np.ndarray:
        return np.array([c.position for c in self.cameras]).reshape(-1, 3)

    @property
    def axes(self) -> np.ndarray:
        return np.array([c.optical_axis for c in self.cameras]).reshape(-1, 3)

    @cached_property
    def row(self) -> np.ndarray:
        """(E,) int32 the candidate of each stored entry, computed once."""
        return np.repeat(np.arange(len(self.cameras), dtype=np.int32), np.diff(self.indptr))

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

    def sums(self, rows, scale=None) -> tuple[np.ndarray, np.ndarray]:
        """(N, 6) information and (N,) weights summed over the candidates `rows`, each times its
        `scale` (len(rows),) where given."""
        info, cover = np.zeros((self.samples, 6)), np.zeros(self.samples)
        for k, i in enumerate(rows):
            s = slice(self.indptr[i], self.indptr[i + 1])
            a = 1.0 if scale is None else scale[k]
            info[self.index[s]] += a * self.entry_info[s]
            cover[self.index[s]] += a * self.entry_weight[s]
        return info, cover

    @cached_property
    def usable_entries(self) -> np.ndarray:
        """(E,) bool: each stored pair is a usable view (w >= USABLE_WEIGHT,
        `vdo.physics.usable.usable_views`), computed once."""
        return usable.usable_views(self.entry_weight)

    def usable_sums(self, rows) -> np.ndarray:
        """(N,) the usable views of each sample among the candidates `rows` (as `sums`)."""
        count = np.zeros(self.samples)
        for i in rows:
            s = slice(self.indptr[i], self.indptr[i + 1])
            count[self.index[s]] += self.usable_entries[s]
        return count

    def regions_seen(self, region: np.ndarray, regions: int) -> np.ndarray:
        """(K, regions) True where the candidate is a usable view of a sample of the region
        (`region` (N,) each sample's), ENTRY_CHUNK entries at a time."""
        K = len(self.cameras)
        out = np.zeros(K * regions, dtype=bool)
        for lo in range(0, len(self.index), ENTRY_CHUNK):
            part = slice(lo, lo + ENTRY_CHUNK)
            use = self.usable_entries[part]
            out[self.row[part][use].astype(np.int64) * regions + region[self.index[part][use]]] = True
        return out.reshape(K, regions)

    def usable_counts(self) -> np.ndarray:
        """(K,) how many samples each candidate sees usably (w >= USABLE_WEIGHT)."""
        return np.bincount(self.row[self.usable_entries], minlength=len(self.cameras))


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


def spots(exp: Experiment) -> list[tuple]:
    """Where candidates stand: (mount name, kind, u, offset (3,), optical centre (3,)) for
    `rail_positions` values of u on every rail (u = 1 left out on a closed rail: it is u = 0) (with `offset_m`, and its mirror below the bar),
    the `zone_grid` of every zone mount, every fixed mount, and every [[camera]] given by
    position_m on no mount; not the mounts of the [[light]]s."""
    d = exp.design
    lit = {lt.mount for lt in exp.lights if lt.mount is not None}
    heads = [d.offset] + ([d.offset * [1, 1, -1]] if d.offset[2] != 0 else [])
    out = [(r.name, "rail", float(u), h, exp.rail(r.name).point(u) + h)
           for r in exp.rails if r.name not in lit for u in r.spread(d.rail_us) for h in heads]
    zero = np.zeros(3)
    for m in (m for m in exp.mounts if m.name not in lit):
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
    cams, rows = [], []
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
    if cams:   # the measure of the layout's clearance check (`vdo.search.obstruction`)
        tree = cKDTree(surface_points(list(meshes), spacing=CLEARANCE_SPACING))
        clear = keep_clear(cams, tree, exp.optimize.clearance)
        for name in dict.fromkeys(r[0] for r in rows):
            of = np.array([r[0] == name for r in rows])
            log.info("mount %s: %d candidate poses, %d dropped for clearance (closer than %g m to a "
                     "mesh)", name or "fixed", of.sum(), (of & ~clear).sum(), exp.optimize.clearance)
            if (of & ~clear).any():
                kept_out[(name or "fixed", "poses within the clearance")] = int((of & ~clear).sum())
        cams = [c for c, ok in zip(cams, clear) if ok]
        rows = [r for r, ok in zip(rows, clear) if ok]
    if cams and exp.keep_outs:   # a pose whose tripod's legs reach into a keep-out (`tripod_checks`' measure)
        on = {m.name: m.tripod for m in exp.mounts if m.tripod is not None}
        table = constraints.tripod_table(cams, [on.get(r[0]) for r in rows])
        if table is not None:
            lows, highs = (np.clip(np.array([getattr(k, a) for k in exp.keep_outs]), -constraints.KEEP_OUT_FAR,
                                   constraints.KEEP_OUT_FAR) for a in ("box_min", "box_max"))
            top, feet = constraints.tripod_legs(np.array([c.position for c in cams]),
                                                np.array([c.optical_axis for c in cams]),
                                                np.array([c.pan for c in cams]), table, xp=np)
            depth = constraints.tripod_depth(top, feet, lows, highs, constraints.TRIPOD_CHECK_POINTS, xp=np)
            inside = table["has"] & (depth > 0).any(axis=1)
            for i in np.flatnonzero(inside):
                key = (rows[i][0], f"poses with tripod legs in keep_out {exp.keep_outs[int(np.argmax(depth[i]))].name!r}")
                kept_out[key] = kept_out.get(key, 0) + 1
            cams = [c for c, bad in zip(cams, inside) if not bad]
            rows = [r for r, bad in zip(rows, inside) if not bad]
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
    path = load_path_of(list(geometry.meshes), load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                        groups=exp.groups)
    steps = () if path is None else loadpath.keyframe_steps(path, exp.design.keyframes)
    moved = []
    for step in steps:      # as `vdo.search.loadpath.path_occlusion`: every keyframe, meshes moved
        g = at_step(geometry, path, step, regions=exp.regions)
        moved.append((g.samples, build_scene(list(g.meshes) + bodies_of(exp, []))))
    light = illuminate(scene, exp.lights, samples, exp.render.ambient_radiance)
    R = len(samples.region_names)
    region_area = scipy.sparse.csr_matrix((samples.area, (np.arange(len(samples)), samples.region)),
                                          shape=(len(samples), R))
    return Judging(exp, geometry, tuple(cams), mount, kind, u, heads, body, tg, aims, scene, bare,
                   steps, tuple(moved), light, samples_for_objective(exp.regions, samples),
                   replace(settings(exp.evaluation), pair_dtype="float64"), region_area, dropped)


@dataclass(frozen=True, eq=False)
class Block:
    """The judgement of candidates [start, stop) (`judge_block`): per candidate the number of
    stored entries (counts), the entries (sample index int32, info (E, 6), weight (E,) float32,
    candidate by candidate, samples ascending), assigned and masked (B, R), framed (B,)
    (`Candidates`), path_lost (B,), and seen (B,) whether it has any entry at rest (before the
    load path)."""

    start: int
    counts: np.ndarray
    index: np.ndarray
    info: np.ndarray
    weight: np.ndarray
    assigned: np.ndarray
    masked: np.ndarray
    framed: np.ndarray
    path_lost: np.ndarray
    seen: np.ndarray

    def unheaped(self) -> "Block":
        """This block with its stored pairs in memory maps of their own (`_unheaped`): a block that
        comes from a Dask worker or from the store is read into the heap first."""
        return replace(self, index=_unheaped(self.index), info=_unheaped(self.info), weight=_unheaped(self.weight))

    @staticmethod
    def join(blocks: list["Block"]) -> "Block":
        """One block of `blocks`' candidates, in their order (starting where the first does)."""
        return Block(start=blocks[0].start, **{k.name: np.concatenate([getattr(b, k.name) for b in blocks])
                                               for k in fields(Block) if k.name != "start"})


def inflation(exp: Experiment, cams, samples, visible, light, speckle) -> np.ndarray | None:
    """[design] score = "measured": (B, N) √κ per (candidate, sample), the factor on the sensor
    noise that divides each candidate's information by κ, its measured error over the bound at its
    median footprint in each region (`vdo.physics.measured.noise_inflation`, over the samples it
    sees at rest, `visible` (B, N), its footprint on KAPPA_LATTICE); None (the bound) for
    "bound". A candidate's κ depends on it alone, not on the block it is judged in nor on the
    process's model cache. The candidates carry the lens that `vdo design` writes (`vdo.design.select.camera_specs`: no f_number, so f/8 in focus is assumed, as
    `vdo evaluate` then assumes for the designed layout)."""
    if exp.design.score != "measured":
        return None
    specs = tuple(CameraSpec(name=c.name, sensor_width=c.pixel_size * c.width,
                             pixels=(c.width, c.height), focal_length=c.focal_length) for c in cams)
    return measured.noise_inflation(specs, exp.evaluation, exp.speckle, exp.sensor, exp.analysis,
                                    cams, samples, visible, light, speckle, lattice=KAPPA_LATTICE)


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
    views = view_data(exp.speckle, exp.sensor, j.smp, vis, j.light, j.geometry.speckle,
                      noise_scale=inflation(exp, cams, samples, vis.visible, j.light,
                                            j.geometry.speckle))
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
    per_region = lambda mask: (j.region_area.T @ mask.T.astype(float)).T     # noqa: E731  (B, R) m^2
    masked = per_region(hidden) / np.maximum(per_region(bare), TINY)
    facing = vis.in_front & vis.facing
    claims = per_region(vis.visible) / np.maximum(area, TINY) >= exp.optimize.assign_fraction
    inside = per_region(facing & vis.in_image) / np.maximum(per_region(facing), TINY)
    framed = ~(claims & (inside < 1 - exp.optimize.max_obscuration)).any(axis=1)
    keep = (weight != 0) | (info != 0).any(axis=-1)
    return Block(start, np.bincount(cam[keep], minlength=B), _unheaped(index[keep].astype(np.int32)),
                 _unheaped(info[keep]), _unheaped(weight[keep]), assigned, masked, framed, lost, seen)


def _unheaped(a: np.ndarray) -> np.ndarray:
    """`a` copied into an anonymous memory map of its own: when it is freed its pages go back to
    the system at once, where the process heap keeps freed memory (`vdo.core.memory`), so that
    `collect` holds each stored pair about once (a block's copy is unmapped as the whole grows)."""
    if a.nbytes == 0:
        return a
    out = np.frombuffer(mmap.mmap(-1, a.nbytes), dtype=a.dtype).reshape(a.shape)
    out[...] = a
    return out


def _named_files(value, out: list) -> list:
    """(path, size, mtime_ns) of every existing file an experiment's dict names, in its order."""
    if isinstance(value, dict):
        for v in value.values():
            _named_files(v, out)
    elif isinstance(value, (list, tuple)):
        for v in value:
            _named_files(v, out)
    elif isinstance(value, str) and os.path.isabs(value) and os.path.isfile(value):
        info = os.stat(value)
        out.append((value, info.st_size, info.st_mtime_ns))
    return out


@dataclass(frozen=True)
class BlockStore:
    """Judged blocks kept in `folder` (module docstring, "Resumable"): `folder/key/START.npz`."""

    folder: Path
    key: str

    @classmethod
    def of(cls, folder: Path, exp: Experiment, size: int, count: int) -> "BlockStore":
        """The store in `folder` for `exp`'s `count` candidates judged in blocks of `size`: its
        key the SHA-256 of the experiment's canonical JSON, the files it names (size, mtime),
        `size`, `count` and vdo's version."""
        data = exp.to_dict()
        try:
            version = metadata.version("vdo")
        except metadata.PackageNotFoundError:
            version = "unknown"
        text = json.dumps([data, _named_files(data, []), size, count, version], sort_keys=True,
                          default=str)
        return cls(Path(folder), hashlib.sha256(text.encode()).hexdigest()[:24])

    def path(self, start: int) -> Path:
        return self.folder / self.key / f"{start}.npz"

    def load(self, start: int) -> "Block | None":
        """The block that starts at candidate `start`, or None when not stored (or unreadable)."""
        try:
            with np.load(self.path(start)) as f:
                return Block(start=int(f["start"]), **{k.name: f[k.name] for k in fields(Block)
                                                       if k.name != "start"})
        except (OSError, KeyError, ValueError):
            return None

    def save(self, block: "Block") -> None:
        """Write `block` atomically (a temporary file renamed over the final one)."""
        target = self.path(block.start)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.stem}.{os.getpid()}.npz")
        np.savez(tmp, **{k.name: getattr(block, k.name) for k in fields(Block)})
        os.replace(tmp, target)


def block_size(samples: int) -> int:
    """Candidates per block: PAIRS_PER_BLOCK pairs (at least one candidate)."""
    return max(1, PAIRS_PER_BLOCK // max(samples, 1))


def collect(j: Judging, blocks: list[Block]) -> Candidates:
    """The `Candidates` of `j` from its blocks (in any order), blind candidates (no sample in view
    at rest) dropped. The stored pairs are copied into their final arrays block by block and
    each block is taken out of `blocks` as it is copied (the list is emptied), so that the pairs
    are held about once, not twice (a block's and the whole)."""
    blocks.sort(key=lambda b: b.start)
    R = len(j.geometry.samples.region_names)
    cat = (lambda f, empty: np.concatenate([f(b) for b in blocks]) if blocks else empty)
    seen = cat(lambda b: b.seen, np.zeros(0, bool))
    counts = cat(lambda b: b.counts, np.zeros(0, int))
    keep = np.flatnonzero(seen)
    pick = lambda seq: tuple(seq[i] for i in keep)                        # noqa: E731
    small = dict(assigned=cat(lambda b: b.assigned, np.zeros((0, R), bool))[keep],
                 masked=cat(lambda b: b.masked, np.zeros((0, R)))[keep],
                 framed=cat(lambda b: b.framed, np.zeros(0, bool))[keep],
                 path_lost=cat(lambda b: b.path_lost, np.zeros(0))[keep])
    total = int(counts.sum())                   # blind candidates have no entries
    index, info, weight = np.empty(total, np.int32), np.empty((total, 6)), np.empty(total, np.float32)
    at = 0
    while blocks:
        b = blocks.pop(0)
        n = len(b.index)
        index[at:at + n], info[at:at + n], weight[at:at + n] = b.index, b.info, b.weight
        at += n
        del b
    return Candidates(
        pick(j.cams), pick(j.mount), pick(j.kind), j.u[keep], j.heads[keep], j.body[keep],
        j.target[keep], j.aims, len(j.geometry.samples),
        np.concatenate([[0], np.cumsum(counts[keep])]).astype(np.int64), index, info, weight,
        small["assigned"], small["masked"], small["framed"], small["path_lost"],
        pruned=int(len(seen) - len(keep)), dropped=_with_blind(j, seen))


def _with_blind(j: Judging, seen: np.ndarray) -> dict:
    """A copy of `j.dropped` ({mount: {reason: count}}) with the blind candidates (`seen` False)
    counted per mount."""
    out = {name: dict(reasons) for name, reasons in j.dropped.items()}
    for name, count in per_mount(j.mount, ~seen).items():
        out.setdefault(name, {})[BLIND] = count
    return out


def per_mount(mount, mask: np.ndarray) -> dict[str, int]:
    """{mount name ("fixed" for a [[camera]]'s own position): how many of the candidates in
    `mask` stand on it}."""
    names = np.array([m or "fixed" for m in mount], dtype=object)[mask]
    return {str(n): int(c) for n, c in zip(*np.unique(names, return_counts=True))}


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
        geometry = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=spacing)),
                           spacing_field="design.sample_spacing_mm")
        _WORKER.update(token=token, judging=judging(exp, geometry))
    return judge_block(_WORKER["judging"], start, stop)


def judge(exp: Experiment, geometry: Geometry, j: Judging | None = None, client=None,
          threads: int | None = None, store: Path | None = None) -> Candidates:
    """Every candidate's information and weights on `geometry`'s samples (module docstring), in
    blocks of `block_size` candidates, stored sparsely; with progress bars when the module logger
    passes INFO (`vdo.core.progress`). With a dask.distributed `client`, the blocks are tasks on
    its workers (`remote_block`; `geometry` must then be `exp` sampled at [design]
    sample_spacing_mm, as `vdo.design.select.design_layout` does) and come back in any order:
    the same result. With `store` (a folder), each judged block is kept there and the blocks
    found there for this experiment are not judged again (`BlockStore`)."""
    j = judging(exp, geometry) if j is None else j
    size = block_size(len(geometry.samples))
    kept = None if store is None else BlockStore.of(store, exp, size, len(j.cams))
    blocks, starts = [], []
    for s in range(0, len(j.cams), size):
        block = None if kept is None else kept.load(s)
        block = None if block is None else block.unheaped()
        if block is None:
            starts.append(s)
        else:
            blocks.append(block)
    if blocks:
        log.info("resumed: %d of %d candidate blocks judged before (%s)", len(blocks),
                 len(blocks) + len(starts), kept.folder)
    if client is None:
        for s in bar(log, iterable=starts, desc="candidates", unit="block", leave=False):
            blocks.append(judge_block(j, s, min(s + size, len(j.cams))))
            if kept is not None:
                kept.save(blocks[-1])
    elif starts:
        from distributed import as_completed

        token = uuid.uuid4().hex
        shared = client.scatter(exp, broadcast=True)
        # no list of the futures kept here: a block's result is freed on its worker once taken
        pending = as_completed([client.submit(remote_block, shared, token, s, min(s + size, len(j.cams)),
                                              threads, key=f"vdo-design-{token}-{s}", pure=False)
                                for s in starts])
        for f in bar(log, iterable=pending, total=len(starts),
                     desc="candidates (dask)", unit="block", leave=False):
            blocks.append(f.result().unheaped())
            if kept is not None:
                kept.save(blocks[-1])
    if len(j.steps):
        log.info("load path: %d keyframe(s) %s judged for the candidates' occlusion", len(j.steps), j.steps)
    return collect(j, blocks)
