"""The predicted uncertainty against correlation on vdo's own renders: the computation of
`vdo validate` (`run_cases`; `vdo.commands.validate` writes the run folder).

For each case of a validation file (experiments/validation.toml, schema in docs/validation.md):

1. a planar speckled plate (tilted by `tilt_deg` about the world x axis; its normal is +z when
   frontal) is rendered by Mitsuba (`vdo.render.build_render_scene`, ambient light only) through each
   camera, once as it is (reference) and once translated by the imposed 3D displacement U, the
   texture moving with the plate. The renders are linear and noise-free: a constant environment
   sampled by cosine-weighted BSDF sampling on a Lambertian plate has zero Monte Carlo variance, and
   the stratified sampler without jitter integrates each box pixel by a fixed midpoint grid, so the
   only noise in the experiment is the sensor's;
2. the uncertainty of the correlated patch is predicted by `vdo.physics.predict.predict` (the mean-field
   Cramér–Rao bound for ONE noisy image against a perfect reference) with the DIC patch area Ω equal
   to the correlated patch;
3. for each seed, independent sensor noise is drawn for the reference and the displaced image of
   every camera (`vdo.render.expose`, distinct seeds), and U is measured by global multi-view
   correlation (`vdo.dic.correlate.correlate`, `Translation` model, `ImageReference`: each camera
   against its own noisy reference image);
4. the scatter of the measured U over the seeds is compared with the prediction. Both images are
   noisy, so the expected standard deviation is √2 σ_predicted, and

       ratio = sigma_measured / (√2 sigma_predicted)      (1 when the model is right).

   Each ratio is judged by its χ² interval from the seed count (`vdo.dic.verdicts.judge`), at 95 %
   confidence jointly over the run's ratios (Bonferroni): "within" the band [0.8, 1.25], "outside"
   it (the run fails), or "inconclusive" when the interval holds a band edge (too few seeds to
   tell; `seeds_to_decide` says how many would).

With one camera only the in-plane axes are reported: the depth is seen through perspective alone.
The model's one-camera information is rank 2 (`predict` reports +inf), so its in-plane bound is the
limit of adding a vanishingly weak second view: a probe camera 35x and 55x farther away, whose information
is ~1e-7 of the first (`_predict_sigma`, checked to converge).

Pair cases (`processing = "pairs"`, the experiment's [analysis] keys): the cameras are processed as
stereo pairs, as a lab does with stereo DIC software. The pairs that serve the patch are those of
`vdo.physics.measured.pair_candidates` (the declared `stereo_pairs`, or every two cameras whose rays
make an angle in [stereo_min_angle(lens), max_pair_angle_deg]) at every prediction sample of the
patch (`serving_pairs`). Each pair is correlated on its own (two cameras, the same global
correlation), and the pairs' displacements are merged as `vdo.physics.measured.pair_merge` defines
it, u = Σ_p A_p u_p ("best": the pair of least σ_max; "fusion": A_p = (Σ_q Cov_q⁻¹)⁻¹ Cov_p⁻¹), with
the patch's per-camera information C_i (`camera_information`) and Cov_p = (C_a + C_b)⁻¹ (the bound:
M_i = C_i). The prediction is `vdo.physics.measured.merge_pairs`' covariance of that merged
estimate (pairs sharing a camera share its noise), reported beside the all-views bound of the
same cameras (`PairPrediction`); the same √2 and ratio.

Strain cases (`strain_microstrain` = [eps_uu, eps_vv, eps_uv] in the plate's face frame): the
deformed plate is also strained homogeneously about the patch centre (X -> X + U + T E Tᵀ X, its
texture strained with it: `DeformedFaces`), correlated with a Q4 mesh of the patch (`q4_mesh`),
and the strain at the centre of the middle element (`measured_strain`) is compared with
`vdo.physics.strain` for that mesh (`predict_strain_sigma`: Σ_u = Ω C⁻¹ of the patch and the finite
mesh's own gradient factors), with the same √2 and the same ratio.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from vdo import objective
from vdo.constraints import stereo_min_angle
from vdo.physics import measured, strain
from vdo.geometry.plate import check_cases, deform, plate_geometry
from vdo.model.camera import Camera
from vdo.model.pose import look_at_angles
from vdo.config import validation
from vdo.config.validation import Case, ValidationSpec
from vdo.dic.correlate import ImageReference, PixelIntegration, Q4, Translation, correlate
from vdo.dic.patch import Patch
from vdo.dic.cases import Setup, build_setup, render_case, speckle_model_of
from vdo.dic.verdicts import VERDICTS, judge, ratio_interval
from vdo.core.errors import ConfigError
from vdo.physics.lighting import pattern_stats
from vdo.physics.predict import samples_for_objective, settings, view_data
from vdo.render import expose, noise_free_dn
from vdo.scene import SurfaceSamples
from vdo.physics.usable import patch_overlap
from vdo.state import Geometry, layout_state

log = logging.getLogger(__name__)

AXES = "xyz"
STRAIN_AXES = ("eps_uu", "eps_vv", "eps_uv")
UM = 1e6
SQRT2 = math.sqrt(2.0)


def load(path) -> ValidationSpec:
    """Read a validation file (`vdo.config.validation.load`: every field of every case) and check
    every case's geometry (`vdo.geometry.plate.check_cases`); ConfigError (file, field, message)
    on any mistake, before any render."""
    spec = validation.load(path)
    check_cases(spec)
    check_pairs(spec)
    return spec


def check_pairs(spec: ValidationSpec) -> None:
    """Every pair case's pairs by the pair rule at its patch (`serving_pairs`): ConfigError (file,
    case field, fix) when a declared pair does not serve the patch, or no pair does; no render."""
    for case in spec.cases:
        if case.processing == "pairs":
            serving_pairs(build_setup(case, spec.path, painted=False))


# --------------------------------------------------------------------------------------------
# Prediction
# --------------------------------------------------------------------------------------------
def _samples(setup: Setup, n: int = 5):
    """n x n samples on the correlated patch (cell centres), as vdo.scene.SurfaceSamples."""

    w, h = setup.case.patch
    a, b = np.meshgrid((np.arange(n) + 0.5) / n * w, (np.arange(n) + 0.5) / n * h, indexing="ij")
    xi = np.stack([a.ravel(), b.ravel()], 1)
    pts = setup.patch.points(xi)
    m = len(pts)
    return SurfaceSamples(points=pts, normals=np.tile(setup.patch.normal, (m, 1)),
                          tangent_u=np.tile(setup.patch.t_u, (m, 1)),
                          tangent_v=np.tile(setup.patch.t_v, (m, 1)),
                          uv=setup.region.uv(pts), area=np.full(m, w * h / m),
                          region=np.zeros(m, dtype=int), region_names=("patch",),
                          region_importance=np.ones(1))


def _probe_camera(setup: Setup, factor: float):
    """A vanishingly weak extra view for the one-camera case: 30 deg off the first camera's
    axis, `factor` times farther away with the same lens (pixel footprint x factor)."""

    c = setup.case.cameras[0]
    polar = c.polar + math.radians(30.0)
    pos = factor * c.distance * np.array([math.sin(polar) * math.cos(c.azimuth),
                                          math.sin(polar) * math.sin(c.azimuth), math.cos(polar)])
    pan, tilt = look_at_angles(pos, np.zeros(3))
    return Camera(name="probe", width=c.pixels[0], height=c.pixels[1], pixel_size=c.pixel_size,
                  focal_length=c.focal_length, position=pos, pan=pan, tilt=tilt)


def _predict_once(setup: Setup, cameras, speckle) -> np.ndarray:
    """Per-axis sigma (m) of the correlated patch: vdo.physics.predict at n x n samples (each with Ω = the
    patch area), combined as the patch's mean information, 1 / mean(1 / σ²) per axis (exact when
    the per-sample covariances differ by a scale only; over a small patch they differ by < 1 %)."""

    # One camera: the model's information is rank 2 at every sample, its null direction the ray
    # through the sample, which tilts away from the normal off the optical axis; only at the patch
    # centre (on the axis) is the in-plane marginal the weak-probe limit. There the in-plane bound
    # is that of the centred patch (first-order variations over the patch cancel).
    pred = _prediction(setup, cameras, speckle, 5 if len(setup.case.cameras) > 1 else 1)
    return 1.0 / np.sqrt(np.mean(1.0 / pred.sigma_xyz ** 2, axis=0))


def _prediction(setup: Setup, cameras, speckle, n: int):
    """vdo.physics.predict at n x n samples of the correlated patch (each with Ω = the patch area)."""
    samples = _samples(setup, n)
    geometry = Geometry(setup.experiment, (setup.plate,), samples, speckle, (setup.region,),
                        patch_overlap(samples, setup.experiment.evaluation.patch_size))
    pred = layout_state(geometry, cameras, clip_patch=False).prediction
    if not np.all(pred.measured):
        raise RuntimeError(f"case {setup.case.name!r}: the prediction leaves part of the patch "
                           "unmeasured")
    return pred


def centre_element(case: Case) -> tuple[int, int]:
    """The Q4 element whose centre strain a strain case reads: the middle one."""
    return case.q4_mesh[0] // 2, case.q4_mesh[1] // 2


def predict_strain_sigma(setup: Setup) -> np.ndarray:
    """(3,) predicted sigma of (eps_uu, eps_vv, eps_uv) at the centre of `centre_element` of the
    case's Q4 mesh (single-image bound): vdo.physics.strain with Σ_u = Ω (mean C over 5 x 5 samples)⁻¹
    and the finite mesh's own factors (`vdo.physics.strain.q4_centre_gradient_factors`); or, for subset
    DIC, the virtual strain gauge's factor (`vdo.physics.strain.vsg_factor`)."""
    case = setup.case
    pred = _prediction(setup, setup.cameras, speckle_model_of(setup), 5)
    area = case.patch[0] * case.patch[1]
    sigma_u = strain.covariance_per_area(pred.information.mean(axis=0)[None], area, [True])
    if case.subsets is not None:
        F1 = F2 = float(strain.vsg_factor(*case.subsets))
    else:
        nx, ny = case.q4_mesh
        F1, F2 = strain.q4_centre_gradient_factors(nx, ny, *centre_element(case),
                                                   case.patch[0] / nx, case.patch[1] / ny)
    p = setup.patch
    return strain.strain_sigma(sigma_u, p.t_u[None], p.t_v[None], F1, F2)[0]


