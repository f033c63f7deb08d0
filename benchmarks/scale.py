"""Scale benchmark (benchmarks/README.md, "Scale"): `vdo evaluate` and `vdo design` on a generated
large experiment (benchmarks/scale_case.py: a box girder several metres long, cameras on floor
tripod zones on both sides and an overhead rail, 4 x segments regions), growing one axis at a
time: samples (evaluate's spacing), regions (segments, samples fixed), cameras, and candidates
(design's grid). Every run is a fresh `python -m vdo ...` under `/usr/bin/time -v`: wall time,
CPU time (user + sys; the machine may be shared, so wall time alone says little) and peak
resident memory. Writes scale.csv and scale.png into --out and prints the table.

Run from the repository root:  python benchmarks/scale.py --out /tmp/scale [--quick]
[--axes samples regions ...] [--pick samples=0,3 regions=0,3]
(--axes full: the full-size design alone, 50,784 candidates and 98,280 samples;
--quick: the smallest case of each axis and the largest of samples and candidates only;
--pick: these runs of an axis).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale_case import write_case  # noqa: E402

from vdo import scene  # noqa: E402
from vdo.config import experiment as config  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
BASE = dict(length_m=6.0, segments=60, cameras=12, spacing_mm=20.0)
AXES = {   # axis: (case parameters of each run, the command)
    "samples": [dict(spacing_mm=s) for s in (40, 20, 14, 11)],
    "regions": [dict(segments=s) for s in (6, 30, 60, 120)],
    "cameras": [dict(cameras=c) for c in (4, 8, 12, 16)],
    "candidates": [dict(zone_points=p, zone_heights=h, lenses_mm=lens, design_spacing_mm=40)
                   for p, h, lens in ((2, 2, (8,)), (3, 2, (8, 16)), (4, 2, (8, 12, 16)))],
    # the full size: 50,784 candidates judged at 40 mm, the designed layout judged at 11 mm (98,280
    # samples); the bound 10 s per camera count (its default is 60)
    "full": [dict(spacing_mm=11, zone_points=4, zone_heights=2, rail_positions=24, lenses_mm=(8, 12),
                  design_spacing_mm=40, bound_s=10)],
}


def timed(args: list[str], cwd: Path, root: Path = ROOT) -> dict:
    """Run `python -m vdo ARGS` (the vdo of the checkout `root`) under /usr/bin/time -v: wall s,
    cpu s (user + sys), peak RSS GB."""
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "vdo", *args]
    env = dict(os.environ, PYTHONPATH=str(root))
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    err = proc.stderr
    field = lambda name: re.search(rf"{name}: (.+)", err)[1]          # noqa: E731
    h, m, s = (["0"] + field(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\)").split(":"))[-3:]
    return {"status": proc.returncode, "wall_s": 3600 * float(h) + 60 * float(m) + float(s),
            "cpu_s": float(field(r"User time \(seconds\)")) + float(field(r"System time \(seconds\)")),
            "peak_gb": int(field(r"Maximum resident set size \(kbytes\)")) * 1024 / 1e9,
            "error": "" if proc.returncode == 0 else err.strip().splitlines()[0][:200]}


def run(axis: str, params: dict, folder: Path, root: Path = ROOT) -> dict:
    case = {**BASE, **params}
    path = write_case(folder, **case)
    out = folder / "out"
    if axis in ("candidates", "full"):
        r = timed(["design", str(path), "--out", str(out), "--overwrite", "--quiet"], folder, root)
        info = json.loads((out / "design.json").read_text()) if r["status"] == 0 else {}
        est, got = info.get("estimate", {}), info.get("measured", {})
        r |= {"samples": info.get("samples"), "candidates": got.get("candidates"),
              "stored_pairs": got.get("entries"), "estimate_gb": est.get("memory_gb"),
              "search_peak_gb": got.get("peak_memory_gb"), "judge_s": got.get("judge_s"),
              "search_s": got.get("search_s"), "estimate_judge_s": est.get("judge_s"),
              "estimate_search_s": est.get("search_s")}
    else:
        r = timed(["evaluate", str(path), "--out", str(out), "--overwrite", "--quiet"], folder, root)
        exp = config.load(path)
        meshes = scene.load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                                   rails=exp.rails, mounts=exp.mounts, path=exp.path)
        r |= {"samples": len(scene.sample_regions(meshes, mesh_specs=exp.meshes, regions=exp.regions,
                                                  spacing=exp.evaluation.sample_spacing, path=exp.path))}
    return {"axis": axis, "root": str(root), "regions": 4 * case["segments"], "cameras": case["cameras"],
            "spacing_mm": case["spacing_mm"], **r}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--root", type=Path, default=ROOT,
                        help="the checkout whose vdo runs (another release, for a before/after)")
    parser.add_argument("--axes", nargs="*", default=[a for a in AXES if a != "full"],
                        help="default: every axis but 'full' (the full-size design, ~7 min)")
    parser.add_argument("--pick", nargs="*", default=[], metavar="AXIS=I,J",
                        help="run only these runs of an axis (indices into AXES[axis])")
    args = parser.parse_args()
    pick = {a: [int(i) for i in v.split(",")] for a, v in (p.split("=") for p in args.pick)}
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for axis in args.axes:
        runs = AXES[axis]
        if axis in pick:
            runs = [runs[i] for i in pick[axis]]
        elif args.quick:
            runs = [runs[0], runs[-1]] if axis in ("samples", "candidates") else [runs[0]]
        for params in runs:
            with tempfile.TemporaryDirectory() as tmp:
                rows.append(run(axis, params, Path(tmp), args.root))
            print(json.dumps(rows[-1]), flush=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(args.out / "scale.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    plot(rows, args.out / "scale.png")


def plot(rows: list[dict], path: Path) -> None:
    axes_x = {"samples": "samples", "regions": "regions", "cameras": "cameras", "candidates": "candidates",
              "full": "candidates"}
    present = [a for a in axes_x if any(r["axis"] == a and r["status"] == 0 for r in rows)]
    if not present:
        print(f"no run succeeded: no figure ({path})")
        return
    fig, axs = plt.subplots(2, len(present), figsize=(3.6 * len(present), 5.5), layout="constrained",
                            squeeze=False)
    for k, axis in enumerate(present):
        ok = [r for r in rows if r["axis"] == axis and r["status"] == 0 and r.get(axes_x[axis])]
        sel = [r for r in ok if r.get("root", str(ROOT)) == str(ROOT)]
        other = [r for r in ok if r not in sel]            # another checkout's (--root): before
        if other:
            axs[0, k].plot([r[axes_x[axis]] for r in other], [r["cpu_s"] for r in other], "kx",
                           label="CPU, before (--root)")
            axs[1, k].plot([r[axes_x[axis]] for r in other], [r["peak_gb"] for r in other], "kx")
        x = [r[axes_x[axis]] for r in sel]
        what = "design" if axis in ("candidates", "full") else "evaluate"
        axs[0, k].plot(x, [r["wall_s"] for r in sel], "o-", label="wall")
        axs[0, k].plot(x, [r["cpu_s"] for r in sel], "s--", label="CPU (user + sys)")
        axs[0, k].set_title(f"{what} vs {axes_x[axis]}", fontsize=10)
        axs[0, k].set_ylabel("s")
        axs[0, k].legend(fontsize=7)
        axs[1, k].plot(x, [r["peak_gb"] for r in sel], "o-", color="C2", label="peak RSS")
        if axis in ("candidates", "full"):
            axs[1, k].plot(x, [r["estimate_gb"] for r in sel], "^:", color="C3", label="estimated")
            axs[1, k].plot(x, [r["search_peak_gb"] for r in sel], "v-", color="C4", label="peak to the search end")
            axs[1, k].legend(fontsize=7)
        axs[1, k].set_ylabel("GB")
        axs[1, k].set_xlabel(axes_x[axis])
        axs[1, k].set_ylim(bottom=0)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
