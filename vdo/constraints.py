"""Practical constraints on a camera layout (paper sec. 3): smooth penalties for the optimizer in
JAX, and exact checks for the report.

* axis angle:   two cameras that share a region (`sharing`: both assigned it, or most of what
                the one sees of it the other sees too) keep their optical axes at least a minimum
                angle apart; by default the stereo-DIC rule of thumb for the shorter lens of the
                two: 35 deg up to 12 mm, 25 deg at 17 mm, 15 deg from 35 mm, linear in between;
                and at most a maximum where one is set: `[optimize] max_axis_angle_deg` for every
                such pair and a region's max_axis_angle_deg for the pairs sharing it (default none:
                a global multi-view layout has no upper limit), and for each declared
                `[[stereo_pair]]` its own [min_angle_deg, max_angle_deg] (default
                max: the minimum + 20 deg, e.g. 15-35 deg for 35 mm lenses), `angle_limits`;
* obscuration:  no obstacle (bars, machine, lights, other camera bodies) masks more than
                `max_obscuration` of an assigned region's image (`vdo.search.obscuration` differentiates
                it through Mitsuba; the report counts blocked rays);
* field of view: an assigned region keeps in the image at least what the hand layout had of it
                (minus 1 %, and at most 1 - max_obscuration is required);
* clearance:    camera bodies keep `clearance` metres from every mesh and from each other;
* keep-out:     no optical centre inside a `[[keep_out]]` box (counted with the clearance);
* floor:        a camera on a zone whose floor is not convex (a ring, an L, a floor with holes)
                stands over it, its optical centre inside the outline and out of the holes
                (`floor_penalty`, counted with the clearance; `floor_checks`); a box or a convex
                floor holds its cameras by construction;
* tripods:      no tripod leg inside a keep-out box, and two tripods' legs the clearance apart
                (`tripod_penalty`, counted with the clearance; `tripod_checks`);
* rails, horizontality: by construction of the parameters (u = sigmoid(z) in (0, 1), or z mod 1 on
                a closed rail; roll held);
* shadows:      camera bodies do not shadow the regions from the lights (lights are not variables:
                the bodies keep off the rays from the lit samples to the panels).

A camera is *assigned* the regions of which it sees at least `assign_fraction` of the area in the
starting layout: what the person who placed it by hand meant it to watch.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from vdo.geometry.obstacles import segment_distance
from vdo.model.camera import image_point, to_camera
from vdo.objective import smoothstep
from vdo.scene import SurfaceSamples
from vdo.physics.visibility import Visibility
from vdo.core.tolerances import CHECK_MET_REL, IN_FRONT_M, LIMIT_SLACK, SMOOTH_SQRT, TINY

if TYPE_CHECKING:
    from vdo.config.procedure import OptimizeSpec, StereoPairSpec
    from vdo.config.rig import RegionSpec

SHADOW_LIMIT = 1e-3   # largest fraction of a region's area where the camera bodies may hide light
                      # (more than 1 % of a light: `vdo.search.obstruction.light_lost`)

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


def sharing(vis: Visibility, samples: SurfaceSamples, fraction: float) -> np.ndarray:
    """(C, C, R) True where cameras i != j share region r: both are assigned it (`assignments`),
    or the area of r that both see is at least `fraction` of the smaller of the areas of r that
    each sees. The second rule forms the pairs of an all-round layout: around a closed surface
    (a ring, a nozzle) no camera sees `fraction` of the region, so none is assigned it, yet
    neighbours see the same part of it; two cameras facing each other across it see disjoint
    parts and share nothing."""
    visible = np.asarray(vis.visible, dtype=float)
    assigned = assignments(vis, samples, fraction)
    C, R = len(visible), len(samples.region_names)
    out = np.zeros((C, C, R), dtype=bool)
    for r in range(R):
        mask = samples.region == r
        seen = visible[:, mask] * samples.area[mask]          # (C, N_r) area each camera sees
        common = seen @ visible[:, mask].T                     # (C, C) area both see
        alone = np.diag(common)
        smaller = np.minimum(alone[:, None], alone[None, :])
        out[:, :, r] = (assigned[:, None, r] & assigned[None, :, r]) | (
            (smaller > 0) & (common >= fraction * smaller))
    out[np.arange(C), np.arange(C)] = False
    return out


def shared_pairs(assigned: np.ndarray) -> np.ndarray:
    """(K, 2) camera pairs i < j assigned at least one common region."""
    n = len(assigned)
    return np.array([(i, j) for i in range(n) for j in range(i + 1, n)
                     if (assigned[i] & assigned[j]).any()], dtype=int).reshape(-1, 2)


# --------------------------------------------------------------------------------------------
# Smooth penalties (JAX); each is 0 when the constraint holds, and grows quadratically
# --------------------------------------------------------------------------------------------
def axis_angle_penalty(axes, pairs, min_angles, max_angles=None):
    """Σ_k (max(0, cos a_k - cos m_k) / (1 - cos m_k))^2 + (max(0, cos M_k - cos a_k) /
    (1 - cos M_k))^2 over the pairs, a_k the angle between the optical axes (unit rows of
    `axes`, (C, 3)), m_k the minimum and M_k the maximum (rad; +inf or None: no maximum, the
    second term is then 0)."""
    if len(pairs) == 0:
        return 0.0
    cos_a = jnp.sum(axes[pairs[:, 0]] * axes[pairs[:, 1]], axis=-1)
    cos_m = jnp.cos(jnp.asarray(min_angles))
    total = jnp.sum((jnp.maximum(cos_a - cos_m, 0.0) / (1.0 - cos_m)) ** 2)
    if max_angles is None:
        return total
    # M >= pi (or +inf) bounds nothing: cos M = -1 <= cos a, so that term is exactly 0 (traceable)
    cos_M = jnp.cos(jnp.minimum(jnp.asarray(max_angles, dtype=float), jnp.pi))
    over = jnp.maximum(cos_M - cos_a, 0.0) / (1.0 - cos_M)
    return total + jnp.sum(over ** 2)


def angle_limits(regions: tuple[RegionSpec, ...], optimize: OptimizeSpec,
                 stereo_pairs: tuple[StereoPairSpec, ...], cameras, assigned: np.ndarray,
                 shared: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pairs (K, 2), min_angles (K,), max_angles (K,)) in rad: the pairs of cameras that share a
    region (`shared` (C, C, R), `sharing`; without it, the pairs assigned a common region:
    `assigned` (C, R), `shared_pairs`) with [optimize] min_axis_angle_deg (or the
    rule of thumb for the shorter lens) and as maximum the least of [optimize]
    max_axis_angle_deg and the max_axis_angle_deg of the regions they share (+inf when none is
    set); then the declared [[stereo_pair]]s, added when not shared and overriding the limits
    when they are (min: the pair's, or the rule of thumb; max: the pair's, or that minimum +
    STEREO_SPAN_DEG). The tables: [[region]], [optimize] and the declared `stereo_pairs`
    ([[stereo_pair]])."""
    from vdo.config.procedure import STEREO_SPAN_DEG

    opt = optimize
    index = {c.name: i for i, c in enumerate(cameras)}
    rule = lambda i, j: stereo_min_angle(min(cameras[i].focal_length, cameras[j].focal_length))
    region_max = np.array([math.inf if r.max_axis_angle is None else r.max_axis_angle
                           for r in regions])
    top = math.inf if opt.max_axis_angle is None else opt.max_axis_angle
    limits = {}
    if shared is None:
        shared = np.asarray(assigned)[:, None, :] & np.asarray(assigned)[None, :, :]
    for i, j in zip(*np.nonzero(np.triu(shared.any(axis=-1), 1))):
        common = shared[i, j]
        limits[(int(i), int(j))] = (opt.min_axis_angle if opt.min_axis_angle is not None else rule(i, j),
                                    min(top, float(region_max[common].min(initial=math.inf))))
    for pair in stereo_pairs:
        i, j = sorted(index[n] for n in pair.cameras)
        low = pair.min_angle if pair.min_angle is not None else rule(i, j)
        high = pair.max_angle if pair.max_angle is not None else low + math.radians(STEREO_SPAN_DEG)
        limits[(i, j)] = (low, high)
    keys = sorted(limits)
    return (np.array(keys, dtype=int).reshape(-1, 2), np.array([limits[k][0] for k in keys]),
            np.array([limits[k][1] for k in keys]))


