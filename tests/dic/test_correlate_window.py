"""Correlation at full size: B-spline interpolation on windows (`SplineImage.around`,
`WindowedImage`) against the whole image's spline and scipy's own B-splines (orders 3 and 5);
subset correlation of many points, batched and one `correlate` per point in spawned processes,
against the whole-image implementation and the imposed shift on images rendered independently (tests/dic/test_correlate)."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_correlate  # noqa: E402
from test_correlate import STEREO, U_TRUE, render  # noqa: E402

pattern = test_correlate.pattern        # the module's fixture, shared

from vdo.dic import images as images_module  # noqa: E402
from vdo.dic.images import SplineImage, WindowedImage  # noqa: E402
from vdo.dic.series import correlate_points  # noqa: E402

WINDOW_TOL = 1e-9            # gray levels: windowed against whole-image coefficients (|z|^24)
SCIPY_TOL = 1e-9             # against scipy.ndimage.map_coordinates of the same order
FD_STEP = 1e-4               # px, central differences of scipy's spline for the gradient
FD_TOL = 1e-5                # gray level per px: their truncation and rounding error
SAME_U_TOL = 1e-12           # m: windowed against whole-image correlation (same arithmetic)
SHIFT_TOL_PX = 0.02          # recovered against imposed, noise-free box-pixel images


@pytest.mark.parametrize("order", [3, 5])
def test_windowed_spline_is_the_whole_images_spline(order):
    rng = np.random.default_rng(1)
    image = ndimage.gaussian_filter(rng.random((300, 400)), 1.5) * 1000
    x = np.column_stack([rng.uniform(120, 180, 50), rng.uniform(100, 140, 50)])
    whole = SplineImage(image, order=order)
    window = SplineImage.around(image, x, order=order)
    assert window.shape[0] < 150 and window.shape[1] < 150
    f_w, g_w = window.value_and_gradient(x)
    f, g = whole.value_and_gradient(x)
    assert np.max(np.abs(f_w - f)) < WINDOW_TOL and np.max(np.abs(g_w - g)) < WINDOW_TOL
    ref = ndimage.map_coordinates(image, [x[:, 1], x[:, 0]], order=order, mode="mirror")
    assert np.max(np.abs(f - ref)) < SCIPY_TOL * 1000
    for k, step in enumerate(np.eye(2) * FD_STEP):
        hi, lo = ((x + s)[:, ::-1].T for s in (step, -step))
        fd = (ndimage.map_coordinates(image, hi, order=order, mode="mirror")
              - ndimage.map_coordinates(image, lo, order=order, mode="mirror")) / (2 * FD_STEP)
        assert np.max(np.abs(g[:, k] - fd)) < FD_TOL * 1000
    # At the image's own border the window is exact too; beyond its window it refuses.
    corner = np.array([[0.3, 0.2], [5.0, 3.0]])
    assert np.allclose(SplineImage.around(image, corner, order=order)(corner), whole(corner), atol=WINDOW_TOL)
    with pytest.raises(ValueError, match="window"):
        window(np.array([[10.0, 10.0]]))
    lazy = WindowedImage(image, order=order)
    assert np.allclose(lazy(x), f, atol=WINDOW_TOL) and np.allclose(lazy(corner), whole(corner), atol=WINDOW_TOL)


@pytest.fixture(scope="module")
def stereo_pair(pattern):
    cams = [replace(c, width=400, height=300, focal_length=2 * c.focal_length) for c in STEREO]
    return cams, [render(c, pattern) for c in cams], [render(c, pattern, U_TRUE) for c in cams]


def test_subset_points_recover_the_shift_serial_pooled_and_as_today(stereo_pair, monkeypatch):
    cams, refs, defs = stereo_pair
    xs = np.linspace(-3e-3, 3e-3, 3)
    points = np.array([[x, y, 0.0] for x in xs for y in xs[:2]])
    tu, tv = np.tile([1.0, 0, 0], (len(points), 1)), np.tile([0, 1.0, 0], (len(points), 1))
    size = 2.4e-3                                       # ~30 px subsets
    U, ok = correlate_points(cams, refs, defs, points, tu, tv, size)
    assert ok.all()
    px = [np.abs(np.einsum("nij,nj->ni", c.sensitivity(points), U - U_TRUE)).max() for c in cams]
    assert max(px) < SHIFT_TOL_PX
    pooled, ok2 = correlate_points(cams, refs, defs, points, tu, tv, size, workers=2, batched=False)
    assert ok2.all() and np.max(np.abs(pooled - U)) < SAME_U_TOL
    monkeypatch.setattr(images_module, "WINDOW_MARGIN_PX", 10 ** 6)     # the whole image: today's
    whole, _ = correlate_points(cams, refs, defs, points, tu, tv, size)
    assert np.max(np.abs(whole - U)) < 1e-9 * np.abs(U_TRUE).max() + SAME_U_TOL
