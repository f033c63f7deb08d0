"""Design checks per camera and region: the numbers a DIC planning sheet asks for, with flags.

For each camera and each region it sees (samples visible to it, `vdo.physics.visibility`):

stand-off      median distance |X - C| (m) from the optical centre to the region's seen samples,
               and their depth range Z_c (along the optical axis, m)
mm_per_px      median footprint 1 / sqrt|det A| (A = s [t_u t_v], `vdo.objective`), mm per pixel
speckle_px     median dot diameter in pixels, dot_diameter x sqrt|det A|; flagged outside
               [3, 5] px (finer dots alias, coarser ones waste resolution)
depth of field thin lens of focal length f, f-number N, focus distance s (along the axis) and
               circle of confusion c = 2 pixel pitches (blur up to two pixels is accepted):
               near = s f^2 / (f^2 + N c (s - f)), far = s f^2 / (f^2 - N c (s - f)) (infinite
               when f^2 <= N c (s - f), beyond the hyperfocal distance). Flagged when the region's
               depth range leaves [near, far]. Not checked for a pinhole (no f_number).
fov_fill       the fraction of the image the region covers, Σ area |det A| / (W H)
exposure       the noise-free gray level of the paint under the predicted irradiance E
               (`vdo.physics.lighting`): DN = sensor.mean_dn(ρ E / π), ρ = ρ_b + (ρ_w - ρ_b) f over the
               pattern's values f and the seen samples (weighted by their pixels). Reported: the
               mean and 99th percentile as a fraction of the range (max DN), and the fraction of
               pixels at or above saturation (min(full well, top DN)). Flagged when the 99th
               percentile is under 25 % (under-exposed) or over 95 % (saturating).
interpolation  the correlation's interpolation floor against the sensor noise, at the footprint
               of the region's median sample: e_DN = e (ρ_w - ρ_b) (E/π) dDN/dL std(f), with e
               the RMS error of cubic B-spline interpolation of the box-pixel image of the unit-
               variance pattern at a half-pixel motion (`vdo.model.speckle.interpolation_error`: the
               speckle's content above the pixel's Nyquist frequency aliases, which no
               interpolation undoes), against σ_n = sqrt(sensor.variance_dn) at the mean gray.
               The error is a fixed gray-level pattern that moves with the motion, so the
               correlation's displacement bias grows with e_DN / σ_n against the noise's √2 σ
               (measured on the built-in joint, noise-free renders: bias at most 0.65 √2σ at
               e_DN / σ_n ≈ 1, 2.5 √2σ at 3.3, up to 11 √2σ at 4.5-10; docs/exports.md). Flagged
               when e_DN > 2 σ_n: the correlation's error is then bias-dominated, not what the
               predicted σ says; finer pixels, or a speckle whose edges are soft at the pixel
               scale, lower e.
"""

from __future__ import annotations

import math

import numpy as np

SPECKLE_PX = (3.0, 5.0)
EXPOSURE = (0.25, 0.95)
INTERPOLATION_NOISE = 2.0  # flag when the interpolation error exceeds this many sensor-noise sigmas
COC_PIXELS = 2.0
PATTERN_VALUES = 4096     # pattern values drawn (evenly strided) for the gray-level distribution


def depth_of_field(focal: float, f_number: float, focus: float, coc: float) -> tuple[float, float]:
    """(near, far) limits of acceptable sharpness along the optical axis (m), thin lens (module
    docstring); far = inf beyond the hyperfocal distance."""
    k = f_number * coc * (focus - focal)
    near = focus * focal ** 2 / (focal ** 2 + k)
    far = focus * focal ** 2 / (focal ** 2 - k) if focal ** 2 > k else math.inf
    return near, far


def _weighted_percentile(values, weights, q):
    order = np.argsort(values)
    cw = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cw, q / 100.0 * cw[-1])])


