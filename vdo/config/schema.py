"""The schema machinery of the experiment file: how one TOML value is checked and converted
(`Kind`), how a dataclass field is described (`Row`, via `row`) and how a table is (`Section`, via
`table`), and how a parsed table is written back (`write_rows`, `table_dict`).

A `Kind` reads a value in file units and returns it in SI units: ``scale`` converts (mm -> m and
ms -> s by 1e-3, deg -> rad by pi/180, `_UNIT_SCALE`), ranges are in file units; `write` divides by the scale
and rounds to `_SIGNIFICANT` digits, so ``read(write(x)) == x`` to ~1e-12 relative. A value that
does not fit raises `BadValue`, which the reading `vdo.config.reader.Table` turns into a
`ConfigError` naming the file and the field. Imports only NumPy.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vdo.core.runfolder import is_file

NAME_PATTERN = r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}"   # names that become parts of file names
NAME_RULE = (f"must match {NAME_PATTERN} (letters, digits, '_', '.', '-'; not starting with '.' or "
             "'-'; at most 64 characters), as it names output files")
MAX_COORDINATE = 1e6               # any vector entry (a lab is not 1000 km wide)
MAX_MAGNITUDE = 1e12               # any number without a range of its own: larger values are unit
                                   # mistakes, and overflow float32 renders and float64 squares
IMAGE_MAGIC = {b"\x89PNG\r\n\x1a\n": "PNG", b"\xff\xd8\xff": "JPEG", b"II*\x00": "TIFF",
               b"MM\x00*": "TIFF", b"BM": "BMP"}
_UNIT_SCALE = {"": 1.0, "m": 1.0, "mm": 1e-3, "s": 1.0, "ms": 1e-3, "deg": math.pi / 180.0}
_SIGNIFICANT = 12       # digits written back: parse(to_dict(e)) equals e to ~1e-12 relative


class _Required:
    def __repr__(self):
        return "required"


REQUIRED = _Required()


class BadValue(Exception):
    """A value that does not fit its Kind; `vdo.config.reader.Table` turns it into a ConfigError naming the field
    (with `key`, the key inside a nested table: ``mount "left".tripod.legs``)."""

    def __init__(self, message: str, key: str = ""):
        super().__init__(message)
        self.key = key


# --------------------------------------------------------------------------------------------
# Kinds: how one TOML value is checked, converted to the attribute value and written back.
# `scale` converts file units to SI (mm -> m, ms -> s, deg -> rad); ranges are in file units.
# --------------------------------------------------------------------------------------------
def is_number(x) -> bool:
    """Whether `x` is a TOML number (an int or a float, not a boolean)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _tidy(x: float) -> float:
    return float(f"{x:.{_SIGNIFICANT}g}")


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


class Kind:
    doc = ""

    def read(self, value, scale: float, base: Path):
        raise NotImplementedError

    def write(self, value, scale: float):
        return value


@dataclass(frozen=True)
class Text(Kind):
    """A string: one of `choices`, a name (NAME_PATTERN) or free text without control characters."""

    choices: tuple[str, ...] | None = None
    name: bool = False
    empty: bool = False
    title: bool = False

    @property
    def doc(self):
        return ", ".join(self.choices) if self.choices else ("name" if self.name else "string")

    def read(self, value, scale, base):
        if not isinstance(value, str) or not (value or self.empty):
            raise BadValue(f"must be a{'' if self.empty else ' non-empty'} string (got {_show(value)})")
        if self.choices is not None and value not in self.choices:
            raise BadValue(f"must be one of {', '.join(self.choices)} (got {_show(value)})")
        if self.name and not re.fullmatch(NAME_PATTERN, value):
            raise BadValue(f"{NAME_RULE} (got {_show(value)})")
        if (self.name or self.title) and not value.isprintable():
            raise BadValue(f"must not contain control characters (got {_show(value)})")
        if self.title and (len(value) > 200 or "/" in value or "\\" in value):
            raise BadValue(f"must be a title of at most 200 characters without '/' or '\\' (got {_show(value)})")
        return value


@dataclass(frozen=True)
class Flag(Kind):
    doc = "true/false"

    def read(self, value, scale, base):
        if not isinstance(value, bool):
            raise BadValue(f"must be true or false (got {_show(value)})")
        return value


