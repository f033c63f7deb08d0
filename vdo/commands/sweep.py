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

import copy
import functools
import hashlib
import itertools
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
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

from vdo.config.experiment import Experiment, parse, sections
from vdo.config.reader import Table, read_toml, with_overrides
from vdo.core.errors import ConfigError
from vdo.core.parallel import Failure, connect_dask, cores, run_tasks
from vdo.core.progress import bar as progress_bar
from vdo.core.tolerances import LIMIT_SLACK

log = logging.getLogger(__name__)

ACTIONS = ("evaluate", "optimize")
LISTS = ("values", "range", "linspace")                     # axis kinds usable in a grid
DRAWS = ("uniform", "log_uniform", "integers")              # axis kinds drawn at random
MARKER = "sweep.json"                                       # marks a folder as a sweep store
METRICS = (("sigma_p50_um", "σ_max p50 (µm)"), ("sigma_p95_um", "σ_max p95 (µm)"),
           ("sigma_max_um", "σ_max max (µm)"), ("seen_1", "area seen by ≥ 1 camera"),
           ("seen_2", "area seen by ≥ 2 cameras"), ("seen_3", "area seen by ≥ 3 cameras"))
EXPERIMENT_TABLES = ("experiment",) + tuple(s.key for s in sections())


def vdo_version() -> str:
    try:
        return metadata.version("vdo")
    except metadata.PackageNotFoundError:
        return "unknown"


# --------------------------------------------------------------------------------------------
# The sweep file
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Axis:
    """One axis: `path` (split into `tokens`), and either the grid `values` or a random `draw`
    (kind, low, high); axes sharing a `zip` name vary together."""

    path: str
    tokens: tuple[str, ...]
    values: tuple | None
    draw: tuple[str, float, float] | None
    zip: str | None


@dataclass(frozen=True)
class SweepSpec:
    path: Path
    name: str
    experiments: tuple[tuple[str, Path], ...]    # (label as written, absolute path)
    action: str
    axes: tuple[Axis, ...]
    samples: int | None                          # None: the grid; N: N random points
    seed: int
    run_folders: bool
    regions: tuple[str, ...] | None              # regions drawn in the figures (None: all)
    pareto: tuple[str | None, str | None]        # columns (x, y) of the Pareto plot


def split_path(path: str) -> tuple[str, ...] | None:
    """``camera."cam.1".focal_mm`` -> ("camera", "cam.1", "focal_mm"); None when malformed."""
    tokens = re.findall(r'"([^"]+)"|([^."]+)', path)
    joined = ".".join(f'"{q}"' if q else p for q, p in tokens)
    if not tokens or joined != path:
        return None
    return tuple(q or p for q, p in tokens)


def _rounded(x: float, digits: int) -> float:
    return float(f"{x:.{digits}g}")


def _axis(t: Table, samples: int | None) -> Axis:
    path = t.string("path")
    tokens = split_path(path)
    if tokens is None or len(tokens) not in (2, 3):
        raise t.error("path", f"{path!r} is not a field path: write table.field "
                              "(evaluation.patch_mm) or table.name.field (camera.cam1.focal_mm)")
    kinds = [k for k in LISTS + DRAWS if t.has(k)]
    if len(kinds) != 1:
        raise t.error("values", "give exactly one of " + ", ".join(LISTS + DRAWS))
    kind = kinds[0]
    values = draw = None
    if kind == "values":
        values = t.raw("values")
        if not isinstance(values, list) or not values:
            raise t.error("values", "must be a non-empty list of field values")
    elif kind == "range":
        start, stop, step = t.vector("range", 3)
        if step == 0 or (stop - start) / step < 0:
            raise t.error("range", "[start, stop, step] needs a step that leads from start to stop")
        count = math.floor((stop - start) / step + LIMIT_SLACK) + 1
        if count > 100_000:
            raise t.error("range", f"gives {count} values; use a coarser step")
        whole = all(isinstance(v, int) for v in t.raw("range"))
        values = [int(start + i * step) if whole else _rounded(start + i * step, 12)
                  for i in range(count)]
    elif kind == "linspace":
        raw = t.raw("linspace")
        start, stop, num = t.vector("linspace", 3)
        if not isinstance(raw[2], int) or num < 1:
            raise t.error("linspace", "[start, stop, num] needs a whole num >= 1")
        values = [_rounded(v, 12) for v in np.linspace(start, stop, int(num))]
    else:
        if samples is None:
            raise t.error(kind, "draws random values: give [sweep] samples = N (the number of "
                                "random points), or list values for a grid")
        low, high = t.vector(kind, 2)
        if not low < high or (kind == "log_uniform" and low <= 0):
            positive = " and low > 0" if kind == "log_uniform" else ""
            raise t.error(kind, f"needs [low, high] with low < high{positive}")
        if kind == "integers" and not all(isinstance(v, int) for v in t.raw(kind)):
            raise t.error(kind, "needs two whole numbers [low, high] (both included)")
        draw = (kind, low, high)
    group = t.string("zip", None)
    if group is not None and draw is not None:
        raise t.error("zip", "zipped axes take lists of values, not random draws")
    return Axis(path, tokens, None if values is None else tuple(values), draw, group)


