"""vdo.objective checked against things it does not compute itself: finite differences of
`camera.project` and of the score, an image-based Cramer-Rao bound (Pan et al. 2008) on a rendered
speckle image, and closed forms for one tilted camera and a symmetric stereo pair."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vdo import objective as ob
from vdo.information import blocks
from vdo.model.camera import intrinsic_matrix, project, rotation, sensitivity
from vdo.model.pose import look_at_angles
from vdo.model.speckle import generate_pattern, gradient_energy_table, normalise

GAUSS = ob.GaussianFieldEnergy(0.6e-3)  # smooth closed-form G


# --------------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------------
def make_samples(points, normals, tangent_u, area=1e-5, region=None, importance=(1.0,),
                 min_cameras=(2.0,)):
    points, normals, tangent_u = (np.asarray(a, dtype=float) for a in (points, normals, tangent_u))
    n = points.shape[0]
    tangent_v = np.cross(normals, tangent_u)
    region = np.zeros(n, dtype=int) if region is None else np.asarray(region)
    return ob.Samples(jnp.asarray(points), jnp.asarray(normals), jnp.asarray(tangent_u),
                      jnp.asarray(tangent_v), jnp.full(n, area), jnp.asarray(region),
                      jnp.asarray(importance, dtype=float), jnp.asarray(min_cameras, dtype=float))


def make_cameras(positions, targets, focal_px=3000.0, width=2000, height=1400, roll=None,
                 angles=None):
    positions = np.asarray(positions, dtype=float)
    c = positions.shape[0]
    if angles is None:
        angles = [look_at_angles(p, t) for p, t in zip(positions, targets)]
    pan, tilt = (np.array(a, dtype=float) for a in zip(*angles))
    full = lambda x: jnp.full(c, float(x))
    return ob.CameraParams(jnp.asarray(positions), jnp.asarray(pan), jnp.asarray(tilt),
                           jnp.zeros(c) if roll is None else jnp.asarray(roll, dtype=float),
                           jnp.asarray(np.broadcast_to(focal_px, (c,)).astype(float)),
                           full((width - 1) / 2), full((height - 1) / 2), full(width), full(height))


def views(smp, c, contrast=800.0, noise=5.0):
    return ob.ViewData.from_dense(np.ones((c, smp.points.shape[0])), contrast, noise, smp)


def two_plane_scene(n=300, seed=0, distortion=None):
    """A floor (z = 0, region 0, >= 2 cameras) and a 30-degree ramp (region 1, >= 3 cameras), seen by
    3 cameras; camera 0 is fronto-parallel over the floor with sample 0 on its principal ray.
    `distortion` (3, 5): the cameras' lens distortion (None: pinholes)."""
    rng = np.random.default_rng(seed)
    n1 = n // 2
    floor = np.c_[rng.uniform(-0.15, 0.15, (n1, 2)), np.zeros(n1)]
    floor[0] = 0.0
    t = math.radians(30.0)
    nr = np.array([-math.sin(t), 0.0, math.cos(t)])
    tr = np.array([math.cos(t), 0.0, math.sin(t)])
    ab = rng.uniform(-0.1, 0.1, (n - n1, 2))
    ramp = np.array([0.3, 0.0, 0.05]) + ab[:, :1] * tr + ab[:, 1:] * np.array([0.0, 1.0, 0.0])
    points = np.r_[floor, ramp]
    normals = np.r_[np.tile([0.0, 0.0, 1.0], (n1, 1)), np.tile(nr, (n - n1, 1))]
    tu = np.r_[np.tile([1.0, 0.0, 0.0], (n1, 1)), np.tile(tr, (n - n1, 1))]
    region = np.r_[np.zeros(n1, int), np.ones(n - n1, int)]
    smp = make_samples(points, normals, tu, 1e-5, region, (1.0, 3.0), (2.0, 3.0))
    pos = [[0.0, 0.0, 1.2], [-0.6, 0.5, 0.9], [0.9, -0.6, 1.0]]
    angles = [(0.0, -math.pi / 2), look_at_angles(pos[1], [0.1, 0, 0]),
              look_at_angles(pos[2], [0.15, 0, 0])]
    cam = make_cameras(pos, None, focal_px=np.array([2600.0, 2400.0, 2800.0]), width=1600,
                       height=1200, roll=[0.0, 0.1, -0.05], angles=angles)
    if distortion is not None:
        cam = eqx_replace(cam, "distortion", np.asarray(distortion, dtype=float))
    return cam, smp, views(smp, 3)


