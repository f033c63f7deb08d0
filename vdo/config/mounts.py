"""Where cameras and lights stand: the [[rail]], [[mount]] (rail, zone or fixed) and [[keep_out]]
tables of the experiment file, their checks, and the floor geometry they need (NumPy only).

A zone's floor is a simple polygon (corners (n, 2) in m, counter-clockwise once checked), possibly
with holes; `inside_floor` tests points against it with the even-odd rule plus a distance
tolerance to the edges. A keep-out is an axis-aligned box; `inside_keep_out` gives the first box
holding each point. `zone_grid` is the grid of points a zone offers to `vdo design`'s cameras
and to the lights that stand on it. `resolve_mounts` turns rail mounts into rails and places the cameras on zone
and fixed mounts before the `Experiment` is built.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from vdo.config.reader import Table
from vdo.config.schema import Numbers, Points, Polygons, Real, SubTable, Text, Vector, Whole, row
from vdo.core.errors import ConfigError
from vdo.core.tolerances import TINY
from vdo.model import nurbs

FLOOR_CHUNK = 4096   # points per vectorised batch of `inside_floor` ((points, edges) temporaries)


def _signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _is_convex(poly: np.ndarray) -> bool:
    """Whether the counter-clockwise polygon turns left (or goes straight) at every corner."""
    edges = np.roll(poly, -1, axis=0) - poly
    turn = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    return bool(np.all(turn >= -1e-12))


def _is_simple(poly: np.ndarray) -> bool:
    """Whether no two non-adjacent edges of the polygon cross or touch (orientation tests)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    n = len(poly)

    def orient(p, q, r):
        return np.sign((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1])
                       - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))
    for i in range(n):
        j = np.arange(i + 2, n)
        j = j[(j + 1) % n != i]
        if not len(j):
            continue
        o1, o2 = orient(a[i], b[i], a[j]), orient(a[i], b[i], b[j])
        o3, o4 = orient(a[j], b[j], a[i]), orient(a[j], b[j], b[i])
        if np.any((o1 != o2) & (o3 != o4)):
            return False
    return True


