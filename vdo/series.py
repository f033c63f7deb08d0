"""A virtual test as an image series: `vdo render CONFIG --series [POSES.csv] --out DIR`.

Step 0 is the reference state (the meshes as configured); every step of the load path
(`vdo.keyframes`) moves mesh groups rigidly and, when the experiment's `[load_path]` names a
displacement file, deforms the specimen. With a POSES.csv the poses come from that file (one row
per step and group, the `vdo.keyframes` format; every mesh is also a group of its own name);
without it, from the experiment's `[load_path]`. The speckle moves with the surface (texture
coordinates from the rest vertices, `vdo.render.build_render_scene`); lights and camera bodies
stay.

The run folder (atomic, `vdo.runfolder`):

    images/<camera>/<camera>_<step:04d>.tif  16-bit TIFF (DN, the sensor's bit depth), step 0000
                                             the reference; sensor noise drawn independently per
                                             image, generator default_rng([seed, camera, step])
    calibration/<format>/                    the cameras for DIC software (`vdo.formats`)
    layout.json, config.toml, poses.csv (when given), series.json
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from .errors import ConfigError

log = logging.getLogger(__name__)


def render_series(exp, out, poses_path=None, scale: float | None = None, spp: int | None = None,
                  seed: int | None = None, overwrite: bool = False) -> dict:
    """Render step 0 and every step of the load path for every camera into the run folder `out`
    (module docstring). `scale`, `spp`, `seed` default to the config's [render] section. Returns
    the series.json dict. Progress goes to the `vdo.series` logger (`vdo.progress`)."""
    from .progress import bar as progress_bar

    from . import html_report, report
    from .formats.calibration import file_stem
    from .formats.export import default_pairs, write_all
    from .keyframes import at_step, load_path_of
    from .render import build_render_scene, render_camera, render_seed, scaled_camera
    from .runfolder import run_folder
    from .sensor import save_image
    from .state import bodies, layout_state, prepare

    rs = exp.render
    scale = rs.scale if scale is None else float(scale)
    spp = rs.spp if spp is None else int(spp)
    seed = rs.seed if seed is None else int(seed)
    if not (0 < scale <= 4) or spp < 1 or seed < 0:
        raise ConfigError(exp.path, "--scale/--spp/--seed", "need 0 < scale <= 4, spp >= 1, seed >= 0")
    if poses_path is not None and not Path(poses_path).is_file():
        raise ConfigError(poses_path, "--series", "no such file: give a CSV of poses per step and "
                                                  "group (see vdo.keyframes)")
    started = time.perf_counter()
    geometry = prepare(exp)
    load_path = load_path_of(exp, geometry.meshes, poses_path)
    if load_path is None:
        raise ConfigError(exp.path, "load_path", "a series needs poses: give --series POSES.csv or "
                                                 "a [load_path] in the experiment")
    cameras = [scaled_camera(c, scale) for c in exp.cameras()]
    obstacles = bodies(exp, cameras)
    steps = [0, *load_path.steps]
    with run_folder(out, overwrite) as tmp:
        for cam in cameras:
            (tmp / "images" / file_stem(cam.name, exp.path)).mkdir(parents=True)
        bar = progress_bar(log, total=len(steps) * len(cameras), desc="series", unit="image")
        for step in steps:
            posed = geometry.meshes if step == 0 else at_step(geometry, load_path, step).meshes
            scene = build_render_scene(exp, geometry.meshes, geometry.region_faces, obstacles,
                                       geometry.speckle.pattern, posed)
            for i, (cam, spec) in enumerate(zip(cameras, exp.camera_specs)):
                linear = render_camera(scene, cam, spec, spp, render_seed(seed, i))
                dn = exp.sensor.expose(linear, np.random.default_rng([seed, i, step]))
                save_image(tmp / "images" / cam.name / f"{cam.name}_{step:04d}.tif", dn,
                           exp.sensor.bit_depth)
                bar.update()
        bar.close()
        report.write_json(tmp / "layout.json", report.layout(cameras))
        report.write_config(tmp / "config.toml", exp)
        vis = layout_state(geometry, cameras, predict_fields=False).visibility
        write_all(cameras, default_pairs(exp, cameras, vis, geometry.samples), tmp / "calibration",
                  exp.path)
        if poses_path is not None:
            shutil.copyfile(poses_path, tmp / "poses.csv")
        summary = {"experiment": exp.name, "config": str(exp.path),
                   "poses": None if poses_path is None else str(poses_path),
                   "scale": scale, "spp": spp, "seed": seed, "steps": steps,
                   "cameras": [c.name for c in cameras],
                   "total_seconds": round(time.perf_counter() - started, 3)}
        (tmp / "series.json").write_text(json.dumps(summary, indent=2) + "\n")
        html_report.write_report(tmp)
    return summary
