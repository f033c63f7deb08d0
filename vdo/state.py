"""The layout state: everything that follows from an experiment and its cameras' poses.

Two pure steps, used by every command (`evaluate`, `render`, `optimize`, `validate`, sweeps) and
by the tests, so that the chain camera bodies -> Mitsuba scene -> visibility -> lighting ->
prediction is written once:

* `prepare(exp)` -> `Geometry`: what does not depend on the cameras (the meshes in metres, the
  surface samples of the regions of interest, the speckle model, the samples' patch overlap). Build it once per experiment
  (and per keyframe of a moving test) and reuse it for every camera layout.
* `layout_state(geometry, cameras)` -> `LayoutState`: the scene with the camera bodies as
  obstacles, the ray-cast visibility of every (camera, sample) pair, the light reaching every
  sample, and (unless `predict_fields=False`) the predicted displacement fields (`vdo.physics.predict`)
  and the strain uncertainty for the experiment's `[analysis]` (`vdo.physics.strain`).

Both results are immutable. A camera whose `[[camera]]` entry says `body = false`, or that the
experiment does not list (a probe camera), is not an obstacle; the tripod of a camera on a zone
mount with a [mount.tripod] is one, wherever the camera stands (`bodies`).

This module is the door: the `Experiment` goes no further. The functions below it (meshes, scene,
geometry, information, objective, physics, constraints) take the tables they read, handed out
here; `check_experiment(exp)`, which checks the whole file up front (before either step), stands
here for that reason.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from vdo.physics import measured as measured_model, strain
from vdo.constraints import assignments, stereo_min_angle
from vdo.model.camera import Camera
from vdo.config.experiment import Experiment, lens_catalogue_errors
from vdo.config.rig import CameraSpec
from vdo.config.mounts import inside_floor
from vdo.core.errors import Collect, ConfigError
from vdo.geometry.keyframes import LoadPath, at_step, load_path_of
from vdo.physics.exposure import ExposurePlan, design_exposure, motion_limits
from vdo.physics.glare import satin_samples
from vdo.physics.lighting import Illumination, exposure_factors, illuminate, relight
from vdo.physics.predict import Prediction, SpeckleModel, predict, speckle_model
from vdo.scene import (RegionFaces, SceneMesh, SurfaceSamples, all_region_faces, build_scene, camera_body,
                       cameras_of, load_meshes, sample_regions, surface_raster, tripods)
from vdo.physics.usable import FINE_PATCH_CELLS, patch_overlap
from vdo.physics.visibility import Visibility, compute_visibility

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Geometry:
    """The camera-independent part of an experiment: meshes (metres), samples, speckle."""

    experiment: Experiment
    meshes: tuple[SceneMesh, ...]
    samples: SurfaceSamples
    speckle: SpeckleModel
    region_faces: tuple[RegionFaces, ...]   # the faces each region selects, in config order
    overlap: object    # (N, N) sparse patch-cell overlap of the samples (`vdo.physics.usable.patch_overlap`)
    # the fixed pair-list sizes of the layouts judged on it (`vdo.objective.ViewData.from_dense`):
    # a new camera layout reuses the compiled programs (docs/api.md, "Compilation")
    sizes: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def centre(self) -> np.ndarray:
        """The regions' centroid (m): the mean of the surface samples, the depth at which a moved
        camera keeps its aim (`Experiment.with_camera`, `vdo optimize`)."""
        return self.samples.points.mean(axis=0)

    def with_camera(self, name: str, **fields) -> Experiment:
        """`Experiment.with_camera` on this geometry's experiment, re-aiming at `centre`."""
        return self.experiment.with_camera(name, centre=self.centre, **fields)


