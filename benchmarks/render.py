"""Render throughput on the built-in 10-camera experiment, on the CPU (llvm_ad_rgb).

Megasamples per second = pixels x spp / seconds, for one camera at 1/4 scale and 16 spp, timed after
a warm-up render (which compiles the kernel), median of --repeats. Then the time per camera at the
config's [render] defaults (scale, spp), rendering and exposure, as `vdo render` does it.
Run: .venv/bin/python benchmarks/render.py [--camera cam1] [--repeats 3]
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
from vdo.render import (build_render_scene, camera_sensor, expose, render_linear,  # noqa: E402
                        render_seed, scaled_camera)
from vdo.model.speckle import pattern_for  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--config", default=ROOT / "experiments/beam_column/ten_cameras.toml")
    parser.add_argument("--camera", default="cam1")
    parser.add_argument("--scale", type=float, default=0.25)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    configure()

    exp = config.load(args.config)
    t0 = time.perf_counter()
    meshes = scene.load_meshes(exp)
    full = exp.cameras()
    bodies = [scene.camera_body(c) for c, s in zip(full, exp.camera_specs) if s.body]
    sc = build_render_scene(exp, meshes, scene.all_region_faces(exp, meshes), bodies,
                            pattern_for(exp.speckle))
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


if __name__ == "__main__":
    main()
