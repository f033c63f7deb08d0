"""A bright marker rendered by Mitsuba lands where `Camera.project` says (< 0.1 px)."""

import numpy as np
import pytest

from vdo.core.backend import mitsuba
from vdo.model.camera import Camera
from vdo.model.pose import look_at_angles
from vdo.render import sensor_dict

MARKER = np.array([0.05, -0.03, 0.02])
CASES = [  # position, roll, principal offset (px)
    ((1.0, 0.3, 0.4), 0.0, (0.0, 0.0)),          # oblique, centred
    ((0.2, -1.0, 0.6), 0.3, (37.0, -21.0)),       # rolled, off-centre principal point
    ((0.0, 0.01, 1.2), 0.0, (0.0, 0.0)),          # straight down
    ((-0.8, 0.9, -0.3), -0.2, (-15.0, 30.0)),     # from below, rolled, off-centre
]


def marker_centroid(camera: Camera, point, radius=0.002, spp=64):
    """Intensity centroid (OpenCV pixel convention) of a small emitting sphere at `point`."""
    mi = mitsuba()
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": sensor_dict(camera, spp=spp),
        "marker": {"type": "sphere", "center": [float(c) for c in point], "radius": radius,
                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
    })
    image = np.asarray(mi.render(scene, seed=0)).squeeze()
    rows, cols = np.mgrid[: image.shape[0], : image.shape[1]]
    return np.array([(image * cols).sum(), (image * rows).sum()]) / image.sum()


@pytest.mark.parametrize("position,roll,offset", CASES)
def test_rendered_marker_lands_on_projection(position, roll, offset):
    """Aim slightly off the marker so it is not at the image centre."""
    pan, tilt = look_at_angles(position, MARKER + np.array([0.06, 0.05, -0.04]))
    cam = Camera("c", 320, 240, 5e-6, 0.008, np.array(position), pan, tilt, roll=roll,
                 principal_offset_px=offset)
    expected = cam.project(MARKER[None])[0]
    assert np.linalg.norm(expected - cam.principal_point) > 20   # really off-centre
    np.testing.assert_allclose(marker_centroid(cam, MARKER), expected, atol=0.1)
