"""The predicted uncertainty against correlation on vdo's own renders: the computation of
`vdo validate` (`run_cases`; `vdo.commands.validate` writes the run folder).

For each case of a validation file (experiments/validation.toml, schema in docs/validation.md):

1. a planar speckled plate (tilted by `tilt_deg` about the world x axis; its normal is +z when
   frontal) is rendered by Mitsuba (`vdo.render.build_render_scene`, ambient light only) through each
   camera, once as it is (reference) and once translated by the imposed 3D displacement U, the
   texture moving with the plate. The renders are linear and noise-free: a constant environment
   sampled by cosine-weighted BSDF sampling on a Lambertian plate has zero Monte Carlo variance, and
   the stratified sampler without jitter integrates each box pixel by a fixed midpoint grid, so the
   only noise in the experiment is the sensor's;
2. the uncertainty of the correlated patch is predicted by `vdo.physics.predict.predict` (the mean-field
   Cramér–Rao bound for ONE noisy image against a perfect reference) with the DIC patch area Ω equal
   to the correlated patch;
3. for each seed, independent sensor noise is drawn for the reference and the displaced image of
   every camera (`vdo.render.expose`, distinct seeds), and U is measured by global multi-view
   correlation (`vdo.dic.correlate.correlate`, `Translation` model, `ImageReference`: each camera
   against its own noisy reference image);
4. the scatter of the measured U over the seeds is compared with the prediction. Both images are
   noisy, so the expected standard deviation is √2 σ_predicted, and

       ratio = sigma_measured / (√2 sigma_predicted)      (1 when the model is right).

With one camera only the in-plane axes are reported: the depth is seen through perspective alone.
The model's one-camera information is rank 2 (`predict` reports +inf), so its in-plane bound is the
limit of adding a vanishingly weak second view: a probe camera 35x and 55x farther away, whose information
is ~1e-7 of the first (`_predict_sigma`, checked to converge).

Strain cases (`strain_microstrain` = [eps_uu, eps_vv, eps_uv] in the plate's face frame): the
deformed plate is also strained homogeneously about the patch centre (X -> X + U + T E Tᵀ X, its
texture strained with it: `DeformedFaces`), correlated with a Q4 mesh of the patch (`q4_mesh`),
and the strain at the centre of the middle element (`measured_strain`) is compared with
`vdo.physics.strain` for that mesh (`predict_strain_sigma`: Σ_u = Ω C⁻¹ of the patch and the finite
mesh's own gradient factors), with the same √2 and the same ratio.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vdo.physics import strain
from vdo.physics.strain import SIZE_TOLERANCE, fits
from vdo.model.camera import Camera, look_at_angles
from vdo.config.experiment import (Analysis, SENSOR_FIELDS, Evaluation, Experiment, MeshSpec, RegionSpec, RenderSpec,
                     SpeckleSpec, Table, as_numbers, read_toml, with_overrides)
from vdo.dic.correlate import ImageReference, PixelIntegration, Patch, Q4, Translation, correlate
from vdo.core.errors import ConfigError
from vdo.physics.lighting import pattern_stats
from vdo.physics.predict import SpeckleModel
from vdo.render import build_render_scene, expose, noise_free_dn, render_linear, render_seed, sensor_dict
from vdo.scene import SceneMesh, SurfaceSamples, face_frame, region_faces
from vdo.model.sensor import SensorModel
from vdo.physics.usable import patch_overlap
from vdo.model.speckle import gradient_energy_table, normalise, pattern_for
from vdo.state import Geometry, layout_state

log = logging.getLogger(__name__)

AXES = "xyz"
STRAIN_AXES = ("eps_uu", "eps_vv", "eps_uv")
UM = 1e6
SQRT2 = math.sqrt(2.0)
BAND = (0.8, 1.25)       # the requirement on every ratio (`ValidationResult.passed`)

# --------------------------------------------------------------------------------------------
# The validation file
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraCase:
    """A camera aimed at the patch centre from `polar` (rad, from world +z) and `azimuth` (rad,
    from +x toward +y), `distance` (m) away."""

    name: str
    polar: float
    azimuth: float
    distance: float
    focal_length: float      # m
    pixel_size: float        # m
    pixels: tuple[int, int]  # width, height


@dataclass(frozen=True)
class Case:
    name: str
    description: str
    patch: tuple[float, float]          # m, the correlated patch (centred on the plate)
    plate_margin: float                 # m of speckled plate beyond the patch on every side
    tilt: float                         # rad, plate normal turned from +z toward -y
    displacement: np.ndarray            # (3,) m, world frame
    cameras: tuple[CameraCase, ...]
    speckle: SpeckleSpec
    edge_blur: float                    # m, std of a Gaussian softening of the painted pattern
    sensor: SensorModel
    ambient_radiance: float
    spp: int
    seed: int                           # base of the noise seeds
    strain: np.ndarray | None = None    # (3,) imposed (eps_uu, eps_vv, eps_uv) in the face frame
    q4_mesh: tuple[int, int] = (1, 1)   # strain cases: Q4 mesh of the patch, centre element read
    subsets: tuple[float, float, int] | None = None   # subset-DIC strain: (side m, step m, window n)


@dataclass(frozen=True)
class ValidationSpec:
    path: Path
    name: str
    seeds: int
    cases: tuple[Case, ...]


_CASE_FIELDS = ("name", "description", "patch_mm", "plate_margin_mm", "tilt_deg", "dot_mm",
                "texel_mm", "edge_blur_mm", "coverage", "strokes", "speckle_seed", "tile_texels", "white_albedo",
                "black_albedo", "cameras", "focal_mm", "pixel_um", "pixels", "distance_mm",
                "ambient_radiance", "spp", "sensor", "displacement_um", "seed",
                "strain_microstrain", "q4_mesh", "subset_mm", "step_mm", "strain_window")
_CAMERA_FIELDS = ("name", "polar_deg", "azimuth_deg", "distance_mm", "focal_mm", "pixel_um",
                  "pixels")


def load(path) -> ValidationSpec:
    """Read and validate a validation file; ConfigError (file, field, message) on any mistake."""
    return parse(read_toml(path), Path(path))


def parse(data: dict, path) -> ValidationSpec:
    """Validate an already-parsed validation document that came from `path`.

    `[defaults]` holds any case field (but name); each `[[case]]` inherits it and overrides it
    (a case's `sensor` table is merged key by key over the defaults' one). The environment's
    VDO_SET items for `validation` and `defaults` are written in first
    (`vdo.config.experiment.with_overrides`)."""
    path = Path(path).resolve()
    data = with_overrides(data, ("validation", "defaults"))
    top = Table(data, "", path, ("validation", "defaults", "case"))
    head = Table(top.raw("validation", {}), "validation", path, ("name", "seeds"))
    name = head.string("name", "vdo validation")
    seeds = head.integer("seeds", 200, low=2)
    defaults = top.raw("defaults", {})
    Table(defaults, "defaults", path, tuple(f for f in _CASE_FIELDS if f != "name"))
    items = top.raw("case")
    if not isinstance(items, list) or not items:
        raise ConfigError(path, "case", "needs at least one [[case]] table")
    cases, names = [], set()
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            raise ConfigError(path, f"case[{i}]", "must be a table")
        label = item.get("name")
        where = f'case "{label}"' if isinstance(label, str) else f"case[{i}]"
        merged = {**defaults, **item}
        if isinstance(defaults.get("sensor"), dict) and isinstance(item.get("sensor"), dict):
            merged["sensor"] = {**defaults["sensor"], **item["sensor"]}
        case = _case(Table(merged, where, path, _CASE_FIELDS), path, where)
        if case.name in names:
            raise ConfigError(path, where, "name is used twice; names must be unique")
        names.add(case.name)
        cases.append(case)
    return ValidationSpec(path=path, name=name, seeds=seeds, cases=tuple(cases))


def _pixels(t: Table, key, default=None):
    value = t.raw(key, default)
    arr = as_numbers(value)
    if arr is None or arr.shape != (2,) or np.any(arr != np.round(arr)) or np.any(arr < 16) \
            or np.any(arr > 4096):
        raise t.error(key, f"must be two whole numbers [width, height] in 16..4096 (got {value!r})")
    return int(arr[0]), int(arr[1])


def _case(t: Table, path: Path, where: str) -> Case:
    name = t.string("name")
    patch = t.vector("patch_mm", 2, positive=True) * 1e-3
    dot = t.number("dot_mm", positive=True) * 1e-3
    texel = t.number("texel_mm", 0.025, positive=True) * 1e-3
    tile = t.integer("tile_texels", 1024, low=64)
    if dot < 3 * texel:
        raise t.error("texel_mm", f"must be at most a third of dot_mm ({dot * 1e3:g} mm)")
    if dot > tile * texel / 4:
        raise t.error("dot_mm", f"must be at most a quarter of the pattern tile "
                                f"({tile * texel * 1e3:g} mm = tile_texels x texel_mm)")
    margin = t.number("plate_margin_mm", 10.0, positive=True) * 1e-3
    if np.any(patch + 2 * margin > tile * texel * 4):
        raise t.error("patch_mm", "the plate is more than 4 pattern tiles wide; raise tile_texels")
    if np.any(patch > tile * texel):
        raise t.error("patch_mm", f"the correlated patch is larger than one pattern tile "
                                  f"({tile * texel * 1e3:g} mm): the pattern would repeat inside it")
    white = t.number("white_albedo", 0.8, low=0.0, high=1.0)
    black = t.number("black_albedo", 0.05, low=0.0, high=1.0)
    if black >= white:
        raise t.error("black_albedo", "must be less than white_albedo")
    speckle = SpeckleSpec(dot_diameter=dot, coverage=t.number("coverage", 0.5, low=0.05, high=0.95),
                          strokes=t.integer("strokes", 0, low=0), texel=texel, tile_texels=tile,
                          seed=t.integer("speckle_seed", 1, low=0), white_albedo=white,
                          black_albedo=black)

    sensor_table = Table(t.raw("sensor", {}), f"{where}.sensor", path, SENSOR_FIELDS)
    try:
        sensor = SensorModel(**{k: sensor_table.raw(k) for k in SENSOR_FIELDS if sensor_table.has(k)})
    except ValueError as exc:
        fld, _, message = str(exc).partition(": ")
        raise sensor_table.error(fld.removeprefix("SensorModel."), message) from None

    common = dict(focal=t.number("focal_mm", None, positive=True) if t.has("focal_mm") else None,
                  pixel=t.number("pixel_um", None, positive=True) if t.has("pixel_um") else None,
                  pixels=_pixels(t, "pixels") if t.has("pixels") else None,
                  distance=t.number("distance_mm", None, positive=True) if t.has("distance_mm") else None)
    raw_cameras = t.raw("cameras")
    if not isinstance(raw_cameras, list) or not raw_cameras:
        raise t.error("cameras", "must be a list of camera tables, e.g. "
                                 "[{polar_deg = 12.5, azimuth_deg = 0}, ...]")
    cameras = []
    for k, raw in enumerate(raw_cameras):
        ct = Table(raw, f"{where}.cameras[{k}]", path, _CAMERA_FIELDS)
        cam_name = ct.string("name", f"cam{k + 1}")
        values = {}
        for key, label, scale in (("focal", "focal_mm", 1e-3), ("pixel", "pixel_um", 1e-6),
                                  ("distance", "distance_mm", 1e-3)):
            if ct.has(label):
                values[key] = ct.number(label, positive=True) * scale
            elif common[key] is not None:
                values[key] = common[key] * scale
            else:
                raise ct.error(label, f"is required (here or as {label} of the case or [defaults])")
        pixels = _pixels(ct, "pixels") if ct.has("pixels") else common["pixels"]
        if pixels is None:
            raise ct.error("pixels", "is required (here or as pixels of the case or [defaults])")
        cameras.append(CameraCase(name=cam_name, polar=math.radians(ct.number("polar_deg", low=0.0, high=85.0)),
                                  azimuth=math.radians(ct.number("azimuth_deg", 0.0)),
                                  distance=values["distance"], focal_length=values["focal"],
                                  pixel_size=values["pixel"], pixels=pixels))
    if len({c.name for c in cameras}) != len(cameras):
        raise t.error("cameras", "camera names must be unique")
    case = Case(name=name, description=t.raw("description", "") or "", patch=(float(patch[0]), float(patch[1])),
                plate_margin=margin, tilt=math.radians(t.number("tilt_deg", 0.0, low=0.0, high=80.0)),
                displacement=t.vector("displacement_um", 3) * 1e-6, cameras=tuple(cameras),
                speckle=speckle, edge_blur=t.number("edge_blur_mm", 0.0, low=0.0, high=dot * 1e3 / 2) * 1e-3,
                sensor=sensor,
                ambient_radiance=t.number("ambient_radiance", 1.0, positive=True),
                spp=t.integer("spp", 64, low=1), seed=t.integer("seed", 0, low=0),
                **_strain_fields(t, len(cameras)))
    _check_geometry(case, t, path, where)
    return case


def _strain_fields(t: Table, n_cameras: int) -> dict:
    """A strain case: `strain_microstrain` = [eps_uu, eps_vv, eps_uv] (tensor shear) imposed on the
    plate in its face frame, correlated with a `q4_mesh` = [nx, ny] mesh (default [1, 1]), or by
    subset DIC: `subset_mm`, `step_mm`, `strain_window` (n x n translation subsets centred in the
    patch, strain from their plane fit)."""
    subset_keys = ("subset_mm", "step_mm", "strain_window")
    if not t.has("strain_microstrain"):
        for key in ("q4_mesh",) + subset_keys:
            if t.has(key):
                raise t.error(key, "only applies to a strain case (strain_microstrain)")
        return {}
    subsets = None
    if any(t.has(k) for k in subset_keys):
        if t.has("q4_mesh"):
            raise t.error("q4_mesh", "give either q4_mesh (global DIC) or subset_mm, step_mm and "
                                     "strain_window (subset DIC)")
        side = t.number("subset_mm", positive=True) * 1e-3
        step = t.number("step_mm", positive=True) * 1e-3
        n = t.integer("strain_window", low=2)
        patch = t.vector("patch_mm", 2) * 1e-3
        if not fits((n - 1) * step + side, min(patch)):
            raise t.error("strain_window", f"the window ((n - 1) step + subset = "
                                           f"{((n - 1) * step + side) * 1e3:g} mm) is larger than "
                                           f"the patch ({min(patch) * 1e3:g} mm; relative tolerance "
                                           f"{SIZE_TOLERANCE:g})")
        subsets = (side, step, n)
    if n_cameras < 2:
        raise t.error("strain_microstrain", "a strain case needs at least two cameras")
    strain = t.vector("strain_microstrain", 3) * 1e-6
    if np.any(np.abs(strain) > 0.02):
        raise t.error("strain_microstrain", "must be small strains (|eps| <= 20000 microstrain)")
    mesh = as_numbers(t.raw("q4_mesh", [1, 1]))
    if mesh is None or mesh.shape != (2,) or np.any(mesh != np.round(mesh)) or np.any(mesh < 1) \
            or np.any(mesh > 9):
        raise t.error("q4_mesh", f"must be two whole numbers [nx, ny] in 1..9 (got {t.raw('q4_mesh')!r})")
    return {"strain": strain, "q4_mesh": (int(mesh[0]), int(mesh[1])), "subsets": subsets}


def _check_geometry(case: Case, t: Table, path: Path, where: str) -> None:
    """Every camera sees the whole patch (corners displaced by U) in front of it, at an incidence
    below 80 deg, at least 4 pixels inside its image; the imposed displacement is sub-pixel."""
    g = plate_geometry(case)
    for k, cam in enumerate(cameras_of(case)):
        ray = g["centre"] - cam.position
        incidence = math.degrees(math.acos(abs(ray @ g["normal"]) / np.linalg.norm(ray)))
        field_name = f"{where}.cameras[{k}]"
        if incidence > 80:
            raise ConfigError(path, field_name, f"sees the plate at {incidence:.0f} deg incidence; "
                                                "keep it below 80 deg")
        corners = np.concatenate([g["corners"], deform(case, g["corners"])])
        x = cam.project(corners)
        if np.any(x < 4) or np.any(x[:, 0] > cam.width - 5) or np.any(x[:, 1] > cam.height - 5):
            raise ConfigError(path, field_name, f"does not see the whole patch with a 4-pixel "
                                                f"margin (corners at {np.round(x[:4]).tolist()} in a "
                                                f"{cam.width}x{cam.height} image): enlarge pixels, "
                                                "move it away or shrink patch_mm")
        shift = np.linalg.norm(cam.sensitivity(g["centre"]) @ case.displacement)
        if shift >= 1.0:
            raise t.error("displacement_um", f"moves the patch by {shift:.2f} px in camera "
                                             f"{cam.name!r}; validation needs a sub-pixel shift")


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------
def strain_tensor(case: Case) -> np.ndarray:
    """The imposed in-plane strain as a world 3x3 displacement gradient T E Tᵀ (T = [t_u t_v],
    E the symmetric 2x2 of (eps_uu, eps_vv, eps_uv)); zeros for a translation case."""
    if case.strain is None:
        return np.zeros((3, 3))
    g = plate_geometry(case)
    T = np.stack([g["t_u"], g["t_v"]], axis=1)
    e = case.strain
    return T @ np.array([[e[0], e[2]], [e[2], e[1]]]) @ T.T


def deform(case: Case, points) -> np.ndarray:
    """Deformed positions X + U + F X (the patch centre is the world origin), metres."""
    points = np.asarray(points, dtype=float)
    return points + case.displacement + points @ strain_tensor(case).T


def undeform(case: Case, points) -> np.ndarray:
    """The reference position of deformed points (inverse of `deform`)."""
    points = np.asarray(points, dtype=float)
    return np.linalg.solve(np.eye(3) + strain_tensor(case), (points - case.displacement).T).T


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


def plate_geometry(case: Case) -> dict:
    """The plate's frame: normal n = (0, -sin tilt, cos tilt), the face frame (t_u, t_v) that
    vdo.scene gives such a face, the patch corners and the plate's 4 vertices (world, m)."""

    n = np.array([0.0, -math.sin(case.tilt), math.cos(case.tilt)])
    t_u, t_v = face_frame(n)
    w, h = case.patch
    centre = np.zeros(3)
    origin = centre - 0.5 * w * t_u - 0.5 * h * t_v
    corners = np.array([origin, origin + w * t_u, origin + w * t_u + h * t_v, origin + h * t_v])
    m = case.plate_margin
    pw, ph = w + 2 * m, h + 2 * m
    p0 = centre - 0.5 * pw * t_u - 0.5 * ph * t_v
    plate = np.array([p0, p0 + pw * t_u, p0 + pw * t_u + ph * t_v, p0 + ph * t_v])
    return dict(normal=n, t_u=t_u, t_v=t_v, centre=centre, origin=origin, corners=corners,
                plate=plate)


