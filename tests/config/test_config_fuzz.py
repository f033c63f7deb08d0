"""Fuzzing the input side: mutated experiment documents, mutated bytes of an experiment file and
mutated mesh files. Every outcome is a validated experiment (which then round-trips) or one
ConfigError naming the file and a field: never another exception.

VDO_FUZZ_SCALE=20 multiplies the number of cases (the suite runs about 1,100)."""

import copy
import math
import os
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w
import trimesh
from config_documents import JUNK, NO_SHRINK, plate_file, same
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from conftest import mesh_tables
from vdo import scene
from vdo.config import experiment as config
from vdo.core.errors import ConfigError

SCALE = int(os.environ.get("VDO_FUZZ_SCALE", "1"))


def fuzz(examples):
    return settings(max_examples=examples * SCALE, deadline=None, derandomize=True, database=None,
                    phases=NO_SHRINK,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.function_scoped_fixture])


BASE = {   # every table; cameras fixed and on a rail, aimed both ways
    "experiment": {"name": "fuzz base", "description": "all tables"},
    "evaluation": {"sample_spacing_mm": 20, "incidence_limit_deg": 70, "patch_mm": 8, "min_cameras": 1},
    "mesh": [{"name": "plate", "file": "plate.stl", "unit": "mm", "role": "specimen", "albedo": 0.6},
             {"name": "wall", "file": "plate.stl", "unit": "mm", "role": "obstacle", "metal": True}],
    "region": [{"name": "top", "mesh": "plate", "normal": [0, 0, 1], "box_min_m": [-0.3, -0.3, -0.1],
                "box_max_m": [0.2, 0.3, 0.1], "importance": 2, "normal_tolerance_deg": 4, "min_cameras": 1}],
    "rail": [{"name": "bar", "control_points_m": [[-1, 0, 1.5], [0, 0.2, 1.6], [1, 0, 1.5]], "degree": 2,
              "weights": [1, 2, 1]}],
    "camera": [{"name": "c1", "sensor_mm": [22.2, 14.8], "pixels": [600, 400], "focal_mm": 24,
                "rail": "bar", "u": 0.3, "offset_m": [0, 0, 0.1], "pan_deg": 0, "tilt_deg": -80,
                "roll_deg": 2, "f_number": 8, "focus_m": 1.5},
               {"name": "c2", "sensor_width_mm": 22.2, "pixels": [600, 400], "focal_mm": 35,
                "position_m": [0.5, -0.5, 1.2], "target_m": [0, 0, 0], "principal_offset_px": [1.5, -2],
                "body": False}],
    "light": [{"name": "led", "position_m": [0, -1, 2], "target_m": [0, 0, 0], "size_m": [0.3, 0.2],
               "radiance": 50}],
    "speckle": {"dot_diameter_mm": 3, "coverage": 0.4, "strokes": 5, "texel_mm": 0.5, "tile_texels": 512,
                "seed": 3, "white_albedo": 0.9, "black_albedo": 0.1},
    "sensor": {"quantum_efficiency": 0.5, "full_well_e": 10000, "read_noise_e": 3, "bit_depth": 10,
               "offset_dn": 10, "photons_per_unit": 5000},
    "render": {"spp": 8, "scale": 0.5, "seed": 2, "ambient_radiance": 0.1, "image_format": "tiff", "exr": True},
    "optimize": {"free": ["u", "pan", "tilt", "lens"], "lenses_mm": [24, 35], "cameras": ["c1"],
                 "regions": ["top"], "min_axis_angle_deg": 20, "clearance_m": 0.1, "max_obscuration": 0.02,
                 "assign_fraction": 0.4, "starts": 2, "rounds": 2, "max_steps": 10, "seed": 1},
}
NEAR = st.sampled_from([0, -1, 1, 0.5, 1e-9, -1e-9, 1e308, -1e308, math.inf, -math.inf, math.nan, 2**63,
                        True, "1", [], [1, 2], [1, 2, 3], [[0, 0, 0]], {}])


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("fuzz")
    plate_file(path)
    return path


def locations(doc):
    """(container, key) of every value in the document, tables and arrays included."""
    out, todo = [], [doc]
    while todo:
        node = todo.pop()
        keys = list(node) if isinstance(node, dict) else range(len(node))
        for key in keys:
            out.append((node, key))
            if isinstance(node[key], (dict, list)):
                todo.append(node[key])
    return out


