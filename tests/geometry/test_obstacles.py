"""A camera's hardware as an obstacle in closed form (`vdo.geometry.obstacles`), checked against
Mitsuba's ray test on the meshes the scene builds for the same body and tripod
(`vdo.scene.camera_body`, `vdo.scene.tripod`): every sight line the meshes stop is hidden, and a
line called hidden that the meshes let through passes within the stand-ins' overshoot of them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist
import trimesh

from vdo.config.mounts import TripodSpec
from vdo.core.backend import mitsuba
from vdo.geometry import obstacles
from vdo.model.camera import Camera
from vdo.model.pose import look_at_angles
from vdo.scene import build_scene, camera_body, tripod

OVERSHOOT_M = 0.03   # the body's spheres overshoot the box by ~1.5 cm; a capsule's ends by its radius
LINES = 4000


def camera_at(position, target, focal_mm=25.0):
    pan, tilt = look_at_angles(np.asarray(position, float), np.asarray(target, float))
    return Camera(name="c", width=2448, height=2048, pixel_size=3.45e-6, focal_length=focal_mm * 1e-3,
                  position=np.asarray(position, float), pan=pan, tilt=tilt, roll=0.0)


@pytest.mark.parametrize("on_tripod, chunk", [(False, None), (True, None), (True, 97)])
def test_hidden_lines_match_the_meshes(on_tripod, chunk, monkeypatch):
    """`chunk`: LINES_CHUNK small enough that the 4,000 lines are tested in 42 chunks, the last
    one partial."""
    if chunk is not None:
        monkeypatch.setattr(obstacles, "LINES_CHUNK", chunk)
    cam = camera_at([0.3, -1.2, 1.3], [0.0, 0.0, 0.9])
    spec = TripodSpec() if on_tripod else None
    meshes = [camera_body(cam)] + (tripod(cam, spec) if on_tripod else [])
    whole = trimesh.util.concatenate([trimesh.Trimesh(m.vertices, m.faces, process=False) for m in meshes])
    hw = obstacles.hardware(cam, spec)
    rng = np.random.default_rng(3)
    # sight lines from a second camera's spot behind and beside it, past the first (and down
    # its tripod) to the specimen beyond
    start = np.array([0.9, -2.6, 1.1]) + rng.normal(0, 0.3, (LINES, 3))
    near = cam.position + np.c_[rng.normal(0, 0.15, (LINES, 2)),
                                rng.uniform(-1.2 if on_tripod else -0.2, 0.2, LINES)]
    end = start + 1.6 * (near - start)
    hidden = obstacles.hidden(start, end, hw)
    direction = end - start
    length = np.linalg.norm(direction, axis=1)
    mi = mitsuba()
    ray = mi.Ray3f(mi.Point3f(*start.T), mi.Vector3f(*(direction / length[:, None]).T))
    ray.maxt = mi.Float(length)
    stopped = np.asarray(build_scene(meshes).ray_test(ray), dtype=bool)
    assert stopped.sum() > 50 and (hidden & ~stopped).sum() > 0     # both kinds of line occur
    assert np.all(hidden[stopped])                                   # the meshes stop -> hidden
    surface = trimesh.sample.sample_surface(whole, 40000, seed=1)[0]
    extra = np.flatnonzero(hidden & ~stopped)
    gap = np.array([obstacles.point_segment_distance(surface, start[i], end[i]).min() for i in extra])
    assert gap.max() < OVERSHOOT_M


def test_segment_distance_against_a_dense_search():
    rng = np.random.default_rng(0)
    a0, a1, b0, b1 = (rng.normal(size=(200, 3)) for _ in range(4))
    b1[:20] = b0[:20] + 0.5 * (a1[:20] - a0[:20])                   # parallel pairs too
    t = np.linspace(0, 1, 401)
    pa = a0[:, None] + t[None, :, None] * (a1 - a0)[:, None]
    pb = b0[:, None] + t[None, :, None] * (b1 - b0)[:, None]
    dense = np.array([cdist(p, q).min() for p, q in zip(pa, pb)])   # 401 x 401 points per pair
    exact = obstacles.segment_distance(a0, a1, b0, b1)
    assert np.all(exact <= dense + 1e-12)
    assert exact == pytest.approx(dense, abs=5e-3)


def test_a_group_missing_between_its_moving_steps_is_warned(caplog, tmp_path):
    """A group with no row at a step of the load path between two steps where it moves stands
    at rest there (the documented meaning of a missing row): said, since a forgotten row gives
    the same jump; a group that returns to rest by its own rows, or moves only at the end, is not."""
    import logging

    import numpy as np

    from vdo.geometry.keyframes import Pose, _warn_gaps

    def pose(dz):
        return Pose(np.eye(3), np.array([0.0, 0.0, dz]), np.zeros(3))

    poses = {(1, "platen"): pose(-0.5), (2, "platen"): pose(-1.0), (4, "platen"): pose(-2.0),
             (1, "hexapod"): pose(0.0), (3, "hexapod"): pose(0.0), (5, "hexapod"): pose(0.003)}
    with caplog.at_level(logging.WARNING, logger="vdo"):
        _warn_gaps(tmp_path / "poses.csv", poses, [1, 2, 3, 4, 5])
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "group 'platen' has no row at step(s) 3" in lines[0], lines