def measured_strain(setup: Setup, U_nodes: np.ndarray) -> np.ndarray:
    """(eps_uu, eps_vv, eps_uv) at the centre of `centre_element` from Q4 nodal displacements
    (nodes, 3) (world, m; node j * (nx + 1) + i): ∂U/∂ξ1 = (U_10 + U_11 - U_00 - U_01) / (2 h_x),
    ∂U/∂ξ2 likewise, projected on the face frame."""
    case, p = setup.case, setup.patch
    nx, ny = case.q4_mesh
    i, j = centre_element(case)
    hx, hy = case.patch[0] / nx, case.patch[1] / ny
    n00 = j * (nx + 1) + i
    u00, u10, u01, u11 = (U_nodes[n] for n in (n00, n00 + 1, n00 + nx + 1, n00 + nx + 2))
    d1 = (u10 + u11 - u00 - u01) / (2 * hx)
    d2 = (u01 + u11 - u00 - u10) / (2 * hy)
    return np.array([p.t_u @ d1, p.t_v @ d2, 0.5 * (p.t_u @ d2 + p.t_v @ d1)])


def predict_sigma(setup: Setup) -> np.ndarray:
    """(3,) predicted sigma per world axis (m), single-image bound. NaN out of plane for one
    camera (see the module docstring: a weak probe view, checked for convergence)."""
    speckle = speckle_model_of(setup)
    if len(setup.cameras) > 1:
        return _predict_once(setup, setup.cameras, speckle)
    a = _predict_once(setup, setup.cameras + [_probe_camera(setup, 35.0)], speckle)
    b = _predict_once(setup, setup.cameras + [_probe_camera(setup, 55.0)], speckle)
    inplane = np.abs(setup.patch.normal) < 0.5
    if np.any(np.abs(a[inplane] / b[inplane] - 1) > 2e-3):
        raise RuntimeError(f"case {setup.case.name!r}: the one-camera in-plane bound did not "
                           f"converge ({a} vs {b})")
    return np.where(inplane, b, np.nan)


