"""`vdo render`: the run folder of a render (`vdo.render.render_images` computes the images,
this module decides what to write).

The run folder (atomic, `vdo.core.runfolder`):

    images/<camera>.png|.tif   noisy DN images (16-bit files above 8-bit depth, counts aligned to
                               the most significant bits or raw: [render] bit_alignment),
                               [render] image_format
    images/<camera>.exr        linear float radiance, when [render] exr = true
    layout.json                K, R, t of the cameras at the rendered scale (`scaled_camera`)
    calibration/<format>/      the same cameras for DIC software (`vdo.formats.export.write_all`)
    contact_sheet.png          all cameras in a grid with their names, titled with the mode and scale
    photometry.csv             per camera and region: brightness b and contrast c of the noise-free
                               render around the projected visible samples, next to vdo.physics.lighting's
                               prediction (b, c of the paint, noise σ) and the contrasts predicted
                               for a camera's box pixels and for the rendered pixels
                               (docs/photometry.md)
    shadows.vtp                per sample: lit_<light> (visible fraction of each light), irradiance
    maps/shadows.png           number of lights reaching each sample (>= half the panel visible)
    config.toml, render.json   the resolved config; settings (the mode; spp and integrator in the
                               sampled mode only) and time per camera
    report.html                the run's page (`vdo.outputs.html_report`)
"""

from __future__ import annotations

import csv
import json
import math
import time

import numpy as np

from vdo.render import RenderResult, render_images, render_settings

PHOTOMETRY_FIELDS = ["camera", "region", "n_samples", "b_render_dn", "b_predicted_dn", "c_render_dn",
                     "c_render_predicted_dn", "c_pixel_predicted_dn", "c_predicted_dn",
                     "pixel_factor", "render_factor", "c_light_sampling_dn", "noise_predicted_dn", "n_interior"]


def render_experiment(exp, out, scale: float | None = None, spp: int | None = None,
                      seed: int | None = None, overwrite: bool = False, pairs=None,
                      only=None) -> dict:
    """Render every camera of `exp` (`vdo.render.render_images`) and write the run folder `out`
    (module docstring). The options, the output folder and the stereo `pairs` of the calibration
    files ((first, second) names; default: cameras assigned a common region) are checked before
    any render; `only` names the cameras to render (default all). Returns the render.json dict."""
    from vdo.core.runfolder import check_out

    render_settings(exp, scale, spp, seed)
    check_out(out, overwrite)
    return write_render(render_images(exp, scale, spp, seed, pairs, only), out, overwrite)


def write_render(result: RenderResult, out, overwrite: bool = False) -> dict:
    """Write a `RenderResult` into the run folder `out` (module docstring); returns the
    render.json dict."""
    from vdo.outputs import html_report
    from vdo.outputs import maps
    from vdo.outputs import report
    from vdo.core import vtp
    from vdo.formats.export import write_all
    from vdo.core.runfolder import inside, run_folder
    from vdo.model.sensor import save_image

    started = time.perf_counter()
    exp, state, cameras = result.experiment, result.state, result.cameras
    rs, illum, samples = exp.render, state.illumination, state.samples
    suffix = {"png": ".png", "tiff": ".tif"}[rs.image_format]
    with run_folder(out, overwrite) as tmp:
        (tmp / "images").mkdir()
        (tmp / "maps").mkdir()
        for cam in cameras:
            save_image(inside(tmp / "images", f"{cam.name}{suffix}"), result.images[cam.name],
                       exp.sensor.bit_depth, rs.bit_alignment)
            if rs.exr:
                from vdo.core.backend import write_exr

                write_exr(inside(tmp / "images", f"{cam.name}.exr"), result.linear[cam.name])
        report.write_json(tmp / "layout.json", report.layout(cameras))
        report.write_config(tmp / "config.toml", exp)
        write_all(cameras, result.pairs, tmp / "calibration", exp.path, no_pair=result.no_pair)
        contact_sheet(result.images, exp.sensor.max_dn, tmp / "contact_sheet.png",
                      f"{exp.name}: {result.mode} mode, scale {result.scale:g}"
                      + ("" if result.spp is None else f", {result.spp} spp"))
        with open(tmp / "photometry.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=PHOTOMETRY_FIELDS, restval="")
            writer.writeheader()
            for row in result.photometry:
                writer.writerow({k: (f"{v:.3f}" if isinstance(v, float) else v) for k, v in row.items()})
        arrays = {f"lit_{name}": illum.lit[k] for k, name in enumerate(illum.light_names)}
        arrays |= {"irradiance": illum.irradiance, "lights": illum.lights_reaching.astype(np.int32),
                   "region": samples.region.astype(np.int32), "normal": samples.normals}
        vtp.write_points(tmp / "shadows.vtp", samples.points, arrays)
        maps.plot_unfolded(samples, illum.lights_reaching, tmp / "maps" / "shadows.png",
                           f"{exp.name}: number of lights reaching each point", "lights",
                           discrete=True)
        sampled = {} if result.spp is None else {"spp": result.spp, "integrator": "direct"}
        summary = {"experiment": exp.name, "config": str(exp.path), "scale": result.scale,
                   "mode": result.mode, **sampled, "seed": result.seed,
                   "lights": list(illum.light_names),
                   "cameras": {c.name: {"width": c.width, "height": c.height,
                                        "seconds": round(result.seconds[c.name], 3)} for c in cameras},
                   "total_seconds": round(result.total_seconds + time.perf_counter() - started, 3)}
        (tmp / "render.json").write_text(json.dumps(summary, indent=2) + "\n")
        html_report.write_report(tmp)
    return summary


def contact_sheet(images: dict, max_dn: int, path, title: str = "") -> None:
    """All cameras' DN images in a grid, each titled with its camera name; PNG."""
    import matplotlib.pyplot as plt

    n = len(images)
    cols = min(n, 5 if n > 6 else 3 if n > 2 else n)
    rows = math.ceil(n / cols)
    first = next(iter(images.values()))
    aspect = first.shape[0] / first.shape[1]
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.6 * aspect * rows + 0.6),
                             squeeze=False, layout="constrained")
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (name, image) in zip(axes.ravel(), images.items()):
        ax.imshow(image, cmap="gray", vmin=0, vmax=max_dn, interpolation="antialiased")
        ax.set_title(f"{name}  ({image.shape[1]}x{image.shape[0]})", fontsize=9)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
