"""Differentiable obscuration (vdo.search.obscuration): value against an independent ray-box computation,
gradient against central finite differences of the same rendered quantity, the JAX bridge.

Scene: a 0.4 m square plate (its top face at z = 0 is the region), a 0.03 x 0.6 x 0.03 m bar at
half the camera height whose shadow (seen from the camera) crosses the plate's +x edge and ends
over the plate, and a camera 600 x 400 px, 24 mm lens on 22.2 mm, ~1.5 m away.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from vdo.model.camera import Camera, rotation
from vdo.model.pose import look_at_angles
from vdo.search.obscuration import ObscurationRenderer, camera_theta
from vdo.scene import SceneMesh

BAR_CENTER = np.array([0.25, 0.18, 0.5])
BAR_EXTENTS = np.array([0.03, 0.6, 0.03])
PLATE = 0.4
ROLL = 0.1


def _box(extents, center) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    box.apply_translation(center)
    return box


def _camera(position, target=(0.0, 0.0, 0.0), pan=None) -> Camera:
    pan_at, tilt = look_at_angles(position, target)
    pan = pan_at if pan is None else pan
    return Camera("cam", 600, 400, 22.2e-3 / 600, 24e-3, np.asarray(position, float), pan, tilt,
                  roll=ROLL)


OBLIQUE = _camera([0.35, -0.25, 1.4])            # bar shadow crosses the plate's edge
DOWN = _camera([0.4, -0.05, 1.5], [0.4, -0.05, 0.0], pan=np.pi / 2)   # straight down
CLEAR = _camera([-0.25, -0.25, 1.4])            # bar in view but its shadow off the plate


def _meshes():
    """The region (the plate's top face) and the obstacles: the bar and the whole plate."""
    plate = _box([PLATE, PLATE, 0.01], [0, 0, -0.005])
    top = np.flatnonzero(plate.face_normals[:, 2] > 0.9)
    vertices, faces = np.asarray(plate.vertices), np.asarray(plate.faces)
    region = SceneMesh("plate:top", "specimen", vertices, faces[top])
    bar = _box(BAR_EXTENTS, BAR_CENTER)
    return region, [SceneMesh("bar", "obstacle", np.asarray(bar.vertices), np.asarray(bar.faces)),
                    SceneMesh("plate", "specimen", vertices, faces)]


@pytest.fixture(scope="module")
def renderer():
    region, obstacles = _meshes()
    return ObscurationRenderer(OBLIQUE, region, obstacles, width=96, spp=256)


def geometric_obscuration(theta, n=800):
    """Independent reference: the image-area-weighted fraction of an n x n grid of plate points
    whose segment to the optical centre crosses the bar (slab test). A plate element dA maps to
    the image area f^2 (n . (C - X)) / (z_c . (X - C))^3 dA (pinhole), so each point is weighted by
    that; also returns the plain area fraction."""
    C = np.asarray(theta[:3], float)
    z_c = np.asarray(rotation(jnp.float64(theta[3]), jnp.float64(theta[4]), jnp.float64(ROLL)))[2]
    s = (np.arange(n) + 0.5) / n * PLATE - PLATE / 2
    X = np.stack(np.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)
    X = np.column_stack([X, np.zeros(len(X))])
    lo, hi = BAR_CENTER - BAR_EXTENTS / 2, BAR_CENTER + BAR_EXTENTS / 2
    d = C - X                                        # segment X + t d, t in [0, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - X) / d, (hi - X) / d
    t_in = np.nanmax(np.minimum(t1, t2), axis=1)
    t_out = np.nanmin(np.maximum(t1, t2), axis=1)
    blocked = (t_out >= np.maximum(t_in, 0.0)) & (t_in <= 1.0)
    weight = d[:, 2] / ((X - C) @ z_c) ** 3
    return float(weight[blocked].sum() / weight.sum()), float(blocked.mean())


@pytest.mark.parametrize("camera", [OBLIQUE, DOWN], ids=["oblique", "down"])
def test_value_matches_ray_box_reference(renderer, camera):
    theta = camera_theta(camera)
    _, free = renderer.images(theta)
    # the whole plate is inside the image (the reference does not crop to the frame)
    assert free.sum() > 400 and free[0].sum() == free[-1].sum() == free[:, 0].sum() == free[:, -1].sum() == 0
    o = renderer.value(theta)
    reference, _ = geometric_obscuration(theta)
    assert 0.03 < reference < 0.3
    assert abs(o - reference) < 0.02 * reference + 1e-3, (o, reference)


def test_value_is_deterministic(renderer):
    theta = camera_theta(OBLIQUE) + np.array([1e-3, 0, 0, 0, 0])
    assert renderer.value(theta) == renderer.value(theta.copy())


def test_gradient_matches_central_differences(renderer):
    theta = camera_theta(OBLIQUE)
    o, grad = renderer.value_and_grad(theta)
    assert 0.03 < o < 0.2
    steps = np.array([1e-2, 1e-2, 1e-2, 1e-2, 1e-2])   # m, m, m, rad, rad
    fd = np.empty(5)
    for k in range(5):
        e = np.zeros(5)
        e[k] = steps[k]
        fd[k] = (renderer.value(theta + e) - renderer.value(theta - e)) / (2 * steps[k])
    big = np.abs(grad) > 0.05 * np.abs(grad).max()
    assert big[:3].sum() == 3                           # x, y, z all matter at this pose
    np.testing.assert_allclose(grad[big], fd[big], rtol=0.10)
    # pan and tilt turn the camera about its optical centre: for a pinhole that moves no
    # silhouette across another, only the image-area weighting changes, so both are tiny
    np.testing.assert_allclose(grad[~big], fd[~big], atol=0.03)


def test_no_overlap_gives_zero():
    region, obstacles = _meshes()
    r = ObscurationRenderer(CLEAR, region, obstacles, width=96, spp=16)
    masked, free = r.images(camera_theta(CLEAR))
    assert free.sum() > 400
    o, grad = r.value_and_grad(camera_theta(CLEAR))
    assert o == 0.0
    assert np.abs(grad).max() < 1e-4


def test_step_against_gradient_reduces_obscuration(renderer):
    theta = camera_theta(OBLIQUE)
    o, grad = renderer.value_and_grad(theta)
    step = -grad / np.linalg.norm(grad) * 0.02        # 2 cm (mostly along -x)
    o2 = renderer.value(theta + step)
    assert o2 < o - 0.5 * 0.02 * np.linalg.norm(grad)
    far = theta + 10 * step                             # 20 cm: the bar's shadow leaves the plate
    assert renderer.value(far) == 0.0


def test_jax_bridge(renderer):
    f = renderer.jax_function()
    theta = camera_theta(OBLIQUE) + np.array([2e-3, -1e-3, 0.0, 1e-3, 0.0])
    value, grad = renderer.value_and_grad(theta)
    t = jnp.asarray(theta)
    np.testing.assert_allclose(float(jax.jit(f)(t)), value)
    np.testing.assert_allclose(np.asarray(jax.jit(jax.grad(f))(t)), grad, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.jit(jax.jacfwd(f))(t)), grad, rtol=1e-6)
    direction = jnp.asarray([1.0, 0.5, -0.2, 0.1, 0.3])
    out, tangent = jax.jit(lambda x, v: jax.jvp(f, (x,), (v,)))(t, direction)
    np.testing.assert_allclose(float(out), value)
    np.testing.assert_allclose(float(tangent), grad @ np.asarray(direction), rtol=1e-6)


def test_forward_and_reverse_modes_agree():
    region, obstacles = _meshes()
    theta = camera_theta(OBLIQUE)
    rev = ObscurationRenderer(OBLIQUE, region, obstacles, width=64, spp=16, mode="reverse")
    fwd = ObscurationRenderer(OBLIQUE, region, obstacles, width=64, spp=16, mode="forward")
    (vr, gr), (vf, gf) = rev.value_and_grad(theta), fwd.value_and_grad(theta)
    assert vr == vf
    np.testing.assert_allclose(gf, gr, rtol=1e-3, atol=1e-4)
