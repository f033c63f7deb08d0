"""`vdo optimize` on small scenes (it clears a view masked by a bar, opens a stereo pair that is
too narrow, writes a complete run folder whose layout loads again) and on the built-in experiment."""

import csv
import dataclasses
import json
import logging
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import PLATE_TOML, aimed_camera, write_box
from vdo.config import experiment as config
from vdo.constraints import stereo_min_angle
from vdo.commands.optimize import optimize
from vdo.search.parameterisation import Parameterization
from vdo.search.solver import MU0
from vdo.scene import cameras_of

EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments" / "beam_column"

SETTINGS = """
[render]
ambient_radiance = 1.0

[optimize]
cameras = {moving}
starts = 1
rounds = 2
max_steps = 25
"""


def experiment(tmp_path, cameras, moving, extra_meshes="", files=()):
    write_box(tmp_path / "plate.stl", [600, 600, 10], center=[0, 0, -5])
    for name, extents, center in files:
        write_box(tmp_path / name, extents, center)
    text = PLATE_TOML.format(spacing=20, limit=75, height=1.2, extra_meshes=extra_meshes,
                             cameras=cameras + SETTINGS.format(moving=json.dumps(moving)))
    path = tmp_path / "exp.toml"
    path.write_text(text)
    return config.load(path)


def constraint(result_dir, name, **match):
    entries = json.loads((result_dir / "constraints.json").read_text())["after"]
    return [e for e in entries if e["constraint"] == name
            and all(e.get(k) == v for k, v in match.items())]


def test_camera_behind_a_bar_ends_with_a_clear_view(tmp_path):
    """Camera `a` starts with a bar across its view of the plate; it must slide or turn until
    nothing masks the plate, and end with no constraint violated."""
    bar = '[[mesh]]\nname = "bar"\nfile = "bar.stl"\nunit = "mm"\nrole = "obstacle"\n'
    cams = aimed_camera("a", 0.65) + aimed_camera("b", 0.2)
    exp = experiment(tmp_path, cams, ["a"], extra_meshes=bar,
                     files=[("bar.stl", [40, 1200, 40], [180, 0, 600])])
    out = tmp_path / "run"
    before_checks = None
    result = optimize(exp, out)
    before_checks = json.loads((out / "constraints.json").read_text())["before"]
    start = [e for e in before_checks if e["constraint"] == "obscuration" and e["cameras"] == ["a"]]
    assert start and start[0]["value"] > 0.05                     # really masked at the start
    after = constraint(out, "obscuration", cameras=["a"])
    assert after[0]["value"] <= exp.optimize.max_obscuration
    assert result.violations == 0, result.violated


