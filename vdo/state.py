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
"""

from __future__ import annotations

from dataclasses import dataclass

from vdo.physics import strain
from vdo.model.camera import Camera
from vdo.config.experiment import Experiment
from vdo.physics.lighting import Illumination, illuminate, relight
from vdo.physics.predict import Prediction, SpeckleModel, predict, speckle_model
from vdo.scene import (RegionFaces, SceneMesh, SurfaceSamples, all_region_faces, build_scene, camera_body,
                    load_meshes, sample_regions, surface_raster, tripods)
from vdo.physics.usable import FINE_PATCH_CELLS, patch_overlap
from vdo.physics.visibility import Visibility, compute_visibility


@dataclass(frozen=True, eq=False)
class Geometry:
    """The camera-independent part of an experiment: meshes (metres), samples, speckle."""

    experiment: Experiment
    meshes: tuple[SceneMesh, ...]
    samples: SurfaceSamples
    speckle: SpeckleModel
    region_faces: tuple[RegionFaces, ...]   # the faces each region selects, in config order
    overlap: object    # (N, N) sparse patch-cell overlap of the samples (`vdo.physics.usable.patch_overlap`)


@dataclass(frozen=True, eq=False)
class LayoutState:
    """One camera layout judged on one geometry. `scene` is the Mitsuba scene of the meshes and
    the camera bodies (for further ray casts); `prediction` is None when not asked for."""

    geometry: Geometry
    cameras: tuple[Camera, ...]
    scene: object
    visibility: Visibility
    illumination: Illumination
    prediction: Prediction | None
    strain: tuple | None = None    # (sigma of the strain (N, 3), of the analysis' displacement (N,))

    @property
    def experiment(self) -> Experiment:
        return self.geometry.experiment

    @property
    def samples(self) -> SurfaceSamples:
        return self.geometry.samples


def prepare(exp: Experiment, meshes: list[SceneMesh] | None = None) -> Geometry:
    """Read the meshes (unless given), sample the regions and build the speckle model."""
    meshes = load_meshes(exp) if meshes is None else meshes
    samples = sample_regions(exp, meshes)
    faces = tuple(all_region_faces(exp, meshes))
    spacing, patch = exp.evaluation.sample_spacing, exp.evaluation.patch_size
    by_name = {m.name: m for m in meshes}
    rasters = [surface_raster(by_name[r.mesh], rf, spacing) if patch <= FINE_PATCH_CELLS * spacing else None
               for r, rf in zip(exp.regions, faces)]
    return Geometry(exp, tuple(meshes), samples, speckle_model(exp), faces,
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
    return [camera_body(c) for c in cameras if c.name in with_body] + tripods(exp, cameras)


def layout_state(geometry: Geometry, cameras=None, *, predict_fields: bool = True,
                 strain_fields: bool = True, clip_patch: bool = True, progress: bool = False,
                 unobstructed: Illumination | None = None) -> LayoutState:
    """Judge `cameras` (default: the experiment's own) on `geometry`: ray cast, lighting and,
    with `predict_fields`, the predicted sensitivity and uncertainty (`vdo.physics.predict`; `clip_patch`
    False keeps every sample's whole DIC patch, for samples that each stand for a whole patch)
    and, with `strain_fields` too, the strain uncertainty of the `[analysis]` (`vdo.physics.strain`).
    `unobstructed`, the lighting of `geometry` without camera bodies (`unobstructed_lighting`),
    when given, makes the lighting cheaper and leaves it the same (`vdo.physics.lighting.relight`)."""
    exp = geometry.experiment
    cameras = tuple(exp.cameras() if cameras is None else cameras)
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
        return LayoutState(geometry, cameras, scene, vis, illumination, None)
    density = None
    if strain_fields:   # checked before the prediction: a bad [analysis] fails early
        density = strain.pixel_density(list(cameras), vis.visible, samples.points, samples.tangent_u,
                                       samples.tangent_v)
        strain.check_regions(exp.analysis, samples, density, exp.path)
    prediction = predict(exp, list(cameras), samples, vis, illumination, geometry.speckle,
                         clip_patch=clip_patch, overlap=geometry.overlap)
    fields = None if density is None else strain.analysis_fields(
        exp.analysis, density, samples, prediction.information, prediction.measured,
        exp.evaluation.patch_size ** 2)
    return LayoutState(geometry, cameras, scene, vis, illumination, prediction, fields)
