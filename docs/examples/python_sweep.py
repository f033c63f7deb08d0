"""A batch of variants as a Python sweep: camera positions and lenses built in code, run by the
sweep engine of `vdo sweep` (resumable: a second run reuses every stored point).

    python docs/examples/python_sweep.py [EXPERIMENT.toml] --out runs/variants
                                         [--spacing-mm 20] [--workers 1] [--dask local]

Each variant moves one camera along its rail (`Experiment.with_camera(name, u=...)`, re-aimed as
`vdo optimize` does: `Geometry.with_camera`) and gives it a lens; `vdo.sweep_variants` evaluates
them in a local pool of processes (or on Dask) into a store whose results.csv has one row each.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import vdo

HERE = Path(__file__).resolve().parent
DEFAULT = HERE.parent.parent / "experiments" / "beam_column" / "three_cameras.toml"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(DEFAULT))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--spacing-mm", type=float, default=20.0)
    parser.add_argument("--camera", default=None, help="the camera that moves (default: the first on a rail)")
    parser.add_argument("--u", type=float, nargs="+", default=[0.3, 0.5, 0.7])
    parser.add_argument("--lenses-mm", type=float, nargs="+", default=[25.0, 35.0])
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--dask", default=None, help='"local" or a scheduler address')
    args = parser.parse_args(argv)

    vdo.configure()
    exp = vdo.load(args.config).with_settings(evaluation={"sample_spacing_mm": args.spacing_mm})
    geometry = vdo.prepare(exp)                     # its centre: where a moved camera keeps aiming
    camera = args.camera or next(s.name for s in exp.camera_specs if s.rail is not None)
    variants = [({"u": u, "focal_mm": focal}, geometry.with_camera(camera, u=u, focal_mm=focal))
                for u, focal in itertools.product(args.u, args.lenses_mm)]
    result = vdo.sweep_variants(variants, args.out, workers=args.workers, dask=args.dask,
                                name=f"{exp.name}: {camera} along its rail")
    region = exp.regions[0].name
    print(f"{len(variants)} variants of {camera}: {result['computed']} computed, "
          f"{result['reused']} reused from {args.out.name}")
    print(f"{'u':>6}{'lens':>8}{f'{region} σ p95 µm':>22}{'seen by ≥ 2':>13}")
    for row in result["rows"]:
        sigma = row.get(f"{region}.sigma_p95_um")
        print(f"{row['u']:>6g}{row['focal_mm']:>6g}mm{'-' if sigma is None else f'{sigma:.3f}':>22}"
              f"{100 * row.get(f'{region}.seen_2', 0):>12.0f}%")
    return result


if __name__ == "__main__":
    try:
        main()
    except vdo.ConfigError as err:       # a user mistake: one line, as vdo's commands print it
        sys.exit(f"error: {err}")
