"""What the cameras' hardware does to the scene, judged by the optimizer at start-up and on its
result and by `vdo design` on its candidates: the mesh points clearances are measured to
(`surface_points`, every CLEARANCE_SPACING m), the points spread on each body (`body_points`),
each body's clearance (`clearances`, m; `keep_clear`, the same measure as a filter), the light
the bodies take from each region (`light_lost`; `light_shadowers`: which bodies, which lights) and the ray cast against the obstacles alone
(`obstacle_visibility`, the obscuration check).

One measure of clearance: the least distance from BODY_POINTS points spread on the body's surface
to the mesh points. Both point sets are samples of the surfaces, so the measure can exceed the
true surface-to-surface distance by up to about the two sets' point spacings; design's filter and the layout's check read the same
measure, so a candidate kept by the one is never broken by the other."""

from __future__ import annotations

import logging
from functools import lru_cache

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from vdo.physics.visibility import Visibility, compute_visibility
from vdo.scene import build_scene, camera_body_local
from vdo.state import bodies

CLEARANCE_SPACING = 0.015   # m between the mesh points clearances are measured to
BODY_POINTS = 400           # points spread on each camera body's surface for its clearance


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


@lru_cache(maxsize=None)
def body_points(focal_length: float) -> np.ndarray:
    """(B, 3) points, B <= BODY_POINTS, spread evenly on the body's surface in the camera frame
    (`vdo.scene.camera_body_local`; read-only). World points: X = x_c R + C (R the camera's
    world-to-camera rotation, C its optical centre)."""
    pts = _spread(camera_body_local(focal_length), BODY_POINTS)
    pts.setflags(write=False)
    return pts


def _world_body_points(camera) -> np.ndarray:
    return body_points(float(camera.focal_length)) @ camera.R + camera.position


def keep_clear(cameras, tree, clearance: float) -> np.ndarray:
    """bool (len(cameras),): each body at least `clearance` (m) from every point of `tree` (the
    `clearances` measure without the other bodies). A camera whose optical centre is farther than
    clearance + its body's reach from every point is clear without looking at its body."""
    reach = {f: float(np.linalg.norm(body_points(f), axis=1).max())
             for f in {float(c.focal_length) for c in cameras}}
    out = np.ones(len(cameras), dtype=bool)
    for f, r in reach.items():
        of = [i for i, c in enumerate(cameras) if float(c.focal_length) == f]
        centres = np.array([cameras[i].position for i in of], dtype=float).reshape(-1, 3)
        near = np.isfinite(tree.query(centres, distance_upper_bound=clearance + r)[0])
        for i in np.asarray(of)[near]:
            gap = tree.query(_world_body_points(cameras[i]), distance_upper_bound=clearance)[0]
            out[i] = bool(np.all(gap >= clearance))
    return out


def clearances(cameras, tree) -> np.ndarray:
    """Distance (m) from each camera body to the nearest mesh point and to the other bodies."""
    dense = [_world_body_points(c) for c in cameras]
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


def light_shadowers(geometry, cameras, unobstructed, lost_light, limit: float) -> dict:
    """{region index: (cameras, lights)} for each region whose `lost_light` (R,) is above `limit`:
    the cameras whose own body (and tripod) hides more than 1 % of a light on some of the region's
    samples (`light_lost`'s measure), and those lights, each in the experiment's order. Each
    camera's bodies are cast alone (`vdo.physics.lighting.relight` from `unobstructed`, the
    lighting without any camera), so the names are what to move; a shadow that only two bodies
    together cast names neither."""
    from vdo.physics.lighting import relight

    exp, samples = geometry.experiment, geometry.samples
    failing = [r for r, lost in enumerate(lost_light) if lost > limit]
    out = {r: ([], []) for r in failing}
    if not failing or not exp.lights:
        return out
    hit = np.zeros((len(cameras), len(exp.lights), len(failing)), dtype=bool)
    for c, cam in enumerate(cameras):
        occluders = bodies(exp, [cam])
        if not occluders:
            continue
        lit = relight(build_scene(list(geometry.meshes) + occluders), exp.lights, samples, unobstructed,
                      [b.vertices for b in occluders]).lit
        lost = (unobstructed.lit - lit) > 0.01                                   # (L, N)
        for k, r in enumerate(failing):
            hit[c, :, k] = lost[:, samples.region == r].any(axis=1)
    for k, r in enumerate(failing):
        out[r] = ([cam.name for c, cam in enumerate(cameras) if hit[c, :, k].any()],
                  [light.name for l, light in enumerate(exp.lights) if hit[:, l, k].any()])
    return out


def obstacle_visibility(geometry, cameras) -> Visibility:
    """The ray cast of `cameras` against the obstacles alone (machine, mounts, camera bodies and
    tripods, not the specimen): what hides a region that the specimen itself does not (the
    obscuration check)."""
    exp = geometry.experiment
    obstacles = build_scene([m for m in geometry.meshes if m.role != "specimen"] + bodies(exp, cameras))
    return compute_visibility(obstacles, cameras, geometry.samples, exp.evaluation.incidence_limit,
                              progress=False)
