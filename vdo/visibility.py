"""Which camera sees which surface sample: the geometric tests and the ray cast.

A camera i sees a sample X (normal n) when all of these hold:

* in front:    Z_c = (R X + t)_z > 0;
* in image:    its pixel (u, v) lies on the sensor, -0.5 <= u <= W - 0.5 and -0.5 <= v <= H - 0.5;
* facing:      the incidence angle acos(n . (C - X)/|C - X|) is below the experiment's limit;
* unoccluded:  the segment from X (lifted by `EPSILON` along n) to the optical centre C hits no
               shape of the scene: the specimen itself, obstacles, other cameras' bodies.

Rays are cast only for the pairs that pass the first three tests, in one Mitsuba `ray_test` batch
per camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from .backend import mitsuba
from .camera import Camera
from .scene import SurfaceSamples

EPSILON = 1e-4   # m: ray origins are lifted off the surface by this, and stop this short of C


@dataclass(frozen=True, eq=False)
class Visibility:
    """Per (camera, sample) test results, each (n_cameras, n_samples)."""

    camera_names: tuple[str, ...]
    in_front: np.ndarray
    in_image: np.ndarray
    facing: np.ndarray
    unoccluded: np.ndarray     # False where a geometric test already failed (no ray was cast)
    incidence: np.ndarray      # rad
    pixels: np.ndarray         # (n_cameras, n_samples, 2)

    @property
    def visible(self) -> np.ndarray:
        return self.in_front & self.in_image & self.facing & self.unoccluded

    @property
    def coverage(self) -> np.ndarray:
        """Number of cameras that see each sample."""
        return self.visible.sum(axis=0)


def geometric_tests(camera: Camera, samples: SurfaceSamples, incidence_limit: float):
    """(in_front, in_image, facing, incidence, pixels) of one camera for all samples."""
    p_cam = samples.points @ camera.R.T + camera.t
    in_front = p_cam[:, 2] > 1e-6
    z = np.where(in_front, p_cam[:, 2], 1.0)
    fx = camera.focal_px
    cx, cy = camera.principal_point
    pixels = np.stack([fx * p_cam[:, 0] / z + cx, fx * p_cam[:, 1] / z + cy], axis=1)
    in_image = (in_front & (pixels[:, 0] >= -0.5) & (pixels[:, 0] <= camera.width - 0.5)
                & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= camera.height - 0.5))
    to_cam = camera.position - samples.points
    cos_inc = np.einsum("ij,ij->i", to_cam, samples.normals) / np.linalg.norm(to_cam, axis=1)
    incidence = np.arccos(np.clip(cos_inc, -1.0, 1.0))
    return in_front, in_image, incidence < incidence_limit, incidence, pixels


def unoccluded(scene, origins: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """True where the segment origin -> target (shortened by EPSILON) hits nothing in `scene`."""
    mi = mitsuba()
    if len(origins) == 0:
        return np.zeros(0, dtype=bool)
    d = targets - origins
    dist = np.linalg.norm(d, axis=1)
    d = d / dist[:, None]
    ray = mi.Ray3f(mi.Point3f(*(np.ascontiguousarray(c, dtype=np.float32) for c in origins.T)),
                   mi.Vector3f(*(np.ascontiguousarray(c, dtype=np.float32) for c in d.T)))
    ray.maxt = mi.Float(np.maximum(dist - EPSILON, 0.0).astype(np.float32))
    return ~np.asarray(scene.ray_test(ray), dtype=bool)


def compute_visibility(scene, cameras: list[Camera], samples: SurfaceSamples,
                       incidence_limit: float, progress: bool = True) -> Visibility:
    """All tests for every camera against every sample (module docstring)."""
    n_cam, n = len(cameras), len(samples)
    shape = (n_cam, n)
    out = {k: np.zeros(shape, dtype=bool) for k in ("in_front", "in_image", "facing", "unoccluded")}
    incidence = np.zeros(shape)
    pixels = np.zeros(shape + (2,))
    lifted = samples.points + EPSILON * samples.normals
    for i, cam in enumerate(tqdm(cameras, desc="visibility", unit="camera", disable=not progress,
                                 leave=False)):
        front, image, facing, incidence[i], pixels[i] = geometric_tests(cam, samples, incidence_limit)
        out["in_front"][i], out["in_image"][i], out["facing"][i] = front, image, facing
        candidates = np.flatnonzero(front & image & facing)
        targets = np.broadcast_to(cam.position, (len(candidates), 3))
        out["unoccluded"][i, candidates] = unoccluded(scene, lifted[candidates], targets)
    return Visibility(tuple(c.name for c in cameras), incidence=incidence, pixels=pixels, **out)
