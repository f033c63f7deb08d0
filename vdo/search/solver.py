"""The solver loop: rounds of BFGS (`_round`) with the ray cast and lighting frozen, feasibility
rounds first from a start that violates a constraint, μ raised after an infeasible round, several
starts (`solve`), each round's layout judged exactly (`judge`, `Result`), and the discrete lens
choice around it (`choose_lenses`). `vdo.optimize` runs it and writes the outputs."""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import jax.numpy as jnp
import numpy as np
import optimistix as optx

from vdo.model.pose import aim_point
from vdo.search.status import Status
from vdo.search.parameterisation import Parameterization, perturbation
from vdo.search.anytime import until_stopped
from vdo.search.bfgs import with_inverse_hessian
from vdo.search.problem import LOCAL_MOVE, Problem, Result, State

MU0 = 10.0   # penalty weight of the first round (score in µm, penalties ~1 at a clear violation)
FEASIBILITY_ROUNDS = 3    # at most this many feasibility rounds (penalties only) per start
LENS_TRIALS = 3   # lens options optimised after screening (`choose_lenses`)
ROUND_TOL = 1e-3  # a start ends when a penalty round, feasible after a feasible one, gains less (relative)
BACKTRACKS = 4    # halvings of a round's move whose refreshed layout ranks worse than its start (`_backtrack`)
CHECKPOINT_STEPS = 10   # steps between the exact verdicts within a round (`solve`)
CHECKPOINT_S = 5.0      # s: in a penalty round, the least time between two verdicts (`solve`)

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# The solver loop
# --------------------------------------------------------------------------------------------
def judge(problem: Problem, theta, state: State, start: int) -> Result:
    """The exact verdict on a refreshed layout: score and every constraint checked."""
    checks = problem.check(state)
    result = Result(np.asarray(theta, float), state, problem.exact_score(state), checks,
                    sum(not e["met"] for e in checks), start, problem)
    run = problem.run
    run.verdicts.append(dict(start=start, wall_s=time.perf_counter() - run.t0,
                             score=result.score, violations=result.violations, theta=result.theta))
    if run.best is None or result.rank < run.best.rank:
        run.best = result   # the best layout of the run so far, whatever stops it
    return result


def _violated(result: Result) -> str:
    """The violated constraints in a few words, e.g. 'axis_angle cam1/cam9; clearance cam2'."""
    return "; ".join(f"{e['constraint']} {'/'.join(e.get('cameras', []))}"
                     + (f" {e['region']}" if "region" in e else "") for e in result.checks if not e["met"])


def _backtrack(problem: Problem, before: Result, theta, start: int, judged=None):
    """(θ, state, result) of a round's end: the layout at θ refreshed and judged (`judged`:
    its (state, result) when a checkpoint judged it already). Within a round
    the ray-cast visibility is frozen, so the solver can move a camera where the refresh then
    finds a counted view hidden (behind an obstacle, or by a part that moves along the load
    path): when the layout ranks worse than `before`, the round's start, the move is halved,
    up to `BACKTRACKS` times, and the first layout that ranks no worse is kept; if none does,
    the round's start."""
    for _ in range(BACKTRACKS + 1):
        state, result = judged or (None, None)
        if judged is None:
            state = problem.refresh(theta)
            result = judge(problem, theta, state, start)
        judged = None
        if result.rank <= before.rank or problem.run.stop():
            return theta, state, result
        theta = before.theta + 0.5 * (np.asarray(theta) - before.theta)
    return before.theta, before.state, before


