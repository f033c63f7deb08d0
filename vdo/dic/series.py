"""A virtual test as an image series: `vdo render CONFIG --series [POSES.csv] --out DIR`.

Step 0 is the reference state (the meshes as configured); every step of the load path
(`vdo.geometry.keyframes`) moves mesh groups rigidly and, when the experiment's `[load_path]` names a
displacement file (a CSV, or the FE model's VTK `.vtu`/`.vtp`/`.pvd`), deforms the specimen. With a POSES.csv the poses come from that file (one row
per step and group, the `vdo.geometry.keyframes` format; every mesh is also a group of its own name);
without it, from the experiment's `[load_path]`. The speckle moves with the surface (texture
coordinates from the rest vertices, `vdo.render.build_render_scene`); lights and camera bodies
stay.

With `[render] mode = "dic"` every image is rendered in the DIC render mode
(`vdo.render.render_camera_dic`: no Monte Carlo noise at all, docs/render.md); otherwise every
image is rendered without the sampler's jitter (`vdo.render.render_camera`, as
`vdo.dic.validate` renders): each pixel is the fixed sqrt(spp) x sqrt(spp) midpoint rule of its box
and the lights' sampling is stratified the same way, with the same Mitsuba seed per camera at
every step. A jittered render adds Monte Carlo noise that differs from image to image and is no
part of the camera (measured on the built-in joint: 34 DN at 16 spp against a sensor noise of
16 DN, docs/exports.md), so a correlation of the series would measure the renderer, not the
design; without jitter the images of two steps differ by the motion and the sensor noise only
(and a deterministic quadrature error of a few DN that moves with the pixel grid).

The run folder (atomic, `vdo.core.runfolder`), written by `vdo.commands.series` image by image as
`series_images` renders them (a long series is never held in memory):

    images/<camera>/<camera>_<step:04d>.tif  16-bit TIFF (DN, the sensor's bit depth), step 0000
                                             the reference; sensor noise drawn independently per
                                             image, generator default_rng([seed, camera, step])
    images/<camera>/<camera>_<step:04d>.exr  the linear float radiance before the sensor, when
                                             [render] exr = true
    calibration/<format>/                    the cameras for DIC software (`vdo.formats`)
    layout.json, config.toml, poses.csv (when given), series.json
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vdo.core.errors import ConfigError
from vdo.core.runfolder import is_file
from vdo.scene import cameras_of

if TYPE_CHECKING:   # annotations only: the heavy modules are imported where they are used
    from vdo.config.experiment import Experiment
    from vdo.geometry.keyframes import LoadPath
    from vdo.model.camera import Camera
    from vdo.state import Geometry

log = logging.getLogger(__name__)
SERIES_LIGHT_SPP = 64   # below this the sampled mode's fixed light points draw shadows as bands


@dataclass(frozen=True)
class SeriesImage:
    """One image of a series: the (scaled) camera, the step (0: the reference), the sensor's
    image in DN (H, W) and the linear radiance before the sensor (H, W)."""

    camera: Camera
    step: int
    dn: np.ndarray
    linear: np.ndarray


@dataclass(frozen=True)
class SeriesPlan:
    """Everything a series needs before its first image (`plan_series`): the experiment, the
    poses file (None: the experiment's [load_path]), the render settings (scale, spp, seed, DIC
    mode and its tile size), the prepared geometry and load path, the scaled cameras and the
    camera bodies, the stereo pairs of the calibration files, the interpolation floor per camera
    and region at this scale (`_interpolation_at_scale`), the steps (0 and the load path's) and
    when the work began (`time.perf_counter()`, for series.json's total_seconds). Its images
    come one at a time from `series_images`."""

    experiment: Experiment
    poses_path: Path | None
    scale: float
    spp: int
    seed: int
    dic: bool                      # [render] mode = "dic"
    tile_pixels: int | None        # the DIC render's tile (`vdo.render.plan_render`)
    geometry: Geometry
    load_path: LoadPath
    cameras: list[Camera]
    obstacles: list
    stereo: list                   # `vdo.formats.export.StereoPair`s
    no_pair: str                   # without a pair, why and the fix (`no_pair_message`); else ""
    interpolation: list[dict]      # per camera and region, `_interpolation_at_scale`
    steps: list[int]
    started: float

    def to_json(self) -> dict:
        """series.json, with total_seconds counted from `started` to now."""
        return {"experiment": self.experiment.name, "config": str(self.experiment.path),
                "poses": None if self.poses_path is None else str(self.poses_path),
                "scale": self.scale, "spp": self.spp, "seed": self.seed, "jitter": False, "steps": self.steps,
                "cameras": [c.name for c in self.cameras],
                "stereo_pairs": [[pair.first.name, pair.second.name] for pair in self.stereo],
                "interpolation": self.interpolation,
                "total_seconds": round(time.perf_counter() - self.started, 3)}


def plan_series(exp, poses_path=None, scale: float | None = None, spp: int | None = None,
                seed: int | None = None, pairs=None) -> SeriesPlan:
    """The `SeriesPlan` of rendering step 0 and every step of the load path for every camera
    (module docstring). `scale`, `spp`, `seed` default to the config's [render] section; `pairs`:
    the stereo pairs of the calibration files as (first, second) names (default: cameras
    assigned a common region), checked to share a field of view before anything is rendered.
    Bad input is refused (`ConfigError`) before the geometry is prepared."""
    from vdo.formats.export import default_pairs, no_pair_message
    from vdo.geometry.keyframes import load_path_of
    from vdo.render import plan_render, render_settings, scaled_camera
    from vdo.state import bodies, layout_state, prepare

    rs = exp.render
    scale = rs.scale if scale is None else float(scale)
    spp = rs.spp if spp is None else int(spp)
    seed = rs.seed if seed is None else int(seed)
    if not (0 < scale <= 4) or spp < 1 or seed < 0:
        raise ConfigError(exp.path, "--scale/--spp/--seed", "need 0 < scale <= 4, spp >= 1, seed >= 0")
    render_settings(exp, scale, spp, seed)                 # the mode, depth of field
    dic = rs.mode == "dic"
    if not dic and exp.lights and spp < SERIES_LIGHT_SPP:
        log.warning("a series in the sampled mode has no jitter: every pixel samples each light at the "
                    "same %d points, so a thin occluder (a tripod leg, a bar) casts %d hard-edged shadow "
                    "bands instead of one soft one; [render] mode = \"dic\" (the light integrated) or "
                    "spp >= %d", spp, spp, SERIES_LIGHT_SPP)
    try:
        plan = plan_render([scaled_camera(c, scale) for c in cameras_of(exp.camera_specs, exp.rails)],
                           rs.mode)
    except MemoryError as err:
        raise ConfigError(exp.path, "[render] scale", f"{err}: lower scale, or render fewer cameras") from None
    if poses_path is not None and not is_file(poses_path):
        raise ConfigError(poses_path, "--series", "no such file: give a CSV of poses per step and "
                                                  "group (see vdo.geometry.keyframes)")
    started = time.perf_counter()
    geometry = prepare(exp)
    load_path = load_path_of(geometry.meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                             groups=exp.groups, poses=poses_path)
    if load_path is None:
        raise ConfigError(exp.path, "load_path", "a series needs poses: give --series POSES.csv or "
                                                 "a [load_path] in the experiment")
    cameras = [scaled_camera(c, scale) for c in cameras_of(exp.camera_specs, exp.rails)]
    obstacles = bodies(exp, cameras)
    state = layout_state(geometry, cameras, predict_fields=False)
    vis = state.visibility
    stereo = default_pairs(exp, cameras, vis, geometry.samples, pairs)
    no_pair = "" if stereo else no_pair_message(exp, cameras, vis, geometry.samples)
    floor = _interpolation_at_scale(exp, cameras, state, scale)
    return SeriesPlan(experiment=exp, poses_path=poses_path, scale=scale, spp=spp, seed=seed, dic=dic,
                      tile_pixels=plan.tile_pixels, geometry=geometry, load_path=load_path, cameras=cameras,
                      obstacles=obstacles, stereo=stereo, no_pair=no_pair, interpolation=floor,
                      steps=[0, *load_path.steps], started=started)


def series_images(plan: SeriesPlan) -> Iterator[SeriesImage]:
    """The images of a series, step by step (the scene posed once per step) and camera by camera,
    one at a time, so that the caller writes each before the next is rendered: DIC render mode
    (`vdo.render.render_camera_dic`) or the sampled render without jitter, the camera's own
    Mitsuba seed at every step; the sensor noise drawn with default_rng([seed, camera, step])."""
    from vdo.geometry.keyframes import at_step
    from vdo.physics.lighting import exposure_factors
    from vdo.render import (build_dic_scene, build_render_scene, render_camera, render_camera_dic,
                            map_holds, render_seed, surface_light_map)

    exp, geometry, seed = plan.experiment, plan.geometry, plan.seed
    gathered = exposure_factors(exp.camera_specs, exp.sensor)
    # the DIC mode's surface light maps, per camera (posed meshes, map): each camera's own (a map
    # shared by the cameras is as fine as the nearest one's, over surfaces the others do not see,
    # `vdo.render.render_images`), reused by the steps whose geometry it holds (`map_holds`:
    # micrometre deformation, not a rigid move by millimetres)
    maps = [[] for _ in plan.cameras]
    for step in plan.steps:
        posed = geometry.meshes if step == 0 else at_step(geometry, plan.load_path, step,
                                                          regions=exp.regions).meshes
        build = build_dic_scene if plan.dic else build_render_scene
        scene = build(exp, geometry.meshes, geometry.region_faces, plan.obstacles,
                      geometry.speckle.pattern, posed)
        for i, (cam, spec) in enumerate(zip(plan.cameras, exp.camera_specs)):
            light_map = None
            if plan.dic:
                light_map = next((m for at, m in maps[i] if map_holds(at, posed)), None)
                if light_map is None:
                    light_map = surface_light_map(scene, [cam])
                    maps[i].append((posed, light_map))
            linear = (render_camera_dic(scene, cam, tile_pixels=plan.tile_pixels, spec=spec,
                                        light_map=light_map)
                      if plan.dic else
                      render_camera(scene, cam, spec, plan.spp, render_seed(seed, i), jitter=False))
            if gathered[i] != 1.0:      # the light this camera's f-number and exposure time gather
                linear = linear * np.float32(gathered[i])
            dn = exp.sensor.expose(linear, np.random.default_rng([seed, i, step]))
            yield SeriesImage(camera=cam, step=step, dn=dn, linear=linear)


def _interpolation_at_scale(exp, cameras, state, scale: float) -> list[dict]:
    """Per camera and region at the rendered `scale` (`cameras` scaled): `vdo.physics.checks`'
    interpolation floor, {camera, region, mm_per_px, error_dn, noise_dn, ratio}; a warning names
    the worst pair when some exceed `checks.INTERPOLATION_NOISE` (correlation on these images is
    then bias-dominated, docs/exports.md)."""
    from vdo.physics import checks

    rows = [{"camera": r["camera"], "region": r["region"], "mm_per_px": r["mm_per_px"], **r["interpolation"]}
            for r in checks.design_checks(exp.camera_specs, exp.evaluation, exp.speckle, exp.sensor,
                                          exp.analysis, cameras, state.samples,
                                          state.visibility.visible, state.illumination.irradiance,
                                          state.geometry.speckle.pattern)
            if r["interpolation"] is not None]
    flagged = [r for r in rows if r["ratio"] > checks.INTERPOLATION_NOISE]
    if flagged:
        worst = max(flagged, key=lambda r: r["ratio"])
        log.warning("at render scale %g the correlation's interpolation error exceeds %g x the sensor "
                    "noise on %d of %d camera-region pairs (worst: %s on %s, %.1f x at %.2f mm/px): "
                    "displacements measured on these images will be bias-dominated; render at the "
                    "cameras' own pixels (--scale 1) for a virtual test", scale, checks.INTERPOLATION_NOISE,
                    len(flagged), len(rows), worst["camera"], worst["region"], worst["ratio"], worst["mm_per_px"])
    return rows


def correlate_series(folder, step: int, camera_names, points, tangent_u, tangent_v,
                     patch_size: float, start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The displacement (N, 3) m that vdo's own correlation measures at `points` (N, 3) between
    the TIFF images of step 0 and `step` of a series folder, with the cameras `camera_names` of
    its layout.json (at least two: a stereo pair or more); `correlate_points` does the measuring
    (`start`: as there, e.g. the previous step's result). Returns (U, converged (N,) bool)."""
    cameras = series_cameras(folder, camera_names)
    references = [series_image(folder, n, 0) for n in camera_names]
    deformed = [series_image(folder, n, step) for n in camera_names]
    return correlate_points(cameras, references, deformed, points, tangent_u, tangent_v, patch_size,
                            start=start)


def series_cameras(folder, camera_names) -> list:
    """The cameras `camera_names` (at least two) of a series folder's layout.json."""
    from vdo.formats.export import camera_from_layout

    layout = Path(folder) / "layout.json"
    entries = {e["name"]: e for e in json.loads(layout.read_text())["cameras"]}
    missing = [n for n in camera_names if n not in entries]
    if missing or len(camera_names) < 2:
        raise ConfigError(layout, "cameras", f"need at least two of its cameras ({', '.join(entries)}); "
                                             f"got {', '.join(camera_names)}")
    return [camera_from_layout(entries[n], layout) for n in camera_names]


def series_image(folder, name: str, step: int, linear: bool = False) -> np.ndarray:
    """Camera `name`'s image of `step` in a series folder, float64 (H, W): the TIFF's DN, or with
    `linear` the radiance of its .exr ([render] exr = true)."""
    path = Path(folder) / "images" / name / f"{name}_{step:04d}.{'exr' if linear else 'tif'}"
    if not path.is_file():
        raise ConfigError(path, "images", "no such image in the series folder"
                          + (" (render it with [render] exr = true)" if linear else ""))
    if linear:
        from vdo.core.backend import mitsuba

        image = np.array(mitsuba().Bitmap(str(path)), dtype=np.float64)
        return image.reshape(image.shape[0], image.shape[1])
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im, dtype=np.float64)


def correlate_points(cameras, references, deformed, points, tangent_u, tangent_v,
                     patch_size: float, workers: int = 1, batched: bool = True,
                     start: np.ndarray | None = None, subset_px: int | None = None,
                     shape_function: str = "affine") -> tuple[np.ndarray, np.ndarray]:
    """The displacement (N, 3) m that vdo's own correlation (`vdo.dic.correlate`, as `vdo.dic.validate`
    uses it: each camera against its own reference image, integrated on its reference pixel
    centres, B-spline interpolation of windows around the patches) measures at `points` (N, 3)
    from the `references` to the `deformed` images (gray levels, one per camera): per point a
    square patch of side `patch_size` (m) in the plane of (tangent_u, tangent_v) centred on it, a
    bilinear (Q4, one element) field so that the patch may stretch and turn, read at the patch
    centre (the mean of its four nodes), starting from `start` (N, 3) m where it is given and
    finite (a lab's incremental tracking: the previous load step's result), else from
    `start_guesses`.

    With `subset_px`, subset DIC as a lab's stereo software runs it instead
    (`vdo.dic.icgn.correlate_subsets_2d`): per camera a square subset of that many pixels around
    the point's image, matched in 2D with `shape_function` ("affine" or "zero") by IC-GN, each
    camera started from its own whole-pixel shift where `start` is not given, the cameras on
    `workers` threads, and their matched points triangulated (patch_size, the tangents and
    `batched` unused).

    `batched` (default): all points at once (`vdo.dic.subsets.correlate_subsets`, the same
    iteration vectorised over the points), shared among `workers` threads. Otherwise one
    `correlate` call per point (the reference implementation), the points shared among `workers`
    processes (spawned: Dr.Jit and JAX do not survive a fork), each given the images once, in
    contiguous chunks (neighbouring points, one image window).
    Returns (U, converged (N,) bool)."""
    points, tangent_u, tangent_v = (np.asarray(a, dtype=float) for a in (points, tangent_u, tangent_v))
    n = len(points)
    workers = max(1, min(int(workers), n))
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    U0 = np.full((n, 3), np.nan) if start is None else np.array(start, dtype=float).reshape(n, 3)
    guess = ~np.isfinite(U0).all(axis=1)
    if subset_px is None and guess.any():
        U0[guess] = start_guesses(cameras, references, deformed, points[guess], workers=workers)
    if subset_px is not None:      # its windows' heap is reused call after call: kept (measured
        from vdo.dic.icgn import correlate_subsets_2d     # in benchmarks/README.md)

        U, converged, _ = correlate_subsets_2d(cameras, references, deformed, points, U0,
                                               size_px=subset_px, shape_function=shape_function,
                                               workers=workers)
        return U, converged
    if batched:
        from vdo.core.memory import release_freed_memory
        from vdo.dic.subsets import correlate_subsets

        result = correlate_subsets(cameras, references, deformed, points, tangent_u, tangent_v,
                                   patch_size, U0, workers=workers)
        release_freed_memory()        # the windows' and splines' buffers (vdo.core.memory)
        return result.centre, result.converged
    if workers == 1:
        return _correlate_chunk(cameras, references, deformed, points, tangent_u, tangent_v, patch_size, U0)
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    chunks = np.array_split(np.arange(n), workers * POOL_CHUNKS_PER_WORKER)
    out, converged = np.zeros((n, 3)), np.zeros(n, bool)
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_pool_start, initargs=(cameras, references, deformed)) as pool:
        jobs = {pool.submit(_pool_chunk, points[k], tangent_u[k], tangent_v[k], patch_size, U0[k]): k
                for k in chunks if len(k)}
        for job, k in jobs.items():
            out[k], converged[k] = job.result()
    return out, converged


