"""Render throughput on the built-in 10-camera experiment, on the CPU (llvm_ad_rgb).

Megasamples per second = pixels x spp / seconds, for one camera at 1/4 scale and 16 spp, timed after
a warm-up render (which compiles the kernel), median of --repeats. Then the time per camera at the
config's [render] defaults (scale, spp), rendering and exposure, as `vdo render` does it.
Run: .venv/bin/python benchmarks/render.py [--camera cam1] [--repeats 3]

With --dic: the DIC render mode (`vdo.render.render_camera_dic`) on the camera at full size
(Mpixel/s, wall and CPU time): without the surface light map (the baseline), with a fresh map
(cold) and with the frame's map already computed; the whole rig's frame with one map and
without; a load step rendered with the map of step 0 against a map of its own; then on a --crop
window at the image centre (and at each --crop-at) the DIC mode with and without the map, today's
sampled mode at --spp, and a reference (the mean of two --reference-spp renders): the per-pixel
error of each against the reference and the reference's own noise, in one run.
Run: .venv/bin/python benchmarks/render.py --dic [--camera cam1] [--crop 600 400] [--crop-at X0 Y0 ...]

With --riley PYTHON (a Python whose environment has riley-raster, not vdo's): a frontal speckled
plate (`benchmarks/correlate.py`'s speckle: 0.3 mm dots, 0.03 mm texels, 2.3 texels per pixel,
under a uniform sky) of --riley-pixels, rendered by vdo's DIC mode, vdo's sampled mode at --spp
and by Riley (`benchmarks/riley_plate.py`, bilinear texture reads) at 2x2, 4x4 and 8x8
subsamples, each renderer's per-pixel error against its own 256-sample reference in per cent of
the speckle's contrast (the image's std), and Mpixel/s, in one run.
Run: .venv/bin/python benchmarks/render.py --riley /path/to/riley-env/bin/python
"""

from __future__ import annotations

