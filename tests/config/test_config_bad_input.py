"""Regression tests for bad input found by a harness of malformed configs and meshes: each ends in
one ConfigError naming the file, the field and the fix, never a traceback, before heavy work."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest
import trimesh
from hypothesis import given, seed, settings
from hypothesis import strategies as st

from vdo import scene
from vdo.config import experiment as config
from vdo.config.schema import NAME_PATTERN
from conftest import DOWN_CAMERA, mesh_tables, region_tables
from vdo.core.errors import ConfigError


def edited(path, *edits):
    text = path.read_text()
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    path.write_text(text)
    return path


def error(path, stage=config.load) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        stage(path)
    err = info.value
    assert err.file == str(path.resolve()) and "\n" not in str(err)
    return err


def meshes_of(path):
    return scene.load_meshes(**mesh_tables(config.load(path)))


def samples_of(path):
    exp = config.load(path)
    return scene.sample_regions(scene.load_meshes(**mesh_tables(exp)), **region_tables(exp))


# --------------------------------------------------------------------------------------------
# Names that become file names
# --------------------------------------------------------------------------------------------
BAD_NAMES = ["../../evil_cam", "a/b", "a\\\\b", "..", ".hidden", "-x", "cam\\u0001", "x" * 65, "sp ace"]


@pytest.mark.parametrize("bad", BAD_NAMES)
@pytest.mark.parametrize("table,old", [("camera", 'name = "down"'), ("mesh", 'name = "plate"'),
                                       ("region", 'name = "top"'), ("rail", 'name = "overhead"')])
def test_names_used_in_paths_are_restricted(plate_experiment, table, old, bad):
    err = error(edited(plate_experiment(), (old, f'name = "{bad}"')))
    assert err.field == f"{table}[0].name"
    assert NAME_PATTERN in err.message and "names output files" in err.message


def test_experiment_name_is_a_title_without_separators(plate_experiment):
    err = error(edited(plate_experiment(), ('name = "plate under one camera"', 'name = "a/../b"')))
    assert err.field == "experiment.name" and "'/'" in err.message


# --------------------------------------------------------------------------------------------
# Files that are not UTF-8 TOML
# --------------------------------------------------------------------------------------------
def test_non_utf8_files(plate_experiment):
    path = plate_experiment()
    text = path.read_text()
    path.write_bytes(text.encode("utf-16"))
    assert "UTF-16" in error(path).message
    path.write_bytes(text.replace("plate under one camera", "plaque à une caméra").encode("latin-1"))
    assert error(path).message.startswith("is not UTF-8 text (byte 0xe0 on line 3)")
    path.write_bytes(bytes(range(256)) * 4)
    assert "not UTF-8" in error(path).message


def test_deep_nesting(plate_experiment):
    path = plate_experiment()
    path.write_text(path.read_text() + "\n[render]\nseed = " + "[" * 5000 + "]" * 5000 + "\n")
    assert "nested too deep" in error(path).message
    path = edited(plate_experiment(), ("normal = [0, 0, 1]", "normal = " + "[" * 100 + "1" + "]" * 100))
    assert error(path).field == 'region "top".normal'


# --------------------------------------------------------------------------------------------
# Wrong types
# --------------------------------------------------------------------------------------------
LIGHT = '\n[[light]]\nname = "p"\nposition_m = [0, 0, 1]\ntarget_m = [0, 0, 0]\nradiance = 1\n'
TYPES = [
    ('normal = [0, 0, 1]', 'normal = ["1", "1", "1"]', 'region "top".normal', "list of 3 finite numbers"),
    ('u = 0.5', 'u = 0.5\noffset_m = ["0", "0", "0.1"]', 'camera "down".offset_m', "list of 3"),
    ('rail = "overhead"\nu = 0.5', 'position_m = ["0", "0", "1.5"]', 'camera "down".position_m', "list of 3"),
    ('[[camera]]', LIGHT + 'size_m = ["0.3", "0.3"]\n[[camera]]', 'light "p".size_m', "list of 2"),
    ('name = "plate under one camera"', 'name = "x"\ndescription = 5', "experiment.description", "string"),
    ('pixels = [600, 400]', 'pixels = [600.0, 400]', 'camera "down".pixels', "whole numbers"),
    ('pixels = [600, 400]', 'pixels = [true, 400]', 'camera "down".pixels', "whole numbers"),
    ('focal_mm = 24', 'focal_mm = true', 'camera "down".focal_mm', "finite number"),
    ('focal_mm = 24', 'focal_mm = "24"', 'camera "down".focal_mm', "finite number"),
    ('sample_spacing_mm = 10', 'sample_spacing_mm = [10]', "evaluation.sample_spacing_mm", "finite number"),
    ('[[camera]]', '[render]\nspp = 4.0\n[[camera]]', "render.spp", "integer"),
    ('[[camera]]', '[optimize]\nfree = "u"\n[[camera]]', "optimize.free", "must list some of"),
    ('[[camera]]', '[sensor]\nbit_depth = 12.0\n[[camera]]', "sensor.bit_depth", "integer"),
    ('[[camera]]', '[sensor]\nbit_depth = 20\n[[camera]]', "sensor.bit_depth", "8..16"),
    ('[[region]]', '[region]', "region", "needs at least one [[region]] table"),
    ('[[camera]]', '[analysis]\ninterpolant = "lanczos"\n[[camera]]', "analysis.interpolant",
     "cubic, quintic, keys"),
]


@pytest.mark.parametrize("old,new,field,words", TYPES, ids=[t[2] + ":" + t[1][:20] for t in TYPES])
def test_wrong_types(plate_experiment, old, new, field, words):
    err = error(edited(plate_experiment(), (old, new)))
    assert (err.field, words in err.message) == (field, True), str(err)


def test_speckle_image_must_be_an_image(plate_experiment):
    path = plate_experiment()
    (path.parent / "other.toml").write_text("[x]\n")
    (path.parent / "renamed.png").write_text("[x]\n")
    text = path.read_text()
    path.write_text(text + '\n[speckle]\nimage = "other.toml"\n')
    assert (error(path).field, "is not an image (PNG" in error(path).message) == ("speckle.image", True)
    path.write_text(text + '\n[speckle]\nimage = "renamed.png"\n')
    assert "is not an image" in error(path).message
    path.write_text(text + '\n[speckle]\nimage = "plate.stl"\n')
    assert error(path).field == "speckle.image"


# --------------------------------------------------------------------------------------------
# Absurd but parseable setups
# --------------------------------------------------------------------------------------------
def two_cameras(u2, name2="b"):
    cam = textwrap.dedent("""
        [[camera]]
        name = "{name}"
        sensor_mm = [22.2, 14.8]
        pixels = [600, 400]
        focal_mm = 24
        rail = "overhead"
        u = {u}
        pan_deg = 0
        tilt_deg = -90
        """)
    return cam.format(name="a", u=0.5) + cam.format(name=name2, u=u2)


ABSURD = [
    ('focal_mm = 24', 'focal_mm = 1e-6', 'camera "down".focal_mm', "[0.5, 5000.0]"),
    ('focal_mm = 24', 'focal_mm = 1e6', 'camera "down".focal_mm', "real lenses"),
    ('pixels = [600, 400]', 'pixels = [60000000, 40000000]', 'camera "down".pixels', "Mpx per camera"),
    ('[-1.0, 0.0, 1.5], [1.0', '[-1.0, 0.0, 1.5], [-1.0, 0.0, 1.5], [1.0', 'rail "overhead".control_points_m',
     "points 0 and 1 coincide"),
    ('[[camera]]', '[sensor]\nquantum_efficiency = 1.5\n[[camera]]', "sensor.quantum_efficiency", "(0, 1]"),
]


@pytest.mark.parametrize("old,new,field,words", ABSURD, ids=[a[2] for a in ABSURD])
def test_absurd_values(plate_experiment, old, new, field, words):
    err = error(edited(plate_experiment(), (old, new)))
    assert (err.field, words in err.message) == (field, True), str(err)


def test_coincident_cameras(plate_experiment):
    err = error(plate_experiment(cameras=two_cameras(0.5)))
    assert err.field == 'camera "b"' and "cannot share one pose" in err.message
    apart = config.load(plate_experiment(cameras=two_cameras(0.51)))
    assert len(scene.cameras_of(apart.camera_specs, apart.rails)) == 2   # 2 cm apart


def test_camera_inside_a_mesh(plate_experiment):
    def at(z, extra=""):
        return edited(plate_experiment(extra_meshes=extra, files=[("block.stl", [100, 100, 100], [0, 0, 500])]),
                      ('rail = "overhead"\nu = 0.5', f"position_m = [0, 0, {z}]"))
    err = error(at(-0.005), meshes_of)                # inside the 10 mm plate
    assert err.field == 'camera "down".position_m' and "inside mesh 'plate'" in err.message
    block = '[[mesh]]\nname = "block"\nfile = "block.stl"\nunit = "mm"\n'
    assert "inside mesh 'block'" in error(at(0.52, block), meshes_of).message
    assert len(meshes_of(at(0.6, block))) == 2        # just above the block: accepted
    assert len(meshes_of(at(0.005))) == 1             # 5 mm above the plate: accepted


def test_mesh_extent_suggests_the_unit(plate_experiment):
    err = error(edited(plate_experiment(), ('unit = "mm"', 'unit = "m"')), meshes_of)
    assert err.field == 'mesh "plate".file'
    assert "spans 1000 m" in err.message and 'is the mesh in mm? set unit = "mm"' in err.message


def test_stray_vertex(plate_experiment):
    path = plate_experiment()
    box = trimesh.load(path.parent / "plate.stl", process=False)
    vertices = np.asarray(box.vertices).copy()
    vertices[0] = 1e30
    trimesh.Trimesh(vertices, box.faces, process=False).export(path.parent / "plate.stl")
    assert "far from the rest of the mesh" in error(path, meshes_of).message


def test_region_missing_a_mesh_in_the_wrong_unit(plate_experiment):
    # a 60 mm plate exported 500 mm off the origin, declared in metres: it spans 470..530 m
    path = plate_experiment()
    trimesh.creation.box(extents=[60, 60, 10]).apply_translation([500, 500, -5]).export(path.parent / "plate.stl")
    path = edited(path, ('unit = "mm"', 'unit = "m"'),
                  ("normal = [0, 0, 1]", "normal = [0, 0, 1]\nbox_min_m = [0.47, 0.47, -0.01]\n"
                                         "box_max_m = [0.53, 0.53, 0.01]"))
    err = error(path, samples_of)
    assert err.field == 'region "top"' and "selects no face" in err.message
    assert "the box misses the mesh, which spans [470.0, 470.0, -10.0]" in err.message
    assert "unit" in err.message


# --------------------------------------------------------------------------------------------
# Memory: the sample count is checked before sampling
# --------------------------------------------------------------------------------------------
def test_sample_count_is_capped_with_the_fix(plate_experiment):
    path = plate_experiment(spacing=0.5)              # 1 m^2 / (0.5 mm)^2 = 4,000,000 samples
    err = error(path, samples_of)
    assert err.field == "evaluation.sample_spacing_mm"
    assert "about 4,000,000 samples" in err.message and "raise sample_spacing_mm to 0.8 or more" in err.message
    exp = config.load(path)
    meshes = scene.load_meshes(**mesh_tables(exp))
    faces = scene.all_region_faces(meshes, **region_tables(exp, 0.8e-3))
    scene.check_sample_count(meshes, faces, 0.8e-3, path=exp.path)    # 1.56 M: the suggested fix fits
    with pytest.raises(ConfigError):
        scene.check_sample_count(meshes, faces, 0.7e-3, path=exp.path)   # 2.04 M


# --------------------------------------------------------------------------------------------
# Mesh files that are not meshes
# --------------------------------------------------------------------------------------------
def test_mesh_file_errors_say_what_is_wrong(plate_experiment):
    path = plate_experiment()
    stl = path.parent / "plate.stl"
    good = stl.read_bytes()
    cases = [(good[:300], "is not a valid binary STL: its header announces 12 triangles (684 bytes) "
                          "but the file has 300 bytes"),
             (b"\x89PNG\r\n\x1a\n" + bytes(100), "is a PNG file, not an STL mesh"),
             (b"", "is empty (0 bytes)"),
             (b"hello", "is neither ASCII STL"),
             (b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0\n", "")]
    for data, words in cases:
        stl.write_bytes(data)
        err = error(path, meshes_of)
        assert err.field == 'mesh "plate".file' and words in err.message, str(err)
        assert "charset_normalizer" not in err.message


# --------------------------------------------------------------------------------------------
# Region boxes that cut faces: the faces are split at the box, the area is the box's part
# --------------------------------------------------------------------------------------------
def test_box_cutting_faces_splits_them(plate_experiment):
    path = edited(plate_experiment(), ("normal = [0, 0, 1]", "normal = [0, 0, 1]\nbox_min_m = [-0.2, -1, -1]\n"
                                                             "box_max_m = [0.2, 1, 1]"))
    exp = config.load(path)
    meshes = scene.load_meshes(**mesh_tables(exp))
    (rf,) = scene.all_region_faces(meshes, **region_tables(exp))
    tm = meshes[0].trimesh
    assert tm.area_faces[rf.faces].sum() == pytest.approx(0.4, rel=1e-12)       # 0.4 m x 1 m
    assert tm.area == pytest.approx(2 * 1 + 4 * 0.01, rel=1e-12)                # surface unchanged
    assert trimesh.Trimesh(tm.vertices, tm.faces).is_watertight                  # no crack at the cut
    samples = scene.sample_regions(meshes, **region_tables(exp))
    assert len(samples) == 40 * 100 and samples.points[:, 0].min() > -0.2


@pytest.mark.xfail(strict=True, reason="known bug: scene.split_at_boxes with a box corner on a "
                   "mesh edge (the plate's diagonal through its centre) leaves a crack, and a "
                   "vertex within the split tolerance of a plane is taken as on it")
@pytest.mark.parametrize("lo, size, turn", [((0.0, 0.0), (0.5, 0.5), 1e-9),
                                            ((0.0, 0.0), (0.5, 0.5), 0.001953125)])
def test_split_at_a_box_corner_on_a_mesh_edge(lo, size, turn):
    """The degenerate cases hypothesis found (recorded here until split_at_boxes handles them)."""
    test_split_area_equals_box_overlap.hypothesis.inner_test(lo=lo, size=size, turn=turn)


@seed(20261202)   # one sequence of examples wherever the checkout lies (derandomize hashed it)
@settings(max_examples=60, deadline=None, database=None)
@given(lo=st.tuples(st.floats(-0.6, 0.4), st.floats(-0.6, 0.4)),
       size=st.tuples(st.floats(0.05, 0.6), st.floats(0.05, 0.6)),
       turn=st.floats(0, np.pi))
def test_split_area_equals_box_overlap(lo, size, turn):
    """A plate turned about z, cut by an axis-aligned box: the top faces inside the box have the
    area of the overlap of the box with the plate's top square: the turned square clipped by the
    box's rectangle (Sutherland-Hodgman), area by the shoelace formula."""
    plate = trimesh.creation.box(extents=[1.0, 1.0, 0.01])
    plate.apply_translation([0, 0, -0.005])
    plate.apply_transform(trimesh.transformations.rotation_matrix(turn, [0, 0, 1]))
    box_min = np.array([lo[0], lo[1], -1.0])
    box_max = np.array([lo[0] + size[0], lo[1] + size[1], 1.0])
    region = config.RegionSpec(name="r", mesh="m", normal=np.array([0, 0, 1.0]), box_min=box_min,
                               box_max=box_max)
    v, f = scene.split_at_boxes(np.asarray(plate.vertices), np.asarray(plate.faces), [region])
    tri = v[f]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2
    c = tri.mean(axis=1)
    up = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2] > 0
    inside = np.all((c >= box_min) & (c <= box_max), axis=1) & up
    # reference: the top square (turned) clipped by the rectangle, area by the shoelace formula
    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    poly = list(corners @ rot.T)
    for axis, bound, keep in ((0, box_min[0], 1), (0, box_max[0], -1), (1, box_min[1], 1), (1, box_max[1], -1)):
        out = []
        for p, q in zip(poly, poly[1:] + poly[:1]):
            dp, dq = keep * (p[axis] - bound), keep * (q[axis] - bound)
            if dp >= 0:
                out.append(p)
            if dp * dq < 0:
                out.append(p + (q - p) * dp / (dp - dq))
        poly = out
        if not poly:
            break
    ref = 0.0 if len(poly) < 3 else 0.5 * abs(sum(p[0] * q[1] - q[0] * p[1]
                                                  for p, q in zip(poly, poly[1:] + poly[:1])))
    assert area[inside].sum() == pytest.approx(ref, abs=1e-12)
    assert area.sum() == pytest.approx(plate.area, rel=1e-12)
    assert trimesh.Trimesh(v, f).is_watertight