def cameras_of(case: Case) -> list:
    """The case's vdo Cameras, each aimed at the patch centre (the world origin)."""

    out = []
    for c in case.cameras:
        d = np.array([math.sin(c.polar) * math.cos(c.azimuth), math.sin(c.polar) * math.sin(c.azimuth),
                      math.cos(c.polar)])
        pos = c.distance * d
        if c.polar < 1e-9:
            pan, tilt = 0.0, -math.pi / 2
        else:
            pan, tilt = look_at_angles(pos, np.zeros(3))
        out.append(Camera(name=c.name, width=c.pixels[0], height=c.pixels[1], pixel_size=c.pixel_size,
                          focal_length=c.focal_length, position=pos, pan=pan, tilt=tilt))
    return out


@dataclass(eq=False)
class Setup:
    """Everything one case needs, built once."""

    case: Case
    experiment: Experiment
    cameras: list
    patch: object                   # vdo.dic.correlate.Patch
    plate: object                   # vdo.scene.SceneMesh
    region: object                  # vdo.scene.RegionFaces
    pattern: np.ndarray
    reference_linear: list = field(default_factory=list)
    deformed_linear: list = field(default_factory=list)


def experiment_for(case: Case, path: Path, cameras=None) -> Experiment:
    """An in-memory vdo Experiment for the case: one specimen plate, one region (the plate's
    face), ambient light only, the DIC patch side sqrt(patch area) (Ω = the correlated area);
    the strain analysis is the case's: subset DIC with its subset, step and window for a
    subset case, else global DIC with the patch's shorter side as element (it fits the region,
    the patch itself, up to rounding: `vdo.physics.strain.SIZE_TOLERANCE`)."""
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
                      analysis=analysis_of(case))


