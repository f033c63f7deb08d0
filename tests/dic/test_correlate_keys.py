"""Keys' cubic convolution in the correlation (`SplineImage(order=KEYS)`): the sampler against
an independent numpy implementation of the kernel (a = -1/2) and, with a = -3/4 (the parameter
OpenCV's INTER_CUBIC uses: its kernel sampled at 1/4, 1/2, 5/4, 3/2 px gives 0.8789, 0.5938,
-0.1055, -0.0938, those of a = -3/4, not of a = -1/2), against `cv2.remap` itself; the gradient
against central differences of the independent sampler."""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from vdo.dic.images import SplineImage, WindowedImage
from vdo.model import spline_response
from vdo.model.spline_response import KEYS

NUMPY_TOL = 1e-12        # gray levels of a [0, 1] image: the same sums in another order
OPENCV_TOL = 1e-4        # of the gray range: OpenCV's float32 arithmetic and 1/32 px coordinates
FD_STEP = 1e-5           # px
FD_TOL = 1e-6            # gray level per px: central differences of the independent sampler
OPENCV_SUBPIXEL = 32     # cv2.remap rounds coordinates to 1/32 px (INTER_BITS = 5)


def keys_numpy(image, u, v, a=-0.5):
    """Σ_m Σ_n I[n, m] k(u - m) k(v - n) over the 4 × 4 neighbours, k written from its definition
    (Keys 1981): (a+2)|s|³ - (a+3)|s|² + 1 (|s| <= 1), a|s|³ - 5a|s|² + 8a|s| - 4a (1 < |s| < 2)."""
    def k(s):
        s = abs(s)
        if s <= 1:
            return (a + 2) * s ** 3 - (a + 3) * s ** 2 + 1
        return a * s ** 3 - 5 * a * s ** 2 + 8 * a * s - 4 * a if s < 2 else 0.0

    out = np.empty(len(u))
    for i, (x, y) in enumerate(zip(u, v)):
        c0, r0 = int(np.floor(x)), int(np.floor(y))
        out[i] = sum(image[r, c] * k(x - c) * k(y - r)
                     for r in range(r0 - 1, r0 + 3) for c in range(c0 - 1, c0 + 3))
    return out


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(4)
    image = ndimage.gaussian_filter(rng.random((60, 70)), 0.8)
    image = (image - image.min()) / (image.max() - image.min())
    x = np.column_stack([rng.uniform(3, 66, 200), rng.uniform(3, 56, 200)])
    return image, x


def test_keys_sampler_is_the_kernel_written_out(scene):
    image, x = scene
    s = SplineImage(image, order=KEYS)
    f, g = s.value_and_gradient(x)
    ref = keys_numpy(image, x[:, 0], x[:, 1])
    assert np.max(np.abs(f - ref)) < NUMPY_TOL and np.max(np.abs(s(x) - ref)) < NUMPY_TOL
    assert np.allclose(s(np.array([[5.0, 7.0]])), image[7, 5], atol=NUMPY_TOL)    # through its samples
    for k, step in enumerate(np.eye(2) * FD_STEP):
        fd = (keys_numpy(image, *(x + step).T) - keys_numpy(image, *(x - step).T)) / (2 * FD_STEP)
        assert np.max(np.abs(g[:, k] - fd)) < FD_TOL
    # windows (what `correlate` reads) and the whole image agree exactly: the kernel is local
    lazy = WindowedImage(image, order=KEYS)
    assert np.max(np.abs(lazy(x[:20]) - f[:20])) < NUMPY_TOL


def test_keys_sampler_with_opencvs_parameter_is_cv2_remap(scene, monkeypatch):
    image, x = scene
    x = np.round(x * OPENCV_SUBPIXEL) / OPENCV_SUBPIXEL
    monkeypatch.setattr(spline_response, "KEYS_A", -0.75)
    ours = SplineImage(image, order=KEYS)(x)
    theirs = cv2.remap(image.astype(np.float32), x[:, 0].astype(np.float32)[None],
                       x[:, 1].astype(np.float32)[None], cv2.INTER_CUBIC)[0]
    assert np.max(np.abs(ours - theirs)) < OPENCV_TOL
    assert np.max(np.abs(ours - keys_numpy(image, x[:, 0], x[:, 1], a=-0.75))) < NUMPY_TOL
    # and vdo's default a = -1/2 is not OpenCV's kernel
    monkeypatch.undo()
    assert np.max(np.abs(SplineImage(image, order=KEYS)(x) - theirs)) > 10 * OPENCV_TOL


def test_keys_subsets_are_the_per_point_solution_and_recover_the_shift():
    """`correlate_subsets(order=KEYS)` (the compiled sampler, `vdo.dic.subset_sums`, with Keys'
    weights) against one `correlate(order=KEYS)` per subset, and the imposed shift of a smooth speckle
    rendered independently (tests/dic/test_correlate.py's box-pixel renders)."""
    import sys
    from dataclasses import replace
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_correlate import DOT, STEREO, TEXEL, U_TRUE, render
    from test_correlate_subsets import SAME_U_M, SHIFT_TOL_PX, SUBSET, grid, px_error

    from vdo.dic.correlate import ImageReference, Q4, correlate
    from vdo.dic.patch import Patch
    from vdo.dic.series import start_guesses
    from vdo.dic.subsets import correlate_subsets
    from vdo.model.speckle import generate_pattern

    cameras = [replace(c, width=240, height=180, focal_length=2 * c.focal_length) for c in STEREO]
    smooth = ndimage.gaussian_filter(generate_pattern(512, TEXEL, DOT, seed=3).astype(float), 4, mode="wrap")
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min())
    refs = [render(c, smooth) for c in cameras]
    defs = [render(c, smooth, U_TRUE) for c in cameras]
    points, tu, tv = grid(n=2)
    U0 = start_guesses(cameras, refs, defs, points)
    batched = correlate_subsets(cameras, refs, defs, points, tu, tv, SUBSET, U0, order=KEYS)
    assert batched.converged.all() and not batched.one_by_one.any()
    for k, (X, t_u, t_v) in enumerate(zip(points, tu, tv)):
        patch = Patch(origin=X - SUBSET / 2 * (t_u + t_v), t_u=t_u, t_v=t_v, size=(SUBSET, SUBSET))
        one = correlate(cameras, defs, patch, ImageReference(refs), model=Q4(1, 1),
                        U0=np.tile(U0[k], (4, 1)), order=KEYS)
        assert np.abs(batched.U[k] - one.U).max() < SAME_U_M
    U_true = np.tile(U_TRUE, (len(points), 1))
    # Keys' bias on this 2 px-blurred speckle: measured 0.0032 px (the cubic B-spline's 0.0005,
    # tests/dic/test_correlate_subsets.py): within the sharp speckle's tolerance, above the spline's
    keys_px = px_error(cameras, points, batched.centre, U_true)
    cubic = correlate_subsets(cameras, refs, defs, points, tu, tv, SUBSET, U0)
    assert keys_px < SHIFT_TOL_PX
    assert keys_px > 2 * px_error(cameras, points, cubic.centre, U_true)