@dataclass(frozen=True)
class Real(Kind):
    """A finite number; `positive`, then [low, high] (file units; `why` explains the range)."""

    low: float | None = None
    high: float | None = None
    positive: bool = False
    why: str = ""

    @property
    def doc(self):
        if self.low is not None and self.high is not None:
            return f"{self.low:g} to {self.high:g}"
        if self.low is not None:
            return f"≥ {self.low:g}"
        return "> 0" if self.positive else "number"

    def read(self, value, scale, base):
        if not is_number(value) or not math.isfinite(value):
            raise BadValue(f"must be a finite number (got {_show(value)})")
        if self.positive and value <= 0:
            raise BadValue(f"must be positive (got {_show(value)})")
        if (self.low is not None and value < self.low) or (self.high is not None and value > self.high):
            within = (f"lie in [{self.low}, {self.high}]" if self.low is not None and self.high is not None
                      else f"be ≥ {self.low:g}" if self.low is not None else f"be ≤ {self.high:g}")
            raise BadValue(f"must {within} (got {_show(value)})"
                       + (f": {self.why}" if self.why else ""))
        if abs(value) > MAX_MAGNITUDE and (self.low is None or self.high is None):
            raise BadValue(f"must lie within ±{MAX_MAGNITUDE:g} (got {_show(value)}): no quantity of an "
                           "experiment is this large in the units it is read in; check the unit")
        return float(value) * scale

    def write(self, value, scale):
        return _tidy(value / scale)


@dataclass(frozen=True)
class Whole(Kind):
    """A TOML integer (not a float, not a boolean) in [low, high]."""

    low: int | None = None
    high: int | None = None

    @property
    def doc(self):
        if self.high is not None:
            return f"integer {self.low}–{self.high}"
        return f"integer ≥ {self.low}" if self.low is not None else "integer"

    def read(self, value, scale, base):
        bad = isinstance(value, bool) or not isinstance(value, int)
        if bad or (self.low is not None and value < self.low) or (self.high is not None and value > self.high):
            bounds = f" >= {self.low}" if self.high is None else f" in {self.low}..{self.high}"
            raise BadValue(f"must be an integer{bounds if self.low is not None else ''} (got {_show(value)})")
        return value


@dataclass(frozen=True)
class Vector(Kind):
    """A list of `length` numbers: an array in SI units, or a tuple when `as_tuple`. `whole`:
    TOML integers; `finite=False` admits ±inf (never NaN)."""

    length: int
    positive: bool = False
    whole: bool = False
    finite: bool = True
    as_tuple: bool = False
    letters: str = ""

    @property
    def doc(self):
        return f"[{', '.join(self.letters)}]" if self.letters else f"{self.length} numbers"

    def read(self, value, scale, base):
        if self.whole:
            ok = isinstance(value, list) and len(value) == self.length and all(
                isinstance(x, int) and not isinstance(x, bool) for x in value)
            if not ok:
                raise BadValue(f"must be {self.length} whole numbers [{', '.join(self.letters)}] "
                           f"(got {_show(value)})")
        ok = isinstance(value, list) and len(value) == self.length and all(
            is_number(x) and not math.isnan(x) and (math.isfinite(x) or not self.finite) for x in value)
        if not ok:
            raise BadValue(f"must be a list of {self.length} {'finite ' if self.finite else ''}numbers "
                       f"(got {_show(value)})")
        if not self.whole and any(math.isfinite(x) and abs(x) > MAX_COORDINATE for x in value):
            raise BadValue(f"has a value beyond ±{MAX_COORDINATE:g} (got {_show(value)})")
        if self.positive and any(x <= 0 for x in value):
            raise BadValue(f"must be positive (got {_show(value)})")
        if self.as_tuple:
            return tuple(value) if self.whole else tuple(float(x) * scale for x in value)
        return np.array(value, dtype=float) * scale

    def write(self, value, scale):
        if self.whole:
            return list(value)
        return [_tidy(float(x) / scale) for x in value]


@dataclass(frozen=True)
class Points(Kind):
    """A list of at least `minimum` points of `dims` coordinates ([x, y, z] or [x, y]): an
    (n, dims) array."""

    minimum: int = 2
    dims: int = 3

    @property
    def doc(self):
        return "[[x, y, z], …]" if self.dims == 3 else "[[x, y], …]"

    def read(self, value, scale, base):
        ok = isinstance(value, list) and len(value) >= self.minimum and all(
            isinstance(p, list) and len(p) == self.dims and all(
                is_number(x) and math.isfinite(x) and abs(x) <= MAX_COORDINATE for x in p)
            for p in value)
        if not ok:
            axes = "[x, y, z]" if self.dims == 3 else "[x, y]"
            raise BadValue(f"must be a list of at least {self.minimum} {axes} points in metres "
                       f"(each coordinate within ±{MAX_COORDINATE:g})")
        return np.array(value, dtype=float) * scale

    def write(self, value, scale):
        return [[_tidy(float(x) / scale) for x in p] for p in value]