def solve(problem: Problem, starts: int | None = None, first_label: int = 0) -> list[Result]:
    """Every start, every round, until they end or `problem.run.stop`; per start the best layout
    met at the end of a round (or the start itself), judged exactly (`Result.rank`); returns
    them sorted best first. Start k > 0 perturbs the hand layout at random; starts are labelled
    from `first_label` in the records; each round's end is logged (INFO)."""
    opt = problem.exp.optimize
    run = problem.run
    rng = np.random.default_rng(opt.seed)
    results = []
    n_starts = opt.starts if starts is None else starts
    for k_start in range(n_starts):
        if results and run.stop():
            break
        start = first_label + k_start
        theta = problem.param.theta0.copy()
        if k_start > 0:
            theta = theta + perturbation(problem.param, rng)
        state = problem.start if k_start == 0 else problem.refresh(theta)   # hand layout: cast once
        best = result = judge(problem, theta, state, start)
        masked = frozenset()   # the (camera, region) pairs whose obscuration this start tracks
        label = 0
        end = Status.CONVERGED
        curvature = None   # (weights, `RoundOutcome.curvature`) of the last round

        def one_round(w_score, mu, name):
            nonlocal theta, state, result, best, label, masked, end, curvature
            masked = problem.track_obscured(state, result.checks, masked)
            where = f"start {start + 1} {name}"
            checked = {}   # the last layout judged within the round

            def checkpoint(at) -> bool:
                """Judge the round's iterate (in a penalty round only once `CHECKPOINT_S` have
                passed since the run's last verdict); True (end the round) in a feasibility round
                once it meets every constraint."""
                nonlocal best
                if w_score != 0 and time.perf_counter() - run.t0 - run.verdicts[-1]["wall_s"] < CHECKPOINT_S:
                    return False
                checked.update(theta=at, state=problem.refresh(at))
                checked["result"] = judge(problem, at, checked["state"], start)
                best = min(best, checked["result"], key=lambda r: r.rank)
                return w_score == 0 and checked["result"].violations == 0

            warm = curvature[1] if curvature is not None and curvature[0] == (w_score, mu) else None
            outcome = _round(problem, theta, state.views, (w_score, mu), opt.max_steps, where, (start, label),
                             checkpoint, warm)
            if outcome.curvature is not None:
                curvature = (w_score, mu), outcome.curvature
            run.history.extend(outcome.history)
            record = dict(outcome.record(start, name), score_weight=w_score, penalty_weight=mu,
                          curvature_from_last_round=warm is not None, violations=result.violations)
            run.rounds.append(record)   # `violations`: of the layout the round ends at
            end = outcome.status
            label += 1
            if np.array_equal(outcome.theta, theta):
                return
            judged = None   # the round's end, when its last checkpoint judged it already
            if checked and np.array_equal(checked["theta"], outcome.theta):
                judged = checked["state"], checked["result"]
            theta, state, result = _backtrack(problem, result, outcome.theta, start, judged)
            record["violations"] = result.violations
            best = min(best, result, key=lambda r: r.rank)
            violated = _violated(result)
            log.info("  start %d %s: score %.4g µm, %d violation(s)%s%s", start + 1, name, result.score,
                     result.violations, f" ({violated})" if violated else "",
                     "" if outcome.status in ("converged", "max_steps") else f" (ended: {outcome.reason})")

        # from a layout that violates a constraint: the penalties alone, until it meets them all
        for k in range(FEASIBILITY_ROUNDS):
            if result.violations == 0 or run.stop():
                break
            one_round(0.0, 1.0, f"feasibility round {k + 1}")
        mu = MU0
        for k in range(opt.rounds):
            if run.stop():
                break
            previous = result
            one_round(1.0, mu, f"round {k + 1}/{opt.rounds}")
            if result.violations:
                mu *= 10.0
            if (k > 0 and previous.violations == 0 and result.violations == 0
                    and previous.score - result.score < ROUND_TOL * previous.score):
                end = Status.CONVERGED   # the penalty continuation has nothing left
                break
        results.append(best)
        run.ends.append(end)
    return sorted(results, key=lambda r: r.rank)