# Brown-Conrady coefficients (k1, k2, p1, p2, k3) of the three cameras: barrel, pincushion with
# tangential terms, mixed; 2-9 px at the image corners of the two-plane scene
LENSES = np.array([[-0.25, 0.08, 0.0, 0.0, -0.01],
                   [0.12, -0.03, 0.0015, -0.001, 0.02],
                   [-0.08, 0.0, -0.002, 0.0025, 0.0]])


# --------------------------------------------------------------------------------------------
# Sensitivity and footprint against finite differences of camera.project
# --------------------------------------------------------------------------------------------
def test_sensitivity_and_footprint_match_finite_differences_of_project():
    cam, smp, _ = two_plane_scene(60)
    geo = ob.geometry(cam, smp)
    K = intrinsic_matrix(cam.focal_px, cam.cx, cam.cy)
    R = rotation(cam.pan, cam.tilt, cam.roll)
    t = -jnp.einsum("cij,cj->ci", R, cam.position)
    proj = lambda X: np.asarray(project(K[:, None], R[:, None], t[:, None], jnp.asarray(X)[None]))
    X = np.asarray(smp.points)
    np.testing.assert_allclose(np.asarray(geo.pixel), proj(X), rtol=0, atol=1e-9)
    h = 1e-6
    fd = np.stack([(proj(X + h * e) - proj(X - h * e)) / (2 * h) for e in np.eye(3)], -1)
    s = np.asarray(geo.sensitivity)
    scale = np.abs(s).max(axis=(-1, -2), keepdims=True)
    assert np.max(np.abs(s - fd) / scale) < 1e-6
    fa = np.stack([(proj(X + h * np.asarray(d)) - proj(X - h * np.asarray(d))) / (2 * h)
                   for d in (smp.tangent_u, smp.tangent_v)], -1)
    A = np.asarray(geo.footprint)
    assert np.max(np.abs(A - fa) / np.abs(A).max(axis=(-1, -2), keepdims=True)) < 1e-6


def test_distorted_pixel_and_sensitivity_match_opencv_and_the_camera_model():
    """With lens distortion: the pixels against cv2.projectPoints, the sensitivity against
    `vdo.model.camera.sensitivity` and against OpenCV's Jacobian of the pixel with respect to the
    translation (d x / d t = d x / d X_c, so d x / d X = (d x / d t) R)."""
    import cv2

    cam, smp, _ = two_plane_scene(60, distortion=LENSES)
    pinhole = ob.geometry(eqx_replace(cam, "distortion", None), smp)
    geo = ob.geometry(cam, smp)
    K = np.asarray(intrinsic_matrix(cam.focal_px, cam.cx, cam.cy))
    R = np.asarray(rotation(cam.pan, cam.tilt, cam.roll))
    t = -np.einsum("cij,cj->ci", R, np.asarray(cam.position))
    X = np.asarray(smp.points)
    moved = 0.0
    for c in range(3):
        rvec, _ = cv2.Rodrigues(R[c])
        uv, jac = cv2.projectPoints(X, rvec, t[c], K[c], LENSES[c])
        np.testing.assert_allclose(np.asarray(geo.pixel[c]), uv[:, 0], rtol=0, atol=1e-6)
        s_cv = jac[:, 3:6].reshape(-1, 2, 3) @ R[c]
        s = np.asarray(geo.sensitivity[c])
        own = np.asarray(sensitivity(K[c], R[c], t[c], jnp.asarray(X), jnp.asarray(LENSES[c])))
        scale = np.abs(s).max()
        assert np.abs(s - s_cv).max() < 1e-9 * scale
        assert np.abs(s - own).max() < 1e-12 * scale
        moved = max(moved, np.abs(s - np.asarray(pinhole.sensitivity[c])).max() / scale)
    assert moved > 1e-2   # the distortion really changes the sensitivity