# --------------------------------------------------------------------------------------------
# Pair processing
# --------------------------------------------------------------------------------------------
def serving_pairs(setup: Setup) -> tuple[tuple[int, int], ...]:
    """The stereo pairs (camera indices) that serve the whole correlated patch: those of
    `vdo.physics.measured.pair_candidates` (the experiment's rule: the declared pairs, or every two
    cameras whose rays make an angle in [stereo_min_angle(the shorter lens), max_pair_angle]) at
    every one of the 5 x 5 prediction samples (every camera sees the whole patch:
    `vdo.geometry.plate.check_cases`). ConfigError (file, case field, fix) when a declared pair
    does not serve, or no pair does; cheap (no render)."""
    case = setup.case
    samples = _samples(setup)
    seen = np.ones((len(setup.cameras), len(samples.points)), dtype=bool)
    pairs, cand = measured.pair_candidates(setup.experiment.analysis, setup.experiment.stereo_pairs,
                                           setup.cameras, samples, seen, stereo_min_angle)
    serve = cand.all(axis=1)
    where = f'case "{case.name}"'
    hi = math.degrees(setup.experiment.analysis.max_pair_angle
                      or math.radians(measured.DEFAULT_MAX_PAIR_ANGLE_DEG))
    centre = setup.patch.points(setup.patch.size / 2)

    def rule(a: int, b: int) -> str:
        ra, rb = (setup.cameras[i].position - centre for i in (a, b))
        angle = math.degrees(math.acos(np.clip(ra @ rb / np.linalg.norm(ra) / np.linalg.norm(rb), -1, 1)))
        lo = math.degrees(stereo_min_angle(min(setup.cameras[i].focal_length for i in (a, b))))
        return (f"{setup.cameras[a].name!r} and {setup.cameras[b].name!r}: {angle:.1f} deg between "
                f"their rays at the patch centre, the rule [{lo:.1f}, {hi:g}] deg")

    for k, (a, b) in enumerate(pairs):
        if case.pairs == "declared" and not serve[k]:
            raise ConfigError(setup.experiment.path, f"{where}.stereo_pairs[{k}]",
                              f"not a stereo pair by the pair rule over the whole patch ({rule(a, b)}): "
                              "declare cameras further apart or closer, or set max_pair_angle_deg")
    if not serve.any():
        raise ConfigError(setup.experiment.path, f"{where}.processing",
                          "no two cameras make a stereo pair by the pair rule over the whole patch "
                          f"(e.g. {rule(*pairs[0])}): move the cameras, set max_pair_angle_deg, "
                          'or use processing = "all-views"')
    return tuple(p for p, ok in zip(pairs, serve) if ok)


