"""Global multi-view correlation (vdo/dic/correlate.py) against images it did not make.

The images here are made by an independent little renderer (not Mitsuba, not the correlator's code):
each pixel of a pinhole camera is supersampled 4 x 4, each sub-pixel ray is intersected with the
(displaced) planar patch, the speckle tile is read bilinearly at 4 texels per pixel footprint, the
16 values are averaged (box pixel) and mapped to gray levels b + c f. A rigid or bilinear displacement
of the surface is rendered exactly (the ray meets the displaced surface). Scene: a 24 x 18 mm patch in
the plane z = 0, cameras 0.3 m away looking at its centre, 200 x 150 pixels of 0.1 mm on the surface,
speckle dots 0.45 mm = 4.5 px.
"""

from __future__ import annotations


import numpy as np
import pytest

from vdo.model.camera import Camera
from vdo.model.pose import look_at_angles
from vdo.dic.correlate import (AverageReference, Gradient, ImageReference, PixelIntegration, Q4, Solver,
                               TextureReference, correlate)
from vdo.dic.images import SplineImage
from vdo.dic.patch import Patch, integration_points
from vdo.model.speckle import generate_pattern

TEXEL = 25e-6                    # 4 texels per pixel footprint
DOT = 0.45e-3                    # 4.5 px in the images
DIST = 0.3
PATCH = Patch(origin=np.array([-12e-3, -9e-3, 0.0]), t_u=np.array([1.0, 0, 0]),
              t_v=np.array([0, 1.0, 0]), size=np.array([24e-3, 18e-3]))
# Imposed translation: (12, -7, 9) µm scaled by 2.5, i.e. ~0.3 px in-plane.
U_TRUE = 2.5 * np.array([12e-6, -7e-6, 9e-6])


def make_camera(name, polar_deg, azimuth_deg, distance=DIST):
    """Camera at `polar_deg` from the patch normal (z), azimuth from +x, aimed at the origin."""
    th, ph = np.radians(polar_deg), np.radians(azimuth_deg)
    pos = distance * np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    if polar_deg == 0:
        pan, tilt = 0.0, -np.pi / 2
    else:
        pan, tilt = look_at_angles(pos, np.zeros(3))
    return Camera(name=name, width=200, height=150, pixel_size=5e-6, focal_length=15e-3,
                  position=pos, pan=pan, tilt=tilt)


STEREO = [make_camera("left", 12.5, 180.0), make_camera("right", 12.5, 0.0)]
TRIPLE = STEREO + [make_camera("front", 20.0, 90.0)]


@pytest.fixture(scope="module")
def pattern():
    return generate_pattern(1024, TEXEL, DOT, seed=3).astype(np.float64)


@pytest.fixture(scope="module")
def images(pattern):
    """Noise-free reference and translated images of the three cameras (STEREO = the first two)."""
    return ([render(cam, pattern) for cam in TRIPLE],
            [render(cam, pattern, U_TRUE) for cam in TRIPLE])


# --------------------------------------------------------------------------------------------
# Independent renderer
# --------------------------------------------------------------------------------------------
def bilinear_wrap(pattern, texel, xi):
    """Pattern value at face coordinates ξ (..., 2), texel (i, j) centred at ((j+½)h, (i+½)h)."""
    n_r, n_c = pattern.shape
    cx = xi[..., 0] / texel - 0.5
    cy = xi[..., 1] / texel - 0.5
    j0, i0 = np.floor(cx), np.floor(cy)
    a, b = cx - j0, cy - i0
    j0 = j0.astype(np.int64) % n_c
    i0 = i0.astype(np.int64) % n_r
    j1, i1 = (j0 + 1) % n_c, (i0 + 1) % n_r
    return ((1 - a) * (1 - b) * pattern[i0, j0] + a * (1 - b) * pattern[i0, j1]
            + (1 - a) * b * pattern[i1, j0] + a * b * pattern[i1, j1])


