"""`vdo sweep`: run one action (evaluate or optimize) on many variants of an experiment.

A sweep file names one or more base experiments and axes over their fields. An axis path names a
field of the experiment file the way its TOML reads: ``evaluation.patch_mm`` (a table's field),
``camera.cam1.focal_mm`` (the field of the ``[[camera]]`` named cam1; ``camera.*.focal_mm`` sets
it on every camera), ``region.joint_top.importance``. Values come as a list, a range, a linspace,
or (with ``samples = N``) random draws from a seeded generator. Axes vary as a grid (product, in
file order, first axis slowest); axes with the same ``zip`` name vary together. Each point is the
base file's TOML with the axis values written in, checked by `vdo.config.experiment.parse` like any
experiment (and its load path's files read whole), every point before any work: a value that fails
its field's check stops the sweep in one line naming the point and the field (`check_points`).

The output folder is a resumable store, not an all-or-nothing run folder: ``points/KEY.json``
holds each point's result under KEY = SHA-256 of the canonical JSON of (the point's TOML with
absolute file paths, the contents' digests of the files it reads, the action, vdo's version),
written atomically. A re-run computes only the points whose key has no stored result (or a failed
one): finished points are never recomputed, a killed point is recomputed. ``results.csv`` (one row
per point, pending ones included) is rewritten atomically after every point; ``figures/`` is drawn
at the end; ``runs/KEY/`` holds a point's run folder when the action writes one.

Points run in a local pool of spawned processes (one per core by default) or on a Dask cluster
(``dask.distributed``), through `vdo.core.parallel.run_tasks`; each worker sets itself up once
(`vdo.core.parallel.configure_worker`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import socket
import textwrap
import time
import traceback
from collections import Counter
from pathlib import Path

import numpy as np

from vdo.config.experiment import Experiment, parse
from vdo.config.sweep import ACTIONS, Axis, Point, SweepSpec, expand, point_key, vdo_version
from vdo.core.errors import ConfigError
from vdo.core.parallel import Failure, connect_dask, cores, run_tasks
from vdo.core.progress import bar as progress_bar

log = logging.getLogger(__name__)

MARKER = "sweep.json"                                       # marks a folder as a sweep store
METRICS = (("sigma_p50_um", "σ_max p50 (µm)"), ("sigma_p95_um", "σ_max p95 (µm)"),
           ("sigma_max_um", "σ_max max (µm)"), ("seen_1", "area seen by ≥ 1 camera"),
           ("seen_2", "area seen by ≥ 2 cameras"), ("seen_3", "area seen by ≥ 3 cameras"))


def check_points(spec: SweepSpec, points: list[Point]) -> None:
    """Every point checked before any work: its experiment parsed (`vdo.config.experiment.parse`)
    and its load path's files read whole (`vdo.geometry.keyframes.check_load_path`, once per
    distinct `[load_path]`, `[[group]]` and `[[mesh]]` tables). The first point that fails is a
    ConfigError naming the sweep file, the point (its index and axis values) and the
    experiment's file and field."""
    from vdo.geometry.keyframes import check_load_path

    read = set()
    for point in points:
        try:
            exp = parse(point.config, Path(point.base))
            tables = json.dumps([point.config.get(k) for k in ("load_path", "group", "mesh")],
                                sort_keys=True, default=str)
            if tables not in read:
                check_load_path(load_path_spec=exp.load_path, groups=exp.groups, mesh_specs=exp.meshes,
                                regions=exp.regions, camera_specs=exp.camera_specs, rails=exp.rails,
                                mounts=exp.mounts, path=exp.path)
                read.add(tables)
        except ConfigError as exc:
            values = ", ".join(f"{k} = {v!r}" for k, v in point.axes.items())
            raise ConfigError(spec.path, f"point {point.index} ({point.experiment}: {values})",
                              str(exc)) from None


