"""Point-in-zone tests of floor-polygon zones: the grid of `vdo optimize`'s start-up
(`vdo.search.problem.Problem`'s mount paths: each moving zone camera's bounding box on a 5 cm grid,
kept where it lies on the polygon within 5 cm), one point at a time (`MountSpec.inside` on a
(2,) point, as before) against all points in one call ((M, 2), vectorised), in the same run, on
the zones of experiments/pressure_vessel/design.toml. Both must agree point for point.
Run: .venv/bin/python benchmarks/floor_zones.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from vdo.config import experiment as config

ROOT = Path(__file__).resolve().parent.parent
GRID_M = 0.05      # the optimizer's zone grid spacing
TOL_M = 0.05       # and its tolerance on the polygon's edge


def grid(zone) -> np.ndarray:
    lo, hi = zone.low, zone.high
    axes = [np.linspace(lo[k], hi[k], max(2, int(np.ceil((hi[k] - lo[k]) / GRID_M)) + 1))
            for k in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)[:, :2]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(ROOT / "experiments/pressure_vessel/design.toml"))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    exp = config.load(args.config)
    zones = [m for m in exp.mounts if m.kind == "zone" and m.floor is not None]
    points = [grid(z) for z in zones]
    total = sum(len(p) for p in points)
    one, batch = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        a = [np.array([z.inside(q, tol=TOL_M) for q in p]) for z, p in zip(zones, points)]
        one.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        b = [z.inside(p, tol=TOL_M) for z, p in zip(zones, points)]
        batch.append(time.perf_counter() - t0)
        assert all(np.array_equal(x, y) for x, y in zip(a, b)), "the two ways disagree"
    print(f"{len(zones)} floor zones, {total:,} grid points, {sum(int(x.sum()) for x in b):,} on the floors")
    print(f"one point at a time   {statistics.median(one):8.3f} s median of {args.repeats}")
    print(f"all points at once    {statistics.median(batch):8.3f} s median of {args.repeats}")
    print(f"ratio                 {statistics.median(one) / statistics.median(batch):8.0f}x")


if __name__ == "__main__":
    main()
