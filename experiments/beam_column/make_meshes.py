"""Build the meshes of the built-in beam-column experiment (paper sec. 2-3) from primitives.

Run from anywhere:  python experiments/beam_column/make_meshes.py

Writes binary STL files in MILLIMETRES (as a CAD export would be; the experiment files declare
unit = "mm") into experiments/beam_column/meshes/. The output is deterministic: running the script
again rewrites byte-identical files.

World frame (metres, z up): the joint centre is at (0, 0, 1.2). The T specimen lies horizontally,
column along x (x in [-1.2, 1.2]), beam along +y (y in [0.06, 1.06]), 120 x 120 mm sections
(z in [1.14, 1.26]). The column ends sit in steel helmets on two posts (x in +-[1.0, 1.2]); the beam
end (y in [0.9, 1.06]) is held by the hexapod's helmet and load cell; the hexapod stands beyond the
beam end. A frame of Newport X95 bars (95 mm square) around the specimen carries the cameras and
the LED panels; `BARS` below lists the bar centre-lines, which the experiment files use as rails.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
OUT = HERE / "meshes"
MM = 1000.0            # the files are written in millimetres
SECTIONS = 20          # facets of every cylinder

# --------------------------------------------------------------------------------------------
# Dimensions (metres)
# --------------------------------------------------------------------------------------------
Z0 = 1.2                    # height of the specimen's axis
HALF = 0.06                 # half the 120 mm section
COLUMN_END = 1.2            # column from -1.2 to 1.2 along x
HELMET_IN = 1.0             # column helmets cover |x| in [1.0, 1.2]
BEAM_END = 1.06             # beam from y = 0.06 to 1.06
BEAM_HELMET = 0.9           # the hexapod's helmet covers y in [0.9, 1.06]

X95 = 0.095                 # Newport X95 profile, square, m
HIGH, LOW = 2.2, 0.35       # heights of the high and low bar levels (centre-lines)
FX, FY_FRONT, FY_BACK = 1.7, -1.9, 2.3     # frame corner posts at x = +-FX, y = FY_FRONT / FY_BACK
Y_LOW_FRONT, Y_LOW_BACK = -1.0, 0.6        # low cross bars in front of and behind the column
Y_OVERHEAD = 0.45                          # high cross bar above the beam

# Bar centre-lines (name: start, end). Rails in the experiment files follow these exactly.
BARS = {
    # corner posts, floor to the top of the high level
    "post_front_left": ((-FX, FY_FRONT, 0.0), (-FX, FY_FRONT, HIGH + X95 / 2)),
    "post_front_right": ((FX, FY_FRONT, 0.0), (FX, FY_FRONT, HIGH + X95 / 2)),
    "post_back_left": ((-FX, FY_BACK, 0.0), (-FX, FY_BACK, HIGH + X95 / 2)),
    "post_back_right": ((FX, FY_BACK, 0.0), (FX, FY_BACK, HIGH + X95 / 2)),
    # a middle post under the long front bar; it also carries a camera close to the joint
    "front_mast": ((0.0, FY_FRONT, 0.0), (0.0, FY_FRONT, HIGH)),
    # high level: perimeter and a cross bar over the beam
    "front_high": ((-FX, FY_FRONT, HIGH), (FX, FY_FRONT, HIGH)),
    "back_high": ((-FX, FY_BACK, HIGH), (FX, FY_BACK, HIGH)),
    "left_high": ((-FX, FY_FRONT, HIGH), (-FX, FY_BACK, HIGH)),
    "right_high": ((FX, FY_FRONT, HIGH), (FX, FY_BACK, HIGH)),
    "overhead": ((-FX, Y_OVERHEAD, HIGH), (FX, Y_OVERHEAD, HIGH)),
    # low level: the two sides and two cross bars (in front of the column, under the beam)
    "left_low": ((-FX, FY_FRONT, LOW), (-FX, FY_BACK, LOW)),
    "right_low": ((FX, FY_FRONT, LOW), (FX, FY_BACK, LOW)),
    "front_low": ((-FX, Y_LOW_FRONT, LOW), (FX, Y_LOW_FRONT, LOW)),
    "back_low": ((-FX, Y_LOW_BACK, LOW), (FX, Y_LOW_BACK, LOW)),
}

# LED panels: (centre, point it faces). 0.3 x 0.3 x 0.03 m boxes.
LEDS = [
    ((-0.75, FY_FRONT + 0.12, HIGH + 0.25), (0.0, 0.0, Z0)),     # front, high, left of the joint cameras
    ((0.75, FY_FRONT + 0.12, HIGH + 0.25), (0.0, 0.0, Z0)),      # front, high, right
    ((0.75, Y_LOW_FRONT - 0.05, LOW + 0.22), (0.0, 0.0, Z0)),    # front, low, lights the underside
    ((-0.75, Y_OVERHEAD, HIGH - 0.22), (0.0, 0.3, Z0)),         # under the overhead bar, over the beam
]


# --------------------------------------------------------------------------------------------
# Primitives
# --------------------------------------------------------------------------------------------
def box(lo, hi) -> trimesh.Trimesh:
    """Axis-aligned box between corners lo and hi (m)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def rod(p0, p1, radius) -> trimesh.Trimesh:
    """Cylinder of `radius` from p0 to p1 (m)."""
    return trimesh.creation.cylinder(radius=radius, segment=np.array([p0, p1], float), sections=SECTIONS)


