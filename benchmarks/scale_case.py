"""A generated large experiment for the scale benchmark (benchmarks/scale.py): a box girder several
metres long in bending, watched by cameras on floor tripods on both sides and an overhead rail.

`write_case(folder, ...)` writes the meshes (binary STL, metres) and `scale.toml` into `folder`
and returns the TOML's path. Everything is generated in code from a few numbers, so the case grows
along one axis at a time: `length_m` (the specimen), `segments` (regions per face: 4 x segments
regions, the faces cut into slices along x), `cameras` (split between the two sides' tripod zones
and the rail), `spacing_mm` (samples: about area / spacing^2) and the [design] grid (candidates).

World frame (metres, z up, floor at z = 0): the girder spans x in [-L/2, L/2], y in [-0.2, 0.2],
z in [0.9, 1.5]; two pedestals under its ends; a loading frame behind it (two columns at y = 0.7
and a crosshead above the girder), which hides parts of the back face from some cameras.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HALF_W, Z_LO, Z_HI = 0.2, 0.9, 1.5          # girder section (m)
SIDE_Y = 2.2                                 # tripod zones: |y| from SIDE_Y to SIDE_Y + 1.2
RAIL_Z = 2.9                                 # the overhead rail's height (m)
FACES = (("front", (0, -1, 0)), ("back", (0, 1, 0)), ("top", (0, 0, 1)), ("bottom", (0, 0, -1)))


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo,
                                transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def meshes(length_m: float) -> dict[str, trimesh.Trimesh]:
    """The girder (specimen), its pedestals and the loading frame (obstacles)."""
    h = length_m / 2
    girder = _box([-h, -HALF_W, Z_LO], [h, HALF_W, Z_HI])
    pedestals = trimesh.util.concatenate([_box([s * (h - 0.2) - 0.15, -0.3, 0.0],
                                               [s * (h - 0.2) + 0.15, 0.3, Z_LO]) for s in (-1, 1)])
    frame = trimesh.util.concatenate(
        [_box([s * 0.8 - 0.1, 0.6, 0.0], [s * 0.8 + 0.1, 0.8, 2.3]) for s in (-1, 1)]
        + [_box([-1.0, 0.0, 2.1], [1.0, 0.8, 2.3])])
    return {"girder": girder, "pedestals": pedestals, "frame": frame}


def _vec(v) -> str:
    return "[" + ", ".join(f"{float(x):.6g}" for x in v) + "]"


def write_case(folder: Path, length_m: float = 6.0, segments: int = 60, cameras: int = 12,
               spacing_mm: float = 11.0, zone_points: int = 4, zone_heights: int = 3,
               rail_positions: int = 12, lenses_mm=(8, 12, 16), aim_offsets_deg=(),
               design_spacing_mm: float = 40.0, bound_s: float | None = None) -> Path:
    """Write the meshes and scale.toml into `folder`; returns the TOML's path. Cameras: two on the
    rail (when cameras >= 6), the rest split evenly between the front and the back tripod zones
    (one zone per camera on each side, the zones tiling the length)."""
    folder = Path(folder)
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    for name, mesh in meshes(length_m).items():
        mesh.export(folder / "meshes" / f"{name}.stl")
    h = length_m / 2
    on_rail = 2 if cameras >= 6 else 0
    front = (cameras - on_rail + 1) // 2
    back = cameras - on_rail - front
    out = ["[experiment]", f'name = "scale case: {length_m:g} m girder, {4 * segments} regions, '
           f'{cameras} cameras"', "", "[evaluation]", f"sample_spacing_mm = {spacing_mm:g}",
           "incidence_limit_deg = 75", "patch_mm = 15", ""]
    for name, role in (("girder", "specimen"), ("pedestals", "obstacle"), ("frame", "obstacle")):
        out += ["[[mesh]]", f'name = "{name}"', f'file = "meshes/{name}.stl"', f'role = "{role}"', ""]
    cuts = np.linspace(-h, h, segments + 1)
    for face, normal in FACES:
        for k, (a, b) in enumerate(zip(cuts, cuts[1:])):
            out += ["[[region]]", f'name = "{face}_{k:03d}"', 'mesh = "girder"', f"normal = {_vec(normal)}",
                    f"box_min_m = {_vec([a, -1, 0])}", f"box_max_m = {_vec([b, 1, 3])}", ""]
    out += ["[[rail]]", 'name = "overhead"', f"control_points_m = [{_vec([-h, 0, RAIL_Z])}, {_vec([h, 0, RAIL_Z])}]",
            "degree = 1", ""]
    zones = []
    for side, count in ((-1, front), (1, back)):
        edges = np.linspace(-h, h, max(count, 1) + 1)
        for k, (a, b) in enumerate(zip(edges, edges[1:])):
            if k >= count:
                break
            name = f"{'front' if side < 0 else 'back'}_{k}"
            y0, y1 = sorted((side * SIDE_Y, side * (SIDE_Y + 1.2)))
            zones.append((name, side, (a + b) / 2))
            out += ["[[mount]]", f'name = "{name}"', 'kind = "zone"', f"box_min_m = {_vec([a, y0, 0.2])}",
                    f"box_max_m = {_vec([b, y1, 2.0])}", "", "[mount.tripod]", "legs = 3",
                    "spread_m = 0.45", "leg_diameter_m = 0.03", "column_diameter_m = 0.05", ""]
    for k, x in enumerate((-0.6 * h, 0.6 * h)):
        out += ["[[light]]", f'name = "front_{k}"', f"position_m = {_vec([x, -2.0, 2.4])}",
                f"target_m = {_vec([x, 0, 1.2])}", "size_m = [0.6, 0.6]", "radiance = 60", "",
                "[[light]]", f'name = "back_{k}"', f"position_m = {_vec([x, 2.0, 2.4])}",
                f"target_m = {_vec([x, 0, 1.2])}", "size_m = [0.6, 0.6]", "radiance = 60", ""]
    out += ["[speckle]", "dot_diameter_mm = 3", "texel_mm = 0.5", "", "[sensor]",
            "quantum_efficiency = 0.65", "full_well_e = 10000", "read_noise_e = 3.0", "bit_depth = 12", "",
            "[render]", "spp = 4", "scale = 0.25", "ambient_radiance = 0.05", ""]
    body = ['sensor_mm = [8.4456, 7.0656]', "pixels = [2448, 2048]"]
    cam = 0
    for name, side, x in zones:
        cam += 1
        out += ["[[camera]]", f'name = "cam{cam}"', *body, "focal_mm = 8", f'mount = "{name}"',
                f"position_m = {_vec([x, side * (SIDE_Y + 0.3), 1.6])}", f"target_m = {_vec([x, 0, 1.2])}", ""]
    for k in range(on_rail):
        cam += 1
        u = 0.25 + 0.5 * k
        out += ["[[camera]]", f'name = "cam{cam}"', *body, "focal_mm = 8", 'rail = "overhead"',
                f"u = {u:g}", "offset_m = [0, 0, -0.15]", "pan_deg = 0", f"tilt_deg = {-75 + 30 * k}", ""]
    out += ["[optimize]", 'free = ["u", "pan", "tilt"]', "clearance_m = 0.05", "starts = 1", "rounds = 2",
            "max_steps = 20", "", "[design]", f"max_cameras = {cameras}", f"lenses_mm = {_vec(lenses_mm)}",
            f"zone_points = {zone_points}", f"zone_heights = {zone_heights}",
            f"rail_positions = {rail_positions}", "offset_m = [0, 0, -0.15]",
            f"aim_offsets_deg = {_vec(aim_offsets_deg)}", f"sample_spacing_mm = {design_spacing_mm:g}",
            "keyframes = 0", *([f"bound_s = {bound_s:g}"] if bound_s is not None else []), ""]
    path = folder / "scale.toml"
    path.write_text("\n".join(out))
    return path
