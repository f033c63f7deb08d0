"""Tables written into a run folder: the camera layout and the per-region summary."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import tomli_w

from vdo.physics import usable
from vdo.model.camera import Camera
from vdo.config.experiment import Experiment, table_dict
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


def _percentiles(values_um: np.ndarray, flagged: np.ndarray | None = None) -> dict:
    """p50, p95 and max over the measured (finite) values, and max_unflagged: the max over those
    not flagged as outliers or edge-limited."""
    finite = np.isfinite(values_um)
    if not finite.any():
        return {"p50": None, "p95": None, "max": None, "max_unflagged": None}
    plain = values_um[finite] if flagged is None else values_um[finite & ~flagged]
    return {"p50": float(np.percentile(values_um[finite], 50)),
            "p95": float(np.percentile(values_um[finite], 95)),
            "max": float(values_um[finite].max()),
            "max_unflagged": float(plain.max()) if plain.size else None}


def state_summary(state: LayoutState) -> dict:
    """The per-region table of a judged layout (`summary` of its pieces)."""
    return summary(state.experiment, state.samples, state.visibility, state.prediction,
                   state.strain)


def summary(exp: Experiment, samples: SurfaceSamples, vis: Visibility, pred: Prediction,
            strain=None) -> dict:
    """Per region: area (m^2), the area fractions seen by >= 1, 2, 3 usable views
    (`vdo.physics.usable`), which cameras are usable views of it (fraction of its area), sigma_max
    p50/p95/max/max_unflagged (um, over the measured samples), the counts of outlier and
    edge-limited samples, the unmeasured area fraction, and the mean global sensitivity per axis
    (mpixel/um). With `strain` = (sigma_strain (N, 3), sigma_dic (N,) m) from
    `vdo.physics.strain.analysis_fields`: per-axis sigma percentiles (um), strain sigma percentiles per
    face-frame component (microstrain) and the analysis' displacement sigma."""
    coverage = pred.coverage
    regions = {}
    for k, name in enumerate(samples.region_names):
        mask = samples.region == k
        area = samples.area[mask]
        total = float(area.sum())
        sens = pred.sensitivity[mask] * 1e-3
        regions[name] = {
            "area_m2": total,
            "importance": float(samples.region_importance[k]),
            "n_samples": int(mask.sum()),
            **{f"seen_by_{m}_or_more": float(area[coverage[mask] >= m].sum() / total) for m in (1, 2, 3)},
            "cameras": {cam: round(float(area[pred.usable[i, mask]].sum() / total), 4)
                        for i, cam in enumerate(vis.camera_names) if pred.usable[i, mask].any()},
            "sigma_max_um": _percentiles(pred.sigma_max[mask] * 1e6,
                                         pred.outlier[mask] | pred.edge_limited[mask]),
            "n_outliers": int(pred.outlier[mask].sum()),
            "n_edge_limited": int(pred.edge_limited[mask].sum()),
            "unmeasured_fraction": float(area[~pred.measured[mask]].sum() / total),
            "sensitivity_mpx_per_um": {a: float(np.average(sens[:, j], weights=area))
                                       for j, a in enumerate("xyz")},
            "sigma_axis_um": {a: _percentiles(pred.sigma_xyz[mask, j] * 1e6)
                              for j, a in enumerate("xyz")},
        }
        if strain is not None:
            eps, disp = strain
            regions[name] |= {
                "sigma_strain_microstrain": {f"eps_{c}": _percentiles(eps[mask, j] * 1e6)
                                             for j, c in enumerate(STRAIN_COMPONENTS)},
                "sigma_dic_max_um": _percentiles(disp[mask] * 1e6)}
    ev = exp.evaluation
    return {"experiment": exp.name, "config": str(exp.path),
            "settings": {"incidence_limit_deg": math.degrees(ev.incidence_limit),
                         "sample_spacing_mm": ev.sample_spacing * 1e3, "patch_mm": ev.patch_size * 1e3,
                         "n_samples": len(samples), "n_cameras": len(vis.camera_names),
                         "sigma": SIGMA_MEANING, "analysis": table_dict(exp.analysis),
                         "strain": STRAIN_MEANING, "usable_weight": usable.USABLE_WEIGHT,
                         "edge_fraction": usable.EDGE_FRACTION,
                         "outlier_factor": usable.OUTLIER_FACTOR,
                         "usable": USABLE_MEANING},
            "regions": regions}


def write_json(path: Path, data: dict) -> None:
    Path(path).write_text(json.dumps(data, indent=2) + "\n")


def write_config(path: Path, exp: Experiment) -> None:
    Path(path).write_text(tomli_w.dumps(exp.to_dict()))
