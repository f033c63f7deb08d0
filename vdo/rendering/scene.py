"""The Mitsuba side of the renders: the sensor for a vdo camera, the render scene, one camera's
image and its exposure (`vdo.render` is the public face; `vdo.render.render_images` renders every
camera of an experiment).

`sensor_dict` is the only place a vdo `Camera` becomes a Mitsuba sensor; the frame conversion
itself lives in `Camera.mitsuba_to_world` / `mitsuba_principal_offset`.

The render scene (`build_render_scene`):

* each region of interest is its own mesh, textured with the speckle albedo
  ρ = ρ_b + (ρ_w - ρ_b) f (f the [0, 1] pattern, `vdo.model.speckle.pattern_for`), mapped at physical scale: a
  point with face coordinates (u, v) in metres (`vdo.scene.RegionFaces.uv`, the samples' uv) has
  texture coordinates (u / T_u, v / T_v), T = texel x pattern size, wrap mode repeat. Mitsuba's
  bitmap has v = 0 on its top row, so the pattern's row i covers v in [i, i+1) texels
  (`pattern_value` reads it the same way);
* a specimen [[mesh]] with finish = "satin": the same paint under Mitsuba's roughplastic coat
  (GGX, `vdo.physics.glare`'s roughness and index), whose specular lobe gives the hot spots;
* the rest of the specimen is white paint (ρ_w); obstacles are diffuse of their `albedo`, or a rough
  conductor (aluminium, α = 0.2) when `metal`; camera bodies are dark (ρ = 0.05);
* each [[light]] is a one-sided rectangle area emitter of its radiance, facing its target (the
  frame of `vdo.physics.lighting.panel_frame`); [render] ambient_radiance is a constant environment;
* the integrator is `vdo_panels` (`_register_integrator`): direct illumination only, no
  interreflection, with one sample on *every* panel per camera sample (Mitsuba's `direct` picks one
  emitter at random: 10 % pixel noise at 64 spp with 4 panels). So the renders and the photometric
  model of `vdo.physics.lighting` describe the same light transport: they agree up to Monte Carlo noise,
  the panel quadrature and the model's sky quadrature (its sky fraction S, the ambient occlusion).

Each camera is rendered with a box filter into a linear float luminance film (bit-identical for a
seed), then `SensorModel.expose` adds shot and read noise and quantises, with the generator
`numpy.random.default_rng([seed, camera_index])`. Mitsuba's own seed for camera i is
seed * 1009 + i.

Scale. `scale` s < 1 renders round(s W) x round(s H) pixels of the same view (`scaled_camera`: same
field of view; pixel pitch and K scaled by s' = round(s W) / W). The linear value stays the
radiance, *not* multiplied by 1/s'^2: the small image stands for the same sensor (same full well,
same exposure level per pixel), so brightness, contrast and noise in DN are those `vdo.physics.lighting`
predicts for the full-size camera, at any scale; only the sampling of the surface changes. (Scaling
by 1/s'^2, "bigger pixels collect more light", would saturate a 1/8-scale preview 64 times over.)
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from vdo.model.camera import Camera, image_point
from vdo.model.speckle import pattern_for
from vdo.physics.glare import SATIN_ALPHA, SATIN_IOR


BODY_ALBEDO = 0.05
NEAR_CLIP_M = 1e-3    # the sensors' near-clip plane (m in front of the camera centre)


def sensor_dict(camera: Camera, spp: int = 16, scale: float = 1.0, jitter: bool = True,
                aperture_radius: float | None = None, focus_distance: float | None = None) -> dict:
    """Mitsuba sensor dict for `camera`: linear float luminance film, box filter (bit-identical
    renders for a seed; a Gaussian filter with several threads differs by ~4e-7 from the order
    of atomic adds), stratified sampler. `scale` < 1 renders a smaller image
    of the same view (pixel pitch / scale). With `aperture_radius` (m) a thin lens focused at
    `focus_distance` (m) gives depth of field (Mitsuba's thinlens has no principal-point offset).
    The sensor is the camera's pinhole part: `render_camera` adds its lens distortion."""
    width, height = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    ox, oy = camera.mitsuba_principal_offset()
    film = {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
            "pixel_format": "luminance", "component_format": "float32"}
    sensor = {"fov_axis": "x", "fov": camera.mitsuba_fov_deg(), "near_clip": NEAR_CLIP_M,
              "far_clip": 1e4, "to_world": _transform(camera.mitsuba_to_world()), "film": film,
              "sampler": {"type": "stratified", "sample_count": spp, "jitter": jitter}}
    if aperture_radius:
        if camera.principal_offset_px != (0.0, 0.0):
            raise ValueError(f"camera {camera.name!r}: a thin lens cannot have a principal-point offset")
        return sensor | {"type": "thinlens", "aperture_radius": aperture_radius,
                         "focus_distance": focus_distance}
    return sensor | {"type": "perspective", "principal_point_offset_x": ox,
                     "principal_point_offset_y": oy}


def _transform(matrix: np.ndarray):
    from vdo.core.backend import mitsuba

    return mitsuba().ScalarTransform4f(np.asarray(matrix, dtype=float))


# --------------------------------------------------------------------------------------------
# Cameras at a render scale
# --------------------------------------------------------------------------------------------
def scaled_camera(camera: Camera, scale: float) -> Camera:
    """The camera that `sensor_dict(camera, scale=scale)` renders: round(s W) x round(s H) pixels,
    the same horizontal field of view, pixel pitch x W / W', principal offset x W' / W. Its K is the
    full-size K with f and c scaled by s' = W' / W (c = (W' - 1)/2 + s' offset)."""
    width, height = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    s = width / camera.width
    return replace(camera, width=width, height=height, pixel_size=camera.pixel_size / s,
                   principal_offset_px=(camera.principal_offset_px[0] * s,
                                        camera.principal_offset_px[1] * s))


# --------------------------------------------------------------------------------------------
# Lens distortion: render a wider pinhole image, resample it onto the distorted pixels
# --------------------------------------------------------------------------------------------
DISTORTION_MARGIN_PX = 3   # pinhole pixels kept beyond the distorted image's footprint (cubic spline)


def undistorted_canvas(camera: Camera, rows_per_chunk: int = 256) -> tuple[Camera, np.ndarray]:
    """Mitsuba has no lens distortion. For a camera with distortion: the pinhole camera to render
    instead (same pose and focal length, distortion zero, W + 2 m_x by H + 2 m_y pixels with the
    principal point moved by (m_x, m_y), so the principal offset and a thin lens stay valid) and,
    for every pixel (u, v) of the distorted image, where it lies in that render:
    (u', v') = `Camera.undistorted_pixels`(u, v) + (m_x, m_y), an (H, W, 2) array. The margins
    m cover the furthest undistorted pixel plus `DISTORTION_MARGIN_PX`."""
    where = np.empty((camera.height, camera.width, 2))
    u = np.arange(camera.width, dtype=float)
    for r0 in range(0, camera.height, rows_per_chunk):
        rows = np.arange(r0, min(r0 + rows_per_chunk, camera.height), dtype=float)
        grid = np.stack(np.broadcast_arrays(u[None, :], rows[:, None]), axis=-1)
        where[r0:r0 + len(rows)] = camera.undistorted_pixels(grid)
    ray = np.linalg.solve(camera.K, np.stack([where[..., 0], where[..., 1], np.ones(where.shape[:2])],
                                             axis=-1).reshape(-1, 3).T)     # same K without distortion
    back = np.stack(image_point(camera.K, ray[0], ray[1], camera.distortion_array), -1)
    grid = np.stack(np.meshgrid(u, np.arange(camera.height, dtype=float)), -1).reshape(-1, 2)
    if not np.all(np.abs(back - grid) < 1e-6):     # NaN or not converged: the distortion folds
        raise ValueError(f"camera {camera.name!r}: the lens distortion {camera.distortion} cannot be "
                         "inverted over the image (it folds the image): check its coefficients")
    over = [max(0.0, -where[..., k].min(), where[..., k].max() - (n - 1))
            for k, n in ((0, camera.width), (1, camera.height))]
    mx, my = (math.ceil(o) + DISTORTION_MARGIN_PX for o in over)
    wide = replace(camera, width=camera.width + 2 * mx, height=camera.height + 2 * my,
                   distortion=(0.0,) * 5)
    return wide, where + np.array([mx, my], dtype=float)


def resample(linear: np.ndarray, where: np.ndarray) -> np.ndarray:
    """The pinhole render `linear` (H', W') read at `where` (H, W, 2) pixel coordinates (u', v'),
    by cubic B-spline interpolation (the inverse mapping of each output pixel), clipped at 0
    (radiance). float32 (H, W)."""
    from scipy import ndimage

    out = ndimage.map_coordinates(np.asarray(linear, dtype=np.float64),
                                  [where[..., 1], where[..., 0]], order=3, mode="nearest")
    return np.maximum(out, 0.0).astype(np.float32)


def render_camera(scene, camera: Camera, spec, spp: int, seed: int, jitter: bool = True) -> np.ndarray:
    """One camera's (H, W) float32 linear image: `render_linear` through `camera_sensor`, and for a
    camera with lens distortion the wider pinhole render resampled onto the distorted pixels
    (`undistorted_canvas`, `resample`). `jitter`: the stratified sampler's random offsets within
    each stratum (False: stratum centres, a fixed sqrt(spp) x sqrt(spp) midpoint rule per pixel
    and per light, as `vdo.dic.validate` and `vdo.dic.series` render). With a `spec` the lens's
    diffraction acts before the pixels integrate (`lens_sigma_px`, `cell_blur`): the film is
    rendered at PRESAMPLE x PRESAMPLE cells a pixel with ceil(spp / PRESAMPLE^2) samples a cell
    (for spp = 4 k^2 the same sample positions as spp at full size), the cells blurred, each
    pixel their mean. Its defocus is Mitsuba's thin lens."""
    sigma = lens_sigma_px(camera, spec)
    wide, where = (camera, None) if not camera.distorted else undistorted_canvas(camera)
    if sigma > 0:
        n = PRESAMPLE
        fine = scaled_camera(wide, n)
        cells = render_linear(scene, camera_sensor(fine, spec, -(-spp // (n * n)), jitter), seed)
        linear = cell_blur(cell_blur(cells, sigma, n, axis=1), sigma, n, axis=0)
    else:
        linear = render_linear(scene, camera_sensor(wide, spec, spp, jitter), seed)
    return linear if where is None else resample(linear, where)


PRESAMPLE = 2      # cells per pixel side on which the lens's blur acts before the pixel integrates


def lens_sigma_px(camera: Camera, spec) -> float:
    """The std (pixels of `camera`, scaled with the render) of the Gaussian that stands for the
    lens's in-focus diffraction at the spec's f_number: 0.42 λ N_w / p (`vdo.model.optics`: the
    Airy core's fit, N_w the working f-number at the focus distance, p the pixel pitch). A spec
    without f_number gets the lens that σ_measured assumes for it (`DEFAULT_F_NUMBER`, in focus:
    diffraction, no depth of field), so that the renders and the prediction see the same optics;
    0 without a spec (no lens blur)."""
    if spec is None:
        return 0.0
    from vdo.model.optics import optics_blur

    return float(optics_blur(camera.pixel_size, camera.focal_length, spec.f_number,
                             spec.focus_distance).sigma_px)


CELL_BLUR_TRUNCATE = 4.0   # the lens's Gaussian is cut at this many standard deviations (as SciPy's)
BLUR_THREAD_CELLS = 1 << 18   # an image of fewer cells is blurred on one thread
BLUR_STRIP_CELLS = 1 << 20    # ... a larger one in strips of about this many cells (the threads take
                              # them in turn: a strip's temporaries stay in the cache)


def cell_blur_kernel(sigma_px: float, n: int) -> np.ndarray:
    """The weights c_k, k = -r .. n - 1 + r, that take n cells a pixel to the pixel's value along
    one axis (`cell_blur`): c = (box of n cells, 1/n each) ⊗ g, g the Gaussian of std n sigma_px
    cells sampled at whole cells within r = ⌊CELL_BLUR_TRUNCATE n sigma_px + ½⌋ and normalised
    to a sum of 1 (the kernel of SciPy's `gaussian_filter1d`)."""
    s = n * sigma_px
    r = int(CELL_BLUR_TRUNCATE * s + 0.5)
    g = np.exp(-0.5 * (np.arange(-r, r + 1) / s) ** 2)
    return np.convolve(np.full(n, 1.0 / n), g / g.sum())


def cell_blur(cells: np.ndarray, sigma_px: float, n: int, axis: int) -> np.ndarray:
    """Along `axis`, an image of n cells a pixel blurred by the lens's Gaussian (std `sigma_px`
    pixels, n sigma_px cells) and each pixel the mean of its n cells: float32, 1/n of the length.
    On both axes, the pixel's box over the image blurred before the pixel integrates it, as a lens
    blurs: the blur of an already sampled image (a Gaussian of the pixels) leaves the aliasing a
    lens removes (measured on the built-in's 24 mm cam9, 2 mm dots at 2 px/mm: the correlation's
    bias 0.0051 / 0.0059 px RMS against 0.0022 / 0.0047 with the blur before sampling, 0.0021 /
    0.0045 on a 3 x 3 grid, and σ_measured's model 0.0021 / 0.0063; benchmarks/README.md).
    Computed at the pixels only: pixel p = Σ_k c_k cell[n p + k] (`cell_blur_kernel`), the cells
    beyond the image's ends taken equal to its first and last (SciPy's "nearest"). A 2-D image is
    cut across `axis` into strips that `vdo.core.backend.cpu_threads` threads blur in turn
    (`_on_strips`): on the built-in's cam1 at full size, 0.14 s on 2 threads (0.55 s on one, in
    one strip)."""
    cells = np.asarray(cells, dtype=np.float32)
    if cells.ndim != 2:
        return _cell_blur(cells, sigma_px, n, axis)
    shape = list(cells.shape)
    shape[axis] //= n
    out = np.empty(shape, dtype=np.float32)

    def strip(s: slice) -> None:
        at = (s, slice(None)) if axis == 1 else (slice(None), s)
        out[at] = _cell_blur(cells[at], sigma_px, n, axis)
    _on_strips(cells.shape[1 - axis], cells.size, strip)
    return out


def _on_strips(length: int, cells: int, work) -> list:
    """[work(s) for each slice s of range(length)], in order: strips of about BLUR_STRIP_CELLS of
    the image's `cells`, `vdo.core.backend.cpu_threads` at once (NumPy releases the GIL); one strip
    for an image of fewer than BLUR_THREAD_CELLS cells. Measured on the built-in's cam1 at full
    size: the blur along the rows 0.23-0.28 s in one strip a thread, 0.17-0.19 s in 48-row strips;
    across them 0.18-0.27 s against 0.14-0.15 s in 48-column strips."""
    from vdo.core.backend import cpu_threads

    threads = max(1, min(cpu_threads(), length)) if cells >= BLUR_THREAD_CELLS else 1
    count = min(length, max(threads, -(-cells // BLUR_STRIP_CELLS))) if threads > 1 else 1
    cuts = np.linspace(0, length, count + 1).astype(int)
    strips = [slice(a, b) for a, b in zip(cuts[:-1], cuts[1:])]
    if threads == 1:
        return [work(s) for s in strips]
    return list(_strip_pool(threads).map(work, strips))


_POOLS: dict = {}


def _strip_pool(threads: int):
    """A thread pool of `threads` workers kept for the process (a render blurs in seven calls;
    a forked child, which has none of its parent's threads, makes its own)."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    key = (os.getpid(), threads)
    pool = _POOLS.get(key)
    if pool is None:
        pool = _POOLS[key] = ThreadPoolExecutor(threads, thread_name_prefix="vdo-blur")
    return pool


def part_blur(part, shape: tuple[int, int], sigma_px: float, n: int) -> np.ndarray:
    """`cell_blur` along the rows (axis 1) of an h x W image (`shape`) whose pixel (y, x) has the
    n x n cells part(i n + j, rows)[y - rows.start, x] (i along the row, j across it; `part`
    gives a part's values on a slice of rows), without laying the cells out: (n h, W) float32,
    pixel row y's cell row j at n y + j. Cell q = n x + i of a cell row j is part i n + j at x, so
    pixel p = Σ_k c_k part(i_k n + j)[:, p + o_k], i_k = (k - r) mod n and o_k = ⌊(k - r) / n⌋
    (`cell_blur_kernel`'s c and r: slices, no strides); cells beyond the row's ends taken equal
    to its first and last. In row strips (`_on_strips`) that the threads take in turn, each
    strip's parts made by `part` on its thread."""
    h, W = shape
    c = cell_blur_kernel(sigma_px, n).astype(np.float32)
    r = (len(c) - n) // 2
    out = np.empty((h, n, W), dtype=np.float32)

    def strip(rows: slice) -> None:
        parts = [part(k, rows) for k in range(n * n)]
        lo, hi = min(W, -(-r // n)), max(0, min(W, (n * W - n - r) // n + 1))   # every tap inside
        for j in range(n):
            target = out[rows, j]
            if hi > lo:
                inner = target[:, lo:hi]
                inner[...] = 0.0
                term = np.empty_like(inner)
                for k, w in enumerate(c):
                    i, o = (k - r) % n, (k - r) // n
                    inner += np.multiply(parts[i * n + j][:, lo + o:hi + o], w, out=term)
            for p in [*range(0, min(lo, W)), *range(max(hi, lo), W)]:      # clamped taps
                q = np.clip(n * p + np.arange(len(c)) - r, 0, n * W - 1)
                target[:, p] = sum(w * parts[(qk % n) * n + j][:, qk // n] for w, qk in zip(c, q))

    _on_strips(h, h * W * n * n, strip)
    return out.reshape(n * h, W)


def _cell_blur(cells: np.ndarray, sigma_px: float, n: int, axis: int) -> np.ndarray:
    """`cell_blur` on one thread."""
    c = cell_blur_kernel(sigma_px, n).astype(np.float32)
    r = (len(c) - n) // 2
    N = cells.shape[axis]
    P = N // n
    shape = list(cells.shape)
    shape[axis] = P
    out = np.zeros(shape, dtype=np.float32)

    def along(a, index):
        return a[(slice(None),) * axis + (index,)]

    lo, hi = min(P, -(-r // n)), max(0, min(P, (N - n - r) // n + 1))   # every tap inside
    if hi > lo:
        inner = along(out, slice(lo, hi))
        term = np.empty_like(inner)
        for k, w in enumerate(c):
            start = n * lo + k - r
            inner += np.multiply(along(cells, slice(start, start + n * (hi - lo), n)), w, out=term)
    for p in [*range(0, min(lo, P)), *range(max(hi, lo), P)]:        # clamped taps
        taps = np.clip(n * p + np.arange(len(c)) - r, 0, N - 1)
        along(out, p)[...] = np.tensordot(np.take(cells, taps, axis=axis), c, axes=([axis], [0]))
    return out


def camera_sensor(camera: Camera, spec, spp: int, jitter: bool = True) -> dict:
    """`sensor_dict` for an already scaled camera and its CameraSpec (thin lens when the spec has
    f_number: aperture radius f / (2N), focused at focus_distance)."""
    if spec is not None and spec.f_number is not None:
        return sensor_dict(camera, spp=spp, jitter=jitter,
                           aperture_radius=camera.focal_length / (2 * spec.f_number),
                           focus_distance=spec.focus_distance)
    return sensor_dict(camera, spp=spp, jitter=jitter)


# --------------------------------------------------------------------------------------------
# Speckle texture
# --------------------------------------------------------------------------------------------
def pattern_value(pattern: np.ndarray, texel: float, uv: np.ndarray) -> np.ndarray:
    """f at face coordinates uv (..., 2) in metres, nearest texel, as the render maps it:
    column = floor(u / texel) mod width, row = floor(v / texel) mod height."""
    uv = np.asarray(uv, dtype=float)
    col = np.floor(uv[..., 0] / texel).astype(np.int64) % pattern.shape[1]
    row = np.floor(uv[..., 1] / texel).astype(np.int64) % pattern.shape[0]
    return np.asarray(pattern)[row, col]


# --------------------------------------------------------------------------------------------
# The render scene
# --------------------------------------------------------------------------------------------
def _mi_mesh(name, vertices, faces, bsdf, uv=None):
    from vdo.scene import SceneMesh, mitsuba_mesh

    return mitsuba_mesh(SceneMesh(name, "render", vertices, faces), bsdf, uv)


def _submesh(vertices, faces):
    used, inverse = np.unique(faces.ravel(), return_inverse=True)
    return vertices[used], inverse.reshape(faces.shape)


def _satin(reflectance: dict) -> dict:
    """A satin paint: Mitsuba's roughplastic (GGX coat of `vdo.physics.glare`'s roughness and
    index over the diffuse `reflectance`)."""
    return {"type": "roughplastic", "distribution": "ggx", "alpha": SATIN_ALPHA, "int_ior": SATIN_IOR,
            "ext_ior": 1.0, "nonlinear": False, "diffuse_reflectance": reflectance}


def _diffuse(albedo):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": float(albedo)}}


def light_emitter(light) -> dict:
    """A one-sided rectangle area emitter of the light's radiance, facing its target."""
    from vdo.physics.lighting import panel_frame

    n, e1, e2 = panel_frame(light)
    w, h = light.size
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = e1 * w / 2, e2 * h / 2, n, light.position
    return {"type": "rectangle", "to_world": _transform(M),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": float(light.radiance)}}}


_PANEL_INTEGRATOR = "vdo_panels"
SPECKLED_SUFFIX = "_speckled"     # the render scene's ids of the speckled region shapes


def _register_integrator() -> str:
    """Register (once) `vdo_panels`, a direct-illumination integrator that samples every light.

    Mitsuba's `direct` integrator picks one emitter at random per sample, so with 4 panels and a sky
    a point lit by one panel gets the right mean from a 1-in-5 lottery: 50 % Monte Carlo noise per
    pixel at 4 spp, 10 % at 64 spp, far above the sensor noise. This one, for each camera ray's
    first hit: (1) adds the radiance of an emitter or the sky seen directly; (2) for *each* light,
    one point P uniform on its rectangle (stratified over the pixel's samples) and a shadow ray:
    f(ω_i, ω_o) cosθ_s L cosθ_l A / r^2 when P is visible (f from the hit's BSDF, so textures and
    the rough conductor work); (3) with an ambient sky, one BSDF-sampled direction and a shadow
    ray: weight x L_amb when it escapes. This is the estimator of exactly the integral in
    `vdo.physics.lighting` (direct light only, no interreflection), with the noise of the cosθ/r^2
    variation over one panel (about 1 % per sample) instead of the emitter lottery. The camera
    rays are traced in Embree's coherent mode (a pixel's samples are neighbouring lanes): 4.1 ->
    3.1 s for cam1 at 1/4 scale and 16 spp, the same image but for 8 of 1.5 M pixels where two
    surfaces tie on a shared edge."""
    from vdo.core.backend import mitsuba

    mi = mitsuba()
    if _PANEL_INTEGRATOR in getattr(_register_integrator, "done", set()):
        return _PANEL_INTEGRATOR
    import drjit as dr

    class PanelDirect(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)
            self.lights = []
            for k in range(props.get("light_count", 0)):
                self.lights.append([props.get(f"light{k}_{c}") for c in "cuvnLA"])
            self.ambient = props.get("ambient", 0.0)

        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(mi.Ray3f(ray), mi.RayFlags.All, True, active)
            valid = mi.Bool(active) & si.is_valid()
            result = mi.Spectrum(0.0)
            result += si.emitter(scene, mi.Bool(active)).eval(si, mi.Bool(active))
            ctx = mi.BSDFContext()
            bsdf = si.bsdf(ray)
            for c, u, v, n, radiance, area in self.lights:
                s = sampler.next_2d(valid)
                P = mi.Point3f(c) + (s.x - 0.5) * mi.Vector3f(u) + (s.y - 0.5) * mi.Vector3f(v)
                d = P - si.p
                dist2 = dr.squared_norm(d)
                d = d * dr.rsqrt(dist2)
                cos_l = -dr.dot(d, mi.Vector3f(n))
                ok = valid & (cos_l > 0) & (dr.dot(d, si.n) > 0)
                ok &= ~scene.ray_test(si.spawn_ray_to(P), ok)
                f = bsdf.eval(ctx, si, si.to_local(d), ok)
                result += dr.select(ok, f * (radiance * area) * cos_l / dist2, 0.0)
            if self.ambient > 0:
                bs, weight = bsdf.sample(ctx, si, sampler.next_1d(valid), sampler.next_2d(valid), valid)
                ok = valid & (bs.pdf > 0)
                ok &= ~scene.ray_test(si.spawn_ray(si.to_world(bs.wo)), ok)
                result += dr.select(ok, weight * self.ambient, 0.0)
            return result, mi.Bool(True), []

    mi.register_integrator(_PANEL_INTEGRATOR, lambda props: PanelDirect(props))
    _register_integrator.done = {_PANEL_INTEGRATOR}
    return _PANEL_INTEGRATOR


def _integrator_dict(lights, ambient: float) -> dict:
    from vdo.physics.lighting import panel_frame

    out = {"type": _register_integrator(), "light_count": len(lights), "ambient": float(ambient)}
    for k, light in enumerate(lights):
        n, e1, e2 = panel_frame(light)
        w, h = light.size
        for key, value in (("c", light.position), ("u", e1 * w), ("v", e2 * h), ("n", n)):
            out[f"light{k}_{key}"] = [float(x) for x in value]
        out[f"light{k}_L"] = float(light.radiance)
        out[f"light{k}_A"] = float(w * h)
    return out


def build_render_scene(exp, meshes, region_faces, bodies=(), pattern=None, posed=None,
                       white_regions: bool = False, robust: bool = False):
    """The Mitsuba scene to render `exp` (module docstring), without sensors. `meshes` are the
    experiment's SceneMeshes at rest (vdo.scene.load_meshes), `region_faces` one RegionFaces per
    region, `bodies` camera-body SceneMeshes, `pattern` the [0, 1] speckle tile (default:
    `vdo.model.speckle.pattern_for(exp.speckle)`). `posed` are the same meshes at a step of the load
    path (`vdo.geometry.keyframes.at_step`): their vertices are rendered, while the texture coordinates
    come from the rest vertices, so the speckle moves with the surface (`vdo.dic.series`).
    `white_regions`: the regions are white (ρ = 1, texture coordinates kept) for the DIC render
    mode, which multiplies in the speckle itself (`build_dic_scene`); their shapes' ids end in
    SPECKLED_SUFFIX either way. `robust`: Embree's watertight mode (RTC_SCENE_FLAG_ROBUST), for
    rays cast on a lattice (the DIC render mode), which can pass exactly through a shared edge."""
    at = {m.name: m.vertices for m in (posed or meshes)}

    def moved(name, faces):
        """The vertices of `faces` of mesh `name` at the step (the order `_submesh` gives)."""
        return _submesh(at[name], faces)[0]

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    sp = exp.speckle
    pattern = pattern_for(sp) if pattern is None else np.asarray(pattern, dtype=np.float32)
    albedo = (sp.black_albedo + (sp.white_albedo - sp.black_albedo) * pattern).astype(np.float32)
    tile = np.array([pattern.shape[1], pattern.shape[0]]) * sp.texel       # (T_u, T_v) metres
    speckled = mi.load_dict({"type": "diffuse", "reflectance": {
        "type": "bitmap", "bitmap": mi.Bitmap(albedo[..., None]), "raw": True,
        "wrap_mode": "repeat", "filter_type": "bilinear"}})
    white = mi.load_dict(_diffuse(sp.white_albedo))
    satin_speckled = mi.load_dict(_satin({"type": "bitmap", "bitmap": mi.Bitmap(albedo[..., None]),
                                          "raw": True, "wrap_mode": "repeat", "filter_type": "bilinear"}))
    satin_white = mi.load_dict(_satin({"type": "rgb", "value": float(sp.white_albedo)}))
    if white_regions:
        speckled = mi.load_dict(_diffuse(1.0))
        satin_speckled = mi.load_dict(_satin({"type": "rgb", "value": 1.0}))
    spec_of = {m.name: m for m in exp.meshes}
    shapes = {}
    for mesh in meshes:
        spec = spec_of.get(mesh.name)
        faces = np.asarray(mesh.faces)
        if mesh.role == "specimen":
            satin = spec is not None and spec.finish == "satin"
            taken = np.zeros(len(faces), dtype=bool)
            for region, rf in zip(exp.regions, region_faces):
                if region.mesh != mesh.name:
                    continue
                fresh = ~taken[rf.faces]
                sel = rf.faces[fresh]
                taken[sel] = True
                if len(sel) == 0:
                    continue
                if rf.development is not None:   # a curved region: corners of its own per face,
                    # so that a ring's seam does not smear the texture (texture coordinates per face)
                    uv = rf.development.triangles_uv(mesh.vertices[faces[rf.faces]])[fresh]
                    soup = np.arange(3 * len(sel)).reshape(-1, 3)
                    shapes[f"region:{region.name}"] = _mi_mesh(
                        f"region:{region.name}", at[mesh.name][faces[sel]].reshape(-1, 3), soup,
                        speckled, uv=uv.reshape(-1, 2) / tile)
                    continue
                v, f = _submesh(mesh.vertices, faces[sel])
                shapes[f"region:{region.name}"] = _mi_mesh(f"region:{region.name}",
                                                           moved(mesh.name, faces[sel]), f,
                                                           satin_speckled if satin else speckled,
                                                           uv=rf.uv(v) / tile)
            rest = faces[~taken]
            if len(rest):
                _, f = _submesh(mesh.vertices, rest)
                shapes[f"paint:{mesh.name}"] = _mi_mesh(f"paint:{mesh.name}", moved(mesh.name, rest),
                                                        f, satin_white if satin else white)
        else:
            if spec is not None and spec.metal:
                bsdf = {"type": "roughconductor", "material": "Al", "alpha": 0.2}
            else:
                bsdf = _diffuse(spec.albedo if spec is not None else 0.5)
            shapes[mesh.name] = _mi_mesh(mesh.name, at[mesh.name], faces, mi.load_dict(bsdf))
    dark = mi.load_dict(_diffuse(BODY_ALBEDO))
    for body in bodies:
        shapes[body.name] = _mi_mesh(body.name, body.vertices, body.faces, dark)
    scene = {"type": "scene", "integrator": _integrator_dict(exp.lights, exp.render.ambient_radiance),
             "embree_use_robust_intersections": robust}
    for i, (name, shape) in enumerate(shapes.items()):
        scene[f"shape_{i:04d}" + (SPECKLED_SUFFIX if name.startswith("region:") else "")] = shape
    for i, light in enumerate(exp.lights):
        scene[f"light_{i:03d}"] = light_emitter(light)
    if exp.render.ambient_radiance > 0:
        scene["ambient"] = {"type": "constant",
                            "radiance": {"type": "rgb", "value": float(exp.render.ambient_radiance)}}
    return mi.load_dict(scene)


def lit_scene(exp, shapes: dict):
    """A Mitsuba scene of the given shapes (name -> `mi.Mesh`) lit by the experiment's [[light]]
    panels and ambient radiance with the `vdo_panels` integrator, as `build_render_scene` lights
    the specimen (`vdo.calib.images` renders the calibration target in it)."""
    from vdo.core.backend import mitsuba

    scene = {"type": "scene", "integrator": _integrator_dict(exp.lights, exp.render.ambient_radiance)}
    for i, shape in enumerate(shapes.values()):
        scene[f"shape_{i:04d}"] = shape
    for i, light in enumerate(exp.lights):
        scene[f"light_{i:03d}"] = light_emitter(light)
    if exp.render.ambient_radiance > 0:
        scene["ambient"] = {"type": "constant",
                            "radiance": {"type": "rgb", "value": float(exp.render.ambient_radiance)}}
    return mitsuba().load_dict(scene)

def render_linear(scene, sensor: dict, seed: int) -> np.ndarray:
    """One render of `scene` through the sensor dict: (H, W) float32 linear radiance."""
    from vdo.core.backend import mitsuba

    mi = mitsuba()
    image = mi.render(scene, sensor=mi.load_dict(sensor), seed=int(seed) & 0xFFFFFFFF)
    return np.array(image, dtype=np.float32).reshape(image.shape[0], image.shape[1])


def render_seed(seed: int, camera_index: int) -> int:
    """Mitsuba's seed for camera `camera_index` of a render with `seed`."""
    return (int(seed) * 1009 + int(camera_index)) & 0xFFFFFFFF


def expose(linear: np.ndarray, sensor, seed: int, camera_index: int) -> np.ndarray:
    """`sensor.expose` with the generator numpy.random.default_rng([seed, camera_index])."""
    return sensor.expose(linear, np.random.default_rng([int(seed), int(camera_index)]))


def noise_free_dn(linear: np.ndarray, sensor) -> np.ndarray:
    """The expected DN of a linear image (no noise, no rounding), clipped to [0, max DN]."""
    return np.clip(sensor.mean_dn(np.asarray(linear, dtype=np.float64)), 0.0, sensor.max_dn)
