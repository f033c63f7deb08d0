"""The calibration's uncertainty carried into each sample's 3D position, displacement and strain.

A rig of calibrated cameras (one group of `vdo.calib.solve`: parameters theta, covariance
Sigma_theta) triangulates a point from its pixels x_i (`triangulate`): each pixel is undistorted
(Newton's method on the distortion, `UNDISTORT_STEPS` steps), becomes the ray C_i + s d_i in the
reference camera's frame (d_i = R_i^T (x, y, 1), C_i = -R_i^T t_i), and the point is the
least-squares intersection X = (sum P_i)^-1 sum P_i C_i, P_i = I - d_i d_i^T / |d_i|^2. The world
frame is the reference camera's true pose (the lab ties its world to the calibrated rig), so
X_world = R_0^T (X - t_0).

With the pixels fixed at the true cameras' projections, a calibration error dtheta moves the
point by J_theta dtheta, J_theta = dX/dtheta (central differences, `point_jacobian`), so Sigma_X = J_theta
Sigma_theta J_theta^T. The same dtheta serves every load step of the test, so a displacement
u = X(t) - X(0) is off by (J_theta(X + u) - J_theta(X)) dtheta: systematic (the same in every
repeat of the test), and proportional to u for small u. A homogeneous strain eps along the
sample's tangent e (u(Y) = eps ((Y - X) . e) e) measured over a gauge of half-length h is off by
e . (du(X + h e) - du(X - h e)) / (2 h): proportional to eps. Both are given per unit
(displacement in m per m, strain per unit strain) and at the test's level ([calibration]
displacement_mm and strain). The maker's pitch tolerance adds a scale error s (sigma = tolerance /
pitch) of every calibrated length: displacements gain s |u| (sigma), strains nothing (positions
and displacements scale together).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vdo.calib.solve import Calibration, rodrigues, rvec
from vdo.core.progress import bar
from vdo.model.camera import distort, distortion_jacobian

log = logging.getLogger(__name__)

UNDISTORT_STEPS = 8      # Newton steps from the distorted point (quadratic convergence)
FD_STEP = 1e-2           # central-difference step of dX/dtheta, in sigmas of each parameter


@dataclass(frozen=True, eq=False)
class Rig:
    """Cameras of one calibrated group used together: `names` (first the group's reference when
    it is among them), `theta` their stacked parameters (per camera 9 intrinsics, then 6
    extrinsics for a non-reference camera), `covariance` of theta, `slices` name -> (intrinsics
    slice, extrinsics slice or None), `world` (R_0, t_0) of the reference camera's true pose."""

    names: tuple
    theta: np.ndarray
    covariance: np.ndarray
    slices: dict
    world: tuple


def rig(cal: Calibration, names, true_cameras) -> Rig:
    """The `Rig` of cameras `names` (one group) of calibration `cal`; `true_cameras` the true vdo
    Cameras (the reference's pose places the world)."""
    reference = {cal.reference[n] for n in names}
    if len(reference) != 1:
        raise ValueError(f"cameras {names} are not calibrated together")
    ref = reference.pop()
    rows, slices, theta, offset = [], {}, [], 0
    for n in names:
        part = [cal.index[(n, "intrinsics")]]
        if n != ref:
            part.append(cal.index[(n, "extrinsics")])
        slices[n] = (slice(offset, offset + 9), slice(offset + 9, offset + 15) if n != ref else None)
        for s in part:
            rows.extend(range(s.start, s.stop))
            offset += s.stop - s.start
        theta.append(cal.intrinsics[n])
        if n != ref:
            R, t = cal.extrinsics[n]
            theta.append(np.r_[rvec(R), t])
    rows = np.array(rows)
    true = {c.name: c for c in true_cameras}[ref]
    return Rig(names=tuple(names), theta=np.concatenate(theta),
               covariance=cal.covariance[np.ix_(rows, rows)], slices=slices,
               world=(true.R, true.t))


