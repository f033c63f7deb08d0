"""Every class of bad input gives one clear error naming the file, the field and the fix."""

import math

import numpy as np
import pytest
import trimesh

from vdo.config import experiment as config
from vdo.commands.cli import main
from vdo.core.errors import ConfigError
from vdo.meshes.mesh import faces_against
from conftest import mesh_tables, region_tables
from vdo.scene import cameras_of, load_meshes, sample_regions


def broken(plate_experiment, old, new):
    path = plate_experiment()
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))
    return path


CASES = [
    # (replace this, with this, field named in the error, words in the message)
    ('focal_mm = 24', 'focal_length = 24', 'camera "down".focal_length', "did you mean 'focal_mm'"),
    ('file = "plate.stl"', 'file = "missing.stl"', 'mesh "plate".file', "does not exist"),
    ('file = "plate.stl"', 'file = "' + "x" * 300 + '.stl"', 'mesh "plate".file', "does not exist"),
    ('unit = "mm"', 'unit = "millimetre"', 'mesh "plate".unit', "must be one of m, cm, mm, in, ft"),
    ('u = 0.5', 'u = 1.3', 'camera "down".u', "off rail 'overhead'"),
    ('rail = "overhead"\nu', 'rail = "overhed"\nu', 'camera "down".rail', "no [[rail]] named 'overhed'"),
    ('focal_mm = 24', 'focal_mm = nan', 'camera "down".focal_mm', "finite number"),
    ('focal_mm = 24', 'focal_mm = -24', 'camera "down".focal_mm', "must be positive"),
    ('sensor_mm = [22.2, 14.8]', 'sensor_mm = [22.2, -14.8]', 'camera "down".sensor_mm', "positive"),
    ('sensor_mm = [22.2, 14.8]', 'sensor_mm = [22.2, 18.0]', 'camera "down".sensor_mm', "non-square pixels"),
    ('pixels = [600, 400]', 'pixels = [600.5, 400]', 'camera "down".pixels', "whole numbers"),
    ('sample_spacing_mm = 10', 'sample_spacing_mm = 0', 'evaluation.sample_spacing_mm', "positive"),
    ('sample_spacing_mm = 10', 'sample_spacing_mm = 1e300', 'evaluation.sample_spacing_mm', "within ±1e+12"),
    ('incidence_limit_deg = 75', 'incidence_limit_deg = 95', 'evaluation.incidence_limit_deg', "[1.0, 89.9]"),
    ('normal = [0, 0, 1]', 'normal = [0, 0]', 'region "top".normal', "list of 3"),
    ('role = "specimen"', 'role = "obstacle"', 'mesh', 'needs at least one mesh with role = "specimen"'),
    ('mesh = "plate"', 'mesh = "plates"', 'region "top".mesh', 'must name a mesh with role "specimen"'),
    ('name = "down"', 'name = "down"\nposition_m = [0, 0, 1]', 'camera "down".rail', "either rail"),
    ('pan_deg = 0', 'target_m = [0, 0, 0]\npan_deg = 0', 'camera "down".target_m', "either target_m"),
    ('control_points_m = [[-1.0, 0.0, 1.5], [1.0, 0.0, 1.5]]', 'control_points_m = [[0, 0, 1]]',
     'rail "overhead".control_points_m', "at least 2"),
    ('normal = [0, 0, 1]', 'normal = [1, 0, 0]\nbox_min_m = [0.6, -1, -1]\nbox_max_m = [0.7, 1, 1]',
     'region "top"', "selects no face"),
]


