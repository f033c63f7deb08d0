"""`vdo optimize`: move the cameras on their mounts (rails, zones) to minimise the predicted
uncertainty under the practical constraints of `vdo.constraints`.

Parameters, per moving camera, each only when listed in ``[optimize] free``: its position ("u":
on a rail z_u with u = sigmoid(z_u), in a zone one sigmoid per axis of its box, so the camera
cannot leave its mount; `Parameterization`), pan, tilt, roll (held at its configured value,
0 = horizontal, unless freed); and, with "lens" free, the focal length, a discrete choice from
``[optimize] lenses_mm`` made in an outer loop (`choose_lenses`). The objective, a JAX function
of the parameter vector θ, is

    J(θ) = a_k score(θ) + μ_k [P_angle + P_fov + P_clearance + P_obscuration + P_shadow](θ)

with `vdo.objective.score` (smooth high percentile of σ_max in µm plus the coverage shortfall) and
the penalties of `vdo.constraints` (`Problem.terms`); each but P_obscuration is 0 exactly where
its constraint holds with a back-off margin (`ANGLE_MARGIN`, `CLEARANCE_MARGIN`, `FOV_MARGIN`,
`SHADOW_MARGIN`): a
quadratic penalty's minimiser always lies a little beyond what the penalty aims at, so aiming
inside the limit puts it on the feasible side. P_fov keeps a smooth in-image area fraction of
each assigned region at least what the hand layout had (minus 1 %, at most 1 - max_obscuration);
P_obscuration = Σ (o / max_obscuration)^2 over the assigned (camera, region) pairs that an
obstacle has masked, o differentiated through Mitsuba (`vdo.search.obscuration`); P_shadow keeps the
camera bodies (covered by spheres) from hiding any part of a light panel from the samples it
lights.

A round is one BFGS solve (optimistix; its line search `RememberingArmijo`) with the ray-cast
occlusion and the lighting frozen; between rounds they are recomputed at the new layout, and the
next round starts from the last one's curvature estimate (inverse Hessian) when its weights are
the same. A round returns its `RoundOutcome` (optimistix's `Solution`, the accepted steps' terms,
how it ended, the curvature). From a start that violates a constraint, feasibility rounds come
first: the penalties alone (a = 0, μ = 1), repeated (at most `FEASIBILITY_ROUNDS`) until the
layout meets every constraint, so that the score never trades against a violation the layout
could shed. Then up to `rounds` rounds with a = 1 and μ = `MU0`, multiplied by 10 after a round
whose layout violates a constraint (a feasible round keeps μ: a larger one only pushes the layout
further inside the limits, at the cost of the score), until a feasible round improves on the
feasible round before it by less than `ROUND_TOL` of the score. Several starts: the hand layout
and randomly perturbed copies. Each round's layout is judged exactly (`judge`: the ray cast, the
score and `constraints.check`), and so is the iterate every `CHECKPOINT_STEPS` steps of a
feasibility round (which ends there once it is feasible) and, when `CHECKPOINT_S` have passed
since the last verdict, of a penalty round, so that the best layout so far is known within a
long round; per start the best one wins (`Result.rank`: feasible first, by score), and the report
names any violation that remains.

Anytime: the solver runs one BFGS step per call and checks a `Stop` (time limit, SIGINT/SIGTERM
via `stop_on_signals`) between steps and rounds; the best judged layout of the run is kept
(`_Run.best`) and written whatever ends the search. Compile once: the step is one jitted program
per run and structure (`_Run.programs`) that takes every layout-dependent array as an argument
(`Problem.data`), with the pair lists padded to one size (`_Run.padded`) and the clearance and
shadow sets to sizes fixed per run (`_Run.size`); without tracked obscuration it holds no host callback, so JAX's persistent
compilation cache can serve it to the next run.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import logging
import math
import signal
import threading
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import optimistix as optx
import trimesh
from scipy.spatial import cKDTree
from scipy.special import expit

from vdo import constraints
from vdo.outputs import html_report
from vdo.search import loadpath
from vdo import objective
from vdo.search import reachability
from vdo.outputs import report
from vdo.model.camera import Camera, aim_point, holds_aim, intrinsic_matrix, rotation
from vdo.config.experiment import Experiment, lens_catalogue_errors
from vdo.core.errors import Collect, ConfigError
from vdo.geometry.keyframes import load_path_of
from vdo.physics.lighting import panel_frame
from vdo.search.obscuration import ObscurationRenderer
from vdo.search.status import Status
from vdo.objective import bucket
from vdo.physics.predict import predict, samples_for_objective, settings, view_data
from vdo.core.progress import bar
from vdo.core.runfolder import run_folder
from vdo.state import LayoutState, bodies, layout_state, prepare, unobstructed_lighting
from vdo.scene import (SceneMesh, build_scene, camera_body, camera_body_points,
                    camera_body_spheres)
from vdo.physics.visibility import Visibility, compute_visibility

MU0 = 10.0   # penalty weight of the first round (score in µm, penalties ~1 at a clear violation)
FEASIBILITY_ROUNDS = 3    # at most this many feasibility rounds (penalties only) per start
PENALTIES = ("angle", "fov", "clearance", "obscuration", "shadow")   # the keys of `Problem.terms` besides score
ANGLE_SCALE = math.radians(3.0)   # rad: the solver's largest unit for an angle (`Parameterization`)
# Back-off: the penalties aim this far inside each limit, so that the penalty solution, which
# always lies a little beyond what it aims at, meets the exact limit.
ANGLE_MARGIN = math.radians(0.5)   # rad added to each minimum axis angle
CLEARANCE_MARGIN = 0.005           # m added to the clearance
CLEARANCE_SPACING = 0.015          # m between the mesh points clearances are measured to
FOV_MARGIN = 0.002                 # added to each least in-image fraction of a region
SHADOW_MARGIN = 0.005              # m added to each body sphere's radius in the shadow penalty
LOCAL_MOVE = 0.1   # m: the clearance and shadow penalties read only what a body point can reach
                   # within this distance of the anchor layout (`Problem.local`)
PATH_SLACK = 0.05  # m: the farthest an optical centre can be from the nearest point of `Problem._paths`
SIZE_PROBES = 1024  # path points per camera from which `Problem._size_local_sets` counts the shadow pairs
LENS_TRIALS = 3   # lens options optimised after screening (`choose_lenses`)
ROUND_TOL = 1e-3  # a start ends when a penalty round, feasible after a feasible one, gains less (relative)
BACKTRACKS = 4    # halvings of a round's move whose refreshed layout ranks worse than its start (`_backtrack`)
CHECKPOINT_STEPS = 10   # steps between the exact verdicts within a round (`solve`)
CHECKPOINT_S = 5.0      # s: in a penalty round, the least time between two verdicts (`solve`)

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Parameterisation
# --------------------------------------------------------------------------------------------
class Parameterization:
    """θ <-> camera poses. `index[c]` maps 'u' (rail), 'x', 'y', 'z' (zone), 'pan', 'tilt',
    'roll' to positions in θ for the free parameters of camera c.

    Position ("u" in `[optimize] free`): on a rail, u = sigmoid(z_u) in (0, 1); in a zone mount
    (a box [lo, hi]), each axis with an extent, p_k = lo_k + (hi_k - lo_k) sigmoid(z_k), so the
    camera can never leave its zone and the map is smooth; an axis with no extent, and a
    camera on a fixed mount, keeps its configured position.

    A camera whose rail position u is free is aimed relative to its *aim point* a_c, the point of
    its hand-layout optical axis at the depth of `centre` (the regions' centroid): its free pan
    and tilt are offsets from the direction a_c - P(u), so that sliding along the rail keeps the
    same point in the middle of the image (without this, u and the angles are strongly coupled
    and BFGS creeps along a narrow valley). Otherwise (u held, or a vertical axis, whose heading
    is undefined) pan, tilt and roll are absolute. θ = 0 offsets reproduce the hand layout; a
    held angle keeps its configured value. Each parameter's natural scale (`scale`, the solver's
    unit) is 0.5 in logit u (or per zone axis), and for an angle `ANGLE_SCALE` or an eighth of the camera's
    horizontal field of view, whichever is smaller."""

    RELATIVE = ("pan", "tilt")  # the angles an aimed camera holds as offsets
    AXES = ("x", "y", "z")      # a zone camera's position parameters
    MOVES = ("u",) + AXES       # the parameters that move an optical centre

    def __init__(self, exp: Experiment, cameras: list[Camera], centre):
        self.exp, self.cameras = exp, cameras
        moving = set(exp.optimize.cameras or [c.name for c in cameras])
        free = exp.optimize.free
        self.index, theta, scale, aims = [], [], [], []
        self.zones = [exp.mount(s.mount) if s.mount and exp.mount(s.mount).kind == "zone" else None
                      for s in exp.camera_specs]
        logit = lambda u: math.log(u / (1 - u))
        for cam, spec, zone in zip(cameras, exp.camera_specs, self.zones):
            idx = {}
            if cam.name in moving:
                for name in ("u", "pan", "tilt", "roll"):
                    if name not in free:
                        continue
                    if name == "u" and spec.rail is not None:
                        idx[name] = len(theta)
                        theta.append(logit(float(np.clip(spec.u, 1e-4, 1 - 1e-4))))
                        scale.append(0.5)
                    elif name == "u" and zone is not None and zone.floor is not None:
                        if not zone.convex:
                            raise ConfigError(exp.path, f'mount "{zone.name}".floor_m',
                                              f"camera {cam.name!r} moves over a floor that is not convex "
                                              "(or has holes): vdo optimize moves cameras over convex "
                                              "floors only; split it into convex sectors for optimize "
                                              "(evaluate and design take it whole)")
                        weights = mean_value_coordinates(zone.floor, cam.position[:2])
                        for k in range(1, len(zone.floor)):   # softmax logits against corner 0
                            idx[f"w{k}"] = len(theta)
                            theta.append(math.log(weights[k] / weights[0]))
                            scale.append(0.5)
                        if zone.high[2] > zone.low[2]:
                            idx["z"] = len(theta)
                            frac = (cam.position[2] - zone.low[2]) / (zone.high[2] - zone.low[2])
                            theta.append(logit(float(np.clip(frac, 1e-4, 1 - 1e-4))))
                            scale.append(0.5)
                    elif name == "u" and zone is not None:
                        for k, axis in enumerate(self.AXES):
                            extent = zone.high[k] - zone.low[k]
                            if extent > 0:
                                idx[axis] = len(theta)
                                frac = (cam.position[k] - zone.low[k]) / extent
                                theta.append(logit(float(np.clip(frac, 1e-4, 1 - 1e-4))))
                                scale.append(0.5)
                    elif name != "u":
                        idx[name] = len(theta)
                        aimed = self._aimed(idx, cam) and name in self.RELATIVE
                        theta.append(0.0 if aimed else getattr(cam, name))
                        # a few degrees, less for a long lens: an eighth of its horizontal field
                        scale.append(min(ANGLE_SCALE, math.atan(cam.width / 2 / cam.focal_px) / 4))
            self.index.append(idx)
            aims.append(aim_point(cam, centre))
        self.theta0 = np.array(theta, dtype=float)
        self.scale = np.array(scale, dtype=float)   # the solver works in units of these
        self.aims = np.array(aims)
        self.rails = [exp.rail(s.rail) if s.rail else None for s in exp.camera_specs]

    @staticmethod
    def _aimed(idx: dict, cam: Camera) -> bool:
        """Aim-relative angles: the position free and the axis not vertical (where the heading is
        undefined)."""
        return Parameterization.moves(idx) and holds_aim(cam)

    @classmethod
    def moves(cls, idx: dict) -> bool:
        """Whether these parameters move the optical centre."""
        return any(cls.is_position(k) for k in idx)

    @classmethod
    def is_position(cls, name: str) -> bool:
        """u (rail), x, y, z (zone box axes, or the height over a floor polygon), w1... (the
        softmax logits of a floor polygon's corners)."""
        return name in cls.MOVES or name[0] == "w"

    @property
    def held(self) -> dict:
        """The layout the parameters are offsets from, as arrays (what `poses` reads besides θ):
        optical centres (C, 3), pan, tilt, roll (C,) of the hand layout and the aim points (C, 3)."""
        return dict(position=jnp.asarray(np.array([c.position for c in self.cameras], dtype=float)),
                    **{k: jnp.asarray([float(getattr(c, k)) for c in self.cameras])
                       for k in ("pan", "tilt", "roll")},
                    aims=jnp.asarray(self.aims))

    @property
    def signature(self) -> tuple:
        """What the traced `poses` depends on besides its array inputs (`held`): two
        parameterisations with the same signature share compiled programs."""
        return (tuple(tuple(sorted(idx.items())) for idx in self.index),
                tuple(self._aimed(idx, c) for idx, c in zip(self.index, self.cameras)),
                tuple((s.rail, tuple(np.asarray(s.offset, float))) for s in self.exp.camera_specs),
                tuple(None if z is None else (tuple(z.low), tuple(z.high),
                                              None if z.floor is None else tuple(z.floor.ravel()))
                      for z in self.zones))

    def poses(self, theta, held: dict | None = None):
        """Optical centres (C, 3), pan, tilt, roll (C,) as JAX arrays; `held` (default
        `self.held`) gives the held values and aim points."""
        held = self.held if held is None else held
        pos, angles = [], {k: [] for k in ("pan", "tilt", "roll")}
        for c, (cam, spec, rail, idx) in enumerate(zip(self.cameras, self.exp.camera_specs, self.rails,
                                                       self.index)):
            if "u" in idx:
                p = rail.position(jax.nn.sigmoid(theta[idx["u"]])) + spec.offset
            elif self.moves(idx):
                p = self.zone_position(self.zones[c], theta, idx, held["position"][c])
            else:
                p = held["position"][c]
            if self._aimed(idx, cam):
                d = held["aims"][c] - p
                base = dict(pan=jnp.arctan2(d[1], d[0]), tilt=jnp.arctan2(d[2], jnp.hypot(d[0], d[1])))
                relative = self.RELATIVE
            else:
                base, relative = {}, ()
            pos.append(p)
            for k in angles:
                if k in idx:
                    angles[k].append(base[k] + theta[idx[k]] if k in relative else theta[idx[k]])
                else:
                    angles[k].append(held[k][c])
        return jnp.stack(pos), *(jnp.stack(angles[k]) for k in ("pan", "tilt", "roll"))

    @classmethod
    def zone_position(cls, zone, theta, idx: dict, held):
        """p_k = lo_k + (hi_k - lo_k) sigmoid(θ[idx[axis k]]) for the zone's free axes, else
        held[k] (m): inside the box [lo, hi] for every θ (written as the convex combination
        (1 - s) lo + s hi and clipped, so that rounding never puts it a hair outside). Over a
        floor polygon with corners v_k: (x, y) = Σ_k softmax(0, θ_w1, ...)_k v_k, inside the
        (convex) polygon for every θ, and z as above."""
        def axis(k, a):
            lo, hi = zone.low[k], zone.high[k]
            s = jax.nn.sigmoid(theta[idx[a]])
            return jnp.clip((1 - s) * lo + s * hi, lo, hi)
        if zone.floor is not None:   # a convex combination of the corners: inside the polygon
            logits = jnp.stack([jnp.zeros(())] + [theta[idx[f"w{k}"]] for k in range(1, len(zone.floor))])
            xy = jax.nn.softmax(logits) @ jnp.asarray(zone.floor)
            return jnp.stack([xy[0], xy[1], axis(2, "z") if "z" in idx else held[2]])
        return jnp.stack([axis(k, a) if a in idx else held[k] for k, a in enumerate(cls.AXES)])

    def u(self, theta) -> list:
        theta = np.asarray(theta)
        return [float(expit(theta[idx["u"]])) if "u" in idx else spec.u
                for spec, idx in zip(self.exp.camera_specs, self.index)]

    def cameras_at(self, theta) -> list[Camera]:
        if not hasattr(self, "_poses_jit"):   # one compiled program, not one per eager operation
            self._poses_jit = jax.jit(self.poses)
        pos, pan, tilt, roll = (np.asarray(a) for a in self._poses_jit(jnp.asarray(theta, dtype=float),
                                                                       self.held))
        return [c.with_pose(pos[i], pan[i], tilt[i], roll[i]) for i, c in enumerate(self.cameras)]

    def specs_at(self, theta) -> list:
        """Camera specs with the optimized rail parameter or zone position and aim (pan/tilt
        replace a target)."""
        cams, us = self.cameras_at(theta), self.u(theta)
        return [dataclasses.replace(spec, u=us[i] if spec.rail else None, target=None,
                                    position=np.asarray(cams[i].position) if spec.mount else spec.position,
                                    pan=cams[i].pan, tilt=cams[i].tilt, roll=cams[i].roll)
                for i, spec in enumerate(self.exp.camera_specs)]


# --------------------------------------------------------------------------------------------
# Obscuration: one JAX function whose set of renderers changes between rounds
# --------------------------------------------------------------------------------------------
class ObscurationTerm:
    """P_obscuration(poses) = Σ_k (o_k / m)^2 over the tracked (camera, region) pairs, with its
    gradient w.r.t. each camera's (x, y, z, pan, tilt) from Mitsuba; poses is (C, 5)."""

    def __init__(self, n_cameras: int, limit: float):
        self.n, self.limit = n_cameras, max(limit, 1e-3)
        self.tracked: list[tuple[int, ObscurationRenderer]] = []
        self._cache = (None, None)

        def host(poses):
            poses = np.asarray(poses, dtype=float)
            key = poses.tobytes()
            if self._cache[0] != key:
                value, grad = 0.0, np.zeros((self.n, 5))
                for c, renderer in self.tracked:
                    o, do = renderer.value_and_grad(poses[c])
                    value += (o / self.limit) ** 2
                    grad[c] += 2 * o / self.limit ** 2 * do
                self._cache = (key, (np.float64(value), grad))
            return self._cache[1]

        shapes = (jax.ShapeDtypeStruct((), jnp.float64), jax.ShapeDtypeStruct((n_cameras, 5), jnp.float64))

        @jax.custom_jvp
        def penalty(poses):
            return jax.pure_callback(host, shapes, poses)[0]

        @penalty.defjvp
        def penalty_jvp(primals, tangents):
            value, grad = jax.pure_callback(host, shapes, primals[0])
            return value, jnp.sum(grad * tangents[0])

        self.penalty = penalty

    def track(self, renderers: list[tuple[int, ObscurationRenderer]]) -> None:
        """Differentiate these (camera, renderer) pairs from now on (the cache of the last
        evaluation is dropped with the old set)."""
        self.tracked = list(renderers)
        self._cache = (None, None)


# --------------------------------------------------------------------------------------------
# The problem: everything an objective evaluation needs, built once
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass
class State:
    """A layout, ray-cast and lit: what a round freezes and what the report needs."""

    theta: np.ndarray
    cameras: list
    vis: object
    vis_obstacles: object
    illumination: object
    views: objective.ViewData


class Problem:
    def __init__(self, exp: Experiment, reference: "Problem | None" = None, user_objective=None):
        """Everything an objective evaluation needs, for the layout of `exp`. With a `reference`
        (the same experiment with other lenses, `choose_lenses`), its meshes, samples and lighting
        are reused, and so is what the hand layout defined: the regions assigned to each camera
        and the least in-image fraction of each (and its `user_objective`). `user_objective`: a
        JAX-traceable scalar function of `vdo.objective.SampleFields` minimised instead of
        `vdo.objective.score` (`check_objective`)."""
        self.exp = exp
        self.user_objective = reference.user_objective if reference is not None else user_objective
        opt = exp.optimize
        if reference is None:
            self.geometry = prepare(exp)
            self.scene_points = _surface_points(list(self.geometry.meshes), spacing=CLEARANCE_SPACING)
            # the lighting with no camera in the scene: what the bodies hide, and the base that
            # each refresh casts again only where a body may be in the way (`layout_state`)
            self.unobstructed = unobstructed_lighting(self.geometry)
        else:
            for name in ("geometry", "scene_points", "unobstructed"):
                setattr(self, name, getattr(reference, name))
        self.lit_without_cameras = self.unobstructed.lit if exp.lights else None
        self.meshes, self.samples = list(self.geometry.meshes), self.geometry.samples
        self.faces, self.speckle = list(self.geometry.region_faces), self.geometry.speckle
        self.settings = settings(exp)
        self.obj_samples = samples_for_objective(exp, self.samples)
        if opt.regions is not None:   # only the named regions enter the score
            keep = np.array([r.name in opt.regions for r in exp.regions])
            self.obj_samples = dataclasses.replace(
                self.obj_samples, importance=jnp.where(jnp.asarray(keep), self.obj_samples.importance, 0.0))
        self.param = Parameterization(exp, exp.cameras(), self.geometry.centre)
        self.cams0 = self.param.cameras
        self.run = reference.run if reference is not None else _Run(len(self.cams0), opt.max_obscuration)
        self.scene_tree = cKDTree(self.scene_points)
        self.body_local = jnp.asarray(np.stack([camera_body_points(c.focal_length) for c in self.cams0]))
        paths = self._paths()
        self.near_sets = constraints.near_points(
            self.scene_points, paths, reach=float(np.abs(self.body_local).max()) * 1.8
            + opt.clearance + CLEARANCE_MARGIN)
        self.near_trees = [cKDTree(p) for p in self.near_sets]
        t0 = time.perf_counter()
        self.start = self.refresh(self.param.theta0)
        self.refresh_s = time.perf_counter() - t0   # s: one layout's ray cast, lighting and views
        self.assigned = (constraints.assignments(self.start.vis, self.samples, opt.assign_fraction)
                         if reference is None else reference.assigned)
        self.shared = (constraints.sharing(self.start.vis, self.samples, opt.assign_fraction)
                       if reference is None else reference.shared)
        self.pairs, self.min_angles, self.max_angles = constraints.angle_limits(
            exp, self.cams0, self.assigned, self.shared)
        # the cameras with a body (the ray cast and the lighting see only those)
        self.bodied = np.array([i for i, s in enumerate(exp.camera_specs) if s.body], dtype=int)
        spheres = [camera_body_spheres(self.cams0[i].focal_length) for i in self.bodied]
        self.sphere_local = jnp.asarray(np.stack([c for c, _ in spheres])) if spheres else None
        self.sphere_radii = jnp.asarray(np.stack([r for _, r in spheres])) if spheres else None
        self.lit_samples = self._lit_samples()
        if reference is None:
            self._size_local_sets(paths)
        if reference is None:
            self.fov_limits = None   # None: 1 - max_obscuration, to judge the hand layout itself
            self.fov_limits = self._fov_limits(self.check(self.start))   # then no worse than it
        else:
            self.fov_limits = reference.fov_limits
        self.fov = self._fov_groups(self.start)

    @property
    def obscuration(self) -> "ObscurationTerm":
        return self.run.obscuration

    @property
    def data(self) -> dict:
        """Every array the traced objective reads (`terms`): passed to the compiled programs as
        an argument, so that another layout of the same structure (another start, a lens trial)
        reuses them."""
        c0 = self.cams0
        return dict(
            held=self.param.held, focal_px=jnp.asarray([c.focal_px for c in c0]),
            cx=jnp.asarray([c.principal_point[0] for c in c0]),
            cy=jnp.asarray([c.principal_point[1] for c in c0]),
            size=jnp.asarray([[c.width, c.height] for c in c0], dtype=float),
            distortion=objective.CameraParams.from_cameras(c0).distortion,
            samples=self.obj_samples, energy=self.speckle.table,
            pairs=jnp.asarray(self.pairs), min_angles=jnp.asarray(self.min_angles + ANGLE_MARGIN),
            max_angles=jnp.asarray(np.minimum(self.max_angles - ANGLE_MARGIN, np.pi)),
            fov=self.fov, body_local=self.body_local,
            keep_out=tuple(jnp.asarray(np.clip(np.array([getattr(k, a) for k in self.exp.keep_outs]).reshape(-1, 3),
                                               -constraints.KEEP_OUT_FAR, constraints.KEEP_OUT_FAR))
                           for a in ("box_min", "box_max")),
            spheres=None if self.sphere_local is None else (self.sphere_local, self.sphere_radii),
            lit=self.lit_samples)

    def body_points(self, theta):
        """(R (C, 3, 3), optical centres (C, 3), body points (C, B, 3) in the world, m) at θ."""
        cams = self.param.cameras_at(theta)
        R = np.stack([c.R for c in cams])
        pos = np.stack([np.asarray(c.position, float) for c in cams])
        return R, pos, np.einsum("cji,cbj->cbi", R, np.asarray(self.body_local)) + pos[:, None, :]

    def _size_local_sets(self, paths: list[np.ndarray]) -> None:
        """Fix the run's padded sizes of `local`'s sets before the first compile, from where the
        bodies can go: the most mesh points within e + clearance (+ margin) + `LOCAL_MOVE` +
        `PATH_SLACK` of one point of a camera's path (e: the farthest body point from the optical
        centre), and the (camera, sample) pairs that `constraints.shadow_pairs` keeps for a sphere
        of the largest radius anywhere on the camera's path, moving e + `LOCAL_MOVE` +
        `PATH_SLACK`. An estimate, not a bound: a larger set raises the size (`_Run.size`). The
        shadow pairs are counted from at most `SIZE_PROBES` points of each path, the move grown by
        the farthest any path point lies from them, so that they cover the whole path (a zone's
        grid has thousands of points: counted from all of them, this took 26 s on the steel
        beam's two tripods)."""
        opt = self.exp.optimize
        extent = float(np.linalg.norm(np.asarray(self.body_local), axis=-1).max())
        reach = opt.clearance + CLEARANCE_MARGIN + LOCAL_MOVE + PATH_SLACK + extent
        self.run.size("near", max(int(np.max(tree.query_ball_point(path, reach, return_length=True)))
                                  for tree, path in zip(self.near_trees, paths)))
        if self.lit_samples is not None and self.sphere_local is not None:
            samples, panels = (np.asarray(a) for a in self.lit_samples)
            radius = float(np.asarray(self.sphere_radii).max())
            count = 0
            for c in self.bodied:
                probes, gap = paths[c], 0.0
                if len(probes) > SIZE_PROBES:
                    probes = probes[np.linspace(0, len(probes) - 1, SIZE_PROBES).round().astype(int)]
                    gap = float(cKDTree(probes).query(paths[c])[0].max())
                move = extent + LOCAL_MOVE + PATH_SLACK + gap
                count += len(constraints.shadow_pairs(probes[None], np.full((1, len(probes)), radius),
                                                      samples, panels, SHADOW_MARGIN, move))
            self.run.size("shadow", count)

    def local(self, theta) -> dict:
        """What the clearance and shadow penalties read near the layout θ (the anchor): its body
        points (C, B, 3) and sphere centres (m), each camera's mesh points within the clearance
        (+ margin) + `LOCAL_MOVE` of its body points (a subset of `near_sets`, padded:
        `_Run.size`), and the (camera, lit sample) pairs that `constraints.shadow_pairs` keeps for
        spheres moving at most `LOCAL_MOVE`. While no body point has moved more than `LOCAL_MOVE`
        from the anchor, the penalties over these sets equal the full ones (`_round` moves the
        anchor with the
        solver's trial point). The sphere centres lie in the convex hull of the body points, so
        under a rigid move they move no more than the farthest body point."""
        R, pos, body = self.body_points(theta)
        reach = self.exp.optimize.clearance + CLEARANCE_MARGIN + LOCAL_MOVE
        kept = [constraints.points_near(pts, b, reach, tree)
                for pts, tree, b in zip(self.near_sets, self.near_trees, body)]
        out = dict(body=jnp.asarray(body), near=jnp.asarray(constraints.padded_points(
            kept, self.run.size("near", max(len(k) for k in kept)))))
        if self.lit_samples is not None and self.sphere_local is not None:
            b = self.bodied
            spheres = np.einsum("cji,cbj->cbi", R[b], np.asarray(self.sphere_local)) + pos[b][:, None, :]
            pairs = constraints.shadow_pairs(spheres, np.asarray(self.sphere_radii),
                                             *(np.asarray(a) for a in self.lit_samples), SHADOW_MARGIN,
                                             LOCAL_MOVE)
            size = self.run.size("shadow", len(pairs))
            out.update(spheres=jnp.asarray(spheres),
                       shadow_pairs=jnp.asarray(np.pad(pairs, ((0, size - len(pairs)), (0, 0)))),
                       shadow_weight=jnp.asarray(np.arange(size) < len(pairs), dtype=float))
        return out

    def _paths(self) -> list[np.ndarray]:
        """Where each optical centre can go: its rail (+ offset) sampled at most ~2 cm apart, or
        its zone on a grid, if its position is free, else its position."""
        out = []
        sliding = [r for r, idx in zip(self.param.rails, self.param.index) if "u" in idx]
        # the control polygon is at least as long as the curve
        n = max([2] + [int(np.linalg.norm(np.diff(r.control_points, axis=0), axis=1).sum() / 0.02) + 1
                       for r in sliding])
        grid = np.linspace(0, 1, n)
        along = iter([r.position(grid, xp=np) for r in sliding])
        for cam, spec, rail, zone, idx in zip(self.cams0, self.exp.camera_specs, self.param.rails,
                                              self.param.zones, self.param.index):
            if "u" in idx:
                out.append(np.asarray(next(along)) + spec.offset)
            elif zone is not None and Parameterization.moves(idx):
                lo, hi = zone.low, zone.high   # a grid at most 5 cm apart
                axes = [np.linspace(lo[k], hi[k], max(2, int(np.ceil((hi[k] - lo[k]) / 0.05)) + 1))
                        for k in range(3)]
                grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
                if zone.floor is not None:   # the grid points over the polygon, and its corners
                    keep = [zone.inside(g[:2], tol=0.05) for g in grid]
                    corners = [[*v, z] for v in zone.floor for z in (lo[2], hi[2])]
                    grid = np.vstack([grid[keep], corners])
                out.append(grid)
            else:
                out.append(np.asarray(cam.position)[None])
        return out

    # -- the frozen state of a round ------------------------------------------------------
    @functools.cached_property
    def path(self):
        """(load path, keyframe steps, fraction) the scored views must hold over, or None
        (`vdo.search.loadpath.scored_path`, `[optimize] load_path`)."""
        return loadpath.scored_path(self.exp, self.geometry)

    def refresh(self, theta) -> State:
        cams = self.param.cameras_at(theta)
        layout = layout_state(self.geometry, cams, predict_fields=False, unobstructed=self.unobstructed)
        vis, illum = layout.visibility, layout.illumination
        vis_obstacles = obstacle_visibility(self.geometry, cams)
        scored = vis
        if self.path is not None:   # the score counts the views that hold over the load path
            load_path, steps, fraction = self.path
            held = loadpath.path_occlusion(self.geometry, load_path, cams, steps, fraction) > 0
            scored = dataclasses.replace(vis, unoccluded=vis.unoccluded & held)
        return State(np.asarray(theta, float), cams, vis, vis_obstacles, illum,
                     self.run.padded(view_data(self.exp, self.obj_samples, scored, illum, self.speckle)))

    def _lit_samples(self, per_light: int = 600):
        """(samples (S, 3), panels (S, 11)) for `constraints.shadow_penalty`: for each light, up to
        `per_light` of the samples it reaches with no camera in the scene (a regular subset),
        each with its light's panel. None without lights."""
        if self.lit_without_cameras is None:
            return None
        points, panels = [], []
        for light, lit in zip(self.exp.lights, self.lit_without_cameras):
            idx = np.flatnonzero(lit > 0.01)
            idx = idx[np.linspace(0, idx.size - 1, min(per_light, idx.size)).astype(int)] if idx.size else idx
            n, e1, _ = panel_frame(light)
            row = np.concatenate([np.asarray(light.position, float), n, e1,
                                  [light.size[0] / 2, light.size[1] / 2]])
            points.append(self.samples.points[idx])
            panels.append(np.tile(row, (idx.size, 1)))
        return jnp.asarray(np.concatenate(points)), jnp.asarray(np.concatenate(panels))

    def _fov_groups(self, state: State) -> dict:
        """The field-of-view constraint's data, one group per assigned (camera, region): the
        region's samples facing the camera in `state` (points, areas, padded to a common size),
        the camera, the least in-image fraction (`fov_limits`) and the smoothing ramp: the
        sample spacing in that camera's image, sqrt(median sample area) x f / median depth (px)."""
        groups = [(c, r) for c in range(len(self.cams0)) for r in np.flatnonzero(self.assigned[c])]
        facing = state.vis.in_front & state.vis.facing
        members = [np.flatnonzero((self.samples.region == r) & facing[c]) for c, r in groups]
        m = bucket(max([1] + [idx.size for idx in members]))   # few sizes: few compilations
        points, area = np.zeros((len(groups), m, 3)), np.zeros((len(groups), m))
        ramp = np.ones(len(groups))
        for g, ((c, r), idx) in enumerate(zip(groups, members)):
            points[g, :idx.size], area[g, :idx.size] = self.samples.points[idx], self.samples.area[idx]
            if idx.size:
                cam = state.cameras[c]
                depth = np.median((self.samples.points[idx] - cam.position) @ cam.optical_axis)
                ramp[g] = max(np.sqrt(np.median(self.samples.area[idx])) * cam.focal_px / depth, 1.0)
        return dict(camera=np.array([c for c, _ in groups], dtype=int),
                    points=jnp.asarray(points), area=jnp.asarray(area), ramp=jnp.asarray(ramp),
                    limit=jnp.asarray([self.fov_limits[c, r] for c, r in groups]))

    def track_obscured(self, state: State, checks: list[dict], masked: frozenset = frozenset()) -> frozenset:
        """Render-differentiated obscuration for every assigned (camera, region) pair that an
        obstacle has masked beyond the limit at this or any earlier refresh of the start (`masked`,
        the pairs so far; returned with this refresh's added: a pair that was cleared stays
        tracked, or the next round could walk the camera back behind the obstacle). Pairs within
        the limit are left to the exact check: each tracked pair costs two Mitsuba renders and a
        backward pass per evaluation, and its Monte Carlo noise (spp 16) stalls BFGS's line search
        when the pair has nothing to gain (measured on the built-in experiment: no accepted step
        with two such pairs, 5 % lower score without them). `checks` is `check(state)`."""
        by_name = {c.name: i for i, c in enumerate(self.cams0)}
        threshold = self.exp.optimize.max_obscuration
        masked = frozenset(masked) | {
            (by_name[e["cameras"][0]], self.samples.region_names.index(e["region"]))
            for e in checks if e["constraint"] == "obscuration" and e["value"] > threshold}
        renderers = []
        for c, r in sorted(masked):
            others = bodies(self.exp, [o for k, o in enumerate(state.cameras) if k != c])
            obstacles = [m for m in self.meshes if m.role != "specimen"] + others
            renderers.append(
                (c, ObscurationRenderer(state.cameras[c], self._region_mesh(r), obstacles, width=96, spp=16)))
        self.obscuration.track(renderers)
        return masked

    def _region_mesh(self, r: int) -> SceneMesh:
        spec = self.exp.regions[r]
        mesh = next(m for m in self.meshes if m.name == spec.mesh)
        faces = mesh.faces[self.faces[r].faces]
        used, inverse = np.unique(faces, return_inverse=True)
        return SceneMesh(spec.name, "specimen", mesh.vertices[used], inverse.reshape(-1, 3))

    # -- the objective (traced: reads only `data` and the static structure) ------------------
    def terms(self, theta, views, data, obscured: bool = True) -> dict:
        """The score and each penalty at θ (float64 JAX scalars): score and the `PENALTIES`;
        P_obscuration only when `obscured` (a Mitsuba callback; 0 otherwise). P_clearance and
        P_shadow read `data["local"]`, `local` at an anchor from which no body point of θ is
        more than `LOCAL_MOVE` away: there they equal the penalties over every mesh point and
        every lit sample (`_round` moves the anchor before every evaluation that needs it)."""
        pos, pan, tilt, roll = self.param.poses(theta, data["held"])
        f, cx, cy, size = data["focal_px"], data["cx"], data["cy"], data["size"]
        cams = objective.CameraParams(pos, pan, tilt, roll, f, cx, cy, size[:, 0], size[:, 1],
                                      data["distortion"])
        R = rotation(pan, tilt, roll)
        t = -jnp.einsum("cij,cj->ci", R, pos)
        K = intrinsic_matrix(f, cx, cy)
        clearance = self.exp.optimize.clearance
        clearance = clearance + CLEARANCE_MARGIN if clearance > 0 else 0.0
        fov = data["fov"]
        local = data["local"]   # the clearance and shadow sets of an anchor near θ (`local`)
        if self.user_objective is not None:
            score = self.user_objective(objective.sample_fields(cams, data["samples"], views, data["energy"],
                                                                self.settings))
        else:
            score = objective.score(cams, data["samples"], views, data["energy"], self.settings)
        out = dict(
            score=score,
            angle=constraints.axis_angle_penalty(R[:, 2, :], data["pairs"], data["min_angles"],
                                                 data["max_angles"]),
            fov=constraints.fov_penalty(constraints.in_image_fraction(
                K, R, t, size[:, 0], size[:, 1], fov["camera"], fov["points"], fov["area"],
                fov["ramp"], data["distortion"]), fov["limit"], FOV_MARGIN),
            clearance=constraints.clearance_penalty(
                constraints.body_points_world(data["body_local"], R, pos), local["near"], clearance)
            + constraints.keep_out_penalty(pos, *data["keep_out"], CLEARANCE_MARGIN),
            obscuration=self.obscuration.penalty(jnp.concatenate([pos, pan[:, None], tilt[:, None]], axis=1))
            if obscured else 0.0,
            shadow=0.0 if data["lit"] is None or data["spheres"] is None else constraints.shadow_penalty(
                constraints.body_points_world(data["spheres"][0], R[self.bodied], pos[self.bodied]),
                data["spheres"][1], *data["lit"], SHADOW_MARGIN, local["shadow_pairs"],
                local["shadow_weight"]))
        return {k: jnp.asarray(v, dtype=jnp.float64) for k, v in out.items()}

    def _scaled(self, y, args, obscured: bool):
        """(J / norm, the terms) at θ = origin + scale y, J = weights[0] score + weights[1] Σ
        penalties (weights: a (2,) array; norm: `_round`)."""
        origin, scale, norm, views, weights, data = args
        terms = self.terms(origin + scale * y, views, data, obscured)
        total = weights[0] * terms["score"] + weights[1] * sum(terms[k] for k in PENALTIES)
        return total / norm, terms

    # -- exact checks ---------------------------------------------------------------------
    def check(self, state: State) -> list[dict]:
        opt = self.exp.optimize
        return constraints.check(state.cameras, state.vis_obstacles, self.samples, self.assigned,
                                 self.pairs, self.min_angles, _clearances(state.cameras, self.scene_tree),
                                 opt.clearance, opt.max_obscuration, light_lost(self.lit_without_cameras, state.illumination.lit, self.samples),
                                 self.param.u(state.theta), roll_free="roll" in opt.free,
                                 fov_limits=self.fov_limits, max_angles=self.max_angles) \
            + constraints.keep_out_checks(state.cameras, self.exp.keep_outs)

    def _fov_limits(self, entries) -> np.ndarray:
        """(C, R) least in-image fraction of each assigned region: 1 - max_obscuration, or what
        the hand layout had minus one percent where that is less."""
        limits = np.full(self.assigned.shape, 1.0 - self.exp.optimize.max_obscuration)
        cams = [c.name for c in self.cams0]
        for e in entries:
            if e["constraint"] == "field_of_view":
                c, r = cams.index(e["cameras"][0]), self.samples.region_names.index(e["region"])
                limits[c, r] = min(limits[c, r], e["value"] - 0.01)
        return limits

    def exact_score(self, state: State) -> float:
        """The score at the refreshed layout (µm): `_score_parts`'s, from the one compiled
        `objective.fields` program that the report also uses (`objective.score` gives the same
        within 1e-7 relative, its pairs in float32, and would be one more program to compile).
        With a `user_objective`, its value at the refreshed layout."""
        if self.user_objective is None:
            return _score_parts(self, state)["score_um"]
        programs = self.run._programs
        if "user" not in programs:   # one program per run: the layout's arrays are arguments
            programs["user"] = eqx.filter_jit(lambda cams, views, samples, energy: self.user_objective(
                objective.sample_fields(cams, samples, views, energy, self.settings)))
        return float(programs["user"](objective.CameraParams.from_cameras(state.cameras), state.views,
                                      self.obj_samples, self.speckle.table))


def _surface_points(meshes, spacing: float) -> np.ndarray:
    """Points on every mesh surface about `spacing` apart (plus the vertices), for clearance."""
    pts = []
    for m in meshes:
        tm = m.trimesh
        count = int(min(max(tm.area / spacing**2, 100), 200_000))
        sampled, _ = trimesh.sample.sample_surface_even(tm, count, seed=0)
        pts += [sampled, m.vertices]
    return np.vstack(pts)


def _clearances(cameras, tree) -> np.ndarray:
    """Distance (m) from each camera body to the nearest mesh point and to the other bodies."""
    bodies = [camera_body(c) for c in cameras]
    dense = [trimesh.sample.sample_surface_even(b.trimesh, 400, seed=0)[0] for b in bodies]
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


def layout_checks(state: LayoutState) -> list[dict]:
    """Every constraint check of `vdo optimize` (`vdo.constraints.check`: axis angles, clearance,
    obscuration, field of view, shadows of the camera bodies, horizontal, on the rail) on a layout
    as it stands: the one verdict that `vdo evaluate`, `vdo design` and the optimizer's report
    share. Regions are assigned as in the optimizer (`vdo.constraints.assignments`), the least
    in-image fraction of an assigned region is 1 - max_obscuration, clearances are measured to
    the meshes sampled every `CLEARANCE_SPACING` metres."""
    exp, geometry, samples = state.experiment, state.geometry, state.samples
    opt, cameras = exp.optimize, list(state.cameras)
    assigned = constraints.assignments(state.visibility, samples, opt.assign_fraction)
    pairs, min_angles, max_angles = constraints.angle_limits(
        exp, cameras, assigned, constraints.sharing(state.visibility, samples, opt.assign_fraction))
    tree = cKDTree(_surface_points(list(geometry.meshes), spacing=CLEARANCE_SPACING))
    lit_without = unobstructed_lighting(geometry).lit if exp.lights else None
    specs = {s.name: s for s in exp.camera_specs}
    rails_u = [specs[c.name].u if c.name in specs and specs[c.name].rail is not None else None
               for c in cameras]
    return constraints.check(cameras, obstacle_visibility(geometry, cameras), samples, assigned, pairs, min_angles,
                             _clearances(cameras, tree), opt.clearance, opt.max_obscuration,
                             light_lost(lit_without, state.illumination.lit, samples), rails_u,
                             roll_free="roll" in opt.free, max_angles=max_angles)


def mean_value_coordinates(polygon: np.ndarray, point) -> np.ndarray:
    """Positive weights w (n,), Σ w = 1, with Σ w_k v_k = point for a point inside the convex
    polygon v (n, 2) (Floater's mean value coordinates: w_k ∝ (tan(α_(k-1)/2) + tan(α_k/2)) /
    |v_k - p|, α_k the angle at p between v_k and v_(k+1)). A point on the outline is first moved
    1e-6 of the way to the centroid (where the formula degenerates)."""
    v = np.asarray(polygon, float)
    p = np.asarray(point, float)
    p = p + 1e-6 * (v.mean(axis=0) - p)
    d = v - p
    r = np.linalg.norm(d, axis=1)
    nxt = np.roll(d, -1, axis=0)
    alpha = np.arctan2(d[:, 0] * nxt[:, 1] - d[:, 1] * nxt[:, 0], np.sum(d * nxt, axis=1))
    t = np.tan(alpha / 2)
    w = (np.roll(t, 1) + t) / r
    return w / w.sum()


# --------------------------------------------------------------------------------------------
# The solver: BFGS with a line search that remembers its step
# --------------------------------------------------------------------------------------------
class _SearchState(eqx.Module):
    step_size: jax.Array


class RememberingArmijo(optx.AbstractSearch):
    """Backtracking Armijo line search that starts each step where the last one was accepted.

    A trial y_eval = y + α d (d the quasi-Newton direction) is accepted when
    f(y_eval) - f(y) <= slope · ∇f(y)·(y_eval - y) with ∇f(y)·(y_eval - y) <= 0. After a
    rejection α ← t α, t the minimiser of the parabola through f(y), its slope along the step and
    f(y_eval) (Δ = f(y_eval) - f(y), p = ∇f(y)·(y_eval - y): t = -p / (2 (Δ - p))), kept within
    [`shrink`, `decrease`] (safeguarded quadratic backtracking); after an acceptance
    α ← min(1, `increase` α), where optimistix's `BacktrackingArmijo` restarts from α = 1.

    Why remember: the penalties of `vdo.constraints` are 0 on the feasible side and rise steeply
    behind it (a camera body entering a light's cone), which BFGS's curvature model, built from
    accepted points where they vanish, cannot see; every full step then runs into a wall and is
    halved 4-12 times (measured on the built-in experiment: 7 of 40
    steps accepted in a penalty round; with this search 18 of 40, and a lower score). The
    parabola matters after a visibility refresh: a stiff penalty term (the shadow penalty, just
    active) dominates the gradient, and the first step overshoots by a factor ~1000: halving took
    13 rejections there (measured on the built-in experiment; with the parabola, 28 of the first
    penalty round's 40 steps are accepted, against 16)."""

    decrease: float = 0.5
    shrink: float = 0.1
    increase: float = 2.0
    slope: float = 0.1

    def init(self, y, f_info_struct):
        del y, f_info_struct
        return _SearchState(jnp.array(1.0))

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        predicted = f_info.compute_grad_dot(jax.tree_util.tree_map(lambda a, b: a - b, y_eval, y))
        change = f_eval_info.as_min() - f_info.as_min()
        armijo = change <= self.slope * predicted
        accept = first_step | (armijo & (predicted <= 0))
        # after a rejection: the minimiser of the parabola through f(y), its slope and f(y_eval),
        # as a fraction of the step, kept within [shrink, decrease]
        curvature = change - predicted
        fraction = jnp.where((predicted < 0) & (curvature > 0),
                             -predicted / (2 * jnp.where(curvature > 0, curvature, 1.0)), self.decrease)
        fraction = jnp.clip(fraction, self.shrink, self.decrease)
        step_size = jnp.where(accept, jnp.minimum(1.0, self.increase * state.step_size),
                              fraction * state.step_size)
        return step_size, accept, optx.RESULTS.successful, _SearchState(step_size)


def with_inverse_hessian(state, inverse_hessian):
    """BFGS's state from `init` (`BFGS`) with its inverse-Hessian estimate replaced by
    `inverse_hessian` (n, n) instead of the identity. The first step keeps it (its update sees
    y_eval - y = 0 and leaves the estimate alone), so the second evaluates y - H ∇f(y)."""
    dtype = state.f_info.hessian_inv.pytree.dtype
    return eqx.tree_at(lambda s: s.f_info.hessian_inv.pytree, state,
                       jnp.asarray(inverse_hessian, dtype=dtype))


class BFGS(optx.AbstractBFGS):
    """optimistix's BFGS (inverse-Hessian update, Newton direction) with `RememberingArmijo`."""

    rtol: float
    atol: float
    norm: object
    use_inverse: bool
    descent: optx.NewtonDescent
    search: RememberingArmijo
    verbose: object

    def __init__(self, rtol: float, atol: float):
        self.rtol, self.atol, self.norm, self.use_inverse = rtol, atol, optx.max_norm, True
        self.descent = optx.NewtonDescent()
        self.search = RememberingArmijo()
        self.verbose = lambda **kwargs: None


# --------------------------------------------------------------------------------------------
# Stopping early, and what a run shares
# --------------------------------------------------------------------------------------------
class Stop:
    """A request to end the search early, checked between solver steps and between rounds (never
    inside a JAX or Dr.Jit call): `request` sets it (a signal handler, a caller), and so does the
    clock once `time_limit` seconds have passed since it was made. `reason` is None,
    "time_limit" or "interrupted"."""

    def __init__(self, time_limit: float = math.inf):
        self.deadline = time.perf_counter() + time_limit
        self.reason: str | None = None

    def request(self, reason: str = "interrupted") -> None:
        if self.reason is None:
            self.reason = reason

    def __call__(self) -> bool:
        """True once a stop was requested or the time limit has passed."""
        if self.reason is None and time.perf_counter() >= self.deadline:
            self.reason = "time_limit"
        return self.reason is not None

    @property
    def left(self) -> float:
        """Seconds to the time limit (inf without one)."""
        return max(self.deadline - time.perf_counter(), 0.0)


@contextlib.contextmanager
def stop_on_signals(stop: Stop):
    """While inside: SIGINT (Ctrl-C) and SIGTERM request `stop` instead of raising; a second
    SIGINT raises KeyboardInterrupt as usual. The previous handlers come back on exit. Outside the
    main thread (where Python delivers no signals) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, frame):
        if signum == signal.SIGINT and stop.reason == "interrupted":
            raise KeyboardInterrupt
        stop.request("interrupted")
        log.warning("%s: stopping after the current step; the best layout so far will be written "
                    "(Ctrl-C again to abort without writing)", signal.Signals(signum).name)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


class _Run:
    """What the starts and lens trials of one run share: the compiled solver programs (one pair
    per structure, `Parameterization.signature`; the layout's arrays are their argument,
    `Problem.data`, so another start or lens reuses them), the obscuration term, the record of
    accepted solver step (`history`, what the rounds returned) and exact verdict (`verdicts`), the best
    verdict so far, the fixed size of the pair lists, each round's outcome, the stop request and the
    progress line."""

    def __init__(self, n_cameras: int, max_obscuration: float):
        self.obscuration = ObscurationTerm(n_cameras, max_obscuration)
        self.history: list[dict] = []
        self.verdicts: list[dict] = []
        self.best: "Result | None" = None
        self.t0 = time.perf_counter()
        self.stop = Stop()
        self.blocks = None   # (block, blocks, chunk) of every pair list
        self.progress = _Progress(None)
        self.rounds: list[dict] = []  # each round's `RoundOutcome.record`
        self.ends: list[str] = []     # how each start ended
        self._programs: dict = {}
        self._sizes: dict = {}

    def size(self, name: str, n: int) -> int:
        """The run's padded length of the array `name` that holds n rows now: set once
        (`Problem._size_local_sets`, `objective.bucket`) so that the compiled programs keep their
        shapes while `Problem.local` moves; a longer array raises it (a new compile)."""
        if name not in self._sizes or self._sizes[name] < n:
            self._sizes[name] = bucket(max(n, 1))
        return self._sizes[name]

    def programs(self, problem: "Problem"):
        """(init, step): BFGS's init and one step on `problem._scaled`, jit-compiled once per
        structure (`Parameterization.signature`) and per presence of tracked obscuration (the
        first problem of a structure defines the traced function; the others differ from it only
        in `Problem.data`, passed in `args`). Without obscuration the programs hold no host
        callback, so the persistent compilation cache (JAX_COMPILATION_CACHE_DIR) can serve them
        to the next run (JAX keys a program with a callback by the callback's address)."""
        obscured = bool(self.obscuration.tracked)
        key = (problem.param.signature, obscured)
        if key not in self._programs:
            solver = BFGS(rtol=1e-6, atol=1e-6)
            fn = lambda y, args: problem._scaled(y, args, obscured)
            f_struct = jax.ShapeDtypeStruct((), jnp.float64)
            aux_struct = {k: f_struct for k in ("score", *PENALTIES)}
            self._programs[key] = (
                eqx.filter_jit(lambda y, args: solver.init(fn, y, args, {}, f_struct, aux_struct, frozenset())),
                eqx.filter_jit(lambda y, args, state: solver.step(fn, y, args, {}, state, frozenset())[:2]))
        return self._programs[key]

    def padded(self, views: objective.ViewData) -> objective.ViewData:
        """`views` with padding blocks (occlusion 0: weight and gradient exactly 0) up to the
        run's fixed block count, so that every pair list of the run has the same shapes and the
        programs compile once: the first list sets it with 25 % headroom, a longer one raises it."""
        L = views.block
        B = views.camera.shape[0] // L
        if self.blocks is None or self.blocks[0] != L or self.blocks[1] < B:
            chunk = views.chunk
            self.blocks = (L, -(-int(1.25 * B) // chunk) * chunk, chunk)
        return views.padded(self.blocks[1], self.blocks[2])


class _Progress:
    """One progress line (tqdm) over the planned solver steps: start, round, step, the best
    score so far (µm; feasible layouts first) and the time left, the least of the time limit
    and the steps left at the mean time per step so far (refreshes and checks included)."""

    def __init__(self, planned: int | None, stop: Stop | None = None):
        self.planned, self.stop, self.done = planned, stop, 0
        self.t0 = time.perf_counter()
        self.bar = bar(log, total=planned, desc="optimize", unit="step", disable=planned is None,
                       bar_format="{desc}: {n}/{total} steps{postfix}", dynamic_ncols=True)

    def left(self) -> float:
        rate = (time.perf_counter() - self.t0) / max(self.done, 1)
        est = rate * max((self.planned or 0) - self.done, 0)
        return min(est, self.stop.left) if self.stop is not None else est

    def step(self, where: str, best: "Result | None") -> None:
        self.done += 1
        if best is None:
            text = "no layout judged yet"
        else:
            text = f"best {best.score:.4g} µm" + ("" if best.violations == 0 else
                                                  f" ({best.violations} violation(s))")
        self.bar.set_postfix_str(f"{where}, {text}, ~{self.left():.0f} s left", refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


# --------------------------------------------------------------------------------------------
# A script's own objective: the mount variables -> differentiable per-sample fields
# --------------------------------------------------------------------------------------------
class MountModel:
    """The mount variables of an experiment and the per-sample fields they give, differentiable
    with JAX: what `vdo optimize` moves, built from its `Problem` (the same parameterisation,
    samples, speckle, lighting and ray cast).

    theta (P,), the optimizer's unconstrained variables (`Parameterization`), one per free
    parameter ([optimize] free) of each moving camera ([optimize] cameras), named in `names`:
    "cam.u": logit of the rail parameter (u = sigmoid(θ), 0..1 along the rail); "cam.x", "cam.y",
    "cam.z": logit of the fraction of a zone's box along that axis (over a floor polygon
    "cam.w1", ...: softmax logits of its corners against the first, and "cam.z"); "cam.pan",
    "cam.tilt" (rad): offsets from the direction to the camera's aim point when its position is
    free (`vdo.model.camera.aim_point`: sliding keeps the same point in the middle of the image),
    else absolute; "cam.roll" (rad). `theta0` is the configured layout. focal_mm (C,) the focal
    length of every camera in mm, a continuous variable (default the configured lenses).

    `fields(theta, focal_mm, views)` is traceable: `jax.grad(lambda t: f(model.fields(t)))`
    works for any JAX function f of the `vdo.objective.SampleFields`. The ray-cast occlusion and
    the lighting are frozen at the layout `views` was cast at (default the configured one;
    `refresh(theta)` casts them at θ), as within one round of `vdo optimize`. `float64`: the
    per-pair work in float64 (for checks against finite differences; the optimizer's float32
    pairs carry ~1e-7 relative rounding)."""

    def __init__(self, exp: Experiment, float64: bool = False):
        self.problem = problem = Problem(exp)
        if float64:
            problem.settings = dataclasses.replace(problem.settings, pair_dtype="float64")
        self.theta0 = problem.param.theta0.copy()
        self.names = [""] * len(self.theta0)
        for cam, idx in zip(problem.cams0, problem.param.index):
            for name, k in idx.items():
                self.names[k] = f"{cam.name}.{name}"
        self.focal0_mm = np.array([c.focal_length * 1e3 for c in problem.cams0])
        self.pixel_size = jnp.asarray([c.pixel_size for c in problem.cams0])
        self.views = problem.start.views

    def camera_params(self, theta, focal_mm=None) -> objective.CameraParams:
        """The cameras at (θ, focal_mm) as `vdo.objective.CameraParams` (traceable)."""
        data = self.problem.data
        pos, pan, tilt, roll = self.problem.param.poses(jnp.asarray(theta), data["held"])
        f = data["focal_px"] if focal_mm is None else jnp.asarray(focal_mm) * 1e-3 / self.pixel_size
        size = data["size"]
        return objective.CameraParams(pos, pan, tilt, roll, f, data["cx"], data["cy"], size[:, 0],
                                      size[:, 1], data["distortion"])

    def fields(self, theta, focal_mm=None, views=None) -> objective.SampleFields:
        """The per-sample fields at (θ, focal_mm) (`vdo.objective.sample_fields`), traceable."""
        p = self.problem
        return objective.sample_fields(self.camera_params(theta, focal_mm), p.obj_samples,
                                       self.views if views is None else views, p.speckle.table,
                                       p.settings)

    def refresh(self, theta) -> objective.ViewData:
        """The ray cast and lighting at θ, as the frozen `views` of `fields`."""
        return self.problem.refresh(np.asarray(theta, dtype=float)).views

    def cameras_at(self, theta) -> list[Camera]:
        """The `vdo.model.camera.Camera`s at θ (configured lenses)."""
        return self.problem.param.cameras_at(np.asarray(theta, dtype=float))

    def experiment_at(self, theta) -> Experiment:
        """The experiment with its cameras at θ (rail parameter, zone position, pan/tilt/roll),
        e.g. for `vdo.layout_state` or writing with `vdo.write_evaluation`."""
        return self.problem.exp.with_cameras(self.problem.param.specs_at(np.asarray(theta, dtype=float)))


def check_objective(user_objective, exp: Experiment) -> None:
    """Refuse, in one line (`ConfigError`), a user objective that is not callable, not
    JAX-traceable or not a real scalar: it is traced once on four placeholder samples
    (`jax.eval_shape`, no computation) before any heavy work."""
    name = getattr(user_objective, "__name__", type(user_objective).__name__)
    where = f"objective {name}"
    if not callable(user_objective):
        raise ConfigError("optimize_experiment", where, "must be a function of vdo.objective.SampleFields "
                                                        "returning a scalar")
    n, r = 4, len(exp.regions)
    f = jax.ShapeDtypeStruct
    probe = objective.SampleFields(
        information=f((n, 3, 3), jnp.float64), sigma_xyz=f((n, 3), jnp.float64),
        sigma_max=f((n,), jnp.float64), coverage=f((n,), jnp.float64), area=f((n,), jnp.float64),
        region=f((n,), jnp.int64), importance=f((r,), jnp.float64), min_cameras=f((r,), jnp.float64))
    try:
        out = jax.eval_shape(user_objective, probe)
    except Exception as exc:   # any failure to trace: numpy on a tracer, float(), a Python branch
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ConfigError("optimize_experiment", where,
                          f"is not JAX-traceable ({type(exc).__name__}: {first[:160]}); write it with "
                          "jax.numpy on the fields' arrays (no numpy, float() or if on their values)") from None
    shape = getattr(out, "shape", None)
    if shape != () or not jnp.issubdtype(out.dtype, jnp.floating):
        raise ConfigError("optimize_experiment", where,
                          f"returns {'shape ' + str(shape) if shape is not None else type(out).__name__}"
                          f"{'' if shape != () else ' of ' + str(out.dtype)}; return one real "
                          "number, e.g. jnp.sum(fields.area * fields.sigma_max) / jnp.sum(fields.area)")


# --------------------------------------------------------------------------------------------
# The solver loop
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Result:
    """A judged layout of `problem` (the lenses it was built with) at θ."""

    theta: np.ndarray
    state: State
    score: float
    checks: list
    violations: int
    start: int
    problem: "Problem"

    @property
    def rank(self):
        """Feasible first, by score; else fewest violations, then least total excess."""
        return (self.violations, sum(e["excess"] for e in self.checks), self.score)


def judge(problem: Problem, theta, state: State, start: int) -> Result:
    """The exact verdict on a refreshed layout: score and every constraint checked."""
    checks = problem.check(state)
    result = Result(np.asarray(theta, float), state, problem.exact_score(state), checks,
                    sum(not e["met"] for e in checks), start, problem)
    run = problem.run
    run.verdicts.append(dict(start=start, wall_s=time.perf_counter() - run.t0,
                             score=result.score, violations=result.violations, theta=result.theta))
    if run.best is None or result.rank < run.best.rank:
        run.best = result   # the best layout of the run so far, whatever stops it
    return result


def _violated(result: Result) -> str:
    """The violated constraints in a few words, e.g. 'axis_angle cam1/cam9; clearance cam2'."""
    return "; ".join(f"{e['constraint']} {'/'.join(e.get('cameras', []))}"
                     + (f" {e['region']}" if "region" in e else "") for e in result.checks if not e["met"])


def _backtrack(problem: Problem, before: Result, theta, start: int, judged=None):
    """(θ, state, result) of a round's end: the layout at θ refreshed and judged (`judged`:
    its (state, result) when a checkpoint judged it already). Within a round
    the ray-cast visibility is frozen, so the solver can move a camera where the refresh then
    finds a counted view hidden (behind an obstacle, or by a part that moves along the load
    path): when the layout ranks worse than `before`, the round's start, the move is halved,
    up to `BACKTRACKS` times, and the first layout that ranks no worse is kept; if none does,
    the round's start."""
    for _ in range(BACKTRACKS + 1):
        state, result = judged or (None, None)
        if judged is None:
            state = problem.refresh(theta)
            result = judge(problem, theta, state, start)
        judged = None
        if result.rank <= before.rank or problem.run.stop():
            return theta, state, result
        theta = before.theta + 0.5 * (np.asarray(theta) - before.theta)
    return before.theta, before.state, before


def solve(problem: Problem, starts: int | None = None, first_label: int = 0) -> list[Result]:
    """Every start, every round, until they end or `problem.run.stop`; per start the best layout
    met at the end of a round (or the start itself), judged exactly (`Result.rank`); returns
    them sorted best first. Start k > 0 perturbs the hand layout at random; starts are labelled
    from `first_label` in the records; each round's end is logged (INFO)."""
    opt = problem.exp.optimize
    run = problem.run
    rng = np.random.default_rng(opt.seed)
    results = []
    n_starts = opt.starts if starts is None else starts
    for k_start in range(n_starts):
        if results and run.stop():
            break
        start = first_label + k_start
        theta = problem.param.theta0.copy()
        if k_start > 0:
            theta = theta + _perturbation(problem.param, rng)
        state = problem.start if k_start == 0 else problem.refresh(theta)   # hand layout: cast once
        best = result = judge(problem, theta, state, start)
        masked = frozenset()   # the (camera, region) pairs whose obscuration this start tracks
        label = 0
        end = Status.CONVERGED
        curvature = None   # (weights, `RoundOutcome.curvature`) of the last round

        def one_round(w_score, mu, name):
            nonlocal theta, state, result, best, label, masked, end, curvature
            masked = problem.track_obscured(state, result.checks, masked)
            where = f"start {start + 1} {name}"
            checked = {}   # the last layout judged within the round

            def checkpoint(at) -> bool:
                """Judge the round's iterate (in a penalty round only once `CHECKPOINT_S` have
                passed since the run's last verdict); True (end the round) in a feasibility round
                once it meets every constraint."""
                nonlocal best
                if w_score != 0 and time.perf_counter() - run.t0 - run.verdicts[-1]["wall_s"] < CHECKPOINT_S:
                    return False
                checked.update(theta=at, state=problem.refresh(at))
                checked["result"] = judge(problem, at, checked["state"], start)
                best = min(best, checked["result"], key=lambda r: r.rank)
                return w_score == 0 and checked["result"].violations == 0

            warm = curvature[1] if curvature is not None and curvature[0] == (w_score, mu) else None
            outcome = _round(problem, theta, state.views, (w_score, mu), opt.max_steps, where, (start, label),
                             checkpoint, warm)
            if outcome.curvature is not None:
                curvature = (w_score, mu), outcome.curvature
            run.history.extend(outcome.history)
            record = dict(outcome.record(start, name), score_weight=w_score, penalty_weight=mu,
                          curvature_from_last_round=warm is not None, violations=result.violations)
            run.rounds.append(record)   # `violations`: of the layout the round ends at
            end = outcome.status
            label += 1
            if np.array_equal(outcome.theta, theta):
                return
            judged = None   # the round's end, when its last checkpoint judged it already
            if checked and np.array_equal(checked["theta"], outcome.theta):
                judged = checked["state"], checked["result"]
            theta, state, result = _backtrack(problem, result, outcome.theta, start, judged)
            record["violations"] = result.violations
            best = min(best, result, key=lambda r: r.rank)
            log.info("  start %d %s: score %.4g µm, %d violation(s) %s%s", start + 1, name, result.score,
                     result.violations, _violated(result),
                     "" if outcome.status in ("converged", "max_steps") else f" (ended: {outcome.reason})")

        # from a layout that violates a constraint: the penalties alone, until it meets them all
        for k in range(FEASIBILITY_ROUNDS):
            if result.violations == 0 or run.stop():
                break
            one_round(0.0, 1.0, f"feasibility round {k + 1}")
        mu = MU0
        for k in range(opt.rounds):
            if run.stop():
                break
            previous = result
            one_round(1.0, mu, f"round {k + 1}/{opt.rounds}")
            if result.violations:
                mu *= 10.0
            if (k > 0 and previous.violations == 0 and result.violations == 0
                    and previous.score - result.score < ROUND_TOL * previous.score):
                end = Status.CONVERGED   # the penalty continuation has nothing left
                break
        results.append(best)
        run.ends.append(end)
    return sorted(results, key=lambda r: r.rank)


def choose_lenses(problem: Problem, best: Result) -> Result:
    """The discrete choice over `[optimize] lenses` by screening: every (moving camera, other
    focal length) option is judged once at the best layout so far (its positions and aims; a
    camera in a zone steps along its axis by the ratio of the focal lengths, clipped to the zone
    and aimed at the same point, so that the regions keep their image size; one ray cast and the exact score and checks, no
    optimisation), the options are ranked by score
    and only the `LENS_TRIALS` best are optimised again (`solve`, one start, feasibility rounds
    first if the option breaks a constraint; a camera on a rail cannot step back, so an option
    that screens worse than the current layout may still win), one camera at a time; an option is kept when its optimised layout ranks better (`Result.rank`). Constraints keep the hand layout's meaning
    (`Problem(reference=...)`); the stereo-angle rule follows the new lenses. Every screened and
    optimised option is logged (INFO)."""
    run = problem.run
    moving = [i for i, idx in enumerate(problem.param.index) if idx]

    centre = problem.geometry.centre

    def trial(current: Result, c: int, focal: float) -> Problem:
        specs = current.problem.param.specs_at(current.theta)
        specs[c] = dataclasses.replace(specs[c], focal_length=focal)
        zone = problem.param.zones[c]
        if zone is not None and Parameterization.moves(problem.param.index[c]):
            # in a zone, step along the axis so that the regions keep their size in the image
            cam = current.state.cameras[c]
            aim = aim_point(cam, centre)
            depth = float((aim - cam.position) @ cam.optical_axis)
            ratio = focal / current.problem.exp.camera_specs[c].focal_length
            moved = np.clip(aim - ratio * depth * cam.optical_axis, zone.low, zone.high)
            if zone.floor is not None and not zone.inside(moved[:2]):
                moved = cam.position   # not over the floor: screen it where it stands
            specs[c] = dataclasses.replace(specs[c], position=moved, target=aim)   # aimed again
        return Problem(current.problem.exp.with_cameras(specs), reference=problem)

    options = []
    label = max(v["start"] for v in run.verdicts) + 1
    for c in moving:
        for focal in problem.exp.camera_specs[c].lenses or problem.exp.optimize.lenses:
            if run.stop():
                break
            if math.isclose(focal, best.problem.exp.camera_specs[c].focal_length, rel_tol=1e-9):
                continue
            t = trial(best, c, focal)
            screened = judge(t, t.param.theta0, t.start, label)
            options.append((screened.score, c, focal))
            log.info("  lens %s %g mm at the current layout: score %.4g µm, %d violation(s)",
                     problem.cams0[c].name, focal * 1e3, screened.score, screened.violations)
    promising = sorted(options)[:LENS_TRIALS]   # moving and aiming may recover what screening lost
    changed = set()
    for _, c, focal in promising:
        if run.stop() or c in changed:
            continue
        label = max(v["start"] for v in run.verdicts) + 1
        result = solve(trial(best, c, focal), starts=1, first_label=label)[0]
        kept = result.rank < best.rank
        log.info("  lens %s %g mm optimised: score %.4g µm, %d violation(s)%s", problem.cams0[c].name,
                 focal * 1e3, result.score, result.violations, " (kept)" if kept else "")
        if kept:
            best = result
            changed.add(c)
    return best


@dataclasses.dataclass(frozen=True)
class RoundOutcome:
    """One BFGS solve (`_round`): θ at its last accepted step, how it ended (`status`:
    "converged", "max_steps", "feasible" (a feasibility round that met every constraint at a
    checkpoint), "time_limit", "interrupted" or "failed"; `reason` in words),
    optimistix's `Solution` (value: y, the scaled step from the round's start; result; aux: the
    terms at y; stats: num_steps, num_accepted_steps, max_steps; state: the solver state), the
    terms at every accepted step (`history`: start, round, wall_s, score, the penalties) and
    `curvature`: BFGS's estimate of the inverse Hessian of J (not J / norm) in the scaled
    variables at the round's end, (n, n), or None when the round accepted fewer than 2 steps."""

    theta: np.ndarray
    status: Status
    reason: str
    solution: optx.Solution | None
    history: tuple[dict, ...]
    curvature: np.ndarray | None = None

    def record(self, start: int, name: str) -> dict:
        """The round for optimizer.json."""
        stats = {} if self.solution is None else {k: int(v) for k, v in self.solution.stats.items()}
        result = "" if self.solution is None else optx.RESULTS[self.solution.result]
        return dict(start=start, round=name, status=self.status, reason=self.reason,
                    solver_result=result or "successful", **stats)


def _round(problem: Problem, theta, views, weights, max_steps: int, where: str,
           label: tuple[int, int], checkpoint=None, curvature=None) -> RoundOutcome:
    """One BFGS solve of J (`Problem._total`) in scaled variables y = (θ - θ_start) / scale, with J
    divided by the largest scaled gradient component at the start, so that the first quasi-Newton
    step moves about one natural unit (`Parameterization.scale`) along the steepest parameter.
    The solver runs step by step (one compiled step per call, `_Run`), checking the stop
    request between steps; `label` (start, round) tags the history rows. A step that leaves the
    solver's iterate, its value or gradient non-finite ends the round ("failed", with the
    reason): it is never replaced. With a `checkpoint` (θ -> bool), every `CHECKPOINT_STEPS` steps
    the last accepted θ, if it moved, is passed to it (`solve` judges it, so that the best layout
    so far is known within a long round); True ends the round there ("feasible").

    With `curvature` (a previous round's `RoundOutcome.curvature`, same weights), BFGS starts
    from that inverse Hessian, times norm, instead of the identity: a round after a visibility
    refresh solves nearly the problem the last one did, and rebuilding the curvature from the
    identity costs it most of its steps (measured on the built-in experiment: of 40 steps, the
    first ~25 gained under 0.1 %, the last few several %)."""
    run = problem.run
    origin = jnp.asarray(theta, dtype=jnp.float64)
    scale = jnp.asarray(problem.param.scale, dtype=jnp.float64)
    weights = jnp.asarray(weights, dtype=jnp.float64)
    data = dict(problem.data, local=problem.local(theta))
    y = jnp.zeros_like(origin)
    args = lambda norm: (origin, scale, jnp.asarray(norm, dtype=jnp.float64), views, weights, data)
    if run.stop():
        return RoundOutcome(np.asarray(theta), run.stop.reason, "stopped before the round", None, ())
    # the first step of a solve accepts its start: there, its gradient is dJ/dy at norm 1
    init, step = run.programs(problem)
    _, probe = step(y, args(1.0), init(y, args(1.0)))
    grad = np.asarray(probe.f_info.grad)
    if not np.all(np.isfinite(grad)):
        return RoundOutcome(np.asarray(theta), "failed", "non-finite gradient at the round's start",
                            None, ())
    norm = float(np.max(np.abs(grad)))
    if norm == 0:
        return RoundOutcome(np.asarray(theta), Status.CONVERGED, "zero gradient at the round's start", None, ())
    solver_args = args(norm)
    state = init(y, solver_args)
    if curvature is not None:
        state = with_inverse_hessian(state, norm * curvature)
    status, reason = Status.MAX_STEPS, f"{max_steps} steps"
    history = []
    judged = np.zeros_like(np.asarray(y))   # the last iterate passed to `checkpoint`
    k = 0
    for k in range(1, max_steps + 1):
        if run.stop():
            status, reason = Status(run.stop.reason), f"stop request after {k - 1} steps"
            k -= 1
            break
        accepted = int(state.num_accepted_steps)
        # the point this step evaluates: the local sets move with it (`Problem.terms`)
        trial = np.asarray(origin + scale * state.y_eval)
        if np.linalg.norm(problem.body_points(trial)[2] - np.asarray(data["local"]["body"]), axis=-1).max() \
                > LOCAL_MOVE / 2:
            data = dict(data, local=problem.local(trial))
            solver_args = (*solver_args[:5], data)
        y_new, state = step(y, solver_args, state)
        if int(state.num_accepted_steps) > accepted:   # the terms at the step just accepted
            history.append(dict(start=label[0], round=label[1], wall_s=time.perf_counter() - run.t0,
                                **{name: float(v) for name, v in state.aux.items()}))
        run.progress.step(f"{where}, step {k}/{max_steps}", run.best)
        finite = {"iterate": y_new, "objective": state.f_info.f, "gradient": state.f_info.grad,
                  "next trial point": state.y_eval}
        bad = [name for name, v in finite.items() if not np.all(np.isfinite(np.asarray(v)))]
        if bad:
            status, reason = Status.FAILED, f"non-finite {', '.join(bad)} at step {k}"
            log.warning("%s: %s; the round ends at its last finite step", where, reason)
            break
        y = y_new
        if bool(state.terminate):
            status, reason = Status.CONVERGED, f"solver tolerance met at step {k}"
            break
        if checkpoint is not None and k % CHECKPOINT_STEPS == 0 and k < max_steps \
                and not np.array_equal(np.asarray(y), judged):
            judged = np.asarray(y)
            if checkpoint(np.asarray(origin + scale * y)):
                status, reason = Status.FEASIBLE, f"every constraint met at step {k}"
                break
        if not bool(state.result == optx.RESULTS.successful):
            status, reason = Status.FAILED, optx.RESULTS[state.result]
            break
    solution = optx.Solution(value=y, result=state.result, aux=state.aux, state=state,
                             stats=dict(num_steps=k, num_accepted_steps=int(state.num_accepted_steps),
                                        max_steps=max_steps))
    estimate = None
    if int(state.num_accepted_steps) >= 2:
        estimate = np.asarray(state.f_info.hessian_inv.pytree) / norm
    return RoundOutcome(np.asarray(origin + scale * y), status, reason, solution, tuple(history), estimate)


def _perturbation(param: Parameterization, rng) -> np.ndarray:
    d = np.zeros_like(param.theta0)
    for idx in param.index:
        for name, k in idx.items():
            d[k] = rng.normal(0, 0.4) if Parameterization.is_position(name) else rng.normal(0, math.radians(3))
    return d


# --------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------
DEFAULT_TIME_LIMIT = 900.0   # s: `vdo optimize --time-limit`


WRITE_S = 5.0   # s: kept at least for writing the run folder (figures, report) after the search


def _wrap_up_s(problem: Problem, steps: int) -> float:
    """Seconds kept from the time limit for what follows the search: the best layout judged
    again for its summary and at each of the load path's `steps`, each about one hand-layout
    refresh (`Problem.refresh_s`, measured at start-up, its compilations included: an upper
    estimate), and the folder written (`WRITE_S`)."""
    return (steps + 2) * problem.refresh_s + WRITE_S


def optimize(exp: Experiment, out: Path, overwrite: bool = False,
             time_limit: float = DEFAULT_TIME_LIMIT, stop: Stop | None = None,
             objective=None, started: float | None = None) -> OptimizeResult:
    """Optimize the layout and write optimized.toml, layout.json, summary_before/after.json,
    constraints.json, optimizer.json, history.csv, convergence.png and moves.csv into `out`.

    `objective`: a user's function of `vdo.objective.SampleFields` returning a JAX scalar,
    minimised instead of the built-in score with the same constraints, penalty rounds,
    visibility refreshes, starts, lens choice and anytime stop (`MountModel` documents the
    fields' variables); refused in one line when it is not traceable or not a scalar
    (`check_objective`). Scale it like the built-in score (a few units at a good layout, e.g.
    micrometres): the penalties weigh ~1 at a clear violation. The returned and written
    score_before/score_after are then its values.

    Anytime: the search ends when every round has run, when the time limit leaves only what
    writing the result needs (`_wrap_up_s`), or on a stop request (SIGINT/SIGTERM while it runs,
    unless the caller passes its own `stop`, which it then owns); in every case the folder is
    written with the best layout judged so far (feasible first, `Result.rank`), and
    optimizer.json says how the search ended. `time_limit` (s, > 0) counts the whole run from
    `started` (a `time.perf_counter()` value, default now; the command line passes its own
    start): start-up (meshes, samples, the hand layout's ray cast, lighting and checks) first,
    then the search gets what is left; when start-up leaves nothing, the starting layout is
    judged and written, with the reason. The log and optimizer.json give start-up and search
    apart (`startup_s`, `search_s`). Progress: INFO lines and a bar through the module logger
    (`vdo.core.progress`)."""
    if not time_limit > 0:
        raise ConfigError("command line", "--time-limit",
                          f"must be a positive number of seconds (got {time_limit}); e.g. --time-limit 600")
    errors = Collect()   # the lens check of `vdo check`, for callers that skip the command line
    errors.errors += lens_catalogue_errors(exp)
    errors.raise_all()
    if objective is not None:
        check_objective(objective, exp)
    own = stop is None
    t_start = time.perf_counter() if started is None else started
    stop = Stop(time_limit) if own else stop
    stop.deadline = min(stop.deadline, t_start + time_limit)
    # start-up: no layout judged yet, so SIGINT/SIGTERM end the run at once (`vdo.core.interrupts`),
    # and its time counts against the limit
    log.info("start-up: meshes, samples, the hand layout's ray cast and lighting, the compiled "
             "programs (Ctrl-C ends the run here, writing nothing)")
    problem = Problem(exp, user_objective=objective)
    run = problem.run
    run.stop = stop
    opt = exp.optimize
    planned = opt.starts * (opt.rounds + 1) * opt.max_steps
    if "lens" in opt.free:
        planned += LENS_TRIALS * (opt.rounds + 1) * opt.max_steps
    log.info("%s samples, %d free parameters, %d camera pairs sharing a region; time limit %g s",
             f"{len(problem.samples):,}", len(problem.param.theta0), len(problem.pairs), time_limit)
    reach = reachability.check(exp, problem.meshes, problem.samples)   # logs a warning per short region
    over_path = load_path_of(exp, problem.meshes)
    kept = _wrap_up_s(problem, len(over_path.steps) if over_path is not None else 0)
    stop.deadline -= kept   # the search ends in time for the result to be judged and written
    startup = time.perf_counter() - t_start
    log.info("start-up took %.0f s of the %g s time limit (%.0f s kept for writing the result); "
             "the search has the rest (%.0f s)", startup, time_limit, kept, stop.left)
    reason = None
    if stop.left == 0:
        reason = (f"start-up took {startup:.0f} s of the {time_limit:g} s time limit ({kept:.0f} s "
                  "kept for writing the result): no time left to search, the starting layout is "
                  f"judged and written; give --time-limit {math.ceil(startup + kept) + 60} or more "
                  "to search")
        log.warning(reason)
    t_search = time.perf_counter()
    with (stop_on_signals(stop) if own else contextlib.nullcontext()):
        run.progress = _Progress(planned, stop)
        try:
            solve(problem)
            if "lens" in opt.free and not stop():
                log.info("lens catalogue: %s mm", ", ".join(f"{f * 1e3:g}" for f in opt.lenses))
                choose_lenses(problem, run.best)
        finally:
            run.progress.close()
    best = run.best
    final = best.problem
    status = Status(stop.reason) if stop.reason else \
        (Status.CONVERGED if all(e == Status.CONVERGED for e in run.ends) else Status.MAX_STEPS)
    search = time.perf_counter() - t_search
    log.info("search ended: %s after %.0f s (start-up %.0f s, search %.0f s); writing %s", status,
             time.perf_counter() - t_start, startup, search, out)
    before = _summary(problem, problem.start)
    after = _summary(final, best.state)
    if over_path is not None:   # the optimized layout judged at every step, as `vdo evaluate` does
        log.info("judging the optimized layout over the %d steps of the load path", len(over_path.steps))
        after = dataclasses.replace(after, load_path=loadpath.summary(loadpath.evaluate_load_path(
            problem.geometry, over_path, best.state.cameras)))
    checks_before = problem.check(problem.start)
    score_before = _score_parts(problem, problem.start)
    score_after = _score_parts(final, best.state)
    if objective is not None:   # the user's objective's values: what was minimised
        score_before["score_um"] = problem.exact_score(problem.start)
        score_after["score_um"] = best.score
        score_before["objective"] = score_after["objective"] = getattr(objective, "__name__", "user")
    joint = _joint_p95(before), _joint_p95(after)
    log.info("best: start %d, score %.4g -> %.4g µm, %d constraint violation(s)", best.start + 1,
             score_before["score_um"], score_after["score_um"], best.violations)
    with run_folder(out, overwrite) as tmp:
        optimized = final.exp.with_cameras(final.param.specs_at(best.theta))
        report.write_config(tmp / "optimized.toml", optimized)
        report.write_json(tmp / "layout.json", report.layout(best.state.cameras))
        report.write_json(tmp / "summary_before.json", before.to_json())
        report.write_json(tmp / "summary_after.json", after.to_json())
        report.write_json(tmp / "constraints.json", {
            "violations": best.violations,
            "violated": [e for e in best.checks if not e["met"]],
            "after": best.checks, "before": checks_before})
        report.write_json(tmp / "optimizer.json", {
            "status": status, "converged": status == "converged",
            "time_limit_s": time_limit if math.isfinite(time_limit) else None,
            "search_wall_s": run.history[-1]["wall_s"] if run.history else 0.0, "startup_s": startup,
            "search_s": search, "reason": reason,
            "rounds": run.rounds, "starts": run.ends, "accepted_steps": len(run.history), "layouts_judged": len(run.verdicts),
            "best_start": best.start, "score_before": score_before, "score_after": score_after,
            "reachability": reach})
        _write_history(tmp / "history.csv", run.history)
        _plot_history(tmp / "convergence.png", run.history, run.verdicts, exp.name)
        _write_moves(tmp / "moves.csv", problem, best)
        html_report.write_report(tmp)
    return OptimizeResult(status=status, score_before_um=score_before["score_um"], score_after_um=best.score,
                          startup_s=startup, search_s=search, reason=reason,
                          score_regions_um=score_after["regions"], reachability=reach,
                          violations=best.violations, joint_p95_um=joint,
                          violated=[e for e in best.checks if not e["met"]], before=before, after=after)


@dataclasses.dataclass(frozen=True)
class OptimizeResult:
    """What `optimize` returns: how the search ended, the score of the hand layout and of the best
    one (µm, the smooth σ_max percentile plus the coverage term, `_score_parts`; the user's
    objective's values when one was given), and the two layouts judged as `vdo evaluate` judges
    them (`before`, `after`: summary_before.json and summary_after.json are their `to_json()`)."""

    status: Status                              # how the search ended (optimizer.json "status")
    score_before_um: float                      # score of the hand layout
    score_after_um: float                       # score of the best layout kept
    startup_s: float                            # s of the time limit spent before the search
    search_s: float                             # s the search itself ran
    reason: str | None                          # why it ended where it did, in words (None: all rounds ran)
    score_regions_um: dict[str, dict]           # region -> `_score_parts` (µm and fractions), best layout
    reachability: list[dict]                    # per region, `vdo.search.reachability.check`
    violations: int                             # constraint checks the best layout breaks
    joint_p95_um: tuple[float | None, float | None]   # worst σ_max p95 of the joint* regions, before/after
    violated: list[dict]                        # those checks (constraints.json "violated")
    before: report.EvaluationResult             # the hand layout
    after: report.EvaluationResult              # the best layout (with its load path, when configured)

    def to_json(self) -> dict:
        """The figures as a JSON dict: score_before, score_after (µm), startup_s, score_regions_um,
        status (its value), reachability, violations, joint_p95_um [before, after], violated."""
        return {"score_before": self.score_before_um, "score_after": self.score_after_um,
                "startup_s": self.startup_s, "search_s": self.search_s, "reason": self.reason,
                "score_regions_um": self.score_regions_um,
                "status": self.status.value, "reachability": self.reachability,
                "violations": self.violations, "joint_p95_um": list(self.joint_p95_um),
                "violated": self.violated}


def _summary(problem: Problem, state: State) -> report.EvaluationResult:
    """`vdo evaluate`'s summary of a round's layout: the one prediction of `vdo.physics.predict` (usable
    views, clipped patches) on the round's ray cast and lighting."""
    pred = predict(problem.exp, list(state.cameras), problem.samples, state.vis, state.illumination,
                   problem.speckle, overlap=problem.geometry.overlap)
    return report.evaluation(problem.exp, problem.samples, state.vis, pred)


def _score_parts(problem: Problem, state: State) -> dict:
    """The score in physical units: overall (what the optimizer minimises, µm) and per region,
    each the smooth percentile of σ_max it is (`vdo.objective`: the power mean
    (Σ ω σ^q / Σ ω)^(1/q) of the smooth σ_max over the region's samples, ω = area, q =
    `score_power`), plus the coverage term (µm; 0 when every sample has its minimum camera count),
    and the area fraction that is unmeasured (fewer than two usable views: its σ counts as the
    prior, `Settings.prior_sigma`, 1 mm, so a few percent of it dominates the power mean)."""
    st = problem.settings
    f = objective.fields(objective.CameraParams.from_cameras(state.cameras), problem.obj_samples,
                         state.views, problem.speckle.table, st)
    sigma = np.asarray(f.sigma_max_smooth) / st.sigma_unit
    smp = problem.obj_samples
    region, area = np.asarray(smp.region), np.asarray(smp.area)
    omega = area * np.asarray(smp.importance)[region]
    q = st.score_power
    mean = lambda w, x: float((np.sum(w * x ** q) / np.sum(w)) ** (1 / q)) if np.sum(w) > 0 else None
    short = np.maximum(np.asarray(smp.min_cameras)[region] - np.asarray(f.coverage), 0.0)
    unmeasured = ~np.asarray(f.measured)
    regions = {name: dict(sigma_smooth_um=mean(area * (region == r), sigma),
                          coverage_um=float(st.coverage_weight * np.sum(area * (region == r) * short ** 2)
                                            / np.sum(area * (region == r))),
                          unmeasured_fraction=float(np.sum(area * (region == r) * unmeasured)
                                                    / np.sum(area * (region == r))),
                          scored=bool(np.asarray(smp.importance)[r] > 0))
               for r, name in enumerate(problem.samples.region_names)}
    overall = mean(omega, sigma)
    coverage = float(st.coverage_weight * np.sum(omega * short ** 2) / np.sum(omega))
    return dict(score_um=overall + coverage, sigma_smooth_um=overall, coverage_um=coverage,
                power=q, regions=regions)


def _joint_p95(summary: report.EvaluationResult):
    values = [r.sigma_max_um.p95 for name, r in summary.regions.items()
              if name.startswith("joint") and r.sigma_max_um.p95 is not None]
    return max(values) if values else None


def _write_history(path, history):
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, ["step", "start", "round", "wall_s", "score", *PENALTIES])
        writer.writeheader()
        for i, row in enumerate(history):
            writer.writerow({"step": i, **row})


def _plot_history(path, history, verdicts, name):
    """Score (log scale when it spans more than a factor 10) at every accepted solver step (thin
    line) and the exact score of each judged layout (markers: filled where it meets every
    constraint; each round's end, and the checkpoints within rounds), per start; layouts judged
    without a solve (lens screening) as crosses."""
    fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
    solved = sorted({h["start"] for h in history})
    for s in solved:
        rows = [h for h in history if h["start"] == s]
        line, = ax.plot([h["wall_s"] for h in rows], [h["score"] for h in rows], lw=0.6, alpha=0.5,
                        label=f"start {s + 1}: accepted steps")
        for feasible in (True, False):
            v = [r for r in verdicts if r["start"] == s and (r["violations"] == 0) == feasible]
            ax.plot([r["wall_s"] for r in v], [r["score"] for r in v], "o", ms=6,
                    color=line.get_color(), mfc=line.get_color() if feasible else "white",
                    label=f"start {s + 1}: judged layout, {'feasible' if feasible else 'violates a constraint'}")
    screened = [r for r in verdicts if r["start"] not in solved]
    if screened:
        ax.plot([r["wall_s"] for r in screened], [r["score"] for r in screened], "x", color="0.4",
                label="lens options screened at the best layout")
    scores = [r["score"] for r in verdicts] + [h["score"] for h in history]
    if scores and max(scores) > 10 * min(scores):   # e.g. from unmeasured points to a few µm
        ax.set_yscale("log")
    ax.set_xlabel("wall time (s)")
    ax.set_ylabel("score (smooth σ_max, µm, + coverage)")
    ax.set_title(f"{name}: convergence")
    if verdicts:
        ax.legend(fontsize=7)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _write_moves(path, problem: Problem, best: Result):
    """Per camera: its mount (rail or zone), rail position (mm along the bar), pan, tilt (deg),
    focal length (mm) and optical centre (m), before (`problem`, the hand layout) and after (`best`)."""
    u0, u1 = problem.param.u(problem.param.theta0), best.problem.param.u(best.theta)
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["camera", "mount", "rail_position_mm_before", "rail_position_mm_after",
                         "pan_deg_before", "pan_deg_after", "tilt_deg_before", "tilt_deg_after",
                         "focal_mm_before", "focal_mm_after", "x_m_before", "y_m_before", "z_m_before",
                         "x_m_after", "y_m_after", "z_m_after"])
        for i, (a, b) in enumerate(zip(problem.cams0, best.state.cameras)):
            rail = problem.param.rails[i]
            along = [f"{rail.arc_length(u) * 1e3:.1f}" if rail else "" for u in (u0[i], u1[i])]
            writer.writerow([a.name, rail.name if rail else problem.exp.camera_specs[i].mount or "", *along,
                             f"{math.degrees(a.pan):.2f}", f"{math.degrees(b.pan):.2f}",
                             f"{math.degrees(a.tilt):.2f}", f"{math.degrees(b.tilt):.2f}",
                             f"{a.focal_length * 1e3:g}", f"{b.focal_length * 1e3:g}",
                             *(f"{v:.4f}" for v in (*a.position, *b.position))])
