"""Sweep throughput with 1 and 2 local workers, and the per-point cost beyond one evaluation.

A 12-point sweep (6 lenses x 2 speckle sizes, one patch size so a worker compiles once) of the
built-in 3-camera experiment at 20 mm sample spacing, run by `vdo.commands.sweep.sweep` with 1 and then 2
spawned workers, beside the same evaluation called in this process (warm, median of 3).

* start-up: from the start of the sweep to its first stored point, less that point's own time
  (expanding the points, spawning the workers, importing vdo); first point: that point's own
  time (it compiles);
* steady throughput: points stored per minute after the first stored point;
* per-point overhead (1 worker): the interval between two consecutive stored points, less the
  second point's own time in its worker (hand-over, pickling, the point's JSON and results.csv);
* in-worker time against in-process time: what a point costs in a worker (parse included)
  against one warm evaluation here; CPU s: the worker process's CPU time for a point (all its
  threads), the work a point needs whatever else runs on the machine.

Run: .venv/bin/python benchmarks/sweep.py [--out runs/bench-sweep] [--spacing-mm 20]
The out folder holds the generated sweep file and the two stores (w1/, w2/), replaced each run.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import time
from pathlib import Path

from vdo.commands import sweep as sw
from vdo.config.sweep import expand, load_sweep
from vdo.config.experiment import load, parse
from vdo.core.parallel import configure_worker, cores

ROOT = Path(__file__).resolve().parent.parent
BASE = ROOT / "experiments" / "beam_column" / "three_cameras.toml"
SWEEP = """[sweep]
name = "benchmark"
experiment = "{base}"
[[axis]]
path = "evaluation.sample_spacing_mm"
values = [{spacing}]
[[axis]]
path = "camera.*.focal_mm"
values = [20, 24, 28, 35, 42, 50]
[[axis]]
path = "speckle.dot_diameter_mm"
values = [1.5, 2.5]
"""


def stored(folder: Path) -> list[tuple[float, float, float]]:
    """(time the sweep stored it, seconds in its worker, CPU seconds of its worker process) per
    point, in storing order."""
    out = []
    for f in (folder / "points").glob("*.json"):
        record = json.loads(f.read_text())
        out.append((f.stat().st_mtime, record["seconds"], record["cpu_seconds"]))
    return sorted(out)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-sweep")
    parser.add_argument("--spacing-mm", type=float, default=20)
    args = parser.parse_args()
    out = args.out.resolve()
    if out.exists() and any(out.iterdir()) and not (out / "bench-sweep.toml").is_file():
        raise SystemExit(f"{out} holds other files; give a new --out folder")
    out.mkdir(parents=True, exist_ok=True)
    file = out / "bench-sweep.toml"
    file.write_text(SWEEP.format(base=BASE, spacing=args.spacing_mm))
    spec = load_sweep(file)
    points = expand(spec)

    exp = load(BASE)
    first = parse(points[0].config, BASE)
    configure_worker(None)
    here, here_cpu = [], []
    for _ in range(4):                                   # the first call compiles
        start, cpu = time.perf_counter(), time.process_time()
        sw._evaluation(first)
        here.append(time.perf_counter() - start)
        here_cpu.append(time.process_time() - cpu)
    one = statistics.median(here[1:])
    print(f"base experiment       {exp.path.name} ({len(exp.camera_specs)} cameras), "
          f"{args.spacing_mm:g} mm spacing, {len(points)} points")
    print(f"cpu cores             {cores()}")
    print(f"one evaluation here   {one:.2f} s warm, {statistics.median(here_cpu[1:]):.2f} CPU s "
          f"(median of 3; first call {here[0]:.1f} s)")
    print(f"{'workers':>7} {'wall s':>7} {'start-up s':>10} {'first pt s':>10} "
          f"{'steady pts/min':>15} {'in-worker s':>11} {'CPU s':>6} {'overhead ms':>11}")
    rates = {}
    for workers in (1, 2):
        folder = out / f"w{workers}"
        shutil.rmtree(folder, ignore_errors=True)
        start = time.time()
        result = sw.sweep(spec, folder, workers=workers)
        wall = time.time() - start
        assert result["done"] == len(points), result
        times = stored(folder)
        startup = times[0][0] - start - times[0][1]
        steady = (len(times) - 1) / (times[-1][0] - times[0][0]) * 60
        in_worker = statistics.median(s for _, s, _ in times[1:])
        cpu = statistics.median(c for _, _, c in times[1:])
        overhead = (statistics.median((t1 - t0) - s for (t0, _, _), (t1, s, _) in zip(times, times[1:]))
                    if workers == 1 else float("nan"))
        rates[workers] = steady
        print(f"{workers:>7} {wall:>7.1f} {startup:>10.1f} {times[0][1]:>10.1f} {steady:>15.1f} "
              f"{in_worker:>11.2f} {cpu:>6.2f} {overhead * 1e3:>11.0f}")
    print(f"steady speed-up, 2 workers against 1: {rates[2] / rates[1]:.2f}x")


if __name__ == "__main__":
    main()
