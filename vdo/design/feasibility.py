"""Which candidate cameras may join a selected set (`Feasibility`), for the selection of
`vdo.design.select`.

Feasible with the selected set:
* the inventory: no more cameras of a body kind than its count;
* one camera per spot: no two optical centres closer than SPOT_M (`vdo.design.candidates`; a
  body and its clearance);
* tripods: two cameras on zones with a [mount.tripod] keep their legs `[optimize] clearance_m`
  apart (`vdo.constraints.tripod_gaps`, the measure of the designed layout's "tripod_clearance"
  check; two heights over one floor point share their feet);
* axis angles: two cameras that share a region (each sees at least `[optimize]
  assign_fraction` of its area with usable weight, or the area of it both see usably is at least
  that fraction of the smaller area either sees: all-round regions, `Feasibility`) keep their optical axes at least `[optimize]
  min_axis_angle_deg` apart, by default `vdo.constraints.stereo_min_angle` of the shorter lens,
  and at most `[optimize]` or that region's `max_axis_angle_deg` where set;
* clearance from the meshes (per candidate: `vdo.design.candidates`);
* obscuration: no obstacle hides more than `[optimize] max_obscuration` of a region the
  candidate is assigned (the area fraction it would see on a scene of the specimen alone but not
  on the whole scene: a second ray cast);
* field of view: a region the candidate sees over at least `[optimize] assign_fraction` of its
  area lies in its image over at least 1 - max_obscuration of the area facing it (the check
  `vdo.constraints.check` makes of the designed layout; `Candidates.framed`);
* depth of field, when `[exposure] free` has "aperture" (the f-number is then chosen for the
  layout, `vdo.physics.exposure`): the depth along the optical axis of the candidate's usable
  samples in its assigned regions can be held sharp a third of a stop below the largest stop of
  `[exposure] f_number_range` (`vdo.physics.exposure.aperture_for`, focused at the harmonic
  mean; the margin because the design's samples are coarser than the final judgement's).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

from vdo.design.candidates import SPOT_M, Candidates, bodies, per_mount
from vdo.config.experiment import Experiment
from vdo.constraints import stereo_min_angle, tripod_gaps, tripod_legs, tripod_table
from vdo.geometry import obstacles
from vdo.physics.exposure import aperture_for
from vdo.core.tolerances import LIMIT_SLACK, TINY

ANGLE_TOL = LIMIT_SLACK       # rad: an axis angle this close to its limit meets it
HARDWARE_CHUNK = 256          # candidates' hardware bounds tested against one camera's lines at once
CONE_CHUNK = 1024             # candidates whose sight lines are gathered at once for their cones
STOP_MARGIN = 2 ** (1 / 6)    # a third of a stop: the design's coarser samples see a little less depth


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
            use = cand.usable_entries
            # the usable entries as sight lines: candidate (int32), sample (`hides`); 8 bytes each
            self._sight = (cand.row[use], cand.index[use])
            # the entries are candidate by candidate, samples ascending: CSR as they lie (float32
            # ones and the int32 samples, 8 bytes per usable pair, no COO copies)
            per = np.bincount(self._sight[0], minlength=len(cand.cameras))
            self._seen = scipy.sparse.csr_matrix(
                (np.ones(int(per.sum()), np.float32), self._sight[1],
                 np.concatenate([[0], np.cumsum(per)])), shape=(len(cand.cameras), cand.samples))
            self._region_area = scipy.sparse.csr_matrix(
                (samples.area, (np.arange(len(samples)), samples.region)),
                shape=(len(samples), len(samples.region_names)))
            self._alone = (self._seen @ self._region_area).toarray()
            self._starts = self._seen.indptr           # (K + 1,) each candidate's sight lines
            self._cones = self._sight_cones(samples)
        self.positions, self.axes = cand.positions, cand.axes
        self.limited = [(r, spec.max_axis_angle) for r, spec in enumerate(exp.regions)
                        if spec.max_axis_angle is not None]
        self.obstructed = (cand.assigned & (cand.masked > exp.optimize.max_obscuration)).any(axis=1)
        self.blurred = np.zeros(len(cand.cameras), bool)
        if samples is not None and "aperture" in exp.exposure.free:
            self.blurred = ~self._sharp(samples) & ~self.obstructed & cand.framed
        self.alone = ~self.obstructed & cand.framed & ~self.blurred
        self.body = cand.body
        self.counts = np.array([b.count for b in bodies(exp)])
        self._rows: dict[int, np.ndarray] = {}
        self._placed: dict[int, np.ndarray] = {}
        self._samples = samples
        self._tripods = {m.name: m.tripod for m in exp.mounts}     # rails stand on no tripod
        table = tripod_table(cand.cameras, [self._tripods.get(m) for m in cand.mount])
        self._legs = None if table is None or exp.optimize.clearance <= 0 else (
            table, *tripod_legs(self.positions, self.axes, np.array([c.pan for c in cand.cameras]), table, xp=np))
        self._hardware: dict[int, obstacles.Hardware] = {}
        self._bounds = None   # every candidate's hardware bounding sphere: (centres (K, 3), radii (K,))

    def left_out(self) -> dict:
        """{mount: {reason: count}} of the candidates no selection may hold (`alone` False)."""
        out: dict = {}
        reasons = (("an assigned region obstructed beyond max_obscuration", self.obstructed),
                   ("a region it sees partly outside its image (field of view)",
                    ~self.cand.framed & ~self.obstructed),
                   (f"its assigned regions deeper than the depth of field at "
                    f"f/{self.exp.exposure.f_numbers[1]:g}", self.blurred))
        for reason, mask in reasons:
            for name, count in per_mount(self.cand.mount, mask).items():
                out.setdefault(name, {})[reason] = count
        return out

    def row(self, j: int) -> np.ndarray:
        """(K,) True where a candidate conflicts with candidate j: `placement`'s rules and, with
        the `samples`, the hardware rule (`hides`)."""
        if j not in self._rows:
            conflict = self.placement(j)
            if self._samples is not None:     # the hardware rule only where nothing else conflicts
                conflict = conflict | self.hides(j, among=~conflict)
            self._rows[j] = conflict
        return self._rows[j]

    def placement(self, j: int) -> np.ndarray:
        """(K,) True where a candidate conflicts with candidate j by one spot, the axis angles or
        the tripods (`row` without the hardware rule, which costs most of a row: 0.5-2 s a
        candidate on the steel beam against 50 ms, measured on a loaded machine). Symmetric in the
        two candidates; kept per j, as `row` is (`vdo.design.bound` asks it of the candidates its
        relaxation weighs)."""
        if j not in self._placed:
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
            self._placed[j] = conflict | self.tripods_touch(j)
        return self._placed[j]

    def tripods_touch(self, j: int) -> np.ndarray:
        """(K,) True where candidate j and another both stand on tripods whose legs come closer
        than [optimize] clearance_m (`tripod_gaps`); only candidates whose tripods' footprints
        (spread + leg radius around the top casting, in plan) come within it are measured."""
        out = np.zeros(len(self.cand.cameras), bool)
        if self._legs is None or not self._legs[0]["has"][j]:
            return out
        table, top, feet = self._legs
        reach = table["spread"] + table["radius"]
        plan = np.linalg.norm(top[:, :2] - top[j, :2], axis=1)
        near = np.flatnonzero(table["has"] & (plan < reach + reach[j] + self.exp.optimize.clearance))
        near = near[near != j]
        if len(near):
            out[near] = tripod_gaps(top, feet, table["radius"], j, near) < self.exp.optimize.clearance
        return out

    def hardware(self, k: int) -> obstacles.Hardware:
        """Candidate k's body and tripod (`vdo.geometry.obstacles.hardware`)."""
        if k not in self._hardware:
            self._hardware[k] = obstacles.hardware(self.cand.cameras[k], self._tripods.get(self.cand.mount[k]))
        return self._hardware[k]

    def _sight_cones(self, samples) -> tuple[np.ndarray, np.ndarray]:
        """(centres (K, 3), radii (K,)) m: the box around each candidate's usable samples as a
        ball (its centre and half-diagonal; a candidate with none: its own position, radius 0).
        Every sight line of candidate k lies within radius_k of the segment from its optical
        centre to centre_k (a line's point p + t (x - p), x = c + u with |u| <= r, is t |u| <= r
        from p + t (c - p)): the capsule that `hides` tests a hardware's bounding sphere against
        before any of the lines."""
        K, index, starts = len(self.cand.cameras), self._sight[1], self._starts
        centres, radii = self.cand.positions.copy(), np.zeros(K)
        for lo in range(0, K, CONE_CHUNK):                # CONE_CHUNK candidates' lines at a time
            hi = min(lo + CONE_CHUNK, K)
            has = np.flatnonzero(starts[lo + 1:hi + 1] > starts[lo:hi]) + lo
            if not len(has):
                continue
            pts = samples.points[index[starts[lo]:starts[hi]]]
            at = starts[has] - starts[lo]                 # increasing: one segment per candidate
            low, high = np.minimum.reduceat(pts, at), np.maximum.reduceat(pts, at)
            centres[has], radii[has] = (low + high) / 2, np.linalg.norm(high - low, axis=1) / 2
        return centres, radii

    def _sharp(self, samples) -> np.ndarray:
        """(K,) True where the depth range [near, far] of the candidate's usable samples in its
        assigned regions needs at most the largest stop of [exposure] f_number_range less
        STOP_MARGIN (`aperture_for`); True for a candidate with no such sample."""
        rows, index = self._sight
        keep = self.cand.assigned[rows, samples.region[index]]
        rows, index = rows[keep], index[keep]
        K = len(self.cand.cameras)
        depth = np.einsum("ij,ij->i", samples.points[index] - self.positions[rows], self.axes[rows])
        near, far = np.full(K, np.inf), np.full(K, -np.inf)
        np.minimum.at(near, rows, depth)
        np.maximum.at(far, rows, depth)
        has = np.isfinite(near)
        f = np.array([c.focal_length for c in self.cand.cameras])
        pixel = np.array([c.pixel_size for c in self.cand.cameras])
        need = np.zeros(K)
        need[has] = aperture_for(f[has], pixel[has], near[has], far[has])[0]
        return need <= self.exp.exposure.f_numbers[1] / STOP_MARGIN

    def _lines_of(self, ks: np.ndarray) -> np.ndarray:
        """Positions in `_sight` of the sight lines of candidates `ks`."""
        a, b = self._starts[ks], self._starts[ks + 1]
        n = b - a
        return np.repeat(a - np.concatenate([[0], np.cumsum(n)[:-1]]), n) + np.arange(int(n.sum()))

    def hides(self, j: int, among: np.ndarray | None = None) -> np.ndarray:
        """(K,) True where candidate j's hardware hides more than max_obscuration of an assigned
        region's usable area from a candidate, or that candidate's hardware hides as much from j
        (class docstring); with `among` (K,) bool, only those candidates are judged (the others
        False)."""
        cand, smp, limit = self.cand, self._samples, self.exp.optimize.max_obscuration
        K, R = cand.assigned.shape
        rows, index = self._sight
        hw, (cone_c, cone_r) = self.hardware(j), self._cones
        # j's hardware in front of the lines of sight of the candidates whose sight capsule
        # (`_sight_cones`) its bounding sphere reaches, gathered a chunk at a time (the lines' end
        # points are 48 bytes each: never all of them at once)
        reach = obstacles.point_segment_distance(hw.bound_centre, self.positions, cone_c) < hw.bound_radius + cone_r
        reach[j] = False
        if among is not None:
            reach &= among
        at = self._lines_of(np.flatnonzero(reach))
        lost = np.zeros(len(at), dtype=bool)
        for lo in range(0, len(at), obstacles.LINES_CHUNK):
            part = at[lo:lo + obstacles.LINES_CHUNK]
            lost[lo:lo + len(part)] = obstacles.hidden(self.positions[rows[part]], smp.points[index[part]], hw)
        at = at[lost]
        hidden = np.bincount(rows[at].astype(np.int64) * R + smp.region[index[at]],
                             weights=smp.area[index[at]], minlength=K * R).reshape(K, R)
        frac = hidden / np.maximum(self._alone, TINY)
        out = (cand.assigned & (frac > limit)).any(axis=1)
        # every other candidate's hardware in front of j's lines of sight
        mine = index[self._starts[j]:self._starts[j + 1]]       # the samples j sees usably
        lines = (self.positions[j], smp.points[mine])
        area = smp.area[mine]
        seen = np.bincount(smp.region[mine], weights=area, minlength=R)
        mine_assigned = cand.assigned[j]
        if self._bounds is None:
            every = [self.hardware(k) for k in range(K)]
            self._bounds = (np.array([h.bound_centre for h in every]), np.array([h.bound_radius for h in every]))
        near = np.zeros(K, dtype=bool)
        centres, radii = self._bounds            # only the hardware that reaches j's sight capsule
        close = np.flatnonzero((obstacles.point_segment_distance(centres, self.positions[j], cone_c[j])
                                < radii + cone_r[j]) & (True if among is None else among))
        for lo in range(0, len(close), HARDWARE_CHUNK):   # (chunk, lines) distances from each centre
            ks = close[lo:lo + HARDWARE_CHUNK]
            d = obstacles.point_segment_distance(centres[ks][:, None], lines[0], lines[1][None])
            near[ks] = (d < radii[ks][:, None]).any(axis=1) if d.size else False
        for k in np.flatnonzero(near & ~out):
            if k == j:
                continue
            lost = obstacles.hidden(np.broadcast_to(lines[0], lines[1].shape), lines[1], self.hardware(k))
            if lost.any():
                part = np.bincount(smp.region[mine][lost], weights=area[lost], minlength=R)
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

    def admits(self, selection) -> bool:
        """Whether the cameras of `selection` can join one another in some order, each allowed
        by those before it (`allowed`), as a design adds them. j's row forbids i after j, so i
        must come before j; an order exists when each is allowed alone, the body counts hold and
        those precedences have no cycle (taken apart camera by camera: the next one forbids none
        of those left)."""
        left = [int(i) for i in selection]
        used = np.bincount(self.body[left], minlength=len(self.counts))
        if not self.alone[left].all() or (used > self.counts).any():
            return False
        while left:
            nxt = next((j for j in left if not self.row(j)[[i for i in left if i != j]].any()), None)
            if nxt is None:
                return False
            left.remove(nxt)
        return True

    def allowed(self, chosen) -> np.ndarray:
        """(K,) True for the candidates compatible with every camera in `chosen` and whose body
        kind is not used up by `chosen`."""
        ok = self.alone.copy()
        for j in chosen:
            ok &= ~self.row(j)
        used = np.bincount(self.body[list(chosen)], minlength=len(self.counts))
        return ok & (used < self.counts)[self.body]
