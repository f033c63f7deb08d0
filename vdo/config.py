"""The experiment file: TOML schema, validation, units and defaults.

One TOML file describes one experiment. Lengths are metres unless a field's name says otherwise
(``_mm``); angles are degrees in the file (``_deg``) and radians inside vdo. Mesh files are read with
the unit they declare. Relative paths are relative to the TOML file.

Everything is validated before any work starts. A user mistake raises `ConfigError` naming the file,
the field (``camera "cam3".focal_mm``) and what is expected. See docs/config.md for the schema.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .camera import Camera, look_at_angles
from .errors import ConfigError
from .rail import Rail
from .sensor import SensorModel

SENSOR_FIELDS = tuple(f.name for f in dataclasses.fields(SensorModel))   # the [sensor] table
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
ROLES = ("specimen", "obstacle")
_REQUIRED = object()


# --------------------------------------------------------------------------------------------
# Validated pieces
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MeshSpec:
    """A mesh file and how it looks: diffuse paint of `albedo`, or bare metal when `metal`."""

    name: str
    path: Path
    unit: str
    role: str
    albedo: float = 0.5
    metal: bool = False

    @property
    def scale(self) -> float:
        """Metres per mesh unit."""
        return UNITS[self.unit]


@dataclass(frozen=True, eq=False)
class RegionSpec:
    """A region of interest: the faces of `mesh` whose normal is within `normal_tolerance` of
    `normal` and whose centroid lies in the box [box_min, box_max] (metres)."""

    name: str
    mesh: str
    normal: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    importance: float = 1.0
    normal_tolerance: float = math.radians(5.0)
    min_cameras: int | None = None     # coverage requirement; None: the experiment's default


@dataclass(frozen=True, eq=False)
class CameraSpec:
    """A camera as written in the file; `Experiment.cameras()` resolves its pose."""

    name: str
    sensor_width: float          # m
    pixels: tuple[int, int]
    focal_length: float          # m
    rail: str | None = None
    u: float | None = None
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    position: np.ndarray | None = None
    target: np.ndarray | None = None
    pan: float | None = None     # rad
    tilt: float | None = None    # rad
    roll: float = 0.0            # rad
    principal_offset_px: tuple[float, float] = (0.0, 0.0)
    body: bool = True
    f_number: float | None = None    # with focus_distance: thin lens with depth of field
    focus_distance: float | None = None  # m
    mount: str | None = None     # a zone or fixed [[mount]] (rail mounts set `rail`)


@dataclass(frozen=True)
class Evaluation:
    sample_spacing: float = 0.01                      # m between surface samples
    incidence_limit: float = math.radians(75.0)       # rad, from the surface normal
    patch_size: float = 0.01                          # m, side of the DIC patch (Omega = side^2)
    min_cameras: int = 2                              # default coverage requirement per point


@dataclass(frozen=True, eq=False)
class LightSpec:
    """A rectangular LED panel: a one-sided diffuse area emitter of `radiance` (W sr^-1 m^-2,
    any consistent unit: the sensor's photons_per_unit maps it to electrons) centred at `position`
    and facing `target`, `size` (width, height) in metres."""

    name: str
    position: np.ndarray
    target: np.ndarray
    size: tuple[float, float]
    radiance: float


@dataclass(frozen=True)
class SpeckleSpec:
    """The paint on the regions of interest: generated dots + strokes, or a user image."""

    dot_diameter: float = 2e-3       # m
    coverage: float = 0.5            # black area fraction
    strokes: int = 10                # brush strokes per tile
    texel: float = 0.25e-3           # m per texel of the pattern
    tile_texels: int = 1024          # the tile repeats every tile_texels * texel metres
    seed: int = 1
    image: Path | None = None        # a photo of a real pattern, at `texel` m per pixel
    white_albedo: float = 0.8
    black_albedo: float = 0.05


@dataclass(frozen=True)
class RenderSpec:
    spp: int = 16                    # samples per pixel
    scale: float = 1.0               # image size relative to the sensor's pixel counts
    seed: int = 0
    ambient_radiance: float = 0.0    # uniform environment light, same unit as LightSpec.radiance
    image_format: str = "png"        # png | tiff (16-bit above 8-bit depth)
    exr: bool = False                # also write the linear float image


@dataclass(frozen=True)
class OptimizeSpec:
    """What `vdo optimize` may move and the practical constraints it enforces."""

    free: tuple[str, ...] = ("u", "pan", "tilt")   # per camera: rail parameter, pan, tilt (, roll, lens)
    lenses: tuple[float, ...] = ()                 # m: focal lengths on the shelf, when "lens" is free
    cameras: tuple[str, ...] | None = None         # cameras that move (None: all)
    regions: tuple[str, ...] | None = None         # regions whose uncertainty is scored (None: all)
    min_axis_angle: float | None = None            # rad; None: the stereo rule of thumb per lens
    clearance: float = 0.05                        # m between camera bodies and everything else
    max_obscuration: float = 0.01                  # fraction of an assigned region's image
    assign_fraction: float = 0.5                   # a camera is assigned the regions it sees this much of
    starts: int = 3                                # multi-start: the hand layout + perturbed copies
    rounds: int = 3                                # visibility refreshes (outer penalty rounds)
    max_steps: int = 40                            # BFGS steps per round
    seed: int = 0


@dataclass(frozen=True, eq=False)
class Experiment:
    """A validated experiment. `path` is the TOML file it came from."""

    path: Path
    name: str
    meshes: tuple[MeshSpec, ...]
    regions: tuple[RegionSpec, ...]
    rails: tuple[Rail, ...]
    camera_specs: tuple[CameraSpec, ...]
    evaluation: Evaluation
    description: str = ""
    lights: tuple[LightSpec, ...] = ()
    speckle: SpeckleSpec = SpeckleSpec()
    sensor: SensorModel = SensorModel()
    render: RenderSpec = RenderSpec()
    optimize: OptimizeSpec = OptimizeSpec()
    mounts: tuple["MountSpec", ...] = ()   # zone and fixed mounts (rail mounts are in `rails`)

    def mount(self, name: str) -> "MountSpec":
        return next(m for m in self.mounts if m.name == name)

    def rail(self, name: str) -> Rail:
        return next(r for r in self.rails if r.name == name)

    def cameras(self) -> list[Camera]:
        """The configured cameras with poses resolved from rails, positions and targets."""
        return [_resolve_camera(self, spec) for spec in self.camera_specs]

    def with_cameras(self, specs) -> "Experiment":
        return replace(self, camera_specs=tuple(specs))

    def to_dict(self) -> dict:
        """The resolved experiment as a TOML-ready dict (absolute mesh paths, defaults filled)."""
        ev, sp, rd = self.evaluation, self.speckle, self.render
        out = {"experiment": {"name": self.name, "description": self.description},
               "evaluation": {"sample_spacing_mm": ev.sample_spacing * 1e3,
                              "incidence_limit_deg": math.degrees(ev.incidence_limit),
                              "patch_mm": ev.patch_size * 1e3, "min_cameras": ev.min_cameras},
               "mesh": [{"name": m.name, "file": str(m.path), "unit": m.unit, "role": m.role,
                         "albedo": m.albedo, "metal": m.metal} for m in self.meshes],
               "region": [_region_to_dict(r) for r in self.regions],
               "rail": [{"name": r.name, "control_points_m": r.control_points.tolist(),
                         "degree": r.degree, "weights": r.weights.tolist()} for r in self.rails],
               "mount": [_mount_to_dict(m) for m in self.mounts],
               "camera": [_camera_to_dict(c) for c in self.camera_specs],
               "light": [{"name": lt.name, "position_m": lt.position.tolist(),
                          "target_m": lt.target.tolist(), "size_m": list(lt.size),
                          "radiance": lt.radiance} for lt in self.lights],
               "speckle": {"dot_diameter_mm": sp.dot_diameter * 1e3, "coverage": sp.coverage,
                           "strokes": sp.strokes, "texel_mm": sp.texel * 1e3,
                           "tile_texels": sp.tile_texels, "seed": sp.seed,
                           "white_albedo": sp.white_albedo, "black_albedo": sp.black_albedo}
               | ({"image": str(sp.image)} if sp.image else {}),
               "sensor": {k: v for k, v in dataclasses.asdict(self.sensor).items() if v is not None},
               "render": {"spp": rd.spp, "scale": rd.scale, "seed": rd.seed,
                          "ambient_radiance": rd.ambient_radiance, "image_format": rd.image_format,
                          "exr": rd.exr}}
        return {k: v for k, v in out.items() if v != []}


def _region_to_dict(r: RegionSpec) -> dict:
    d = {"name": r.name, "mesh": r.mesh, "normal": r.normal.tolist(), "importance": r.importance,
         "normal_tolerance_deg": math.degrees(r.normal_tolerance)}
    if r.min_cameras is not None:
        d["min_cameras"] = r.min_cameras
    for key, box in (("box_min_m", r.box_min), ("box_max_m", r.box_max)):
        if np.all(np.isfinite(box)):
            d[key] = box.tolist()
    return d


def _camera_to_dict(c: CameraSpec) -> dict:
    d = {"name": c.name, "sensor_width_mm": c.sensor_width * 1e3, "pixels": list(c.pixels),
         "focal_mm": c.focal_length * 1e3}
    if c.rail is not None:
        d |= {"rail": c.rail, "u": c.u, "offset_m": c.offset.tolist()}
    elif c.mount is not None:
        d |= {"mount": c.mount, "position_m": c.position.tolist()}
    else:
        d["position_m"] = c.position.tolist()
    if c.target is not None:
        d["target_m"] = c.target.tolist()
    else:
        d |= {"pan_deg": math.degrees(c.pan), "tilt_deg": math.degrees(c.tilt)}
    d |= {"roll_deg": math.degrees(c.roll), "principal_offset_px": list(c.principal_offset_px),
          "body": c.body}
    if c.f_number is not None:
        d |= {"f_number": c.f_number, "focus_m": c.focus_distance}
    return d


def _resolve_camera(exp: Experiment, spec: CameraSpec) -> Camera:
    if spec.rail is not None:
        position = np.asarray(exp.rail(spec.rail).position(spec.u)) + spec.offset
    else:
        position = spec.position
    if spec.target is not None:
        pan, tilt = look_at_angles(position, spec.target)
    else:
        pan, tilt = spec.pan, spec.tilt
    width, height = spec.pixels
    return Camera(name=spec.name, width=width, height=height,
                  pixel_size=spec.sensor_width / width, focal_length=spec.focal_length,
                  position=np.asarray(position, dtype=float), pan=pan, tilt=tilt, roll=spec.roll,
                  principal_offset_px=spec.principal_offset_px)


# --------------------------------------------------------------------------------------------
# Reading with clear errors
# --------------------------------------------------------------------------------------------
class Table:
    """One TOML table being read: every key must be known, every value checked."""

    def __init__(self, data, where: str, file: Path, allowed: tuple[str, ...]):
        self.file, self.where = file, where
        if not isinstance(data, dict):
            raise ConfigError(file, where, "must be a table")
        for key in data:
            if key not in allowed:
                close = difflib.get_close_matches(key, allowed, n=1)
                hint = f"did you mean {close[0]!r}?" if close else f"known fields: {', '.join(allowed)}"
                raise ConfigError(file, self._field(key), f"unknown field; {hint}")
        self.data = data

    def _field(self, key):
        return f"{self.where}.{key}" if self.where else key

    def error(self, key, message):
        return ConfigError(self.file, self._field(key), message)

    def has(self, key):
        return key in self.data

    def raw(self, key, default=_REQUIRED):
        if key not in self.data:
            if default is _REQUIRED:
                raise self.error(key, "is required")
            return default
        return self.data[key]

    def string(self, key, default=_REQUIRED, choices=None):
        value = self.raw(key, default)
        if value is None:
            return None
        if not isinstance(value, str) or not value:
            raise self.error(key, f"must be a non-empty string (got {value!r})")
        if choices is not None and value not in choices:
            raise self.error(key, f"must be one of {', '.join(choices)} (got {value!r})")
        return value

    def boolean(self, key, default=_REQUIRED):
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"must be true or false (got {value!r})")
        return value

    def number(self, key, default=_REQUIRED, low=None, high=None, positive=False):
        value = self.raw(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.error(key, f"must be a finite number (got {value!r})")
        if positive and value <= 0:
            raise self.error(key, f"must be positive (got {value!r})")
        if (low is not None and value < low) or (high is not None and value > high):
            raise self.error(key, f"must lie in [{low}, {high}] (got {value!r})")
        return float(value)

    def integer(self, key, default=_REQUIRED, low=None):
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or (low is not None and value < low):
            raise self.error(key, f"must be an integer >= {low} (got {value!r})")
        return value

    def vector(self, key, length, default=_REQUIRED, positive=False):
        if key not in self.data and default is not _REQUIRED:
            return default
        value = self.raw(key)
        arr = as_numbers(value)
        if arr is None or arr.shape != (length,):
            raise self.error(key, f"must be a list of {length} finite numbers (got {value!r})")
        if positive and np.any(arr <= 0):
            raise self.error(key, f"must be positive (got {value!r})")
        return arr

    def points(self, key, minimum=2):
        value = self.raw(key)
        arr = as_numbers(value)
        if arr is None or arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < minimum:
            raise self.error(key, f"must be a list of at least {minimum} [x, y, z] points in metres")
        return arr


def as_numbers(value):
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return None
    if arr.dtype == object or not np.all(np.isfinite(arr)):
        return None
    return arr


def _entries(top: Table, key: str, file: Path, allowed, required=True):
    items = top.raw(key, [] if not required else _REQUIRED)
    if not isinstance(items, list) or (required and not items):
        raise ConfigError(file, key, f"needs at least one [[{key}]] table")
    tables, names = [], set()
    for i, item in enumerate(items):
        name = item.get("name") if isinstance(item, dict) else None
        where = f'{key} "{name}"' if isinstance(name, str) else f"{key}[{i}]"
        table = Table(item, where, file, allowed)
        table.string("name")
        if name in names:
            raise ConfigError(file, where, "name is used twice; names must be unique")
        names.add(name)
        tables.append(table)
    return tables


def read_toml(path) -> dict:
    """The parsed TOML document at `path`; ConfigError when it is missing, unreadable or invalid."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except OSError as exc:
        raise ConfigError(path, "", f"cannot be read ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(path, "", f"is not valid TOML ({exc})") from None


def load(path) -> Experiment:
    """Read and validate an experiment file. Raises ConfigError on any user mistake."""
    return parse(read_toml(path), Path(path))


def parse(data: dict, path: Path) -> Experiment:
    """Validate an already-parsed TOML document that came from `path`."""
    path = Path(path).resolve()
    top = Table(data, "", path, ("experiment", "evaluation", "mesh", "region", "rail", "mount",
                                  "camera", "light", "speckle", "sensor", "render", "optimize"))
    exp = Table(top.raw("experiment"), "experiment", path, ("name", "description"))
    ev = Table(top.raw("evaluation", {}), "evaluation", path,
                ("sample_spacing_mm", "incidence_limit_deg", "patch_mm", "min_cameras"))
    evaluation = Evaluation(
        sample_spacing=ev.number("sample_spacing_mm", 10.0, positive=True) * 1e-3,
        incidence_limit=math.radians(ev.number("incidence_limit_deg", 75.0, low=1.0, high=89.9)),
        patch_size=ev.number("patch_mm", 10.0, positive=True) * 1e-3,
        min_cameras=ev.integer("min_cameras", 2, low=1))

    meshes = tuple(_mesh(t, path) for t in _entries(
        top, "mesh", path, ("name", "file", "unit", "role", "albedo", "metal")))
    mesh_roles = {m.name: m.role for m in meshes}
    if "specimen" not in mesh_roles.values():
        raise ConfigError(path, "mesh", 'needs at least one mesh with role = "specimen"')
    regions = tuple(_region(t, mesh_roles) for t in _entries(
        top, "region", path, ("name", "mesh", "normal", "box_min_m", "box_max_m", "importance",
                              "normal_tolerance_deg", "min_cameras")))
    rails = tuple(_rail(t) for t in _entries(top, "rail", path,
                                             ("name", "control_points_m", "degree", "weights"),
                                             required=False))
    mount_rails, mounts = _mounts(top, path)
    clash = {r.name for r in rails} & ({r.name for r in mount_rails} | {m.name for m in mounts})
    if clash:
        raise ConfigError(path, "mount", f"{sorted(clash)[0]!r} names both a [[rail]] and a [[mount]]; rename one")
    rails += mount_rails
    rail_names = {r.name for r in rails}
    cameras = tuple(_camera(t, rail_names, mounts) for t in _entries(
        top, "camera", path, ("name", "sensor_mm", "sensor_width_mm", "pixels", "focal_mm", "rail",
                              "u", "offset_m", "position_m", "target_m", "pan_deg", "tilt_deg",
                              "roll_deg", "principal_offset_px", "body", "f_number", "focus_m",
                              "mount")))
    lights = tuple(_light(t) for t in _entries(
        top, "light", path, ("name", "position_m", "target_m", "size_m", "radiance"), required=False))
    result = Experiment(path=path, name=exp.string("name"),
                        description=exp.raw("description", "") or "", meshes=meshes,
                        regions=regions, rails=rails, camera_specs=cameras, evaluation=evaluation,
                        lights=lights, speckle=_speckle(top, path), sensor=_sensor(top, path),
                        render=_render(top, path),
                        optimize=_optimize(top, path, {c.name for c in cameras},
                                           {r.name for r in regions}), mounts=mounts)
    for spec, camera in zip(cameras, result.cameras()):
        if spec.target is not None and np.linalg.norm(spec.target - camera.position) < 1e-6:
            raise ConfigError(path, f'camera "{spec.name}".target_m', "is the camera's own position")
    return result


def _light(t: Table) -> LightSpec:
    position, target = t.vector("position_m", 3), t.vector("target_m", 3)
    if np.linalg.norm(target - position) < 1e-6:
        raise t.error("target_m", "must differ from position_m (the panel faces the target)")
    return LightSpec(name=t.string("name"), position=position, target=target,
                     size=tuple(t.vector("size_m", 2, positive=True)),
                     radiance=t.number("radiance", positive=True))


def _speckle(top: Table, path: Path) -> SpeckleSpec:
    t = Table(top.raw("speckle", {}), "speckle", path,
               ("dot_diameter_mm", "coverage", "strokes", "texel_mm", "tile_texels", "seed", "image",
                "white_albedo", "black_albedo"))
    image = t.string("image", None)
    if image is not None:
        image = (path.parent / image).resolve()
        if not image.is_file():
            raise t.error("image", f"pattern image {str(image)!r} does not exist")
    spec = SpeckleSpec(dot_diameter=t.number("dot_diameter_mm", 2.0, positive=True) * 1e-3,
                       coverage=t.number("coverage", 0.5, low=0.01, high=0.95),
                       strokes=t.integer("strokes", 10, low=0),
                       texel=t.number("texel_mm", 0.25, positive=True) * 1e-3,
                       tile_texels=t.integer("tile_texels", 1024, low=64), seed=t.integer("seed", 1, low=0),
                       image=image, white_albedo=t.number("white_albedo", 0.8, low=0.0, high=1.0),
                       black_albedo=t.number("black_albedo", 0.05, low=0.0, high=1.0))
    if spec.black_albedo >= spec.white_albedo:
        raise t.error("black_albedo", "must be less than white_albedo")
    if image is None and spec.dot_diameter < 3 * spec.texel:
        raise t.error("texel_mm", f"must be at most a third of the dot diameter "
                                  f"({spec.dot_diameter * 1e3:g} mm) to draw round dots")
    return spec


def _sensor(top: Table, path: Path) -> SensorModel:
    t = Table(top.raw("sensor", {}), "sensor", path, SENSOR_FIELDS)
    values = {k: t.raw(k) for k in SENSOR_FIELDS if t.has(k)}
    try:
        return SensorModel(**values)
    except ValueError as exc:      # SensorModel names the field: "SensorModel.<field>: ..."
        field, _, message = str(exc).partition(": ")
        raise t.error(field.removeprefix("SensorModel."), message) from None


def _optimize(top: Table, path: Path, cameras: set, regions: set) -> OptimizeSpec:
    t = Table(top.raw("optimize", {}), "optimize", path,
               ("free", "cameras", "regions", "min_axis_angle_deg", "clearance_m", "max_obscuration",
                "assign_fraction", "starts", "rounds", "max_steps", "seed", "lenses_mm"))
    free = t.raw("free", ["u", "pan", "tilt"])
    if not isinstance(free, list) or not set(free) <= {"u", "pan", "tilt", "roll", "lens"} or not free:
        raise t.error("free", f"must list some of u, pan, tilt, roll, lens (got {free!r})")
    lenses = t.raw("lenses_mm", [])
    if not isinstance(lenses, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                               and math.isfinite(x) and x > 0 for x in lenses):
        raise t.error("lenses_mm", f"must be a list of focal lengths in mm, each > 0 (got {lenses!r})")
    if "lens" in free and not lenses:
        raise t.error("free", 'lists "lens" but no lenses_mm catalogue is given: add e.g. '
                              'lenses_mm = [24, 35, 50, 100]')
    moving = t.raw("cameras", None)
    if moving is not None:
        if not isinstance(moving, list) or not all(isinstance(c, str) for c in moving):
            raise t.error("cameras", "must be a list of camera names")
        unknown = sorted(set(moving) - cameras)
        if unknown:
            raise t.error("cameras", f"no [[camera]] named {', '.join(map(repr, unknown))}")
    scored = t.raw("regions", None)
    if scored is not None:
        if not isinstance(scored, list) or not scored or not all(isinstance(r, str) for r in scored):
            raise t.error("regions", "must be a non-empty list of region names")
        unknown = sorted(set(scored) - regions)
        if unknown:
            raise t.error("regions", f"no [[region]] named {', '.join(map(repr, unknown))}")
    angle = t.number("min_axis_angle_deg", None, low=0.0, high=90.0) if t.has("min_axis_angle_deg") else None
    return OptimizeSpec(free=tuple(free), lenses=tuple(sorted(set(float(x) * 1e-3 for x in lenses))),
                        cameras=None if moving is None else tuple(moving),
                        regions=None if scored is None else tuple(scored),
                        min_axis_angle=None if angle is None else math.radians(angle),
                        clearance=t.number("clearance_m", 0.05, low=0.0),
                        max_obscuration=t.number("max_obscuration", 0.01, low=0.0, high=1.0),
                        assign_fraction=t.number("assign_fraction", 0.5, low=0.01, high=1.0),
                        starts=t.integer("starts", 3, low=1), rounds=t.integer("rounds", 3, low=1),
                        max_steps=t.integer("max_steps", 40, low=1),
                        seed=t.integer("seed", 0, low=0))


def _render(top: Table, path: Path) -> RenderSpec:
    t = Table(top.raw("render", {}), "render", path,
               ("spp", "scale", "seed", "ambient_radiance", "image_format", "exr"))
    return RenderSpec(spp=t.integer("spp", 16, low=1), scale=t.number("scale", 1.0, positive=True, high=4.0),
                      seed=t.integer("seed", 0, low=0),
                      ambient_radiance=t.number("ambient_radiance", 0.0, low=0.0),
                      image_format=t.string("image_format", "png", choices=("png", "tiff")),
                      exr=t.boolean("exr", False))


def _mesh(t: Table, config_path: Path) -> MeshSpec:
    file = t.string("file")
    mesh_path = (config_path.parent / file).resolve()
    if not mesh_path.is_file():
        raise t.error("file", f"mesh file {str(mesh_path)!r} does not exist; give a path to an "
                              "STL, OBJ or PLY file, relative to the config file")
    if not os.access(mesh_path, os.R_OK):
        raise t.error("file", f"mesh file {str(mesh_path)!r} is not readable")
    if mesh_path.suffix.lower() not in (".stl", ".obj", ".ply"):
        raise t.error("file", f"{mesh_path.name!r} is not an STL, OBJ or PLY file")
    return MeshSpec(name=t.string("name"), path=mesh_path,
                    unit=t.string("unit", "m", choices=tuple(UNITS)),
                    role=t.string("role", "obstacle", choices=ROLES),
                    albedo=t.number("albedo", 0.5, low=0.0, high=1.0), metal=t.boolean("metal", False))


def _region(t: Table, mesh_roles: dict) -> RegionSpec:
    mesh = t.string("mesh")
    if mesh_roles.get(mesh) != "specimen":
        raise t.error("mesh", f"must name a mesh with role \"specimen\" (got {mesh!r}; "
                              f"specimen meshes: {', '.join(n for n, r in mesh_roles.items() if r == 'specimen')})")
    normal = t.vector("normal", 3)
    if np.linalg.norm(normal) < 1e-9:
        raise t.error("normal", "must be a non-zero vector")
    box_min = t.vector("box_min_m", 3, np.full(3, -np.inf))
    box_max = t.vector("box_max_m", 3, np.full(3, np.inf))
    if np.any(box_min >= box_max):
        raise t.error("box_max_m", "must be greater than box_min_m on every axis")
    return RegionSpec(name=t.string("name"), mesh=mesh, normal=normal / np.linalg.norm(normal),
                      box_min=box_min, box_max=box_max,
                      importance=t.number("importance", 1.0, positive=True),
                      normal_tolerance=math.radians(t.number("normal_tolerance_deg", 5.0,
                                                             low=0.0, high=89.0)),
                      min_cameras=t.integer("min_cameras", None, low=1) if t.has("min_cameras") else None)


def _rail(t: Table) -> Rail:
    points = t.points("control_points_m")
    degree = t.integer("degree", 1, low=1)
    if degree >= len(points):
        raise t.error("degree", f"must be less than the number of control points ({len(points)})")
    weights = t.vector("weights", len(points), None, positive=True)
    return Rail(name=t.string("name"), control_points=points, degree=degree, weights=weights)


def _camera(t: Table, rails: set, mounts: tuple = ()) -> CameraSpec:
    name = t.string("name")
    if t.has("sensor_mm") == t.has("sensor_width_mm"):
        raise t.error("sensor_mm", "give the sensor size once: sensor_mm = [width, height] or "
                                   "sensor_width_mm")
    pixels = t.vector("pixels", 2, positive=True)
    if np.any(pixels != np.round(pixels)):
        raise t.error("pixels", f"must be two whole numbers [width, height] (got {pixels.tolist()})")
    width_px, height_px = int(pixels[0]), int(pixels[1])
    if t.has("sensor_mm"):
        sensor = t.vector("sensor_mm", 2, positive=True)
        pitch_w, pitch_h = sensor[0] / width_px, sensor[1] / height_px
        if abs(pitch_w - pitch_h) > 0.01 * pitch_w:
            raise t.error("sensor_mm", f"gives non-square pixels ({pitch_w * 1e3:.3f} x "
                                       f"{pitch_h * 1e3:.3f} um); vdo models square pixels: check "
                                       "the sensor size and pixel counts")
        width_mm = float(sensor[0])
    else:
        width_mm = t.number("sensor_width_mm", positive=True)

    spec = dict(name=name, sensor_width=width_mm * 1e-3, pixels=(width_px, height_px),
                focal_length=t.number("focal_mm", positive=True) * 1e-3,
                roll=math.radians(t.number("roll_deg", 0.0)),
                principal_offset_px=tuple(t.vector("principal_offset_px", 2, np.zeros(2))),
                body=t.boolean("body", True))
    if t.has("f_number") != t.has("focus_m"):
        raise t.error("f_number", "depth of field needs both f_number and focus_m")
    if t.has("f_number"):
        spec |= dict(f_number=t.number("f_number", positive=True),
                     focus_distance=t.number("focus_m", positive=True))
    if t.has("mount"):
        spec |= _camera_mount(t, rails, mounts)
    elif t.has("rail") == t.has("position_m"):
        raise t.error("rail", "give either rail (with u), mount or position_m, not several or none")
    elif t.has("rail"):
        rail = t.string("rail")
        if rail not in rails:
            raise t.error("rail", f"no [[rail]] named {rail!r} (rails: {', '.join(sorted(rails)) or 'none'})")
        u = t.number("u")
        if not 0.0 <= u <= 1.0:
            raise t.error("u", f"= {u} is off rail {rail!r}: the rail parameter runs from 0 to 1")
        spec |= dict(rail=rail, u=u, offset=t.vector("offset_m", 3, np.zeros(3)))
    else:
        for key in ("u", "offset_m"):
            if t.has(key):
                raise t.error(key, "only applies to a camera on a rail")
        spec["position"] = t.vector("position_m", 3)
    if t.has("target_m") == (t.has("pan_deg") or t.has("tilt_deg")):
        raise t.error("target_m", "aim the camera with either target_m or pan_deg + tilt_deg")
    if t.has("target_m"):
        spec["target"] = t.vector("target_m", 3)
    else:
        spec |= dict(pan=math.radians(t.number("pan_deg")), tilt=math.radians(t.number("tilt_deg")))
    return CameraSpec(**spec)


# --------------------------------------------------------------------------------------------
# Mounts (`[[mount]]`): where a camera can stand; `vdo.optimize` moves it within
# --------------------------------------------------------------------------------------------
MOUNT_FIELDS = {"rail": ("control_points_m",), "zone": ("box_min_m", "box_max_m"), "fixed": ("position_m",)}
ZONE_FLOOR = ("floor_m", "height_m")   # the other form of a zone: a convex floor polygon
MOUNT_EXAMPLES = {"control_points_m": "control_points_m = [[0, 0, 1.5], [2, 0, 1.5]]",
                  "box_min_m": "box_min_m = [0.5, -1.0, 1.2]", "box_max_m": "box_max_m = [1.5, 1.0, 1.8]",
                  "position_m": "position_m = [1.0, 0.0, 1.5]",
                  "height_m": "height_m = [1.2, 1.8]"}


@dataclass(frozen=True, eq=False)
class MountSpec:
    """Where a camera stands. kind "zone": anywhere in the axis-aligned box [box_min, box_max]
    (m), e.g. a tripod on a floor area (extent in x and y) with its height range in z (a zero
    extent holds that axis), or, with `floor` ((n, 2) m, a convex polygon, counter-clockwise),
    anywhere above that polygon within the box's height range (the box is then the polygon's
    bounding box); "fixed": at `position` (m). Rail mounts are `Rail`s."""

    name: str
    kind: str
    box_min: np.ndarray | None = None
    box_max: np.ndarray | None = None
    position: np.ndarray | None = None
    floor: np.ndarray | None = None


def _mounts(top: Table, path: Path) -> tuple[tuple[Rail, ...], tuple[MountSpec, ...]]:
    """The `[[mount]]` entries: rail mounts as `Rail`s, zone and fixed mounts as `MountSpec`s."""
    rails, mounts = [], []
    every = ("control_points_m", "degree", "weights", "box_min_m", "box_max_m", "position_m") + ZONE_FLOOR
    for t in _entries(top, "mount", path, ("name", "kind") + every, required=False):
        name = t.string("name")
        kind = t.string("kind", choices=tuple(MOUNT_FIELDS))
        floor = kind == "zone" and t.has("floor_m")
        needs = ZONE_FLOOR if floor else MOUNT_FIELDS[kind]
        allowed = needs + (("degree", "weights") if kind == "rail" else ())
        for key in every:
            if t.has(key) and key not in allowed:
                raise t.error(key, f"does not apply to a {kind} mount{' with floor_m' if floor else ''} "
                                   f"(it takes {', '.join(allowed)})")
        for key in needs:
            if not t.has(key):
                raise t.error(key, f"is required for a {kind} mount, e.g. {MOUNT_EXAMPLES[key]}")
        if kind == "rail":
            rails.append(_rail(t))
        elif floor:
            mounts.append(_floor_zone(t, name))
        elif kind == "zone":
            lo, hi = t.vector("box_min_m", 3), t.vector("box_max_m", 3)
            if np.any(hi < lo):
                raise t.error("box_max_m", f"must be >= box_min_m on every axis (got {hi.tolist()} "
                                           f"against {lo.tolist()})")
            if hi[0] <= lo[0] or hi[1] <= lo[1]:
                raise t.error("box_max_m", "the zone has no floor area: give it an extent in both x "
                                           "and y (box_min_m < box_max_m), or use a rail or fixed mount")
            mounts.append(MountSpec(name, kind, box_min=lo, box_max=hi))
        else:
            mounts.append(MountSpec(name, kind, position=t.vector("position_m", 3)))
    names = [r.name for r in rails] + [m.name for m in mounts]
    if len(set(names)) < len(names):
        raise ConfigError(path, "mount", "mount names must be unique")
    return tuple(rails), tuple(mounts)


def _floor_zone(t: Table, name: str) -> MountSpec:
    """A zone given as a convex floor polygon (`floor_m`, [[x, y], ...], m, either orientation)
    and a height range (`height_m`, [low, high], m)."""
    floor = as_numbers(t.raw("floor_m"))
    if floor is None or floor.ndim != 2 or floor.shape[1] != 2 or len(floor) < 3:
        raise t.error("floor_m", "must be a list of at least 3 [x, y] corners in metres, e.g. "
                                 "floor_m = [[0, -2], [1, -2], [1, -1], [0, -1]]")
    x, y = floor[:, 0], floor[:, 1]
    area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    if abs(area) < 1e-6:
        raise t.error("floor_m", "the zone has no floor area: its corners are on one line or repeated")
    if area < 0:
        floor = floor[::-1]
    edges = np.roll(floor, -1, axis=0) - floor
    turn = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    if np.any(turn < -1e-12):
        raise t.error("floor_m", "must be a convex polygon (split a concave floor area into several "
                                 "zones, one per tripod)")
    low, high = t.vector("height_m", 2)
    if high < low:
        raise t.error("height_m", f"must be [low, high] with low <= high (got {[low, high]})")
    return MountSpec(name, "zone", box_min=np.array([*floor.min(0), low]),
                     box_max=np.array([*floor.max(0), high]), floor=floor)


def inside_floor(floor: np.ndarray, xy: np.ndarray, tol: float = 1e-9) -> bool:
    """Whether the point xy (m) lies in the convex, counter-clockwise polygon `floor`."""
    edges = np.roll(floor, -1, axis=0) - floor
    rel = np.asarray(xy)[None] - floor
    return bool(np.all(edges[:, 0] * rel[:, 1] - edges[:, 1] * rel[:, 0] >= -tol))


def _camera_mount(t: Table, rails: set, mounts: tuple) -> dict:
    """A camera's `mount = "name"`: on a rail mount as on a rail (u, offset_m); in a zone at
    position_m (default: the zone's centre), which must lie inside it; on a fixed mount at the
    mount's position."""
    name = t.string("mount")
    if t.has("rail"):
        raise t.error("mount", "give either rail or mount, not both")
    if name in rails:
        u = t.number("u")
        if not 0.0 <= u <= 1.0:
            raise t.error("u", f"= {u} is off rail mount {name!r}: the rail parameter runs from 0 to 1")
        return dict(rail=name, u=u, offset=t.vector("offset_m", 3, np.zeros(3)))
    for key in ("u", "offset_m"):
        if t.has(key):
            raise t.error(key, "only applies to a camera on a rail")
    mount = next((m for m in mounts if m.name == name), None)
    if mount is None:
        known = sorted(rails | {m.name for m in mounts})
        raise t.error("mount", f"no [[mount]] or [[rail]] named {name!r} (known: {', '.join(known) or 'none'})")
    if mount.kind == "fixed":
        position = t.vector("position_m", 3, mount.position)
        if np.linalg.norm(position - mount.position) > 1e-6:
            raise t.error("position_m", f"differs from fixed mount {name!r} at {mount.position.tolist()}; "
                                        "drop position_m")
        return dict(mount=name, position=mount.position)
    centre = (mount.box_min + mount.box_max) / 2
    if mount.floor is not None:
        centre[:2] = mount.floor.mean(axis=0)
    position = t.vector("position_m", 3, centre)
    if (np.any(position < mount.box_min - 1e-9) or np.any(position > mount.box_max + 1e-9)
            or (mount.floor is not None and not inside_floor(mount.floor, position[:2]))):
        raise t.error("position_m", f"{position.tolist()} is outside zone {name!r} "
                                    f"({mount.box_min.tolist()} to {mount.box_max.tolist()})")
    return dict(mount=name, position=position)


def _mount_to_dict(m: MountSpec) -> dict:
    if m.floor is not None:
        return {"name": m.name, "kind": m.kind, "floor_m": m.floor.tolist(),
                "height_m": [float(m.box_min[2]), float(m.box_max[2])]}
    if m.kind == "zone":
        return {"name": m.name, "kind": m.kind, "box_min_m": m.box_min.tolist(), "box_max_m": m.box_max.tolist()}
    return {"name": m.name, "kind": m.kind, "position_m": m.position.tolist()}
