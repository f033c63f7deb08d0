"""Each camera's f-number and exposure time, and the lights' power, for a placed layout: what
`vdo design` and `vdo optimize` set after placing the cameras when [exposure] free asks for it.

Light gathered. A camera at f-number N and exposure time t records k = (t / t_ref) (8 / N)^2
times the sensor's reference light ([sensor] exposure_ms at f/8, `vdo.model.optics.exposure_factor`).
The paint's gray level at a sample of irradiance E is g k ρ E / π + offset (DN, g the sensor's
DN per unit linear value, ρ the paint's albedo: `vdo.physics.lighting`), so for one camera and one
region every gray level above the offset scales with k and, through E = Σ_l w_l E_l + E_amb, with
each light's power factor w_l (E_l its irradiance at its configured radiance).

Aperture ("aperture" free). The depth Z along the optical axis of the samples the camera holds
sharp spans [Z_near, Z_far]: every sample it sees when a stop of the range allows, else those of
the regions it is assigned (`vdo.constraints.assignments`; the others are then flagged out of
focus by the depth-of-field check). The thin lens focused at s is sharp (circle of confusion
c = COC_PIXELS pixel pitches, `vdo.physics.checks.depth_of_field`) from s f^2 / (f^2 + N c (s - f))
to s f^2 / (f^2 - N c (s - f)); focused at the harmonic mean s = 2 Z_near Z_far / (Z_near + Z_far)
both ends need the same

    N_dof = f^2 (Z_far - Z_near) / (c (s - f) (Z_far + Z_near)),

rounded up to a third stop (2^(j/6): f/2.83, 3.17, 3.56, 4, ...) within [exposure]
f_number_range; above the range's largest stop the depth of field falls short, which is
reported. The camera takes, among that stop and the whole stops above it (ratio sqrt 2, up to
the largest), the one where the lab's correlation measures best: a wider aperture gathers more
light (less noise, with the exposure below), a smaller one blurs the image more by diffraction
(less interpolation bias on fine speckle, less contrast). Per stop, each (camera, region) pair's
σ_measured² (the trace of `vdo.physics.checks.measurement_floor`'s covariance, px², at the
region's median footprint and irradiance, through that stop's `vdo.model.optics.optics_blur`,
with the exposure k of that stop at the configured light) is summed over the camera's regions;
the smallest sum wins.

Exposure ("time", "lights" free). Per (camera c, region r) with seen samples, p_cr(w) is the 99th
percentile of the gray level above the offset at k = 1 over the seen samples (weighted by their
pixels) and the paint's values (`GRAY_LEVELS` quantiles of the pattern), as `vdo.physics.checks`'
exposure check takes it. The camera's exposure puts its brightest region at the target
T = [exposure] target_gray of the range, within the time limit:

    k_c(w) = min(T S / max_r p_cr(w),  (t_max,c / t_ref) (8 / N_c)^2),   S = max DN - offset,

(k_c fixed by the file's exposure time when "time" is not free). t_max,c is [exposure] max_ms, and
with the load running during the images ([load_path] step_s = Δt per step) also the motion
limit (`motion_limits`): a sample X_n moves between steps a < b (step 0 the rest state) by
Δx_cn = |x_c(X_n(b)) - x_c(X_n(a))| pixels in camera c, at image speed v_cn = Δx_cn / ((b - a) Δt),
and an exposure t smears it over v_cn t pixels, so

    t_max,c = min(max_ms, blur_px / max_{n seen by c, steps} v_cn).

With "lights" free the power factors w_l ∈ [LIGHT_MIN, max_radiance_l / radiance_l] minimise

    Σ_cr [max(0, ln(F_0 S) - ln(k_c p_cr))^2 + max(0, ln(k_c p_cr) - ln(F_1 S))^2] - ε Σ_cr ln(k_c p_cr),

(F_0, F_1) = `vdo.physics.checks.EXPOSURE`: the squared shortfall of every seen region below the
under-exposure floor and its excess over saturation (with the times fixed), then (ε =
`BRIGHTNESS_WEIGHT`) the light gathered, which lowers the noise; L-BFGS-B on ln w from w = 1,
kept when it lowers the sum. Then t_c = t_ref k_c (N_c / 8)^2.

Light places ("light_positions" free). A [[light]] with a `mount` may stand at any of the mount's
points (`vdo.config.experiment.Experiment.light_places`: a rail's [design] rail_positions, a
zone's zone_grid, off the keep-outs), still facing its target_m. The lights are placed one after
the other, before their power: at each place the light's irradiance and visible fraction are cast
again on the samples the pairs read (`vdo.physics.lighting.illuminate`, with the camera bodies)
and the place is judged at the current power (the times follow); the PLACE_SHORTLIST best places
are judged again with the power re-optimised, and a place's cost is that sum plus
γ = GLARE_WEIGHT times Σ over the (camera, satin region) pairs of the area fraction that is a hot
spot (saturated or washed out by a reflection, `vdo.physics.glare`). Each light takes its
mount's best point (its position_m is only where it stood before) where no other panel stands
(centres closer than half the sum of the two panels' diagonals) and where the panel hides at
most [optimize] max_obscuration of any (camera, region) pair's view (`panel_hides`: the sight
lines from the camera to the pair's samples against the panel's rectangle). The stops (above)
are chosen at the configured places. A place inside a mesh is not ruled out (keep-outs are).

The checks of the result are `vdo.physics.checks`' own, on the experiment with these settings
(`vdo evaluate`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize

from vdo.config.procedure import Analysis, ExposureSpec
from vdo.config.rig import CameraSpec, Evaluation, LightSpec, SpeckleSpec
from vdo.model.optics import DEFAULT_F_NUMBER, exposure_factor, optics_blur
from vdo.model.sensor import SensorModel
from vdo.physics.checks import COC_PIXELS, EXPOSURE, measurement_floor
from vdo.physics.glare import hot_spot_kinds, specular_radiance
from vdo.physics.lighting import Illumination, exposure_factors, illuminate, panel_frame

log = logging.getLogger(__name__)

GRAY_LEVELS = 16            # pattern quantiles the 99th percentile is taken over
MAX_SAMPLES = 500           # seen samples per (camera, region) at most (an even stride)
LIGHT_MIN = 0.05            # a light dims to 5 % of its configured radiance at the least
BRIGHTNESS_WEIGHT = 1e-3    # ε: the light gathered, against the shortfall below the floor
THIRD_STOP = 2.0 ** (1.0 / 6.0)   # f-numbers step by a third of a stop: N ratio 2^(1/6)
GLARE_WEIGHT = 1.0          # γ: a satin region wholly washed out by a reflection, against the exposure cost
PLACE_SHORTLIST = 2         # places per light whose power is searched again (the others judged at the current power)


@dataclass(frozen=True)
class CameraExposure:
    """One camera's settings: f-number N, focus distance (m), exposure time (s), the light it
    gathers against the sensor's reference (k), the depth it must hold sharp (m), its longest
    exposure allowed (s) and its fastest image speed over the load path (px/s, 0 at rest)."""

    camera: str
    f_number: float
    focus_m: float
    exposure_s: float
    gathered: float
    depth_m: tuple[float, float]
    max_s: float = math.nan
    image_speed: float = 0.0


@dataclass(frozen=True)
class ExposurePlan:
    """`design_exposure`'s result: the [[camera]] specs and [[light]] tables with the settings
    written in, per camera its `CameraExposure`, per light its radiance, and what could not be
    met (one line each)."""

    camera_specs: tuple[CameraSpec, ...]
    lights: tuple[LightSpec, ...]
    cameras: tuple[CameraExposure, ...]
    radiance: dict
    problems: tuple[str, ...]
    moved: tuple[str, ...] = ()     # the lights "light_positions" moved

    def to_json(self) -> dict:
        return {"cameras": [{"camera": c.camera, "f_number": c.f_number, "focus_m": c.focus_m,
                             "exposure_ms": c.exposure_s * 1e3, "gathered": c.gathered,
                             "depth_m": list(c.depth_m), "max_exposure_ms": c.max_s * 1e3,
                             "image_speed_px_s": c.image_speed} for c in self.cameras],
                "radiance": self.radiance,
                "light_positions_m": {lt.name: [float(x) for x in lt.position]
                                      for lt in self.lights if lt.name in self.moved},
                "problems": list(self.problems)}


def motion_limits(cameras, visible, tracks, step_s: float, blur_px: float,
                  max_time: float) -> tuple[np.ndarray, np.ndarray]:
    """(t_max (C,) s, v (C,) px/s): each camera's longest exposure and fastest image speed
    (module docstring). `tracks`: [(step, points (N, 3) m)] in step order, the rest state (step
    0) first; `visible` (C, N) the samples each camera sees at rest; `step_s` the seconds per step
    (None: the load does not run during the images, t_max = max_time, v = 0)."""
    speed = np.zeros(len(cameras))
    if step_s is not None:
        for i, cam in enumerate(cameras):
            seen = np.flatnonzero(np.asarray(visible[i]))
            if seen.size == 0:
                continue
            px = [cam.project(points[seen]) for _, points in tracks]
            for (a, _), (b, _), xa, xb in zip(tracks, tracks[1:], px, px[1:]):
                speed[i] = max(speed[i], float(np.linalg.norm(xb - xa, axis=1).max()) / ((b - a) * step_s))
    with np.errstate(divide="ignore"):
        return np.minimum(max_time, np.where(speed > 0, blur_px / speed, np.inf)), speed


def stop_at_least(n: float, low: float, high: float) -> float:
    """The smallest third stop 2^(j/6) (integer j: f/2.83, 3.17, 3.56, 4, ..., 16) at or above
    max(n, low), at most `high` (high when n is above it), to 0.01."""
    j = math.ceil(6.0 * math.log2(max(n, low)) - 1e-9)
    return round(min(THIRD_STOP ** j, high), 2)


def aperture_for(focal: float, pixel: float, near: float, far: float) -> tuple[float, float]:
    """(N_dof, s): the f-number that holds depths [near, far] (m) sharp at the circle of confusion
    COC_PIXELS x `pixel` (m), focused at the harmonic mean s (module docstring)."""
    s = 2.0 * near * far / (near + far)
    c = COC_PIXELS * pixel
    return focal ** 2 * (far - near) / (c * (s - focal) * (far + near)), s


def _p99_signal(E: np.ndarray, w: np.ndarray, rho: np.ndarray) -> float:
    """99th percentile over samples (irradiance E, weights w) and albedos rho (equal weight) of
    rho E / π: the linear value above the offset at k = 1, before the sensor's DN per unit."""
    v = np.outer(E, rho).ravel() / np.pi
    ww = np.repeat(w / (w.sum() * len(rho)), len(rho))
    order = np.argsort(v)
    return float(v[order][np.searchsorted(np.cumsum(ww[order]), 0.99)])


