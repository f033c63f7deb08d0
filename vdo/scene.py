"""The physical scene, the public face of its part: the configured cameras (`cameras_of`), the
Mitsuba scene built from the meshes (`build_scene`; each mesh handed to Mitsuba in memory,
`mitsuba_mesh`), and the pieces a script needs from `vdo.meshes`: the meshes read and checked
(`vdo.meshes.mesh`), the regions of interest (`vdo.meshes.regions`), their surface samples
(`vdo.meshes.samples`, whose docstring describes the sampling), and the camera bodies and tripods
as obstacles (`vdo.meshes.hardware`).
"""

from __future__ import annotations

import numpy as np

from vdo.config.experiment import camera_positions
from vdo.config.mounts import RailSpec
from vdo.config.rig import CameraSpec
from vdo.core.backend import mitsuba
from vdo.meshes.hardware import (TRIPOD_SECTIONS, camera_body, camera_body_local, camera_body_points,
                                 camera_body_spheres, lens_length, prism, tripod, tripod_cylinders,
                                 tripods)
from vdo.meshes.mesh import SceneMesh, cameras_inside, inside_mesh, load_meshes, split_at_boxes
from vdo.meshes.regions import (RegionFaces, RegionSelector, all_region_faces, region_faces,
                                region_selector)
from vdo.meshes.samples import (SurfaceRaster, SurfaceSamples, check_sample_count, ring_spacing,
                                sample_region, sample_regions, surface_raster)
from vdo.model.camera import Camera

# the face: what scripts and the other packages use of the scene
__all__ = ["cameras_of", "mitsuba_mesh", "build_scene",
           "SceneMesh", "load_meshes", "cameras_inside", "inside_mesh", "split_at_boxes",
           "RegionFaces", "RegionSelector", "all_region_faces", "region_faces", "region_selector",
           "SurfaceRaster", "SurfaceSamples", "check_sample_count", "ring_spacing", "sample_region",
           "sample_regions", "surface_raster",
           "TRIPOD_SECTIONS", "camera_body", "camera_body_local", "camera_body_points",
           "camera_body_spheres", "lens_length", "prism", "tripod", "tripod_cylinders", "tripods"]


def cameras_of(camera_specs: tuple[CameraSpec, ...], rails: tuple[RailSpec, ...]) -> list[Camera]:
    """The cameras (`vdo.model.camera.Camera`) that `camera_specs` (an experiment's [[camera]]
    tables, `exp.camera_specs`) configure, in their order: optical centres from `rails` (its
    [[rail]] tables, `exp.rails`) and positions (`camera_positions`), aimed at target_m or by pan
    and tilt (`CameraSpec.angles`), pixel pitch = sensor width / pixel columns."""
    out = []
    for spec, position in zip(camera_specs, camera_positions(camera_specs, rails)):
        pan, tilt = spec.angles(position)
        width, height = spec.pixels
        out.append(Camera(name=spec.name, width=width, height=height,
                          pixel_size=spec.sensor_width / width, focal_length=spec.focal_length,
                          position=position, pan=pan, tilt=tilt, roll=spec.roll,
                          principal_offset_px=spec.principal_offset_px, distortion=spec.distortion))
    return out


def mitsuba_mesh(mesh: SceneMesh, bsdf=None, uv: np.ndarray | None = None):
    """An in-memory `mi.Mesh` with the same vertices and faces, an optional BSDF (a loaded
    Mitsuba BSDF or a dict) and optional per-vertex texture coordinates uv (n, 2)."""
    mi = mitsuba()
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    out = mi.Mesh(mesh.name, len(mesh.vertices), len(mesh.faces), props=props,
                  has_vertex_texcoords=uv is not None)
    params = mi.traverse(out)
    params["vertex_positions"] = np.ascontiguousarray(mesh.vertices, dtype=np.float32).ravel()
    params["faces"] = np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel()
    if uv is not None:
        params["vertex_texcoords"] = np.ascontiguousarray(uv, dtype=np.float32).ravel()
    params.update()
    return out


def build_scene(meshes: list[SceneMesh]):
    """A Mitsuba scene holding the meshes as shapes, for ray casting."""
    mi = mitsuba()
    scene = {"type": "scene"}
    for i, mesh in enumerate(meshes):
        scene[f"shape_{i:03d}"] = mitsuba_mesh(mesh)
    return mi.load_dict(scene)
