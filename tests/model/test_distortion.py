"""Lens distortion (Brown-Conrady, OpenCV's order k1, k2, p1, p2, k3) in the camera model: the
projection against OpenCV, the Jacobians against finite differences, the inverse mapping, the
[[camera]] distortion field."""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import DOWN_CAMERA, mesh_tables, region_tables
from vdo.config import experiment as config
from vdo.model.camera import PARAMETERS, Camera, parameter_jacobian, project, rotation, sensitivity
from vdo.model.pose import look_at_angles
from vdo.core.errors import ConfigError
from vdo.scene import cameras_of

RNG = np.random.default_rng(11)
LENSES = [(-0.25, 0.08, 0.0, 0.0, -0.01),            # barrel, radial only
          (0.12, -0.03, 0.0015, -0.001, 0.02),       # pincushion with tangential terms
          (-0.08, 0.0, -0.002, 0.0025, 0.0)]


def camera(distortion, i=0):
    position = RNG.uniform(-2, 2, 3) + np.array([0, 0, 2])
    pan, tilt = look_at_angles(position, RNG.uniform(-0.2, 0.2, 3))
    return Camera(f"c{i}", width=800, height=600, pixel_size=5e-6, focal_length=0.012,
                  position=position, pan=pan, tilt=tilt, roll=RNG.uniform(-0.5, 0.5),
                  principal_offset_px=tuple(RNG.uniform(-30, 30, 2)), distortion=distortion)


CAMERAS = [camera(d, i) for i, d in enumerate(LENSES)]


def points_in_view(cam, n=300):
    """World points whose undistorted image lies within the frame (depth 0.5 to 3 m)."""
    z = RNG.uniform(0.5, 3, n)
    half_w, half_h = cam.width / (2 * cam.focal_px), cam.height / (2 * cam.focal_px)
    p_cam = np.column_stack([RNG.uniform(-half_w, half_w, n) * z, RNG.uniform(-half_h, half_h, n) * z, z])
    return (p_cam - cam.t) @ cam.R


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.name)
def test_distorted_projection_matches_opencv(cam):
    X = points_in_view(cam)
    rvec, _ = cv2.Rodrigues(cam.R)
    expected, _ = cv2.projectPoints(X, rvec, cam.t, cam.K, np.array(cam.distortion))
    got = cam.project(X)
    assert np.abs(got - expected[:, 0]).max() < 1e-6
    pinhole = Camera(cam.name, cam.width, cam.height, cam.pixel_size, cam.focal_length,
                     cam.position, cam.pan, cam.tilt, cam.roll, cam.principal_offset_px)
    assert np.abs(got - pinhole.project(X)).max() > 1.0     # the distortion really moves points


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.name)
def test_sensitivity_with_distortion_matches_finite_differences(cam):
    X = points_in_view(cam, 20)
    S = cam.sensitivity(X)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (cam.project(X + e) - cam.project(X - e)) / (2 * h)
        np.testing.assert_allclose(S[:, :, k], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.name)
def test_parameter_jacobian_with_distortion_matches_finite_differences(cam):
    cx, cy = cam.principal_point
    d = jnp.asarray(cam.distortion)
    params = np.concatenate([cam.position, [cam.pan, cam.tilt, cam.roll, cam.focal_px]])

    def pixels(p, X):
        K = jnp.array([[p[6], 0, cx], [0, p[6], cy], [0, 0, 1.0]])
        R = rotation(p[3], p[4], p[5])
        return np.asarray(project(K, R, -R @ p[:3], X, d))

    for X in points_in_view(cam, 4):
        J = np.asarray(parameter_jacobian(cam.focal_px, cx, cy, cam.position, cam.pan, cam.tilt,
                                          cam.roll, X, d))
        assert J.shape == (2, len(PARAMETERS))
        for k, h in enumerate([1e-6] * 3 + [1e-7] * 3 + [1e-3]):
            e = np.zeros(7)
            e[k] = h
            fd = (pixels(params + e, X) - pixels(params - e, X)) / (2 * h)
            np.testing.assert_allclose(J[:, k], fd, rtol=2e-6, atol=1e-5 * np.abs(fd).max() + 1e-6)


def test_sensitivity_function_without_distortion_is_the_pinhole_formula():
    """s = (f / Z_c) [[1, 0, -X_c/Z_c], [0, 1, -Y_c/Z_c]] R when the distortion is None."""
    cam = CAMERAS[0]
    X = points_in_view(cam, 10)
    p = X @ cam.R.T + cam.t
    f = cam.focal_px
    expected = np.stack([np.stack([f / p[:, 2], 0 * p[:, 0], -f * p[:, 0] / p[:, 2] ** 2], -1),
                         np.stack([0 * p[:, 0], f / p[:, 2], -f * p[:, 1] / p[:, 2] ** 2], -1)], -2) @ cam.R
    np.testing.assert_allclose(np.asarray(sensitivity(cam.K, cam.R, cam.t, X)), expected, rtol=1e-12)


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.name)
def test_undistorted_pixels_invert_the_distortion(cam):
    """Against OpenCV's own inverse (cv2.undistortPoints with P = K) on the image's pixel grid."""
    u, v = np.meshgrid(np.arange(0, cam.width, 37.0), np.arange(0, cam.height, 29.0))
    uv = np.stack([u.ravel(), v.ravel()], -1)
    got = cam.undistorted_pixels(uv)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    ref = cv2.undistortPoints(uv[:, None], cam.K, np.array(cam.distortion), R=None, P=cam.K,
                              criteria=crit)
    np.testing.assert_allclose(got, ref[:, 0], atol=1e-6)


