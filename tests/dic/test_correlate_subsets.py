"""Many subsets at once (`vdo.dic.subsets.correlate_subsets`, `vdo.dic.series.start_guesses`)
against the per-point solver (`correlate`, today's implementation) on the same points and images,
and against the imposed displacement of images rendered independently (tests/dic/test_correlate's
little renderer): a translation, an affine field, and a sub-pixel translation of a smooth speckle
(the closed form: the recovered U is the imposed one)."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_correlate  # noqa: E402
from test_correlate import DOT, PATCH, STEREO, TEXEL, U_TRUE, render  # noqa: E402

import jax.numpy as jnp  # noqa: E402

from vdo.dic import subset_sums  # noqa: E402
from vdo.dic import shifts as shifts_module  # noqa: E402
from vdo.dic import subsets as subsets_module  # noqa: E402
from vdo.dic.images import SplineImage  # noqa: E402
from vdo.dic.correlate import ImageReference, Q4, correlate  # noqa: E402
from vdo.dic.patch import Patch  # noqa: E402
from vdo.dic.subsets import correlate_subsets  # noqa: E402
from vdo.dic.series import correlate_points, start_guess, start_guesses  # noqa: E402
from vdo.model.speckle import generate_pattern  # noqa: E402
from vdo.model.spline_response import KEYS  # noqa: E402

pattern = test_correlate.pattern        # the module's fixture, shared

SAME_U_M = 1e-12          # m (2e-8 px here): batched against per-point, the same iteration (measured ~5e-17)
SAME_BC = 1e-9            # brightness (gray levels) and contrast: the same iteration
SAME_SAMPLE = 1e-9        # grey levels of ~4000: the same sum in another order (measured ~1e-12)
SAME_SUM = 1e-12          # relative: the compiled sums against NumPy's (float64 rounding)
SAME_START_PX = 1e-9      # start guesses: whole-pixel shifts through the same least squares
SHIFT_TOL_PX = 0.02       # recovered against imposed, noise-free box-pixel speckle (as test_correlate_window)
CLOSED_FORM_TOL_PX = 0.002  # smooth speckle (dots blurred by 2 px): measured 5e-4 px
SUBSET = 1.45e-3          # m: 29 px at 0.05 mm per pixel
# An affine field on the patch (ξ in metres from PATCH.origin): stretch, shear, turn and tilt of a
# few 1e-3, on top of U_TRUE: ~0.1 px across the points, 0.03 px across a subset.
GRAD = np.array([[2e-3, -1.5e-3], [1e-3, -2.5e-3], [1.2e-3, 0.8e-3]])
CENTRE = PATCH.size / 2


def affine(xi):
    return U_TRUE + (np.asarray(xi) - CENTRE) @ GRAD.T


@pytest.fixture(scope="module")
def cameras():
    """The stereo pair at 0.05 mm per pixel on a 240 x 180 crop."""
    return [replace(c, width=240, height=180, focal_length=2 * c.focal_length) for c in STEREO]


def grid(n=3, half=2e-3):
    xs = np.linspace(-half, half, n)
    points = np.array([[x, y, 0.0] for x in xs for y in xs])
    return points, np.tile([1.0, 0, 0], (len(points), 1)), np.tile([0, 1.0, 0], (len(points), 1))


def px_error(cams, points, U, U_true):
    return max(np.abs(np.einsum("nij,nj->ni", c.sensitivity(points), U - U_true)).max() for c in cams)


@pytest.mark.parametrize("motion", ["translation", "affine"])
def test_batched_subsets_are_the_per_point_solution(pattern, cameras, monkeypatch, motion):
    disp = U_TRUE if motion == "translation" else affine
    refs = [render(c, pattern) for c in cameras]
    defs = [render(c, pattern, disp) for c in cameras]
    points, tu, tv = grid()
    # and one subset cut by the image margin (handed to `correlate`; its start guess's window is
    # cut too: `start_guess` itself)
    points = np.vstack([points, [-4.4e-3, 0, 0]])
    tu, tv = np.vstack([tu, tu[:1]]), np.vstack([tv, tv[:1]])
    U0 = start_guesses(cameras, refs, defs, points)
    one = np.array([start_guess(cameras, refs, defs, X) for X in points])
    assert px_error(cameras, points, U0, one) < SAME_START_PX
    assert np.array_equal(start_guesses(cameras, refs, defs, points, workers=2), U0)
    monkeypatch.setattr(shifts_module, "START_CHUNK", 3)         # several chunks, several threads
    assert np.array_equal(start_guesses(cameras, refs, defs, points, workers=2), U0)
    monkeypatch.setattr(subsets_module, "SUBSET_CHUNK", 4)       # several chunks, several threads
    batched = correlate_subsets(cameras, refs, defs, points, tu, tv, SUBSET, U0)
    threads = correlate_subsets(cameras, refs, defs, points, tu, tv, SUBSET, U0, workers=2)
    assert np.array_equal(batched.U, threads.U)
    assert batched.converged.all()
    assert not batched.one_by_one[:-1].any() and batched.one_by_one[-1]      # the cut one: `correlate`
    for k, (X, t_u, t_v) in enumerate(zip(points, tu, tv)):
        patch = Patch(origin=X - SUBSET / 2 * (t_u + t_v), t_u=t_u, t_v=t_v, size=(SUBSET, SUBSET))
        today = correlate(cameras, defs, patch, ImageReference(refs), model=Q4(1, 1), U0=np.tile(U0[k], (4, 1)))
        assert np.abs(batched.U[k] - today.U).max() < SAME_U_M
        assert np.abs(batched.c[k] - today.c).max() < SAME_BC and np.abs(batched.b[k] - today.b).max() < SAME_BC
        assert batched.iterations[k] == today.iterations and today.converged
    xi = points[:, :2] - PATCH.origin[:2]
    U_true = np.tile(U_TRUE, (len(points), 1)) if motion == "translation" else affine(xi)
    assert px_error(cameras, points[:-1], batched.centre[:-1], U_true[:-1]) < SHIFT_TOL_PX    # whole subsets
    U, ok = correlate_points(cameras, refs, defs, points, tu, tv, SUBSET)         # the wiring
    assert ok.all() and np.array_equal(U, batched.centre)
    # A given start (a previous load step's result) is used where finite, the start guess elsewhere.
    start = U_true + [[2e-5, -1e-5, 1e-5]]
    start[0] = np.nan
    given = correlate_subsets(cameras, refs, defs, points, tu, tv, SUBSET,
                              np.where(np.isfinite(start), start, U0))
    U2, ok2 = correlate_points(cameras, refs, defs, points, tu, tv, SUBSET, start=start)
    assert ok2.all() and np.array_equal(U2, given.centre)
    from vdo.dic.correlate import Solver
    assert np.abs(U2 - U).max() < Solver().tol       # the same minimum, within the solver's stop


def test_subpixel_translation_of_a_smooth_speckle_is_recovered(cameras):
    smooth = ndimage.gaussian_filter(generate_pattern(512, TEXEL, DOT, seed=3).astype(float), 4, mode="wrap")
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min())
    refs = [render(c, smooth) for c in cameras]
    defs = [render(c, smooth, U_TRUE) for c in cameras]
    points, tu, tv = grid()
    U, ok = correlate_points(cameras, refs, defs, points, tu, tv, SUBSET)
    assert ok.all() and px_error(cameras, points, U, U_TRUE) < CLOSED_FORM_TOL_PX
    per_point, _ = correlate_points(cameras, refs, defs, points, tu, tv, SUBSET, batched=False)
    assert np.abs(U - per_point).max() < SAME_U_M


def test_subsets_off_the_image_go_to_correlate_and_bad_tangents_are_one_line(pattern, cameras):
    refs = [render(c, pattern) for c in cameras]
    points, tu, tv = grid(1)
    # A subset off the image: `correlate` raises, and so does the batched call (which hands it over).
    far = points + [9e-3, 0, 0]
    with pytest.raises(ValueError, match="integration points"):
        correlate_subsets(cameras, refs, refs, far, tu, tv, SUBSET)
    with pytest.raises(ValueError, match="orthonormal"):
        correlate_subsets(cameras, refs, refs, points, tu, tu, SUBSET)


@pytest.mark.parametrize("order", [3, 5, KEYS])
def test_compiled_sampler_is_scipys_spline(order):
    """`vdo.dic.subset_sums.spline_sample`, the compiled step's B-spline sum, against SciPy's
    `map_coordinates` on the same coefficients (cubic, quintic) and against `SplineImage`'s Keys
    interpolant, at random positions over the window less the kernel's reach."""
    rng = np.random.default_rng(4)
    image = ndimage.gaussian_filter(rng.random((70, 90)), 1.5) * 4000
    spline = SplineImage(image, order=order)
    rows, cols = rng.uniform(3, 66, (5, 400)), rng.uniform(3, 86, (5, 400))
    got = np.asarray(subset_sums.spline_sample(jnp.asarray(spline.coeffs), jnp.asarray(rows), jnp.asarray(cols), order))
    if order == KEYS:
        want = spline.sample_local(rows, cols)
    else:
        want = ndimage.map_coordinates(spline.coeffs, [rows, cols], order=order, prefilter=False, mode="mirror")
    assert np.abs(got - want).max() < SAME_SAMPLE