def _pair_signals(pairs, w, rho, sensor: SensorModel, n_cam: int) -> tuple[np.ndarray, np.ndarray]:
    """(p (pairs,), top (C,)): each (camera, region) pair's p99 signal (DN above the offset, at
    k = 1) under the light power factors `w` (the lights' irradiance w @ D plus the sky's at each
    sample), and each camera's largest."""
    p = np.array([_p99_signal(w @ D + sky, px, rho) for _, _, D, px, _, sky in pairs]) \
        * sensor.dn_per_unit
    top = np.zeros(n_cam)
    for (i, *_), v in zip(pairs, p):
        top[i] = max(top[i], v)
    return p, top


def _best_stops(apertures, pairs, top, cameras, camera_specs, spec_x, speckle, sensor, analysis,
                pattern, t_max) -> list:
    """`apertures` with each camera's stop moved to the stop, its depth-of-field stop or a whole
    stop above it up to the range's largest, where its pairs' summed σ_measured² is least (module
    docstring): one `measurement_floor` over every (pair, stop). `top` (C,): each camera's
    brightest region's p99 signal (DN above the offset) at k = 1 and the configured light; `t_max`
    (C,) each camera's longest exposure (s)."""
    free, t_ref = set(spec_x.free), sensor.exposure_ms * 1e-3
    span = sensor.max_dn - sensor.offset
    jobs = []                              # (camera, stop, pair's middle, k)
    for i, (n, focus, _) in enumerate(apertures):
        if n is None or top[i] <= 0:
            continue
        first = round(6.0 * math.log2(n))     # n's third stop; then whole stops above it
        stops = [n] + [round(THIRD_STOP ** j, 2) for j in range(first + 3, first + 7 * 6, 3)
                       if round(THIRD_STOP ** j, 2) <= spec_x.f_numbers[1]]
        for stop in stops:
            k = exposure_factor(stop, camera_specs[i].exposure_time, t_ref)
            if "time" in free:
                k = min(spec_x.target_gray * span / top[i],
                        (t_max[i] / t_ref) * (DEFAULT_F_NUMBER / stop) ** 2)
            jobs += [(i, stop, mid, k) for j, _, _, _, mid, _ in pairs if j == i]
    if not jobs:
        return apertures
    cams = list(cameras)
    floors = measurement_floor(
        [mid[0] for _, _, mid, _ in jobs], [k * mid[1] for _, _, mid, k in jobs],
        [mid[3] for _, _, mid, _ in jobs],
        [optics_blur(cams[i].pixel_size, cams[i].focal_length, stop, apertures[i][1], mid[2])
         for i, stop, mid, _ in jobs], speckle, sensor, pattern, analysis.interpolant,
        analysis.reference == "noisy")
    model, _ = floors[0]["model"]
    cov = model.covariance(np.array([f["noise_rel"] for f in floors]),
                           np.array([f["patch_pixels"] for f in floors]))
    score: dict = {}
    for (i, stop, _, _), c in zip(jobs, np.trace(cov, axis1=1, axis2=2)):
        score[(i, stop)] = score.get((i, stop), 0.0) + float(c)
    out = list(apertures)
    for i, (n, focus, dof) in enumerate(apertures):
        mine = {stop: v for (j, stop), v in score.items() if j == i}
        if mine:
            out[i] = (min(mine, key=mine.get), focus, dof)
    return out