def test_config_distortion_field(plate_experiment):
    cams = DOWN_CAMERA.format(name="down", focal=24, u=0.5) + "distortion = [-0.1, 0.02, 0.001, -0.002, 0.003]\n"
    exp = config.load(plate_experiment(cameras=cams))
    assert cameras_of(exp.camera_specs, exp.rails)[0].distortion == (-0.1, 0.02, 0.001, -0.002, 0.003)
    assert exp.to_dict()["camera"][0]["distortion"] == [-0.1, 0.02, 0.001, -0.002, 0.003]
    with pytest.raises(ConfigError, match="distortion"):
        config.load(plate_experiment(cameras=cams.replace("0.003]", "0.003, 0.1]")))


# --------------------------------------------------------------------------------------------
# Renders with distortion: a wider pinhole render resampled onto the distorted pixels
# --------------------------------------------------------------------------------------------
MARKER = np.array([0.05, -0.03, 0.02])
RENDER_CASES = [  # position, roll, principal offset (px), distortion, aim offset from the marker
    ((1.0, 0.3, 0.4), 0.0, (0.0, 0.0), (-0.35, 0.12, 0.0, 0.0, 0.0), (0.0, 0.2, -0.06)),
    ((0.2, -1.0, 0.6), 0.3, (37.0, -21.0), (0.25, -0.05, 0.002, -0.0015, 0.01), (0.2, 0.16, -0.1)),
]


@pytest.mark.parametrize("position,roll,offset,distortion,aim", RENDER_CASES)
def test_rendered_marker_lands_on_distorted_projection(position, roll, offset, distortion, aim):
    """A bright sphere (4 mm, ~3 px radius) far from the principal point, where the distortion
    moves it by more than a pixel: its intensity centroid in `render_camera`'s image is within
    0.05 px of the distorted projection of its centre."""
    from vdo.core.backend import mitsuba
    from vdo.render import render_camera

    mi = mitsuba()
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"}, "marker": {
        "type": "sphere", "center": [float(c) for c in MARKER], "radius": 0.004,
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
    pan, tilt = look_at_angles(position, MARKER + np.array(aim))
    cam = Camera("c", 320, 240, 5e-6, 0.004, np.array(position), pan, tilt, roll=roll,
                 principal_offset_px=offset, distortion=distortion)
    pinhole = Camera("c", 320, 240, 5e-6, 0.004, np.array(position), pan, tilt, roll=roll,
                     principal_offset_px=offset)
    expected = cam.project(MARKER[None])[0]
    assert np.linalg.norm(expected - pinhole.project(MARKER[None])[0]) > 1.0
    image = render_camera(scene, cam, None, 64, 0)
    assert image.shape == (240, 320)
    rows, cols = np.mgrid[:240, :320]
    centroid = np.array([(image * cols).sum(), (image * rows).sum()]) / image.sum()
    assert np.linalg.norm(centroid - expected) < 0.05


def test_visibility_uses_the_distorted_image(plate_experiment):
    """Barrel distortion pulls the plate's far points into the frame: the ray cast's in-image test
    agrees with `Camera.project` (float32 there: points within 0.01 px of an edge may differ)."""
    from vdo import scene
    from vdo.physics import visibility

    cams = """
[[camera]]
name = "wide"
sensor_mm = [22.2, 14.8]
pixels = [300, 200]
focal_mm = 20
position_m = [0.0, 0.0, 0.5]
pan_deg = 0
tilt_deg = -90
body = false
distortion = [-0.2, 0.02, 0.0, 0.0, 0.0]   # monotone: no fold anywhere
"""
    exp = config.load(plate_experiment(cameras=cams))
    meshes = scene.load_meshes(**mesh_tables(exp))
    samples = scene.sample_regions(meshes, **region_tables(exp))
    cam = cameras_of(exp.camera_specs, exp.rails)[0]
    vis = visibility.compute_visibility(scene.build_scene(meshes), [cam], samples,
                                        exp.evaluation.incidence_limit, progress=False)
    uv = cam.project(samples.points)
    margin = np.minimum.reduce([uv[:, 0] + 0.5, cam.width - 0.5 - uv[:, 0],
                                uv[:, 1] + 0.5, cam.height - 0.5 - uv[:, 1]])
    clear = np.abs(margin) > 0.01
    np.testing.assert_array_equal(vis.in_image[0][clear], margin[clear] > 0)
    pinhole = Camera(cam.name, cam.width, cam.height, cam.pixel_size, cam.focal_length,
                     cam.position, cam.pan, cam.tilt).project(samples.points)
    inside_pinhole = ((pinhole[:, 0] >= -0.5) & (pinhole[:, 0] <= cam.width - 0.5)
                      & (pinhole[:, 1] >= -0.5) & (pinhole[:, 1] <= cam.height - 0.5))
    assert vis.in_image[0].sum() > inside_pinhole.sum() + 50     # the distortion matters here