def analysis_of(case: Case) -> Analysis:
    """The `[analysis]` of a case (`experiment_for`): subset DIC (subset, step and window in
    metres, sizes in pixels unset) for a subset case, else global DIC, element = the patch's
    shorter side."""
    if case.subsets is not None:
        side, step, n = case.subsets
        return Analysis(method="subset", subset=side, subset_px=None, step=step, step_px=None,
                        strain_window=n)
    return Analysis(element=min(case.patch))


def build_setup(case: Case, path: Path) -> Setup:

    g = plate_geometry(case)
    exp = experiment_for(case, path)
    plate = SceneMesh("plate", "specimen", g["plate"], np.array([[0, 1, 2], [0, 2, 3]]))
    rf = region_faces(plate, exp.regions[0], exp.evaluation.sample_spacing, (path, case.name))
    patch = Patch(origin=g["origin"], t_u=g["t_u"], t_v=g["t_v"], size=np.array(case.patch))
    return Setup(case=case, experiment=exp, cameras=cameras_of(case), patch=patch, plate=plate,
                 region=rf, pattern=case_pattern(case))


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


# --------------------------------------------------------------------------------------------
# Prediction
# --------------------------------------------------------------------------------------------
def _samples(setup: Setup, n: int = 5):
    """n x n samples on the correlated patch (cell centres), as vdo.scene.SurfaceSamples."""

    w, h = setup.case.patch
    a, b = np.meshgrid((np.arange(n) + 0.5) / n * w, (np.arange(n) + 0.5) / n * h, indexing="ij")
    xi = np.stack([a.ravel(), b.ravel()], 1)
    pts = setup.patch.points(xi)
    m = len(pts)
    return SurfaceSamples(points=pts, normals=np.tile(setup.patch.normal, (m, 1)),
                          tangent_u=np.tile(setup.patch.t_u, (m, 1)),
                          tangent_v=np.tile(setup.patch.t_v, (m, 1)),
                          uv=setup.region.uv(pts), area=np.full(m, w * h / m),
                          region=np.zeros(m, dtype=int), region_names=("patch",),
                          region_importance=np.ones(1))


