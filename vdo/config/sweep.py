"""The sweep file, read before any work: its base experiments, axes (values, ranges, zips, random
draws) and action (`load_sweep`, `SweepSpec`), and the points they expand to (`expand`, `Point`:
each a full experiment configuration with a key that names its content, `point_key`), checked up
front by `vdo.commands.sweep.check_points`, which runs them and keeps the store."""

from __future__ import annotations

import copy
import functools
import hashlib
import itertools
import json
import math
import os
import re
from collections import Counter
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

from vdo.config.experiment import parse, sections
from vdo.config.reader import Table, read_toml, with_overrides
from vdo.core.errors import ConfigError
from vdo.core.runfolder import is_file
from vdo.core.tolerances import LIMIT_SLACK

ACTIONS = ("evaluate", "optimize")


LISTS = ("values", "range", "linspace")                     # axis kinds usable in a grid


DRAWS = ("uniform", "log_uniform", "integers")              # axis kinds drawn at random


EXPERIMENT_TABLES = ("experiment",) + tuple(s.key for s in sections())


def vdo_version() -> str:
    try:
        return metadata.version("vdo")
    except metadata.PackageNotFoundError:
        return "unknown"


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
        if not is_file(file):
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
