"""A lens study: judge one camera layout with each lens of a catalogue, from Python.

    python docs/examples/lens_study.py [EXPERIMENT.toml] [--lenses-mm 25 35 50] [--spacing-mm 20]
                                       [--csv lens_study.csv]

Every camera takes the same lens (`Experiment.with_camera(name, focal_mm=...)`: checked as the
file is); the geometry is prepared once and reused (a lens does not change it); each layout is
judged with `vdo.layout_state(geometry, experiment)` and summarised per region
(`LayoutState.regions()`, units in the names). Prints one row per (lens, region) and writes them
as a CSV (`vdo.write_csv`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import vdo

HERE = Path(__file__).resolve().parent
DEFAULT = HERE.parent.parent / "experiments" / "beam_column" / "three_cameras.toml"


@dataclasses.dataclass(frozen=True)
class LensRow:
    """One region under one lens."""

    focal_mm: float
    stats: vdo.RegionStats

    def to_dict(self) -> dict:
        return {"focal_mm": self.focal_mm} | self.stats.to_dict()


def main(argv=None) -> list[LensRow]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(DEFAULT))
    parser.add_argument("--lenses-mm", type=float, nargs="+", default=[25.0, 35.0, 50.0])
    parser.add_argument("--spacing-mm", type=float, default=20.0, help="surface sample spacing")
    parser.add_argument("--csv", type=Path, default=None, help="write the rows here")
    args = parser.parse_args(argv)

    vdo.configure()
    exp = vdo.load(args.config).with_settings(evaluation={"sample_spacing_mm": args.spacing_mm})
    geometry = vdo.prepare(exp)                        # meshes and samples: once
    rows = []
    for focal in args.lenses_mm:
        variant = exp
        for spec in exp.camera_specs:                   # every camera takes this lens
            variant = variant.with_camera(spec.name, focal_mm=focal)
        state = vdo.layout_state(geometry, variant)     # judged with the variant's cameras
        rows += [LensRow(focal, stats) for stats in state.regions()]
    print(f"{exp.name}: {len(geometry.samples):,} samples, {len(exp.camera_specs)} cameras")
    print(f"{'lens':>6}  {'region':<20}{'covered':>9}{'σ_max p95 µm':>14}{'σ_z p95 µm':>12}")
    fmt = lambda x: "-" if x is None else f"{x:.3f}"  # noqa: E731 (None: no sample measured)
    for r in rows:
        s = r.stats
        print(f"{r.focal_mm:>4g}mm  {s.region:<20}{100 * s.covered_fraction:>8.0f}%"
              f"{fmt(s.sigma_max_um_p95):>14}{fmt(s.sigma_z_um_p95):>12}")
    if args.csv is not None:
        vdo.write_csv(args.csv, rows)
    return rows


if __name__ == "__main__":
    try:
        main()
    except vdo.ConfigError as err:       # a user mistake: one line, as vdo's commands print it
        sys.exit(f"error: {err}")