def load_sweep(path) -> SweepSpec:
    """Read and check a sweep file (ConfigError on any mistake, before any work)."""
    path = Path(path).resolve()
    top = Table(read_toml(path), "", path, ("sweep", "axis"))
    t = Table(top.raw("sweep"), "sweep", path,
              ("name", "experiment", "action", "samples", "seed", "run_folders", "regions",
               "pareto_x", "pareto_y"))
    named = t.raw("experiment")
    named = [named] if isinstance(named, str) else named
    if not isinstance(named, list) or not named or not all(isinstance(n, str) and n for n in named):
        raise t.error("experiment", "must be an experiment file or a list of them (relative to "
                                    "the sweep file)")
    if len(set(named)) != len(named):
        raise t.error("experiment", "names a file twice")
    experiments = []
    for label in named:
        file = (path.parent / label).resolve()
        if not file.is_file():
            raise t.error("experiment", f"{str(file)!r} does not exist")
        experiments.append((label, file))
    samples = t.integer("samples", 1, low=1) if t.has("samples") else None
    regions = t.raw("regions", None)
    if regions is not None and (not isinstance(regions, list) or not regions
                                or not all(isinstance(r, str) for r in regions)):
        raise t.error("regions", "must be a non-empty list of region names")
    items = top.raw("axis", [])
    if not isinstance(items, list):
        raise ConfigError(path, "axis", "write each axis as an [[axis]] table")
    axes = tuple(_axis(Table(item, f"axis[{i}]", path,
                             ("path", "zip") + LISTS + DRAWS), samples)
                 for i, item in enumerate(items))
    paths = [a.path for a in axes]
    for p, n in Counter(paths).items():
        if n > 1:
            raise ConfigError(path, "axis", f"path {p!r} is swept twice; zip or merge the axes")
    for group, members in itertools.groupby(sorted((a.zip, len(a.values)) for a in axes if a.zip),
                                            key=lambda m: m[0]):
        if len({n for _, n in members}) > 1:
            raise ConfigError(path, "axis", f"the axes zipped as {group!r} must list the same "
                                            "number of values")
    return SweepSpec(path=path, name=t.string("name", path.stem), experiments=tuple(experiments),
                     action=t.string("action", "evaluate", choices=ACTIONS), axes=axes,
                     samples=samples, seed=t.integer("seed", 0, low=0),
                     run_folders=t.boolean("run_folders", False),
                     regions=None if regions is None else tuple(regions),
                     pareto=(t.string("pareto_x", None), t.string("pareto_y", None)))


# --------------------------------------------------------------------------------------------
# Points
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Point:
    """One point of a sweep, picklable: the experiment's TOML dict with the axis values written
    in and file paths made absolute; `base` is the file it came from (errors name it)."""

    index: int
    key: str
    experiment: str
    base: str
    axes: dict
    config: dict
    action: str
    run_dir: str | None


def _groups(axes) -> list[list[Axis]]:
    """Axes in file order, zipped ones gathered at the place of their group's first axis."""
    groups, where = [], {}
    for axis in axes:
        if axis.zip is None:
            groups.append([axis])
        elif axis.zip in where:
            groups[where[axis.zip]].append(axis)
        else:
            where[axis.zip] = len(groups)
            groups.append([axis])
    return groups


def combinations(spec: SweepSpec) -> list[dict]:
    """The axis values of every point (path -> value), per base experiment: the grid, or
    `samples` draws from numpy's default_rng(seed) (floats rounded to 6 significant digits)."""
    groups = _groups(spec.axes)
    if spec.samples is None:
        choices = [[{a.path: a.values[i] for a in g} for i in range(len(g[0].values))]
                   for g in groups]
        return [dict(kv for part in combo for kv in part.items())
                for combo in itertools.product(*choices)]
    rng = np.random.default_rng(spec.seed)
    out = []
    for _ in range(spec.samples):
        combo = {}
        for g in groups:
            if g[0].draw is None:
                i = int(rng.integers(len(g[0].values)))
                combo |= {a.path: a.values[i] for a in g}
                continue
            kind, low, high = g[0].draw
            if kind == "integers":
                combo[g[0].path] = int(rng.integers(int(low), int(high) + 1))
            elif kind == "uniform":
                combo[g[0].path] = _rounded(rng.uniform(low, high), 6)
            else:
                combo[g[0].path] = _rounded(math.exp(rng.uniform(math.log(low), math.log(high))), 6)
        out.append(combo)
    return out