import argparse
import os
import statistics
import textwrap
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
    parser.add_argument("--filled-repeats", type=int, default=5,
                        help="--dic: renders of the camera with its map already computed")
    parser.add_argument("--dic", action="store_true", help="the DIC render mode against today's")
    parser.add_argument("--crop", type=int, nargs=2, default=(600, 400))
    parser.add_argument("--reference-spp", type=int, default=256)
    parser.add_argument("--riley", default=None, metavar="PYTHON",
                        help="the Python of an environment with riley-raster: vdo against Riley")
    parser.add_argument("--riley-pixels", type=int, nargs=2, default=(1500, 1000))
    parser.add_argument("--crop-at", type=int, nargs=2, action="append", default=[], metavar=("X0", "Y0"),
                        help="--dic: another crop whose top-left pixel is X0 Y0 (repeatable)")
    args = parser.parse_args()
    configure()
    if args.riley:
        return riley_benchmark(args)
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
    """The DIC mode (module docstring): cam1 at full size without the surface light map (the
    baseline: every light-map node computed for the camera), with a fresh map (a cold render:
    the map's nodes computed as the camera needs them) and with the frame's map already computed
    (a second render); the whole rig's frame with one map; a load step with the map of step 0
    against one computed on the deformed step; and the per-pixel error in the --crop windows."""
    import numpy as np

    from vdo.render import surface_light_map

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
    small = crop(cam, *args.crop)
    render_camera_dic(ds, small, spec=spec, light_map=False)        # compile the kernels
    render_camera_dic(ds, small, spec=spec)
    mp = cam.width * cam.height / 1e6

    def line(label, wall, cpu, megapixels=mp):
        print(f"{label:<58} {wall:6.2f} s wall {cpu:6.2f} s CPU  {megapixels / wall:5.2f} Mpixel/s wall, "
              f"{megapixels / cpu:5.2f} per CPU-s  (load {os.getloadavg()[0]:.1f})", flush=True)

    print(f"dic mode, {cam.name} full size {cam.width}x{cam.height}:")
    for k in range(2):
        _, wall, cpu = timed(render_camera_dic, ds, cam, spec=spec, light_map=False)
        line(f"  baseline (no surface map), render {k + 1}", wall, cpu)
    shared, wall, cpu = timed(surface_light_map, ds, [cam])
    print(f"  surface map of the camera: lattices laid out in {wall:.2f} s wall, {cpu:.2f} s CPU")
    _, wall, cpu = timed(render_camera_dic, ds, cam, spec=spec, light_map=shared)
    line(f"  (a) cold: the map's {shared.computed:,} nodes computed", wall, cpu)
    walls = []
    for k in range(args.filled_repeats):
        image, wall, cpu = timed(render_camera_dic, ds, cam, spec=spec, light_map=shared)
        line(f"  (b) the map already computed, render {k + 1}", wall, cpu)
        walls.append(wall)
    print(f"      best {mp / min(walls):.2f}, median {mp / statistics.median(walls):.2f} Mpixel/s wall "
          f"of {len(walls)} renders (the best: the code's speed with the least of the machine's noise)")

    # (c) the rig's frame: every camera, one map
    t0, c0 = time.perf_counter(), time.process_time()
    rig = surface_light_map(ds, full)
    pixels = 0
    for c, s in zip(full, exp.camera_specs):
        render_camera_dic(ds, c, spec=s, light_map=rig)
        pixels += c.width * c.height
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    line(f"  (c) the rig's frame, {len(full)} cameras, one map ({rig.computed:,} nodes)", wall, cpu, pixels / 1e6)
    t0, c0 = time.perf_counter(), time.process_time()
    for c, s in zip(full, exp.camera_specs):
        render_camera_dic(ds, c, spec=s, light_map=False)
    line(f"      the same {len(full)} cameras without the map (baseline)", time.perf_counter() - t0,
         time.process_time() - c0, pixels / 1e6)

    deformed_step(args, exp, full, index, spec, image)

    windows = [None] + [tuple(a) for a in args.crop_at]
    rows = []
    for at in windows:
        small = crop(cam, *args.crop, at=at)
        base = render_camera_dic(ds, small, spec=spec, light_map=False)
        fast, wall_f, cpu_f = timed(render_camera_dic, ds, small, spec=spec, light_map=shared)
        render_camera(sc, small, spec, args.spp, 0)
        today, wall_s, cpu_s = timed(render_camera, sc, small, spec, args.spp, 1)
        a, wall_r, _ = timed(render_camera, sc, small, spec, args.reference_spp, 2)
        b = render_camera(sc, small, spec, args.reference_spp, 3)
        ref = (a.astype(float) + b) / 2
        noise = np.std(a.astype(float) - b) / 2
        n = small.width * small.height
        where = "the centre" if at is None else f"x {at[0]}, y {at[1]}"
        print(f"crop {small.width}x{small.height} at {where}:")
        print(f"  dic mode (shared map) {wall_f:.2f} s wall, {cpu_f:.2f} s CPU: "
              f"{n / 1e6 / cpu_f:.2f} Mpixel/s per CPU-s")
        print(f"  sampled {args.spp:>3} spp    {wall_s:.2f} s wall, {cpu_s:.2f} s CPU: {n / 1e6 / cpu_s:.3f} "
              f"Mpixel/s, {n * args.spp / 1e6 / cpu_s:.2f} Msamples/s per CPU-s")
        print(f"  reference          2 x {args.reference_spp} spp ({wall_r:.1f} s wall each); image std "
              f"{ref.std():.4f}, its own per-pixel noise {noise:.5f}")
        errors = []
        for name, image in (("dic, shared map", fast), ("dic, no map", base), (f"sampled {args.spp} spp", today)):
            d = image.astype(float) - ref
            errors.append(d.std())
            print(f"  {name:<18} - reference: std {d.std():.5f}, mean {d.mean():+.5f}, "
                  f"p99 |d| {np.percentile(np.abs(d), 99):.5f}")
        print(f"  dic shared map - no map: max |d| {np.abs(fast.astype(float) - base).max():.5f}")
        rows.append((where, *errors, noise))
    print("per-pixel error against the reference (std of the difference):")
    print(f"  {'window':<16}{'dic, shared map':>16}{'dic, no map':>13}{f'{args.spp} spp':>9}{'ref. noise':>11}  ok")
    for where, e_map, e_base, e_spp, noise in rows:
        print(f"  {where:<16}{e_map:>16.5f}{e_base:>13.5f}{e_spp:>9.5f}{noise:>11.5f}  "
              f"{'yes' if e_map <= e_spp else 'NO'}")


