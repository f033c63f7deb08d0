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
from dataclasses import dataclass

import numpy as np

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
    true sd of `trials` independent normal draws (module docstring): sqrt(chi2_{n-1, q} / (n - 1))
    at q = a / 2P and 1 - a / 2P, a = 1 - confidence, n = trials (Bonferroni over parameters)."""
    from scipy.stats import chi2

    n, q = trials - 1, (1 - confidence) / 2 / parameters
    return tuple(float(np.sqrt(chi2.ppf(x, n) / n)) for x in (q, 1 - q))


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


def parameter_names(r: prop.Rig) -> tuple:
    out = []
    for name in r.names:
        out += [f"{name}.{p}" for p in INTRINSICS]
        if r.slices[name][1] is not None:
            out += [f"{name}.{p}" for p in ("rx", "ry", "rz", "tx", "ty", "tz")]
    return tuple(out)


def run(cameras, session, rigs, points: dict, motions: dict, trials: int, seed: int,
        sigma_det: float | None = None, images=None, sensor=None, deadline: float | None = None) -> MonteCarlo:
    """`trials` calibrations (module docstring). `cameras` the true vdo Cameras (at the images'
    scale), `rigs` tuples of camera names (each rig's first camera its group's reference),
    `points`/`motions` per rig the samples X (N, 3) and their `propagate.Motion`. Either
    `sigma_det` (simulated corners) or `images` (`vdo.calib.images.SessionImages`) with `sensor`."""
    from vdo.calib.detect import detect_all
    from vdo.core.progress import bar

    started = time.perf_counter()
    by_name = {c.name: c for c in cameras}
    names = [c.name for c in cameras]
    sizes = {c.name: (c.width, c.height) for c in cameras}
    thetas = {r: [] for r in rigs}
    du = {r: [] for r in rigs}
    de = {r: [] for r in rigs}
    corners = []
    first = None
    for t in bar(log, iterable=range(trials), desc="Monte Carlo", unit="calibration"):
        if deadline is not None and time.monotonic() > deadline:
            raise TimeoutError(f"the Monte Carlo ran past its time limit after {t} of {trials} trials")
        if images is None:
            obs = simulate(cameras, session, sigma_det, np.random.default_rng([seed, t]))
        else:
            obs, missed = detect_all(images.exposed(sensor, seed, t), session.target, sensor.max_dn)
            keep = {(o.camera, o.pose) for o in obs}
            if first is not None and keep != first:
                raise RuntimeError(f"trial {t}: the target was found in other images than in trial 0")
            first = keep
            corners.append(np.stack([o.corners for o in obs]))
        cal = calibrate(names, sizes, obs, session.target, sigma_det if images is None else 1.0)
        for r_names in rigs:
            r = prop.rig(cal, r_names, cameras)
            cams = [by_name[n] for n in r_names]
            thetas[r_names].append((r.theta, r.covariance))
            eu, ee = prop.measured_errors(r, r.theta, cams, points[r_names], motions[r_names])
            du[r_names].append(eu)
            de[r_names].append(ee)
    if images is None:
        scale2, measured = 1.0, float(sigma_det)
    else:
        c = np.stack(corners)                                    # (trials, O, n, 2)
        measured = float(np.sqrt(((c - c.mean(axis=0)) ** 2).sum() / (c[..., 0].size * 2 - c[0].size)))
        scale2 = measured ** 2          # the covariances above were for sigma_det = 1 px
    out = []
    for r_names in rigs:
        cams = [by_name[n] for n in r_names]
        th = np.stack([a for a, _ in thetas[r_names]])
        covs = [b * scale2 for _, b in thetas[r_names]]
        S = np.mean(covs, axis=0)
        r = prop.Rig(names=r_names, theta=th[0], covariance=S, slices=prop.rig(cal, r_names, cameras).slices,
                     world=(cams[0].R, cams[0].t))
        predicted = prop.propagate(r, cams, points[r_names], motions[r_names])
        truth = true_theta(r, cams)
        err = th - truth
        Sinv = np.linalg.inv(S)
        nees = float(np.mean(np.einsum("tp,pq,tq->t", err, Sinv, err)) / th.shape[1])
        U = np.stack(du[r_names])                                # (trials, N, 3)
        E = np.stack(de[r_names])                                # (trials, N)
        out.append(RigScatter(
            names=r_names, parameters=parameter_names(r), predicted=np.sqrt(np.diag(S)),
            observed=th.std(axis=0, ddof=1),
            displacement_predicted=predicted.displacement,
            displacement_observed=np.sqrt(U.var(axis=0, ddof=1).sum(axis=1)),
            strain_predicted=predicted.strain, strain_observed=E.std(axis=0, ddof=1), nees=nees,
            bias_displacement=U.mean(axis=0), bias_strain=E.mean(axis=0)))
    return MonteCarlo(trials=trials, sigma_det=measured, rigs=tuple(out),
                      seconds=time.perf_counter() - started)
