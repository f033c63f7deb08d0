"""Reading a configuration file with clear errors: the TOML document (`read_toml`, UTF-8 only),
the fields of the environment variable VDO_SET written over it (`with_overrides`), one table read
key by key against its schema rows (`Table`: unknown keys are refused with the nearest known name)
and one table or array of tables of the experiment file read into its dataclass (`read_section`).
Shared by the experiment file (`vdo.config.experiment`) and the validation file
(`vdo.config.validation`). Imports only NumPy.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from pathlib import Path

import numpy as np

from vdo.config.schema import (NAME_PATTERN, REQUIRED, BadValue, Flag, Kind, Real, Row, Section, Text,
                               Vector, Whole, is_number, unknown_field)
from vdo.core.errors import ConfigError

class Table:
    """One TOML table being read: every key must be known, every value checked."""

    def __init__(self, data, where: str, file: Path, allowed: tuple[str, ...]):
        self.file, self.where = file, where
        if not isinstance(data, dict):
            raise ConfigError(file, where, "must be a table")
        for key in data:
            if key not in allowed:
                raise ConfigError(file, self._field(key), unknown_field(key, allowed))
        self.data = data

    def _field(self, key):
        key = key if key.isprintable() else repr(key)
        return f"{self.where}.{key}" if self.where and key else (key or self.where)

    def error(self, key, message):
        return ConfigError(self.file, self._field(key), message)

    def has(self, key):
        return key in self.data

    def raw(self, key, default=REQUIRED):
        if key not in self.data:
            if default is REQUIRED:
                raise self.error(key, "is required")
            return default
        return self.data[key]

    def read(self, key, kind: Kind, scale: float = 1.0):
        """The value at `key` (present) checked and converted by `kind`."""
        try:
            return kind.read(self.data[key], scale, self.file.parent)
        except BadValue as exc:
            raise self.error(f"{key}.{exc.key}" if exc.key else key, str(exc)) from None

    def get(self, r: Row, default=None):
        """The attribute value of schema row `r`: read from the file, else `default` (the
        dataclass default), else an error when the row is required."""
        if r.key in self.data:
            return self.read(r.key, r.kind, r.scale)
        if r.default is REQUIRED and not (r.either and self.has(r.either)):
            raise self.error(r.key, "is required")
        return default

    # The helpers below read fields that have no schema row (validate.py's cases, sweep files).
    def _value(self, key, default, kind):
        return self.read(key, kind) if key in self.data else self.raw(key, default)

    def string(self, key, default=REQUIRED, choices=None):
        return self._value(key, default, Text(tuple(choices) if choices else None))

    def number(self, key, default=REQUIRED, low=None, high=None, positive=False):
        return self._value(key, default, Real(low, high, positive))

    def integer(self, key, default=REQUIRED, low=None):
        return self._value(key, default, Whole(low))

    def boolean(self, key, default=REQUIRED):
        return self._value(key, default, Flag())

    def vector(self, key, length, default=REQUIRED, positive=False):
        return self._value(key, default, Vector(length, positive))


def as_numbers(value):
    """`value` (a number or a rectangular list of lists of numbers) as a float array; None when it
    holds anything else (strings, booleans, NaN or inf, ragged or too deep nesting)."""
    try:
        arr = np.asarray(value, dtype=object)
    except (ValueError, RecursionError):
        return None
    if not all(is_number(x) and math.isfinite(x) for x in arr.flat):
        return None
    return arr.astype(float)


def read_toml(path) -> dict:
    """The parsed TOML document at `path`; ConfigError when it is missing, unreadable, not UTF-8
    text or invalid."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except OSError as exc:
        raise ConfigError(path, "", f"cannot be read ({exc.strerror})") from None
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise ConfigError(path, "", "is UTF-16 text; save it as UTF-8 (TOML files are UTF-8)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise ConfigError(path, "", f"is not UTF-8 text (byte 0x{raw[exc.start]:02x} on line {line}); "
                                    "save it as UTF-8 (TOML files are UTF-8)") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(path, "", f"is not valid TOML ({exc})") from None
    except RecursionError:
        raise ConfigError(path, "", "is not valid TOML for vdo: arrays or tables nested too deep") from None


OVERRIDE_VARIABLE = "VDO_SET"   # environment: field values written over the files vdo reads


def _override_items() -> list[tuple[str, list[str]]]:
    """VDO_SET's items (separated by ';'), each with the dotted path before its '=' split."""
    import os

    text = os.environ.get(OVERRIDE_VARIABLE, "").strip()
    items = filter(None, (part.strip() for part in text.split(";")))
    return [(item, item.partition("=")[0].strip().split(".")) for item in items]


