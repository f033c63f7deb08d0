"""Monte Carlo calibrations: many calibrations of one session with independent detection noise,
their scatter against the covariance each predicts.

Each trial draws new corner observations (`simulate`: the true corners plus N(0, sigma^2) per
coordinate; or `images`: the noise-free renders exposed with new sensor noise and detected, no
render per trial), calibrates the whole rig (`vdo.calib.solve.calibrate`) and, for every rig of
cameras (`vdo.calib.propagate.Rig`, e.g. a stereo pair), triangulates the true cameras' pixels of
a known motion: the displacement and strain errors that calibration leaves
(`propagate.measured_errors`). The scatter over trials (standard deviation about the trials'
mean) is compared with the sigma predicted from one calibration's covariance
sigma_det^2 (J^T J)^-1 (`propagate.propagate`); for rendered images sigma_det is the corners'
measured scatter between trials (pooled over every corner), the noise the covariance is about.

Also the normalised estimation error squared, NEES = (theta - theta_true)^T Sigma^-1
(theta - theta_true) / P, averaged over trials (1 when the covariance is right, 1/P-dimensional
chi-square scatter otherwise).

How far a ratio may stray by chance (`ratio_interval`): the sample sd of n normal draws over the
true sd is sqrt(chi2_{n-1} / (n - 1)), so one ratio's 95 % interval is [0.80, 1.20] at 50 trials
and [0.90, 1.10] at 200; P ratios at once need the Bonferroni interval (each at 0.05 / P): at 50
trials [0.68, 1.34] for the 54 parameters of 4 cameras, so a few of them at 0.73-0.79 are chance,
not a missing term. All 54 within [0.8, 1.25] with 95 % confidence needs n >= 135.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from vdo.core.stats import sd_ratio_band

from vdo.calib import propagate as prop
from vdo.calib.solve import INTRINSICS, calibrate, rvec, simulate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RigScatter:
    """One rig's Monte Carlo: `parameters` names, `predicted` and `observed` sigma (P,) and
    their `ratio` (observed / predicted); per sample the displacement error's predicted and
    observed rms sigma (N,) (sqrt of the trace), the strain error's (N,); `nees` the trials'
    mean normalised estimation error squared; `bias_*` the trials' mean errors."""

    names: tuple
    parameters: tuple
    predicted: np.ndarray
    observed: np.ndarray
    displacement_predicted: np.ndarray
    displacement_observed: np.ndarray
    strain_predicted: np.ndarray
    strain_observed: np.ndarray
    nees: float
    bias_displacement: np.ndarray
    bias_strain: np.ndarray

    @property
    def ratio(self) -> np.ndarray:
        return self.observed / self.predicted

    @property
    def displacement_ratio(self) -> float:
        """rms over samples of the observed over that of the predicted sigma."""
        return float(np.sqrt((self.displacement_observed ** 2).mean() / (self.displacement_predicted ** 2).mean()))

    @property
    def strain_ratio(self) -> float:
        return float(np.sqrt((self.strain_observed ** 2).mean() / (self.strain_predicted ** 2).mean()))


@dataclass(frozen=True)
class MonteCarlo:
    trials: int
    sigma_det: float
    rigs: tuple
    seconds: float


def ratio_interval(trials: int, parameters: int = 1, confidence: float = 0.95) -> tuple[float, float]:
    """The interval holding, with probability `confidence`, all `parameters` ratios sample sd /
    true sd of `trials` independent normal draws (module docstring; `vdo.core.stats.sd_ratio_band`,
    Bonferroni over parameters)."""
    return sd_ratio_band(trials, parameters, confidence)


def true_theta(r: prop.Rig, cameras) -> np.ndarray:
    """The rig's parameters of the true cameras (`cameras` in `r.names` order)."""
    from vdo.calib.truth import true_intrinsics

    ref = cameras[0]
    parts = []
    for name, cam in zip(r.names, cameras):
        parts.append(true_intrinsics(cam))
        if r.slices[name][1] is not None:
            R = cam.R @ ref.R.T
            parts.append(np.r_[rvec(R), cam.t - R @ ref.t])
    return np.concatenate(parts)


