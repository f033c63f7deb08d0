"""The reachability check: a region that no mount can show to two cameras is named in a warning
before any optimization; a region both rail cameras see is not."""

import logging

from conftest import PLATE_TOML, aimed_camera, mesh_tables, region_tables, write_box
from vdo import scene
from vdo.config import experiment as config
from vdo.search import reachability

BOTTOM = """
[[region]]
name = "bottom"
mesh = "plate"
normal = [0, 0, -1]
"""


def plate_with_bottom(tmp_path):
    """The plate with its top and bottom regions and two cameras on the overhead rail: the
    experiment, its meshes and its samples."""
    write_box(tmp_path / "plate.stl", [600, 600, 10], center=[0, 0, -5])
    text = PLATE_TOML.format(spacing=40, limit=75, height=1.2, extra_meshes=BOTTOM,
                             cameras=aimed_camera("a", 0.3) + aimed_camera("b", 0.7))
    (tmp_path / "exp.toml").write_text(text)
    exp = config.load(tmp_path / "exp.toml")
    meshes = scene.load_meshes(**mesh_tables(exp))
    samples = scene.sample_regions(meshes, **region_tables(exp))
    return exp, meshes, samples


def test_region_no_mount_can_show_to_two_cameras_is_warned_about(tmp_path, caplog):
    exp, meshes, samples = plate_with_bottom(tmp_path)
    with caplog.at_level(logging.WARNING, logger="vdo"):
        entries = {e["region"]: e for e in reachability.check(exp, meshes, samples)}
    # the top face faces both cameras from every rail position: all of it reachable by both
    assert entries["top"]["best_coverage"] == 1.0 and not entries["top"]["short"]
    assert entries["top"]["cameras"] == ["a", "b"]
    # the bottom face looks at the floor: nothing above can see it
    assert entries["bottom"]["best_coverage"] == 0.0 and entries["bottom"]["short"]
    assert entries["bottom"]["cameras"] == []
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert 'region "bottom"' in warnings[0] and "rail overhead" in warnings[0]


def test_the_configured_poses_count_too(tmp_path, monkeypatch):
    """Trial 4: the sweep aims every pose at a region's centroid, which for a band around a
    branch lies inside the pipe; the hand layout saw 96 % of the band twice, the sweep 14 %, and
    the warning said "at most 14 %". The cameras' configured poses are tried as well: with no
    sweep poses at all (each mount's sweep emptied) the top face both cameras see as configured
    is reachable whole, and the bottom face, which they cannot see, stays at 0."""
    import numpy as np

    exp, meshes, samples = plate_with_bottom(tmp_path)
    monkeypatch.setattr(reachability, "mount_positions", lambda *a, **k: ("rail overhead", np.zeros((0, 3))))
    entries = {e["region"]: e for e in reachability.check(exp, meshes, samples)}
    assert entries["top"]["best_coverage"] == 1.0 and entries["top"]["cameras"] == ["a", "b"]
    assert entries["bottom"]["best_coverage"] == 0.0
