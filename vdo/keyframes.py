"""The test at step k of its load path: rigid poses of mesh groups and nodal displacements of the
specimen, applied to a prepared geometry.

A load path (the `[load_path]` table of an experiment) names mesh **groups** that move rigidly
(a hexapod's platform with its end-effector, a crosshead) and reads their poses per step from a
CSV file, one row per (step, group):

    step, group, x_mm, y_mm, z_mm, rx_deg, ry_deg, rz_deg

Translations may be given in `_m` or `_mm`, rotations in `_deg` or `_rad` (the header says which;
every column needs its unit). A pose moves a point X of the group to

    X' = p + R (X - p) + T,      R = Rz(rz) Ry(ry) Rx(rx)

(rotations about the fixed world axes x, then y, then z; p the group's `pivot_m`, T the
translation). A step with no row for a group leaves that group at rest.

Optionally the specimen deforms: a second CSV gives nodal displacements per step,

    step, x_m, y_m, z_m, ux_mm, uy_mm, uz_mm

(node coordinates in world metres at rest; displacements in `_m` or `_mm`). Each node must match a
vertex of the specimen mesh within `NODE_TOLERANCE` (and moves every copy of it: STL files repeat
vertices per triangle); vertices with no node stay at rest. Surface
samples move with their triangle (barycentric interpolation of its vertices' displacements) and
keep their rest normals and tangents (the rotations of a test's strains are far below the
incidence limits that the normals feed).
"""

from __future__ import annotations

import csv
import logging
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .errors import ConfigError

logger = logging.getLogger(__name__)

NODE_TOLERANCE = 1e-4         # m: a displacement node matches a mesh vertex this close
MAX_ROTATION_DEG = 360.0      # |rotation| beyond a full turn is a unit mistake
SMALL_ROTATION_DEG = 0.2      # all rotations below this in a _deg column: likely radians
_UNITS = {"m": 1.0, "mm": 1e-3, "deg": math.pi / 180.0, "rad": 1.0}


@dataclass(frozen=True)
class Pose:
    """A rigid motion X' = pivot + R (X - pivot) + translation (metres)."""

    rotation: np.ndarray      # (3, 3)
    translation: np.ndarray   # (3,) m
    pivot: np.ndarray         # (3,) m

    def move(self, points: np.ndarray) -> np.ndarray:
        return self.pivot + (np.asarray(points) - self.pivot) @ self.rotation.T + self.translation

    def turn(self, vectors: np.ndarray) -> np.ndarray:
        return np.asarray(vectors) @ self.rotation.T


def rotation_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    """R = Rz(rz) Ry(ry) Rx(rx), radians: about world x first, then y, then z."""
    cx, sx, cy, sy, cz, sz = (math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry),
                              math.cos(rz), math.sin(rz))
    rot_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rot_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rot_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rot_z @ rot_y @ rot_x


@dataclass(frozen=True, eq=False)
class LoadPath:
    """Steps of a test: per step, a pose per moving group and the specimen's vertex
    displacements (or None)."""

    steps: tuple[int, ...]
    groups: dict              # group name -> tuple of mesh names
    poses: dict               # (step, group) -> Pose
    deformed_mesh: str | None = None
    displacements: dict | None = None   # step -> (n_vertices, 3) m

    def mesh_pose(self, step: int, mesh: str) -> Pose | None:
        """The pose of `mesh` at `step` (None: at rest). A mesh in a declared group and also
        posed under its own name is refused when the file is read (`read_poses`)."""
        for group, meshes in self.groups.items():
            if mesh in meshes and (step, group) in self.poses:
                return self.poses[(step, group)]
        return None


# --------------------------------------------------------------------------------------------
# Reading the CSV files
# --------------------------------------------------------------------------------------------
def _columns(header: list[str], wanted: tuple[str, ...], units: tuple[str, ...], file: Path):
    """Map each wanted quantity (e.g. "x") to (column index, factor to SI) from a header such as
    `x_mm`; ConfigError naming the missing column and the units it may take."""
    found = {}
    for want in wanted:
        hits = [(i, m.group(1)) for i, h in enumerate(header)
                if (m := re.fullmatch(rf"{want}_({'|'.join(units)})", h.strip()))]
        if len(hits) != 1:
            raise ConfigError(file, f"column {want}", f"needs exactly one column {want}_<unit> with "
                                                      f"unit one of {', '.join(units)} "
                                                      f"(header: {', '.join(header)})")
        found[want] = (hits[0][0], _UNITS[hits[0][1]], hits[0][1])
    return found


