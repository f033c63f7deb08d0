"""Build the meshes and the load path of the pipe-elbow experiment from closed-form surfaces.

Run from anywhere:  python experiments/pipe_elbow/make_meshes.py

Writes binary STL files in MILLIMETRES (unit = "mm" in the experiment file) into
experiments/pipe_elbow/meshes/ and the load path's displacement CSV beside this script.
Deterministic: a re-run rewrites identical files.

World frame (metres, z up, floor at z = 0): a 90-degree elbow of pipe radius 0.1 m swept along a
centreline at z = 0.9 m: a straight leg A along +y (0.3 m, its blind flange the fixed end), a
quarter torus of bend radius 0.35 m about the vertical axis through (-0.1, -0.1), and a straight
leg B along -x (0.3 m, the free end). One grid of 48 points around the pipe at every centreline
station, so the bend-to-leg junctions (the girth welds) are grid lines. Two block supports stand
under the legs.

The load path is a closed-form out-of-plane bending of the free leg: at step k every vertex
moves down by uz = -delta_k s^2 (s: the normalised centreline length, 0 at the fixed flange, 1 at
the free one), delta_k = 1, 2, 3 mm, written at every vertex of the elbow mesh.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
OUT = HERE / "meshes"
MM = 1000.0
R_PIPE, R_BEND, LEG = 0.1, 0.35, 0.3      # pipe radius, bend radius (centreline), leg length (m)
ZC = 0.9                                 # pipe axis height
SHIFT = np.array([-0.1, -0.1])           # bend centre, so the elbow is roughly centred on the origin
AROUND, N_LEG, N_BEND = 48, 8, 24
STEPS_MM = [1.0, 2.0, 3.0]          # free-end deflection per step


def centreline():
    """(points, tangents, s) along leg A (fixed end first), the bend, leg B (free end)."""
    c = np.array([*SHIFT, ZC])
    pts, tan = [], []
    for t in np.linspace(0, 1, N_LEG + 1)[:-1]:          # leg A along +y up to the bend start
        pts.append(c + [R_BEND, -LEG * (1 - t), 0]); tan.append([0, 1, 0])
    for th in np.linspace(0, math.pi / 2, N_BEND + 1):
        pts.append(c + [R_BEND * math.cos(th), R_BEND * math.sin(th), 0]); tan.append([-math.sin(th), math.cos(th), 0])
    for t in np.linspace(0, 1, N_LEG + 1)[1:]:           # leg B along -x
        pts.append(c + [-LEG * t, R_BEND, 0]); tan.append([-1, 0, 0])
    pts, tan = np.array(pts), np.array(tan, float)
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    return pts, tan, s / s[-1]


def elbow():
    pts, tan, s = centreline()
    ez = np.array([0, 0, 1.0])
    ph = np.linspace(0, 2 * math.pi, AROUND, endpoint=False)
    verts = []
    for p, t in zip(pts, tan):
        n = np.cross(t, ez)
        verts.append(p + R_PIPE * (np.cos(ph)[:, None] * n + np.sin(ph)[:, None] * ez))
    verts = np.concatenate(verts)
    rows = len(pts)
    faces = []
    for i in range(rows - 1):
        for j in range(AROUND):
            a, b = i * AROUND + j, i * AROUND + (j + 1) % AROUND
            c, d = a + AROUND, b + AROUND
            faces += [[a, c, b], [b, c, d]]
    # blind flanges: a centre vertex per end
    ends = []
    for i, centre in ((0, pts[0]), (rows - 1, pts[-1])):
        k = len(verts) + len(ends)
        ends.append(centre)
        for j in range(AROUND):
            a, b = i * AROUND + j, i * AROUND + (j + 1) % AROUND
            faces.append([k, a, b] if i == 0 else [k, b, a])
    verts = np.concatenate([verts, np.array(ends)])
    mesh = trimesh.Trimesh(verts, np.array(faces), process=False)
    assert mesh.volume > 0, mesh.volume
    s_vert = np.r_[np.repeat(s, AROUND), 0.0, 1.0]
    return mesh, s_vert


def supports():
    pts, _, _ = centreline()
    parts = []
    for p in (pts[2], pts[-3]):
        box = trimesh.creation.box(extents=[0.12, 0.12, ZC - R_PIPE - 0.005])
        box.apply_translation([p[0], p[1], (ZC - R_PIPE - 0.005) / 2])
        parts.append(box)
    return trimesh.util.concatenate(parts)


def main():
    OUT.mkdir(exist_ok=True)
    mesh, s = elbow()
    sup = supports()
    for name, m in (("elbow", mesh), ("supports", sup)):
        m = m.copy(); m.apply_scale(MM); m.export(OUT / f"{name}.stl")
        print(f"{name}.stl: {len(m.faces)} triangles, watertight {m.is_watertight}")
    with open(HERE / "load_path_elbow.csv", "w") as f:
        f.write("# out-of-plane bending of the free leg, uz = -delta s^2 at every vertex; written by make_meshes.py\n")
        f.write("step,x_m,y_m,z_m,ux_mm,uy_mm,uz_mm\n")
        for step, d in enumerate(STEPS_MM, 1):
            for (x, y, z), si in zip(mesh.vertices, s):
                f.write(f"{step},{x:.6f},{y:.6f},{z:.6f},0,0,{-d * si * si:.5f}\n")


if __name__ == "__main__":
    main()