def camera_information(setup: Setup, speckle, n: int = 5) -> np.ndarray:
    """(C, n², 3, 3) 1/m², each camera's information at the n x n samples of the patch (each with
    Ω = the patch area): `vdo.objective.camera_information` with the views of `_prediction`'s
    second pass (every usable view keeps the whole patch); their sum is `_prediction`'s C."""
    exp = setup.experiment
    samples = _samples(setup, n)
    geometry = Geometry(exp, (setup.plate,), samples, speckle, (setup.region,),
                        patch_overlap(samples, exp.evaluation.patch_size))
    state = layout_state(geometry, setup.cameras, clip_patch=False)
    smp = samples_for_objective(exp.regions, samples)
    views = view_data(exp.speckle, exp.sensor, smp, state.visibility, state.illumination, speckle,
                      state.prediction.usable.astype(float))
    return np.asarray(objective.camera_information(objective.CameraParams.from_cameras(setup.cameras),
                                                   smp, views, speckle.table, settings(exp.evaluation)))


@dataclass(frozen=True, eq=False)
class PairPrediction:
    """The bound (one noisy image) of a pair case's merged displacement: `covariance` (3, 3) m²,
    beside the all-views bound of the same cameras, `all_views` (3, 3) m². `weights` (P, 3, 3):
    A_p of u = Σ_p A_p u_p over `pairs`; `naive` (3, 3) m²: what fusion ignoring the shared cameras
    would claim, (Σ_p Cov_p⁻¹)⁻¹ ("fusion"; else None)."""

    pairs: tuple[tuple[int, int], ...]
    weights: np.ndarray
    covariance: np.ndarray
    all_views: np.ndarray
    naive: np.ndarray | None

    @property
    def sigma(self) -> np.ndarray:
        """(3,) m, per world axis."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def sigma_all_views(self) -> np.ndarray:
        """(3,) m, per world axis, all views in one correlation."""
        return np.sqrt(np.diag(self.all_views))


def predict_pairs(setup: Setup, pairs) -> PairPrediction:
    """The merge of `pairs` (camera indices) per the case's rule with the patch's per-camera
    information C_i (the mean over the 5 x 5 samples, `camera_information`) and M_i = C_i (the
    bound): `vdo.physics.measured.pair_merge` (weights) and `merge_pairs` (covariance)."""
    C = camera_information(setup, speckle_model_of(setup)).mean(axis=1, keepdims=True)  # (C, 1, 3, 3)
    cand = np.ones((len(pairs), 1), dtype=bool)
    m = measured.pair_merge(C, C, list(pairs), cand, setup.case.merge)
    cov, ok, _, _ = measured.merge_pairs(C, C, list(pairs), cand, setup.case.merge)
    cov_all, ok_all = measured.all_views(C, C)
    if not (ok[0] and ok_all[0]):
        raise RuntimeError(f"case {setup.case.name!r}: the pairs leave the patch unmeasured")
    return PairPrediction(tuple(pairs), m.weights[:, 0], cov[0], cov_all[0],
                          None if m.naive is None else m.naive[0])


def merged_displacement(weights: np.ndarray, U_pairs) -> np.ndarray:
    """The pairs' merged displacement u = Σ_p A_p u_p (m): `weights` (P, 3, 3) the A_p of
    `vdo.physics.measured.pair_merge` (`PairPrediction.weights`), `U_pairs` (P, 3) the pairs' own."""
    return np.einsum("pij,pj->i", np.asarray(weights), np.asarray(U_pairs))