def _in_polygon(poly: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Even-odd rule: a ray from each point xy (..., 2) along +x crosses the polygon's edges an
    odd number of times; bool (...)."""
    a, b = poly, np.roll(poly, -1, axis=0)                     # (E, 2) edges a -> b
    x, y = xy[..., 0, None], xy[..., 1, None]
    straddle = (a[:, 1] > y) != (b[:, 1] > y)                  # (..., E)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return np.count_nonzero(straddle & (cross > x), axis=-1) % 2 == 1


def _edge_distance(poly: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance (m) from each point xy (..., 2) to the polygon's boundary; (...)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    d = b - a
    rel = xy[..., None, :] - a                                 # (..., E, 2)
    t = np.clip(np.einsum("...ij,ij->...i", rel, d) / np.maximum(np.einsum("ij,ij->i", d, d), TINY),
                0, 1)
    return np.min(np.linalg.norm(rel - t[..., None] * d, axis=-1), axis=-1)


def inside_floor(floor: np.ndarray, xy: np.ndarray, tol: float = 1e-9, holes=()):
    """Whether the point xy (m) lies on the floor polygon `floor` (any simple polygon; within
    `tol` of its edge counts as on it) and in none of `holes` (strictly inside one: off). xy (2,)
    gives a bool, xy (M, 2) a bool array (M,), computed `FLOOR_CHUNK` points at a time."""
    xy = np.asarray(xy, dtype=float)[..., :2]
    if xy.ndim == 1:
        return bool(inside_floor(floor, xy[None], tol, holes)[0])
    out = np.empty(len(xy), dtype=bool)
    for k in range(0, len(xy), FLOOR_CHUNK):
        p = xy[k:k + FLOOR_CHUNK]
        on = _in_polygon(floor, p) | (_edge_distance(floor, p) <= tol)
        for h in holes:
            on &= ~(_in_polygon(h, p) & (_edge_distance(h, p) > tol))
        out[k:k + FLOOR_CHUNK] = on
    return out


KEEP_OUT_RAIL_POINTS = 201   # positions along a rail tested against the keep-out volumes


def inside_keep_out(keep_outs, points: np.ndarray) -> np.ndarray:
    """(N,) index of the first keep-out volume holding each point (N, 3), -1 where none does."""
    p = np.atleast_2d(np.asarray(points, float))
    out = np.full(len(p), -1)
    for k, box in reversed(list(enumerate(keep_outs))):
        out[box.contains(p)] = k
    return out


MOUNT_NEEDS = {"rail": ("control_points_m",), "zone": ("box_min_m", "box_max_m"),
               "fixed": ("position_m",)}
ZONE_FLOOR = ("floor_m", "height_m")   # the other form of a zone: a floor polygon
MOUNT_EXAMPLES = {"control_points_m": "control_points_m = [[0, 0, 1.5], [2, 0, 1.5]]",
                  "box_min_m": "box_min_m = [0.5, -1.0, 1.2]", "box_max_m": "box_max_m = [1.5, 1.0, 1.8]",
                  "position_m": "position_m = [1.0, 0.0, 1.5]", "height_m": "height_m = [1.2, 1.8]",
                  "floor_m": "floor_m = [[0, -2], [1, -2], [1, -1], [0, -1]]"}


def zone_grid(zone, per_axis: int, heights: int) -> np.ndarray:
    """(P, 3) candidate optical centres (or panel centres, m) in a zone [[mount]]: `per_axis` evenly spaced values
    along x and along y (edges included; one, the middle, where the extent is zero) times `heights`
    values over its height range; over a floor polygon, the points of that grid on its bounding box
    that lie on the polygon (off its holes), and its centroid when that does."""
    lo, hi = zone.low, zone.high
    axes = [np.linspace(lo[k], hi[k], per_axis) if hi[k] > lo[k] and per_axis > 1
            else np.array([(lo[k] + hi[k]) / 2]) for k in range(2)]
    axes.append(np.linspace(lo[2], hi[2], heights) if hi[2] > lo[2] and heights > 1
                else np.array([(lo[2] + hi[2]) / 2]))
    xy = np.stack(np.meshgrid(axes[0], axes[1], indexing="ij"), -1).reshape(-1, 2)
    if zone.floor is not None:
        xy = xy[zone.inside(xy)]
        centre = zone.floor.mean(axis=0)
        xy = np.vstack([xy, centre]) if zone.inside(centre) else xy
    return np.array([[x, y, z] for x, y in xy for z in axes[2]])


@dataclass(frozen=True, eq=False)
class RailSpec:
    """A bar cameras slide along: a clamped NURBS curve (`point` evaluates it in NumPy;
    `vdo.model.rail.Rail` in JAX, for its derivative). `control_points` (n, 3) in metres,
    `weights` (n,)."""

    name: str = row("name", Text(name=True), doc="unique")
    control_points: np.ndarray = row("control_points_m", Points(2), unit="m",
                                     doc="at least 2, consecutive points distinct")
    degree: int = row("degree", Whole(low=1), 1, doc="B-spline degree p < n (1 = polyline)")
    weights: np.ndarray | None = row("weights", Numbers(what="weights"), None, shown="all 1",
                                     doc="NURBS weights, one per control point")
    knots: np.ndarray | None = row("knots", Numbers(what="knots", positive=False), None,
                                   shown="clamped uniform",
                                   doc="NURBS knot vector, n + degree + 1 non-decreasing values, "
                                       "clamped (the first and last degree + 1 equal), as CAD "
                                       "exports it (a circle's double knots); mapped onto u in [0, 1]")

    def point(self, u) -> np.ndarray:
        """C(u) in metres (u.shape + (3,)), u in [0, 1] (`vdo.model.nurbs.point`)."""
        return nurbs.point(self.control_points, self.degree, self.weights, u, self.knots)

    @property
    def closed(self) -> bool:
        """A ring: its last control point is its first (`vdo.model.nurbs.is_closed`)."""
        return nurbs.is_closed(self.control_points)

    def spread(self, us: np.ndarray) -> np.ndarray:
        """The values `us` in [0, 1] of u to place things at, without u = 1 on a closed rail
        where u = 0 is taken (the same place)."""
        us = np.asarray(us, dtype=float)
        return us[:-1] if self.closed and len(us) > 1 and us[0] == 0.0 and us[-1] == 1.0 else us


@dataclass(frozen=True)
class TripodSpec:
    """The tripod a zone mount's camera stands on (`vdo.scene.tripod`): a top casting `head_m`
    below the underside of the camera body, `legs` straight legs from it to feet on the floor
    (z = `floor_z_m`) spaced evenly on a circle of radius `spread_m` around the point below it,
    the first at `azimuth_deg` from the camera's pan, and a centre column hanging
    `column_length_m` below it. Legs and column are cylinders that move with the camera: they
    hide the other cameras' views and cast shadows."""

    legs: int = row("legs", Whole(low=3), 3, doc="number of legs")
    spread: float = row("spread_m", Real(positive=True), 0.45, unit="m",
                        doc="radius of the circle of the feet, around the point below the head")
    leg_diameter: float = row("leg_diameter_m", Real(positive=True), 0.03, unit="m",
                              doc="diameter of a leg")
    column_diameter: float = row("column_diameter_m", Real(positive=True), 0.05, unit="m",
                                 doc="diameter of the centre column")
    column_length: float = row("column_length_m", Real(positive=True), 0.35, unit="m",
                               doc="the centre column's length below the top casting (cut at the floor)")
    head: float = row("head_m", Real(positive=True), 0.1, unit="m",
                      doc="height of the tripod head: from the underside of the camera body to the "
                          "top casting where the legs meet")
    floor_z: float = row("floor_z_m", Real(), 0.0, unit="m",
                         doc="height of the floor the feet stand on (below the zone)")
    azimuth: float = row("azimuth_deg", Real(), 180.0, unit="deg",
                         doc="direction of the first leg from the camera's pan (180: one leg back, "
                             "the others spread in front, out of the view)")


@dataclass(frozen=True, eq=False)
class MountSpec:
    """Where a camera stands. kind "rail": a NURBS curve (as a [[rail]]; read into `rails`);
    "zone": anywhere in the axis-aligned box [box_min, box_max] (m), e.g. a tripod on a floor
    area with its height range in z (a zero extent holds that axis), or anywhere above the simple
    polygon `floor` ((n, 2) m, counter-clockwise) off its `floor_holes`, within `height` (m);
    "fixed": at `position` (m)."""

    name: str = row("name", Text(name=True), doc="unique among mounts and rails")
    kind: str = row("kind", Text(choices=tuple(MOUNT_NEEDS)), doc="rail, zone or fixed")
    control_points: np.ndarray | None = row("control_points_m", Points(2), None, unit="m",
                                            shown="rail", doc="a rail mount's control points")
    degree: int | None = row("degree", Whole(low=1), None, shown="rail: 1", doc="a rail mount's degree")
    weights: np.ndarray | None = row("weights", Numbers(what="weights"), None, shown="rail: all 1",
                                     doc="a rail mount's NURBS weights")
    knots: np.ndarray | None = row("knots", Numbers(what="knots", positive=False), None,
                                   shown="rail: clamped uniform", doc="a rail mount's NURBS knot vector")
    box_min: np.ndarray | None = row("box_min_m", Vector(3, letters="xyz"), None, unit="m",
                                     shown="zone", doc="a box zone's lower corner")
    box_max: np.ndarray | None = row("box_max_m", Vector(3, letters="xyz"), None, unit="m",
                                     shown="zone", doc="a box zone's upper corner")
    floor: np.ndarray | None = row("floor_m", Points(3, dims=2), None, unit="m", shown="zone",
                                   doc="or a floor polygon, any simple one (with height_m)")
    height: tuple[float, float] | None = row("height_m", Vector(2, as_tuple=True, letters=("low", "high")),
                                             None, unit="m", shown="zone", doc="the polygon zone's heights")
    floor_holes: tuple[np.ndarray, ...] | None = row(
        "floor_holes_m", Polygons(), None, unit="m", shown="none",
        doc="polygons cut out of the floor polygon (a ring around the specimen: one hole)")
    position: np.ndarray | None = row("position_m", Vector(3, letters="xyz"), None, unit="m",
                                      shown="fixed", doc="a fixed mount's optical centre")
    tripod: TripodSpec | None = row("tripod", SubTable(TripodSpec), None, shown="none",
                                    doc="a zone's tripod as the table [mount.tripod] (fields below; "
                                        "`tripod = {}` takes the defaults): its legs and column "
                                        "occlude the other cameras and cast shadows")

    @property
    def convex(self) -> bool:
        """Whether the zone is a box or a convex floor polygon without holes."""
        return self.floor is None or (not self.floor_holes and _is_convex(self.floor))

    def inside(self, xy: np.ndarray, tol: float = 1e-9):
        """Whether the floor point xy (m) lies on the zone's floor (a box zone: its x, y range);
        xy (2,): a bool, xy (M, 2): a bool array (M,)."""
        if self.floor is None:
            xy = np.asarray(xy, dtype=float)
            on = np.all((xy >= self.low[:2] - tol) & (xy <= self.high[:2] + tol), axis=-1)
            return bool(on) if xy.ndim == 1 else on
        return inside_floor(self.floor, xy, tol, self.floor_holes or ())

    @property
    def low(self) -> np.ndarray:
        """The zone's lower bounding corner (m)."""
        return self.box_min if self.floor is None else np.array([*self.floor.min(0), self.height[0]])

    @property
    def high(self) -> np.ndarray:
        """The zone's upper bounding corner (m)."""
        return self.box_max if self.floor is None else np.array([*self.floor.max(0), self.height[1]])


@dataclass(frozen=True, eq=False)
class KeepOutSpec:
    """A volume no camera may stand in (the specimen's surroundings, a machine, a walkway): the
    box [box_min, box_max] (m). A camera's optical centre inside one is refused; design drops the
    candidate poses inside one; optimize keeps the cameras out."""

    name: str = row("name", Text(name=True), doc="unique")
    box_min: np.ndarray = row("box_min_m", Vector(3, finite=False, letters="xyz"), unit="m",
                              doc="lower corner (±inf allowed)")
    box_max: np.ndarray = row("box_max_m", Vector(3, finite=False, letters="xyz"), unit="m",
                              doc="upper corner (±inf allowed)")

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) whether points (N, 3) (m) lie strictly inside the box."""
        p = np.atleast_2d(np.asarray(points, float))
        return np.all((p > self.box_min) & (p < self.box_max), axis=1)


def check_rail(t: Table, v: dict) -> None:
    """[[rail]] (and a rail [[mount]]): degree below the control point count, consecutive control
    points distinct (1e-6 m), one weight per control point (default all 1, set in `v`), knots
    (when given) n + p + 1 non-decreasing, clamped, spanning an interval, no interior knot
    repeated more than p times (the curve would break there)."""
    points = v["control_points"]
    if v["degree"] >= len(points):
        raise t.error("degree", f"must be less than the number of control points ({len(points)})")
    gaps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    if np.any(gaps < 1e-6):
        i = int(np.argmax(gaps < 1e-6))
        raise t.error("control_points_m", f"points {i} and {i + 1} coincide: a rail needs distinct "
                                          "consecutive control points (remove the repeated one)")
    if v["weights"] is None:
        v["weights"] = np.ones(len(points))
    elif len(v["weights"]) != len(points):
        raise t.error("weights", f"must be a list of {len(points)} numbers > 0, one per control point")
    else:
        v["weights"] = np.asarray(v["weights"], dtype=float)
    if v.get("knots") is not None:
        k, p, n = np.asarray(v["knots"], dtype=float), v["degree"], len(points)
        example = "e.g. a 9-point circle of degree 2: [0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 4]"
        if len(k) != n + p + 1:
            raise t.error("knots", f"must hold n + degree + 1 = {n + p + 1} values for {n} control points "
                                   f"of degree {p} (got {len(k)}); {example}")
        if np.any(np.diff(k) < 0) or k[-1] <= k[0]:
            raise t.error("knots", f"must be non-decreasing and span an interval (got {k.tolist()})")
        if np.any(k[:p + 1] != k[0]) or np.any(k[-p - 1:] != k[-1]):
            raise t.error("knots", f"must be clamped: the first {p + 1} values equal and the last {p + 1} "
                                   f"equal (got {k.tolist()}); {example}")
        inner = k[p + 1:n]
        values, counts = np.unique(inner, return_counts=True)
        if np.any(counts > p):
            raise t.error("knots", f"repeat the interior knot {values[counts > p][0]:g} {counts.max()} "
                                   f"times, more than the degree {p}: the rail would break in two there")
        v["knots"] = k


def check_mount(t: Table, v: dict) -> None:
    """[[mount]]: the fields its kind takes (and no others); a rail as `check_rail`; a floor
    polygon simple (checked first), with an area, its holes inside it, turned counter-clockwise in `v`; a box
    zone with a floor extent; a tripod only under a zone, with room below the lowest height."""
    kind = v["kind"]
    floor = kind == "zone" and t.has("floor_m")
    if t.has("floor_holes_m") and not floor:
        raise t.error("floor_holes_m", "applies to a zone with floor_m (a floor polygon)")
    needs = ZONE_FLOOR if floor else MOUNT_NEEDS[kind]
    allowed = needs + (("degree", "weights", "knots") if kind == "rail" else ())
    for key in ("control_points_m", "degree", "weights", "knots", "box_min_m", "box_max_m", "position_m") + ZONE_FLOOR:
        if t.has(key) and key not in allowed:
            raise t.error(key, f"does not apply to a {kind} mount{' with floor_m' if floor else ''} "
                               f"(it takes {', '.join(allowed)})")
    for key in needs:
        if not t.has(key):
            raise t.error(key, f"is required for a {kind} mount, e.g. {MOUNT_EXAMPLES[key]}")
    if t.has("tripod") and kind != "zone":
        raise t.error("tripod", f"only a zone mount stands on a tripod (this one is {kind}): move "
                                "[mount.tripod] under a zone mount or drop it")
    if kind == "rail":
        v["degree"] = v["degree"] or 1
        check_rail(t, v)
    elif floor:
        corners = v["floor"]
        x, y = corners[:, 0], corners[:, 1]
        area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
        if not _is_simple(corners):   # before the area: a symmetric bow-tie's signed area is 0
            raise t.error("floor_m", "must be a simple polygon: two of its edges cross (list the "
                                     "corners in order around the area)")
        if abs(area) < 1e-6:
            raise t.error("floor_m", "the zone has no floor area: its corners are on one line or repeated")
        corners = corners if area > 0 else corners[::-1]
        for k, hole in enumerate(v["floor_holes"] or ()):
            if not _is_simple(hole) or abs(_signed_area(hole)) < 1e-6:
                raise t.error("floor_holes_m", f"hole {k} must be a simple polygon with an area")
            if not all(inside_floor(corners, p) for p in hole):
                raise t.error("floor_holes_m", f"hole {k} must lie inside floor_m")
        if v["height"][1] < v["height"][0]:
            raise t.error("height_m", f"must be [low, high] with low <= high (got {list(v['height'])})")
        v["floor"] = corners
    elif kind == "zone":
        lo, hi = v["box_min"], v["box_max"]
        if np.any(hi < lo):
            raise t.error("box_max_m", f"must be >= box_min_m on every axis (got {hi.tolist()} "
                                       f"against {lo.tolist()})")
        if hi[0] <= lo[0] or hi[1] <= lo[1]:
            raise t.error("box_max_m", "the zone has no floor area: give it an extent in both x "
                                       "and y (box_min_m < box_max_m), or use a rail or fixed mount")
    tripod = v.get("tripod")
    if tripod is not None:
        lowest = float(v["height"][0] if floor else v["box_min"][2])
        if tripod.floor_z + tripod.head >= lowest:
            raise t.error("tripod.floor_z_m", f"= {tripod.floor_z:g} m leaves no room for the tripod "
                                              f"under the zone's lowest camera height {lowest:g} m "
                                              f"(head_m = {tripod.head:g} m): lower floor_z_m or "
                                              "raise the zone")


def check_keep_out(t: Table, v: dict) -> None:
    """[[keep_out]]: box_max_m above box_min_m on every axis."""
    if np.any(v["box_min"] >= v["box_max"]):
        raise t.error("box_max_m", "must be greater than box_min_m on every axis")


def _off_zone(mount: MountSpec, position: np.ndarray) -> str:
    """Why `position` is not in zone `mount`, and the fix: in one of its floor's holes, off its
    floor polygon, or outside its box (heights included)."""
    box = f"({mount.low.tolist()} to {mount.high.tolist()})"
    inside_box = not (np.any(position < mount.low - 1e-9) or np.any(position > mount.high + 1e-9))
    if inside_box and mount.floor is not None:
        for k, hole in enumerate(mount.floor_holes or ()):
            if inside_floor(hole, position[:2], -1e-9):
                return (f"in hole {k} of the floor of zone {mount.name!r} (floor_holes_m); move the "
                        "camera onto the floor, off its holes")
        return f"off the floor polygon of zone {mount.name!r} (floor_m); move the camera onto it"
    return f"outside zone {mount.name!r} {box}; move the camera into it"


def resolve_mounts(values: dict, tables: dict, path: Path) -> None:
    """Rail mounts become rails (a camera on one sits on that rail); a camera on a fixed mount
    takes its position, one in a zone its position_m (default: the zone's centre), checked to be
    inside. Runs before the Experiment is built, so the parsed experiment has one form."""
    rails = {r.name for r in values["rails"]}
    clash = rails & {m.name for m in values["mounts"]}
    if clash:
        raise ConfigError(path, "mount", f"{sorted(clash)[0]!r} names both a [[rail]] and a "
                                         "[[mount]]; rename one")
    as_rails = [m for m in values["mounts"] if m.kind == "rail"]
    values["rails"] = values["rails"] + tuple(
        RailSpec(name=m.name, control_points=m.control_points, degree=m.degree, weights=m.weights,
                 knots=m.knots)
        for m in as_rails)
    mounts = {m.name: m for m in values["mounts"] if m.kind != "rail"}
    values["mounts"] = tuple(mounts.values())
    rail_names = rails | {m.name for m in as_rails}
    specs = []
    for spec, t in zip(values["camera_specs"], tables["camera"]):
        name = spec.mount
        if name is not None and name in rail_names:
            if not t.has("u"):
                raise t.error("u", "is required for a camera on a rail mount (0 to 1)")
            if not 0.0 <= spec.u <= 1.0:
                points = next(r.control_points for r in values["rails"] if r.name == name)
                raise t.error("u", f"= {spec.u} is off rail mount {name!r}: the rail parameter runs "
                                   f"from 0 to 1{nurbs.off_rail_hint(points, spec.u)}")
            spec = replace(spec, rail=name, mount=None)
        elif name is not None:
            mount = mounts.get(name)
            if mount is None:
                known = sorted(rail_names | set(mounts))
                raise t.error("mount", f"no [[mount]] or [[rail]] named {name!r} (known: "
                                       f"{', '.join(known) or 'none'})")
            if t.has("u") or np.any(spec.offset != 0):
                raise t.error("u" if t.has("u") else "offset_m", "only applies to a camera on a rail")
            if mount.kind == "fixed":
                if spec.position is not None and np.linalg.norm(spec.position - mount.position) > 1e-6:
                    raise t.error("position_m", f"differs from fixed mount {name!r} at "
                                                f"{mount.position.tolist()}; drop position_m")
                spec = replace(spec, position=mount.position)
            else:
                centre = (mount.low + mount.high) / 2
                if mount.floor is not None:
                    centre[:2] = mount.floor.mean(axis=0)
                if spec.position is None and not mount.inside(centre[:2]):
                    raise t.error("position_m", f"is required on zone {name!r}: its centroid "
                                                f"{np.round(centre, 4).tolist()} is not on its floor (a ring)")
                position = centre if spec.position is None else spec.position
                if (np.any(position < mount.low - 1e-9) or np.any(position > mount.high + 1e-9)
                        or not mount.inside(position[:2])):
                    raise t.error("position_m", f"{position.tolist()} is {_off_zone(mount, position)}")
                spec = replace(spec, position=position)
        specs.append(spec)
    values["camera_specs"] = tuple(specs)
