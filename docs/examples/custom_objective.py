"""Your own objective, optimized with gradients: the mean out-of-plane uncertainty of the
scored regions, with the built-in constraints.

    python docs/examples/custom_objective.py [EXPERIMENT.toml] --out runs/custom
                                             [--spacing-mm 20] [--rounds 2] [--steps 20]

1. `vdo.MountModel(exp)` maps the mount variables θ (rail positions, pan, tilt: what
   `vdo optimize` moves) and the focal lengths (mm) to per-sample fields (`vdo.SampleFields`:
   σ per axis, the information matrix, the smooth usable-view count). The objective below is a
   JAX function of those fields; `jax.grad` gives its gradient, checked here against central
   finite differences.
2. `vdo.optimize_experiment(exp, out, objective=...)` minimises it with the optimizer's
   constraints (axis angles, field of view, clearance, obscuration, shadows), penalty rounds,
   visibility refreshes and time limit; the run folder is `vdo optimize`'s.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import vdo

HERE = Path(__file__).resolve().parent
DEFAULT = HERE.parent.parent / "experiments" / "beam_column" / "three_cameras.toml"
FD_STEP = 1e-6   # central differences: truncation ~1e-6 relative on these fields


def out_of_plane_um(fields: vdo.SampleFields, mask=1.0):
    """Area- and importance-weighted mean σ_z (µm) + 10 x the mean squared shortfall of usable
    views below each region's minimum (cameras²): about 1 per missing camera. The importance is
    0 outside [optimize] regions. `mask` (N,) weighs the samples further (the gradient check)."""
    w = fields.area * fields.importance[fields.region] * mask
    w = w / jnp.sum(w)
    short = jnp.maximum(fields.min_cameras[fields.region] - fields.coverage, 0.0)
    return jnp.sum(w * fields.sigma_xyz[:, 2]) * 1e6 + 10.0 * jnp.sum(w * short ** 2)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(DEFAULT))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--spacing-mm", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--regions", nargs="+", default=["joint_top"], help="the scored regions")
    args = parser.parse_args(argv)

    vdo.configure()
    exp = vdo.load(args.config).with_settings(
        evaluation={"sample_spacing_mm": args.spacing_mm},
        optimize={"starts": 1, "rounds": args.rounds, "max_steps": args.steps, "regions": args.regions})

    # 1. the gradient of the objective w.r.t. θ and the lenses, against finite differences. The
    # check weighs the samples measured at the file's layout only: where no camera pair measures
    # a sample its σ is the 1 mm prior, computed from a nearly singular information matrix whose
    # rounding (~1e-10 relative) swamps a finite difference (not the gradient).
    model = vdo.MountModel(exp, float64=True)
    theta, focal = jnp.asarray(model.theta0), jnp.asarray(model.focal0_mm)
    measured = jnp.asarray(np.asarray(model.fields(theta).sigma_max) < 100e-6, dtype=float)
    checked = lambda fields: out_of_plane_um(fields, measured)  # noqa: E731
    J = jax.jit(lambda t, f: checked(model.fields(t, f)))
    grad_theta, grad_focal = jax.jit(jax.grad(lambda t, f: checked(model.fields(t, f)),
                                              argnums=(0, 1)))(theta, focal)
    fd_theta = [(J(theta + e, focal) - J(theta - e, focal)) / (2 * FD_STEP)
                for e in FD_STEP * np.eye(len(theta))]
    fd_focal = [(J(theta, focal + e) - J(theta, focal - e)) / (2 * FD_STEP)
                for e in FD_STEP * np.eye(len(focal))]
    print(f"{exp.name}: scored regions {', '.join(args.regions)}; objective over the measured "
          f"samples at the file's layout {float(J(theta, focal)):.4f}")
    print(f"{'variable':<14}{'jax.grad':>14}{'finite diff.':>14}")
    names = model.names + [f"{c.name}.focal_mm" for c in model.problem.cams0]
    for name, g, fd in zip(names, [*grad_theta, *grad_focal], fd_theta + fd_focal):
        print(f"{name:<14}{float(g):>14.6g}{float(fd):>14.6g}")
    grads = np.concatenate([np.asarray(grad_theta), np.asarray(grad_focal)])
    fds = np.array([float(x) for x in fd_theta + fd_focal])
    error = float(np.max(np.abs(grads - fds)) / np.max(np.abs(fds)))
    print(f"max |grad - FD| / max |FD| = {error:.2e}")

    # 2. the optimizer on it, with the built-in constraints
    result = vdo.optimize_experiment(exp, args.out, overwrite=True, objective=out_of_plane_um,
                                     time_limit=600)
    print(f"optimized: objective {result.score_before_um:.4f} -> {result.score_after_um:.4f}, "
          f"{result.violations} constraint violation(s), search {result.status}")
    moves = (args.out / "moves.csv").read_text().splitlines()
    print("\n".join(moves[:1 + len(exp.camera_specs)]))
    return {"gradient_error": error, "result": result,
            "optimizer": json.loads((args.out / "optimizer.json").read_text())}


if __name__ == "__main__":
    try:
        main()
    except vdo.ConfigError as err:       # a user mistake: one line, as vdo's commands print it
        sys.exit(f"error: {err}")