def nearest_branch(r: prop.Rig, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, covariance) of the rig `r` with each camera's rotation vector on the branch of the
    true one `truth` (`true_theta`). A rotation by angle a about n is also one by a - 2 pi about
    n: r and r' = r (1 - 2 pi / |r|) are the same rotation, and near a = pi (a camera turned
    half round against the reference, as cam3 of experiments/beam_column/three_cameras.toml)
    calibrations land on either, which is no error. A rotation vector that points away from the
    true one (r . r_true < 0) moves to the other branch, its covariance with it through the
    Jacobian dr'/dr = (1 - 2 pi / |r|) I + 2 pi r r^T / |r|^3 (at |r| = pi the reflection
    -I + 2 n n^T, so the rotation's sigmas keep their size)."""
    theta, cov = r.theta.copy(), r.covariance.copy()
    for _, ext in r.slices.values():
        if ext is None:
            continue
        rot = slice(ext.start, ext.start + 3)
        v = theta[rot]
        norm = float(np.linalg.norm(v))
        if norm == 0.0 or float(v @ truth[rot]) >= 0.0:
            continue
        T = np.eye(len(theta))
        T[rot, rot] = (1 - 2 * np.pi / norm) * np.eye(3) + 2 * np.pi * np.outer(v, v) / norm ** 3
        theta[rot] = v * (1 - 2 * np.pi / norm)
        cov = T @ cov @ T.T
    return theta, cov


def parameter_names(r: prop.Rig) -> tuple:
    out = []
    for name in r.names:
        out += [f"{name}.{p}" for p in INTRINSICS]
        if r.slices[name][1] is not None:
            out += [f"{name}.{p}" for p in ("rx", "ry", "rz", "tx", "ty", "tz")]
    return tuple(out)


@dataclass(frozen=True)
class Trials:
    """Trials `start` to `stop` - 1 of one Monte Carlo, a task for `run_trials` (picklable): the true
    `cameras`, the `session`, the `rigs`, per rig the `points` and `motions`, the `seed`, and
    either `sigma_det` or `images` with `sensor` (`run`). `deadline`: time.time() after which
    no trial starts (TimeoutError)."""

    start: int
    stop: int
    cameras: tuple
    session: object
    rigs: tuple
    points: dict
    motions: dict
    seed: int
    sigma_det: float | None
    images: object = None
    sensor: object = None
    deadline: float | None = None


@dataclass(frozen=True)
class TrialResults:
    """What `run_trials` returns for trials start..stop - 1 (k of them), per rig of `Trials.rigs`:
    `theta` (k, P) the calibrated parameters, `covariance` (k, P, P) each calibration's
    covariance (for sigma_det = 1 px with rendered images), `displacement` (k, N, 3) and `strain`
    (k, N) the triangulated errors (`propagate.measured_errors`), `slices` the rig's parameter
    slices; with rendered images per trial the detected `corners` (O, n, 2) and the `found`
    (camera, pose) pairs, else empty tuples."""

    start: int
    stop: int
    theta: dict
    covariance: dict
    displacement: dict
    strain: dict
    slices: dict
    corners: tuple
    found: tuple


def run_trials(task: Trials) -> TrialResults:
    """Calibrate trials task.start..task.stop - 1 (module docstring): trial t's corners are
    `simulate`d with the generator default_rng([seed, t]), or its images exposed with
    `SessionImages.exposed(sensor, seed, t)` and detected; so a trial's result does not depend on
    the task that computes it. OpenCV, NumPy and SciPy run on one thread here, the earlier
    counts restored after: OpenCV's threaded calibrateCamera (the start values) sums over the
    views in an order that varies from call to call, so that the same corners gave calibrations
    that differed in their last bits (up to 6e-5 of a parameter's sigma over 4 trials), and the
    covariance's inverse differed in its last bits with 1 and 2 OpenBLAS threads
    (`vdo.core.parallel.blas_threads`); on one thread a trial is a function of its seed alone.
    It is faster too: the 4-camera calibration took 6.5 s with 2 OpenBLAS threads on 2 loaded
    cores, 0.69 s with 1. (OpenCV's count is set here and not in `vdo.calib.solve.initial`: set
    and reset there at every calibration, it slowed SciPy's threaded Cholesky of the planner's
    calibrations twentyfold, 1.2 -> 25 s in `vdo calibrate --plan` on 2 loaded cores.)"""
    import cv2

    from vdo.core.parallel import blas_threads

    opencv = cv2.getNumThreads()
    cv2.setNumThreads(0)
    try:
        with blas_threads(1):
            return _trials(task)
    finally:
        cv2.setNumThreads(opencv)


