"""Build the meshes of the curved built-in experiment, a pressure vessel's nozzle-to-shell
junction seen from all around, from closed-form surfaces.

Run from anywhere:  python experiments/pressure_vessel/make_meshes.py

Writes binary STL files in MILLIMETRES (unit = "mm" in the experiment file) into
experiments/pressure_vessel/meshes/. Deterministic: a re-run rewrites identical files.

World frame (metres, z up, floor at z = 0): a cylindrical shell of radius R = 0.3 m along x
(x in [-0.6, 0.6], axis at z = 1.0) with flat ends, and a nozzle of radius r = 0.08 m on its
top, axis along z through the origin, closed by a blind flange at z = 1.45. The shell is meshed
in its development (x, s = R theta, theta from the top): a regular grid with a block around the
nozzle replaced by rings from the exact intersection curve x^2 + (R sin(s / R))^2 = r^2 out to the
block's edge, so that the shell's hole edge and the nozzle's bottom share their vertices (no gap
and no overlap at the junction). Two saddles carry the shell.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
OUT = HERE / "meshes"
MM = 1000.0

R, ZC, X_END = 0.3, 1.0, 0.6          # shell radius, axis height, half length (m)
R_NOZZLE, Z_TOP = 0.08, 1.45          # nozzle radius, flange height (m)
CELL_X, CELLS_AROUND = 0.025, 76      # grid of the development: 48 x 76 cells
BLOCK = 5                             # cells each side of the nozzle replaced by the rings
RINGS = 4                             # rings of quads between the hole edge and the block edge
NOZZLE_ROWS = 8
SADDLES = (-0.4, 0.4)


def shell_point(x, s):
    """3D point of the development (x, s) on the shell (theta = s / R from the top)."""
    t = np.asarray(s) / R
    return np.stack([np.asarray(x, float) + 0 * t, R * np.sin(t), ZC + R * np.cos(t)], axis=-1)


def hole_point(direction):
    """The point of the intersection curve x^2 + (R sin(s/R))^2 = r^2 along the developed ray
    t (cos a, sin a) (bisection on t)."""
    lo, hi = 0.0, 0.2
    for _ in range(80):
        t = (lo + hi) / 2
        x, s = t * math.cos(direction), t * math.sin(direction)
        lo, hi = (t, hi) if x * x + (R * math.sin(s / R)) ** 2 < R_NOZZLE ** 2 else (lo, t)
    return np.array([lo * math.cos(direction), lo * math.sin(direction)])


def quads(grid):
    """Triangles (2 per quad) of a (n, m, 3) grid of points, as an (k, 3, 3) array."""
    a, b, c, d = grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]
    return np.concatenate([np.stack([a, b, c], -2).reshape(-1, 3, 3), np.stack([a, c, d], -2).reshape(-1, 3, 3)])


def outward(tri, direction):
    """Triangles wound so that their normal points along direction(centroid)."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", n, direction(tri.mean(axis=1))) < 0
    tri[flip] = tri[flip][:, ::-1]
    return tri


def mesh_of(tri):
    return trimesh.Trimesh(tri.reshape(-1, 3) * MM, np.arange(len(tri) * 3).reshape(-1, 3), process=False)


def shell_and_nozzle():
    ds = 2 * math.pi * R / CELLS_AROUND
    xs = np.linspace(-X_END, X_END, int(round(2 * X_END / CELL_X)) + 1)
    ss = (np.arange(CELLS_AROUND + 1) - CELLS_AROUND // 2) * ds          # s = 0 at the top
    X, S = np.meshgrid(xs, ss, indexing="ij")
    grid = shell_point(X, S)
    ix0 = int(np.argmin(np.abs(xs))) - BLOCK
    is0 = CELLS_AROUND // 2 - BLOCK
    keep = np.ones((len(xs) - 1, CELLS_AROUND), dtype=bool)
    keep[ix0:ix0 + 2 * BLOCK, is0:is0 + 2 * BLOCK] = False
    tri = quads(grid)
    tri = tri[np.concatenate([keep.ravel(), keep.ravel()])]
    # the block's edge, counter-clockwise in (x, s), and the hole's points in the same directions
    edge = []
    for side in range(4):
        for k in range(2 * BLOCK):
            i, j = [(ix0 + k, is0), (ix0 + 2 * BLOCK, is0 + k), (ix0 + 2 * BLOCK - k, is0 + 2 * BLOCK),
                    (ix0, is0 + 2 * BLOCK - k)][side]
            edge.append((xs[i], ss[j]))
    edge = np.array(edge)
    hole = np.array([hole_point(math.atan2(s, x)) for x, s in edge])
    w = np.linspace(0, 1, RINGS + 1)[:, None, None]
    rings = (1 - w) * hole[None] + w * edge[None]                          # (RINGS + 1, K, 2)
    rings = np.concatenate([rings, rings[:, :1]], axis=1)                  # close the loop
    ring_tri = quads(shell_point(rings[..., 0], rings[..., 1]))
    shell = outward(np.concatenate([tri, ring_tri]),
                    lambda c: np.c_[np.zeros(len(c)), c[:, 1], c[:, 2] - ZC])
    ends = []
    for x in (-X_END, X_END):
        rim = shell_point(np.full(CELLS_AROUND + 1, x), ss)
        centre = np.array([x, 0.0, ZC])
        fan = np.stack([np.broadcast_to(centre, rim[:-1].shape), rim[:-1], rim[1:]], axis=1)
        ends.append(outward(fan, lambda c, x=x: np.tile([math.copysign(1, x), 0, 0], (len(c), 1))))
    shell = np.concatenate([shell] + ends)
    # nozzle: its bottom ring is the hole's edge in 3D (shared vertices), straight up to the flange
    bottom = shell_point(hole[:, 0], hole[:, 1])
    bottom = np.concatenate([bottom, bottom[:1]])
    h = np.linspace(0, 1, NOZZLE_ROWS + 1)[:, None, None]
    top = bottom.copy()
    top[:, 2] = Z_TOP
    wall = outward(quads((1 - h) * bottom[None] + h * top[None]),
                   lambda c: np.c_[c[:, 0], c[:, 1], np.zeros(len(c))])
    centre = np.array([0.0, 0.0, Z_TOP])
    flange = outward(np.stack([np.broadcast_to(centre, top[:-1].shape), top[:-1], top[1:]], axis=1),
                     lambda c: np.tile([0, 0, 1.0], (len(c), 1)))
    return mesh_of(shell), mesh_of(np.concatenate([wall, flange]))


def saddles():
    parts = []
    for x in SADDLES:
        box = trimesh.creation.box(extents=[0.08, 0.5, ZC - 0.22])
        box.apply_translation([x, 0.0, (ZC - 0.22) / 2])
        parts.append(box)
    mesh = trimesh.util.concatenate(parts)
    mesh.apply_scale(MM)
    return mesh


def main():
    OUT.mkdir(exist_ok=True)
    shell, nozzle = shell_and_nozzle()
    for name, mesh in (("shell", shell), ("nozzle", nozzle), ("saddles", saddles())):
        mesh.export(OUT / f"{name}.stl")
        print(f"{name}.stl: {len(mesh.faces)} triangles")


if __name__ == "__main__":
    main()