def deformed_step(args, exp, full, index, spec, image0):
    """cam1 at a load step, rendered with the map of step 0 and with a map computed on the step
    itself: their difference, for the load path's first step (the hexapod moves the specimen by
    5 mm: a step `map_holds` refuses, a new map) and for the same motion scaled to MAP_REUSE_M
    (20 µm: a step that reads the map of step 0)."""
    from dataclasses import replace

    import numpy as np

    from vdo.geometry.keyframes import at_step, load_path_of
    from vdo.render import map_holds, surface_light_map
    from vdo.rendering.lightmap import MAP_REUSE_M
    from vdo.state import bodies as camera_bodies, prepare

    geometry = prepare(exp)
    load_path = load_path_of(geometry.meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                             groups=exp.groups)
    if load_path is None:
        print("load step: the experiment has no [load_path]")
        return
    step = load_path.steps[0]
    obstacles = camera_bodies(exp, full)
    rest = build_dic_scene(exp, geometry.meshes, geometry.region_faces, obstacles, geometry.speckle.pattern)
    posed = at_step(geometry, load_path, step, regions=exp.regions).meshes
    shift = max(float(np.abs(p.vertices - m.vertices).max()) for p, m in zip(posed, geometry.meshes))
    small = [replace(p, vertices=m.vertices + (p.vertices - m.vertices) * (MAP_REUSE_M / shift))
             for p, m in zip(posed, geometry.meshes)]
    cam = full[index]
    frame = surface_light_map(rest, full)
    render_camera_dic(rest, cam, spec=spec, light_map=frame)              # step 0 fills the map
    for label, meshes in ((f"step {step} (the hexapod moves the specimen {shift * 1e3:.1f} mm)", posed),
                          (f"step {step}'s motion scaled to {MAP_REUSE_M * 1e6:.0f} um", small)):
        moved = build_dic_scene(exp, geometry.meshes, geometry.region_faces, obstacles,
                                geometry.speckle.pattern, meshes)
        shared = render_camera_dic(moved, cam, spec=spec, light_map=frame)
        fresh = render_camera_dic(moved, cam, spec=spec, light_map=surface_light_map(moved, full))
        d = shared.astype(float) - fresh
        print(f"load {label}, {cam.name} full size: the map of step 0 against one of the step: max |d| "
              f"{np.abs(d).max():.5f}, std {d.std():.6f}, {int((np.abs(d) > 1e-3).sum())} pixels above "
              f"0.001 (image std {fresh.std():.3f}); map_holds: {map_holds(geometry.meshes, meshes)}", flush=True)


RILEY_SUBSAMPLES = (2, 4, 8)     # Riley's sub_sample: k x k samples per pixel
RILEY_REFERENCE = 16             # its own reference: 16 x 16 = 256 samples per pixel
FRONTAL_CAMERA = """
[[camera]]
name = "frontal"
sensor_width_mm = {width_mm}
pixels = [{w}, {h}]
focal_mm = 50
position_m = [0.0, 0.0, 1.0]
target_m = [0.0, 0.0, 0.0]
"""