def test_narrow_stereo_pair_opens_to_the_minimum_angle(tmp_path):
    """Two 24 mm cameras 8 cm apart (axes ~4 deg apart) must open to the rule-of-thumb angle."""
    cams = aimed_camera("a", 0.48) + aimed_camera("b", 0.52)
    exp = experiment(tmp_path, cams, ["a", "b"])
    out = tmp_path / "run"
    result = optimize(exp, out)
    limit = math.degrees(stereo_min_angle(0.024))
    angle = constraint(out, "axis_angle")[0]
    before = json.loads((out / "constraints.json").read_text())["before"]
    assert [e for e in before if e["constraint"] == "axis_angle"][0]["value"] < 5
    assert angle["limit"] == pytest.approx(limit)
    assert angle["value"] >= limit - 1e-6 and angle["met"]
    assert result.violations == 0, result.violated

    # the run folder: files, moves along the rail in mm, and a layout that loads again
    names = sorted(p.name for p in out.iterdir())
    assert names == FOLDER
    # the OptimizeResult is what the folder holds: summary_before/after.json byte for byte, and
    # optimizer.json's status and starting score
    for name, judged in (("summary_before.json", result.before), ("summary_after.json", result.after)):
        assert (out / name).read_text() == json.dumps(judged.to_json(), indent=2) + "\n"
    written = json.loads((out / "optimizer.json").read_text())
    assert written["status"] == result.status == result.to_json()["status"]
    assert written["score_before"]["score_um"] == result.score_before_um
    assert written["score_after"]["regions"] == result.score_regions_um
    assert result.after.regions["top"].sigma_max_um.p95 < result.before.regions["top"].sigma_max_um.p95
    moves = list(csv.DictReader((out / "moves.csv").open()))
    rail_length_mm = 2000.0
    for row, u0 in zip(moves, (0.48, 0.52)):
        assert float(row["rail_position_mm_before"]) == pytest.approx(u0 * rail_length_mm, abs=0.1)
    reloaded = config.load(out / "optimized.toml")
    layout = json.loads((out / "layout.json").read_text())["cameras"]
    for cam, saved in zip(cameras_of(reloaded.camera_specs, reloaded.rails), layout):
        np.testing.assert_allclose(cam.R, saved["R"], atol=1e-9)
        np.testing.assert_allclose(cam.t, saved["t"], atol=1e-9)
    history = list(csv.DictReader((out / "history.csv").open()))
    assert len(history) > 5
    # the score in µm: the report's power mean of the fields' smooth sigma (numpy, float64 per
    # pair) is the optimizer's score (JAX, float32 per pair); one region: it equals the overall
    summary = json.loads((out / "optimizer.json").read_text())["score_after"]
    assert summary["score_um"] == pytest.approx(result.score_after_um, rel=1e-5)
    assert summary["regions"]["top"]["sigma_smooth_um"] == pytest.approx(summary["sigma_smooth_um"], rel=1e-12)
    assert 0.1 < summary["sigma_smooth_um"] < 100   # micrometres, not metres or pixels
    # the penalty weight grows only after a round whose layout breaks a constraint, and a
    # penalty round after another with the same weights starts from its curvature
    rounds = json.loads((out / "optimizer.json").read_text())["rounds"]
    penalty = [r for r in rounds if r["score_weight"] == 1.0]
    assert penalty and penalty[0]["penalty_weight"] == MU0
    assert not penalty[0]["curvature_from_last_round"]
    for before, after in zip(penalty, penalty[1:]):
        assert after["penalty_weight"] == before["penalty_weight"] * (10 if before["violations"] else 1)
        assert after["curvature_from_last_round"] == (after["penalty_weight"] == before["penalty_weight"]
                                                      and before["num_accepted_steps"] >= 2)
    assert len(penalty) >= 2 and penalty[-1]["violations"] == 0


def test_rail_cameras_are_aimed_at_their_hand_aim_point_as_they_slide():
    """θ0 reproduces the hand layout; sliding a camera along its rail with zero angle offsets
    keeps its aim point on the optical axis; a pan offset turns the heading by that angle; with
    u held the angles are absolute."""
    exp = config.load(EXPERIMENTS / "ten_cameras.toml")
    cams = cameras_of(exp.camera_specs, exp.rails)
    param = Parameterization(exp, cams, np.zeros(3))
    for hand, rebuilt in zip(cams, param.cameras_at(param.theta0)):
        np.testing.assert_allclose(rebuilt.position, hand.position, atol=1e-12)
        np.testing.assert_allclose(rebuilt.R, hand.R, atol=1e-12)
    theta = param.theta0.copy()
    for idx in param.index:
        theta[idx["u"]] += 0.3
    for cam, aim in zip(param.cameras_at(theta), param.aims):
        off_axis = (aim - cam.position) - ((aim - cam.position) @ cam.optical_axis) * cam.optical_axis
        assert np.linalg.norm(off_axis) < 1e-9
    k = param.index[0]["pan"]
    turned = theta.copy()
    turned[k] += 0.05
    a, b = param.cameras_at(theta)[0], param.cameras_at(turned)[0]
    np.testing.assert_allclose(b.position, a.position, atol=1e-12)
    # a heading change d at tilt t turns the axis by 2 asin(cos t sin(d/2))
    turn = math.acos(np.clip(a.optical_axis @ b.optical_axis, -1, 1))
    assert turn == pytest.approx(2 * math.asin(math.cos(a.tilt) * math.sin(0.025)), rel=1e-9)
    # with u held, pan and tilt are the absolute angles of the hand layout
    held = dataclasses.replace(exp, optimize=dataclasses.replace(exp.optimize, free=("pan", "tilt")))
    absolute = Parameterization(held, cams, np.zeros(3))
    assert absolute.theta0[absolute.index[0]["pan"]] == pytest.approx(cams[0].pan)
    np.testing.assert_allclose(absolute.cameras_at(absolute.theta0)[0].R, cams[0].R, atol=1e-12)