def _probe_camera(setup: Setup, factor: float):
    """A vanishingly weak extra view for the one-camera case: 30 deg off the first camera's
    axis, `factor` times farther away with the same lens (pixel footprint x factor)."""

    c = setup.case.cameras[0]
    polar = c.polar + math.radians(30.0)
    pos = factor * c.distance * np.array([math.sin(polar) * math.cos(c.azimuth),
                                          math.sin(polar) * math.sin(c.azimuth), math.cos(polar)])
    pan, tilt = look_at_angles(pos, np.zeros(3))
    return Camera(name="probe", width=c.pixels[0], height=c.pixels[1], pixel_size=c.pixel_size,
                  focal_length=c.focal_length, position=pos, pan=pan, tilt=tilt)


def _predict_once(setup: Setup, cameras, speckle) -> np.ndarray:
    """Per-axis sigma (m) of the correlated patch: vdo.physics.predict at n x n samples (each with Ω = the
    patch area), combined as the patch's mean information, 1 / mean(1 / σ²) per axis (exact when
    the per-sample covariances differ by a scale only; over a small patch they differ by < 1 %)."""

    # One camera: the model's information is rank 2 at every sample, its null direction the ray
    # through the sample, which tilts away from the normal off the optical axis; only at the patch
    # centre (on the axis) is the in-plane marginal the weak-probe limit. There the in-plane bound
    # is that of the centred patch (first-order variations over the patch cancel).
    pred = _prediction(setup, cameras, speckle, 5 if len(setup.case.cameras) > 1 else 1)
    return 1.0 / np.sqrt(np.mean(1.0 / pred.sigma_xyz ** 2, axis=0))


