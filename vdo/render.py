"""Images with Mitsuba: the sensor for a vdo camera, the render scene, and the images of every
camera of an experiment (`render_images`, the computation of `vdo render`; `vdo.commands.render`
writes them into a run folder).

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
  the panel quadrature and ambient occlusion (which the model ignores).

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

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np

from vdo.model.camera import Camera, image_point
from vdo.model.speckle import normalise, pattern_for
from vdo.physics.glare import SATIN_ALPHA, SATIN_IOR
from vdo.scene import cameras_of

log = logging.getLogger(__name__)

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
    and per light, as `vdo.dic.validate` and `vdo.dic.series` render). A camera with an f_number
    also gets the lens's diffraction (`diffraction_blur`); its defocus is Mitsuba's thin lens."""
    if not camera.distorted:
        return diffraction_blur(render_linear(scene, camera_sensor(camera, spec, spp, jitter), seed),
                                camera, spec)
    wide, where = undistorted_canvas(camera)
    return resample(diffraction_blur(render_linear(scene, camera_sensor(wide, spec, spp, jitter),
                                                   seed), wide, spec), where)


def diffraction_blur(linear: np.ndarray, camera: Camera, spec) -> np.ndarray:
    """The image blurred by the diffraction of a lens at the spec's f_number: a Gaussian of std
    0.42 λ N_w / p pixels (`vdo.model.optics`: the Airy core's fit, N_w the working f-number at
    the focus distance, p the camera's pixel pitch, scaled with the render). Mitsuba's thin lens
    models defocus only. Unchanged for a pinhole (no f_number)."""
    if spec is None or spec.f_number is None:
        return linear
    from scipy import ndimage

    from vdo.model.optics import optics_blur

    sigma = optics_blur(camera.pixel_size, camera.focal_length, spec.f_number,
                        spec.focus_distance).sigma_px
    return ndimage.gaussian_filter(np.asarray(linear), sigma, mode="nearest").astype(np.float32)


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
    variation over one panel (about 1 % per sample) instead of the emitter lottery."""
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
            si = scene.ray_intersect(mi.Ray3f(ray), active)
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
                       white_regions: bool = False):
    """The Mitsuba scene to render `exp` (module docstring), without sensors. `meshes` are the
    experiment's SceneMeshes at rest (vdo.scene.load_meshes), `region_faces` one RegionFaces per
    region, `bodies` camera-body SceneMeshes, `pattern` the [0, 1] speckle tile (default:
    `vdo.model.speckle.pattern_for(exp.speckle)`). `posed` are the same meshes at a step of the load
    path (`vdo.geometry.keyframes.at_step`): their vertices are rendered, while the texture coordinates
    come from the rest vertices, so the speckle moves with the surface (`vdo.dic.series`).
    `white_regions`: the regions are white (ρ = 1, texture coordinates kept) for the DIC render
    mode, which multiplies in the speckle itself (`build_dic_scene`); their shapes' ids end in
    SPECKLED_SUFFIX either way."""
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
    scene = {"type": "scene", "integrator": _integrator_dict(exp.lights, exp.render.ambient_radiance)}
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


# --------------------------------------------------------------------------------------------
# Photometry of the renders
# --------------------------------------------------------------------------------------------
def rendered_std(pattern_normalised, texel: float, pixel_sides, spp: int | None) -> np.ndarray:
    """(K,) std of the rendered pixel values of a unit-variance pattern f̂: each pixel is the
    mean of `spp` samples, one uniform in each of the sqrt(spp) x sqrt(spp) strata of the pixel
    (the stratified sampler with jitter), not the box average a camera pixel takes. With
    s(P) = `vdo.model.speckle.pixel_averaged_std` over a parallelogram P (the pixel A^-1, a stratum
    A^-1 / sqrt(spp)) and s_0 that of the texture alone (P = 0):

        std^2 = s(A^-1)^2 + (s_0^2 - s(A^-1 / sqrt spp)^2) / spp

    (law of total variance: the box average's variance, plus the mean variance of f within a
    stratum, s_0^2 - s(stratum)^2 for a stationary pattern, over spp independent samples). The
    second term is the render's Monte Carlo sampling of the speckle: small when a stratum is
    small against a speckle, large for a reduced-scale render whose pixels span speckles.
    `spp` None: the DIC render mode's exact box average, std = s(A^-1)."""
    from vdo.model.speckle import pixel_averaged_std

    sides = np.asarray(pixel_sides, dtype=float).reshape(-1, 2, 2)
    box = pixel_averaged_std(pattern_normalised, texel, sides)
    if spp is None:
        return box
    stratum = pixel_averaged_std(pattern_normalised, texel, sides / math.sqrt(spp))
    texture = pixel_averaged_std(pattern_normalised, texel, np.zeros((1, 2, 2)))[0]
    return np.sqrt(box ** 2 + (texture ** 2 - stratum ** 2) / spp)


