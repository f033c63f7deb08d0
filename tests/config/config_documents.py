"""Hypothesis strategies for experiment files: valid TOML documents (as dicts, file units) that use
every table and, at random, every optional field; and junk values for mutating them.

The documents refer to the mesh file "plate.stl" next to the config (see `plate_file`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import trimesh
from hypothesis import Phase
from hypothesis import strategies as st

NO_SHRINK = tuple(p for p in Phase if p != Phase.shrink)   # a failure is reported at once, unshrunk

NAMES = st.from_regex(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,8}", fullmatch=True)
REAL = st.floats(-100, 100, allow_nan=False, allow_infinity=False)
NUMBER = st.one_of(st.integers(-100, 100), REAL)


def plate_file(folder: Path) -> Path:
    """A 1 m x 1 m x 10 mm plate (STL in mm), top face at z = 0."""
    box = trimesh.creation.box(extents=[1000, 1000, 10])
    box.apply_translation([0, 0, -5])
    box.export(folder / "plate.stl")
    return folder / "plate.stl"


def vec(n, elements=NUMBER):
    return st.lists(elements, min_size=n, max_size=n)


def optional(draw, table: dict, key: str, strategy) -> None:
    if draw(st.booleans()):
        table[key] = draw(strategy)


@st.composite
def documents(draw, rails=True):
    """A valid experiment document (dict), with its camera, region and mesh names unique."""
    title = st.text(st.characters(min_codepoint=32, max_codepoint=0x2FF, exclude_characters="/\\"),
                    min_size=1, max_size=20).filter(str.isprintable)
    doc = {"experiment": {"name": draw(title)}}
    optional(draw, doc["experiment"], "description", st.text(max_size=30))
    ev = {}
    optional(draw, ev, "sample_spacing_mm", st.floats(1, 100))
    optional(draw, ev, "incidence_limit_deg", st.floats(1, 89.9))
    optional(draw, ev, "patch_mm", st.floats(0.5, 50))
    optional(draw, ev, "min_cameras", st.integers(1, 4))
    if ev or draw(st.booleans()):
        doc["evaluation"] = ev

    mesh_names = draw(st.lists(NAMES, min_size=1, max_size=3, unique=True))
    doc["mesh"] = []
    for i, name in enumerate(mesh_names):
        mesh = {"name": name, "file": "plate.stl"}
        if i == 0:
            mesh["role"] = "specimen"
        else:
            optional(draw, mesh, "role", st.sampled_from(["specimen", "obstacle"]))
        optional(draw, mesh, "unit", st.sampled_from(["m", "cm", "mm", "in", "ft"]))
        optional(draw, mesh, "albedo", st.floats(0, 1))
        optional(draw, mesh, "metal", st.booleans())
        doc["mesh"].append(mesh)

    region_names = draw(st.lists(NAMES, min_size=1, max_size=3, unique=True))
    doc["region"] = []
    for name in region_names:
        region = {"name": name, "mesh": mesh_names[0],
                  "normal": draw(vec(3).filter(lambda v: np.linalg.norm(v) > 1e-3))}
        if draw(st.booleans()):
            lo = draw(vec(3, REAL))
            region["box_min_m"] = lo
            region["box_max_m"] = [x + draw(st.floats(0.01, 10)) for x in lo]
        optional(draw, region, "importance", st.floats(0.1, 10))
        optional(draw, region, "normal_tolerance_deg", st.floats(0, 89))
        optional(draw, region, "min_cameras", st.integers(1, 5))
        doc["region"].append(region)

    rail_names = draw(st.lists(NAMES, max_size=2 if rails else 0, unique=True))
    on_rail = bool(rail_names) and draw(st.integers(0, 3)) == 0     # rail positions cost JAX calls
    if rail_names:
        doc["rail"] = []
    for name in rail_names:
        start = draw(vec(3, REAL))
        steps = draw(st.lists(vec(3, st.floats(0.1, 5)), min_size=1, max_size=3))
        points = [start]
        for step in steps:
            points.append([p + s for p, s in zip(points[-1], step)])
        rail = {"name": name, "control_points_m": points}
        optional(draw, rail, "degree", st.integers(1, len(points) - 1))
        optional(draw, rail, "weights", st.lists(st.floats(0.1, 10), min_size=len(points), max_size=len(points)))
        doc["rail"].append(rail)

    camera_names = draw(st.lists(NAMES, min_size=1, max_size=4, unique=True))
    spots = draw(st.lists(st.tuples(st.integers(-50, 50), st.integers(-50, 50), st.integers(-50, 50)),
                          min_size=len(camera_names), max_size=len(camera_names), unique=True))
    doc["camera"] = []
    for k, (name, spot) in enumerate(zip(camera_names, spots)):
        width, height = draw(st.integers(16, 8000)), draw(st.integers(16, 8000))
        cam = {"name": name, "pixels": [width, height], "focal_mm": draw(st.floats(0.5, 5000))}
        sensor_width = draw(st.floats(1, 60))
        if draw(st.booleans()):
            cam["sensor_mm"] = [sensor_width, sensor_width * height / width]
        else:
            cam["sensor_width_mm"] = sensor_width
        if on_rail and k == 0:        # one camera on a rail (the others fixed: no coincidence)
            cam["rail"] = draw(st.sampled_from(rail_names))
            cam["u"] = draw(st.floats(0, 1))
            cam["offset_m"] = [100.0, 100.0, 100.0 + draw(st.floats(0, 1))]
        else:
            cam["position_m"] = list(spot)
        if draw(st.booleans()):
            cam["target_m"] = [spot[0] + 0.5, spot[1] + 0.25, -200.0]
        else:
            cam["pan_deg"], cam["tilt_deg"] = draw(REAL), draw(st.floats(-90, 90))
        optional(draw, cam, "roll_deg", REAL)
        optional(draw, cam, "principal_offset_px", vec(2))
        optional(draw, cam, "body", st.booleans())
        if draw(st.booleans()):
            cam["f_number"], cam["focus_m"] = draw(st.floats(1, 32)), draw(st.floats(0.1, 10))
        doc["camera"].append(cam)

    lights = draw(st.lists(NAMES, max_size=2, unique=True))
    if lights:
        doc["light"] = [{"name": n, "position_m": [0, 0, 2 + i], "target_m": draw(vec(3, st.floats(-100, 1))),
                         "size_m": draw(vec(2, st.floats(0.01, 2))), "radiance": draw(st.floats(0.1, 100))}
                        for i, n in enumerate(lights)]

    sp = {}
    texel = draw(st.floats(0.05, 0.6))
    optional(draw, sp, "texel_mm", st.just(texel))
    optional(draw, sp, "dot_diameter_mm", st.floats(3.01 * max(texel, 0.25), 20))
    optional(draw, sp, "coverage", st.floats(0.01, 0.95))
    optional(draw, sp, "strokes", st.integers(0, 20))
    optional(draw, sp, "tile_texels", st.integers(64, 4096))
    optional(draw, sp, "seed", st.integers(0, 2**31))
    optional(draw, sp, "white_albedo", st.floats(0.5, 1))
    optional(draw, sp, "black_albedo", st.floats(0, 0.49))
    doc["speckle"] = sp

    sensor = {}
    bits = draw(st.integers(8, 16))
    optional(draw, sensor, "bit_depth", st.just(bits))
    optional(draw, sensor, "quantum_efficiency", st.floats(0.01, 1))
    optional(draw, sensor, "full_well_e", st.floats(100, 1e6))
    optional(draw, sensor, "read_noise_e", st.floats(0, 100))
    optional(draw, sensor, "gain_dn_per_e", st.floats(0.001, 10))
    optional(draw, sensor, "offset_dn", st.floats(0, 2**8 - 2))
    optional(draw, sensor, "photons_per_unit", st.floats(1, 1e6))
    doc["sensor"] = sensor

    render = {}
    optional(draw, render, "spp", st.integers(1, 1024))
    optional(draw, render, "scale", st.floats(0.01, 4))
    optional(draw, render, "seed", st.integers(0, 1000))
    optional(draw, render, "ambient_radiance", st.floats(0, 10))
    optional(draw, render, "image_format", st.sampled_from(["png", "tiff"]))
    optional(draw, render, "exr", st.booleans())
    doc["render"] = render

    opt = {}
    free = draw(st.lists(st.sampled_from(["u", "pan", "tilt", "roll", "lens"]), min_size=1, unique=True))
    opt["free"] = free
    if "lens" in free or draw(st.booleans()):
        opt["lenses_mm"] = draw(st.lists(st.floats(1, 1000), min_size=1, max_size=4))
    optional(draw, opt, "cameras", st.lists(st.sampled_from(camera_names), unique=True))
    optional(draw, opt, "regions", st.lists(st.sampled_from(region_names), min_size=1, unique=True))
    optional(draw, opt, "min_axis_angle_deg", st.floats(0, 90))
    optional(draw, opt, "clearance_m", st.floats(0, 1))
    optional(draw, opt, "max_obscuration", st.floats(0, 1))
    optional(draw, opt, "assign_fraction", st.floats(0.01, 1))
    for key in ("starts", "rounds", "max_steps"):
        optional(draw, opt, key, st.integers(1, 50))
    optional(draw, opt, "seed", st.integers(0, 100))
    doc["optimize"] = opt
    return doc


JUNK = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(),
              st.text(max_size=8), st.sampled_from(["../x", "a/b", "", ".", "..", "\x00", "x\ny", "plate.toml",
                                                     "plate.stl", "mm", "specimen", "u", "lens"])),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=4), inner, max_size=3)),
    max_leaves=8)


def same(a, b, path="e") -> None:
    """Assert that two parsed values are equal: dataclasses field by field, arrays and floats to
    1e-11 relative (the file keeps 12 significant digits), everything else exactly."""
    if dataclasses.is_dataclass(a):
        assert type(a) is type(b), path
        for f in dataclasses.fields(a):
            same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, (tuple, list)):
        assert isinstance(b, type(a)) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            same(x, y, f"{path}[{i}]")
    elif isinstance(a, (np.ndarray, float)) and not isinstance(a, bool):
        x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        assert type(a) is type(b) and x.shape == y.shape, path
        assert np.allclose(x, y, rtol=1e-11, atol=1e-14) and np.array_equal(np.isinf(x), np.isinf(y)), \
            (path, a, b)
    else:
        assert type(a) is type(b) and a == b, (path, a, b)

