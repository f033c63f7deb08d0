"""Shared fixtures: small experiments written to disk the way a user would write them."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vdo.core.configure import configure


def pytest_configure(config):
    """The process-wide settings the command line applies (float64, the persistent compilation
    cache, Agg, malloc options), once per test session."""
    configure()


# The files that take longest (seconds of all their tests, `--durations` on 2 workers, warm), run
# first: `make test` hands out whole files in collection order (`--dist loadfile
# --no-loadscope-reorder`), so a worker that is given one of these late leaves the other idle
# while it runs (about a minute of a 12-minute suite). A file missing here only runs later.
HEAVY_FIRST = (
    "tests/commands/test_shipped_examples.py",   # 225 s
    "tests/design/test_design.py",               # 72 s
    "tests/calib/test_calibration.py",           # 69 s
    "tests/test_optimize.py",                    # 57 s
    "tests/dic/test_series.py",                  # 51 s
    "tests/design/test_restarts.py",             # 48 s
    "tests/test_api_docs.py",                    # 46 s
    "tests/physics/test_measured.py",            # 44 s
    "tests/calib/test_montecarlo.py",            # 38 s
    "tests/commands/test_sweep.py",              # 34 s
    "tests/physics/test_measured_fields.py",     # 34 s
    "tests/test_scripting.py",                   # 33 s
    "tests/design/test_design_measured.py",      # 29 s
    "tests/core/test_interrupts.py",             # 28 s
    "tests/design/test_speckle_design.py",       # 22 s
    "tests/design/test_bound.py",                # 22 s
    "tests/commands/test_evaluate_parallel.py",  # 20 s
    "tests/design/test_bound_views.py",          # 19 s
    "tests/test_objective.py",                   # 18 s
    "tests/dic/test_validate.py",                # 18 s
)


def pytest_collection_modifyitems(config, items):
    """HEAVY_FIRST's files first, in its order; the rest after, in collection order."""
    rank = {name: k for k, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(HEAVY_FIRST)))


def read_vtp(path):
    """(points (N, 3), vertex count, {name: array}) of a samples.vtp, read by VTK's own XML reader
    (imported here only: the rest of the suite runs without VTK loaded)."""
    from vtk import vtkXMLPolyDataReader
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    data = reader.GetOutput()
    pd = data.GetPointData()
    arrays = {pd.GetArrayName(i): vtk_to_numpy(pd.GetArray(i)) for i in range(pd.GetNumberOfArrays())}
    return vtk_to_numpy(data.GetPoints().GetData()), data.GetNumberOfVerts(), arrays


def mesh_tables(exp) -> dict:
    """The tables of `exp` that `vdo.scene.load_meshes` reads, as its keyword arguments:
    ``load_meshes(**mesh_tables(exp))``."""
    return dict(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                rails=exp.rails, mounts=exp.mounts, path=exp.path)


def region_tables(exp, spacing=None) -> dict:
    """The tables of `exp` that `vdo.scene.all_region_faces` and `sample_regions` read, at its
    sample spacing unless `spacing` (m), as their keyword arguments:
    ``sample_regions(meshes, **region_tables(exp))``."""
    return dict(mesh_specs=exp.meshes, regions=exp.regions, path=exp.path,
                spacing=exp.evaluation.sample_spacing if spacing is None else spacing)


def load_path_tables(exp) -> dict:
    """The tables of `exp` that `vdo.geometry.keyframes.load_path_of` reads, as its keyword
    arguments: ``load_path_of(meshes, **load_path_tables(exp))``."""
    return dict(load_path_spec=exp.load_path, mesh_specs=exp.meshes, groups=exp.groups)


def write_box(path: Path, extents, center=(0, 0, 0), unit_scale=1.0):
    """An axis-aligned box mesh saved as STL (coordinates multiplied by unit_scale)."""
    box = trimesh.creation.box(extents=np.asarray(extents, dtype=float) * unit_scale)
    box.apply_translation(np.asarray(center, dtype=float) * unit_scale)
    box.export(path)
    return path


