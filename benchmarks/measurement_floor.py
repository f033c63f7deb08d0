"""The design checks' speckle models per footprint: `vdo.model.interpolant.interpolation_error` (the
interpolation floor) and `vdo.model.interpolant.correlation_error` (what the lab's correlation
measures: bias, noise and scatter over 8 x 8 sub-pixel positions), on the built-in experiment's
pattern, at footprints spread like the camera-region pairs of `vdo evaluate` (2.5-5 px per mm).

Baseline in the same run: one footprint of each model computed alone (a fresh cache), against
the per-footprint cost of a batch of K footprints (the spectrum of the tile is shared by a batch;
`correlation_error` keeps each footprint's terms, so a second call on the same footprints costs
nothing: shown too). benchmarks/README.md, "Design checks", has the figures before and after the
vectorisation of both models.

Run from the repository root: python benchmarks/measurement_floor.py [--footprints 20]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vdo.config.experiment import load
from vdo.model import interpolant, speckle


def footprints(k: int) -> np.ndarray:
    """K pixel footprints (K, 2, 2) m: 2.5-5 px per mm, slightly sheared."""
    density = np.linspace(2500.0, 5000.0, k)
    return np.linalg.inv(np.stack([np.array([[d, 0.05 * d], [0.02 * d, 1.05 * d]]) for d in density]))


def timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--footprints", type=int, default=20)
    args = ap.parse_args(argv)
    exp = load("experiments/beam_column/ten_cameras.toml")
    f = speckle.normalise(speckle.pattern_for(exp.speckle))
    sides = footprints(args.footprints)
    texel = exp.speckle.texel
    interpolant.interpolation_error(f, texel, sides[:1])          # imports and first calls
    one_ie = timed(lambda: interpolant.interpolation_error(f, texel, sides[:1]))
    batch_ie = timed(lambda: interpolant.interpolation_error(f, texel, sides)) / len(sides)
    interpolant.correlation_error(f, texel, footprints(1) * 1.01)   # warm-up on another footprint
    one_ce = timed(lambda: interpolant.correlation_error(f, texel, sides[:1]))
    batch_ce = timed(lambda: interpolant.correlation_error(f, texel, sides[1:])) / (len(sides) - 1)
    again_ce = timed(lambda: interpolant.correlation_error(f, texel, sides)) / len(sides)
    print(f"pattern {f.shape[0]} x {f.shape[1]} texels, {len(sides)} footprints\n")
    print("| model | one footprint alone (ms) | per footprint in a batch (ms) | cached (ms) |")
    print("|---|---|---|---|")
    print(f"| interpolation_error | {1e3 * one_ie:.1f} | {1e3 * batch_ie:.1f} | — |")
    print(f"| correlation_error | {1e3 * one_ce:.0f} | {1e3 * batch_ce:.0f} | {1e3 * again_ce:.2f} |")


if __name__ == "__main__":
    main()
