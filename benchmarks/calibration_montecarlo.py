"""Monte Carlo of calibrations against the predicted covariance (docs/calibration.md, "How well
the predicted covariance holds"): the holed plate's stereo pair and a 4-camera rig (the pair
plus two cameras 0.25 m above it, calibrated together), `--trials` calibrations each with
independent N(0, sigma^2) corner noise (`vdo.calib.montecarlo.run`). Prints, per rig, every
parameter's ratio observed scatter / predicted sigma, the displacement and strain ratios,
sqrt(NEES), and the 95 % interval of a ratio for the trial count (sample sd over true sd:
sqrt(chi2_{n-1, q} / (n - 1)), q = 0.025, 0.975), of one and (Bonferroni, q = 0.025 / P) of all P
ratios at once.

With `--workers W` (W >= 2) each rig's trials also run on a local pool of W spawned processes
(`run(..., workers=W)`, `vdo.core.parallel`) in the same run: the wall times serial and pooled
(start-up of the pool included) and whether the two results are the same to the last bit.

Run from the repository root:  python benchmarks/calibration_montecarlo.py [--trials 200] [--workers 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from vdo.calib import montecarlo as mc  # noqa: E402
from vdo.calib import propagate as prop  # noqa: E402
from vdo.calib.session import plan  # noqa: E402
from vdo.config.experiment import load, parse  # noqa: E402

HOLED = ROOT / "experiments" / "holed_plate" / "stereo.toml"
ABOVE_M = 0.25       # the 4-camera rig's upper pair stands this much above the lower one


def experiment(cameras: int, poses_per_camera: int, shared_poses: int):
    """The holed plate with [calibration] and 2 or 4 cameras (4: the pair copied ABOVE_M higher,
    aimed at the same point; pairs left:right, up_left:up_right and the two columns, so that
    every camera shares poses with the rig)."""
    data = load(HOLED).to_dict()
    data["calibration"] = {**data.get("calibration", {}), "poses_per_camera": poses_per_camera,
                           "shared_poses": shared_poses}
    if cameras == 4:
        upper = []
        for c in data["camera"]:
            u = dict(c)
            u["name"] = "up_" + c["name"]
            u["position_m"] = [c["position_m"][0], c["position_m"][1], c["position_m"][2] + ABOVE_M]
            upper.append(u)
        data["camera"] = data["camera"] + upper
        data["optimize"].pop("cameras", None)
        data["stereo_pair"] = [{"cameras": ["left", "right"]}, {"cameras": ["up_left", "up_right"]},
                               {"cameras": ["left", "up_left"]}, {"cameras": ["right", "up_right"]}]
    return parse(data, load(HOLED).path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--sigma", type=float, default=0.1, help="corner noise, px")
    ap.add_argument("--poses", type=int, default=5, help="poses per camera")
    ap.add_argument("--shared", type=int, default=3, help="shared poses per pair")
    ap.add_argument("--rigs", nargs="+", type=int, default=[2, 4])
    ap.add_argument("--workers", type=int, default=1,
                    help="also run the trials on a local pool of this many processes (>= 2)")
    args = ap.parse_args()
    import vdo

    vdo.configure()
    low, high = mc.ratio_interval(args.trials)
    print(f"trials {args.trials}, corner sigma {args.sigma} px; 95 % interval of one ratio "
          f"[{low:.3f}, {high:.3f}]")
    for n_cam in args.rigs:
        exp = experiment(n_cam, args.poses, args.shared)
        planned = plan(exp, 1.0)
        cams = list(planned.cameras)
        samples = planned.geometry.samples
        X, motion = prop.probe(exp, samples, cams, 4)
        rig = tuple(c.name for c in cams)
        inputs = (cams, planned.session, [rig], {rig: X}, {rig: motion}, args.trials, 0)
        started = time.perf_counter()
        res = mc.run(*inputs, sigma_det=args.sigma)
        serial = time.perf_counter() - started
        r = res.rigs[0]
        outside = int(np.sum((r.ratio < low) | (r.ratio > high)))
        print(f"\n{n_cam} cameras ({', '.join(rig)}), {len(planned.session.poses)} poses, "
              f"{len(r.parameters)} parameters, {serial:.1f} s serial")
        if args.workers > 1:
            started = time.perf_counter()
            pooled = mc.run(*inputs, sigma_det=args.sigma, workers=args.workers).rigs[0]
            wall = time.perf_counter() - started
            same = all(np.array_equal(getattr(r, f), getattr(pooled, f)) for f in
                       ("observed", "predicted", "nees", "displacement_observed", "strain_observed"))
            print(f"{args.workers} workers: {wall:.1f} s wall (pool start-up included), "
                  f"{serial / wall:.2f}x the serial run; the same result to the last bit: {same}")
        print(f"{'parameter':18s} {'predicted':>11s} {'observed':>11s} {'ratio':>6s}")
        for name, p, o, q in zip(r.parameters, r.predicted, r.observed, r.ratio):
            flag = "" if low <= q <= high else "  *"
            print(f"{name:18s} {p:11.4g} {o:11.4g} {q:6.3f}{flag}")
        print(f"parameters: median {np.median(r.ratio):.3f}, range {r.ratio.min():.3f}-{r.ratio.max():.3f}, "
              f"{outside} of {len(r.ratio)} outside [{low:.3f}, {high:.3f}] "
              f"(expected {0.05 * len(r.ratio):.1f} if independent)")
        fw = mc.ratio_interval(args.trials, len(r.ratio))
        inside = bool(np.all((r.ratio >= fw[0]) & (r.ratio <= fw[1])))
        print(f"all {len(r.ratio)} at once (Bonferroni): 95 % interval [{fw[0]:.3f}, {fw[1]:.3f}], "
              f"every ratio inside: {inside}")
        print(f"sqrt(NEES) {np.sqrt(r.nees):.3f}   displacement {r.displacement_ratio:.3f}   "
              f"strain {r.strain_ratio:.3f}")


if __name__ == "__main__":
    main()
