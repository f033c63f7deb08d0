"""Images with Mitsuba, the public face of the renders: the images of every camera of an
experiment (`render_images`, the computation of `vdo render`; `vdo.commands.render` writes them
into a run folder), their photometry against the prediction, and the pieces a script needs from
`vdo.rendering`: the render scene and one camera's image (`vdo.rendering.scene`, whose docstring
describes the scene, the exposure and the render scale) and the DIC render mode
(`vdo.rendering.dic`, its light shared by a frame's cameras in `vdo.rendering.lightmap`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from vdo.model.camera import Camera
from vdo.model.speckle import normalise
from vdo.rendering.dic import (CELL_BYTES_PER_PIXEL, IMAGE_BYTES_PER_PIXEL, MIN_TILE_PIXELS, RENDER_MODES,
                               TILE_PIXELS, SpeckleTable, build_dic_scene, plan_render, render_camera_dic)
from vdo.rendering.lightmap import SurfaceLightMap, map_holds, surface_light_map
from vdo.rendering.scene import (build_render_scene, camera_sensor, cell_blur, expose, lens_sigma_px,
                                 lit_scene, noise_free_dn, render_camera, render_linear,
                                 render_seed, scaled_camera, sensor_dict)
from vdo.scene import cameras_of

# the face: what scripts and the other packages use of the renders
__all__ = ["RenderResult", "render_images", "render_settings", "rendered_std", "pixel_response", "region_photometry",
           "photometry_warnings", "PHOTOMETRY_TOLERANCE",
           "CELL_BYTES_PER_PIXEL", "IMAGE_BYTES_PER_PIXEL", "MIN_TILE_PIXELS", "RENDER_MODES", "TILE_PIXELS", "SpeckleTable",
           "build_dic_scene", "plan_render", "render_camera_dic", "SurfaceLightMap", "map_holds", "surface_light_map",
           "build_render_scene",
           "camera_sensor", "cell_blur", "expose", "lens_sigma_px", "lit_scene", "noise_free_dn",
           "render_camera", "render_linear", "render_seed", "scaled_camera", "sensor_dict"]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Photometry of the renders
# --------------------------------------------------------------------------------------------
def pixel_response(freq, sigma_px: float) -> np.ndarray:
    """Along one image axis, the transfer function of a rendered pixel at `freq` (cycles/px, any
    shape): the lens's Gaussian (std `sigma_px` px) acting on PRESAMPLE = n cells a pixel before
    the pixel averages them (`vdo.rendering.scene.cell_blur`). Pixel p = Σ_k c_k cell_k, cell k
    the box of 1/n px centred at x_k = (k - r + 1/2) / n - 1/2 from the pixel's centre and c the
    weights of `cell_blur_kernel`, so

        H(f) = sinc(f / n) Σ_k c_k cos(2π f x_k)          [1]

    (c is symmetric); sigma_px = 0: the box pixel, H = sinc(f)."""
    from vdo.rendering.scene import PRESAMPLE, cell_blur_kernel

    f = np.asarray(freq, dtype=np.float64)
    if sigma_px <= 0:
        return np.sinc(f)
    n = PRESAMPLE
    c = cell_blur_kernel(sigma_px, n)
    x = (np.arange(len(c)) - (len(c) - n) // 2 + 0.5) / n - 0.5
    return np.sinc(f / n) * np.tensordot(c, np.cos(2.0 * np.pi * np.multiply.outer(x, f)), axes=1)


RESPONSE_POINTS = 1 << 14   # frequencies of the pixel response's table in `rendered_std`


def sample_weight(sigma_px: float) -> float:
    """n² (Σ_k c_k²)² of the sampled mode's pixel with the lens blur `sigma_px` (px): the factor on
    the variance of independent per-sample noise (of variance v, the pixel's is weight v / spp)
    when each of the n² = PRESAMPLE² cells averages spp / n² samples and the separable blur's 1-D
    kernel c (`vdo.rendering.scene.cell_blur_kernel`) mixes cells; 1 without a blur (the mean of
    spp samples)."""
    from vdo.rendering.scene import PRESAMPLE, cell_blur_kernel

    return 1.0 if sigma_px <= 0 else PRESAMPLE ** 2 * float(np.sum(cell_blur_kernel(sigma_px, PRESAMPLE) ** 2)) ** 2


def rendered_std(pattern_normalised, texel: float, pixel_sides, spp: int | None,
                 sigma_px: float = 0.0) -> np.ndarray:
    """(K,) std of the rendered pixel values of a unit-variance pattern f̂ for K footprints
    `pixel_sides` (K, 2, 2) [m] (columns a_1, a_2: one pixel step along image x, y on the surface,
    A^-1). The lens's Gaussian (`sigma_px`, `vdo.rendering.scene.lens_sigma_px`) blurs PRESAMPLE^2
    cells a pixel before the pixel averages them (`pixel_response` H along each image axis); a
    surface wave of frequency k (cycles/m) has image frequencies (k.a_1, k.a_2) cycles/px, so the
    pixel's deterministic part has

        s² = Σ_k |F(k)|² H²(k.a_1) H²(k.a_2) sinc⁴(k_u h) sinc⁴(k_v h)

    (`vdo.model.speckle.pixel_averaged_std` when sigma_px = 0). The sampled mode's pixel is not
    the exact integral: each of its n^2 cells is the mean of spp / n^2 samples, one per stratum
    A^-1 / sqrt(spp) (`spp` None: the DIC mode's exact average), which adds the Monte Carlo term

        (s_0² - s(A^-1 / sqrt spp)²) n² (Σ_k c_k²)² / spp

    (law of total variance over independent cells weighted c_i c_j; s_0 the texture alone; with
    no blur n² (Σ c²)² = 1, the stratified mean of spp samples): small when a stratum is small
    against a speckle, large for a reduced-scale render whose pixels span speckles."""
    from vdo.model.speckle import blocked_spectrum, pixel_averaged_std

    sides = np.asarray(pixel_sides, dtype=float).reshape(-1, 2, 2)
    w, ku, kv = blocked_spectrum(pattern_normalised, texel, texel_filter=True)
    # H² tabulated at RESPONSE_POINTS frequencies up to a bound on |k.a| over these footprints and
    # read by linear interpolation (H is even and smooth: its second derivative is ~(2π sigma)²
    # per px², the table's error below 1e-5): a cosine per tap, frequency and footprint cost
    # 7 ms a footprint on the built-in's pattern
    top = max(float(np.abs(ku).max() * np.abs(sides[:, 0]).max() + np.abs(kv).max() * np.abs(sides[:, 1]).max()),
              1e-12) if len(sides) else 1.0          # |k.a| <= |k_u| |a_u| + |k_v| |a_v|
    step = top / (RESPONSE_POINTS - 1)
    table = pixel_response(np.arange(RESPONSE_POINTS + 1) * step, sigma_px) ** 2

    def response2(f):
        x = np.abs(f) / step
        i = np.minimum(x.astype(np.int64), RESPONSE_POINTS - 1)
        return table[i] + (x - i) * (table[i + 1] - table[i])

    box = np.array([math.sqrt(float(np.sum(w * response2(ku * a[0, 0] + kv * a[1, 0])
                                           * response2(ku * a[0, 1] + kv * a[1, 1]))))
                    for a in sides])
    if spp is None:
        return box
    weight = sample_weight(sigma_px)
    stratum = pixel_averaged_std(pattern_normalised, texel, sides / math.sqrt(spp))
    texture = pixel_averaged_std(pattern_normalised, texel, np.zeros((1, 2, 2)))[0]
    return np.sqrt(box ** 2 + weight * (texture ** 2 - stratum ** 2) / spp)


PHOTOMETRY_WINDOW = 3     # px: each visible sample contributes the window x window pixels around it
PHOTOMETRY_FOOTPRINTS = 16  # samples per row (evenly spread over its visible ones) whose footprints
                            # give the row's predicted pixel and render factors (their rms)
PHOTOMETRY_REACH_PX = 1.5   # px beyond the window's half-diagonal that a row's sample keeps from its
                            # region's edge (the rounding of its projection and the pixel's own
                            # footprint), on top of twice the lens blur; closer ones are left out
PHOTOMETRY_TOLERANCE = 0.15  # relative: `vdo render` warns of a row whose rendered contrast is further
                             # than this from c_render_predicted (the built-in's and the pressure
                             # vessel's rows lie within 5 %; a row of a few samples scatters by
                             # ~1 / sqrt(2 x its independent speckles), 10 % at 50)


def region_photometry(cameras, vis, samples, pho, linear: dict, sensor, pattern_normalised,
                      texel: float, spp: int | None, sigma_px=None, light_cv2=None) -> list[dict]:
    """One row per (camera, region) of photometry.csv (docs/photometry.md). Over the
    `PHOTOMETRY_WINDOW`^2 pixels around each visible sample's projection in the noise-free
    render (`noise_free_dn` of each camera's `linear` image): b_render = mean DN; c_render = std
    of (DN - offset) / (b_predicted(X) - offset) x mean(b_predicted - offset), the contrast with
    the predicted light level divided out (so that the irradiance's variation over the region
    does not count as contrast). Since c_predicted / (b_predicted - offset) is the same at every
    sample, that std is predicted by the rms of the samples' factors s_i:

        c_render_predicted = mean(c_predicted) sqrt(mean_i s_i²)        [DN]

    with s_i = `rendered_std` at sample i's footprint A_i^-1 (A = ∂x/∂ξ, px/m) and its camera's
    lens blur `sigma_px` (C,) (None: none): render_factor. On a curved region the footprint
    varies (foreshortened towards the silhouette), so no one sample stands for the region. The
    factors are those of up to PHOTOMETRY_FOOTPRINTS samples spread evenly over the visible ones.
    pixel_factor is the rms of the box pixel's `pixel_averaged_std` at the same footprints (no
    lens, no Monte Carlo): c_pixel_predicted = c_predicted x pixel_factor.

    The sampled mode (`spp` given) also samples the light: a pixel sample's value ρ Ê / π has the
    variance Var(ρ) E² + E[ρ²] V (texture and light drawn independently; V / E² = `light_cv2`
    (N,), `vdo.physics.lighting.Illumination.sampling_cv2`), so the pixel carries, beside the
    texture's term in render_factor,

        c_light_sampling = mean(b - offset) sqrt((1 + q²) w mean_i(V_i / E_i²) / spp)     [DN]

    with q = c_predicted / (b - offset) = (ρ_w - ρ_b) std(f) / <ρ> (E[ρ²] / <ρ>² = 1 + q²) and
    w = `sample_weight` of the camera's blur; c_render_predicted is the quadrature sum of both.
    On trial renders at 1/10 scale and 4 spp (a pipe under three panels and a sky, S ~ 0.7) the
    Monte Carlo part measured from two seeds was 408-460 DN against 424-460 predicted."""
    from vdo.meshes.samples import edge_distance
    from vdo.model.speckle import pixel_averaged_std

    rows, footprints = [], []          # (row, its footprints (m, 2, 2), its camera's blur)
    half = PHOTOMETRY_WINDOW // 2
    dx, dy = np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1))
    tangents = np.stack([samples.tangent_u, samples.tangent_v], axis=-1)      # (N, 3, 2)
    offset_dn = sensor.offset
    for i, cam in enumerate(cameras):
        clean = noise_free_dn(linear[cam.name], sensor)
        uv = cam.project(samples.points)
        sigma = 0.0 if sigma_px is None else float(sigma_px[i])
        weight = sample_weight(sigma)
        edge = edge_distance(samples, vis.visible[i])   # to the region's edge or the view's
        for k, region in enumerate(samples.region_names):
            mask = vis.visible[i] & (samples.region == k)
            row = {"camera": cam.name, "region": region, "n_samples": int(mask.sum())}
            if mask.any():
                # only samples whose window (and the pixels' and the blur's reach) stays on the
                # region: beyond its edge lie other paint or other surfaces (module constants)
                visible = np.flatnonzero(mask)
                A_visible = cam.sensitivity(samples.points[visible]) @ tangents[visible]   # (n, 2, 2) px/m
                metres_per_px = 1.0 / np.maximum(np.linalg.svd(A_visible, compute_uv=False)[:, -1], 1e-300)
                inner = edge[visible] >= (PHOTOMETRY_REACH_PX + half * math.sqrt(2) + 2 * sigma) * metres_per_px
                row["n_interior"] = int(inner.sum())
                if inner.any():
                    mask = np.zeros_like(mask)
                    mask[visible[inner]] = True
                col = np.clip(np.rint(uv[mask, 0]).astype(int)[:, None] + dx.ravel(), 0, cam.width - 1)
                r = np.clip(np.rint(uv[mask, 1]).astype(int)[:, None] + dy.ravel(), 0, cam.height - 1)
                values = clean[r, col]                         # (n, window^2)
                level = pho.brightness[i, mask] - offset_dn
                ratio = (values - offset_dn) / level[:, None]
                seen = np.flatnonzero(mask)
                some = seen[np.unique(np.linspace(0, len(seen) - 1, PHOTOMETRY_FOOTPRINTS).round().astype(int))]
                A = A_visible[np.searchsorted(visible, some)]                       # (m, 2, 2) px/m
                light = 0.0
                if spp is not None and light_cv2 is not None:
                    q = float(np.mean(pho.contrast[i, mask] / np.maximum(level, 1e-300)))
                    light = float(level.mean()) * math.sqrt((1 + q * q) * weight
                                                            * float(np.mean(light_cv2[mask])) / spp)
                row["c_light_sampling_dn"] = light
                footprints.append((row, np.linalg.inv(A), sigma))
                row |= {"b_render_dn": values.mean(), "b_predicted_dn": pho.brightness[i, mask].mean(),
                        "c_render_dn": ratio.std() * level.mean(),
                        "c_predicted_dn": pho.contrast[i, mask].mean(),
                        "noise_predicted_dn": pho.noise[i, mask].mean()}
            rows.append(row)
    if footprints:   # every row's footprints at once: the pattern's spectrum once per lens blur
        sides = np.concatenate([f for _, f, _ in footprints])
        pixel = pixel_averaged_std(pattern_normalised, texel, sides)
        render = np.empty(len(sides))
        blur = np.concatenate([np.full(len(f), sigma) for _, f, sigma in footprints])
        for sigma in np.unique(blur):
            render[blur == sigma] = rendered_std(pattern_normalised, texel, sides[blur == sigma], spp, float(sigma))
        ends = np.cumsum([len(f) for _, f, _ in footprints])
        for (row, _, _), p, r in zip(footprints, np.split(pixel, ends[:-1]), np.split(render, ends[:-1])):
            p, r = math.sqrt(float(np.mean(p ** 2))), math.sqrt(float(np.mean(r ** 2)))
            row |= {"c_render_predicted_dn": math.hypot(row["c_predicted_dn"] * r, row["c_light_sampling_dn"]),
                    "c_pixel_predicted_dn": row["c_predicted_dn"] * p, "pixel_factor": p, "render_factor": r}
    return rows


def photometry_warnings(rows) -> list[str]:
    """One line per photometry row whose rendered contrast c_render is further than
    PHOTOMETRY_TOLERANCE (relative) from c_render_predicted: camera, region and both numbers. A
    row without a sample whose window stays on the region (`n_interior` 0: a region narrower than
    a few pixels at the rendered scale) mixes other surfaces into its numbers and is not warned of."""
    return [f"photometry: {r['camera']}/{r['region']}: rendered contrast {r['c_render_dn']:.0f} DN is "
            f"{100 * (r['c_render_dn'] / r['c_render_predicted_dn'] - 1):+.0f} % off the predicted "
            f"{r['c_render_predicted_dn']:.0f} DN (tolerance {100 * PHOTOMETRY_TOLERANCE:.0f} %; docs/photometry.md)"
            for r in rows if r["n_samples"] and r.get("n_interior", r["n_samples"]) and
            abs(r["c_render_dn"] / r["c_render_predicted_dn"] - 1) > PHOTOMETRY_TOLERANCE]




# --------------------------------------------------------------------------------------------
# Every camera of an experiment (the computation behind `vdo render`)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class RenderResult:
    """The images of every camera of an experiment and what was predicted for them
    (`render_images`). Writing them is `vdo.commands.render`'s business.

    state        the layout state of the cameras *at the rendered scale* (`scaled_camera`; same
                 poses and lenses, hence the same bodies, visibility and lighting)
    images       camera name -> noisy DN image (H, W), uint8 or uint16 (`SensorModel.expose`)
    linear       camera name -> linear float32 image (H, W) before the sensor: the radiance times
                 the camera's exposure factor (`vdo.physics.lighting.exposure_factors`)
    photometry   one row per (camera, region): rendered against predicted brightness and
                 contrast (`region_photometry`, docs/photometry.md)
    seconds      camera name -> render time (s)
    pairs        the stereo pairs of the calibration files (`vdo.formats.export.default_pairs`)
    no_pair      without a pair, why and the fix (`vdo.formats.export.no_pair_message`); else ""
    """

    state: object                 # vdo.state.LayoutState
    scale: float
    mode: str                     # the render mode, one of RENDER_MODES ([render] mode)
    spp: int | None               # samples per pixel; None in the dic mode (one ray per pixel, no spp)
    seed: int
    images: dict
    linear: dict
    photometry: list
    seconds: dict
    total_seconds: float
    pairs: list
    no_pair: str

    @property
    def experiment(self):
        """The experiment rendered (its full-size cameras; `cameras` are scaled)."""
        return self.state.geometry.experiment

    @property
    def cameras(self) -> list[Camera]:
        return list(self.state.cameras)


def render_settings(exp, scale: float | None = None, spp: int | None = None,
                    seed: int | None = None, mode: str | None = None) -> tuple[float, int, int]:
    """(scale, spp, seed): the given values or the experiment's [render] ones, checked (a
    ConfigError naming the option and the fix, before any heavy work), with the render `mode`
    (default [render] mode): one of RENDER_MODES; the DIC mode has no depth of field, so it
    refuses a camera with f_number."""
    from vdo.core.errors import ConfigError

    rs = exp.render
    scale = rs.scale if scale is None else float(scale)
    spp = rs.spp if spp is None else int(spp)
    seed = rs.seed if seed is None else int(seed)
    if not (0 < scale <= 4):
        raise ConfigError(exp.path, "--scale", f"must lie in (0, 4] (got {scale})")
    if spp < 1:
        raise ConfigError(exp.path, "--spp", f"must be at least 1 (got {spp})")
    if seed < 0:
        raise ConfigError(exp.path, "--seed", f"must be >= 0 (got {seed})")
    mode = rs.mode if mode is None else mode
    if mode not in RENDER_MODES:
        raise ConfigError(exp.path, "[render] mode", f"must be one of {', '.join(RENDER_MODES)} "
                                                     f"(got {mode!r})")
    for spec in exp.camera_specs:
        if mode == "dic" and spec.f_number is not None:
            raise ConfigError(exp.path, f'camera "{spec.name}".f_number',
                              'the "dic" render mode has no depth of field: remove f_number or '
                              'set [render] mode = "sampled"')
        if spec.f_number is not None and tuple(spec.principal_offset_px) != (0.0, 0.0):
            raise ConfigError(exp.path, f'camera "{spec.name}".f_number',
                              "a thin lens (depth of field) cannot have a principal_offset_px")
    return scale, spp, seed


def render_images(exp, scale: float | None = None, spp: int | None = None,
                  seed: int | None = None, pairs=None, only=None) -> RenderResult:
    """Render every camera of `exp` (the render scene of `build_render_scene`, camera i with
    Mitsuba seed `render_seed(seed, i)` and sensor noise `expose(linear, sensor, seed, i)`) and
    compare the noise-free renders with the photometric prediction (`region_photometry`).
    `scale`, `spp`, `seed` default to the config's [render] section (`render_settings`). Progress
    goes to the `vdo.render` logger (`vdo.core.progress`). `pairs`: the stereo pairs of the
    calibration files as (first, second) names (default: cameras assigned a common region),
    checked to share a field of view before anything is rendered. `only`: the names of the
    cameras to render (default all); the others stay in the scene as bodies and tripods, and
    camera i keeps its seed."""
    import dataclasses

    from vdo.formats.export import default_pairs, no_pair_message
    from vdo.physics.lighting import exposure_factors, photometry
    from vdo.core.progress import bar
    from vdo.state import bodies, layout_state, prepare

    scale, spp, seed = render_settings(exp, scale, spp, seed)
    dic = exp.render.mode == "dic"
    started = time.perf_counter()
    cameras = [scaled_camera(c, scale) for c in cameras_of(exp.camera_specs, exp.rails)]
    try:
        plan = plan_render(cameras, exp.render.mode)
    except MemoryError as err:
        from vdo.core.errors import ConfigError

        fix = ("lower scale, or render fewer cameras" if dic else
               'lower scale, render fewer cameras, or set [render] mode = "dic" (tiles)')
        raise ConfigError(exp.path, "[render] scale", f"{err}: {fix}") from None
    geometry = prepare(exp)
    # The scaled cameras have the full-size cameras' poses and lenses, hence the same bodies.
    state = layout_state(geometry, cameras, predict_fields=False)
    chosen = [i for i, c in enumerate(cameras) if only is None or c.name in only]
    vis = state.visibility
    if len(chosen) < len(cameras):   # the chosen cameras' rows of the ray cast
        vis = dataclasses.replace(vis, camera_names=tuple(vis.camera_names[i] for i in chosen),
                                  **{f: getattr(vis, f)[chosen] for f in
                                     ("in_front", "in_image", "facing", "unoccluded")})
        state = dataclasses.replace(state, cameras=tuple(cameras[i] for i in chosen), visibility=vis)
    stereo = default_pairs(exp, list(state.cameras), vis, geometry.samples, pairs)
    no_pair = "" if stereo else no_pair_message(exp, list(state.cameras), vis, geometry.samples)
    pattern = geometry.speckle.pattern
    build = build_dic_scene if dic else build_render_scene
    scene = build(exp, list(geometry.meshes), list(geometry.region_faces), bodies(exp, cameras), pattern)
    if dic:
        log.info("rendering %d cameras at scale %g in the dic mode, seed %d", len(chosen), scale, seed)
    else:
        log.info("rendering %d cameras at scale %g, %d spp, seed %d", len(chosen), scale, spp, seed)
    images, linear, seconds = {}, {}, {}
    gathered = exposure_factors(exp.camera_specs, exp.sensor)
    # The DIC mode's light in surface space (`vdo.rendering.lightmap`): one map per camera. One
    # map shared by the frame's cameras has lattices as fine as the nearest camera's over
    # surfaces the others do not see (built-in, ten cameras at full size: 96.5 s CPU against
    # 82.9 s without a map when this was chosen; 60.7 against 72.6 s since every camera runs the
    # same compiled kernels; per-camera maps were not timed beside it, benchmarks/README.md); a
    # map pays most where a frame is rendered again (a series' steps, `vdo.dic.series`).
    for i in bar(log, iterable=chosen, desc="render", unit="camera"):
        cam, spec = cameras[i], exp.camera_specs[i]
        t0 = time.perf_counter()
        radiance = (render_camera_dic(scene, cam, tile_pixels=plan.tile_pixels, spec=spec)
                    if dic else render_camera(scene, cam, spec, spp, render_seed(seed, i)))
        linear[cam.name] = radiance if gathered[i] == 1.0 else radiance * np.float32(gathered[i])
        images[cam.name] = expose(linear[cam.name], exp.sensor, seed, i)
        seconds[cam.name] = time.perf_counter() - t0
    pho = photometry(state.illumination, exp.speckle, exp.sensor, geometry.speckle.mean,
                     geometry.speckle.std, len(chosen), gathered[chosen])
    specs = {spec.name: spec for spec in exp.camera_specs}
    rows = region_photometry(list(state.cameras), vis, geometry.samples, pho, linear, exp.sensor,
                             normalise(pattern), exp.speckle.texel, None if dic else spp,
                             [lens_sigma_px(c, specs[c.name]) for c in state.cameras],
                             None if dic else state.illumination.sampling_cv2)
    for line in photometry_warnings(rows):
        log.warning(line)
    return RenderResult(state=state, scale=scale, mode=exp.render.mode, spp=None if dic else spp,
                        seed=seed, images=images, linear=linear,
                        photometry=rows, seconds=seconds,
                        total_seconds=time.perf_counter() - started, pairs=stereo,
                        no_pair=no_pair)
