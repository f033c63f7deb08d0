"""`vdo validate`: the predicted uncertainty against correlation on vdo's own renders.

For each case of a validation file (experiments/validation.toml, schema in docs/validation.md):

1. a planar speckled plate (tilted by `tilt_deg` about the world x axis; its normal is +z when
   frontal) is rendered by Mitsuba (`vdo.render.build_render_scene`, ambient light only) through each
   camera, once as it is (reference) and once translated by the imposed 3D displacement U, the
   texture moving with the plate. The renders are linear and noise-free: a constant environment
   sampled by cosine-weighted BSDF sampling on a Lambertian plate has zero Monte Carlo variance, and
   the stratified sampler without jitter integrates each box pixel by a fixed midpoint grid, so the
   only noise in the experiment is the sensor's;
2. the uncertainty of the correlated patch is predicted by `vdo.predict.predict` (the mean-field
   Cramér–Rao bound for ONE noisy image against a perfect reference) with the DIC patch area Ω equal
   to the correlated patch;
3. for each seed, independent sensor noise is drawn for the reference and the displaced image of
   every camera (`vdo.render.expose`, distinct seeds), and U is measured by global multi-view
   correlation (`vdo.correlate.correlate`, translation model, reference="images": each camera
   against its own noisy reference image);
4. the scatter of the measured U over the seeds is compared with the prediction. Both images are
   noisy, so the expected standard deviation is √2 σ_predicted, and

       ratio = sigma_measured / (√2 sigma_predicted)      (1 when the model is right).

With one camera only the in-plane axes are reported: the depth is seen through perspective alone.
The model's one-camera information is rank 2 (`predict` reports +inf), so its in-plane bound is the
limit of adding a vanishingly weak second view: a probe camera 35x and 55x farther away, whose information
is ~1e-7 of the first (`_predict_sigma`, checked to converge).
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .camera import Camera, look_at_angles
from .config import (SENSOR_FIELDS, Evaluation, Experiment, MeshSpec, RegionSpec, RenderSpec,
                     SpeckleSpec, Table, as_numbers, read_toml)
from .correlate import Patch, correlate
from .errors import ConfigError
from .lighting import illuminate, pattern_stats
from .predict import SpeckleModel, predict
from .render import (build_render_scene, contact_sheet, expose, noise_free_dn, render_linear,
                     render_seed, sensor_dict)
from .runfolder import inside, run_folder
from .scene import SceneMesh, SurfaceSamples, build_scene, face_frame, region_faces
from .sensor import SensorModel
from .speckle import gradient_energy_table, normalise, pattern_for
from .visibility import compute_visibility

AXES = "xyz"
UM = 1e6
SQRT2 = math.sqrt(2.0)
BAND = (0.8, 1.25)
CSV_FIELDS = ["case", "axis", "sigma_predicted_um", "sigma_measured_um", "ratio", "n_seeds",
              "sigma_expected_um", "ratio_ci95_low", "ratio_ci95_high", "bias_um", "rms_error_um",
              "sigma_linear_um"]
CONVENTION = ("sigma_predicted_um: vdo.predict, the Cramer-Rao bound for ONE noisy image against a "
              "noise-free reference, for the correlated patch. sigma_measured_um: standard "
              "deviation over the seeds of the correlated displacement, reference and deformed "
              "images both noisy (reference='images'). sigma_expected_um = sqrt(2) * "
              "sigma_predicted_um. ratio = sigma_measured_um / sigma_expected_um (1 when the model "
              "is right; the requirement is [0.8, 1.25]). ratio_ci95_*: the 95% interval of the "
              "ratio from the seed count alone. bias_um: mean error (measured - imposed). "
              "rms_error_um: rms error about the imposed displacement. sigma_linear_um: the "
              "correlation's own linear noise propagation (CorrelationResult.covariance) at the "
              "modelled noise level, on the noise-free images.")


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


@dataclass(frozen=True)
class ValidationSpec:
    path: Path
    name: str
    seeds: int
    cases: tuple[Case, ...]


_CASE_FIELDS = ("name", "description", "patch_mm", "plate_margin_mm", "tilt_deg", "dot_mm",
                "texel_mm", "edge_blur_mm", "coverage", "strokes", "speckle_seed", "tile_texels", "white_albedo",
                "black_albedo", "cameras", "focal_mm", "pixel_um", "pixels", "distance_mm",
                "ambient_radiance", "spp", "sensor", "displacement_um", "seed")
_CAMERA_FIELDS = ("name", "polar_deg", "azimuth_deg", "distance_mm", "focal_mm", "pixel_um",
                  "pixels")


def load(path) -> ValidationSpec:
    """Read and validate a validation file; ConfigError (file, field, message) on any mistake."""
    return parse(read_toml(path), Path(path))


def parse(data: dict, path) -> ValidationSpec:
    """Validate an already-parsed validation document that came from `path`.

    `[defaults]` holds any case field (but name); each `[[case]]` inherits it and overrides it
    (a case's `sensor` table is merged key by key over the defaults' one)."""
    path = Path(path).resolve()
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
                spp=t.integer("spp", 64, low=1), seed=t.integer("seed", 0, low=0))
    _check_geometry(case, t, path, where)
    return case


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
        corners = np.concatenate([g["corners"], g["corners"] + case.displacement])
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
    patch: object                   # vdo.correlate.Patch
    plate: object                   # vdo.scene.SceneMesh
    region: object                  # vdo.scene.RegionFaces
    pattern: np.ndarray
    reference_linear: list = field(default_factory=list)
    deformed_linear: list = field(default_factory=list)


def experiment_for(case: Case, path: Path, cameras=None) -> Experiment:
    """An in-memory vdo Experiment for the case: one specimen plate, one region (the plate's
    face), ambient light only, the DIC patch side sqrt(patch area) (Ω = the correlated area)."""
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
                      render=RenderSpec(spp=case.spp, ambient_radiance=case.ambient_radiance))


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
    """vdo.predict's SpeckleModel (statistics and gradient-energy table, vdo.speckle) of the
    pattern actually painted; the same as `vdo.predict.speckle_model` when edge_blur = 0."""

    sp = setup.case.speckle
    mean, std = pattern_stats(setup.pattern)
    table = gradient_energy_table(normalise(setup.pattern), sp.texel,
                                  l_max=max(50 * sp.dot_diameter, 0.05))
    return SpeckleModel(setup.pattern, mean, std, table)


# --------------------------------------------------------------------------------------------
# Renders
# --------------------------------------------------------------------------------------------
def render_case(setup: Setup) -> None:
    """Noise-free linear renders of every camera: the plate as it is, and translated by U with
    its texture (the face frame's origin moves with the vertices, so every point keeps its uv)."""

    case, exp = setup.case, setup.experiment
    U = case.displacement
    moved = SceneMesh("plate", "specimen", setup.plate.vertices + U, setup.plate.faces)
    moved_rf = replace(setup.region, origin=setup.region.origin + U)
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
    """Per-axis sigma (m) of the correlated patch: vdo.predict at n x n samples (each with Ω = the
    patch area), combined as the patch's mean information, 1 / mean(1 / σ²) per axis (exact when
    the per-sample covariances differ by a scale only; over a small patch they differ by < 1 %)."""

    exp = setup.experiment
    # One camera: the model's information is rank 2 at every sample, its null direction the ray
    # through the sample, which tilts away from the normal off the optical axis; only at the patch
    # centre (on the axis) is the in-plane marginal the weak-probe limit. There the in-plane bound
    # is that of the centred patch (first-order variations over the patch cancel).
    samples = _samples(setup, 5 if len(setup.case.cameras) > 1 else 1)
    blockers = build_scene([setup.plate])
    vis = compute_visibility(blockers, cameras, samples, exp.evaluation.incidence_limit, progress=False)
    illum = illuminate(blockers, (), samples, exp.render.ambient_radiance)
    pred = predict(exp, cameras, samples, vis, illum, speckle)
    if not np.all(pred.measured):
        raise RuntimeError(f"case {setup.case.name!r}: the prediction leaves part of the patch "
                           "unmeasured")
    return 1.0 / np.sqrt(np.mean(1.0 / pred.sigma_xyz ** 2, axis=0))


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
    """Correlate the noise-free renders. Returns (CorrelationResult, per-camera error of the
    measured U projected into each image, (n_cameras, 2) px)."""

    res = correlate(setup.cameras, noise_free_images(setup, True), setup.patch, reference="images",
                    reference_images=noise_free_images(setup, False), model="translation")
    err = res.U - setup.case.displacement
    centre = setup.patch.points(setup.patch.size / 2)
    px = np.array([cam.sensitivity(centre) @ err for cam in setup.cameras])
    return res, px


def noise_sigma_dn(setup: Setup) -> float:
    """The modelled image noise (DN rms) at the mean gray level, as vdo.lighting computes it."""

    sp, case = setup.case.speckle, setup.case
    mean_f, _ = pattern_stats(setup.pattern)
    mean_rho = sp.black_albedo + (sp.white_albedo - sp.black_albedo) * mean_f
    return float(case.sensor.noise_sigma_dn(mean_rho * case.ambient_radiance))


def correlate_seed(setup: Setup, k: int, xi) -> np.ndarray:
    """U (3,) measured with seed k: independent noise in reference and deformed images."""

    case = setup.case
    base = (case.seed * 1_000_003 + 2 * k) & 0x7FFFFFFF
    refs = [expose(im, case.sensor, base, i).astype(np.float64)
            for i, im in enumerate(setup.reference_linear)]
    defs = [expose(im, case.sensor, base + 1, i).astype(np.float64)
            for i, im in enumerate(setup.deformed_linear)]
    res = correlate(setup.cameras, defs, setup.patch, reference="images", reference_images=refs,
                    model="translation", xi=xi)
    if not res.converged:
        raise RuntimeError(f"case {case.name!r}, seed {k}: correlation did not converge")
    return res.U


# --------------------------------------------------------------------------------------------
# One case, all cases
# --------------------------------------------------------------------------------------------
def axes_reported(case: Case) -> list[int]:
    """World axes reported: all three, or the in-plane ones for a single camera."""
    if len(case.cameras) > 1:
        return [0, 1, 2]
    n = plate_geometry(case)["normal"]
    return [k for k in range(3) if abs(n[k]) < 0.5]


def run_case(case: Case, path: Path, seeds: int, progress=None) -> dict:
    """Render, predict, correlate `seeds` times; returns the per-axis statistics and diagnostics."""
    t0 = time.perf_counter()
    setup = build_setup(case, path)
    render_case(setup)
    t_render = time.perf_counter() - t0
    sigma_pred = predict_sigma(setup)
    res0, px_err = noise_free_check(setup)
    sigma_dn = noise_sigma_dn(setup)
    sigma_lin = np.sqrt(np.diag(res0.covariance(sigma_dn)))
    estimates = np.empty((seeds, 3))
    for k in range(seeds):
        estimates[k] = correlate_seed(setup, k, res0.xi)
        if progress is not None:
            progress(1)
    err = estimates - case.displacement
    sigma_meas = err.std(axis=0, ddof=1)
    rows = []
    for a in axes_reported(case):
        expected = SQRT2 * sigma_pred[a]
        ratio = sigma_meas[a] / expected
        # chi-square interval of a standard deviation from n - 1 degrees of freedom
        from scipy.stats import chi2
        lo = sigma_meas[a] * math.sqrt((seeds - 1) / chi2.ppf(0.975, seeds - 1)) / expected
        hi = sigma_meas[a] * math.sqrt((seeds - 1) / chi2.ppf(0.025, seeds - 1)) / expected
        rows.append({"case": case.name, "axis": AXES[a], "sigma_predicted_um": sigma_pred[a] * UM,
                     "sigma_measured_um": sigma_meas[a] * UM, "ratio": ratio, "n_seeds": seeds,
                     "sigma_expected_um": expected * UM, "ratio_ci95_low": lo, "ratio_ci95_high": hi,
                     "bias_um": err[:, a].mean() * UM,
                     "rms_error_um": math.sqrt(np.mean(err[:, a] ** 2)) * UM,
                     "sigma_linear_um": sigma_lin[a] * UM})
    centre = setup.patch.points(setup.patch.size / 2)
    return {"rows": rows, "estimates": estimates, "setup": setup,
            "info": {"case": case.name, "cameras": len(case.cameras),
                     "noise_dn": sigma_dn,
                     "noise_free_error_px": {c.name: px_err[i].tolist() for i, c in enumerate(setup.cameras)},
                     "noise_free_ok": bool(np.all(np.abs(px_err) < 0.01)),
                     "pixels_per_camera": [int(len(x)) for x in res0.xi],
                     "speckle_px": [float(case.speckle.dot_diameter * np.sqrt(np.abs(np.linalg.det(
                         c.sensitivity(centre) @ setup.patch.tangents)))) for c in setup.cameras],
                     "shift_px": [float(np.linalg.norm(c.sensitivity(centre) @ case.displacement))
                                  for c in setup.cameras],
                     "render_seconds": round(t_render, 2),
                     "seconds": round(time.perf_counter() - t0, 2)}}


def plot(rows: list[dict], path, title: str = "") -> None:
    """Measured against expected (√2 x predicted) sigma, log-log, y = x and the [0.8, 1.25] band."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 5.6), layout="constrained")
    x = np.array([r["sigma_expected_um"] for r in rows])
    y = np.array([r["sigma_measured_um"] for r in rows])
    lo, hi = min(x.min(), y.min()) / 1.6, max(x.max(), y.max()) * 1.6
    line = np.geomspace(lo, hi, 50)
    ax.fill_between(line, BAND[0] * line, BAND[1] * line, color="0.88", label="ratio in [0.8, 1.25]")
    ax.plot(line, line, "k-", lw=1, label="measured = √2 predicted")
    cases = list(dict.fromkeys(r["case"] for r in rows))
    colors = plt.get_cmap("tab10")
    markers = {"x": "o", "y": "s", "z": "^"}
    for r in rows:
        ci = cases.index(r["case"])
        err = [[r["sigma_measured_um"] * (1 - r["ratio_ci95_low"] / r["ratio"])],
               [r["sigma_measured_um"] * (r["ratio_ci95_high"] / r["ratio"] - 1)]]
        ax.errorbar(r["sigma_expected_um"], r["sigma_measured_um"], yerr=err, fmt=markers[r["axis"]],
                    color=colors(ci % 10), ms=6, capsize=2,
                    label=f"{r['case']} {r['axis']}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_xlabel("expected σ = √2 × predicted (µm)  [both images noisy]")
    ax.set_ylabel("measured σ over seeds (µm)")
    ax.set_title(title or "vdo validate: predicted vs measured uncertainty", fontsize=10)
    ax.legend(fontsize=6, ncol=2, loc="upper left")
    ax.grid(True, which="both", alpha=0.3)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_csv(rows: list[dict], path) -> None:
    with open(path, "w", newline="") as fh:
        fh.write(f"# {CONVENTION}\n")
        writer = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for r in rows:
            writer.writerow({k: (f"{v:.5g}" if isinstance(v, float) else v) for k, v in r.items()})


def validate(spec: ValidationSpec, out, seeds: int | None = None, overwrite: bool = False,
             quiet: bool = False, cases: list[str] | None = None) -> dict:
    """Run every case (or those named in `cases`) with `seeds` seeds (default: the file's) and
    write the run folder `out` (vdo.runfolder, appears whole or not at all):

    validation.csv     per case and axis: predicted, measured, ratio, n_seeds (+ diagnostics);
                       a '#' comment line states the convention
    validation.png     measured against √2 x predicted sigma, log-log, the [0.8, 1.25] band
    estimates.csv      every measured U (µm) per case and seed
    summary.json       the convention, per-case diagnostics (noise-free errors, speckle and shift in
                       pixels, times), wall time, pass/fail
    images/<case>.png  the noise-free reference image of each camera
    validation.toml    a copy of the validation file
    """
    from tqdm import tqdm


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
    rows, infos, estimates = [], [], {}
    with run_folder(out, overwrite) as tmp:
        (tmp / "images").mkdir()
        bar = tqdm(total=seeds * len(chosen), desc="validate", unit="seed", disable=quiet)
        for case in chosen:
            bar.set_postfix_str(case.name)
            result = run_case(case, spec.path, seeds, progress=bar.update)
            rows += result["rows"]
            infos.append(result["info"])
            estimates[case.name] = result["estimates"]
            setup = result["setup"]
            contact_sheet({c.name: np.rint(im).astype(np.int64) for c, im in
                           zip(setup.cameras, noise_free_images(setup, False))}, case.sensor.max_dn,
                          inside(tmp / "images", f"{case.name}.png"), f"{case.name}: noise-free reference")
        bar.close()
        wall = time.perf_counter() - started
        write_csv(rows, tmp / "validation.csv")
        with open(tmp / "estimates.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["case", "seed", "Ux_um", "Uy_um", "Uz_um"])
            for name, est in estimates.items():
                for k, u in enumerate(est):
                    w.writerow([name, k, *(f"{v * UM:.6g}" for v in u)])
        plot(rows, tmp / "validation.png", f"{spec.name}: {seeds} seeds per case")
        shutil.copyfile(spec.path, tmp / "validation.toml")
        passed = all(BAND[0] <= r["ratio"] <= BAND[1] for r in rows)
        summary = {"name": spec.name, "config": str(spec.path), "seeds": seeds,
                   "convention": CONVENTION, "band": list(BAND), "passed": passed,
                   "noise_free_passed": all(i["noise_free_ok"] for i in infos),
                   "wall_seconds": round(wall, 1), "cases": infos,
                   "rows": [{k: (round(v, 6) if isinstance(v, float) else v) for k, v in r.items()}
                            for r in rows]}
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def print_table(rows: list[dict]) -> None:
    print(f"{'case':<24}{'axis':>5}{'pred um':>10}{'sqrt2*pred':>12}{'meas um':>10}{'ratio':>8}"
          f"{'95% CI':>15}{'bias um':>10}{'n':>6}")
    for r in rows:
        flag = "" if BAND[0] <= r["ratio"] <= BAND[1] else "  OUTSIDE"
        print(f"{r['case']:<24}{r['axis']:>5}{r['sigma_predicted_um']:>10.4f}"
              f"{r['sigma_expected_um']:>12.4f}{r['sigma_measured_um']:>10.4f}{r['ratio']:>8.3f}"
              f"{r['ratio_ci95_low']:>8.3f}-{r['ratio_ci95_high']:.3f}{r['bias_um']:>10.4f}"
              f"{r['n_seeds']:>6}{flag}")
