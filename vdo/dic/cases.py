"""A validation case's scene (`vdo.dic.validate`): the planar speckled plate, its deformation
(the texture moving and straining with it), the cameras around it, the experiment that predicts
it (`Setup`, `build_setup`) and its noise-free reference and deformed renders (`render_case`)."""

from __future__ import annotations
import math
from dataclasses import dataclass, field
from pathlib import Path
import numpy as np
from vdo.geometry.plate import cameras_of, deform, plate_geometry, undeform
from vdo.config.experiment import Experiment
from vdo.config.rig import Evaluation, MeshSpec, RegionSpec, RenderSpec
from vdo.config.procedure import Analysis, StereoPairSpec
from vdo.config.validation import Case
from vdo.dic.patch import Patch
from vdo.physics.lighting import pattern_stats
from vdo.physics.predict import SpeckleModel
from vdo.render import build_render_scene, render_linear, render_seed, sensor_dict
from vdo.scene import SceneMesh, region_faces
from vdo.model.speckle import gradient_energy_table, normalise, pattern_for

@dataclass(frozen=True, eq=False)
class DeformedFaces:
    """The plate region's faces after the deformation: every point keeps the uv of its reference
    position, so the texture moves and strains with the plate (what `build_render_scene` reads)."""

    base: object        # vdo.scene.RegionFaces of the reference plate
    case: Case

    development = None   # a plate: planar, uv by `uv` (the render scene asks)

    @property
    def faces(self):
        return self.base.faces

    def uv(self, points) -> np.ndarray:
        return self.base.uv(undeform(self.case, points))


@dataclass(eq=False)
class Setup:
    """Everything one case needs, built once."""

    case: Case
    experiment: Experiment
    cameras: list
    patch: object                   # vdo.dic.patch.Patch
    plate: object                   # vdo.scene.SceneMesh
    region: object                  # vdo.scene.RegionFaces
    pattern: np.ndarray | None
    reference_linear: list = field(default_factory=list)
    deformed_linear: list = field(default_factory=list)
    pairs: tuple = ()               # pair cases: the pairs the merge uses (camera indices)
    pair_weights: np.ndarray | None = None   # (P, 3, 3) A_p of the merge, `predict_pairs`


def experiment_for(case: Case, path: Path, cameras=None) -> Experiment:
    """An in-memory vdo Experiment for the case: one specimen plate, one region (the plate's
    face), ambient light only, the DIC patch side sqrt(patch area) (Ω = the correlated area);
    the strain analysis is the case's: subset DIC with its subset, step and window for a
    subset case, else global DIC with the patch's shorter side as element (it fits the region,
    the patch itself, up to rounding: `vdo.core.tolerances.SIZE_TOLERANCE`)."""
    g = plate_geometry(case)
    region = RegionSpec(name="patch", mesh="plate", normal=g["normal"],
                        box_min=np.full(3, -np.inf), box_max=np.full(3, np.inf),
                        normal_tolerance=math.radians(1.0), min_cameras=1)
    w, h = case.patch
    return Experiment(path=Path(path), name=case.name, description=case.description,
                      meshes=(MeshSpec(name="plate", path=Path(path), unit="m", role="specimen"),),
                      regions=(region,), rails=(), camera_specs=(),
                      evaluation=Evaluation(sample_spacing=min(w, h) / 4, incidence_limit=math.radians(85.0),
                                            patch_size=math.sqrt(w * h), min_cameras=1),
                      speckle=case.speckle, sensor=case.sensor,
                      render=RenderSpec(spp=case.spp, ambient_radiance=case.ambient_radiance),
                      analysis=analysis_of(case),
                      stereo_pairs=tuple(StereoPairSpec(cameras=p) for p in case.stereo_pairs))


def analysis_of(case: Case) -> Analysis:
    """The `[analysis]` of a case (`experiment_for`): subset DIC (subset, step and window in
    metres, sizes in pixels unset) for a subset case, else global DIC, element = the patch's
    shorter side; the case's processing (all views, or stereo pairs and their merge)."""
    if case.subsets is not None:
        side, step, n = case.subsets
        return Analysis(method="subset", subset=side, subset_px=None, step=step, step_px=None,
                        strain_window=n)
    return Analysis(element=min(case.patch), processing=case.processing, pairs=case.pairs,
                    merge=case.merge, max_pair_angle=case.max_pair_angle)


def build_setup(case: Case, path: Path, painted: bool = True) -> Setup:
    """The case's experiment, plate, region, patch and cameras; with `painted`, its speckle
    pattern too (False: the geometry only, for the checks before any render)."""
    g = plate_geometry(case)
    exp = experiment_for(case, path)
    plate = SceneMesh("plate", "specimen", g["plate"], np.array([[0, 1, 2], [0, 2, 3]]))
    rf = region_faces(plate, exp.regions[0], exp.evaluation.sample_spacing, (path, case.name))
    patch = Patch(origin=g["origin"], t_u=g["t_u"], t_v=g["t_v"], size=np.array(case.patch))
    return Setup(case=case, experiment=exp, cameras=cameras_of(case), patch=patch, plate=plate,
                 region=rf, pattern=case_pattern(case) if painted else None)


def case_pattern(case: Case) -> np.ndarray:
    """The [0, 1] pattern painted on the plate: vdo's generated tile, its edges softened by a
    periodic Gaussian of std `edge_blur` (ink spread) when that is > 0."""
    from scipy import ndimage


    pattern = pattern_for(case.speckle).astype(np.float64)
    if case.edge_blur > 0:
        pattern = ndimage.gaussian_filter(pattern, case.edge_blur / case.speckle.texel, mode="wrap")
    return pattern.astype(np.float32)


def speckle_model_of(setup: Setup):
    """vdo.physics.predict's SpeckleModel (statistics and gradient-energy table, vdo.model.speckle) of the
    pattern actually painted; the same as `vdo.physics.predict.speckle_model` when edge_blur = 0."""

    sp = setup.case.speckle
    mean, std = pattern_stats(setup.pattern)
    table = gradient_energy_table(normalise(setup.pattern), sp.texel,
                                  l_max=max(50 * sp.dot_diameter, 0.05))
    return SpeckleModel(setup.pattern, mean, std, table)


# --------------------------------------------------------------------------------------------
# Renders
# --------------------------------------------------------------------------------------------
def render_case(setup: Setup) -> None:
    """Noise-free linear renders of every camera: the plate as it is, and deformed (translated
    by U and, in a strain case, strained homogeneously) with its texture (`DeformedFaces`: every
    point keeps its uv; the plate is flat, so the affine map of its vertices is exact)."""

    case, exp = setup.case, setup.experiment
    moved = SceneMesh("plate", "specimen", deform(case, setup.plate.vertices), setup.plate.faces)
    moved_rf = DeformedFaces(setup.region, case)
    scenes = [build_render_scene(exp, [setup.plate], [setup.region], (), setup.pattern),
              build_render_scene(exp, [moved], [moved_rf], (), setup.pattern)]
    setup.reference_linear, setup.deformed_linear = [], []
    for i, cam in enumerate(setup.cameras):
        # jitter=False: each pixel is integrated on a fixed sub-pixel midpoint grid (no render noise)
        sensor = sensor_dict(cam, spp=case.spp, jitter=False)
        setup.reference_linear.append(render_linear(scenes[0], sensor, render_seed(0, i)))
        setup.deformed_linear.append(render_linear(scenes[1], sensor, render_seed(0, i)))
