"""report.html: one self-contained page per run folder (plotly.js inline, opens offline).

The page holds an interactive 3D view of the run (`view3d.load`: meshes, region samples coloured by
a field chosen from a list, camera frustums and names, light panels), the region table from
summary.json, every other table of the folder's JSON files, the contact sheet, the unfolded maps,
the optimizer's before/after and convergence figure, a design's camera-count curve, chosen cameras
and candidate statistics, and a sweep's results.csv and figures. What a
folder lacks (an interrupted run) is listed at the top instead of failing.

The field shown first can be chosen by the address: report.html#field=sigma_max.
"""

from __future__ import annotations

import base64
import csv
import html
import json
import logging
from pathlib import Path

import numpy as np
import plotly.graph_objects as go

from vdo.outputs import view3d

log = logging.getLogger(__name__)

# What each command's run folder holds, the command recognised by the first file of its marker
# list that is present (an evaluate folder when none is).
KINDS = (("design", ("designed.toml", "design.json", "pareto.csv")),
         ("optimize", ("optimized.toml", "summary_before.json", "summary_after.json")),
         ("sweep", ("results.csv",)),
         ("validate", ("validation.csv", "validation.png")),
         ("series", ("series.json",)),
         ("calibrate", ("target.yml",)),
         ("render", ("render.json", "contact_sheet.png")))
EXPECTED = {"evaluate": ("config.toml", "layout.json", "samples.vtp", "summary.json"),
            "design": ("designed.toml", "layout.json", "summary.json", "design.json", "pareto.csv",
                       "pareto.png", "candidates.csv"),
            "optimize": ("optimized.toml", "layout.json", "summary_before.json",
                         "summary_after.json", "constraints.json", "convergence.png"),
            "sweep": ("results.csv",),
            "validate": ("validation.csv", "validation.png"),
            "render": ("config.toml", "layout.json", "render.json", "contact_sheet.png"),
            "series": ("config.toml", "layout.json", "series.json"),
            "calibrate": ("config.toml", "target.yml", "summary.json", "samples.vtp", "contact_sheet.png")}
WHY = {"config.toml": "meshes and lights are not drawn", "optimized.toml": "meshes and lights are "
       "not drawn", "layout.json": "no camera is drawn", "samples.vtp": "no field is drawn",
       "summary.json": "no region table", "summary_before.json": "no table before optimizing",
       "summary_after.json": "no table after optimizing", "convergence.png": "no convergence figure",
       "designed.toml": "meshes and lights are not drawn", "design.json": "no design section",
       "pareto.png": "no camera-count curve"}