@dataclass(frozen=True, eq=False)
class LayoutState:
    """One camera layout judged on one geometry. `scene` is the Mitsuba scene of the meshes and
    the camera bodies (for further ray casts); `prediction` is None when not asked for. `source`
    is the experiment whose settings (lights, sensor, analysis) it was judged with (default: the
    geometry's)."""

    geometry: Geometry
    cameras: tuple[Camera, ...]
    scene: object
    visibility: Visibility
    illumination: Illumination
    prediction: Prediction | None
    strain: tuple | None = None    # (sigma of the strain (N, 3), of the analysis' displacement (N,))
    source: Experiment | None = None

    @cached_property
    def experiment(self) -> Experiment:
        """The experiment this state was judged with, cameras included: `source` (or the
        geometry's experiment) with its [[camera]] tables describing `cameras`
        (`experiment_with_cameras`), the one `write_evaluation` writes as config.toml."""
        return experiment_with_cameras(self.source or self.geometry.experiment, self.cameras)

    @property
    def samples(self) -> SurfaceSamples:
        return self.geometry.samples

    @cached_property
    def measured(self) -> "measured_model.MeasuredFields":
        """σ_measured of this layout for the experiment's [analysis] processing
        (`vdo.physics.measured.measured_fields`, with `experiment`'s tables): what `vdo evaluate`
        writes and `vdo design` scores its curve with."""
        e = self.experiment
        return measured_model.measured_fields(
            e.regions, e.camera_specs, e.evaluation, e.speckle, e.sensor, e.analysis,
            e.stereo_pairs, e.path, list(self.cameras), self.samples, self.visibility,
            self.illumination, self.geometry.speckle, self._predicted(), stereo_min_angle)

    # -- for scripts: the fields in named units, per region ----------------------------------
    def _predicted(self) -> Prediction:
        if self.prediction is None:
            raise ValueError("this layout state was judged with predict_fields=False: call "
                             "vdo.layout_state(geometry, cameras) to predict the fields")
        return self.prediction

    @property
    def coverage(self) -> np.ndarray:
        """(N,) int: the number of usable views of each sample (`vdo.physics.usable`: a camera
        counts where its soft weight reaches `USABLE_WEIGHT`), the coverage of `vdo evaluate`'s
        summary and maps. (`visibility.coverage` is the hard ray-cast count, before the soft
        incidence and image-edge weights: not the one to report.)"""
        return self._predicted().coverage

    @property
    def sigma_max_um(self) -> np.ndarray:
        """(N,) µm: worst-direction displacement uncertainty, NaN where unmeasured (fewer than two
        usable views), as samples.vtp holds it."""
        p = self._predicted()
        return np.where(p.measured, p.sigma_max * 1e6, np.nan)

    @property
    def sigma_xyz_um(self) -> np.ndarray:
        """(N, 3) µm: uncertainty along world x, y, z, NaN where unmeasured."""
        p = self._predicted()
        return np.where(p.measured[:, None], p.sigma_xyz * 1e6, np.nan)

    def region_mask(self, name: str) -> np.ndarray:
        """(N,) bool: the samples of region `name` (ConfigError, one line, for an unknown name)."""
        names = self.samples.region_names
        if name not in names:
            raise ConfigError(self.experiment.path, f"region {name!r}", f"no such region (regions: "
                                                                        f"{', '.join(names)})")
        return self.samples.region == names.index(name)

    def region_stats(self, name: str) -> "RegionStats":
        """The statistics of region `name` (`RegionStats`, the definitions of `vdo evaluate`'s
        summary.json)."""
        mask = self.region_mask(name)
        area = self.samples.area[mask]
        need = self.experiment.regions[self.samples.region_names.index(name)].min_cameras \
            or self.experiment.evaluation.min_cameras
        cov = self.coverage[mask]
        sigma, axes = self.sigma_max_um[mask], self.sigma_xyz_um[mask]
        pct = lambda x, q: float(np.percentile(x[np.isfinite(x)], q)) if np.isfinite(x).any() else None
        total = float(area.sum())
        return RegionStats(
            region=name, area_m2=total, n_samples=int(mask.sum()), min_cameras=int(need),
            covered_fraction=float(area[cov >= need].sum() / total),
            seen_by_2_or_more=float(area[cov >= 2].sum() / total),
            measured_fraction=float(area[np.isfinite(sigma)].sum() / total),
            sigma_max_um_p50=pct(sigma, 50), sigma_max_um_p95=pct(sigma, 95),
            sigma_max_um_max=pct(sigma, 100),
            sigma_x_um_p95=pct(axes[:, 0], 95), sigma_y_um_p95=pct(axes[:, 1], 95),
            sigma_z_um_p95=pct(axes[:, 2], 95))

    def regions(self) -> list["RegionStats"]:
        """`region_stats` of every region, in the file's order."""
        return [self.region_stats(name) for name in self.samples.region_names]