def panel_hides(light: LightSpec, camera_position, points, weights) -> float:
    """The weighted fraction of `points` (M, 3) whose sight line from `camera_position` crosses
    the panel of `light` (a rectangle: centre P, normal n, edges e_1, e_2 of `panel_frame`): the
    segment C + t (X - C) meets the panel's plane at t = n.(P - C) / n.(X - C), and hides X when
    0 < t < 1 and the crossing lies within half the width along e_1 and half the height along e_2."""
    n, e1, e2 = panel_frame(light)
    P, C = np.asarray(light.position, float), np.asarray(camera_position, float)
    d = np.asarray(points, float) - C
    den = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(np.abs(den) > 1e-12, ((P - C) @ n) / den, -1.0)
    q = C + t[:, None] * d - P
    w, h = light.size
    hit = (t > 0) & (t < 1) & (np.abs(q @ e1) <= w / 2) & (np.abs(q @ e2) <= h / 2)
    return float(np.asarray(weights)[hit].sum() / np.sum(weights))


def _place_lights(lights, places, pairs, seens, illum, scene, samples, cameras, speckle, sensor,
                  satin, power, problems, max_obscuration):
    """Each light of `places` moved, one after the other, to the place (of its mount's points)
    with the least exposure cost (`power`, the power and times re-optimised)
    plus γ times the satin pairs' hot-spot fraction, saturated or washed out as
    `vdo.physics.glare.hot_spots` judges it (module docstring), among the places where the panel
    hides at most `max_obscuration` of any pair's view (`panel_hides`). Returns (lights, pairs
    with the moved lights' irradiance, names of the lights moved)."""
    used = np.unique(np.concatenate(seens))
    sub = samples.take(used)
    cols = [np.searchsorted(used, seen) for seen in seens]
    sat = np.zeros(len(used), bool) if satin is None else np.asarray(satin)[used]

    def rebuild(direct):
        return [(i, k, direct[:, c], px, mid, sky) for (i, k, _, px, mid, sky), c in zip(pairs, cols)]

    def total(lts, direct, lit, at=None, start=None) -> tuple[float, np.ndarray]:
        """(cost, w): the place's cost and the power factors it was judged at."""
        w, value, k = power(rebuild(direct), at, start)
        if not sat.any():
            return value, w
        E = w @ direct[:, sat] + illum.sky_irradiance[used][sat]
        Ls = specular_radiance([replace(lt, radiance=lt.radiance * x) for lt, x in zip(lts, w)],
                               lit[:, sat], sub.points[sat], sub.normals[sat], [c.position for c in cameras])
        hot_spot = np.zeros((len(cameras), len(used)), bool)
        hot_spot[:, sat] = np.logical_or(*hot_spot_kinds(Ls, E, k, speckle, sensor))
        hot = sum(float(px[sat[c]][hot_spot[i][c][sat[c]]].sum() / px.sum())
                  for (i, _, _, px, _, _), c in zip(pairs, cols) if sat[c].any())
        return value + GLARE_WEIGHT * hot, w

    direct, lit = illum.direct[:, used].copy(), illum.lit[:, used].copy()
    _, w_now = total(lights, direct, lit)
    moved = []
    for l, P in places.items():
        tried, reached, hiding = [], False, False
        for p in np.asarray(P, float).reshape(-1, 3):       # each place at the current power
            if any(np.linalg.norm(p - np.asarray(o.position)) < (np.hypot(*lights[l].size) + np.hypot(*o.size)) / 2
                   for j, o in enumerate(lights) if j != l):
                continue                                     # another panel stands there
            cand = replace(lights[l], position=p)
            if any(panel_hides(cand, cameras[i].position, samples.points[seen], px) > max_obscuration
                   for (i, _, _, px, _, _), seen in zip(pairs, seens)):
                hiding = True
                continue                                     # it stands in a camera's view
            one = illuminate(scene, [cand], sub)
            reached |= bool(one.direct.any())
            d2, l2 = direct.copy(), lit.copy()
            d2[l], l2[l] = one.direct[0], one.lit[0]
            lts = lights[:l] + (cand,) + lights[l + 1:]
            tried.append((total(lts, d2, l2, at=w_now)[0], lts, d2, l2))
        if not tried:
            problems.append(f"light {lights[l].name}: every place on mount {lights[l].mount!r} "
                            + ("stands in a camera's view or on another panel" if hiding else
                               "is taken by another panel") + ": it stays where it was (a larger "
                            "mount, or one out of the cameras' views)")
            continue
        if not reached:
            problems.append(f"light {lights[l].name}: no place on mount {lights[l].mount!r} lights a "
                            "region a camera sees (aim its target_m at the regions, or another mount)")
        tried.sort(key=lambda t: t[0])
        best = None                                          # the shortlist with its power searched
        for _, lts, d2, l2 in tried[:PLACE_SHORTLIST]:
            value, w = total(lts, d2, l2, start=w_now)
            if best is None or value < best[0]:
                best = (value, w, lts, d2, l2)
        _, w_now, lts, direct, lit = best
        if not np.allclose(lts[l].position, lights[l].position):
            moved.append(lights[l].name)
        lights = lts
    return lights, rebuild(direct), moved