def _prediction(setup: Setup, cameras, speckle, n: int):
    """vdo.physics.predict at n x n samples of the correlated patch (each with Ω = the patch area)."""
    samples = _samples(setup, n)
    geometry = Geometry(setup.experiment, (setup.plate,), samples, speckle, (setup.region,),
                        patch_overlap(samples, setup.experiment.evaluation.patch_size))
    pred = layout_state(geometry, cameras, clip_patch=False).prediction
    if not np.all(pred.measured):
        raise RuntimeError(f"case {setup.case.name!r}: the prediction leaves part of the patch "
                           "unmeasured")
    return pred


def centre_element(case: Case) -> tuple[int, int]:
    """The Q4 element whose centre strain a strain case reads: the middle one."""
    return case.q4_mesh[0] // 2, case.q4_mesh[1] // 2


def predict_strain_sigma(setup: Setup) -> np.ndarray:
    """(3,) predicted sigma of (eps_uu, eps_vv, eps_uv) at the centre of `centre_element` of the
    case's Q4 mesh (single-image bound): vdo.physics.strain with Σ_u = Ω (mean C over 5 x 5 samples)⁻¹
    and the finite mesh's own factors (`vdo.physics.strain.q4_centre_gradient_factors`); or, for subset
    DIC, the virtual strain gauge's factor (`vdo.physics.strain.vsg_factor`)."""
    case = setup.case
    pred = _prediction(setup, setup.cameras, speckle_model_of(setup), 5)
    area = case.patch[0] * case.patch[1]
    sigma_u = strain.covariance_per_area(pred.information.mean(axis=0)[None], area, [True])
    if case.subsets is not None:
        F1 = F2 = float(strain.vsg_factor(*case.subsets))
    else:
        nx, ny = case.q4_mesh
        F1, F2 = strain.q4_centre_gradient_factors(nx, ny, *centre_element(case),
                                                   case.patch[0] / nx, case.patch[1] / ny)
    p = setup.patch
    return strain.strain_sigma(sigma_u, p.t_u[None], p.t_v[None], F1, F2)[0]