@dataclass(frozen=True)
class RegionStats:
    """One region of a judged layout (`LayoutState.region_stats`), with the definitions of
    `vdo evaluate`'s summary.json: fractions are of the region's area; coverage counts usable
    views (`LayoutState.coverage`); σ percentiles (µm) over the measured samples, None when none
    is measured; one noisy image (x sqrt 2 when the reference is noisy too)."""

    region: str
    area_m2: float
    n_samples: int
    min_cameras: int                # the region's coverage requirement
    covered_fraction: float         # area with at least min_cameras usable views
    seen_by_2_or_more: float        # area with at least 2 usable views
    measured_fraction: float        # area where the 3D displacement is measured (σ finite)
    sigma_max_um_p50: float | None
    sigma_max_um_p95: float | None
    sigma_max_um_max: float | None
    sigma_x_um_p95: float | None
    sigma_y_um_p95: float | None
    sigma_z_um_p95: float | None

    def to_dict(self) -> dict:
        """The fields as a flat dict (a CSV row: `vdo.core.table.write_csv`)."""
        return dataclasses.asdict(self)


SAME_POSITION_M = 1e-9   # m: a camera closer than this to its configured optical centre has not moved
SAME_ANGLE_RAD = 1e-9    # rad: nor turned, within this of its configured pan, tilt and roll
SAME_REL = 1e-12         # relative: a sensor width that differs by less is the same (rounding)
GEOMETRY_TABLES = ("mesh", "region", "speckle", "evaluation")   # what `prepare` reads ...
GEOMETRY_KEYS = {"evaluation": ("sample_spacing_mm", "patch_mm")}   # ... of these tables only these keys