def test_zero_distortion_gives_the_pinhole_results():
    """Coefficients all zero take the distorted code path: value, gradient and the report's
    sigma agree with the pinhole path to 1e-12 relative."""
    cam, smp, vd = two_plane_scene(300)
    zero = eqx_replace(cam, "distortion", np.zeros((3, 5)))
    st = ob.Settings(image_margin_px=40.0, incidence_ramp=math.radians(20.0))
    (v0, g0), (v1, g1) = (ob.score_and_grad(c, smp, vd, GAUSS, st) for c in (cam, zero))
    assert abs(float(v1) / float(v0) - 1.0) < 1e-12
    for name in ("position", "pan", "tilt", "roll", "focal_px", "cx", "cy"):
        a, b = np.asarray(getattr(g0, name)), np.asarray(getattr(g1, name))
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max(), name
    f0, f1 = (ob.fields(c, smp, vd, GAUSS, st) for c in (cam, zero))
    np.testing.assert_allclose(np.asarray(f1.sigma_max), np.asarray(f0.sigma_max), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(f1.sensitivity), np.asarray(f0.sensitivity), rtol=1e-12)


# --------------------------------------------------------------------------------------------
# The gradient tensor: against an SVD reference, and smooth where a_1 = a_2
# --------------------------------------------------------------------------------------------
def _tensor_reference(A, G, kappa=ob.KAPPA_BOX):
    U, a, _ = np.linalg.svd(A)
    T = np.zeros((2, 2))
    for k in range(2):
        T += G(kappa / a[k], kappa / a[1 - k]) / a[k] ** 2 * np.outer(U[:, k], U[:, k])
    return T


def test_gradient_tensor_matches_svd_reference():
    rng = np.random.default_rng(1)
    G = lambda lp, lq: float(GAUSS(lp, lq))
    for _ in range(20):
        A = rng.normal(size=(2, 2)) * 3000.0
        T = np.asarray(ob.gradient_tensor(jnp.asarray(A), GAUSS))
        np.testing.assert_allclose(T, _tensor_reference(A, G), rtol=1e-7, atol=1e-7 * np.abs(T).max())


def test_gradient_tensor_isotropic_footprint_is_exact_and_differentiable():
    a = 2500.0
    A = jnp.asarray(a * np.array([[0.6, -0.8], [0.8, 0.6]]))  # a rotation times a: a_1 = a_2 exactly
    T = np.asarray(ob.gradient_tensor(A, GAUSS))
    l = ob.KAPPA_BOX / a
    # exact up to the gap floor's O(gap_eps^2) = 1e-8
    np.testing.assert_allclose(T, float(GAUSS(l, l)) / a ** 2 * np.eye(2), rtol=2e-8, atol=1e-12)
    # a generic scalar function of T, differentiated at the degenerate point
    probe = jnp.array([[1.0, 0.3], [0.3, 2.0]])
    fun = lambda A: jnp.sum(probe * ob.gradient_tensor(A, GAUSS)) * 1e12
    g = np.asarray(jax.grad(fun)(A))
    assert np.all(np.isfinite(g))
    h = 1e-3
    fd = np.zeros((2, 2))
    for i in range(2):
        for j in range(2):
            E = np.zeros((2, 2))
            E[i, j] = h
            fd[i, j] = (float(fun(A + E)) - float(fun(A - E))) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


# --------------------------------------------------------------------------------------------
# Score gradients against finite differences
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_table():
    h = 1e-4
    f = normalise(generate_pattern(256, h, 8 * h, 0.5, 5, 2))
    return gradient_energy_table(f, h, n=48)


@pytest.mark.parametrize("energy_kind, lens", [("gauss", None), ("table", None), ("gauss", "distorted"),
                                               ("table", "distorted")])