def _camera_rays(intr, uv) -> np.ndarray:
    """Directions (N, 3) in the camera's frame (z = 1) of pixels uv (N, 2) through a camera with
    intrinsics `intr` (fx, fy, cx, cy, k1, k2, p1, p2, k3): the distortion inverted by
    `UNDISTORT_STEPS` Newton steps."""
    fx, fy, cx, cy = intr[:4]
    dist = tuple(intr[4:9])
    xd, yd = (uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy
    x, y = xd, yd
    for _ in range(UNDISTORT_STEPS):
        fx_, fy_ = distort(x, y, dist)
        rx, ry = fx_ - xd, fy_ - yd
        a, b, c, d = distortion_jacobian(x, y, dist)
        det = a * d - b * c
        x, y = x - (d * rx - b * ry) / det, y - (a * ry - c * rx) / det
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def _in_reference(ext, direction) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), directions (N, 3)) in the reference frame of camera-frame `direction`s of a
    camera with extrinsics `ext` (rvec, t; None: the reference camera)."""
    if ext is None:
        return np.zeros(3), direction
    R = rodrigues(ext[:3])
    return -R.T @ ext[3:], direction @ R


def _terms(C, d) -> tuple[np.ndarray, np.ndarray]:
    """(P (N, 3, 3), P C (N, 3)), P = I - d d^T / |d|^2, of rays from C along d (N, 3)."""
    P = np.eye(3) - np.einsum("ni,nj->nij", d, d) / np.einsum("ni,ni->n", d, d)[:, None, None]
    return P, P @ C


def _normal_terms(theta, pixels_i, si, se) -> tuple[np.ndarray, np.ndarray]:
    """One camera's part of the least-squares intersection: (P_i (N, 3, 3), P_i C_i (N, 3)),
    P_i = I - d_i d_i^T / |d_i|^2 for its rays through `pixels_i` (N, 2)."""
    return _terms(*_in_reference(None if se is None else theta[se],
                                 _camera_rays(theta[si], pixels_i)))


def _intersect(A: np.ndarray, b: np.ndarray, world) -> np.ndarray:
    """World points (N, 3): X = A^-1 b for the (N, 3, 3) symmetric sums A, by the adjugate
    (A^-1 = adj A / det A; rows of the adjugate are cross products of A's columns), then
    R_0^T (X - t_0)."""
    c0, c1, c2 = A[:, :, 0], A[:, :, 1], A[:, :, 2]
    adj = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=1)   # (N, 3, 3)
    det = np.einsum("ni,ni->n", c0, adj[:, 0])
    X = np.einsum("nij,nj->ni", adj, b) / det[:, None]
    R0, t0 = world
    return (X - t0) @ R0


def triangulate(theta, pixels, slices: dict, names, world) -> np.ndarray:
    """World points (N, 3) from `pixels` (N, k, 2), column i of camera names[i] (module
    docstring)."""
    A = np.zeros((len(pixels), 3, 3))
    b = np.zeros((len(pixels), 3))
    for i, n in enumerate(names):
        P, PC = _normal_terms(theta, pixels[:, i], *slices[n])
        A += P
        b += PC
    return _intersect(A, b, world)


def _pixels(cameras, X):
    return np.stack([c.project(X) for c in cameras], axis=1)


def points(r: Rig, theta: np.ndarray, cameras, X: np.ndarray) -> np.ndarray:
    """The rig with parameters `theta` triangulates the true `cameras`' pixels of X (N, 3)."""
    return triangulate(theta, _pixels(cameras, X), r.slices, r.names, r.world)


def point_jacobian(r: Rig, cameras, X: np.ndarray) -> np.ndarray:
    """dX/dtheta (N, 3, P) at world points X (N, 3), the pixels those of the true `cameras`
    (vdo Cameras in `r.names` order): central differences with steps `FD_STEP` x the parameter's
    sigma. A parameter moves one camera's rays only, so the other cameras' terms of the
    intersection are computed once; an extrinsic parameter moves them rigidly, so its camera's
    undistorted directions are too."""
    pixels = _pixels(cameras, X)
    step = FD_STEP * np.sqrt(np.diag(r.covariance))
    terms = [_normal_terms(r.theta, pixels[:, i], *r.slices[n]) for i, n in enumerate(r.names)]
    A, b = sum(t[0] for t in terms), sum(t[1] for t in terms)
    out = np.empty((len(X), 3, len(r.theta)))
    for i, n in enumerate(r.names):
        si, se = r.slices[n]
        A_rest, b_rest = A - terms[i][0], b - terms[i][1]
        directions = _camera_rays(r.theta[si], pixels[:, i])
        for p in [*range(si.start, si.stop), *(range(se.start, se.stop) if se is not None else [])]:
            ends = []
            for sign in (1.0, -1.0):
                theta = r.theta.copy()
                theta[p] += sign * step[p]
                if si.start <= p < si.stop:     # intrinsics: the rays bend
                    P, PC = _normal_terms(theta, pixels[:, i], si, se)
                else:                           # extrinsics: the same rays, moved
                    P, PC = _terms(*_in_reference(theta[se], directions))
                ends.append(_intersect(A_rest + P, b_rest + PC, r.world))
            out[:, :, p] = (ends[0] - ends[1]) / (2 * step[p])
    return out


@dataclass(frozen=True)
class Motion:
    """The known motion at each sample: a rigid displacement `displacement` (N, 3) m, and a
    homogeneous strain `strain` along the unit tangent `tangent` (N, 3), measured over a gauge of
    half-length `gauge` (m)."""

    displacement: np.ndarray
    tangent: np.ndarray
    strain: float
    gauge: float


def gradients(r: Rig, cameras, X: np.ndarray, motion: Motion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dX/dtheta (N, 3, P), d(displacement error)/dtheta (N, 3, P), d(strain error)/dtheta
    (N, P)) at the samples X for `motion` (module docstring)."""
    JX = point_jacobian(r, cameras, X)
    Ju = point_jacobian(r, cameras, X + motion.displacement) - JX
    e, h, eps = motion.tangent, motion.gauge, motion.strain
    ends = []
    for sign in (1.0, -1.0):
        Y = X + sign * h * e
        ends.append(point_jacobian(r, cameras, Y + eps * sign * h * e) - point_jacobian(r, cameras, Y))
    Je = np.einsum("ni,nip->np", e, ends[0] - ends[1]) / (2 * h)
    return JX, Ju, Je


@dataclass(frozen=True)
class Propagated:
    """Per sample, 1 sigma from the calibration: `position` (N,) m (sqrt of the trace of
    Sigma_X), `displacement` (N,) m at the motion's displacement (sqrt trace, with the pitch
    tolerance's scale term), `strain` (N,) at the motion's strain; `per_unit_displacement`
    (N,) m/m and `per_unit_strain` (N,) the same divided by the level."""

    position: np.ndarray
    displacement: np.ndarray
    strain: np.ndarray
    per_unit_displacement: np.ndarray
    per_unit_strain: np.ndarray


def propagate(r: Rig, cameras, X: np.ndarray, motion: Motion, pitch_sigma: float = 0.0) -> Propagated:
    """The calibration's sigma at samples X (module docstring); `pitch_sigma` the relative scale
    sigma of the target's pitch."""
    JX, Ju, Je = gradients(r, cameras, X, motion)
    S = r.covariance
    var_x = np.einsum("nip,pq,niq->n", JX, S, JX)
    var_u = np.einsum("nip,pq,niq->n", Ju, S, Ju)
    var_u = var_u + (pitch_sigma * np.linalg.norm(motion.displacement, axis=1)) ** 2
    var_e = np.einsum("np,pq,nq->n", Je, S, Je)
    level = np.linalg.norm(motion.displacement, axis=1)
    return Propagated(position=np.sqrt(var_x), displacement=np.sqrt(var_u), strain=np.sqrt(var_e),
                      per_unit_displacement=np.sqrt(var_u) / level,
                      per_unit_strain=np.sqrt(var_e) / motion.strain)


def measured_errors(r: Rig, theta: np.ndarray, cameras, X: np.ndarray, motion: Motion):
    """(displacement error (N, 3) m, strain error (N,)) of a rig with parameters `theta`
    triangulating the true cameras' pixels of the known motion (the Monte Carlo's measurement)."""
    u = points(r, theta, cameras, X + motion.displacement) - points(r, theta, cameras, X)
    e, h, eps = motion.tangent, motion.gauge, motion.strain
    ends = []
    for sign in (1.0, -1.0):
        Y = X + sign * h * e
        ends.append(points(r, theta, cameras, Y + eps * sign * h * e) - points(r, theta, cameras, Y))
    measured = np.einsum("ni,ni->n", e, ends[0] - ends[1]) / (2 * h)
    return u - motion.displacement, measured - eps


def seen_samples(samples, cameras, count: int) -> np.ndarray:
    """Indices of up to `count` samples (evenly spread in sample order) that project inside every
    camera's image with their front face towards it (no occlusion test: a planning choice of
    where to look, not a visibility claim)."""
    ok = np.ones(len(samples.points), dtype=bool)
    for cam in cameras:
        uv = cam.project(samples.points)
        towards = np.einsum("ni,ni->n", samples.normals, cam.position - samples.points) > 0
        ok &= towards & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) \
            & (uv[:, 1] <= cam.height - 1)
    idx = np.flatnonzero(ok)
    if len(idx) <= count:
        return idx
    return idx[np.linspace(0, len(idx) - 1, count).round().astype(int)]