def angle_checks(regions: tuple[RegionSpec, ...], optimize: OptimizeSpec,
                 stereo_pairs: tuple[StereoPairSpec, ...], cameras, vis: Visibility,
                 samples: SurfaceSamples) -> list[dict]:
    """The axis-angle checks of a layout as `vdo evaluate` reports them: the pairs of cameras
    that share a region (`sharing`, [optimize] assign_fraction) and the declared
    stereo pairs, each with an "axis_angle" entry (the minimum) and, where a maximum applies, an
    "axis_angle_max" entry (`check`'s entries: value, limit, met, excess). The tables as
    `angle_limits` takes them."""
    fraction = optimize.assign_fraction
    pairs, low, high = angle_limits(regions, optimize, stereo_pairs, cameras,
                                    assignments(vis, samples, fraction),
                                    sharing(vis, samples, fraction))
    out = []
    for (i, j), lo, hi, angle in zip(pairs, low, high, axis_angles(cameras, pairs)):
        about = dict(cameras=[cameras[i].name, cameras[j].name])
        out.append(_entry("axis_angle", angle, math.degrees(lo), "deg", "min", **about))
        if np.isfinite(hi):
            out.append(_entry("axis_angle_max", angle, math.degrees(hi), "deg", "max", **about))
    return out


def axis_angles(cameras, pairs: np.ndarray) -> np.ndarray:
    """(K,) angles (deg) between the optical axes of the camera pairs."""
    return np.array([math.degrees(math.acos(np.clip(cameras[i].optical_axis @ cameras[j].optical_axis,
                                                    -1.0, 1.0))) for i, j in pairs])