@pytest.mark.slow
def test_builtin_ten_camera_layout_gets_better_and_meets_every_constraint(tmp_path):
    """The hand layout of the built-in experiment breaks the stereo-angle rule (cam9 against
    cam1 and cam2); one feasibility round and one penalty round of 15 steps each must end with
    every constraint met and a lower sigma_max p95 of the worst scored (joint) region than the hand layout (samples every
    25 mm: the same two broken pairs as at the file's 10 mm, in a third of the time)."""
    exp = config.load(EXPERIMENTS / "ten_cameras.toml").with_settings(evaluation={"sample_spacing_mm": 25})
    exp = dataclasses.replace(exp, optimize=dataclasses.replace(exp.optimize, rounds=1, starts=1,
                                                                max_steps=15))
    result = optimize(exp, tmp_path / "run")
    before = json.loads((tmp_path / "run" / "constraints.json").read_text())["before"]
    assert [e["cameras"] for e in before if not e["met"]] == [["cam1", "cam9"], ["cam2", "cam9"]]
    assert result.violations == 0, result.violated
    p95_before, p95_after = result.worst_p95_um   # the scored regions: joint_top, _bottom, _front
    assert p95_after < 0.98 * p95_before
    assert result.score_after_um < result.score_before_um


LENS_SETTINGS = """
[render]
ambient_radiance = 1.0

[optimize]
cameras = ["a"]
free = ["u", "pan", "tilt", "lens"]
lenses_mm = [{lenses}]
starts = 1
rounds = 1
max_steps = 25
"""


def lens_experiment(tmp_path, lenses):
    write_box(tmp_path / "plate.stl", [600, 600, 10], center=[0, 0, -5])
    cams = aimed_camera("a", 0.3) + aimed_camera("b", 0.7)
    text = PLATE_TOML.format(spacing=20, limit=75, height=1.2, extra_meshes="",
                             cameras=cams + LENS_SETTINGS.format(lenses=lenses))
    (tmp_path / "exp.toml").write_text(text)
    return config.load(tmp_path / "exp.toml")


def test_lens_catalogue_keeps_the_longest_lens_that_still_holds_the_plate(tmp_path):
    """Camera `a` (24 mm, 1.2 m above a 0.6 m plate, a 1.11 x 0.74 m field) may take 28 mm
    (0.95 x 0.63 m: the plate still fits, more pixels per mm, lower sigma) or 50 mm (0.53 x 0.36 m:
    the plate no longer fits, a field-of-view violation): the loop must end on 28 mm with every
    constraint met and a lower score than the 24 mm optimum."""
    exp = lens_experiment(tmp_path, "24, 28, 50")
    assert exp.optimize.lenses == pytest.approx((0.024, 0.028, 0.050))
    fixed = dataclasses.replace(exp, optimize=dataclasses.replace(exp.optimize, free=("u", "pan", "tilt")))
    base = optimize(fixed, tmp_path / "fixed")
    result = optimize(exp, tmp_path / "run")
    moves = {row["camera"]: row for row in csv.DictReader((tmp_path / "run" / "moves.csv").open())}
    assert (moves["a"]["focal_mm_before"], moves["a"]["focal_mm_after"]) == ("24", "28")
    assert moves["b"]["focal_mm_after"] == "24"
    assert result.violations == 0, result.violated
    assert result.score_after_um < base.score_after_um
    assert config.load(tmp_path / "run" / "optimized.toml").camera_specs[0].focal_length == pytest.approx(0.028)


def test_lens_without_a_catalogue_is_a_config_error(tmp_path):
    from vdo.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r'optimize.free: lists "lens" but no lenses_mm'):
        lens_experiment(tmp_path, "").optimize


def _layout_reloads(out):
    """optimized.toml loads again and gives the cameras of layout.json."""
    reloaded = config.load(out / "optimized.toml")
    layout = json.loads((out / "layout.json").read_text())["cameras"]
    for cam, saved in zip(cameras_of(reloaded.camera_specs, reloaded.rails), layout):
        np.testing.assert_allclose(cam.R, saved["R"], atol=1e-9)
        np.testing.assert_allclose(cam.t, saved["t"], atol=1e-9)
    return reloaded


FOLDER = ["constraints.json", "convergence.png", "history.csv", "layout.json", "moves.csv",
          "optimized.toml", "optimizer.json", "report.html", "summary_after.json",
          "summary_before.json"]


