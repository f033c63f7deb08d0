"""Designing a layout from scratch: the selection of cameras from candidate poses (`vdo design`).

The pieces: where candidates stand and their one judgement (`vdo.design.candidates`), the score
of a set of them (`vdo.design.score`), the rules a selected set keeps (`vdo.design.feasibility`)
and the time and memory the design will take, estimated before the work (`vdo.design.budget`).

Selection. Greedy forward selection adds the feasible candidate (`vdo.design.feasibility`) with
the lowest score (`vdo.design.score`), then exchange passes replace one selected camera by the
best feasible candidate while that lowers the score. The score is smooth and averages over the
samples; what a user reads is the worst scored region's σ_max p95, and swaps the score rates
nearly equal can move it by a third (the steel beam: 0.398 -> 0.279 µm). So a polish follows
(`vdo.design.polish`): swap passes on that figure, from the candidates' sums, that keep the area seen by
min_cameras; the polished layout is kept when its judgement (bodies and tripods included) reads
better too. Obscuration by other camera bodies and
tripods is not judged during selection; the designed layout is judged whole (bodies and tripods
included) with `vdo.state.layout_state` at [evaluation]'s sample spacing, and with every
constraint check of `vdo optimize` (`vdo.optimize.layout_checks`, constraints.json).

How many cameras. The greedy order and exchange passes per count give the best layout for every
count from `[design] min_cameras` to the inventory, the inventory's count first: with a time limit
the counts left when it comes are not searched (said in `problems`), so the layout of the whole
inventory is always there; `pareto.csv` holds, per count, sigma_max p95 over the scored regions
(the worst region's p95, at the selection spacing, camera bodies included) and the area fraction
seen by its region's min_cameras. With `target_sigma_um` the smallest count
that meets it with full coverage is reported.

The bound. Per count, `vdo.design.bound` relaxes the selection to weights in [0, 1] (body counts
and obscuration kept, then the spot, axis-angle and tripod rules among the candidates it weighs)
and certifies a lower bound on the score of every selection of that many cameras; `design.json`
(curve, bound, gap_to_bound), pareto.csv, the console and pareto.png give the gap
1 - bound / score ([design] bound_s seconds per count). The
relaxation's weights are also a second start for each count (`vdo.design.moves.rounded`: the
candidates by decreasing weight while feasible, then the exchange and the polish): its selection
replaces the count's when it scores lower ("rounded" in design.json's curve); so does the best
selection of the outer approximation (`vdo.design.outer`: a mixed-integer model of the score
from its tangent planes at the relaxation's weights, its mix of selections, the count's
selection and the tree's, over sample groups `outer.sample_groups`; on the inventory's count,
OUTER_SHARE of the branch and bound's seconds) ("outer"), and, on the inventory's count, the
best of the selections the branch and bound met (at most 8, the best first), each taken down by
the exchange passes, when it scores lower than the count's ("branched"). Then random restarts
(`moves.restarts`, [design] restart_s seconds per count): starts drawn from the weights, a tenth of
each draw spread over all candidates, each taken down by the exchange passes; the best (exchanged
over all candidates, polished and judged as `_count` does) replaces the count's selection when it
scores lower, as the rounded start does ("restarts" and "restarted" in the curve); the console says
when it reads worse on the worst scored region's p95 or on the area seen by min_cameras (the score
weighs the two, `coverage_weight`). Exchange passes stop at a local minimum of single swaps, and
the two starts above are two of many: on the holed plate's design problem the greedy start ends
1.57x above the best pair, which restarts find (docs/design.md has the figures).

What no selection can fix is reported naming the region and what is missing (`problems`,
`shortfalls`): an inventory below its min_cameras, no candidate that sees it (at rest or over the
keyframes), fewer candidate spots seeing it than its min_cameras, a target sigma not reached, a
region the design leaves short of its min_cameras; the best layout is written all the same.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from vdo.design import bound, branch, outer
from vdo.design.budget import Estimate, available_memory, estimate, peak_rss, refuse
from vdo.design.candidates import BLIND, SPOT_M, Candidates, bodies, inventory, judge, judging, lenses
from vdo.design.feasibility import Feasibility
from vdo.design.measures import (SEEN_SHOWN, common_p95, measures, seen_fractions, sharper_smaller_count,
                                 sigma_key)
from vdo.design.score import Scorer
from vdo.design.moves import RESTART_SEED, ROUNDING_RTOL, exchange, greedy, restarts, rounded
from vdo.design.polish import POLISH_RTOL, polish
from vdo.outputs import report
from vdo.model.camera import Camera
from vdo.config.experiment import Experiment
from vdo.config.rig import CameraSpec
from vdo.core.errors import ConfigError, check_time_limit
from vdo.optimize import OptimizeResult, layout_checks, optimize_layout
from vdo.core.progress import bar
from vdo.scene import cameras_of
from vdo.search.anytime import Stop, stop_on_signals
from vdo.state import layout_state, prepare, with_exposure
from vdo.core.tolerances import LIMIT_SLACK

log = logging.getLogger(__name__)

_clock = time.perf_counter      # the design's clock (its time limit; a test moves it)


REFINE_MIN_S = 10.0         # --refine's optimize gets at least this long when the time limit is spent
OUTER_SHARE = 0.25          # the outer approximation's seconds on the inventory's count, of [design] branch_s


def _count(exp: Experiment, cand: Candidates, scorer: Scorer, feas: Feasibility, coarse,
           can_measure, start) -> dict:
    """One count's entry of the curve from the selection `start`: `exchange` passes, then
    `polish` (kept when the judged layout, bodies included, reads better), the layout judged
    (`_judged`) and its score, swaps, lenses and bodies."""
    chosen, score, swaps = exchange(cand, scorer, feas, start)
    judged = _judged(exp, cand, coarse, chosen, can_measure)
    polished, polish_swaps = polish(cand, scorer, feas, coarse.samples, chosen)
    if polish_swaps:     # kept when the judged layout (bodies included) agrees
        again = _judged(exp, cand, coarse, polished, can_measure)
        if _reads_better(again, judged, sigma_key(exp)):
            chosen, score, judged = polished, scorer.of(cand, polished), again
        else:
            polish_swaps = 0
    return {"cameras": len(start), "score": score, "swaps": swaps, "polish_swaps": polish_swaps,
            "chosen": chosen,
            "lenses_mm": " ".join(f"{cand.cameras[i].focal_length * 1e3:g}" for i in chosen),
            "bodies": " ".join(bodies(exp)[cand.body[i]].name for i in chosen), **judged}


def _judged(exp: Experiment, cand: Candidates, coarse, chosen, can_measure) -> dict:
    """`measures` of the chosen candidates judged as a layout on the `coarse` samples (camera
    bodies and tripods included)."""
    layout = designed(exp, cand, chosen)
    return measures(layout_state(coarse, cameras_of(layout.camera_specs, layout.rails)), exp,
                    can_measure)


def _reads_better(a: dict, b: dict, key: str) -> bool:
    """Judged figures `a` read better than `b`: no less area seen by min_cameras, and the worst
    scored region's p95 (`key`) lower (a measured region against an unmeasured one counts as
    lower)."""
    if a["coverage"] < b["coverage"] - LIMIT_SLACK:
        return False
    return a[key] is not None and (b[key] is None or a[key] < b[key])


def _reads_no_worse(a: dict, b: dict, key: str) -> bool:
    """Judged figures `a` read no worse than `b`: no less area seen by min_cameras, and the worst
    scored region's p95 (`key`) no higher (beyond POLISH_RTOL; measured where `b` is)."""
    if a["coverage"] < b["coverage"] - LIMIT_SLACK:
        return False
    return b[key] is None or (a[key] is not None and a[key] <= b[key] * (1 + POLISH_RTOL))