def in_image_fraction(K, R, t, width, height, camera, points, area, ramp, distortion=None):
    """(G,) smooth fraction of each group's area that projects inside its camera's image.

    Group g holds the points (G, M, 3) with areas (G, M) (0 for padding) of one region as seen
    by camera `camera[g]`. A point counts with S((d + r_g) / (2 r_g)) for each image edge, d its
    signed distance inside that edge in pixels, r_g = ramp[g] pixels (about the sample spacing in
    the image, so that the fraction varies smoothly as the edge sweeps over the samples) and S the
    C^2 smoothstep: 1/2 on the edge itself, so that on a region that the edge crosses the smooth
    fraction equals the exact one to O(r^2); points behind the camera count 0. The pixel is the
    camera's (`vdo.model.camera.image_point`), with the lens `distortion` (C, 5) when given."""
    c = jnp.asarray(camera)
    p = to_camera(R[c][:, None], t[c][:, None], points)
    front = p[..., 2] > IN_FRONT_M
    p = jnp.where(front[..., None], p, jnp.array([0.0, 0.0, 1.0]))
    u, v = image_point(K[c][:, None], p[..., 0] / p[..., 2], p[..., 1] / p[..., 2],
                       None if distortion is None else jnp.asarray(distortion)[c][:, None])
    w, h = width[c][:, None], height[c][:, None]
    r = jnp.asarray(ramp)[:, None]
    edge = lambda d: smoothstep((d + r) / (2 * r))
    inside = edge(u + 0.5) * edge(w - 0.5 - u) * edge(v + 0.5) * edge(h - 0.5 - v)
    return jnp.sum(area * jnp.where(front, inside, 0.0), -1) / jnp.maximum(jnp.sum(area, -1), TINY)


def fov_penalty(fraction, limit, margin: float):
    """Σ_g (max(0, limit_g + margin - fraction_g) / 0.01)^2: shortfall in percent of the region."""
    return jnp.sum((jnp.maximum(jnp.asarray(limit) + margin - fraction, 0.0) / 0.01) ** 2)


def body_points_world(local_points, R, position):
    """(C, B, 3) world positions of each camera's body points (camera frame, (C, B, 3))."""
    return jnp.einsum("cji,cbj->cbi", R, local_points) + position[:, None, :]


def clearance_penalty(body_world, near_points, clearance: float):
    """Σ (max(0, clearance - d) / clearance)^2 over every (body point, mesh point) pair of a
    camera's neighbourhood (`near_points` (C, Q, 3), padded with far points) and over every pair
    of body points of two different cameras (each pair once), d their distance (m).

    Summing the hinge over all point pairs, not taking the nearest one, makes the penalty C^1 in
    the poses (a minimum over points has a kink wherever the nearest point changes, where BFGS
    stalls), and it is 0 exactly when every distance is at least `clearance` (1e-12 m^2 under
    the root keeps the gradient finite where two points coincide)."""
    if clearance <= 0:
        return 0.0

    def hinge(d2):
        d = jnp.sqrt(d2 + SMOOTH_SQRT)
        return (jnp.maximum(clearance - d, 0.0) / clearance) ** 2

    # |b - q|^2 = |b|^2 + |q|^2 - 2 b.q: one batched product instead of a (C, B, Q, 3) difference
    d2 = (jnp.sum(body_world ** 2, -1)[:, :, None] + jnp.sum(near_points ** 2, -1)[:, None, :]
          - 2 * jnp.einsum("cbk,cqk->cbq", body_world, near_points))
    total = jnp.sum(hinge(jnp.maximum(d2, 0.0)))
    n = body_world.shape[0]
    if n > 1:
        diff = body_world[:, None, :, None, :] - body_world[None, :, None, :, :]
        per_pair = jnp.sum(hinge(jnp.sum(diff ** 2, -1)), axis=(-2, -1))
        total = total + 0.5 * jnp.sum(jnp.where(~jnp.eye(n, dtype=bool), per_pair, 0.0))
    return total


KEEP_OUT_FAR = 1e6      # m: an unbounded side of a keep-out box, for the penalty's arithmetic
KEEP_OUT_SCALE = 0.05   # m: the penalty is ((depth + margin) / this)^2


def keep_out_depth(positions, lows, highs):
    """(C, B) how deep (m) each optical centre (C, 3) lies inside each keep-out box (B, 3) x 2:
    min over the axes of min(p - low, high - p); negative outside (minus the distance to the
    nearest face along one axis, or less)."""
    p = positions[:, None, :]
    return jnp.min(jnp.minimum(p - lows[None], highs[None] - p), axis=-1)


def keep_out_penalty(positions, lows, highs, margin: float):
    """Σ (max(0, depth + margin) / KEEP_OUT_SCALE)^2 over cameras and keep-out boxes
    (`keep_out_depth`): 0 exactly where every optical centre is `margin` or more outside every
    box, C^1 in the positions (a hinge squared)."""
    if lows.shape[0] == 0:
        return 0.0
    depth = keep_out_depth(positions, lows, highs)
    return jnp.sum((jnp.maximum(depth + margin, 0.0) / KEEP_OUT_SCALE) ** 2)


def keep_out_checks(cameras, keep_outs) -> list[dict]:
    """One "keep_out" entry per camera and keep-out box: the depth (m) of its optical centre
    inside the box (`keep_out_depth`), met when <= 0."""
    if not keep_outs:
        return []
    lows, highs = (np.clip(np.array([getattr(k, a) for k in keep_outs]), -KEEP_OUT_FAR, KEEP_OUT_FAR)
                   for a in ("box_min", "box_max"))
    depth = np.asarray(keep_out_depth(jnp.asarray([c.position for c in cameras]), jnp.asarray(lows),
                                      jnp.asarray(highs)))
    return [_entry("keep_out", float(depth[c, b]), 0.0, "m inside", "max", cameras=[cam.name],
                   keep_out=box.name)
            for c, cam in enumerate(cameras) for b, box in enumerate(keep_outs)]


