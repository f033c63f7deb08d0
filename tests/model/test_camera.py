"""The camera model against OpenCV's projection and finite differences."""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from vdo.model.camera import PARAMETERS, Camera, parameter_jacobian, project, rotation, rotation_derivatives
from vdo.model.pose import look_at_angles

RNG = np.random.default_rng(7)


def random_camera(i):
    position = RNG.uniform(-2, 2, 3) + np.array([0, 0, 2])
    pan, tilt = look_at_angles(position, RNG.uniform(-0.2, 0.2, 3))
    return Camera(f"c{i}", width=640 + 64 * i, height=480, pixel_size=4.3e-6,
                  focal_length=RNG.uniform(0.012, 0.1), position=position, pan=pan, tilt=tilt,
                  roll=RNG.uniform(-0.5, 0.5), principal_offset_px=tuple(RNG.uniform(-40, 40, 2)))


CAMERAS = [random_camera(i) for i in range(6)] + [
    Camera("straight-down", 600, 400, 3.7e-6, 0.024, np.array([0.1, 0.2, 1.5]), 0.3, -np.pi / 2)]


def points_in_front(cam, n=200):
    """World points spread in front of `cam` (camera depth 0.5 to 3 m)."""
    p_cam = np.column_stack([RNG.uniform(-0.4, 0.4, n), RNG.uniform(-0.3, 0.3, n), RNG.uniform(0.5, 3, n)])
    return (p_cam - cam.t) @ cam.R


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.name)
def test_projection_matches_opencv(cam):
    X = points_in_front(cam)
    rvec, _ = cv2.Rodrigues(cam.R)
    expected, _ = cv2.projectPoints(X, rvec, cam.t, cam.K, np.zeros(5))
    got = cam.project(X)
    np.testing.assert_allclose(got, expected[:, 0, :], rtol=1e-9, atol=0)


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.name)
def test_rotation_is_proper_and_horizontal(cam):
    R = cam.R
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    level = Camera("level", 10, 10, 1e-5, 0.01, np.zeros(3), cam.pan, cam.tilt, roll=0.0)
    assert abs(level.R[0, 2]) < 1e-12          # image x axis horizontal when roll = 0
    assert level.R[1, 2] <= 1e-12              # image y axis points down (or horizontal)


def test_look_at_points_the_optical_axis_at_the_target():
    position, target = np.array([1.0, -2.0, 2.5]), np.array([0.2, 0.3, 1.1])
    pan, tilt = look_at_angles(position, target)
    cam = Camera("c", 101, 81, 1e-5, 0.02, position, pan, tilt)
    direction = (target - position) / np.linalg.norm(target - position)
    np.testing.assert_allclose(cam.optical_axis, direction, atol=1e-12)
    np.testing.assert_allclose(cam.project(target[None])[0], cam.principal_point, atol=1e-9)


def central_difference(f, x, h):
    x = np.asarray(x, dtype=float)
    cols = []
    for k in range(x.size):
        e = np.zeros_like(x)
        e.flat[k] = h
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.name)
def test_sensitivity_matches_finite_differences(cam):
    for X in points_in_front(cam, 5):
        fd = central_difference(lambda x: cam.project(x[None])[0], X, 1e-6)
        np.testing.assert_allclose(cam.sensitivity(X[None])[0], fd, rtol=1e-6, atol=1e-4)


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.name)
def test_parameter_jacobian_matches_finite_differences(cam):
    cx, cy = cam.principal_point
    params = np.concatenate([cam.position, [cam.pan, cam.tilt, cam.roll, cam.focal_px]])

    def pixels(p, X):
        K = jnp.array([[p[6], 0, cx], [0, p[6], cy], [0, 0, 1.0]])
        R = rotation(p[3], p[4], p[5])
        return project(K, R, -R @ p[:3], X)

    for X in points_in_front(cam, 4):
        J = np.asarray(parameter_jacobian(cam.focal_px, cx, cy, cam.position, cam.pan, cam.tilt,
                                          cam.roll, X))
        assert J.shape == (2, len(PARAMETERS))
        steps = np.array([1e-6] * 3 + [1e-7] * 3 + [1e-3])
        for k, h in enumerate(steps):
            e = np.zeros(7)
            e[k] = h
            fd = (np.asarray(pixels(params + e, X)) - np.asarray(pixels(params - e, X))) / (2 * h)
            np.testing.assert_allclose(J[:, k], fd, rtol=2e-6, atol=1e-5 * np.abs(fd).max() + 1e-6)


def test_rotation_derivatives_match_finite_differences():
    angles = np.array([0.7, -0.4, 0.2])
    analytic = rotation_derivatives(*angles)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-7
        fd = (np.asarray(rotation(*(angles + e))) - np.asarray(rotation(*(angles - e)))) / 2e-7
        np.testing.assert_allclose(analytic[k], fd, atol=1e-8)


def test_sensitivity_closed_form_fronto_parallel():
    """Looking straight down from height Z, a horizontal move dX of a point under the optical
    centre moves its image by f/Z pixels per metre (paper eq. 4 in its simplest case)."""
    cam = Camera("c", 600, 400, 3.7e-6, 0.05, np.array([0.0, 0.0, 2.0]), 0.0, -np.pi / 2)
    s = cam.sensitivity(np.array([[0.0, 0.0, 0.0]]))[0]
    f_over_z = cam.focal_px / 2.0
    np.testing.assert_allclose(np.abs(s[:, :2]).max(axis=0), [f_over_z, f_over_z], rtol=1e-12)
    np.testing.assert_allclose(s[:, 2], 0.0, atol=1e-9)