def measured_strain(setup: Setup, U_nodes: np.ndarray) -> np.ndarray:
    """(eps_uu, eps_vv, eps_uv) at the centre of `centre_element` from Q4 nodal displacements
    (nodes, 3) (world, m; node j * (nx + 1) + i): ∂U/∂ξ1 = (U_10 + U_11 - U_00 - U_01) / (2 h_x),
    ∂U/∂ξ2 likewise, projected on the face frame."""
    case, p = setup.case, setup.patch
    nx, ny = case.q4_mesh
    i, j = centre_element(case)
    hx, hy = case.patch[0] / nx, case.patch[1] / ny
    n00 = j * (nx + 1) + i
    u00, u10, u01, u11 = (U_nodes[n] for n in (n00, n00 + 1, n00 + nx + 1, n00 + nx + 2))
    d1 = (u10 + u11 - u00 - u01) / (2 * hx)
    d2 = (u01 + u11 - u00 - u10) / (2 * hy)
    return np.array([p.t_u @ d1, p.t_v @ d2, 0.5 * (p.t_u @ d2 + p.t_v @ d1)])


def predict_sigma(setup: Setup) -> np.ndarray:
    """(3,) predicted sigma per world axis (m), single-image bound. NaN out of plane for one
    camera (see the module docstring: a weak probe view, checked for convergence)."""
    speckle = speckle_model_of(setup)
    if len(setup.cameras) > 1:
        return _predict_once(setup, setup.cameras, speckle)
    a = _predict_once(setup, setup.cameras + [_probe_camera(setup, 35.0)], speckle)
    b = _predict_once(setup, setup.cameras + [_probe_camera(setup, 55.0)], speckle)
    inplane = np.abs(setup.patch.normal) < 0.5
    if np.any(np.abs(a[inplane] / b[inplane] - 1) > 2e-3):
        raise RuntimeError(f"case {setup.case.name!r}: the one-camera in-plane bound did not "
                           f"converge ({a} vs {b})")
    return np.where(inplane, b, np.nan)


# --------------------------------------------------------------------------------------------
# Correlation
# --------------------------------------------------------------------------------------------
def noise_free_images(setup: Setup, deformed: bool) -> list:
    """The noise-free DN images (reference or deformed) of every camera."""
    images = setup.deformed_linear if deformed else setup.reference_linear
    return [noise_free_dn(im, setup.case.sensor) for im in images]


def noise_free_check(setup: Setup):
    """Correlate the noise-free renders. Returns (the CorrelationResults: one, or one per subset;
    per-camera error of the measured displacement at the patch centre projected into each image,
    (n_cameras, 2) px)."""

    results = _correlate(setup, noise_free_images(setup, True), noise_free_images(setup, False))
    centre = setup.patch.points(setup.patch.size / 2)
    err = _centre_displacement(setup, results) - (deform(setup.case, centre) - centre)
    px = np.array([cam.sensitivity(centre) @ err for cam in setup.cameras])
    return results, px


def subset_patches(setup: Setup) -> list:
    """The n x n subsets of a subset-DIC case, centred in the patch on a grid of `step`, as
    `vdo.dic.correlate.Patch`es; index k = j n + i, i along t_u."""
    side, step, n = setup.case.subsets
    p = setup.patch
    offsets = (np.arange(n) - (n - 1) / 2) * step + p.size[0] / 2 - side / 2, \
        (np.arange(n) - (n - 1) / 2) * step + p.size[1] / 2 - side / 2
    return [Patch(origin=p.origin + offsets[0][i] * p.t_u + offsets[1][j] * p.t_v, t_u=p.t_u,
                  t_v=p.t_v, size=np.array([side, side])) for j in range(n) for i in range(n)]