def floor_edges(zone) -> tuple[np.ndarray, np.ndarray]:
    """The edges of a zone's floor polygon and of its holes as segments: starts (E, 2), ends
    (E, 2), m."""
    rings = [np.asarray(zone.floor, float)] + [np.asarray(h, float) for h in zone.floor_holes or ()]
    return (np.concatenate(rings), np.concatenate([np.roll(r, -1, axis=0) for r in rings]))


def floor_depth(xy, starts, ends):
    """(K,) how far (m) each floor point xy (K, 2) lies off a floor with the edges starts -> ends
    (E, 2) each (`floor_edges`): + the distance to the nearest edge where the point is off it
    (outside the outline or inside a hole: an odd number of edges crossed by the ray to +x, the
    even-odd rule), - that distance where it is on it."""
    e = ends - starts
    d = xy[:, None, :] - starts[None]                                     # (K, E, 2)
    t = jnp.clip(jnp.sum(d * e, axis=-1) / jnp.sum(e * e, axis=-1), 0.0, 1.0)
    gap = d - t[..., None] * e
    distance = jnp.sqrt(jnp.min(jnp.sum(gap * gap, axis=-1), axis=1) + SMOOTH_SQRT)
    y = xy[:, 1:2]
    straddles = (starts[None, :, 1] > y) != (ends[None, :, 1] > y)
    dy = jnp.where(straddles, e[None, :, 1], 1.0)
    x_cross = starts[None, :, 0] + (y - starts[None, :, 1]) * e[None, :, 0] / dy
    on = jnp.sum(straddles & (x_cross > xy[:, 0:1]), axis=1) % 2 == 1
    return jnp.where(on, -distance, distance)


def floor_penalty(positions, floors, margin: float):
    """Σ (max(0, depth + margin) / KEEP_OUT_SCALE)^2 over the cameras on non-convex floors,
    `floors` a tuple of (camera indices (k,), edge starts, edge ends) per such zone
    (`floor_depth` of the optical centre's x, y): 0 exactly where each stands `margin` or more
    inside its floor, C^1 in the positions."""
    total = 0.0
    for index, starts, ends in floors:
        depth = floor_depth(positions[index, :2], starts, ends)
        total = total + jnp.sum((jnp.maximum(depth + margin, 0.0) / KEEP_OUT_SCALE) ** 2)
    return total


def non_convex_floors(specs, mounts) -> list[tuple[list[int], object]]:
    """[(indices of the cameras in `specs` standing on it, zone)] per zone of `mounts` whose
    floor is a polygon that is not convex or has holes (`MountSpec.convex`)."""
    out = []
    for zone in mounts:
        if zone.kind == "zone" and zone.floor is not None and not zone.convex:
            index = [i for i, s in enumerate(specs) if s.mount == zone.name]
            if index:
                out.append((index, zone))
    return out


def floor_checks(cameras, specs, mounts) -> list[dict]:
    """One "floor" entry per camera on a non-convex floor (`non_convex_floors`): how far (m) its
    optical centre lies off the floor (`floor_depth`: outside the outline or in a hole), met
    when <= 0."""
    out = []
    for index, zone in non_convex_floors(specs, mounts):
        starts, ends = (jnp.asarray(a) for a in floor_edges(zone))
        depth = np.asarray(floor_depth(jnp.asarray([cameras[i].position[:2] for i in index], dtype=float),
                                       starts, ends))
        out += [_entry("floor", float(d), 0.0, "m off the floor", "max", cameras=[cameras[i].name],
                       zone=zone.name) for i, d in zip(index, depth)]
    return out


TRIPOD_LEG_POINTS = 9      # points along each tripod leg (top casting to foot) in the smooth penalty
TRIPOD_CHECK_POINTS = 65   # ... in the exact keep-out check (a leg of 1.5 m: every 2.3 cm)


def tripods_of(cameras, camera_specs, mounts) -> list:
    """Each camera's `TripodSpec`, None where it stands on none: the [mount.tripod] of the zone
    [[mount]] its [[camera]] table names (`camera_specs`)."""
    mount_of = {s.name: s.mount for s in camera_specs}
    specs = {m.name: m.tripod for m in mounts if m.tripod is not None}
    return [specs.get(mount_of.get(c.name)) for c in cameras]


