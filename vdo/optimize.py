"""`vdo optimize`: move the cameras on their mounts (rails, zones) to minimise the predicted
uncertainty under the practical constraints of `vdo.constraints`.

Parameters, per moving camera, each only when listed in ``[optimize] free``: its position ("u":
on a rail z_u with u = sigmoid(z_u), or z_u mod 1 round a closed rail, in a zone one sigmoid per axis of its box, so the camera
cannot leave its mount; `Parameterization`), pan, tilt, roll (held at its configured value,
0 = horizontal, unless freed); and, with "lens" free, the focal length, a discrete choice from
``[optimize] lenses_mm`` made in an outer loop (`choose_lenses`). The objective, a JAX function
of the parameter vector θ, is

    J(θ) = a_k score(θ) + μ_k [P_angle + P_fov + P_clearance + P_obscuration + P_shadow](θ)

with `vdo.objective.score` (smooth high percentile of σ_max in µm plus the coverage shortfall) and
the penalties of `vdo.constraints` (`Problem.terms`); each but P_obscuration is 0 exactly where
its constraint holds with a back-off margin (`ANGLE_MARGIN`, `CLEARANCE_MARGIN`, `FOV_MARGIN`,
`SHADOW_MARGIN`): a
quadratic penalty's minimiser always lies a little beyond what the penalty aims at, so aiming
inside the limit puts it on the feasible side. P_fov keeps a smooth in-image area fraction of
each assigned region at least what the hand layout had (minus 1 %, at most 1 - max_obscuration);
P_obscuration = Σ (o / max_obscuration)^2 over the assigned (camera, region) pairs that an
obstacle has masked, o differentiated through Mitsuba (`vdo.search.obscuration`); P_shadow keeps the
camera bodies (covered by spheres) from hiding any part of a light panel from the samples it
lights.

A round is one BFGS solve (optimistix; its line search `RememberingArmijo`) with the ray-cast
occlusion and the lighting frozen; between rounds they are recomputed at the new layout, and the
next round starts from the last one's curvature estimate (inverse Hessian) when its weights are
the same. A round returns its `RoundOutcome` (optimistix's `Solution`, the accepted steps' terms,
how it ended, the curvature). From a start that violates a constraint, feasibility rounds come
first: the penalties alone (a = 0, μ = 1), repeated (at most `FEASIBILITY_ROUNDS`) until the
layout meets every constraint, so that the score never trades against a violation the layout
could shed. Then up to `rounds` rounds with a = 1 and μ = `MU0`, multiplied by 10 after a round
whose layout violates a constraint (a feasible round keeps μ: a larger one only pushes the layout
further inside the limits, at the cost of the score), until a feasible round improves on the
feasible round before it by less than `ROUND_TOL` of the score. Several starts: the hand layout
and randomly perturbed copies. Each round's layout is judged exactly (`judge`: the ray cast, the
score and `constraints.check`), and so is the iterate every `CHECKPOINT_STEPS` steps of a
feasibility round (which ends there once it is feasible) and, when `CHECKPOINT_S` have passed
since the last verdict, of a penalty round, so that the best layout so far is known within a
long round; per start the best one wins (`Result.rank`: feasible first, by score), and the report
names any violation that remains.

Anytime: the solver runs one BFGS step per call and checks a `Stop` (time limit, SIGINT/SIGTERM
via `stop_on_signals`) between steps and rounds; the best judged layout of the run is kept
(`Run.best`) and written whatever ends the search. Compile once: the step is one jitted program
per run and structure (`Run.programs`) that takes every layout-dependent array as an argument
(`Problem.data`), with the pair lists padded to one size (`Run.padded`) and the clearance and
shadow sets to sizes fixed per run (`Run.size`); without tracked obscuration it holds no host
callback, so JAX's persistent compilation cache can serve it to the next run.

The pieces live in `vdo.search`: `parameterisation` (θ <-> camera specs), `problem` (`Problem`,
the penalties, `Run`), `mountmodel` (`MountModel`), `obstruction` (clearances, light lost),
`solver` (rounds, starts, `judge`, `choose_lenses`), `bfgs`
(the step) and `anytime` (`Stop`, `stop_on_signals`, the progress line); this module runs them
(start-up, time limit, the result `optimize_layout` returns; `vdo.commands.optimize` writes its run
folder) and holds the constraint verdict shared with `vdo evaluate` and
`vdo design` (`layout_checks`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from vdo import constraints
from vdo.search import loadpath
from vdo import objective
from vdo.search import reachability
from vdo.outputs import report
from vdo.config.experiment import Experiment, lens_catalogue_errors
from vdo.core.errors import Collect, ConfigError, check_time_limit
from vdo.geometry.keyframes import load_path_of
from vdo.model.camera import Camera
from vdo.search.status import Status
from vdo.physics.lighting import exposure_factors
from vdo.physics.predict import predict
from vdo.state import LayoutState, layout_state, prepare, unobstructed_lighting, with_exposure
from vdo.search.anytime import Progress, Stop, stop_on_signals
from vdo.search.obstruction import (CLEARANCE_SPACING, clearances, light_lost, light_shadowers, obstacle_visibility,
                                   surface_points)
from vdo.search.problem import Problem, Result, State, score_parts
from vdo.search.solver import LENS_TRIALS, choose_lenses, solve

log = logging.getLogger(__name__)


def run_labels(history, verdicts) -> dict[int, str]:
    """The name of each solved run of the search (its "start" index in `history`): "start k" for
    the starts, "lens trial k" for the solves after the lens screening (whose layouts are judged
    under the one index after the starts' and never solved: "the lens screening")."""
    solved = sorted({h["start"] for h in history})
    screening = min((r["start"] for r in verdicts if r["start"] not in solved and solved
                     and r["start"] > solved[0]), default=None)    # judged after a solve, not solved
    trials = [s for s in solved if screening is not None and s > screening]
    labels = {s: f"lens trial {trials.index(s) + 1}" if s in trials else f"start {s + 1}" for s in solved}
    return labels | ({} if screening is None else {screening: "the lens screening"})


def layout_checks(state: LayoutState) -> list[dict]:
    """Every constraint check of `vdo optimize` (`vdo.constraints.check`: axis angles, clearance,
    obscuration, field of view, shadows of the camera bodies, horizontal, on the rail; and
    `vdo.constraints.tripod_checks`: tripods out of the keep-outs and apart) on a layout
    as it stands: the one verdict that `vdo evaluate`, `vdo design` and the optimizer's report
    share. Regions are assigned as in the optimizer (`vdo.constraints.assignments`), the least
    in-image fraction of an assigned region is 1 - max_obscuration, clearances are measured to
    the meshes sampled every `CLEARANCE_SPACING` metres."""
    exp, geometry, samples = state.experiment, state.geometry, state.samples
    opt, cameras = exp.optimize, list(state.cameras)
    assigned = constraints.assignments(state.visibility, samples, opt.assign_fraction)
    pairs, min_angles, max_angles = constraints.angle_limits(
        exp.regions, opt, exp.stereo_pairs, cameras, assigned,
        constraints.sharing(state.visibility, samples, opt.assign_fraction))
    tree = cKDTree(surface_points(list(geometry.meshes), spacing=CLEARANCE_SPACING))
    unlit = unobstructed_lighting(geometry) if exp.lights else None
    lit_without = None if unlit is None else unlit.lit
    specs = {s.name: s for s in exp.camera_specs}
    rails_u = [specs[c.name].u if c.name in specs and specs[c.name].rail is not None else None
               for c in cameras]
    lost = light_lost(lit_without, state.illumination.lit, samples)
    shadowers = (light_shadowers(geometry, cameras, unlit, lost, constraints.SHADOW_LIMIT)
                 if unlit is not None else None)
    return constraints.check(cameras, obstacle_visibility(geometry, cameras), samples, assigned, pairs, min_angles,
                             clearances(cameras, tree), opt.clearance, opt.max_obscuration, lost, rails_u,
                             roll_free="roll" in opt.free, max_angles=max_angles, shadowers=shadowers) \
        + constraints.tripod_checks(cameras, constraints.tripod_table(cameras, constraints.tripods_of(cameras, exp.camera_specs, exp.mounts)),
                                    exp.keep_outs, opt.clearance)


def check_objective(user_objective, exp: Experiment) -> None:
    """Refuse, in one line (`ConfigError`), a user objective that is not callable, not
    JAX-traceable or not a real scalar: it is traced once on four placeholder samples
    (`jax.eval_shape`, no computation) before any heavy work."""
    name = getattr(user_objective, "__name__", type(user_objective).__name__)
    where = f"objective {name}"
    if not callable(user_objective):
        raise ConfigError("optimize_experiment", where, "must be a function of vdo.objective.SampleFields "
                                                        "returning a scalar")
    n, r = 4, len(exp.regions)
    f = jax.ShapeDtypeStruct
    probe = objective.SampleFields(
        information=f((n, 3, 3), jnp.float64), sigma_xyz=f((n, 3), jnp.float64),
        sigma_max=f((n,), jnp.float64), coverage=f((n,), jnp.float64), area=f((n,), jnp.float64),
        region=f((n,), jnp.int64), importance=f((r,), jnp.float64), min_cameras=f((r,), jnp.float64))
    try:
        out = jax.eval_shape(user_objective, probe)
    except Exception as exc:   # any failure to trace: numpy on a tracer, float(), a Python branch
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ConfigError("optimize_experiment", where,
                          f"is not JAX-traceable ({type(exc).__name__}: {first[:160]}); write it with "
                          "jax.numpy on the fields' arrays (no numpy, float() or if on their values)") from None
    shape = getattr(out, "shape", None)
    if shape != () or not jnp.issubdtype(out.dtype, jnp.floating):
        raise ConfigError("optimize_experiment", where,
                          f"returns {'shape ' + str(shape) if shape is not None else type(out).__name__}"
                          f"{'' if shape != () else ' of ' + str(out.dtype)}; return one real "
                          "number, e.g. jnp.sum(fields.area * fields.sigma_max) / jnp.sum(fields.area)")


# --------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------
DEFAULT_TIME_LIMIT = 900.0   # s: `vdo optimize --time-limit`


WRITE_S = 5.0   # s: kept at least for writing the run folder (figures, report) after the search

# Relative rise of a scored region's σ_max p95 (after / before - 1) past which a run whose score
# fell warns that it traded precision for coverage (`precision_traded`): a p95 over a few hundred
# samples moves by a few percent as the views shift, a tenth is a change the lab would notice.
PRECISION_RISE = 0.10


def _wrap_up_s(problem: Problem, judge_s: float, steps: int) -> float:
    """Seconds kept from the time limit for what follows the search: the best layout judged as
    the hand layout was at start-up (`judge_s`: its summary, constraint checks and score parts)
    plus one hand-layout refresh (`Problem.refresh_s`, measured at start-up, its compilations
    included: room for a best layout whose lenses need new programs), the best layout at each of
    the load path's `steps` (a refresh each), and the folder written (`WRITE_S`)."""
    return judge_s + (steps + 1) * problem.refresh_s + WRITE_S


def optimize_layout(exp: Experiment, time_limit: float = DEFAULT_TIME_LIMIT, stop: Stop | None = None,
                    objective=None, started: float | None = None) -> OptimizeResult:
    """Optimize the layout; returns the `OptimizeResult` that `vdo.commands.optimize` writes as
    optimized.toml, layout.json, summary_before/after.json, constraints.json, optimizer.json,
    history.csv, convergence.png and moves.csv (`write_optimization`; this function writes nothing).

    `objective`: a user's function of `vdo.objective.SampleFields` returning a JAX scalar,
    minimised instead of the built-in score with the same constraints, penalty rounds,
    visibility refreshes, starts, lens choice and anytime stop (`MountModel` documents the
    fields' variables); refused in one line when it is not traceable or not a scalar
    (`check_objective`). Scale it like the built-in score (a few units at a good layout, e.g.
    micrometres): the penalties weigh ~1 at a clear violation. The returned (and written)
    score_before/score_after are then its values.

    Anytime: the search ends when every round has run, when the time limit leaves only what
    writing the result needs (`_wrap_up_s`), or on a stop request (SIGINT/SIGTERM while it runs,
    unless the caller passes its own `stop`, which it then owns); in every case the result holds
    the best layout judged so far (feasible first, `Result.rank`), and its `status` says how the
    search ended. `time_limit` (s, > 0) counts the whole run from `started` (a
    `time.perf_counter()` value, default now; the command line passes its own start): start-up
    (meshes, samples, the hand layout's ray cast, lighting and checks) first, then the search
    gets what is left; when start-up leaves nothing, the starting layout is judged and returned,
    with the reason. The log and the result give start-up and search apart (`startup_s`,
    `search_s`). Progress: INFO lines and a bar through the module logger (`vdo.core.progress`)."""
    check_time_limit(time_limit)
    errors = Collect()   # the lens check of `vdo check`, for callers that skip the command line
    errors.errors += lens_catalogue_errors(exp)
    errors.raise_all()
    if objective is not None:
        check_objective(objective, exp)
    own = stop is None
    t_start = time.perf_counter() if started is None else started
    stop = Stop(time_limit) if own else stop
    stop.deadline = min(stop.deadline, t_start + time_limit)
    # start-up: no layout judged yet, so SIGINT/SIGTERM end the run at once (`vdo.core.interrupts`),
    # and its time counts against the limit
    log.info("start-up: meshes, samples, the hand layout's ray cast and lighting, the compiled "
             "programs (Ctrl-C ends the run here, writing nothing)")
    problem = Problem(exp, user_objective=objective)
    run = problem.run
    run.stop = stop
    opt = exp.optimize
    planned = opt.starts * (opt.rounds + 1) * opt.max_steps
    if "lens" in opt.free:
        planned += LENS_TRIALS * (opt.rounds + 1) * opt.max_steps
    log.info("%s samples, %d free parameters, %d camera pairs sharing a region; time limit %g s",
             f"{len(problem.samples):,}", len(problem.param.theta0), len(problem.pairs), time_limit)
    reach = reachability.check(exp, problem.meshes, problem.samples)   # logs a warning per short region
    over_path = load_path_of(problem.meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                             groups=exp.groups)
    # the hand layout judged now, inside start-up: its time measures the best layout's judgement
    t_judge = time.perf_counter()
    before, sigma_before = _summary(problem, problem.start)
    checks_before = problem.check(problem.start)
    score_before = score_parts(problem, problem.start)
    judge_s = time.perf_counter() - t_judge
    kept = _wrap_up_s(problem, judge_s, len(over_path.steps) if over_path is not None else 0)
    stop.deadline -= kept   # the search ends in time for the result to be judged and written
    startup = time.perf_counter() - t_start
    log.info("start-up took %.0f s of the %g s time limit (%.0f s kept for writing the result); "
             "the search has the rest (%.0f s)", startup, time_limit, kept, stop.left)
    reason = None
    if stop.left == 0:
        reason = (f"start-up took {startup:.0f} s of the {time_limit:g} s time limit ({kept:.0f} s "
                  "kept for writing the result): no time left to search, the starting layout is "
                  f"judged and written; give --time-limit {math.ceil(startup + kept) + 60} or more "
                  "to search")
        log.warning(reason)
    t_search = time.perf_counter()
    with (stop_on_signals(stop) if own else contextlib.nullcontext()):
        run.progress = Progress(planned, stop)
        try:
            solve(problem)
            if "lens" in opt.free and not stop():
                log.info("lens catalogue: %s mm", ", ".join(f"{f * 1e3:g}" for f in opt.lenses))
                choose_lenses(problem, run.best)
        finally:
            run.progress.close()
    best = run.best
    final = best.problem
    status = Status(stop.reason) if stop.reason else \
        (Status.CONVERGED if all(e == Status.CONVERGED for e in run.ends) else Status.MAX_STEPS)
    search = time.perf_counter() - t_search
    log.info("search ended: %s after %.0f s (start-up %.0f s, search %.0f s)", status,
             time.perf_counter() - t_start, startup, search)
    after, sigma_after = _summary(final, best.state)
    if over_path is not None:   # the optimized layout judged at every step, as `vdo evaluate` does
        log.info("judging the optimized layout over the %d steps of the load path", len(over_path.steps))
        after = dataclasses.replace(after, load_path=loadpath.summary(loadpath.evaluate_load_path(
            problem.geometry, over_path, best.state.cameras)))
    score_after = score_parts(final, best.state)
    if objective is not None:   # the user's objective's values: what was minimised
        score_before["score_um"] = problem.exact_score(problem.start)
        score_after["score_um"] = best.score
        score_before["objective"] = score_after["objective"] = getattr(objective, "__name__", "user")
    optimized = final.exp.with_cameras(final.param.specs_at(best.theta))
    settings = None
    if optimized.exposure.free:   # f-numbers, exposure times and light power for the best layout
        optimized, settings = with_exposure(optimized)
        judged = layout_state(prepare(optimized))
        after = dataclasses.replace(report.state_evaluation(judged), load_path=after.load_path)
        sigma_after = judged.prediction.sigma_max
    scored = problem.exp.optimize.regions or [r.name for r in problem.exp.regions]
    worst = _worst_p95(before, scored), _worst_p95(after, scored)
    common = p95_where_both_measure(problem.samples, sigma_before, sigma_after)
    traded = precision_traded(before, after, scored, score_before["score_um"], best.score, common)
    if traded is not None:
        log.warning(traded["message"])
    log.info("best: %s, score %.4g -> %.4g µm, %d constraint violation(s)%s",
             run_labels(run.history, run.verdicts).get(best.start, f"start {best.start + 1}"),
             score_before["score_um"], score_after["score_um"], best.violations,
             why_higher(score_before["score_um"], score_after["score_um"], best.violations,
                        sum(not e["met"] for e in checks_before)))
    return OptimizeResult(status=status, score_before_um=score_before["score_um"], score_after_um=best.score,
                          startup_s=startup, search_s=search, reason=reason,
                          score_regions_um=score_after["regions"], reachability=reach,
                          violations=best.violations, worst_p95_um=worst, precision_traded=traded,
                          violated=[e for e in best.checks if not e["met"]], before=before, after=after,
                          optimized=optimized,
                          exposure=None if settings is None else settings.to_json(),
                          cameras=tuple(best.state.cameras), checks_before=checks_before,
                          checks_after=best.checks, moves=_moves(problem, best),
                          record=SearchRecord(
                              time_limit_s=time_limit, rounds=run.rounds, starts=run.ends,
                              history=run.history, verdicts=run.verdicts, best_start=best.start,
                              score_before=score_before, score_after=score_after))


def why_higher(before_um: float, after_um: float, violations: int, broken: int) -> str:
    """What the "best:" line adds when the optimized score is higher than the start's: the start
    broke `broken` constraints and the result breaks fewer (`violations`), and the search puts
    meeting constraints before the score (`vdo.search.solver`); "" otherwise."""
    if after_um <= before_um or violations >= broken:
        return ""
    return (f" (higher than the start's: the start broke {broken} constraint(s), this breaks "
            f"{violations}, and meeting them comes first)")


@dataclasses.dataclass(frozen=True)
class OptimizeResult:
    """What `optimize` returns: how the search ended, the score of the hand layout and of the best
    one (µm, the smooth σ_max percentile plus the coverage term, `score_parts`; the user's
    objective's values when one was given), and the two layouts judged as `vdo evaluate` judges
    them (`before`, `after`: summary_before.json and summary_after.json are their `to_json()`)."""

    status: Status                              # how the search ended (optimizer.json "status")
    score_before_um: float                      # score of the hand layout
    score_after_um: float                       # score of the best layout kept
    startup_s: float                            # s of the time limit spent before the search
    search_s: float                             # s the search itself ran
    reason: str | None                          # why it ended where it did, in words (None: all rounds ran)
    score_regions_um: dict[str, dict]           # region -> `score_parts` (µm and fractions), best layout
    reachability: list[dict]                    # per region, `vdo.search.reachability.check`
    violations: int                             # constraint checks the best layout breaks
    worst_p95_um: tuple[float | None, float | None]   # σ_max p95 of the worst scored region, before/after
    violated: list[dict]                        # those checks (constraints.json "violated")
    before: report.EvaluationResult             # the hand layout
    after: report.EvaluationResult              # the best layout (with its load path, when configured)
    optimized: Experiment                       # the experiment with the best layout (optimized.toml)
    cameras: tuple[Camera, ...]                 # the best layout's cameras (layout.json)
    checks_before: list[dict]                   # every constraint check of the hand layout
    checks_after: list[dict]                    # every constraint check of the best layout
    moves: tuple[CameraMove, ...]               # per camera, hand layout -> best layout (moves.csv)
    record: SearchRecord                        # what the search did (optimizer.json, history.csv)
    exposure: dict | None = None                # [exposure] free: the settings (`vdo.physics.exposure`)
    precision_traded: dict | None = None        # `precision_traded`: σ p95 rose while the score fell

    def to_json(self) -> dict:
        """The figures as a JSON dict: score_before, score_after (µm), startup_s, score_regions_um,
        status (its value), reachability, violations, worst_p95_um [before, after], violated,
        exposure, precision_traded."""
        return {"score_before": self.score_before_um, "score_after": self.score_after_um,
                "startup_s": self.startup_s, "search_s": self.search_s, "reason": self.reason,
                "score_regions_um": self.score_regions_um,
                "status": self.status.value, "reachability": self.reachability,
                "violations": self.violations, "worst_p95_um": list(self.worst_p95_um),
                "violated": self.violated, "exposure": self.exposure,
                "precision_traded": self.precision_traded}


@dataclasses.dataclass(frozen=True)
class SearchRecord:
    """What the search did, as optimizer.json, history.csv and convergence.png give it: the time
    limit (s, inf: none), the rounds (optimistix's statistics per round) and how each start
    ended, the accepted solver steps (`history`: start, round, wall_s, score and each penalty)
    and the judged layouts (`verdicts`: start, wall_s, exact score, violations), the start that
    won and the score's parts of the hand and the best layout (`score_parts`, µm)."""

    time_limit_s: float                         # s, the run's limit
    rounds: list[dict]                          # per round of the search
    starts: list                                # per start, how its last round ended (`Status`)
    history: list[dict]                         # per accepted solver step
    verdicts: list[dict]                        # per judged layout
    best_start: int                             # the start whose layout won (0: the hand layout)
    score_before: dict                          # `score_parts` of the hand layout
    score_after: dict                           # `score_parts` of the best layout


@dataclasses.dataclass(frozen=True)
class CameraMove:
    """One camera before (the hand layout) and after (the best layout), with its mount's name
    (rail or zone, "" for none) and, on a rail, its arc length along the bar (m) before and after
    (None off a rail)."""

    before: Camera
    after: Camera
    mount: str
    rail_before_m: float | None
    rail_after_m: float | None


def _summary(problem: Problem, state: State) -> tuple[report.EvaluationResult, np.ndarray]:
    """`vdo evaluate`'s summary of a round's layout: the one prediction of `vdo.physics.predict` (usable
    views, clipped patches) on the round's ray cast and lighting; and its σ_max per sample (m,
    +inf where not measured)."""
    exp = problem.exp
    pred = predict(exp.regions, exp.evaluation, exp.speckle, exp.sensor, list(state.cameras),
                   problem.samples, state.vis, state.illumination, problem.speckle,
                   overlap=problem.geometry.overlap,
                   exposure=exposure_factors(exp.camera_specs, exp.sensor))
    return report.evaluation(problem.exp, problem.samples, state.vis, pred), pred.sigma_max


def _worst_p95(summary: report.EvaluationResult, scored) -> float | None:
    """σ_max p95 (µm) of the worst of the `scored` regions ([optimize] regions, default all);
    None when one of them has no measured sample."""
    values = [summary.regions[name].sigma_max_um.p95 for name in scored]
    return None if any(v is None for v in values) else max(values)


def p95_where_both_measure(samples, sigma_before: np.ndarray, sigma_after: np.ndarray) -> dict:
    """{region name: [σ_max p95 before, after] (µm, `report.region_p95`)} over the samples that
    both layouts measure (finite σ_max (N,), m): where the two compare, unlike each layout's p95
    over its own measured area, which rises when a layout adds hard, grazing area. [None, None]
    where no sample of the region is measured by both."""
    both = np.isfinite(sigma_before) & np.isfinite(sigma_after)
    b, a = (report.region_p95(samples, s, both) for s in (sigma_before, sigma_after))
    return {name: [b[name], a[name]] for name in samples.region_names}


def precision_traded(before: report.EvaluationResult, after: report.EvaluationResult, scored,
                     score_before_um: float, score_after_um: float, common: dict) -> dict | None:
    """When the score fell (µm) yet a `scored` region's σ_max p95 over the area both layouts
    measure (`common`: `p95_where_both_measure`) rose by more than `PRECISION_RISE`, or the
    region lost every measured sample: {"regions": per such region its name, min_cameras,
    "sigma_p95_um" (over each layout's own measured area), "sigma_p95_common_um" and
    "seen_by_min_cameras" (area fraction), each as [before, after]; "message": the warning,
    naming each with what the lab can do}. None otherwise. The score counts area short of
    min_cameras (and unmeasured area at the 1 mm prior) so heavily that a search can buy a sliver
    of it with σ everywhere (docs/optimize.md); a higher σ over newly measured area alone,
    grazing where the hand layout saw nothing, is not precision lost."""
    if not score_after_um < score_before_um:
        return None
    rows = []
    for name in scored:
        b, a = before.regions[name], after.regions[name]
        p0, p1 = b.sigma_max_um.p95, a.sigma_max_um.p95
        c0, c1 = common[name]
        lost = p0 is not None and p1 is None
        if lost or (c0 is not None and c1 > (1 + PRECISION_RISE) * c0):
            rows.append(dict(region=name, min_cameras=a.min_cameras, sigma_p95_um=[p0, p1],
                             sigma_p95_common_um=[c0, c1],
                             seen_by_min_cameras=[b.seen_by_min_cameras, a.seen_by_min_cameras]))
    if not rows:
        return None
    show = lambda v: "unmeasured" if v is None else f"{v:.3f}"
    named = "; ".join(f"{r['region']}: sigma_max p95 over the area measured before and after "
                      f"{show(r['sigma_p95_common_um'][0])} -> {show(r['sigma_p95_common_um'][1])} um "
                      f"(over each one's own {show(r['sigma_p95_um'][0])} -> "
                      f"{show(r['sigma_p95_um'][1])} um), seen by {r['min_cameras']}+ cameras "
                      f"{100 * r['seen_by_min_cameras'][0]:.1f} -> {100 * r['seen_by_min_cameras'][1]:.1f} %"
                      for r in rows)
    message = (f"the score fell ({score_before_um:.4g} -> {score_after_um:.4g} um) but sigma_max p95 "
               f"rose by more than {100 * PRECISION_RISE:.0f} % in {len(rows)} scored region(s) "
               f"({named}): the score bought area seen by min_cameras with precision. To keep "
               "precision: keep the hand layout (summary_before.json), lower that region's "
               "min_cameras, leave it out of [optimize] regions, or design the layout with vdo design "
               "and [design] coverage_weight below 1 (docs/design.md, \"Coverage against precision\")")
    return {"regions": rows, "message": message}


def _moves(problem: Problem, best: Result) -> tuple[CameraMove, ...]:
    """Per camera its `CameraMove` from the hand layout (`problem`) to the best one (`best`)."""
    u0, u1 = problem.param.u(problem.param.theta0), best.problem.param.u(best.theta)
    moves = []
    for i, (a, b) in enumerate(zip(problem.cams0, best.state.cameras)):
        rail = problem.param.rails[i]
        moves.append(CameraMove(before=a, after=b,
                                mount=rail.name if rail else problem.exp.camera_specs[i].mount or "",
                                rail_before_m=rail.arc_length(u0[i]) if rail else None,
                                rail_after_m=rail.arc_length(u1[i]) if rail else None))
    return tuple(moves)
