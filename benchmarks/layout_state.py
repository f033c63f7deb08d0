"""Cost of `vdo.layout_state` over new camera positions, and the JAX compilations each runs.

    python benchmarks/layout_state.py [EXPERIMENT.toml] [--spacing-mm 10] [--positions 50]
                                      [--camera cam1]

The first camera on a rail (or --camera) is slid to `--positions` rail parameters evenly spread
over 0.05..0.95 (each re-aimed as `vdo optimize` does) and judged on one prepared geometry.
Prints per layout the wall and CPU seconds and the compilations (XLA compiles and loads from the
persistent compilation cache, counted with `jax.monitoring`), then the summary. (The commit
before the fixed pair-list sizes, `Geometry.sizes`, runs it too: the figures of before.)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

import vdo

DEFAULT = Path(__file__).resolve().parents[1] / "experiments" / "beam_column" / "three_cameras.toml"
COUNTED = ("/jax/core/compile/backend_compile_duration", "/jax/compilation_cache/cache_retrieval_time_sec")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(DEFAULT))
    parser.add_argument("--spacing-mm", type=float, default=10.0)
    parser.add_argument("--positions", type=int, default=50)
    parser.add_argument("--camera", default=None)
    args = parser.parse_args(argv)
    vdo.configure()
    compiles = [0]
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: compiles.__setitem__(0, compiles[0] + (name in COUNTED)))
    exp = vdo.load(args.config).with_settings(evaluation={"sample_spacing_mm": args.spacing_mm})
    geometry = vdo.prepare(exp)
    camera = args.camera or next(s.name for s in exp.camera_specs if s.rail is not None)
    rows = []
    for k, u in enumerate(np.linspace(0.05, 0.95, args.positions)):
        variant = geometry.with_camera(camera, u=float(u))
        before, t, c = compiles[0], time.perf_counter(), time.process_time()
        vdo.layout_state(geometry, variant)
        rows.append((time.perf_counter() - t, time.process_time() - c, compiles[0] - before))
        print(f"{k:3d}  u = {u:.3f}  wall {rows[-1][0]:.3f} s  cpu {rows[-1][1]:.3f} s  "
              f"compilations {rows[-1][2]}", flush=True)
    wall, cpu, comp = (np.array(x) for x in zip(*rows))
    print(f"{exp.name}, {len(geometry.samples):,} samples, {camera} at {args.positions} rail positions:")
    print(f"first layout: {wall[0]:.2f} s wall, {comp[0]} compilations")
    print(f"after it: median {np.median(wall[1:]):.3f} s wall (max {wall[1:].max():.3f}), median "
          f"{np.median(cpu[1:]):.3f} s CPU; compilations after the first: {comp[1:].sum()}")
    return {"wall": wall, "cpu": cpu, "compilations": comp}


if __name__ == "__main__":
    main()