def _correlate(setup: Setup, deformed, references, xi=None) -> list:
    """The case's correlation(s) of `deformed` against `references`: one global correlation
    (translation or Q4), or one translation per subset. `xi`: the points of an earlier call."""
    case = setup.case
    reference = ImageReference(references)
    if case.subsets is None:
        return [correlate(setup.cameras, deformed, setup.patch, reference, model=_model(case),
                          integration=PixelIntegration(None if xi is None else xi[0]))]
    return [correlate(setup.cameras, deformed, p, reference,
                      integration=PixelIntegration(None if xi is None else xi[k]))
            for k, p in enumerate(subset_patches(setup))]


def _subset_fit(setup: Setup, results) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane through the subsets' displacements: (mean U, (∂U/∂ξ1, ∂U/∂ξ2))."""
    side, step, n = setup.case.subsets
    U = np.array([r.U for r in results]).reshape(n, n, 3)        # [j, i]
    x = (np.arange(n) - (n - 1) / 2) * step
    w = x / (n * (x @ x))
    return U.mean(axis=(0, 1)), (np.einsum("i,jia->a", w, U), np.einsum("j,jia->a", w, U))


def _estimate(setup: Setup, results) -> np.ndarray:
    """U (translation) or the strain (eps_uu, eps_vv, eps_uv) from the correlation results."""
    case = setup.case
    if case.strain is None:
        return results[0].U
    if case.subsets is None:
        return measured_strain(setup, results[0].U)
    _, (d1, d2) = _subset_fit(setup, results)
    p = setup.patch
    return np.array([p.t_u @ d1, p.t_v @ d2, 0.5 * (p.t_u @ d2 + p.t_v @ d1)])


def _model(case: Case) -> Translation | Q4:
    return Translation() if case.strain is None else Q4(*case.q4_mesh)


def _centre_displacement(setup: Setup, results) -> np.ndarray:
    """The measured displacement at the patch centre: U itself (translation), the Q4 field
    interpolated there, or the subsets' plane fit's value there (their mean)."""
    if setup.case.subsets is not None:
        return _subset_fit(setup, results)[0]
    U = results[0].U
    if setup.case.strain is None:
        return U
    from vdo.dic.correlate import q4_shape_functions
    nx, ny = setup.case.q4_mesh
    N = q4_shape_functions(setup.patch.size[None] / 2, setup.patch.size, nx, ny)
    return np.asarray(N @ U)[0]


def noise_sigma_dn(setup: Setup) -> float:
    """The modelled image noise (DN rms) at the mean gray level, as vdo.physics.lighting computes it."""

    sp, case = setup.case.speckle, setup.case
    mean_f, _ = pattern_stats(setup.pattern)
    mean_rho = sp.black_albedo + (sp.white_albedo - sp.black_albedo) * mean_f
    return float(case.sensor.noise_sigma_dn(mean_rho * case.ambient_radiance))


def correlate_seed(setup: Setup, k: int, xi) -> np.ndarray:
    """U (3,) (or the strain, for a strain case) measured with seed k: independent noise in the
    reference and deformed images. `xi`: one list of per-camera points per correlation."""

    case = setup.case
    base = (case.seed * 1_000_003 + 2 * k) & 0x7FFFFFFF
    refs = [expose(im, case.sensor, base, i).astype(np.float64)
            for i, im in enumerate(setup.reference_linear)]
    defs = [expose(im, case.sensor, base + 1, i).astype(np.float64)
            for i, im in enumerate(setup.deformed_linear)]
    results = _correlate(setup, defs, refs, xi)
    if not all(r.converged for r in results):
        raise RuntimeError(f"case {case.name!r}, seed {k}: correlation did not converge")
    return _estimate(setup, results)


# --------------------------------------------------------------------------------------------
# One case, all cases
# --------------------------------------------------------------------------------------------
def axes_reported(case: Case) -> list[int]:
    """World axes reported: all three, or the in-plane ones for a single camera."""
    if len(case.cameras) > 1:
        return [0, 1, 2]
    n = plate_geometry(case)["normal"]
    return [k for k in range(3) if abs(n[k]) < 0.5]