def tripod_table(cameras, tripod) -> dict | None:
    """The constants of each camera's tripod legs (`vdo.scene.tripod_cylinders`, whose formula
    `tripod_legs` repeats for the penalty and the checks), arrays over `cameras` and their
    `TripodSpec`s `tripod` (`tripods_of`): has (C,) bool
    (the camera stands on a zone [[mount]] with a [mount.tripod]), back (C,) m (optical centre to
    the body's centre along the optical axis: lens length + half the body depth), drop (C,) m
    (body centre down to the top casting: half the body height + head_m), floor (C,) m, spread
    (C,) m, angles (C, L) rad (azimuth + 2 pi k / legs from the pan, the last leg repeated up to
    the most legs L) and radius (C,) m (the legs'). None when no camera stands on a tripod."""
    from vdo.meshes.hardware import BODY_SIZE, lens_length

    if not any(t is not None for t in tripod):
        return None
    most = max(t.legs for t in tripod if t is not None)
    blank = dict(legs=1, head=0.0, floor_z=0.0, spread=0.0, azimuth=0.0, leg_diameter=0.0)
    rows = [blank if t is None else dict(legs=t.legs, head=t.head, floor_z=t.floor_z, spread=t.spread,
                                         azimuth=t.azimuth, leg_diameter=t.leg_diameter) for t in tripod]
    angles = np.array([[r["azimuth"] + 2 * np.pi * min(k, r["legs"] - 1) / r["legs"] for k in range(most)]
                       for r in rows])
    return dict(has=np.array([t is not None for t in tripod]),
                back=np.array([lens_length(c.focal_length) + BODY_SIZE[2] / 2 for c in cameras]),
                drop=np.array([BODY_SIZE[1] / 2 + r["head"] for r in rows]),
                floor=np.array([r["floor_z"] for r in rows]), spread=np.array([r["spread"] for r in rows]),
                angles=angles, radius=np.array([r["leg_diameter"] / 2 for r in rows]))


def tripod_legs(positions, axes, pans, table, xp=jnp):
    """Each camera's tripod legs as segments: tops (C, 3) and feet (C, L, 3), m (`tripod_table`;
    the formula of `vdo.scene.tripod_cylinders`): the top casting T = C - back z_c - drop e_z below
    the body, feet on the floor at spread (cos phi_k, sin phi_k) from the point below T, phi_k =
    pan + angles_k. `positions` (C, 3) the optical centres, `axes` (C, 3) the optical axes z_c,
    `pans` (C,) rad; `xp` numpy or jax.numpy."""
    top = positions - table["back"][:, None] * axes
    top = top - xp.stack([xp.zeros_like(table["drop"]), xp.zeros_like(table["drop"]), table["drop"]], axis=-1)
    phi = pans[:, None] + table["angles"]
    feet = xp.stack([top[:, :1] + table["spread"][:, None] * xp.cos(phi),
                     top[:, 1:2] + table["spread"][:, None] * xp.sin(phi),
                     xp.broadcast_to(table["floor"][:, None], phi.shape)], axis=-1)
    return top, feet


def _leg_points(top, feet, count: int, xp=jnp):
    """(C, L count, 3) `count` points along each leg, top to foot."""
    s = xp.linspace(0.0, 1.0, count)
    pts = top[:, None, None, :] + s[None, None, :, None] * (feet - top[:, None, :])[:, :, None, :]
    return pts.reshape(top.shape[0], -1, 3)


def tripod_depth(top, feet, lows, highs, count: int, xp=jnp):
    """(C, B) how deep (m) each tripod's legs reach into each keep-out box: the greatest over
    `count` points along each leg of `keep_out_depth`, except at the feet, which stand on the
    floor whatever the pose: a foot's depth is the horizontal one, min over the x and y faces,
    where the floor's height lies within the box (else it is outside), so that the remedy it
    points to is a move across the floor."""
    pts = _leg_points(top, feet, count, xp)[:, :, None, :]             # (C, P, 1, 3)
    depth = xp.min(xp.minimum(pts - lows[None, None], highs[None, None] - pts), axis=-1).max(axis=1)
    return xp.maximum(depth, _feet_depth(feet, lows, highs, xp).max(axis=1))


def _feet_depth(feet, lows, highs, xp=jnp):
    """(C, L, B) each foot's horizontal depth in each box (min over its x and y faces) where the
    floor's height lies within the box, else -KEEP_OUT_FAR (outside)."""
    f = feet[:, :, None, :]                                             # (C, L, 1, 3)
    flat = xp.min(xp.minimum(f[..., :2] - lows[None, None, :, :2], highs[None, None, :, :2] - f[..., :2]), axis=-1)
    on = (f[..., 2] >= lows[None, None, :, 2]) & (f[..., 2] <= highs[None, None, :, 2])
    return xp.where(on, flat, -KEEP_OUT_FAR)


def tripod_penalty(top, feet, table, lows, highs, clearance: float, margin: float):
    """The tripods' smooth penalty, with the clearance's: Σ over the TRIPOD_LEG_POINTS points
    along every leg and every keep-out box of (max(0, depth + margin) / KEEP_OUT_SCALE)^2
    (`keep_out_depth`; and each foot's horizontal depth, as `tripod_depth`), and over the points
    of two different tripods, (max(0, g - d) / g)^2 with g = clearance + margin + both legs'
    radii, d their distance (m): a keep-out holds no equipment, and two tripods keep the bodies'
    clearance apart (`tripod_checks` judges both exactly). C^1 in the poses (hinges squared)."""
    has = jnp.asarray(table["has"], dtype=float)
    pts = _leg_points(top, feet, TRIPOD_LEG_POINTS)                      # (C, P, 3)
    total = 0.0
    if lows.shape[0]:
        pts3 = pts[:, :, None, :]
        depth = jnp.min(jnp.minimum(pts3 - lows[None, None], highs[None, None] - pts3), axis=-1)   # (C, P, B)
        feet_depth = _feet_depth(feet, lows, highs)                      # (C, L, B)
        total = total + jnp.sum(has[:, None, None] * (jnp.maximum(depth + margin, 0.0) / KEEP_OUT_SCALE) ** 2) \
            + jnp.sum(has[:, None, None] * (jnp.maximum(feet_depth + margin, 0.0) / KEEP_OUT_SCALE) ** 2)
    n = pts.shape[0]
    if n > 1 and clearance > 0:
        gap = clearance + margin + table["radius"][:, None] + table["radius"][None, :]   # (C, C)
        d = jnp.sqrt(jnp.sum((pts[:, None, :, None, :] - pts[None, :, None, :, :]) ** 2, -1) + SMOOTH_SQRT)
        hinge = (jnp.maximum(gap[:, :, None, None] - d, 0.0) / gap[:, :, None, None]) ** 2
        pair = has[:, None] * has[None, :] * (1.0 - jnp.eye(n))
        total = total + 0.5 * jnp.sum(pair[:, :, None, None] * hinge)
    return total