def test_sigint_mid_round_stops_after_the_step_and_writes_the_best_layout(tmp_path, monkeypatch):
    """A real SIGINT sent to this process at the 2nd solver step: the search must end there (no
    further step in any round), and the folder must be complete, say "interrupted", and hold a
    layout that reloads."""
    import os
    import signal

    from vdo.search.anytime import Progress

    cams = aimed_camera("a", 0.48) + aimed_camera("b", 0.52)
    exp = experiment(tmp_path, cams, ["a", "b"])
    steps = []
    original = Progress.step

    def step(self, where, best):
        steps.append(where)
        if len(steps) == 2:
            os.kill(os.getpid(), signal.SIGINT)   # delivered to this (main) thread at once
        original(self, where, best)

    monkeypatch.setattr(Progress, "step", step)
    out = tmp_path / "run"
    handler = signal.getsignal(signal.SIGINT)   # Python's default, or SIG_IGN in a test worker
    result = optimize(exp, out)
    assert len(steps) == 2
    assert result.status == "interrupted"
    summary = json.loads((out / "optimizer.json").read_text())
    assert summary["status"] == "interrupted" and not summary["converged"]
    # the round in progress ended on the signal (or had just converged at that very step)
    assert summary["rounds"][-1]["status"] in ("interrupted", "converged") and len(summary["rounds"]) == 1
    assert summary["rounds"][-1]["num_steps"] <= 2   # optimistix's stats, kept per round
    assert sorted(p.name for p in out.iterdir()) == FOLDER
    _layout_reloads(out)
    assert signal.getsignal(signal.SIGINT) is handler   # the handler restored


def test_time_limit_ends_the_search_with_a_complete_folder(tmp_path, caplog, capsys):
    """With a time limit shorter than one round the search stops on time: the folder is complete,
    optimizer.json says "time_limit", and the layout (the best judged so far) reloads. Its
    log lines go to the `vdo.optimize` logger and its progress line to `vdo.search.anytime` (INFO),
    never to stdout."""
    cams = aimed_camera("a", 0.48) + aimed_camera("b", 0.52)
    exp = experiment(tmp_path, cams, ["a", "b"])
    out = tmp_path / "run"
    with caplog.at_level(logging.INFO, logger="vdo"):
        result = optimize(exp, out, time_limit=1e-3)
    lines = [r.getMessage() for r in caplog.records if r.name == "vdo.optimize"]
    assert lines[0].startswith("start-up: ")
    assert lines[1].endswith("time limit 0.001 s") and "free parameters" in lines[1]
    assert any(line.startswith("start-up took ") for line in lines)      # counted, and said apart
    assert any(line.startswith("search ended: time_limit after") for line in lines)
    assert lines[-1].startswith("best: start 1, score ")
    assert capsys.readouterr().out == ""
    assert result.status == "time_limit"
    summary = json.loads((out / "optimizer.json").read_text())
    assert summary["status"] == "time_limit" and summary["time_limit_s"] == 1e-3
    assert summary["startup_s"] > 1e-3 and summary["search_wall_s"] == 0.0
    assert sorted(p.name for p in out.iterdir()) == FOLDER
    _layout_reloads(out)


AFTER_STARTUP_S = 10.0   # s: judging the starting layout and writing the folder (measured: ~2 s)


def test_a_limit_spent_by_start_up_ends_with_the_starting_layout_judged(tmp_path, caplog):
    """The limit counts start-up, from the caller's `started`: a limit that start-up alone
    spends leaves no search (no solver step, nothing compiled for it): the starting layout is
    judged and written, the reason said in the log, optimizer.json and the result, start-up and
    search given apart; the whole call ends within start-up + AFTER_STARTUP_S."""
    import time

    cams = aimed_camera("a", 0.48) + aimed_camera("b", 0.52)
    exp = experiment(tmp_path, cams, ["a", "b"])
    out = tmp_path / "run"
    started = time.perf_counter()
    with caplog.at_level(logging.INFO, logger="vdo"):
        result = optimize(exp, out, time_limit=0.5, started=started - 0.5)   # spent before the call
    wall = time.perf_counter() - started
    assert result.status == "time_limit" and result.reason.startswith("start-up took ")
    assert "no time left to search, the starting layout is judged and written" in result.reason
    assert wall <= result.startup_s - 0.5 + AFTER_STARTUP_S
    assert result.startup_s >= 0.5 and result.score_after_um == result.score_before_um
    summary = json.loads((out / "optimizer.json").read_text())
    assert summary["accepted_steps"] == 0 and summary["rounds"] == [] and summary["layouts_judged"] == 1
    assert summary["reason"] == result.reason and summary["startup_s"] == result.startup_s
    lines = [r.getMessage() for r in caplog.records if r.name == "vdo.optimize"]
    assert any(line.startswith("search ended: time_limit after ") and "(start-up " in line for line in lines)
    assert result.reason in lines
    _layout_reloads(out)