def test_score_gradient_matches_finite_differences(energy_kind, lens, small_table):
    cam, smp, pho = two_plane_scene(300, distortion=None if lens is None else LENSES)
    energy = GAUSS if energy_kind == "gauss" else small_table
    st = ob.Settings(coverage_weight=1.0, image_margin_px=40.0, incidence_ramp=math.radians(20.0))
    w = np.asarray(ob.geometry(cam, smp, st).weight)
    assert np.sum((w > 0) & (w < 1)) >= 5  # the soft transitions take part
    assert np.sum(w == 1) > 300
    value, grad = ob.score_and_grad(cam, smp, pho, energy, st)
    assert np.isfinite(float(value))
    f = lambda c: float(ob.score(c, smp, pho, energy, st))
    for name, h in [("position", 1e-6), ("pan", 1e-7), ("tilt", 1e-7), ("focal_px", 1e-4)]:
        x0 = np.asarray(getattr(cam, name))
        g = np.asarray(getattr(grad, name))
        assert np.all(np.isfinite(g)), name
        fd = np.zeros_like(x0)
        for idx in np.ndindex(x0.shape):
            e = np.zeros_like(x0)
            e[idx] = h
            plus = eqx_replace(cam, name, x0 + e)
            minus = eqx_replace(cam, name, x0 - e)
            fd[idx] = (f(plus) - f(minus)) / (2 * h)
        err = np.max(np.abs(g - fd)) / np.max(np.abs(fd))
        print(f"{energy_kind} {name}: max |AD - FD| / max |FD| = {err:.2e}")
        assert err < 1e-4, (name, g, fd)
        # the fronto-parallel camera's own gradient is finite and informative too
        assert np.all(np.isfinite(g[0]))


def eqx_replace(cam, name, value):
    """`cam` with one field replaced (None allowed: a pinhole's distortion)."""
    import dataclasses
    return dataclasses.replace(cam, **{name: None if value is None else jnp.asarray(value)})


# --------------------------------------------------------------------------------------------
# Closed form: one fronto-parallel camera over a speckled patch (Pan et al. 2008)
# --------------------------------------------------------------------------------------------
def test_fronto_parallel_camera_matches_image_cramer_rao_bound():
    """Predicted in-plane variance vs sigma^2 (sum_pixels grad f grad f^T)^-1 on the image of a
    speckle tile (1024^2 texels of 0.1 mm, 1.6 mm dots = 4 px, 256^2 pixels of 0.4 mm).

    The image is rendered spectrally (exact for the tile's trigonometric interpolation), its
    gradient taken exactly at the pixel centres. With a Gaussian pixel of std kappa = 1/sqrt(12)
    px, the model's own assumption, the two agree to < 1.5 %. With a true box pixel the model
    predicts ~4.5 % less variance (~2.3 % less sigma): the Gaussian keeps more energy above the
    pixel Nyquist frequency than the box's sinc^2 transfer does, and a sharp-edged dot pattern has
    a k^-3 power tail, so its gradient energy sits largely at the pixel scale for any dot size
    (kappa ~ 0.30 px would match the box for this pattern)."""
    NT, h, px = 1024, 1e-4, 4
    f = normalise(generate_pattern(NT, h, 16 * h, 0.5, 0, 3))
    table = gradient_energy_table(f, h)
    p = px * h  # pixel footprint, m
    Z = 1.0
    c, sigma = 1000.0, 10.0
    omega = (NT * h) ** 2
    cam = make_cameras([[0.0, 0.0, Z]], None, focal_px=Z / p, width=256, height=256,
                       angles=[(0.0, -math.pi / 2)])
    smp = make_samples([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]], area=omega)
    pho = views(smp, 1, c, sigma)
    C = np.asarray(ob.information(cam, smp, pho, table, ob.Settings(patch_area=omega)))[0]
    assert abs(C[2, 2]) < 1e-12 * C[0, 0]  # one camera: no out-of-plane information
    predicted = np.linalg.inv(C[:2, :2])

    k = np.fft.fftfreq(NT, d=h)
    F = np.fft.fft2(f)
    shift = np.exp(2j * np.pi * k * 1.5 * h)  # pixel centre = texel 1.5 of its 4x4 block

    def direct(transfer):
        S = F * np.outer(transfer, transfer) * np.outer(shift, shift)
        gx = np.fft.ifft2(S * 2j * np.pi * k[None, :]).real[::px, ::px] * p  # DN... per pixel
        gy = np.fft.ifft2(S * 2j * np.pi * k[:, None]).real[::px, ::px] * p
        fisher = (c / sigma) ** 2 * np.array([[np.sum(gx * gx), np.sum(gx * gy)],
                                              [np.sum(gx * gy), np.sum(gy * gy)]])  # 1/px^2
        return np.linalg.inv(fisher) * p ** 2  # m^2

    gauss = direct(np.exp(-2 * np.pi ** 2 * (ob.KAPPA_BOX * p) ** 2 * k ** 2))
    box = direct(np.sinc(k * p))
    r_gauss = np.trace(predicted) / np.trace(gauss)
    r_box = np.trace(predicted) / np.trace(box)
    print(f"Pan closed form: predicted/direct variance, Gaussian pixel {r_gauss:.4f}, "
          f"box pixel {r_box:.4f} (sigma ratio {math.sqrt(r_box):.4f})")
    assert abs(r_gauss - 1) < 0.015
    assert 0.97 < math.sqrt(r_box) < 1.0


