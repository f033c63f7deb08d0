"""Visibility throughput on the built-in 10-camera experiment.

Counts (camera, sample) queries per second with every test included (in front, in image,
incidence, occlusion ray cast against the specimen, machine, frame, LED panels and camera bodies).
Run: .venv/bin/python benchmarks/visibility.py [--spacing-mm 4] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

from vdo import scene
from vdo.config import experiment as config
from vdo.physics import visibility
from vdo.core.configure import configure
from vdo.scene import cameras_of

ROOT = Path(__file__).resolve().parent.parent


def numpy_baseline(sc, cameras, samples, limit):
    """The same four tests with numpy geometry (float64) and one Mitsuba ray batch per camera:
    the obvious implementation, kept here as the baseline."""
    masks = []
    for cam in cameras:
        p = samples.points @ cam.R.T + cam.t
        front = p[:, 2] > 1e-6
        z = np.where(front, p[:, 2], 1.0)
        (cx, cy), f = cam.principal_point, cam.focal_px
        u, v = f * p[:, 0] / z + cx, f * p[:, 1] / z + cy
        image = front & (u >= -0.5) & (u <= cam.width - 0.5) & (v >= -0.5) & (v <= cam.height - 0.5)
        facing = visibility.incidence_angles(cam, samples) < limit
        cand = np.flatnonzero(image & facing)
        origins = samples.points[cand] + visibility.EPSILON * samples.normals[cand]
        clear = np.zeros(len(samples), dtype=bool)
        clear[cand] = _segment_clear(sc, origins, cam.position)
        masks.append(image & facing & clear)
    return np.array(masks)


def _segment_clear(sc, origins, target):
    from vdo.core.backend import mitsuba

    mi = mitsuba()
    d = target - origins
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    ray = mi.Ray3f(mi.Point3f(*(np.ascontiguousarray(c, dtype=np.float32) for c in origins.T)),
                   mi.Vector3f(*(np.ascontiguousarray(c, dtype=np.float32) for c in d.T)))
    ray.maxt = mi.Float((dist - visibility.EPSILON).astype(np.float32))
    return ~np.asarray(sc.ray_test(ray), dtype=bool)


def timed(fn, repeats):
    fn()   # compile kernels / warm caches
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return result, statistics.median(times), times


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--config", default=ROOT / "experiments/beam_column/ten_cameras.toml")
    parser.add_argument("--spacing-mm", type=float, default=3.5)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    configure()

    exp = config.load(args.config)
    meshes = scene.load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                               rails=exp.rails, mounts=exp.mounts, path=exp.path)
    samples = scene.sample_regions(meshes, mesh_specs=exp.meshes, regions=exp.regions,
                                   spacing=args.spacing_mm * 1e-3, path=exp.path)
    cameras = cameras_of(exp.camera_specs, exp.rails)
    bodies = [scene.camera_body(c) for c in cameras]
    sc = scene.build_scene(meshes + bodies)
    n_tri = sum(len(m.faces) for m in meshes + bodies)
    limit = exp.evaluation.incidence_limit

    vis, t, times = timed(lambda: visibility.compute_visibility(sc, cameras, samples, limit,
                                                                progress=False), args.repeats)
    base, t_base, _ = timed(lambda: numpy_baseline(sc, cameras, samples, limit), args.repeats)
    agree = np.mean(base == vis.visible)
    rays = int((vis.in_front & vis.in_image & vis.facing).sum())
    queries = len(cameras) * len(samples)
    print(f"cpu threads           {len(os.sched_getaffinity(0))}")
    print(f"scene                 {n_tri:,} triangles, {len(cameras)} cameras")
    print(f"samples               {len(samples):,} ({args.spacing_mm:g} mm spacing)")
    print(f"(camera, sample)      {queries:,} queries, {rays:,} occlusion rays cast")
    print(f"vdo (Dr.Jit kernel)   {t * 1e3:.0f} ms median of {args.repeats} "
          f"(min {min(times) * 1e3:.0f}, max {max(times) * 1e3:.0f}): {queries / t / 1e6:.1f} M queries/s")
    print(f"numpy + ray batches   {t_base * 1e3:.0f} ms: {queries / t_base / 1e6:.1f} M queries/s")
    print(f"speed-up              {t_base / t:.1f}x   (masks agree on {100 * agree:.3f}% of pairs)")


if __name__ == "__main__":
    main()