@pytest.mark.parametrize("limit", ["0", "-5"])
def test_non_positive_time_limit_is_refused_in_one_line(tmp_path, capsys, limit):
    from vdo.commands.cli import main

    cams = aimed_camera("a", 0.48)
    experiment(tmp_path, cams, ["a"])
    code = main(["optimize", str(tmp_path / "exp.toml"), "--out", str(tmp_path / "run"),
                 "--time-limit", limit])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "--time-limit" in err[0] and "positive" in err[0]
    assert not (tmp_path / "run").exists()


def test_local_clearance_and_shadow_sets_match_every_point_and_pair_near_the_anchor(tmp_path):
    """On a plate under two rail cameras with a bar beside one of them and an LED panel above
    them: the clearance and shadow penalties the solver evaluates (`Problem.terms` over
    `Problem.local`'s sets at the start layout) equal those over every mesh point near the rails
    and every lit sample, at layouts whose body points moved up to `LOCAL_MOVE`; and those
    layouts do violate both (else the equality would prove nothing)."""
    import jax.numpy as jnp

    from vdo import constraints
    from vdo.search.problem import CLEARANCE_MARGIN, LOCAL_MOVE, SHADOW_MARGIN, Problem

    bar = '[[mesh]]\nname = "bar"\nfile = "bar.stl"\nunit = "mm"\nrole = "obstacle"\n'
    light = ('[[light]]\nname = "panel"\nposition_m = [0.0, 0.0, 2.0]\ntarget_m = [0, 0, 0]\n'
             'size_m = [0.6, 0.6]\nradiance = 60\n')
    cams = aimed_camera("a", 0.45) + aimed_camera("b", 0.6)
    exp = experiment(tmp_path, cams + light, ["a", "b"], extra_meshes=bar,
                     files=[("bar.stl", [40, 40, 600], [-100, 120, 1000])])
    exp = dataclasses.replace(exp, optimize=dataclasses.replace(exp.optimize, clearance=0.15))
    problem = Problem(exp)
    theta0 = problem.param.theta0
    data = dict(problem.data, local=problem.local(theta0))
    body0 = problem.body_points(theta0)[2]
    near_all = jnp.asarray(constraints.padded_points(problem.near_sets))
    rng = np.random.default_rng(0)
    active = [0, 0]
    for _ in range(12):
        step = rng.normal(size=theta0.size) * problem.param.scale
        # the largest multiple of the step that keeps every body point within LOCAL_MOVE
        t = 1.0
        while np.linalg.norm(problem.body_points(theta0 + t * step)[2] - body0, axis=-1).max() > LOCAL_MOVE:
            t *= 0.8
        theta = theta0 + t * step
        terms = problem.terms(jnp.asarray(theta), problem.start.views, data, obscured=False)
        R, pos, body = problem.body_points(theta)
        full_clearance = float(constraints.clearance_penalty(
            jnp.asarray(body), near_all, exp.optimize.clearance + CLEARANCE_MARGIN))
        spheres = np.einsum("cji,cbj->cbi", R, np.asarray(problem.sphere_local)) + pos[:, None]
        full_shadow = float(constraints.shadow_penalty(jnp.asarray(spheres), problem.sphere_radii,
                                                       *problem.lit_samples, SHADOW_MARGIN))
        assert float(terms["clearance"]) == pytest.approx(full_clearance, rel=1e-9, abs=1e-12)
        assert float(terms["shadow"]) == pytest.approx(full_shadow, rel=1e-9, abs=1e-12)
        active[0] += full_clearance > 0
        active[1] += full_shadow > 0
    assert min(active) > 0, active


