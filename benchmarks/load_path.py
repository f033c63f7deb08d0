"""Cost of evaluating a layout over a load path against the number of keyframes.

Evaluates the built-in 10-camera experiment over the first K steps of its load path for several
K, and prints the wall time, the time per keyframe and a least-squares line t = a + b K (the fixed
cost a: meshes, samples, speckle; b per keyframe: ray cast, lighting, prediction). The first run
compiles the prediction and is not timed. Then the part the optimizer pays at each visibility
refresh for scoring over the path: `vdo.search.loadpath.path_occlusion` (one ray cast per keyframe, no
lighting, no prediction) at the keyframes `keyframe_steps` picks, beside the rest state's cast.
Run: .venv/bin/python benchmarks/load_path.py [--spacing-mm 10] [--counts 1 4 8 16 24]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

import vdo
from vdo.geometry.keyframes import load_path_of
from vdo.search.loadpath import evaluate_load_path, keyframe_steps, path_occlusion
from vdo.state import layout_state
from vdo.scene import cameras_of

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacing-mm", type=float, default=10.0)
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 4, 8, 16, 24])
    args = parser.parse_args()
    vdo.configure()
    exp = vdo.load(ROOT / "experiments" / "beam_column" / "ten_cameras.toml")
    exp = dataclasses.replace(exp, evaluation=dataclasses.replace(
        exp.evaluation, sample_spacing=args.spacing_mm * 1e-3))
    geometry = vdo.prepare(exp)
    full = load_path_of(geometry.meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes, groups=exp.groups)
    evaluate_load_path(geometry, dataclasses.replace(full, steps=full.steps[:1]))     # compile
    print(f"samples               {len(geometry.samples):,} ({args.spacing_mm:g} mm spacing), "
          f"{len(exp.camera_specs)} cameras, {len(full.steps)} steps in the load path")
    counts, seconds = [], []
    for k in args.counts:
        path = dataclasses.replace(full, steps=full.steps[:k])
        t0 = time.perf_counter()
        evaluate_load_path(geometry, path)
        dt = time.perf_counter() - t0
        counts.append(k + 1)            # the rest state is judged too
        seconds.append(dt)
        print(f"{k:3d} steps (+ rest)     {dt:6.2f} s   {dt / (k + 1):.3f} s per keyframe")
    b, a = np.polyfit(counts, seconds, 1)
    residual = np.max(np.abs(np.polyval([b, a], counts) - seconds) / np.asarray(seconds))
    print(f"fit t = a + b K        a = {a:.2f} s, b = {b:.3f} s per keyframe "
          f"(largest deviation from the line {100 * residual:.0f} %)")
    cameras = cameras_of(exp.camera_specs, exp.rails)
    t0 = time.perf_counter()
    layout_state(geometry, cameras, predict_fields=False)
    rest = time.perf_counter() - t0
    print(f"optimizer refresh: rest ray cast + lighting {rest:.2f} s")
    for k in (1, 4, 8):
        steps = keyframe_steps(full, k)
        t0 = time.perf_counter()
        held = path_occlusion(geometry, full, cameras, steps)
        dt = time.perf_counter() - t0
        print(f"  path_occlusion, {k} keyframes {steps}: {dt:.2f} s ({dt / k:.3f} s each); "
              f"{int(held.sum()):,} of {held.size:,} (camera, sample) views hold over them")


if __name__ == "__main__":
    main()
