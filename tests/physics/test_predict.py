"""The predicted fields through the whole pipeline (config -> ray cast -> lights -> objective),
against closed forms and the paper's orders of magnitude."""

from pathlib import Path

import numpy as np
import pytest

from conftest import DOWN_CAMERA, raycast
from vdo.physics import lighting
from vdo.physics.predict import predict, speckle_model

LIGHT = """
[[light]]
name = "panel"
position_m = [{x}, 0.0, 1.2]
target_m = [0.0, 0.0, 0.0]
size_m = [{size}, {size}]
radiance = 60.0
"""
BAR = '[[mesh]]\nname = "bar"\nfile = "bar.stl"\nunit = "mm"\nrole = "obstacle"\n'


def run(path):
    exp, samples, cams, sc, vis = raycast(path)
    illum = lighting.illuminate(sc, exp.lights, samples, exp.render.ambient_radiance)
    pred = predict(exp.regions, exp.evaluation, exp.speckle, exp.sensor, cams, samples, vis, illum,
                   speckle_model(exp.speckle))
    return exp, samples, cams, vis, illum, pred


def test_sensitivity_of_one_camera_is_its_projection_jacobian(plate_experiment):
    """With one camera the global sensitivity per axis is the norm of the column of dx/dX
    (paper eq. 4), wherever the camera sees the point well inside the image and incidence limit."""
    exp, samples, cams, vis, _, pred = run(plate_experiment(cameras=DOWN_CAMERA.format(
        name="down", focal=24, u=0.5)))
    s = cams[0].sensitivity(samples.points)
    expected = np.linalg.norm(s, axis=1)
    inner = vis.visible[0] & (np.abs(samples.points[:, 0]) < 0.35)
    np.testing.assert_allclose(pred.sensitivity[inner], expected[inner], rtol=1e-9)
    assert not pred.measured.any() and np.isinf(pred.sigma_max).all()    # one view: unmeasured


def test_stereo_pair_closed_form(plate_experiment):
    """Two cameras at +-theta about the plate normal: sigma_z / sigma_x = cot(theta) at the centre
    (the cameras' common point), the stereo triangulation closed form."""
    theta = np.radians(20)
    r = 1.5
    cams = "".join(f"""
[[camera]]
name = "{name}"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 35
position_m = [{sx * r * np.sin(theta)}, 0.0, {r * np.cos(theta)}]
target_m = [0.0, 0.0, 0.0]
""" for name, sx in (("left", -1), ("right", 1)))
    exp, samples, _, _, _, pred = run(plate_experiment(cameras=cams + LIGHT.format(x=0.0, size=0.4)))
    centre = np.argmin(np.linalg.norm(samples.points, axis=1))
    sx, sy, sz = pred.sigma_xyz[centre]
    assert pred.measured[centre]
    assert sz / sx == pytest.approx(1 / np.tan(theta), rel=0.02)


def test_a_sample_in_shadow_is_predicted_worse(plate_experiment):
    """A bar between the panel and the plate: its shadow, lit by the ambient light only, has less
    contrast, so a higher sigma (without ambient light it would be black: unmeasured)."""
    theta = np.radians(15)
    cams = "".join(f"""
[[camera]]
name = "{name}"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
position_m = [0.0, {sy * 1.5 * np.sin(theta)}, {1.5 * np.cos(theta)}]
target_m = [0.0, 0.0, 0.0]
""" for name, sy in (("a", -1), ("b", 1)))
    ambient = "\n[render]\nambient_radiance = 0.02\n"
    path = plate_experiment(cameras=cams + LIGHT.format(x=0.6, size=0.1) + ambient, extra_meshes=BAR,
                            files=[("bar.stl", [80, 2000, 80], [150, 0, 300])])
    exp, samples, _, vis, illum, pred = run(path)
    lit = illum.lit[0]
    both = vis.visible.all(axis=0) & pred.measured
    shadow, sun = both & (lit == 0), both & (lit == 1)
    assert shadow.sum() > 50 and sun.sum() > 50
    assert illum.irradiance[shadow].max() < illum.irradiance[sun].min()
    assert np.median(pred.sigma_max[shadow]) > 1.5 * np.median(pred.sigma_max[sun])


@pytest.mark.parametrize("name,low,high", [("three_cameras.toml", 4, 16), ("ten_cameras.toml", 15, 60)])
def test_paper_orders_of_magnitude_on_the_joint(name, low, high):
    """Paper sec. 5.2: about 8 mpixel/um on the joint with its 3 cameras, about 30 with all 10.
    We check the best axis of the median joint sensitivity is within a factor 2 of that."""
    path = Path(__file__).resolve().parents[2] / "experiments" / "beam_column" / name
    exp, samples, _, _, _, pred = run(path)
    joint = np.isin(samples.region, [k for k, r in enumerate(samples.region_names) if r.startswith("joint")])
    best_axis = np.median(pred.sensitivity[joint] * 1e-3, axis=0).max()
    assert low <= best_axis <= high, best_axis