def test_rejected_step_backtracks_to_the_parabola_minimum_within_its_bounds():
    """On f(y) = (y - 1)^2 from y = 0 along d = 1, a trial at α (f(α) - f(0) = α^2 - 2α, slope
    -2) is rejected for α >= 1.8 (Armijo slope 0.1) and the next α is the minimiser of f along
    d, 1 (exact: f is the parabola), clipped to [0.1 α, 0.5 α]."""
    import equinox as eqx
    import optimistix as optx

    from vdo.search.bfgs import RememberingArmijo

    search = RememberingArmijo()
    y = jnp.zeros(1)
    remembered = lambda alpha: eqx.tree_at(lambda st: st.step_size, search.init(y, None), jnp.asarray(alpha))
    at_y = optx.FunctionInfo.EvalGrad(jnp.asarray(1.0), jnp.asarray([-2.0]))
    for alpha, expected in [(4.0, 1.0), (2.5, 1.0), (20.0, 2.0), (1.9, 0.95)]:
        trial = y + alpha
        f_trial = optx.FunctionInfo.Eval(jnp.asarray((alpha - 1.0) ** 2))
        step, accept, _, _ = search.step(jnp.asarray(False), y, trial, at_y, f_trial, remembered(alpha))
        assert not bool(accept)
        assert float(step) == pytest.approx(expected, rel=1e-12)
    # an accepted step doubles α, up to 1
    ok = optx.FunctionInfo.Eval(jnp.asarray(0.0))
    step, accept, _, _ = search.step(jnp.asarray(False), y, y + 1.0, at_y, ok, remembered(0.25))
    assert bool(accept) and float(step) == pytest.approx(0.5)


def test_bfgs_started_from_the_exact_inverse_hessian_lands_on_the_minimum_in_one_step():
    """On a quadratic ½ yᵀA y - bᵀy, BFGS given A⁻¹ by `with_inverse_hessian` takes the Newton
    step A⁻¹ b on its first move (accepted, the minimum); from the identity it does not."""
    from vdo.search.bfgs import BFGS, with_inverse_hessian

    rng = np.random.default_rng(0)
    M = rng.normal(size=(5, 5))
    A = jnp.asarray(M @ M.T + 5 * np.eye(5))
    b = jnp.asarray(rng.normal(size=5))
    fn = lambda y, args: (0.5 * y @ A @ y - b @ y, None)
    solver = BFGS(rtol=1e-9, atol=1e-9)
    y0 = jnp.zeros(5)
    f_struct = jax.ShapeDtypeStruct((), jnp.float64)

    def two_steps(state):
        y = y0
        for _ in range(2):   # the first step accepts the start; the second evaluates the move
            y, state, _ = solver.step(fn, y, None, {}, state, frozenset())
        return state.y_eval

    start = solver.init(fn, y0, None, {}, f_struct, None, frozenset())
    minimum = np.linalg.solve(np.asarray(A), np.asarray(b))
    np.testing.assert_allclose(two_steps(with_inverse_hessian(start, np.linalg.inv(np.asarray(A)))),
                               minimum, rtol=1e-10, atol=1e-12)
    assert np.abs(np.asarray(two_steps(start)) - minimum).max() > 1e-2


def test_the_solver_step_compiles_once_for_the_first_and_the_later_steps():
    """The state BFGS's init returns has the same types (shapes, dtypes, weak types) as the one
    each step returns, so one jit-compiled step serves the whole solve: counted by JAX's own
    compilation events around three jitted steps (a weakly typed first step size made it two)."""
    import equinox as eqx
    import jax.monitoring

    from vdo.search.bfgs import BFGS

    fn = lambda y, args: (jnp.sum((y - args) ** 2) + jnp.sum(y ** 4), None)
    solver = BFGS(rtol=1e-9, atol=1e-9)
    f_struct = jax.ShapeDtypeStruct((), jnp.float64)
    step = eqx.filter_jit(lambda y, args, state: solver.step(fn, y, args, {}, state, frozenset())[:2])
    y, args = jnp.zeros(4), jnp.arange(4.0)
    init = eqx.filter_jit(lambda y, args: solver.init(fn, y, args, {}, f_struct, None, frozenset()))
    state = init(y, args)     # both jitted, as `vdo.search.problem.Run.programs` has them
    compiles = []
    listener = lambda event, duration, **kw: compiles.append(event) \
        if event == "/jax/core/compile/backend_compile_duration" and kw.get("fun_name") == "jit(<lambda>)" else None
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        for _ in range(3):
            y, state = step(y, args, state)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert len(compiles) == 1