def experiment_with_cameras(exp: Experiment, cameras) -> Experiment:
    """`exp` with [[camera]] tables that describe `cameras` (`vdo.model.camera.Camera`s): a camera
    of `exp` keeps its table where it has not moved or turned (within `SAME_POSITION_M`,
    `SAME_ANGLE_RAD`); moved, it keeps its zone mount while inside the zone, else stands at
    `position_m`; turned (or moved), it is aimed by pan, tilt and roll; its lens, sensor and
    distortion are the camera's. A camera `exp` does not list (a probe) is added with
    `body = false`; a camera of `exp` absent from `cameras` is dropped. `exp` itself when every
    camera is as it configures them."""
    cameras = tuple(cameras)
    configured = {c.name: c for c in cameras_of(exp.camera_specs, exp.rails)}
    specs = {s.name: s for s in exp.camera_specs}
    out = []
    for cam in cameras:
        lens = dict(focal_length=float(cam.focal_length), sensor_width=float(cam.pixel_size * cam.width),
                    pixels=(int(cam.width), int(cam.height)),
                    principal_offset_px=tuple(float(x) for x in cam.principal_offset_px),
                    distortion=tuple(float(x) for x in cam.distortion))
        aim = dict(target=None, pan=float(cam.pan), tilt=float(cam.tilt), roll=float(cam.roll))
        position = np.asarray(cam.position, dtype=float)
        if cam.name not in specs:
            out.append(CameraSpec(name=cam.name, position=position, body=False, **lens, **aim))
            continue
        spec, before = specs[cam.name], configured[cam.name]
        if abs(lens["sensor_width"] - spec.sensor_width) <= SAME_REL * spec.sensor_width:
            lens["sensor_width"] = spec.sensor_width   # pixel size x width rounds it
        moved = np.linalg.norm(position - before.position) > SAME_POSITION_M
        turned = max(abs(a - b) for a, b in zip((cam.pan, cam.tilt, cam.roll),
                                                 (before.pan, before.tilt, before.roll))) > SAME_ANGLE_RAD
        spec = dataclasses.replace(spec, **lens, **(aim if moved or turned else {}))
        if moved:
            zone = exp.mount(spec.mount) if spec.mount else None
            inside = (zone is not None and zone.kind == "zone" and np.all(position >= zone.low)
                      and np.all(position <= zone.high)
                      and (zone.floor is None or inside_floor(zone.floor, position[:2])))
            spec = dataclasses.replace(spec, position=position, rail=None, u=None,
                                       offset=np.zeros(3), mount=spec.mount if inside else None)
        out.append(spec)
    unchanged = len(out) == len(exp.camera_specs) and all(
        a is b or (a.name == b.name and all(_same(getattr(a, f.name), getattr(b, f.name))
                                            for f in dataclasses.fields(a)))
        for a, b in zip(out, exp.camera_specs))
    return exp if unchanged else exp.with_cameras(out)


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return a is not None and b is not None and np.array_equal(a, b)
    return a == b


def check_geometry(geometry: Geometry, exp: Experiment) -> None:
    """Refuse (`ConfigError`, one line naming the first field that differs) an experiment whose
    meshes, regions, speckle or sample spacing and patch (what `prepare` read) differ from those
    of the experiment `geometry` was prepared from."""
    if exp is geometry.experiment:
        return
    mine, theirs = geometry.experiment.to_dict(), exp.to_dict()
    for table in GEOMETRY_TABLES:
        a, b = mine.get(table), theirs.get(table)
        keys = GEOMETRY_KEYS.get(table)
        if keys is not None:
            a, b = ({k: t.get(k) for k in keys} for t in (a or {}, b or {}))
        field = _first_difference(table, a, b)
        if field is not None:
            raise ConfigError(exp.path, field, f"differs from the experiment the geometry was prepared "
                                               f"from ({geometry.experiment.path.name}): prepare a "
                                               "geometry for this one, vdo.prepare(exp)")


def _first_difference(table: str, a, b) -> str | None:
    """The field name (`region "joint".box_max_m`) of the first difference of two TOML tables (or
    arrays of named tables), None when equal."""
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for x, y in zip(a, b):
            if x.get("name") != y.get("name"):
                return table
            field = _first_difference(f'{table} "{x.get("name")}"', x, y)
            if field is not None:
                return field
        return None
    if isinstance(a, dict) and isinstance(b, dict):
        for key in list(a) + [k for k in b if k not in a]:
            if a.get(key) != b.get(key):
                return f"{table}.{key}"
        return None
    return None if a == b else table




