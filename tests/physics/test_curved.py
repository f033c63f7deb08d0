"""Curved regions: selection, development, sampling and the sigma model on a cylinder, checked
against an independent computation on the exact cylinder (not its facets): the DIC patch's
information integrated on a fine grid of the true surface (exact radial normals and tangents),
each point's per-area information from `vdo.objective` (the per-point model itself, which
tests/test_objective.py checks against finite differences and renders)."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest
import trimesh

from vdo import objective
from vdo.config import experiment as config
from vdo.core.errors import ConfigError
from vdo.physics import strain
from vdo.outputs.maps import developed_outline
from vdo.physics.lighting import photometry
from vdo.physics.predict import settings, sigmas
from conftest import mesh_tables, region_tables
from vdo.scene import all_region_faces, load_meshes, sample_regions
from vdo.state import layout_state, prepare

RADIUS, HEIGHT, SECTIONS = 0.1, 0.3, 256
PATCH_RTOL = 0.02     # sigma vs the exact-cylinder integral: facets (0.7 deg) and 4 mm cells
FINE = 41             # reference quadrature points per side of the patch
STL_ROUNDING = 1e-6  # m: STL stores float32 coordinates (7 digits of a 0.1 m part)
FACET_FRAME = 1e-4   # a sample's frame against the smooth surface's: its facet's plane, float32 corners
RING_DISTORTION = 0.10   # a ring cut open into a strip: p95 of its area distortion (8 % with a 2 cm lip)

CAMERA = """
[[camera]]
name = "{name}"
sensor_mm = [22.2, 14.8]
pixels = [1200, 800]
focal_mm = 35
position_m = {position}
target_m = [0, 0, 0]
"""


def write_cylinder(tmp_path, patch_mm=20, region=None):
    trimesh.creation.cylinder(radius=RADIUS, height=HEIGHT, sections=SECTIONS).export(tmp_path / "cyl.stl")
    region = region or textwrap.dedent("""
        near_axis_m = [[0, 0, 0], [0, 0, 1]]
        within_m = 0.11
        box_min_m = [-1, -1, -0.149]
        box_max_m = [1, 1, 0.149]""")
    cams = "".join(CAMERA.format(name=n, position=p) for n, p in
                   (("a", "[0.8, -0.3, 0.1]"), ("b", "[0.8, 0.3, 0.1]"), ("c", "[-0.8, 0.0, -0.1]")))
    text = textwrap.dedent(f"""
        [experiment]
        name = "cylinder"
        [evaluation]
        sample_spacing_mm = 4
        patch_mm = {patch_mm}
        incidence_limit_deg = 75
        [render]
        ambient_radiance = 20
        [analysis]
        method = "global"
        element_mm = 20
        [[mesh]]
        name = "cyl"
        file = "cyl.stl"
        role = "specimen"
        [[region]]
        name = "shell"
        mesh = "cyl"
        """) + textwrap.dedent(region) + cams
    path = tmp_path / "cyl.toml"
    path.write_text(text)
    return path


def exact_patch(theta0, z0, L):
    """Points, normals and frames (M, 3) of a FINE x FINE grid of the patch of side L centred at
    (theta0, z0) on the exact cylinder, and each point's share of the patch (1 / FINE^2)."""
    s = (np.arange(FINE) + 0.5) / FINE * L - L / 2
    S, T = np.meshgrid(s, s, indexing="ij")
    theta = theta0 + S.ravel() / RADIUS
    radial = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=1)
    points = RADIUS * radial + np.outer(z0 + T.ravel(), [0, 0, 1.0])
    t_u = np.stack([-np.sin(theta), np.cos(theta), np.zeros_like(theta)], axis=1)
    t_v = np.tile([0, 0, 1.0], (len(theta), 1))
    return points, radial, t_u, t_v


@pytest.fixture(scope="module")
def cylinder_state(tmp_path_factory):
    path = write_cylinder(tmp_path_factory.mktemp("cyl"))
    exp = config.load(path)
    return exp, layout_state(prepare(exp))


