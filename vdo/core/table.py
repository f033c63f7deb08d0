"""Results tables for scripts: rows (dataclasses with `to_dict`, or dicts) written as one CSV.

A list of typed rows is the table (no pandas: `pandas.DataFrame([r.to_dict() for r in rows])`
makes one where it is wanted). Nested dicts are flattened with "_" (``{"sigma": {"p95": 1}}`` ->
``sigma_p95``); None is an empty cell.
"""

from __future__ import annotations

import csv
import dataclasses
import os
from pathlib import Path


def flat(row) -> dict:
    """A row as a flat dict: `row.to_dict()`, a dataclass's fields, or a dict; nested dicts
    joined with "_"."""
    if hasattr(row, "to_dict"):
        row = row.to_dict()
    elif dataclasses.is_dataclass(row):
        row = dataclasses.asdict(row)
    out = {}
    for key, value in row.items():
        if isinstance(value, dict):
            out |= {f"{key}_{k}": v for k, v in flat(value).items()}
        else:
            out[key] = value
    return out


def write_csv(path, rows) -> Path:
    """Write `rows` to the CSV file `path`, whole or not at all (a temporary file renamed); the
    columns are the union of the rows' keys in first-seen order. Returns the path."""
    rows = [flat(r) for r in rows]
    columns = list(dict.fromkeys(k for r in rows for k in r))
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for r in rows:
            writer.writerow({k: "" if r.get(k) is None else r.get(k) for k in columns})
    os.replace(tmp, path)
    return path
