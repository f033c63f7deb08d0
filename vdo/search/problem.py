"""The optimizer's problem: everything an objective evaluation needs, built once per experiment
and lens choice (`Problem`: meshes, samples, lighting, the regions assigned to each camera, the
pair lists frozen by a refresh), the objective

    J(θ) = a_k score(θ) + μ_k [P_angle + P_fov + P_clearance + P_obscuration + P_shadow](θ)

(`Problem.terms`; `vdo.objective.score` and the penalties of `vdo.constraints`, each but
P_obscuration 0 exactly where its constraint holds with a back-off margin), the score in physical
units (`score_parts`), what the starts and lens trials of one run share (`Run`: the compiled
programs, the obscuration term, the history); `vdo.search.mountmodel.MountModel` is the same for a
script's own objective."""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from vdo import constraints
from vdo.search import loadpath
from vdo import objective
from vdo.model.camera import intrinsic_matrix, rotation
from vdo.config.experiment import Experiment
from vdo.physics.lighting import exposure_factors, panel_frame
from vdo.search.obscuration import ObscurationRenderer, ObscurationTerm
from vdo.search.obstruction import CLEARANCE_SPACING, clearances, light_lost, obstacle_visibility, surface_points
from vdo.objective import bucket
from vdo.physics import measured
from vdo.physics.predict import samples_for_objective, settings, view_data
from vdo.state import bodies, layout_state, prepare, unobstructed_lighting
from vdo.scene import SceneMesh, camera_body_points, camera_body_spheres, cameras_of
from vdo.search.parameterisation import Parameterization
from vdo.search.bfgs import BFGS
from vdo.search.anytime import Progress, Stop


PENALTIES = ("angle", "fov", "clearance", "obscuration", "shadow")   # the keys of `Problem.terms` besides score
# Back-off: the penalties aim this far inside each limit, so that the penalty solution, which
# always lies a little beyond what it aims at, meets the exact limit.
ANGLE_MARGIN = math.radians(0.5)   # rad added to each minimum axis angle
CLEARANCE_MARGIN = 0.005           # m added to the clearance
FOV_MARGIN = 0.002                 # added to each least in-image fraction of a region
SHADOW_MARGIN = 0.005              # m added to each body sphere's radius in the shadow penalty
LOCAL_MOVE = 0.1   # m: the clearance and shadow penalties read only what a body point can reach
                   # within this distance of the anchor layout (`Problem.local`)