def choose_lenses(problem: Problem, best: Result) -> Result:
    """The discrete choice over `[optimize] lenses` by screening: every (moving camera, other
    focal length) option is judged once at the best layout so far (its positions and aims; a
    camera in a zone steps along its axis by the ratio of the focal lengths, clipped to the zone
    and aimed at the same point, so that the regions keep their image size; one ray cast and the exact score and checks, no
    optimisation), the options are ranked by score
    and only the `LENS_TRIALS` best are optimised again (`solve`, one start, feasibility rounds
    first if the option breaks a constraint; a camera on a rail cannot step back, so an option
    that screens worse than the current layout may still win), one camera at a time; an option is kept when its optimised layout ranks better (`Result.rank`). Constraints keep the hand layout's meaning
    (`Problem(reference=...)`); the stereo-angle rule follows the new lenses. Every screened and
    optimised option is logged (INFO)."""
    run = problem.run
    moving = [i for i, idx in enumerate(problem.param.index) if idx]

    centre = problem.geometry.centre

    def trial(current: Result, c: int, focal: float) -> Problem:
        specs = current.problem.param.specs_at(current.theta)
        specs[c] = dataclasses.replace(specs[c], focal_length=focal)
        zone = problem.param.zones[c]
        if zone is not None and Parameterization.moves(problem.param.index[c]):
            # in a zone, step along the axis so that the regions keep their size in the image
            cam = current.state.cameras[c]
            aim = aim_point(cam.position, cam.pan, cam.tilt, centre)
            depth = float((aim - cam.position) @ cam.optical_axis)
            ratio = focal / current.problem.exp.camera_specs[c].focal_length
            moved = np.clip(aim - ratio * depth * cam.optical_axis, zone.low, zone.high)
            if zone.floor is not None and not zone.inside(moved[:2]):
                moved = cam.position   # not over the floor: screen it where it stands
            specs[c] = dataclasses.replace(specs[c], position=moved, target=aim)   # aimed again
        return Problem(current.problem.exp.with_cameras(specs), reference=problem)

    options = []
    label = max(v["start"] for v in run.verdicts) + 1
    for c in moving:
        for focal in problem.exp.camera_specs[c].lenses or problem.exp.optimize.lenses:
            if run.stop():
                break
            if math.isclose(focal, best.problem.exp.camera_specs[c].focal_length, rel_tol=1e-9):
                continue
            t = trial(best, c, focal)
            screened = judge(t, t.param.theta0, t.start, label)
            options.append((screened.score, c, focal))
            log.info("  lens %s %g mm at the current layout: score %.4g µm, %d violation(s)",
                     problem.cams0[c].name, focal * 1e3, screened.score, screened.violations)
    promising = sorted(options)[:LENS_TRIALS]   # moving and aiming may recover what screening lost
    changed = set()
    for _, c, focal in promising:
        if run.stop() or c in changed:
            continue
        label = max(v["start"] for v in run.verdicts) + 1
        result = solve(trial(best, c, focal), starts=1, first_label=label)[0]
        kept = result.rank < best.rank
        log.info("  lens %s %g mm optimised: score %.4g µm, %d violation(s)%s", problem.cams0[c].name,
                 focal * 1e3, result.score, result.violations, " (kept)" if kept else "")
        if kept:
            best = result
            changed.add(c)
    return best


@dataclasses.dataclass(frozen=True)
class RoundOutcome:
    """One BFGS solve (`_round`): θ at its last accepted step, how it ended (`status`:
    "converged", "max_steps", "feasible" (a feasibility round that met every constraint at a
    checkpoint), "time_limit", "interrupted" or "failed"; `reason` in words),
    optimistix's `Solution` (value: y, the scaled step from the round's start; result; aux: the
    terms at y; stats: num_steps, num_accepted_steps, max_steps; state: the solver state), the
    terms at every accepted step (`history`: start, round, wall_s, score, the penalties) and
    `curvature`: BFGS's estimate of the inverse Hessian of J (not J / norm) in the scaled
    variables at the round's end, (n, n), or None when the round accepted fewer than 2 steps."""

    theta: np.ndarray
    status: Status
    reason: str
    solution: optx.Solution | None
    history: tuple[dict, ...]
    curvature: np.ndarray | None = None

    def record(self, start: int, name: str) -> dict:
        """The round for optimizer.json."""
        stats = {} if self.solution is None else {k: int(v) for k, v in self.solution.stats.items()}
        result = "" if self.solution is None else optx.RESULTS[self.solution.result]
        return dict(start=start, round=name, status=self.status, reason=self.reason,
                    solver_result=result or "successful", **stats)


