"""The curved built-in experiment (experiments/pressure_vessel): its meshes come from the
committed script, its three regions are developed as the cylinders they are, `vdo evaluate`
runs on it and draws each region developed, and the developed hole edge is as long as the
mesh's own hole edge in 3D (a development keeps lengths on the surface)."""

import importlib.util
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vdo.commands.evaluate import evaluate
from conftest import mesh_tables, region_tables
from vdo.config import experiment as config
from vdo.outputs.maps import developed_outline
from vdo.scene import all_region_faces, load_meshes, sample_regions

HERE = Path(__file__).resolve().parent.parent / "experiments" / "pressure_vessel"
CHORD_RTOL = 2e-3      # a facet's chord against its arc on the shell (R 0.3 m, 76 cells around)


def load_script():
    spec = importlib.util.spec_from_file_location("make_meshes", HERE / "make_meshes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_meshes_are_what_the_script_builds():
    script = load_script()
    shell, nozzle = script.shell_and_nozzle()
    for name, mesh in (("shell", shell), ("nozzle", nozzle), ("saddles", script.saddles())):
        assert mesh.export(file_type="stl") == (HERE / "meshes" / f"{name}.stl").read_bytes(), name


def coarse(spacing=0.016):
    exp = config.load(HERE / "all_round.toml")
    return replace(exp, evaluation=replace(exp.evaluation, sample_spacing=spacing))


def test_regions_are_the_cylinders_they_are():
    exp = coarse()
    meshes = load_meshes(**mesh_tables(exp))
    faces = all_region_faces(meshes, **region_tables(exp))
    by_name = dict(zip((r.name for r in exp.regions), faces))
    script = load_script()
    assert by_name["junction"].development.kind == "cylinder"
    assert abs(by_name["junction"].development.radius) == pytest.approx(script.R, rel=1e-3)
    assert by_name["junction"].development.period == 0            # a patch, not a ring
    assert by_name["shell"].development.period == pytest.approx(2 * math.pi * script.R, rel=1e-3)
    assert abs(by_name["nozzle"].development.radius) == pytest.approx(script.R_NOZZLE, rel=1e-3)
    assert abs(by_name["nozzle"].development.axis[2]) == pytest.approx(1, abs=1e-6)


def test_developed_hole_edge_keeps_its_length():
    exp = coarse()
    meshes = {m.name: m for m in load_meshes(**mesh_tables(exp))}
    samples = sample_regions(list(meshes.values()), **region_tables(exp))
    faces = all_region_faces(list(meshes.values()), **region_tables(exp))
    shell = meshes["shell"]
    outline = developed_outline(samples, 0, faces[0], shell.vertices, shell.faces)
    developed = np.linalg.norm(outline.holes[:, 1] - outline.holes[:, 0], axis=1).sum()
    # the same edges found by trimesh on the welded mesh: edges of one face, within the band
    welded = trimesh.Trimesh(shell.vertices, shell.faces)           # process=True welds corners
    edges = welded.edges_sorted
    once = trimesh.grouping.group_rows(edges, require_count=1)
    segment = welded.vertices[edges[once]]
    mid = segment.mean(axis=1)
    near = (np.hypot(mid[:, 0], mid[:, 1]) < 0.25) & (mid[:, 2] > 1.0)
    length = np.linalg.norm(segment[near, 1] - segment[near, 0], axis=1).sum()
    assert length > 0.4                                       # the nozzle's 2 pi 0.08 m, roughly
    assert developed == pytest.approx(length, rel=CHORD_RTOL)


def test_evaluate_draws_every_region_developed(tmp_path):
    result = evaluate(coarse(0.02), tmp_path / "run")
    for name in ("junction", "nozzle", "shell"):
        assert (tmp_path / "run" / "maps" / f"developed_{name}.png").stat().st_size > 10_000
        d = result.developed[name]
        assert d["kind"] == "cylinder" and d["area_distortion"] < 0.01
        assert set(d["cameras"]) <= {c.name for c in coarse().camera_specs}


def test_a_curved_regions_outline_is_drawn_in_each_view_it_spans():
    """The projected maps: the shell (a ring) faces every side view, so its outline is one ring
    per view, each inside its own panel (one hull over all views crossed the sheet), and each
    region is named once."""
    from vdo.outputs.maps import layout

    exp = coarse()
    meshes = load_meshes(**mesh_tables(exp))
    lay = layout(sample_regions(meshes, **region_tables(exp)))
    assert len(lay.hulls["shell"]) >= 4
    for name, rings in lay.hulls.items():
        for ring in rings:
            inside = [p for p in lay.panels
                      if np.all((ring >= [p.x0 - 1e-9, p.y0 - 1e-9]) & (ring <= [p.x0 + p.width + 1e-9,
                                                                                 p.y0 + p.height + 1e-9]))]
            assert len(inside) == 1, (name, ring.min(0), ring.max(0))
    assert sorted(text for text, _ in lay.labels) == sorted(r.name for r in exp.regions)
