"""vdo.calib: the [calibration] table, the session's checks, the rendered target images (read
back by OpenCV alone), the calibration and its covariance, the propagation, the imports."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vdo.config.experiment import load, parse
from vdo.core.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
HOLED = ROOT / "experiments" / "holed_plate" / "stereo.toml"
STEEL = ROOT / "experiments" / "steel_beam" / "four_point_bending.toml"
BEAM = ROOT / "experiments" / "beam_column" / "three_cameras.toml"


def with_calibration(path, cameras=None, **fields):
    """The experiment at `path` with [calibration] `fields` (file units) and, optionally, only
    the cameras named in `cameras`."""
    exp = load(path)
    data = exp.to_dict()
    data["calibration"] = {**data.get("calibration", {}), **fields}
    if cameras is not None:
        data["camera"] = [c for c in data["camera"] if c["name"] in cameras]
        data["optimize"].pop("cameras", None)
        data.pop("stereo_pair", None)
        data["stereo_pair"] = [{"cameras": list(cameras[:2])}]
    return parse(data, exp.path)


# ---- step 1: the table and the session's checks, before any render ----------------------------
@pytest.mark.parametrize("fields,field", [
    ({"target": "charuco_v9"}, "calibration.target"),
    ({"rows": 7, "columns": 9}, "calibration.columns"),
    ({"pose_normals": [[0, -1, 0]]}, "calibration.pose_normals"),
    ({"pitch_mm": 5, "pitch_tolerance_mm": 1}, "calibration.pitch_tolerance_mm"),
])
def test_bad_table_is_one_line(fields, field):
    with pytest.raises(ConfigError) as err:
        with_calibration(HOLED, **fields)
    assert err.value.field == field and "\n" not in str(err.value)


def plan_error(exp, scale=0.25):
    from vdo.calib.session import plan

    with pytest.raises(ConfigError) as err:
        plan(exp, scale)
    assert "\n" not in str(err.value)
    return err.value


def test_target_larger_than_field():
    err = plan_error(with_calibration(HOLED, pitch_mm=40))
    assert err.field == "calibration.pitch_mm" and "more than camera" in err.message


def test_target_never_seen_by_a_camera():
    # every explicit pose faces away from the cameras (they stand at y < 0)
    err = plan_error(with_calibration(HOLED, pose_centres_m=[[0, -0.2, 1.0]] * 4,
                                      pose_normals=[[0, 1, 0]] * 4))
    assert err.field == "calibration.pose_centres_m" and "sees the whole target in 0" in err.message


def test_all_fronto_parallel_is_degenerate():
    centres = [[x, -0.1, z] for x in (-0.02, 0.0, 0.02) for z in (0.98, 1.02)]
    err = plan_error(with_calibration(HOLED, pitch_mm=4, pose_centres_m=centres,
                                      pose_normals=[[0, -1, 0]] * len(centres)))
    assert err.field == "calibration.pose_normals" and "parallel planes" in err.message


def test_squares_too_small_at_the_render_scale():
    err = plan_error(with_calibration(STEEL, pitch_mm=3), scale=0.1)
    assert err.field == "calibration.pitch_mm" and "render scale" in err.message


@pytest.mark.parametrize("path", [HOLED, STEEL])
def test_generated_session_every_camera_sees_its_poses(path):
    """Each generated pose a camera is said to see projects inside its image (checked here with
    cv2.projectPoints, not vdo's projection), and every stereo pair shares poses."""
    import cv2

    from vdo.calib.session import plan

    planned = plan(load(path), 0.25)
    s = planned.session
    corners = s.target.points()
    for cam in planned.cameras:
        assert len(s.views[cam.name]) >= 3
        rvec = cv2.Rodrigues(cam.R)[0]
        for k in s.views[cam.name]:
            uv = cv2.projectPoints(s.poses[k].world(corners), rvec, cam.t, cam.K,
                                   np.array(cam.distortion))[0][:, 0]
            assert (uv >= 0).all() and (uv[:, 0] < cam.width).all() and (uv[:, 1] < cam.height).all()
    for a, b in s.pairs:
        assert set(s.views[a]) & set(s.views[b])
