"""The cameras' own hardware as obstacle meshes (role "camera"), in metres: a camera's body, a
lens barrel and a DSLR-sized box behind its optical centre (`camera_body`), and the tripod under a
camera on a zone mount with a [mount.tripod], its legs and centre column as closed prisms
(`tripods`). `vdo.geometry.obstacles` holds their closed-form stand-ins for sight lines.
"""

from __future__ import annotations

import functools

import numpy as np
import trimesh

from vdo.config.mounts import MountSpec, TripodSpec
from vdo.config.rig import CameraSpec
from vdo.meshes.mesh import SceneMesh
from vdo.model.camera import Camera


BODY_SIZE = (0.14, 0.10, 0.08)   # width, height, depth of a DSLR body, m
LENS_DIAMETER = 0.075            # m


def lens_length(focal_length: float) -> float:
    """Length of the lens barrel (m): 1.2 x the focal length, within [4, 15] cm."""
    return float(np.clip(focal_length * 1.2, 0.04, 0.15))


@functools.lru_cache(maxsize=64)
def _body_arrays(focal_length: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of `camera_body_local`, built once per focal length (read-only)."""
    length = lens_length(focal_length)
    lens = trimesh.creation.cylinder(radius=LENS_DIAMETER / 2, height=length, sections=24)
    lens.apply_translation([0, 0, -length / 2])
    body = trimesh.creation.box(extents=BODY_SIZE)
    body.apply_translation([0, 0, -length - BODY_SIZE[2] / 2])
    mesh = trimesh.util.concatenate([lens, body])
    vertices, faces = np.array(mesh.vertices), np.array(mesh.faces)
    vertices.setflags(write=False)
    faces.setflags(write=False)
    return vertices, faces


def camera_body_local(focal_length: float) -> trimesh.Trimesh:
    """The body in the camera's own OpenCV frame (z forward): a lens barrel over z in [-L, 0] and
    a DSLR-sized box behind it. Everything lies behind the optical centre (the lens front), so a
    ray that reaches the camera's own optical centre from its field of view never crosses it."""
    vertices, faces = _body_arrays(float(focal_length))
    return trimesh.Trimesh(vertices.copy(), faces.copy(), process=False)


def camera_body_points(focal_length: float) -> np.ndarray:
    """(B, 3) points on the body's outline in the camera frame, for clearance: the rims of the
    lens barrel and the corners and face centres of the box."""
    length = lens_length(focal_length)
    a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = np.c_[np.cos(a), np.sin(a), np.zeros(8)] * (LENS_DIAMETER / 2)
    w, h, d = BODY_SIZE
    corners = np.array([[x, y, z] for x in (-w / 2, w / 2) for y in (-h / 2, h / 2)
                        for z in (-length, -length - d)])
    faces = np.array([[0, 0, -length - d], [w / 2, 0, -length - d / 2], [-w / 2, 0, -length - d / 2],
                      [0, h / 2, -length - d / 2], [0, -h / 2, -length - d / 2]])
    return np.vstack([ring, ring - [0, 0, length], corners, faces])


def camera_body_spheres(focal_length: float) -> tuple[np.ndarray, np.ndarray]:
    """Spheres whose union covers the body (camera frame): centres (10, 3) and radii (10,) m;
    two along the lens barrel and one around each eighth of the box (overshoot ~1.5 cm), a smooth
    stand-in for the mesh in the shadow penalty."""
    length = lens_length(focal_length)
    w, h, d = BODY_SIZE
    quarter = length / 4
    lens = np.array([[0, 0, -quarter], [0, 0, -3 * quarter]])
    box = np.array([[x * w / 4, y * h / 4, -length - d / 2 + z * d / 4]
                    for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    radii = [float(np.hypot(LENS_DIAMETER / 2, quarter))] * 2 + [0.25 * float(np.sqrt(w * w + h * h + d * d))] * 8
    return np.vstack([lens, box]), np.array(radii)


def camera_body(camera: Camera) -> SceneMesh:
    """`camera_body_local` placed at the camera's pose, as an obstacle for the other cameras:
    X_world = R^T X_cam + C."""
    vertices, faces = _body_arrays(float(camera.focal_length))
    return SceneMesh(f"camera:{camera.name}", "camera", vertices @ camera.R + camera.position,
                     faces.copy())


TRIPOD_SECTIONS = 24     # sides of the prisms that stand for the legs' and column's cylinders


def tripod_cylinders(camera: Camera, spec: TripodSpec) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The tripod under `camera` as cylinders (top (3,), bottom (3,), radius), metres, world frame:
    the legs first, then the centre column; [] when the top casting is not above the floor.

    The body's centre is B = C - (L + d/2) z_c (`camera_body_local`: lens length L, body depth d,
    optical centre C, optical axis z_c); the top casting is T = B - (h_body/2 + head_m) e_z. Leg k
    (k = 0 .. legs-1) runs from T to the foot T_floor + spread_m (cos φ_k, sin φ_k, 0), with
    T_floor = T with z = floor_z_m and φ_k = pan + azimuth_deg + 2πk/legs; the column runs from T
    down by min(column_length_m, T_z - floor_z_m). Everything hangs below the top casting, inside
    the cone of the legs, so a camera that looks up, level, or down less steeply than its legs
    lean sees past its own tripod (tests/test_tripods.py)."""
    length = lens_length(camera.focal_length)
    body_centre = np.asarray(camera.position, float) - (length + BODY_SIZE[2] / 2) * camera.optical_axis
    top = body_centre - np.array([0.0, 0.0, BODY_SIZE[1] / 2 + spec.head])
    height = top[2] - spec.floor_z
    if height <= 0:
        return []
    below = np.array([top[0], top[1], spec.floor_z])
    angles = camera.pan + spec.azimuth + 2 * np.pi * np.arange(spec.legs) / spec.legs
    feet = below + spec.spread * np.c_[np.cos(angles), np.sin(angles), np.zeros(spec.legs)]
    legs = [(top, foot, spec.leg_diameter / 2) for foot in feet]
    column = top - np.array([0.0, 0.0, min(spec.column_length, height)])
    return legs + [(top, column, spec.column_diameter / 2)]


def _prism_faces(sections: int) -> np.ndarray:
    """Triangles of a closed prism whose vertices are `sections` points of the bottom ring, the
    same of the top ring, then the bottom and top centres; wound counter-clockwise seen from
    outside (outward normals, as the renderer's one-sided BSDFs need)."""
    k = np.arange(sections)
    nxt = (k + 1) % sections
    bottom, top = 2 * sections, 2 * sections + 1
    side = np.concatenate([np.c_[k, nxt, sections + nxt], np.c_[k, sections + nxt, sections + k]])
    caps = np.concatenate([np.c_[np.full(sections, bottom), nxt, k],
                           np.c_[np.full(sections, top), sections + k, sections + nxt]])
    return np.concatenate([side, caps])


PRISM_FACES = _prism_faces(TRIPOD_SECTIONS)


def prism(top: np.ndarray, bottom: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the closed TRIPOD_SECTIONS-sided prism inscribed in the cylinder of
    axis bottom -> top and `radius` (m): ring vertices bottom + r (cos α_j e_1 + sin α_j e_2)
    (+ the axis for the top ring), e_1, e_2 unit and perpendicular to the axis."""
    bottom, axis = np.asarray(bottom, float), np.asarray(top, float) - np.asarray(bottom, float)
    a = axis / np.linalg.norm(axis)
    e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    angle = 2 * np.pi * np.arange(TRIPOD_SECTIONS) / TRIPOD_SECTIONS
    ring = bottom + radius * (np.cos(angle)[:, None] * e1 + np.sin(angle)[:, None] * e2)
    return np.vstack([ring, ring + axis, bottom, bottom + axis]), PRISM_FACES


def tripod(camera: Camera, spec: TripodSpec) -> list[SceneMesh]:
    """`tripod_cylinders` as closed prisms of TRIPOD_SECTIONS sides inscribed in the cylinders
    (`prism`: radius short by at most r (1 - cos(π / TRIPOD_SECTIONS)), under 1 %), one obstacle
    mesh each (so that `vdo.physics.lighting.relight` bounds each part alone)."""
    return [SceneMesh(f"tripod:{camera.name}:{k}", "camera", *prism(top, bottom, radius))
            for k, (top, bottom, radius) in enumerate(tripod_cylinders(camera, spec))]


def tripods(cameras, *, camera_specs: tuple[CameraSpec, ...],
            mounts: tuple[MountSpec, ...]) -> list[SceneMesh]:
    """The `tripod` parts of every camera of `cameras` that `camera_specs` (an experiment's
    [[camera]] tables) list on a zone of `mounts` (its [[mount]] tables) with a [mount.tripod],
    built where the camera stands."""
    mount_of = {spec.name: spec.mount for spec in camera_specs}
    specs = {m.name: m.tripod for m in mounts if m.tripod is not None}
    return [part for c in cameras if mount_of.get(c.name) in specs
            for part in tripod(c, specs[mount_of[c.name]])]