def _trials(task: Trials) -> TrialResults:
    """The calibrations of `run_trials`."""
    from vdo.calib.detect import detect_all

    cameras = list(task.cameras)
    by_name = {c.name: c for c in cameras}
    names = [c.name for c in cameras]
    sizes = {c.name: (c.width, c.height) for c in cameras}
    out = {key: {r: [] for r in task.rigs} for key in ("theta", "covariance", "displacement", "strain")}
    slices, corners, found = {}, [], []
    for t in range(task.start, task.stop):
        if task.deadline is not None and time.time() > task.deadline:
            raise TimeoutError(f"trial {t} would start past the time limit")
        if task.images is None:
            obs = simulate(cameras, task.session, task.sigma_det, np.random.default_rng([task.seed, t]))
        else:
            obs, _ = detect_all(task.images.exposed(task.sensor, task.seed, t), task.session.target,
                                task.sensor.max_dn)
            found.append(frozenset((o.camera, o.pose) for o in obs))
            corners.append(np.stack([o.corners for o in obs]))
        cal = calibrate(names, sizes, obs, task.session.target,
                        task.sigma_det if task.images is None else 1.0)
        for r_names in task.rigs:
            r = prop.rig(cal, r_names, cameras)
            cams = [by_name[n] for n in r_names]
            eu, ee = prop.measured_errors(r, r.theta, cams, task.points[r_names], task.motions[r_names])
            theta, covariance = nearest_branch(r, true_theta(r, cams))
            for key, value in (("theta", theta), ("covariance", covariance),
                               ("displacement", eu), ("strain", ee)):
                out[key][r_names].append(value)
            slices[r_names] = r.slices
    stacked = {key: {r: np.stack(v) for r, v in d.items()} for key, d in out.items()}
    return TrialResults(start=task.start, stop=task.stop, slices=slices, corners=tuple(corners),
                        found=tuple(found), **stacked)


CHUNKS_PER_WORKER = 8     # tasks per worker: progress, the time limit and the load stay even


