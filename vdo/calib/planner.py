"""`vdo calibrate --plan`: how many target images reach a calibration-induced strain error.

For each candidate count n of generated poses per camera (`COUNTS`, shared poses per pair scaled
alike), the session is built and checked as `vdo calibrate` would (`vdo.calib.session.plan`), its
corners simulated without noise at the true cameras, calibrated with sigma_det = [calibration]
detection_sigma_px (default `DEFAULT_SIGMA_DET_PX`), and the covariance sigma_det^2 (J^T J)^-1
propagated into every sample seen by a stereo pair (`vdo.calib.propagate.sample_errors`). The
plan is the smallest n whose strain sigma (p95 over the samples, at the test's strain) is at most
[calibration] target_strain_error; the curve of that sigma against the number of images shows
the diminishing returns (about 1/sqrt(images) once the parameters are constrained). The curve
goes PLAN_PAST_TARGET counts past the first that reaches the target, then stops (the larger
sessions cost the most: trial 4's plan met its target at 3 poses in 7 s, then calibrated up to
845 images for 6 min). The progress counts poses, so that its time left weighs the larger
sessions. The sessions
nest (`vdo.calib.session`: each pose depends on its index alone), so each larger session adds
rows to the same least squares and the curve never rises.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

log = logging.getLogger(__name__)
COUNTS = (3, 4, 6, 8, 12, 16, 24, 32)     # poses per camera tried
PLAN_PAST_TARGET = 1                      # counts tried past the first that reaches the target
DEFAULT_SIGMA_DET_PX = 0.05               # corner detection noise when none is configured (px)


@dataclass(frozen=True)
class Plan:
    """`counts` poses per camera tried, `images` the images each session takes, `strain_p95` the
    calibration-induced strain sigma (p95 over samples, at the test's strain), `chosen` the
    count picked (None: none reaches `target`), `sigma_det` px."""

    counts: tuple
    images: tuple
    strain_p95: tuple
    chosen: int | None
    target: float
    sigma_det: float


def shared_pairs(pairs, names, visible: np.ndarray) -> list:
    """The pairs of `pairs` (camera names) whose two cameras both see at least one sample
    (`visible` (C, N) from the ray cast, rows in the order of `names`)."""
    row = {n: i for i, n in enumerate(names)}
    return [(a, b) for a, b in pairs if np.any(visible[row[a]] & visible[row[b]])]


def unshared_message(exp, cameras, visibility, samples, pairs) -> str:
    """Why no calibrated stereo pair sees a region sample with both cameras, and the fix with an
    example pair in [[stereo_pair]] form (`vdo.formats.export.no_pair_message`, `pair_example`:
    the two cameras that see the most of one region together). No `pairs` at all (none declared,
    none by the default rule): why the rule found none."""
    from vdo.calib.session import STEREO_PAIR_TABLE
    from vdo.formats.export import no_pair_message, pair_example

    if not pairs:
        return ("the plan needs a stereo pair, none is declared, and "
                + no_pair_message(exp, cameras, visibility, samples, STEREO_PAIR_TABLE))
    example = pair_example(exp, cameras, visibility.visible, samples, STEREO_PAIR_TABLE)
    return ("no calibrated stereo pair sees a region sample with both cameras: name stereo pairs "
            "that share a view of a region with " + STEREO_PAIR_TABLE.form + ", "
            + (example or "after moving two cameras so that they do"))


def plan_session(exp, visibility, geometry, pairs) -> Plan:
    """The curve and the chosen count (module docstring). `visibility` the ray cast (its
    `visible` (C, N), rows in the order of `exp.camera_specs`, `vdo.scene.cameras_of`); `pairs`
    the stereo pairs to calibrate (`vdo.calib.session.stereo_names`). Raises ConfigError before
    any calibration when no pair's cameras see a common sample (`unshared_message`)."""
    from vdo.calib.propagate import sample_errors
    from vdo.calib.session import plan
    from vdo.calib.solve import calibrate, simulate
    from vdo.core.errors import ConfigError
    from vdo.core.progress import bar, finish_early, hidden
    from vdo.scene import cameras_of

    cameras = cameras_of(exp.camera_specs, exp.rails)
    visible = visibility.visible
    if not shared_pairs(pairs, [c.name for c in cameras], visible):
        raise ConfigError(exp.path, "stereo_pair",
                          unshared_message(exp, cameras, visibility, geometry.samples, pairs))
    spec = exp.calibration
    sigma = spec.detection_sigma_px or DEFAULT_SIGMA_DET_PX
    counts, images, p95 = [], [], []
    unseen = False                # a session calibrated, but no pair saw a sample with both cameras
    base_shared = spec.shared_poses / max(1, spec.poses_per_camera)
    progress = bar(log, total=sum(COUNTS), desc="planning the session", unit="pose")
    past = None                   # counts tried since the target was reached
    for n in COUNTS:
        if past is not None and past >= PLAN_PAST_TARGET:
            log.info("target %.3g reached at %d poses per camera: larger sessions not tried",
                     spec.target_strain_error, counts[len(counts) - 1 - past])
            break
        trial = replace(spec, poses_per_camera=n, shared_poses=max(1, round(base_shared * n)))
        try:
            planned = plan(exp, 1.0, geometry, trial, pairs)
        except ConfigError as exc:
            log.info("%d poses per camera: %s", n, exc.message)
            progress.update(n)
            continue
        cams = list(planned.cameras)
        obs = simulate(cams, planned.session, 0.0, np.random.default_rng(0))
        cal = calibrate([c.name for c in cams], {c.name: (c.width, c.height) for c in cams}, obs,
                        planned.session.target, sigma)
        with hidden("vdo.calib.propagate"):
            errors = sample_errors(cal, exp, cams, geometry.samples, visible, planned.session.pairs)
        progress.update(n)
        finite = errors.strain[np.isfinite(errors.strain)]
        if len(finite) == 0:
            unseen = True
            continue
        counts.append(n)
        images.append(sum(len(v) for v in planned.session.views.values()))
        p95.append(float(np.percentile(finite, 95)))
        log.info("%d poses per camera: %d images, strain sigma p95 %.3g", n, images[-1], p95[-1])
        if past is not None:
            past += 1
        elif p95[-1] <= spec.target_strain_error:
            past = 0
    finish_early(progress)        # the larger sessions past the target are not tried
    if not counts and unseen:     # pairs that share samples but were not calibrated together
        raise ConfigError(exp.path, "stereo_pair",
                          unshared_message(exp, cameras, visibility, geometry.samples, pairs))
    if not counts:
        raise ConfigError(exp.path, "calibration", "no session of the planner's sizes passes the "
                                                   "checks: see vdo calibrate's message for one")
    reached = [n for n, e in zip(counts, p95) if e <= spec.target_strain_error]
    return Plan(counts=tuple(counts), images=tuple(images), strain_p95=tuple(p95),
                chosen=reached[0] if reached else None, target=spec.target_strain_error,
                sigma_det=sigma)


def plot(p: Plan, path, title: str) -> None:
    """The diminishing-returns curve: strain sigma against the number of images (log-log), the
    target and the chosen session."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), layout="constrained")
    ax.loglog(p.images, np.array(p.strain_p95) * 1e6, "o-", label="calibration strain sigma (p95)")
    ax.axhline(p.target * 1e6, color="k", ls="--", label="target")
    if p.chosen is not None:
        k = p.counts.index(p.chosen)
        ax.plot(p.images[k], p.strain_p95[k] * 1e6, "r*", ms=14,
                label=f"chosen: {p.chosen} poses per camera")
    ax.set_xlabel("images in the session")
    ax.set_ylabel("microstrain at the test's strain")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
