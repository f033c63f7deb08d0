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

Or the displacements come from a finite-element model as VTK XML files (`vdo.core.vtkxml`): a `.vtu` or
`.vtp` (one step, step 1) or a `.pvd` collection (its DataSets in the order of their timesteps
are steps 1, 2, ...; a DataSet at timestep 0 is the rest state, skipped, and must not move). The
file's points are the nodes (in the `[load_path]` `unit`, world frame, at rest) and its
displacement point array (`displacement_array`, or the one 3-component array, or the one named as
FE exporters name it, `DISPLACEMENT_NAMES`) their displacements. The nodes must lie on the
specimen mesh's surface (within `SURFACE_TOLERANCE`: export the FE model's outer surface, e.g.
ParaView's Extract Surface): a file with nodes off it is refused, naming how many and the largest
distance (wrong unit, frame or mesh). Each mesh vertex takes the displacement of a node within
`NODE_TOLERANCE` of it, else a weighted linear least-squares fit of its `FIT_NODES` nearest nodes
(weights 1/(1 + d/h)^2, h the median node spacing), which reproduces any linear field exactly; the
surface samples then follow their triangle as above.
"""

from __future__ import annotations

import csv
import hashlib
import logging
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vdo.core.errors import ConfigError
from vdo.core.tolerances import BARYCENTRIC_SLACK

if TYPE_CHECKING:
    from vdo.config.mounts import MountSpec, RailSpec
    from vdo.config.procedure import GroupSpec, LoadPathSpec
    from vdo.config.rig import CameraSpec, MeshSpec, RegionSpec

logger = logging.getLogger(__name__)

NODE_TOLERANCE = 1e-4         # m: a displacement node matches a mesh vertex this close
SURFACE_TOLERANCE = 1e-4      # m: a VTK node lies on the mesh surface this close
FIT_NODES = 12                # nearest nodes of a VTK file fitted at a vertex with no node
DISPLACEMENT_NAMES = ("displacement", "displacements", "disp", "displ", "u", "depl")
SPHERE_CLASS = 2.0            # `_locate`: triangles' bounding spheres searched in classes of radii this
                              # factor apart (one ball search per class, at its largest radius)
SPHERE_WIDEN = 1.25           # ... each sphere's radius widened by this factor (a point a little off a
                              # triangle's plane, as a curved region's sample off its chord, still inside)
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

    @property
    def is_identity(self) -> bool:
        """Whether the pose moves nothing (the rest pose)."""
        return not np.any(self.translation != 0) and not np.any(self.rotation != np.eye(3))


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

    def step_key(self, step) -> tuple:
        """What `at_step` reads at `step`, exactly and hashable: each group's pose that is not the
        identity (its rotation and translation bytes) and a digest of the specimen's displacements
        if any is non-zero. Steps with equal keys have the same geometry (up to rounding); a step
        that moves nothing has the key of the rest state, (). Cyclic paths return to a pose many
        times (the built-in one to rest at 12 of its 24 steps), and `vdo.search.loadpath` judges each
        geometry once."""
        key = []
        for group in sorted(g for at, g in self.poses if at == step):
            pose = self.poses[(step, group)]
            if not pose.is_identity:
                key.append((group, pose.rotation.tobytes(), pose.translation.tobytes(), pose.pivot.tobytes()))
        u = (self.displacements or {}).get(step)
        if u is not None and np.any(u != 0):
            key.append(("displacement", hashlib.sha1(np.ascontiguousarray(u, dtype=float).tobytes()).hexdigest()))
        return tuple(key)


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
    """(header, [(line, row), ...]): the header and the data rows of a CSV, blank rows and `#`
    comment rows skipped, each data row with the file's line number on which it ends (what an
    editor or a spreadsheet shows as its row: the messages' "row N")."""
    try:
        with open(file, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            rows = [(reader.line_num, r) for r in reader if r and not r[0].lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(file, "", f"cannot be read as a UTF-8 CSV file ({exc})") from None
    if len(rows) < 2:
        raise ConfigError(file, "", "needs a header row and at least one data row")
    return [h.strip() for h in rows[0][1]], rows[1:]


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


def _warn_gaps(file: Path, poses: dict, steps) -> None:
    """A warning per group that has no row at a step of the load path (`steps`: the pose file's
    and the displacement file's) lying between two of its own steps where it is moved (not at
    rest): it stands at rest there (module docstring), a jump back and forth in the middle of its
    motion that a forgotten row would also give."""
    for group in sorted({g for _, g in poses}):
        own = [step for step in steps if (step, group) in poses]
        moved = [step for step in own if not poses[(step, group)].is_identity]
        gaps = [step for step in steps if (step, group) not in poses and moved
                and moved[0] < step < moved[-1]]
        if gaps:
            logger.warning("%s: group %r has no row at step(s) %s, between steps where it moves: it "
                           "stands at rest there; add its rows if it should not", file, group,
                           ", ".join(map(str, gaps[:MISSING_STEPS_SHOWN])) + (" ..." if len(gaps) > MISSING_STEPS_SHOWN else ""))


def read_poses(file: Path, groups: dict, pivots: dict) -> dict:
    """{(step, group): Pose} from a pose CSV (module docstring)."""
    header, rows = _rows(file)
    if "step" not in header or "group" not in header:
        raise ConfigError(file, "header", f"needs columns step and group (got {', '.join(header)})")
    i_step, i_group = header.index("step"), header.index("group")
    lin = _columns(header, ("x", "y", "z"), ("m", "mm"), file)
    rot = _columns(header, ("rx", "ry", "rz"), ("deg", "rad"), file)
    poses, angles, posed = {}, [], {}
    for line, row in rows:
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
    for line, row in rows:
        step = _step(row, i_step, file, line)
        x = np.array([_number(row, pos[a][0], file, line, f"{a}_{pos[a][2]}") * pos[a][1] for a in "xyz"])
        u = np.array([_number(row, disp[a][0], file, line, f"{a}_{disp[a][2]}") * disp[a][1]
                      for a in ("ux", "uy", "uz")])
        matches = tree.query_ball_point(x, NODE_TOLERANCE)   # all copies (STL repeats vertices)
        if not matches:
            distance = tree.query(x)[0]
            hint = ""
            for factor, written, right in ((1e-3, "m", "mm"), (1e3, "mm", "m")):   # a unit slip?
                if tree.query(x * factor)[0] <= NODE_TOLERANCE:
                    hint = (f"; at {factor:g} times it is a vertex: the positions are in {right}, so "
                            f"name their columns x_{right}, y_{right}, z_{right} (not _{written})")
            raise ConfigError(file, f"row {line}", f"node {x.tolist()} m is {distance * 1e3:.2f} mm "
                                                   f"from the nearest vertex of mesh {mesh!r}: the "
                                                   f"nodes must be the mesh's vertices (world metres, at rest){hint}")
        out.setdefault(step, np.zeros_like(vertices))[matches] = u
    return out


def _point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance from points p to triangles (a, b, c), all broadcast against each other (..., 3):
    the closest point on the triangle by its Voronoi regions (vertex, edge, face; Ericson,
    Real-Time Collision Detection, sec. 5.1.5)."""
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        q = a + (vb / denom)[..., None] * ab + (vc / denom)[..., None] * ac      # face region
        edges = ((vc <= 0) & (d1 >= 0) & (d3 <= 0), d1 / (d1 - d3), a, ab), \
                ((vb <= 0) & (d2 >= 0) & (d6 <= 0), d2 / (d2 - d6), a, ac), \
                ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), (d4 - d3) / ((d4 - d3) + (d5 - d6)), b, c - b)
        for mask, t, origin, direction in edges:
            q = np.where(mask[..., None], origin + t[..., None] * direction, q)
    for mask, corner in (((d1 <= 0) & (d2 <= 0), a), ((d3 >= 0) & (d4 <= d3), b), ((d6 >= 0) & (d5 <= d6), c)):
        q = np.where(mask[..., None], corner + 0 * q, q)
    q = np.where(np.isfinite(q), q, a + 0 * q)                          # degenerate triangles
    return np.linalg.norm(p - q, axis=-1)


def surface_distance(points: np.ndarray, triangles: np.ndarray, chunk: int = 1_000_000) -> np.ndarray:
    """Distance (N,) from each point (N, 3) to the nearest of `triangles` (T, 3, 3), brute force
    over chunks of `chunk` point-triangle pairs."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    out = np.empty(len(points))
    step = max(1, chunk // max(1, len(triangles)))
    for start in range(0, len(points), step):
        out[start:start + step] = _point_triangle_distance(points[start:start + step, None], a, b, c).min(axis=1)
    return out


def off_surface(points: np.ndarray, triangles: np.ndarray, tolerance: float,
                max_reported: int = 100) -> tuple[np.ndarray, float]:
    """(which points (N,) lie farther than `tolerance` from the triangles, the largest such
    distance). Triangles are grouped by size (their centroid-to-corner radius r, by powers of 2);
    a point is tested against a group's triangles whose centroid lies within `tolerance` + the
    group's largest r (any triangle nearer than `tolerance` is among them). The largest distance
    is exact over at most `max_reported` far points (those farthest from any centroid)."""
    from scipy.spatial import cKDTree

    centroids = triangles.mean(axis=1)
    radius = np.linalg.norm(triangles - centroids[:, None], axis=2).max(axis=1)
    size_class = np.floor(np.log2(np.maximum(radius, 1e-12))).astype(int)
    nearest = np.full(len(points), np.inf)
    for cls in np.unique(size_class):
        members = np.flatnonzero(size_class == cls)
        hits = cKDTree(centroids[members]).query_ball_point(points, float(radius[members].max()) + tolerance)
        counts = np.fromiter((len(h) for h in hits), int, len(points))
        if counts.sum() == 0:
            continue
        node = np.repeat(np.arange(len(points)), counts)
        tri = triangles[members[np.concatenate([np.asarray(h, int) for h in hits])]]
        d = _point_triangle_distance(points[node], tri[:, 0], tri[:, 1], tri[:, 2])
        np.minimum.at(nearest, node, d)
    far = nearest > tolerance
    if not far.any():
        return far, 0.0
    idx = np.flatnonzero(far)
    idx = idx[np.argsort(-cKDTree(centroids).query(points[idx])[0])[:max_reported]]
    return far, float(surface_distance(points[idx], triangles).max())


def _displacement_array(data, file: Path, name: str | None) -> np.ndarray:
    """The displacement point array of a VTK file: `name`, else the only 3-component array, else
    the only one named as in DISPLACEMENT_NAMES (case-insensitive)."""
    vectors = {k: v for k, v in data.arrays.items() if v.ndim == 2 and v.shape[1] == 3}
    if name is not None:
        if name not in data.arrays:
            raise ConfigError(file, "displacement_array", f"no point array {name!r} (arrays: "
                                                          f"{', '.join(data.arrays) or 'none'})")
        if name not in vectors:
            raise ConfigError(file, f"point array {name!r}", "is not a 3-component vector array")
        return vectors[name]
    named = [k for k in vectors if k.lower() in DISPLACEMENT_NAMES]
    if len(vectors) == 1 or len(named) == 1:
        return vectors[named[0] if len(named) == 1 else next(iter(vectors))]
    raise ConfigError(file, "displacement_array", f"cannot tell which point array holds the "
                                                  f"displacements (3-component arrays: "
                                                  f"{', '.join(vectors) or 'none'}): name it in "
                                                  f"[load_path] displacement_array")


def _vtk_steps(file: Path) -> list[tuple[int, Path]]:
    """(step, .vtu/.vtp file) of a VTK displacement file: step 1 for one file; a .pvd's DataSets
    by timestep as steps 1, 2, ..., a timestep-0 DataSet (the rest state) kept as step 0."""
    from vdo.core.vtkxml import collection

    if file.suffix.lower() != ".pvd":
        return [(1, file)]
    sets = collection(file)
    rest = [f for t, f in sets if t == 0]
    moving = [f for t, f in sets if t != 0]
    return [(0, f) for f in rest] + [(k, f) for k, f in enumerate(moving, start=1)]


def read_vtk_displacements(file: Path, vertices: np.ndarray, faces: np.ndarray, mesh: str,
                           unit: str, array: str | None = None) -> dict:
    """{step: (n_vertices, 3) displacement in m} from VTK XML nodal displacements (module
    docstring): nodes checked on the mesh surface, every vertex given its node's displacement or
    the fit of its nearest nodes."""
    from scipy.spatial import cKDTree

    from vdo.config.rig import UNITS
    from vdo.core.vtkxml import read_points

    file = Path(file)
    scale = UNITS[unit]
    triangles = vertices[faces]
    out, nodes_seen = {}, None
    for step, path in _vtk_steps(file):
        data = read_points(path)
        nodes = data.points * scale
        u = _displacement_array(data, path, array) * scale
        bad = ~np.isfinite(u).all(axis=1) | ~np.isfinite(nodes).all(axis=1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ConfigError(path, f"node {k}", f"displacement {u[k].tolist()} or position is not "
                                                 f"finite ({int(bad.sum())} such nodes; node ids "
                                                 "count from 0 as in ParaView)")
        if nodes_seen is None or nodes.shape != nodes_seen.shape or not np.array_equal(nodes, nodes_seen):
            far, largest = off_surface(nodes, triangles, SURFACE_TOLERANCE)
            if far.any():
                raise ConfigError(path, "points", f"{int(far.sum())} of {len(nodes)} nodes are farther "
                                                  f"than {SURFACE_TOLERANCE * 1e3:g} mm from the surface "
                                                  f"of mesh {mesh!r} (largest {largest * 1e3:.3g} mm): "
                                                  f"the nodes must lie on it (check the unit "
                                                  f"{unit!r}, the frame, and give the FE model's "
                                                  "outer surface only)")
            fit = _vertex_fit(nodes, vertices, cKDTree(nodes))
            nodes_seen = nodes
        if step == 0:
            if np.abs(u).max() > 0:
                raise ConfigError(path, "timestep 0", "the rest state's displacements must be zero "
                                                      "(vdo's step 0 is the undeformed mesh)")
            continue
        out[step] = fit(u)
    return out


def _vertex_fit(nodes: np.ndarray, vertices: np.ndarray, tree):
    """A linear map node displacements (M, 3) -> vertex displacements (V, 3): the node within
    NODE_TOLERANCE of a vertex, else the weighted affine least-squares fit of its FIT_NODES
    nearest nodes evaluated at the vertex (exact for linear fields; minimum-norm in directions
    the nodes do not span, e.g. across a flat face)."""
    from scipy import sparse

    k = min(FIT_NODES, len(nodes))
    spacing = float(np.median(tree.query(nodes, k=2)[0][:, 1])) if len(nodes) > 1 else 1.0
    dist, idx = tree.query(vertices, k=k)
    dist, idx = dist.reshape(len(vertices), k), idx.reshape(len(vertices), k)
    exact = np.flatnonzero(dist[:, 0] <= NODE_TOLERANCE)
    rows, cols, values = [exact], [idx[exact, 0]], [np.ones(len(exact))]
    for v in np.flatnonzero(dist[:, 0] > NODE_TOLERANCE):
        w = 1.0 / (dist[v] / spacing + 1.0) ** 2
        design = np.hstack([np.ones((k, 1)), (nodes[idx[v]] - vertices[v]) / spacing]) * w[:, None]
        # the fit's value at the vertex: the first row of pinv(design) applied to w * u
        rows.append(np.full(k, v))
        cols.append(idx[v])
        values.append(np.linalg.pinv(design, rcond=1e-10)[0] * w)
    weights = sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(len(vertices), len(nodes)))
    return lambda u: np.asarray(weights @ u)


# --------------------------------------------------------------------------------------------
# Applying a step to a geometry
# --------------------------------------------------------------------------------------------
def _barycentric_displacement(points, triangles, displaced, candidates: int = 16) -> np.ndarray:
    """Displacement at `points` (N, 3) lying on `triangles` (T, 3, 3): barycentric interpolation
    of the corner displacements `displaced` (T, 3, 3) of the triangle each point lies on (its
    in-plane coordinates (l1, l2) with X - A = l1 (B - A) + l2 (C - A), all >= -BARYCENTRIC_SLACK
    and l1 + l2 <= 1 + BARYCENTRIC_SLACK; `_locate`)."""
    tri, lam = _locate(np.asarray(points, float), triangles, candidates)
    out = np.zeros((len(points), 3))
    found = tri >= 0
    t, l1, l2 = tri[found], lam[found, :1], lam[found, 1:]
    out[found] = (1 - l1 - l2) * displaced[t, 0] + l1 * displaced[t, 1] + l2 * displaced[t, 2]
    return out


def _locate(points: np.ndarray, triangles: np.ndarray, candidates: int = 16):
    """(triangle (N,) int, -1 where none holds the point; (l1, l2) (N, 2)): the triangle of
    `triangles` (T, 3, 3) each point lies on, where two hold it (a shared edge) the one with the
    nearer centroid (the field is continuous across it). The `candidates` triangles with the
    nearest centroids are tried first; the points none of them holds try every triangle whose
    bounding sphere (about its centroid c_t, radius SPHERE_WIDEN R_t, R_t = max |vertex - c_t|,
    plus the barycentric slack) holds them, found by a ball search per class of radii within a factor
    SPHERE_CLASS of one another, so that a few long thin triangles (a fan around a hole) do not
    make the search a pass over every triangle for every point; any point still unplaced (off
    every triangle's plane by more than its sphere) tries every triangle."""
    from scipy.spatial import cKDTree

    n = len(points)
    e1, e2 = triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    g11, g12, g22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    det = g11 * g22 - g12 * g12
    usable = np.abs(det) >= 1e-30
    centroid = triangles.mean(axis=1)
    tri_out, lam_out = np.full(n, -1), np.zeros((n, 2))

    def solve(p, t):   # pairs (point, triangle) -> barycentric (m, 2), inside (m,)
        rel = points[p] - triangles[t, 0]
        r1, r2 = (rel * e1[t]).sum(-1), (rel * e2[t]).sum(-1)
        d = np.where(usable[t], det[t], 1.0)
        lam = np.stack([(g22[t] * r1 - g12[t] * r2) / d, (g11[t] * r2 - g12[t] * r1) / d], -1)
        inside = usable[t] & (lam >= -BARYCENTRIC_SLACK).all(-1) & (lam.sum(-1) <= 1 + BARYCENTRIC_SLACK)
        return lam, inside

    def assign(p, t):  # pairs -> the inside pair of nearest centroid per point; the points left
        lam, inside = solve(p, t)
        p, t, lam = p[inside], t[inside], lam[inside]
        near = np.linalg.norm(points[p] - centroid[t], axis=1)
        order = np.lexsort((near, p))
        first = order[np.r_[True, p[order][1:] != p[order][:-1]]] if len(order) else order
        tri_out[p[first]], lam_out[p[first]] = t[first], lam[first]

    k = min(candidates, len(triangles))
    _, near = cKDTree(centroid).query(points, k=k)
    assign(np.repeat(np.arange(n), k), np.asarray(near).reshape(-1))
    left = np.flatnonzero(tri_out < 0)
    if len(left):
        edge = np.sqrt(np.maximum(g11, g22))
        radius = SPHERE_WIDEN * np.linalg.norm(triangles - centroid[:, None], axis=2).max(axis=1) \
            + 2 * BARYCENTRIC_SLACK * edge
        smallest = radius[radius > 0].min() if (radius > 0).any() else 1.0   # degenerate: radius 0
        level = np.floor(np.log(np.maximum(radius, smallest) / smallest) / np.log(SPHERE_CLASS)).astype(int)
        pairs_p, pairs_t = [], []
        for c in np.unique(level):
            members = np.flatnonzero(level == c)
            hits = cKDTree(centroid[members]).query_ball_point(points[left], r=float(radius[members].max()))
            sizes = np.fromiter((len(h) for h in hits), int, len(hits))
            if sizes.sum():
                pairs_p.append(np.repeat(left, sizes))
                pairs_t.append(members[np.concatenate([h for h in hits if h])])
        if pairs_p:
            assign(np.concatenate(pairs_p), np.concatenate(pairs_t))
    left = np.flatnonzero(tri_out < 0)
    every = np.arange(len(triangles))
    for chunk in np.array_split(left, max(1, len(left) * len(triangles) // 2_000_000 + 1)):
        if len(chunk):
            assign(np.repeat(chunk, len(every)), np.tile(every, len(chunk)))
    return tri_out, lam_out


def at_step(geometry, load_path: LoadPath, step: int, *, regions: tuple[RegionSpec, ...]):
    """The geometry at `step`: every mesh of a moving group posed, the specimen's vertices
    displaced, and the surface samples moved with the mesh they lie on (a new `Geometry`).
    `regions`: the [[region]] tables the geometry was prepared from (`geometry.experiment.regions`),
    which say the mesh each region's samples lie on."""
    from vdo.scene import SceneMesh

    samples = geometry.samples
    points, normals = samples.points.copy(), samples.normals.copy()
    t_u, t_v = samples.tangent_u.copy(), samples.tangent_v.copy()
    region_mesh = np.array([regions[k].mesh for k in range(len(regions))])[samples.region]
    meshes = []
    for mesh in geometry.meshes:
        vertices = mesh.vertices
        on_mesh = region_mesh == mesh.name
        u = (load_path.displacements or {}).get(step) if mesh.name == load_path.deformed_mesh else None
        if u is not None:
            for k, faces in enumerate(geometry.region_faces):
                if regions[k].mesh == mesh.name:
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


MISSING_STEPS_SHOWN = 10   # steps named in the one line of a displacement file that lacks some


def _check_displaced_steps(file: Path, poses: Path | None, posed: set, displaced: set) -> None:
    """ConfigError when the displacement `file` has no rows for a step that the pose file has:
    at that step the specimen would stand undeformed while its supports move."""
    missing = sorted(posed - displaced)
    if not missing:
        return
    shown = ", ".join(map(str, missing[:MISSING_STEPS_SHOWN])) + (
        f", ... ({len(missing)} steps)" if len(missing) > MISSING_STEPS_SHOWN else "")
    raise ConfigError(file, "step", f"has no displacements at step {shown}, which the pose file "
                                    f"{poses.name!r} has (the specimen would stand undeformed "
                                    "there): add those steps (zeros where it does not deform), or "
                                    "drop them from the pose file")


def load_path_of(meshes, *, load_path_spec: LoadPathSpec, mesh_specs: tuple[MeshSpec, ...],
                 groups: tuple[GroupSpec, ...], poses: Path | None = None) -> LoadPath | None:
    """The experiment's `[load_path]` (`load_path_spec`) read from its CSV files, or None when it
    has none and no `poses` file is given. `poses` replaces the `[load_path]`'s pose file (`vdo
    render --series`). Groups are the experiment's `[[group]]` tables (`groups`), and every mesh
    of `mesh_specs` (its [[mesh]] tables) is also a group of its own name (pivot at the origin),
    so a pose file may move single meshes without declaring groups. Rows are checked here, before
    any ray is cast, and so is every step of the pose file found in the displacement file
    (`_check_displaced_steps`). `meshes`: the experiment's SceneMeshes (needed for the
    displacement nodes). With `[load_path] every = k`, the steps kept are every k-th of the
    files' and the last (all rows checked first)."""
    spec = load_path_spec
    if not spec.active and poses is None:
        return None
    members = {m.name: (m.name,) for m in mesh_specs}
    pivots = {name: np.zeros(3) for name in members}
    for g in groups:
        members[g.name] = tuple(g.meshes)
        pivots[g.name] = np.asarray(g.pivot, dtype=float)
    poses = poses if poses is not None else spec.poses
    displacements = None
    if spec.displacements is not None:
        mesh = next(m for m in meshes if m.name == spec.deformed_mesh)
        if spec.displacements.suffix.lower() == ".csv":
            displacements = read_displacements(spec.displacements, mesh.vertices, mesh.name)
        else:
            displacements = read_vtk_displacements(spec.displacements, mesh.vertices, mesh.faces,
                                                   mesh.name, spec.unit, spec.displacement_array)
    table = read_poses(Path(poses), members, pivots) if poses is not None else {}
    if displacements is not None:
        _check_displaced_steps(spec.displacements, Path(poses) if poses is not None else None,
                               {step for step, _ in table}, set(displacements))
    steps = sorted({step for step, _ in table} | set(displacements or {}))
    if poses is not None:
        _warn_gaps(Path(poses), table, steps)
    if spec.every > 1 and steps:      # every every-th step, and the last
        steps = sorted(set(steps[::spec.every]) | {steps[-1]})
    return LoadPath(tuple(steps), members, table, spec.deformed_mesh, displacements)


def check_load_path(*, load_path_spec: LoadPathSpec, groups: tuple[GroupSpec, ...],
                    mesh_specs: tuple[MeshSpec, ...], regions: tuple[RegionSpec, ...],
                    camera_specs: tuple[CameraSpec, ...], rails: tuple[RailSpec, ...],
                    mounts: tuple[MountSpec, ...], path, poses: Path | None = None) -> LoadPath | None:
    """Read the experiment's load path (`load_path_spec`, its `groups`; and `poses`, `vdo render
    --series`'s file) whole, as the commands do before any ray is cast, rendering or compile:
    every row of every step checked, the first bad one a ConfigError naming the file, the row and
    the column (`load_path_of`). The meshes are read (and checked, `vdo.scene.load_meshes`, with
    the [[mesh]], [[region]], [[camera]], [[rail]] and [[mount]] tables and the experiment file
    `path`) only when the specimen's displacements need its vertices. Returns the load path, or
    None when there is none."""
    from vdo.scene import load_meshes

    if not load_path_spec.active and poses is None:
        return None
    meshes = load_meshes(mesh_specs=mesh_specs, regions=regions, camera_specs=camera_specs, rails=rails,
                         mounts=mounts, path=path) if load_path_spec.displacements is not None else []
    return load_path_of(meshes, load_path_spec=load_path_spec, mesh_specs=mesh_specs, groups=groups,
                        poses=poses)
