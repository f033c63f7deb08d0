"""Reachability: before optimizing, can the mounts give each region the cameras it needs?

For each region of interest and each camera, a coarse sweep of the poses its mount allows: a
rail at `positions` evenly spaced values of u, a zone at a grid of round(sqrt(positions))
values along each axis with an extent (3 by default: faces, edges, corners and centre; over a
floor polygon its corners and centroid at those heights), a fixed mount (or a
camera that does not move) at its configured position; at every position the camera is aimed
at the region's centre (its area-weighted centroid; roll 0) with its own lens; and each camera's
own configured pose (a band's centroid can lie inside the specimen, off every view: trial 4's
weld-toe band, 14 % from the sweep against 96 % from the hand layout). The ray cast
(`vdo.physics.visibility`: in front, in the image, below the incidence limit, not occluded by the
specimen, the machine or the lights; the other camera bodies are left out, since they move too)
gives which samples each pose sees. A sample counts as reachable by a camera when some pose of
that camera sees it; the region's best coverage is the area fraction of its samples reachable by
at least `min_cameras` cameras. That is an upper bound on what any layout can reach (the poses
for different samples need not be one pose), up to the sweep's coarseness.

`check` returns one entry per region and logs a warning naming the region and the mounts where
the best coverage is below `[optimize] assign_fraction` (default 0.5).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from vdo.model.pose import look_at_angles
from vdo.config.experiment import Experiment
from vdo.scene import SurfaceSamples, build_scene, cameras_of
from vdo.physics.visibility import compute_visibility

log = logging.getLogger(__name__)


def mount_positions(exp: Experiment, spec, camera, moving: bool, positions: int = 9) -> tuple[str, np.ndarray]:
    """(mount label, (K, 3) optical centres in metres) the sweep tries for one camera."""
    if moving and spec.rail is not None:
        return f"rail {spec.rail}", exp.rail(spec.rail).point(np.linspace(0, 1, positions)) + spec.offset
    if moving and spec.mount is not None and exp.mount(spec.mount).kind == "zone":
        zone = exp.mount(spec.mount)
        per_axis = max(2, round(positions ** (1 / 2)))
        axes = [np.linspace(lo, hi, per_axis if hi > lo else 1) for lo, hi in zip(zone.low, zone.high)]
        if zone.floor is not None:   # the corners (a hair inside) and the centroid, at each height
            centre = zone.floor.mean(axis=0)      # (those of the corners and holes' corners on the floor)
            corners = np.vstack([zone.floor, *(zone.floor_holes or ())])
            floor = np.vstack([corners + 1e-3 * (centre - corners), centre])
            floor = floor[zone.inside(floor)]
            return f"zone {spec.mount}", np.array([[*xy, z] for xy in floor for z in axes[2]])
        return f"zone {spec.mount}", np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    label = f"fixed mount {spec.mount}" if spec.mount else "fixed position"
    return label, np.asarray(camera.position, dtype=float)[None]


def _subset(samples: SurfaceSamples, mask: np.ndarray) -> SurfaceSamples:
    per_sample = ("points", "normals", "tangent_u", "tangent_v", "uv", "area", "region")
    return dataclasses.replace(samples, **{k: getattr(samples, k)[mask] for k in per_sample})


def check(exp: Experiment, meshes, samples: SurfaceSamples, positions: int = 9) -> list[dict]:
    """Per region: name, min_cameras, best coverage (area fraction, module docstring), the
    cameras that can see some of it and their mounts, and whether it falls short (below
    `assign_fraction`); each shortfall is logged as a warning."""
    cameras = cameras_of(exp.camera_specs, exp.rails)
    moving = set(exp.optimize.cameras or [c.name for c in cameras])
    sweeps = [mount_positions(exp, spec, cam, cam.name in moving and "u" in exp.optimize.free, positions)
              for spec, cam in zip(exp.camera_specs, cameras)]
    scene = build_scene(list(meshes))
    out = []
    for r, (name, spec) in enumerate(zip(samples.region_names, exp.regions)):
        mask = samples.region == r
        sub = _subset(samples, mask)
        centre = (sub.points * sub.area[:, None]).sum(0) / sub.area.sum()
        poses, owner = [], []
        for c, (cam, (_, centres)) in enumerate(zip(cameras, sweeps)):
            poses.append(cam)                   # as configured
            owner.append(c)
            for p in centres:
                if np.linalg.norm(centre - p) > 1e-6:
                    poses.append(cam.with_pose(p, *look_at_angles(p, centre), 0.0))
                    owner.append(c)
        vis = compute_visibility(scene, poses, sub, exp.evaluation.incidence_limit, progress=False)
        seen = np.zeros((len(cameras), len(sub)), dtype=bool)
        np.logical_or.at(seen, np.array(owner), np.asarray(vis.visible, dtype=bool))
        need = spec.min_cameras
        count = seen.sum(axis=0)
        best = float((sub.area * (count >= need)).sum() / sub.area.sum())
        seers = [c for c in range(len(cameras)) if seen[c].any()]
        entry = dict(region=name, min_cameras=need, best_coverage=best,
                     cameras=[cameras[c].name for c in seers],
                     mounts=sorted({sweeps[c][0] for c in seers}),
                     short=best < exp.optimize.assign_fraction)
        if entry["short"]:
            entry["message"] = (
                f'region "{name}": at most {100 * best:.0f} % of its area can be seen by '
                f"{need} cameras at once from the poses tried on the mounts "
                f"({', '.join(sorted({s[0] for s in sweeps}))}: {positions} per mount aimed at the "
                "region's centre, and the configured ones); "
                + ((f"only {', '.join(entry['cameras'])} ({', '.join(entry['mounts'])}) see any of it"
                    if len(seers) < len(cameras) else "every camera sees some of it")
                   if seers else "no camera sees any of it")
                + ": add a mount or a camera that can see it, or lower its min_cameras")
            log.warning(entry["message"])
        out.append(entry)
    return out

