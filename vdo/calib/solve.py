"""Calibration from detected corners: intrinsics with distortion and multi-camera extrinsics by a
joint bundle adjustment, and the parameters' covariance.

Model (OpenCV's): a camera c sees target point X_t of pose p at
x = pi(K_c, d_c, R_c (R_p X_t + t_p) + t_c), with pi the pinhole division, Brown-Conrady
distortion d = (k1, k2, p1, p2, k3) and K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
(`vdo.model.camera.image_point`). (R_p, t_p) maps the target into the frame of the reference
camera of c's group (the cameras linked to it through poses both see; the group's first camera
in the experiment's order), (R_c, t_c) that frame into camera c (identity for the reference).
Rotations are Rodrigues vectors.

Parameters theta: per camera (fx, fy, cx, cy, k1, k2, p1, p2, k3) (`INTRINSICS`), per
non-reference camera (r_c, t_c), per pose (r_p, t_p). Start: `cv2.calibrateCamera` per camera,
the extrinsics chained through shared poses. Then Levenberg-Marquardt on the sum of squared
residuals r = x_model - x_detected, with the Jacobian J = dr/dtheta exact (JAX forward mode per
observation, assembled sparse).

Covariance: Sigma_theta = sigma_det^2 (J^T J)^-1 at the optimum (Gauss-Markov for independent
isotropic detection noise), sigma_det = [calibration] detection_sigma_px, or else the residuals'
estimate sqrt(sum r^2 / (m - P)) (m residuals, P parameters).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np

from vdo.core.configure import require_x64
from vdo.model.camera import image_point

log = logging.getLogger(__name__)
INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
LM_MAX_ITERATIONS = 100
LM_RELATIVE_COST = 1e-12     # stop when the cost falls by less than this fraction
LM_START_DAMPING = 1e-3
SERIES_BELOW = 1e-8          # rad^2: Rodrigues' coefficients by their series below this angle^2


def rodrigues(r, xp=np):
    """Rotation matrix of the Rodrigues vector r (3,): I + A [r]x + B [r]x^2 with a = |r|,
    A = sin(a)/a, B = (1 - cos a)/a^2, and their series 1 - a^2/6, 1/2 - a^2/24 below
    `SERIES_BELOW` (finite values and derivatives at r = 0)."""
    a2 = r[0] ** 2 + r[1] ** 2 + r[2] ** 2
    small = a2 < SERIES_BELOW
    safe = xp.where(small, 1.0, a2)
    a = xp.sqrt(safe)
    A = xp.where(small, 1.0 - a2 / 6.0, xp.sin(a) / a)
    B = xp.where(small, 0.5 - a2 / 24.0, (1.0 - xp.cos(a)) / safe)
    z = 0.0 * r[0]
    K = xp.stack([xp.stack([z, -r[2], r[1]]), xp.stack([r[2], z, -r[0]]), xp.stack([-r[1], r[0], z])])
    return xp.eye(3) + A * K + B * (K @ K)


def rvec(R: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=float))[0].ravel()


def project(intr, ext, pose, X, xp=np):
    """Pixels (n, 2) of target points X (n, 3) (module docstring's model)."""
    Rp, Rc = rodrigues(pose[:3], xp), rodrigues(ext[:3], xp)
    Xc = (X @ Rp.T + pose[3:]) @ Rc.T + ext[3:]
    x, y = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
    u, v = image_point((intr[0], None, intr[2], intr[1], intr[3]), x, y,
                       (intr[4], intr[5], intr[6], intr[7], intr[8]))
    return xp.stack([u, v], axis=-1)


@dataclass(frozen=True)
class Observation:
    camera: str
    pose: int
    corners: np.ndarray     # (n, 2) px, target order


@dataclass(frozen=True, eq=False)
class Calibration:
    """A calibrated rig. Per camera name: `intrinsics` (9,) in `INTRINSICS` order, `size` (W, H),
    `extrinsics` (R, t) from its group's reference frame, `reference` that camera's name. `poses`
    (pose index -> (R, t) target -> reference frame). `covariance` of every parameter, `index`
    ((name, "intrinsics"|"extrinsics") or ("pose", k) -> slice into it). `sigma_det` the
    detection noise the covariance uses, `sigma_residual` the residuals' estimate of it, `rms`
    per camera and `rms_all` (px, OpenCV's reprojection error: sqrt(sum |r_i|^2 / points)), `views` per camera, `pitch` the target pitch assumed (m)."""

    intrinsics: dict
    size: dict
    extrinsics: dict
    reference: dict
    poses: dict
    covariance: np.ndarray
    index: dict
    sigma_det: float
    sigma_residual: float
    rms: dict
    rms_all: float
    views: dict
    pitch: float

    @property
    def names(self) -> list[str]:
        return list(self.intrinsics)

    def sigma(self, name: str) -> np.ndarray:
        """1-sigma of the camera's intrinsics (9,)."""
        s = self.index[(name, "intrinsics")]
        return np.sqrt(np.diag(self.covariance)[s])

    def K(self, name: str) -> np.ndarray:
        fx, fy, cx, cy = self.intrinsics[name][:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def distortion(self, name: str) -> np.ndarray:
        return np.asarray(self.intrinsics[name][4:], dtype=float)

    def relative(self, first: str, second: str) -> tuple[np.ndarray, np.ndarray]:
        """(R, T): X_second = R X_first + T (camera frames, metres), `cv2.stereoCalibrate`'s
        convention; the two cameras must be in one group."""
        if self.reference[first] != self.reference[second]:
            raise ValueError(f"cameras {first!r} and {second!r} share no pose")
        R1, t1 = self.extrinsics[first]
        R2, t2 = self.extrinsics[second]
        R = R2 @ R1.T
        return R, t2 - R @ t1


@functools.cache
def _kernels():
    """The jitted residual model and its Jacobian over a batch of observations (compiled once
    per batch shape: Monte Carlo trials reuse them)."""
    import jax
    import jax.numpy as jnp

    def one(intr, ext, pose, X):
        return project(intr, ext, pose, X, jnp).reshape(-1)

    axes = (0, 0, 0, None)
    return (jax.jit(jax.vmap(one, in_axes=axes)),
            jax.jit(jax.vmap(jax.jacfwd(one, argnums=(0, 1, 2)), in_axes=axes)))


def _groups(cameras: list[str], observations: list[Observation]) -> dict[str, str]:
    """camera -> the reference camera of its group (cameras linked through shared poses)."""
    seen: dict[int, set] = {}
    for o in observations:
        seen.setdefault(o.pose, set()).add(o.camera)
    reference = {}
    for start in cameras:
        if start in reference:
            continue
        group, todo = {start}, [start]
        while todo:
            c = todo.pop()
            for names in seen.values():
                if c in names:
                    for other in names - group:
                        group.add(other)
                        todo.append(other)
        for c in group:
            reference[c] = start
    return reference


def _as4(R, t) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, np.ravel(t)
    return M


def initial(cameras, sizes, observations, target):
    """Start values: per camera cv2.calibrateCamera; extrinsics and poses chained through shared
    poses (module docstring). Returns (intrinsics, extrinsics 4x4, poses 4x4, reference)."""
    import cv2

    obj = target.points().astype(np.float32)
    intr, view = {}, {}
    for name in cameras:
        mine = [o for o in observations if o.camera == name]
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [obj] * len(mine), [o.corners.astype(np.float32) for o in mine], sizes[name], None, None)
        intr[name] = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist.ravel()[:5]])
        for o, r, t in zip(mine, rvecs, tvecs):
            view[(name, o.pose)] = _as4(cv2.Rodrigues(r)[0], t)
    reference = _groups(cameras, observations)
    ext = {c: np.eye(4) for c in cameras if reference[c] == c}     # camera <- reference
    changed = True
    while changed:
        changed = False
        for (c, p), T in view.items():
            if c in ext:
                continue
            for k in ext:
                if (k, p) in view:
                    ext[c] = T @ np.linalg.inv(view[(k, p)]) @ ext[k]
                    changed = True
                    break
    poses = {}
    for (c, p), T in sorted(view.items(), key=lambda kv: kv[0][1]):
        poses.setdefault(p, np.linalg.inv(ext[c]) @ T)
    return intr, ext, poses, reference


