"""The experiment file: one schema table drives reading, writing and docs/config.md.

One TOML file describes one experiment. Lengths are metres unless a field's name says otherwise
(``_mm``); angles are degrees in the file (``_deg``) and radians inside vdo. Mesh files are
read with the unit they declare. Relative paths are relative to the TOML file.

The schema is the table of `Row`s attached to the fields of the parsed dataclasses (`Experiment`,
`CameraSpec`, ...): each row gives the TOML key, its type (a `Kind`: check + conversion), the unit
in the file, the default and the documentation (the machinery: `vdo.config.schema`). The same rows
read a file (`parse`, with `vdo.config.reader`), write one back (`Experiment.to_dict`, so
``parse(e.to_dict()) == e``) and generate docs/config.md (`vdo.config.reference.markdown`). The
tables live by domain: what stands in the lab ([[mesh]], [[region]], [[camera]], [[body]],
[[light]], [speckle], [evaluation], [render], [sensor]) in `vdo.config.rig`; what is done with it
([analysis], [[stereo_pair]], [[group]], [load_path], [optimize], [design], [calibration]) in
`vdo.config.procedure`; where cameras stand ([[rail]], [[mount]], [[keep_out]]) and their floor
geometry in `vdo.config.mounts`. Defaults live in the rows only. Adding a field is one `row(...)` line in its
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
                               check_mount, check_rail, inside_keep_out, resolve_mounts, zone_grid)
from vdo.config.procedure import (Analysis, CalibrationSpec, DesignSpec, ExposureSpec, GroupSpec,
                                  LoadPathSpec, ON_REQUEST, OptimizeSpec, StereoPairSpec,
                                  check_analysis, check_calibration, check_design, check_exposure,
                                  check_load_path, check_optimize,
                                  check_stereo_pair)
from vdo.config.rig import (BodySpec, CameraSpec, Evaluation, LightSpec, MeshSpec, RegionSpec,
                            RenderSpec, SpeckleSpec, check_body, check_camera, check_light,
                            check_region, check_speckle, sensor_mm_row, sensor_rows)
from vdo.config.reader import Table, from_override, read_section, read_toml, with_overrides
from vdo.config.schema import Section, Text, row, rows_of, table, unknown_field, write_rows
from vdo.core.errors import ConfigError, ConfigErrors
from vdo.model import nurbs
from vdo.model.pose import aim_point, holds_aim, look_at_angles
from vdo.model.sensor import SensorModel

COINCIDENT_M = 1e-3                # two optical centres closer than this are one pose


# --------------------------------------------------------------------------------------------
# The tables
# --------------------------------------------------------------------------------------------


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
                                  f"{spec.focal_length * 1e3:g} mm is not in the lens catalogue "
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
    for m, t in zip(exp.mounts, tables.get("mount", [])):
        if m.kind != "zone" or m.tripod is None:
            continue
        # where the feet can stand: the zone's footprint grown by the legs' spread, on its floor
        xy = m.floor if m.floor is not None else np.array([m.low[:2], m.high[:2]])
        reach = np.array([xy.min(axis=0) - m.tripod.spread, xy.max(axis=0) + m.tripod.spread])
        for box in exp.keep_outs:
            if (box.box_min[2] <= m.tripod.floor_z <= box.box_max[2]
                    and np.all(box.box_min[:2] <= reach[0]) and np.all(box.box_max[:2] >= reach[1])):
                raise t.error("tripod.floor_z_m", f"= {m.tripod.floor_z:g} m, where the feet of zone "
                                                  f"{m.name!r}'s tripods stand, lies in keep_out {box.name!r} "
                                                  f"({box.box_min.tolist()} to {box.box_max.tolist()} m) "
                                                  "under the whole zone: no pose can move them out of it; "
                                                  "end the keep-out below the floor (box_max_m z < "
                                                  f"{m.tripod.floor_z:g}) or narrow it")
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


# --------------------------------------------------------------------------------------------
# Checks across the fields of one table: check(t, values) raises t.error or completes values
# --------------------------------------------------------------------------------------------


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
        "region", RegionSpec, array=True, required=True, check=check_region,
        doc="A patch of interest on a specimen mesh, chosen by a normal, a box, a distance to a "
            "point, an axis, another mesh or a region mesh (all that are given apply). A planar "
            "selection is one face; a curved one must be one connected piece of surface, developed "
            "onto the plane (docs/curved.md).")
    rails: tuple[RailSpec, ...] = table(
        "rail", RailSpec, array=True, check=check_rail,
        doc="A bar cameras slide along: a NURBS curve. Its knot vector is clamped and uniform on [0, 1], "
            "or `knots` as CAD exports them (a full circle: 9 control points on a square, degree 2, "
            "corner weights 1/sqrt(2), knots [0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 4]), mapped onto [0, 1]: "
            "`u = 0` is the first control point, `u = 1` the last. `u` is the curve's parameter, "
            "not its arc length: on a rational circle it is not proportional to the angle (on the "
            "9-point circle above, u = 0.0625 lies at 21.6 deg and u = 0.3 at 107.1 deg, not 22.5 "
            "and 108: exact at the quarters, up to ~1 deg between them), so where the angle matters "
            "read a camera's place from `vdo evaluate`'s layout or give `position_m`.")
    camera_specs: tuple[CameraSpec, ...] = table(
        "camera", CameraSpec, array=True, required=True, check=check_camera, extra=(sensor_mm_row(),),
        doc="Place a camera with `rail` + `u` (+ `offset_m`) or `position_m`; aim it with `target_m` "
            "or `pan_deg` + `tilt_deg`. Two cameras may not share one optical centre.")
    evaluation: Evaluation = table("evaluation", Evaluation)
    description: str = row("description", Text(empty=True), "", doc="free text")
    lights: tuple[LightSpec, ...] = table("light", LightSpec, array=True, check=check_light,
                                          doc="A rectangular LED panel.", default=())
    speckle: SpeckleSpec = table("speckle", SpeckleSpec, check=check_speckle, default=SpeckleSpec(),
                                 doc="The paint on the regions of interest (`vdo render`).")
    sensor: SensorModel = table("sensor", SensorModel, rows=sensor_rows(), default=SensorModel(),
                                doc="EMVA 1288 sensor model (`vdo.model.sensor.SensorModel`).")
    render: RenderSpec = table("render", RenderSpec, default=RenderSpec())
    exposure: ExposureSpec = table(
        "exposure", ExposureSpec, check=check_exposure, default=ExposureSpec(),
        doc="The light each camera gathers, (t / t_ref) (8 / N)², and what `vdo design` and "
            "`vdo optimize` set of it: f-numbers, exposure times, light power (docs/exposure.md).")
    optimize: OptimizeSpec = table("optimize", OptimizeSpec, check=check_optimize,
                                   default=OptimizeSpec(), doc="What `vdo optimize` may move.")
    analysis: Analysis = table("analysis", Analysis, check=check_analysis, default=Analysis(),
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
        "stereo_pair", StereoPairSpec, array=True, check=check_stereo_pair, default=(),
        doc="Two cameras used as a stereo pair: their axes keep an angle in [min, max].")
    groups: tuple[GroupSpec, ...] = table(
        "group", GroupSpec, array=True, default=(),
        doc="Meshes that move rigidly together along the load path.")
    load_path: LoadPathSpec = table(
        "load_path", LoadPathSpec, check=check_load_path, default=LoadPathSpec(),
        doc="A moving test: `vdo evaluate` judges every step (`vdo.geometry.keyframes`, docs/load_path.md).")
    design: DesignSpec = table("design", DesignSpec, check=check_design, default=DesignSpec(),
                               doc="What `vdo design` chooses from (`vdo.design.candidates`).")
    bodies: tuple[BodySpec, ...] = table(
        "body", BodySpec, array=True, check=check_body, extra=(sensor_mm_row(),), default=(),
        doc="`vdo design`'s inventory of camera bodies, e.g. 6 of a 5 MP sensor and 4 of a 12 MP "
            "one; without any, [design] sensor_width_mm + pixels (or the first [[camera]]'s) and "
            "max_cameras.")
    calibration: CalibrationSpec = table(
        "calibration", CalibrationSpec, check=check_calibration, default=CalibrationSpec(),
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

    def light_places(self, light: LightSpec) -> np.ndarray:
        """(P, 3) the panel centres (m) `light` may take on its [[mount]], off every [[keep_out]]:
        a rail's `[design] rail_positions` points evenly spread in u, a zone's `zone_grid`
        ([design] zone_points x zone_heights); (0, 3) for a light on no mount."""
        if light.mount is None:
            return np.zeros((0, 3))
        d = self.design
        if any(r.name == light.mount for r in self.rails):
            rail = self.rail(light.mount)
            points = np.asarray(rail.point(rail.spread(d.rail_us)), float).reshape(-1, 3)
        else:
            points = zone_grid(self.mount(light.mount), d.zone_points, d.zone_heights)
        return points[inside_keep_out(self.keep_outs, points) < 0] if len(points) else points

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
        position = camera_positions(self.camera_specs, self.rails)[index]
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
            pan, tilt = look_at_angles(camera_positions(edited.camera_specs, edited.rails)[index],
                                       aim_point(position, pan, tilt, centre))
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


def camera_positions(camera_specs: tuple[CameraSpec, ...], rails: tuple[RailSpec, ...]) -> list[np.ndarray]:
    """The optical centre (m) of every camera spec of `camera_specs` (the [[camera]] tables): the
    point of its rail (of `rails`, the [[rail]] tables) + offset, or position_m."""
    out = []
    for spec in camera_specs:
        if spec.rail is not None:
            out.append(next(r for r in rails if r.name == spec.rail).point(spec.u) + spec.offset)
        else:
            out.append(np.asarray(spec.position, dtype=float))
    return out


def load(path) -> Experiment:
    """Read and validate an experiment file. Raises ConfigError on any user mistake (saying so
    where the field was written by VDO_SET, `vdo.config.reader.from_override`)."""
    data = read_toml(path)
    try:
        return parse(data, Path(path))
    except ConfigErrors:
        raise
    except ConfigError as err:
        raise from_override(err) from None


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
    rails = {r.name: r for r in exp.rails}
    for cam, t in zip(exp.camera_specs, tables["camera"]):
        if cam.rail is not None and cam.rail not in rails:
            raise t.error("rail", f"no [[rail]] named {cam.rail!r} (rails: {', '.join(sorted(rails)) or 'none'})")
        if cam.rail is not None and not 0.0 <= cam.u <= 1.0:
            raise t.error("u", f"= {cam.u} is off rail {cam.rail!r}: the rail parameter runs from 0 to 1"
                               f"{nurbs.off_rail_hint(rails[cam.rail].control_points, cam.u)}")
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
    mounts = {m.name: m.kind for m in exp.mounts} | {r.name: "rail" for r in exp.rails}
    for light, t in zip(exp.lights, tables["light"]):
        if light.mount is None:
            continue
        if mounts.get(light.mount) not in ("rail", "zone"):
            raise t.error("mount", f"no rail or zone [[mount]] named {light.mount!r} (rail and zone "
                                   "mounts: " + (", ".join(sorted(n for n, k in mounts.items()
                                                                  if k != "fixed")) or "none")
                          + "); a panel that stays put needs only position_m")
        if not len(exp.light_places(light)):
            raise t.error("mount", f"every point of mount {light.mount!r} lies in a [[keep_out]]: "
                                   "no place for the panel; enlarge the mount or shrink the keep-out")
    lit = {lt.mount for lt in exp.lights if lt.mount is not None}
    for cam, t in zip(exp.camera_specs, tables["camera"]):
        on = next((name for name in (cam.mount, cam.rail) if name in lit), None)
        if on is not None:        # the field the file used (a rail [[mount]] is read as a rail)
            panels = ", ".join(repr(lt.name) for lt in exp.lights if lt.mount == on)
            raise t.error("mount" if t.has("mount") else "rail",
                          f"{on!r} carries the [[light]] {panels}: a mount holds lights or cameras, "
                          "not both; give the camera or the light another mount")
    if "light_positions" in exp.exposure.free and not any(lt.mount for lt in exp.lights):
        raise ConfigError(path, "exposure.free", 'lists "light_positions" but no [[light]] has a '
                                                 'mount: give each panel that may move mount = '
                                                 '"a rail or zone [[mount]]"')
    if "lights" in exp.exposure.free and not any(lt.max_radiance for lt in exp.lights):
        raise ConfigError(path, "exposure.free", 'lists "lights" but no [[light]] has max_radiance: '
                                                 "give each panel that may be set its brightest "
                                                 "setting, e.g. max_radiance = 2 x its radiance")
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
    positions = camera_positions(exp.camera_specs, exp.rails)
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