def _targets(config: dict, tokens, file: Path, path: str) -> list[dict]:
    """The tables an axis path writes into (ConfigError when the path cannot name a field)."""
    section = tokens[0]
    current = config.get(section)
    if isinstance(current, list):
        if len(tokens) != 3:
            raise ConfigError(file, f"axis {path!r}", f"[[{section}]] is a list of tables: write "
                                                      f"{section}.NAME.FIELD or {section}.*.FIELD")
        entries = [e for e in current if isinstance(e, dict)
                   and (tokens[1] == "*" or e.get("name") == tokens[1])]
        if not entries:
            names = ", ".join(str(e.get("name")) for e in current if isinstance(e, dict))
            raise ConfigError(file, f"axis {path!r}", f"no [[{section}]] named {tokens[1]!r} "
                                                      f"(there are: {names or 'none'})")
        return entries
    if len(tokens) != 2:
        raise ConfigError(file, f"axis {path!r}", f"names no field: {section!r} is not a list "
                                                  f"of named tables here; write {section}.FIELD")
    if current is None:
        config[section] = current = {}
    if not isinstance(current, dict):
        raise ConfigError(file, f"axis {path!r}", f"names no field: {section!r} is not a table")
    return [current]


def _assign(config: dict, axis_tokens, value, file: Path, path: str) -> None:
    for table in _targets(config, axis_tokens, file, path):
        table[axis_tokens[-1]] = copy.deepcopy(value)


def _file_fields(config: dict) -> list[tuple[dict, str]]:
    """(table, key) of every file path the experiment reads: mesh files, the speckle image."""
    meshes = config.get("mesh") if isinstance(config.get("mesh"), list) else []
    fields = [(m, "file") for m in meshes if isinstance(m, dict) and isinstance(m.get("file"), str)]
    speckle = config.get("speckle")
    if isinstance(speckle, dict) and isinstance(speckle.get("image"), str):
        fields.append((speckle, "image"))
    return fields


def _absolute_files(config: dict, base: Path) -> None:
    """File paths resolved against the base file's folder, as `vdo.config.experiment.parse` reads them."""
    for table, key in _file_fields(config):
        table[key] = str((base.parent / table[key]).resolve())


@functools.lru_cache(maxsize=256)
def _digest(file: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(file, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_digest(file: str) -> str | None:
    """SHA-256 of a file's contents (None when it cannot be read)."""
    try:
        st = os.stat(file)
        return _digest(file, st.st_size, st.st_mtime_ns)
    except OSError:
        return None


def point_key(config: dict, action: str) -> str:
    """Hash of the canonical JSON of the point: its TOML dict, the digests of the files it reads,
    the action and vdo's version. 20 hex digits (80 bits)."""
    material = {"config": config,
                "files": {t[k]: file_digest(t[k]) for t, k in _file_fields(config)},
                "action": action, "vdo": vdo_version()}
    text = json.dumps(material, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def _check_axis_paths(spec: SweepSpec, raw: dict, base: Path) -> None:
    """An axis path that names no field of `base` is a ConfigError (before any work). A field
    absent from the file is found by writing the axis' first value and parsing: the parser
    rejects unknown fields first."""
    for axis in spec.axes:
        probe = copy.deepcopy(raw)
        value = axis.values[0] if axis.values is not None else axis.draw[1]
        _assign(probe, axis.tokens, value, spec.path, axis.path)
        try:
            parse(probe, base)
        except ConfigError as exc:
            if exc.message.startswith("unknown field") and (
                    exc.field == axis.tokens[0] or exc.field.endswith("." + axis.tokens[-1])):
                raise ConfigError(spec.path, f"axis {axis.path!r}",
                                  f"names no field of {base.name} ({exc.field}: {exc.message})") from None


def expand(spec: SweepSpec, out: Path | None = None) -> list[Point]:
    """Every point of the sweep, with its key; ConfigError when a base experiment is invalid or
    an axis path names no field. `out` places the points' run folders (out/runs/KEY)."""
    combos = combinations(spec)
    points = []
    for label, base in spec.experiments:
        raw = read_toml(base)
        exp = parse(raw, base)                            # the base itself must be valid
        unknown = sorted(set(spec.regions or ()) - {r.name for r in exp.regions})
        if unknown:
            raise ConfigError(spec.path, "sweep.regions", f"{base.name} has no region named "
                                                          f"{', '.join(map(repr, unknown))}")
        _check_axis_paths(spec, raw, base)
        for combo in combos:
            config = copy.deepcopy(raw)
            for axis in spec.axes:
                _assign(config, axis.tokens, combo[axis.path], spec.path, axis.path)
            config = with_overrides(config, EXPERIMENT_TABLES)  # in the key: a coarse run is another point
            _absolute_files(config, base)
            key = point_key(config, spec.action)
            writes = spec.action == "optimize" or spec.run_folders
            points.append(Point(index=len(points), key=key, experiment=label, base=str(base),
                                axes=combo, config=config, action=spec.action,
                                run_dir=str(out / "runs" / key) if writes and out else None))
    return points


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
                check_load_path(exp)
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
