"""Render throughput on the built-in 10-camera experiment, on the CPU (llvm_ad_rgb).

Megasamples per second = pixels x spp / seconds, for one camera at 1/4 scale and 16 spp, timed after
a warm-up render (which compiles the kernel), median of --repeats. Then the time per camera at the
config's [render] defaults (scale, spp), rendering and exposure, as `vdo render` does it.
Run: .venv/bin/python benchmarks/render.py [--camera cam1] [--repeats 3]

With --dic: the DIC render mode (`vdo.render.render_camera_dic`) on the camera at full size
(Mpixel/s, wall and CPU time, first and second render), then on a --crop window at the image
centre (and at each --crop-at) the DIC mode, today's
sampled mode at --spp, and a reference (the mean of two --reference-spp renders): the per-pixel
error of each against the reference, the reference's own noise, and the difference between the
two modes, in one run.
Run: .venv/bin/python benchmarks/render.py --dic [--camera cam1] [--crop 600 400] [--crop-at X0 Y0 ...]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("VDO_VARIANT", "llvm_ad_rgb")

from vdo import scene
from vdo.config import experiment as config  # noqa: E402
from vdo.core.configure import configure  # noqa: E402
from vdo.render import (build_dic_scene, build_render_scene, camera_sensor, expose,  # noqa: E402
                        render_camera, render_camera_dic, render_linear, render_seed, scaled_camera)
from vdo.model.speckle import pattern_for  # noqa: E402
from vdo.scene import cameras_of

ROOT = Path(__file__).resolve().parent.parent


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--config", default=ROOT / "experiments/beam_column/ten_cameras.toml")
    parser.add_argument("--camera", default="cam1")
    parser.add_argument("--scale", type=float, default=0.25)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--dic", action="store_true", help="the DIC render mode against today's")
    parser.add_argument("--crop", type=int, nargs=2, default=(600, 400))
    parser.add_argument("--reference-spp", type=int, default=256)
    parser.add_argument("--crop-at", type=int, nargs=2, action="append", default=[], metavar=("X0", "Y0"),
                        help="--dic: another crop whose top-left pixel is X0 Y0 (repeatable)")
    args = parser.parse_args()
    configure()
    if args.dic:
        return dic_benchmark(args)

    exp = config.load(args.config)
    t0 = time.perf_counter()
    meshes = scene.load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                               rails=exp.rails, mounts=exp.mounts, path=exp.path)
    full = cameras_of(exp.camera_specs, exp.rails)
    bodies = [scene.camera_body(c) for c, s in zip(full, exp.camera_specs) if s.body]
    faces = scene.all_region_faces(meshes, mesh_specs=exp.meshes, regions=exp.regions,
                                   spacing=exp.evaluation.sample_spacing, path=exp.path)
    sc = build_render_scene(exp, meshes, faces, bodies, pattern_for(exp.speckle))
    t_scene = time.perf_counter() - t0
    index = [c.name for c in full].index(args.camera)
    cam, spec = scaled_camera(full[index], args.scale), exp.camera_specs[index]
    sensor = camera_sensor(cam, spec, args.spp)
    t0 = time.perf_counter()
    render_linear(sc, sensor, 0)
    t_warm = time.perf_counter() - t0
    times = []
    for k in range(args.repeats):
        t0 = time.perf_counter()
        render_linear(sc, sensor, k + 1)
        times.append(time.perf_counter() - t0)
    t = statistics.median(times)
    samples = cam.width * cam.height * args.spp
    print(f"cpu threads          {len(os.sched_getaffinity(0))}")
    print(f"scene build          {t_scene:.2f} s (meshes, speckle tile, Mitsuba scene)")
    print(f"{args.camera} at scale {args.scale:g}  {cam.width}x{cam.height} px, {args.spp} spp, "
          f"{len(exp.lights)} lights + ambient")
    print(f"first render         {t_warm:.2f} s (includes kernel compilation)")
    print(f"warm render          {t:.2f} s median of {args.repeats}: "
          f"{samples / t / 1e6:.2f} Msamples/s")

    rs = exp.render
    per_camera = []
    for i, (c, s) in enumerate(zip(full, exp.camera_specs)):
        small = scaled_camera(c, rs.scale)
        t0 = time.perf_counter()
        linear = render_linear(sc, camera_sensor(small, s, rs.spp), render_seed(rs.seed, i))
        expose(linear, exp.sensor, rs.seed, i)
        per_camera.append(time.perf_counter() - t0)
        print(f"  {c.name:<6} {small.width}x{small.height} px  {per_camera[-1]:.2f} s")
    print(f"defaults (scale {rs.scale:g}, {rs.spp} spp): {statistics.mean(per_camera):.2f} s per camera "
          f"on average, {sum(per_camera):.1f} s for {len(full)} cameras")


def crop(camera, width, height, at=None):
    """The camera's window of width x height pixels whose top-left pixel is `at` (x0, y0), by
    default centred (same K up to the principal point)."""
    from dataclasses import replace

    import numpy as np

    x0, y0 = at if at is not None else ((camera.width - width) // 2, (camera.height - height) // 2)
    cx, cy = camera.principal_point
    return replace(camera, width=width, height=height,
                   principal_offset_px=(cx - x0 - (width - 1) / 2, cy - y0 - (height - 1) / 2),
                   position=np.asarray(camera.position, dtype=float))


def timed(fn, *a, **k):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*a, **k)
    return out, time.perf_counter() - t0, time.process_time() - c0


def dic_benchmark(args):
    import numpy as np

    exp = config.load(args.config)
    meshes = scene.load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                               rails=exp.rails, mounts=exp.mounts, path=exp.path)
    full = cameras_of(exp.camera_specs, exp.rails)
    bodies = [scene.camera_body(c) for c, s in zip(full, exp.camera_specs) if s.body]
    faces = scene.all_region_faces(meshes, mesh_specs=exp.meshes, regions=exp.regions,
                                   spacing=exp.evaluation.sample_spacing, path=exp.path)
    pattern = pattern_for(exp.speckle)
    index = [c.name for c in full].index(args.camera)
    cam, spec = full[index], exp.camera_specs[index]
    ds, t_dic_scene, _ = timed(build_dic_scene, exp, meshes, faces, bodies, pattern)
    sc, t_scene, _ = timed(build_render_scene, exp, meshes, faces, bodies, pattern)
    print(f"cpu threads          {len(os.sched_getaffinity(0))}; load average {os.getloadavg()[0]:.1f} "
          f"(shared machine: CPU time is the figure to compare)")
    print(f"scene build          dic {t_dic_scene:.2f} s, sampled {t_scene:.2f} s")
    render_camera_dic(ds, crop(cam, *args.crop), spec=spec)         # compile the kernels
    mp = cam.width * cam.height / 1e6
    for label in ("first", "second"):
        _, wall, cpu = timed(render_camera_dic, ds, cam, spec=spec)
        print(f"dic mode, {cam.name} full size {cam.width}x{cam.height}, {label} render: {wall:.1f} s "
              f"wall, {cpu:.1f} s CPU: {mp / wall:.2f} Mpixel/s wall, {mp / cpu:.2f} Mpixel/s per CPU-second")
    windows = [None] + [tuple(a) for a in args.crop_at]
    for at in windows:
        small = crop(cam, *args.crop, at=at)
        fast, wall_f, cpu_f = timed(render_camera_dic, ds, small, spec=spec)
        render_camera(sc, small, spec, args.spp, 0)
        today, wall_s, cpu_s = timed(render_camera, sc, small, spec, args.spp, 1)
        a, wall_r, _ = timed(render_camera, sc, small, spec, args.reference_spp, 2)
        b = render_camera(sc, small, spec, args.reference_spp, 3)
        ref = (a.astype(float) + b) / 2
        noise = np.std(a.astype(float) - b) / 2
        n = small.width * small.height
        where = "the centre" if at is None else f"x {at[0]}, y {at[1]}"
        print(f"crop {small.width}x{small.height} at {where}:")
        print(f"  dic mode           {wall_f:.2f} s wall, {cpu_f:.2f} s CPU: {n / 1e6 / cpu_f:.2f} Mpixel/s per CPU-s")
        print(f"  sampled {args.spp:>3} spp    {wall_s:.2f} s wall, {cpu_s:.2f} s CPU: {n / 1e6 / cpu_s:.3f} "
              f"Mpixel/s, {n * args.spp / 1e6 / cpu_s:.2f} Msamples/s per CPU-s")
        print(f"  reference          2 x {args.reference_spp} spp ({wall_r:.1f} s wall each); image std "
              f"{ref.std():.4f}, its own per-pixel noise {noise:.5f}")
        for name, image in (("dic", fast), (f"sampled {args.spp} spp", today)):
            d = image.astype(float) - ref
            print(f"  {name:<18} - reference: std {d.std():.5f}, mean {d.mean():+.5f}, "
                  f"p99 |d| {np.percentile(np.abs(d), 99):.5f}")
        d = fast.astype(float) - today
        print(f"  dic - sampled {args.spp} spp: std {d.std():.5f}")


if __name__ == "__main__":
    main()