# --------------------------------------------------------------------------------------------
# Validation before heavy imports
# --------------------------------------------------------------------------------------------
def test_config_errors_come_before_heavy_imports(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[experiment]\nname = "x"\n[[mesh]]\nname = "a"\nfile = "nope.stl"\n')
    code = ("import sys\nfrom vdo.config.experiment import load\ntry:\n    load(sys.argv[1])\n"
            "except Exception as exc:\n    print(type(exc).__name__)\n"
            "print(sorted(m for m in ('jax', 'mitsuba', 'drjit', 'matplotlib', 'trimesh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code, str(bad)], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["ConfigError", "[]"]


# --------------------------------------------------------------------------------------------
# Geometric checks found together: a camera inside a mesh, a lens outside the catalogue
# --------------------------------------------------------------------------------------------
def test_inside_mesh_against_closed_forms():
    """`scene.inside_mesh` against the closed-form insides of a convex (sphere) and a non-convex
    (annulus: a ring with a hole) closed mesh, at random points kept clear of the faceting
    error; the faces' winding does not matter; a box with a face missing holds no inside."""
    rng = np.random.default_rng(3)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    p = rng.uniform(-1.3, 1.3, (120, 3))
    r = np.linalg.norm(p, axis=1)
    p, r = p[np.abs(r - 1.0) > 0.02], r[np.abs(r - 1.0) > 0.02]     # faceting: < 0.005 off the sphere
    got = scene.inside_mesh(p, sphere.vertices, sphere.faces)
    assert got.tolist() == (r < 1.0).tolist() and 0 < got.sum() < len(p)
    assert scene.inside_mesh(p, sphere.vertices, sphere.faces[:, ::-1]).tolist() == got.tolist()
    ring = trimesh.creation.annulus(r_min=0.5, r_max=1.0, height=0.4, sections=64)
    q = rng.uniform([-1.1, -1.1, -0.3], [1.1, 1.1, 0.3], (150, 3))
    rho = np.linalg.norm(q[:, :2], axis=1)
    clear = (np.abs(rho - 0.5) > 0.01) & (np.abs(rho - 1.0) > 0.01) & (np.abs(np.abs(q[:, 2]) - 0.2) > 0.01)
    q, rho = q[clear], rho[clear]
    truth = (rho > 0.5) & (rho < 1.0) & (np.abs(q[:, 2]) < 0.2)
    assert scene.inside_mesh(q, ring.vertices, ring.faces).tolist() == truth.tolist() and truth.any()
    box = trimesh.creation.box(extents=[1, 1, 1])
    open_top = box.faces[box.face_normals[:, 2] < 0.5]                    # the +z face removed
    assert not scene.inside_mesh(np.zeros((1, 3)), box.vertices, open_top)[0]
    assert scene.inside_mesh(np.zeros((1, 3)), box.vertices, box.faces)[0]


def test_cameras_inside_two_meshes_are_reported_together(plate_experiment):
    """Two cameras, one inside the plate and one inside a block: both errors in one raise
    (ConfigErrors), one line each, naming the file, the camera's field, the mesh and the fix."""
    from vdo.core.errors import ConfigErrors

    cams = "".join(f'[[camera]]\nname = "{n}"\nsensor_mm = [22.2, 14.8]\npixels = [600, 400]\n'
                   f"focal_mm = 24\nposition_m = {pos}\npan_deg = 0\ntilt_deg = -90\n\n"
                   for n, pos in (("low", "[0.1, 0, -0.005]"), ("high", "[0, 0, 0.52]"),
                                  ("fine", "[0, 0, 0.9]")))
    block = '[[mesh]]\nname = "block"\nfile = "block.stl"\nunit = "mm"\n'
    path = plate_experiment(cameras=cams, extra_meshes=block,
                            files=[("block.stl", [100, 100, 100], [0, 0, 500])])
    with pytest.raises(ConfigErrors) as info:
        meshes_of(path)
    errors = info.value.errors
    assert [(e.field, e.file) for e in errors] == [('camera "low".position_m', str(path.resolve())),
                                                   ('camera "high".position_m', str(path.resolve()))]
    assert "inside mesh 'plate'" in errors[0].message and "inside mesh 'block'" in errors[1].message
    assert all("move it out of the mesh" in e.message for e in errors)
    assert str(info.value).splitlines() == [str(e) for e in errors]


LENS_OPTIMIZE = '\n[optimize]\nfree = ["u", "pan", "tilt", "lens"]\nlenses_mm = [{lenses}]\n'


def test_lens_outside_the_catalogue_is_refused(plate_experiment, tmp_path):
    """With "lens" free, the lens choice swaps only to catalogue lenses: a moving camera whose
    own lens is not listed would keep it in optimized.toml when no other wins. Refused before
    any work, naming the camera's focal_mm and the fix; a listed lens (or a camera's own
    lenses_mm that lists it) passes."""
    from vdo.commands.optimize import optimize

    def exp(lenses, extra=""):
        cams = DOWN_CAMERA.format(name="down", focal=24, u=0.5) + extra + LENS_OPTIMIZE.format(lenses=lenses)
        return config.load(plate_experiment(cameras=cams))

    [err] = config.lens_catalogue_errors(exp("28, 50"))
    assert err.field == 'camera "down".focal_mm'
    assert "24 mm is not in the lens catalogue ([optimize] lenses_mm = [28, 50])" in err.message
    assert "add 24 to [optimize] lenses_mm" in err.message
    assert config.lens_catalogue_errors(exp("24, 50")) == []
    assert config.lens_catalogue_errors(exp("28, 50", "lenses_mm = [24, 35]\n")) == []
    with pytest.raises(ConfigError, match=r'camera "down".focal_mm: 24 mm is not in'):
        optimize(exp("28, 50"), tmp_path / "run")     # before any work: no folder, no start-up
    assert not (tmp_path / "run").exists()


def test_a_normal_whose_faces_lie_outside_the_box_says_so(plate_experiment):
    """The plate's top faces (+z) lie outside a box that holds only its lower half: the line
    gives the closest normal among the faces in the box (its sides, 90 deg; not the top's 0 deg,
    which would say the normal is fine) and where the faces that face +z are."""
    path = plate_experiment()
    path = edited(path, ("normal = [0, 0, 1]", "normal = [0, 0, 1]\nbox_min_m = [-1, -1, -1]\n"
                                               "box_max_m = [1, 1, -0.006]"))
    err = error(path, samples_of)
    assert err.field == 'region "top"' and "selects no face" in err.message
    assert "the closest face normal in the box is 90.0 deg from normal" in err.message, err.message
    assert "the faces that face it lie outside the box" in err.message


def test_a_field_written_by_vdo_set_is_blamed_on_it(plate_experiment, monkeypatch):
    """VDO_SET (`vdo.config.reader.with_overrides`): a bad field it writes names the item and says
    the value is not the file's (trial 4: 'render.mod' read as the file's own typo); one camera
    by its name (`camera.NAME.FIELD`), and a name no camera has, one line naming VDO_SET."""
    path = plate_experiment()
    monkeypatch.setenv("VDO_SET", "render.mod = 'dic'")
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert err.value.field == "render.mod" and "did you mean 'mode'" in err.value.message
    assert str(err.value).endswith("(this value comes from the environment's VDO_SET item "
                                   "\"render.mod = 'dic'\", not from the file)")
    monkeypatch.setenv("VDO_SET", "camera.down.focal_mm = 35")
    assert config.load(path).camera_specs[0].focal_length == pytest.approx(0.035)
    monkeypatch.setenv("VDO_SET", "camera.down.focal_mm = -35")
    with pytest.raises(ConfigError, match=r'camera "down".focal_mm: must be positive .*VDO_SET item'):
        config.load(path)
    monkeypatch.setenv("VDO_SET", "camera.dwn.focal_mm = 35")
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert err.value.file == "VDO_SET" and "no [[camera]] is named 'dwn'" in str(err.value)
    monkeypatch.delenv("VDO_SET")
    assert config.load(path).camera_specs[0].focal_length == pytest.approx(0.024)   # the file's
