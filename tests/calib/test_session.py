"""vdo.calib.session: generated sessions nest, so the calibration's covariance only shrinks as
poses are added (the planner's curve cannot rise)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vdo.config.experiment import load, parse

ROOT = Path(__file__).resolve().parents[2]
BEAM = ROOT / "experiments" / "beam_column" / "three_cameras.toml"
PSD_SLACK = 1e-9      # relative to the larger session's largest variance: rounding of (J^T J)^-1
PREFIX_GAP = 3.05     # the largest gap of n centres, times sqrt(n), on the [-1, 1]^2 square


def session(poses_per_camera: int, shared_poses: int):
    from vdo.calib.session import plan

    exp = load(BEAM)
    data = exp.to_dict()
    data["calibration"] = {**data.get("calibration", {}), "poses_per_camera": poses_per_camera,
                           "shared_poses": shared_poses}
    return plan(parse(data, exp.path), 1.0)


def test_spread_prefixes_cover_the_square():
    """Every prefix of the pose centres' sequence spreads over [-1, 1]^2: the largest empty
    gap (the farthest point of a fine grid from the first n centres) stays within
    PREFIX_GAP / sqrt(n) for every n. Measured: 2.2-3.0 / sqrt(n); a uniform random set's median
    is 2.8-3.2 / sqrt(n); the first n points of a 32-point Fibonacci lattice leave half the
    square empty (gap > 1 for n <= 16)."""
    from vdo.calib.session import spread

    g = np.stack(np.meshgrid(np.linspace(-1, 1, 81), np.linspace(-1, 1, 81)), -1).reshape(-1, 2)
    for n in (3, 4, 6, 8, 12, 16, 24, 32):
        pts = np.array([spread(k) for k in range(n)])
        gap = np.sqrt(((g[:, None] - pts[None]) ** 2).sum(-1)).min(1).max()
        assert gap < PREFIX_GAP / np.sqrt(n), (n, gap)


def test_sessions_nest_and_the_covariance_shrinks():
    """The session of n poses per camera is contained in that of 2n (same poses, same views),
    and the noise-free calibration's covariance of the whole rig falls in Loewner order:
    Sigma(n) - Sigma(2n) is positive semi-definite (adding rows to J only adds to J^T J)."""
    from vdo.calib import propagate as prop
    from vdo.calib.solve import calibrate, simulate

    small, large = session(3, 2), session(6, 4)
    key = lambda p: (tuple(np.round(p.origin, 12)), tuple(np.round(p.R.ravel(), 12)))  # noqa: E731
    assert {key(p) for p in small.session.poses} <= {key(p) for p in large.session.poses}
    covariances = []
    for planned in (small, large):
        cams = list(planned.cameras)
        names = [c.name for c in cams]
        obs = simulate(cams, planned.session, 0.0, np.random.default_rng(0))
        cal = calibrate(names, {c.name: (c.width, c.height) for c in cams}, obs,
                        planned.session.target, 0.1)
        covariances.append(prop.rig(cal, tuple(names), cams).covariance)
    difference = covariances[0] - covariances[1]
    scale = np.abs(np.diag(covariances[0])).max()
    assert np.linalg.eigvalsh(difference).min() > -PSD_SLACK * scale
    assert np.all(np.diag(covariances[1]) < np.diag(covariances[0]))


@pytest.mark.parametrize("n", [3, 5])
def test_roll_depends_on_the_pose_alone(n):
    """A pose's in-plane turn is the same whatever the session's size (nesting), within
    +-ROLL_DEG, and changes with the seed."""
    from vdo.calib.session import ROLL_DEG, _roll

    turns = [_roll(0, 1, k) for k in range(n)]
    assert turns == [_roll(0, 1, k) for k in range(n)]
    assert max(abs(t) for t in turns) <= np.radians(ROLL_DEG)
    assert turns != [_roll(1, 1, k) for k in range(n)]
