"""The calibration session: where the target stands in each image, and which camera sees it.

A pose places the target frame (`vdo.calib.target`) in the world: X_world = o + R_t X_target
(R_t's columns are the target's axes in the world). A camera sees a pose when every point of the
pattern's outline (the outer squares' corners) projects inside its image
with `EDGE_PX` to spare, the target lies in front of it, and the printed face turns towards it by
less than `MAX_VIEW_ANGLE_DEG`.

Generated poses (`generate`): for each camera, `poses_per_camera` poses at its working distance
(the median depth of the region samples inside its field, or [calibration] distances_m, cycled),
their centres spread over the field by the R2 sequence (the whole field, less the target's half
size), each tilted by up to tilt_deg about an axis that turns by the golden angle from pose to
pose, and turned in-plane by up to `ROLL_DEG` (a draw seeded by [calibration] seed, the camera or
pair and the pose's index); for each stereo pair, `shared_poses` poses about
the point the two optical axes pass closest to, facing the bisector of the two viewing
directions, tilted by up to half tilt_deg, so that both cameras see them (extrinsics).

Every pose depends on its index k alone, never on the count: the session of n poses per camera is
the first n poses of every larger one (nested sessions). Adding a pose adds rows to the
calibration's least squares, so J^T J only grows and the parameters' covariance
sigma_det^2 (J^T J)^-1 only shrinks (Loewner order): the planner's curve (`vdo.calib.planner`)
falls with every image added. The R2 sequence (k alpha_1, k alpha_2) mod 1 with
alpha_i = phi_2^-i, phi_2 = 1.32471795724... the plastic number (the real root of
x^3 = x + 1), spreads every prefix evenly (Roberts 2018), which a Fibonacci lattice, whose
points move with n, does not.

`check` refuses, before anything is rendered, a session that cannot calibrate: a target larger
than a camera's field, a camera that sees fewer than `MIN_VIEWS` poses, a camera whose views are
all parallel planes (Zhang's method cannot separate the focal length from the distance), a stereo
pair that shares no pose, squares too small to detect at the render scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vdo.calib.target import MARGIN_PITCHES, Target
from vdo.core.errors import ConfigError
from vdo.formats.export import PairSyntax
from vdo.scene import cameras_of

EDGE_PX = 4.0                # the pattern's outline stays this far inside the image
MAX_VIEW_ANGLE_DEG = 70.0    # a print seen more obliquely than this is not detected reliably
MIN_VIEWS = 3                # Zhang: at least 3 views of a plane for 4 intrinsics + distortion
MIN_NORMAL_SPREAD_DEG = 5.0  # views whose target normals all lie within this are degenerate
MIN_SQUARE_PX = 8.0          # smallest pitch in pixels the detectors find reliably
ROLL_DEG = 15.0              # largest in-plane turn of a generated pose
GOLDEN = math.pi * (3.0 - math.sqrt(5.0))   # golden angle, rad
PLASTIC = 1.324717957244746    # the plastic number phi_2, the real root of x^3 = x + 1
# how an experiment file names the pairs to calibrate (the messages of `stereo_names`, the planner's)
STEREO_PAIR_TABLE = PairSyntax('[[stereo_pair]] cameras = ["FIRST", "SECOND"]',
                               '[[stereo_pair]] cameras = ["{first}", "{second}"]')


@dataclass(frozen=True)
class Pose:
    """The target in the world: X = origin + R X_target."""

    R: np.ndarray
    origin: np.ndarray

    def world(self, points: np.ndarray) -> np.ndarray:
        return self.origin + points @ self.R.T

    @property
    def front(self) -> np.ndarray:
        """The printed face's normal in the world (the target's -z)."""
        return -self.R[:, 2]


@dataclass(frozen=True)
class Session:
    """The poses and, per camera name, the indices of the poses it sees (ascending)."""

    target: Target
    poses: tuple[Pose, ...]
    views: dict
    pairs: tuple[tuple[str, str], ...]


def outline(target: Target) -> np.ndarray:
    """(8, 3) points of the pattern's outline in the target frame: the corners and edge middles of
    the region the detector needs (the outer squares)."""
    low, high = target.extent
    low = low + MARGIN_PITCHES * target.pitch
    high = high - MARGIN_PITCHES * target.pitch
    xs, ys = (low[0], (low[0] + high[0]) / 2, high[0]), (low[1], (low[1] + high[1]) / 2, high[1])
    return np.array([(x, y, 0.0) for x in xs for y in ys if (x, y) != (xs[1], ys[1])])


def sees(camera, target: Target, pose: Pose) -> bool:
    """Whether `camera` sees the whole pattern at `pose` (module docstring)."""
    X = pose.world(outline(target))
    depth = (X - camera.position) @ camera.optical_axis
    if np.any(depth <= 0):
        return False
    to_camera = camera.position - pose.world(target.centre[None])[0]
    cos = pose.front @ to_camera / np.linalg.norm(to_camera)
    if cos <= math.cos(math.radians(MAX_VIEW_ANGLE_DEG)):
        return False
    uv = camera.project(X)
    return bool(np.all((uv[:, 0] >= EDGE_PX) & (uv[:, 0] <= camera.width - 1 - EDGE_PX)
                       & (uv[:, 1] >= EDGE_PX) & (uv[:, 1] <= camera.height - 1 - EDGE_PX)))


def _rot(axis, angle) -> np.ndarray:
    """Rotation by `angle` (rad) about the unit `axis` (Rodrigues)."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def facing(target: Target, centre, axes: np.ndarray, tilt: float, heading: float, roll: float) -> Pose:
    """The pose whose pattern centre is at `centre`, facing a viewer whose axes (rows x, y, z of a
    camera: z the viewing direction) are `axes`, then tilted by `tilt` about the in-plane axis at
    angle `heading` and turned by `roll` about the viewing direction (radians)."""
    R0 = np.asarray(axes, dtype=float).T           # target x, y, z = viewer x, y, z
    axis = math.cos(heading) * R0[:, 0] + math.sin(heading) * R0[:, 1]
    R = _rot(axis, tilt) @ _rot(R0[:, 2], roll) @ R0
    return Pose(R=R, origin=np.asarray(centre, dtype=float) - R @ target.centre)


