"""vdo.calib.montecarlo on a pool and on Dask (the serial result to the last bit), and
`vdo calibrate --montecarlo` (its ratios against the chi-square intervals; its bad flags)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from vdo.config.experiment import load, parse

ROOT = Path(__file__).resolve().parents[2]
HOLED = ROOT / "experiments" / "holed_plate" / "stereo.toml"
TRIALS = 6             # enough for 6 one-trial tasks spread over 2 workers
FIELDS = ("predicted", "observed", "displacement_predicted", "displacement_observed",
          "strain_predicted", "strain_observed", "nees", "bias_displacement", "bias_strain")


def small_pair(**fields):
    """The holed plate's pair with a 13-pose session (5 poses per camera, 3 shared)."""
    exp = load(HOLED)
    data = exp.to_dict()
    data["calibration"] = {**data.get("calibration", {}), "poses_per_camera": 5, "shared_poses": 3,
                           **fields}
    return parse(data, exp.path)


@pytest.fixture(scope="module")
def pair():
    """(arguments of `montecarlo.run` for TRIALS trials of the small pair, its serial result)."""
    from vdo.calib import montecarlo as mc
    from vdo.calib import propagate as prop
    from vdo.calib.session import plan

    exp = small_pair()
    planned = plan(exp, 1.0)
    cams = list(planned.cameras)
    samples = planned.geometry.samples
    X, motion = prop.probe(exp, samples, cams, 4)
    rig = tuple(c.name for c in cams)
    args = (cams, planned.session, [rig], {rig: X}, {rig: motion}, TRIALS, 0)
    return args, mc.run(*args, sigma_det=0.1)


def assert_same(a, b):
    assert a.trials == b.trials and a.sigma_det == b.sigma_det
    for ra, rb in zip(a.rigs, b.rigs, strict=True):
        assert ra.names == rb.names and ra.parameters == rb.parameters
        for field in FIELDS:
            assert np.array_equal(getattr(ra, field), getattr(rb, field)), field


def test_a_pool_of_two_workers_gives_the_serial_result(pair):
    """The trials as 6 tasks on 2 spawned processes: every number the same to the last bit (each
    trial's noise from its own seed, gathered in trial order); and the scatter is a scatter."""
    from vdo.calib import montecarlo as mc

    args, serial = pair
    pooled = mc.run(*args, sigma_det=0.1, workers=2)
    assert_same(serial, pooled)
    assert np.all(serial.rigs[0].observed > 0)


def test_dask_gives_the_serial_result(pair):
    """The same on a dask.distributed LocalCluster of 2 spawned workers whose OpenBLAS starts as
    this process's (`blas_environment`; `vdo calibrate --dask local` starts it so); a task that
    raises comes back from `vdo.core.parallel.run_tasks` as a `Failure` with the exception's line."""
    from vdo.calib import montecarlo as mc
    from vdo.core.parallel import Failure, blas_environment, dask_client, run_tasks

    args, serial = pair
    with dask_client("local", 2, env=blas_environment()) as client:
        assert_same(serial, mc.run(*args, sigma_det=0.1, client=client))
        out = dict(run_tasks(math.sqrt, [4.0, -1.0], client=client))
    assert out[4.0] == 2.0
    assert isinstance(out[-1.0], Failure) and out[-1.0].error == "ValueError: math domain error"
    assert "Traceback" in out[-1.0].traceback


def chi2_interval(dof: int, q: float) -> tuple[float, float]:
    """sqrt(chi2_dof at q and 1 - q / dof): where the sample sd over the true sd of dof + 1 normal
    draws lies with probability 1 - 2q (scipy's chi-square, not `ratio_interval`)."""
    from scipy.stats import chi2

    return tuple(float(np.sqrt(chi2.ppf(x, dof) / dof)) for x in (q, 1 - q))


CLI_TRIALS = 40      # sampling sd of a ratio 1/sqrt(2 (40 - 1)) = 11 %