# --------------------------------------------------------------------------------------------
# Closed forms: one tilted camera, a symmetric stereo pair
# --------------------------------------------------------------------------------------------
def test_tilted_camera_information_is_rank_two_with_the_ray_as_null_vector():
    rng = np.random.default_rng(4)
    pts = np.c_[rng.uniform(-0.05, 0.05, (20, 2)), np.zeros(20)]
    smp = make_samples(pts, np.tile([0, 0, 1.0], (20, 1)), np.tile([1.0, 0, 0], (20, 1)))
    pos = np.array([0.7, -0.4, 0.8])
    cam = make_cameras([pos], [[0.01, 0.02, 0.0]], roll=[0.2])
    Ci = np.asarray(ob.camera_information(cam, smp, views(smp, 1), GAUSS))[0]
    for X, M in zip(pts, Ci):
        ray = (pos - X) / np.linalg.norm(pos - X)
        lam, V = np.linalg.eigh(M)
        assert lam[1] > 1e-3 * lam[2] > 0
        assert abs(lam[0]) < 1e-12 * lam[2]
        assert np.linalg.norm(M @ ray) < 1e-12 * lam[2]
        assert abs(abs(V[:, 0] @ ray) - 1) < 1e-10


@pytest.mark.parametrize("theta_deg", [10.0, 25.0, 40.0])
def test_symmetric_stereo_pair_closed_form(theta_deg):
    """Cameras at distance D at +-theta from the normal in the x-z plane, both aimed at X = 0.
    At the principal point s_i = (f/D) [e_x; e_y] (rows orthonormal, null on the ray), the
    footprint has a = f/D along y and a cos(theta) along x, so with phi_x = G(l_x, l_y)/(a cos)^2,
    phi_y = G(l_y, l_x)/a^2, l_x = kappa/(a cos), l_y = kappa/a, K = Omega (c/sigma)^2 a^2 cos * a^2:

        C = 2 K [phi_x (cos^2 x x^T + sin^2 z z^T) + phi_y y y^T]
        sigma_x^2 = 1/(2 K phi_x cos^2), sigma_z^2 = 1/(2 K phi_x sin^2), sigma_y^2 = 1/(2 K phi_y)

    so sigma_z / sigma_x = cot(theta), whatever the pattern."""
    th = math.radians(theta_deg)
    D, f, c, sigma, omega = 1.1, 3000.0, 700.0, 4.0, 1e-4
    pos = [[D * math.sin(th), 0.0, D * math.cos(th)], [-D * math.sin(th), 0.0, D * math.cos(th)]]
    cam = make_cameras(pos, [[0, 0, 0]] * 2, focal_px=f, roll=[0.3, -0.7])
    smp = make_samples([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [[0.6, 0.8, 0.0]])
    st = ob.Settings(patch_area=omega)
    out = ob.fields(cam, smp, views(smp, 2, c, sigma), GAUSS, st)
    a = f / D
    lx, ly = ob.KAPPA_BOX / (a * math.cos(th)), ob.KAPPA_BOX / a
    phix = float(GAUSS(lx, ly)) / (a * math.cos(th)) ** 2
    phiy = float(GAUSS(ly, lx)) / a ** 2
    K = omega * (c / sigma) ** 2 * a ** 4 * math.cos(th)
    expected = np.sqrt([1 / (2 * K * phix * math.cos(th) ** 2), 1 / (2 * K * phiy),
                        1 / (2 * K * phix * math.sin(th) ** 2)])
    got = np.asarray(out.sigma_xyz)[0]
    np.testing.assert_allclose(got, expected, rtol=1e-7)
    np.testing.assert_allclose(got[2] / got[0], 1 / math.tan(th), rtol=1e-7)
    assert bool(out.measured[0])
    np.testing.assert_allclose(float(out.sigma_max[0]), expected.max(), rtol=1e-7)
    # the smooth regularised value used by the score: above the exact one by the p-norm's bias
    # (at most 3^(1/2p)), below it by the prior's (sigma / prior_sigma)^2 ~ 1e-6
    ratio = float(out.sigma_max_smooth[0]) / float(out.sigma_max[0])
    assert 1.0 - 1e-5 <= ratio < 3 ** (1 / (2 * st.eigen_power)) + 1e-9


def test_single_view_is_reported_unmeasured_and_scored_finitely():
    cam = make_cameras([[0.0, 0.0, 1.0]], None, angles=[(0.0, -math.pi / 2)])
    smp = make_samples([[0.01, 0.0, 0.0]], [[0, 0, 1.0]], [[1.0, 0, 0]])
    pho = views(smp, 1)
    out = ob.fields(cam, smp, pho, GAUSS)
    assert not bool(out.measured[0])
    assert np.isinf(float(out.sigma_max[0])) and np.all(np.isinf(np.asarray(out.sigma_xyz)))
    st = ob.Settings()
    assert 0.9 * st.prior_sigma < float(out.sigma_max_smooth[0]) <= st.prior_sigma * (1 + 1e-9)
    v, g = ob.score_and_grad(cam, smp, pho, GAUSS)
    assert np.isfinite(float(v)) and all(np.all(np.isfinite(x)) for x in jax.tree.leaves(g))


# --------------------------------------------------------------------------------------------
# Soft weights
# --------------------------------------------------------------------------------------------
def test_weights_fall_smoothly_to_zero_at_the_image_edge():
    """Shift the principal point so that a point's image sweeps across the left image edge."""
    smp = make_samples([[0.0, 0.0, 0.0]], [[0, 0, 1.0]], [[1.0, 0, 0]])
    st = ob.Settings(image_margin_px=10.0)
    f = 2000.0

    def w_of_cx(cx):
        cam = make_cameras([[0.0, 0.0, 1.0]], None, focal_px=f, width=200, height=200,
                           angles=[(0.0, -math.pi / 2)])
        cam = eqx_replace(cam, "cx", jnp.atleast_1d(cx))
        g = ob.geometry(cam, smp, st)
        return g.weight[0, 0], g.pixel[0, 0, 0]

    cxs = np.linspace(-20.0, 20.0, 801)  # u = cx: edge at -0.5, ramp to 9.5
    ws = np.array([float(w_of_cx(c)[0]) for c in cxs])
    us = np.array([float(w_of_cx(c)[1]) for c in cxs])
    np.testing.assert_allclose(us, cxs, atol=1e-9)
    assert np.all(ws[us <= -0.5] == 0) and np.all(ws[us >= 9.5] == 1)
    assert np.all((ws >= 0) & (ws <= 1)) and np.all(np.diff(ws) >= 0)
    assert np.max(np.abs(np.diff(ws))) < 0.01  # continuous on a 0.05 px grid
    dw = jax.grad(lambda c: w_of_cx(c)[0])
    for c in (-0.5, -0.4999, 4.5, 9.5, 9.5001, -5.0, 15.0):
        g = float(dw(c))
        assert np.isfinite(g)
        fd = (float(w_of_cx(c + 1e-6)[0]) - float(w_of_cx(c - 1e-6)[0])) / 2e-6
        assert abs(g - fd) < 1e-5
    assert float(dw(-0.5)) == 0.0 and float(dw(9.5)) == 0.0  # C^1 (indeed C^2) at both ends


def test_weights_fall_smoothly_to_zero_at_the_incidence_limit():
    """Move a camera around a point on an arc so that the incidence angle sweeps past the limit;
    the camera keeps aiming at the point (so it stays mid-image)."""
    limit, ramp = math.radians(70.0), math.radians(10.0)
    st = ob.Settings(incidence_limit=limit, incidence_ramp=ramp)
    smp = make_samples([[0.0, 0.0, 0.0]], [[0, 0, 1.0]], [[1.0, 0, 0]])

    def cam_at(theta):
        pos = jnp.stack([jnp.sin(theta), 0.0 * theta, jnp.cos(theta)])[None]
        tilt = -(math.pi / 2 - theta)
        return ob.CameraParams(pos, jnp.atleast_1d(jnp.pi + 0.0 * theta), jnp.atleast_1d(tilt),
                               jnp.zeros(1), jnp.full(1, 2000.0), jnp.full(1, 99.5),
                               jnp.full(1, 99.5), jnp.full(1, 200.0), jnp.full(1, 200.0))

    w = jax.jit(lambda th: ob.geometry(cam_at(th), smp, st).weight[0, 0])
    ths = np.radians(np.linspace(50.0, 85.0, 701))
    ws = np.array([float(w(t)) for t in ths])
    # exactly 0 beyond the limit; at the limit itself cos(theta) and cos(limit) are rounded apart
    # differently on different CPUs (FMA contraction), leaving S(~1e-16) ~ 1e-45 at most
    at = np.isclose(ths, limit, rtol=0, atol=1e-12)
    assert np.all(ws[(ths > limit) & ~at] == 0) and np.all(ws[at] < 1e-40)
    assert np.all(ws[ths <= limit - ramp] == 1)
    assert np.all(np.diff(ws) <= 1e-15) and np.max(np.abs(np.diff(ws))) < 0.01
    dw = jax.jit(jax.grad(w))
    for t in (limit - ramp, limit - ramp / 2, limit, limit + 1e-9):
        g = float(dw(t))
        fd = (float(w(t + 1e-7)) - float(w(t - 1e-7))) / 2e-7
        assert np.isfinite(g) and abs(g - fd) < 1e-5 * max(1.0, abs(fd))
    # the score's gradient is finite right at the limit (with a second, fixed camera)
    c2 = make_cameras([[0.0, 0.3, 1.0]], [[0, 0, 0]], focal_px=2000.0, width=200, height=200)
    pho2 = views(smp, 2)

    @jax.jit
    @jax.grad
    def total(th):
        both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), cam_at(th), c2)
        return ob.score(both, smp, pho2, GAUSS, st)

    for t in (limit, limit - ramp, limit - ramp / 2):
        assert np.isfinite(float(total(t)))