COMPILE_LIMIT_S = 20.0   # the run's time limit in the test below
COMPILE_SLACK_S = 5.0    # past it: one poll of the stop request and the run folder's writing


def test_time_limit_holds_while_the_solver_compiles(tmp_path, monkeypatch):
    """The solver's first call compiles its programs, minutes for a large layout on a loaded
    machine (the scale benchmark: 2 x 2.5 min, past a 300 s limit). Simulated here by a first
    call that does not return: the run still ends at its time limit, with the starting layout
    as its result and the round's reason saying what was running."""
    import threading
    import time

    from vdo.search.problem import Run

    released = threading.Event()
    real = Run.programs

    def programs(self, problem):
        init, step = real(self, problem)

        def stuck(*args):
            released.wait(120)
            raise RuntimeError("released at the end of the test")

        return init, stuck

    monkeypatch.setattr(Run, "programs", programs)
    cams = aimed_camera("a", 0.48) + aimed_camera("b", 0.52)
    exp = experiment(tmp_path, cams, ["a", "b"])
    started = time.perf_counter()
    try:
        result = optimize(exp, tmp_path / "run", time_limit=COMPILE_LIMIT_S)
    finally:
        released.set()
    assert time.perf_counter() - started < COMPILE_LIMIT_S + COMPILE_SLACK_S
    assert result.status == "time_limit"
    assert result.score_after_um == result.score_before_um
    written = json.loads((tmp_path / "run" / "optimizer.json").read_text())
    assert any("while the solver's programs compiled" in r["reason"] for r in written["rounds"]), \
        written["rounds"]


def test_the_console_gives_the_score_views_and_the_final_evaluations_unmeasured_area(monkeypatch, capsys):
    """The unmeasured area of a scored region comes from two judgements that can differ (the
    search's views; the final layout's evaluation with every body and tripod, summary_after.json):
    the console line names both, each with its own number."""
    from types import SimpleNamespace

    from vdo.commands import cli, optimize as command

    after = SimpleNamespace(regions={"bend": SimpleNamespace(unmeasured_fraction=0.119)})
    result = SimpleNamespace(
        status="converged", startup_s=3.0, search_s=40.0, score_before_um=2.0, score_after_um=1.0,
        reason="", worst_p95_um=(2.5, 1.5), violated=[], after=after,
        score_regions_um={"bend": dict(scored=True, sigma_smooth_um=1.2, unmeasured_fraction=0.075,
                                       coverage_um=0.0)})
    monkeypatch.setattr(command, "optimize", lambda *a, **k: result)
    exp = SimpleNamespace(optimize=SimpleNamespace(score="bound"))
    cli._optimize(exp, SimpleNamespace(out="run", overwrite=False, time_limit=60, started=None, quiet=False))
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("  bend:")][0]
    assert ("7.5 % of the area unmeasured in the score's views, counted as 1 mm; 11.9 % in "
            "summary_after.json") in line, line


def test_the_convergence_figure_names_the_lens_trials_apart_from_the_starts():
    """Two starts (0, 1), the lens screening judged under index 2 without a solve, two lens
    trials solved under 3 and 4: "start 1", "start 2", "lens trial 1", "lens trial 2" (the figure
    said "start 4" and "start 5", and no start 3 existed)."""
    from vdo.optimize import run_labels

    history = [{"start": s} for s in (0, 0, 1, 3, 4)]
    verdicts = [{"start": s} for s in (0, 1, 2, 2, 3, 4)]
    assert run_labels(history, verdicts) == {0: "start 1", 1: "start 2", 2: "the lens screening",
                                             3: "lens trial 1", 4: "lens trial 2"}
    assert run_labels([{"start": 0}], [{"start": 0}]) == {0: "start 1"}