def chunks(count: int, workers: int) -> list[tuple[int, int]]:
    """(start, stop) of the tasks that split `count` trials over `workers`: about
    CHUNKS_PER_WORKER each, at least one trial per task."""
    size = max(1, -(-count // (workers * CHUNKS_PER_WORKER)))
    return [(a, min(a + size, count)) for a in range(0, count, size)]


def run(cameras, session, rigs, points: dict, motions: dict, trials: int, seed: int,
        sigma_det: float | None = None, images=None, sensor=None, deadline: float | None = None,
        workers: int | None = None, client=None) -> MonteCarlo:
    """`trials` calibrations (module docstring). `cameras` the true vdo Cameras (at the images'
    scale), `rigs` tuples of camera names (each rig's first camera its group's reference),
    `points`/`motions` per rig the samples X (N, 3) and their `propagate.Motion`. Either
    `sigma_det` (simulated corners) or `images` (`vdo.calib.images.SessionImages`) with `sensor`.
    `deadline` (time.monotonic) stops with TimeoutError.

    Where: in this process (default), on a local pool of `workers` >= 2 spawned processes, or on
    the workers of a dask.distributed `client` (`vdo.core.parallel.run_tasks`), the trials split
    into `chunks`; the result is the same to the last bit wherever the trials ran (each trial's
    noise comes from its own seed, and the trials are gathered in their order) on the same kind
    of machine, provided the workers' OpenBLAS started with this process's thread count (a local
    pool's do; for Dask workers, `vdo.core.parallel.blas_environment`)."""
    from vdo.core.progress import bar

    started = time.perf_counter()
    rigs = [tuple(r) for r in rigs]
    task = Trials(start=0, stop=0, cameras=tuple(cameras), session=session, rigs=tuple(rigs),
                  points=dict(points), motions=dict(motions), seed=seed, sigma_det=sigma_det,
                  images=images, sensor=sensor)
    done: list[TrialResults] = []
    progress = bar(log, total=trials, desc="Monte Carlo", unit="calibration")
    try:
        if client is None and (workers or 1) <= 1:
            for t in range(trials):
                if deadline is not None and time.monotonic() > deadline:
                    raise TimeoutError(f"the Monte Carlo ran past its time limit after {t} of {trials} "
                                       "trials")
                done.append(run_trials(replace(task, start=t, stop=t + 1)))
                progress.update()
        else:
            done = _parallel(task, trials, deadline, workers, client, progress)
    finally:
        progress.close()
    return gather(done, task, trials, started)


def _parallel(task: Trials, count: int, deadline, workers, client, progress) -> list[TrialResults]:
    """The chunks of `run` on a local pool or Dask, in trial order; the first failed chunk ends
    the run (TimeoutError past the `deadline`, else RuntimeError with the worker's error)."""
    from vdo.core.parallel import Failure, cores, run_tasks

    if client is not None:
        workers = max(1, sum(client.nthreads().values()))
    wall = None if deadline is None else time.time() + (deadline - time.monotonic())
    tasks = [replace(task, start=a, stop=b, deadline=wall) for a, b in chunks(count, workers)]
    threads = None if client is not None else max(1, cores() // workers)
    results = run_tasks(run_trials, tasks, workers=workers, threads=threads, client=client,
                        name="vdo-montecarlo")
    done = []
    try:
        for chunk, result in results:
            finished = sum(r.stop - r.start for r in done)
            if isinstance(result, Failure):
                if deadline is not None and time.monotonic() > deadline:
                    raise TimeoutError(f"the Monte Carlo ran past its time limit after {finished} "
                                       f"of {count} trials")
                raise RuntimeError(f"Monte Carlo trials {chunk.start}-{chunk.stop - 1}: {result.error}")
            done.append(result)
            progress.update(result.stop - result.start)
            if deadline is not None and time.monotonic() > deadline and len(done) < len(tasks):
                raise TimeoutError(f"the Monte Carlo ran past its time limit after "
                                   f"{finished + result.stop - result.start} of {count} trials")
    finally:
        results.close()          # stops the pool (or cancels the Dask tasks) when ended early
    return sorted(done, key=lambda r: r.start)


def gather(done: list[TrialResults], task: Trials, count: int, started: float) -> MonteCarlo:
    """The `MonteCarlo` of the trials' results `done` (in trial order) of `run`."""
    by_name = {c.name: c for c in task.cameras}
    cat = (lambda key, r: np.concatenate([getattr(d, key)[r] for d in done]))    # noqa: E731
    if task.images is None:
        scale2, measured = 1.0, float(task.sigma_det)
    else:
        found = [f for d in done for f in d.found]
        for t, f in enumerate(found):
            if f != found[0]:
                raise RuntimeError(f"trial {t}: the target was found in other images than in trial 0")
        c = np.stack([x for d in done for x in d.corners])      # (trials, O, n, 2)
        measured = float(np.sqrt(((c - c.mean(axis=0)) ** 2).sum() / (c[..., 0].size * 2 - c[0].size)))
        scale2 = measured ** 2          # the covariances above were for sigma_det = 1 px
    out = []
    for r_names in task.rigs:
        cams = [by_name[n] for n in r_names]
        th = cat("theta", r_names)
        S = np.mean(cat("covariance", r_names) * scale2, axis=0)
        r = prop.Rig(names=r_names, theta=th[0], covariance=S, slices=done[-1].slices[r_names],
                     world=(cams[0].R, cams[0].t))
        predicted = prop.propagate(r, cams, task.points[r_names], task.motions[r_names])
        truth = true_theta(r, cams)
        err = th - truth
        Sinv = np.linalg.inv(S)
        nees = float(np.mean(np.einsum("tp,pq,tq->t", err, Sinv, err)) / th.shape[1])
        U = cat("displacement", r_names)                         # (trials, N, 3)
        E = cat("strain", r_names)                               # (trials, N)
        out.append(RigScatter(
            names=r_names, parameters=parameter_names(r), predicted=np.sqrt(np.diag(S)),
            observed=th.std(axis=0, ddof=1),
            displacement_predicted=predicted.displacement,
            displacement_observed=np.sqrt(U.var(axis=0, ddof=1).sum(axis=1)),
            strain_predicted=predicted.strain, strain_observed=E.std(axis=0, ddof=1), nees=nees,
            bias_displacement=U.mean(axis=0), bias_strain=E.mean(axis=0)))
    return MonteCarlo(trials=count, sigma_det=measured, rigs=tuple(out),
                      seconds=time.perf_counter() - started)