NOT_TABULATED = ("candidates.csv",)   # one row per candidate: counted, not listed
MAX_TABLE_ROWS = 500

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.2em 2em; color: #222; }
table { border-collapse: collapse; font-size: 12px; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #f0f0f0; } td:first-child, th:first-child { text-align: left; }
.missing { background: #fff3cd; border: 1px solid #e0c060; padding: 0.6em 1em; }
img { max-width: 100%; border: 1px solid #ddd; margin: 0.3em 0; }
#view3d { width: 100%; height: 720px; }
"""

# Applies a field (from the list or from #field=NAME) to the sample cells and the colour bar.
_SCRIPT = """
(function () {
  var fields = JSON.parse(document.getElementById('vdo-fields').textContent);
  var gd = document.getElementById('view3d');
  var select = document.getElementById('field');
  function show(key) {
    var f = fields[key]; if (!f || !gd) return;
    var bin = atob(f.index), bytes = new Uint8Array(bin.length), faces = [];
    for (var i = 0; i < bin.length; i++) { bytes[i] = bin.charCodeAt(i); }
    var index = new Uint16Array(bytes.buffer);
    for (var k = 0; k < index.length; k++) {
      var c = f.palette[index[k]]; faces.push(c, c);         // two triangles per sample
    }
    Plotly.restyle(gd, {facecolor: [faces]}, [f.cells_trace]);
    Plotly.restyle(gd, {'marker.colorscale': [f.colorscale], 'marker.cmin': f.cmin,
                        'marker.cmax': f.cmax, 'marker.colorbar.title.text': f.title},
                   [f.bar_trace]);
    Plotly.restyle(gd, {'marker.colorbar.tickmode': f.ticks ? 'array' : 'auto',
                        'marker.colorbar.tickvals': [f.ticks || []]}, [f.bar_trace]);
    select.value = key;
    document.body.setAttribute('data-field', key);
  }
  select.addEventListener('change', function () { show(select.value); });
  var m = /field=([A-Za-z0-9_]+)/.exec(window.location.hash);
  show(m && fields[m[1]] ? m[1] : select.value);
})();
"""


def _hex(rgba: np.ndarray) -> list[str]:
    rgb = np.clip(np.round(np.asarray(rgba)[:, :3] * 255), 0, 255).astype(int)
    return [f"#{r:02x}{g:02x}{b:02x}" for r, g, b in rgb]


def _colorscale(fld: view3d.Field, lo: float, hi: float) -> list:
    """A plotly colour scale equal to the field's matplotlib colormap over [lo, hi]."""
    import matplotlib.pyplot as plt

    if fld.discrete:
        n = int(round(hi - lo))
        colours = _hex(plt.get_cmap(fld.cmap, n)(np.arange(n)))
        return [s for k, c in enumerate(colours) for s in ([k / n, c], [(k + 1) / n, c])]
    stops = np.linspace(0, 1, 11)
    return [[float(s), c] for s, c in zip(stops, _hex(plt.get_cmap(fld.cmap)(stops)))]


def figure(sc: view3d.Scene3D) -> tuple[go.Figure, dict]:
    """The 3D figure and, per field, what the page's script needs to show it."""
    fig = go.Figure()
    for name, role, v, f in sc.meshes:
        specimen = role == "specimen"
        fig.add_trace(go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2],
                                color="#c8c8c8" if specimen else "#8a8f99",
                                opacity=1.0 if specimen else 0.25, name=name, hoverinfo="name",
                                flatshading=True, showlegend=True))
    for name, centre, corners in sc.cameras:
        seg = view3d.frustum_segments(centre, corners)
        xyz = np.concatenate([np.vstack([s, [np.nan] * 3]) for s in seg])
        fig.add_trace(go.Scatter3d(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], mode="lines",
                                   line=dict(color="#1f77b4", width=3), name=name,
                                   hoverinfo="name", showlegend=False))
    if sc.cameras:
        c = np.array([centre for _, centre, _ in sc.cameras])
        fig.add_trace(go.Scatter3d(x=c[:, 0], y=c[:, 1], z=c[:, 2], mode="text+markers",
                                   text=[n for n, _, _ in sc.cameras], textposition="top center",
                                   marker=dict(size=3, color="#1f77b4"), name="cameras"))
    for name, corners in sc.lights:
        fig.add_trace(go.Mesh3d(x=corners[:, 0], y=corners[:, 1], z=corners[:, 2], i=[0, 0],
                                j=[1, 2], k=[2, 3], color="#ffd23f", opacity=0.8, name=name,
                                hoverinfo="name", showlegend=False))
    fields = {}
    if sc.samples is not None and sc.fields:
        quads = view3d.cells(sc)
        v = quads.reshape(-1, 3).astype(np.float32)        # 0.1 mm steps at 1 km: plenty
        base = 4 * np.arange(len(quads))
        tri = np.concatenate([np.stack([base, base + 1, base + 2], 1)[:, None],
                              np.stack([base, base + 2, base + 3], 1)[:, None]],
                             axis=1).reshape(-1, 3).astype(np.int32)
        cells_trace = len(fig.data)
        first = sc.fields[0]
        rgba, lo, hi, _ = first.colours()
        fig.add_trace(go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=tri[:, 0], j=tri[:, 1],
                                k=tri[:, 2], facecolor=np.repeat(_hex(rgba), 2), flatshading=True,
                                name="region samples", hoverinfo="skip",
                                lighting=dict(ambient=0.85, diffuse=0.2, specular=0.0)))
        bar_trace = len(fig.data)
        centre = sc.samples.points.mean(axis=0)
        fig.add_trace(go.Scatter3d(x=[centre[0]], y=[centre[1]], z=[centre[2]], mode="markers",
                                   hoverinfo="skip", showlegend=False, name="colour scale",
                                   marker=dict(size=0.1, opacity=0, color=[lo], cmin=lo, cmax=hi,
                                               colorscale=_colorscale(first, lo, hi),
                                               showscale=True, colorbar=dict(title=""))))
        for fld in sc.fields:
            rgba, lo, hi, how = fld.colours()
            title = f"{fld.label}<br>{how if fld.discrete else f'{lo:.4g} – {hi:.4g} ({how})'}"
            palette, index = np.unique(_hex(rgba), return_inverse=True)
            fields[fld.key] = {"palette": palette.tolist(), "cmin": lo, "cmax": hi, "title": title,
                               "index": base64.b64encode(index.astype("<u2").tobytes()).decode(),
                               "ticks": list(range(int(hi + 0.5))) if fld.discrete else None,
                               "colorscale": _colorscale(fld, lo, hi), "label": fld.label,
                               "cells_trace": cells_trace, "bar_trace": bar_trace}
    fig.update_layout(scene=dict(aspectmode="data", xaxis_title="x (m)", yaxis_title="y (m)",
                                 zaxis_title="z (m)", camera=dict(eye=dict(x=1.1, y=-1.6, z=0.9))),
                      height=720, margin=dict(l=0, r=0, t=10, b=0), legend=dict(x=0, y=1))
    return fig, fields


