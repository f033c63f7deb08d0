"""What a judged layout of `vdo design` reports (`vdo.design.select`): σ_max p95 per region and
of the worst scored region, coverage, the area the candidates can measure at all and the figures
over it (`measures`); the curve's p95 over the area every count measures (`common_p95`); a
smaller count sharper in every scored region than the written one (`sharper_smaller_count`); each
chosen camera's usably seen fraction of each region (`seen_fractions`)."""

from __future__ import annotations

import numpy as np

from vdo.config.experiment import Experiment
from vdo.core.tolerances import TINY
from vdo.outputs import report


def sigma_key(exp: Experiment) -> str:
    """The curve's σ that the target and the figures read: σ_measured's p95 with [design] score =
    "measured", else the bound's."""
    return "sigma_measured_p95_um" if exp.design.score == "measured" else "sigma_p95_um"


def measures(state, exp: Experiment, can_measure: np.ndarray | None = None) -> dict:
    """Of a judged layout: sigma_max p95 (um) of the worst scored region (None when a scored
    region is unmeasured), the area fraction of all regions seen by their region's min_cameras
    usable views, and over the area that can be measured at all (`can_measure`, `measurable`;
    default everywhere): that area's fraction, the fraction of it seen by min_cameras, sigma_max
    p95 per region over its measured samples there (None for a region with none), and the worst
    of those (None only when no region has one). With [design] score = "measured" also
    σ_measured (`LayoutState.measured`, the [analysis] processing): p95 per region
    over its served samples ("sigma_measured_p95_by_region_um") and of the worst scored region
    ("sigma_measured_p95_um", None when a scored region is served nowhere), the figure the
    target and the curve then read (`sigma_key`)."""
    judged = report.state_evaluation(state)
    scored = exp.optimize.regions or [r.name for r in exp.regions]
    p95 = [judged.regions[r].sigma_max_um.p95 for r in scored]
    smp, pred = state.samples, state.prediction
    need = np.array([r.min_cameras for r in exp.regions])[smp.region]
    covered = pred.coverage >= need
    seen = smp.area[covered].sum() / smp.area.sum()
    can = np.ones(len(smp), dtype=bool) if can_measure is None else np.asarray(can_measure, bool)
    by_region = report.region_p95(smp, pred.sigma_max, can & pred.measured)
    values = [by_region[r] for r in scored if by_region[r] is not None]
    area = float(smp.area[can].sum())
    out = {}
    if exp.design.score == "measured":
        meas = state.measured
        by_meas = report.region_p95(smp, meas.sigma_max, np.isfinite(meas.sigma_max))
        worst = [by_meas[r] for r in scored]
        out = {"sigma_measured_p95_um": None if any(v is None for v in worst) else max(worst),
               "sigma_measured_p95_by_region_um": by_meas}
    return out | {"_sigma_max": np.asarray(pred.sigma_max, float), "_measured": can & np.asarray(pred.measured, bool),
                  "sigma_p95_um": None if any(v is None for v in p95) else max(p95),
            "coverage": float(seen),
            "measurable_fraction": area / float(smp.area.sum()),
            "coverage_of_measurable": float(smp.area[can & covered].sum() / area) if area > 0 else 0.0,
            "sigma_p95_measurable_um": max(values) if values else None,
            "sigma_p95_by_region_um": by_region}


def common_p95(exp: Experiment, samples, curve: list[dict]) -> None:
    """Give each count of `curve` its σ_max p95 over the area that EVERY count measures
    ("sigma_p95_common_um", µm: the worst scored region's p95 over its samples measured by every
    count, None where a scored region has none; "common_fraction", that area's share of all
    regions): each count's own figure is over the area it measures, which grows with the count,
    so that curve can rise where a camera more adds hard, grazing area; on one area the figures
    compare. The counts' private arrays (`measures`) are dropped."""
    if not curve:
        return
    common = np.logical_and.reduce([c["_measured"] for c in curve])
    scored = exp.optimize.regions or [r.name for r in exp.regions]
    for c in curve:
        by = report.region_p95(samples, c.pop("_sigma_max"), common)
        c.pop("_measured")
        values = [by[r] for r in scored if by.get(r) is not None]
        c["sigma_p95_common_um"] = max(values) if values else None
        c["common_fraction"] = float(samples.area[common].sum() / samples.area.sum())


def sharper_smaller_count(exp: Experiment, curve: list[dict], written: dict) -> str | None:
    """The line saying that a smaller count of the camera-count `curve` has a lower σ p95 (µm,
    per region over its measured samples: `sigma_p95_by_region_um`, or σ_measured's with [design]
    score = "measured") than the `written` count (the inventory's, designed.toml) in every scored
    region, and no higher a σ_max p95 over the area every count measures (`common_p95`'s
    "sigma_p95_common_um", where both have one): the largest such count, with its p95 per region
    and coverage against the written one's. None when no smaller count does. The curve can rise
    with the count where a camera more buys hard, grazing area (docs/curved.md); the lab may
    prefer the sharper, smaller layout, unless it is sharper only for measuring less."""
    key = "sigma_measured_p95_by_region_um" if sigma_key(exp) != "sigma_p95_um" else "sigma_p95_by_region_um"
    scored = exp.optimize.regions or [r.name for r in exp.regions]
    mine = written[key]
    lower = lambda c, r: c[key][r] is not None and (mine[r] is None or c[key][r] < mine[r])
    common = lambda c: c.get("sigma_p95_common_um") is None or written.get("sigma_p95_common_um") is None \
        or c["sigma_p95_common_um"] <= written["sigma_p95_common_um"]
    better = [c for c in curve if c["cameras"] < written["cameras"] and all(lower(c, r) for r in scored)
              and common(c)]
    if not better:
        return None
    c = max(better, key=lambda c: c["cameras"])
    show = lambda v: "unmeasured" if v is None else f"{v:.3f}"
    name = "sigma_measured" if key.startswith("sigma_measured") else "sigma_max"
    return (f"{c['cameras']} cameras reach a lower {name} p95 than the {written['cameras']} written to "
            "designed.toml in every scored region ("
            + ", ".join(f"{r} {show(c[key][r])} against {show(mine[r])} um" for r in scored)
            + f") at coverage {100 * c['coverage']:.1f} % against {100 * written['coverage']:.1f} %: "
            f"the design writes the inventory's count; [design] max_cameras = {c['cameras']} writes "
            f"a {c['cameras']}-camera layout (pareto.csv compares the counts)")


SEEN_SHOWN = 0.05   # the console lists the regions a chosen camera sees at least this fraction of


def seen_fractions(state) -> dict[str, dict[str, float]]:
    """Per camera of the layout `state`, the area fraction of each region it views usably (the
    usable views of `vdo.physics.usable`, the measure that assigns regions, `[optimize]
    assign_fraction`): on an all-round rig no camera sees half of a curved region, yet each sees
    a useful part."""
    samples, usable = state.samples, np.asarray(state.prediction.usable, bool)
    area = np.bincount(samples.region, samples.area, minlength=len(samples.region_names))
    return {cam.name: {name: float(samples.area[usable[c] & (samples.region == r)].sum() / max(area[r], TINY))
                       for r, name in enumerate(samples.region_names)}
            for c, cam in enumerate(state.cameras)}
