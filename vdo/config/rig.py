"""The tables of what stands in the lab, read by `vdo.config.experiment`: the meshes and the
regions of interest ([[mesh]], [[region]]), the cameras and the bodies design may choose
([[camera]], [[body]]), the lights, the speckle, the evaluation's sampling and the render settings
([[light]], [speckle], [evaluation], [render]), and the [sensor] rows; each table's own checks
(`check_camera`, ...). Lengths are metres inside vdo, angles radians (the file's units are in
the rows)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vdo.config.reader import Table
from vdo.config.schema import File, Flag, Numbers, Points, Real, Row, Text, Vector, Whole, row
from vdo.model.pose import look_at_angles
from vdo.model.sensor import ALIGNMENTS, SensorModel

ROLES = ("specimen", "obstacle")


MAX_CAMERA_PIXELS = 100e6          # per camera (1.2 GB per linear RGB float image)


FOCAL_RANGE_MM = (0.5, 5000.0)     # shortest fisheye .. longest telephoto lenses made


MAX_ANGLE_DEG = 360.0              # a camera angle beyond ±360° is radians or a typo


ANGLE_WHY = "an angle in degrees (a value in radians? multiply by 57.3)"


SENSOR_FIELDS = tuple(f.name for f in dataclasses.fields(SensorModel))   # the [sensor] table


UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}


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


def sensor_width_row():
    """The sensor width row, shared by a camera and a body of the design inventory."""
    return row("sensor_width_mm", Real(positive=True), unit="mm", either="sensor_mm",
               shown="or sensor_mm", doc="sensor width")


def pixels_row():
    """The pixel count row, shared by a camera and a body of the design inventory."""
    return row("pixels", Vector(2, positive=True, whole=True, as_tuple=True, letters="WH"),
               doc=f"whole numbers, at most {MAX_CAMERA_PIXELS / 1e6:g} Mpx")


@dataclass(frozen=True, eq=False)
class CameraSpec:
    """A camera as written in the file; `camera_positions` and `angles` resolve its pose,
    `vdo.scene.cameras_of` builds the `vdo.model.camera.Camera`."""

    name: str = row("name", Text(name=True), doc="unique; names the camera's output files")
    sensor_width: float = sensor_width_row()
    pixels: tuple[int, int] = pixels_row()
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
                                 doc="with focus_m: thin lens with depth of field in renders "
                                 "(none: f/8 in focus assumed, diffraction only)")
    focus_distance: float | None = row("focus_m", Real(positive=True), None, unit="m", shown="none",
                                       doc="focus distance, with f_number")
    exposure_time: float | None = row("exposure_ms", Real(positive=True), None, unit="ms",
                                      shown="[sensor] exposure_ms",
                                      doc="exposure time; with the f-number (f/8 without one) it sets "
                                          "the light the camera gathers, (t / t_ref) (8 / N)²")
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


def sensor_mm_row() -> Row:
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
    max_radiance: float | None = row("max_radiance", Real(positive=True), None, shown="radiance",
                                     doc='the panel\'s brightest setting: with "lights" in [exposure] '
                                         "free, design and optimize set the radiance up to it")
    mount: str | None = row("mount", Text(name=True), None, shown="none",
                            doc='a rail or zone [[mount]] the panel may stand anywhere on: with '
                                '"light_positions" in [exposure] free, design and optimize move '
                                "its centre to the best of the mount's [design] grid points, still "
                                "facing target_m (a mount holds lights or cameras, not both)")


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


def sensor_rows() -> tuple[Row, ...]:
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
                                 "a linear value of 1 fills 70 % of the full well"),
            "exposure_ms": ("the exposure time (ms) photons_per_unit holds at, with the lens at "
                            "f/8; a camera's exposure_ms and f_number scale it", "")}
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


@dataclass(frozen=True, eq=False)
class BodySpec:
    """A kind of camera body in `vdo design`'s inventory: its sensor and how many are available."""

    name: str = row("name", Text(name=True), doc="unique, e.g. \"5MP\"")
    sensor_width: float = sensor_width_row()
    pixels: tuple[int, int] = pixels_row()
    count: int = row("count", Whole(low=1), doc="how many bodies of this kind are available")
    lenses: tuple[float, ...] = row("lenses_mm", Numbers(as_set=True, what="focal lengths in mm"), [],
                                    unit="mm", shown="[design] lenses_mm",
                                    doc="the lenses this body takes")


def sensor_size(t: Table, v: dict) -> None:
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
        sensor = t.get(sensor_mm_row())
        pitch_w, pitch_h = sensor[0] / width_px, sensor[1] / height_px
        if abs(pitch_w - pitch_h) > 0.01 * pitch_w:
            raise t.error("sensor_mm", f"gives non-square pixels ({pitch_w * 1e6:.3f} x "
                                       f"{pitch_h * 1e6:.3f} um); vdo models square pixels: check "
                                       "the sensor size and pixel counts")
        v["sensor_width"] = float(sensor[0])


def check_camera(t: Table, v: dict) -> None:
    sensor_size(t, v)
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
        # its range is checked with the rail's ends known (`vdo.config.experiment`)
    if t.has("target_m") == (t.has("pan_deg") or t.has("tilt_deg")):
        raise t.error("target_m", "aim the camera with either target_m or pan_deg + tilt_deg")
    if t.has("pan_deg") != t.has("tilt_deg"):
        raise t.error("pan_deg", "give both pan_deg and tilt_deg")


def check_region(t: Table, v: dict) -> None:
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


def check_light(t: Table, v: dict) -> None:
    if np.linalg.norm(v["target"] - v["position"]) < 1e-6:
        raise t.error("target_m", "must differ from position_m (the panel faces the target)")
    if v["max_radiance"] is not None and v["max_radiance"] < v["radiance"]:
        raise t.error("max_radiance", f"= {v['max_radiance']:g} is below radiance = "
                                      f"{v['radiance']:g}: give the panel's brightest setting")


def check_speckle(t: Table, v: dict) -> None:
    if v["black_albedo"] >= v["white_albedo"]:
        raise t.error("black_albedo", "must be less than white_albedo")
    if v["image"] is None and v["dot_diameter"] < 3 * v["texel"]:
        raise t.error("texel_mm", f"must be at most a third of the dot diameter "
                                  f"({v['dot_diameter'] * 1e3:g} mm) to draw round dots")


def check_body(t: Table, v: dict) -> None:
    sensor_size(t, v)
