"""Tables written into a run folder: the camera layout and the per-region summary."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import tomli_w

from . import usable
from .camera import Camera
from .config import Experiment
from .predict import Prediction
from .scene import SurfaceSamples
from .visibility import Visibility


def layout(cameras: list[Camera]) -> dict:
    """Per camera: name, width, height, K, R, t with x ~ K (R X + t) (OpenCV convention, metres),
    plus the pose in words (optical centre, pan/tilt/roll in degrees, focal length in mm)."""
    return {"convention": "OpenCV: x ~ K (R X + t); camera x right, y down, z forward; pixel (0,0) "
                          "is the centre of the top-left pixel; world z up; metres",
            "cameras": [{"name": c.name, "width": c.width, "height": c.height,
                         "K": c.K.tolist(), "R": c.R.tolist(), "t": c.t.tolist(),
                         "position_m": np.asarray(c.position).tolist(),
                         "pan_deg": math.degrees(c.pan), "tilt_deg": math.degrees(c.tilt),
                         "roll_deg": math.degrees(c.roll), "focal_mm": c.focal_length * 1e3,
                         "pixel_um": c.pixel_size * 1e6} for c in cameras]}


SIGMA_MEANING = ("Cramér-Rao bound of the 3D displacement for one noisy image against a noise-free "
                 "reference, over a patch of patch_mm x patch_mm (multiply by sqrt(2) when the "
                 "reference image is noisy too); percentiles over the measured points")


USABLE_MEANING = ("a camera counts (coverage, seen_by_*, cameras) where its soft weight is >= "
                  "usable_weight; sigma uses only those views, over the DIC patch clipped to the "
                  "surface they see; n_edge_limited: samples with less than edge_fraction of their "
                  "patch usable by >= 2 views; n_outliers: samples with sigma_max above "
                  "outlier_factor x the region's median; max_unflagged leaves both out")


def _percentiles(values_um: np.ndarray, flagged: np.ndarray) -> dict:
    """p50, p95 and max over the measured (finite) values, and max_unflagged: the max over those
    not flagged as outliers or edge-limited."""
    finite = np.isfinite(values_um)
    if not finite.any():
        return {"p50": None, "p95": None, "max": None, "max_unflagged": None}
    plain = values_um[finite & ~flagged]
    return {"p50": float(np.percentile(values_um[finite], 50)),
            "p95": float(np.percentile(values_um[finite], 95)),
            "max": float(values_um[finite].max()),
            "max_unflagged": float(plain.max()) if plain.size else None}


def summary(exp: Experiment, samples: SurfaceSamples, vis: Visibility, pred: Prediction) -> dict:
    """Per region: area (m^2), the area fractions seen by >= 1, 2, 3 usable views
    (`vdo.usable`), which cameras are usable views of it (fraction of its area), sigma_max
    p50/p95/max/max_unflagged (um, over the measured samples), the counts of outlier and
    edge-limited samples, the unmeasured area fraction, and the mean global sensitivity per axis
    (mpixel/um)."""
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
        }
    ev = exp.evaluation
    return {"experiment": exp.name, "config": str(exp.path),
            "settings": {"incidence_limit_deg": math.degrees(ev.incidence_limit),
                         "sample_spacing_mm": ev.sample_spacing * 1e3, "patch_mm": ev.patch_size * 1e3,
                         "n_samples": len(samples), "n_cameras": len(vis.camera_names),
                         "sigma": SIGMA_MEANING, "usable_weight": usable.USABLE_WEIGHT,
                         "edge_fraction": usable.EDGE_FRACTION,
                         "outlier_factor": usable.OUTLIER_FACTOR,
                         "usable": USABLE_MEANING},
            "regions": regions}


def write_json(path: Path, data: dict) -> None:
    Path(path).write_text(json.dumps(data, indent=2) + "\n")


def write_config(path: Path, exp: Experiment) -> None:
    Path(path).write_text(tomli_w.dumps(exp.to_dict()))
