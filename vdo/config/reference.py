"""docs/config.md, generated from the schema: one Markdown table per table of the experiment
file (field, type, unit, default, meaning), written by scripts/config_docs.py and checked against
the file by tests/config/test_config_schema.py."""

from __future__ import annotations

from vdo.config.experiment import Experiment, sections
from vdo.config.schema import NAME_PATTERN, REQUIRED, SubTable, rows_of

# --------------------------------------------------------------------------------------------
# docs/config.md
# --------------------------------------------------------------------------------------------
_DOC_HEAD = """\
# The experiment file

<!-- Generated from the schema in vdo/config/ by scripts/config_docs.py; do not edit by hand. -->

One TOML file (UTF-8) describes one experiment. Lengths are **metres** unless the field's name says
`_mm`; angles are **degrees** (`_deg`). Relative paths are relative to the TOML file.
Every field is checked before any work starts; an unknown field is an error (with the nearest
known name). Names of meshes, regions, rails, cameras and lights become parts of file names: they
must match `{pattern}` (letters, digits, `_`, `.`, `-`; at most 64 characters).
`experiments/beam_column/ten_cameras.toml` is a complete example.
"""


def _doc_value(value) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list):
        return "[" + ", ".join(_doc_value(x) for x in value) + "]"
    return str(value)


def _doc_table(title: str, rows, doc: str) -> str:
    lines = [f"## {title}", ""]
    if doc:
        lines += [doc, ""]
    lines += ["| field | type | unit | default | meaning |", "| --- | --- | --- | --- | --- |"]
    for r in rows:
        default = r.shown or ("required" if r.default is REQUIRED else
                              "none" if r.default is None else _doc_value(r.default))
        unit = "°" if r.unit == "deg" else r.unit
        lines.append(f"| `{r.key}` | {r.kind.doc} | {unit} | {default} | {r.doc} |")
    return "\n".join(lines) + "\n"


def markdown() -> str:
    """docs/config.md: the schema as tables, generated from the rows."""
    parts = [_DOC_HEAD.format(pattern=NAME_PATTERN),
             _doc_table("`[experiment]`", rows_of(Experiment), "")]
    for sec in sections():
        title = f"`[[{sec.key}]]`" if sec.array else f"`[{sec.key}]`"
        rows = []
        for r in sec.rows:
            rows += [x for x in sec.extra if x.key == r.either] + [r]
        parts.append(_doc_table(title, rows, sec.doc + (" Optional." if not sec.required and sec.array
                                                        else "")))
        for r in sec.rows:
            if isinstance(r.kind, SubTable):
                doc = " ".join((r.kind.cls.__doc__ or "").split())
                parts.append(_doc_table(f"`[{sec.key}.{r.key}]`", rows_of(r.kind.cls), doc))
    return "\n".join(parts)