def with_overrides(data: dict, tables: tuple[str, ...]) -> dict:
    """`data` (a parsed TOML document) with the fields of the environment variable VDO_SET
    written in, for a quick, coarse run of any file without editing it (the test of the shipped
    examples runs them so). VDO_SET holds `TABLE.FIELD = VALUE` items separated by ';', VALUE in
    TOML syntax, e.g. `evaluation.sample_spacing_mm = 60; optimize.starts = 1`;
    `TABLE.*.FIELD` sets FIELD on every table of an array of tables ([[camera]]), `TABLE.NAME.FIELD`
    on the one named NAME (ConfigError when none is). Only the items
    whose TABLE is one of `tables` apply (a validation file reads `validation` and `defaults`,
    an experiment its own tables), so one VDO_SET serves every kind of file; an item the file's
    table does not take is refused by the file's own checks. ConfigError (naming VDO_SET) for an
    item that is not of that form."""
    import copy
    import tomllib

    items = _override_items()
    if not items:
        return data
    data = copy.deepcopy(data)
    for item, tokens in items:
        _, eq, value = item.partition("=")
        try:
            parsed = tomllib.loads(f"v = {value.strip()}")["v"] if eq else None
        except tomllib.TOMLDecodeError:
            parsed = None
        if parsed is None or len(tokens) not in (2, 3) or not all(tokens):
            raise ConfigError(OVERRIDE_VARIABLE, item, "write TABLE.FIELD = VALUE, TABLE.*.FIELD = "
                                                       "VALUE or TABLE.NAME.FIELD = VALUE (VALUE in "
                                                       "TOML), items separated by ';'")
        if tokens[0] not in tables:
            continue
        if len(tokens) == 2:
            table = data.setdefault(tokens[0], {})
            if isinstance(table, dict):
                table[tokens[1]] = parsed
        else:
            tables_of = [t for t in data.get(tokens[0], []) if isinstance(t, dict)
                         and (tokens[1] == "*" or t.get("name") == tokens[1])]
            if not tables_of and tokens[1] != "*":
                raise ConfigError(OVERRIDE_VARIABLE, item, f"no [[{tokens[0]}]] is named {tokens[1]!r}: "
                                                           "name one of the file's, or write "
                                                           f"{tokens[0]}.*.{tokens[2]} for all of them")
            for table in tables_of:
                table[tokens[2]] = parsed
    return data


def from_override(err: ConfigError) -> ConfigError:
    """`err` (from a file's checks) saying that its field was written by VDO_SET, not by the
    file, when a VDO_SET item names that field (`TABLE.FIELD`, or `TABLE.*.FIELD` /
    `TABLE.NAME.FIELD` for a field of an array's table); else `err` itself."""
    field = str(err.field or "")
    for item, tokens in _override_items():
        ours = (len(tokens) == 2 and field == f"{tokens[0]}.{tokens[1]}") or (
            len(tokens) == 3 and field.startswith(f"{tokens[0]} ") and field.endswith(f".{tokens[2]}")
            and (tokens[1] == "*" or f'"{tokens[1]}"' in field))
        if ours:
            return ConfigError(err.file, err.field, f"{err.message} (this value comes from the "
                                                    f"environment's {OVERRIDE_VARIABLE} item {item!r}, "
                                                    "not from the file)")
    return err


def read_section(top: Table, sec: Section, path: Path):
    """The value of one table (or the tuple of an array of tables) of the experiment file."""
    defaults = {f.name: f.default if f.default is not dataclasses.MISSING else
                (f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
                for f in dataclasses.fields(sec.cls)}
    allowed = tuple(r.key for r in sec.rows + sec.extra)

    def one(data, where):
        t = Table(data, where, path, allowed)
        values = {r.attr: t.get(r, defaults[r.attr]) for r in sec.rows}
        for r in sec.rows:
            if r.when and t.has(r.key) and all(values[w] is None for w in r.when.split()):
                other = " or ".join(o.key for o in sec.rows if o.attr in r.when.split())
                raise t.error(r.key, f"only applies together with {other}")
        if sec.check is not None:
            sec.check(t, values)
        try:
            return sec.cls(**values), t
        except ValueError as exc:      # SensorModel names the field: "SensorModel.<field>: ..."
            name, _, message = str(exc).partition(": ")
            raise t.error(name.rpartition(".")[2], message) from None

    if not sec.array:
        if not top.has(sec.key) and not sec.required:
            return sec.cls(), ()
        value, t = one(top.raw(sec.key), sec.key)
        return value, (t,)
    items = top.raw(sec.key, REQUIRED if sec.required else [])
    if not isinstance(items, list) or (sec.required and not items):
        raise ConfigError(path, sec.key, f"needs at least one [[{sec.key}]] table")
    values, tables, names = [], [], set()
    for i, item in enumerate(items):
        name = item.get("name") if isinstance(item, dict) else None
        ok = isinstance(name, str) and re.fullmatch(NAME_PATTERN, name)
        where = f'{sec.key} "{name}"' if ok else f"{sec.key}[{i}]"
        value, t = one(item, where)
        key = getattr(value, "name", None)      # unnamed tables (stereo pairs) are checked later
        if key is not None and key in names:
            raise ConfigError(path, where, "name is used twice; names must be unique")
        names.add(key)
        values.append(value)
        tables.append(t)
    return tuple(values), tuple(tables)