def working_distance(camera, points: np.ndarray) -> float | None:
    """Median depth (m) of the `points` (N, 3) that project inside the camera's image, None when
    none does."""
    depth = (points - camera.position) @ camera.optical_axis
    ahead = depth > 0
    if not ahead.any():
        return None
    uv = camera.project(points[ahead])
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1)
    return float(np.median(depth[ahead][inside])) if inside.any() else None


def field_width(camera, distance: float) -> float:
    """Width (m) of the camera's field at `distance`: W / f_px x distance."""
    return camera.width / camera.focal_px * distance


def auto_pitch(spec, cameras, distances: dict) -> float:
    """[calibration] pitch_mm when given, else field_fill x the narrowest field width at the
    working distance over the sheet's width in pitches, rounded down to 0.5 mm (0.1 mm below
    2 mm)."""
    if spec.pitch is not None:
        return spec.pitch
    widest = spec.columns + 1 + 2
    width = min(field_width(c, distances[c.name]) for c in cameras)
    pitch = spec.field_fill * width / widest
    step = 0.5e-3 if pitch >= 2e-3 else 0.1e-3
    return max(step, math.floor(pitch / step) * step)


def spread(k: int) -> tuple[float, float]:
    """Point k of the R2 sequence on [-1, 1]^2, started at the centre: 2 ((1/2 + k alpha) mod 1)
    - 1 with alpha = (1/phi_2, 1/phi_2^2) (module docstring); every prefix is evenly spread."""
    a = (0.5 + k / PLASTIC) % 1.0
    b = (0.5 + k / PLASTIC ** 2) % 1.0
    return 2 * a - 1, 2 * b - 1


def _roll(seed: int, owner: int, k: int) -> float:
    """The in-plane turn of pose k of camera or pair `owner`, rad: uniform in +-ROLL_DEG, drawn
    from a generator seeded by (seed, owner, k) alone, so that sessions nest."""
    return math.radians(ROLL_DEG) * float(np.random.default_rng([seed, 7, owner, k]).uniform(-1, 1))


def _camera_poses(target: Target, camera, distances, count: int, tilt: float, seed: int,
                  owner: int) -> list[Pose]:
    half = 0.5 * math.hypot(*target.size)
    out = []
    axes = camera.R
    for k in range(count):
        d = distances[k % len(distances)]
        a, b = spread(k)
        # the centre's room in normalised coordinates: the field less the target's half size
        room_x = max(0.0, camera.width / 2 / camera.focal_px - half / d)
        room_y = max(0.0, camera.height / 2 / camera.focal_px - half / d)
        ray = np.array([a * room_x, b * room_y, 1.0])
        centre = camera.position + d * (axes.T @ ray)
        t = tilt * (0.5 + 0.5 * ((k * 0.618034) % 1.0))
        out.append(facing(target, centre, axes, t, k * GOLDEN, _roll(seed, owner, k)))
    return out