def test_a_score_that_falls_while_sigma_rises_is_named_with_the_area_it_bought(plate_experiment):
    """Two cameras on the plate with 24 mm lenses (sharper, part of the plate seen once) against
    12 mm (every point seen twice, σ about doubled): read as a run whose score fell from the 24 mm
    layout to the 12 mm one, `precision_traded` names the region with σ p95 over the area both
    measure and over each one's own, and both areas seen by min_cameras; it stays silent when σ
    fell, when the score did not fall, and when only the newly measured area is worse (the p95
    over the common area unchanged)."""
    from vdo.optimize import PRECISION_RISE, p95_where_both_measure, precision_traded
    from vdo.outputs import report
    from vdo.state import layout_state, prepare

    def judged(focal):
        cams = "".join(aimed_camera(n, u).replace("focal_mm = 24", f"focal_mm = {focal}")
                       for n, u in (("a", 0.3), ("b", 0.7))) + "\n[render]\nambient_radiance = 1.0\n"
        exp = config.load(plate_experiment(spacing=25, cameras=cams))
        state = layout_state(prepare(exp))
        return report.state_evaluation(state), state.prediction.sigma_max, state.samples

    (sharp, sigma_sharp, samples), (wide, sigma_wide, _) = judged(24), judged(12)
    s0, s1 = sharp.regions["top"], wide.regions["top"]
    assert s1.sigma_max_um.p95 > (1 + PRECISION_RISE) * s0.sigma_max_um.p95     # the scene does trade
    assert s0.seen_by_min_cameras < s1.seen_by_min_cameras == pytest.approx(1.0)
    assert s0.min_cameras == 2 and s0.seen_by_min_cameras == s0.seen_by_2_or_more
    common = p95_where_both_measure(samples, sigma_sharp, sigma_wide)
    both = np.isfinite(sigma_sharp) & np.isfinite(sigma_wide)
    assert common["top"] == [pytest.approx(np.percentile(sigma_sharp[both] * 1e6, 95), rel=1e-12),
                             pytest.approx(np.percentile(sigma_wide[both] * 1e6, 95), rel=1e-12)]
    c0, c1 = common["top"]
    assert c1 > (1 + PRECISION_RISE) * c0      # on the area both measure, too
    traded = precision_traded(sharp, wide, ["top"], 2.0, 1.0, common)
    assert traded["regions"] == [dict(region="top", min_cameras=2,
                                      sigma_p95_um=[s0.sigma_max_um.p95, s1.sigma_max_um.p95],
                                      sigma_p95_common_um=[c0, c1],
                                      seen_by_min_cameras=[s0.seen_by_min_cameras, 1.0])]
    message = traded["message"]
    assert (f"top: sigma_max p95 over the area measured before and after {c0:.3f} -> {c1:.3f} um "
            f"(over each one's own {s0.sigma_max_um.p95:.3f} -> {s1.sigma_max_um.p95:.3f} um), seen by 2+ "
            f"cameras {100 * s0.seen_by_min_cameras:.1f} -> 100.0 %") in message, message
    assert "min_cameras" in message and "[design] coverage_weight below 1" in message
    flipped = {"top": [c1, c0]}
    assert precision_traded(wide, sharp, ["top"], 2.0, 1.0, flipped) is None    # σ fell
    assert precision_traded(sharp, wide, ["top"], 1.0, 1.0, common) is None     # the score did not fall
    # each one's own p95 rose, the common area's did not: new, harder area is not precision lost
    assert precision_traded(sharp, wide, ["top"], 2.0, 1.0, {"top": [c0, c0]}) is None


def test_the_p95_where_both_measure_is_over_the_samples_both_measure():
    """σ (m) measured at samples 0, 1, 3 before and 0, 1, 2 after: the common area is samples 0
    and 1 of region a (p95 of [1, 2] µm, linear: 1.95) and nothing of region b."""
    from types import SimpleNamespace

    from vdo.optimize import p95_where_both_measure

    inf = np.inf
    before = np.array([1.0, 2.0, inf, 4.0]) * 1e-6
    after = np.array([3.0, 5.0, 6.0, inf]) * 1e-6
    region = np.array([0, 0, 0, 1])
    out = p95_where_both_measure(SimpleNamespace(region=region, region_names=("a", "b")), before, after)
    assert out["a"] == [pytest.approx(1.95), pytest.approx(3.0 + 0.95 * 2.0)]
    assert out["b"] == [None, None]


def test_a_higher_score_after_a_broken_start_says_why():
    """Trial 4: `design --refine` read "score 896.3 -> 1236 µm" with no word on why: the designed
    start broke a constraint, which the search meets first. The "best:" line says so only then."""
    from vdo.optimize import why_higher

    said = why_higher(896.3, 1236.0, 0, 1)
    assert "the start broke 1 constraint(s), this breaks 0" in said
    assert why_higher(1236.0, 896.3, 0, 1) == ""           # lower: nothing to explain
    assert why_higher(896.3, 1236.0, 1, 1) == ""           # as many broken: not the reason