# --------------------------------------------------------------------------------------------
# Correlation
# --------------------------------------------------------------------------------------------
def noise_free_images(setup: Setup, deformed: bool) -> list:
    """The noise-free DN images (reference or deformed) of every camera."""
    images = setup.deformed_linear if deformed else setup.reference_linear
    return [noise_free_dn(im, setup.case.sensor) for im in images]


def noise_free_check(setup: Setup):
    """Correlate the noise-free renders. Returns (the CorrelationResults: one, one per subset or
    one per pair; per-camera error of the measured displacement at the patch centre projected into
    each image, (n_cameras, 2) px, NaN for a camera that no pair of a pair case uses: a pair's
    weak depth would show in a camera that does not measure)."""

    results = _correlate(setup, noise_free_images(setup, True), noise_free_images(setup, False))
    centre = setup.patch.points(setup.patch.size / 2)
    err = _centre_displacement(setup, results) - (deform(setup.case, centre) - centre)
    used = {i for pair in setup.pairs for i in pair} if setup.pairs else range(len(setup.cameras))
    px = np.array([cam.sensitivity(centre) @ err if i in used else np.full(2, np.nan)
                   for i, cam in enumerate(setup.cameras)])
    return results, px


def subset_patches(setup: Setup) -> list:
    """The n x n subsets of a subset-DIC case, centred in the patch on a grid of `step`, as
    `vdo.dic.patch.Patch`es; index k = j n + i, i along t_u."""
    side, step, n = setup.case.subsets
    p = setup.patch
    offsets = (np.arange(n) - (n - 1) / 2) * step + p.size[0] / 2 - side / 2, \
        (np.arange(n) - (n - 1) / 2) * step + p.size[1] / 2 - side / 2
    return [Patch(origin=p.origin + offsets[0][i] * p.t_u + offsets[1][j] * p.t_v, t_u=p.t_u,
                  t_v=p.t_v, size=np.array([side, side])) for j in range(n) for i in range(n)]


def _correlate(setup: Setup, deformed, references, xi=None) -> list:
    """The case's correlation(s) of `deformed` against `references`: one global correlation
    (translation or Q4), or one translation per subset. `xi`: the points of an earlier call."""
    case = setup.case
    if setup.pairs:         # each stereo pair on its own: two cameras, one translation
        return [correlate([setup.cameras[a], setup.cameras[b]], [deformed[a], deformed[b]],
                          setup.patch, ImageReference([references[a], references[b]]),
                          integration=PixelIntegration(None if xi is None else xi[k]))
                for k, (a, b) in enumerate(setup.pairs)]
    reference = ImageReference(references)
    if case.subsets is None:
        return [correlate(setup.cameras, deformed, setup.patch, reference, model=_model(case),
                          integration=PixelIntegration(None if xi is None else xi[0]))]
    return [correlate(setup.cameras, deformed, p, reference,
                      integration=PixelIntegration(None if xi is None else xi[k]))
            for k, p in enumerate(subset_patches(setup))]


