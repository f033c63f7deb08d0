"""From an experiment to the predicted fields: the inputs `vdo.objective` takes, assembled once.

The cameras, samples and ray-cast occlusion come from `vdo.scene` and `vdo.visibility`; contrast
and noise from the light and sensor models (`vdo.lighting`); the speckle's gradient energy from its
power spectrum (`vdo.speckle`). `evaluate` reports the fields; `optimize` differentiates the score.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from . import objective
from .camera import Camera
from .config import Experiment
from .lighting import Illumination, pattern_stats, photometry
from .scene import SurfaceSamples
from .speckle import GradientEnergyTable, gradient_energy_table, normalise, pattern_for
from .visibility import Visibility


@dataclass(frozen=True, eq=False)
class SpeckleModel:
    """The pattern tile, its statistics and its gradient-energy table."""

    pattern: np.ndarray
    mean: float
    std: float
    table: GradientEnergyTable


def speckle_model(exp: Experiment) -> SpeckleModel:
    pattern = pattern_for(exp.speckle)
    mean, std = pattern_stats(pattern)
    table = gradient_energy_table(normalise(pattern), exp.speckle.texel,
                                  l_max=max(50 * exp.speckle.dot_diameter, 0.05))
    return SpeckleModel(pattern, mean, std, table)


def settings(exp: Experiment) -> objective.Settings:
    """The objective's settings for an experiment. The score's per-pair work in float32 (the
    per-sample sums, the score and the report fields in float64): on the 10-camera x 100k-sample
    benchmark, value within 4e-8 and gradient within 8e-6 of float64 and value + gradient ~1.5x
    faster (`vdo.objective.Settings.pair_dtype`, `benchmarks/README.md`)."""
    return objective.Settings(patch_area=exp.evaluation.patch_size ** 2,
                              incidence_limit=exp.evaluation.incidence_limit,
                              pair_dtype="float32")


def samples_for_objective(exp: Experiment, samples: SurfaceSamples) -> objective.Samples:
    minimum = [r.min_cameras or exp.evaluation.min_cameras for r in exp.regions]
    return objective.Samples(*(jnp.asarray(a) for a in (
        samples.points, samples.normals, samples.tangent_u, samples.tangent_v, samples.area,
        samples.region)), jnp.asarray(samples.region_importance, dtype=float),
        jnp.asarray(minimum, dtype=float))


def view_data(exp: Experiment, samples: objective.Samples, vis: Visibility,
              illumination: Illumination, speckle: SpeckleModel) -> objective.ViewData:
    """Occlusion from the ray cast, contrast and noise (DN) from the light and sensor models, as
    the sparse pair list of `objective.ViewData` over `samples`: the pairs the ray cast found
    unoccluded (it marks pairs that failed a geometric test, behind, outside the image or facing
    away, as occluded), exact for these cameras."""
    pho = photometry(illumination, exp.speckle, exp.sensor, speckle.mean, speckle.std,
                     len(vis.camera_names))
    return objective.ViewData.from_dense(np.asarray(vis.unoccluded, dtype=float),
                                         np.asarray(pho.contrast), np.asarray(pho.noise), samples)


@dataclass(frozen=True, eq=False)
class Prediction:
    """Per-sample fields in SI units (numpy). Sigmas are the Cramér-Rao bound for one noisy image
    against a noise-free reference (x sqrt(2) when both images are noisy); +inf where fewer than
    two usable, non-parallel views make the 3D displacement unmeasurable."""

    sensitivity: np.ndarray   # (N, 3) pixel/m
    sigma_max: np.ndarray     # (N,) m
    sigma_xyz: np.ndarray     # (N, 3) m
    measured: np.ndarray      # (N,) bool
    information: np.ndarray   # (N, 3, 3) 1/m^2, C for the patch area Omega (evaluation.patch_mm^2)


def predict(exp: Experiment, cameras: list[Camera], samples: SurfaceSamples, vis: Visibility,
            illumination: Illumination, speckle: SpeckleModel) -> Prediction:
    smp = samples_for_objective(exp, samples)
    f = objective.fields(objective.CameraParams.from_cameras(cameras), smp,
                         view_data(exp, smp, vis, illumination, speckle), speckle.table,
                         settings(exp))
    return Prediction(np.asarray(f.sensitivity), np.asarray(f.sigma_max), np.asarray(f.sigma_xyz),
                      np.asarray(f.measured), np.asarray(f.information))