@st.composite
def mutated(draw):
    doc = copy.deepcopy(BASE)
    for _ in range(draw(st.integers(1, 3))):
        places = locations(doc)
        if not places:
            break
        node, key = draw(st.sampled_from(places))
        action = draw(st.sampled_from(["junk", "near", "scale", "delete", "unknown"]))
        if action == "junk":
            node[key] = copy.deepcopy(draw(JUNK))
        elif action == "near":
            node[key] = copy.deepcopy(draw(NEAR))      # the constants must stay as they are
        elif action == "scale" and isinstance(node[key], (int, float)) and not isinstance(node[key], bool):
            node[key] = node[key] * draw(st.sampled_from([-1, 0, 1e-3, 1e3, 1e9, 0.5]))
        elif action == "delete":
            del node[key]
        elif action == "unknown" and isinstance(node[key], dict):
            node[key][draw(st.text(min_size=1, max_size=12))] = copy.deepcopy(draw(JUNK))
    return doc


def check_outcome(path: Path, run) -> object:
    """run() either succeeds or raises one ConfigError naming `path` and a field, in one line."""
    try:
        result = run()
        event("accepted")
        return result
    except ConfigError as err:
        event(f"ConfigError: {err.message[:25]}")
        assert err.file == str(path) and str(err).startswith(f"{path}: "), str(err)
        assert "\n" not in str(err) and "\r" not in str(err), str(err)
        return err


def test_base_document_is_valid(folder):
    exp = config.parse(BASE, folder / "exp.toml")
    assert exp.camera_specs[0].rail == "bar" and exp.optimize.lenses == (0.024, 0.035)


@fuzz(700)
@given(doc=mutated())
def test_mutated_documents(folder, doc):
    path = (folder / "exp.toml").resolve()
    result = check_outcome(path, lambda: config.parse(doc, path))
    if isinstance(result, ConfigError):
        assert result.field, str(result)
    else:
        same(result, config.parse(tomllib.loads(tomli_w.dumps(result.to_dict())), path))


@fuzz(200)
@given(data=st.data(), encoding=st.sampled_from(["utf-8"] * 4 + ["utf-16", "utf-32", "latin-1", "cp1252"]),
       cut=st.floats(0, 1), noise=st.lists(st.tuples(st.floats(0, 1), st.binary(min_size=1, max_size=4)),
                                          max_size=3))
def test_mutated_file_bytes(folder, data, encoding, cut, noise):
    text = tomli_w.dumps(BASE).replace("fuzz base", "fuzz bäse")
    raw = bytearray(text.encode(encoding, errors="replace"))
    if data.draw(st.booleans()):
        del raw[int(cut * len(raw)):]
    for where, junk in noise:
        i = int(where * len(raw))
        raw[i:i + len(junk)] = junk
    path = (folder / "bytes.toml").resolve()
    path.write_bytes(bytes(raw))
    check_outcome(path, lambda: config.load(path))


def mesh_bytes(kind: str, scale: float) -> bytes:
    box = trimesh.creation.box(extents=[200, 200, 10])
    box.apply_scale(scale)
    box.apply_translation([0, 0, -5 * scale])
    file_type, options = {"stl": ("stl", {}), "stl_ascii": ("stl_ascii", {}), "obj": ("obj", {}),
                          "ply": ("ply", {}), "ply_ascii": ("ply", {"encoding": "ascii"})}[kind]
    data = trimesh.exchange.export.export_mesh(box, None, file_type=file_type, **options)
    return data if isinstance(data, bytes) else data.encode()


MESHES = {(kind, scale): mesh_bytes(kind, scale) for kind in ("stl", "stl_ascii", "obj", "ply", "ply_ascii")
          for scale in (1.0, 1e3, 1e30)}


@fuzz(200)
@given(key=st.sampled_from(sorted(MESHES)), cut=st.one_of(st.none(), st.floats(0, 1)),
       flips=st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), max_size=3),
       prefix=st.one_of(st.just(b""), st.sampled_from([b"\x89PNG\r\n\x1a\n", b"%PDF-1.4\n", b"PK\x03\x04",
                                                       b"\xff\xd8\xff"])),
       unit=st.sampled_from(["mm", "m", "in"]))
def test_mutated_mesh_files(folder, key, cut, flips, prefix, unit):
    kind, _ = key
    raw = bytearray(prefix + MESHES[key])
    if cut is not None:
        del raw[int(cut * len(raw)):]
    for where, value in flips:
        if raw:
            raw[min(int(where * len(raw)), len(raw) - 1)] = value
    name = f"mesh.{kind.split('_')[0]}"
    (folder / name).write_bytes(bytes(raw))
    doc = copy.deepcopy(BASE)
    doc["mesh"][0] |= {"file": name, "unit": unit}
    del doc["rail"], doc["camera"][0]
    doc["optimize"]["cameras"] = ["c2"]
    path = (folder / "mesh.toml").resolve()
    exp = config.parse(doc, path)
    result = check_outcome(path, lambda: scene.load_meshes(**mesh_tables(exp)))
    if isinstance(result, ConfigError):
        assert result.field in ('mesh "plate".file', 'camera "c2"'), str(result)
    else:
        assert all(np.all(np.isfinite(m.vertices)) and np.ptp(m.vertices, axis=0).max() <= 100 for m in result)