def _um(value) -> str:
    return "unmeasured" if value is None else f"{value:.3f}"


def camera_specs(exp: Experiment, cand: Candidates, chosen) -> list[CameraSpec]:
    """[[camera]] entries d1, d2, ... for the chosen candidates: rail + u + offset, zone or fixed
    mount + position, or position; each with its body's lens catalogue
    (`vdo.design.candidates.lenses`) as lenses_mm, so that `--refine` chooses among the lenses the
    design chose from."""
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
    views = np.zeros(len(samples), dtype=int)
    for rows in np.split(np.argsort(spot, kind="stable"), np.flatnonzero(np.diff(np.sort(spot))) + 1):
        views += cand.usable_sums(rows) > 0             # one spot at a time: no per-entry arrays
    return views >= need


def problems(exp: Experiment, cand: Candidates, samples) -> list[str]:
    """What no selection can fix, each naming the region and what is missing: an inventory below
    its min_cameras; no candidate that is a usable view of it (at rest, or over the load path's
    keyframes); fewer candidate spots (optical centres SPOT_M apart) seeing it than its
    min_cameras."""
    out, n = [], inventory(exp)
    seen = cand.regions_seen(samples.region, len(exp.regions))
    where = "[design] max_cameras" if exp.design.max_cameras else \
        ("the [[body]] counts" if exp.bodies else "the [[camera]] count")
    for r, spec in enumerate(exp.regions):
        need = spec.min_cameras
        if need > n:
            out.append(f"region {spec.name!r} needs {need} cameras (min_cameras) but the inventory "
                       f"has {n} ({where}): add {need - n} camera bod{'y' if need - n == 1 else 'ies'}")
        seeing = np.flatnonzero(seen[:, r])
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
                  time_limit: float | None = None, client=None, threads: int | None = None,
                  store: Path | None = None) -> DesignResult:
    """Design a layout (module docstring); returns the `DesignResult` that `vdo.commands.design`
    writes as designed.toml, layout.json, summary.json, constraints.json, candidates.csv,
    pareto.csv, pareto.png, design.json and report.html (this function writes nothing). With
    `refine`, also `vdo.optimize.optimize_layout` of the designed layout (`DesignResult.refined`,
    written into out/refine, within what is left of `time_limit`; its constraints.json "before"
    holds every constraint check of the designed layout). Before the work, the time and memory
    it will take are estimated (`vdo.design.budget.estimate`, one INFO line) and a problem that
    needs more than `memory_limit` bytes (default: `vdo.design.budget.available_memory`), or
    whose judging needs more than `time_limit` seconds, is refused (`vdo.design.budget.refuse`:
    ConfigError naming the spacing and the candidate count that fit). The selection then stops
    at the time limit: the inventory's count is searched first, the smaller counts while time is
    left (each assumed to take as long as the last one; kept for the final judgement: the first
    preparation's time times the ratio of the design's spacing to [evaluation]'s, and twice the
    first count's), and the bounds and restarts share what is left (module docstring). With a
    dask.distributed `client` the candidates are judged on its workers
    (`vdo.design.candidates.judge`; `threads` Dr.Jit threads each). With `store` (a folder) the
    judged candidate blocks are kept there, and those of an interrupted run of the same
    experiment are not judged again (`vdo.design.candidates.BlockStore`). Progress and the
    chosen cameras: INFO lines and bars through the module logger; each problem found (also in
    the result): a warning."""
    check_time_limit(time_limit)
    t0 = _clock()
    deadline = math.inf if time_limit is None else t0 + time_limit
    d = exp.design
    n_max = inventory(exp)
    coarse = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=d.sample_spacing)),
                     spacing_field="design.sample_spacing_mm")
    # the final judgement prepares the designed layout at [evaluation]'s spacing: its time, scaled
    # by the spacings' ratio (measured: the vessel's 30 -> 8 mm preparation 0.79 -> 2.8 s, not 14x)
    final_prepare_s = (_clock() - t0) * max(1.0, d.sample_spacing / exp.evaluation.sample_spacing)
    j = judging(exp, coarse)
    scorer = Scorer(exp, coarse.samples)
    est = estimate(exp, j, scorer)
    log.info(est.line())
    refuse(exp, est, available_memory() if memory_limit is None else memory_limit, time_limit)
    t_judge = _clock()
    cand = judge(exp, coarse, j, client=client, threads=threads, store=store)
    K, N = len(cand.cameras), cand.samples
    judged_s = _clock() - t_judge
    log.info("%s candidates x %s samples (%g mm) judged in %.0f s (%.0f s since the start, the "
             "samples and the estimate before)", f"{K:,}", f"{N:,}", d.sample_spacing * 1e3, judged_s,
             _clock() - t0)
    for name, reasons in cand.dropped.items():       # (the other reasons say their own line)
        if BLIND in reasons:
            log.info("mount %s: %d candidate(s) left out: %s", name, reasons[BLIND], BLIND)
    issues = problems(exp, cand, coarse.samples)
    for msg in issues:
        log.warning(msg)
    if K == 0:
        raise ConfigError(exp.path, "design", (
            f"none of the {cand.pruned} candidate poses that keep their clearance sees a sample: add "
            "a [[mount]] or [[rail]] in view of the regions") if cand.pruned else (
            "no candidate pose keeps its clearance: add a [[mount]] or [[rail]] clear of the meshes"))
    feas = Feasibility(exp, cand, coarse.samples)
    for name, reasons in feas.left_out().items():
        for reason, count in reasons.items():
            cand.dropped.setdefault(name, {})[reason] = count
            log.info("mount %s: %d candidate(s) left out: %s", name, count, reason)
    can_measure = measurable(exp, cand, coarse.samples)
    log.info("%.0f %% of the regions' area can be measured from the candidate spots (%d+ views); "
             "the camera-count curve is over that area", 100 * coarse.samples.area[can_measure].sum()
             / coarse.samples.area.sum(), exp.evaluation.min_cameras)
    t_search = _clock()
    order, _ = greedy(cand, scorer, feas, n_max)
    curve, count_s, final_s, skipped = [], 0.0, 0.0, []
    counts = list(range(len(order), min(d.min_cameras, len(order)) - 1, -1))      # the inventory first
    for n in bar(log, iterable=counts, desc="counts", leave=False):
        if curve and _clock() + count_s + final_s > deadline:      # this count, and the final judgement
            skipped = [m for m in counts if m <= n]
            break
        started = _clock()
        curve.append(_count(exp, cand, scorer, feas, coarse, can_measure, order[:n]))
        count_s = _clock() - started
        # the final judgement of the inventory's layout; twice with [exposure] free (its step
        # judges the layout once more and searches the stops)
        final_s = final_s or (final_prepare_s + 2 * count_s) * (2 if exp.exposure.free else 1)
    best = curve[0]                     # the inventory's count
    curve.reverse()
    if skipped:
        done = [c["cameras"] for c in curve]
        issues.append(f"the time limit of {time_limit:g} s came before the camera counts "
                      f"{skipped[-1]}..{skipped[0]} were searched: the curve holds "
                      f"{done[0]}{'' if len(done) == 1 else f'..{done[-1]}'} cameras (a longer "
                      "--time-limit searches them)")
        log.warning(issues[-1])
    remaining = max(0.0, deadline - _clock() - final_s)     # before the final judgement
    branch_s = min(d.branch_seconds, remaining / 2)         # the inventory's count's branch and bound
    left = (remaining - branch_s) / len(curve)              # per count
    # the bounds, the further starts and the restarts: Ctrl-C or SIGTERM ends them early and the
    # best layout so far is judged and written (a second Ctrl-C aborts without writing)
    stop = Stop()
    with stop_on_signals(stop):
        relaxed = relax_curve(cand, scorer, feas, curve, min(d.bound_seconds, left), branch_seconds=branch_s,
                              stop=stop)
        for c, b in zip(curve, relaxed):
            if b is None:
                continue
            # more starts: the relaxation's weights rounded, the outer approximation's selection
            # (below), and the best of the selections its branch and bound met, each taken down by
            # the exchange passes first (after Ctrl-C, all but the outer approximation: they take seconds)
            starts = [("the relaxation's rounding", "rounded", rounded(cand, scorer, feas, b.weights, c["cameras"]))]
            if c is best and branch_s > 0 and _clock() + count_s + final_s < deadline and not stop():
                # the selection the score's tangent planes at the relaxation's weights, its mix, the
                # count's selection and the tree's rate best (`vdo.design.outer`), on the inventory's
                # count, OUTER_SHARE of the branch and bound's time
                o = outer.search(scorer.term, cand, None, c["cameras"], feas.alone, feas.body, feas.counts,
                                 feas.placement, feas.admits, outer.sample_groups(np.asarray(coarse.samples.points)),
                                 [b.weights, c["chosen"]] + list(b.mix) + list(b.found or []),
                                 min(branch_s * OUTER_SHARE, max(deadline - _clock() - count_s - final_s, 0.0)),
                                 stop=stop)
                if o.chosen is not None:
                    starts.append(("the outer approximation", "outer", o.chosen))
            met, met_score = None, math.inf
            for v in b.found or []:
                if _clock() + count_s + final_s > deadline:
                    break
                chosen, score, _ = exchange(cand, scorer, feas, list(v))
                if score < met_score:
                    met, met_score = chosen, score
            if met is not None and met_score < c["score"] * (1 - ROUNDING_RTOL):
                starts.append(("the best of the branch and bound's selections", "branched", met))
            for what, key, start in starts:
                if _clock() + count_s + final_s > deadline:
                    break
                again = _count(exp, cand, scorer, feas, coarse, can_measure, start)
                if again["score"] < c["score"] * (1 - ROUNDING_RTOL):
                    log.info("%d cameras: %s scores %.4g against %.4g: gap %.1f -> %.1f %%", c["cameras"], what,
                             again["score"], c["score"], 100 * c["gap"],
                             100 * max(0.0, 1.0 - c["bound"] / again["score"]))
                    c.update(again, bound=c["bound"], gap=max(0.0, 1.0 - c["bound"] / again["score"]),
                             bound_converged=c["bound_converged"], rounded=key == "rounded",
                             branched=key == "branched", outer=key == "outer")
        rng = np.random.default_rng(RESTART_SEED)
        for i, (c, b) in enumerate(zip(curve, relaxed)):     # random restarts, the bound's weights as a guide
            per_count = (deadline - _clock() - final_s) / (len(curve) - i)
            seconds = min(d.restart_seconds, per_count)
            if d.restart_seconds <= 0 or seconds <= count_s or stop():
                continue
            chosen, score, starts = restarts(cand, scorer, feas, None if b is None else b.weights,
                                             c["cameras"], seconds - count_s, rng, stop=stop)
            c["restarts"] = starts
            again = None
            if score < c["score"] * (1 - ROUNDING_RTOL):    # over all candidates, polished, judged
                again = _count(exp, cand, scorer, feas, coarse, can_measure, chosen)
            if again is not None and again["score"] < c["score"] * (1 - ROUNDING_RTOL):
                key = sigma_key(exp)
                gap = None if c["bound"] is None else max(0.0, 1.0 - c["bound"] / again["score"])
                traded = "" if _reads_no_worse(again, c, key) else (
                    f" (the score trades: worst scored region's p95 {_um(again[key])} against "
                    f"{_um(c[key])} um, area seen by min_cameras {100 * again['coverage']:.1f} against "
                    f"{100 * c['coverage']:.1f} %)")
                log.info("%d cameras: %d random restarts score %.4g against %.4g%s%s", c["cameras"], starts,
                         again["score"], c["score"], "" if gap is None else
                         f": gap {100 * c['gap']:.1f} -> {100 * gap:.1f} %", traded)
                c.update(again, bound=c["bound"], gap=gap, bound_converged=c["bound_converged"],
                         rounded=c.get("rounded", False), restarts=starts, restarted=True)
    if stop.reason == "interrupted":
        issues.append("the search was interrupted (Ctrl-C or SIGTERM): the bounds and the branch and "
                      "bound ended where they stood (the bound and gap written are theirs), the outer "
                      "approximation and the restarts were not run; the best layout met is written")
        log.warning(issues[-1])
    common_p95(exp, coarse.samples, curve)
    sharper = sharper_smaller_count(exp, curve, best)
    if sharper:
        issues.append(sharper)
        log.warning(sharper)
    searched_s = _clock() - t_search
    search_peak = peak_rss()      # what the estimate covers: judging and selection
    target = None
    if d.target_sigma_um is not None:
        key = sigma_key(exp)
        name = "sigma_measured" if key != "sigma_p95_um" else "sigma_max"
        ok = [c for c in curve if c[key] is not None and
              c[key] <= d.target_sigma_um and c["coverage"] >= 1 - LIMIT_SLACK]
        target = ok[0]["cameras"] if ok else None
        sharp = [c for c in curve if c[key] is not None and c[key] <= d.target_sigma_um]
        scored = ", ".join(repr(r) for r in (exp.optimize.regions or [r.name for r in exp.regions]))
        if target is None and sharp:     # sigma is met, the coverage of every region is not
            issues.append(f"target {name} p95 {d.target_sigma_um:g} um is reached on region(s) "
                          f"{scored} from {sharp[0]['cameras']} cameras ({sharp[0][key]:.4g} um), "
                          f"but no count sees every region by its min_cameras (at most "
                          f"{100 * max(c['coverage'] for c in curve):.1f} % of the area; the region(s) "
                          "short are named below)")
            log.warning(issues[-1])
        elif target is None:
            reached = "unmeasured" if best[key] is None else f"{best[key]:.4g} um"
            issues.append(f"target {name} p95 {d.target_sigma_um:g} um is not reached on "
                          f"region(s) {scored} with {len(best['chosen'])} cameras (best: {reached}; "
                          "missing: more cameras, longer lenses or closer mounts)")
            log.warning(issues[-1])
    final = designed(exp, cand, best["chosen"])
    settings = None
    if exp.exposure.free:       # f-numbers, exposure times and light power for the chosen layout
        final, settings = with_exposure(final)
        issues.extend(settings.problems)
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
    seen = seen_fractions(state)
    for c in stats["chosen"]:
        c["seen_fraction"] = seen.get(c["camera"], {})
        parts = [f"{r} {100 * f:.0f} %" for r, f in c["seen_fraction"].items() if f >= SEEN_SHOWN]
        log.info("%s: %s, %g mm, %s %s at %s m, sees %s", c["camera"], c["body"], c["focal_mm"], c["kind"],
                 c["mount"], c["position_m"], ", ".join(parts) or "no region usably")
    wall = _clock() - t0
    final_peak = peak_rss()       # before the refinement, as the figures above
    # the refinement gets what is left of the time limit (at least REFINE_MIN_S), else its default
    refined = None if not refine else optimize_layout(final) if math.isinf(deadline) else \
        optimize_layout(final, time_limit=max(REFINE_MIN_S, deadline - _clock()))
    return DesignResult(cameras=len(best["chosen"]), problems=issues, target_count=target,
                        refined=refined, statistics=stats, violations=len(violated), curve=curve,
                        summary=summary, wall_s=wall,
                        exposure=None if settings is None else settings.to_json(),
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
    exposure: dict | None = None           # [exposure] free: the settings (`vdo.physics.exposure`)

    def to_json(self) -> dict:
        """The fields as a JSON dict, `summary` and `refined` as their `to_json()`."""
        return {"cameras": self.cameras, "problems": self.problems, "target_count": self.target_count,
                "refined": None if self.refined is None else self.refined.to_json(),
                "statistics": self.statistics, "violations": self.violations, "curve": self.curve,
                "summary": self.summary.to_json(), "wall_s": self.wall_s, "exposure": self.exposure}


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


def relax_curve(cand: Candidates, scorer: Scorer, feas: Feasibility, curve,
                seconds: float, branch_seconds: float = 0.0,
                stop: Callable[[], bool] | None = None) -> list[bound.Bound | None]:
    """Adds to each count of `curve` the certified lower bound on the score of any selection of
    that many cameras (`vdo.design.bound.relaxation`, body counts and obscuration kept, and the
    spot, axis-angle and tripod rules among the candidates the relaxation weighs,
    `Feasibility.placement`; `seconds` wall seconds per count): "bound", "gap" (1 - bound / score),
    "bound_converged" and "bound_nodes" (the branch and bound's nodes, 0: none); None where
    `seconds` is 0. The score never rises when a camera is
    added, so the best k-camera score is at least the best score of k + 1 cameras within the body
    counts: each count's bound is the largest of its own and the plain bounds (pairwise rules
    dropped) of larger counts (while the relaxation's count grows). The largest count (the
    inventory's, the layout written) then gets `branch_seconds` of branch and bound over the
    candidates' classes (`vdo.design.branch.classes`: aim point, mount, body kind, lens, spot),
    which lifts its bound where the relaxation
    mixes selections (docs/design.md, "The bound"). Once `stop()` is True (Ctrl-C,
    `vdo.search.anytime.Stop`) the branch and bound ends and the counts left get one step of the
    relaxation each (a weaker bound, still a bound). Logs each gap. Returns each count's
    `vdo.design.bound.Bound` (None where `seconds` is 0)."""
    if seconds <= 0:
        for c in curve:
            c.update(bound=None, gap=None, bound_converged=None)
        return [None] * len(curve)
    top = max(c["cameras"] for c in curve)
    groups = branch.classes(cand.target, cand.mount, cand.body, [c.focal_length for c in cand.cameras],
                            cand.positions) if branch_seconds > 0 else None
    stopped = stop if stop is not None else (lambda: False)
    found = [bound.relaxation(scorer.value, cand, None, c["cameras"], feas.alone, feas.body,
                              feas.counts, start=c["chosen"], conflicts=feas.placement,
                              time_limit=0.0 if stopped() else seconds, groups=groups,
                              branch_s=branch_seconds if c["cameras"] == top and not stopped() else 0.0,
                              term=scorer.term, stop=stop)
             for c in bar(log, iterable=curve, desc="bound", leave=False)]
    value, later = [b.value for b in found], 0.0
    for i in reversed(range(len(found))):
        # adding a camera never raises the score, so a bound for every k + 1 cameras within the
        # body counts (uncut; the plain one: a feasible selection plus one camera may break a
        # pairwise rule) bounds k
        value[i] = max(value[i], later)
        later = max(later, found[i].plain) if i == 0 or found[i].cameras > found[i - 1].cameras else 0.0
    for c, b, v in zip(curve, found, value):
        c.update(bound=v, gap=max(0.0, 1.0 - v / c["score"]), bound_converged=b.converged, bound_nodes=b.nodes)
        log.info("%d cameras: score %.4g, no selection below %.4g (relaxation bound%s): gap %.1f %% "
                 "(%d steps, %s)", c["cameras"], c["score"], v,
                 f", {b.nodes} branch-and-bound nodes" if b.nodes else "", 100 * c["gap"], b.iterations,
                 "converged" if b.converged else f"time limit {seconds:g} s")
    return found
