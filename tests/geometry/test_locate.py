"""Where a surface sample lies on a mesh (`vdo.geometry.keyframes._locate`), checked against a
brute-force search over every triangle and against a linear field that barycentric
interpolation carries exactly (a closed form)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from vdo.core.tolerances import BARYCENTRIC_SLACK
from vdo.geometry.keyframes import _barycentric_displacement, _locate

FIELD = np.array([[0.01, -0.02, 0.003], [0.004, 0.02, -0.01], [0.0, 0.005, 0.03]])   # u = F X + c
SHIFT = np.array([1e-4, -2e-4, 3e-4])


def brute_force(points, triangles):
    """(N, T) True where triangle t holds point n (its projection within the barycentric slack)."""
    a, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    g = np.stack([[(e1 * e1).sum(-1), (e1 * e2).sum(-1)], [(e1 * e2).sum(-1), (e2 * e2).sum(-1)]])
    rel = points[:, None] - a[None]
    r = np.stack([(rel * e1).sum(-1), (rel * e2).sum(-1)], -1)                  # (N, T, 2)
    lam = np.linalg.solve(np.moveaxis(g, (0, 1), (-2, -1))[None], r[..., None])[..., 0]
    return (lam >= -BARYCENTRIC_SLACK).all(-1) & (lam.sum(-1) <= 1 + BARYCENTRIC_SLACK)


def fan_plate():
    """The face of a plate with a hole meshed as a fan of long thin triangles (the rings 1 mm and
    300 mm apart, 400 sections: triangles 300 mm long and ~2 mm wide, whose centroids lie far
    from most of their points)."""
    ring = trimesh.creation.annulus(r_min=0.001, r_max=0.3, height=0.01, sections=400)
    return trimesh.Trimesh(ring.vertices, ring.faces[ring.face_normals[:, 2] > 0.9])


@pytest.mark.parametrize("mesh_of", [fan_plate, lambda: trimesh.creation.icosphere(subdivisions=3, radius=0.2)],
                         ids=["thin-fan", "sphere"])
def test_every_sample_finds_the_triangle_it_lies_on(mesh_of):
    """Points sampled on the faces: each is placed on a triangle that holds it (brute force), and a
    linear field comes out exactly."""
    mesh = mesh_of()
    points, _ = trimesh.sample.sample_surface(mesh, 3000, seed=4)
    triangles = mesh.vertices[mesh.faces]
    tri, lam = _locate(points, triangles)
    holds = brute_force(points, triangles)
    assert (tri >= 0).all()
    assert holds[np.arange(len(points)), tri].all()
    u = _barycentric_displacement(points, triangles, (mesh.vertices @ FIELD.T + SHIFT)[mesh.faces])
    np.testing.assert_allclose(u, points @ FIELD.T + SHIFT, rtol=0, atol=1e-14)


def test_samples_on_the_true_cylinder_find_its_facets():
    """Points on the true cylinder lie off its 24 facets' planes (by up to the sagitta, 1.7 mm
    at 0.1 m radius): each is still placed on the facet whose projection holds it, and a linear
    field comes out within |F| times its distance to that plane."""
    radius, sections = 0.1, 24
    mesh = trimesh.creation.cylinder(radius=radius, height=0.4, sections=sections)
    rng = np.random.default_rng(7)
    angle, z = rng.uniform(0, 2 * np.pi, 2000), rng.uniform(-0.19, 0.19, 2000)
    points = np.stack([radius * np.cos(angle), radius * np.sin(angle), z], axis=1)
    triangles = mesh.vertices[mesh.faces]
    side = np.abs(mesh.face_normals[:, 2]) < 1e-9
    tri, _ = _locate(points, triangles[side])
    holds = brute_force(points, triangles[side])
    assert (tri >= 0).all() and holds[np.arange(len(points)), tri].all()
    normals = mesh.face_normals[side][tri]
    off = np.abs(((points - triangles[side][tri, 0]) * normals).sum(-1))
    assert off.max() > 1e-3                         # the case is the one described
    u = _barycentric_displacement(points, triangles[side], (mesh.vertices @ FIELD.T)[mesh.faces][side])
    assert (np.linalg.norm(u - points @ FIELD.T, axis=1) <= np.linalg.norm(FIELD, 2) * off + 1e-15).all()