PATH_SLACK = 0.05  # m: the farthest an optical centre can be from the nearest point of `Problem._paths`
SIZE_PROBES = 1024  # path points per camera from which `Problem._size_local_sets` counts the shadow pairs


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
            self.scene_points = surface_points(list(self.geometry.meshes), spacing=CLEARANCE_SPACING)
            # the lighting with no camera in the scene: what the bodies hide, and the base that
            # each refresh casts again only where a body may be in the way (`layout_state`)
            self.unobstructed = unobstructed_lighting(self.geometry)
        else:
            for name in ("geometry", "scene_points", "unobstructed"):
                setattr(self, name, getattr(reference, name))
        self.lit_without_cameras = self.unobstructed.lit if exp.lights else None
        self.meshes, self.samples = list(self.geometry.meshes), self.geometry.samples
        self.faces, self.speckle = list(self.geometry.region_faces), self.geometry.speckle
        self.settings = settings(exp.evaluation)
        self.obj_samples = samples_for_objective(exp.regions, self.samples)
        if opt.regions is not None:   # only the named regions enter the score
            keep = np.array([r.name in opt.regions for r in exp.regions])
            self.obj_samples = dataclasses.replace(
                self.obj_samples, importance=jnp.where(jnp.asarray(keep), self.obj_samples.importance, 0.0))
        self.param = Parameterization(exp, cameras_of(exp.camera_specs, exp.rails), self.geometry.centre)
        self.cams0 = self.param.cameras
        self.run = reference.run if reference is not None else Run(len(self.cams0), opt.max_obscuration)
        self.scene_tree = cKDTree(self.scene_points)
        self.body_local = jnp.asarray(np.stack([camera_body_points(c.focal_length) for c in self.cams0]))
        self.tripods = constraints.tripod_table(self.cams0, constraints.tripods_of(self.cams0, exp.camera_specs, exp.mounts))
        paths = self._paths()
        self.near_sets = constraints.near_points(
            self.scene_points, paths, reach=float(np.abs(self.body_local).max()) * 1.8
            + opt.clearance + CLEARANCE_MARGIN)
        self.near_trees = [cKDTree(p) for p in self.near_sets]
        t0 = time.perf_counter()
        self.kappa_s = 0.0   # s: the last refresh's `measured.noise_inflation` ([optimize] score)
        self.start = self.refresh(self.param.theta0)
        # s: one layout's ray cast, lighting and views, as the judging after the search redoes
        # them (without the score's κ, which it does not compute)
        self.refresh_s = time.perf_counter() - t0 - self.kappa_s
        self.assigned = (constraints.assignments(self.start.vis, self.samples, opt.assign_fraction)
                         if reference is None else reference.assigned)
        self.shared = (constraints.sharing(self.start.vis, self.samples, opt.assign_fraction)
                       if reference is None else reference.shared)
        self.pairs, self.min_angles, self.max_angles = constraints.angle_limits(
            exp.regions, opt, exp.stereo_pairs, self.cams0, self.assigned, self.shared)
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
            tripods=None if self.tripods is None else {k: jnp.asarray(v) for k, v in self.tripods.items()},
            keep_out=tuple(jnp.asarray(np.clip(np.array([getattr(k, a) for k in self.exp.keep_outs]).reshape(-1, 3),
                                               -constraints.KEEP_OUT_FAR, constraints.KEEP_OUT_FAR))
                           for a in ("box_min", "box_max")),
            floors=tuple((jnp.asarray(index), *(jnp.asarray(a) for a in constraints.floor_edges(zone)))
                         for index, zone in constraints.non_convex_floors(self.exp.camera_specs, self.exp.mounts)),
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
        `PATH_SLACK`. An estimate, not a bound: a larger set raises the size (`Run.size`). The
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
        `Run.size`), and the (camera, lit sample) pairs that `constraints.shadow_pairs` keeps for
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
                    keep = zone.inside(grid[:, :2], tol=0.05)
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
        scale = None
        if self.exp.optimize.score == "measured":   # the lab's error over the bound, this round's
            t0 = time.perf_counter()
            e = self.exp
            scale = measured.noise_inflation(e.camera_specs, e.evaluation, e.speckle, e.sensor,
                                             e.analysis, cams, self.samples, scored.visible, illum,
                                             self.speckle)
            self.kappa_s = time.perf_counter() - t0
        return State(np.asarray(theta, float), cams, vis, vis_obstacles, illum,
                     self.run.padded(view_data(self.exp.speckle, self.exp.sensor, self.obj_samples,
                                               scored, illum, self.speckle, noise_scale=scale,
                                               exposure=exposure_factors(self.exp.camera_specs,
                                                                         self.exp.sensor))))

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
            + constraints.keep_out_penalty(pos, *data["keep_out"], CLEARANCE_MARGIN)
            + constraints.floor_penalty(pos, data["floors"], CLEARANCE_MARGIN)
            + (0.0 if data["tripods"] is None else constraints.tripod_penalty(
                *constraints.tripod_legs(pos, R[:, 2, :], pan, data["tripods"]), data["tripods"],
                *data["keep_out"], self.exp.optimize.clearance, CLEARANCE_MARGIN)),
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
                                 self.pairs, self.min_angles, clearances(state.cameras, self.scene_tree),
                                 opt.clearance, opt.max_obscuration, light_lost(self.lit_without_cameras, state.illumination.lit, self.samples),
                                 self.param.u(state.theta), roll_free="roll" in opt.free,
                                 fov_limits=self.fov_limits, max_angles=self.max_angles) \
            + constraints.keep_out_checks(state.cameras, self.exp.keep_outs) \
            + constraints.floor_checks(state.cameras, self.exp.camera_specs, self.exp.mounts) \
            + constraints.tripod_checks(state.cameras, self.tripods, self.exp.keep_outs, opt.clearance)

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
        """The score at the refreshed layout (µm): `score_parts`'s, from the one compiled
        `objective.fields` program that the report also uses (`objective.score` gives the same
        within 1e-7 relative, its pairs in float32, and would be one more program to compile).
        With a `user_objective`, its value at the refreshed layout."""
        if self.user_objective is None:
            return score_parts(self, state)["score_um"]
        programs = self.run._programs
        if "user" not in programs:   # one program per run: the layout's arrays are arguments
            programs["user"] = eqx.filter_jit(lambda cams, views, samples, energy: self.user_objective(
                objective.sample_fields(cams, samples, views, energy, self.settings)))
        return float(programs["user"](objective.CameraParams.from_cameras(state.cameras), state.views,
                                      self.obj_samples, self.speckle.table))


# --------------------------------------------------------------------------------------------
# What the starts and lens trials of one run share
# --------------------------------------------------------------------------------------------
class Run:
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
        self.best: Result | None = None
        self.t0 = time.perf_counter()
        self.stop = Stop()
        self.blocks = None   # (block, blocks, chunk) of every pair list
        self.progress = Progress(None)
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


def score_parts(problem: Problem, state: State) -> dict:
    """The score in physical units: overall (what the optimizer minimises, µm) and per region,
    each the smooth percentile of σ_max it is (`vdo.objective`: the power mean
    (Σ ω σ^q / Σ ω)^(1/q) of the smooth σ_max over the region's samples, ω = area, q =
    `score_power`), plus the coverage term (µm; 0 when every sample has its minimum camera count),
    and the area fraction that is unmeasured (fewer than two usable views: its σ counts as the
    prior, `Settings.prior_sigma`, 1 mm, so a few percent of it dominates the power mean). `sigma`:
    which σ it scores ([optimize] score: "bound" or "measured", `Problem.refresh`)."""
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
                power=q, regions=regions, sigma=problem.exp.optimize.score)


@dataclasses.dataclass
class Result:
    """A judged layout of `problem` (the lenses it was built with) at θ."""

    theta: np.ndarray
    state: State
    score: float
    checks: list
    violations: int
    start: int
    problem: Problem

    @property
    def rank(self):
        """Feasible first, by score; else fewest violations, then least total excess."""
        return (self.violations, sum(e["excess"] for e in self.checks), self.score)