# --------------------------------------------------------------------------------------------
# The hand-written reverse pass and the float32 per-pair path
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("energy_kind, lens", [("gauss", None), ("table", None), ("gauss", "distorted")])
def test_hand_written_pair_backward_matches_autodiff(energy_kind, lens, small_table):
    """`vdo.information.blocks.block_vjp` against jax.vjp of the same per-pair forward, for random
    cotangents (with lens distortion, its coefficients are constants: zero cotangent from both)."""
    cam, smp, vd = two_plane_scene(300, distortion=None if lens is None else LENSES)
    energy = GAUSS if energy_kind == "gauss" else small_table
    st = ob.Settings(image_margin_px=40.0, incidence_ramp=math.radians(20.0))
    ctab, sq, occ, kc, one = blocks.pair_inputs(cam, vd, st, jnp.float64)
    rng = np.random.default_rng(3)
    c_ent = tuple(jnp.asarray(rng.normal(size=occ.shape)) for _ in range(6))
    c_w = jnp.asarray(rng.normal(size=occ.shape))

    def forward(ctab):
        ent, w, _ = blocks.block_forward(blocks.block_columns(ctab, sq[0].dtype), sq, occ, kc, one,
                                         energy, st)
        return ent, w

    (ent, w), vjp = jax.vjp(forward, ctab)
    assert np.sum((np.asarray(w) > 0) & (np.asarray(w) < 1)) >= 5  # soft weights take part
    auto = np.asarray(vjp((c_ent, c_w))[0])
    hand = np.asarray(blocks.block_vjp(ctab, sq, occ, kc, one, c_ent, c_w, energy, st))
    # R is a rotation: what counts of dL/dR is the skew part of dL/dR R^T (dR = W R, W skew)
    Rb = np.asarray(ctab[:, :9]).reshape(-1, 3, 3)

    def skew(g):
        m = g[:, :9].reshape(-1, 3, 3) @ np.swapaxes(Rb, 1, 2)
        return m - np.swapaxes(m, 1, 2)

    auto = np.concatenate([skew(auto).reshape(-1, 9), auto[:, 9:15]], 1)
    assert hand.shape[1] == (17 if lens is None else 22)
    assert np.all(hand[:, 15:] == 0.0)  # width, height (and distortion): constants
    hand = np.concatenate([skew(hand).reshape(-1, 9), hand[:, 9:15]], 1)
    scale = np.maximum(np.abs(auto).max(axis=0), 1e-12 * np.abs(auto).max())  # per column
    assert np.max(np.abs(hand - auto) / scale) < 1e-9


