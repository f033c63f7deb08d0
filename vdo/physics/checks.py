"""Design checks per camera and region: the numbers a DIC planning sheet asks for, with flags.

For each camera and each region it sees (samples visible to it, `vdo.physics.visibility`), but
the pairs whose usable view is negligible (under NEGLIGIBLE_VIEW of the region, `negligible_views`):

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
interpolation  what the lab's correlation measures against the noise alone, at the footprint of the
               region's median sample (`vdo.model.interpolant.correlation_error`): the B-spline
               interpolant of [analysis] on the box-pixel image after the lens's blur
               (`vdo.model.optics`: diffraction at the f-number, or f/8 assumed when the camera
               has none, and the defocus at the median depth), for a patch of P = Ω |det A|
               pixels and the sensor noise σ_n against the pattern's gray contrast. Reported:
               `measured_over_noise` = σ_measured / σ_noise (its noise part alone, what an exact
               interpolant would give) and `measured_over_bound` (against the Cramér-Rao bound
               of one noisy image without the lens's blur, as vdo's σ), per image axis, and the bias's RMS over sub-pixel positions
               (px). Also e_DN, the RMS interpolation error of the gray levels at a half-pixel
               motion of the images as `vdo render` makes them (diffraction only for a camera
               with an f_number), against σ_n (`interpolation_floor`; `vdo.dic.series` warns
               when e_DN > INTERPOLATION_NOISE σ_n on its renders).

Severity. Each finding carries one: "fail" (the measurement will not work as planned: the region
leaves the depth of field, the paint saturates), "warn" (it works, worse than the bound says:
dots finer than 3 px, under-exposure, a correlation whose error is more than
INTERPOLATION_WARN x its noise part) and "advice" (dots coarser than 5 px waste resolution; the
interpolation bias adds more than INTERPOLATION_ADVICE x to the noise part). σ_measured
(`vdo.physics.measured`) accounts for the interpolation bias, so that check never fails a design.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from vdo.config.procedure import Analysis
    from vdo.config.rig import CameraSpec, Evaluation, SpeckleSpec
    from vdo.model.sensor import SensorModel

SPECKLE_PX = (3.0, 5.0)
EXPOSURE = (0.25, 0.95)
INTERPOLATION_NOISE = 2.0  # e_DN / σ_n above this: images as rendered are bias-dominated (vdo.dic.series)
INTERPOLATION_WARN = 2.0    # σ_measured / σ_noise above this: the bias dominates ("warn")
INTERPOLATION_ADVICE = 1.25  # above this: the bias adds visibly to the noise ("advice")
SEVERITIES = ("fail", "warn", "advice")   # most severe first
COC_PIXELS = 2.0
# A camera whose usable view (`vdo.physics.usable`) covers less than this fraction of a region's
# area is left out of that region's checks (`negligible_views`): its median footprint, depth and
# gray levels describe a sliver at the image's edge or at grazing incidence, which weighs next to
# nothing in the region's σ (area-weighted) while its flags crowded out the views that matter
# (0.07 % of a dome at 0.2 % FOV fill made half of one lab's warnings).
NEGLIGIBLE_VIEW = 0.01
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


def _gray(speckle, sensor, pattern, irradiance) -> tuple[float, float]:
    """(contrast, noise) in DN under irradiance E: the gray levels per unit of the pattern value f
    (white minus black), and σ_n = sqrt(sensor.variance_dn) at the mean gray."""
    f = np.asarray(pattern, dtype=np.float64)
    radiance = irradiance / np.pi
    contrast = float(sensor.mean_dn(radiance * speckle.white_albedo)
                     - sensor.mean_dn(radiance * speckle.black_albedo))
    mean = sensor.mean_dn(radiance * (speckle.black_albedo + (speckle.white_albedo
                                                              - speckle.black_albedo) * f.mean()))
    return contrast, float(math.sqrt(sensor.variance_dn(float(mean))))


def interpolation_floor(footprints, irradiance, speckle, sensor, pattern, optics=None) -> list[dict]:
    """The e_DN check of the module docstring at K footprints A (K, 2, 2) px/m under
    irradiances E (K,) W m^-2, for the [0, 1] `pattern`, through the K `optics`
    (`vdo.model.optics.OpticsBlur` or None): one {"error_dn", "noise_dn", "ratio"} per
    footprint, e_DN and σ_n in DN."""
    from vdo.model.speckle import normalise
    from vdo.model.interpolant import interpolation_error

    f = np.asarray(pattern, dtype=np.float64)
    e = interpolation_error(normalise(f), speckle.texel, np.linalg.inv(np.asarray(footprints)),
                            optics=optics)
    out = []
    for e_k, E in zip(e, np.asarray(irradiance, dtype=float)):
        contrast, noise = _gray(speckle, sensor, f, E)
        error = float(e_k) * contrast * float(f.std())
        out.append({"error_dn": error, "noise_dn": noise, "ratio": error / noise})
    return out


def measurement_floor(footprints, irradiance, pixels, optics, speckle, sensor, pattern,
                      interpolant: str = "cubic", noisy_reference: bool = True) -> list[dict]:
    """The interpolation check of the module docstring: what the lab's correlation measures at K
    footprints A (K, 2, 2) px/m, irradiances E (K,), patches of `pixels` (K,) pixels, through the
    K `optics`. σ (in pattern stds) = σ_n / (contrast std f). One dict per footprint:
    measured_over_noise and measured_over_bound (2,) per image axis, bias_px (2,) RMS over
    sub-pixel positions, noise_rel σ, patch_pixels the patch's pixel count (an area, px²), and
    the `vdo.model.interpolant.CorrelationError` as "model" (not JSON: `design_checks` drops
    it)."""
    from vdo.model.speckle import normalise
    from vdo.model.interpolant import correlation_error
    from vdo.model.spline_response import INTERPOLANTS

    f = np.asarray(pattern, dtype=np.float64)
    model = correlation_error(normalise(f), speckle.texel, np.linalg.inv(np.asarray(footprints)),
                              order=INTERPOLANTS[interpolant], optics=optics,
                              noisy_reference=noisy_reference)
    sigma = np.array([_gray(speckle, sensor, f, E)[1] / (_gray(speckle, sensor, f, E)[0] * f.std())
                      for E in np.asarray(irradiance, dtype=float)])
    p = np.asarray(pixels, dtype=float)
    total = np.diagonal(model.covariance(sigma, p), axis1=1, axis2=2)
    noise = (sigma ** 2 / p)[:, None] * np.diagonal(model.noise, axis1=1, axis2=2)
    over_bound = model.ratio(sigma, p, sharp=True)
    bias = np.sqrt(np.diagonal(model.bias, axis1=1, axis2=2))
    return [{"measured_over_noise": [float(x) for x in np.sqrt(total[k] / noise[k])],
             "measured_over_bound": [float(x) for x in over_bound[k]],
             "bias_px": [float(x) for x in bias[k]], "noise_rel": float(sigma[k]),
             "patch_pixels": float(p[k]), "interpolant": interpolant, "model": (model, k)}
            for k in range(len(p))]


def _camera_optics(cam, spec, depth: float):
    """The camera's `vdo.model.optics.OpticsBlur` at `depth` m (f/8 assumed without f_number)."""
    from vdo.model.optics import optics_blur

    return optics_blur(cam.pixel_size, cam.focal_length, spec.f_number, spec.focus_distance, depth)