def _warn_overlaps(exp: Experiment, selected: dict, meshes: dict) -> None:
    """A warning per two regions of one mesh that keep some of the same surface (points inside the
    faces both select that both regions' boxes and distance bands keep): their samples lie on
    one another, so that surface counts twice in every area-weighted figure and score. Faces
    that a distance band cuts between two regions are shared without any overlap."""
    names = [r.name for r in exp.regions if r.name in selected]
    mesh = {r.name: r.mesh for r in exp.regions}
    # points inside each face (not on its edges, where two bands meet exactly)
    w = np.array([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
    for k, a in enumerate(names):
        for b in names[k + 1:]:
            if mesh[a] != mesh[b]:
                continue
            shared = np.intersect1d(selected[a].faces, selected[b].faces)
            if not shared.size:
                continue
            m = meshes[mesh[a]]
            pts = np.einsum("pk,fkc->fpc", w, m.vertices[m.faces[shared]]).reshape(-1, 3)
            both = np.ones(len(pts), dtype=bool)
            for name in (a, b):
                if selected[name].selector is not None:
                    both &= selected[name].selector.keep(pts)
            faces = int(both.reshape(len(shared), -1).any(axis=1).sum())
            if faces:
                log.warning("%s: regions %r and %r both keep parts of %d face(s) of mesh %r: that surface "
                            "counts twice; narrow one of them if they should not overlap", exp.path, a, b,
                            faces, mesh[a])


def check_experiment(exp: Experiment, poses: Path | None = None) -> LoadPath | None:
    """Run every up-front check of `exp` that needs more than its TOML file, together, before any
    heavy work (ray casting, rendering, JAX compilation): its meshes read and checked, no camera
    inside one (`vdo.scene.load_meshes`), every region selecting some of its mesh
    (`vdo.scene.all_region_faces`), its load path's files read whole with every step of the
    pose file in the displacement file (`vdo.geometry.keyframes.load_path_of`; `poses`, `vdo
    render --series`'s pose file, replaces the [load_path]'s), and, with "lens" in [optimize]
    free, every moving camera's lens in its catalogue
    (`vdo.config.experiment.lens_catalogue_errors`). The checks do not stop at the first mistake:
    the one mistake found is raised as a `ConfigError`, several together as `ConfigErrors` (one
    line each), so that a file with several mistakes is fixed in one go. Returns the load path
    (None when there is none). A load path whose displacements need a mesh that could not be read
    is not read (the mesh's error is reported). It checks the whole file, so it stands here, at
    the door, and hands each check below the tables it reads."""
    errors = Collect()
    meshes = load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                         rails=exp.rails, mounts=exp.mounts, path=exp.path, errors=errors)
    if not errors.errors:                    # every region selects some of its mesh (each one said)
        selected = {}
        for region in exp.regions:
            with errors.check():
                selected[region.name] = all_region_faces(meshes, mesh_specs=exp.meshes, regions=(region,),
                                                         spacing=exp.evaluation.sample_spacing, path=exp.path)[0]
        _warn_overlaps(exp, selected, {m.name: m for m in meshes})
        _warn_below_floor(exp, meshes)
    load_path = None
    needed = exp.load_path.deformed_mesh if exp.load_path.displacements is not None else None
    if (exp.load_path.active or poses is not None) and (
            needed is None or needed in {m.name for m in meshes}):
        with errors.check():
            load_path = load_path_of(meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                                     groups=exp.groups, poses=poses)
    errors.errors += lens_catalogue_errors(exp)
    errors.raise_all()
    if load_path is not None:
        _warn_penetration(exp, meshes, load_path)
    return load_path


FLOOR_RAIL_POINTS = 513     # points along a rail tested against the floor (u every 1/512)
FLOOR_SLACK_M = 0.01        # a rail this far below the lowest mesh point is said to run under the floor


def _warn_below_floor(exp: Experiment, meshes) -> None:
    """A warning per rail that runs more than FLOOR_SLACK_M below every mesh (the lowest vertex
    taken as the floor; trial 4: a ring around a pipe dipped 0.3 m under it, and design and
    optimize put cameras there), naming the stretch of u, its depth and the fix. A keep-out
    below the floor keeps the cameras' optical centres out of it."""
    if not exp.rails or not meshes:
        return
    floor = min(float(np.min(m.vertices[:, 2])) for m in meshes)
    u = np.linspace(0.0, 1.0, FLOOR_RAIL_POINTS)
    for rail in exp.rails:
        z = rail.point(u)[:, 2]
        under = z < floor - FLOOR_SLACK_M
        if under.any():
            edges = np.flatnonzero(np.diff(np.r_[0, under.astype(int), 0]))    # run starts, ends
            runs = " and ".join(f"[{u[a]:.2f}, {u[b - 1]:.2f}]" for a, b in zip(edges[::2], edges[1::2]))
            log.warning("rail %r runs below every mesh (the lowest at z = %.3f m, taken as the floor) "
                        "for u in %s, down to z = %.3f m: cameras there stand under the floor; "
                        "raise the rail, or add a [[keep_out]] below the floor (box_max_m z = %.3f) "
                        "that design and optimize keep the cameras out of", rail.name, floor, runs,
                        z.min(), floor)


PENETRATION_M = 1e-3        # a moving mesh's vertex deeper than this inside a specimen is said
PENETRATION_VERTICES = 400  # vertices of a moving mesh tested at each step (evenly spread)


def _warn_penetration(exp: Experiment, meshes, load_path: LoadPath) -> None:
    """A warning per (moving mesh, specimen mesh) whose posed vertices reach more than
    PENETRATION_M inside the specimen at some step of the load path (`inside_mesh`, the depth by
    `vdo.model.surface.distance_to_mesh`): a platen driven through the specimen (poses 10x too
    large, mm read as m) changes every occlusion silently. The specimen is taken at rest."""
    from vdo.meshes.mesh import inside_mesh
    from vdo.model.surface import distance_to_mesh

    specimens = [m for m in meshes if m.role == "specimen"]
    worst = {}
    for step in load_path.steps:
        for mesh in meshes:
            pose = load_path.mesh_pose(step, mesh.name)
            if pose is None or mesh.role == "specimen" or pose.is_identity:
                continue
            pick = np.unique(np.linspace(0, len(mesh.vertices) - 1, PENETRATION_VERTICES).astype(int))
            moved = pose.move(mesh.vertices[pick])
            for spec in specimens:
                lo, hi = spec.vertices.min(axis=0), spec.vertices.max(axis=0)
                near = np.all((moved >= lo) & (moved <= hi), axis=1)
                if not near.any():
                    continue
                inside = moved[near][inside_mesh(moved[near], spec.vertices, spec.faces)]
                if len(inside):
                    depth = float(distance_to_mesh(inside, spec.vertices, spec.faces).max())
                    key = (mesh.name, spec.name)
                    if depth > PENETRATION_M and depth > worst.get(key, (0.0, 0))[0]:
                        worst[key] = (depth, step)
    for (moving, specimen), (depth, step) in worst.items():
        log.warning("%s: at step %d of the load path mesh %r reaches %.1f mm inside specimen %r: check "
                    "the pose file's units and values (a platen presses on the surface, not through it)",
                    exp.path, step, moving, depth * 1e3, specimen)


def prepare(exp: Experiment, meshes: list[SceneMesh] | None = None,
            spacing_field: str = "evaluation.sample_spacing_mm") -> Geometry:
    """Read the meshes (unless given), sample the regions and build the speckle model.
    `spacing_field` names the field the sample spacing came from in the messages (`vdo design`
    samples at "design.sample_spacing_mm")."""
    if meshes is None:
        meshes = load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                             rails=exp.rails, mounts=exp.mounts, path=exp.path)
    spacing, patch = exp.evaluation.sample_spacing, exp.evaluation.patch_size
    faces = tuple(all_region_faces(meshes, mesh_specs=exp.meshes, regions=exp.regions, spacing=spacing,
                                   path=exp.path))
    samples = sample_regions(meshes, mesh_specs=exp.meshes, regions=exp.regions, spacing=spacing,
                             path=exp.path, faces=list(faces), field=spacing_field)
    by_name = {m.name: m for m in meshes}
    rasters = [surface_raster(by_name[r.mesh], rf, spacing) if patch <= FINE_PATCH_CELLS * spacing else None
               for r, rf in zip(exp.regions, faces)]
    return Geometry(exp, tuple(meshes), samples, speckle_model(exp.speckle), faces,
                    patch_overlap(samples, patch, rasters))


