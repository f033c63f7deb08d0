"""What the cameras' hardware does to the scene, judged by the optimizer at start-up and on its
result: the mesh points clearances are measured to (`surface_points`), each body's clearance
(`clearances`, m), the light the bodies take from each region (`light_lost`) and the ray cast
against the obstacles alone (`obstacle_visibility`, the obscuration check)."""

from __future__ import annotations

import logging

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from vdo.physics.visibility import Visibility, compute_visibility
from vdo.scene import build_scene, camera_body
from vdo.state import bodies


def _spread(tm, count: int) -> np.ndarray:
    """Up to `count` points spread evenly over the surface of `tm` (trimesh's rejection sampling,
    seed 0). It returns fewer than asked where it rejects points too close to others, and logs a
    warning for that; fewer is what the callers want (points about evenly spaced), so the
    warning is kept off the user's console."""
    sampler = logging.getLogger("trimesh.sample")
    level = sampler.level
    sampler.setLevel(logging.ERROR)
    try:
        return trimesh.sample.sample_surface_even(tm, count, seed=0)[0]
    finally:
        sampler.setLevel(level)


def surface_points(meshes, spacing: float) -> np.ndarray:
    """Points on every mesh surface about `spacing` apart (plus the vertices), for clearance."""
    pts = []
    for m in meshes:
        tm = m.trimesh
        count = int(min(max(tm.area / spacing**2, 100), 200_000))
        pts += [_spread(tm, count), m.vertices]
    return np.vstack(pts)


def clearances(cameras, tree) -> np.ndarray:
    """Distance (m) from each camera body to the nearest mesh point and to the other bodies."""
    bodies = [camera_body(c) for c in cameras]
    dense = [_spread(b.trimesh, 400) for b in bodies]
    out = np.array([tree.query(d)[0].min() for d in dense])
    for i, di in enumerate(dense):
        for j, dj in enumerate(dense):
            if i != j:
                out[i] = min(out[i], cKDTree(dj).query(di)[0].min())
    return out


def light_lost(lit_without_cameras, lit, samples) -> np.ndarray:
    """Per region, the area fraction where the camera bodies hide more than 1 % of a light:
    `lit_without_cameras` and `lit` (L, N) the light each sample gets without and with the bodies
    (None: no light, nothing lost)."""
    if lit_without_cameras is None:
        return np.zeros(len(samples.region_names))
    lost = ((lit_without_cameras - lit) > 0.01).any(axis=0)
    return np.array([(samples.area[(samples.region == r) & lost]).sum() / samples.area[samples.region == r].sum()
                     for r in range(len(samples.region_names))])


def obstacle_visibility(geometry, cameras) -> Visibility:
    """The ray cast of `cameras` against the obstacles alone (machine, mounts, camera bodies and
    tripods, not the specimen): what hides a region that the specimen itself does not (the
    obscuration check)."""
    exp = geometry.experiment
    obstacles = build_scene([m for m in geometry.meshes if m.role != "specimen"] + bodies(exp, cameras))
    return compute_visibility(obstacles, cameras, geometry.samples, exp.evaluation.incidence_limit,
                              progress=False)