def render(cam, pattern, disp=None, b=0.1, c=0.8, ss=4, patch=PATCH):
    """Box-pixel image of the patch displaced by `disp` (None, a (3,) vector or a callable ξ -> (…, 3)),
    gray = b + c f. The ray of each sub-pixel meets the displaced surface X(ξ) + U(ξ): for a constant U
    in one step, for a field by fixed-point iteration ξ <- hit of the plane shifted by U(ξ)."""
    if disp is None:
        disp = np.zeros(3)
    field = disp if callable(disp) else (lambda xi, d=np.asarray(disp, float): np.broadcast_to(d, xi.shape[:-1] + (3,)))
    off = (np.arange(ss) + 0.5) / ss - 0.5
    u = np.arange(cam.width)[None, :, None, None] + off[None, None, None, :]
    v = np.arange(cam.height)[:, None, None, None] + off[None, None, :, None]
    u, v = np.broadcast_arrays(u, v)
    f, (cx, cy) = cam.focal_px, cam.principal_point
    d_cam = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], -1)
    d = d_cam @ cam.R                              # R^T d_cam, world directions
    C = np.asarray(cam.position, float)
    n = patch.normal
    xi = np.zeros(u.shape + (2,))
    for _ in range(1 if not callable(disp) else 4):
        U = field(xi)
        lam = ((patch.origin + U - C) @ n) / (d @ n)
        rel = C + lam[..., None] * d - U - patch.origin
        xi = np.stack([rel @ patch.t_u, rel @ patch.t_v], -1)
    tex = bilinear_wrap(pattern, TEXEL, xi)
    return b + c * tex.mean(axis=(2, 3))


def px_error(cams, U_est, U_true, X=None):
    """|s_i (U_est - U_true)| in pixels for each camera, at X (default the patch centre)."""
    X = PATCH.points(PATCH.size / 2) if X is None else X
    return np.array([np.linalg.norm(cam.sensitivity(X) @ (U_est - U_true)) for cam in cams])


# --------------------------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------------------------
def test_spline_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    img = rng.random((40, 50))
    s = SplineImage(img)
    x = np.stack([rng.uniform(-0.5, 49.5, 300), rng.uniform(-0.5, 39.5, 300)], 1)
    f, g = s.value_and_gradient(x)
    assert np.allclose(f, s(x), atol=1e-12)
    assert np.allclose(s(np.array([[3.0, 7.0]])), img[7, 3])      # (u, v) = (column, row)
    e = 1e-5
    fd = np.stack([(s(x + [e, 0]) - s(x - [e, 0])) / (2 * e),
                   (s(x + [0, e]) - s(x - [0, e])) / (2 * e)], -1)
    assert np.allclose(g, fd, atol=1e-7)


def test_integration_points_are_seen_by_every_camera():
    xi, area = integration_points(PATCH, TRIPLE, margin_px=3)
    X = PATCH.points(xi)
    for cam in TRIPLE:
        x = cam.project(X)
        assert np.all((x >= 3) & (x <= np.array([cam.width, cam.height]) - 4))
    # about one point per pixel of the best camera
    best = max(np.sqrt(abs(np.linalg.det(cam.sensitivity(X) @ PATCH.tangents))).max() for cam in TRIPLE)
    assert 0.8 < best * np.sqrt(area) < 1.01


# --------------------------------------------------------------------------------------------
# Noise-free recovery
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cams", [STEREO, TRIPLE], ids=["2 cameras", "3 cameras"])
@pytest.mark.parametrize("reference", ["images", "texture", "average"])
def test_translation_noise_free(pattern, images, cams, reference):
    ref, dfm = (ims[:len(cams)] for ims in images)
    options = {"images": ImageReference(ref), "texture": TextureReference(pattern, TEXEL),
               "average": AverageReference(ref)}
    res = correlate(cams, dfm, PATCH, options[reference], solver=Solver(tol=1e-9))
    assert res.converged and not res.rank_deficient
    err = px_error(cams, res.U, U_TRUE)
    # "average" (paper eq. 3) needs one ξ grid for all cameras, so every reference image is read by
    # spline interpolation off its pixel grid: the interpolation bias of this sharp (box-pixel only)
    # speckle at a 0.3 px shift is ~0.015 px. The per-camera references integrate on each camera's
    # own pixel centres and stay < 0.01 px (measured ~0.003 px).
    assert np.all(err < (0.03 if reference == "average" else 0.01)), err
    if reference == "images":
        # b, c near (0, 1): the spline interpolant attenuates the sharp speckle off the pixel grid
        assert np.allclose(res.b, 0.0, atol=0.02) and np.allclose(res.c, 1.0, atol=0.03)


