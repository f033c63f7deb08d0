"""From an experiment to the predicted fields: the inputs `vdo.objective` takes, assembled once.

The cameras, samples and ray-cast occlusion come from `vdo.scene` and `vdo.physics.visibility`; contrast
and noise from the light and sensor models (`vdo.physics.lighting`); the speckle's gradient energy from its
power spectrum (`vdo.model.speckle`). `evaluate` reports the fields; `optimize` differentiates the score.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from vdo import objective
from vdo.physics import usable
from vdo.model.camera import Camera
from vdo.config.rig import Evaluation, RegionSpec, SpeckleSpec
from vdo.model.sensor import SensorModel
from vdo.physics.lighting import Illumination, pattern_stats, photometry
from vdo.scene import SurfaceSamples
from vdo.model.speckle import GradientEnergyTable, gradient_energy_table, normalise, pattern_for
from vdo.physics.visibility import Visibility


CURVED_PATCH_SPREAD = 0.05   # rad: above this spread of normals over a patch (L / R on a
# surface of radius R), its information is summed over its own surface points (docs/theory.md)


@dataclass(frozen=True, eq=False)
class SpeckleModel:
    """The pattern tile, its statistics and its gradient-energy table."""

    pattern: np.ndarray
    mean: float
    std: float
    table: GradientEnergyTable


def speckle_model(speckle_spec: SpeckleSpec) -> SpeckleModel:
    """The model of the [speckle] table's pattern."""
    pattern = pattern_for(speckle_spec)
    mean, std = pattern_stats(pattern)
    table = gradient_energy_table(normalise(pattern), speckle_spec.texel,
                                  l_max=max(50 * speckle_spec.dot_diameter, 0.05))
    return SpeckleModel(pattern, mean, std, table)


def settings(evaluation: Evaluation) -> objective.Settings:
    """The objective's settings for an experiment's [evaluation] table. The score's per-pair work
    in float32 (the per-sample sums, the score and the report fields in float64): on the
    10-camera x 100k-sample benchmark, value within 4e-8 and gradient within 8e-6 of float64 and
    value + gradient ~1.5x faster (`vdo.objective.Settings.pair_dtype`, `benchmarks/README.md`)."""
    return objective.Settings(patch_area=evaluation.patch_size ** 2,
                              incidence_limit=evaluation.incidence_limit,
                              pair_dtype="float32")


def samples_for_objective(regions: tuple[RegionSpec, ...],
                          samples: SurfaceSamples) -> objective.Samples:
    """The samples as `vdo.objective` takes them, with each [[region]]'s min_cameras."""
    minimum = [r.min_cameras for r in regions]
    return objective.Samples(*(jnp.asarray(a) for a in (
        samples.points, samples.normals, samples.tangent_u, samples.tangent_v, samples.area,
        samples.region)), jnp.asarray(samples.region_importance, dtype=float),
        jnp.asarray(minimum, dtype=float))


def view_data(speckle_spec: SpeckleSpec, sensor: SensorModel, samples: objective.Samples,
              vis: Visibility, illumination: Illumination, speckle: SpeckleModel,
              patch_fraction: np.ndarray | None = None, sizes: dict | None = None,
              noise_scale: np.ndarray | None = None,
              exposure: np.ndarray | None = None) -> objective.ViewData:
    """Occlusion from the ray cast, contrast and noise (DN) from the light and sensor models, as
    the sparse pair list of `objective.ViewData` over `samples`: the pairs the ray cast found
    unoccluded (it marks pairs that failed a geometric test, behind, outside the image or facing
    away, as occluded), exact for these cameras. With `patch_fraction` (C, N) (`vdo.physics.usable`:
    phi_i, the usable fraction of each camera's patch) the occlusion is multiplied by it, so
    that the patch area becomes Omega phi_i. `sizes`: fixed list sizes across layouts
    (`objective.ViewData.from_dense`). `noise_scale` (C, N): a factor on each pair's noise
    (`vdo.physics.measured.noise_inflation`: the information of what the lab measures).
    `exposure` (C,): the light each camera gathers against the sensor's reference
    (`vdo.physics.lighting.exposure_factors`; None: 1). `speckle_spec` and `sensor`: the
    [speckle] and [sensor] tables."""
    pho = photometry(illumination, speckle_spec, sensor, speckle.mean, speckle.std,
                     len(vis.camera_names), exposure)
    occlusion = np.asarray(vis.unoccluded, dtype=float)
    if patch_fraction is not None:
        occlusion = occlusion * patch_fraction
    noise = np.asarray(pho.noise) if noise_scale is None else np.asarray(pho.noise) * noise_scale
    return objective.ViewData.from_dense(occlusion, np.asarray(pho.contrast), noise, samples,
                                         sizes=sizes)


@dataclass(frozen=True, eq=False)
class Prediction:
    """Per-sample fields in SI units (numpy). Sigmas are the Cramér-Rao bound for one noisy image
    against a noise-free reference (x sqrt(2) when both images are noisy), over the DIC patch
    clipped to the usable surface (`vdo.physics.usable`); +inf where fewer than two usable, non-parallel
    views make the 3D displacement unmeasurable. `usable` (C, N) is `vdo.physics.usable.usable_views`;
    coverage, patch_fraction, edge_limited and outlier are `vdo.physics.usable.flags`."""

    sensitivity: np.ndarray   # (N, 3) pixel/m, every view by its soft weight (not only usable ones)
    sigma_max: np.ndarray     # (N,) m
    sigma_xyz: np.ndarray     # (N, 3) m
    measured: np.ndarray      # (N,) bool
    information: np.ndarray   # (N, 3, 3) 1/m^2, C for the (clipped) patch
    usable: np.ndarray        # (C, N) bool
    coverage: np.ndarray      # (N,) int: usable views
    patch_fraction: np.ndarray  # (N,) fraction of the patch usable by >= 2 views
    edge_limited: np.ndarray  # (N,) bool
    outlier: np.ndarray       # (N,) bool


