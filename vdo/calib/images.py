"""The calibration images: the target at every pose, rendered through each camera that sees it
with the experiment's lights, sensor, noise and lens distortion, and written as a lab's
calibration software reads them.

The scene (`target_scene`) is the target alone under the experiment's [[light]] panels and ambient
light (`vdo.render.lit_scene`): a lab calibrates before the specimen is mounted. The target is a
grid mesh of the printed sheet (`Target.albedo_image` as a nearest-texel bitmap, raw albedo),
bowed towards the print side by [calibration] flatness_mm at its centre,
z = -flatness (1 - rho^2 / rho_max^2) in the target frame (rho from the pattern centre, rho_max
the sheet's half diagonal): the calibration still assumes a flat target, so the bow shows as a
calibration error.

Each (camera, pose) is rendered once without sensor noise (`vdo.render.render_camera`, stratum
centres: a deterministic midpoint rule), at the render scale (`vdo.render.scaled_camera`); each
trial exposes it with the sensor (`SensorModel.expose`, generator
default_rng([seed, trial, camera index, pose])), so Monte Carlo trials cost no render.

Written (`write`): images/<camera>/pose_<k>.png|.tif (k the pose index, shared by every camera
that sees it, so that stereo software pairs the files by name) and target.yml
(`vdo.calib.target.description_yaml`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from vdo.calib.session import Session
from vdo.calib.target import Target
from vdo.scene import cameras_of

log = logging.getLogger(__name__)
MESH_CELLS = 16    # grid cells per side of the target mesh (resolves the flatness bow)


def target_mesh(target: Target, pose, flatness: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (n, 3) world, faces (m, 3), uv (n, 2)) of the printed sheet at `pose`, bowed by
    `flatness` (module docstring); faces wound so that the normal is the print side (-z)."""
    low, high = target.extent
    n = MESH_CELLS + 1
    x, y = np.meshgrid(np.linspace(low[0], high[0], n), np.linspace(low[1], high[1], n))
    rho2 = (x - target.centre[0]) ** 2 + (y - target.centre[1]) ** 2
    rho_max2 = ((high - low) ** 2).sum() / 4
    z = -flatness * (1.0 - rho2 / rho_max2)
    local = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=-1)
    uv = np.stack([(x.ravel() - low[0]) / (high[0] - low[0]),
                   (y.ravel() - low[1]) / (high[1] - low[1])], axis=-1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)])
    return pose.world(local), faces, uv


def target_scene(exp, target: Target, pose, flatness: float):
    """The Mitsuba scene of the target at `pose` under the experiment's lights."""
    from vdo.core.backend import mitsuba
    from vdo.render import lit_scene
    from vdo.scene import SceneMesh, mitsuba_mesh

    mi = mitsuba()
    vertices, faces, uv = target_mesh(target, pose, flatness)
    bsdf = mi.load_dict({"type": "diffuse", "reflectance": {
        "type": "bitmap", "bitmap": mi.Bitmap(target.albedo_image()[..., None]), "raw": True,
        "wrap_mode": "clamp", "filter_type": "nearest"}})
    mesh = mitsuba_mesh(SceneMesh("target", "render", vertices, faces), bsdf, uv)
    return lit_scene(exp, {"target": mesh})


@dataclass(frozen=True, eq=False)
class SessionImages:
    """The noise-free renders of a session: `linear[(camera name, pose index)]` (H, W) float32
    radiance, `cameras` the cameras at the render scale (same order as the experiment's)."""

    session: Session
    cameras: tuple
    linear: dict
    scale: float
    spp: int
    seconds: float

    def exposed(self, sensor, seed: int, trial: int) -> dict:
        """One trial's noisy DN images, {(camera, pose): image} (module docstring)."""
        index = {c.name: i for i, c in enumerate(self.cameras)}
        return {(name, k): sensor.expose(image, np.random.default_rng([seed, trial, index[name], k]))
                for (name, k), image in self.linear.items()}


def render_session(exp, session: Session, scale: float, spp: int, deadline: float | None = None) -> SessionImages:
    """Render every (camera, pose) the session's views list (module docstring); progress on the
    `vdo.calib.images` logger; `deadline` (time.monotonic) stops with TimeoutError."""
    from vdo.core.progress import bar
    from vdo.render import render_camera, render_seed, scaled_camera

    started = time.perf_counter()
    cameras = tuple(scaled_camera(c, scale) for c in cameras_of(exp.camera_specs, exp.rails))
    specs = {s.name: s for s in exp.camera_specs}
    jobs = sorted(((i, cam, k) for i, cam in enumerate(cameras) for k in session.views[cam.name]),
                  key=lambda job: (job[2], job[0]))     # pose by pose: one scene per pose
    linear = {}
    scenes = {}
    for i, cam, k in bar(log, iterable=jobs, desc="calibration images", unit="image"):
        if deadline is not None and time.monotonic() > deadline:
            raise TimeoutError(f"the calibration renders ran past the time limit after {len(linear)} "
                               f"of {len(jobs)} images")
        if k not in scenes:
            scenes = {k: target_scene(exp, session.target, session.poses[k], exp.calibration.flatness)}
        linear[(cam.name, k)] = render_camera(scenes[k], cam, specs[cam.name], spp,
                                              render_seed(k, i), jitter=False)
    return SessionImages(session=session, cameras=cameras, linear=linear, scale=scale, spp=spp,
                         seconds=time.perf_counter() - started)


def write(images: dict, session: Session, folder, sensor, image_format: str, alignment: str) -> list:
    """images/<camera>/pose_<k>.<ext> and target.yml into `folder` (module docstring); returns
    the image paths."""
    from pathlib import Path

    from vdo.calib.target import description_yaml
    from vdo.core.runfolder import inside
    from vdo.model.sensor import save_image

    folder = Path(folder)
    suffix = {"png": ".png", "tiff": ".tif"}[image_format]
    written = []
    for (name, k), dn in sorted(images.items()):
        sub = inside(folder / "images", name)
        sub.mkdir(parents=True, exist_ok=True)
        written.append(save_image(sub / f"pose_{k:03d}{suffix}", dn, sensor.bit_depth, alignment))
    (folder / "target.yml").write_text(description_yaml(session.target))
    return written