def _table(rows: list[dict], caption: str = "") -> str:
    """An HTML table of dicts (nested dicts flattened to 'a.b' columns)."""
    def flat(d, prefix=""):
        out = {}
        for k, v in d.items():
            if isinstance(v, dict):
                out |= flat(v, f"{prefix}{k}.")
            else:
                out[f"{prefix}{k}"] = v
        return out

    rows = [flat(r) for r in rows[:MAX_TABLE_ROWS]]
    cols = list(dict.fromkeys(k for r in rows for k in r))

    def cell(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, list):
            return html.escape(", ".join(cell(x) for x in v))
        return html.escape("" if v is None else str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{cell(r.get(c))}</td>" for c in cols) + "</tr>"
                   for r in rows)
    cap = f"<caption>{html.escape(caption)}</caption>" if caption else ""
    return f"<table>{cap}<tr>{head}</tr>{body}</table>"


def _regions_table(summary: dict) -> str:
    rows = [{"region": name, **{k: v for k, v in r.items() if k != "cameras"}}
            for name, r in summary.get("regions", {}).items()]
    return _table(rows)


def _calibration_table(summary: dict) -> str:
    """Per region, p50 / p95 of the calibration-induced errors (systematic: the same in every load
    step) beside the image noise's (random, per step), from summary.json's "calibration"."""
    cal = summary["calibration"]
    keys = (("calibration_displacement_um", "calibration u (µm)"),
            ("noise_displacement_um", "noise u (µm)"),
            ("calibration_strain_microstrain", "calibration strain (µε)"),
            ("noise_strain_microstrain", "noise strain (µε)"),
            ("calibration_strain_per_unit_strain", "calibration strain per unit strain"))
    rows = [{"region": name, **{f"{label} p50 / p95": [r[k]["p50"], r[k]["p95"]] for k, label in keys}}
            for name, r in cal.get("regions", {}).items()]
    level = next(iter(cal.get("regions", {}).values()), {})
    caption = (f"at the test's strain {level.get('test_strain', '?')} and displacement "
               f"{level.get('test_displacement_mm', '?')} mm; calibration of {cal.get('images')} "
               f"images, corner noise {cal.get('sigma_det_px')} px ({cal.get('sigma_det_from')}); "
               "pairs " + ", ".join(cal.get("pairs", [])))
    return _table(rows, caption)


SHOWN_JSON = ("summary.json", "summary_before.json", "summary_after.json", "constraints.json",
              "layout.json", "design.json")
COMPARED = (("sigma_max_um", "p95", "σ_max p95 (µm)"), ("sigma_max_um", "max", "σ_max max (µm)"),
            ("seen_by_2_or_more", None, "seen by ≥ 2"), ("unmeasured_fraction", None, "unmeasured"))


def _compare_table(before: dict, after: dict) -> str:
    """Per region: σ_max p95 and max, the fraction seen by >= 2 cameras and the unmeasured
    fraction, before -> after."""
    rows = []
    for name, b in before.get("regions", {}).items():
        a = after.get("regions", {}).get(name, {})
        row = {"region": name}
        for key, sub, label in COMPARED:
            vb, va = b.get(key), a.get(key)
            if sub is not None:
                vb = vb.get(sub) if isinstance(vb, dict) else None
                va = va.get(sub) if isinstance(va, dict) else None
            row[f"{label} before"], row[f"{label} after"] = vb, va
        rows.append(row)
    return _table(rows)


