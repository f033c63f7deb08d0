"""Coverage and uncertainty over a test's load path: one layout state per keyframe.

For each step k of the load path (`vdo.keyframes`) the geometry is moved to that step and the
cameras judged on it (`vdo.state.layout_state`). Per sample the **worst case** over the steps is
kept: the fewest cameras that see it and the largest σ_max (and the step where it occurs). Per
region and step: the area fraction seen by at least the region's minimum number of cameras and
the σ_max p95. A camera **loses** a region at the first step where it sees less than
`SEEN_FRACTION` of the region's area after having seen at least that much at rest.

The cost is one ray cast, one lighting pass and one prediction per step: linear in the number of
steps (`benchmarks/load_path.py`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from .keyframes import LoadPath, at_step
from .state import Geometry, LayoutState, layout_state

logger = logging.getLogger(__name__)

SEEN_FRACTION = 0.5     # a camera sees a region when it sees at least this fraction of its area


@dataclass(frozen=True, eq=False)
class LoadPathResult:
    """Per-step fields over the samples (index 0 is the rest state, then the load path's steps)."""

    steps: tuple                  # ("rest", step_1, step_2, ...)
    camera_names: tuple[str, ...]
    region_names: tuple[str, ...]
    coverage: np.ndarray          # (K, N) cameras that see each sample
    sigma_max: np.ndarray         # (K, N) m, +inf where unmeasured
    seen_fraction: np.ndarray     # (K, C, R) area fraction of each region each camera sees
    region_covered: np.ndarray    # (K, R) area fraction seen by >= the region's minimum cameras
    region_sigma_p95: np.ndarray  # (K, R) m over the measured samples (NaN if none)
    losses: tuple[dict, ...]      # {"camera", "region", "step", "rest_fraction", "fraction"}

    @property
    def worst_coverage(self) -> np.ndarray:
        return self.coverage.min(axis=0)

    @property
    def worst_sigma(self) -> np.ndarray:
        return self.sigma_max.max(axis=0)

    @property
    def worst_step_index(self) -> np.ndarray:
        """Index into `steps` of each sample's largest σ_max."""
        return self.sigma_max.argmax(axis=0)


def _region_stats(state: LayoutState, minimum: np.ndarray):
    samples = state.samples
    area = samples.area
    visible = state.prediction.usable           # usable views (`vdo.usable`), as everywhere
    covered = state.prediction.coverage >= minimum[samples.region]
    sigma = np.where(state.prediction.measured, state.prediction.sigma_max, np.inf)
    n_regions = len(samples.region_names)
    seen = np.zeros((visible.shape[0], n_regions))
    cov = np.zeros(n_regions)
    p95 = np.full(n_regions, np.nan)
    for r in range(n_regions):
        mask = samples.region == r
        total = area[mask].sum()
        seen[:, r] = (visible[:, mask] * area[mask]).sum(axis=1) / total
        cov[r] = area[mask & covered].sum() / total
        finite = sigma[mask][np.isfinite(sigma[mask])]
        if finite.size:
            p95[r] = np.percentile(finite, 95)
    return seen, cov, p95, sigma


def evaluate_load_path(geometry: Geometry, load_path: LoadPath, cameras=None,
                       progress: bool = False, rest: LayoutState | None = None) -> LoadPathResult:
    """Judge `cameras` (default: the experiment's) at rest and at every step of `load_path`.
    `rest`: the state at rest when already computed (`layout_state(geometry, cameras)`)."""
    exp = geometry.experiment
    minimum = np.array([r.min_cameras or exp.evaluation.min_cameras for r in exp.regions])
    steps = ("rest",) + tuple(load_path.steps)
    coverage, sigma, seen, covered, p95 = [], [], [], [], []
    for step in tqdm(steps, desc="load path", unit="step", disable=not progress):
        if step == "rest" and rest is not None:
            state = rest
        else:
            moved = geometry if step == "rest" else at_step(geometry, load_path, step)
            state = layout_state(moved, cameras)
        s, c, p, sig = _region_stats(state, minimum)
        coverage.append(state.prediction.coverage)
        sigma.append(sig)
        seen.append(s)
        covered.append(c)
        p95.append(p)
    seen_arr = np.array(seen)
    camera_names = state.visibility.camera_names
    losses = []
    for c, camera in enumerate(camera_names):
        for r, region in enumerate(geometry.samples.region_names):
            if seen_arr[0, c, r] < SEEN_FRACTION:
                continue
            lost = np.flatnonzero(seen_arr[1:, c, r] < SEEN_FRACTION)
            if lost.size:
                k = lost[0] + 1
                losses.append({"camera": camera, "region": region, "step": steps[k],
                               "rest_fraction": float(seen_arr[0, c, r]),
                               "fraction": float(seen_arr[k, c, r])})
                logger.warning("camera %s loses region %s at step %s (sees %.0f%% of it, %.0f%% at rest)",
                               camera, region, steps[k], 100 * seen_arr[k, c, r], 100 * seen_arr[0, c, r])
    return LoadPathResult(steps, camera_names, geometry.samples.region_names, np.array(coverage),
                          np.array(sigma), seen_arr, np.array(covered), np.array(p95), tuple(losses))


def summary(result: LoadPathResult) -> dict:
    """For summary.json: the steps, the losses, and per region the worst step's covered area
    fraction and σ_max p95 (µm) with the steps where they occur."""
    regions = {}
    for r, region in enumerate(result.region_names):
        covered, p95 = result.region_covered[:, r], result.region_sigma_p95[:, r]
        worst = int(np.nanargmax(p95)) if np.isfinite(p95).any() else None
        regions[region] = {
            "covered_fraction_min": float(covered.min()),
            "covered_fraction_min_step": result.steps[int(covered.argmin())],
            "sigma_max_p95_um_max": None if worst is None else float(p95[worst] * 1e6),
            "sigma_max_p95_um_max_step": None if worst is None else result.steps[worst]}
    return {"steps": len(result.steps) - 1, "seen_fraction": SEEN_FRACTION,
            "losses": list(result.losses), "regions": regions}


def table(result: LoadPathResult) -> list[dict]:
    """Rows (step, region, covered fraction, σ_max p95 in µm) for `load_path.csv`."""
    rows = []
    for k, step in enumerate(result.steps):
        for r, region in enumerate(result.region_names):
            p95 = result.region_sigma_p95[k, r]
            rows.append({"step": step, "region": region,
                         "covered_fraction": round(float(result.region_covered[k, r]), 4),
                         "sigma_max_p95_um": "" if np.isnan(p95) else round(float(p95) * 1e6, 4)})
    return rows


def plot(result: LoadPathResult, path, title: str = "") -> None:
    """Two panels against the step: each region's covered area fraction and its σ_max p95."""
    import matplotlib.pyplot as plt

    x = np.arange(len(result.steps))
    fig, (ax_c, ax_s) = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    colours = plt.get_cmap("tab20")
    for r, region in enumerate(result.region_names):
        style = dict(marker=".", label=region, color=colours(r % 20), ls="-" if r < 20 else "--")
        ax_c.plot(x, 100 * result.region_covered[:, r], **style)
        ax_s.plot(x, result.region_sigma_p95[:, r] * 1e6, **style)
    ax_c.set_ylabel("area seen by ≥ min. cameras (%)")
    ax_c.set_ylim(-5, 105)
    ax_s.set_ylabel("σ_max p95 (µm)")
    ax_s.set_xlabel("step")
    ax_s.set_xticks(x, [str(s) for s in result.steps], rotation=90 if len(x) > 20 else 0, fontsize=7)
    ax_c.legend(fontsize=7, ncol=3, loc="lower left")
    for loss in result.losses:
        k = result.steps.index(loss["step"])
        ax_c.axvline(k, color="0.6", lw=0.8, ls="--")
    ax_c.set_title(title or "coverage and uncertainty over the load path", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