PHOTOMETRY_WINDOW = 3     # px: each visible sample contributes the window x window pixels around it


def region_photometry(cameras, vis, samples, pho, linear: dict, sensor, pattern_normalised,
                      texel: float, spp: int | None) -> list[dict]:
    """One row per (camera, region) of photometry.csv (docs/photometry.md). Over the
    `PHOTOMETRY_WINDOW`^2 pixels around each visible sample's projection in the noise-free
    render (`noise_free_dn` of each camera's `linear` image): b_render = mean DN; c_render = std of (DN - offset) / (b_predicted(X) - offset) x
    mean(b_predicted - offset), the contrast with the predicted light level divided out (so that
    the irradiance's variation over the region does not count as contrast). Predictions at the
    pixel footprint of the row's middle visible sample: c_pixel_predicted = c_predicted x
    pixel_factor (`vdo.model.speckle.pixel_averaged_std`), the contrast of a camera's box pixels;
    c_render_predicted = c_predicted x render_factor (`rendered_std`), that of the rendered
    pixels, each a mean of `spp` samples."""
    from vdo.model.speckle import pixel_averaged_std

    rows, sides = [], []
    half = PHOTOMETRY_WINDOW // 2
    dx, dy = np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1))
    tangents = np.stack([samples.tangent_u, samples.tangent_v], axis=-1)      # (N, 3, 2)
    offset_dn = sensor.offset
    for i, cam in enumerate(cameras):
        clean = noise_free_dn(linear[cam.name], sensor)
        uv = cam.project(samples.points)
        for k, region in enumerate(samples.region_names):
            mask = vis.visible[i] & (samples.region == k)
            row = {"camera": cam.name, "region": region, "n_samples": int(mask.sum())}
            if mask.any():
                col = np.clip(np.rint(uv[mask, 0]).astype(int)[:, None] + dx.ravel(), 0, cam.width - 1)
                r = np.clip(np.rint(uv[mask, 1]).astype(int)[:, None] + dy.ravel(), 0, cam.height - 1)
                values = clean[r, col]                         # (n, window^2)
                level = pho.brightness[i, mask] - offset_dn
                ratio = (values - offset_dn) / level[:, None]
                middle = np.flatnonzero(mask)[mask.sum() // 2]
                A = cam.sensitivity(samples.points[middle:middle + 1]) @ tangents[middle]  # px/m
                sides.append(np.linalg.inv(A[0]))
                row |= {"b_render_dn": values.mean(), "b_predicted_dn": pho.brightness[i, mask].mean(),
                        "c_render_dn": ratio.std() * level.mean(),
                        "c_predicted_dn": pho.contrast[i, mask].mean(),
                        "noise_predicted_dn": pho.noise[i, mask].mean()}
            rows.append(row)
    if sides:
        box = pixel_averaged_std(pattern_normalised, texel, np.array(sides))
        rendered = rendered_std(pattern_normalised, texel, np.array(sides), spp)
        for row, factor, render_factor in zip((r for r in rows if r["n_samples"]), box, rendered):
            row |= {"c_render_predicted_dn": row["c_predicted_dn"] * render_factor,
                    "c_pixel_predicted_dn": row["c_predicted_dn"] * factor,
                    "pixel_factor": factor, "render_factor": render_factor}
    return rows




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
    linear       camera name -> linear float32 radiance image (H, W) before the sensor
    photometry   one row per (camera, region): rendered against predicted brightness and
                 contrast (`region_photometry`, docs/photometry.md)
    seconds      camera name -> render time (s)
    pairs        the stereo pairs of the calibration files (`vdo.formats.export.default_pairs`)
    """

    state: object                 # vdo.state.LayoutState
    scale: float
    spp: int
    seed: int
    images: dict
    linear: dict
    photometry: list
    seconds: dict
    total_seconds: float
    pairs: list

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

    from vdo.formats.export import default_pairs
    from vdo.physics.lighting import photometry
    from vdo.core.progress import bar
    from vdo.state import bodies, layout_state, prepare

    scale, spp, seed = render_settings(exp, scale, spp, seed)
    dic = exp.render.mode == "dic"
    started = time.perf_counter()
    cameras = [scaled_camera(c, scale) for c in cameras_of(exp)]
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
    pattern = geometry.speckle.pattern
    build = build_dic_scene if dic else build_render_scene
    scene = build(exp, list(geometry.meshes), list(geometry.region_faces), bodies(exp, cameras), pattern)
    if dic:
        log.info("rendering %d cameras at scale %g in the dic mode, seed %d", len(chosen), scale, seed)
    else:
        log.info("rendering %d cameras at scale %g, %d spp, seed %d", len(chosen), scale, spp, seed)
    images, linear, seconds = {}, {}, {}
    for i in bar(log, iterable=chosen, desc="render", unit="camera"):
        cam, spec = cameras[i], exp.camera_specs[i]
        t0 = time.perf_counter()
        linear[cam.name] = (render_camera_dic(scene, cam, tile_pixels=plan.tile_pixels) if dic
                            else render_camera(scene, cam, spec, spp, render_seed(seed, i)))
        images[cam.name] = expose(linear[cam.name], exp.sensor, seed, i)
        seconds[cam.name] = time.perf_counter() - t0
    pho = photometry(state.illumination, exp.speckle, exp.sensor, geometry.speckle.mean,
                     geometry.speckle.std, len(chosen))
    rows = region_photometry(list(state.cameras), vis, geometry.samples, pho, linear, exp.sensor,
                             normalise(pattern), exp.speckle.texel, None if dic else spp)
    return RenderResult(state=state, scale=scale, spp=spp, seed=seed, images=images, linear=linear,
                        photometry=rows, seconds=seconds,
                        total_seconds=time.perf_counter() - started, pairs=stereo)


# --------------------------------------------------------------------------------------------
# The DIC render mode: one primary ray per pixel, the speckle averaged over the pixel's footprint
# --------------------------------------------------------------------------------------------
RENDER_MODES = ("sampled", "dic")
SAT_PAD_TEXELS = 64          # texels of wrapped pattern around the tile in the summed-area table;
                             # a footprint is clamped to a half-extent of SAT_PAD_TEXELS - 2
MIN_HALF_TEXELS = 1e-3       # smallest half-width of a footprint box (texels): below it, the box's
                             # corner differences lose digits and its average is the point value
FOOTPRINT_SPLIT = 2          # each pixel's footprint parallelogram is cut into SPLIT x SPLIT parts
LIGHT_POINTS = 8             # midpoint rule of LIGHT_POINTS^2 points on each light panel (a
                             # penumbra moves in steps of 1 / LIGHT_POINTS^2 of the panel)
AMBIENT_POINTS = 8           # AMBIENT_POINTS^2 BSDF-sampled directions for the ambient sky
SHADE_STRIDE = 8             # px between the nodes of the per-camera light map
SHADE_TOLERANCE = 0.03       # a light-map cell whose corner values differ by more than this
                             # fraction (a shadow edge, a panel's rim) is computed at every pixel
EDGE_SUPERSAMPLE = 4         # a pixel whose neighbours see another shape (a silhouette) is the
                             # mean of EDGE_SUPERSAMPLE^2 sub-pixel rays, each with its own footprint
TILE_PIXELS = 1 << 20        # pixels per tile of a DIC-mode render (fewer when memory is short)
MIN_TILE_PIXELS = 1 << 14    # below this a tile's fixed costs dominate: refuse instead
TILE_BYTES_PER_PIXEL = 150   # peak working set of a DIC tile per pixel (115 measured with
                             # ru_maxrss on a 1920 x 1280 plate render, plus a margin)
SAMPLED_BYTES_PER_PIXEL = 80 # Mitsuba's film and wavefront per pixel, any spp (59 measured at
                             # 16 and 64 spp on 614k px, plus a margin)
DISTORTION_BYTES_PER_PIXEL = 48   # the resampling map (H, W, 2) float64 and its spline copies
IMAGE_BYTES_PER_PIXEL = 6    # what render_images keeps per pixel and camera: float32 + 16-bit DN


@dataclass(frozen=True, eq=False)
class SpeckleTable:
    """Summed-area table of a [0, 1] speckle tile for exact box averages of its bilinear texture.

    The texture (`build_render_scene`'s bitmap, bilinear, periodic) in texel coordinates
    x = u W_t, y = v H_t is f = g * box, g(x, y) = pattern[floor y mod H_t, floor x mod W_t] the
    nearest-texel image and box the unit square centred at 0. With G the antiderivative of g
    (bilinear between the integer corners S[j, i] = sum of g over [0, i) x [0, j)), the
    antiderivative of f is H(x, y) = sum_ij S[j, i] B2(x - i) B2(y - j), B2 the quadratic
    B-spline (3 x 3 taps), so that

        ∫∫_[x0, x1] x [y0, y1] f = H(x1, y1) - H(x0, y1) - H(x1, y0) + H(x0, y0)   (texel^2)

    exactly. `table` holds S of g - mean over the tile padded by `pad` wrapped texels
    (row/column k is corner k - pad), so any box whose centre lies in the tile and whose
    half-extent is at most pad - 2 is read without wrapping."""

    table: np.ndarray       # (H_t + 2 pad + 1, W_t + 2 pad + 1) float64
    mean: float
    pad: int
    shape: tuple[int, int]  # (H_t, W_t)

    @classmethod
    def of(cls, pattern, pad: int = SAT_PAD_TEXELS) -> "SpeckleTable":
        g = np.asarray(pattern, dtype=np.float64)
        mean = float(g.mean())
        tiled = np.pad(g - mean, pad, mode="wrap")
        table = np.zeros((tiled.shape[0] + 1, tiled.shape[1] + 1))
        table[1:, 1:] = tiled.cumsum(0).cumsum(1)
        return cls(table, mean, int(pad), g.shape)

    def box_average(self, x0, x1, y0, y1) -> np.ndarray:
        """The mean of the bilinear texture f over the boxes [x0, x1] x [y0, y1] (texels, any
        position: each box is moved by whole tiles to centre it in the tile); numpy reference of
        what the DIC render computes with Dr.Jit."""
        x0, x1, y0, y1 = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (x0, x1, y0, y1)))
        h, w = self.shape
        sx = np.floor((x0 + x1) / 2 / w) * w
        sy = np.floor((y0 + y1) / 2 / h) * h
        total = 0.0
        for xs, ys, sign in ((x1, y1, 1), (x0, y1, -1), (x1, y0, -1), (x0, y0, 1)):
            total = total + sign * self._antiderivative(xs - sx, ys - sy)
        return self.mean + total / ((x1 - x0) * (y1 - y0))

    def _antiderivative(self, x, y):
        rx, ry = np.rint(x), np.rint(y)
        wx, wy = _b2_weights(x - rx), _b2_weights(y - ry)
        ix, iy = rx.astype(np.int64) + self.pad, ry.astype(np.int64) + self.pad
        return sum(wy[a] * wx[b] * self.table[iy + a - 1, ix + b - 1]
                   for a in range(3) for b in range(3))


def _b2_weights(t):
    """Quadratic B-spline weights of the corners round(x) - 1, round(x), round(x) + 1 for
    t = x - round(x) in [-1/2, 1/2]."""
    return (0.5 * (0.5 - t) ** 2, 0.75 - t * t, 0.5 * (0.5 + t) ** 2)


@dataclass(frozen=True, eq=False)
class DicScene:
    """What the DIC render mode needs of an experiment: the render scene with white regions
    (`build_render_scene(white_regions=True)`), the registry ids of the speckled shapes, the
    speckle's summed-area table and tile size, the paint's albedos and the lights."""

    scene: object
    speckled_ids: tuple[int, ...]
    table: SpeckleTable
    tile: tuple[int, int]          # (W_t, H_t) texels of the pattern tile
    black: float
    white: float
    lights: tuple                  # per light (centre, e_u w, e_v h, normal, radiance)
    ambient: float


def build_dic_scene(exp, meshes, region_faces, bodies=(), pattern=None, posed=None) -> DicScene:
    """The `DicScene` of `exp` (arguments as `build_render_scene`)."""
    import drjit as dr

    from vdo.core.backend import mitsuba
    from vdo.physics.lighting import panel_frame

    mi = mitsuba()
    sp = exp.speckle
    pattern = pattern_for(sp) if pattern is None else np.asarray(pattern, dtype=np.float32)
    scene = build_render_scene(exp, meshes, region_faces, bodies, pattern, posed, white_regions=True)
    ids = tuple(int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in scene.shapes()
                if s.id().endswith(SPECKLED_SUFFIX))
    lights = []
    for light in exp.lights:
        n, e1, e2 = panel_frame(light)
        w, h = light.size
        lights.append((np.asarray(light.position, float), e1 * w, e2 * h, n, float(light.radiance)))
    return DicScene(scene, ids, SpeckleTable.of(pattern), (pattern.shape[1], pattern.shape[0]),
                    float(sp.black_albedo), float(sp.white_albedo), tuple(lights),
                    float(exp.render.ambient_radiance))


def available_memory() -> int:
    """Bytes this process may still allocate: MemAvailable of /proc/meminfo (Linux), else the
    physical memory (os.sysconf)."""
    import os

    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


@dataclass(frozen=True)
class RenderPlan:
    """The memory a render needs (`plan_render`): `tile_pixels` per DIC tile, `kept` bytes of
    the finished images, `working` bytes of the largest camera's render, `available` bytes."""

    mode: str
    tile_pixels: int
    kept: int
    working: int
    available: int

    @property
    def needed(self) -> int:
        return self.kept + self.working


def plan_render(cameras, mode: str, available: int | None = None) -> RenderPlan:
    """The memory of rendering `cameras` (already scaled) in `mode`, before anything is rendered:
    every finished image is kept (IMAGE_BYTES_PER_PIXEL per pixel); one camera renders at a time,
    the sampled mode with its whole film (SAMPLED_BYTES_PER_PIXEL, plus
    DISTORTION_BYTES_PER_PIXEL for a distorted camera), the DIC mode in tiles of TILE_PIXELS
    (TILE_BYTES_PER_PIXEL each), split into smaller tiles (down to MIN_TILE_PIXELS) when that
    does not fit in `available` bytes (default `available_memory`). Raises MemoryError with the
    bytes it would need when even that does not fit."""
    available = available_memory() if available is None else int(available)
    kept = sum(c.width * c.height for c in cameras) * IMAGE_BYTES_PER_PIXEL
    tile = TILE_PIXELS
    if mode == "dic":
        room = available - kept
        while tile > MIN_TILE_PIXELS and tile * TILE_BYTES_PER_PIXEL > room:
            tile //= 2
        working = tile * TILE_BYTES_PER_PIXEL
    else:
        working = max((c.width * c.height * (SAMPLED_BYTES_PER_PIXEL
                                             + (DISTORTION_BYTES_PER_PIXEL if c.distorted else 0))
                       for c in cameras), default=0)
    plan = RenderPlan(mode, tile, kept, working, available)
    if plan.needed > available:
        raise MemoryError(f"the render needs {plan.needed / 2 ** 30:.2f} GiB ({kept / 2 ** 30:.2f} GiB "
                          f"of images, {working / 2 ** 30:.2f} GiB to render one camera); "
                          f"{available / 2 ** 30:.2f} GiB available")
    return plan


def render_camera_dic(dscene: DicScene, camera: Camera, progress=None,
                      tile_pixels: int = TILE_PIXELS) -> np.ndarray:
    """One camera's (H, W) float32 linear image in the DIC render mode, in tiles of at most
    `tile_pixels` pixels (whole rows; `plan_render` chooses). Per pixel (u, v) of the (distorted) image:

    * one primary ray through the pinhole pixel p = `Camera.undistorted_pixels`(u, v), with ray
      differentials through p + ∂p/∂u and p + ∂p/∂v (central differences over ±½ px): Mitsuba's
      `compute_uv_partials` gives the footprint's sides a = ∂(x, y)/∂u, b = ∂(x, y)/∂v in texels;
    * on a speckled region, the albedo ρ = ρ_b + (ρ_w - ρ_b) f̄ with f̄ the mean of the bilinear
      texture over the footprint parallelogram c + [-½, ½] a + [-½, ½] b, cut into
      FOOTPRINT_SPLIT^2 parts, each replaced by the axis-aligned box of the same second moments
      (half-widths ½ |(a_x, b_x)| / n and ½ |(a_y, b_y)| / n), averaged exactly with the
      `SpeckleTable` (exact for a footprint aligned with the texture axes);
    * the light reaching the hit (`_shade`: each panel by a LIGHT_POINTS^2 midpoint rule with a
      shadow ray per point, the ambient sky by AMBIENT_POINTS^2 BSDF-sampled directions) from a
      light map per camera: computed at the nodes every SHADE_STRIDE pixels and interpolated
      bilinearly, except in a cell whose corners see another shape than the pixel or differ by more
      than SHADE_TOLERANCE, where it is computed at the pixel;
    * value = emitted radiance seen + ρ × light (white regions: the BSDF's own albedo elsewhere).

    `progress`: called with the number of rows done after each tile."""
    rows = max(1, tile_pixels // camera.width)
    out = np.empty((camera.height, camera.width), dtype=np.float32)
    for r0 in range(0, camera.height, rows):
        r1 = min(camera.height, r0 + rows)
        out[r0:r1] = _dic_tile(dscene, camera, r0, r1)
        if progress is not None:
            progress(r1 - r0)
    return out


def _pixel_grid(u, v) -> np.ndarray:
    return np.stack(np.broadcast_arrays(u[None, :], v[:, None]), axis=-1).reshape(-1, 2)


def _rays(camera: Camera, grid, step: float = 1.0):
    """Mitsuba ray differentials for the (distorted) pixels `grid` ((n, 2) array, or a pair of
    Dr.Jit Floats (u, v)): from the near-clip plane through the pinhole pixel p =
    `Camera.undistorted_pixels`(u, v) and, as differentials, through p + ∂p/∂u and p + ∂p/∂v
    for a step of `step` pixels (central differences over ±step/2 for a distorted camera)."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    M = camera.R.T @ np.linalg.inv(camera.K)          # world direction of a homogeneous pixel

    def direction(x, y):
        return mi.Vector3f(*(float(M[k, 0]) * x + float(M[k, 1]) * y + float(M[k, 2]) for k in range(3)))

    if camera.distorted:
        at = camera.undistorted_pixels
        du, dv = np.array([step / 2, 0.0]), np.array([0.0, step / 2])
        p, pu, pv = at(grid), at(grid + du) - at(grid - du), at(grid + dv) - at(grid - dv)
        px, py, pux, puy, pvx, pvy = (mi.Float(np.ascontiguousarray(a[:, k], dtype=np.float32))
                                      for a in (p, pu, pv) for k in range(2))
    else:
        if isinstance(grid, np.ndarray):
            px, py = (mi.Float(np.ascontiguousarray(grid[:, k], dtype=np.float32)) for k in range(2))
        else:
            px, py = grid
        pux, puy, pvx, pvy = step, 0.0, 0.0, step
    # Each ray starts on the near-clip plane (the camera frame's z = NEAR_CLIP_M, as Mitsuba's
    # perspective sensor), so that a camera's own body around its centre is not hit.
    o = mi.Point3f(*(float(c) for c in camera.position))
    d, d_x, d_y = direction(px, py), direction(px + pux, py + puy), direction(px + pvx, py + pvy)
    ray = mi.RayDifferential3f(o + NEAR_CLIP_M * d, dr.normalize(d))
    ray.o_x, ray.o_y = o + NEAR_CLIP_M * d_x, o + NEAR_CLIP_M * d_y
    ray.d_x, ray.d_y = d_x, d_y
    ray.has_differentials = True
    return ray


def _footprint_albedo(dscene: DicScene, si):
    """ρ at each hit (Dr.Jit Float): the footprint-averaged speckle albedo on the speckled
    shapes (`render_camera_dic`), 1 elsewhere."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    F = mi.Float64
    t = dscene.table
    (wt, ht), pad = dscene.tile, t.pad
    flat = F(np.ascontiguousarray(t.table.ravel()))
    stride = t.table.shape[1]
    x, y = F(si.uv.x) * wt, F(si.uv.y) * ht
    x, y = x - dr.floor(x / wt) * wt, y - dr.floor(y / ht) * ht
    ax, ay = F(si.duv_dx.x) * wt, F(si.duv_dx.y) * ht
    bx, by = F(si.duv_dy.x) * wt, F(si.duv_dy.y) * ht
    extent = dr.maximum(dr.abs(ax) + dr.abs(bx), dr.abs(ay) + dr.abs(by)) / 2
    k = dr.minimum(1.0, (pad - 3) / dr.maximum(extent, 1e-30))        # clamp huge footprints
    ax, ay, bx, by = ax * k, ay * k, bx * k, by * k
    n = FOOTPRINT_SPLIT
    hx = dr.maximum(0.5 * dr.sqrt(ax * ax + bx * bx) / n, MIN_HALF_TEXELS)
    hy = dr.maximum(0.5 * dr.sqrt(ay * ay + by * by) / n, MIN_HALF_TEXELS)

    def antiderivative(px, py):
        rx, ry = dr.round(px), dr.round(py)
        wx, wy = _b2_weights(px - rx), _b2_weights(py - ry)
        ix, iy = mi.Int32(rx) + pad - 1, mi.Int32(ry) + pad - 1
        total = F(0.0)
        for a in range(3):
            row = (iy + a) * stride + ix
            total += wy[a] * (wx[0] * dr.gather(F, flat, row) + wx[1] * dr.gather(F, flat, row + 1)
                              + wx[2] * dr.gather(F, flat, row + 2))
        return total

    acc = F(0.0)
    for i in range(n):
        for j in range(n):
            oi, oj = (i + 0.5) / n - 0.5, (j + 0.5) / n - 0.5
            cx, cy = x + oi * ax + oj * bx, y + oi * ay + oj * by
            acc += (antiderivative(cx + hx, cy + hy) - antiderivative(cx - hx, cy + hy)
                    - antiderivative(cx + hx, cy - hy) + antiderivative(cx - hx, cy - hy))
    f = t.mean + acc / (n * n * 4 * hx * hy)
    rho = dscene.black + (dscene.white - dscene.black) * mi.Float(f)
    shape = dr.reinterpret_array(mi.UInt32, si.shape)
    speckled = mi.Bool(False)
    for sid in dscene.speckled_ids:
        speckled |= shape == sid
    return dr.select(si.is_valid() & speckled, rho, 1.0)


SHADE_LANES = 1 << 19        # (hit, light point) pairs per shadow-ray batch (memory bound)


def _quadrature(dscene: DicScene):
    """The lights' quadrature: points P (Q, 3), panel normals (Q, 3) and weights L A / LIGHT_POINTS^2
    (Q,), LIGHT_POINTS^2 midpoints per panel."""
    q = LIGHT_POINTS
    mid = (np.arange(q) + 0.5) / q - 0.5
    P, N, w = [], [], []
    for c, e1, e2, normal, radiance in dscene.lights:
        for a in mid:
            for b in mid:
                P.append(c + a * e1 + b * e2)
                N.append(normal)
                w.append(radiance * float(np.linalg.norm(np.cross(e1, e2))) / (q * q))
    return np.array(P).reshape(-1, 3), np.array(N).reshape(-1, 3), np.array(w)


def _shade(dscene: DicScene, si) -> np.ndarray:
    """The light reflected towards the camera at each hit ((n,) float64, luminance), the integral
    of `_register_integrator`'s estimator by quadrature: Σ over lights and the LIGHT_POINTS^2
    midpoints P of each panel of f(ω_i, ω_o) cosθ_s L cosθ_l (A / LIGHT_POINTS^2) / r^2 where P is
    visible (shadow ray), plus the ambient sky through AMBIENT_POINTS^2 stratum-centre BSDF
    samples that escape. 0 where the ray missed. Every (hit, point) pair is one lane of a batch
    of at most SHADE_LANES (small kernels, compiled once)."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    n = dr.width(si)
    dr.eval(si)
    P, normals, weights = _quadrature(dscene)
    m = AMBIENT_POINTS if dscene.ambient > 0 else 0
    mid = (np.arange(m) + 0.5) / max(m, 1)
    samples = np.stack(np.meshgrid(mid, mid), -1).reshape(-1, 2)
    Q = len(P) + len(samples)
    out = np.zeros(n)
    if Q == 0:
        return out
    table = [mi.Point3f(*(np.ascontiguousarray(x[:, k]) for k in range(3))) for x in (P, normals)]
    w_light = mi.Float(weights) if len(P) else None
    S = mi.Point2f(*(np.ascontiguousarray(samples[:, k]) for k in range(2))) if m else None
    ctx = mi.BSDFContext()
    chunk = max(1, SHADE_LANES // Q)
    for start in range(0, n, chunk):
        count = min(chunk, n - start)
        total = mi.Float(0.0)
        if len(P):
            lane = dr.arange(mi.UInt32, count * len(P))
            hit = dr.gather(type(si), si, start + lane // len(P))
            k = lane % len(P)
            point, normal = (dr.gather(mi.Point3f, t, k) for t in table)
            d = point - hit.p
            dist2 = dr.squared_norm(d)
            d = d * dr.rsqrt(dist2)
            cos_l = -dr.dot(d, mi.Vector3f(normal))
            ok = hit.is_valid() & (cos_l > 0) & (dr.dot(d, hit.n) > 0)
            ok &= ~dscene.scene.ray_test(hit.spawn_ray_to(point), ok)
            f = hit.bsdf().eval(ctx, hit, hit.to_local(d), ok)
            value = mi.luminance(dr.select(ok, f * (dr.gather(mi.Float, w_light, k) * cos_l / dist2), 0.0))
            total = dr.block_sum(value, len(P))
        if m:
            lane = dr.arange(mi.UInt32, count * len(samples))
            hit = dr.gather(type(si), si, start + lane // len(samples))
            valid = hit.is_valid()
            bs, w = hit.bsdf().sample(ctx, hit, 0.5, dr.gather(mi.Point2f, S, lane % len(samples)), valid)
            ok = valid & (bs.pdf > 0)
            ok &= ~dscene.scene.ray_test(hit.spawn_ray(hit.to_world(bs.wo)), ok)
            value = mi.luminance(dr.select(ok, w * (dscene.ambient / len(samples)), 0.0))
            total = total + dr.block_sum(value, len(samples))
        out[start:start + count] = np.array(total, dtype=np.float64)
    return out


def _cast(dscene: DicScene, camera: Camera, grid, step: float = 1.0):
    """Primary hits (with uv partials over a footprint of `step` pixels) of the pixels `grid`
    (`_rays`)."""
    ray = _rays(camera, grid, step)
    si = dscene.scene.ray_intersect(ray)
    si.compute_uv_partials(ray)
    return si


def _dic_tile(dscene: DicScene, camera: Camera, r0: int, r1: int) -> np.ndarray:
    """Rows r0 .. r1 - 1 of `render_camera_dic`'s image, (r1 - r0, W) float32."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    W, h = camera.width, r1 - r0
    u, v = np.arange(W, dtype=float), np.arange(r0, r1, dtype=float)
    # The light map's nodes: every SHADE_STRIDE px, and the last column and row of the tile.
    s = SHADE_STRIDE
    xs = np.unique(np.r_[np.arange(0, W, s), W - 1]).astype(float)
    ys = np.unique(np.r_[np.arange(r0, r1, s), r1 - 1]).astype(float)
    node_si = _cast(dscene, camera, _pixel_grid(xs, ys))
    node_light = mi.Float(_shade(dscene, node_si))
    node_ids = dr.reinterpret_array(mi.UInt32, node_si.shape)
    dr.eval(node_ids)
    del node_si
    index = dr.arange(mi.UInt32, W * h)
    col, row = index % W, index // W
    pixel = (mi.Float(col), mi.Float(row + r0))
    si = _cast(dscene, camera, _pixel_grid(u, v) if camera.distorted else pixel)
    rho = _footprint_albedo(dscene, si)
    emitted = mi.luminance(si.emitter(dscene.scene).eval(si))
    ids = dr.reinterpret_array(mi.UInt32, si.shape)
    # Bilinear in the cell (nodes cx, cx + 1 and cy, cy + 1; the last cell may be narrower).
    nx, ny = len(xs), len(ys)
    cx = dr.minimum(col // s, max(nx - 2, 0))
    cy = dr.minimum(row // s, max(ny - 2, 0))
    cx1, cy1 = dr.minimum(cx + 1, nx - 1), dr.minimum(cy + 1, ny - 1)
    X, Y = mi.Float(xs), mi.Float(ys - r0)
    x0, x1 = dr.gather(mi.Float, X, cx), dr.gather(mi.Float, X, cx1)
    y0, y1 = dr.gather(mi.Float, Y, cy), dr.gather(mi.Float, Y, cy1)
    fx = dr.select(x1 > x0, (pixel[0] - x0) / dr.maximum(x1 - x0, 1.0), 0.0)
    fy = dr.select(y1 > y0, (mi.Float(row) - y0) / dr.maximum(y1 - y0, 1.0), 0.0)
    corners = [cy * nx + cx, cy * nx + cx1, cy1 * nx + cx, cy1 * nx + cx1]
    L = [dr.gather(mi.Float, node_light, k) for k in corners]
    same = mi.Bool(True)
    for k in corners:
        same &= dr.gather(mi.UInt32, node_ids, k) == ids
    lo = dr.minimum(dr.minimum(L[0], L[1]), dr.minimum(L[2], L[3]))
    hi = dr.maximum(dr.maximum(L[0], L[1]), dr.maximum(L[2], L[3]))
    smooth = same & (hi <= lo * (1 + SHADE_TOLERANCE))
    light = (1 - fy) * ((1 - fx) * L[0] + fx * L[1]) + fy * ((1 - fx) * L[2] + fx * L[3])
    value = emitted + rho * light
    dr.eval(value, smooth, ids, rho, emitted)
    value, smooth = np.array(value, dtype=np.float64), np.array(smooth)
    ids_np = np.array(ids).reshape(h, W)
    rough = np.flatnonzero(~smooth)
    if len(rough):
        grid = np.column_stack([u[rough % W], v[rough // W]])
        value[rough] = (np.array(dr.gather(mi.Float, emitted, mi.UInt32(rough)), dtype=np.float64)
                        + np.array(dr.gather(mi.Float, rho, mi.UInt32(rough)), dtype=np.float64)
                        * _shade(dscene, _cast(dscene, camera, grid)))
    del si
    edges = np.flatnonzero(_silhouette(ids_np))
    if len(edges):
        value[edges] = _supersampled(dscene, camera, np.column_stack([u[edges % W], v[edges // W]]))
    return value.astype(np.float32).reshape(h, W)


def _silhouette(ids: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels with a 4-neighbour (within the tile) that sees another shape."""
    out = np.zeros(ids.shape, dtype=bool)
    dy, dx = ids[1:] != ids[:-1], ids[:, 1:] != ids[:, :-1]
    out[1:] |= dy
    out[:-1] |= dy
    out[:, 1:] |= dx
    out[:, :-1] |= dx
    return out


def _supersampled(dscene: DicScene, camera: Camera, grid: np.ndarray) -> np.ndarray:
    """(n,) the mean of EDGE_SUPERSAMPLE^2 sub-pixel values (stratum centres, each ray with the
    footprint of its stratum, its albedo and its light computed at the ray) of the pixels `grid`."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    k = EDGE_SUPERSAMPLE
    mid = (np.arange(k) + 0.5) / k - 0.5
    offsets = np.stack(np.meshgrid(mid, mid), -1).reshape(-1, 2)
    sub = (grid[:, None, :] + offsets[None]).reshape(-1, 2)
    si = _cast(dscene, camera, sub, 1.0 / k)
    value = mi.luminance(si.emitter(dscene.scene).eval(si)) * 1.0
    rho = _footprint_albedo(dscene, si)
    dr.eval(value, rho)
    total = np.array(value, dtype=np.float64) + np.array(rho, dtype=np.float64) * _shade(dscene, si)
    return total.reshape(len(grid), k * k).mean(axis=1)