def _design_section(run_dir: Path, data: dict) -> str:
    """`vdo design`'s folder: the problems, the camera-count curve (figure and table), the chosen
    cameras with their bodies and lenses, and the candidate statistics (design.json)."""
    parts = ["<h2>Design</h2>"]
    problems = data.get("problems") or []
    if problems:
        parts.append('<div class="missing"><b>What the design could not meet</b><ul>'
                     + "".join(f"<li>{html.escape(str(p))}</li>" for p in problems) + "</ul></div>")
    scalars = {k: data.get(k) for k in ("candidates", "samples", "selection_spacing_mm",
                                        "inventory", "lenses_mm", "target_sigma_um",
                                        "smallest_count_meeting_target", "coverage_weight", "bound",
                                        "gap_to_bound", "wall_s")}
    parts.append(_table([scalars]))
    if (run_dir / "pareto.png").is_file():
        parts.append("<h3>Cameras needed</h3>" + _image(run_dir / "pareto.png", "pareto.png"))
    if isinstance(data.get("curve"), list):
        parts.append(_table([c for c in data["curve"] if isinstance(c, dict)],
                            "per camera count: σ_max p95 of the worst scored region (µm), area seen "
                            "by its min_cameras, chosen lenses (mm) and bodies, the score, the "
                            "bound no selection of that many cameras can beat and the gap "
                            "1 - bound/score"))
    stats = data.get("statistics") if isinstance(data.get("statistics"), dict) else {}
    if isinstance(stats.get("chosen"), list):
        parts.append("<h3>Chosen cameras and lenses</h3>"
                     + _table([c for c in stats["chosen"] if isinstance(c, dict)]))
    if isinstance(data.get("bodies"), list):
        parts.append("<h3>Inventory</h3>" + _table([b for b in data["bodies"] if isinstance(b, dict)]))
    counts = {k: v for k, v in stats.items() if isinstance(v, dict)}
    if counts:
        parts.append("<h3>Candidates</h3>" + "".join(
            _table([{"": k, **v}], k) for k, v in counts.items())
            + _table([{k: v for k, v in stats.items() if not isinstance(v, (dict, list))}]))
    return "".join(parts)


def _json_section(title: str, data) -> str:
    """A JSON document as tables: its scalars as one key/value table, each list of dicts and each
    dict of dicts as a table of its own."""
    parts = [f"<h3>{html.escape(title)}</h3>"]
    if isinstance(data, list):
        data = {"rows": data}
    if not isinstance(data, dict):
        return parts[0] + f"<pre>{html.escape(json.dumps(data, indent=1))}</pre>"
    scalars = {k: v for k, v in data.items() if not isinstance(v, (dict, list))}
    if scalars:
        parts.append(_table([scalars]))
    for k, v in data.items():
        if k == "regions":
            continue
        if isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            parts.append(_table(v, k))
        elif isinstance(v, dict) and v and all(isinstance(x, dict) for x in v.values()):
            parts.append(_table([{"name": n, **x} for n, x in v.items()], k))
        elif isinstance(v, (dict, list)) and v:
            parts.append(_table([v] if isinstance(v, dict) else [{"values": v}], k))
    return "".join(parts)


