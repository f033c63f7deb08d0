"""The cubic B-spline sampler that subset correlation spends its steps in: SciPy's
`map_coordinates` (today's, `vdo.dic.images.SplineImage.sample_local`) against the same sums
compiled by JAX (XLA, float64) and Dr.Jit's cubic texture lookup (`Texture2f64.eval_cubic`, the
LLVM backend, float64), in one run, on the access pattern of `vdo.dic.subsets.correlate_subsets`.

A window of B-spline coefficients (--window pixels square, a Gaussian-blurred random speckle,
`scipy.ndimage.spline_filter`); --subsets square subsets of --subset pixels at random centres in
it, each moved by its own small affine map (a shift of up to ±3 px, stretch and shear ±2e-3), so
that one call reads --subsets × --subset² positions, subset after subset (as a step of the
batched solver does). Each sampler sums the same (order + 1)² coefficients with the same weights;
the largest difference to SciPy's values is printed beside its time. Times are the median of
--repeats calls after one warm-up (JAX and Dr.Jit compile on their first call), per sample, wall
and CPU (Dr.Jit runs on its own thread pool, one thread per core; SciPy and this JAX program on
one).
Run: .venv/bin/python benchmarks/sampler.py [--window 2048] [--subsets 3000] [--subset 29] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np
from scipy import ndimage

os.environ.setdefault("VDO_VARIANT", "llvm_ad_rgb")


def positions(window: int, subsets: int, subset: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) (subsets, subset²) of the subsets' displaced pixel centres."""
    half = (subset - 1) / 2
    d = np.arange(subset) - half
    dr, dc = (a.ravel() for a in np.meshgrid(d, d, indexing="ij"))
    centre = rng.uniform(40 + half, window - 40 - half, (subsets, 2))
    shift = rng.uniform(-3, 3, (subsets, 2))
    A = np.eye(2) + rng.uniform(-2e-3, 2e-3, (subsets, 2, 2))
    rows = centre[:, :1] + shift[:, :1] + A[:, 0, :1] * dr + A[:, 0, 1:] * dc
    cols = centre[:, 1:] + shift[:, 1:] + A[:, 1, :1] * dr + A[:, 1, 1:] * dc
    return rows, cols


def timed(call, repeats: int) -> tuple[float, float, np.ndarray]:
    """Median wall and CPU seconds of `call` over `repeats` runs after a warm-up, and its value."""
    out = call()
    walls, cpus = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = call()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus), out


def jax_sampler(coeffs: np.ndarray):
    """The 4 x 4 cubic B-spline sum at (rows, cols), one XLA program (float64)."""
    import jax
    import jax.numpy as jnp

    W = coeffs.shape[1]
    flat = jnp.asarray(coeffs.ravel())

    def weights(t):
        s = 1.0 - t
        t2 = t * t
        return (s * s * s / 6, (3 * t2 * t - 6 * t2 + 4) / 6, (-3 * t2 * t + 3 * t2 + 3 * t + 1) / 6, t2 * t / 6)

    @jax.jit
    def sample(rows, cols):
        fr, fc = jnp.floor(rows), jnp.floor(cols)
        wr, wc = weights(rows - fr), weights(cols - fc)
        base = (fr.astype(jnp.int32) - 1) * W + fc.astype(jnp.int32) - 1
        out = 0.0
        for a in range(4):
            row = 0.0
            for b in range(4):
                row = row + wc[b] * flat[base + (a * W + b)]
            out = out + wr[a] * row
        return out

    return lambda rows, cols: np.asarray(sample(jnp.asarray(rows), jnp.asarray(cols)))


def drjit_sampler(coeffs: np.ndarray):
    """Dr.Jit's cubic B-spline texture lookup on the coefficients (texel centres at (i + ½)/n)."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(os.environ["VDO_VARIANT"])
    from drjit.llvm import Array2f64, TensorXf64, Texture2f64

    H, W = coeffs.shape
    tex = Texture2f64(TensorXf64(np.ascontiguousarray(coeffs[..., None])), filter_mode=dr.FilterMode.Linear,
                      wrap_mode=dr.WrapMode.Mirror)

    def sample(rows, cols):
        pos = Array2f64((cols.ravel() + 0.5) / W, (rows.ravel() + 0.5) / H)
        return np.array(tex.eval_cubic(pos)[0]).reshape(rows.shape)

    return sample


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--window", type=int, default=2048, help="coefficient window side, pixels")
    parser.add_argument("--subsets", type=int, default=3000)
    parser.add_argument("--subset", type=int, default=29, help="subset side, pixels")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    from vdo.core.configure import configure

    configure()
    rng = np.random.default_rng(0)
    image = ndimage.gaussian_filter(rng.random((args.window, args.window)), 1.2) * 4000
    coeffs = ndimage.spline_filter(image, order=3, mode="mirror")
    rows, cols = positions(args.window, args.subsets, args.subset, rng)
    n = rows.size
    print(f"window {args.window} x {args.window}, {args.subsets} subsets of {args.subset} x {args.subset} px: "
          f"{n:,} samples per call; cpu threads {len(os.sched_getaffinity(0))}, load average "
          f"{os.getloadavg()[0]:.1f}")
    samplers = {"SciPy map_coordinates (today)": lambda r, c: ndimage.map_coordinates(
                    coeffs, [r, c], order=3, prefilter=False, mode="mirror"),
                "JAX, one XLA program": jax_sampler(coeffs),
                "Dr.Jit Texture2f64.eval_cubic": drjit_sampler(coeffs)}
    base = None
    for label, call in samplers.items():
        wall, cpu, out = timed(lambda: call(rows, cols), args.repeats)
        base = out if base is None else base
        print(f"{label:<32} {wall / n * 1e9:7.1f} ns/sample wall, {cpu / n * 1e9:7.1f} ns CPU; "
              f"max |difference to SciPy| {np.abs(out - base).max():.1e} grey levels")
    return 0


if __name__ == "__main__":
    sys.exit(main())