def exposure(irradiance, weights, speckle, sensor, pattern) -> dict:
    """Gray-level statistics of the paint under irradiance E (N,) with per-sample weights (N,)
    (module docstring): mean and p99 as fractions of max DN, the saturated fraction, and flags."""
    f = np.asarray(pattern, dtype=float).ravel()
    f = f[:: max(1, f.size // PATTERN_VALUES)]
    # the distinct values with their counts: the same distribution, several times fewer gray levels
    # to sort (a pattern has a few hundred distinct values among its PATTERN_VALUES)
    f, count = np.unique(f, return_counts=True)
    rho = speckle.black_albedo + (speckle.white_albedo - speckle.black_albedo) * f
    dn = sensor.mean_dn(np.outer(irradiance / np.pi, rho))          # (N, distinct values)
    w = (np.asarray(weights, dtype=float)[:, None] * (count / count.sum())[None, :]).ravel()
    top = sensor.max_dn
    sat = min(top, sensor.mean_dn(sensor.saturation_linear()))
    mean, p99 = float(np.average(dn.ravel(), weights=w)), _weighted_percentile(dn.ravel(), w, 99)
    flags = []
    if p99 < EXPOSURE[0] * top:
        flags.append(f"under-exposed: 99th percentile gray {p99:.0f} of {top} DN "
                     f"({p99 / top:.0%} < {EXPOSURE[0]:.0%})")
    if p99 > EXPOSURE[1] * top:
        flags.append(f"saturating: 99th percentile gray {min(p99, top):.0f} of {top} DN "
                     f"(> {EXPOSURE[1]:.0%})")
    return {"mean_gray_fraction": min(mean, top) / top, "p99_gray_fraction": min(p99, top) / top,
            "saturated_fraction": float(np.sum(w[dn.ravel() >= sat]) / np.sum(w)), "flags": flags}


def interpolation_floor(footprints, irradiance, speckle, sensor, pattern) -> list[dict]:
    """The interpolation check of the module docstring at K footprints A (K, 2, 2) px/m under
    irradiances E (K,) W m^-2, for the [0, 1] `pattern`: one {"error_dn", "noise_dn", "ratio"}
    per footprint, e_DN and σ_n in DN."""
    from vdo.model.speckle import interpolation_error, normalise

    f = np.asarray(pattern, dtype=np.float64)
    e = interpolation_error(normalise(f), speckle.texel, np.linalg.inv(np.asarray(footprints)))
    out = []
    for e_k, E in zip(e, np.asarray(irradiance, dtype=float)):
        radiance = E / np.pi
        contrast = float(sensor.mean_dn(radiance * speckle.white_albedo)
                         - sensor.mean_dn(radiance * speckle.black_albedo))   # DN per unit of f
        mean = sensor.mean_dn(radiance * (speckle.black_albedo + (speckle.white_albedo
                                                                  - speckle.black_albedo) * f.mean()))
        noise = float(math.sqrt(sensor.variance_dn(float(mean))))
        error = float(e_k) * contrast * float(f.std())
        out.append({"error_dn": error, "noise_dn": noise, "ratio": error / noise})
    return out


def design_checks(exp, cameras, samples, visible, irradiance, pattern) -> list[dict]:
    """One row per (camera, region) with seen samples: the checks of the module docstring.
    `visible` (C, N) bool (`Visibility.visible`), `irradiance` (N,) W m^-2
    (`Illumination.irradiance`), `pattern` the [0, 1] speckle tile."""
    rows, footprints, irradiances = [], [], []
    T = np.stack([samples.tangent_u, samples.tangent_v], axis=-1)
    for i, (cam, spec) in enumerate(zip(cameras, exp.camera_specs)):
        for k, region in enumerate(samples.region_names):
            seen = np.asarray(visible[i]) & (samples.region == k)
            if not seen.any():
                continue
            X = samples.points[seen]
            A = cam.sensitivity(X) @ T[seen]                                        # px/m
            density = np.sqrt(np.abs(np.linalg.det(A)))
            pixels = samples.area[seen] * density ** 2
            depth = (X - cam.position) @ cam.optical_axis
            speckle_px = float(np.median(exp.speckle.dot_diameter * density))
            flags = []
            if not SPECKLE_PX[0] <= speckle_px <= SPECKLE_PX[1]:
                flags.append(f"speckle dots {speckle_px:.1f} px (want {SPECKLE_PX[0]:g}-"
                             f"{SPECKLE_PX[1]:g} px)")
            dof = None
            if spec.f_number is not None:
                near, far = depth_of_field(cam.focal_length, spec.f_number, spec.focus_distance,
                                           COC_PIXELS * cam.pixel_size)
                dof = {"near_m": near, "far_m": far if math.isfinite(far) else None,
                       "f_number": spec.f_number, "focus_m": spec.focus_distance,
                       "circle_of_confusion_um": COC_PIXELS * cam.pixel_size * 1e6}
                if depth.min() < near or depth.max() > far:
                    flags.append(f"out of focus: depth {depth.min():.3f}-{depth.max():.3f} m "
                                 f"leaves the depth of field {near:.3f}-"
                                 f"{far:.3f} m")
            expo = exposure(irradiance[seen], pixels, exp.speckle, exp.sensor, pattern)
            median = int(np.argsort(density)[len(density) // 2])
            footprints.append(A[median])
            irradiances.append(float(irradiance[seen][median]))
            rows.append({
                "camera": cam.name, "region": region,
                "standoff_m": float(np.median(np.linalg.norm(X - cam.position, axis=1))),
                "depth_min_m": float(depth.min()), "depth_max_m": float(depth.max()),
                "mm_per_px": float(np.median(1e3 / density)), "speckle_px": speckle_px,
                "depth_of_field": dof,
                "fov_fill": float(pixels.sum() / (cam.width * cam.height)),
                "exposure": {k: v for k, v in expo.items() if k != "flags"},
                "flags": flags + expo["flags"]})
    if rows:
        floors = interpolation_floor(footprints, irradiances, exp.speckle, exp.sensor, pattern)
        for row, interp in zip(rows, floors):
            row["interpolation"] = interp
            if interp["ratio"] > INTERPOLATION_NOISE:
                row["flags"].append(f"interpolation floor: the correlation's interpolation error "
                                    f"{interp['error_dn']:.0f} DN exceeds the sensor noise "
                                    f"{interp['noise_dn']:.0f} DN ({interp['ratio']:.1f}x): "
                                    f"displacement bias, not noise, will dominate (finer pixels "
                                    f"or a softer speckle)")
    return rows


def print_checks(rows: list[dict]) -> None:
    """The design-check table on the console (the CLI's)."""
    wc = max([6] + [len(r["camera"]) for r in rows]) + 2
    wr = max([6] + [len(r["region"]) for r in rows]) + 2
    print(f"{'camera':<{wc}}{'region':<{wr}}{'stand-off m':>12}{'mm/px':>8}{'dot px':>8}"
          f"{'DoF m':>14}{'FOV fill':>9}{'gray mean/p99':>15}{'sat':>6}{'interp/noise':>13}  flags")
    for r in rows:
        d = r["depth_of_field"]
        dof = "-" if d is None else f"{d['near_m']:.2f}-" + (f"{d['far_m']:.2f}" if d["far_m"]
                                                            else "inf")
        e = r["exposure"]
        print(f"{r['camera']:<{wc}}{r['region']:<{wr}}{r['standoff_m']:>12.3f}{r['mm_per_px']:>8.3f}"
              f"{r['speckle_px']:>8.2f}{dof:>14}{r['fov_fill']:>9.1%}"
              f"{e['mean_gray_fraction']:>8.0%}/{e['p99_gray_fraction']:<6.0%}"
              f"{e['saturated_fraction']:>6.1%}{r['interpolation']['ratio']:>13.2f}  {'; '.join(r['flags'])}")
