"""Speckle design: per region, the dot size (or a mix of dot sizes) that best serves the cameras
that see it, and print-ready files of it (`vdo speckle CONFIG --out DIR`).

The layout is the experiment's own cameras, judged once at [design] sample_spacing_mm (ray cast
and lighting, `vdo.state.layout_state`). Per (camera, region) with seen samples the footprint
m_c (mm per pixel, the median of 1 / sqrt|det A|, `vdo.physics.checks.design_checks`).

Candidates. Single dot sizes D: the 3-5 px rule's centre 4 m_c for every camera seeing a region,
and the geometric middle sqrt(3 m_min 5 m_max) of a region's cameras, all snapped to a geometric
grid of ratio GRID_RATIO (close sizes judge alike); a two-scale mix (D_1, D_2) = (4 m_min, 4 m_max)
of a region whose footprints differ by more than 5/3 (no single size is 3-5 px in all its
cameras). A mix is two Boolean dot models overlaid, each of black fraction
1 - sqrt(1 - coverage), so that the union covers `coverage` ([speckle] coverage): its power
spectrum is that of the union (`vdo.model.speckle.gradient_energy_table` of the mixed tile), with
energy at both dot scales.

Judging. Every candidate tile is generated at the print raster (texel = 25.4 mm / print_dpi, the
tile at least TILE_DOTS of its largest dots across) and judged on the whole layout:
* the sigma model: `vdo.physics.predict.predict` with the candidate's speckle model (its
  gradient-energy table and statistics), sigma_max p95 per region (`vdo.outputs.report.summary`);
* the dot-size rule per (camera, region): some dot size of the pattern is 3-5 px
  (`vdo.physics.checks.SPECKLE_PX`) in that camera;
* the interpolation floor per (camera, region) (`vdo.physics.checks.interpolation_floor`): the
  correlation's interpolation error of this pattern at the camera's median footprint against the
  sensor noise, flagged above `vdo.physics.checks.INTERPOLATION_NOISE`.
Per region the chosen pattern has the fewest flagged (camera, region) checks, then the lowest
sigma_max p95.

Files (written by `vdo.commands.speckle` from `design_speckle`'s result; per region, names made safe): `<region>.png` and `<region>.pdf`, the tile at physical
scale (print_dpi, the PNG's dpi set; repeated side by side to at least SHEET_MM) with a 10 mm
scale bar and the pattern's statistics below it;
`<region>_tile.png`, the bare tile, and `<region>.toml`, a [speckle] table pointing at it (the
pattern for `vdo evaluate`, `vdo render` and `vdo optimize`); `speckle.json` with every
candidate's judgement; `candidates.csv`.

Bad input: a dot size the cameras need that is below MIN_DOT_TEXELS printer dots at print_dpi
(a round dot cannot be printed), named with the region and the fix.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, replace

import numpy as np

from vdo.config.experiment import Experiment
from vdo.core.errors import ConfigError
from vdo.core.progress import bar
from vdo.model.speckle import MIN_DOT_TEXELS, generate_pattern, gradient_energy_table, normalise
from vdo.outputs import report
from vdo.physics.checks import INTERPOLATION_NOISE, SPECKLE_PX, design_checks
from vdo.physics.lighting import exposure_factors, pattern_stats
from vdo.physics.predict import SpeckleModel, predict
from vdo.state import layout_state, prepare

log = logging.getLogger(__name__)

MM_PER_INCH = 25.4
GRID_RATIO = 1.25       # candidate dot sizes snap to 0.1 mm x GRID_RATIO^n
TARGET_PX = 4.0         # the dot size each camera asks for: the middle of the 3-5 px rule
TILE_DOTS = 24          # the tile spans at least this many of its largest dots
TILE_TEXELS = (1024, 4096)   # tile side in texels (printer dots): at least, at most
SCALE_BAR_MM = 10.0     # the scale bar's length on the printed sheet
SHEET_MM = 150.0        # the printed sheet is at least this wide: the tile repeated side by side
MIX_RATIO = SPECKLE_PX[1] / SPECKLE_PX[0]   # footprints further apart than this need two sizes


@dataclass(frozen=True)
class Judged:
    """One candidate pattern judged on the layout: dots_mm (one or two sizes), coverage, texel_mm,
    tile texels; per region its sigma_max p95 (um, None unmeasured), flagged dot-size and
    interpolation checks (lists of 'camera: reason')."""

    dots_mm: tuple[float, ...]
    coverage: float
    texel_mm: float
    tile: int
    sigma_p95_um: dict
    flags: dict

    @property
    def name(self) -> str:
        return "+".join(f"{d:g}" for d in self.dots_mm) + " mm"


def snap(d_mm: float) -> float:
    """d rounded to the grid 0.1 mm x GRID_RATIO^n (3 significant digits)."""
    n = round(math.log(d_mm / 0.1) / math.log(GRID_RATIO))
    return float(f"{0.1 * GRID_RATIO ** n:.3g}")


def footprints(rows: list[dict]) -> dict:
    """{region: {camera: mm per pixel}} from `design_checks` rows."""
    out: dict = {}
    for r in rows:
        out.setdefault(r["region"], {})[r["camera"]] = r["mm_per_px"]
    return out


def candidates(seen: dict) -> list[tuple[float, ...]]:
    """The candidate dot sizes (module docstring): singles and two-scale mixes, in mm, sorted."""
    out = set()
    for cams in seen.values():
        m = np.array(list(cams.values()))
        out |= {(snap(TARGET_PX * x),) for x in m}
        out.add((snap(math.sqrt(SPECKLE_PX[0] * m.min() * SPECKLE_PX[1] * m.max())),))
        if m.max() > MIX_RATIO * m.min():
            pair = (snap(TARGET_PX * m.min()), snap(TARGET_PX * m.max()))
            if pair[0] < pair[1]:
                out.add(pair)
    return sorted(out, key=lambda d: (len(d), d))


def printable(exp: Experiment, seen: dict, dpi: float) -> None:
    """ConfigError naming [speckle] print_dpi when a region's cameras ask for dots (TARGET_PX x the
    finest footprint) smaller than MIN_DOT_TEXELS printer dots at `dpi`."""
    dot = MM_PER_INCH / dpi
    for region, cams in seen.items():
        camera, m = min(cams.items(), key=lambda kv: kv[1])
        need = TARGET_PX * m
        if need < MIN_DOT_TEXELS * dot:
            raise ConfigError(exp.path, "speckle.print_dpi",
                              f"{dpi:g} dpi prints dots of at least {MIN_DOT_TEXELS * dot:.3f} mm "
                              f"({MIN_DOT_TEXELS:g} printer dots) but camera {camera!r} on region "
                              f"{region!r} needs {need:.3f} mm dots: print at "
                              f"{math.ceil(MIN_DOT_TEXELS * MM_PER_INCH / need)} dpi or more")


def tile(dots_mm, coverage: float, texel_mm: float, seed: int) -> tuple[np.ndarray, int]:
    """The [0, 1] tile of a candidate (module docstring) at `texel_mm`: one Boolean dot model of
    black fraction `coverage`, or the union of one per size, each 1 - (1 - coverage)^(1/n)."""
    n = int(np.clip(2 ** math.ceil(math.log2(TILE_DOTS * max(dots_mm) / texel_mm)), *TILE_TEXELS))
    each = 1 - (1 - coverage) ** (1 / len(dots_mm))
    f = np.ones((n, n), np.float32)
    for k, d in enumerate(dots_mm):
        f = np.minimum(f, generate_pattern(n, texel_mm * 1e-3, d * 1e-3, each, 0, seed + k))
    return f, n


def model(f: np.ndarray, texel_mm: float, dots_mm) -> SpeckleModel:
    """The speckle model (`vdo.physics.predict.SpeckleModel`) of tile f."""
    mean, std = pattern_stats(f)
    table = gradient_energy_table(normalise(f), texel_mm * 1e-3, l_max=max(50 * max(dots_mm) * 1e-3, 0.05))
    return SpeckleModel(f, mean, std, table)


def judge(exp: Experiment, state, dots_mm, dpi: float) -> tuple[Judged, np.ndarray]:
    """One candidate on the judged layout `state` (module docstring): the Judged and its tile."""
    texel = MM_PER_INCH / dpi
    f, n = tile(dots_mm, exp.speckle.coverage, texel, exp.speckle.seed)
    spec = replace(exp.speckle, dot_diameter=min(dots_mm) * 1e-3, texel=texel * 1e-3, image=None)
    e = replace(exp, speckle=spec)
    sm = model(f, texel, dots_mm)
    pred = predict(e.regions, e.evaluation, e.speckle, e.sensor, list(state.cameras), state.samples,
                   state.visibility, state.illumination, sm, overlap=state.geometry.overlap,
                   exposure=exposure_factors(e.camera_specs, e.sensor))
    summary = report.summary(e, state.samples, state.visibility, pred)
    rows = design_checks(e.camera_specs, e.evaluation, e.speckle, e.sensor, e.analysis,
                         list(state.cameras), state.samples, state.visibility.visible,
                         state.illumination.irradiance, f)
    flags: dict = {r: [] for r in state.samples.region_names}
    for r in rows:
        px = [d / r["mm_per_px"] for d in dots_mm]
        if not any(SPECKLE_PX[0] <= p <= SPECKLE_PX[1] for p in px):
            flags[r["region"]].append(f"{r['camera']}: dots {'/'.join(f'{p:.1f}' for p in px)} px")
        if r["interpolation"] is not None and r["interpolation"]["ratio"] > INTERPOLATION_NOISE:
            flags[r["region"]].append(f"{r['camera']}: interpolation floor "
                                      f"{r['interpolation']['ratio']:.1f}x noise")
    sigma = {k: v["sigma_max_um"]["p95"] for k, v in summary["regions"].items()}
    return Judged(tuple(dots_mm), exp.speckle.coverage, texel, n, sigma, flags), f


def safe(name: str) -> str:
    """A file name from a region name: letters, digits, '-', '_' only."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_") or "region"