def unobstructed_lighting(geometry: Geometry) -> Illumination:
    """The lighting of `geometry` with no camera in the scene (for `layout_state`'s
    `unobstructed`, and to see what the camera bodies hide)."""
    exp = geometry.experiment
    return illuminate(build_scene(list(geometry.meshes)), exp.lights, geometry.samples,
                      exp.render.ambient_radiance)


def bodies(exp: Experiment, cameras) -> list[SceneMesh]:
    """The obstacles that move with the cameras: the bodies of cameras the experiment lists with
    `body = true` (the default), and the tripods (`vdo.scene.tripods`) of those on a zone
    [[mount]] with a [mount.tripod], built where the cameras stand now."""
    with_body = {spec.name for spec in exp.camera_specs if spec.body}
    return [camera_body(c) for c in cameras if c.name in with_body] + tripods(
        cameras, camera_specs=exp.camera_specs, mounts=exp.mounts)


def layout_state(geometry: Geometry, cameras=None, *, predict_fields: bool = True,
                 strain_fields: bool = True, clip_patch: bool = True, progress: bool = False,
                 unobstructed: Illumination | None = None) -> LayoutState:
    """Judge `cameras` on `geometry`: a list of `Camera`s (judged with the geometry's
    experiment's settings), an `Experiment` (an edited or re-parsed copy of the geometry's:
    its cameras and its settings; refused in one line by `check_geometry` when its meshes,
    regions, speckle, sample spacing or patch differ from the geometry's), or None (the
    geometry's experiment's own cameras). Ray cast, lighting and,
    with `predict_fields`, the predicted sensitivity and uncertainty (`vdo.physics.predict`; `clip_patch`
    False keeps every sample's whole DIC patch, for samples that each stand for a whole patch)
    and, with `strain_fields` too, the strain uncertainty of the `[analysis]` (`vdo.physics.strain`).
    `unobstructed`, the lighting of `geometry` without camera bodies (`unobstructed_lighting`),
    when given, makes the lighting cheaper and leaves it the same (`vdo.physics.lighting.relight`)."""
    exp = geometry.experiment
    if isinstance(cameras, Experiment):
        check_geometry(geometry, cameras)
        exp, cameras = cameras, cameras_of(cameras.camera_specs, cameras.rails)
    cameras = tuple(cameras_of(exp.camera_specs, exp.rails) if cameras is None else cameras)
    obstacles = bodies(exp, cameras)
    scene = build_scene(list(geometry.meshes) + obstacles)
    vis = compute_visibility(scene, list(cameras), geometry.samples,
                             exp.evaluation.incidence_limit, progress=progress)
    samples = geometry.samples
    if unobstructed is None:
        illumination = illuminate(scene, exp.lights, samples, exp.render.ambient_radiance)
    else:
        illumination = relight(scene, exp.lights, samples, unobstructed, [b.vertices for b in obstacles])
    if not predict_fields:
        return LayoutState(geometry, cameras, scene, vis, illumination, None, source=exp)
    density = None
    if strain_fields:   # checked before the prediction: a bad [analysis] fails early
        density = strain.pixel_density(list(cameras), vis.visible, samples.points, samples.tangent_u,
                                       samples.tangent_v)
        strain.check_regions(exp.analysis, samples, density, exp.path)
    prediction = predict(exp.regions, exp.evaluation, exp.speckle, exp.sensor, list(cameras), samples,
                         vis, illumination, geometry.speckle, clip_patch=clip_patch,
                         overlap=geometry.overlap, sizes=geometry.sizes,
                         exposure=camera_exposure(exp, cameras))
    fields = None if density is None else strain.analysis_fields(
        exp.analysis, density, samples, prediction.information, prediction.measured,
        exp.evaluation.patch_size ** 2)
    return LayoutState(geometry, cameras, scene, vis, illumination, prediction, fields, source=exp)


