"""σ_measured: the error the lab's processing will measure, per sample and world axis, beside the bound.

The bound (`vdo.physics.predict`, Σ = C⁻¹, C = Σ_i C_i) is the Cramér-Rao bound of one noisy image,
all views in one correlation, with a perfect interpolant. The lab's correlation differs per camera i
(`vdo.model.interpolant.correlation_error`, at the footprint of the camera's median sample of each
region, after the lens's blur of `vdo.model.optics`, with the [analysis] interpolant and reference):
its image-plane error has the covariance

    Σ_i^meas = ν_i W_i⁻¹ + B_i,     ν_i = tr(σ² N̄ + V̄) / tr(σ² H_sharp⁻¹)      (px²)

with W_i the camera's image-plane information over the patch (the bound's own, W_i = S_i⁺ᵀ C_i S_i⁺,
S_i = ∂x/∂X the 2x3 sensitivity, S⁺ its pseudo-inverse: C_i = S_iᵀ W_i S_i exactly), ν_i the noise
through the interpolant plus the bias's patch-to-patch scatter against the bound of the sharp
(no-optics) image (so ν_i also carries the optics' loss of gradient), and B_i = <b bᵀ> the systematic
bias (px², RMS over sub-pixel positions). ν_i ~ √2² for a smooth pattern and a noisy reference.
Cameras' errors are independent (different sensors, different sub-pixel positions), and the
correlation weights each view by its information W_i, so the estimate u = C⁻¹ Σ_i S_iᵀ W_i x_i has

    Cov_meas = C⁻¹ [Σ_i (ν_i C_i + S_iᵀ W_i B_i W_i S_i)] C⁻¹                  (m²)

σ_measured per axis is sqrt(diag Cov_meas), σ_max its largest eigenvalue's square root.

Stereo pairs ([analysis] processing = "pairs"). Pair p = (a, b) measures with C_p = C_a + C_b and
M_p = M_a + M_b (M_i the bracket above, per camera): Cov_p = C_p⁻¹ M_p C_p⁻¹. The candidate pairs at a
sample are the declared [[stereo_pair]]s, or every two usable views whose viewing rays at the sample
make an angle in [stereo_min_angle(lens), max_pair_angle] (the rule of `pair_candidates`). Merge:
"best" keeps the pair of least σ_max; "fusion" averages the pairs' results with weights Cov_p⁻¹ and
reports the true covariance, A Σ_full Aᵀ with A_p = (Σ_q Cov_q⁻¹)⁻¹ Cov_p⁻¹ and
Cov(u_p, u_q) = C_p⁻¹ (Σ_{i ∈ p ∩ q} M_i) C_q⁻¹: pairs that share a camera share its noise and bias,
which naive fusion (Σ Cov_p⁻¹)⁻¹ ignores (`fused_naive`, optimistic).
Strain: σ_ε measured = σ_ε bound × σ_max,measured / σ_max,bound per sample (the bias is taken as a
random error from subset to subset: its sub-pixel position changes with the displacement field).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vdo import objective
from vdo.config.procedure import Analysis, StereoPairSpec
from vdo.config.rig import CameraSpec, Evaluation, RegionSpec, SpeckleSpec
from vdo.core.errors import ConfigError
from vdo.physics import usable
from vdo.physics.checks import measurement_floor
from vdo.physics.lighting import exposure_factors
from vdo.model.optics import optics_blur
from vdo.model.sensor import SensorModel
from vdo.physics.predict import samples_for_objective, settings, view_data
from vdo.physics.strain import STRAIN_COMPONENTS

DEFAULT_MAX_PAIR_ANGLE_DEG = 60.0   # beyond this the two views of a subset differ so much in
#                                     foreshortening that stereo matching between them fails
RANK_RTOL = 1e-10                   # eigenvalue ratio under which a pair's C_p counts as singular
# `noise_inflation` snaps each footprint to a lattice so that the optimizer's refreshes, whose
# cameras move a little each round, find its correlation model in the cache (~0.3 s each to compute)
SNAP_OCTAVE = 1.0 / 16              # singular values of the footprint: log2 steps (4.4 %)
SNAP_ANGLE = math.radians(7.5)      # rad: the footprint's two rotation angles
SNAP_DEPTH = 1.0 / 32               # the depth (defocus): log2 steps (2.2 %)


@dataclass(frozen=True, eq=False)
class MeasuredFields:
    """σ_measured per sample (m), beside the bound; +inf where unmeasured.

    sigma_xyz (N, 3), sigma_max (N,): the processing of [analysis] (all views, or pairs merged)
    ratio (N,): sigma_max / the bound's sigma_max (nan where either is unmeasured)
    pair (N,) int: index into `pairs` of the pair serving the sample ("best"; -1 otherwise)
    pairs: the candidate camera pairs (names), empty for all-views processing
    fused_naive (N,): σ_max of inverse-variance fusion ignoring the shared cameras (pairs, "fusion")
    per_camera: one dict per (camera, region) with nu, gamma, bias_px (2,) and f_number
    """

    sigma_xyz: np.ndarray
    sigma_max: np.ndarray
    ratio: np.ndarray
    pair: np.ndarray
    pairs: tuple
    fused_naive: np.ndarray | None
    per_camera: list


def _pinv_sym(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C⁻¹ (…, 3, 3), full rank (…,) bool) of symmetric PSD matrices; rank < 3 gives 0 and False."""
    w, V = np.linalg.eigh(C)
    ok = w[..., 0] > RANK_RTOL * np.maximum(w[..., -1], 1e-300)
    inv_w = np.where(ok[..., None], 1.0 / np.where(w > 0, w, 1.0), 0.0)
    return np.einsum("...ij,...j,...kj->...ik", V, inv_w, V), ok


