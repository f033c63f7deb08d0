"""Build the meshes of the second built-in experiment, a steel beam in four-point bending, from
primitives.

Run from anywhere:  python experiments/steel_beam/make_meshes.py

Writes binary STL files in MILLIMETRES (as a CAD export would be; the experiment file declares
unit = "mm") into experiments/steel_beam/meshes/. Deterministic: a re-run rewrites identical files.

World frame (metres, z up, floor at z = 0): a 1.4 m steel beam of 60 x 120 mm section lies along x
(x in [-0.7, 0.7], y in [-0.03, 0.03], z in [0.84, 0.96]) on two rollers at x = +-0.6 (span
1.2 m); a spreader beam loads it through two rollers at x = +-0.2, so that the middle third
(|x| < 0.2) is in constant moment. A crosshead on two columns carries the actuator above. The
beam is three boxes split at x = +-0.2, so that the front face's middle third and its outer
parts are separate triangles (the regions of interest select triangles). Two LED panels light
the front face from the left and the right.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
OUT = HERE / "meshes"
MM = 1000.0       # the files are written in millimetres
SECTIONS = 24     # facets of every cylinder

HALF_W, Z_LO, Z_HI = 0.03, 0.84, 0.96      # beam section: y in +-0.03, z in [0.84, 0.96]
BEAM_END, SUPPORT_X, LOAD_X = 0.7, 0.6, 0.2
ROLLER_R = 0.02
LEDS = [((-0.6, -1.3, 1.95), (0.0, 0.0, 0.9)), ((0.6, -1.3, 1.95), (0.0, 0.0, 0.9))]   # (centre, faces)


def box(lo, hi) -> trimesh.Trimesh:
    """Axis-aligned box between corners lo and hi (m)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def rod(p0, p1, radius) -> trimesh.Trimesh:
    """Cylinder of `radius` from p0 to p1 (m)."""
    return trimesh.creation.cylinder(radius=radius, segment=np.array([p0, p1], float), sections=SECTIONS)


def panel(centre, target, size=(0.3, 0.3, 0.03)) -> trimesh.Trimesh:
    """A flat box whose large face looks from `centre` toward `target` (its x edge horizontal)."""
    mesh = trimesh.creation.box(extents=size)
    d = np.asarray(target, float) - np.asarray(centre, float)
    d /= np.linalg.norm(d)
    x = np.cross([0.0, 0.0, 1.0], d)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(d, x), d])
    T[:3, 3] = centre
    mesh.apply_transform(T)
    return mesh


def specimen() -> trimesh.Trimesh:
    cuts = [-BEAM_END, -LOAD_X, LOAD_X, BEAM_END]
    return trimesh.util.concatenate([box([a, -HALF_W, Z_LO], [b, HALF_W, Z_HI]) for a, b in zip(cuts, cuts[1:])])


def rig() -> trimesh.Trimesh:
    """Support rollers on pedestals, loading rollers (both as wide as the beam), spreader beam,
    actuator, crosshead, columns."""
    parts = []
    for s in (-1, 1):
        x = s * SUPPORT_X
        parts += [rod([x, -HALF_W, Z_LO - ROLLER_R], [x, HALF_W, Z_LO - ROLLER_R], ROLLER_R),
                  box([x - 0.05, -0.1, 0.0], [x + 0.05, 0.1, Z_LO - 2 * ROLLER_R])]
        x = s * LOAD_X
        parts.append(rod([x, -HALF_W, Z_HI + ROLLER_R], [x, HALF_W, Z_HI + ROLLER_R], ROLLER_R))
        parts.append(rod([s * 0.9, 0.0, 0.0], [s * 0.9, 0.0, 1.75], 0.06))   # columns
    parts += [box([-0.3, -0.05, Z_HI + 2 * ROLLER_R], [0.3, 0.05, Z_HI + 2 * ROLLER_R + 0.08]),  # spreader
              rod([0, 0, Z_HI + 2 * ROLLER_R + 0.08], [0, 0, 1.6], 0.05),                         # actuator
              box([-0.95, -0.15, 1.6], [0.95, 0.15, 1.75])]                                        # crosshead
    return trimesh.util.concatenate(parts)


def leds() -> trimesh.Trimesh:
    return trimesh.util.concatenate([panel(c, t) for c, t in LEDS])


PARTS = {"beam": specimen, "rig": rig, "leds": leds}


def main() -> None:
    OUT.mkdir(exist_ok=True)
    for name, build in PARTS.items():
        mesh = build()
        mesh = trimesh.Trimesh(np.round(mesh.vertices * MM, 6), mesh.faces, process=False)
        path = OUT / f"{name}.stl"
        data = mesh.export(file_type="stl")
        path.write_bytes(data)
        print(f"{path.relative_to(HERE.parent.parent)}: {len(mesh.faces)} triangles, {len(data) / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