def test_brightness_contrast_per_camera(pattern, images):
    bc = [(0.05, 1.3), (0.2, 0.6), (-0.1, 0.9)]
    ref = images[0]
    dfm = [render(cam, pattern, U_TRUE, b=0.1 * ci + bi, c=0.8 * ci)
           for cam, (bi, ci) in zip(TRIPLE, bc)]
    res = correlate(TRIPLE, dfm, PATCH, ImageReference(ref), solver=Solver(tol=1e-9))
    assert np.all(px_error(TRIPLE, res.U, U_TRUE) < 0.01)
    # c is ~1.6% low: the spline interpolant off the pixel grid attenuates the sharp speckle
    assert np.allclose(res.c, [ci for _, ci in bc], rtol=0.03)
    assert np.allclose(res.b, [bi for bi, _ in bc], atol=0.02)
    # and against the true texture (gray = b + c f with f in [0, 1])
    res = correlate(TRIPLE, dfm, PATCH, TextureReference(pattern, TEXEL), solver=Solver(tol=1e-9))
    assert np.all(px_error(TRIPLE, res.U, U_TRUE) < 0.01)
    assert np.allclose(res.c, [0.8 * ci for _, ci in bc], rtol=0.03)


@pytest.mark.parametrize("mesh, tol_px", [((1, 1), 0.01), ((2, 2), 0.02)])
def test_q4_bilinear_field(pattern, mesh, tol_px):
    """A bilinear 3D field (nodal displacements differing by up to ~0.15 px) on a 16 x 12 mm patch
    inside every view. A Q4 mesh of any size represents it exactly. The sharp box-pixel speckle
    leaves a spline-interpolation misfit of ~0.04 gray rms that acts on the estimate like image
    noise: ~0.003 px on a translation, ~0.009 px at the corner nodes of one element, ~0.012 px at
    the nodes of a 2 x 2 mesh (each node supported by fewer pixels), hence 0.02 px there."""
    patch = Patch(origin=np.array([-8e-3, -6e-3, 0.0]), t_u=np.array([1.0, 0, 0]),
                  t_v=np.array([0, 1.0, 0]), size=np.array([16e-3, 12e-3]))
    L = patch.size
    c00 = U_TRUE
    c10 = U_TRUE + np.array([10e-6, 4e-6, -8e-6])
    c01 = U_TRUE + np.array([-5e-6, 12e-6, 6e-6])
    c11 = U_TRUE + np.array([6e-6, -6e-6, 10e-6])

    def field(xi):
        a, b = xi[..., 0:1] / L[0], xi[..., 1:2] / L[1]
        return (1 - a) * (1 - b) * c00 + a * (1 - b) * c10 + (1 - a) * b * c01 + a * b * c11

    ref = [render(cam, pattern, patch=patch) for cam in TRIPLE]
    dfm = [render(cam, pattern, field, patch=patch) for cam in TRIPLE]
    nx, ny = mesh
    res = correlate(TRIPLE, dfm, patch, ImageReference(ref), model=Q4(*mesh), solver=Solver(tol=1e-9))
    assert res.converged and not res.rank_deficient
    assert res.U.shape == ((nx + 1) * (ny + 1), 3)
    nodes = np.stack(np.meshgrid(np.linspace(0, L[0], nx + 1), np.linspace(0, L[1], ny + 1),
                                 indexing="xy"), -1).reshape(-1, 2)
    U_nodes = field(nodes)
    err = np.array([[np.linalg.norm(cam.sensitivity(X) @ (ue - ut)) for cam in TRIPLE]
                    for X, ue, ut in zip(patch.points(nodes), res.U, U_nodes)])
    assert err.max() < tol_px, err
    # the nodal field varies by much more than the error: the field itself is resolved
    corners = [c00, c10, c01, c11]
    spread = max(np.linalg.norm(cam.sensitivity(patch.points(L / 2)) @ (p - q))
                 for cam in TRIPLE for p in corners for q in corners)
    assert spread > 0.15