def test_padding_adds_nothing_to_the_compiled_sums():
    """Padding does not change a sum: the pixels of weight 0 and the inactive subsets add nothing,
    checked against the unpadded NumPy sums Σ w f j of the module docstring."""
    rng = np.random.default_rng(5)
    coeffs = ndimage.gaussian_filter(rng.random((160, 160)), 1.5) * 4000
    K, P = 3, 50
    X = np.stack([rng.uniform(-0.02, 0.02, (K, P)), rng.uniform(-0.02, 0.02, (K, P)), np.ones((K, P))], -1)
    N = rng.dirichlet(np.ones(4), (K, P))
    U = rng.uniform(-1e-4, 1e-4, (K, 4, 3))
    w, g, G = (rng.random((K, P)) > 0.2).astype(float), rng.random((K, P)), rng.normal(size=(K, P, 3))
    k = np.array([2000.0, 0.0, 80.0, 2000.0, 80.0])
    corners = X[:, :4]
    valid = np.array([3.0, 156.0, 3.0, 156.0])
    pc = X + N @ U
    u, v = k[0] * pc[..., 0] / pc[..., 2] + k[2], k[3] * pc[..., 1] / pc[..., 2] + k[4]
    f = ndimage.map_coordinates(coeffs, [v, u], order=3, prefilter=False, mode="mirror")
    j = np.concatenate([(N[..., :, None] * G[..., None, :]).reshape(K, P, 12), np.ones((K, P, 1)), g[..., None]], -1)
    want = np.einsum("kp,kpi->ki", w * f, j)
    shape = (8, 64)
    args = [subset_sums.padded(a, shape) for a in (X, N)] + [subset_sums.padded(U, shape[:1])] \
        + [subset_sums.padded(w, shape), np.r_[1.0, 0.0, 1.0, np.zeros(5)]] \
        + [subset_sums.padded(a, shape) for a in (g, G)] + [subset_sums.padded(corners, shape[:1])]
    t, inside = subset_sums.residual_sums(jnp.asarray(subset_sums.padded(coeffs, (512, 512))), np.zeros(2), k,
                                          np.eye(3), *args[:3], *args[3:5], *args[5:7], args[7], valid, order=3)
    t = np.asarray(t)
    assert np.abs(t[[0, 2]] - want[[0, 2]]).max() < SAME_SUM * np.abs(want).max()
    assert np.all(t[[1]] == 0) and np.all(t[3:] == 0)          # inactive and padding subsets
    M = np.asarray(subset_sums.normal_sums(*(subset_sums.padded(a, shape) for a in (N, w, G, g))))
    assert np.abs(M[:K] - np.einsum("kp,kpi,kpj->kij", w, j, j)).max() < SAME_SUM * np.abs(M).max()