def negligible_views(camera_names, samples, visible, usable) -> list[dict]:
    """The (camera, region) pairs with seen samples (`visible` (C, N) bool, the ray cast) whose
    usable view (`usable` (C, N) bool, `Prediction.usable`) covers less than `NEGLIGIBLE_VIEW` of
    the region's area: {"camera", "region", "usable_fraction"} (area fraction), in the cameras'
    and regions' order."""
    out = []
    for i, name in enumerate(camera_names):
        for k, region in enumerate(samples.region_names):
            mask = samples.region == k
            if not np.asarray(visible[i])[mask].any():
                continue
            fraction = float(samples.area[mask & np.asarray(usable[i])].sum() / samples.area[mask].sum())
            if fraction < NEGLIGIBLE_VIEW:
                out.append({"camera": name, "region": region, "usable_fraction": fraction})
    return out


def design_checks(camera_specs: tuple[CameraSpec, ...], evaluation: Evaluation,
                  speckle: SpeckleSpec, sensor: SensorModel, analysis: Analysis,
                  cameras, samples, visible, irradiance, pattern, leave_out=()) -> list[dict]:
    """One row per (camera, region) with seen samples, but the (camera name, region name) pairs
    in `leave_out` (`negligible_views`): the checks of the module docstring, each
    finding {"severity", "check", "message"} in "findings" (most severe first), their messages in
    "flags" and the worst severity in "severity" (None when nothing was found).
    `visible` (C, N) bool (`Visibility.visible`), `irradiance` (N,) W m^-2
    (`Illumination.irradiance`), `pattern` the [0, 1] speckle tile. The tables: the cameras'
    [[camera]] specs (f-number, focus), [evaluation] (the patch), [speckle], [sensor] and
    [analysis] (the interpolant and the reference). A camera gathering k times the sensor's
    reference light (its f-number and exposure time, `vdo.physics.lighting.exposure_factors`)
    is judged under k E."""
    from vdo.physics.lighting import exposure_factors

    gathered = exposure_factors(camera_specs, sensor)
    rows, lit, footprints, irradiances, lens, rendered, pixels = [], [], [], [], [], [], []
    T = np.stack([samples.tangent_u, samples.tangent_v], axis=-1)
    for i, (cam, spec) in enumerate(zip(cameras, camera_specs)):
        for k, region in enumerate(samples.region_names):
            seen = np.asarray(visible[i]) & (samples.region == k)
            if not seen.any() or (cam.name, region) in leave_out:
                continue
            X = samples.points[seen]
            A = cam.sensitivity(X) @ T[seen]                                        # px/m
            density = np.sqrt(np.abs(np.linalg.det(A)))
            pixels_seen = samples.area[seen] * density ** 2
            depth = (X - cam.position) @ cam.optical_axis
            speckle_px = float(np.median(speckle.dot_diameter * density))
            found = []
            if speckle_px < SPECKLE_PX[0]:
                found.append(("warn", "speckle", f"speckle dots {speckle_px:.1f} px (want "
                              f"{SPECKLE_PX[0]:g}-{SPECKLE_PX[1]:g} px): finer dots alias"))
            elif speckle_px > SPECKLE_PX[1]:
                found.append(("advice", "speckle", f"speckle dots {speckle_px:.1f} px (want "
                              f"{SPECKLE_PX[0]:g}-{SPECKLE_PX[1]:g} px): coarser dots waste "
                              f"resolution"))
            dof = None
            if spec.f_number is not None:
                near, far = depth_of_field(cam.focal_length, spec.f_number, spec.focus_distance,
                                           COC_PIXELS * cam.pixel_size)
                dof = {"near_m": near, "far_m": far if math.isfinite(far) else None,
                       "f_number": spec.f_number, "focus_m": spec.focus_distance,
                       "circle_of_confusion_um": COC_PIXELS * cam.pixel_size * 1e6}
                if depth.min() < near or depth.max() > far:
                    found.append(("fail", "depth of field", f"out of focus: depth "
                                  f"{depth.min():.3f}-{depth.max():.3f} m leaves the depth of "
                                  f"field {near:.3f}-{far:.3f} m"))
            expo = exposure(gathered[i] * irradiance[seen], pixels_seen, speckle, sensor, pattern)
            for flag in expo["flags"]:
                found.append(("fail" if flag.startswith("saturating") else "warn", "exposure", flag))
            median = int(np.argsort(density)[len(density) // 2])
            rows.append({
                "camera": cam.name, "region": region,
                "standoff_m": float(np.median(np.linalg.norm(X - cam.position, axis=1))),
                "depth_min_m": float(depth.min()), "depth_max_m": float(depth.max()),
                "mm_per_px": float(np.median(1e3 / density)), "speckle_px": speckle_px,
                "depth_of_field": dof,
                "fov_fill": float(pixels_seen.sum() / (cam.width * cam.height)),
                "exposure": {k: v for k, v in expo.items() if k != "flags"},
                "found": found, "interpolation": None})
            if not irradiance[seen][median] > 0:      # dark: no contrast, nothing to interpolate
                continue
            lit.append(rows[-1])
            footprints.append(A[median])
            irradiances.append(float(gathered[i] * irradiance[seen][median]))
            lens.append(_camera_optics(cam, spec, float(depth[median])))
            rendered.append(lens[-1] if spec.f_number is not None else None)
            pixels.append(evaluation.patch_size ** 2 * float(density[median]) ** 2)
    if lit:
        floors = interpolation_floor(footprints, irradiances, speckle, sensor, pattern, rendered)
        measured = measurement_floor(footprints, irradiances, pixels, lens, speckle, sensor,
                                     pattern, analysis.interpolant, analysis.reference == "noisy")
        for row, interp, meas, opt in zip(lit, floors, measured, lens):
            meas.pop("model")
            row["interpolation"] = interp | {"measured": meas, "optics": {
                "f_number": opt.f_number, "f_number_assumed": opt.assumed,
                "sigma_px": opt.sigma_px, "defocus_px": opt.defocus_px}}
            worst = max(meas["measured_over_noise"])
            if worst > INTERPOLATION_ADVICE:
                lens_note = f"f/{opt.f_number:g}" + (" assumed" if opt.assumed else "")
                row["found"].append((
                    "warn" if worst > INTERPOLATION_WARN else "advice", "interpolation",
                    f"interpolation bias: the {meas['interpolant']} correlation's error is "
                    f"{worst:.1f}x its noise part ({max(meas['measured_over_bound']):.1f}x the "
                    f"bound; bias {max(meas['bias_px']):.4f} px RMS, {lens_note}): finer pixels, "
                    f"a softer speckle, a smaller aperture or the quintic interpolant lower it"))
    for row in rows:
        found = sorted(row.pop("found"), key=lambda f: SEVERITIES.index(f[0]))
        row["findings"] = [{"severity": s, "check": c, "message": m} for s, c, m in found]
        row["flags"] = [m for _, _, m in found]
        row["severity"] = found[0][0] if found else None
    return rows


def _measured_over_noise(row: dict) -> float:
    """The row's worst σ_measured / σ_noise over the image axes; NaN for a dark pair (no light,
    no contrast: nothing interpolated)."""
    if row["interpolation"] is None:
        return math.nan
    return max(row["interpolation"]["measured"]["measured_over_noise"])


def count_findings(rows: list[dict]) -> dict:
    """{severity: number of findings} over the rows, every severity listed."""
    return {s: sum(f["severity"] == s for r in rows for f in r["findings"]) for s in SEVERITIES}


def print_checks(rows: list[dict], negligible=()) -> None:
    """The design-check table on the console (the CLI's): the camera-region pairs counted by their
    worst finding's severity, the findings per severity and the `negligible` pairs left out
    (`negligible_views`), then the pairs whose worst finding is above advice, the worst first (by
    severity, then by the interpolation's σ_measured / σ_noise), each with its findings. Pairs
    with advice only are in summary.json and report.html, not on the console."""
    counts = count_findings(rows)
    worst = {s: sum(r["severity"] == s for r in rows) for s in SEVERITIES}   # None: no finding
    clean = sum(not r["findings"] for r in rows)
    print(f"design checks on {len(rows)} camera-region pairs, by worst finding: "
          + ", ".join(f"{n} {s}" + (" only" if s == SEVERITIES[-1] else "") for s, n in worst.items())
          + f", {clean} clean; findings: " + ", ".join(f"{n} {s}" for s, n in counts.items())
          + " (all of them in summary.json and report.html)"
          + (f"; {len(negligible)} pair(s) left out as negligible (usable view under "
             f"{100 * NEGLIGIBLE_VIEW:g} % of the region: summary.json negligible_views)" if negligible else ""))
    flagged = [r for r in rows if r["findings"] and r["severity"] != SEVERITIES[-1]]
    if not flagged:
        return
    flagged.sort(key=lambda r: (SEVERITIES.index(r["severity"]),
                                -np.nan_to_num(_measured_over_noise(r))))
    wc = max([6] + [len(r["camera"]) for r in flagged]) + 2
    wr = max([6] + [len(r["region"]) for r in flagged]) + 2
    print(f"{'':<8}{'camera':<{wc}}{'region':<{wr}}{'stand-off m':>12}{'mm/px':>8}{'dot px':>8}"
          f"{'DoF m':>14}{'FOV fill':>9}{'gray mean/p99':>15}{'sat':>6}{'meas/noise':>11}  findings")
    for r in flagged:
        d = r["depth_of_field"]
        dof = "-" if d is None else f"{d['near_m']:.2f}-" + (f"{d['far_m']:.2f}" if d["far_m"]
                                                            else "inf")
        e = r["exposure"]
        ratio = _measured_over_noise(r)
        print(f"{r['severity'].upper():<8}{r['camera']:<{wc}}{r['region']:<{wr}}"
              f"{r['standoff_m']:>12.3f}{r['mm_per_px']:>8.3f}"
              f"{r['speckle_px']:>8.2f}{dof:>14}{r['fov_fill']:>9.1%}"
              f"{e['mean_gray_fraction']:>8.0%}/{e['p99_gray_fraction']:<6.0%}"
              f"{e['saturated_fraction']:>6.1%}{ratio:>11.2f}  "
              + "; ".join(f"[{f['severity']}] {f['message']}" for f in r["findings"]))
