"""Which camera sees which surface sample: the geometric tests and the ray cast.

A camera i sees a sample X (normal n) when all of these hold:

* in front:    Z_c = (R X + t)_z > 0;
* in image:    its pixel (u, v) (lens distortion included) lies on the sensor, -0.5 <= u <= W - 0.5
               and -0.5 <= v <= H - 0.5;
* facing:      the incidence angle between n and C - X is below the experiment's limit,
               i.e. n . (C - X) > cos(limit) |C - X|;
* unoccluded:  the segment from X (lifted by `EPSILON` along n) to the optical centre C hits no
               shape of the scene: the specimen itself, obstacles, other cameras' bodies.

All (camera, sample) pairs are evaluated in Dr.Jit kernels (single precision, vectorised over
all CPU threads), and a ray is traced only for the pairs that pass the first three tests. Doing
the geometric tests in numpy and casting rays per camera was 3x slower (benchmarks/README.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vdo.core.backend import mitsuba
from vdo.core.progress import shown_bar
from vdo.model.camera import Camera, image_point
from vdo.scene import SurfaceSamples
from vdo.core.tolerances import IN_FRONT_M, RAY_OFFSET_M

EPSILON = RAY_OFFSET_M   # m: ray origins are lifted off the surface by this, and stop this short of C


@dataclass(frozen=True, eq=False)
class Visibility:
    """Per (camera, sample) test results, each (n_cameras, n_samples) booleans."""

    camera_names: tuple[str, ...]
    in_front: np.ndarray
    in_image: np.ndarray
    facing: np.ndarray
    unoccluded: np.ndarray     # False where a geometric test already failed (no ray was cast)

    @property
    def visible(self) -> np.ndarray:
        return self.in_front & self.in_image & self.facing & self.unoccluded

    @property
    def coverage(self) -> np.ndarray:
        """Number of cameras that see each sample."""
        return self.visible.sum(axis=0)


def incidence_angles(camera: Camera, samples: SurfaceSamples) -> np.ndarray:
    """Angle (rad) between each sample's normal and its direction to the camera, float64."""
    to_cam = camera.position - samples.points
    cross = np.linalg.norm(np.cross(samples.normals, to_cam), axis=1)
    return np.arctan2(cross, np.einsum("ij,ij->i", samples.normals, to_cam))


def _camera_table(cameras: list[Camera]) -> np.ndarray:
    """One row per camera: R (9), t (3), f, cx, cy, W, H, C (3), distortion (5)."""
    return np.array([np.concatenate([c.R.ravel(), c.t, [c.focal_px, *c.principal_point, c.width,
                                                        c.height], c.position, c.distortion])
                     for c in cameras])


def compute_visibility(scene, cameras: list[Camera], samples: SurfaceSamples,
                       incidence_limit: float, progress: bool = True,
                       batch_pairs: int = 8_000_000) -> Visibility:
    """All four tests for every (camera, sample) pair, in batches of `batch_pairs` pairs."""
    import drjit as dr

    mi = mitsuba()
    n_cam, n = len(cameras), len(samples)
    table = mi.Float(np.ascontiguousarray(_camera_table(cameras), dtype=np.float32).ravel())
    points = mi.Float(np.ascontiguousarray(samples.points, dtype=np.float32).ravel())
    normals = mi.Float(np.ascontiguousarray(samples.normals, dtype=np.float32).ravel())
    cols = _camera_table(cameras).shape[1]
    cos_limit = float(np.cos(incidence_limit))
    flags = np.zeros(n_cam * n, dtype=np.uint8)

    def gather3(array, index):
        return mi.Vector3f(*(dr.gather(mi.Float, array, index * 3 + k) for k in range(3)))

    starts = range(0, n_cam * n, batch_pairs)
    for start in shown_bar(bool(progress) and len(starts) >= 2, iterable=starts, desc="visibility",
                           unit="batch", leave=False):
        pair = dr.arange(mi.UInt32, start, min(start + batch_pairs, n_cam * n))
        cam = pair // n
        sample = pair - cam * n
        col = [dr.gather(mi.Float, table, cam * cols + k) for k in range(cols)]
        X, nrm = gather3(points, sample), gather3(normals, sample)
        p = mi.Vector3f(*(col[3 * r] * X.x + col[3 * r + 1] * X.y + col[3 * r + 2] * X.z + col[9 + r]
                          for r in range(3)))
        f, cx, cy, width, height = col[12:17]
        centre = mi.Point3f(*col[17:20])
        in_front = p.z > IN_FRONT_M
        z = dr.select(in_front, p.z, 1.0)
        u, v = image_point((f, None, cx, f, cy), p.x / z, p.y / z, tuple(col[20:25]))
        in_image = in_front & (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)
        origin = X + EPSILON * nrm
        to_cam = centre - origin
        dist = dr.norm(to_cam)
        facing = dr.dot(nrm, centre - X) > cos_limit * dr.norm(centre - X)
        ray = mi.Ray3f(origin, to_cam / dist)
        ray.maxt = dr.maximum(dist - EPSILON, 0.0)
        candidate = in_image & facing
        hit = scene.ray_test(ray, candidate)
        bits = (dr.select(in_front, 1, 0) + dr.select(in_image, 2, 0) + dr.select(facing, 4, 0)
                + dr.select(candidate & ~hit, 8, 0))
        flags[start:start + len(bits)] = np.asarray(mi.UInt32(bits), dtype=np.uint8)
    flags = flags.reshape(n_cam, n)
    return Visibility(tuple(c.name for c in cameras), in_front=(flags & 1) > 0,
                      in_image=(flags & 2) > 0, facing=(flags & 4) > 0, unoccluded=(flags & 8) > 0)
