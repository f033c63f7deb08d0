"""Keys' cubic convolution in the correlation (`SplineImage(order=KEYS)`): the sampler against
an independent numpy implementation of the kernel (a = -1/2) and, with a = -3/4 (the parameter
OpenCV's INTER_CUBIC uses: its kernel sampled at 1/4, 1/2, 5/4, 3/2 px gives 0.8789, 0.5938,
-0.1055, -0.0938, those of a = -3/4, not of a = -1/2), against `cv2.remap` itself; the gradient
against central differences of the independent sampler."""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from vdo.dic.correlate import SplineImage, WindowedImage
from vdo.model import speckle
from vdo.model.speckle import KEYS

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
    monkeypatch.setattr(speckle, "KEYS_A", -0.75)
    ours = SplineImage(image, order=KEYS)(x)
    theirs = cv2.remap(image.astype(np.float32), x[:, 0].astype(np.float32)[None],
                       x[:, 1].astype(np.float32)[None], cv2.INTER_CUBIC)[0]
    assert np.max(np.abs(ours - theirs)) < OPENCV_TOL
    assert np.max(np.abs(ours - keys_numpy(image, x[:, 0], x[:, 1], a=-0.75))) < NUMPY_TOL
    # and vdo's default a = -1/2 is not OpenCV's kernel
    monkeypatch.undo()
    assert np.max(np.abs(SplineImage(image, order=KEYS)(x) - theirs)) > 10 * OPENCV_TOL