def design_exposure(spec_x: ExposureSpec, camera_specs: tuple[CameraSpec, ...],
                    lights: tuple[LightSpec, ...], speckle: SpeckleSpec, sensor: SensorModel,
                    evaluation: Evaluation, analysis: Analysis,
                    cameras, samples, visible, illum: Illumination, pattern,
                    sharp=None, motion=None, scene=None, places=None, satin=None,
                    max_obscuration: float = 0.0) -> ExposurePlan:
    """The settings of the module docstring for what [exposure] free lists (`spec_x`), the rest as
    the tables give it: `cameras` (`vdo.model.camera.Camera`s) described by `camera_specs`, seeing
    `visible` (C, N) of `samples`, lit as `illum` (`vdo.physics.lighting.illuminate` at the
    configured radiances of `lights`), the paint [speckle] with its [0, 1] `pattern` tile, the
    [sensor], [evaluation] (the patch) and [analysis] (the interpolant, the reference).
    `sharp` (C, N) bool: the samples each camera's depth of field must hold (default `visible`;
    a camera with none holds all it sees). `motion`: (t_max, v) of `motion_limits` (default
    [exposure] max_ms for every camera, at rest). With "light_positions" free: `places` {light
    index: (P, 3) panel centres it may take} (`Experiment.light_places`), `scene` the Mitsuba
    scene its shadow rays are cast in (`vdo.physics.lighting.illuminate`) and `satin` (N,) the
    samples of a satin finish (`vdo.physics.glare.satin_samples`; None: none); a place whose
    panel hides more than `max_obscuration` of a (camera, region) pair's view is not taken
    ([optimize] max_obscuration)."""
    free = set(spec_x.free)
    t_max, speed = motion if motion is not None else \
        (np.full(len(camera_specs), spec_x.max_time), np.zeros(len(camera_specs)))
    t_ref = sensor.exposure_ms * 1e-3
    span = sensor.max_dn - sensor.offset
    low_n, high_n = spec_x.f_numbers
    rho = speckle.black_albedo + (speckle.white_albedo - speckle.black_albedo) * \
        np.quantile(np.asarray(pattern, float), (np.arange(GRAY_LEVELS) + 0.5) / GRAY_LEVELS)
    T = np.stack([samples.tangent_u, samples.tangent_v], axis=-1)
    problems, apertures, pairs, seens = [], [], [], []
    for i, (cam, spec) in enumerate(zip(cameras, camera_specs)):
        seen_any = np.asarray(visible[i])
        if not seen_any.any():
            apertures.append((spec.f_number, spec.focus_distance, (math.nan, math.nan)))
            continue
        depth = (samples.points[seen_any] - cam.position) @ cam.optical_axis
        near, far = float(depth.min()), float(depth.max())
        need, focus = aperture_for(cam.focal_length, cam.pixel_size, near, far)
        if need > high_n and sharp is not None and np.any(sharp[i]):   # hold its own regions
            depth = (samples.points[np.asarray(sharp[i])] - cam.position) @ cam.optical_axis
            near, far = float(depth.min()), float(depth.max())
            need, focus = aperture_for(cam.focal_length, cam.pixel_size, near, far)
        if "aperture" in free:
            n = stop_at_least(need, low_n, high_n)
            if need > high_n:
                problems.append(f"camera {cam.name}: depth {near:.3f}-{far:.3f} m needs f/{need:.1f} "
                                f"to be sharp; the lens stops at f/{high_n:g} (widen [exposure] "
                                "f_number_range, or a shorter lens or farther stand-off)")
            apertures.append((n, focus, (near, far)))
        else:
            apertures.append((spec.f_number, spec.focus_distance, (near, far)))
        for k in range(len(samples.region_names)):
            seen = np.flatnonzero(seen_any & (samples.region == k))
            if seen.size == 0:
                continue
            seen = seen[:: max(1, seen.size // MAX_SAMPLES)]
            A = cam.sensitivity(samples.points[seen]) @ T[seen]
            density = np.abs(np.linalg.det(A))
            m = int(np.argsort(density)[len(density) // 2])       # the median footprint
            middle = (A[m], float(illum.irradiance[seen[m]]),
                      float((samples.points[seen[m]] - cam.position) @ cam.optical_axis),
                      evaluation.patch_size ** 2 * float(density[m]))
            pairs.append((i, k, illum.direct[:, seen], samples.area[seen] * density, middle,
                          illum.sky_irradiance[seen]))
            seens.append(seen)
    n_cam = len(camera_specs)
    if "aperture" in free and pairs:
        _, top = _pair_signals(pairs, np.ones(len(lights)), rho, sensor, n_cam)
        apertures = _best_stops(apertures, pairs, top, cameras, camera_specs, spec_x, speckle,
                                sensor, analysis, pattern, t_max)
    base = exposure_factors([replace(s, f_number=a[0]) for s, a in zip(camera_specs, apertures)],
                            sensor)                       # the file's times at the chosen stops
    n_eff = np.array([DEFAULT_F_NUMBER if a[0] is None else a[0] for a in apertures])
    k_max = (t_max / t_ref) * (DEFAULT_F_NUMBER / n_eff) ** 2 if "time" in free else base
    configured = np.array([lt.radiance for lt in lights])
    w_max = np.array([(lt.max_radiance or lt.radiance) / lt.radiance for lt in lights])
    w_min = np.minimum(LIGHT_MIN, w_max)

    def signals(w, prs=pairs):
        """(p (pairs,), k (C,)): each pair's p99 signal in DN at k = 1 and each camera's k."""
        p, top = _pair_signals(prs, w, rho, sensor, n_cam)
        k = np.minimum(spec_x.target_gray * span / np.where(top > 0, top, np.inf), k_max) \
            if "time" in free else base
        k = np.where(top > 0, k, base)
        return p, k

    def cost(log_w, prs=pairs):
        p, k = signals(np.exp(log_w), prs)
        got = np.log(np.maximum(np.array([k[i] for i, *_ in prs]) * p, 1e-300))
        short = np.maximum(0.0, math.log(EXPOSURE[0] * span) - got)
        over = np.maximum(0.0, got - math.log(EXPOSURE[1] * span))
        return float(np.sum(short ** 2) + np.sum(over ** 2) - BRIGHTNESS_WEIGHT * np.sum(got))

    def power(prs=pairs, at=None, start=None):
        """(w, cost, k): the light power factors ("lights" free; else 1), the cost there and
        each camera's light factor k; `at` (L,) fixed power factors instead (no search), `start`
        (L,) where the search starts besides w = 1."""
        w = np.ones(len(lights)) if at is None else np.asarray(at, float)
        if at is None and "lights" in free and prs and len(w):
            x0 = np.zeros(len(w)) if start is None else np.log(start)
            res = minimize(cost, x0, args=(prs,), method="L-BFGS-B",
                           bounds=list(zip(np.log(w_min), np.log(w_max))), options={"maxiter": 60})
            w = min((np.zeros(len(w)), x0, res.x), key=lambda x: cost(x, prs))
            w = np.exp(w)
        return w, cost(np.log(w), prs), signals(w, prs)[1]

    lights, moved = tuple(lights), []
    if "light_positions" in free and places and pairs:
        lights, pairs, moved = _place_lights(lights, places, pairs, seens, illum, scene, samples,
                                             cameras, speckle, sensor, satin, power, problems,
                                             max_obscuration)
    w, _, _ = power(pairs)
    p, k = signals(w)
    brightest = np.zeros(n_cam)
    for (i, *_), v in zip(pairs, p):
        brightest[i] = max(brightest[i], k[i] * v / span)
    for (i, r, *_), v in zip(pairs, p):
        level = k[i] * v / span
        if level >= EXPOSURE[0]:
            continue
        light = ("more light on it (a light aimed at it, or \"lights\" free with a higher "
                 "max_radiance)")
        if "time" not in free:
            fix = f"{light}, or \"time\" in [exposure] free"
        elif k[i] < k_max[i] * (1.0 - 1e-9):      # the brightest region caps the time
            fix = light
        elif speed[i] * spec_x.max_time <= spec_x.blur_px:
            fix = f"{light} or a longer [exposure] max_ms"
        else:
            fix = (f"{light}, a larger [exposure] blur_px (the load moves its image "
                   f"{speed[i]:.3g} px/s: {t_max[i] * 1e3:.3g} ms at {spec_x.blur_px:g} px) or a "
                   "slower load")
        problems.append(f"camera {camera_specs[i].name}: {samples.region_names[r]} stays at "
                        f"{level:.0%} of the range (99th percentile) with the camera's brightest "
                        f"region at {brightest[i]:.0%}: {fix}")
    specs, chosen = [], []
    for spec, (n, focus, dof), k_c, t_c, v_c in zip(camera_specs, apertures, k, t_max, speed):
        t = t_ref * k_c * ((DEFAULT_F_NUMBER if n is None else n) / DEFAULT_F_NUMBER) ** 2 \
            if "time" in free else (spec.exposure_time or t_ref)
        specs.append(replace(spec, f_number=n, focus_distance=focus,
                             exposure_time=t if "time" in free else spec.exposure_time))
        chosen.append(CameraExposure(spec.name, DEFAULT_F_NUMBER if n is None else float(n),
                                     math.nan if focus is None else float(focus), float(t),
                                     float(k_c), dof, float(t_c), float(v_c)))
    lit = tuple(replace(lt, radiance=float(r)) for lt, r in zip(lights, configured * w))
    for msg in problems:
        log.warning(msg)
    return ExposurePlan(tuple(specs), lit, tuple(chosen), {lt.name: lt.radiance for lt in lit},
                        tuple(problems), tuple(moved))
