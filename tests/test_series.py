"""`vdo render --series`: rigid motions per mesh per step rendered as a 16-bit TIFF series whose
image motion OpenCV's phase correlation measures where the projection predicts it."""

import json

import cv2
import numpy as np
import pytest
from PIL import Image

from vdo import cli, config
from vdo.errors import ConfigError
from vdo.render import scaled_camera
from vdo.keyframes import load_path_of
from vdo.series import render_series

CAMERA = """
[[camera]]
name = "down"
sensor_width_mm = 2.0
pixels = [200, 150]
focal_mm = 20
position_m = [0.0, 0.0, 1.0]
pan_deg = 0
tilt_deg = -90
body = false

[speckle]
dot_diameter_mm = 2.0
texel_mm = 0.25
tile_texels = 512

[render]
spp = 4
ambient_radiance = 1.0
"""
# 0.5 mm per pixel at 1 m: step 1 a translation, step 2 a 1 deg turn about z plus a translation
MOTIONS = """step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg
1,plate,1.2,-0.7,0,0,0,0
2,plate,0,0.8,0,0,0,1.0
"""


def shift(a, b, centre, half=32):
    """Sub-pixel shift (du, dv) of image b against image a in the window around `centre`: OpenCV's
    ECC alignment (cv2.findTransformECC, translation): b(x + d) = a(x)."""
    u, v = np.rint(centre).astype(int)
    crop = lambda im: np.asarray(im, dtype=np.float32)[v - half:v + half, u - half:u + half]
    warp = np.eye(2, 3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-8)
    _, warp = cv2.findTransformECC(crop(a), crop(b), warp, cv2.MOTION_TRANSLATION, criteria, None, 1)
    return warp[:, 2].astype(float)


def test_series_images_move_as_the_projection_predicts(plate_experiment, tmp_path):
    path = plate_experiment(cameras=CAMERA)
    (tmp_path / "motions.csv").write_text(MOTIONS)
    exp = config.load(path)
    out = tmp_path / "series"
    summary = render_series(exp, out, tmp_path / "motions.csv")
    assert summary["steps"] == [0, 1, 2]
    images = []
    for step in range(3):
        with Image.open(out / "images" / "down" / f"down_{step:04d}.tif") as im:
            assert im.size == (200, 150) and im.mode.startswith("I;16")
            images.append(np.asarray(im))
    assert images[0].std() > 100                              # speckled and lit
    cam = scaled_camera(exp.cameras()[0], 1.0)
    poses = load_path_of(exp, [], tmp_path / "motions.csv").poses
    for step, centres in ((1, [(100, 75), (60, 50)]), (2, [(60, 45), (140, 105)])):
        pose = poses[(step, "plate")]
        for centre in centres:
            # the plate point seen at `centre`, and where the motion takes it
            ray = np.linalg.solve(cam.K, [*centre, 1.0]) @ cam.R
            X = cam.position + ray * (0.0 - cam.position[2]) / ray[2]
            expected = cam.project(pose.move(X[None]))[0] - np.asarray(centre, float)
            assert np.linalg.norm(expected) > 1.0
            np.testing.assert_allclose(shift(images[0], images[step], centre), expected, atol=0.05)
    layout = json.loads((out / "layout.json").read_text())
    fs = cv2.FileStorage(str(out / "calibration" / "opencv" / "down.yml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), layout["cameras"][0]["K"])
    assert (out / "poses.csv").read_text() == MOTIONS


HEADER = "step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n"


@pytest.mark.parametrize("text,message", [
    (HEADER + "1,plate,nan,0,0,0,0,0\n", "row 2: column x_mm: nan is not finite"),
    (HEADER + "1,beam,1,0,0,0,0,0\n", "row 2: group 'beam' is neither a [[group]] nor a [[mesh]]"),
    ("step,group,ux_mm\n1,plate,1\n", "column x: needs exactly one column x_<unit>"),
    (HEADER + "0,plate,1,0,0,0,0,0\n", "row 2: step must be a whole number >= 1"),
    (HEADER + "1,plate,1,0,0,0,0,0\n1,plate,2,0,0,0,0,0\n", "row 3: a second pose for group 'plate'"),
])
def test_bad_motion_files_are_one_clear_line(plate_experiment, tmp_path, capsys, text, message):
    path = plate_experiment(cameras=CAMERA)
    (tmp_path / "m.csv").write_text(text)
    with pytest.raises(ConfigError):
        load_path_of(config.load(path), [], tmp_path / "m.csv")
    code = cli.main(["render", str(path), "--series", str(tmp_path / "m.csv"), "--out",
                     str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "m.csv" in err and message in err
    assert not (tmp_path / "o").exists()