def damped_step(scaled: np.ndarray, rhs: np.ndarray, damping: float) -> np.ndarray | None:
    """The Levenberg-Marquardt step (A + damping diag(A)) x = -g in Jacobi-scaled form: with
    D = diag(A), S = D^-1/2 A D^-1/2 (unit diagonal) and rhs = -D^-1/2 g, the solution of
    (S + damping I) y = rhs by Cholesky, x = D^-1/2 y (y is returned; None when S + damping I is
    not positive definite in floating point: the step is refused and the damping raised). A
    Cholesky of the small SPD system, not np.linalg.solve: numpy's threaded LU took 30-50 ms of
    CPU per 100 x 100 solve on a loaded 2-core machine, scipy's Cholesky 0.07 ms."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve

    try:
        return cho_solve(cho_factor(scaled + damping * np.eye(len(rhs))), rhs)
    except LinAlgError:
        return None


def calibrate(cameras: list[str], sizes: dict, observations: list[Observation], target,
              sigma_det: float | None = None) -> Calibration:
    """The joint calibration of `cameras` (names, each with `sizes` (W, H)) from the detected
    `observations` (module docstring)."""
    import jax.numpy as jnp
    from scipy import sparse

    require_x64()
    intr0, ext0, poses0, reference = initial(cameras, sizes, observations, target)
    # parameter layout
    index, offset = {}, 0
    for c in cameras:
        index[(c, "intrinsics")] = slice(offset, offset + 9)
        offset += 9
    for c in cameras:
        if reference[c] != c:
            index[(c, "extrinsics")] = slice(offset, offset + 6)
            offset += 6
    pose_ids = sorted(poses0)
    for p in pose_ids:
        index[("pose", p)] = slice(offset, offset + 6)
        offset += 6
    n_par = offset
    theta = np.zeros(n_par)
    for c in cameras:
        theta[index[(c, "intrinsics")]] = intr0[c]
        if (c, "extrinsics") in index:
            theta[index[(c, "extrinsics")]] = np.r_[rvec(ext0[c][:3, :3]), ext0[c][:3, 3]]
    for p in pose_ids:
        theta[index[("pose", p)]] = np.r_[rvec(poses0[p][:3, :3]), poses0[p][:3, 3]]

    X = jnp.asarray(target.points())
    observed = np.stack([o.corners for o in observations])          # (O, n, 2)
    n = observed.shape[1]
    ci = np.array([index[(o.camera, "intrinsics")].start for o in observations])
    ce = np.array([index[(o.camera, "extrinsics")].start if (o.camera, "extrinsics") in index else -1
                   for o in observations])
    cp = np.array([index[("pose", o.pose)].start for o in observations])
    kernel_predict, kernel_jacobian = _kernels()

    def predict(*b):
        return kernel_predict(*b, X)

    def jacobian(*b):
        return kernel_jacobian(*b, X)

    def blocks(th):
        ext = np.where(ce[:, None] >= 0, th[np.maximum(ce, 0)[:, None] + np.arange(6)], 0.0)
        return (th[ci[:, None] + np.arange(9)], ext, th[cp[:, None] + np.arange(6)])

    def residual(th):
        return np.asarray(predict(*blocks(th))) - observed.reshape(len(observations), -1)

    def jac(th):
        Ji, Je, Jp = (np.asarray(a) for a in jacobian(*blocks(th)))
        rows = np.arange(len(observations) * 2 * n).reshape(len(observations), 2 * n)
        parts = [(Ji, ci, 9), (Je, ce, 6), (Jp, cp, 6)]
        data, rr, cc = [], [], []
        for Jb, start, width in parts:
            keep = start >= 0
            cols = start[keep][:, None, None] + np.arange(width)[None, None, :]
            data.append(Jb[keep].ravel())
            rr.append(np.broadcast_to(rows[keep][:, :, None], Jb[keep].shape).ravel())
            cc.append(np.broadcast_to(cols, Jb[keep].shape).ravel())
        return sparse.csr_matrix((np.concatenate(data), (np.concatenate(rr), np.concatenate(cc))),
                                 shape=(rows.size, n_par))

    r = residual(theta).ravel()
    cost, damping = r @ r, LM_START_DAMPING
    for _ in range(LM_MAX_ITERATIONS):
        J = jac(theta)
        A = (J.T @ J).toarray()
        g = J.T @ r
        d = np.sqrt(np.diag(A))
        scaled, rhs = A / d[:, None] / d[None, :], -g / d
        while True:
            y = damped_step(scaled, rhs, damping)
            if y is not None:
                step = y / d
                r_new = residual(theta + step).ravel()
                if r_new @ r_new <= cost:
                    break
            damping *= 10.0
            if damping > 1e12:
                step = np.zeros_like(theta)
                r_new = r
                break
        theta = theta + step
        drop = cost - r_new @ r_new
        r, cost = r_new, r_new @ r_new
        damping = max(damping / 10.0, 1e-12)
        if drop <= LM_RELATIVE_COST * cost:
            break
    J = jac(theta)
    A = (J.T @ J).toarray()
    scale = 1.0 / np.sqrt(np.diag(A))
    inverse = scale[:, None] * np.linalg.inv(scale[:, None] * A * scale[None, :]) * scale[None, :]
    m = r.size
    sigma_residual = float(np.sqrt(cost / max(1, m - n_par)))
    sigma = sigma_residual if sigma_det is None else float(sigma_det)
    per_obs = residual(theta)
    rms = {c: float(np.sqrt(2 * np.mean(per_obs[[o.camera == c for o in observations]] ** 2)))
           for c in cameras}
    extrinsics = {}
    for c in cameras:
        if (c, "extrinsics") in index:
            e = theta[index[(c, "extrinsics")]]
            extrinsics[c] = (rodrigues(e[:3]), e[3:].copy())
        else:
            extrinsics[c] = (np.eye(3), np.zeros(3))
    poses = {p: (rodrigues(theta[index[("pose", p)]][:3]), theta[index[("pose", p)]][3:].copy())
             for p in pose_ids}
    return Calibration(
        intrinsics={c: theta[index[(c, "intrinsics")]].copy() for c in cameras},
        size=dict(sizes), extrinsics=extrinsics, reference=reference, poses=poses,
        covariance=sigma ** 2 * inverse, index=index, sigma_det=sigma,
        sigma_residual=sigma_residual, rms=rms, rms_all=float(np.sqrt(2 * cost / m)),
        views={c: sum(o.camera == c for o in observations) for c in cameras}, pitch=target.pitch)


def simulate(cameras, session, sigma: float, rng) -> list[Observation]:
    """Observations of the session's views by `cameras` (vdo `Camera`s): the true corners
    (`Camera.project`) plus independent N(0, sigma^2) noise on each coordinate (px)."""
    out = []
    X = session.target.points()
    for cam in cameras:
        for k in session.views[cam.name]:
            uv = cam.project(session.poses[k].world(X))
            out.append(Observation(cam.name, k, uv + rng.normal(0.0, sigma, uv.shape)))
    return out