# --------------------------------------------------------------------------------------------
# One point (runs in a worker)
# --------------------------------------------------------------------------------------------
def _evaluation(exp):
    """`vdo evaluate`'s judged layout (`vdo.outputs.report.EvaluationResult`, summary.json's
    regions and settings) without writing a run folder."""
    from vdo.outputs import report
    from vdo.state import layout_state, prepare

    return report.state_evaluation(layout_state(prepare(exp)))


def metrics(result) -> dict:
    """A table row's numbers from a judged layout (`vdo.outputs.report.EvaluationResult`): camera
    and sample counts, and per region the σ_max p50/p95/max (µm, None where no point is measured),
    the area fractions seen by ≥ 1, 2, 3 usable views, and (when it has them) the strain σ p95 per
    face-frame component (µε, `vdo.physics.strain`)."""
    row = {"n_cameras": result.settings.n_cameras, "n_samples": result.settings.n_samples}
    for name, r in result.regions.items():
        sigma = r.sigma_max_um
        row |= {f"{name}.sigma_p50_um": sigma.p50, f"{name}.sigma_p95_um": sigma.p95,
                f"{name}.sigma_max_um": sigma.max}
        row |= {f"{name}.seen_1": r.seen_by_1_or_more, f"{name}.seen_2": r.seen_by_2_or_more,
                f"{name}.seen_3": r.seen_by_3_or_more}
        for component, stats in (r.sigma_strain_microstrain or {}).items():
            row[f"{name}.{component}_p95_ue"] = stats.p95
    return row


def run_point(point: Point) -> dict:
    """Run the point's action; the record of what happened (a dict of JSON values: picklable, and
    written as points/KEY.json): "metrics" (`metrics` of the judged layout, and for optimize its
    scores and violations) and "summary" (the judged layout's summary.json, `to_json()` of the
    result the action returned: after optimizing, summary_after.json). Never raises for a failing
    point: status "failed" with the error (the ConfigError line for a user mistake)."""
    started, t0, cpu0 = time.time(), time.perf_counter(), time.process_time()
    record = {"status": "done", "error": "", "metrics": {}, "summary": None}
    try:
        exp = parse(point.config, Path(point.base))
        if point.action == "optimize":
            from vdo.commands.optimize import optimize

            result = optimize(exp, Path(point.run_dir), overwrite=True)
            judged = result.after
            extra = {"score_before": result.score_before_um, "score_after": result.score_after_um,
                     "violations": result.violations}
        elif point.run_dir is not None:
            from vdo.commands.evaluate import evaluate

            judged, extra = evaluate(exp, Path(point.run_dir), overwrite=True), {}
        else:
            judged, extra = _evaluation(exp), {}
        record |= {"metrics": metrics(judged) | extra, "summary": judged.to_json()}
    except ConfigError as exc:
        record |= {"status": "failed", "error": str(exc)}
    except Exception as exc:  # a failing point is recorded; the sweep goes on
        record |= {"status": "failed", "error": f"{type(exc).__name__}: {exc}",
                   "traceback": traceback.format_exc()}
    return record | {"seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - cpu0,
                     "started": started, "finished": time.time(), "host": socket.gethostname(),
                     "pid": os.getpid()}


def _failure(message: str) -> dict:
    """The record of a point that failed outside `run_point` (its check, its worker's death)."""
    now = time.time()
    return {"status": "failed", "error": message, "metrics": {}, "summary": None, "seconds": 0.0,
            "cpu_seconds": 0.0, "started": now, "finished": now, "host": socket.gethostname(),
            "pid": os.getpid()}


# --------------------------------------------------------------------------------------------
# Execution: a local pool of spawned processes, or Dask (`vdo.core.parallel`)
# --------------------------------------------------------------------------------------------
def _records(results):
    """(point, record) from `run_tasks`' (point, record or Failure)."""
    for point, result in results:
        if isinstance(result, Failure):
            result = _failure(result.error) | ({"traceback": result.traceback} if result.traceback else {})
        yield point, result