def disc(centre, radius, thickness) -> trimesh.Trimesh:
    """Vertical-axis cylinder centred at `centre`."""
    c = np.asarray(centre, float)
    return rod(c - [0, 0, thickness / 2], c + [0, 0, thickness / 2], radius)


def bar(p0, p1, size=X95) -> trimesh.Trimesh:
    """A square profile along an axis-aligned centre-line, extended by half a profile at each end
    so that bars meeting at a corner overlap."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = np.argmax(np.abs(p1 - p0))
    lo, hi = np.minimum(p0, p1) - size / 2, np.maximum(p0, p1) + size / 2
    if axis == 2:   # posts stand on the floor
        lo[2], hi[2] = min(p0[2], p1[2]), max(p0[2], p1[2])
    return box(lo, hi)


def panel(centre, target, size=(0.3, 0.3, 0.03)) -> trimesh.Trimesh:
    """A flat box whose large face looks from `centre` toward `target`."""
    mesh = trimesh.creation.box(extents=size)
    direction = np.asarray(target, float) - np.asarray(centre, float)
    direction /= np.linalg.norm(direction)
    # rotate +z onto the direction, keeping the panel's x edge horizontal
    x = np.cross([0.0, 0.0, 1.0], direction)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(direction, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, direction])
    T[:3, 3] = centre
    mesh.apply_transform(T)
    return mesh


def helmet(axis: int, sign: float, inner: float, outer: float, centre_yz, length=0.2, wall=0.03):
    """A steel helmet: a square tube of outer section 2*outer around an axis-parallel bar end,
    open toward the specimen, closed by an end plate of thickness `wall` at the far end.
    `axis` 0 (x) or 1 (y); the helmet spans sign*[inner, inner + length] along it."""
    a0, a1 = sorted((sign * inner, sign * (inner + length)))
    plates = []
    other = 1 - axis                       # the horizontal axis across the bar
    c_o, c_z = centre_yz
    half_in = outer - wall
    for lo_o, hi_o, lo_z, hi_z in [(-outer, outer, half_in, outer), (-outer, outer, -outer, -half_in),
                                   (-outer, -half_in, -half_in, half_in), (half_in, outer, -half_in, half_in)]:
        lo, hi = np.zeros(3), np.zeros(3)
        lo[axis], hi[axis] = a0, a1
        lo[other], hi[other] = c_o + lo_o, c_o + hi_o
        lo[2], hi[2] = c_z + lo_z, c_z + hi_z
        plates.append(box(lo, hi))
    lo, hi = np.zeros(3), np.zeros(3)
    far = sign * (inner + length)
    lo[axis], hi[axis] = sorted((far, far - sign * wall))
    lo[other], hi[other] = c_o - half_in, c_o + half_in
    lo[2], hi[2] = c_z - half_in, c_z + half_in
    plates.append(box(lo, hi))
    return trimesh.util.concatenate(plates)


# --------------------------------------------------------------------------------------------
# The parts
# --------------------------------------------------------------------------------------------
def specimen() -> trimesh.Trimesh:
    """The T as one watertight prism: its outline in the xy plane extruded over z.

    The outline carries extra vertices (x = +-0.06 on both column edges, x = +-1.0 where the
    helmets start, y = 0.9 where the hexapod's helmet starts) so that the caps split into
    rectangles without T-junctions and every region of interest is a set of whole triangles."""
    h, c, e, b, be = HALF, COLUMN_END, HELMET_IN, BEAM_END, BEAM_HELMET
    outline = np.array([                      # counter-clockwise seen from +z
        (-c, -h), (-e, -h), (-h, -h), (h, -h), (e, -h), (c, -h),          # 0-5   front edge y = -h
        (c, h), (e, h), (h, h),                                          # 6-8   back edge, right
        (h, be), (h, b), (-h, b), (-h, be),                              # 9-12  beam
        (-h, h), (-e, h), (-c, h),                                       # 13-15 back edge, left
    ])
    rectangles = [(0, 1, 14, 15), (1, 2, 13, 14), (2, 3, 8, 13), (3, 4, 7, 8), (4, 5, 6, 7),
                  (13, 8, 9, 12), (12, 9, 10, 11)]   # column-left end, column-left, joint,
    #                                                  column-right, its end, beam, beam end
    n = len(outline)
    z_lo, z_hi = Z0 - h, Z0 + h
    vertices = np.vstack([np.column_stack([outline, np.full(n, z_lo)]),
                          np.column_stack([outline, np.full(n, z_hi)])])
    faces = []
    for a, b_, c_, d in rectangles:
        faces += [(n + a, n + b_, n + c_), (n + a, n + c_, n + d)]          # top cap, normal +z
        faces += [(a, c_, b_), (a, d, c_)]                                  # bottom cap, normal -z
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, n + j), (i, n + j, n + i)]                         # side wall, outward
    mesh = trimesh.Trimesh(vertices, np.array(faces), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0, "specimen is not a closed solid"
    return mesh


def supports() -> trimesh.Trimesh:
    parts = []
    for s in (-1.0, 1.0):
        x = s * (HELMET_IN + 0.1)
        parts.append(box((x - 0.075, -0.075, 0.0), (x + 0.075, 0.075, Z0 - 0.1)))        # post
        parts.append(box((x - 0.2, -0.2, 0.0), (x + 0.2, 0.2, 0.02)))                    # foot plate
        parts.append(helmet(0, s, HELMET_IN, 0.1, (0.0, Z0)))                           # steel helmet
    return trimesh.util.concatenate(parts)


HEXAPOD_CENTRE = np.array([0.0, 1.5, 0.0])
HEXAPOD_BASE_Z, HEXAPOD_PLATFORM_Z = 0.03, 0.70


def hexapod_base() -> trimesh.Trimesh:
    """The part that stays on the floor: base plate and the actuators' lower joints."""
    centre, base_z = HEXAPOD_CENTRE, HEXAPOD_BASE_Z
    parts = [disc(centre + [0, 0, base_z], 0.6, 0.06)]
    for k, side in ((k, side) for k in range(3) for side in (-1.0, 1.0)):
        a_b = np.radians(120 * k + 90 + side * 12)
        p_b = centre + [0.5 * np.cos(a_b), 0.5 * np.sin(a_b), base_z + 0.08]
        parts.append(disc(p_b - [0, 0, 0.04], 0.06, 0.05))                # lower joint
    return trimesh.util.concatenate(parts)


def hexapod_top() -> trimesh.Trimesh:
    """The part that the load path moves: platform, end-effector, load cell and the beam's
    helmet, with the six actuators (in the test each actuator's lower end stays on its joint;
    moving it with the platform is within the load path's +-15 mm)."""
    centre, base_z, plat_z = HEXAPOD_CENTRE, HEXAPOD_BASE_Z, HEXAPOD_PLATFORM_Z
    parts = [disc(centre + [0, 0, plat_z], 0.4, 0.05)]                  # moving platform
    for k, side in ((k, side) for k in range(3) for side in (-1.0, 1.0)):   # crossing pairs
        a_b = np.radians(120 * k + 90 + side * 12)
        a_p = np.radians(120 * k + 90 + side * 48)
        p_b = centre + [0.5 * np.cos(a_b), 0.5 * np.sin(a_b), base_z + 0.08]
        p_p = centre + [0.33 * np.cos(a_p), 0.33 * np.sin(a_p), plat_z - 0.05]
        parts.append(rod(p_b, p_p, 0.04))
        parts.append(disc(p_p + [0, 0, 0.02], 0.05, 0.04))                # upper joint
    # end-effector column from the platform up to the load cell, which holds the beam's helmet
    parts.append(box((-0.09, 1.22, plat_z + 0.025), (0.09, 1.40, Z0 + 0.12)))
    parts.append(rod((0.0, BEAM_END + 0.02, Z0), (0.0, 1.22, Z0), 0.09))          # load cell
    parts.append(helmet(1, 1.0, BEAM_HELMET, 0.1, (0.0, Z0), length=BEAM_END + 0.02 - BEAM_HELMET))
    return trimesh.util.concatenate(parts)


def frame() -> trimesh.Trimesh:
    return trimesh.util.concatenate([bar(p0, p1) for p0, p1 in BARS.values()])


def leds() -> trimesh.Trimesh:
    return trimesh.util.concatenate([panel(c, t) for c, t in LEDS])


PARTS = {"specimen": specimen, "supports": supports, "hexapod_base": hexapod_base,
         "hexapod_top": hexapod_top, "frame": frame, "leds": leds}


# --------------------------------------------------------------------------------------------
# Load path (the [load_path] of ten_cameras.toml): the hexapod drives the beam end
# --------------------------------------------------------------------------------------------
def load_history() -> list[tuple[float, float]]:
    """(x, z) translations of the beam end in metres, one per step: three cycles of growing
    amplitude (5, 10, 15 mm), each a horizontal (x) then a vertical (z) push and pull, as in the
    paper's multi-axial histories."""
    steps = []
    for amplitude in (0.005, 0.010, 0.015):
        for axis in (0, 1):
            for value in (amplitude, 0.0, -amplitude, 0.0):
                steps.append((value, 0.0) if axis == 0 else (0.0, value))
    return steps


def write_load_path(folder: Path = HERE) -> None:
    """load_path_platform.csv: the platform group's pose per step; load_path_specimen.csv: the
    specimen's beam-end vertices (y >= BEAM_HELMET) follow the platform; the beam's other
    vertices are at the joint (y = HALF) and stay at rest, so the beam's faces tilt linearly."""
    mesh = specimen()
    moving = np.unique(np.round(mesh.vertices[mesh.vertices[:, 1] >= BEAM_HELMET - 1e-9], 9), axis=0)
    platform = ["# the hexapod platform's pose per step (vdo.geometry.keyframes); written by make_meshes.py",
                "step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg"]
    nodes = ["# specimen vertices that move with the beam end (vdo.geometry.keyframes); written by make_meshes.py",
             "step,x_m,y_m,z_m,ux_mm,uy_mm,uz_mm"]
    for k, (dx, dz) in enumerate(load_history(), start=1):
        platform.append(f"{k},platform,{dx * MM:g},0,{dz * MM:g},0,0,0")
        nodes += [f"{k},{x:.6f},{y:.6f},{z:.6f},{dx * MM:g},0,{dz * MM:g}" for x, y, z in moving]
    (folder / "load_path_platform.csv").write_text("\n".join(platform) + "\n")
    (folder / "load_path_specimen.csv").write_text("\n".join(nodes) + "\n")


def main() -> None:
    write_load_path()
    OUT.mkdir(exist_ok=True)
    total = 0
    for name, build in PARTS.items():
        mesh = build()
        mesh = trimesh.Trimesh(np.round(mesh.vertices * MM, 6), mesh.faces, process=False)
        path = OUT / f"{name}.stl"
        data = mesh.export(file_type="stl")
        path.write_bytes(data)
        total += len(data)
        print(f"{path.relative_to(HERE.parent.parent)}: {len(mesh.faces)} triangles, {len(data) / 1024:.0f} KiB")
    print(f"total {total / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