POOL_CHUNKS_PER_WORKER = 4      # chunks per process: the slowest chunk's wait stays short
_POOL = {}                      # a pool process's cameras and images (`_pool_start`)


def _pool_start(cameras, references, deformed):
    from vdo.core.configure import configure

    configure()
    _POOL.update(cameras=cameras, references=references, deformed=deformed)


def _pool_chunk(points, tangent_u, tangent_v, patch_size, U0):
    return _correlate_chunk(_POOL["cameras"], _POOL["references"], _POOL["deformed"], points,
                            tangent_u, tangent_v, patch_size, U0)


def _correlate_chunk(cameras, references, deformed, points, tangent_u, tangent_v, patch_size, U0):
    from vdo.dic.correlate import ImageReference, Q4, correlate
    from vdo.dic.patch import Patch

    half = patch_size / 2
    out, converged = np.zeros((len(points), 3)), np.zeros(len(points), bool)
    for k, (X, t_u, t_v) in enumerate(zip(points, tangent_u, tangent_v)):
        patch = Patch(origin=X - half * t_u - half * t_v, t_u=t_u, t_v=t_v, size=(patch_size, patch_size))
        result = correlate(cameras, deformed, patch, ImageReference(references), model=Q4(1, 1),
                           U0=np.tile(U0[k], (4, 1)))
        out[k] = result.U.mean(axis=0)
        converged[k] = result.converged
    return out, converged