def _subset_fit(setup: Setup, results) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane through the subsets' displacements: (mean U, (∂U/∂ξ1, ∂U/∂ξ2))."""
    side, step, n = setup.case.subsets
    U = np.array([r.U for r in results]).reshape(n, n, 3)        # [j, i]
    x = (np.arange(n) - (n - 1) / 2) * step
    w = x / (n * (x @ x))
    return U.mean(axis=(0, 1)), (np.einsum("i,jia->a", w, U), np.einsum("j,jia->a", w, U))


def _estimate(setup: Setup, results) -> np.ndarray:
    """U (translation; the pairs' merge Σ_p A_p U_p in a pair case) or the strain (eps_uu, eps_vv,
    eps_uv) from the correlation results."""
    case = setup.case
    if setup.pairs:
        return merged_displacement(setup.pair_weights, [r.U for r in results])
    if case.strain is None:
        return results[0].U
    if case.subsets is None:
        return measured_strain(setup, results[0].U)
    _, (d1, d2) = _subset_fit(setup, results)
    p = setup.patch
    return np.array([p.t_u @ d1, p.t_v @ d2, 0.5 * (p.t_u @ d2 + p.t_v @ d1)])


def _model(case: Case) -> Translation | Q4:
    return Translation() if case.strain is None else Q4(*case.q4_mesh)


def _centre_displacement(setup: Setup, results) -> np.ndarray:
    """The measured displacement at the patch centre: U itself (translation), the Q4 field
    interpolated there, the subsets' plane fit's value there (their mean), or the pairs' merge."""
    if setup.pairs:
        return _estimate(setup, results)
    if setup.case.subsets is not None:
        return _subset_fit(setup, results)[0]
    U = results[0].U
    if setup.case.strain is None:
        return U
    from vdo.dic.patch import q4_shape_functions
    nx, ny = setup.case.q4_mesh
    N = q4_shape_functions(setup.patch.size[None] / 2, setup.patch.size, nx, ny)
    return np.asarray(N @ U)[0]


def noise_sigma_dn(setup: Setup) -> float:
    """The modelled image noise (DN rms) at the mean gray level, as vdo.physics.lighting computes it."""

    sp, case = setup.case.speckle, setup.case
    mean_f, _ = pattern_stats(setup.pattern)
    mean_rho = sp.black_albedo + (sp.white_albedo - sp.black_albedo) * mean_f
    return float(case.sensor.noise_sigma_dn(mean_rho * case.ambient_radiance))


def correlate_seed(setup: Setup, k: int, xi) -> np.ndarray:
    """U (3,) (or the strain, for a strain case) measured with seed k: independent noise in the
    reference and deformed images. `xi`: one list of per-camera points per correlation."""

    case = setup.case
    base = (case.seed * 1_000_003 + 2 * k) & 0x7FFFFFFF
    refs = [expose(im, case.sensor, base, i).astype(np.float64)
            for i, im in enumerate(setup.reference_linear)]
    defs = [expose(im, case.sensor, base + 1, i).astype(np.float64)
            for i, im in enumerate(setup.deformed_linear)]
    results = _correlate(setup, defs, refs, xi)
    if not all(r.converged for r in results):
        raise RuntimeError(f"case {case.name!r}, seed {k}: correlation did not converge")
    return _estimate(setup, results)


# --------------------------------------------------------------------------------------------
# One case, all cases
# --------------------------------------------------------------------------------------------
def axes_reported(case: Case) -> list[int]:
    """World axes reported: all three, or the in-plane ones for a single camera."""
    if len(case.cameras) > 1:
        return [0, 1, 2]
    n = plate_geometry(case)["normal"]
    return [k for k in range(3) if abs(n[k]) < 0.5]


