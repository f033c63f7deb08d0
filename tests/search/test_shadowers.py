"""The shadow check names what to move: the camera whose body stands between a region and a light,
and that light (`vdo.search.obstruction.light_shadowers`), found by casting each body alone.

A 1 m plate at z = 0 under a panel 2.5 m above its centre; a camera looking straight down from
1.5 m above the centre stands on the segment from the plate's centre to the panel, so its body
hides part of that panel from the plate's middle. A second camera 0.8 m to the side and a second
panel low at the side are far from every segment from a plate sample to the other's panel
(checked below in closed form), so neither is named."""

from __future__ import annotations

import numpy as np

from conftest import DOWN_CAMERA, aimed_camera, write_plate_experiment

LIGHTS = """
[[light]]
name = "above"
position_m = [0, 0, 2.5]
target_m = [0, 0, 0]
size_m = [0.2, 0.2]
radiance = 10

[[light]]
name = "side"
position_m = [3, 0, 1]
target_m = [0, 0, 0]
size_m = [0.2, 0.2]
radiance = 10
"""


def segment_distance(p, a, b):
    """Distance from point p to the segments a -> b (rows)."""
    d = b - a
    t = np.clip(((p - a) * d).sum(axis=1) / (d * d).sum(axis=1), 0, 1)
    return np.linalg.norm(a + t[:, None] * d - p, axis=1)


def test_the_body_between_a_region_and_a_light_is_named_with_the_light(tmp_path):
    from vdo.commands.evaluate import _shadow_line
    from vdo.config.experiment import load
    from vdo.optimize import layout_checks
    from vdo.search.obstruction import light_lost
    from vdo.state import layout_state, prepare, unobstructed_lighting

    cameras = DOWN_CAMERA.format(name="down", focal=24, u=0.5) + aimed_camera("aside", 0.1) + LIGHTS
    exp = load(write_plate_experiment(tmp_path, spacing=50, cameras=cameras))
    geometry = prepare(exp)
    state = layout_state(geometry, predict_fields=False)
    X = geometry.samples.points
    down, aside = (c.position for c in state.cameras)
    above, side = (np.asarray(light.position, float) for light in exp.lights)
    # closed form: 'down' is on the plate centre's segment to 'above'; 'aside' is > 0.5 m from
    # every sample's segment to 'above' and to 'side', 'down' > 0.5 m from every one to 'side'
    assert segment_distance(down, np.zeros((1, 3)), above[None])[0] < 1e-9
    assert segment_distance(aside, X, np.broadcast_to(above, X.shape)).min() > 0.5
    assert segment_distance(aside, X, np.broadcast_to(side, X.shape)).min() > 0.5
    assert segment_distance(down, X, np.broadcast_to(side, X.shape)).min() > 0.5

    entry = next(c for c in layout_checks(state) if c["constraint"] == "no_shadow_from_cameras")
    lost = light_lost(unobstructed_lighting(geometry).lit, state.illumination.lit, geometry.samples)[0]
    assert entry["value"] == lost > 0 and not entry["met"]
    assert entry["cameras"] == ["down"] and entry["lights"] == ["above"]
    line = _shadow_line(entry)
    assert "region top" in line and "down stands between the region and light 'above'" in line
    assert "move that camera or the light" in line and "'side'" not in line and "aside" not in line