# --------------------------------------------------------------------------------------------
# One camera: depth along the viewing direction is (nearly) unmeasured
# --------------------------------------------------------------------------------------------
def test_one_camera_is_ill_conditioned_along_the_viewing_direction(pattern):
    cam = make_camera("down", 0.0, 0.0)
    ref = [render(cam, pattern)]
    dfm = [render(cam, pattern, U_TRUE)]
    view = PATCH.points(PATCH.size / 2) - cam.position
    view /= np.linalg.norm(view)

    # Full solve: not singular (perspective), but the weak direction is the viewing ray and its
    # uncertainty is tens of times the in-plane one.
    res = correlate([cam], dfm, PATCH, ImageReference(ref), solver=Solver(tol=1e-9))
    assert res.uncertainty_ratio > 20
    assert abs(res.weakest_direction @ view) > 0.99
    # Dropping it (pseudo-inverse) is flagged, and the components across the viewing direction are
    # still recovered to < 0.01 px while the one along it is not.
    res = correlate([cam], dfm, PATCH, ImageReference(ref), solver=Solver(tol=1e-9, rcond=1e-2))
    assert res.rank_deficient and res.rank == 4
    assert abs(res.null_directions[0][:3] @ view) / np.linalg.norm(res.null_directions[0][:3]) > 0.99
    e = res.U - U_TRUE
    across = e - (e @ view) * view
    assert np.linalg.norm(cam.sensitivity(PATCH.points(PATCH.size / 2)) @ across) < 0.01
    assert np.linalg.norm(across) * cam.focal_px / DIST < 0.01
    assert abs(res.U @ view) < 0.1 * abs(U_TRUE @ view)        # out-of-plane not measured


# --------------------------------------------------------------------------------------------
# Noise: measured scatter against the propagated covariance 2 σ² H⁻¹
# --------------------------------------------------------------------------------------------
def test_noise_scatter_matches_propagated_covariance(images):
    sigma = 0.02                              # gray levels; the images span about 0.1 .. 0.9
    seeds = 40
    cams = TRIPLE
    ref0, dfm0 = images
    clean = correlate(cams, dfm0, PATCH, ImageReference(ref0))
    predicted = 2 * sigma ** 2 * np.linalg.inv(clean.hessian_U)
    # the helper accounts for c ≈ 0.98 (noise of the reference enters as c² σ²): within a few %
    assert np.allclose(np.diag(clean.covariance(sigma)), np.diag(predicted), rtol=0.05, atol=0)
    est = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        ref = [im + rng.normal(0, sigma, im.shape) for im in ref0]
        dfm = [im + rng.normal(0, sigma, im.shape) for im in dfm0]
        res = correlate(cams, dfm, PATCH, ImageReference(ref), integration=PixelIntegration(clean.xi))
        assert res.converged
        est.append(res.U)
    est = np.array(est)
    # Per axis, the std of a 40-sample std is ~11%, so 20% is ~1.8 sampling sigmas: this block of
    # seeds gives (1.05, 0.87, 0.96); seeds 40-79 and 80-119 gave (1.10, 1.17, 1.04) and
    # (0.75, 0.90, 1.04); pooled over the 120, (0.98, 0.99, 1.01).
    ratio = est.std(axis=0, ddof=1) / np.sqrt(np.diag(predicted))
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    # The whole covariance (correlations included): mean Mahalanobis² per axis ~ 1 (120 dof).
    dev = est - est.mean(0)
    m2 = np.einsum("si,ij,sj->s", dev, np.linalg.inv(predicted), dev).sum() / (3 * (seeds - 1))
    assert abs(m2 - 1) < 0.25, m2
    # the mean is the noise-free answer (no noise-induced bias beyond the scatter of the mean)
    assert np.all(np.abs(est.mean(0) - clean.U) < 4 * np.sqrt(np.diag(predicted) / seeds))


def test_option_objects_reject_wrong_combinations(images):
    ref, dfm = images
    with pytest.raises(ValueError, match="GridIntegration"):
        correlate(TRIPLE, dfm, PATCH, AverageReference(ref), integration=PixelIntegration())
    with pytest.raises(ValueError, match="not available"):
        correlate(TRIPLE, dfm, PATCH, AverageReference(ref), gradient=Gradient.REFERENCE)
    with pytest.raises(ValueError, match="one reference image per camera"):
        correlate(TRIPLE, dfm, PATCH, ImageReference(ref[:2]))
    with pytest.raises(ValueError, match="ImageReference"):
        correlate(TRIPLE, dfm, PATCH, ref)
    with pytest.raises(ValueError, match="nx, ny >= 1"):
        Q4(0, 2)