def _round(problem: Problem, theta, views, weights, max_steps: int, where: str,
           label: tuple[int, int], checkpoint=None, curvature=None) -> RoundOutcome:
    """One BFGS solve of J (`Problem._total`) in scaled variables y = (θ - θ_start) / scale, with J
    divided by the largest scaled gradient component at the start, so that the first quasi-Newton
    step moves about one natural unit (`Parameterization.scale`) along the steepest parameter.
    The solver runs step by step (one compiled step per call, `Run`), checking the stop
    request between steps; `label` (start, round) tags the history rows. A step that leaves the
    solver's iterate, its value or gradient non-finite ends the round ("failed", with the
    reason): it is never replaced. With a `checkpoint` (θ -> bool), every `CHECKPOINT_STEPS` steps
    the last accepted θ, if it moved, is passed to it (`solve` judges it, so that the best layout
    so far is known within a long round); True ends the round there ("feasible").

    With `curvature` (a previous round's `RoundOutcome.curvature`, same weights), BFGS starts
    from that inverse Hessian, times norm, instead of the identity: a round after a visibility
    refresh solves nearly the problem the last one did, and rebuilding the curvature from the
    identity costs it most of its steps (measured on the built-in experiment: of 40 steps, the
    first ~25 gained under 0.1 %, the last few several %)."""
    run = problem.run
    origin = jnp.asarray(theta, dtype=jnp.float64)
    scale = jnp.asarray(problem.param.scale, dtype=jnp.float64)
    weights = jnp.asarray(weights, dtype=jnp.float64)
    data = dict(problem.data, local=problem.local(theta))
    y = jnp.zeros_like(origin)
    args = lambda norm: (origin, scale, jnp.asarray(norm, dtype=jnp.float64), views, weights, data)
    if run.stop():
        return RoundOutcome(np.asarray(theta), run.stop.reason, "stopped before the round", None, ())
    # the first step of a solve accepts its start: there, its gradient is dJ/dy at norm 1
    init, step = run.programs(problem)
    # the first call compiles the programs (minutes for a large layout on a loaded machine): it
    # runs aside, so that the time limit and Ctrl-C hold while XLA compiles
    done, first = until_stopped(run.stop, lambda: step(y, args(1.0), init(y, args(1.0))))
    if not done:
        return RoundOutcome(np.asarray(theta), Status(run.stop.reason),
                            "stop request while the solver's programs compiled", None, ())
    _, probe = first
    grad = np.asarray(probe.f_info.grad)
    if not np.all(np.isfinite(grad)):
        return RoundOutcome(np.asarray(theta), "failed", "non-finite gradient at the round's start",
                            None, ())
    norm = float(np.max(np.abs(grad)))
    if norm == 0:
        return RoundOutcome(np.asarray(theta), Status.CONVERGED, "zero gradient at the round's start", None, ())
    solver_args = args(norm)
    state = init(y, solver_args)
    if curvature is not None:
        state = with_inverse_hessian(state, norm * curvature)
    status, reason = Status.MAX_STEPS, f"{max_steps} steps"
    history = []
    judged = np.zeros_like(np.asarray(y))   # the last iterate passed to `checkpoint`
    k = 0
    for k in range(1, max_steps + 1):
        if run.stop():
            status, reason = Status(run.stop.reason), f"stop request after {k - 1} steps"
            k -= 1
            break
        accepted = int(state.num_accepted_steps)
        # the point this step evaluates: the local sets move with it (`Problem.terms`)
        trial = np.asarray(origin + scale * state.y_eval)
        if np.linalg.norm(problem.body_points(trial)[2] - np.asarray(data["local"]["body"]), axis=-1).max() \
                > LOCAL_MOVE / 2:
            data = dict(data, local=problem.local(trial))
            solver_args = (*solver_args[:5], data)
        y_new, state = step(y, solver_args, state)
        if int(state.num_accepted_steps) > accepted:   # the terms at the step just accepted
            history.append(dict(start=label[0], round=label[1], wall_s=time.perf_counter() - run.t0,
                                **{name: float(v) for name, v in state.aux.items()}))
        run.progress.step(f"{where}, step {k}/{max_steps}", run.best)
        finite = {"iterate": y_new, "objective": state.f_info.f, "gradient": state.f_info.grad,
                  "next trial point": state.y_eval}
        bad = [name for name, v in finite.items() if not np.all(np.isfinite(np.asarray(v)))]
        if bad:
            status, reason = Status.FAILED, f"non-finite {', '.join(bad)} at step {k}"
            log.warning("%s: %s; the round ends at its last finite step", where, reason)
            break
        y = y_new
        if bool(state.terminate):
            status, reason = Status.CONVERGED, f"solver tolerance met at step {k}"
            break
        if checkpoint is not None and k % CHECKPOINT_STEPS == 0 and k < max_steps \
                and not np.array_equal(np.asarray(y), judged):
            judged = np.asarray(y)
            if checkpoint(np.asarray(origin + scale * y)):
                status, reason = Status.FEASIBLE, f"every constraint met at step {k}"
                break
        if not bool(state.result == optx.RESULTS.successful):
            status, reason = Status.FAILED, optx.RESULTS[state.result]
            break
    solution = optx.Solution(value=y, result=state.result, aux=state.aux, state=state,
                             stats=dict(num_steps=k, num_accepted_steps=int(state.num_accepted_steps),
                                        max_steps=max_steps))
    estimate = None
    if int(state.num_accepted_steps) >= 2:
        estimate = np.asarray(state.f_info.hessian_inv.pytree) / norm
    return RoundOutcome(np.asarray(origin + scale * y), status, reason, solution, tuple(history), estimate)