def _closest_point(a, b) -> np.ndarray:
    """The midpoint of the shortest segment between the optical axes of cameras a and b (their
    mean working point when the axes are nearly parallel)."""
    p, q, u, v = a.position, b.position, a.optical_axis, b.optical_axis
    w = p - q
    uv = u @ v
    den = 1 - uv * uv
    if den < 1e-6:
        return None
    s = (uv * (v @ w) - (u @ w)) / den
    t = ((v @ w) - uv * (u @ w)) / den
    return 0.5 * (p + s * u + q + t * v)


def _pair_poses(target: Target, a, b, da: float, db: float, count: int, tilt: float, seed: int,
                owner: int) -> list[Pose]:
    centre = _closest_point(a, b)
    if centre is None:
        centre = 0.5 * (a.position + da * a.optical_axis + b.position + db * b.optical_axis)
    z = (centre - a.position) / np.linalg.norm(centre - a.position) + \
        (centre - b.position) / np.linalg.norm(centre - b.position)
    z /= np.linalg.norm(z)
    x = a.R[0] + b.R[0]
    x -= (x @ z) * z
    x /= np.linalg.norm(x)
    axes = np.array([x, np.cross(z, x), z])
    d = min(np.linalg.norm(centre - a.position), np.linalg.norm(centre - b.position))
    room = 0.25 * min(field_width(a, d), field_width(b, d)) - 0.5 * math.hypot(*target.size)
    room = max(room, 0.0)
    out = []
    for k in range(count):
        u, v = spread(k)
        c = centre + room * (u * axes[0] + v * axes[1])
        t = 0.5 * tilt * (0.5 + 0.5 * ((k * 0.618034) % 1.0))
        out.append(facing(target, c, axes, t, k * GOLDEN, _roll(seed, owner, k)))
    return out


def build(spec, cameras, distances: dict, pairs, path) -> Session:
    """The session of [calibration] `spec` for `cameras` (working distances by name, stereo
    `pairs` as name tuples): explicit poses, or generated ones (module docstring). Not checked:
    `check` does that."""
    target = Target(spec.target, spec.rows, spec.columns, auto_pitch(spec, cameras, distances))
    by_name = {c.name: c for c in cameras}
    if spec.pose_centres is not None:
        poses = []
        for centre, normal in zip(spec.pose_centres, spec.pose_normals):
            z = -np.asarray(normal)                       # target z points away from the print
            up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
            x = np.cross(up, z)
            x /= np.linalg.norm(x)
            axes = np.array([x, np.cross(z, x), z])
            poses.append(facing(target, centre, axes, 0.0, 0.0, 0.0))
    else:
        poses = []
        for i, cam in enumerate(cameras):
            ds = spec.distances or (distances[cam.name],)
            poses += _camera_poses(target, cam, ds, spec.poses_per_camera, spec.tilt, spec.seed, i)
        for j, (a, b) in enumerate(pairs):
            poses += _pair_poses(target, by_name[a], by_name[b], distances[a], distances[b],
                                 spec.shared_poses, spec.tilt, spec.seed, len(cameras) + j)
    views = {c.name: [k for k, p in enumerate(poses) if sees(c, target, p)] for c in cameras}
    return Session(target=target, poses=tuple(poses), views=views, pairs=tuple(pairs))


