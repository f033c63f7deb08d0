"""`vdo render --series` as a command: the plan of `vdo.dic.series` (`plan_series`) and its run
folder, each image written as `series_images` renders it (a long series is never held in
memory): images/<camera>/<camera>_<step:04d>.tif (and .exr with [render] exr = true),
calibration/<format>/, layout.json, config.toml, poses.csv (the poses used, when any), series.json and
report.html."""

from __future__ import annotations

import json
import logging
import shutil

from vdo.core.progress import bar as progress_bar
from vdo.core.runfolder import run_folder
from vdo.dic.series import SeriesPlan, plan_series, series_images
from vdo.formats.calibration import file_stem
from vdo.formats.export import write_all
from vdo.model.sensor import save_image
from vdo.outputs import html_report, report

log = logging.getLogger(__name__)


def render_series(exp, out, poses_path=None, scale: float | None = None, spp: int | None = None,
                  seed: int | None = None, overwrite: bool = False, pairs=None) -> dict:
    """Render step 0 and every step of the load path for every camera into the run folder `out`
    (`vdo.dic.series.plan_series`, the arguments as there; `write_series`). Returns the
    series.json dict. Progress goes to this module's logger (`vdo.core.progress`)."""
    return write_series(plan_series(exp, poses_path, scale=scale, spp=spp, seed=seed, pairs=pairs),
                        out, overwrite)


def write_series(plan: SeriesPlan, out, overwrite: bool = False) -> dict:
    """Render the series of `plan` image by image into the run folder `out` (atomic,
    `vdo.core.runfolder`; module docstring), each image written before the next is rendered.
    Returns the series.json dict."""
    exp = plan.experiment
    with run_folder(out, overwrite) as tmp:
        for cam in plan.cameras:
            (tmp / "images" / file_stem(cam.name, exp.path)).mkdir(parents=True)
        bar = progress_bar(log, total=len(plan.steps) * len(plan.cameras), desc="series", unit="image")
        for image in series_images(plan):
            stem = tmp / "images" / image.camera.name / f"{image.camera.name}_{image.step:04d}"
            save_image(stem.with_suffix(".tif"), image.dn, exp.sensor.bit_depth)
            if exp.render.exr:
                from vdo.core.backend import write_exr

                write_exr(stem.with_suffix(".exr"), image.linear)
            bar.update()
        bar.close()
        report.write_json(tmp / "layout.json", report.layout(plan.cameras))
        report.write_config(tmp / "config.toml", exp)
        write_all(plan.cameras, plan.stereo, tmp / "calibration", exp.path, no_pair=plan.no_pair)
        poses = plan.poses_path if plan.poses_path is not None else exp.load_path.poses
        if poses is not None:                 # --series POSES.csv, else the [load_path]'s
            shutil.copyfile(poses, tmp / "poses.csv")
        summary = plan.to_json()
        (tmp / "series.json").write_text(json.dumps(summary, indent=2) + "\n")
        html_report.write_report(tmp)
    return summary