@dataclass(frozen=True)
class Polygons(Kind):
    """A list of polygons, each a list of at least 3 [x, y] points (m): a tuple of (n, 2) arrays."""

    doc = "[[[x, y], …], …]"

    def read(self, value, scale, base):
        if not isinstance(value, list) or not value:
            raise BadValue(f"must be a non-empty list of polygons, each a list of at least 3 [x, y] points "
                       f"(got {_show(value)})")
        return tuple(Points(3, dims=2).read(p, scale, base) for p in value)

    def write(self, value, scale):
        return [Points(3, dims=2).write(p, scale) for p in value]


@dataclass(frozen=True)
class Numbers(Kind):
    """A list of numbers > 0 (any finite numbers without `positive`), as a tuple (sorted and
    without repeats when `as_set`)."""

    as_set: bool = False
    what: str = "numbers"
    positive: bool = True

    @property
    def doc(self):
        return "list of numbers > 0" if self.positive else "list of numbers"

    def read(self, value, scale, base):
        if not isinstance(value, list) or not all(is_number(x) and math.isfinite(x) and abs(x) <= MAX_MAGNITUDE
                                                  and (x > 0 or not self.positive) for x in value):
            raise BadValue(f"must be a list of {self.what}{', each > 0' if self.positive else ''} "
                           f"(got {_show(value)})")
        if self.as_set:     # one value per number as written back (`write`'s digits): 1 and 1 + 1e-16 are one
            return tuple(sorted({_tidy(float(x)) * scale for x in value}))
        return tuple(float(x) * scale for x in value)

    def write(self, value, scale):
        return [_tidy(x / scale) for x in value]


@dataclass(frozen=True)
class Words(Kind):
    """A list of strings (a tuple): some of `choices`, or names of other tables (`what`)."""

    choices: tuple[str, ...] | None = None
    what: str = "names"
    nonempty: bool = False

    @property
    def doc(self):
        return f"list of {', '.join(self.choices)}" if self.choices else f"list of {self.what}"

    def read(self, value, scale, base):
        ok = isinstance(value, list) and all(isinstance(x, str) for x in value) \
            and (value or not self.nonempty)
        if self.choices is not None:
            if not ok or not set(value) <= set(self.choices):
                raise BadValue(f"must list some of {', '.join(self.choices)} (got {_show(value)})")
        elif not ok:
            raise BadValue(f"must be a {'non-empty ' if self.nonempty else ''}list of {self.what}")
        twice = sorted({x for x in value if value.count(x) > 1})
        if twice:
            raise BadValue(f"lists {', '.join(map(repr, twice))} more than once")
        return tuple(value)

    def write(self, value, scale):
        return list(value)


@dataclass(frozen=True)
class File(Kind):
    """A path to an existing, readable file with one of `suffixes`, relative to the config file;
    `magic`: the first bytes must be one of these image formats."""

    suffixes: tuple[str, ...]
    what: str
    kinds: str
    magic: bool = False
    doc = "path"

    def read(self, value, scale, base):
        if not isinstance(value, str) or not value or "\x00" in value:
            raise BadValue(f"must be a non-empty string (got {_show(value)})")
        path = (base / value).resolve()
        if not is_file(path):
            raise BadValue(f"{self.what} file {str(path)!r} does not exist; give a path to "
                       f"{self.kinds} file, relative to the config file")
        if not os.access(path, os.R_OK):
            raise BadValue(f"{self.what} file {str(path)!r} is not readable")
        if path.suffix.lower() not in self.suffixes:
            raise BadValue(f"{path.name!r} is not {self.kinds} file (by its suffix)")
        if self.magic:
            with open(path, "rb") as fh:
                head = fh.read(8)
            if not any(head.startswith(m) for m in IMAGE_MAGIC):
                raise BadValue(f"{path.name!r} is not an image: its content is not "
                           f"{', '.join(sorted(set(IMAGE_MAGIC.values())))}")
        return path

    def write(self, value, scale):
        return str(value)


