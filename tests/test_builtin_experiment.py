"""The built-in beam-column experiment: its meshes come from the committed script, its
specimen is a closed solid of the paper's size, and its cameras see every joint face."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import trimesh

from conftest import raycast

HERE = Path(__file__).resolve().parent.parent / "experiments" / "beam_column"


def load_script():
    spec = importlib.util.spec_from_file_location("make_meshes", HERE / "make_meshes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_meshes_are_what_the_script_builds():
    script = load_script()
    for name, build in script.PARTS.items():
        mesh = build()
        mesh = trimesh.Trimesh(np.round(mesh.vertices * script.MM, 6), mesh.faces, process=False)
        assert mesh.export(file_type="stl") == (HERE / "meshes" / f"{name}.stl").read_bytes(), name


def test_committed_load_path_is_what_the_script_writes(tmp_path):
    load_script().write_load_path(tmp_path)
    for name in ("load_path_platform.csv", "load_path_specimen.csv"):
        assert (tmp_path / name).read_text() == (HERE / name).read_text(), name


def test_specimen_is_the_papers_t():
    """Watertight T of 120 mm sections: column 2.4 m, beam 1.0 m from the joint face (sec. 2.2)."""
    specimen = trimesh.load(HERE / "meshes" / "specimen.stl")
    specimen.apply_scale(1e-3)
    assert specimen.is_watertight and specimen.is_winding_consistent and specimen.volume > 0
    lo, hi = specimen.bounds
    np.testing.assert_allclose(hi - lo, [2.4, 1.12, 0.12], atol=1e-9)
    expected_volume = 0.12 * 0.12 * (2.4 + 1.0)
    assert specimen.volume == pytest.approx(expected_volume, rel=1e-9)


@pytest.mark.parametrize("name,joint_min", [("ten_cameras.toml", 3), ("three_cameras.toml", 3)])
def test_joint_faces_are_covered(name, joint_min):
    _, samples, _, _, vis = raycast(HERE / name)
    for k, region in enumerate(samples.region_names):
        if region.startswith("joint") and (name.startswith("ten") or region == "joint_top"):
            assert vis.coverage[samples.region == k].min() >= joint_min, region