def _run_local(points: list[Point], workers: int, threads: int | None):
    """Yield (point, record) as points finish in a local pool of spawned processes (a point
    whose worker process dies is tried again in a fresh pool, `vdo.core.parallel.MAX_ATTEMPTS`
    times in all)."""
    yield from _records(run_tasks(run_point, points, workers=workers, threads=threads))


def _run_dask(points: list[Point], client, threads: int | None):
    """Yield (point, record) as points finish on the Dask workers."""
    yield from _records(run_tasks(run_point, points, client=client, threads=threads,
                                  keys=[f"vdo-point-{p.key}" for p in points], name="vdo-sweep"))


# --------------------------------------------------------------------------------------------
# The store
# --------------------------------------------------------------------------------------------
def write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def open_store(out: Path) -> Path:
    """Check `out` is new, empty or a sweep store (ConfigError otherwise) and return it."""
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise ConfigError(out, "--out", "exists and is not a folder; choose a folder path")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise ConfigError(out, "--out", "holds files that are not a vdo sweep; a sweep folder "
                                        "is a resumable store: give a new folder, or the folder "
                                        "of an earlier run of this sweep to resume it")
    return out


def load_record(out: Path, key: str) -> dict | None:
    try:
        return json.loads((out / "points" / f"{key}.json").read_text())
    except (OSError, ValueError):
        return None


def row(point: Point, record: dict | None, several: bool) -> dict:
    r = {"index": point.index} | ({"experiment": point.experiment} if several else {})
    r |= {k: json.dumps(v) if isinstance(v, (list, dict)) else v for k, v in point.axes.items()}
    if record is None:
        return r | {"status": "pending"}
    return r | {"status": record["status"]} | record["metrics"] | {
        "seconds": record["seconds"], "error": record["error"], "key": point.key}


def write_table(path: Path, rows: list[dict]) -> None:
    """results.csv, atomically: every column any row has, in first-seen order."""
    import csv
    import io

    columns = list(dict.fromkeys(k for r in rows for k in r))
    if "error" in columns:     # the long columns last
        columns = [c for c in columns if c not in ("seconds", "error", "key")] + ["seconds", "error", "key"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if v is None else repr(v) if isinstance(v, float) else v)
                         for k, v in r.items()})
    write_atomic(path, buf.getvalue())


# --------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------
def sweep(spec: SweepSpec, out, workers: int | None = None, dask: str | None = None,
          connect_timeout: float = 5.0, max_points: int | None = None) -> dict:
    """Run every point of `spec` not yet stored in `out` (on `workers` local processes, default
    one per core, or on the Dask scheduler at `dask`, "local" for a LocalCluster of `workers`
    processes), or the first `max_points` of them (a trial: the rest stay "pending" in
    results.csv, and running again completes the store); write results.csv and figures/.
    Returns the counts (points, done, failed, pending, reused: stored before, computed: run
    now), the rows and the output paths. Progress goes to the `vdo.commands.sweep` logger
    (`vdo.core.progress`)."""
    if max_points is not None and max_points < 1:
        raise ConfigError(spec.path, "--max-points", f"must be at least 1 (got {max_points}); "
                                                     "leave it out to run every point")
    out = open_store(out)
    points = expand(spec, out)
    check_points(spec, points)
    return run_sweep(spec, points, out, spec.path.read_text(), workers, dask, connect_timeout,
                     max_points)


