"""Subset DIC as a lab's software runs it (`vdo.dic.icgn`): the 2D IC-GN match against a closed
form (an analytic pattern under a known affine warp and a grey-level change) and against OpenCV's
ECC alignment (`cv2.findTransformECC`, an independent implementation of the same affine
matching); the triangulation against exact projections through distorted lenses; and the whole
3D measurement (`correlate_points(..., subset_px=29)`) on the stereo images of tests/dic/
test_correlate's own little renderer, against the imposed displacement and against the Q4
element correlation of the same points."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_correlate  # noqa: E402
from test_correlate import PATCH, STEREO, U_TRUE, render  # noqa: E402

from vdo.dic import icgn  # noqa: E402
from vdo.dic.icgn import match_subsets, triangulate  # noqa: E402
from vdo.dic.series import correlate_points  # noqa: E402

pattern = test_correlate.pattern        # the module's fixture, shared

CLOSED_FORM_PX = 2e-3       # smooth blobs (σ 2.5 px): the cubic spline's error, measured 5e-4 px
GRADIENT_TOL = 1e-4         # the affine terms (px per px): measured 6e-5 (8e-4 px across the subset)
ECC_PX = 0.02               # against OpenCV's ECC (its bilinear warps): measured 0.012 px
ZERO_ORDER_PX = 0.03        # a translation-only subset under a 2e-3 stretch: ~14 px x 2e-3
SAME_TRIANGULATION_M = 1e-9  # exact projections, pinhole or distorted
SHIFT_TOL_PX = 0.02         # rendered box-pixel speckle, noise-free (as test_correlate_subsets)
ELEMENT_PX = 0.02           # against the Q4 element's answer at the same points
SIZE = 29
BLOB_REACH_PX = 16          # a blob is summed within this of its centre: 6.4 σ, exp(-20) of its peak
# The closed form: x' = x0 + A (x - x0) + t, and a grey-level change f = 10 + 1.3 g.
X0, A, T = np.array([250.0, 200.0]), np.array([[1.002, 0.001], [-0.0015, 0.999]]), np.array([0.37, -0.61])


@pytest.fixture(scope="module")
def blobs():
    """A 500 x 400 image of 3,000 random Gaussian blobs (σ 2.5 px) and the same pattern under the
    warp and grey-level change above, evaluated in closed form at every pixel within BLOB_REACH_PX
    of where a blob lies in that image (what is left out: below 1e-5 grey levels in all)."""
    rng = np.random.default_rng(0)
    cu, cv, amp = rng.uniform(-10, 510, 3000), rng.uniform(-10, 410, 3000), rng.uniform(0.5, 1.0, 3000)

    def pattern_at(u, v, where):
        out = np.zeros_like(u)
        for k, (cx, cy) in enumerate(np.rint(where).astype(int)):
            near = (slice(max(cy - BLOB_REACH_PX, 0), max(cy + BLOB_REACH_PX + 1, 0)),
                    slice(max(cx - BLOB_REACH_PX, 0), max(cx + BLOB_REACH_PX + 1, 0)))
            out[near] += amp[k] * np.exp(-((u[near] - cu[k]) ** 2 + (v[near] - cv[k]) ** 2) / (2 * 2.5 ** 2))
        return 100 + 50 * out

    v, u = np.mgrid[0:400, 0:500].astype(float)
    back = np.einsum("ij,...j->...i", np.linalg.inv(A), np.stack([u, v], -1) - X0 - T) + X0
    centres = np.stack([cu, cv], -1)
    return pattern_at(u, v, centres), 10 + 1.3 * pattern_at(back[..., 0], back[..., 1], closed_form(centres))


def closed_form(x):
    return (x - X0) @ A.T + X0 + T


def points_2d():
    u, v = np.meshgrid(np.arange(60, 440, 41.3), np.arange(60, 340, 37.7))
    return np.stack([u.ravel(), v.ravel()], -1)


def test_the_affine_match_is_the_closed_form(blobs, monkeypatch):
    ref, dfm = blobs
    x = points_2d()
    monkeypatch.setattr(icgn, "SUBSET_CHUNK", 8)            # several chunks, and a padded one
    m = match_subsets(ref, dfm, x, np.tile([0.0, -1.0], (len(x), 1)), size_px=SIZE)
    assert m.converged.all() and (m.iterations <= 12).all()
    assert np.abs(m.x - closed_form(x)).max() < CLOSED_FORM_PX
    assert np.abs(m.p[:, [1, 2, 4, 5]] - (A - np.eye(2)).ravel()).max() < GRADIENT_TOL
    assert (m.znssd < 1e-4).all()                           # the grey-level change is no mismatch
    threads = match_subsets(ref, dfm, x, np.tile([0.0, -1.0], (len(x), 1)), size_px=SIZE, workers=2)
    assert np.array_equal(threads.x, m.x)
    zero = match_subsets(ref, dfm, x, np.tile([0.0, -1.0], (len(x), 1)), size_px=SIZE, shape_function="zero")
    assert zero.converged.all() and np.abs(zero.x - closed_form(x)).max() < ZERO_ORDER_PX
    assert zero.p.shape == (len(x), 2)


def test_the_affine_match_is_opencvs_ecc_alignment(blobs):
    cv2 = pytest.importorskip("cv2")
    ref, dfm = blobs
    x = points_2d()[::5]
    m = match_subsets(ref, dfm, x, np.zeros((len(x), 2)), size_px=SIZE)
    h = SIZE // 2
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-8)
    for k, point in enumerate(x):
        c = np.rint(point).astype(int)
        template = ref[c[1] - h:c[1] + h + 1, c[0] - h:c[0] + h + 1].astype(np.float32)
        warp = np.array([[1, 0, c[0] - h], [0, 1, c[1] - h]], np.float32)    # template -> image
        _, warp = cv2.findTransformECC(template, dfm.astype(np.float32), warp, cv2.MOTION_AFFINE,
                                       criteria, None, 1)
        ecc = warp[:, :2] @ (point - (c - h)) + warp[:, 2]
        assert np.abs(ecc - m.x[k]).max() < ECC_PX


def test_a_subset_off_the_image_or_without_texture_is_not_matched_and_bad_settings_are_one_line(blobs):
    ref, dfm = blobs
    flat = np.full_like(ref, 7.0)
    x = np.array([[5.0, 200.0], [250.0, 200.0], [250.0, 395.0]])     # edge, inside, edge
    m = match_subsets(ref, dfm, x, size_px=SIZE)
    assert list(m.converged) == [False, True, False]
    assert not match_subsets(flat, flat, x[1:2], size_px=SIZE).converged.any()
    for kwargs, field in (({"size_px": 28}, "size_px"), ({"size_px": 3}, "size_px"),
                          ({"shape_function": "quadratic"}, "shape_function"), ({"tol_px": 0.0}, "tol_px")):
        with pytest.raises(ValueError, match=field):
            match_subsets(ref, dfm, x, **kwargs)


@pytest.mark.parametrize("distortion", [None, (-0.12, 0.05, 1e-3, -5e-4, 0.0)])
def test_triangulation_returns_the_point_that_projects_to_the_images(distortion):
    cams = [replace(c, distortion=distortion or (0, 0, 0, 0, 0)) for c in STEREO]
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-8e-3, 8e-3, 20), rng.uniform(-6e-3, 6e-3, 20), rng.uniform(-2e-3, 2e-3, 20)])
    x = np.stack([c.project(X) for c in cams])
    got, residual = triangulate(cams, x, X + rng.normal(0, 2e-4, X.shape))
    assert np.abs(got - X).max() < SAME_TRIANGULATION_M and residual.max() < 1e-6
    with pytest.raises(ValueError, match="image points"):
        triangulate(cams[:1], x[:1], X)


@pytest.fixture(scope="module")
def cameras():
    """The stereo pair at 0.05 mm per pixel on a 240 x 180 crop (as test_correlate_subsets)."""
    return [replace(c, width=240, height=180, focal_length=2 * c.focal_length) for c in STEREO]


@pytest.mark.parametrize("motion", ["translation", "affine"])
def test_subset_dic_measures_the_imposed_displacement_of_rendered_images(pattern, cameras, motion):
    grad = np.array([[2e-3, -1.5e-3], [1e-3, -2.5e-3], [1.2e-3, 0.8e-3]])
    centre = PATCH.size / 2

    def field(xi):
        return U_TRUE + (np.asarray(xi) - centre) @ grad.T
    disp = U_TRUE if motion == "translation" else field
    refs = [render(c, pattern) for c in cameras]
    defs = [render(c, pattern, disp) for c in cameras]
    xs = np.linspace(-2e-3, 2e-3, 3)
    points = np.array([[x, y, 0.0] for x in xs for y in xs])
    tu, tv = np.tile([1.0, 0, 0], (len(points), 1)), np.tile([0, 1.0, 0], (len(points), 1))
    U, ok = correlate_points(cameras, refs, defs, points, tu, tv, 1.45e-3, subset_px=SIZE)
    true = np.tile(U_TRUE, (len(points), 1)) if motion == "translation" else field(points[:, :2] - PATCH.origin[:2])

    def px(U_a, U_b):
        return max(np.abs(np.einsum("nij,nj->ni", c.sensitivity(points), U_a - U_b)).max() for c in cameras)
    assert ok.all() and px(U, true) < SHIFT_TOL_PX
    element, _ = correlate_points(cameras, refs, defs, points, tu, tv, 1.45e-3)
    assert px(U, element) < ELEMENT_PX
    threads, _ = correlate_points(cameras, refs, defs, points, tu, tv, 1.45e-3, subset_px=SIZE, workers=2)
    assert np.array_equal(threads, U)
    given, ok2 = correlate_points(cameras, refs, defs, points, tu, tv, 1.45e-3, subset_px=SIZE,
                                  start=true + [[3e-5, -2e-5, 1e-5]])
    assert ok2.all() and px(given, U) < 1e-3            # the same match from another start