def test_vdo_calibrate_montecarlo(tmp_path, capsys):
    """`vdo calibrate --montecarlo 40 --workers 1` on the small pair (corners sigma 0.1 px):
    montecarlo.json holds every parameter's ratio inside the interval of all 24 at once for 40
    trials (Bonferroni, 95 %: [0.67, 1.36]), sqrt(NEES) (the mean of 40 trials' chi2_24 / 24, so
    chi2 with 960 degrees of freedom over 960) within its 95 % interval [0.955, 1.045], the
    displacement and strain ratios within one ratio's [0.78, 1.22]; the intervals it states are
    scipy's. (Measured: ratios 0.90-1.18, sqrt(NEES) 0.986, displacement 1.096, strain 0.999.)"""
    import tomli_w

    from vdo.commands.cli import main

    path = tmp_path / "pair.toml"
    path.write_text(tomli_w.dumps(small_pair(detection_sigma_px=0.1).to_dict()))
    out = tmp_path / "mc"
    assert main(["calibrate", str(path), "--montecarlo", str(CLI_TRIALS), "--workers", "1",
                 "--out", str(out)]) == 0
    result = json.loads((out / "montecarlo.json").read_text())
    assert result["trials"] == CLI_TRIALS and result["sigma_det_px"] == 0.1
    (label, rig), = result["rigs"].items()
    assert label == "left:right"
    ratios = np.array([p["ratio"] for p in rig["parameters"].values()])
    assert len(ratios) == 24 and np.allclose(
        ratios, [p["observed"] / p["predicted"] for p in rig["parameters"].values()], rtol=1e-12)
    one = chi2_interval(CLI_TRIALS - 1, 0.025)
    every = chi2_interval(CLI_TRIALS - 1, 0.025 / 24)
    assert np.allclose(result["interval_one_ratio"], one) and np.allclose(rig["interval_all_ratios"], every)
    assert np.all((every[0] < ratios) & (ratios < every[1])), ratios.round(3)
    low, high = chi2_interval(CLI_TRIALS * 24, 0.025)
    assert low < rig["sqrt_nees"] < high
    assert one[0] < rig["displacement_ratio"] < one[1]
    assert one[0] < rig["strain_ratio"] < one[1]
    assert (out / "montecarlo.png").stat().st_size > 10_000
    assert "rig left:right: 24 parameters" in capsys.readouterr().out


