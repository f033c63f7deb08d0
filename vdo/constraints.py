"""Practical constraints on a camera layout (paper sec. 3): smooth penalties for the optimizer in
JAX, and exact checks for the report.

* axis angle:   two cameras assigned a common region keep their optical axes at least a minimum
                angle apart; by default the stereo-DIC rule of thumb for the shorter lens of the
                two: 35 deg up to 12 mm, 25 deg at 17 mm, 15 deg from 35 mm, linear in between;
* obscuration:  no obstacle (bars, machine, lights, other camera bodies) masks more than
                `max_obscuration` of an assigned region's image (`vdo.obscuration` differentiates
                it through Mitsuba; the report counts blocked rays);
* field of view: an assigned region stays inside the image;
* clearance:    camera bodies keep `clearance` metres from every mesh and from each other;
* rails, horizontality: by construction of the parameters (u = sigmoid(z) in (0, 1), roll held);
* shadows:      camera bodies do not shadow the regions from the lights (lights are not variables,
                so this is checked, not optimized).

A camera is *assigned* the regions of which it sees at least `assign_fraction` of the area in the
starting layout: what the person who placed it by hand meant it to watch.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .camera import project
from .scene import SurfaceSamples
from .visibility import Visibility


def stereo_min_angle(focal_length: float) -> float:
    """Rule-of-thumb minimum angle (rad) between the optical axes of a stereo pair with this lens
    (m): 35 deg for 8-12 mm, 25 deg at 17 mm, 15 deg from 35 mm, linear in between."""
    f_mm = focal_length * 1e3
    return math.radians(float(np.interp(f_mm, [12.0, 17.0, 35.0], [35.0, 25.0, 15.0])))


def assignments(vis: Visibility, samples: SurfaceSamples, fraction: float) -> np.ndarray:
    """(C, R) True where camera c sees at least `fraction` of region r's area."""
    n_regions = len(samples.region_names)
    seen = np.zeros((len(vis.camera_names), n_regions))
    for r in range(n_regions):
        mask = samples.region == r
        area = samples.area[mask]
        seen[:, r] = (vis.visible[:, mask] * area).sum(axis=1) / area.sum()
    return seen >= fraction


def shared_pairs(assigned: np.ndarray) -> np.ndarray:
    """(K, 2) camera pairs i < j assigned at least one common region."""
    n = len(assigned)
    return np.array([(i, j) for i in range(n) for j in range(i + 1, n)
                     if (assigned[i] & assigned[j]).any()], dtype=int).reshape(-1, 2)


# --------------------------------------------------------------------------------------------
# Smooth penalties (JAX); each is 0 when the constraint holds, and grows quadratically
# --------------------------------------------------------------------------------------------
def axis_angle_penalty(axes, pairs, min_angles):
    """Σ_k (max(0, cos a_k - cos m_k) / (1 - cos m_k))^2 over the pairs, a_k the angle between
    the optical axes (unit rows of `axes`, (C, 3)) and m_k the minimum."""
    if len(pairs) == 0:
        return 0.0
    cos_a = jnp.sum(axes[pairs[:, 0]] * axes[pairs[:, 1]], axis=-1)
    cos_m = jnp.cos(jnp.asarray(min_angles))
    return jnp.sum((jnp.maximum(cos_a - cos_m, 0.0) / (1.0 - cos_m)) ** 2)


def fov_penalty(K, R, t, width, height, points, mask):
    """Σ over cameras of the mean squared distance, in hundredths of the image width, by which
    the assigned region points (C, M, 3) with `mask` (C, M) fall outside the image."""
    uv = project(K[:, None], R[:, None], t[:, None], points)
    u, v = uv[..., 0], uv[..., 1]
    w, h = width[:, None], height[:, None]
    out = (jnp.maximum(-0.5 - u, 0) + jnp.maximum(u - (w - 0.5), 0)
           + jnp.maximum(-0.5 - v, 0) + jnp.maximum(v - (h - 0.5), 0)) / (0.01 * w)
    count = jnp.maximum(mask.sum(axis=1), 1)
    return jnp.sum(jnp.sum(jnp.where(mask, out ** 2, 0.0), axis=1) / count)


def body_points_world(local_points, R, position):
    """(C, B, 3) world positions of each camera's body points (camera frame, (C, B, 3))."""
    return jnp.einsum("cji,cbj->cbi", R, local_points) + position[:, None, :]


