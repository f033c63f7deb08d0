"""A calibration against the true cameras it was rendered with: every parameter's error, its
predicted sigma and their ratio (the z-score), and each stereo pair's relative pose error."""

from __future__ import annotations

import numpy as np

from vdo.calib.solve import INTRINSICS, Calibration, rvec


def true_intrinsics(camera) -> np.ndarray:
    """(fx, fy, cx, cy, k1, k2, p1, p2, k3) of a vdo Camera."""
    return np.array([camera.focal_px, camera.focal_px, *camera.K[:2, 2], *camera.distortion])


def versus_truth(cal: Calibration, cameras, pairs) -> dict:
    """{"cameras": {name: {param: {value, true, error, sigma, z}}}, "pairs": {"a:b": {...}}}:
    `cameras` the true (render-scale) vdo Cameras, `pairs` (first, second) names. A pair's
    relative pose (`Calibration.relative`) against the truth: rotation-vector error (deg),
    translation error (mm), the baseline's error (mm) and the sigmas of the six parameters
    when the first camera is its group's reference."""
    out = {"cameras": {}, "pairs": {}}
    by_name = {c.name: c for c in cameras}
    for name in cal.names:
        true = true_intrinsics(by_name[name])
        value, sigma = cal.intrinsics[name], cal.sigma(name)
        out["cameras"][name] = {p: {"value": float(v), "true": float(t), "error": float(v - t),
                                    "sigma": float(s), "z": float((v - t) / s) if s > 0 else None}
                                for p, v, t, s in zip(INTRINSICS, value, true, sigma)}
        out["cameras"][name]["rms_px"] = cal.rms[name]
        out["cameras"][name]["views"] = cal.views[name]
    for a, b in pairs:
        if cal.reference[a] != cal.reference[b]:
            continue
        R, T = cal.relative(a, b)
        A, B = by_name[a], by_name[b]
        R_true = B.R @ A.R.T
        T_true = B.t - R_true @ A.t
        dr = rvec(R) - rvec(R_true)
        entry = {"rotation_error_deg": np.degrees(dr).tolist(),
                 "translation_error_mm": ((T - T_true) * 1e3).tolist(),
                 "baseline_error_mm": float((np.linalg.norm(T) - np.linalg.norm(T_true)) * 1e3)}
        if cal.reference[a] == a and (b, "extrinsics") in cal.index:
            s = np.sqrt(np.diag(cal.covariance)[cal.index[(b, "extrinsics")]])
            entry["rotation_sigma_deg"] = np.degrees(s[:3]).tolist()
            entry["translation_sigma_mm"] = (s[3:] * 1e3).tolist()
        out["pairs"][f"{a}:{b}"] = entry
    return out