def test_motion(exp, samples, idx: np.ndarray) -> Motion:
    """The test's known motion at samples `idx`: [calibration] displacement_mm along each
    sample's first tangent, [calibration] strain along it, over a gauge of half the DIC patch."""
    e = samples.tangent_u[idx]
    return Motion(displacement=exp.calibration.displacement * e, tangent=e,
                  strain=exp.calibration.strain, gauge=exp.evaluation.patch_size / 2)


def reference_first(reference: dict, a: str, b: str) -> tuple[str, str]:
    """The pair (a, b) in `rig`'s order: the group's reference camera first when it is one of
    the two (`reference` camera -> its group's reference, `Calibration.reference`)."""
    return (a, b) if reference[a] == a or reference[b] != b else (b, a)


def probe(exp, samples, cameras, count: int) -> tuple[np.ndarray, Motion]:
    """Where a rig of `cameras` is checked: up to `count` samples it sees (`seen_samples`) and
    the test's motion there (`test_motion`): (X (n, 3) m, Motion); n may be 0."""
    idx = seen_samples(samples, cameras, count)
    return samples.points[idx], test_motion(exp, samples, idx)


@dataclass(frozen=True)
class SampleErrors:
    """Per sample of the experiment, the calibration-induced 1-sigma errors through the best
    calibrated stereo pair that sees it (lowest strain sigma; NaN where none does): `position` m,
    `displacement` m at the test's displacement, `strain` at the test's strain, `per_unit_*` the
    same per unit displacement (m/m) and per unit strain; `pair` the index into `pairs` (-1)."""

    position: np.ndarray
    displacement: np.ndarray
    strain: np.ndarray
    per_unit_displacement: np.ndarray
    per_unit_strain: np.ndarray
    pair: np.ndarray
    pairs: tuple


