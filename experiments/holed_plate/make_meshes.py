"""Build the meshes of the holed-plate tensile test from primitives.

Run from anywhere:  python experiments/holed_plate/make_meshes.py [OUT_DIR]

Writes binary STL files in MILLIMETRES (the experiment file declares unit = "mm") into OUT_DIR
(default: experiments/holed_plate/meshes/). Deterministic: a re-run writes byte-identical files.

World frame (metres, z up). A 100 mm x 300 mm x 5 mm plate hangs vertically in the grips of a
tensile machine, its front face at y = -2.5 mm facing -y, with a circular hole of radius 15 mm at
(0, 1.0) in (x, z). The grips clamp z below 0.90 and above 1.10, so the free length is 200 mm.
The machine is two columns behind the plate, a crosshead and a base; a stereo pair stands in front
on two tripods (legs and heads only: the camera bodies are added by vdo).

The plate is built without a boolean library: the front and back faces are an annulus-like grid
around the hole (a ring of `RING` points on the circle mapped radially, in `RADIAL` steps, to the
boundary of the centre square of side 100 mm) plus plain rectangles above and below it, joined by
the hole's wall and the plate's side walls. The faces have edges at the grips' lines, so that a region box
ending there selects whole triangles. The hole is a polygon of `RING` sides: its sagitta
R (1 - cos(pi / RING)) = 1.1 um for R = 15 mm.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
MM = 1000.0

WIDTH, LENGTH, THICK = 0.100, 0.300, 0.005    # plate, m
CENTRE_Z = 1.0                                 # hole centre and plate middle height, m
RADIUS = 0.015                                 # hole radius, m
GRIP_LOW, GRIP_HIGH = 0.90, 1.10               # the grips cover z outside this range (symmetric)
RING, RADIAL = 256, 24                         # points on the hole, steps from hole to square
SECTIONS = 20


def _square_point(theta: np.ndarray, half: float) -> np.ndarray:
    """Point of the square |x|, |z| <= half on the ray from its centre at angle theta."""
    c, s = np.cos(theta), np.sin(theta)
    t = half / np.maximum(np.abs(c), np.abs(s))
    return np.stack([t * c, t * s], axis=-1)


def face_2d() -> tuple[np.ndarray, np.ndarray]:
    """The plate's face in (x, z) about the hole centre: vertices (V, 2) m and triangles (T, 3),
    counter-clockwise in (x, z), i.e. with normal x cross z = -y."""
    half = WIDTH / 2
    theta = np.linspace(0, 2 * np.pi, RING, endpoint=False)   # RING % 8 == 0: the corners too
    inner = RADIUS * np.stack([np.cos(theta), np.sin(theta)], -1)
    outer = _square_point(theta, half)
    s = np.linspace(0, 1, RADIAL + 1)[:, None, None]
    grid = (1 - s) * inner[None] + s * outer[None]               # (RADIAL+1, RING, 2)
    verts = [grid.reshape(-1, 2)]
    tris = []
    idx = lambda r, k: r * RING + (k % RING)
    for r in range(RADIAL):
        for k in range(RING):
            a, b, c, d = idx(r, k), idx(r, k + 1), idx(r + 1, k + 1), idx(r + 1, k)
            tris += [(a, b, c), (a, c, d)]
    base = len(verts[0])
    # rectangles above and below the centre square, split in rows of the ring's points on its edge
    for sign in (1, -1):
        edge_k = [k for k in range(RING) if abs(outer[k, 1] - sign * half) < 1e-12 and abs(outer[k, 0]) < half - 1e-12]
        xs = np.r_[-half, np.sort(outer[edge_k, 0]), half]
        grip = (GRIP_HIGH if sign > 0 else CENTRE_Z - (GRIP_HIGH - CENTRE_Z)) - CENTRE_Z
        rows = np.array([sign * half, grip, sign * LENGTH / 2])   # an edge where the grips start
        pts = np.array([[x, z] for z in rows for x in xs])
        n = len(xs)
        for i in range(len(rows) - 1):
            for j in range(n - 1):
                a, b, c, d = (base + i * n + j, base + i * n + j + 1, base + (i + 1) * n + j + 1,
                              base + (i + 1) * n + j)
                tris += [(a, b, c), (a, c, d)]
        verts.append(pts)
        base += len(pts)
    V = np.concatenate(verts)
    T = np.array(tris)
    # orient every triangle counter-clockwise in (x, z)
    p = V[T]
    cross = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    T[cross < 0] = T[cross < 0][:, ::-1]
    return V, T


def plate() -> trimesh.Trimesh:
    """The holed plate: front face (y = -THICK/2, normal -y), back face, hole wall, side walls."""
    V2, T = face_2d()
    V2 = V2 + [0.0, CENTRE_Z]
    y0, y1 = -THICK / 2, THICK / 2
    front = np.c_[V2[:, 0], np.full(len(V2), y0), V2[:, 1]]
    back = np.c_[V2[:, 0], np.full(len(V2), y1), V2[:, 1]]
    # counter-clockwise in (x, z) has normal -y for (x, y, z) right-handed: x cross z = -y
    faces = [T, T[:, ::-1] + len(V2)]
    verts = [front, back]
    base = 2 * len(V2)

    def wall(loop_xz, outward_sign):
        nonlocal base
        n = len(loop_xz)
        ring = np.r_[np.c_[loop_xz[:, 0], np.full(n, y0), loop_xz[:, 1]],
                     np.c_[loop_xz[:, 0], np.full(n, y1), loop_xz[:, 1]]]
        f = []
        for k in range(n):
            a, b, c, d = k, (k + 1) % n, n + (k + 1) % n, n + k
            f += [(a, b, c), (a, c, d)] if outward_sign > 0 else [(a, c, b), (a, d, c)]
        verts.append(ring)
        faces.append(np.array(f) + base)
        base += len(ring)

    theta = np.linspace(0, 2 * np.pi, RING, endpoint=False)
    wall(np.c_[RADIUS * np.cos(theta), CENTRE_Z + RADIUS * np.sin(theta)], 1)
    hw, hl = WIDTH / 2, LENGTH / 2
    wall(np.array([[-hw, CENTRE_Z - hl], [hw, CENTRE_Z - hl], [hw, CENTRE_Z + hl], [-hw, CENTRE_Z + hl]]), -1)
    return trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)


def box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def rod(p0, p1, radius) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=radius, segment=np.array([p0, p1], float), sections=SECTIONS)


def machine() -> trimesh.Trimesh:
    """Grips (jaws around the plate's ends), crossheads, two columns behind, the base."""
    parts = [box([-0.06, -0.03, GRIP_HIGH], [0.06, 0.03, GRIP_HIGH + 0.08]),
             box([-0.06, -0.03, GRIP_LOW - 0.08], [0.06, 0.03, GRIP_LOW]),
             box([-0.35, -0.08, GRIP_HIGH + 0.08], [0.35, 0.12, GRIP_HIGH + 0.20]),
             box([-0.35, -0.08, 0.0], [0.35, 0.12, GRIP_LOW - 0.08]),
             rod([-0.3, 0.05, 0.0], [-0.3, 0.05, 1.6], 0.04),
             rod([0.3, 0.05, 0.0], [0.3, 0.05, 1.6], 0.04)]
    return trimesh.util.concatenate(parts)


CAMERAS = {"left": (-0.152, -0.686, 1.0), "right": (0.152, -0.686, 1.0)}   # stereo pair, 25 deg


def tripods() -> trimesh.Trimesh:
    """A tripod under each camera: a head 0.18 m below the optical centre (clear of the body) and
    three legs to the floor."""
    parts = []
    for x, y, z in CAMERAS.values():
        head = np.array([x, y - 0.05, z - 0.18])
        parts.append(box(head - [0.03, 0.03, 0.03], head + [0.03, 0.03, 0.0]))
        for a in (0.0, 2.1, 4.2):
            foot = head + [0.35 * np.cos(a), 0.35 * np.sin(a), 0.0]
            foot[2] = 0.0
            parts.append(rod(head, foot, 0.012))
    return trimesh.util.concatenate(parts)


PARTS = {"plate": plate, "machine": machine, "tripods": tripods}


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, build in PARTS.items():
        mesh = build()
        mesh = trimesh.Trimesh(np.round(mesh.vertices * MM, 6), mesh.faces, process=False)
        data = mesh.export(file_type="stl")
        (out / f"{name}.stl").write_bytes(data)
        print(f"{out / (name + '.stl')}: {len(mesh.faces)} triangles")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "meshes")