def clearance_penalty(body_world, near_points, clearance: float):
    """Σ (max(0, clearance - d) / clearance)^2 over body points, d the distance to the nearest
    mesh point of that camera's neighbourhood (`near_points` (C, Q, 3), padded with far points),
    and over pairs of cameras, d the closest distance between their body points."""
    if clearance <= 0:
        return 0.0
    d2 = jnp.sum((body_world[:, :, None, :] - near_points[:, None, :, :]) ** 2, -1)
    d_scene = jnp.sqrt(jnp.min(d2, -1) + 1e-12)
    total = jnp.sum((jnp.maximum(clearance - d_scene, 0.0) / clearance) ** 2)
    n = body_world.shape[0]
    if n > 1:
        diff = body_world[:, None, :, None, :] - body_world[None, :, None, :, :]
        d_cam = jnp.sqrt(jnp.min(jnp.sum(diff ** 2, -1), axis=(-2, -1)) + 1e-12)
        off = ~jnp.eye(n, dtype=bool)
        total = total + 0.5 * jnp.sum(jnp.where(off, (jnp.maximum(clearance - d_cam, 0.0) / clearance) ** 2, 0.0))
    return total


def near_points(points: np.ndarray, paths: list[np.ndarray], reach: float) -> np.ndarray:
    """(C, Q, 3): for each camera, the mesh points within `reach` of its path (the points its
    optical centre can take: a sampled rail, or its fixed position), padded to a common Q with a
    point far away (1 km) that never binds."""
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    chosen = []
    for path in paths:
        idx = sorted(set().union(*tree.query_ball_point(np.atleast_2d(path), reach)))
        chosen.append(points[idx])
    q = max(1, max(len(c) for c in chosen))
    out = np.full((len(paths), q, 3), 1e3)
    for c, pts in enumerate(chosen):
        out[c, :len(pts)] = pts
    return out


# --------------------------------------------------------------------------------------------
# Exact checks for the report
# --------------------------------------------------------------------------------------------
def check(cameras, vis: Visibility, samples: SurfaceSamples, assigned: np.ndarray,
          pairs: np.ndarray, min_angles: np.ndarray, clearances: np.ndarray, clearance: float,
          max_obscuration: float, lost_light: np.ndarray, rails_u: list,
          roll_free: bool = False) -> list[dict]:
    """One entry per constraint instance: name, what it concerns, value, limit, met.

    `clearances` (C,) is the measured distance from each body to everything else (m),
    `lost_light` (R,) the fraction of each region's area where camera bodies block light."""
    out = []
    for (i, j), limit in zip(pairs, min_angles):
        angle = math.degrees(math.acos(np.clip(cameras[i].optical_axis @ cameras[j].optical_axis, -1, 1)))
        out.append(dict(constraint="axis_angle", cameras=[cameras[i].name, cameras[j].name],
                        value=angle, limit=math.degrees(limit), unit="deg", met=bool(angle >= math.degrees(limit) - 1e-6)))
    geometric = vis.in_front & vis.in_image & vis.facing
    facing = vis.in_front & vis.facing
    for c, cam in enumerate(cameras):
        for r in np.flatnonzero(assigned[c]):
            mask = samples.region == r
            area = samples.area[mask]
            region = samples.region_names[r]
            in_view = geometric[c, mask]
            blocked = float((area * (in_view & ~vis.unoccluded[c, mask])).sum() / max((area * in_view).sum(), 1e-30))
            out.append(dict(constraint="obscuration", cameras=[cam.name], region=region, value=blocked,
                            limit=max_obscuration, unit="fraction of the region's image", met=blocked <= max_obscuration))
            faces = facing[c, mask]
            inside = float((area * (faces & vis.in_image[c, mask])).sum() / max((area * faces).sum(), 1e-30))
            out.append(dict(constraint="field_of_view", cameras=[cam.name], region=region, value=inside,
                            limit=1 - max_obscuration, unit="fraction of the region in the image",
                            met=inside >= 1 - max_obscuration))
        out.append(dict(constraint="clearance", cameras=[cam.name], value=float(clearances[c]),
                        limit=clearance, unit="m", met=bool(clearances[c] >= clearance)))
        if not roll_free:
            out.append(dict(constraint="horizontal", cameras=[cam.name], value=math.degrees(cam.roll),
                            limit=0.0, unit="deg roll", met=abs(cam.roll) < 1e-9))
        if rails_u[c] is not None:
            out.append(dict(constraint="on_rail", cameras=[cam.name], value=float(rails_u[c]),
                            limit=[0.0, 1.0], unit="u", met=0.0 <= rails_u[c] <= 1.0))
    for r, lost in enumerate(lost_light):
        out.append(dict(constraint="no_shadow_from_cameras", region=samples.region_names[r],
                        value=float(lost), limit=0.0, unit="fraction of the region losing light",
                        met=bool(lost <= 1e-3)))
    return out