def repeats(tile_texels: int, texel_mm: float) -> int:
    """How many tiles per side the printed sheet holds: at least SHEET_MM wide."""
    return max(1, math.ceil(SHEET_MM / (tile_texels * texel_mm)))


def design_speckle(exp: Experiment) -> SpeckleResult:
    """Design the speckle per region (module docstring); returns the `SpeckleResult` that
    `vdo.commands.speckle` writes (this function writes nothing)."""
    dpi = exp.speckle.print_dpi
    spacing = exp.design.sample_spacing
    geometry = prepare(replace(exp, evaluation=replace(exp.evaluation, sample_spacing=spacing)),
                       spacing_field="design.sample_spacing_mm")
    state = layout_state(geometry, predict_fields=False)
    rows = design_checks(exp.camera_specs, exp.evaluation, exp.speckle, exp.sensor, exp.analysis,
                         list(state.cameras), state.samples, state.visibility.visible,
                         state.illumination.irradiance, geometry.speckle.pattern)
    seen = footprints(rows)
    if not seen:
        raise ConfigError(exp.path, "camera", "no camera sees a region: nothing to design a speckle for")
    printable(exp, seen, dpi)
    judged, tiles = [], {}
    for dots in bar(log, iterable=candidates(seen), desc="patterns", leave=False):
        j, f = judge(exp, state, dots, dpi)
        judged.append(j)
        tiles[j.dots_mm] = f
        log.info("%s: %s", j.name, ", ".join(
            f"{r} {'-' if s is None else f'{s:.3g} um'} ({len(j.flags[r])} flags)"
            for r, s in j.sigma_p95_um.items() if r in seen))
    chosen = {}
    for region in seen:
        def rank(j, region=region):
            s = j.sigma_p95_um[region]
            return (len(j.flags[region]), math.inf if s is None else s)
        chosen[region] = min(judged, key=rank)
    return SpeckleResult(experiment=exp, print_dpi=dpi, spacing_m=spacing, footprints_mm_per_px=seen,
                         judged=tuple(judged), tiles=tiles, chosen=chosen)


@dataclass(frozen=True)
class SpeckleResult:
    """What `design_speckle` returns: the experiment, its print resolution (dpi) and selection
    spacing (m), the cameras' footprints per region (mm per pixel, `footprints`), every candidate
    judged (`Judged`), each candidate's tile (gray levels in [0, 1], by its dots_mm) and the
    pattern chosen per region."""

    experiment: Experiment
    print_dpi: float
    spacing_m: float
    footprints_mm_per_px: dict                  # region -> camera -> mm per pixel
    judged: tuple[Judged, ...]
    tiles: dict[tuple, np.ndarray]              # dots_mm -> tile
    chosen: dict[str, Judged]                   # region -> its pattern