def camera_exposure(exp: Experiment, cameras) -> np.ndarray | None:
    """(C,) the light each of `cameras` gathers (`vdo.physics.lighting.exposure_factors`) when
    `exp`'s [[camera]] specs are these cameras (the same names in the same order); None (the
    sensor's reference exposure) for cameras the file does not describe, e.g. design candidates."""
    if [s.name for s in exp.camera_specs] != [c.name for c in cameras]:
        return None
    return exposure_factors(exp.camera_specs, exp.sensor)


def with_exposure(exp: Experiment) -> tuple[Experiment, ExposurePlan]:
    """`exp` with the f-numbers, exposure times and light power that [exposure] free asks for
    (`vdo.physics.exposure.design_exposure` on its layout, judged without predicting the fields;
    the depth of field holds each camera's assigned regions, `vdo.constraints.assignments`; with
    [load_path] step_s, each exposure within [exposure] blur_px of image motion over the path's
    steps, `vdo.physics.exposure.motion_limits`), and the plan itself."""
    t0 = time.perf_counter()
    state = layout_state(prepare(exp), predict_fields=False)
    vis, samples = state.visibility, state.samples
    assigned = assignments(vis, samples, exp.optimize.assign_fraction)
    cameras = list(state.cameras)
    motion = None
    if exp.load_path.step_time is not None and "time" in exp.exposure.free:
        path = load_path_of(state.geometry.meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                            groups=exp.groups)
        tracks = [(0, samples.points)] + [
            (step, at_step(state.geometry, path, step, regions=exp.regions).samples.points)
            for step in path.steps if step > 0]
        motion = motion_limits(cameras, vis.visible, tracks, exp.load_path.step_time,
                               exp.exposure.blur_px, exp.exposure.max_time)
    plan = design_exposure(exp.exposure, exp.camera_specs, exp.lights, exp.speckle, exp.sensor,
                           exp.evaluation, exp.analysis,
                           cameras, samples, vis.visible, state.illumination,
                           state.geometry.speckle.pattern,
                           sharp=vis.visible & assigned[:, samples.region], motion=motion,
                           scene=state.scene,
                           places={l: exp.light_places(lt)
                                   for l, lt in enumerate(exp.lights) if lt.mount is not None},
                           satin=satin_samples(exp.meshes, exp.regions, samples),
                           max_obscuration=exp.optimize.max_obscuration)
    log.info("exposure (%.0f s): %s%s", time.perf_counter() - t0, ", ".join(
        f"{c.camera} f/{c.f_number:g} {c.exposure_s * 1e3:.3g} ms"
        + (f" (at most {c.max_s * 1e3:.3g} ms: {c.image_speed:.3g} px/s)" if c.image_speed > 0 else "")
        for c in plan.cameras),
        "; lights " + ", ".join(
            f"{lt.name} {lt.radiance:.3g}" + (" at [" + ", ".join(f"{x:.2f}" for x in lt.position) + "] m"
                                               if lt.name in plan.moved else "")
            for lt in plan.lights) if plan.lights else "")
    return dataclasses.replace(exp.with_cameras(plan.camera_specs), lights=plan.lights), plan


def warm_up(geometry: Geometry, cameras=None) -> float:
    """Compile what judging a layout on `geometry` needs, and fix its pair-list sizes
    (`Geometry.sizes`), by judging `cameras` (as `layout_state` takes them; default the
    experiment's) once. Later layouts on this geometry then compile nothing while they see at
    most `vdo.objective.PAIR_HEADROOM` times the pairs of this one (warm up with the layout that
    sees the most); the compiled programs also go to the persistent compilation cache
    (`vdo.configure`), so the next process loads them instead of compiling. Returns the seconds
    it took."""
    t0 = time.perf_counter()
    layout_state(geometry, cameras)
    return time.perf_counter() - t0
