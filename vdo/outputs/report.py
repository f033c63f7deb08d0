"""Tables written into a run folder: the camera layout and the per-region summary."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tomli_w

from vdo.physics import usable
from vdo.model.camera import Camera
from vdo.config.experiment import Experiment
from vdo.config.schema import table_dict
from vdo.physics.predict import Prediction
from vdo.scene import SurfaceSamples
from vdo.state import LayoutState
from vdo.physics.strain import STRAIN_COMPONENTS
from vdo.physics.visibility import Visibility


def layout(cameras: list[Camera]) -> dict:
    """Per camera: name, width, height, K, R, t with x ~ K (R X + t) (OpenCV convention, metres),
    the lens distortion (k1, k2, p1, p2, k3) in OpenCV's order,
    plus the pose in words (optical centre, pan/tilt/roll in degrees, focal length in mm)."""
    return {"convention": "OpenCV: x ~ K (R X + t) with distortion (k1, k2, p1, p2, k3) as "
                          "cv2.projectPoints; camera x right, y down, z forward; pixel (0,0) "
                          "is the centre of the top-left pixel; world z up; metres",
            "cameras": [{"name": c.name, "width": c.width, "height": c.height,
                         "K": c.K.tolist(), "R": c.R.tolist(), "t": c.t.tolist(),
                         "distortion": list(c.distortion),
                         "position_m": np.asarray(c.position).tolist(),
                         "pan_deg": math.degrees(c.pan), "tilt_deg": math.degrees(c.tilt),
                         "roll_deg": math.degrees(c.roll), "focal_mm": c.focal_length * 1e3,
                         "pixel_um": c.pixel_size * 1e6} for c in cameras]}


SIGMA_MEANING = ("Cramér-Rao bound of the 3D displacement for one noisy image against a noise-free "
                 "reference, over a patch of patch_mm x patch_mm (multiply by sqrt(2) when the "
                 "reference image is noisy too); percentiles over the measured points")


STRAIN_MEANING = ("sigma_strain_microstrain: Cramér-Rao bound of the in-plane strain (eps_uu, "
                  "eps_vv, tensor shear eps_uv along each region's face frame t_u, t_v) for the "
                  "[analysis] settings: global DIC, the centre of an interior Q4 element; subset "
                  "DIC, a plane fit over strain_window x strain_window subsets (docs/theory.md, sec. 8). "
                  "sigma_dic_max_um: the analysis' displacement sigma (an interior Q4 node, or one "
                  "subset), worst direction. One noisy image, as sigma (x sqrt(2) for two).")


USABLE_MEANING = ("a camera counts (coverage, seen_by_*, cameras) where its soft weight is >= "
                  "usable_weight; sigma uses only those views, over the DIC patch clipped to the "
                  "surface they see; n_edge_limited: samples with less than edge_fraction of their "
                  "patch usable by >= 2 views; n_outliers: samples with sigma_max above "
                  "outlier_factor x the region's median; max_unflagged leaves both out")


@dataclass(frozen=True)
class Percentiles:
    """Percentiles of one field over a region's measured (finite) samples, in the field's unit (µm
    for a displacement σ, µε for a strain σ); None where no sample is measured. `max_unflagged`:
    the max over the samples not flagged as outliers or edge-limited (the max itself where no
    flag applies)."""

    p50: float | None
    p95: float | None
    max: float | None
    max_unflagged: float | None

    def to_json(self) -> dict:
        """{"p50", "p95", "max", "max_unflagged"}, as summary.json holds them."""
        return {"p50": self.p50, "p95": self.p95, "max": self.max, "max_unflagged": self.max_unflagged}


@dataclass(frozen=True)
class RegionSummary:
    """One region of a judged layout (a row of summary.json's "regions"). Fractions are of the
    region's area; a camera counts where its soft weight is >= usable_weight (`vdo.physics.usable`)."""

    area_m2: float
    importance: float                                # the region's weight in the score
    n_samples: int
    seen_by_1_or_more: float                         # area fraction with >= 1 usable view
    seen_by_2_or_more: float
    seen_by_3_or_more: float
    min_cameras: int                                 # the region's coverage requirement ([[region]] min_cameras)
    seen_by_min_cameras: float                       # area fraction with >= min_cameras usable views
    cameras: dict[str, float]                        # camera -> area fraction it usably sees (4 digits)
    sigma_max_um: Percentiles                        # µm, worst-direction displacement σ
    n_outliers: int                                  # σ_max > outlier_factor x the region's median
    n_edge_limited: int                              # < edge_fraction of the patch seen by >= 2 views
    unmeasured_fraction: float                       # area fraction with < 2 usable views
    sensitivity_mpx_per_um: dict[str, float]         # axis (x, y, z) -> area-weighted mean, mpixel/µm
    sigma_axis_um: dict[str, Percentiles]            # axis (x, y, z) -> σ along it, µm
    sigma_strain_microstrain: dict[str, Percentiles] | None = None   # eps_uu/vv/uv -> µε; None: no strain
    sigma_dic_max_um: Percentiles | None = None      # µm, the [analysis] DIC's displacement σ

    def to_json(self) -> dict:
        """The region's row of summary.json (the strain keys only when computed)."""
        out = {"area_m2": self.area_m2, "importance": self.importance, "n_samples": self.n_samples,
               "seen_by_1_or_more": self.seen_by_1_or_more, "seen_by_2_or_more": self.seen_by_2_or_more,
               "seen_by_3_or_more": self.seen_by_3_or_more, "min_cameras": self.min_cameras,
               "seen_by_min_cameras": self.seen_by_min_cameras, "cameras": dict(self.cameras),
               "sigma_max_um": self.sigma_max_um.to_json(), "n_outliers": self.n_outliers,
               "n_edge_limited": self.n_edge_limited, "unmeasured_fraction": self.unmeasured_fraction,
               "sensitivity_mpx_per_um": dict(self.sensitivity_mpx_per_um),
               "sigma_axis_um": {a: p.to_json() for a, p in self.sigma_axis_um.items()}}
        if self.sigma_strain_microstrain is not None:
            out["sigma_strain_microstrain"] = {c: p.to_json() for c, p in self.sigma_strain_microstrain.items()}
        if self.sigma_dic_max_um is not None:
            out["sigma_dic_max_um"] = self.sigma_dic_max_um.to_json()
        return out


@dataclass(frozen=True)
class EvaluationSettings:
    """The settings a layout was judged with (summary.json's "settings", with the meanings of σ,
    strain and usable views in words)."""

    incidence_limit_deg: float
    sample_spacing_mm: float
    patch_mm: float                 # side of the DIC patch
    n_samples: int
    n_cameras: int
    analysis: dict                  # the [analysis] table
    usable_weight: float            # `vdo.physics.usable.USABLE_WEIGHT`
    edge_fraction: float
    outlier_factor: float

    def to_json(self) -> dict:
        return {"incidence_limit_deg": self.incidence_limit_deg, "sample_spacing_mm": self.sample_spacing_mm,
                "patch_mm": self.patch_mm, "n_samples": self.n_samples, "n_cameras": self.n_cameras,
                "sigma": SIGMA_MEANING, "analysis": self.analysis, "strain": STRAIN_MEANING,
                "usable_weight": self.usable_weight, "edge_fraction": self.edge_fraction,
                "outlier_factor": self.outlier_factor, "usable": USABLE_MEANING}


SECTIONS = ("axis_angles", "design_checks", "negligible_views", "cameras_seeing_nothing", "constraints", "glare",
            "measured", "load_path", "developed", "calibration",
            "calibration_files")   # EvaluationResult's optional parts, JSON order


@dataclass(frozen=True)
class EvaluationResult:
    """A judged layout: what `vdo evaluate` returns and writes as summary.json (`to_json`), and
    what `vdo optimize` writes as summary_before.json / summary_after.json (regions only, and the
    load path). The sections after `regions` are None where the producer did not judge them
    (absent from the JSON); each holds the JSON of the module that computes it."""

    experiment: str                                  # the experiment's name
    config: str                                      # the experiment file's path
    settings: EvaluationSettings
    regions: dict[str, RegionSummary]                # in the file's order
    axis_angles: list[dict] | None = None            # `vdo.constraints.angle_checks`
    design_checks: list[dict] | None = None          # `vdo.physics.checks.design_checks`
    negligible_views: list[dict] | None = None       # pairs left out of them (`checks.negligible_views`)
    cameras_seeing_nothing: list[str] | None = None  # cameras with no usable view of any sample
    constraints: dict | None = None                  # {"violations": count, "checks": `layout_checks`}
    glare: list[dict] | None = None                  # `vdo.physics.glare.hot_spots`
    measured: dict | None = None                     # `vdo.physics.measured.summary`
    load_path: dict | None = None                    # `vdo.search.loadpath.summary`
    developed: dict | None = None                    # region -> `vdo.outputs.maps.plot_developed`
    calibration: dict | None = None                  # `vdo.commands.calibrate.evaluation_errors`
    calibration_files: dict | None = None            # camera -> its --calibration file (`vdo.calib.importer.imported`)

    def to_json(self) -> dict:
        """summary.json: experiment, config, settings, regions, then each section that is not None."""
        out = {"experiment": self.experiment, "config": self.config, "settings": self.settings.to_json(),
               "regions": {name: r.to_json() for name, r in self.regions.items()}}
        return out | {k: getattr(self, k) for k in SECTIONS if getattr(self, k) is not None}


def percentiles(values_um: np.ndarray, flagged: np.ndarray | None = None) -> Percentiles:
    """p50, p95 and max over the measured (finite) values, and max_unflagged: the max over those
    not flagged as outliers or edge-limited."""
    finite = np.isfinite(values_um)
    if not finite.any():
        return Percentiles(None, None, None, None)
    plain = values_um[finite] if flagged is None else values_um[finite & ~flagged]
    return Percentiles(p50=float(np.percentile(values_um[finite], 50)),
                       p95=float(np.percentile(values_um[finite], 95)),
                       max=float(values_um[finite].max()),
                       max_unflagged=float(plain.max()) if plain.size else None)


def region_p95(samples, sigma_m: np.ndarray, keep: np.ndarray) -> dict:
    """Per region name of `samples`: the p95 (µm, `percentiles`) of `sigma_m` (N,) (m) over its
    samples where `keep` (N,) bool; None where none is kept (or none is finite)."""
    return {name: percentiles(sigma_m[(samples.region == r) & keep] * 1e6).p95
            for r, name in enumerate(samples.region_names)}


def state_evaluation(state: LayoutState) -> EvaluationResult:
    """The per-region table of a judged layout (`evaluation` of its pieces)."""
    return evaluation(state.experiment, state.samples, state.visibility, state.prediction, state.strain)


def state_summary(state: LayoutState) -> dict:
    """`state_evaluation` as summary.json's dict."""
    return state_evaluation(state).to_json()


def summary(exp: Experiment, samples: SurfaceSamples, vis: Visibility, pred: Prediction,
            strain=None) -> dict:
    """`evaluation` as summary.json's dict."""
    return evaluation(exp, samples, vis, pred, strain).to_json()


def evaluation(exp: Experiment, samples: SurfaceSamples, vis: Visibility, pred: Prediction,
               strain=None) -> EvaluationResult:
    """Per region: area (m^2), the area fractions seen by >= 1, 2, 3 usable views
    (`vdo.physics.usable`) and by >= its min_cameras (`seen_by_min_cameras`), which cameras are
    usable views of it (fraction of its area), sigma_max p50/p95/max/max_unflagged (um, over the
    measured samples), the counts of outlier and
    edge-limited samples, the unmeasured area fraction, and the mean global sensitivity per axis
    (mpixel/um). With `strain` = (sigma_strain (N, 3), sigma_dic (N,) m) from
    `vdo.physics.strain.analysis_fields`: per-axis sigma percentiles (um), strain sigma percentiles per
    face-frame component (microstrain) and the analysis' displacement sigma."""
    coverage = pred.coverage
    need = {r.name: r.min_cameras for r in exp.regions}
    regions = {}
    for k, name in enumerate(samples.region_names):
        mask = samples.region == k
        area = samples.area[mask]
        total = float(area.sum())
        sens = pred.sensitivity[mask] * 1e-3
        seen = [float(area[coverage[mask] >= m].sum() / total) for m in (1, 2, 3, need[name])]
        strain_sigma = disp_sigma = None
        if strain is not None:
            eps, disp = strain
            strain_sigma = {f"eps_{c}": percentiles(eps[mask, j] * 1e6)
                            for j, c in enumerate(STRAIN_COMPONENTS)}
            disp_sigma = percentiles(disp[mask] * 1e6)
        regions[name] = RegionSummary(
            area_m2=total, importance=float(samples.region_importance[k]), n_samples=int(mask.sum()),
            seen_by_1_or_more=seen[0], seen_by_2_or_more=seen[1], seen_by_3_or_more=seen[2],
            min_cameras=need[name], seen_by_min_cameras=seen[3],
            cameras={cam: round(float(area[pred.usable[i, mask]].sum() / total), 4)
                     for i, cam in enumerate(vis.camera_names) if pred.usable[i, mask].any()},
            sigma_max_um=percentiles(pred.sigma_max[mask] * 1e6,
                                      pred.outlier[mask] | pred.edge_limited[mask]),
            n_outliers=int(pred.outlier[mask].sum()),
            n_edge_limited=int(pred.edge_limited[mask].sum()),
            unmeasured_fraction=float(area[~pred.measured[mask]].sum() / total),
            sensitivity_mpx_per_um={a: float(np.average(sens[:, j], weights=area))
                                    for j, a in enumerate("xyz")},
            sigma_axis_um={a: percentiles(pred.sigma_xyz[mask, j] * 1e6) for j, a in enumerate("xyz")},
            sigma_strain_microstrain=strain_sigma, sigma_dic_max_um=disp_sigma)
    ev = exp.evaluation
    settings = EvaluationSettings(
        incidence_limit_deg=math.degrees(ev.incidence_limit), sample_spacing_mm=ev.sample_spacing * 1e3,
        patch_mm=ev.patch_size * 1e3, n_samples=len(samples), n_cameras=len(vis.camera_names),
        analysis=table_dict(exp.analysis), usable_weight=usable.USABLE_WEIGHT,
        edge_fraction=usable.EDGE_FRACTION, outlier_factor=usable.OUTLIER_FACTOR)
    return EvaluationResult(experiment=exp.name, config=str(exp.path), settings=settings, regions=regions)


def write_json(path: Path, data: dict) -> None:
    Path(path).write_text(json.dumps(data, indent=2) + "\n")


def write_config(path: Path, exp: Experiment, comment: list[str] | None = None) -> None:
    """The resolved experiment as TOML at `path`, after `comment`'s lines as TOML comments."""
    head = "".join(f"# {line}\n" for line in comment or ())
    Path(path).write_text(head + tomli_w.dumps(exp.to_dict()))