def predict(regions: tuple[RegionSpec, ...], evaluation: Evaluation, speckle_spec: SpeckleSpec,
            sensor: SensorModel, cameras: list[Camera], samples: SurfaceSamples, vis: Visibility,
            illumination: Illumination, speckle: SpeckleModel,
            clip_patch: bool = True, overlap=None, sizes: dict | None = None,
            exposure: np.ndarray | None = None) -> Prediction:
    """The report fields with the usable-view definition and the clipped patch of `vdo.physics.usable`:
    a first pass gives the soft weights, hence the usable views and each camera's usable patch
    fraction phi_i; the second pass weights each pair by phi_i (Omega_i = phi_i Omega). With
    `clip_patch` False every usable view keeps the whole patch (phi_i = 1): for samples that each
    stand for one whole correlated patch (`vdo.dic.validate`), not for points of a sampled surface.
    `overlap`: `usable.patch_overlap(samples, patch_size)` when already known (it depends on the
    samples' parametric cells only, not on the cameras or on a keyframe's motion). `sizes`: the
    pair lists' fixed sizes for these samples (`objective.ViewData.from_dense`): a new layout
    then compiles nothing. `regions`, `evaluation`, `speckle_spec`, `sensor`: the experiment's
    [[region]], [evaluation], [speckle] and [sensor] tables; `exposure` (C,) the cameras' light
    factors (`view_data`).

    Curved surfaces: where the normals over a sample's patch spread by more than
    CURVED_PATCH_SPREAD (`vdo.physics.usable.patch_normal_spread`), its information is the sum over
    the patch's own cells, each with its own normal, frame and view
    (`vdo.physics.usable.surface_patch_information`), instead of the centre's view times phi_i."""
    smp = samples_for_objective(regions, samples)
    cams = objective.CameraParams.from_cameras(cameras)
    st = settings(evaluation)
    first_views = view_data(speckle_spec, sensor, smp, vis, illumination, speckle, sizes=sizes,
                            exposure=exposure)
    first = objective.fields(cams, smp, first_views, speckle.table, st)
    use = usable.usable_views(np.asarray(first.weights))
    if overlap is None:
        overlap = usable.patch_overlap(samples, evaluation.patch_size)
    phi = usable.patch_fractions(overlap, use) if clip_patch else use.astype(float)
    f = objective.fields(cams, smp, view_data(speckle_spec, sensor, smp, vis, illumination, speckle,
                                              phi, sizes, exposure=exposure), speckle.table, st)
    information = np.asarray(f.information)
    f_measured, f_sigma_max, f_sigma_xyz = (np.array(x) for x in (f.measured, f.sigma_max, f.sigma_xyz))
    curved = np.flatnonzero(usable.patch_normal_spread(overlap, samples.normals) > CURVED_PATCH_SPREAD) \
        if clip_patch else np.zeros(0, dtype=int)
    if len(curved):
        per_camera = np.asarray(objective.camera_information(cams, smp, first_views, speckle.table, st))
        information = information.copy()
        information[curved] = usable.surface_patch_information(overlap, use, per_camera, curved)
        f_measured[curved], f_sigma_max[curved], f_sigma_xyz[curved] = sigmas(information[curved],
                                                                              st.rank_rtol)
    measured = f_measured & (use.sum(axis=0) >= 2)
    sigma_max = np.where(measured, f_sigma_max, np.inf)
    sigma_xyz = np.where(measured[:, None], f_sigma_xyz, np.inf)
    flag = usable.flags(overlap, use, sigma_max, measured, samples.region)
    return Prediction(np.asarray(first.sensitivity), sigma_max, sigma_xyz, measured,
                      information, use, flag["coverage"], flag["patch_fraction"],
                      flag["edge_limited"], flag["outlier"])


def sigmas(information: np.ndarray, rank_rtol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(measured (N,), sigma_max (N,) m, sigma_xyz (N, 3) m) of information matrices C (N, 3, 3)
    in 1/m^2: Sigma = C^-1, sigma_max = lam_min(C)^(-1/2), sigma_xyz = sqrt(diag Sigma); not
    measured (+inf) where lam_min <= rank_rtol lam_max (as `vdo.objective.fields`)."""
    C = np.asarray(information, dtype=float)
    tc = np.trace(C, axis1=-2, axis2=-1)
    scale = np.where(tc > 0, tc, 1.0)
    lam, V = np.linalg.eigh(C / scale[:, None, None])
    measured = (tc > 0) & (lam[:, 0] > rank_rtol * lam[:, 2])
    safe = np.where(measured[:, None], lam, 1.0)
    var = np.einsum("nkj,nj->nk", V * V, 1.0 / safe) / scale[:, None]
    return (measured, np.where(measured, 1.0 / np.sqrt(safe[:, 0] * scale), np.inf),
            np.where(measured[:, None], np.sqrt(var), np.inf))