def run_case(case: Case, path: Path, seeds: int, progress=None) -> CaseResult:
    """Render, predict, correlate `seeds` times; returns the per-axis statistics and diagnostics.
    `progress`: called with 1 after each seed."""
    t0 = time.perf_counter()
    setup = build_setup(case, path)
    render_case(setup)
    t_render = time.perf_counter() - t0
    res0, px_err = noise_free_check(setup)
    sigma_dn = noise_sigma_dn(setup)
    cov = res0[0].covariance(sigma_dn)
    if case.strain is None:
        sigma_pred, truth, scale, unit, names = predict_sigma(setup), case.displacement, UM, "um", AXES
        reported = axes_reported(case)
        sigma_lin = np.sqrt(np.diag(cov))
    else:
        sigma_pred, truth, scale, unit = predict_strain_sigma(setup), case.strain, 1e6, "microstrain"
        names, reported = STRAIN_AXES, [0, 1, 2]
        if case.subsets is None:
            G = np.array([measured_strain(setup, e.reshape(-1, 3)) for e in np.eye(len(cov))]).T
            sigma_lin = np.sqrt(np.diag(G @ cov @ G.T))
        else:       # the subsets' cross-covariances are not propagated by correlate
            sigma_lin = np.full(3, np.nan)
    estimates = np.empty((seeds, 3))
    for k in range(seeds):
        estimates[k] = correlate_seed(setup, k, [r.xi for r in res0])
        if progress is not None:
            progress(1)
    err = estimates - truth
    sigma_meas = err.std(axis=0, ddof=1)
    # the rows' *_um columns carry `unit`: micrometres, or microstrain for strain cases
    rows = []
    for a in reported:
        expected = SQRT2 * sigma_pred[a]
        ratio = sigma_meas[a] / expected
        # chi-square interval of a standard deviation from n - 1 degrees of freedom
        from scipy.stats import chi2
        lo = sigma_meas[a] * math.sqrt((seeds - 1) / chi2.ppf(0.975, seeds - 1)) / expected
        hi = sigma_meas[a] * math.sqrt((seeds - 1) / chi2.ppf(0.025, seeds - 1)) / expected
        rows.append({"case": case.name, "axis": names[a], "sigma_predicted_um": sigma_pred[a] * scale,
                     "sigma_measured_um": sigma_meas[a] * scale, "ratio": ratio, "n_seeds": seeds,
                     "sigma_expected_um": expected * scale, "ratio_ci95_low": lo, "ratio_ci95_high": hi,
                     "bias_um": err[:, a].mean() * scale,
                     "rms_error_um": math.sqrt(np.mean(err[:, a] ** 2)) * scale,
                     "sigma_linear_um": sigma_lin[a] * scale, "unit": unit})
    centre = setup.patch.points(setup.patch.size / 2)
    return CaseResult(rows=rows, estimates=estimates, setup=setup,
                      info={"case": case.name, "cameras": len(case.cameras),
                     "noise_dn": sigma_dn,
                     "noise_free_error_px": {c.name: px_err[i].tolist() for i, c in enumerate(setup.cameras)},
                     "noise_free_ok": bool(np.all(np.abs(px_err) < 0.01)),
                     **({} if case.strain is None else {"noise_free_strain_error_microstrain": (
                         (_estimate(setup, res0) - case.strain) * 1e6).tolist()}),
                     "pixels_per_camera": [int(len(x)) for x in res0[0].xi],
                     "speckle_px": [float(case.speckle.dot_diameter * np.sqrt(np.abs(np.linalg.det(
                         c.sensitivity(centre) @ setup.patch.tangents)))) for c in setup.cameras],
                     "shift_px": [float(np.linalg.norm(c.sensitivity(centre) @ case.displacement))
                                  for c in setup.cameras],
                     "render_seconds": round(t_render, 2),
                     "seconds": round(time.perf_counter() - t0, 2)})



@dataclass(frozen=True, eq=False)
class CaseResult:
    """One case's outcome (`run_case`): `rows` per reported axis (predicted, measured, ratio, ...;
    the *_um columns in `unit`), `estimates` (seeds, 3) the measured U (m) or strain, `setup` the
    case's cameras, patch and noise-free renders, `info` the diagnostics of summary.json."""

    rows: list
    estimates: np.ndarray
    setup: Setup
    info: dict


@dataclass(frozen=True, eq=False)
class ValidationResult:
    """Every chosen case of a validation file (`run_cases`), in file order."""

    spec: ValidationSpec
    seeds: int
    cases: tuple[CaseResult, ...]
    wall_seconds: float

    @property
    def rows(self) -> list[dict]:
        return [row for case in self.cases for row in case.rows]

    @property
    def passed(self) -> bool:
        """Every ratio inside `BAND`."""
        return all(BAND[0] <= r["ratio"] <= BAND[1] for r in self.rows)

    @property
    def noise_free_passed(self) -> bool:
        """Every case's noise-free correlation within 0.01 px of the imposed motion."""
        return all(c.info["noise_free_ok"] for c in self.cases)


def run_cases(spec: ValidationSpec, seeds: int | None = None,
              cases: list[str] | None = None) -> ValidationResult:
    """Run every case of `spec` (or those named in `cases`) with `seeds` noise seeds (default: the
    file's); a ConfigError for a bad seed count or an unknown case name before any work. Progress
    goes to the `vdo.dic.validate` logger (`vdo.core.progress`)."""
    from vdo.core.progress import bar

    seeds = spec.seeds if seeds is None else int(seeds)
    if seeds < 2:
        raise ConfigError(spec.path, "--seeds", f"must be at least 2 (got {seeds})")
    chosen = spec.cases
    if cases is not None:
        unknown = sorted(set(cases) - {c.name for c in spec.cases})
        if unknown:
            raise ConfigError(spec.path, "case", f"no case named {', '.join(map(repr, unknown))}")
        chosen = tuple(c for c in spec.cases if c.name in cases)
    started = time.perf_counter()
    results = []
    with bar(log, total=seeds * len(chosen), desc="validate", unit="seed") as progress:
        for case in chosen:
            progress.set_postfix_str(case.name)
            results.append(run_case(case, spec.path, seeds, progress=progress.update))
    return ValidationResult(spec=spec, seeds=seeds, cases=tuple(results),
                            wall_seconds=time.perf_counter() - started)