@pytest.mark.parametrize("flags,field,words", [
    (["--montecarlo", "1"], "--montecarlo", "at least 2 calibrations (got 1)"),
    (["--montecarlo", "0"], "--montecarlo", "at least 2 calibrations (got 0)"),
    (["--montecarlo", "50", "--workers", "0"], "--workers", "must be at least 1 (got 0)"),
    (["--montecarlo", "50", "--plan"], "--montecarlo", "and --plan are two different runs"),
    (["--workers", "2"], "--workers", "add --montecarlo N"),
    (["--dask", "local"], "--dask", "add --montecarlo N"),
])
def test_bad_montecarlo_flags_are_one_line(flags, field, words, tmp_path, capsys, monkeypatch):
    """Each mistake: one line naming the file, the flag and the fix, before the experiment is read
    (the session planner is never called) and no output folder."""
    import vdo.calib.session
    from vdo.commands.cli import main

    def never(*_, **__):
        raise AssertionError("planned a session")

    monkeypatch.setattr(vdo.calib.session, "plan", never)
    out = tmp_path / "out"
    assert main(["calibrate", str(HOLED), *flags, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {HOLED}: {field}: ") and words in err[0], err
    assert not out.exists()


DOCS_COMMAND = ["calibrate", "experiments/holed_plate/stereo.toml", "--montecarlo", "8", "--workers", "2"]


def test_the_docs_command(tmp_path, monkeypatch):
    """docs/calibration.md's `vdo calibrate --montecarlo` line runs (the shipped-examples test
    collects fenced code blocks only), with --workers 1 as that test sets it (the pool's start-up
    is the other tests'): the holed plate's 30-pose session, its one pair with 24 positive
    ratios, the figure and the resolved experiment written."""
    from vdo.commands.cli import main

    docs = (ROOT / "docs" / "calibration.md").read_text()
    assert "vdo " + " ".join(DOCS_COMMAND) + " --out runs/holed_montecarlo" in docs
    monkeypatch.chdir(ROOT)
    out = tmp_path / "mc"
    assert main([*DOCS_COMMAND[:-1], "1", "--out", str(out), "--quiet"]) == 0
    result = json.loads((out / "montecarlo.json").read_text())
    assert list(result["rigs"]) == ["left:right"] and result["workers"] == 1 and result["trials"] == 8
    ratios = [p["ratio"] for p in result["rigs"]["left:right"]["parameters"].values()]
    assert len(ratios) == 24 and min(ratios) > 0
    assert (out / "montecarlo.png").is_file() and (out / "config.toml").is_file()


def test_time_limit_is_one_line_and_no_folder(tmp_path, capsys):
    """`--time-limit` shorter than the session's planning: the first trial does not start, one
    line says so, exit status 1, nothing written."""
    import tomli_w

    from vdo.commands.cli import main

    path = tmp_path / "pair.toml"
    path.write_text(tomli_w.dumps(small_pair().to_dict()))
    out = tmp_path / "mc"
    assert main(["calibrate", str(path), "--montecarlo", "5", "--workers", "1", "--time-limit", "0.01",
                 "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: the Monte Carlo ran past its time limit after 0 of 5 trials (--time-limit "
                   "0.01 s); nothing written"]
    assert not out.exists()


def test_nearest_branch_is_the_same_rotation():
    """A rotation vector near |r| = pi that points away from the true one moves to the other
    branch: the same rotation (OpenCV's Rodrigues), now beside the truth, and its covariance
    carried by the branch map's Jacobian (checked by central differences); the intrinsics and
    translation and a vector on the truth's side are left alone."""
    import cv2

    from vdo.calib import montecarlo as mc
    from vdo.calib import propagate as prop

    rng = np.random.default_rng(3)
    axis = np.array([0.0, -0.68, -0.73]) / np.linalg.norm([0.0, -0.68, -0.73])
    truth = np.r_[np.zeros(9), np.zeros(9), np.pi * axis, [0.5, 0.0, 0.1]]
    estimate = truth.copy()
    estimate[18:21] = -(np.pi - 0.01) * axis + 1e-3 * rng.normal(size=3)     # the other branch
    A = rng.normal(size=(24, 24))
    cov = A @ A.T * 1e-6
    slices = {"a": (slice(0, 9), None), "b": (slice(9, 18), slice(18, 24))}
    r = prop.Rig(names=("a", "b"), theta=estimate, covariance=cov, slices=slices,
                 world=(np.eye(3), np.zeros(3)))
    theta, moved = mc.nearest_branch(r, truth)
    rot = cv2.Rodrigues
    assert np.allclose(rot(theta[18:21])[0], rot(estimate[18:21])[0], atol=1e-12)
    assert np.linalg.norm(theta[18:21] - truth[18:21]) < 0.05
    assert np.array_equal(np.delete(theta, range(18, 21)), np.delete(estimate, range(18, 21)))

    def branch(v):
        return v * (1 - 2 * np.pi / np.linalg.norm(v))

    h = 1e-6
    J = np.stack([(branch(estimate[18:21] + h * e) - branch(estimate[18:21] - h * e)) / (2 * h)
                  for e in np.eye(3)], axis=1)
    T = np.eye(24)
    T[18:21, 18:21] = J
    assert np.allclose(moved, T @ cov @ T.T, rtol=1e-6, atol=1e-16)
    same, kept = mc.nearest_branch(prop.Rig(("a", "b"), truth, cov, slices, r.world), truth)
    assert np.array_equal(same, truth) and np.array_equal(kept, cov)


def test_a_session_whose_rigs_see_no_sample_is_one_line(tmp_path, capsys, monkeypatch):
    """The pressure vessel seen all round: its only rig calibrated together (all six cameras)
    has no region sample in every image. One line naming the file and the fix, no folder
    (it used to end in a traceback while drawing an empty figure)."""
    from vdo.commands.cli import main

    monkeypatch.setenv("VDO_SET", "calibration.poses_per_camera = 6; calibration.shared_poses = 3")
    path = Path(__file__).resolve().parents[2] / "experiments" / "pressure_vessel" / "all_round.toml"
    out = tmp_path / "mc"
    assert main(["calibrate", str(path), "--montecarlo", "5", "--workers", "1", "--out", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line.lower()]
    assert len(err) == 1 and "all_round.toml" in err[0] and "stereo_pair" in err[0]
    assert not out.exists()