def tripod_checks(cameras, table, keep_outs, clearance: float) -> list[dict]:
    """The tripods' exact checks: a "tripod_keep_out" entry per tripod and keep-out box, the
    depth (m) of its legs inside the box (`tripod_depth` over TRIPOD_CHECK_POINTS points along
    each leg), met when <= 0; and a "tripod_clearance" entry per two tripods, the
    least distance between their legs' surfaces (`segment_distance` minus both radii), met when
    >= `clearance` (the bodies' clearance; none when it is 0)."""
    if table is None:
        return []
    top, feet = tripod_legs(np.array([c.position for c in cameras], float),
                            np.array([c.optical_axis for c in cameras], float),
                            np.array([c.pan for c in cameras], float), table, xp=np)
    has = np.flatnonzero(table["has"])
    out = []
    if keep_outs:
        lows, highs = (np.clip(np.array([getattr(k, a) for k in keep_outs]), -KEEP_OUT_FAR, KEEP_OUT_FAR)
                       for a in ("box_min", "box_max"))
        depth = tripod_depth(top, feet, lows, highs, TRIPOD_CHECK_POINTS, xp=np)
        out += [_entry("tripod_keep_out", float(depth[c, b]), 0.0, "m inside", "max",
                       cameras=[cameras[c].name], keep_out=box.name) for c in has for b, box in enumerate(keep_outs)]
    if clearance > 0:
        for k, i in enumerate(has):
            for j, gap in zip(has[k + 1:], tripod_gaps(top, feet, table["radius"], i, has[k + 1:])):
                out.append(_entry("tripod_clearance", float(gap), clearance, "m", "min",
                                  cameras=[cameras[i].name, cameras[j].name]))
    return out


def tripod_gaps(top, feet, radius, i: int, others) -> np.ndarray:
    """(n,) the least distance (m) between the surfaces of tripod i's legs and those of each
    tripod `others` (n indices): `segment_distance` over every pair of legs (tops (C, 3), feet
    (C, L, 3) from `tripod_legs`) less both legs' radii (C,). Two tripods at one floor point share
    their feet: -2 r."""
    o = np.asarray(others, dtype=int)
    L = feet.shape[1]
    gap = segment_distance(np.broadcast_to(top[i], (len(o), L, L, 3)), feet[i][None, :, None, :],
                           top[o][:, None, None, :], feet[o][:, None, :, :])
    return gap.min(axis=(1, 2)) - radius[i] - radius[o]


def shadow_penalty(centres, radii, samples, panels, margin: float, pairs=None, weight=None):
    """Σ (max(0, α + margin / D - β) / α)^2 over every body sphere (centres (C, K, 3), radii
    (C, K), m) and lit sample X, in angles seen from X: the sphere (centre c at distance D)
    covers a cone of half-angle α = r / D, and β is the angle between X -> c and X -> Y, Y the
    point of the light's panel nearest (in the panel's plane) to where the ray X -> c meets that
    plane. The sphere hides part of the panel from X when β < α. Only spheres between the sample
    and the panel count (the ray meets the plane beyond c).

    `samples` (S, 3) are lit samples, `panels` (S, 11) per sample its light's centre, normal
    (emitting side), width direction e_1, half-width and half-height (the height direction,
    n x e_1, is derived). 0 when no body comes within `margin` (m, at the body) of
    shadowing a sample; continuous in the body poses, C^1 except where the ray X -> c crosses
    the panel's outline (where the slope of β changes) or the panel's plane.

    With `pairs` (P, 2) rows (camera, sample) and `weight` (P,) (1, or 0 for padding rows), the
    sum runs over those pairs only (every sphere of the camera): `shadow_pairs` keeps the pairs
    that can be nonzero near a layout, so that the sum equals the full one there."""
    if pairs is None:
        terms = _shadow_terms(samples, centres[:, :, None, :], radii[:, :, None], panels, margin)
        return jnp.sum(terms)
    cam, sample = pairs[:, 0], pairs[:, 1]
    terms = _shadow_terms(samples[sample][:, None, :], centres[cam], radii[cam],
                          panels[sample][:, None, :], margin)
    return jnp.sum(weight[:, None] * terms)