def riley_benchmark(args):
    """vdo's DIC and sampled modes against Riley on one frontal speckled plate (module docstring)."""
    import subprocess
    import tempfile

    import numpy as np
    import trimesh

    w, h = args.riley_pixels
    folder = Path(tempfile.mkdtemp(prefix="vdo-riley-"))
    trimesh.creation.box(extents=[1000, 1000, 10]).apply_translation([0, 0, -5]).export(folder / "plate.stl")
    from correlate import PLATE           # benchmarks/correlate.py's plate and speckle

    (folder / "plate.toml").write_text(textwrap.dedent(PLATE)
                                       + FRONTAL_CAMERA.format(width_mm=w * 3.45e-3, w=w, h=h))
    exp = config.load(folder / "plate.toml")
    meshes = scene.load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                               rails=exp.rails, mounts=exp.mounts, path=exp.path)
    faces = scene.all_region_faces(meshes, mesh_specs=exp.meshes, regions=exp.regions,
                                   spacing=exp.evaluation.sample_spacing, path=exp.path)
    pattern = pattern_for(exp.speckle)
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    ds = build_dic_scene(exp, meshes, faces, (), pattern)
    sc = build_render_scene(exp, meshes, faces, (), pattern)
    n = w * h
    render_camera_dic(ds, cam)                                     # compile
    fast, wall_d, cpu_d = timed(render_camera_dic, ds, cam)
    render_camera(sc, cam, None, args.spp, 0)
    today, wall_s, cpu_s = timed(render_camera, sc, cam, None, args.spp, 1)
    a = render_camera(sc, cam, None, 256, 2).astype(float)
    b = render_camera(sc, cam, None, 256, 3).astype(float)
    ref = (a + b) / 2
    texels_per_px = cam.pixel_size / cam.focal_length * 1.0 / exp.speckle.texel
    job, out = folder / "job.npz", folder / "riley.npz"
    np.savez(job, texture=np.asarray(pattern, dtype=np.float64), pixels=np.array([w, h]),
             texels_per_px=texels_per_px, sub_samples=np.array([*RILEY_SUBSAMPLES, RILEY_REFERENCE]),
             threads=len(os.sched_getaffinity(0)))
    subprocess.run([args.riley, str(ROOT / "benchmarks" / "riley_plate.py"), str(job), str(out)], check=True)
    riley = np.load(out)
    riley_ref = riley["images"][-1]

    def error(image, reference):
        return 100 * np.std(image - reference) / np.std(reference)

    print(f"cpu threads          {len(os.sched_getaffinity(0))}; load average {os.getloadavg()[0]:.1f}")
    print(f"frontal speckled plate {w}x{h} px, {texels_per_px:.2f} texels per pixel, uniform sky; "
          f"error: per-pixel std against the renderer's own 256-sample reference, % of the speckle contrast")
    print(f"{'renderer':<28}{'samples/px':>11}{'wall s':>9}{'Mpixel/s':>10}{'Msamples/s':>12}{'error %':>9}")
    print(f"{'vdo dic mode':<28}{'1 ray':>11}{wall_d:>9.3f}{n / 1e6 / wall_d:>10.2f}{'':>12}"
          f"{error(fast, ref):>9.3f}")
    print(f"{'vdo sampled':<28}{args.spp:>11}{wall_s:>9.3f}{n / 1e6 / wall_s:>10.2f}"
          f"{n * args.spp / 1e6 / wall_s:>12.2f}{error(today, ref):>9.3f}")
    for k, image, seconds in zip(RILEY_SUBSAMPLES, riley["images"], riley["seconds"]):
        print(f"{'Riley (riley-raster)':<28}{k * k:>11}{seconds:>9.3f}{n / 1e6 / seconds:>10.2f}"
              f"{n * k * k / 1e6 / seconds:>12.2f}{error(image, riley_ref):>9.3f}")
    print(f"vdo's 256-spp reference noise: {100 * np.std(a - b) / 2 / np.std(ref):.3f} % of the contrast")


if __name__ == "__main__":
    main()
