"""The light reaching every sample (`vdo.physics.lighting.illuminate`) against a NumPy baseline.

Both integrate every light panel over the same grid (`vdo.physics.lighting.GRID`^2 points per panel) with
one shadow ray per (sample, panel point) traced by Mitsuba's `ray_test`: the baseline builds the
rays, the cosines and the sums in NumPy (float64 arrays of all rays of a batch, as vdo did up to
this release), vdo in one Dr.Jit kernel per light. Prints the median wall time of each over
`--repeats` calls after one untimed call, their ratio, and the largest differences of the lit
fraction and of the direct irradiance (relative to its largest value).

Run: .venv/bin/python benchmarks/lighting.py [--config experiments/beam_column/ten_cameras.toml]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

import vdo
from vdo.core.backend import mitsuba
from vdo.physics.lighting import EPSILON, GRID, SKY_GRID, illuminate, panel_frame, panel_points
from vdo.scene import build_scene

ROOT = Path(__file__).resolve().parent.parent


def numpy_baseline(scene, lights, X, nrm, grid=GRID, batch_rays=4_000_000):
    """(lit, direct), each (L, N): the same integral with the rays built in NumPy."""
    mi = mitsuba()
    lit = np.zeros((len(lights), len(X)))
    direct = np.zeros((len(lights), len(X)))
    for k, light in enumerate(lights):
        P, dA = panel_points(light, grid)
        n_l = panel_frame(light)[0]
        per = max(1, batch_rays // len(P))
        for start in range(0, len(X), per):
            x, nn = X[start:start + per], nrm[start:start + per]
            d = P[None] - x[:, None]
            r = np.linalg.norm(d, axis=-1)
            d /= r[..., None]
            cos_s = np.einsum("mgk,mk->mg", d, nn)
            cos_l = -(d @ n_l)
            front = (cos_s > 0) & (cos_l > 0)
            origin = x[:, None] + EPSILON * nn[:, None]
            seg = P[None] - origin
            dist = np.linalg.norm(seg, axis=-1)
            seg /= dist[..., None]
            idx = np.flatnonzero(front.ravel())
            clear = np.zeros(front.size, dtype=bool)
            o = np.broadcast_to(origin, seg.shape).reshape(-1, 3)[idx]
            v = seg.reshape(-1, 3)[idx]
            ray = mi.Ray3f(mi.Point3f(*(np.ascontiguousarray(c, dtype=np.float32) for c in o.T)),
                           mi.Vector3f(*(np.ascontiguousarray(c, dtype=np.float32) for c in v.T)))
            ray.maxt = mi.Float(np.maximum(dist.ravel()[idx] - EPSILON, 0.0).astype(np.float32))
            clear[idx] = ~np.asarray(scene.ray_test(ray), dtype=bool)
            V = clear.reshape(front.shape)
            lit[k, start:start + per] = V.mean(axis=1)
            direct[k, start:start + per] = light.radiance * dA * np.sum(
                np.where(V, cos_s * cos_l / r ** 2, 0.0), axis=1)
    return lit, direct


def timed(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=ROOT / "experiments" / "beam_column" / "ten_cameras.toml")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    vdo.configure()
    exp = vdo.load(args.config)
    geometry = vdo.prepare(exp)
    scene = build_scene(list(geometry.meshes))
    s = geometry.samples
    X, nrm = np.asarray(s.points, float), np.asarray(s.normals, float)
    t_np, (lit_np, dir_np) = timed(lambda: numpy_baseline(scene, exp.lights, X, nrm), args.repeats)
    t_vdo, ill = timed(lambda: illuminate(scene, exp.lights, s), args.repeats)
    rays = len(exp.lights) * len(X) * GRID ** 2
    print(f"{exp.name}: {len(X):,} samples, {len(exp.lights)} lights, {rays / 1e6:.2f} M shadow rays per call")
    print(f"numpy baseline   {t_np:.3f} s   (median of {args.repeats})")
    print(f"vdo (Dr.Jit)     {t_vdo:.3f} s   ratio {t_np / t_vdo:.2f}x")
    print(f"largest difference: lit {np.abs(ill.lit - lit_np).max():.2e}, direct "
          f"{np.abs(ill.direct - dir_np).max() / max(dir_np.max(), 1e-300):.2e} of its largest value")
    if exp.render.ambient_radiance > 0:   # the sky fraction S too: SKY_GRID^2 shadow rays a sample
        t_sky, lit_sky = timed(lambda: illuminate(scene, exp.lights, s, exp.render.ambient_radiance), args.repeats)
        print(f"vdo with the sky fraction ({SKY_GRID}^2 rays a sample, {len(X) * SKY_GRID ** 2 / 1e6:.2f} M "
              f"more): {t_sky:.3f} s; S from {lit_sky.sky.min():.3f} to {lit_sky.sky.max():.3f}, "
              f"mean {lit_sky.sky.mean():.3f}")


if __name__ == "__main__":
    main()