@dataclass(frozen=True)
class SubTable(Kind):
    """A table nested in another (`[mount.tripod]` under a `[[mount]]`), read into `cls` by
    `cls`'s own schema rows; absent keys take their defaults, unknown keys are refused."""

    cls: type
    doc = "table"

    def read(self, value, scale, base):
        if not isinstance(value, dict):
            raise BadValue(f"must be a table of {', '.join(r.key for r in rows_of(self.cls))} "
                       f"(got {_show(value)})")
        rows = rows_of(self.cls)
        known = tuple(r.key for r in rows)
        for key in value:
            if key not in known:
                raise BadValue(unknown_field(key, known), key=key if key.isprintable() else repr(key))
        values = {}
        for r in rows:
            if r.key in value:
                try:
                    values[r.attr] = r.kind.read(value[r.key], r.scale, base)
                except BadValue as exc:
                    raise BadValue(str(exc), key=f"{r.key}.{exc.key}" if exc.key else r.key) from None
        return self.cls(**values)

    def write(self, value, scale):
        return write_rows(value, rows_of(self.cls))


# --------------------------------------------------------------------------------------------
# Rows and tables
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Row:
    """One schema row: TOML `key` -> dataclass attribute `attr` (filled from the field's name).

    `default` is in file units (REQUIRED, or None: absent). `either`: another key that may stand in
    for a required one (checked by the table's check). `when`: attributes (space-separated) one of
    which must be set for this key to apply (written only then). `shown`: the default as the docs show it."""

    key: str
    kind: Kind
    default: Any = REQUIRED
    unit: str = ""
    doc: str = ""
    either: str = ""
    when: str = ""
    shown: str = ""
    attr: str = ""

    @property
    def scale(self) -> float:
        return _UNIT_SCALE[self.unit]


@dataclass(frozen=True)
class Section:
    """A TOML table ([key]) or array of tables ([[key]], each with a unique name) read into `cls`.
    `check(t, values)` checks several fields together and may complete `values` before `cls(**values)`;
    `extra`: keys accepted in the file that are not attributes (read by `check`)."""

    key: str
    cls: type
    array: bool = False
    required: bool = False
    check: Callable | None = None
    extra: tuple[Row, ...] = ()
    rows: tuple[Row, ...] | None = None
    doc: str = ""
    attr: str = ""


def row(key, kind, default=REQUIRED, *, unit="", doc="", either="", when="", shown=""):
    """A dataclass field described by a schema row; its default is the row's default in SI units."""
    spec = Row(key, kind, default, unit, doc, either, when, shown)
    meta = {"vdo.row": spec}
    if default is REQUIRED:
        return field(metadata=meta)
    if default is None:
        return field(default=None, metadata=meta)
    value = kind.read(default, spec.scale, Path("."))
    if isinstance(value, np.ndarray):
        return field(default_factory=value.copy, metadata=meta)
    return field(default=value, metadata=meta)


def table(key, cls, *, array=False, required=False, check=None, extra=(), rows=None, doc="",
          default=dataclasses.MISSING):
    """A dataclass field holding a parsed table (`cls`) or a tuple of them (`array`)."""
    return field(default=default, metadata={"vdo.table": Section(key, cls, array, required, check,
                                                                  tuple(extra), rows, doc)})


@functools.cache
def rows_of(cls) -> tuple[Row, ...]:
    """The schema rows of a dataclass, in field order, with `attr` filled in."""
    return tuple(replace(f.metadata["vdo.row"], attr=f.name) for f in dataclasses.fields(cls)
                 if "vdo.row" in f.metadata)


def table_dict(obj) -> dict:
    """One parsed table (e.g. `exp.analysis`) as its TOML dict, in file units."""
    return write_rows(obj, rows_of(type(obj)))


def write_rows(obj, rows) -> dict:
    """The TOML dict (file units) of the attributes of `obj` described by schema `rows`: None
    values are left out, and so are the rows whose `when` attributes are all None."""
    out = {}
    for r in rows:
        value = getattr(obj, r.attr)
        if value is not None and not (r.when and all(getattr(obj, w) is None for w in r.when.split())):
            out[r.key] = r.kind.write(value, r.scale)
    return out


def unknown_field(key: str, allowed) -> str:
    """The message for a key no schema row has: the nearest known one, else all of them."""
    close = difflib.get_close_matches(key, allowed, n=1)
    return "unknown field; " + (f"did you mean {close[0]!r}?" if close else f"known fields: {', '.join(allowed)}")