def test_block_and_chunk_sizes_do_not_change_value_or_gradient(small_table):
    """The pair list's layout (pairs per block, blocks per chunk of both passes) is a
    performance choice only: many small chunks give the one-chunk value and gradient."""
    cam, smp, _ = two_plane_scene(300)
    occlusion = np.ones((3, 300))
    occlusion[2, 100:] = 0.0  # cameras with different pair counts
    st = ob.Settings(image_margin_px=40.0, incidence_ramp=math.radians(20.0))
    one = ob.ViewData.from_dense(occlusion, 800.0, 5.0, smp)
    many = ob.ViewData.from_dense(occlusion, 800.0, 5.0, smp, block=16, chunk_pairs=32)
    assert one.camera.size // (one.block * one.chunk) == 1
    assert many.camera.size // (many.block * many.chunk) > 10
    (v1, g1), (v2, g2) = (ob.score_and_grad(cam, smp, vd, small_table, st) for vd in (one, many))
    assert abs(float(v2) / float(v1) - 1.0) < 1e-12
    flat = [np.concatenate([np.ravel(x) for x in jax.tree.leaves(g)]) for g in (g1, g2)]
    assert np.max(np.abs(flat[1] - flat[0])) < 1e-10 * np.max(np.abs(flat[0]))  # rounding only