def run_case(case: Case, path: Path, seeds: int, progress=None) -> CaseResult:
    """Render, predict, correlate `seeds` times; returns the per-axis statistics and diagnostics.
    `progress`: called with 1 after each seed."""
    t0 = time.perf_counter()
    setup = build_setup(case, path)
    pair_pred = None
    if case.processing == "pairs":
        pair_pred = predict_pairs(setup, serving_pairs(setup))
        # only the pairs the merge uses are correlated ("best": one)
        used = np.flatnonzero(np.any(pair_pred.weights != 0, axis=(1, 2)))
        setup.pairs = tuple(pair_pred.pairs[k] for k in used)
        setup.pair_weights = pair_pred.weights[used]
    render_case(setup)
    t_render = time.perf_counter() - t0
    res0, px_err = noise_free_check(setup)
    sigma_dn = noise_sigma_dn(setup)
    cov = res0[0].covariance(sigma_dn)
    processing = "all-views" if pair_pred is None else f"pairs ({case.merge})"
    if pair_pred is not None:
        sigma_pred, truth, scale, unit, names = pair_pred.sigma, case.displacement, UM, "um", AXES
        reported, sigma_all = axes_reported(case), pair_pred.sigma_all_views
        # the one pair used: its own linear propagation; fused pairs share cameras, whose
        # cross-covariances correlate does not propagate
        sigma_lin = np.sqrt(np.diag(cov)) if len(setup.pairs) == 1 else np.full(3, np.nan)
    elif case.strain is None:
        sigma_pred, truth, scale, unit, names = predict_sigma(setup), case.displacement, UM, "um", AXES
        reported, sigma_all = axes_reported(case), None
        sigma_lin = np.sqrt(np.diag(cov))
    else:
        sigma_pred, truth, scale, unit = predict_strain_sigma(setup), case.strain, 1e6, "microstrain"
        names, reported, sigma_all = STRAIN_AXES, [0, 1, 2], None
        if case.subsets is None:
            G = np.array([measured_strain(setup, e.reshape(-1, 3)) for e in np.eye(len(cov))]).T
            sigma_lin = np.sqrt(np.diag(G @ cov @ G.T))
        else:       # the subsets' cross-covariances are not propagated by correlate
            sigma_lin = np.full(3, np.nan)
    estimates = np.empty((seeds, 3))
    for k in range(seeds):
        estimates[k] = correlate_seed(setup, k, [r.xi for r in res0])
        if progress is not None:
            progress(1)
    err = estimates - truth
    sigma_meas = err.std(axis=0, ddof=1)
    # the rows' *_um columns carry `unit`: micrometres, or microstrain for strain cases
    rows = []
    for a in reported:
        expected = SQRT2 * sigma_pred[a]
        ratio = sigma_meas[a] / expected
        lo, hi = ratio_interval(ratio, seeds)
        rows.append({"case": case.name, "axis": names[a], "sigma_predicted_um": sigma_pred[a] * scale,
                     "sigma_measured_um": sigma_meas[a] * scale, "ratio": ratio, "n_seeds": seeds,
                     "sigma_expected_um": expected * scale, "ratio_ci95_low": lo, "ratio_ci95_high": hi,
                     "bias_um": err[:, a].mean() * scale,
                     "rms_error_um": math.sqrt(np.mean(err[:, a] ** 2)) * scale,
                     "sigma_linear_um": sigma_lin[a] * scale, "unit": unit,
                     "processing": processing,
                     "sigma_predicted_all_views_um": (sigma_pred if sigma_all is None
                                                      else sigma_all)[a] * scale})
    centre = setup.patch.points(setup.patch.size / 2)
    return CaseResult(rows=rows, estimates=estimates, setup=setup, pairs=pair_pred,
                      info={"case": case.name, "cameras": len(case.cameras),
                     "noise_dn": sigma_dn,
                     "noise_free_error_px": {c.name: px_err[i].tolist() for i, c in enumerate(setup.cameras)
                                             if np.all(np.isfinite(px_err[i]))},
                     "noise_free_ok": bool(np.all(np.abs(px_err[np.isfinite(px_err)]) < 0.01)),
                     **({} if case.strain is None else {"noise_free_strain_error_microstrain": (
                         (_estimate(setup, res0) - case.strain) * 1e6).tolist()}),
                     "pixels_per_camera": pixels_per_camera(setup, res0),
                     **({} if pair_pred is None else {
                         "processing": processing,
                         "pairs_serving": [f"{setup.cameras[a].name}+{setup.cameras[b].name}"
                                           for a, b in pair_pred.pairs],
                         "pairs_used": [f"{setup.cameras[a].name}+{setup.cameras[b].name}"
                                        for a, b in setup.pairs],
                         "pair_weights": setup.pair_weights.round(6).tolist(),
                         **({} if pair_pred.naive is None else {
                             "sigma_fused_naive_um": (np.sqrt(np.diag(pair_pred.naive)) * UM).tolist()})}),
                     "speckle_px": [float(case.speckle.dot_diameter * np.sqrt(np.abs(np.linalg.det(
                         c.sensitivity(centre) @ setup.patch.tangents)))) for c in setup.cameras],
                     "shift_px": [float(np.linalg.norm(c.sensitivity(centre) @ case.displacement))
                                  for c in setup.cameras],
                     "render_seconds": round(t_render, 2),
                     "seconds": round(time.perf_counter() - t0, 2)})



