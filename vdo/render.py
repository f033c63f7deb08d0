"""Images with Mitsuba: the sensor for a vdo camera, and renders of the scene.

`sensor_dict` is the only place a vdo `Camera` becomes a Mitsuba sensor; the frame conversion
itself lives in `Camera.mitsuba_to_world` / `mitsuba_principal_offset`.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera


def sensor_dict(camera: Camera, spp: int = 16, scale: float = 1.0, jitter: bool = True,
                aperture_radius: float | None = None, focus_distance: float | None = None) -> dict:
    """Mitsuba sensor dict for `camera`: linear float luminance film, box filter (bit-identical
    renders for a seed, see STACK-NOTES), stratified sampler. `scale` < 1 renders a smaller image
    of the same view (pixel pitch / scale). With `aperture_radius` (m) a thin lens focused at
    `focus_distance` (m) gives depth of field (Mitsuba's thinlens has no principal-point offset)."""
    width, height = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    ox, oy = camera.mitsuba_principal_offset()
    film = {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
            "pixel_format": "luminance", "component_format": "float32"}
    sensor = {"fov_axis": "x", "fov": camera.mitsuba_fov_deg(), "near_clip": 1e-3,
              "far_clip": 1e4, "to_world": _transform(camera.mitsuba_to_world()), "film": film,
              "sampler": {"type": "stratified", "sample_count": spp, "jitter": jitter}}
    if aperture_radius:
        if camera.principal_offset_px != (0.0, 0.0):
            raise ValueError(f"camera {camera.name!r}: a thin lens cannot have a principal-point offset")
        return sensor | {"type": "thinlens", "aperture_radius": aperture_radius,
                         "focus_distance": focus_distance}
    return sensor | {"type": "perspective", "principal_point_offset_x": ox,
                     "principal_point_offset_y": oy}


def _transform(matrix: np.ndarray):
    from .backend import mitsuba

    return mitsuba().ScalarTransform4f(np.asarray(matrix, dtype=float))