def _ratio(measured: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """measured / bound where both are finite, else nan."""
    both = np.isfinite(measured) & np.isfinite(bound) & (bound > 0)
    return np.where(both, measured / np.where(both, bound, 1.0), np.nan)


def _sigma(cov: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sigma per axis (..., 3), sigma_max (...)) of covariances (..., 3, 3); inf where not `ok`
    (those matrices, possibly non-finite, are not decomposed)."""
    ok = ok & np.isfinite(cov).all(axis=(-2, -1))
    cov = np.where(ok[..., None, None], cov, 0.0)
    xyz = np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 0.0))
    mx = np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[..., -1], 0.0))
    return np.where(ok[..., None], xyz, np.inf), np.where(ok, mx, np.inf)


def _snap(A: np.ndarray, lattice: tuple = (SNAP_OCTAVE, SNAP_ANGLE)) -> np.ndarray:
    """The 2x2 footprint A = R(u) diag(s) F R(v)ᵀ (R a rotation, F = diag(1, ±1)) with log2 s on
    `lattice` = (octave, angle) steps: log2 s on octave steps and the angles u, v on angle steps
    (rad); angle None: diag(s), the rotations and F dropped (the pattern's statistics do not turn
    with v or F; u, the anisotropy's direction against the pixel grid, moves κ by a few percent)."""
    octave, angle = lattice
    U, s, Vt = np.linalg.svd(A)
    if angle is None:
        return np.diag(2.0 ** np.array([octave * round(math.log2(x) / octave) for x in s]))
    if np.linalg.det(U) < 0:
        U, Vt = U @ np.diag([1.0, -1.0]), np.diag([1.0, -1.0]) @ Vt
    F = np.diag([1.0, np.sign(np.linalg.det(Vt))])
    step = lambda x, q: q * round(x / q)
    turn = lambda a: np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    u = step(math.atan2(U[1, 0], U[0, 0]), angle)
    v = step(math.atan2(Vt[0, 1], Vt[0, 0]), angle)            # F R(v)ᵀ's first row: (cos v, sin v)
    s = 2.0 ** np.array([step(math.log2(x), octave) for x in s])
    return turn(u) @ np.diag(s) @ F @ turn(v).T


def region_floors(camera_specs: tuple[CameraSpec, ...], evaluation: Evaluation,
                  speckle_spec: SpeckleSpec, sensor: SensorModel, analysis: Analysis,
                  cameras, samples, views, illumination, speckle,
                  snap: bool = False, lattice: tuple = (SNAP_OCTAVE, SNAP_ANGLE)) -> list[tuple]:
    """What the lab's correlation measures for each camera in each region it views: one
    (i, k, seen, floor, lens) per (camera i, region k) with samples in `views` (C, N) bool, lit at
    the camera's median footprint, where `seen` are those samples, `floor` the
    `vdo.physics.checks.measurement_floor` row at that median footprint (its "model" the
    `vdo.model.interpolant.CorrelationError`) and `lens` the camera's `vdo.model.optics.OpticsBlur`
    there. The median is by pixel density sqrt|det A|, A = ∂x/∂(u, v) the footprint in px/m.
    `snap`: the footprint and the depth on the lattice of `_snap` (`lattice`) and SNAP_DEPTH.
    The tables: the cameras' [[camera]] specs (f-number, focus, exposure time: the light each
    gathers, `vdo.physics.lighting.exposure_factors`), [evaluation] (the patch), [speckle],
    [sensor] and [analysis] (the interpolant and the reference)."""
    T = np.stack([samples.tangent_u, samples.tangent_v], axis=-1)
    gathered = exposure_factors(camera_specs, sensor)
    jobs = []
    for i, (cam, spec) in enumerate(zip(cameras, camera_specs)):
        for k in range(len(samples.region_names)):
            seen = np.nonzero(np.asarray(views[i]) & (samples.region == k))[0]
            if seen.size == 0:
                continue
            X = samples.points[seen]
            A = cam.sensitivity(X) @ T[seen]
            density = np.sqrt(np.abs(np.linalg.det(A)))
            m = int(np.argsort(density)[len(density) // 2])
            if not illumination.irradiance[seen[m]] > 0:     # dark: sigma stays inf there
                continue
            depth = float((X[m] - cam.position) @ cam.optical_axis)
            footprint = A[m]
            if snap:
                footprint = _snap(footprint, lattice)
                depth = 2.0 ** (SNAP_DEPTH * round(math.log2(depth) / SNAP_DEPTH))
            lens = optics_blur(cam.pixel_size, cam.focal_length, spec.f_number, spec.focus_distance,
                               depth)
            jobs.append((i, k, seen, footprint, float(gathered[i] * illumination.irradiance[seen[m]]),
                         evaluation.patch_size ** 2 * float(density[m]) ** 2, lens))
    if not jobs:
        return []
    floors = measurement_floor([j[3] for j in jobs], [j[4] for j in jobs], [j[5] for j in jobs],
                               [j[6] for j in jobs], speckle_spec, sensor, speckle.pattern,
                               analysis.interpolant, analysis.reference == "noisy")
    return [(i, k, seen, floor, lens) for (i, k, seen, *_, lens), floor in zip(jobs, floors)]


def _nu(floor) -> float:
    """ν of the module docstring: tr(σ² N̄ + V̄) / tr(σ² H_sharp⁻¹), the noise through the
    interpolant and the bias's scatter against the sharp image's bound."""
    model, j = floor["model"]
    s2 = floor["noise_rel"] ** 2
    return float(np.trace(s2 * model.noise[j] + model.scatter[j]) / np.trace(s2 * model.bound_sharp[j]))


def noise_inflation(camera_specs: tuple[CameraSpec, ...], evaluation: Evaluation,
                    speckle_spec: SpeckleSpec, sensor: SensorModel, analysis: Analysis,
                    cameras, samples, views, illumination, speckle,
                    snap: bool = True, lattice: tuple = (SNAP_OCTAVE, SNAP_ANGLE)) -> np.ndarray:
    """(C, N) √κ per (camera, sample): the factor on the sensor noise that turns the bound's
    per-camera information C_i into the information of what the lab measures, C_i / κ, with

        κ = tr(Σ_meas) / tr(Σ_bound) = ν + P tr(B) / (σ² tr(H_sharp⁻¹))     (image plane, px²)

    per (camera, region) at the camera's median footprint (`region_floors`; ν, B, P pixels and σ
    of the module docstring); 1 where a camera views none of the region. Scoring on C = Σ_i C_i/κ_i
    is the all-views σ_measured when each camera's measured covariance is a multiple of its bound
    (isotropic bias); otherwise its trace-equivalent. `views` (C, N) bool: the samples the
    median is taken over. `snap` (default): the footprints on a lattice (`region_floors`), κ
    within a few percent of the exact footprint's, so that a camera that moved a little finds its
    model in the cache; `lattice` (`_snap`): coarser for many cameras (`vdo design`'s candidates).
    The tables as `region_floors` takes them."""
    scale = np.ones(np.shape(views))
    for i, _, seen, floor, _ in region_floors(camera_specs, evaluation, speckle_spec, sensor,
                                              analysis, cameras, samples, views, illumination,
                                              speckle, snap, lattice):
        model, j = floor["model"]
        s2, p = floor["noise_rel"] ** 2, floor["patch_pixels"]
        kappa = _nu(floor) + p * float(np.trace(model.bias[j])) / (s2 * float(np.trace(model.bound_sharp[j])))
        scale[i, seen] = math.sqrt(kappa)
    return scale


def camera_terms(regions: tuple[RegionSpec, ...], camera_specs: tuple[CameraSpec, ...],
                 evaluation: Evaluation, speckle_spec: SpeckleSpec, sensor: SensorModel,
                 analysis: Analysis, cameras, samples, vis, illumination, speckle, pred):
    """(C_i (C, N, 3, 3) 1/m², M_i (C, N, 3, 3) 1/m², per_camera rows): each camera's information
    over its clipped patch (as `predict`'s second pass) and the bracket ν_i C_i + S_iᵀ W_i B_i W_i S_i
    of the module docstring, ν_i and B_i from `correlation_error` at the median footprint of the
    camera's usable samples in each region (`region_floors`). The tables: [[region]] (as
    `vdo.physics.predict.predict` takes it) and those of `region_floors`."""
    smp = samples_for_objective(regions, samples)
    cams = objective.CameraParams.from_cameras(cameras)
    overlap = usable.patch_overlap(samples, evaluation.patch_size)
    phi = usable.patch_fractions(overlap, pred.usable)
    vd = view_data(speckle_spec, sensor, smp, vis, illumination, speckle, phi,
                   exposure=exposure_factors(camera_specs, sensor))
    C_i = np.asarray(objective.camera_information(cams, smp, vd, speckle.table, settings(evaluation)))
    M_i = np.zeros_like(C_i)
    rows = []
    for i, k, seen, floor, lens in region_floors(camera_specs, evaluation, speckle_spec, sensor,
                                                 analysis, cameras, samples, pred.usable,
                                                 illumination, speckle):
        model, j = floor["model"]
        nu = _nu(floor)
        gamma = float(np.trace(model.bound[j]) / np.trace(model.bound_sharp[j]))
        B = model.bias[j]
        S = cameras[i].sensitivity(samples.points[seen])                    # (n, 2, 3) px/m
        Sp = np.linalg.pinv(S)                                               # (n, 3, 2)
        W = np.einsum("nia,nij,njb->nab", Sp, C_i[i, seen], Sp)              # (n, 2, 2) 1/px²
        WS = W @ S
        M_i[i, seen] = nu * C_i[i, seen] + np.einsum("nai,ab,nbj->nij", WS, B, WS)
        rows.append({"camera": cameras[i].name, "region": samples.region_names[k], "nu": nu,
                     "optics_gradient_loss": gamma, "bias_px": [float(x) for x in np.sqrt(np.diag(B))],
                     "patch_pixels": floor["patch_pixels"], "f_number": lens.f_number,
                     "f_number_assumed": lens.assumed, "optics_sigma_px": lens.sigma_px})
    return C_i, M_i, rows


def pair_candidates(analysis: Analysis, stereo_pairs: tuple[StereoPairSpec, ...], cameras,
                    samples, usable_views, min_angle) -> tuple[list, np.ndarray]:
    """([(a, b) camera indices], ok (P, N) bool): the stereo pairs the lab may use at each sample.
    The declared `stereo_pairs` ([[stereo_pair]]) when [analysis] pairs = "declared", else every
    two cameras (the rule): both usable views of the sample, and the angle between their viewing
    rays at the sample within [min, max] with min = `min_angle`(the shorter focal length, m) in rad
    (`vdo.constraints.stereo_min_angle`, the stereo rule of thumb per lens) and max = [analysis]
    max_pair_angle_deg (default DEFAULT_MAX_PAIR_ANGLE_DEG)."""
    names = [c.name for c in cameras]
    X = samples.points
    rays = np.stack([c.position for c in cameras])[:, None, :] - X[None]        # (C, N, 3)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    max_angle = analysis.max_pair_angle if analysis.max_pair_angle is not None \
        else math.radians(DEFAULT_MAX_PAIR_ANGLE_DEG)                  # the file's value is in rad
    if analysis.pairs == "declared":
        pairs = []
        for spec in stereo_pairs:
            a, b = (names.index(n) for n in spec.cameras)
            lo = spec.min_angle if spec.min_angle is not None else \
                min_angle(min(cameras[a].focal_length, cameras[b].focal_length))
            hi = spec.max_angle if spec.max_angle is not None else max_angle
            pairs.append((a, b, lo, hi))
    else:
        pairs = [(a, b, min_angle(min(cameras[a].focal_length, cameras[b].focal_length)),
                  max_angle) for a in range(len(cameras)) for b in range(a + 1, len(cameras))]
    ok = np.zeros((len(pairs), len(X)), dtype=bool)
    for p, (a, b, lo, hi) in enumerate(pairs):
        angle = np.arccos(np.clip(np.einsum("nk,nk->n", rays[a], rays[b]), -1.0, 1.0))
        ok[p] = usable_views[a] & usable_views[b] & (angle >= lo) & (angle <= hi)
    return [(a, b) for a, b, _, _ in pairs], ok


def all_views(C_i: np.ndarray, M_i: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Cov (N, 3, 3), ok (N,)): one correlation over all views, C⁻¹ (Σ M_i) C⁻¹, C = Σ C_i."""
    Cinv, ok = _pinv_sym(C_i.sum(axis=0))
    return Cinv @ M_i.sum(axis=0) @ Cinv, ok


@dataclass(frozen=True, eq=False)
class PairMerge:
    """How pair processing merges the pairs' estimates at each sample (module docstring): the
    merged displacement is u = Σ_p A_p u_p, u_p the estimate of pair p alone.

    weights (P, N, 3, 3): A_p; "best": the identity for the pair of least σ_max, 0 for the others;
        "fusion": (Σ_q Cov_q⁻¹)⁻¹ Cov_p⁻¹ over the candidate pairs, 0 for the others
    served (N,) bool: some candidate pair of full rank serves the sample
    best (N,) int: index of the serving pair ("best"), -1 otherwise
    pair_inverse (P, N, 3, 3): C_p⁻¹ (m²), C_p = C_a + C_b
    naive (N, 3, 3): the covariance (m²) that fusion ignoring the shared cameras would claim,
        (Σ_p Cov_p⁻¹)⁻¹ (valid where `served`; "fusion"), else None
    """

    weights: np.ndarray
    served: np.ndarray
    best: np.ndarray
    pair_inverse: np.ndarray
    naive: np.ndarray | None


def pair_merge(C_i: np.ndarray, M_i: np.ndarray, pairs, cand: np.ndarray, merge: str) -> PairMerge:
    """The merging weights of stereo-pair processing (`PairMerge`) from per-camera C_i, M_i
    (C, N, 3, 3), the pairs [(a, b)] and where each may serve, cand (P, N) bool; each pair's
    covariance is Cov_p = C_p⁻¹ M_p C_p⁻¹ (module docstring)."""
    n = C_i.shape[1]
    P = len(pairs)
    cand = cand.copy()
    Cp_inv = np.zeros((P, n, 3, 3))
    cov_p = np.zeros((P, n, 3, 3))
    for p, (a, b) in enumerate(pairs):
        Cinv, ok = _pinv_sym(C_i[a] + C_i[b])
        cand[p] &= ok
        Cp_inv[p] = Cinv
        cov_p[p] = Cinv @ (M_i[a] + M_i[b]) @ Cinv
    served = cand.any(axis=0)
    if merge == "best":
        _, sig_p = _sigma(cov_p, cand)                                  # (P, N) σ_max per pair
        best = np.where(served, np.argmin(sig_p, axis=0) if P else 0, -1)
        A = np.zeros((P, n, 3, 3))
        A[best[served], np.flatnonzero(served)] = np.eye(3)
        return PairMerge(A, served, best, Cp_inv, None)
    prec = np.where(cand[..., None, None],
                    np.linalg.pinv(np.where(cand[..., None, None], cov_p, np.eye(3))), 0.0)
    total_inv, ok = _pinv_sym(prec.sum(axis=0))
    ok &= served
    A = np.einsum("nij,pnjk->pnik", total_inv, prec)                    # (P, N, 3, 3)
    return PairMerge(A, ok, np.full(n, -1), Cp_inv, total_inv)


def merge_pairs(C_i: np.ndarray, M_i: np.ndarray, pairs, cand: np.ndarray, merge: str):
    """Stereo-pair processing (module docstring) from per-camera C_i, M_i (C, N, 3, 3), the pairs
    [(a, b)] and where each may serve, cand (P, N) bool. Returns (Cov (N, 3, 3), ok (N,), best
    (N,) pair index or -1, naive (N,) σ_max of fusion ignoring shared cameras or None): the
    covariance of u = Σ_p A_p u_p (`pair_merge`), Σ_{p,q} A_p Cov(u_p, u_q) A_qᵀ with
    Cov(u_p, u_q) = C_p⁻¹ (Σ_{i ∈ p ∩ q} M_i) C_q⁻¹."""
    m = pair_merge(C_i, M_i, pairs, cand, merge)
    A, Cp_inv = m.weights, m.pair_inverse
    cov = np.zeros((C_i.shape[1], 3, 3))
    for p, (a, b) in enumerate(pairs):
        for q, (c, d) in enumerate(pairs):
            shared = [i for i in (a, b) if i in (c, d)]
            if not shared:
                continue
            cross = Cp_inv[p] @ sum(M_i[i] for i in shared) @ Cp_inv[q]
            cov += A[p] @ cross @ np.swapaxes(A[q], -1, -2)
    naive = None if m.naive is None else \
        np.where(m.served, np.sqrt(np.maximum(np.linalg.eigvalsh(m.naive)[..., -1], 0.0)), np.inf)
    return cov, m.served, m.best, naive


def measured_fields(regions: tuple[RegionSpec, ...], camera_specs: tuple[CameraSpec, ...],
                    evaluation: Evaluation, speckle_spec: SpeckleSpec, sensor: SensorModel,
                    analysis: Analysis, stereo_pairs: tuple[StereoPairSpec, ...], path,
                    cameras, samples, vis, illumination, speckle, pred,
                    min_angle=None) -> MeasuredFields:
    """σ_measured of the module docstring for the processing in [analysis] (`min_angle`: the pair
    rule's minimum angle per focal length, `pair_candidates`; needed for pairs). A declared pair
    that no sample can use (no common usable view at an angle within its limits) is a
    ConfigError naming the pair and the experiment file `path`. The tables: those of
    `camera_terms`, and the declared `stereo_pairs` ([[stereo_pair]])."""
    C_i, M_i, rows = camera_terms(regions, camera_specs, evaluation, speckle_spec, sensor, analysis,
                                  cameras, samples, vis, illumination, speckle, pred)
    bound = np.where(pred.measured, pred.sigma_max, np.inf)
    if analysis.processing == "all-views":
        cov, ok = all_views(C_i, M_i)
        xyz, mx = _sigma(cov, ok & pred.measured)
        return MeasuredFields(xyz, mx, _ratio(mx, bound), np.full(len(bound), -1), (), None, rows)
    pairs, cand = pair_candidates(analysis, stereo_pairs, cameras, samples, pred.usable, min_angle)
    if analysis.pairs == "declared":
        for (a, b), ok in zip(pairs, cand):
            if not ok.any():
                raise ConfigError(path, f"stereo_pair [{cameras[a].name!r}, {cameras[b].name!r}]",
                                  "the two cameras share no usable view of any region at an angle "
                                  "within the pair's limits: pair processing covers only pairs "
                                  "that both see a region")
    cov, ok, best, naive = merge_pairs(C_i, M_i, pairs, cand, analysis.merge)
    xyz, mx = _sigma(cov, ok)
    names = tuple((cameras[a].name, cameras[b].name) for a, b in pairs)
    return MeasuredFields(xyz, mx, _ratio(mx, bound), best, names, naive, rows)


def _stats(values_um: np.ndarray) -> dict:
    """p50, p95 and max (µm or µε) over the finite values; None when there are none."""
    v = values_um[np.isfinite(values_um)]
    if not v.size:
        return {"p50": None, "p95": None, "max": None}
    return {"p50": float(np.percentile(v, 50)), "p95": float(np.percentile(v, 95)),
            "max": float(v.max())}


def summary(analysis: Analysis, meas: MeasuredFields, samples, pred, strain_sigma=None) -> dict:
    """summary.json's "measured": the processing, per region the area fraction with a finite
    σ_measured (served: by some pair, or by >= 2 usable views), σ_measured (µm, per axis and max)
    beside the bound's σ_max, their ratio per sample, the strain σ (µε) measured, which pair serves how much
    of the region ("best"), and the per-camera terms (`camera_terms`); `analysis` the [analysis]
    table."""
    a = analysis
    regions = {}
    for k, name in enumerate(samples.region_names):
        mask = samples.region == k
        area = samples.area[mask]
        r = {"served_fraction": float(area[np.isfinite(meas.sigma_max[mask])].sum() / area.sum()),
             "sigma_measured_um": _stats(meas.sigma_max[mask] * 1e6),
             "sigma_bound_um": _stats(np.where(pred.measured[mask], pred.sigma_max[mask], np.inf) * 1e6),
             "sigma_measured_axis_um": {ax: _stats(meas.sigma_xyz[mask, j] * 1e6)
                                        for j, ax in enumerate("xyz")},
             "ratio": _stats(meas.ratio[mask])}
        if strain_sigma is not None:
            eps = strain_sigma[mask] * np.where(np.isfinite(meas.ratio[mask]), meas.ratio[mask],
                                                np.inf)[:, None]
            r["sigma_strain_measured_microstrain"] = {
                f"eps_{c}": _stats(eps[:, j] * 1e6) for j, c in enumerate(STRAIN_COMPONENTS)}
        if meas.pairs and a.merge == "best":
            served = meas.pair[mask]
            r["pairs"] = {f"{p[0]}+{p[1]}": round(float(area[served == i].sum() / area.sum()), 4)
                          for i, p in enumerate(meas.pairs) if (served == i).any()}
        if meas.fused_naive is not None:
            r["sigma_fused_naive_um"] = _stats(meas.fused_naive[mask] * 1e6)
        regions[name] = r
    return {"processing": a.processing, "pairs": a.pairs if a.processing == "pairs" else None,
            "merge": a.merge if a.processing == "pairs" else None, "interpolant": a.interpolant,
            "reference": a.reference, "regions": regions, "per_camera": meas.per_camera,
            "meaning": "sigma_measured: the error the lab's processing will measure (noise through "
                       "the interpolant, the interpolation bias RMS over sub-pixel positions, the "
                       "lens's blur); sigma_bound: the Cramér-Rao bound of one noisy image, all "
                       "views (docs/theory.md)"}