@pytest.mark.parametrize("old,new,field,words", CASES, ids=[c[2] + ":" + c[3] for c in CASES])
def test_bad_input_names_file_field_and_fix(plate_experiment, capsys, tmp_path, old, new, field, words):
    path = broken(plate_experiment, old, new)
    out = tmp_path / "out"
    assert main(["evaluate", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    assert err.startswith(f"error: {path}: {field}: ") or err.startswith(f"error: {path}: {field} ")
    assert words in err
    assert not out.exists()
    assert not list(tmp_path.glob(".out.partial*"))


def test_invalid_toml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[experiment\nname = 'x'")
    with pytest.raises(ConfigError, match="is not valid TOML"):
        config.load(bad)
    with pytest.raises(ConfigError, match="file not found"):
        config.load(tmp_path / "nope.toml")


def test_unreadable_mesh_content(plate_experiment):
    path = plate_experiment()
    (path.parent / "plate.stl").write_bytes(b"solid junk\n this is not an stl\n")
    exp = config.load(path)
    with pytest.raises(ConfigError, match=r'mesh "plate"\.file: .*(cannot read|holds no triangles)'):
        load_meshes(**mesh_tables(exp))


BLOCK = '[[mesh]]\nname = "block"\nfile = "block.stl"\nunit = "mm"\nrole = "obstacle"\n'


@pytest.mark.parametrize("flipped", [(), (0, 3, 5)])
def test_faces_wound_against_their_neighbours_are_said_once(plate_experiment, capsys, flipped):
    """A closed box with some faces turned over (their vertex order reversed, so that they run
    each shared edge the way their neighbours do): `vdo check` says so in one line naming the
    mesh, its file and how many faces; a box as trimesh makes it is silent."""
    path = plate_experiment(extra_meshes=BLOCK)
    box = trimesh.creation.box(extents=[100.0, 100.0, 100.0])
    box.apply_translation([300.0, 300.0, 50.0])
    faces = box.faces.copy()
    faces[list(flipped)] = faces[list(flipped)][:, ::-1]
    trimesh.Trimesh(box.vertices, faces, process=False).export(path.parent / "block.stl")
    assert main(["check", str(path)]) == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "wound against" in line]
    assert said == ([f"mesh 'block' (block.stl): {len(flipped)} face(s) wound against their neighbours "
                     "(their normals point the other way: the renders draw them dark and a region's "
                     "normal selector and area take them wrong): fix the winding in the file (e.g. "
                     "trimesh's repair.fix_winding)"] if flipped else []), said


def test_the_faces_against_are_the_smaller_class_and_a_one_sided_strip_has_none():
    """Of a box's 12 faces, 7 turned over leave 5 wound against the rest (the smaller class); a
    Moebius strip has no consistent winding (None)."""
    box = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    faces = box.faces.copy()
    faces[:7] = faces[:7, ::-1]
    assert faces_against(box.vertices, box.faces) == 0 and faces_against(box.vertices, faces) == 5
    turn = np.linspace(0, 2 * np.pi, 20, endpoint=False)
    edge = np.array([[(1 + w * np.cos(t / 2)) * np.cos(t), (1 + w * np.cos(t / 2)) * np.sin(t),
                      w * np.sin(t / 2)] for t in turn for w in (-0.2, 0.2)])
    a, b = 2 * np.arange(20), 2 * np.arange(20) + 1
    c, d = np.r_[a[1:], 1], np.r_[b[1:], 0]           # the last rung joins the first turned over
    strip = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    assert faces_against(edge, strip) is None


def test_non_planar_region_is_refused(plate_experiment):
    path = broken(plate_experiment, 'normal = [0, 0, 1]', 'normal = [0, 0, 1]\nnormal_tolerance_deg = 89')
    # a stepped specimen: two top faces 50 mm apart selected by one region
    a = trimesh.creation.box(extents=[500, 1000, 10])
    a.apply_translation([-250, 0, -5])
    b = trimesh.creation.box(extents=[500, 1000, 60])
    b.apply_translation([250, 0, 25])
    trimesh.util.concatenate([a, b]).export(path.parent / "plate.stl")
    exp = config.load(path)
    with pytest.raises(ConfigError, match=r'region "top": selects faces that are not coplanar'):
        sample_regions(load_meshes(**mesh_tables(exp)), **region_tables(exp))


def test_defaults_and_units_are_resolved(plate_experiment):
    exp = config.load(plate_experiment())
    assert exp.meshes[0].scale == 0.001
    assert exp.evaluation.incidence_limit == pytest.approx(math.radians(75))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    assert cam.pixel_size == pytest.approx(22.2e-3 / 600)
    assert cam.position.tolist() == pytest.approx([0.0, 0.0, 1.5])


def test_vdo_set_writes_fields_over_the_file(plate_experiment, monkeypatch):
    """VDO_SET gives the experiment that the file edited by hand gives: a table's field, a field
    of every [[camera]], a table the file lacks; items for a validation file's tables are left
    alone; a malformed item is one line naming VDO_SET."""
    from conftest import CAMERAS

    path = plate_experiment(spacing=25, cameras=CAMERAS)
    text = path.read_text()
    assert "sample_spacing_mm = 25" in text and text.count("focal_mm = 24") == 2
    edited = path.with_name("edited.toml")
    edited.write_text(text.replace("sample_spacing_mm = 25", "sample_spacing_mm = 60")
                      .replace("focal_mm = 24", "focal_mm = 35") + "\n[optimize]\nstarts = 1\n")
    by_hand = config.load(edited)
    monkeypatch.setenv("VDO_SET", "evaluation.sample_spacing_mm = 60; camera.*.focal_mm = 35;"
                                  " optimize.starts = 1; defaults.spp = 4; validation.seeds = 2")
    overridden = config.load(path)
    assert overridden.evaluation == by_hand.evaluation and overridden.optimize == by_hand.optimize
    assert [c.focal_length for c in overridden.camera_specs] == [0.035, 0.035] == [
        c.focal_length for c in by_hand.camera_specs]
    monkeypatch.setenv("VDO_SET", "evaluation.sample_spacing_mm = -1")
    with pytest.raises(ConfigError, match=r"evaluation.sample_spacing_mm: must be positive"):
        config.load(path)
    for bad in ("evaluation.sample_spacing_mm", "evaluation = 3", "camera.a.cam1.focal_mm = 35",
                "evaluation.sample_spacing_mm = [1,"):
        monkeypatch.setenv("VDO_SET", bad)
        with pytest.raises(ConfigError) as err:
            config.load(path)
        assert str(err.value).startswith(f"VDO_SET: {bad}: write TABLE.FIELD = VALUE")