def sweep_variants(variants, out, action: str = "evaluate", workers: int | None = None,
                   dask: str | None = None, name: str = "variants", connect_timeout: float = 5.0) -> dict:
    """The sweep engine on experiments built in code: `variants` is a list of `Experiment`s
    (e.g. from `Experiment.with_camera` / `with_settings`), each alone (its column "variant" is
    its index) or as a pair (values, experiment), values a dict of the columns that describe it
    (``{"focal_mm": 50, "camera": "cam2"}``; every variant the same keys) or a label. Runs
    `action` ("evaluate" or "optimize") on each in a local pool of `workers` processes or on
    Dask (`dask`: an address or "local"), into the resumable store `out` exactly as `vdo sweep`
    does (a variant whose experiment was stored before is not run again; results.csv,
    points/KEY.json, figures/); returns `sweep`'s dict. ConfigError (one line) for a bad list."""
    if action not in ACTIONS:
        raise ConfigError("sweep_variants", "action", f"must be one of {', '.join(ACTIONS)} (got {action!r})")
    if not isinstance(variants, (list, tuple)) or not variants:
        raise ConfigError("sweep_variants", "variants", "give a non-empty list of experiments or "
                                                        "(values, experiment) pairs")
    pairs = []
    for i, item in enumerate(variants):
        values, exp = item if isinstance(item, tuple) and len(item) == 2 else (i, item)
        values = values if isinstance(values, dict) else {"variant": values}
        if not isinstance(exp, Experiment):
            raise ConfigError("sweep_variants", f"variant {i}", f"is a {type(exp).__name__}, not a "
                                                                "vdo.Experiment (vdo.load, with_camera, ...)")
        if pairs and set(values) != set(pairs[0][0]):
            raise ConfigError("sweep_variants", f"variant {i}", f"describes itself by {sorted(values)}, "
                                                                f"variant 0 by {sorted(pairs[0][0])}: "
                                                                "give every variant the same keys")
        pairs.append((values, exp))
    out = open_store(out)
    bases = list(dict.fromkeys(str(exp.path) for _, exp in pairs))
    labels = {b: Path(b).name if len(bases) == 1 else f"{k}:{Path(b).name}" for k, b in enumerate(bases)}
    axes = tuple(Axis(path=k, tokens=(k,), values=tuple(dict.fromkeys(v[k] for v, _ in pairs)),
                      draw=None, zip=None) for k in pairs[0][0])
    spec = SweepSpec(path=Path(bases[0]), name=name, experiments=tuple((labels[b], Path(b)) for b in bases),
                     action=action, axes=axes, samples=None, seed=0, run_folders=False, regions=None,
                     pareto=(None, None))
    points = []
    for values, exp in pairs:
        config = exp.to_dict()   # absolute file paths: the point reads what the experiment read
        key = point_key(config, action)
        points.append(Point(index=len(points), key=key, experiment=labels[str(exp.path)], base=str(exp.path),
                            axes=values, config=config, action=action,
                            run_dir=str(out / "runs" / key) if action == "optimize" else None))
    source = (f"# {name}: {len(points)} variants built in Python (vdo.sweep_variants); each point's "
              "experiment is in points/KEY.json\n")
    return run_sweep(spec, points, out, source, workers, dask, connect_timeout)