def _shadow_terms(x, c, r, panel, margin: float):
    """`shadow_penalty`'s term for samples x (..., 3), sphere centres c (..., 3), radii r (...)
    and the samples' panel rows (..., 11), broadcast against each other."""
    centre, normal, e1, half_w, half_h = (panel[..., :3], panel[..., 3:6], panel[..., 6:9],
                                          panel[..., 9:10], panel[..., 10:11])
    e2 = jnp.cross(normal, e1)
    ray = c - x                                               # X -> c
    along = jnp.sum(ray * normal, -1)                         # < 0 toward the emitting face
    reach = jnp.sum((centre - x) * normal, -1)                # < 0: X in front of the panel
    toward = along < -1e-9
    lam = jnp.where(toward, reach / jnp.where(toward, along, -1.0), 0.0)
    q = x + lam[..., None] * ray - centre                     # in the panel plane, from its centre
    y = (centre + jnp.clip(jnp.sum(q * e1, -1, keepdims=True), -half_w, half_w) * e1
         + jnp.clip(jnp.sum(q * e2, -1, keepdims=True), -half_h, half_h) * e2 - x)
    dist = jnp.sqrt(jnp.sum(ray * ray, -1) + SMOOTH_SQRT)
    sin_b = jnp.sqrt(jnp.sum(jnp.cross(ray, y) ** 2, -1) + 1e-18)
    beta = jnp.arctan2(sin_b, jnp.sum(ray * y, -1))
    alpha = r / dist
    hit = toward & (lam > 1.0)
    return jnp.where(hit, (jnp.maximum(alpha + margin / dist - beta, 0.0) / alpha) ** 2, 0.0)


def shadow_pairs(centres: np.ndarray, radii: np.ndarray, samples: np.ndarray, panels: np.ndarray,
                 margin: float, move: float) -> np.ndarray:
    """(P, 2) rows (camera, sample) of `shadow_penalty` that can be nonzero while no sphere centre
    moves more than `move` (m) from `centres` (C, K, 3): the others are 0 there, so the sum over
    these pairs equals the full sum.

    A term (sphere c' = c + δ, |δ| <= move, at distance D' from X) is nonzero only if
    β' < (r + margin) / D'. β' is at least the angle β* from X -> c' to the nearest direction
    from X into the panel; β* changes by at most asin(move / D) when c moves by `move` (D = |c - X|),
    D' >= D - move, and β* >= ∠(X -> c, X -> panel centre) - γ, γ the largest angle from the
    centre's direction to a corner's (the panel lies in that cone: the cone is convex for
    γ < 90 deg, and so is its cut with the panel's plane). A pair is kept when for one of its
    spheres ∠ - γ < (r + margin) / (D - move) + asin(move / D), or D <= move + r + margin, or
    γ >= 90 deg."""
    centre, normal, e1, half_w, half_h = (panels[:, :3], panels[:, 3:6], panels[:, 6:9],
                                          panels[:, 9:10], panels[:, 10:11])
    e2 = np.cross(normal, e1)
    unit = lambda v: v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), TINY)
    to_centre = unit(centre - samples)                                              # (S, 3)
    corners = np.stack([centre + a * half_w * e1 + b * half_h * e2 - samples
                        for a in (-1, 1) for b in (-1, 1)], 1)                      # (S, 4, 3)
    gamma = np.arccos(np.clip(np.einsum("sj,skj->sk", to_centre, unit(corners)), -1, 1)).max(1)
    ray = centres[:, :, None, :] - samples                                          # (C, K, S, 3)
    dist = np.linalg.norm(ray, axis=-1)
    angle = np.arccos(np.clip(np.einsum("cksj,sj->cks", unit(ray), to_centre), -1, 1))
    rho = radii[:, :, None] + margin
    room = dist - move
    bound = rho / np.maximum(room, TINY) + np.arcsin(np.clip(move / np.maximum(dist, TINY), 0, 1))
    keep = (room <= rho) | (angle - gamma < bound) | (gamma >= np.pi / 2)
    return np.argwhere(keep.any(axis=1)).astype(np.int32)


def near_points(points: np.ndarray, paths: list[np.ndarray], reach: float) -> list[np.ndarray]:
    """For each camera, the mesh points (Q_c, 3) within `reach` of its path (the points its
    optical centre can take: a sampled rail, or its fixed position)."""
    return [points_near(points, path, reach) for path in paths]


def points_near(points: np.ndarray, anchors: np.ndarray, reach: float,
                tree: cKDTree | None = None) -> np.ndarray:
    """The rows of `points` within `reach` (m) of any row of `anchors` (A, 3), in their order.
    With `tree` (a k-d tree of `points`, for many calls with a few anchors each) a ball query
    around each anchor; without, each point's nearest anchor from a tree of the anchors (one
    call, many anchors). For a body's points as anchors and reach = clearance + d: every point
    that `clearance_penalty` can count while no body point moves more than d."""
    if len(points) == 0:
        return points
    if tree is not None:
        return points[sorted(set().union(*tree.query_ball_point(np.atleast_2d(anchors), reach)))]
    distance, _ = cKDTree(np.atleast_2d(anchors)).query(points, distance_upper_bound=2 * reach)
    return points[distance <= reach]


