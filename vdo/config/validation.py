"""The validation file of `vdo validate` (schema in docs/validation.md): its cases, read and
checked field by field. Imports no JAX, Mitsuba or matplotlib, so that a mistake in any case is
refused before any heavy import; what needs the cameras themselves (each sees the whole patch, a
sub-pixel shift) is checked next by `vdo.geometry.plate.check_cases`, still before any render.

Units as in the file's names (mm, µm, deg, microstrain); the `Case` holds SI (m, rad, strain).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vdo.config.rig import SENSOR_FIELDS, SpeckleSpec
from vdo.config.procedure import Analysis
from vdo.config.reader import Table, as_numbers, read_toml, with_overrides
from vdo.config.schema import rows_of
from vdo.core.errors import ConfigError
from vdo.core.tolerances import SIZE_TOLERANCE, fits
from vdo.model.sensor import SensorModel


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
    processing: str = "all-views"       # [analysis] processing: "all-views" or "pairs"
    pairs: str = "auto"                 # [analysis] pairs: "auto" (the pair rule) or "declared"
    merge: str = "best"                 # [analysis] merge: "best" or "fusion"
    max_pair_angle: float | None = None  # rad, [analysis] max_pair_angle_deg (auto pairs)
    stereo_pairs: tuple[tuple[str, str], ...] = ()   # declared pairs, by camera name


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
                "strain_microstrain", "q4_mesh", "subset_mm", "step_mm", "strain_window",
                "processing", "pairs", "merge", "max_pair_angle_deg", "stereo_pairs")
# the pair-processing fields of a case: the experiment's [analysis] rows (same keys, choices, units)
_PAIR_ROWS = {r.key: r for r in rows_of(Analysis)
              if r.key in ("processing", "pairs", "merge", "max_pair_angle_deg")}
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
    (`vdo.config.reader.with_overrides`)."""
    path = Path(path).resolve()
    data = with_overrides(data, ("validation", "defaults"))
    if "case" not in data and "validation" not in data and ("experiment" in data or "camera" in data):
        raise ConfigError(path, "", "is an experiment file; vdo validate reads a validation file "
                                    "([validation] and [[case]] tables, e.g. experiments/validation.toml, "
                                    "docs/validation.md); an experiment's renders are correlated as "
                                    "docs/exports.md shows")
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
                **_strain_fields(t, len(cameras)), **_pair_fields(t, cameras))
    return case


def _pair_fields(t: Table, cameras) -> dict:
    """Stereo-pair processing of a displacement case, with the keys and choices of the
    experiment's [analysis] (`processing`, `pairs`, `merge`, `max_pair_angle_deg`) and, for
    declared pairs, `stereo_pairs` = [["cam1", "cam2"], ...] by camera name."""
    v = {r.attr: t.get(r, r.default) for r in _PAIR_ROWS.values()}
    if v["processing"] == "pairs":
        if len(cameras) < 2:
            raise t.error("processing", f'"pairs" needs at least two cameras (the case has '
                                        f'{len(cameras)}); use processing = "all-views"')
        if t.has("strain_microstrain"):
            raise t.error("processing", 'pair processing applies to displacement cases; remove '
                                        'strain_microstrain or use processing = "all-views"')
    elif v["pairs"] == "declared":
        raise t.error("pairs", 'declared pairs need processing = "pairs"')
    if v["pairs"] != "declared":
        if t.has("stereo_pairs"):
            raise t.error("stereo_pairs", 'declared pairs need pairs = "declared"')
        return {**v, "stereo_pairs": ()}
    names = [c.name for c in cameras]
    raw = t.raw("stereo_pairs", None)
    if not isinstance(raw, list) or not raw:
        raise t.error("stereo_pairs", 'pairs = "declared" needs stereo_pairs = [["cam1", "cam2"], ...] '
                                      f'(cameras: {", ".join(names)})')
    declared = []
    for k, pair in enumerate(raw):
        if not (isinstance(pair, list) and len(pair) == 2 and all(isinstance(n, str) for n in pair)
                and pair[0] != pair[1]):
            raise t.error(f"stereo_pairs[{k}]", f'must name two different cameras, e.g. '
                                                f'["{names[0]}", "{names[1]}"] (got {pair!r})')
        unknown = [n for n in pair if n not in names]
        if unknown:
            raise t.error(f"stereo_pairs[{k}]", f"no camera named {unknown[0]!r} in this case "
                                                f"(cameras: {', '.join(names)})")
        if tuple(sorted(pair)) in {tuple(sorted(p)) for p in declared}:
            raise t.error(f"stereo_pairs[{k}]", f"the pair {pair!r} is declared twice")
        declared.append((pair[0], pair[1]))
    return {**v, "stereo_pairs": tuple(declared)}


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