def _image(path: Path, alt: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    kind = "png" if path.suffix.lower() == ".png" else "jpeg"
    return (f'<figure><img alt="{html.escape(alt)}" src="data:image/{kind};base64,{data}">'
            f"<figcaption>{html.escape(alt)}</figcaption></figure>")


def _read_json(path: Path, missing: list[str]):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        missing.append(f"{path.name} unreadable ({exc})")
        return None


def kind_of(run_dir: Path) -> str:
    """Which command wrote the folder: design, optimize, sweep, validate, a render's series,
    calibrate, render or evaluate."""
    for kind, markers in KINDS:
        if any((run_dir / m).exists() for m in markers):
            return kind
    return "evaluate"


def write_report(run_dir, static_figures: bool = True) -> Path:
    """Write run_dir/report.html from what the folder holds and return its path; first, with
    `static_figures`, the static 3D figures maps/view3d_*.png (`view3d.write_static`) when the
    folder has samples and not yet these figures."""
    run_dir = Path(run_dir)
    sc = view3d.load(run_dir)
    if static_figures and sc.samples is not None and not list(run_dir.glob("maps/view3d_*.png")):
        view3d.write_static(run_dir, sc)
    kind = kind_of(run_dir)
    missing = [f"{f} ({WHY[f]})" if f in WHY else f for f in EXPECTED[kind]
               if not (run_dir / f).exists()] + sc.unreadable
    summaries = {f: _read_json(run_dir / f, missing) for f in
                 ("summary.json", "summary_before.json", "summary_after.json")
                 if (run_dir / f).is_file()}
    summary = summaries.get("summary.json")
    name = next((d.get("experiment") for d in summaries.values() if isinstance(d, dict)
                 and d.get("experiment")), sc.name or run_dir.name)
    body = [f"<h1>{html.escape(str(name))}</h1>"]
    if summary is not None and summary.get("config"):
        body.append(f"<p>Experiment file <code>{html.escape(str(summary['config']))}</code>.</p>")
    top = len(body)                       # the list of missing files goes here, once complete
    fig, fields = figure(sc)
    if fig.data:
        options = "".join(f'<option value="{k}">{html.escape(f["label"])}</option>'
                          for k, f in fields.items())
        body.append("<h2>3D view</h2>")
        if fields:
            body.append(f'<label>Colour the region samples by <select id="field">{options}'
                        "</select></label> (grey: no value). Drag to turn, scroll to zoom.")
        else:
            body.append('<select id="field" hidden></select>')
        body.append(fig.to_html(include_plotlyjs=True, full_html=False, div_id="view3d",
                                config={"displaylogo": False}))
        payload = json.dumps(fields).replace("</", "<\\/")
        body.append(f'<script type="application/json" id="vdo-fields">{payload}</script>')
        body.append(f"<script>{_SCRIPT}</script>")

    shown = set()
    design = run_dir / "design.json"
    data = _read_json(design, missing) if design.is_file() else None
    if isinstance(data, dict):
        body.append(_design_section(run_dir, data))
        shown.add(run_dir / "pareto.png")
    if summary is not None:
        body.append("<h2>Regions</h2>" + _regions_table(summary))
        if isinstance(summary.get("calibration"), dict):
            body.append("<h2>Calibration-induced errors beside the image noise</h2>"
                        + _calibration_table(summary))
        body.append(_json_section("summary.json", summary))
    layout = run_dir / "layout.json"
    cams = _read_json(layout, []) if layout.is_file() else None
    if isinstance(cams, dict) and isinstance(cams.get("cameras"), list):
        body.append("<h2>Cameras</h2>" + _table([{k: v for k, v in c.items() if k not in ("K", "R", "t")}
                                                 for c in cams["cameras"] if isinstance(c, dict)],
                                                str(cams.get("convention", ""))))
    before, after = summaries.get("summary_before.json"), summaries.get("summary_after.json")
    if isinstance(before, dict) and isinstance(after, dict):
        body.append("<h2>Before and after optimizing</h2>" + _compare_table(before, after))
    for extra in ("summary_before.json", "summary_after.json", "constraints.json"):
        path = run_dir / extra
        data = summaries.get(extra) if extra in summaries else (
            _read_json(path, missing) if path.is_file() else None)
        if isinstance(data, dict):
            body.append(f"<h2>{extra}</h2>" + (_regions_table(data) if "regions" in data else "")
                        + _json_section(extra, data))
    for path in sorted(run_dir.glob("*.json")):
        if path.name not in SHOWN_JSON:
            data = _read_json(path, missing)
            if data is not None:
                body.append(f"<h2>{html.escape(path.name)}</h2>" + _json_section(path.name, data))
    for path in sorted(run_dir.glob("*.csv"), key=lambda p: (p.name != "results.csv", p.name)):
        if path.name in NOT_TABULATED:
            with path.open() as fh:
                rows = sum(1 for _ in fh) - 1
            body.append(f"<h2>{html.escape(path.name)}</h2><p>{rows} rows, one per candidate "
                        "(open the file).</p>")
            continue
        try:
            with path.open(newline="") as fh:
                rows = list(csv.DictReader(fh))
        except (OSError, csv.Error, UnicodeDecodeError) as exc:
            body.append(f'<p class="missing">{html.escape(path.name)} unreadable ({exc})</p>')
            continue
        shown_rows = "" if len(rows) <= MAX_TABLE_ROWS else f", first {MAX_TABLE_ROWS} shown"
        body.append(f"<h2>{html.escape(path.name)} ({len(rows)} rows{shown_rows})</h2>"
                    + _table(rows))

    for title, paths in (("Contact sheet", [run_dir / "contact_sheet.png"]),
                         ("Convergence", [run_dir / "convergence.png"]),
                         ("Figures", sorted(run_dir.glob("*.png")) + sorted(run_dir.glob("figures/*.png"))),
                         ("Maps", sorted((run_dir / "maps").glob("*.png")))):
        imgs = [p for p in paths if p.is_file() and p not in shown]
        if imgs:
            body.append(f"<h2>{title}</h2>" + "".join(_image(p, p.relative_to(run_dir).as_posix())
                                                     for p in imgs))
            shown.update(imgs)
    if missing:
        body.insert(top, f'<div class="missing"><b>Missing from this {kind} run folder</b> (an '
                    "interrupted run?):<ul>" + "".join(f"<li>{html.escape(m)}</li>" for m in missing)
                    + "</ul></div>")
    page = ("<!DOCTYPE html><html><head><meta charset=\"utf-8\">"
            f"<title>vdo report: {html.escape(str(name))}</title><style>{_STYLE}</style></head>"
            f"<body>{''.join(body)}</body></html>")
    out = run_dir / "report.html"
    out.write_text(page, encoding="utf-8")
    log.debug("wrote %s (%.1f MB)", out, out.stat().st_size / 1e6)
    return out
