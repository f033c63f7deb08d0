"""`vdo speckle` as a command: the speckle design of `vdo.design.pattern` (`design_speckle`) and
its print-ready files (`write_speckle`): per region `<region>.png` and `<region>.pdf` (the tile at
physical scale with a scale bar and its statistics), `<region>_tile.png`, `<region>.toml`; and
candidates.csv and speckle.json."""

from __future__ import annotations

import csv
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from PIL import Image

from vdo.config.experiment import Experiment
from vdo.core.runfolder import run_folder
from vdo.design.pattern import MM_PER_INCH, SCALE_BAR_MM, SpeckleResult, design_speckle, repeats, safe
from vdo.outputs import report


def speckle(exp: Experiment, out: Path, overwrite: bool = False) -> dict:
    """Design the speckle per region (`vdo.design.pattern.design_speckle`) and write its files into
    `out` (`write_speckle`). Returns the speckle.json dict."""
    t0 = time.perf_counter()
    return write_speckle(design_speckle(exp), out, overwrite, started=t0)


def write_speckle(result: SpeckleResult, out: Path, overwrite: bool = False,
                  started: float | None = None) -> dict:
    """The files of `vdo speckle` from its result (atomic, `vdo.core.runfolder`; module docstring).
    speckle.json's wall_s counts from `started` (a `time.perf_counter()` value; default: now).
    Returns the speckle.json dict."""
    t0 = time.perf_counter() if started is None else started
    exp, dpi, seen = result.experiment, result.print_dpi, result.footprints_mm_per_px
    judged, tiles, chosen, spacing = result.judged, result.tiles, result.chosen, result.spacing_m
    with run_folder(out, overwrite) as tmp:
        for region, j in chosen.items():
            name = safe(region)
            f = tiles[j.dots_mm]
            tile_mm = j.tile * j.texel_mm
            s = j.sigma_p95_um[region]
            lines = [f"{exp.name}: region {region}",
                     f"dots {j.name}, black {100 * (1 - f.mean()):.1f} %, gray std {f.std():.3f}",
                     f"tile {tile_mm:.1f} mm ({j.tile} printer dots at {dpi:g} dpi), seamless",
                     f"sigma_max p95 {'-' if s is None else f'{s:.3g}'} um, "
                     f"{len(j.flags[region])} flagged checks"]
            write_print(tmp / name, f, j.texel_mm, dpi, lines)
            Image.fromarray((f * 255).round().astype(np.uint8)).save(tmp / f"{name}_tile.png",
                                                                     dpi=(dpi, dpi))
            (tmp / f"{name}.toml").write_text(
                f"# the speckle designed for region {region!r}: paste into the experiment\n"
                f"[speckle]\nimage = \"{name}_tile.png\"\ntexel_mm = {j.texel_mm!r}\n"
                f"dot_diameter_mm = {min(j.dots_mm)!r}\ncoverage = {j.coverage!r}\n"
                f"white_albedo = {exp.speckle.white_albedo!r}\nblack_albedo = {exp.speckle.black_albedo!r}\n")
        with open(tmp / "candidates.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["dots_mm", "region", "sigma_p95_um", "flags", "chosen"])
            for j in judged:
                for region in seen:
                    s = j.sigma_p95_um[region]
                    w.writerow([j.name, region, "" if s is None else f"{s:.5g}", len(j.flags[region]),
                                int(chosen[region] is j)])
        result = {"print_dpi": dpi, "selection_spacing_mm": spacing * 1e3,
                  "footprints_mm_per_px": seen,
                  "regions": {r: {"dots_mm": list(j.dots_mm), "coverage": j.coverage,
                                  "texel_mm": j.texel_mm, "tile_texels": j.tile,
                                  "print_repeats": repeats(j.tile, j.texel_mm),
                                  "sigma_p95_um": j.sigma_p95_um[r], "flags": j.flags[r],
                                  "files": [f"{safe(r)}.{x}" for x in ("png", "pdf", "toml")]
                                  + [f"{safe(r)}_tile.png"]}
                              for r, j in chosen.items()},
                  "candidates": [{"dots_mm": list(j.dots_mm), "sigma_p95_um": j.sigma_p95_um,
                                  "flags": j.flags} for j in judged],
                  "wall_s": time.perf_counter() - t0}
        report.write_json(tmp / "speckle.json", result)
    return result


def write_print(path: Path, f: np.ndarray, texel_mm: float, dpi: float, lines: list[str]) -> None:
    """`path`.png and `path`.pdf: the tile repeated `repeats` times per side at physical scale
    (one texel per printer dot at `dpi`), a SCALE_BAR_MM scale bar and `lines` of statistics
    below it."""
    r = repeats(f.shape[1], texel_mm)
    dots = np.where(np.tile(f, (r, r)) > 0.5, 255, 0).astype(np.uint8)
    side_in = dots.shape[1] * texel_mm / MM_PER_INCH
    margin_in = 0.25 + 0.17 * len(lines)
    h = side_in + margin_in
    fig = plt.figure(figsize=(side_in, h), dpi=dpi)
    bar_ax = fig.add_axes((0, 0, 1, margin_in / h))
    bar_ax.set_xlim(0, side_in * MM_PER_INCH)
    bar_ax.set_ylim(0, margin_in * MM_PER_INCH)
    bar_ax.set_axis_off()
    top = margin_in * MM_PER_INCH
    bar_ax.add_patch(plt.Rectangle((1, top - 3), SCALE_BAR_MM, 1.5, facecolor="k", linewidth=0))
    bar_ax.text(SCALE_BAR_MM + 2, top - 2.3, f"{SCALE_BAR_MM:g} mm", fontsize=6, va="center")
    for i, text in enumerate(lines):
        bar_ax.text(1, top - 6 - 4.3 * i, text, fontsize=6, va="center")
    # The tiles pixel for pixel, one texel per printer dot at `dpi`. The PNG: the margin drawn
    # alone and the tiles pasted into its top rows (Agg would pass tens of Mpixel through its
    # resampler: ~6 s for an A4 sheet). The PDF: the tiles embedded as they are ("none": no
    # resampling in a vector file; lossless).
    fig.canvas.draw()
    page = np.array(fig.canvas.buffer_rgba())
    page[:dots.shape[0], :dots.shape[1], :3] = dots[:, :, None]
    page[:dots.shape[0], :dots.shape[1], 3] = 255
    plt.imsave(path.with_suffix(".png"), page, dpi=dpi)
    tiles_ax = fig.add_axes((0, margin_in / h, 1, side_in / h))
    tiles_ax.imshow(np.repeat(dots[:, :, None], 3, axis=2), interpolation="none", aspect="auto")
    tiles_ax.set_axis_off()
    fig.savefig(path.with_suffix(".pdf"), dpi=dpi)
    plt.close(fig)