def sample_errors(cal: Calibration, exp, cameras, samples, visible: np.ndarray, pairs) -> SampleErrors:
    """`propagate` for every sample seen by both cameras of a calibrated pair (`visible` (C, N)
    from the ray cast, `cameras` the true cameras in the calibration's scale and order), with the
    test's motion (`test_motion`) and the pitch tolerance's scale sigma."""
    n = len(samples.points)
    fields = {k: np.full(n, np.nan) for k in ("position", "displacement", "strain",
                                               "per_unit_displacement", "per_unit_strain")}
    best = np.full(n, -1)
    index = {c.name: i for i, c in enumerate(cameras)}
    pitch_sigma = exp.calibration.pitch_tolerance / cal.pitch
    used = []
    for a, b in bar(log, iterable=pairs, desc="propagating the calibration", unit="pair",
                     disable=len(pairs) < 2):
        if cal.reference[a] != cal.reference[b]:
            continue
        names = reference_first(cal.reference, a, b)
        idx = np.flatnonzero(visible[index[a]] & visible[index[b]])
        used.append((a, b))
        if len(idx) == 0:
            continue
        r = rig(cal, names, cameras)
        cams = [cameras[index[m]] for m in names]
        p = propagate(r, cams, samples.points[idx], test_motion(exp, samples, idx), pitch_sigma)
        better = ~(fields["strain"][idx] <= p.strain)
        take = idx[better]
        for key in fields:
            fields[key][take] = getattr(p, key)[better]
        best[take] = len(used) - 1
    return SampleErrors(pair=best, pairs=tuple(used), **fields)