def test_cylinder_is_developed_exactly(cylinder_state):
    exp, state = cylinder_state
    rf = state.geometry.region_faces[0]
    dev = rf.development
    assert dev.kind == "cylinder" and dev.period > 0
    assert abs(dev.radius) == pytest.approx(RADIUS, rel=1e-6)
    assert abs(dev.axis[2]) == pytest.approx(1.0, abs=1e-9)
    s = state.samples
    # area: the facets' area inside the box, |z| <= 0.149 (chord sin(x)/x of the arc)
    chord = SECTIONS * 2 * RADIUS * math.sin(math.pi / SECTIONS)
    cell = s.region_cell[0]
    assert s.area.sum() == pytest.approx(chord * 0.298, rel=cell / 0.298)
    # frames: t_u along the circumference, t_v along the axis, t_u x t_v = the face normal
    radial = s.points[:, :2] / np.linalg.norm(s.points[:, :2], axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", np.cross(s.tangent_u, s.tangent_v), s.normals) - 1).max() < 1e-12
    assert np.abs(np.einsum("ij,ij->i", s.normals[:, :2], radial) - 1).max() < 1e-4
    assert np.abs(s.tangent_v[:, 2]).min() > 1 - 1e-9
    # u = R theta: the samples' u against the angle about the axis
    theta = np.arctan2(s.points[:, 1], s.points[:, 0])
    d = s.uv[:, 0] / (dev.flip * dev.radius) - np.sign(dev.axis[2]) * theta
    assert np.abs(np.angle(np.exp(1j * (d - d[0])))).max() < 1e-3     # one offset, the seam's


def test_sigma_and_strain_match_the_exact_cylinder(cylinder_state):
    exp, state = cylinder_state
    s, p = state.samples, state.prediction
    L = exp.evaluation.patch_size
    use = p.usable
    # samples whose patch lies on cells with the same usable cameras, away from the region's ends
    neighbours = state.geometry.overlap
    same = np.array([np.all(use[:, neighbours[n].indices] == use[:, [n]]) for n in range(len(s))])
    ok = p.measured & same & (np.abs(s.points[:, 2]) < 0.149 - L)
    chosen = np.flatnonzero(ok)[:: max(1, ok.sum() // 12)]
    assert len(chosen) >= 8
    cams = objective.CameraParams.from_cameras(list(state.cameras))
    st = settings(exp.evaluation)
    pho = photometry(state.illumination, exp.speckle, exp.sensor, state.geometry.speckle.mean,
                     state.geometry.speckle.std, len(state.cameras))
    # ambient light only: the contrast varies over the shell only where a camera body hides some
    # of a sample's sky (its sky fraction, `vdo.physics.lighting`); the reference takes sample n's
    Fs, _ = strain.analysis_factors(exp.analysis, np.ones(1))
    for n in chosen:
        contrast, noise = np.asarray(pho.contrast)[:, n:n + 1], np.asarray(pho.noise)[:, n:n + 1]
        theta0 = math.atan2(s.points[n, 1], s.points[n, 0])
        pts, nrm, tu, tv = exact_patch(theta0, s.points[n, 2], L)
        m = len(pts)
        ref_smp = objective.Samples(pts, nrm, tu, tv, np.full(m, (L / FINE) ** 2), np.zeros(m, int),
                                    np.ones(1), np.full(1, 2.0))
        views = objective.ViewData.from_dense(np.ones((len(state.cameras), m)), contrast, noise, ref_smp)
        per_camera = np.asarray(objective.camera_information(cams, ref_smp, views,
                                                             state.geometry.speckle.table, st))
        weights = np.asarray(objective.fields(cams, ref_smp, views, state.geometry.speckle.table, st).weights)
        assert np.all((weights >= 0.5) == use[:, [n]])       # the same cameras over the whole patch
        C = np.einsum("c,cmij->ij", use[:, n].astype(float), per_camera) / m
        _, ref_sigma, ref_xyz = sigmas(C[None], st.rank_rtol)
        assert p.sigma_max[n] == pytest.approx(ref_sigma[0], rel=PATCH_RTOL)
        assert p.sigma_xyz[n] == pytest.approx(ref_xyz[0], rel=PATCH_RTOL)
        # strain: var eps_uu = F t_u' Sigma_u t_u, Sigma_u = Omega C^-1, exact hoop direction
        sigma_u = L ** 2 * np.linalg.inv(C)
        t_u = tu[m // 2]
        ref_eps_uu = math.sqrt(Fs[0] * t_u @ sigma_u @ t_u)
        ref_eps_vv = math.sqrt(Fs[0] * tv[0] @ sigma_u @ tv[0])
        assert state.strain[0][n, 0] == pytest.approx(ref_eps_uu, rel=PATCH_RTOL)
        assert state.strain[0][n, 1] == pytest.approx(ref_eps_vv, rel=PATCH_RTOL)


def test_selection_that_selects_nothing_says_what_it_needs(tmp_path):
    path = write_cylinder(tmp_path, region="""
        near_point_m = [1, 0, 0]
        within_m = 0.2""")
    exp = config.load(path)
    with pytest.raises(ConfigError) as err:
        sample_regions(load_meshes(**mesh_tables(exp)), **region_tables(exp))
    e = err.value
    assert e.field == 'region "shell"' and "near_point_m" in e.message and "within_m" in e.message
    assert "faces lie 0.9" in e.message      # the nearest face centroid: about 1 m - R = 0.9 m away


def test_distance_band_selects_a_ring(tmp_path):
    """A band beyond_m..within_m around a point on the axis: the cylinder wall between two
    heights (sample level), area 2 pi R x (height of the band)."""
    path = write_cylinder(tmp_path, region="""
        near_point_m = [0, 0, 0]
        within_m = 0.12
        box_min_m = [-1, -1, -0.149]
        box_max_m = [1, 1, 0.149]""")
    exp = config.load(path)
    s = sample_regions(load_meshes(**mesh_tables(exp)), **region_tables(exp))
    half = math.sqrt(0.12 ** 2 - RADIUS ** 2)           # |z| where the sphere meets the wall
    assert np.abs(s.points[:, 2]).max() <= half
    assert s.area.sum() == pytest.approx(2 * math.pi * RADIUS * 2 * half, rel=2 * s.region_cell[0] / (2 * half))


def test_a_band_ends_a_face_where_it_ends(tmp_path):
    """A band beyond_m = 0.08 m around the axis of the capped cylinder's upper half: the cap's
    fan triangles are split where each radial edge is 0.08 m from the axis, so the region's
    faces are the wall's rectangles and the cap's ring between two SECTIONS-gons, area
    SECTIONS x chord x HEIGHT / 2 + (SECTIONS / 2) sin(2 pi / SECTIONS) (R^2 - 0.08^2), not the
    whole cap that a band's faces held before; the pieces inside 0.08 m are left out."""
    path = write_cylinder(tmp_path, region="""
        near_axis_m = [[0, 0, 0], [0, 0, 1]]
        beyond_m = 0.08
        within_m = 0.2
        box_min_m = [-1, -1, 0]
        box_max_m = [1, 1, 1]""")
    exp = config.load(path)
    meshes = load_meshes(**mesh_tables(exp))
    rf = all_region_faces(meshes, **region_tables(exp))[0]
    tm = meshes[0].trimesh
    wall = SECTIONS * 2 * RADIUS * math.sin(math.pi / SECTIONS) * HEIGHT / 2
    ring = SECTIONS / 2 * math.sin(2 * math.pi / SECTIONS) * (RADIUS ** 2 - 0.08 ** 2)
    assert tm.area_faces[rf.faces].sum() == pytest.approx(wall + ring, rel=1e-6)   # float32 STL
    inner = np.linalg.norm(tm.triangles[rf.faces][..., :2], axis=2).min()
    assert inner == pytest.approx(0.08, abs=STL_ROUNDING)       # cut on the radial edges
    # the wall with its lip is a ring: mapped cut open into a strip (as a ring: 775 % in area,
    # and half of its area without samples), so its samples hold its area
    assert rf.development.kind == "general" and rf.development.distortion.area_p95 < RING_DISTORTION
    samples = sample_regions(meshes, **region_tables(exp))
    assert samples.area.sum() == pytest.approx(wall + ring, rel=0.01)


def test_a_tube_is_cut_open_and_a_band_round_a_small_hole_is_not():
    """`lscm` of an open tube (no cylinder fit: a general patch with a ring's topology) opens it
    into a strip: near isometric (the ring mapped whole is an annulus, > 100 % in area); of a
    band round a dome's pole, mapped whole and cut open, the less distorted is kept."""
    from vdo.model.surface import _conformal, boundary_loops, cut_ring, lscm, merged

    tube = trimesh.creation.cylinder(radius=0.1, height=0.3, sections=48)
    wall = tube.triangles[np.abs(tube.face_normals[:, 2]) < 0.5]
    v, f = merged(wall)
    assert len(boundary_loops(f, len(v))) == 2
    cv, cf = cut_ring(v, f)
    assert len(boundary_loops(cf, len(cv))) == 1 and len(cv) > len(v)
    assert lscm(wall).distortion.area_p95 < RING_DISTORTION
    # a band 0.08 to 0.3 m of arc round the pole of a 1 m sphere (a dome round a nozzle): whole
    # 2.0 % in area, cut open 0.9 %: the smaller is kept
    arc, turn = np.meshgrid(np.linspace(0.08, 0.3, 19), np.linspace(0, 2 * np.pi, 65)[:-1], indexing="ij")
    points = np.stack([np.sin(arc.ravel()) * np.cos(turn.ravel()), np.sin(arc.ravel()) * np.sin(turn.ravel()),
                       np.cos(arc.ravel())], axis=1)
    k = np.arange(64)
    quads = [(i * 64 + k, i * 64 + (k + 1) % 64, (i + 1) * 64 + (k + 1) % 64, (i + 1) * 64 + k) for i in range(18)]
    faces = np.concatenate([np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]) for a, b, c, d in quads])
    band = points[faces]
    v, f = merged(band)
    whole, opened = _conformal(band, v, f), _conformal(band, *cut_ring(v, f))
    assert opened.distortion.area_p95 < 0.6 * whole.distortion.area_p95
    assert lscm(band).distortion.area_p95 == opened.distortion.area_p95




def test_the_least_distance_from_a_line_to_a_triangle_is_dense_samplings_least():
    """`line_triangle_distance` against the least over 1,891 points of each triangle: never
    above it, and below it by at most the grid's reach (1/60 of an edge); 0 for the triangles
    the line pierces; a triangle in a plane parallel to the line at its plane's distance."""
    from vdo.model.surface import distance_to_line, line_triangle_distance

    rng = np.random.default_rng(3)
    tri = rng.normal(size=(400, 3, 3))
    a, b = rng.normal(size=3), rng.normal(size=3)
    n = 60
    ij = np.array([(i / n, j / n) for i in range(n + 1) for j in range(n + 1 - i)])
    pts = (tri[:, None, 0] + ij[None, :, :1] * (tri[:, 1] - tri[:, 0])[:, None]
           + ij[None, :, 1:] * (tri[:, 2] - tri[:, 0])[:, None])
    dense = distance_to_line(pts.reshape(-1, 3), a, b).reshape(len(tri), -1).min(axis=1)
    least = line_triangle_distance(tri, a, b)
    reach = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1) / n
    assert np.all(least <= dense + 1e-12) and np.all(dense - least <= reach)
    assert 5 < np.sum(least == 0) < 400
    flat = np.array([[[0.3, -1, 0], [0.3, 1, -1], [0.3, 1, 1]]])     # x = 0.3, the line is the z axis
    assert line_triangle_distance(flat, np.zeros(3), np.array([0, 0, 1.0]))[0] == pytest.approx(0.3)


def test_cone_is_developed_exactly(tmp_path):
    """The lateral surface of a cone (base radius 0.1 m, height 0.2 m): half-angle atan(r / h),
    no distortion, the samples' area the closed form pi r l (l the slant height)."""
    r, h = 0.1, 0.2
    trimesh.creation.cone(radius=r, height=h, sections=256).export(tmp_path / "cyl.stl")
    path = write_cylinder(tmp_path, region="""
        box_min_m = [-1, -1, 0.001]""")
    trimesh.creation.cone(radius=r, height=h, sections=256).export(tmp_path / "cyl.stl")
    exp = config.load(path)
    meshes = load_meshes(**mesh_tables(exp))
    from vdo.scene import all_region_faces
    dev = all_region_faces(meshes, **region_tables(exp))[0].development
    assert dev.kind == "cone"
    assert dev.half_angle == pytest.approx(math.atan(r / h), abs=STL_ROUNDING / h)
    assert dev.centre == pytest.approx([0, 0, h], abs=STL_ROUNDING)
    assert max(dev.distortion.area_p95, dev.distortion.angle_p95) < 1e-3
    s = sample_regions(meshes, **region_tables(exp))
    # the strain frame: t_u around the axis (horizontal), t_v along the slant, as on a cylinder
    # (the developed sector's Cartesian u turns by its 2 pi sin(alpha) from one edge to the other)
    # (within FACET_FRAME: a facet's plane in float32 STL coordinates; around the axis, a point's
    # radial direction is up to half a facet's angle, pi / 256, off its facet's)
    assert np.abs(s.tangent_u[:, 2]).max() < FACET_FRAME
    radial = s.points[:, :2] / np.linalg.norm(s.points[:, :2], axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", s.tangent_u[:, :2], radial)).max() < math.sin(math.pi / 256) + FACET_FRAME
    assert np.abs(np.abs(s.tangent_v[:, 2]) - h / math.hypot(r, h)).max() < FACET_FRAME   # cos(alpha)
    slant = math.hypot(r, h)
    # sample cells tile the developed sector; its rim is resolved to a cell
    assert s.area.sum() == pytest.approx(math.pi * r * slant, rel=4 * s.region_cell[0] / slant)


def test_general_surface_is_mapped_with_its_distortion_warned(tmp_path, caplog):
    """A spherical cap (polar angle up to 60 deg) cannot be developed: the least-squares conformal
    map keeps angles (a conformal map) and distorts areas, by (1 + cos 60)^2 / 4 = 0.56 between
    the rim and the pole for any conformal map of the cap (the stereographic scale factor);
    the warning names the region and the distortion."""
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.1)
    sphere.export(tmp_path / "cyl.stl")
    path = write_cylinder(tmp_path, region="""
        normal = [0, 0, 1]
        normal_tolerance_deg = 60""")
    sphere.export(tmp_path / "cyl.stl")
    exp = config.load(path)
    meshes = load_meshes(**mesh_tables(exp))
    from vdo.model.surface import face_distortion
    from vdo.scene import all_region_faces
    with caplog.at_level("WARNING"):
        rf = all_region_faces(meshes, **region_tables(exp))[0]
    dev = rf.development
    assert dev.kind == "general"
    assert dev.distortion.angle_p95 < 0.05
    tri = meshes[0].trimesh.triangles[rf.faces]
    ratio, _ = face_distortion(tri, dev.faces_uv)
    z = tri.mean(axis=1)[:, 2] / 0.1
    rim, pole = np.median(ratio[z < 0.52]), np.median(ratio[z > 0.98])
    assert rim / pole == pytest.approx((1 + 0.5) ** 2 / 4, rel=0.1)
    assert dev.distortion.large
    assert any('region "shell"' in r.message and "distortion" in r.message for r in caplog.records)


def test_a_ring_is_textured_without_a_seam(tmp_path):
    """The render scene gives a curved region's faces texture coordinates of their own: around
    the closed cylinder no face spans more than its own width in u (a face across the seam would
    span the whole period with shared vertices), and u runs over the full turn 2 pi R."""
    import mitsuba as mi

    from vdo.model.speckle import pattern_for
    from vdo.render import build_render_scene
    from vdo.scene import all_region_faces

    exp = config.load(write_cylinder(tmp_path))
    meshes = load_meshes(**mesh_tables(exp))
    faces = all_region_faces(meshes, **region_tables(exp))
    scene = build_render_scene(exp, meshes, faces)
    (shape,) = [s for s in scene.shapes() if s.has_vertex_texcoords()]     # the speckled region
    params = mi.traverse(shape)
    uv = np.asarray(params["vertex_texcoords"]).reshape(-1, 3, 2)
    tile = exp.speckle.texel * np.array(pattern_for(exp.speckle).shape[::-1])
    u = uv[..., 0] * tile[0]
    width = 2 * math.pi * RADIUS / SECTIONS
    assert np.ptp(u, axis=1).max() < 1.01 * width
    # the full turn, plus at most the faces across the seam, which keep their corners together
    assert 2 * math.pi * RADIUS * (1 - 1e-3) <= np.ptp(u) <= 2 * math.pi * RADIUS + 1.01 * width


@pytest.mark.parametrize("spacing_mm, patch_mm", [(4, 20), (8, 12)])   # kd-tree cells; surface raster
def test_a_closed_cone_has_no_edge_at_its_seam(tmp_path, spacing_mm, patch_mm):
    """A full cone ring (the lateral surface of a cone, 0.03-0.17 m below its apex, half-angle
    atan(1/2): developed into a sector of 2 pi sin alpha = 161 deg) is cut open at a seam to be
    developed, but the surface has no edge there: away from the ring's two rims the whole DIC
    patch lies on the region, so the fraction of the patch on the region's cells (the overlap's
    row sum) is 1 at the seam as everywhere else (within what the cells, square in the developed
    plane and turned by the seam's angle, resolve). Without the cells continued across the seam
    the samples beside it lost up to half their patch."""
    r, h = 0.1, 0.2
    path = write_cylinder(tmp_path, patch_mm=patch_mm, region="""
        box_min_m = [-1, -1, 0.03]
        box_max_m = [1, 1, 0.17]""")
    text = path.read_text().replace("sample_spacing_mm = 4", f"sample_spacing_mm = {spacing_mm}")
    path.write_text(text)
    trimesh.creation.cone(radius=r, height=h, sections=256).export(tmp_path / "cyl.stl")
    geometry = prepare(config.load(path))
    dev = geometry.region_faces[0].development
    assert dev.kind == "cone" and dev.turn == pytest.approx(2 * math.pi * math.sin(math.atan(r / h)), rel=1e-4)
    pts, L = geometry.samples.points, patch_mm * 1e-3
    z = pts[:, 2]
    margin = L + spacing_mm * 1e-3      # the patch and the cells it touches clear of both rims
    inner = (z > 0.03 + margin) & (z < 0.17 - margin)
    phi = np.mod(np.arctan2(pts @ dev.e2, pts @ dev.e1), 2 * math.pi)
    slant_r = (h - z) * math.tan(dev.half_angle)               # radius of each sample's circle
    seam = inner & (np.minimum(phi, 2 * math.pi - phi) * slant_r < L)
    assert seam.sum() > 10
    share = np.asarray(geometry.overlap.sum(axis=1)).ravel()
    assert share[inner & ~seam] == pytest.approx(1.0, abs=0.02)
    assert share[seam] == pytest.approx(1.0, abs=0.1)
    # the developed map draws the ring's outline at its two rims only, and the seam as two rays
    mesh = geometry.meshes[0]
    outline = developed_outline(geometry.samples, 0, geometry.region_faces[0], mesh.vertices, mesh.faces)
    s_cells = np.linalg.norm(geometry.samples.uv, axis=1)
    s_edges = np.linalg.norm(outline.outline.mean(axis=1), axis=1)
    h = geometry.samples.region_cell[0]
    assert np.all((s_edges < s_cells.min() + 1.5 * h) | (s_edges > s_cells.max() - 1.5 * h))
    rays = outline.seam[:, 1] - outline.seam[:, 0]
    between = math.acos(rays[0] @ rays[1] / np.linalg.norm(rays[0]) / np.linalg.norm(rays[1]))
    assert between == pytest.approx(dev.turn, abs=1e-9)


def test_a_general_map_runs_along_its_surface(tmp_path):
    """The least-squares conformal map of a pipe bend's intrados (a torus band: bend radius 0.45 m,
    pipe radius 0.1 m, 90 degrees of bend, 120 degrees about the pipe facing the bend's centre):
    u runs along the bend, the band's long direction. Checked against the torus's own
    parametrisation: at every face, the surface direction of +u (the map's Jacobian) against the
    exact bend direction dX/dtheta at the face's centre; the map's pins alone set u along the
    band's diagonal (17-34 degrees off)."""
    from vdo.model.surface import lscm

    bend, pipe = 0.45, 0.1
    theta = np.linspace(0, np.pi / 2, 61)
    phi = np.linspace(np.radians(120), np.radians(240), 25)
    T, P = np.meshgrid(theta, phi, indexing="ij")

    def point(t, p):
        rho = bend + pipe * np.cos(p)
        return np.stack([rho * np.cos(t), rho * np.sin(t), pipe * np.sin(p)], axis=-1)

    X = point(T, P)
    quads = [(X[a, b], X[a + 1, b], X[a + 1, b + 1], X[a, b + 1])
             for a in range(len(theta) - 1) for b in range(len(phi) - 1)]
    tri = np.array([t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))])
    dev = lscm(tri)
    uv = dev.faces_uv
    duv = np.stack([uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], axis=2)          # (T, 2, 2)
    dX = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=2)       # (T, 3, 2)
    t_u = (dX @ np.linalg.inv(duv))[:, :, 0]
    t_u /= np.linalg.norm(t_u, axis=1, keepdims=True)
    c = tri.mean(axis=1)
    along = np.stack([-c[:, 1], c[:, 0], np.zeros(len(c))], axis=1)            # dX/dtheta
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", t_u, along)), 0, 1)))
    assert np.median(angle) < 3.0 and np.percentile(angle, 95) < 8.0, np.percentile(angle, [50, 95])