def start_guesses(cameras, references, deformed, points, half: int = 24, workers: int = 1) -> np.ndarray:
    """`start_guess` (N, 3) m for every point of `points` (N, 3): the whole-pixel shifts of all
    points whose windows lie whole inside every image per camera (`vdo.dic.shifts.image_shifts`
    on `workers` threads, each window's numbers as `start_guess` takes them), the others one at
    a time."""
    from vdo.dic.shifts import image_shifts

    points = np.asarray(points, dtype=float).reshape(-1, 3)
    whole = np.full(len(points), len(cameras) >= 2)     # fewer: `start_guess` answers 0
    shifts = np.zeros((len(points), 2 * len(cameras)))
    for i, (cam, ref, dfm) in enumerate(zip(cameras, references, deformed)):
        uv = np.rint(cam.project(points)).astype(int)
        u, v = uv[:, 0], uv[:, 1]
        whole &= np.minimum.reduce([u, v, cam.width - 1 - u, cam.height - 1 - v]) >= half
        centres = np.stack([np.clip(u, half, cam.width - 1 - half), np.clip(v, half, cam.height - 1 - half)], -1)
        shifts[:, 2 * i:2 * i + 2] = image_shifts(ref, dfm, centres, half, workers)
    S = np.concatenate([np.asarray(cam.sensitivity(points)) for cam in cameras], axis=1)
    U0 = np.einsum("kij,kj->ki", np.linalg.pinv(S), shifts)
    for k in np.flatnonzero(~whole):
        U0[k] = start_guess(cameras, references, deformed, points[k], half)
    return U0


