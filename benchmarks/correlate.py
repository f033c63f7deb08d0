"""Subset correlation at full resolution: points per second, the batched solver against today's
per-point one, in one run.

Two 6000 x 4000 cameras (3.45 µm pixels, 50 mm lenses) look at a speckled plate 1 m away from
±12°, lit by a uniform sky; the images are rendered in the DIC render mode (`vdo.render`), the
reference with the plate at rest and the deformed one with the plate translated by U (each camera
moved by -U: the same images). Points on a full-field grid (--step pixels apart, default one
subset: subsets side by side) over the middle of the plate's common view; per point a square
subset of --subset pixels (a Q4 element: affine and more), both cameras at once
(`vdo.dic.series.correlate_points`): "batched" solves all points at once
(`vdo.dic.subsets.correlate_subsets`, --workers threads; its first call in the process compiles
its XLA programs, so it is timed twice on 1 thread), "today's" one `correlate` call per point
(`batched=False`, one process), timed on the first --today points. Reports points/s (wall
and per CPU-second, the machine being shared), the error against the imposed U and the largest
difference between the two on the points both solved.
Run: .venv/bin/python benchmarks/correlate.py [--points 5000] [--workers 2] [--today 100] [--profile 20]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import textwrap
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

os.environ.setdefault("VDO_VARIANT", "llvm_ad_rgb")

from vdo import scene  # noqa: E402
from vdo.config import experiment as config  # noqa: E402
from vdo.core.configure import configure  # noqa: E402
from vdo.dic.series import correlate_points, start_guesses  # noqa: E402
from vdo.model.speckle import pattern_for  # noqa: E402
from vdo.render import build_dic_scene, render_camera_dic  # noqa: E402
from vdo.scene import cameras_of

ROOT = Path(__file__).resolve().parent.parent
U_IMPOSED = np.array([23e-6, -17e-6, 11e-6])      # m: ~0.3 px in-plane at 69 µm per pixel

PLATE = """
[experiment]
name = "correlation benchmark plate"
[evaluation]
sample_spacing_mm = 20
[[mesh]]
name = "plate"
file = "plate.stl"
role = "specimen"
unit = "mm"
[[region]]
name = "top"
mesh = "plate"
normal = [0, 0, 1]
[[rail]]
name = "overhead"
control_points_m = [[-1.0, 0.0, 1.0], [1.0, 0.0, 1.0]]
[speckle]
dot_diameter_mm = 0.3
texel_mm = 0.03
tile_texels = 2048
[render]
ambient_radiance = 1.0
mode = "dic"
"""


def camera(name, x, pixels):
    return textwrap.dedent(f"""
    [[camera]]
    name = "{name}"
    sensor_width_mm = {pixels[0] * 3.45e-3}
    pixels = {list(pixels)}
    focal_mm = 50
    position_m = [{x}, 0.0, 1.0]
    target_m = [0.0, 0.0, 0.0]
    """)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--pixels", type=int, nargs=2, default=(6000, 4000))
    parser.add_argument("--points", type=int, default=5000)
    parser.add_argument("--subset", type=int, default=29, help="subset side, pixels")
    parser.add_argument("--step", type=float, default=None, help="grid step, pixels (default: --subset)")
    parser.add_argument("--workers", type=int, default=2, help="threads of the batched solver")
    parser.add_argument("--today", type=int, default=100, help="points timed with today's per-point solver")
    parser.add_argument("--profile", type=int, default=0, help="print this many lines of cProfile's "
                                                               "tottime ranking of a batched 1-thread run")
    args = parser.parse_args()
    configure()
    import trimesh

    folder = Path(tempfile.mkdtemp(prefix="vdo-bench-"))
    trimesh.creation.box(extents=[1000, 1000, 10]).apply_translation([0, 0, -5]).export(folder / "plate.stl")
    x = np.tan(np.radians(12.0))
    (folder / "plate.toml").write_text(textwrap.dedent(PLATE) + camera("left", -x, args.pixels)
                                       + camera("right", x, args.pixels))
    exp = config.load(folder / "plate.toml")
    meshes = scene.load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                               rails=exp.rails, mounts=exp.mounts, path=exp.path)
    faces = scene.all_region_faces(meshes, mesh_specs=exp.meshes, regions=exp.regions,
                                   spacing=exp.evaluation.sample_spacing, path=exp.path)
    ds = build_dic_scene(exp, meshes, faces, (), pattern_for(exp.speckle))
    cams = cameras_of(exp.camera_specs, exp.rails)
    t0, c0 = time.perf_counter(), time.process_time()
    refs = [render_camera_dic(ds, c).astype(np.float64) * 4000 for c in cams]
    defs = [render_camera_dic(ds, replace(c, position=np.asarray(c.position) - U_IMPOSED)).astype(np.float64)
            * 4000 for c in cams]
    print(f"rendered 4 images {args.pixels[0]}x{args.pixels[1]} (dic mode): {time.perf_counter() - t0:.1f} s wall, "
          f"{time.process_time() - c0:.1f} s CPU (this process)")
    mm_per_px = 1.0 / (cams[0].focal_px) * 1e3 / np.cos(np.radians(12))
    size = args.subset * mm_per_px * 1e-3
    n = int(np.ceil(np.sqrt(args.points)))
    step = (args.step or args.subset) * mm_per_px * 1e-3
    g = (np.arange(n) - (n - 1) / 2) * step
    points = np.array([[a, b, 0.0] for b in g for a in g])[:args.points]
    tu, tv = np.tile([1.0, 0, 0], (len(points), 1)), np.tile([0, 1.0, 0], (len(points), 1))
    print(f"cpu threads {len(os.sched_getaffinity(0))}, load average {os.getloadavg()[0]:.1f}; "
          f"{len(points)} points {args.step or args.subset:g} px apart, subsets {args.subset} px "
          f"({size * 1e3:.2f} mm), 2 cameras")

    def run(pts, workers, options):
        t0, c0 = time.perf_counter(), time.process_time()
        U, ok = correlate_points(cams, refs, defs, pts, tu[:len(pts)], tv[:len(pts)], size, workers=workers,
                                 **options)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        err = np.array([np.abs(np.einsum("nij,nj->ni", c.sensitivity(pts), U - U_IMPOSED)).max(axis=1)
                        for c in cams]).max(axis=0)
        return U, wall, cpu, ok, err

    results = {}
    subset = {"subset_px": args.subset, "shape_function": "affine"}
    for label, pts, workers, options in (
            ("today's (per point)", points[:args.today], 1, {"batched": False}),
            ("batched, 1 thread", points, 1, {}),
            ("batched, 1 thread again", points, 1, {}),
            (f"batched, {args.workers} threads", points, args.workers, {}),
            ("subset 2D, 1 thread", points, 1, subset),
            ("subset 2D, 1 thread again", points, 1, subset),
            (f"subset 2D, {args.workers} threads", points, args.workers, subset),
            (f"subset 2D, {args.workers} threads again", points, args.workers, subset)):
        U, wall, cpu, ok, err = run(pts, workers, options)
        results[label] = U
        print(f"{label:<26} {len(pts):>6} points: {wall:6.2f} s wall, {cpu:6.2f} s CPU: {len(pts) / wall:7.1f} "
              f"points/s wall, {len(pts) / cpu:7.1f} per CPU-s; converged {ok.mean():.0%}, "
              f"|error| median {np.median(err):.4f} px, max {err.max():.4f} px")
    today, batched = results["today's (per point)"], results["batched, 1 thread"][:args.today]
    print(f"batched - today's on the first {args.today} points: max |dU| {np.abs(batched - today).max():.2e} m")
    t0 = time.perf_counter()
    start = start_guesses(cams, refs, defs, points, workers=args.workers)
    begun = time.perf_counter() - t0
    t0 = time.perf_counter()
    correlate_points(cams, refs, defs, points, tu, tv, size, workers=args.workers, start=start, **subset)
    solved = time.perf_counter() - t0
    print(f"subset 2D, {args.workers} threads, split: the start guesses (phase correlation) {begun:.2f} s, "
          f"the matches and triangulation from them {solved:.2f} s ({len(points) / solved:.0f} points/s)")
    if args.profile:
        import cProfile
        import pstats

        profile = cProfile.Profile()
        profile.runcall(correlate_points, cams, refs, defs, points, tu, tv, size)
        pstats.Stats(profile).sort_stats("tottime").print_stats(args.profile)


if __name__ == "__main__":
    sys.exit(main())
