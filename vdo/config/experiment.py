"""The experiment file: one schema table drives reading, writing and docs/config.md.

One TOML file describes one experiment. Lengths are metres unless a field's name says otherwise
(``_mm``); angles are degrees in the file (``_deg``) and radians inside vdo. Mesh files are
read with the unit they declare. Relative paths are relative to the TOML file.

The schema is the table of `Row`s attached to the fields of the parsed dataclasses (`Experiment`,
`CameraSpec`, ...): each row gives the TOML key, its type (a `Kind`: check + conversion), the unit
in the file, the default and the documentation (the machinery: `vdo.config.schema`). The same rows
read a file (`parse`, with `vdo.config.reader`), write one back (`Experiment.to_dict`, so
``parse(e.to_dict()) == e``) and generate docs/config.md (`vdo.config.reference.markdown`). The
tables of where cameras stand ([[rail]], [[mount]], [[keep_out]]) and their floor geometry live in
`vdo.config.mounts`. Defaults live in the rows only. Adding a field is one `row(...)` line in its
dataclass; adding a table is one dataclass plus one `table(...)` line in `Experiment`; checks that
involve several fields of a table go in the table's `check` function, checks across tables in
`_check_references`.

Everything is validated before any work starts. A user mistake raises `ConfigError` naming the file,
the field (``camera "cam3".focal_mm``) and what is expected. The package imports only NumPy and the
light model modules (`sensor`, `nurbs` for the rails, `pose` to aim and re-aim cameras), so a config
error comes before any heavy import (JAX, Mitsuba), and editing a camera (`with_camera`) needs none:
it builds no `vdo.model.camera.Camera` (`vdo.scene.cameras_of` does) and no JAX rail.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from vdo.config.mounts import (KEEP_OUT_RAIL_POINTS, KeepOutSpec, MountSpec, RailSpec, check_keep_out,
                               check_mount, check_rail, inside_keep_out, resolve_mounts)
from vdo.config.reader import Table, read_section, read_toml, with_overrides
from vdo.config.schema import (File, Flag, Numbers, Points, Real, Row, Section, Text, Vector, Whole, Words,
                               row, rows_of, table, unknown_field, write_rows)
from vdo.core.errors import ConfigError
from vdo.model.pose import aim_point, holds_aim, look_at_angles
from vdo.model.sensor import ALIGNMENTS, SensorModel

SENSOR_FIELDS = tuple(f.name for f in dataclasses.fields(SensorModel))   # the [sensor] table
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
ROLES = ("specimen", "obstacle")
MAX_CAMERA_PIXELS = 100e6          # per camera (1.2 GB per linear RGB float image)
FOCAL_RANGE_MM = (0.5, 5000.0)     # shortest fisheye .. longest telephoto lenses made
COINCIDENT_M = 1e-3                # two optical centres closer than this are one pose
MAX_ANGLE_DEG = 360.0              # a camera angle beyond ±360° is radians or a typo
ANGLE_WHY = "an angle in degrees (a value in radians? multiply by 57.3)"


# --------------------------------------------------------------------------------------------
# The tables
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MeshSpec:
    """A mesh file and how it looks: diffuse paint of `albedo`, or bare metal when `metal`."""

    name: str = row("name", Text(name=True), doc="unique")
    path: Path = row("file", File((".stl", ".obj", ".ply"), "mesh", "an STL, OBJ or PLY"), doc="STL, OBJ or PLY")
    unit: str = row("unit", Text(choices=tuple(UNITS)), "m", doc="unit of the file's coordinates")
    role: str = row("role", Text(choices=ROLES), "obstacle",
                    doc="regions of interest lie on specimen meshes; every mesh occludes")
    albedo: float = row("albedo", Real(0.0, 1.0), 0.5, doc="diffuse reflectance for renders")
    metal: bool = row("metal", Flag(), False, doc="render as rough metal instead of paint")
    finish: str = row("finish", Text(choices=("matte", "satin")), "matte",
                      doc="a specimen's paint: matte, or satin (a specular coat: renders and the "
                          "hot-spot check, `vdo.physics.glare`)")

    @property
    def scale(self) -> float:
        """Metres per mesh unit."""
        return UNITS[self.unit]


@dataclass(frozen=True, eq=False)
class RegionSpec:
    """A region of interest: a patch of the surface of `mesh`, every selector given applying at
    once: faces whose normal is within `normal_tolerance` of `normal` (when given), the part
    inside the box [box_min, box_max] (metres; faces that cross the box are split at it when the
    meshes are loaded), and the part at a distance in [beyond, within] (metres) of a point, of an
    axis (the line through two points), of another mesh, or of a separate region mesh
    (`region_file`, in the specimen mesh's unit). Without any selector the whole mesh is the
    region. A planar selection is one face; a curved one is developed (`vdo.model.surface`)."""

    name: str = row("name", Text(name=True), doc="unique")
    mesh: str = row("mesh", Text(name=True), doc="a specimen mesh")
    normal: np.ndarray | None = row("normal", Vector(3, letters="xyz"), None, shown="any",
                                    doc="faces whose outward normal (world frame; normalised) is "
                                        "within normal_tolerance_deg of this")
    box_min: np.ndarray = row("box_min_m", Vector(3, finite=False, letters="xyz"), [-math.inf] * 3,
                              unit="m", shown="unbounded",
                              doc="the region is the part of the selected faces inside this box "
                                  "(faces crossing it are split at it; ±inf allowed)")
    box_max: np.ndarray = row("box_max_m", Vector(3, finite=False, letters="xyz"), [math.inf] * 3,
                              unit="m", shown="unbounded", doc="upper corner of the box")
    importance: float = row("importance", Real(positive=True), 1.0,
                            doc="weight in the score (the joint matters most)")
    normal_tolerance: float = row("normal_tolerance_deg", Real(0.0, 89.0), 5.0, unit="deg",
                                  doc="faces whose normal is within this of `normal`")
    max_axis_angle: float | None = row(
        "max_axis_angle_deg", Real(0.0, 180.0), None, unit="deg", shown="none",
        doc="largest angle between the optical axes of two cameras that share this region")
    min_cameras: int | None = row("min_cameras", Whole(low=1), None, shown="[evaluation] min_cameras",
                                  doc="coverage requirement on this region")
    near_point: np.ndarray | None = row("near_point_m", Vector(3, letters="xyz"), None, unit="m",
                                        shown="none", doc="select by the distance to this point")
    near_axis: np.ndarray | None = row("near_axis_m", Points(2), None, unit="m", shown="none",
                                       doc="select by the distance to the line through these 2 points")
    near_mesh: str | None = row("near_mesh", Text(name=True), None, shown="none",
                                doc="select by the distance to this [[mesh]]'s surface")
    region_file: Path | None = row("region_file", File((".stl", ".obj", ".ply"), "region mesh",
                                                       "an STL, OBJ or PLY"), None, shown="none",
                                   doc="select the part of the mesh within within_m of this "
                                       "surface (same unit as the specimen mesh)")
    within: float | None = row("within_m", Real(positive=True), None, unit="m",
                               shown="sample spacing for region_file",
                               doc="largest distance to the near_* point, axis or mesh")
    beyond: float = row("beyond_m", Real(low=0.0), 0.0, unit="m",
                        doc="smallest distance to the near_* point, axis or mesh")

    @property
    def near(self) -> str | None:
        """The distance selector's field name, or None."""
        keys = [k for k, v in (("near_point_m", self.near_point), ("near_axis_m", self.near_axis),
                               ("near_mesh", self.near_mesh), ("region_file", self.region_file))
                if v is not None]
        return keys[0] if keys else None


def _sensor_width_row():
    """The sensor width row, shared by a camera and a body of the design inventory."""
    return row("sensor_width_mm", Real(positive=True), unit="mm", either="sensor_mm",
               shown="or sensor_mm", doc="sensor width")


def _pixels_row():
    """The pixel count row, shared by a camera and a body of the design inventory."""
    return row("pixels", Vector(2, positive=True, whole=True, as_tuple=True, letters="WH"),
               doc=f"whole numbers, at most {MAX_CAMERA_PIXELS / 1e6:g} Mpx")


@dataclass(frozen=True, eq=False)
class CameraSpec:
    """A camera as written in the file; `camera_positions` and `angles` resolve its pose,
    `vdo.scene.cameras_of` builds the `vdo.model.camera.Camera`."""

    name: str = row("name", Text(name=True), doc="unique; names the camera's output files")
    sensor_width: float = _sensor_width_row()
    pixels: tuple[int, int] = _pixels_row()
    focal_length: float = row("focal_mm", Real(*FOCAL_RANGE_MM, positive=True,
                                               why="the focal lengths of real lenses"), unit="mm",
                              doc="lens focal length")
    rail: str | None = row("rail", Text(name=True), None, shown="either rail + u",
                           doc="the [[rail]] the camera sits on")
    mount: str | None = row("mount", Text(name=True), None, shown="or mount",
                            doc="the [[mount]] the camera stands on (a rail mount takes u, a zone "
                                "position_m, default its centre; a fixed mount nothing)")
    u: float | None = row("u", Real(), None, when="rail mount", doc="position on the rail, 0 to 1")
    offset: np.ndarray = row("offset_m", Vector(3, letters="xyz"), [0.0, 0.0, 0.0], unit="m",
                             when="rail mount", doc="from the rail point to the optical centre")
    position: np.ndarray | None = row("position_m", Vector(3, letters="xyz"), None, unit="m",
                                      shown="or this", doc="optical centre")
    target: np.ndarray | None = row("target_m", Vector(3, letters="xyz"), None, unit="m",
                                    shown="either this", doc="aim the optical axis at a point")
    pan: float | None = row("pan_deg", Real(-MAX_ANGLE_DEG, MAX_ANGLE_DEG, why=ANGLE_WHY), None, unit="deg", shown="or pan + tilt",
                            doc="azimuth from +x toward +y")
    tilt: float | None = row("tilt_deg", Real(-MAX_ANGLE_DEG, MAX_ANGLE_DEG, why=ANGLE_WHY), None, unit="deg", shown="or pan + tilt",
                             doc="elevation (negative looks down)")
    roll: float = row("roll_deg", Real(-MAX_ANGLE_DEG, MAX_ANGLE_DEG, why=ANGLE_WHY), 0.0, unit="deg", doc="0 keeps the image x axis horizontal")
    principal_offset_px: tuple[float, float] = row(
        "principal_offset_px", Vector(2, as_tuple=True, letters=("dx", "dy")), [0.0, 0.0],
        doc="principal point offset from the image centre")
    body: bool = row("body", Flag(), True, doc="the camera's body occludes the other cameras' views")
    f_number: float | None = row("f_number", Real(positive=True), None, shown="none",
                                 doc="with focus_m: thin lens with depth of field in renders")
    focus_distance: float | None = row("focus_m", Real(positive=True), None, unit="m", shown="none",
                                       doc="focus distance, with f_number")
    lenses: tuple[float, ...] = row(
        "lenses_mm", Numbers(as_set=True, what="focal lengths in mm"), [], unit="mm", shown="none",
        doc="the lenses this body takes, for \"lens\" in [optimize] free (default: [optimize] lenses_mm)")
    distortion: tuple[float, ...] = row(
        "distortion", Vector(5, as_tuple=True, letters=("k1", "k2", "p1", "p2", "k3")),
        [0.0, 0.0, 0.0, 0.0, 0.0], doc="Brown-Conrady lens distortion, OpenCV's order and units")

    def angles(self, position) -> tuple[float, float]:
        """(pan, tilt) in radians of this camera with its optical centre at `position` (m): toward
        target_m (`vdo.model.pose.look_at_angles`), else pan_deg and tilt_deg."""
        return look_at_angles(position, self.target) if self.target is not None else (self.pan, self.tilt)


def _sensor_mm_row() -> Row:
    return Row("sensor_mm", Vector(2, positive=True, letters="wh"), None, "mm",
               "sensor size (instead of sensor_width_mm); pixels must be square within 1 %",
               shown="or sensor_width_mm")


@dataclass(frozen=True)
class Evaluation:
    """[evaluation]: how the regions are sampled and what a camera sees."""

    sample_spacing: float = row("sample_spacing_mm", Real(positive=True), 10.0, unit="mm",
                                doc="grid spacing of the surface samples on each region")
    incidence_limit: float = row("incidence_limit_deg", Real(1.0, 89.9), 75.0, unit="deg",
                                 doc="a camera sees a point only when the angle between the normal "
                                     "and the direction to the camera is below this")
    patch_size: float = row("patch_mm", Real(positive=True), 10.0, unit="mm",
                            doc="side of the DIC measurement patch (Ω = side²) used by the uncertainty")
    min_cameras: int = row("min_cameras", Whole(low=1), 2,
                           doc="coverage requirement per point (a region may override it)")


@dataclass(frozen=True, eq=False)
class LightSpec:
    """A rectangular LED panel: a one-sided diffuse area emitter of `radiance` (W sr^-1 m^-2,
    any consistent unit: the sensor's photons_per_unit maps it to electrons) centred at `position`
    and facing `target`, `size` (width, height) in metres."""

    name: str = row("name", Text(name=True), doc="unique")
    position: np.ndarray = row("position_m", Vector(3, letters="xyz"), unit="m", doc="panel centre")
    target: np.ndarray = row("target_m", Vector(3, letters="xyz"), unit="m", doc="the panel faces it")
    size: tuple[float, float] = row("size_m", Vector(2, positive=True, as_tuple=True, letters="wh"),
                                    unit="m", doc="panel width and height")
    radiance: float = row("radiance", Real(positive=True),
                          doc="emitted radiance (any unit consistent with [sensor] photons_per_unit)")


@dataclass(frozen=True)
class SpeckleSpec:
    """The paint on the regions of interest: generated dots + strokes, or a user image."""

    dot_diameter: float = row("dot_diameter_mm", Real(positive=True), 2.0, unit="mm",
                              doc="black dots on white paint")
    coverage: float = row("coverage", Real(0.01, 0.95), 0.5, doc="black area fraction")
    strokes: int = row("strokes", Whole(low=0), 10, doc="random brush strokes per tile")
    texel: float = row("texel_mm", Real(positive=True), 0.25, unit="mm",
                       doc="pattern resolution on the surface (at most a third of the dot diameter)")
    tile_texels: int = row("tile_texels", Whole(low=64), 1024,
                           doc="the pattern tile repeats seamlessly every tile_texels × texel_mm")
    seed: int = row("seed", Whole(low=0), 1, doc="random seed of the pattern")
    image: Path | None = row("image", File((".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp"), "pattern",
                                           "an image (PNG, JPEG, TIFF or BMP)", magic=True), None, shown="none",
                             doc="a photo of a real pattern instead (at texel_mm per pixel)")
    white_albedo: float = row("white_albedo", Real(0.0, 1.0), 0.8, doc="reflectance of the white paint")
    black_albedo: float = row("black_albedo", Real(0.0, 1.0), 0.05,
                              doc="reflectance of the black paint (below white_albedo)")
    print_dpi: float = row("print_dpi", Real(positive=True), 600.0,
                           doc="printer resolution of `vdo speckle`'s print-ready patterns (dots per inch)")


def _sensor_rows() -> tuple[Row, ...]:
    """[sensor]: `SensorModel`'s fields; it keeps the defaults and checks the ranges itself."""
    defaults = {f.name: f.default for f in dataclasses.fields(SensorModel)}
    kinds = {"bit_depth": Whole()}
    docs = {"quantum_efficiency": ("fraction of photons converted to electrons, in (0, 1]", ""),
            "full_well_e": ("full-well capacity, electrons > 0", ""),
            "read_noise_e": ("read noise, electrons rms ≥ 0", ""),
            "bit_depth": ("A/D converter resolution, 8 to 16 bits", ""),
            "gain_dn_per_e": ("system gain, DN per electron > 0", "full well → top DN"),
            "offset_dn": ("dark offset, DN in [0, 2^bit_depth − 1)", "2^(bit_depth − 7)"),
            "photons_per_unit": ("photons per pixel per unit of the linear render value, > 0",
                                 "a linear value of 1 fills 70 % of the full well")}
    return tuple(Row(name, kinds.get(name, Real()), defaults[name], doc=docs[name][0],
                     shown=docs[name][1], attr=name) for name in SENSOR_FIELDS)


@dataclass(frozen=True)
class RenderSpec:
    """[render]: settings of `vdo render`."""

    spp: int = row("spp", Whole(low=1), 16, doc="samples per pixel")
    scale: float = row("scale", Real(positive=True, high=4.0), 1.0,
                       doc="image size relative to the sensor's pixel counts")
    seed: int = row("seed", Whole(low=0), 0, doc="render noise seed")
    ambient_radiance: float = row("ambient_radiance", Real(low=0.0), 0.0,
                                  doc="uniform environment light, same unit as [[light]] radiance")
    image_format: str = row("image_format", Text(choices=("png", "tiff")), "png",
                            doc="tiff: 16-bit above 8-bit depth")
    exr: bool = row("exr", Flag(), False, doc="also write the linear float images")
    bit_alignment: str = row("bit_alignment", Text(choices=ALIGNMENTS), "msb",
                             doc="16-bit files: msb (counts shifted to the top bits, as most DIC "
                                 "software expects) or raw (counts as they are)")
    mode: str = row("mode", Text(choices=("sampled", "dic")), "sampled",
                    doc="sampled: spp path samples per pixel (the reference); dic: one ray per "
                        "pixel, the speckle averaged over the pixel's footprint, for full-size "
                        "images (docs/render.md)")


@dataclass(frozen=True)
class Analysis:
    """The DIC analysis the strain uncertainty is predicted for (`vdo.physics.strain`): global DIC with Q4
    elements of side `element` (m), or subset DIC with square subsets of side `subset` (m) or
    `subset_px` pixels on a grid of `step` (m) or `step_px` pixels, shape function "zero" or
    "affine", strain from a plane fit over `strain_window` x `strain_window` subset centres.
    Pixels are those of the finest camera at each sample (`vdo.physics.strain.sizes`)."""

    method: str = row("method", Text(choices=("global", "subset")), "global",
                      doc="global (finite-element) or subset (local) DIC")
    element: float | None = row("element_mm", Real(positive=True), None, unit="mm",
                                shown="[evaluation] patch_mm", doc="Q4 element side (global DIC)")
    subset: float | None = row("subset_mm", Real(positive=True), None, unit="mm", shown="none",
                               doc="subset side in mm (or subset_px)")
    subset_px: float | None = row("subset_px", Real(positive=True), 29.0,
                                  doc="subset side in pixels (unless subset_mm)")
    step: float | None = row("step_mm", Real(positive=True), None, unit="mm", shown="none",
                             doc="subset grid step in mm (or step_px)")
    step_px: float | None = row("step_px", Real(positive=True), 7.0,
                                doc="subset grid step in pixels (unless step_mm)")
    shape_function: str = row("shape_function", Text(choices=("zero", "affine")), "affine",
                              doc="subset shape function")
    strain_window: int = row("strain_window", Whole(low=2), 15,
                             doc="subset centres per side of the strain plane fit (virtual gauge)")
    interpolant: str = row("interpolant", Text(choices=("cubic", "quintic", "keys")), "cubic",
                           doc="the correlation's interpolant: cubic or quintic B-spline, or keys "
                               "(Keys' bicubic convolution, a = -0.5) (σ_measured's bias and noise)")
    reference: str = row("reference", Text(choices=("noisy", "noise-free")), "noisy",
                         doc="noisy: a recorded reference image; noise-free: a synthetic one")
    processing: str = row("processing", Text(choices=("all-views", "pairs")), "all-views",
                          doc="all views in one correlation, or stereo pairs merged per point")
    pairs: str = row("pairs", Text(choices=("auto", "declared")), "auto",
                     doc="pairs: auto (any two usable views with the angle between their rays "
                         "in [lens minimum, max_pair_angle_deg]) or the [[stereo_pair]] tables")
    merge: str = row("merge", Text(choices=("best", "fusion")), "best",
                     doc="pairs at a point: the best one, or inverse-variance fusion")
    max_pair_angle: float | None = row("max_pair_angle_deg", Real(1.0, 180.0), None, unit="deg",
                                       shown="60", doc="largest angle between a pair's rays (auto)")


def _check_analysis(t: Table, v: dict) -> None:
    if v["pairs"] == "declared" and v["processing"] != "pairs":
        raise t.error("pairs", 'declared pairs need processing = "pairs"')
    for mm, px in (("subset", "subset_px"), ("step", "step_px")):
        if t.has(f"{mm}_mm") and t.has(px):
            raise t.error(px, f"give the size once: {px} or {mm}_mm")
        if v[mm] is not None:
            v[px] = None


SAME_LENS_REL = 1e-9   # relative: focal lengths this close are one lens (mm read as m, rounding)


def lens_catalogue_errors(exp: Experiment) -> list[ConfigError]:
    """With "lens" in [optimize] free, one `ConfigError` per moving camera (`[optimize] cameras`,
    default all) whose focal_mm is not in its lens catalogue (its own lenses_mm, else [optimize]
    lenses_mm): the lens choice only swaps to catalogue lenses, so when none wins the optimized
    layout (optimized.toml) would keep a lens the catalogue does not list."""
    if "lens" not in exp.optimize.free:
        return []
    moving = set(exp.optimize.cameras or [c.name for c in exp.camera_specs])
    errors = []
    for spec in exp.camera_specs:
        catalogue = spec.lenses or exp.optimize.lenses
        if spec.name not in moving or not catalogue or any(
                math.isclose(spec.focal_length, f, rel_tol=SAME_LENS_REL) for f in catalogue):
            continue
        where = "its lenses_mm" if spec.lenses else "[optimize] lenses_mm"
        listed = ", ".join(f"{f * 1e3:g}" for f in catalogue)
        errors.append(ConfigError(exp.path, f'camera "{spec.name}".focal_mm',
                                  f"= {spec.focal_length * 1e3:g} mm is not in the lens catalogue "
                                  f"({where} = [{listed}]) that \"lens\" in [optimize] free chooses "
                                  "from, so the optimized layout could keep a lens the catalogue "
                                  f"does not list: add {spec.focal_length * 1e3:g} to {where}, or "
                                  "start from a lens of the catalogue"))
    return errors


def _check_keep_outs(exp: "Experiment", tables: dict) -> None:
    """ConfigError for a camera whose optical centre lies in a keep-out volume, and for a keep-out
    that holds every position of a camera's mount (a zone's box or floor corners at both heights,
    KEEP_OUT_RAIL_POINTS along a rail), naming the camera, the mount and the fix."""
    if not exp.keep_outs:
        return
    mounts = {m.name: m for m in exp.mounts}
    for spec, t in zip(exp.camera_specs, tables["camera"]):
        if spec.rail is not None:
            track = exp.rail(spec.rail).point(np.linspace(0, 1, KEEP_OUT_RAIL_POINTS)) + spec.offset
            where, field, what = inside_keep_out(exp.keep_outs, track), "rail", f"rail {spec.rail!r}"
        elif spec.mount is not None and mounts[spec.mount].kind == "zone":
            zone = mounts[spec.mount]
            xy = zone.floor if zone.floor is not None else np.array(
                [[x, y] for x in (zone.low[0], zone.high[0]) for y in (zone.low[1], zone.high[1])])
            track = np.array([[*c, z] for c in xy for z in (zone.low[2], zone.high[2])])
            where, field, what = inside_keep_out(exp.keep_outs, track), "mount", f"zone {spec.mount!r}"
            # a box holds a convex zone when it holds its corners; a floor polygon is checked by them too
        else:
            where = np.array([-1])
        if len(where) and np.all(where >= 0) and len(set(where.tolist())) == 1:
            box = exp.keep_outs[int(where[0])]
            raise t.error(field, f"every position of {what} lies in keep_out {box.name!r} "
                                 f"({box.box_min.tolist()} to {box.box_max.tolist()} m): camera "
                                 f"{spec.name!r} has nowhere to stand; shrink the keep-out or move the mount")
        own = spec.position if spec.rail is None else \
            exp.rail(spec.rail).point(spec.u) + spec.offset
        if own is not None:
            k = int(inside_keep_out(exp.keep_outs, own)[0])
            if k >= 0:
                box = exp.keep_outs[k]
                raise t.error("position_m" if spec.rail is None else "u",
                              f"{np.round(own, 4).tolist()} lies in keep_out {box.name!r} "
                                            f"({box.box_min.tolist()} to {box.box_max.tolist()} m): "
                                            "move the camera out of it")


STEREO_SPAN_DEG = 20.0            # a declared pair's default max_angle_deg = its min + this


@dataclass(frozen=True)
class StereoPairSpec:
    """A declared stereo pair: two cameras whose optical axes must make an angle in
    [min_angle, max_angle] (rad). min_angle None: the stereo rule of thumb for the shorter lens
    (`vdo.constraints.stereo_min_angle`); max_angle None: that minimum + STEREO_SPAN_DEG."""

    cameras: tuple[str, ...] = row("cameras", Words(what="two camera names", nonempty=True),
                                   doc='the two cameras, e.g. ["left", "right"]')
    min_angle: float | None = row("min_angle_deg", Real(0.0, 180.0), None, unit="deg",
                                  shown="by lens", doc="smallest angle between the optical axes")
    max_angle: float | None = row("max_angle_deg", Real(0.0, 180.0), None, unit="deg",
                                  shown=f"min + {STEREO_SPAN_DEG:g}", doc="largest angle between the optical axes")


def _check_stereo_pair(t: Table, v: dict) -> None:
    if len(v["cameras"]) != 2:
        raise t.error("cameras", f'must name two different cameras, e.g. ["left", "right"] '
                                 f"(got {list(v['cameras'])!r})")
    _check_angles(t, v, "min_angle_deg", "max_angle_deg", "min_angle", "max_angle")


def _check_angles(t: Table, v: dict, low_key, high_key, low, high) -> None:
    if v[low] is not None and v[high] is not None and v[high] < v[low]:
        raise t.error(high_key, f"= {math.degrees(v[high]):g} is below {low_key} = "
                                f"{math.degrees(v[low]):g}: the maximum must be at least the minimum")


@dataclass(frozen=True, eq=False)
class GroupSpec:
    """Meshes that move together along the load path (a hexapod's platform with its
    end-effector, a crosshead). Every mesh is also a group of its own name."""

    name: str = row("name", Text(name=True), doc="unique; not the name of a mesh")
    meshes: tuple[str, ...] = row("meshes", Words(what="mesh names", nonempty=True),
                                  doc="the [[mesh]] names that move together")
    pivot: np.ndarray = row("pivot_m", Vector(3, letters="xyz"), [0.0, 0.0, 0.0], unit="m",
                            doc="the point the group's rotations turn about")


@dataclass(frozen=True)
class LoadPathSpec:
    """The steps of a moving test (`vdo.geometry.keyframes`): rigid poses of groups per step, and
    optionally nodal displacements of one specimen mesh per step."""

    poses: Path | None = row("poses", File((".csv",), "pose", "a CSV"), None, shown="none",
                             doc="CSV: step, group, x_mm, y_mm, z_mm, rx_deg, ry_deg, rz_deg")
    displacements: Path | None = row("displacements", File((".csv", ".vtu", ".vtp", ".pvd"), "displacement",
                                                           "a CSV, .vtu, .vtp or .pvd"), None,
                                     shown="none", doc="CSV: step, x_m, y_m, z_m, ux_mm, uy_mm, uz_mm; or "
                                                       "VTK XML nodal displacements (.vtu/.vtp, one step; "
                                                       ".pvd, one file per step)")
    deformed_mesh: str | None = row("deformed_mesh", Text(name=True), None, shown="none",
                                    doc="the specimen mesh the displacements apply to")
    unit: str | None = row("unit", Text(choices=tuple(UNITS)), None, shown="none",
                           doc="length unit of a VTK file's points and displacements (required for VTK)")
    displacement_array: str | None = row("displacement_array", Text(), None, shown="auto",
                                         doc="the VTK point array of displacements (default: the one "
                                             "3-component array, or the one named displacement, U, ...)")
    every: int = row("every", Whole(low=1), 1,
                     doc="judge and render every every-th step of the files and the last one (a "
                         "quicker look at a long series; every row of every step is still checked)")

    @property
    def active(self) -> bool:
        return self.poses is not None or self.displacements is not None


def _check_load_path(t: Table, v: dict) -> None:
    if (v["displacements"] is None) != (v["deformed_mesh"] is None):
        raise t.error("deformed_mesh", "give displacements and deformed_mesh together (the file's "
                                       "nodes are that mesh's vertices)")
    vtk = v["displacements"] is not None and v["displacements"].suffix.lower() != ".csv"
    if vtk and v["unit"] is None:
        raise t.error("unit", "a VTK file carries no length unit: give unit = \"mm\" or \"m\" (its "
                              "points and displacements)")
    if not vtk and (v["unit"] is not None or v["displacement_array"] is not None):
        raise t.error("unit" if v["unit"] is not None else "displacement_array",
                      "is for a VTK displacement file (a CSV names its units in its header)")


@dataclass(frozen=True)
class OptimizeSpec:
    """What `vdo optimize` may move and the practical constraints it enforces."""

    free: tuple[str, ...] = row(
        "free", Words(choices=("u", "pan", "tilt", "roll", "lens")), ["u", "pan", "tilt"],
        doc='parameters that move per camera (add "roll" to free it, otherwise cameras stay '
            'horizontal; add "lens" to choose each moving camera\'s lens from lenses_mm)')
    lenses: tuple[float, ...] = row(
        "lenses_mm", Numbers(as_set=True, what="focal lengths in mm"), [], unit="mm",
        doc='the lens catalogue for "lens" in free: a greedy outer loop tries each other lens on each '
            "moving camera and keeps it when the result is better (feasible first, then by score)")
    cameras: tuple[str, ...] | None = row("cameras", Words(what="camera names"), None, shown="all",
                                          doc="names of the cameras that move")
    regions: tuple[str, ...] | None = row(
        "regions", Words(what="region names", nonempty=True), None, shown="all",
        doc="regions whose uncertainty and coverage enter the score (constraints apply everywhere)")
    min_axis_angle: float | None = row(
        "min_axis_angle_deg", Real(0.0, 90.0), None, unit="deg", shown="by lens",
        doc="minimum angle between the optical axes of two cameras sharing a region; default 35° up "
            "to 12 mm, 25° at 17 mm, 15° from 35 mm (the shorter lens of the pair)")
    max_axis_angle: float | None = row(
        "max_axis_angle_deg", Real(0.0, 180.0), None, unit="deg", shown="none",
        doc="largest angle between the optical axes of two cameras sharing a region (off by default "
            "for multi-view; declared stereo pairs have their own)")
    clearance: float = row("clearance_m", Real(low=0.0), 0.05, unit="m",
                           doc="camera bodies keep this distance from every mesh and each other")
    max_obscuration: float = row("max_obscuration", Real(0.0, 1.0), 0.01,
                                 doc="largest fraction of an assigned region's image an obstacle may mask")
    assign_fraction: float = row("assign_fraction", Real(0.01, 1.0), 0.5,
                                 doc="a camera is assigned the regions it sees this much of in the "
                                     "starting layout")
    score: str = row(
        "score", Text(choices=("bound", "measured")), "bound",
        doc='what the score\'s σ is: "bound", the Cramér-Rao bound; "measured", what the lab\'s '
            "correlation measures ([analysis] interpolant and reference: each camera's information "
            "divided by its error over the bound, refreshed every round; docs/theory.md)")
    starts: int = row("starts", Whole(low=1), 3, doc="multi-start: the hand layout + perturbed copies")
    rounds: int = row("rounds", Whole(low=1), 3,
                      doc="penalty rounds, each ending with a visibility refresh")
    max_steps: int = row("max_steps", Whole(low=1), 40, doc="BFGS steps per round")
    seed: int = row("seed", Whole(low=0), 0, doc="perturbation of the extra starts")
    load_path: bool = row(
        "load_path", Flag(), True,
        doc="with a [load_path]: score the views that hold over the test (seen at rest and at "
            "load_path_fraction of the keyframes), not at rest alone (docs/theory.md)")
    load_path_fraction: float = row(
        "load_path_fraction", Real(high=1.0, positive=True), 1.0,
        doc="fraction q (0 < q <= 1) of the keyframes at which a view must be seen to count; 1 = "
            "every one (the worst case)")
    load_path_keyframes: int = row(
        "load_path_keyframes", Whole(low=1), 4,
        doc="keyframes each visibility refresh casts: the extremes of the path first, then evenly "
            "spaced (all steps when the path has no more); the result is judged over every step")


@dataclass(frozen=True, eq=False)
class BodySpec:
    """A kind of camera body in `vdo design`'s inventory: its sensor and how many are available."""

    name: str = row("name", Text(name=True), doc="unique, e.g. \"5MP\"")
    sensor_width: float = _sensor_width_row()
    pixels: tuple[int, int] = _pixels_row()
    count: int = row("count", Whole(low=1), doc="how many bodies of this kind are available")
    lenses: tuple[float, ...] = row("lenses_mm", Numbers(as_set=True, what="focal lengths in mm"), [],
                                    unit="mm", shown="[design] lenses_mm",
                                    doc="the lenses this body takes")


@dataclass(frozen=True, eq=False)
class DesignSpec:
    """What `vdo design` may choose: the camera bodies ([[body]], or [design]'s one sensor), the
    lens catalogue, where candidates stand on the mounts and how they aim (`vdo.design.candidates`)."""

    max_cameras: int | None = row("max_cameras", Whole(low=1), None,
                                  shown="the [[body]] counts, else the [[camera]] count",
                                  doc="the most cameras to place (the inventory)")
    min_cameras: int = row("min_cameras", Whole(low=1), 2, doc="fewest cameras on the Pareto curve")
    sensor_width: float | None = row("sensor_width_mm", Real(positive=True), None, unit="mm",
                                     shown="the first [[camera]]'s", doc="sensor width of the bodies")
    pixels: tuple[int, int] | None = row(
        "pixels", Vector(2, positive=True, whole=True, as_tuple=True, letters="WH"), None,
        shown="the first [[camera]]'s", doc="pixel counts of the bodies")
    lenses: tuple[float, ...] = row("lenses_mm", Numbers(as_set=True, what="focal lengths in mm"), [],
                                    unit="mm", shown="the [[camera]] lenses", doc="the lens catalogue")
    target_sigma_um: float | None = row("target_sigma_um", Real(positive=True), None, shown="none",
                                        doc="sigma_max p95 (µm) to reach on the scored regions: the "
                                            "smallest camera count that does is reported")
    rail_positions: int = row("rail_positions", Whole(low=1), 12,
                              doc="candidate positions per rail, evenly spread in u")
    offset: np.ndarray = row("offset_m", Vector(3, letters="xyz"), [0.0, 0.0, 0.15], unit="m",
                             doc="from the rail point to a candidate's optical centre (also tried mirrored below the bar)")
    aim_offsets: tuple[float, ...] = row("aim_offsets_deg", Numbers(as_set=True, what="angles in deg"),
                                         [], unit="deg", shown="none",
                                         doc="extra aims: each region target's pan and tilt +- these")
    sample_spacing: float = row("sample_spacing_mm", Real(positive=True), 20.0, unit="mm",
                                doc="sample spacing for the selection (the result is judged at [evaluation]'s)")
    zone_points: int = row("zone_points", Whole(low=1), 3,
                           doc="candidate positions per horizontal axis of a zone [[mount]] (a grid; "
                               "in a floor polygon, the grid points inside it)")
    zone_heights: int = row("zone_heights", Whole(low=1), 3,
                            doc="candidate heights per zone, evenly spread over its height range")
    keyframes: int = row("keyframes", Whole(low=0), 3,
                         doc="load-path steps at which the candidates' occlusion is also judged (the "
                             "steps farthest from rest and from each other); a candidate counts where "
                             "it sees a sample at rest and at each (0: at rest only)")
    bound_seconds: float = row("bound_s", Real(low=0), 60.0,
                               doc="wall seconds per camera count for the bound on the best score "
                                   "(`vdo.design.bound`; 0: no bound)")
    score: str = row(
        "score", Text(choices=("bound", "measured")), "bound",
        doc='what the selection\'s σ is: "bound", the Cramér-Rao bound; "measured", what the lab\'s '
            "correlation measures ([analysis] interpolant and reference: each candidate's information "
            "divided by its error over the bound in each region; docs/design.md)")


ON_REQUEST = ("calibration",)      # tables whose presence asks for work: written back only when given
TARGET_KINDS = ("checkerboard",)   # what `vdo calibrate` renders and detects (OpenCV)


@dataclass(frozen=True, eq=False)
class CalibrationSpec:
    """[calibration]: the lab's calibration session that `vdo calibrate` renders, calibrates and
    propagates (`vdo.calib`, docs/calibration.md): the target, its poses, the detection noise."""

    target: str = row("target", Text(choices=TARGET_KINDS), "checkerboard",
                      doc="checkerboard (inner corners: findChessboardCorners + cornerSubPix)")
    rows: int = row("rows", Whole(low=3, high=60), 7,
                    doc="inner corners per column; rows + columns odd (one odd, one even) so "
                        "that the board's orientation is unambiguous")
    columns: int = row("columns", Whole(low=3, high=60), 10, doc="inner corners per row")
    pitch: float | None = row("pitch_mm", Real(positive=True), None, unit="mm",
                              shown="the target spans field_fill of the narrowest field",
                              doc="square side")
    pitch_tolerance: float = row("pitch_tolerance_mm", Real(low=0.0), 0.0, unit="mm",
                                 doc="the maker's pitch tolerance (1 sigma): a scale error of the "
                                     "whole calibration, shared by every load step")
    flatness: float = row("flatness_mm", Real(low=0.0), 0.0, unit="mm",
                          doc="the maker's flatness tolerance: the rendered target bows by this "
                              "much at its centre (the calibration assumes it flat)")
    field_fill: float = row("field_fill", Real(0.1, 1.0), 0.5,
                            doc="fraction of a camera's field width the target spans at the "
                                "working distance (generated poses, automatic pitch)")
    poses_per_camera: int = row("poses_per_camera", Whole(low=3, high=500), 12,
                                doc="generated poses per camera (intrinsics), spread over its field")
    shared_poses: int = row("shared_poses", Whole(low=0, high=500), 6,
                            doc="generated poses per stereo pair seen by both cameras (extrinsics)")
    distances: tuple[float, ...] | None = row(
        "distances_m", Numbers(what="distances in metres"), None, unit="m",
        shown="each camera's working distance", doc="target distances from the camera, cycled")
    tilt: float = row("tilt_deg", Real(0.0, 60.0), 30.0, unit="deg",
                      doc="largest tilt of a generated pose away from facing the camera")
    pose_centres: np.ndarray | None = row("pose_centres_m", Points(minimum=1), None, unit="m",
                                          shown="none (generated)",
                                          doc="explicit poses: where the target's centre is")
    pose_normals: np.ndarray | None = row("pose_normals", Points(minimum=1), None, shown="none",
                                          when="pose_centres",
                                          doc="explicit poses: the target's front normal, one per centre")
    detection_sigma_px: float | None = row(
        "detection_sigma_px", Real(positive=True), None, shown="from the residuals",
        doc="corner/dot detection noise (px, 1 sigma) of the covariance sigma^2 (J^T J)^-1")
    strain: float = row("strain", Real(positive=True, high=0.5), 0.002,
                        doc="the test's strain level (calibration-induced error is also given per unit)")
    displacement: float = row("displacement_mm", Real(positive=True), 1.0, unit="mm",
                              doc="the test's displacement level")
    target_strain_error: float = row("target_strain_error", Real(positive=True), 1e-5,
                                     doc="`vdo calibrate --plan`: calibration-induced strain error "
                                         "(1 sigma, p95 over samples) to reach at the test's level")
    seed: int = row("seed", Whole(low=0), 0, doc="seed of the generated poses and the images' noise")


def _check_calibration(t: Table, v: dict) -> None:
    if (v["rows"] + v["columns"]) % 2 == 0:
        raise t.error("columns", f"rows = {v['rows']} and columns = {v['columns']} have the same "
                                 "parity: make one odd and one even (a board that looks the same "
                                 "turned by 180 deg has no defined corner order)")
    centres, normals = v["pose_centres"], v["pose_normals"]
    if (centres is None) != (normals is None):
        raise t.error("pose_normals", "explicit poses need pose_centres_m and pose_normals together")
    if centres is not None:
        if len(normals) != len(centres):
            raise t.error("pose_normals", f"must hold one normal per centre ({len(centres)})")
        length = np.linalg.norm(normals, axis=1)
        if np.any(length < 1e-9):
            raise t.error("pose_normals", f"normal {int(np.argmin(length))} is zero")
        v["pose_normals"] = normals / length[:, None]
    if v["pitch"] is not None and v["pitch_tolerance"] >= 0.1 * v["pitch"]:
        raise t.error("pitch_tolerance_mm", "must be below a tenth of pitch_mm")


# --------------------------------------------------------------------------------------------
# Checks across the fields of one table: check(t, values) raises t.error or completes values
# --------------------------------------------------------------------------------------------
def _sensor_size(t: Table, v: dict) -> None:
    """A camera's or body's sensor: sensor_mm or sensor_width_mm (once), square pixels, at most
    MAX_CAMERA_PIXELS; sets v["sensor_width"] from sensor_mm."""
    if t.has("sensor_mm") == t.has("sensor_width_mm"):
        raise t.error("sensor_mm", "give the sensor size once: sensor_mm = [width, height] or "
                                   "sensor_width_mm")
    width_px, height_px = v["pixels"]
    if width_px * height_px > MAX_CAMERA_PIXELS:
        raise t.error("pixels", f"{width_px} x {height_px} is {width_px * height_px / 1e6:.4g} Mpx; "
                                f"at most {MAX_CAMERA_PIXELS / 1e6:g} Mpx per camera")
    if t.has("sensor_mm"):
        sensor = t.get(_sensor_mm_row())
        pitch_w, pitch_h = sensor[0] / width_px, sensor[1] / height_px
        if abs(pitch_w - pitch_h) > 0.01 * pitch_w:
            raise t.error("sensor_mm", f"gives non-square pixels ({pitch_w * 1e6:.3f} x "
                                       f"{pitch_h * 1e6:.3f} um); vdo models square pixels: check "
                                       "the sensor size and pixel counts")
        v["sensor_width"] = float(sensor[0])


def _check_camera(t: Table, v: dict) -> None:
    _sensor_size(t, v)
    if t.has("f_number") != t.has("focus_m"):
        raise t.error("f_number", "depth of field needs both f_number and focus_m")
    if t.has("mount"):
        if t.has("rail"):
            raise t.error("mount", "give either rail or mount, not both")
    elif t.has("rail") == t.has("position_m"):
        raise t.error("rail", "give either rail (with u), mount or position_m, not several or none")
    if t.has("rail"):
        if not t.has("u"):
            raise t.error("u", "is required for a camera on a rail (0 to 1)")
        if not 0.0 <= v["u"] <= 1.0:
            raise t.error("u", f"= {v['u']} is off rail {v['rail']!r}: the rail parameter runs "
                               "from 0 to 1")
    if t.has("target_m") == (t.has("pan_deg") or t.has("tilt_deg")):
        raise t.error("target_m", "aim the camera with either target_m or pan_deg + tilt_deg")
    if t.has("pan_deg") != t.has("tilt_deg"):
        raise t.error("pan_deg", "give both pan_deg and tilt_deg")


def _check_region(t: Table, v: dict) -> None:
    if v["normal"] is not None:
        if np.linalg.norm(v["normal"]) < 1e-9:
            raise t.error("normal", "must be a non-zero vector")
        v["normal"] = v["normal"] / np.linalg.norm(v["normal"])
    near = [k for k in ("near_point_m", "near_axis_m", "near_mesh", "region_file") if t.has(k)]
    if len(near) > 1:
        raise t.error(near[1], f"give one distance selector per region (also {near[0]}); "
                               "intersect several with a box or a normal instead")
    if near[:1] and near[0] != "region_file" and v["within"] is None:
        raise t.error("within_m", f"is required with {near[0]}: the largest distance (m)")
    if (v["within"] is not None or v["beyond"] > 0) and not near:
        raise t.error("within_m" if v["within"] is not None else "beyond_m",
                      "applies to a distance selector: add near_point_m, near_axis_m, near_mesh or "
                      "region_file")
    if v["near_axis"] is not None:
        axis = v["near_axis"]
        if len(axis) != 2 or np.linalg.norm(axis[1] - axis[0]) < 1e-9:
            raise t.error("near_axis_m", "must be 2 distinct points [[x, y, z], [x, y, z]] on the axis")
    if v["within"] is not None and v["beyond"] >= v["within"]:
        raise t.error("beyond_m", f"must be less than within_m ({v['within']:g} m)")
    if np.any(v["box_min"] >= v["box_max"]):
        raise t.error("box_max_m", "must be greater than box_min_m on every axis")


def _check_light(t: Table, v: dict) -> None:
    if np.linalg.norm(v["target"] - v["position"]) < 1e-6:
        raise t.error("target_m", "must differ from position_m (the panel faces the target)")


def _check_speckle(t: Table, v: dict) -> None:
    if v["black_albedo"] >= v["white_albedo"]:
        raise t.error("black_albedo", "must be less than white_albedo")
    if v["image"] is None and v["dot_diameter"] < 3 * v["texel"]:
        raise t.error("texel_mm", f"must be at most a third of the dot diameter "
                                  f"({v['dot_diameter'] * 1e3:g} mm) to draw round dots")


def _check_optimize(t: Table, v: dict) -> None:
    _check_angles(t, v, "min_axis_angle_deg", "max_axis_angle_deg", "min_axis_angle", "max_axis_angle")


def _check_body(t: Table, v: dict) -> None:
    _sensor_size(t, v)


def _check_design(t: Table, v: dict) -> None:
    if (v["sensor_width"] is None) != (v["pixels"] is None):
        raise t.error("pixels", "give the bodies' sensor_width_mm and pixels together (or neither: "
                                "the first [[camera]]'s)")
    if v["max_cameras"] is not None and v["max_cameras"] < v["min_cameras"]:
        raise t.error("max_cameras", f"= {v['max_cameras']} is below min_cameras = {v['min_cameras']}")


# --------------------------------------------------------------------------------------------
# The experiment
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Experiment:
    """A validated experiment. `path` is the TOML file it came from; `name` and `description` are
    the [experiment] table, the other fields one table each."""

    path: Path
    name: str = row("name", Text(title=True),
                    doc="shown in figures and summaries; at most 200 characters, no `/`, `\\` or "
                        "control characters")
    meshes: tuple[MeshSpec, ...] = table("mesh", MeshSpec, array=True, required=True,
                                         doc='At least one with `role = "specimen"`.')
    regions: tuple[RegionSpec, ...] = table(
        "region", RegionSpec, array=True, required=True, check=_check_region,
        doc="A patch of interest on a specimen mesh, chosen by a normal, a box, a distance to a "
            "point, an axis, another mesh or a region mesh (all that are given apply). A planar "
            "selection is one face; a curved one must be one connected piece of surface, developed "
            "onto the plane (docs/curved.md).")
    rails: tuple[RailSpec, ...] = table(
        "rail", RailSpec, array=True, check=check_rail,
        doc="A bar cameras slide along. The knot vector is clamped and uniform on [0, 1]: `u = 0` is "
            "the first control point, `u = 1` the last.")
    camera_specs: tuple[CameraSpec, ...] = table(
        "camera", CameraSpec, array=True, required=True, check=_check_camera, extra=(_sensor_mm_row(),),
        doc="Place a camera with `rail` + `u` (+ `offset_m`) or `position_m`; aim it with `target_m` "
            "or `pan_deg` + `tilt_deg`. Two cameras may not share one optical centre.")
    evaluation: Evaluation = table("evaluation", Evaluation)
    description: str = row("description", Text(empty=True), "", doc="free text")
    lights: tuple[LightSpec, ...] = table("light", LightSpec, array=True, check=_check_light,
                                          doc="A rectangular LED panel.", default=())
    speckle: SpeckleSpec = table("speckle", SpeckleSpec, check=_check_speckle, default=SpeckleSpec(),
                                 doc="The paint on the regions of interest (`vdo render`).")
    sensor: SensorModel = table("sensor", SensorModel, rows=_sensor_rows(), default=SensorModel(),
                                doc="EMVA 1288 sensor model (`vdo.model.sensor.SensorModel`).")
    render: RenderSpec = table("render", RenderSpec, default=RenderSpec())
    optimize: OptimizeSpec = table("optimize", OptimizeSpec, check=_check_optimize,
                                   default=OptimizeSpec(), doc="What `vdo optimize` may move.")
    analysis: Analysis = table("analysis", Analysis, check=_check_analysis, default=Analysis(),
                               doc="The DIC analysis strain uncertainties are predicted for "
                                   "(docs/theory.md, strain).")
    mounts: tuple[MountSpec, ...] = table(
        "mount", MountSpec, array=True, check=check_mount, default=(),
        doc="Where cameras can stand: a rail, a zone (a box, or a floor polygon with a height "
            "range: a tripod) or a fixed point. Cameras name one with `mount`; rail mounts are "
            "written back as [[rail]].")
    keep_outs: tuple[KeepOutSpec, ...] = table(
        "keep_out", KeepOutSpec, array=True, check=check_keep_out, default=(),
        doc="A box no camera may stand in: cameras inside one are refused, design drops the "
            "candidates inside one, optimize keeps its cameras out.")
    stereo_pairs: tuple[StereoPairSpec, ...] = table(
        "stereo_pair", StereoPairSpec, array=True, check=_check_stereo_pair, default=(),
        doc="Two cameras used as a stereo pair: their axes keep an angle in [min, max].")
    groups: tuple[GroupSpec, ...] = table(
        "group", GroupSpec, array=True, default=(),
        doc="Meshes that move rigidly together along the load path.")
    load_path: LoadPathSpec = table(
        "load_path", LoadPathSpec, check=_check_load_path, default=LoadPathSpec(),
        doc="A moving test: `vdo evaluate` judges every step (`vdo.geometry.keyframes`, docs/load_path.md).")
    design: DesignSpec = table("design", DesignSpec, check=_check_design, default=DesignSpec(),
                               doc="What `vdo design` chooses from (`vdo.design.candidates`).")
    bodies: tuple[BodySpec, ...] = table(
        "body", BodySpec, array=True, check=_check_body, extra=(_sensor_mm_row(),), default=(),
        doc="`vdo design`'s inventory of camera bodies, e.g. 6 of a 5 MP sensor and 4 of a 12 MP "
            "one; without any, [design] sensor_width_mm + pixels (or the first [[camera]]'s) and "
            "max_cameras.")
    calibration: CalibrationSpec = table(
        "calibration", CalibrationSpec, check=_check_calibration, default=CalibrationSpec(),
        doc="The calibration session `vdo calibrate` renders and calibrates (docs/calibration.md).")
    given: frozenset = field(default=frozenset(), repr=False)   # the ON_REQUEST tables the file gives

    def has(self, key: str) -> bool:
        """Whether the file gives table `key` (for the tables whose presence asks for work, e.g.
        [calibration]: `vdo evaluate` then adds the calibration-induced errors)."""
        return key in self.given

    def __post_init__(self):
        """The defaults that depend on another table, resolved once here: a Q4 element defaults
        to the DIC patch, a region's min_cameras to [evaluation] min_cameras."""
        if self.analysis.element is None:
            object.__setattr__(self, "analysis", replace(self.analysis,
                                                         element=self.evaluation.patch_size))
        if any(r.min_cameras is None for r in self.regions):
            object.__setattr__(self, "regions", tuple(
                r if r.min_cameras is not None else replace(r, min_cameras=self.evaluation.min_cameras)
                for r in self.regions))

    def mount(self, name: str) -> MountSpec:
        """The zone or fixed [[mount]] called `name`."""
        return next(m for m in self.mounts if m.name == name)

    def rail(self, name: str) -> RailSpec:
        """The [[rail]] called `name`."""
        return next(r for r in self.rails if r.name == name)

    def with_cameras(self, specs) -> "Experiment":
        """This experiment with other `CameraSpec`s (SI units, unchecked: for code that builds
        specs from a checked experiment, e.g. `vdo optimize`). From a script use `with_camera`."""
        return replace(self, camera_specs=tuple(specs))

    PLACEMENT = ("rail", "u", "offset_m", "mount", "position_m")   # the keys that move a camera
    AIM = ("target_m", "pan_deg", "tilt_deg")                      # the keys that aim it

    def with_camera(self, name: str, *, centre=None, **fields) -> "Experiment":
        """This experiment with camera `name` edited, checked as the file is: `fields` are the
        [[camera]] keys of the file in its units (``u=0.3, focal_mm=50, pan_deg=-20,
        target_m=[x, y, z], position_m=..., mount="zone1"``; docs/config.md), and any mistake
        (off a rail, outside a zone, a focal length out of range, an angle beyond ±360°, an
        unknown key) raises the file's one-line `ConfigError` naming the camera and the field.

        A new placement replaces the old: `rail` or `mount` drops the camera's rail, u, offset and
        position; `position_m` on a rail camera takes it off the rail; `u` or `offset_m` keep it.
        Likewise `target_m` replaces pan and tilt, and `pan_deg` or `tilt_deg` replaces a target
        (the other angle is kept). A camera aimed with `target_m` keeps looking at its target
        when it moves. One aimed with pan and tilt re-aims as `vdo optimize` does: after the
        move it looks at its `vdo.model.pose.aim_point`, the point of its old optical axis at
        the depth of `centre` (m; the regions' centroid, `Geometry.centre`; `Geometry.with_camera`
        passes it), with its roll kept (a camera whose axis is vertical keeps its angles,
        `holds_aim`). Giving pan/tilt or a target with the move aims it as given."""
        where = f'camera "{name}"'
        data = self.to_dict()
        entries = data["camera"]
        index = next((i for i, c in enumerate(entries) if c["name"] == name), None)
        if index is None:
            raise ConfigError(self.path, where, f"no [[camera]] named {name!r} (cameras: "
                                                f"{', '.join(c['name'] for c in entries)})")
        known = tuple(r.key for r in rows_of(CameraSpec)) + ("sensor_mm",)
        for key in fields:
            if key not in known:
                raise ConfigError(self.path, f"{where}.{key}", unknown_field(key, known))
        entry = {k: v for k, v in entries[index].items() if k not in fields}
        drop = set()
        if "rail" in fields or "mount" in fields:
            drop |= {"rail", "u", "offset_m", "mount", "position_m"}
        if "position_m" in fields and "rail" in entry:
            drop |= {"rail", "u", "offset_m"}
        if "target_m" in fields:
            drop |= {"pan_deg", "tilt_deg"}
        position = camera_positions(self)[index]
        pan, tilt = self.camera_specs[index].angles(position)
        if "pan_deg" in fields or "tilt_deg" in fields:
            entry.setdefault("pan_deg", math.degrees(pan))
            entry.setdefault("tilt_deg", math.degrees(tilt))
            drop.add("target_m")
        if "sensor_mm" in fields:
            drop.add("sensor_width_mm")
        entry = {k: v for k, v in entry.items() if k not in drop - set(fields)} | fields
        moved = any(k in fields for k in self.PLACEMENT)
        reaim = moved and not any(k in fields for k in self.AIM) and "target_m" not in entry
        data["camera"] = entries[:index] + [entry] + entries[index + 1:]
        edited = parse(data, self.path)
        if reaim and holds_aim(tilt) and centre is None:
            raise ConfigError(self.path, where, "moves, and a camera aimed with pan and tilt re-aims "
                                                "at the depth of the regions' centre: pass centre="
                                                "geometry.centre (or call geometry.with_camera), or "
                                                "give pan_deg + tilt_deg or target_m")
        if reaim and holds_aim(tilt):
            pan, tilt = look_at_angles(camera_positions(edited)[index], aim_point(position, pan, tilt, centre))
            entry = entry | {"pan_deg": math.degrees(pan), "tilt_deg": math.degrees(tilt)}
            data["camera"] = entries[:index] + [entry] + entries[index + 1:]
            edited = parse(data, self.path)
        return edited

    def with_settings(self, **tables) -> "Experiment":
        """This experiment with keys of its single tables changed, checked as the file is:
        ``exp.with_settings(evaluation={"sample_spacing_mm": 20}, sensor={"read_noise_e": 3})``
        (file keys and units, docs/config.md; the other keys of each table keep their values).
        Cameras: `with_camera`."""
        single = tuple(sec.key for sec in sections() if not sec.array)
        data = self.to_dict()
        for key, values in tables.items():
            if key not in single:
                raise ConfigError(self.path, key, f"with_settings edits the tables {', '.join(single)}"
                                                  " (a camera: with_camera)")
            if not isinstance(values, dict):
                raise ConfigError(self.path, key, f"give a dict of {key} keys, e.g. "
                                                  f"{key}={{{next(iter(data.get(key, {'key': 1})))!r}: ...}}")
            data[key] = data.get(key, {}) | values
        return parse(data, self.path)

    def to_dict(self) -> dict:
        """The experiment as a TOML-ready dict: every table (an `ON_REQUEST` one only when given),
        defaults filled, absolute paths;
        ``parse(e.to_dict(), e.path)`` gives back `e` (to 12 significant digits)."""
        out = {"experiment": write_rows(self, rows_of(Experiment))}
        for sec in sections():
            value = getattr(self, sec.attr)
            if sec.key in ON_REQUEST and not self.has(sec.key):
                continue
            if sec.array:
                if value:
                    out[sec.key] = [write_rows(item, sec.rows) for item in value]
            else:
                out[sec.key] = write_rows(value, sec.rows)
        return out


@functools.cache
def sections() -> tuple[Section, ...]:
    """The tables of an experiment file (besides [experiment]), in `Experiment` field order."""
    out = []
    for f in dataclasses.fields(Experiment):
        if "vdo.table" in f.metadata:
            sec = f.metadata["vdo.table"]
            out.append(replace(sec, attr=f.name, rows=sec.rows or rows_of(sec.cls)))
    return tuple(out)


def camera_positions(exp: Experiment) -> list[np.ndarray]:
    """The optical centre (m) of every camera spec: rail point + offset, or position_m."""
    out = []
    for spec in exp.camera_specs:
        if spec.rail is not None:
            out.append(exp.rail(spec.rail).point(spec.u) + spec.offset)
        else:
            out.append(np.asarray(spec.position, dtype=float))
    return out


def load(path) -> Experiment:
    """Read and validate an experiment file. Raises ConfigError on any user mistake."""
    return parse(read_toml(path), Path(path))


def parse(data: dict, path: Path) -> Experiment:
    """Validate an already-parsed TOML document that came from `path` (with the fields of
    `with_overrides` written in)."""
    path = Path(path).resolve()
    secs = sections()
    data = with_overrides(data, ("experiment",) + tuple(s.key for s in secs))
    top = Table(data, "", path, ("experiment",) + tuple(s.key for s in secs))
    head = Table(top.raw("experiment"), "experiment", path, tuple(r.key for r in rows_of(Experiment)))
    values = {r.attr: head.get(r, r.default) for r in rows_of(Experiment)}
    tables = {}
    for sec in secs:
        values[sec.attr], tables[sec.key] = read_section(top, sec, path)
    resolve_mounts(values, tables, path)
    exp = Experiment(path=path, **values, given=frozenset(k for k in ON_REQUEST if top.has(k)))
    _check_references(exp, tables)
    _check_keep_outs(exp, tables)
    return exp


def _check_references(exp: Experiment, tables: dict) -> None:
    """Checks across tables: names that refer to other tables, and camera poses."""
    path = exp.path
    roles = {m.name: m.role for m in exp.meshes}
    if "specimen" not in roles.values():
        raise ConfigError(path, "mesh", 'needs at least one mesh with role = "specimen"')
    for region, t in zip(exp.regions, tables["region"]):
        if roles.get(region.mesh) != "specimen":
            raise t.error("mesh", f"must name a mesh with role \"specimen\" (got {region.mesh!r}; "
                                  f"specimen meshes: {', '.join(n for n, r in roles.items() if r == 'specimen')})")
        if region.near_mesh is not None and region.near_mesh not in roles:
            raise t.error("near_mesh", f"no [[mesh]] named {region.near_mesh!r} (meshes: "
                                       f"{', '.join(sorted(roles))})")
    rails = {r.name for r in exp.rails}
    for cam, t in zip(exp.camera_specs, tables["camera"]):
        if cam.rail is not None and cam.rail not in rails:
            raise t.error("rail", f"no [[rail]] named {cam.rail!r} (rails: {', '.join(sorted(rails)) or 'none'})")
    for key, names, kind in (("cameras", exp.optimize.cameras, "camera"),
                             ("regions", exp.optimize.regions, "region")):
        known = {x.name for x in (exp.camera_specs if kind == "camera" else exp.regions)}
        unknown = sorted(set(names or ()) - known)
        if unknown:
            raise ConfigError(path, f"optimize.{key}", f"no [[{kind}]] named {', '.join(map(repr, unknown))}")
    if "lens" in exp.optimize.free and not exp.optimize.lenses and \
            not any(c.lenses for c in exp.camera_specs):
        raise ConfigError(path, "optimize.free", 'lists "lens" but no lenses_mm catalogue is given: '
                                                 'add e.g. lenses_mm = [24, 35, 50, 100] here or on '
                                                 'a [[camera]]')
    cameras, pairs = {c.name for c in exp.camera_specs}, set()
    for pair, t in zip(exp.stereo_pairs, tables["stereo_pair"]):
        unknown = sorted(set(pair.cameras) - cameras)
        if unknown:
            raise t.error("cameras", f"no [[camera]] named {', '.join(map(repr, unknown))}")
        if frozenset(pair.cameras) in pairs:
            raise t.error("cameras", "this pair is declared twice")
        pairs.add(frozenset(pair.cameras))
    if exp.analysis.pairs == "declared" and not exp.stereo_pairs:
        raise ConfigError(path, "analysis.pairs", 'is "declared" but the file has no [[stereo_pair]]: '
                                                  'declare the lab\'s pairs, or use pairs = "auto"')
    meshes = set(roles)
    grouped: dict[str, str] = {}
    for group, t in zip(exp.groups, tables["group"]):
        if group.name in meshes:
            raise t.error("name", f"{group.name!r} is a mesh's name (every mesh is already a group "
                                  "of its own name); choose another")
        for mesh in group.meshes:
            if mesh not in meshes:
                raise t.error("meshes", f"no [[mesh]] named {mesh!r} (meshes: {', '.join(sorted(meshes))})")
            if mesh in grouped:
                raise t.error("meshes", f"mesh {mesh!r} is already in group {grouped[mesh]!r}")
            grouped[mesh] = group.name
    if exp.bodies:
        if exp.design.sensor_width is not None:
            raise ConfigError(path, "design.sensor_width_mm", "give the camera bodies either as "
                                                             "[[body]] tables or as [design] "
                                                             "sensor_width_mm + pixels, not both")
        total = sum(b.count for b in exp.bodies)
        if exp.design.max_cameras is not None and exp.design.max_cameras > total:
            raise ConfigError(path, "design.max_cameras", f"= {exp.design.max_cameras} is more than "
                                                          f"the {total} [[body]] bodies; lower it or "
                                                          "raise a body's count")
    deformed = exp.load_path.deformed_mesh
    if deformed is not None and roles.get(deformed) != "specimen":
        raise ConfigError(path, "load_path.deformed_mesh", f"must name a specimen mesh (got {deformed!r})")
    positions = camera_positions(exp)
    for spec, position, t in zip(exp.camera_specs, positions, tables["camera"]):
        if spec.target is not None and np.linalg.norm(spec.target - position) < 1e-6:
            raise t.error("target_m", "is the camera's own position")
    if len(positions) > 1:
        p = np.array(positions)
        gap = np.linalg.norm(p[:, None] - p[None], axis=-1)
        np.fill_diagonal(gap, np.inf)
        i, j = np.unravel_index(np.argmin(gap), gap.shape)
        if gap[i, j] < COINCIDENT_M:
            a, b = sorted((int(i), int(j)))
            raise tables["camera"][b].error(
                "", f"has its optical centre {gap[i, j] * 1e3:.3g} mm from camera "
                    f"{exp.camera_specs[a].name!r}'s ({np.round(p[b], 4).tolist()} m): two cameras "
                    "cannot share one pose; move or remove one")