def pixels_per_camera(setup: Setup, results) -> list[int]:
    """The pixels each camera correlates (in its first pair, for a pair case; 0 for a camera that
    serves no pair)."""
    if not setup.pairs:
        return [int(len(x)) for x in results[0].xi]
    counts = [0] * len(setup.cameras)
    for (a, b), r in reversed(list(zip(setup.pairs, results))):
        counts[a], counts[b] = int(len(r.xi[0])), int(len(r.xi[1]))
    return counts


@dataclass(frozen=True, eq=False)
class CaseResult:
    """One case's outcome (`run_case`): `rows` per reported axis (predicted, measured, ratio, ...;
    the *_um columns in `unit`), `estimates` (seeds, 3) the measured U (m) or strain, `setup` the
    case's cameras, patch and noise-free renders, `info` the diagnostics of summary.json, `pairs`
    the pair-mode prediction of a pair case (else None)."""

    rows: list
    estimates: np.ndarray
    setup: Setup
    info: dict
    pairs: PairPrediction | None = None


@dataclass(frozen=True, eq=False)
class ValidationResult:
    """Every chosen case of a validation file (`run_cases`), in file order."""

    spec: ValidationSpec
    seeds: int
    cases: tuple[CaseResult, ...]
    wall_seconds: float

    @cached_property
    def rows(self) -> list[dict]:
        """Every case's rows, each judged (`judge`) at joint `verdicts.CONFIDENCE` over all of them."""
        m = sum(len(case.rows) for case in self.cases)
        return [judge(row, m) for case in self.cases for row in case.rows]

    @property
    def verdicts(self) -> dict[str, int]:
        """How many ratios are "outside", "inconclusive" and "within" (`verdict`)."""
        return {v: sum(r["verdict"] == v for r in self.rows) for v in VERDICTS}

    @property
    def passed(self) -> bool:
        """No ratio outside `verdicts.BAND` (its joint interval wholly outside it); an inconclusive ratio,
        one its seeds cannot place, does not fail the run."""
        return self.verdicts["outside"] == 0

    @property
    def noise_free_passed(self) -> bool:
        """Every case's noise-free correlation within 0.01 px of the imposed motion."""
        return all(c.info["noise_free_ok"] for c in self.cases)


def run_cases(spec: ValidationSpec, seeds: int | None = None,
              cases: list[str] | None = None) -> ValidationResult:
    """Run every case of `spec` (or those named in `cases`) with `seeds` noise seeds (default: the
    file's); a ConfigError for a bad seed count or an unknown case name before any work. Progress
    goes to the `vdo.dic.validate` logger (`vdo.core.progress`)."""
    from vdo.core.progress import bar

    seeds = spec.seeds if seeds is None else int(seeds)
    if seeds < 2:
        raise ConfigError(spec.path, "--seeds", f"must be at least 2 (got {seeds})")
    chosen = spec.cases
    if cases is not None:
        unknown = sorted(set(cases) - {c.name for c in spec.cases})
        if unknown:
            raise ConfigError(spec.path, "case", f"no case named {', '.join(map(repr, unknown))}")
        chosen = tuple(c for c in spec.cases if c.name in cases)
    started = time.perf_counter()
    results = []
    with bar(log, total=seeds * len(chosen), desc="validate", unit="seed") as progress:
        for case in chosen:
            progress.set_postfix_str(case.name)
            results.append(run_case(case, spec.path, seeds, progress=progress.update))
    return ValidationResult(spec=spec, seeds=seeds, cases=tuple(results),
                            wall_seconds=time.perf_counter() - started)
