"""The NumPy pose (vdo.model.pose) against the JAX camera model and closed forms."""
import math

import jax.numpy as jnp
import numpy as np
import pytest

from vdo.model import camera, pose

RNG = np.random.default_rng(3)


def test_the_numpy_rotation_is_the_jax_one_and_a_rotation():
    pan, tilt, roll = RNG.uniform(-math.pi, math.pi, (3, 20))
    R = pose.rotation(pan, tilt, roll)
    np.testing.assert_allclose(R, np.asarray(camera.rotation(jnp.asarray(pan), jnp.asarray(tilt),
                                                             jnp.asarray(roll))), atol=1e-14)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(R[:, 2], pose.optical_axis(pan, tilt), atol=1e-15)


def test_the_aim_point_is_on_the_axis_at_the_centres_depth():
    position, target = np.array([1.0, -2.0, 1.5]), np.array([0.2, 0.3, 0.1])
    pan, tilt = pose.look_at_angles(position, target)
    # the centre on the axis is its own aim point; off the axis, its projection on the axis
    np.testing.assert_allclose(pose.aim_point(position, pan, tilt, target), target, atol=1e-12)
    side = np.cross(target - position, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(pose.aim_point(position, pan, tilt, target + 0.4 * side), target, atol=1e-12)
    # a centre behind the camera: the least depth in front of it
    z = (target - position) / np.linalg.norm(target - position)
    np.testing.assert_allclose(pose.aim_point(position, pan, tilt, position - z),
                               position + pose.MIN_AIM_DEPTH * z, atol=1e-12)


@pytest.mark.parametrize("tilt_deg,holds", [(-90.0, False), (90.0, False), (-89.0, True), (0.0, True)])
def test_a_vertical_axis_does_not_hold_its_aim(tilt_deg, holds):
    assert pose.holds_aim(math.radians(tilt_deg)) is holds