@pytest.mark.parametrize("energy_kind", ["gauss", "table"])
def test_float32_pairs_agree_with_float64(energy_kind, small_table):
    """pair_dtype float32 (per-sample sums and score in float64) against float64: value and
    gradient within 1e-4 relative (measured ~1e-7 and ~1e-5), also for samples one camera
    short (the assembly stays float64, so one camera's information keeps the ray null)."""
    cam, smp, _ = two_plane_scene(300)
    occlusion = np.ones((3, 300))
    occlusion[1:, :40] = 0.0  # the first 40 samples seen by camera 0 alone
    vd = ob.ViewData.from_dense(occlusion, 800.0, 5.0, smp)
    energy = GAUSS if energy_kind == "gauss" else small_table
    st64 = ob.Settings(coverage_weight=1.0, image_margin_px=40.0, incidence_ramp=math.radians(20.0))
    st32 = ob.Settings(coverage_weight=1.0, image_margin_px=40.0, incidence_ramp=math.radians(20.0),
                       pair_dtype="float32")
    v64, g64 = ob.score_and_grad(cam, smp, vd, energy, st64)
    v32, g32 = ob.score_and_grad(cam, smp, vd, energy, st32)
    assert abs(float(v32) / float(v64) - 1) < 1e-4
    for a, b in zip(jax.tree.leaves(g32), jax.tree.leaves(g64)):
        a, b = np.asarray(a), np.asarray(b)
        assert np.max(np.abs(a - b)) <= 1e-4 * max(np.max(np.abs(b)), 1e-300), (a, b)
    f64, f32 = ob.fields(cam, smp, vd, energy, st64), ob.fields(cam, smp, vd, energy, st32)
    assert not np.asarray(f64.measured).all()  # the one-camera samples are there
    # the report stays float64 whatever the pair dtype
    np.testing.assert_array_equal(np.asarray(f32.sigma_max_smooth), np.asarray(f64.sigma_max_smooth))