def _rows(file: Path):
    try:
        with open(file, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(file, "", f"cannot be read as a UTF-8 CSV file ({exc})") from None
    if len(rows) < 2:
        raise ConfigError(file, "", "needs a header row and at least one data row")
    return [h.strip() for h in rows[0]], rows[1:]


def _number(row, index, file, line, name) -> float:
    try:
        value = float(row[index])
    except (IndexError, ValueError):
        raise ConfigError(file, f"row {line}", f"column {name}: expected a number, got "
                                               f"{row[index] if index < len(row) else 'nothing'!r}") from None
    if not math.isfinite(value):
        raise ConfigError(file, f"row {line}", f"column {name}: {value} is not finite")
    return value


def _step(row, index, file, line) -> int:
    value = _number(row, index, file, line, "step")
    if value != int(value) or value < 1:
        raise ConfigError(file, f"row {line}", f"step must be a whole number >= 1 (got {row[index]!r}; "
                                               "step 0 is the rest state)")
    return int(value)


def read_poses(file: Path, groups: dict, pivots: dict) -> dict:
    """{(step, group): Pose} from a pose CSV (module docstring)."""
    header, rows = _rows(file)
    if "step" not in header or "group" not in header:
        raise ConfigError(file, "header", f"needs columns step and group (got {', '.join(header)})")
    i_step, i_group = header.index("step"), header.index("group")
    lin = _columns(header, ("x", "y", "z"), ("m", "mm"), file)
    rot = _columns(header, ("rx", "ry", "rz"), ("deg", "rad"), file)
    poses, angles, posed = {}, [], {}
    for line, row in enumerate(rows, start=2):
        step = _step(row, i_step, file, line)
        group = row[i_group].strip() if i_group < len(row) else ""
        if group not in groups:
            raise ConfigError(file, f"row {line}", f"group {group!r} is neither a [[group]] nor a [[mesh]] "
                                                   f"(groups: {', '.join(sorted(groups))})")
        if (step, group) in poses:
            raise ConfigError(file, f"row {line}", f"a second pose for group {group!r} at step {step}")
        twice = [m for m in groups[group] if m in posed.setdefault(step, set())]
        if twice:
            raise ConfigError(file, f"row {line}", f"mesh {twice[0]!r} is already posed at step {step} "
                                                   "(by another group that holds it)")
        posed[step] |= set(groups[group])
        t = np.array([_number(row, lin[a][0], file, line, f"{a}_{lin[a][2]}") * lin[a][1] for a in "xyz"])
        r = [_number(row, rot[a][0], file, line, f"{a}_{rot[a][2]}") for a in ("rx", "ry", "rz")]
        unit = rot["rx"][2]
        limit = MAX_ROTATION_DEG if unit == "deg" else math.radians(MAX_ROTATION_DEG)
        if max(abs(v) for v in r) > limit:
            raise ConfigError(file, f"row {line}", f"rotation {max(r, key=abs)} {unit} is more than a "
                                                   f"full turn: are the rotations in degrees? Name the "
                                                   f"columns rx_deg, ry_deg, rz_deg")
        angles += r
        factor = rot["rx"][1]
        poses[(step, group)] = Pose(rotation_xyz(*(v * factor for v in r)), t, pivots[group])
    nonzero = [abs(a) for a in angles if a != 0]
    if rot["rx"][2] == "deg" and nonzero and max(nonzero) < SMALL_ROTATION_DEG:
        logger.warning("%s: every rotation is below %g deg; if they are radians, name the columns "
                       "rx_rad, ry_rad, rz_rad", file, SMALL_ROTATION_DEG)
    return poses


def read_displacements(file: Path, vertices: np.ndarray, mesh: str) -> dict:
    """{step: (n_vertices, 3) displacement in m} from a nodal displacement CSV (module docstring):
    each node matched to the mesh vertex within NODE_TOLERANCE."""
    from scipy.spatial import cKDTree

    header, rows = _rows(file)
    if "step" not in header:
        raise ConfigError(file, "header", f"needs a column step (got {', '.join(header)})")
    i_step = header.index("step")
    pos = _columns(header, ("x", "y", "z"), ("m", "mm"), file)
    disp = _columns(header, ("ux", "uy", "uz"), ("m", "mm"), file)
    tree = cKDTree(vertices)
    out: dict[int, np.ndarray] = {}
    for line, row in enumerate(rows, start=2):
        step = _step(row, i_step, file, line)
        x = np.array([_number(row, pos[a][0], file, line, f"{a}_{pos[a][2]}") * pos[a][1] for a in "xyz"])
        u = np.array([_number(row, disp[a][0], file, line, f"{a}_{disp[a][2]}") * disp[a][1]
                      for a in ("ux", "uy", "uz")])
        matches = tree.query_ball_point(x, NODE_TOLERANCE)   # all copies (STL repeats vertices)
        if not matches:
            distance = tree.query(x)[0]
            raise ConfigError(file, f"row {line}", f"node {x.tolist()} m is {distance * 1e3:.2f} mm "
                                                   f"from the nearest vertex of mesh {mesh!r}: the "
                                                   "nodes must be the mesh's vertices (world metres, at rest)")
        out.setdefault(step, np.zeros_like(vertices))[matches] = u
    return out


# --------------------------------------------------------------------------------------------
# Applying a step to a geometry
# --------------------------------------------------------------------------------------------
def _barycentric_displacement(points, triangles, displaced) -> np.ndarray:
    """Displacement at `points` (N, 3) lying on `triangles` (T, 3, 3): barycentric interpolation
    of the corner displacements `displaced` (T, 3, 3) of the triangle each point lies on."""
    out = np.zeros_like(points)
    todo = np.ones(len(points), bool)
    for tri, d in zip(triangles, displaced):
        e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
        gram = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
        if abs(np.linalg.det(gram)) < 1e-30:
            continue
        rel = points[todo] - tri[0]
        lam = np.linalg.solve(gram, np.stack([rel @ e1, rel @ e2])).T       # (n, 2)
        inside = (lam >= -1e-6).all(axis=1) & (lam.sum(axis=1) <= 1 + 1e-6)
        idx = np.flatnonzero(todo)[inside]
        l1, l2 = lam[inside, :1], lam[inside, 1:]
        out[idx] = (1 - l1 - l2) * d[0] + l1 * d[1] + l2 * d[2]
        todo[idx] = False
    return out


def at_step(geometry, load_path: LoadPath, step: int):
    """The geometry at `step`: every mesh of a moving group posed, the specimen's vertices
    displaced, and the surface samples moved with the mesh they lie on (a new `Geometry`)."""
    from .scene import SceneMesh

    exp = geometry.experiment
    samples = geometry.samples
    points, normals = samples.points.copy(), samples.normals.copy()
    t_u, t_v = samples.tangent_u.copy(), samples.tangent_v.copy()
    region_mesh = np.array([exp.regions[k].mesh for k in range(len(exp.regions))])[samples.region]
    meshes = []
    for mesh in geometry.meshes:
        vertices = mesh.vertices
        on_mesh = region_mesh == mesh.name
        u = (load_path.displacements or {}).get(step) if mesh.name == load_path.deformed_mesh else None
        if u is not None:
            for k, faces in enumerate(geometry.region_faces):
                if exp.regions[k].mesh == mesh.name:
                    on_region = samples.region == k
                    tri = mesh.faces[faces.faces]
                    points[on_region] += _barycentric_displacement(points[on_region], vertices[tri], u[tri])
            vertices = vertices + u
        pose = load_path.mesh_pose(step, mesh.name)
        if pose is not None:
            vertices = pose.move(vertices)
            points[on_mesh] = pose.move(points[on_mesh])
            for arr in (normals, t_u, t_v):
                arr[on_mesh] = pose.turn(arr[on_mesh])
        meshes.append(mesh if vertices is mesh.vertices else SceneMesh(mesh.name, mesh.role, vertices, mesh.faces))
    moved = replace(samples, points=points, normals=normals, tangent_u=t_u, tangent_v=t_v)
    return replace(geometry, meshes=tuple(meshes), samples=moved)


def load_path_of(exp, meshes, poses: Path | None = None) -> LoadPath | None:
    """The experiment's `[load_path]` read from its CSV files, or None when it has none and no
    `poses` file is given. `poses` replaces the `[load_path]`'s pose file (`vdo render --series`).
    Groups are the experiment's `[[group]]` tables, and every mesh is also a group of its own name
    (pivot at the origin), so a pose file may move single meshes without declaring groups. Rows
    are checked here, before any ray is cast. `meshes`: the experiment's SceneMeshes (needed for
    the displacement nodes)."""
    spec = exp.load_path
    if not spec.active and poses is None:
        return None
    groups = {m.name: (m.name,) for m in exp.meshes}
    pivots = {name: np.zeros(3) for name in groups}
    for g in exp.groups:
        groups[g.name] = tuple(g.meshes)
        pivots[g.name] = np.asarray(g.pivot, dtype=float)
    poses = poses if poses is not None else spec.poses
    displacements = None
    if spec.displacements is not None:
        mesh = next(m for m in meshes if m.name == spec.deformed_mesh)
        displacements = read_displacements(spec.displacements, mesh.vertices, mesh.name)
    table = read_poses(Path(poses), groups, pivots) if poses is not None else {}
    steps = sorted({step for step, _ in table} | set(displacements or {}))
    return LoadPath(tuple(steps), groups, table, spec.deformed_mesh, displacements)