def start_guess(cameras, references, deformed, X, half: int = 24) -> np.ndarray:
    """A starting displacement (3,) m at the world point X for the Gauss-Newton correlation (whose
    basin is about a speckle dot): per camera the whole-pixel image shift d_i of a (2 half + 1)^2
    window around X's image (smaller near the image border), the peak of the phase correlation (normalised cross-power spectrum),
    then the least-squares 3D motion with s_i U = d_i (s_i = dx/dX, `Camera.sensitivity`)."""
    rows, rhs = [], []
    for cam, ref, dfm in zip(cameras, references, deformed):
        u, v = np.rint(cam.project(X[None])[0]).astype(int)
        h = min(half, u, v, cam.width - 1 - u, cam.height - 1 - v)     # the window inside the image
        if h < 8:
            continue
        window = np.s_[v - h:v + h + 1, u - h:u + h + 1]
        taper = np.outer(*(2 * [np.hanning(2 * h + 1)]))
        a, b = ((img[window] - img[window].mean()) * taper for img in (ref, dfm))
        spectrum = np.fft.fft2(b) * np.conj(np.fft.fft2(a))
        peak = np.unravel_index(np.argmax(np.fft.ifft2(spectrum).real), a.shape)
        dv, du = ((k + n // 2) % n - n // 2 for k, n in zip(peak, a.shape))
        rows.append(np.asarray(cam.sensitivity(X[None]))[0])
        rhs.append([du, dv])
    if len(rows) < 2:
        return np.zeros(3)
    return np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