def run_sweep(spec: SweepSpec, points: list[Point], out: Path, source: str, workers: int | None,
              dask: str | None, connect_timeout: float, max_points: int | None = None) -> dict:
    """Run the `points` not yet stored in the store `out` (`open_store`), at most `max_points`
    of them in their order, and write results.csv and figures/ (`sweep`, `sweep_variants`);
    `source` is kept as sweep.toml."""
    records = {p.key: load_record(out, p.key) for p in points}
    finished = {k for k, r in records.items() if r and r["status"] == "done"}
    todo = list({p.key: p for p in points if p.key not in finished}.values())[:max_points]
    workers = max(1, min(workers or cores(), len(todo) or 1))
    threads = max(1, cores() // workers) if dask in (None, "local") else None
    several = len(spec.experiments) > 1
    log.info("%d points, %d stored, %d to run", len(points), len(finished), len(todo))

    client = cluster = None
    if dask and dask != "local" and todo:      # before writing anything
        client, cluster = connect_dask(dask, workers, connect_timeout, out)
    (out / "points").mkdir(parents=True, exist_ok=True)
    write_atomic(out / MARKER, json.dumps({"vdo_sweep": 1, "vdo": vdo_version(),
                                           "sweep": str(spec.path), "points": len(points)}, indent=2))
    write_atomic(out / "sweep.toml", source)

    def table():
        write_table(out / "results.csv", [row(p, records[p.key], several) for p in points])

    def store(point: Point, record: dict) -> None:
        full = {"key": point.key, "experiment": point.experiment, "axes": point.axes,
                "action": point.action, "vdo": vdo_version()} | record | {"config": point.config}
        write_atomic(out / "points" / f"{point.key}.json", json.dumps(full, indent=1, default=str))
        records[point.key] = full
        table()

    table()
    failed = 0
    bar = progress_bar(log, total=len(todo), unit="point", desc="sweep",
                       disable=not todo, dynamic_ncols=True)
    bar.set_postfix(failed=failed)
    try:
        if todo and dask == "local":
            client, cluster = connect_dask("local", workers, connect_timeout, out / "dask-scratch")
        if todo and client is not None:
            results = _run_dask(todo, client, threads)
        else:
            results = _run_local(todo, workers, threads)
        for point, record in results:
            store(point, record)
            failed += record["status"] != "done"
            bar.update()
            bar.set_postfix(failed=failed)
    finally:
        bar.close()
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
            shutil.rmtree(out / "dask-scratch", ignore_errors=True)

    rows = [row(p, records[p.key], several) for p in points]
    figures = plot(spec, rows, records, out / "figures")
    from vdo.outputs.html_report import write_report

    write_report(out)
    status = Counter(r["status"] for r in rows)
    return {"points": len(points), "done": status["done"], "failed": status["failed"],
            "pending": status["pending"], "computed": len(todo), "reused": sum(p.key in finished for p in points),
            "rows": rows, "results": out / "results.csv", "figures": figures, "out": out}


# --------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------
def _numeric(values) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def _median(values) -> float:
    finite = [v for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def _save(fig, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    fig.savefig(tmp, dpi=110, format="png")
    os.replace(tmp, path)


def _region_order(records: dict, rows: list[dict]) -> list[str]:
    for r in rows:
        summary = (records.get(r.get("key")) or {}).get("summary")
        if summary:
            return list(summary["regions"])
    return []


def pareto_front(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Indices of the points no other point beats on both x and y (both minimised), by x."""
    order = np.lexsort((y, x))
    front, best = [], math.inf
    for i in order:
        if y[i] < best:
            front.append(i)
            best = y[i]
    return np.asarray(front, dtype=int)


def _figure_name(n: int, column: str) -> str:
    """A file name for an axis' figure: its position and its path, only [A-Za-z0-9_.-] kept."""
    return f"axis{n}_" + re.sub(r"[^A-Za-z0-9_.-]", "_", column.replace("*", "all"))[:80] + ".png"


def plot(spec: SweepSpec, rows: list[dict], records: dict, folder: Path) -> list[Path]:
    """figures/axis<n>_<path>.png: each metric (σ_max p50/p95/max on a log scale, coverage
    ≥ 1/2/3) against each axis with more than one value, one line per region (median over the
    other axes' points); figures/pareto.png: [sweep] pareto_y against pareto_x (default: the
    most important region's σ_max p95 against the camera count, when that varies)."""
    import matplotlib.pyplot as plt

    done = [r for r in rows if r["status"] == "done"]
    if not done:
        return []
    folder.mkdir(exist_ok=True)
    regions = list(spec.regions or _region_order(records, done))
    axes = [a.path for a in spec.axes] + (["experiment"] if len(spec.experiments) > 1 else [])
    varying = [name for name in axes if len({r[name] for r in done}) > 1]
    written = [_plot_axis(plt, spec.name, done, name, regions,
                          folder / _figure_name(axes.index(name) + 1, name)) for name in varying]
    x_name, y_name = spec.pareto
    if x_name is None and len({r["n_cameras"] for r in done}) > 1:
        x_name = "n_cameras"
    if y_name is None and regions:
        summary = next(rec["summary"] for rec in records.values() if rec and rec.get("summary"))
        top = max(regions, key=lambda g: summary["regions"].get(g, {}).get("importance", 0))
        y_name = f"{top}.sigma_p95_um"
    usable = [r for r in done if _numeric([r.get(x_name), r.get(y_name)])]
    if x_name is None or not usable:
        log.info("no Pareto plot: set [sweep] pareto_x and pareto_y to numeric columns "
                 "(camera count, cost) that the finished points have")
        return written
    colour_by = next((name for name in varying if name != x_name), None)
    return written + [_plot_pareto(plt, spec.name, usable, x_name, y_name, colour_by, varying,
                                   folder / "pareto.png")]


def _plot_axis(plt, title, done, name, regions, path) -> Path:
    values = list(dict.fromkeys(r[name] for r in done))
    numeric = _numeric(values)
    if numeric:
        values.sort()
    colours = plt.get_cmap("tab20")(np.linspace(0, 1, 20))
    fig, panels = plt.subplots(2, 3, figsize=(15, 7.5), constrained_layout=True)
    for panel, (metric, label) in zip(panels.flat, METRICS):
        for k, region in enumerate(regions):
            ys = [_median([r.get(f"{region}.{metric}") for r in done if r[name] == v]) for v in values]
            panel.plot(values if numeric else range(len(values)), ys, "o-",
                       color=colours[k % 20], label=region, ms=4)
        if metric.startswith("sigma"):
            panel.set_yscale("log")
        panel.set_xlabel(name)
        panel.set_ylabel(label)
        if not numeric:
            panel.set_xticks(range(len(values)), [str(v) for v in values], rotation=15)
        panel.grid(alpha=0.3, which="both")
    handles, labels = panels.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right center", fontsize=8)
    fig.suptitle(f"{title}\nmetrics against {name} (median over the other axes' points)")
    _save(fig, path)
    plt.close(fig)
    return path


def _plot_pareto(plt, title, usable, x_name, y_name, colour_by, axes, path) -> Path:
    x = np.array([r[x_name] for r in usable], dtype=float)
    y = np.array([r[y_name] for r in usable], dtype=float)
    front = pareto_front(x, y)
    fig, ax = plt.subplots(figsize=(8, 5.5), constrained_layout=True)
    groups = list(dict.fromkeys(r[colour_by] for r in usable)) if colour_by else [None]
    for k, g in enumerate(groups):
        mask = np.array([colour_by is None or r[colour_by] == g for r in usable])
        ax.scatter(x[mask], y[mask], s=24, color=f"C{k % 10}",
                   label="points" if colour_by is None else f"{colour_by} = {g}")
    ax.step(x[front], y[front], where="post", color="k", lw=1, label="Pareto front")
    ax.scatter(x[front], y[front], s=90, facecolors="none", edgecolors="k")
    lines = []
    for i in front:
        ax.annotate(f"#{usable[i]['index']}", (x[i], y[i]), textcoords="offset points",
                    xytext=(6, 4), fontsize=8)
        lines.append(textwrap.fill(f"#{usable[i]['index']}: " + ", ".join(
            f"{a} = {usable[i][a]}" for a in axes), 110, subsequent_indent="    "))
    ax.set_xlabel(x_name)
    ax.set_ylabel(y_name)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{title}\n{y_name} against {x_name} (both lower is better)", fontsize=10)
    ax.text(0, -0.12, "Pareto front:\n" + "\n".join(lines[:4]), transform=ax.transAxes,
            fontsize=7, ha="left", va="top")
    _save(fig, path)
    plt.close(fig)
    return path