def padded_points(chosen: list[np.ndarray], size: int | None = None) -> np.ndarray:
    """(C, Q, 3): the per-camera point sets `chosen`, padded to Q = `size` (default the largest
    set, at least 1) with a point far away (1 km) that never binds `clearance_penalty`."""
    q = max([1] + [len(c) for c in chosen]) if size is None else size
    out = np.full((len(chosen), q, 3), 1e3)
    for c, pts in enumerate(chosen):
        out[c, :len(pts)] = pts
    return out


# --------------------------------------------------------------------------------------------
# Exact checks for the report
# --------------------------------------------------------------------------------------------
def _entry(constraint: str, value: float, limit, unit: str, kind: str, **about) -> dict:
    """A check entry. kind 'min' (value >= limit), 'max' (value <= limit), 'zero' (|value| <= limit
    within LIMIT_SLACK) or 'range' (limit = [low, high]). `excess` is by how much the value is beyond
    its limit, relative to the limit's scale (max(|limit|, 1) for 'zero', max(high - low, 1) for
    'range', else max(|limit|, 1e-3), where the limit is met within CHECK_MET_REL of the scale), 0 when
    met: a common measure of how far a layout is from feasible."""
    if kind == "range":
        low, high = limit
        gap = max(low - value, value - high, 0.0) / max(high - low, 1.0)
    elif kind == "zero":
        gap = max(abs(value) - limit - LIMIT_SLACK, 0.0) / max(abs(limit), 1.0)
    else:
        scale = max(abs(limit), 1e-3)
        beyond = (limit - value) if kind == "min" else (value - limit)
        gap = max(beyond - CHECK_MET_REL * scale, 0.0) / scale   # met within CHECK_MET_REL of the scale
    return dict(constraint=constraint, **about, value=value, limit=limit, unit=unit,
                met=bool(gap == 0.0), excess=float(gap))


def check(cameras, vis: Visibility, samples: SurfaceSamples, assigned: np.ndarray,
          pairs: np.ndarray, min_angles: np.ndarray, clearances: np.ndarray, clearance: float,
          max_obscuration: float, lost_light: np.ndarray, rails_u: list,
          roll_free: bool = False, fov_limits: np.ndarray | None = None,
          max_angles: np.ndarray | None = None, shadowers: dict | None = None) -> list[dict]:
    """One entry per constraint instance: name, what it concerns, value, limit, met and excess
    (`_entry`); `max_angles` (K,) rad adds an "axis_angle_max" entry for each pair with a
    finite maximum.

    `clearances` (C,) is the measured distance from each body to everything else (m),
    `lost_light` (R,) the fraction of each region's area where camera bodies block light, and
    `fov_limits` (C, R) the least in-image fraction of each assigned region (default
    1 - max_obscuration), `shadowers` {region index: (camera names, light names)}
    (`vdo.search.obstruction.light_shadowers`) the bodies that shadow a region and the lights
    they hide, written into its "no_shadow_from_cameras" entry as `cameras` and `lights`."""
    out = []
    tops = np.full(len(pairs), np.inf) if max_angles is None else np.asarray(max_angles, dtype=float)
    for (i, j), limit, top, angle in zip(pairs, min_angles, tops, axis_angles(cameras, pairs)):
        out.append(_entry("axis_angle", angle, math.degrees(limit), "deg", "min",
                          cameras=[cameras[i].name, cameras[j].name]))
        if np.isfinite(top):
            out.append(_entry("axis_angle_max", angle, math.degrees(top), "deg", "max",
                              cameras=[cameras[i].name, cameras[j].name]))
    geometric = vis.in_front & vis.in_image & vis.facing
    facing = vis.in_front & vis.facing
    for c, cam in enumerate(cameras):
        for r in np.flatnonzero(assigned[c]):
            mask = samples.region == r
            area = samples.area[mask]
            about = dict(cameras=[cam.name], region=samples.region_names[r])
            in_view = geometric[c, mask]
            blocked = float((area * (in_view & ~vis.unoccluded[c, mask])).sum() / max((area * in_view).sum(), TINY))
            out.append(_entry("obscuration", blocked, max_obscuration, "fraction of the region's image",
                              "max", **about))
            faces = facing[c, mask]
            inside = float((area * (faces & vis.in_image[c, mask])).sum() / max((area * faces).sum(), TINY))
            limit = 1 - max_obscuration if fov_limits is None else float(fov_limits[c, r])
            out.append(_entry("field_of_view", inside, limit, "fraction of the region in the image",
                              "min", **about))
        out.append(_entry("clearance", float(clearances[c]), clearance, "m", "min", cameras=[cam.name]))
        if not roll_free:
            out.append(_entry("horizontal", math.degrees(cam.roll), 0.0, "deg roll", "zero",
                              cameras=[cam.name]))
        if rails_u[c] is not None:
            out.append(_entry("on_rail", float(rails_u[c]), [0.0, 1.0], "u", "range", cameras=[cam.name]))
    for r, lost in enumerate(lost_light):
        who, lights = (shadowers or {}).get(r, ([], []))
        about = dict(cameras=list(who), lights=list(lights)) if who else {}
        out.append(_entry("no_shadow_from_cameras", float(lost), SHADOW_LIMIT, "fraction of the region losing light",
                          "max", region=samples.region_names[r], **about))
    return out
