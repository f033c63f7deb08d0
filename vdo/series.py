"""A virtual test as an image series: `vdo render CONFIG --series MOTIONS.csv --out DIR`.

Step 0 is the reference state (the meshes as configured); each step k >= 1 of the CSV moves the
listed meshes rigidly; meshes not listed at a step stay where they are in the reference. One row
per (step, mesh):

    step, mesh, tx_mm, ty_mm, tz_mm, rx_deg, ry_deg, rz_deg, px_mm, py_mm, pz_mm

X' = P + R (X - P) + T: T = (tx, ty, tz) mm, R the rotation by the rotation vector
(rx, ry, rz) degrees (axis x angle, world axes), P = (px, py, pz) mm the pivot. Only step and mesh
are required; a missing motion column is 0. The speckle moves with the surface (texture
coordinates from the reference vertices, `vdo.render.build_render_scene`); lights and camera
bodies stay.

The run folder (atomic, `vdo.runfolder`):

    images/<camera>/<camera>_<step:04d>.tif  16-bit TIFF (DN, the sensor's bit depth), step 0000
                                             the reference; sensor noise drawn independently per
                                             image, generator default_rng([seed, camera, step])
    calibration/<format>/                    the cameras for DIC software (`vdo.formats`)
    layout.json, config.toml, motions.csv, series.json
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np

from .errors import ConfigError

MOTION_COLUMNS = ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg", "px_mm", "py_mm", "pz_mm")


def rigid_motion(t_mm, r_deg, pivot_mm) -> np.ndarray:
    """4x4 world motion (metres) X' = P + R (X - P) + T, R = exp([r]x) for the rotation vector r
    (degrees; Rodrigues' formula by scipy), T and P in mm."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.radians(np.asarray(r_deg, dtype=float))).as_matrix()
    P = np.asarray(pivot_mm, dtype=float) * 1e-3
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = P - R @ P + np.asarray(t_mm, dtype=float) * 1e-3
    return M


def load_motions(path, exp) -> dict[int, dict[str, np.ndarray]]:
    """{step: {mesh name: 4x4 motion}} from the CSV (module docstring), every value checked:
    known columns and mesh names, whole steps >= 1, finite numbers, one row per (step, mesh)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(path, "--series", "no such file: give a CSV of rigid motions per step")
    meshes = {m.name for m in exp.meshes}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        header = [h.strip() for h in (reader.fieldnames or [])]
        unknown = [h for h in header if h not in ("step", "mesh") + MOTION_COLUMNS]
        if "step" not in header or "mesh" not in header or unknown:
            raise ConfigError(path, "header", f"needs columns step, mesh and any of "
                                              f"{', '.join(MOTION_COLUMNS)}"
                              + (f" (unknown: {', '.join(unknown)})" if unknown else ""))
        reader.fieldnames = header
        motions: dict[int, dict[str, np.ndarray]] = {}
        for n, row in enumerate(reader, start=2):
            where = f"line {n}"
            try:
                step = float(row["step"])
                values = {c: float(row[c]) if row.get(c, "").strip() else 0.0 for c in MOTION_COLUMNS}
            except (TypeError, ValueError):
                raise ConfigError(path, where, "step and the motion columns must be numbers") from None
            if not (math.isfinite(step) and step == int(step) and step >= 1):
                raise ConfigError(path, where, f"step must be a whole number >= 1 (got {row['step']}; "
                                               "step 0 is the reference)")
            bad = [c for c, v in values.items() if not math.isfinite(v)]
            if bad:
                raise ConfigError(path, where, f"{', '.join(bad)} not finite (NaN or inf)")
            mesh = (row["mesh"] or "").strip()
            if mesh not in meshes:
                raise ConfigError(path, where, f"no [[mesh]] named {mesh!r} "
                                               f"(meshes: {', '.join(sorted(meshes))})")
            step = int(step)
            if mesh in motions.setdefault(step, {}):
                raise ConfigError(path, where, f"mesh {mesh!r} moves twice at step {step}")
            v = [values[c] for c in MOTION_COLUMNS]
            motions[step][mesh] = rigid_motion(v[0:3], v[3:6], v[6:9])
    if not motions:
        raise ConfigError(path, "", "holds no motion rows")
    return dict(sorted(motions.items()))


def render_series(exp, motions_path, out, scale: float | None = None, spp: int | None = None,
                  seed: int | None = None, overwrite: bool = False, quiet: bool = False) -> dict:
    """Render step 0 and every step of `motions_path` for every camera into the run folder `out`
    (module docstring). `scale`, `spp`, `seed` default to the config's [render] section. Returns
    the series.json dict."""
    from tqdm import tqdm

    from . import report
    from .formats.calibration import file_stem
    from .formats.export import default_pairs, raycast, write_all
    from .render import build_render_scene, render_camera, render_seed, scaled_camera
    from .runfolder import run_folder
    from .scene import all_region_faces, camera_body, load_meshes
    from .sensor import save_image
    from .speckle import pattern_for

    rs = exp.render
    scale = rs.scale if scale is None else float(scale)
    spp = rs.spp if spp is None else int(spp)
    seed = rs.seed if seed is None else int(seed)
    if not (0 < scale <= 4) or spp < 1 or seed < 0:
        raise ConfigError(exp.path, "--scale/--spp/--seed", "need 0 < scale <= 4, spp >= 1, seed >= 0")
    motions = load_motions(motions_path, exp)
    started = time.perf_counter()
    meshes = load_meshes(exp)
    region_faces = all_region_faces(exp, meshes)
    full = exp.cameras()
    cameras = [scaled_camera(c, scale) for c in full]
    bodies = [camera_body(c) for c, spec in zip(full, exp.camera_specs) if spec.body]
    pattern = pattern_for(exp.speckle)
    steps = [0, *motions]
    with run_folder(out, overwrite) as tmp:
        for cam in cameras:
            (tmp / "images" / file_stem(cam.name, exp.path)).mkdir(parents=True)
        bar = tqdm(total=len(steps) * len(cameras), desc="series", unit="image", disable=quiet)
        for step in steps:
            scene = build_render_scene(exp, meshes, region_faces, bodies, pattern, motions.get(step))
            for i, (cam, spec) in enumerate(zip(cameras, exp.camera_specs)):
                linear = render_camera(scene, cam, spec, spp, render_seed(seed, i))
                dn = exp.sensor.expose(linear, np.random.default_rng([seed, i, step]))
                save_image(tmp / "images" / cam.name / f"{cam.name}_{step:04d}.tif", dn,
                           exp.sensor.bit_depth)
                bar.update()
        bar.close()
        report.write_json(tmp / "layout.json", report.layout(cameras))
        report.write_config(tmp / "config.toml", exp)
        vis, samples = raycast(exp, cameras, meshes)
        write_all(cameras, default_pairs(exp, cameras, vis, samples), tmp / "calibration", exp.path)
        shutil.copyfile(motions_path, tmp / "motions.csv")
        summary = {"experiment": exp.name, "config": str(exp.path), "motions": str(motions_path),
                   "scale": scale, "spp": spp, "seed": seed, "steps": steps,
                   "cameras": [c.name for c in cameras],
                   "total_seconds": round(time.perf_counter() - started, 3)}
        (tmp / "series.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
