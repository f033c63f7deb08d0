"""The plate of a validation case (`vdo validate`): its frame, the cameras aimed at it, its
imposed deformation, and the check that every camera sees the patch, all in metres and radians.
Light enough (no Mitsuba scene, no correlation) to check every case before any render.

The patch centre is the world origin; the plate's normal n = (0, -sin tilt, cos tilt); a point X
of the plate moves to X + U + T E Tᵀ X (U the imposed displacement, E the in-plane strain in the
face frame (t_u, t_v) = T).
"""

from __future__ import annotations

import math

import numpy as np

from vdo.config.validation import Case, ValidationSpec
from vdo.core.errors import ConfigError
from vdo.model.camera import Camera
from vdo.model.pose import look_at_angles
from vdo.model.surface import face_frame

MAX_INCIDENCE_DEG = 80.0  # a camera sees the plate at most this far from its normal
MARGIN_PX = 4            # the patch stays this many pixels inside every image


def strain_tensor(case: Case) -> np.ndarray:
    """The imposed in-plane strain as a world 3x3 displacement gradient T E Tᵀ (T = [t_u t_v],
    E the symmetric 2x2 of (eps_uu, eps_vv, eps_uv)); zeros for a translation case."""
    if case.strain is None:
        return np.zeros((3, 3))
    g = plate_geometry(case)
    T = np.stack([g["t_u"], g["t_v"]], axis=1)
    e = case.strain
    return T @ np.array([[e[0], e[2]], [e[2], e[1]]]) @ T.T


def deform(case: Case, points) -> np.ndarray:
    """Deformed positions X + U + F X (the patch centre is the world origin), metres."""
    points = np.asarray(points, dtype=float)
    return points + case.displacement + points @ strain_tensor(case).T


def undeform(case: Case, points) -> np.ndarray:
    """The reference position of deformed points (inverse of `deform`)."""
    points = np.asarray(points, dtype=float)
    return np.linalg.solve(np.eye(3) + strain_tensor(case), (points - case.displacement).T).T


def plate_geometry(case: Case) -> dict:
    """The plate's frame: normal n = (0, -sin tilt, cos tilt), the face frame (t_u, t_v) that
    vdo.scene gives such a face, the patch corners and the plate's 4 vertices (world, m)."""

    n = np.array([0.0, -math.sin(case.tilt), math.cos(case.tilt)])
    t_u, t_v = face_frame(n)
    w, h = case.patch
    centre = np.zeros(3)
    origin = centre - 0.5 * w * t_u - 0.5 * h * t_v
    corners = np.array([origin, origin + w * t_u, origin + w * t_u + h * t_v, origin + h * t_v])
    m = case.plate_margin
    pw, ph = w + 2 * m, h + 2 * m
    p0 = centre - 0.5 * pw * t_u - 0.5 * ph * t_v
    plate = np.array([p0, p0 + pw * t_u, p0 + pw * t_u + ph * t_v, p0 + ph * t_v])
    return dict(normal=n, t_u=t_u, t_v=t_v, centre=centre, origin=origin, corners=corners,
                plate=plate)


def cameras_of(case: Case) -> list:
    """The case's vdo Cameras, each aimed at the patch centre (the world origin)."""

    out = []
    for c in case.cameras:
        d = np.array([math.sin(c.polar) * math.cos(c.azimuth), math.sin(c.polar) * math.sin(c.azimuth),
                      math.cos(c.polar)])
        pos = c.distance * d
        if c.polar < 1e-9:
            pan, tilt = 0.0, -math.pi / 2
        else:
            pan, tilt = look_at_angles(pos, np.zeros(3))
        out.append(Camera(name=c.name, width=c.pixels[0], height=c.pixels[1], pixel_size=c.pixel_size,
                          focal_length=c.focal_length, position=pos, pan=pan, tilt=tilt))
    return out


def check_cases(spec: ValidationSpec) -> None:
    """For every case: every camera sees the whole patch (corners displaced by U) in front of it,
    at an incidence below `MAX_INCIDENCE_DEG`, at least `MARGIN_PX` pixels inside its image; the
    imposed displacement is sub-pixel. ConfigError naming the case and camera otherwise."""
    for case in spec.cases:
        where = f'case "{case.name}"'
        g = plate_geometry(case)
        for k, cam in enumerate(cameras_of(case)):
            ray = g["centre"] - cam.position
            incidence = math.degrees(math.acos(abs(ray @ g["normal"]) / np.linalg.norm(ray)))
            field_name = f"{where}.cameras[{k}]"
            if incidence > MAX_INCIDENCE_DEG:
                raise ConfigError(spec.path, field_name,
                                  f"sees the plate at {incidence:.0f} deg incidence; keep it below "
                                  f"{MAX_INCIDENCE_DEG:g} deg")
            corners = np.concatenate([g["corners"], deform(case, g["corners"])])
            x = cam.project(corners)
            if np.any(x < MARGIN_PX) or np.any(x[:, 0] > cam.width - 1 - MARGIN_PX) \
                    or np.any(x[:, 1] > cam.height - 1 - MARGIN_PX):
                raise ConfigError(spec.path, field_name,
                                  f"does not see the whole patch with a {MARGIN_PX}-pixel margin "
                                  f"(corners at {np.round(x[:4]).tolist()} in a "
                                  f"{cam.width}x{cam.height} image): enlarge pixels, move it away "
                                  "or shrink patch_mm")
            shift = np.linalg.norm(cam.sensitivity(g["centre"]) @ case.displacement)
            if shift >= 1.0:
                raise ConfigError(spec.path, f"{where}.displacement_um",
                                  f"moves the patch by {shift:.2f} px in camera {cam.name!r}; "
                                  "validation needs a sub-pixel shift")
