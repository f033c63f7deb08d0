"""What tripods ([mount.tripod]) add to one visibility refresh of `vdo optimize` on the steel beam.

A refresh (`vdo.search.problem.Problem.refresh`) is `layout_state` without the prediction (the ray cast
of every camera and sample, the lighting cast again where a camera or tripod may be in the way)
plus the same ray cast against the obstacles alone. Both are timed here on the hand layout of
experiments/steel_beam/four_point_bending.toml, with its tripods and with them removed, in the
same run. Run: .venv/bin/python benchmarks/tripods.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

from vdo.config import experiment as config
from vdo.core.configure import configure
from vdo.scene import build_scene, cameras_of
from vdo.state import bodies, layout_state, prepare, unobstructed_lighting
from vdo.physics.visibility import compute_visibility

ROOT = Path(__file__).resolve().parent.parent


def refresh_seconds(exp, geometry, unobstructed, repeats: int) -> tuple[list[float], int]:
    """Wall times of `repeats` refreshes of the hand layout, and the number of moving obstacles."""
    cameras = cameras_of(exp.camera_specs, exp.rails)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        layout_state(geometry, cameras, predict_fields=False, unobstructed=unobstructed)
        obstacles = build_scene([m for m in geometry.meshes if m.role != "specimen"] + bodies(exp, cameras))
        compute_visibility(obstacles, cameras, geometry.samples, exp.evaluation.incidence_limit,
                           progress=False)
        times.append(time.perf_counter() - t0)
    return times, len(bodies(exp, cameras))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    configure()
    with_tripods = config.load(ROOT / "experiments/steel_beam/four_point_bending.toml")
    assert any(m.tripod is not None for m in with_tripods.mounts), "the steel beam has no tripods"
    without = dataclasses.replace(with_tripods, mounts=tuple(dataclasses.replace(m, tripod=None)
                                                              for m in with_tripods.mounts))
    geometry = prepare(with_tripods)
    unobstructed = unobstructed_lighting(geometry)
    print(f"samples               {len(geometry.samples):,}, {len(with_tripods.camera_specs)} cameras, "
          f"{len(with_tripods.lights)} lights")
    refresh_seconds(with_tripods, geometry, unobstructed, 1)          # compile the kernels once
    rows = {}
    for _ in range(2):                                                # interleaved against load drift
        for name, exp in (("without tripods", without), ("with tripods", with_tripods)):
            times, parts = refresh_seconds(exp, dataclasses.replace(geometry, experiment=exp),
                                           unobstructed, args.repeats)
            rows.setdefault(name, ([], parts))[0].extend(times)
    for name, (times, parts) in rows.items():
        print(f"{name:<21} {statistics.median(times) * 1e3:7.1f} ms median of {len(times)} "
              f"(min {min(times) * 1e3:.1f}), {parts} moving obstacle meshes")
    ratio = statistics.median(rows["with tripods"][0]) / statistics.median(rows["without tripods"][0])
    print(f"ratio                 {ratio:.2f}x")


if __name__ == "__main__":
    main()
