"""Coverage and uncertainty over a test's load path: one layout state per keyframe.

For each step k of the load path (`vdo.geometry.keyframes`) the geometry is moved to that step and the
cameras judged on it (`vdo.state.layout_state`). Per sample the **worst case** over the steps is
kept: the fewest cameras that see it and the largest σ_max (and the step where it occurs). Per
region and step: the area fraction seen by at least the region's minimum number of cameras and
the σ_max p95. A camera **loses** a region at the first step where it sees less than
`SEEN_FRACTION` of the region's area after having seen at least that much at rest.

The cost is one ray cast, one lighting pass and one prediction per step: linear in the number of
steps (`benchmarks/load_path.py`). The steps are independent: `evaluate_load_path` runs them in
this process, on a local pool of spawned processes or on a Dask cluster
(`vdo.core.parallel.run_tasks`, `vdo evaluate --workers N | --dask ADDRESS`), with the same
arrays to the last bit: each step is judged from the rest geometry alone (`judge_step`).

For the optimizer and the design search (`path_occlusion`, `scored_path`): a view (camera i,
sample n) **holds over the path** when camera i sees sample n (in front, in the image, facing it
within the incidence limit, unoccluded: `vdo.physics.visibility`) in the geometry moved to at least a
fraction q of the chosen keyframes (q = 1: every one, the worst case); the score then counts only
views that hold over the path and are seen at rest (the reference image), while the sensitivity
and footprint stay those of the rest geometry (docs/theory.md, "Over the load path").
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from vdo.core.parallel import Failure, TaskFailed, cores, run_tasks
from vdo.core.progress import shown_bar
from vdo.geometry.keyframes import LoadPath, at_step, load_path_of
from vdo.scene import build_scene
from vdo.state import Geometry, LayoutState, bodies, layout_state
from vdo.physics.visibility import compute_visibility
from vdo.core.tolerances import LIMIT_SLACK

logger = logging.getLogger(__name__)

SEEN_FRACTION = 0.5     # a camera sees a region when it sees at least this fraction of its area
SIGMA_RATIO = 1.5       # a region's sigma_max p95 at a step this many times its p95 at rest: a change
COVERAGE_DROP = 0.05    # its area fraction seen by its min_cameras this far below rest: a change


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
    changes: tuple[dict, ...] = ()  # `region_changes`

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
    visible = state.prediction.usable           # usable views (`vdo.physics.usable`), as everywhere
    covered = state.prediction.coverage >= minimum[samples.region]
    sigma = np.where(state.prediction.measured, state.prediction.sigma_max, np.inf)
    n_regions = len(samples.region_names)
    seen = np.zeros((visible.shape[0], n_regions))
    cov = np.zeros(n_regions)
    p95 = np.full(n_regions, np.nan)
    region = samples.region
    total = np.bincount(region, area, minlength=n_regions)
    for c in range(visible.shape[0]):      # per camera, every region at once
        seen[c] = np.bincount(region, area * visible[c], minlength=n_regions) / total
    cov = np.bincount(region, area * covered, minlength=n_regions) / total
    finite = np.isfinite(sigma)
    order = np.lexsort((sigma[finite], region[finite]))        # by region, then sigma
    values, owner = sigma[finite][order], region[finite][order]
    start = np.searchsorted(owner, np.arange(n_regions))
    count = np.bincount(owner, minlength=n_regions)
    for r in np.flatnonzero(count):        # numpy's linear percentile of each region's sorted values
        p95[r] = np.percentile(values[start[r]:start[r] + count[r]], 95)
    return seen, cov, p95, sigma


@dataclass(frozen=True, eq=False)
class StepJudgement:
    """The cameras judged at one step (or at rest): what `LoadPathResult` keeps of it."""

    camera_names: tuple[str, ...]
    coverage: np.ndarray       # (N,) cameras that see each sample
    seen: np.ndarray           # (C, R) area fraction of each region each camera sees
    covered: np.ndarray        # (R,) area fraction seen by >= the region's minimum cameras
    p95: np.ndarray            # (R,) m, sigma_max p95 over the measured samples (NaN if none)
    sigma: np.ndarray          # (N,) m, +inf where unmeasured


@dataclass(frozen=True, eq=False)
class PathShared:
    """What every step of a load-path run needs (`vdo.core.parallel.run_tasks`' `shared`, sent
    to each worker once): the geometry at rest, its pair-list sizes those the rest state left
    (`vdo.state.Geometry.sizes`), the load path and the cameras (None: the experiment's)."""

    geometry: Geometry
    load_path: LoadPath
    cameras: tuple | None


def _judgement(state: LayoutState) -> StepJudgement:
    minimum = np.array([r.min_cameras for r in state.geometry.experiment.regions])
    seen, covered, p95, sigma = _region_stats(state, minimum)
    return StepJudgement(tuple(state.visibility.camera_names), state.prediction.coverage, seen,
                         covered, p95, sigma)


def judge_step(shared: PathShared, step: int) -> StepJudgement:
    """The cameras judged at `step` of the load path (`at_step`, `layout_state` without the
    strain fields), on a copy of the rest geometry's pair-list sizes: each step's arrays depend
    on that step alone, the same to the last bit in any process and after any other step."""
    rest = replace(shared.geometry, sizes=dict(shared.geometry.sizes))
    moved = at_step(rest, shared.load_path, step, regions=rest.experiment.regions)
    cameras = None if shared.cameras is None else list(shared.cameras)
    return _judgement(layout_state(moved, cameras, strain_fields=False))


def evaluate_load_path(geometry: Geometry, load_path: LoadPath, cameras=None,
                       progress: bool = False, rest: LayoutState | None = None,
                       workers: int | None = None, client=None) -> LoadPathResult:
    """Judge `cameras` (default: the experiment's) at rest and at every step of `load_path`,
    each distinct geometry once (`LoadPath.step_key`: a step that returns to an earlier pose
    reuses its judgement). `rest`: the state at rest when already computed
    (`layout_state(geometry, cameras)`).

    Where: in this process (default; `workers` 1 too), on a local pool of `workers` >= 2 spawned
    processes, or on the workers of a dask.distributed `client` (`vdo.core.parallel.run_tasks`):
    the rest state here, then one task per distinct step, the geometry, the load path and the
    cameras sent to each worker once (`PathShared`). The arrays are the same to the
    last bit wherever the steps ran (`judge_step`) on the same kind of machine, provided the
    workers' OpenBLAS started with this process's thread count (a local pool's do; for Dask
    workers, `vdo.core.parallel.blas_environment`). A step whose task fails ends the run:
    `vdo.core.parallel.TaskFailed` naming the step. Progress counts the distinct geometries."""
    steps = ("rest",) + tuple(load_path.steps)
    first: dict = {}                       # step key -> the first step with it (rest: ())
    for step in load_path.steps:
        first.setdefault(load_path.step_key(step), step)
    todo = [step for key, step in first.items() if key != ()]
    counter = shown_bar(progress, total=len(todo) + 1, desc="load path", unit="pose")
    try:
        if rest is None:
            rest = layout_state(geometry, cameras, strain_fields=False)
        judged = {(): _judgement(rest)}
        counter.update()
        shared = PathShared(replace(geometry, sizes=dict(geometry.sizes)), load_path,
                            None if cameras is None else tuple(cameras))
        for step, judgement in _judge(shared, todo, workers, client):
            judged[load_path.step_key(step)] = judgement
            counter.update()
    finally:
        counter.close()
    per_step = [judged[() if step == "rest" else load_path.step_key(step)] for step in steps]
    camera_names = per_step[0].camera_names
    seen_arr = np.array([j.seen for j in per_step])
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
                logger.debug("camera %s loses region %s at step %s (sees %.0f%% of it, %.0f%% at rest)",
                             camera, region, steps[k], 100 * seen_arr[k, c, r], 100 * seen_arr[0, c, r])
    covered, p95 = np.array([j.covered for j in per_step]), np.array([j.p95 for j in per_step])
    return LoadPathResult(steps, camera_names, geometry.samples.region_names,
                          np.array([j.coverage for j in per_step]), np.array([j.sigma for j in per_step]),
                          seen_arr, covered, p95, tuple(losses),
                          region_changes(geometry.samples.region_names, steps, covered, p95))


def _judge(shared: PathShared, steps: list[int], workers: int | None, client):
    """(step, `StepJudgement`) for each of `steps`, in this process or as tasks
    (`evaluate_load_path`); in this process in step order, as tasks as they finish."""
    if client is None and (workers or 1) <= 1:
        for step in steps:
            yield step, judge_step(shared, step)
        return
    count = max(1, sum(client.nthreads().values())) if client is not None else workers
    threads = None if client is not None else max(1, cores() // count)
    results = run_tasks(judge_step, steps, workers=count, threads=threads, client=client,
                        name="vdo-load-path", shared=shared)
    try:
        for step, result in results:
            if isinstance(result, Failure):
                logger.debug("load path step %s failed on its worker:\n%s", step, result.traceback)
                raise TaskFailed(f"load path step {step}", result)
            yield step, result
    finally:
        results.close()          # stops the pool (or cancels the Dask tasks) when ended early


def region_changes(region_names, steps, covered: np.ndarray, p95: np.ndarray) -> tuple[dict, ...]:
    """The changes over the load path that matter, per region, at the step where each is largest:
    sigma_max p95 at least SIGMA_RATIO times its value at rest ({"kind": "sigma", "rest_um",
    "value_um", "ratio"}; also a region measured at rest and unmeasured at a step, ratio inf),
    and the area fraction seen by the region's min_cameras at least COVERAGE_DROP below rest
    ({"kind": "coverage", "rest", "value", "drop"}). `covered`, `p95` (K, R), index 0 at rest."""
    out = []
    for r, region in enumerate(region_names):
        rest, later = p95[0, r], p95[1:, r]
        if np.isfinite(rest) and later.size:
            ratio = np.where(np.isnan(later), np.inf, later / rest)
            k = int(np.argmax(ratio))
            if ratio[k] >= SIGMA_RATIO:
                out.append({"region": region, "kind": "sigma", "step": steps[k + 1],
                            "rest_um": float(rest * 1e6),
                            "value_um": None if np.isnan(later[k]) else float(later[k] * 1e6),
                            "ratio": float(ratio[k])})
        drop = covered[0, r] - covered[1:, r]
        if drop.size and drop.max() >= COVERAGE_DROP:
            k = int(np.argmax(drop))
            out.append({"region": region, "kind": "coverage", "step": steps[k + 1],
                        "rest": float(covered[0, r]), "value": float(covered[k + 1, r]),
                        "drop": float(drop[k])})
    return tuple(out)


def _motion(load_path: LoadPath, step: int) -> np.ndarray:
    """What moves at `step`, as one vector (m): per group its translation and its rotation
    vector (rad, read as metres at a 1 m lever), then the specimen's mean nodal displacement and
    the largest nodal displacement's length."""
    from scipy.spatial.transform import Rotation

    out = []
    for group in sorted(load_path.groups):
        pose = load_path.poses.get((step, group))
        if pose is None:
            out += [0.0] * 6
        else:
            out += [*pose.translation, *Rotation.from_matrix(pose.rotation).as_rotvec()]
    if load_path.displacements:
        u = load_path.displacements.get(step)
        u = np.zeros((1, 3)) if u is None else u
        out += [*u.mean(axis=0), float(np.linalg.norm(u, axis=1).max())]
    return np.array(out, dtype=float)


def keyframe_steps(load_path: LoadPath, count: int) -> tuple[int, ...]:
    """`count` steps of `load_path` that stand for it (all of them when it has no more): first
    the extremes, the steps where a component of the motion (`_motion`: a group's translation or
    rotation along an axis, the specimen's mean or largest displacement) is largest or smallest,
    those that move most first; then steps evenly spaced along the path. Sorted."""
    steps = list(load_path.steps)
    if count >= len(steps):
        return tuple(steps)
    motion = np.array([_motion(load_path, s) for s in steps])
    size = np.linalg.norm(motion, axis=1)
    extremes = set()
    for column in motion.T:
        if np.ptp(column) > 0:
            extremes |= {int(np.argmax(column)), int(np.argmin(column))}
    chosen = sorted(extremes, key=lambda k: (-size[k], k))[:count]
    for k in np.linspace(0, len(steps) - 1, count).round().astype(int):
        if len(chosen) < count and k not in chosen:
            chosen.append(int(k))
    for k in np.argsort(-size, kind="stable"):   # evenly spaced steps that were extremes already
        if len(chosen) < count and k not in chosen:
            chosen.append(int(k))
    return tuple(steps[k] for k in sorted(chosen))


def path_occlusion(geometry: Geometry, load_path: LoadPath, cameras, steps=None,
                   fraction: float = 1.0) -> np.ndarray:
    """(C, N) float, 1.0 where camera c sees sample n (`vdo.physics.visibility`: in front, in the image,
    facing within the incidence limit, unoccluded by the meshes and the experiment's camera
    bodies) in the geometry moved to at least `fraction` of `steps` (default: every step of the
    path; `fraction` 1: all of them, the worst case), else 0.0. `cameras`: a list of
    `vdo.model.camera.Camera` (judged where they stand; only those the experiment lists with a body
    are obstacles). The rest state is not among the steps: combine with its own ray cast.
    One ray cast per step."""
    exp = geometry.experiment
    cameras = list(cameras)
    steps = tuple(load_path.steps if steps is None else steps)
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"path_occlusion: fraction must lie in (0, 1], got {fraction}")
    seen = np.zeros((len(cameras), len(geometry.samples)))
    for step in steps:
        moved = at_step(geometry, load_path, step, regions=exp.regions)
        scene = build_scene(list(moved.meshes) + bodies(exp, cameras))
        seen += compute_visibility(scene, cameras, moved.samples, exp.evaluation.incidence_limit,
                                   progress=False).visible
    need = math.ceil(fraction * len(steps) - LIMIT_SLACK)
    return (seen >= need).astype(float)


def scored_path(exp, geometry: Geometry):
    """What `vdo optimize` scores over: (load path, keyframe steps, fraction q) from
    `[optimize] load_path`, `load_path_keyframes` and `load_path_fraction`, or None when the
    experiment has no `[load_path]` or scoring over it is off."""
    if not exp.optimize.load_path:
        return None
    load_path = load_path_of(geometry.meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                             groups=exp.groups)
    if load_path is None or not load_path.steps:
        return None
    return (load_path, keyframe_steps(load_path, exp.optimize.load_path_keyframes),
            exp.optimize.load_path_fraction)


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
            "losses": list(result.losses), "sigma_ratio": SIGMA_RATIO, "coverage_drop": COVERAGE_DROP,
            "changes": list(result.changes), "regions": regions}


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