def check(session: Session, spec, cameras, distances: dict, scale: float, path) -> None:
    """Refuse a session that cannot calibrate (module docstring), naming the [calibration] field
    and the fix; nothing is rendered before this passes."""
    target = session.target
    where = "calibration.pose_centres_m" if spec.pose_centres is not None else "calibration.poses_per_camera"
    for cam in cameras:
        d = min(spec.distances or (distances[cam.name],))
        w, h = target.size
        span_px = (w * cam.focal_px / d, h * cam.focal_px / d)
        if span_px[0] > cam.width or span_px[1] > cam.height:
            raise ConfigError(path, "calibration.pitch_mm",
                              f"the {w * 1e3:.0f} x {h * 1e3:.0f} mm target spans {span_px[0]:.0f} x "
                              f"{span_px[1]:.0f} px at {d:.3g} m, more than camera {cam.name!r}'s "
                              f"{cam.width} x {cam.height} px field: lower pitch_mm, rows or columns, "
                              "or raise distances_m")
        square = target.pitch * cam.focal_px * scale / max(spec.distances or (distances[cam.name],))
        if square < MIN_SQUARE_PX:
            raise ConfigError(path, "calibration.pitch_mm",
                              f"a pitch of {target.pitch * 1e3:.3g} mm is {square:.1f} px in camera "
                              f"{cam.name!r} at render scale {scale:g}, under {MIN_SQUARE_PX:g} px: "
                              "raise pitch_mm or the render scale (--scale)")
        seen = session.views[cam.name]
        if len(seen) < MIN_VIEWS:
            raise ConfigError(path, where,
                              f"camera {cam.name!r} sees the whole target in {len(seen)} of "
                              f"{len(session.poses)} poses, fewer than {MIN_VIEWS}: add poses in its "
                              "field (or lower tilt_deg, rows/columns)")
        normals = np.array([session.poses[k].front for k in seen])
        spread = math.degrees(math.acos(float(np.clip((normals @ normals.T).min(), -1.0, 1.0))))
        if spread < MIN_NORMAL_SPREAD_DEG:
            raise ConfigError(path, "calibration.tilt_deg" if spec.pose_centres is None else
                              "calibration.pose_normals",
                              f"camera {cam.name!r}'s {len(seen)} views are all parallel planes "
                              f"(normals within {spread:.1f} deg): Zhang's calibration cannot tell the "
                              f"focal length from the distance; tilt the target (>= "
                              f"{2 * MIN_NORMAL_SPREAD_DEG:g} deg between views)")
    for a, b in session.pairs:
        if not set(session.views[a]) & set(session.views[b]):
            raise ConfigError(path, "calibration.shared_poses",
                              f"no pose is seen by both cameras {a!r} and {b!r} of a stereo pair, "
                              "so their relative pose cannot be calibrated: raise shared_poses or "
                              "give an explicit pose in front of both")


@dataclass(frozen=True, eq=False)
class Planned:
    """A checked session with what it was built from: the full-size cameras, their working
    distances (m, by name), the experiment's `vdo.state.Geometry`."""

    session: Session
    cameras: tuple
    distances: dict
    geometry: object


def stereo_names(exp, cameras, geometry, visibility=None) -> list[tuple[str, str]]:
    """The stereo pairs to calibrate: the declared [[stereo_pair]]s, else the cameras assigned a
    common region (`vdo.formats.export.default_pairs`, on `visibility`: the layout's ray cast,
    cast here when not given; its messages name [[stereo_pair]], `STEREO_PAIR_TABLE`)."""
    if exp.stereo_pairs:
        return [tuple(p.cameras) for p in exp.stereo_pairs]
    from vdo.formats.export import default_pairs
    from vdo.state import layout_state

    if visibility is None:
        visibility = layout_state(geometry, cameras, predict_fields=False).visibility
    return [(p.first.name, p.second.name)
            for p in default_pairs(exp, cameras, visibility, geometry.samples,
                                   syntax=STEREO_PAIR_TABLE)]


def plan(exp, scale: float, geometry=None, spec=None, pairs=None) -> Planned:
    """The experiment's calibration session, built and checked (`build`, `check`) with `spec`
    (default [calibration]) and `pairs` (default `stereo_names`); raises ConfigError before
    anything is rendered."""
    from vdo.state import prepare

    spec = spec or exp.calibration
    geometry = geometry or prepare(exp)
    cameras = tuple(cameras_of(exp.camera_specs, exp.rails))
    distances = {}
    for cam in cameras:
        d = working_distance(cam, geometry.samples.points)
        if d is None:
            raise ConfigError(exp.path, f'camera "{cam.name}"',
                              "sees no region sample, so it has no working distance for the "
                              "calibration target: aim it at a region or give [calibration] distances_m")
        distances[cam.name] = d
    pairs = stereo_names(exp, cameras, geometry) if pairs is None else pairs
    session = build(spec, cameras, distances, pairs, exp.path)
    check(session, spec, cameras, distances, scale, exp.path)
    return Planned(session=session, cameras=cameras, distances=distances, geometry=geometry)
