"""Judge a camera layout from Python, then move one camera and judge it again.

    python docs/examples/compare_layouts.py [EXPERIMENT.toml] [--spacing-mm 20]

Uses vdo's public API only: load -> prepare (meshes, samples; once) -> layout_state (per layout)
-> summary. Prints each region's coverage and sigma_max p95 for both layouts.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

import vdo

HERE = Path(__file__).resolve().parent
DEFAULT = HERE.parent.parent / "experiments" / "beam_column" / "three_cameras.toml"


def table(summary: dict) -> dict:
    """region -> (fraction seen by >= 2 cameras, sigma_max p95 in um)."""
    return {name: (r["seen_by_2_or_more"], r["sigma_max_um"]["p95"])
            for name, r in summary["regions"].items()}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(DEFAULT))
    parser.add_argument("--spacing-mm", type=float, default=20.0, help="surface sample spacing")
    args = parser.parse_args(argv)

    vdo.configure()
    exp = vdo.load(args.config)
    exp = dataclasses.replace(exp, evaluation=dataclasses.replace(
        exp.evaluation, sample_spacing=args.spacing_mm * 1e-3))
    geometry = vdo.prepare(exp)                      # camera-independent: done once
    before = vdo.layout_state(geometry)              # the layout of the file

    # Raise the first camera by 10 cm (same pan and tilt): a new pose, the same geometry.
    cameras = list(before.cameras)
    first = cameras[0]
    cameras[0] = dataclasses.replace(first, position=np.asarray(first.position) + [0.0, 0.0, 0.1])
    after = vdo.layout_state(geometry, cameras)

    rows = {"before": table(vdo.summary(before)), "after": table(vdo.summary(after))}
    print(f"{exp.name}: {len(geometry.samples):,} samples; {first.name} raised by 0.1 m")
    print(f"{'region':<24}{'>=2 cams before/after':>24}{'sigma p95 um before/after':>28}")
    for name in rows["before"]:
        (c0, s0), (c1, s1) = rows["before"][name], rows["after"][name]
        fmt = lambda s: "-" if s is None else f"{s:.3f}"  # noqa: E731 (unmeasured: None)
        print(f"{name:<24}{f'{100 * c0:.0f}% / {100 * c1:.0f}%':>24}{f'{fmt(s0)} / {fmt(s1)}':>28}")
    return rows


if __name__ == "__main__":
    try:
        main()
    except vdo.ConfigError as err:       # a user mistake: one line, as vdo's commands print it
        sys.exit(f"error: {err}")