# A tripod zone (y from -1.2 to -1.0 m) beside the plate experiment's plate (appended to its meshes).
TRIPOD_ZONE = """
[[mount]]
name = "floor"
kind = "zone"
box_min_m = [-1.0, -1.2, 0.5]
box_max_m = [1.0, -1.0, 1.1]
[mount.tripod]
spread_m = 0.45
leg_diameter_m = 0.04
"""


# An obstacle mesh "shutter.stl" in a group "slide" that the poses of "poses.csv" move: a part
# that hides a region during the load path (appended to PLATE_TOML's meshes).
SLIDING_SHUTTER = """
[[mesh]]
name = "shutter"
file = "shutter.stl"
unit = "mm"
role = "obstacle"

[[group]]
name = "slide"
meshes = ["shutter"]

[load_path]
poses = "poses.csv"
"""


PLATE_TOML = """
[experiment]
name = "plate under one camera"

[evaluation]
sample_spacing_mm = {spacing}
incidence_limit_deg = {limit}

[[mesh]]
name = "plate"
file = "plate.stl"
unit = "mm"
role = "specimen"

{extra_meshes}

[[region]]
name = "top"
mesh = "plate"
normal = [0, 0, 1]

[[rail]]
name = "overhead"
control_points_m = [[-1.0, 0.0, {height}], [1.0, 0.0, {height}]]

{cameras}
"""

AIMED_CAMERA = """
[[camera]]
name = "{name}"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
rail = "overhead"
u = {u}
target_m = [0.0, 0.0, 0.0]
{extra}
"""


def aimed_camera(name: str, u: float, extra: str = "") -> str:
    """A 24 mm camera on PLATE_TOML's overhead rail at `u`, aimed at the plate's centre; `extra`:
    more [[camera]] lines."""
    return AIMED_CAMERA.format(name=name, u=u, extra=extra)


DOWN_CAMERA = """
[[camera]]
name = "{name}"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = {focal}
rail = "overhead"
u = {u}
pan_deg = 0
tilt_deg = -90
"""


def write_plate_experiment(folder: Path, spacing=10, limit=75, height=1.5, cameras=None,
                           extra_meshes="", files=()) -> Path:
    """A 1 m x 1 m plate (top face at z = 0) seen from above, written into `folder`; returns the
    TOML path. `files`: more boxes (name, extents mm, centre mm)."""
    write_box(folder / "plate.stl", [1000, 1000, 10], center=[0, 0, -5])
    for name, extents, center in files:
        write_box(folder / name, extents, center)
    cams = cameras if cameras is not None else DOWN_CAMERA.format(name="down", focal=24, u=0.5)
    text = PLATE_TOML.format(spacing=spacing, limit=limit, height=height, cameras=cams,
                             extra_meshes=extra_meshes)
    path = folder / "plate.toml"
    path.write_text(textwrap.dedent(text))
    return path


@pytest.fixture
def plate_experiment(tmp_path):
    """Factory: `write_plate_experiment` into the test's temporary folder."""

    def make(**options):
        return write_plate_experiment(tmp_path, **options)

    return make


def raycast(path):
    """Load an experiment and ray-cast it as `vdo evaluate` does (every camera body an obstacle).
    Returns (experiment, samples, cameras, Mitsuba scene, visibility)."""
    from vdo.config import experiment as config
    from vdo.state import layout_state, prepare

    exp = config.load(path)
    state = layout_state(prepare(exp), predict_fields=False)
    samples, cams, sc, vis = state.samples, list(state.cameras), state.scene, state.visibility
    return exp, samples, cams, sc, vis


# The sweep tests' rig (tests/commands/test_sweep.py, also used by other files):
HEIGHT = 1.5        # m, the rail above the plate's top face (z = 0)
SENSOR = 15.0       # mm, square sensor

# Two cameras looking straight down from x = -0.3 and x = +0.3 m (rail u = 0.35, 0.65):
# square footprints of side SENSOR / f * HEIGHT on the 1 m x 1 m plate.
CAMERAS = "".join(f"""
[[camera]]
name = "{name}"
sensor_mm = [{SENSOR}, {SENSOR}]
pixels = [300, 300]
focal_mm = 24
rail = "overhead"
u = {u}
pan_deg = 0
tilt_deg = -90
""" for name, u in (("left", 0.35), ("right", 0.65)))
