"""Gray images read between their pixels: the interpolants the correlation samples.

* `SplineImage`: the B-spline interpolant (cubic by default, quintic, or Keys' cubic convolution
  kernel, `vdo.model.spline_response.KEYS`) of a gray image at vdo pixel coordinates x = (u, v) =
  (column, row), pixel centres at integers: the value, its exact gradient (the spline's
  derivative on the (order + 1)² support), and the gradient at every pixel centre at once. The
  coefficients (`scipy.ndimage.spline_filter`, mirror extension) are computed on a window of the
  image (`SplineImage.around` a set of points), equal to the whole image's within
  WINDOW_MARGIN_PX of its inside to |z|^WINDOW_MARGIN_PX (z the spline's pole).
* `WindowedImage`: an image read through the `SplineImage` of the last window, rebuilt around
  the new points when a call leaves it (what `vdo.dic.correlate` reads a 24-megapixel image with).
* `TextureSampler`: a speckle pattern array on a patch's face coordinates ξ (metres), mapped as
  `vdo.render` maps it (bilinear between texel centres, periodic).

With `vdo.dic.patch`, the lowest module of `vdo.dic`: it imports nothing of the package.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from vdo.model.spline_response import KEYS, keys_kernel

__all__ = ["SPLINE_ORDER", "WINDOW_MARGIN_PX", "bspline", "SplineImage", "WindowedImage", "TextureSampler"]


SPLINE_ORDER = 3                # cubic B-splines (an odd order: 3 or 5; or KEYS, Keys' kernel)
WINDOW_MARGIN_PX = 24           # coefficients computed this far beyond the points' support: the
                                # crop's mirror boundary changes them by |z|^24 of the contrast
                                # (z = -0.268 cubic: 2e-14; z = -0.430 quintic: 2e-9)


def bspline(x, order: int, xp=np):
    """The centred cardinal B-spline β_n(x) of degree `order` (support |x| < (n + 1) / 2):
    β_n(x) = Σ_j (-1)^j C(n+1, j) (x + (n+1)/2 - j)_+^n / n!. xp: numpy or jax.numpy."""
    from math import comb, factorial

    n = order
    total = 0.0
    for j in range(n + 2):
        total = total + (-1) ** j * comb(n + 1, j) * xp.maximum(x + (n + 1) / 2 - j, 0.0) ** n
    return total / factorial(n)


class SplineImage:
    """B-spline interpolant (odd `order`, default SPLINE_ORDER: cubic) of a gray image, evaluated
    at vdo pixel coordinates x = (u, v) = (column, row), pixel centres at integers. `order` = KEYS:
    Keys' cubic convolution (`vdo.model.spline_response.keys_kernel`, a = -0.5; OpenCV's INTER_CUBIC is
    the same kernel with a = -0.75): no prefilter, the 4 × 4 taps weigh the samples themselves,
    the gradient from the kernel's derivative.

    The coefficients are computed once, on the whole image or, with `window` = (row0, row1,
    col0, col1), on that crop only (`SplineImage.around` picks it around a set of points): the
    crop's coefficients equal the whole image's within WINDOW_MARGIN_PX of its inside (to |z|^m,
    z the spline's pole) wherever the crop is cut inside the image, and exactly at the image's
    own borders (mirror extension in both). A point outside the window's valid part raises."""

    def __init__(self, image, window=None, order: int = SPLINE_ORDER):
        img = np.asarray(image)
        if img.ndim != 2:
            raise ValueError(f"image: expected a 2-D gray image, got shape {img.shape}")
        if order not in (3, 5, KEYS):
            raise ValueError(f"order: expected an odd spline order 3 or 5, or {KEYS!r}, got {order}")
        self.order = order if order == KEYS else int(order)
        self.image_shape = img.shape
        r0, r1, c0, c1 = window if window is not None else (0, img.shape[0], 0, img.shape[1])
        r0, c0 = max(0, int(r0)), max(0, int(c0))
        r1, c1 = min(img.shape[0], int(r1)), min(img.shape[1], int(c1))
        if r1 - r0 < 2 or c1 - c0 < 2:
            raise ValueError("SplineImage: the window lies outside the image")
        self.origin = np.array([c0, r0], dtype=float)            # (u, v) of the crop's corner
        self.shape = (r1 - r0, c1 - c0)
        # The part of the crop where the coefficients are the whole image's (cut sides lose a margin).
        m = WINDOW_MARGIN_PX
        self._valid = (c0 + (m if c0 > 0 else -1.0), (c1 - 1) - (m if c1 < img.shape[1] else -1.0),
                       r0 + (m if r0 > 0 else -1.0), (r1 - 1) - (m if r1 < img.shape[0] else -1.0))
        crop = np.asarray(img[r0:r1, c0:c1], dtype=np.float64)
        self.coeffs = crop if order == KEYS else ndimage.spline_filter(crop, order=self.order,
                                                                       mode="mirror")
        self._pad = 3 if order == KEYS else self.order
        self._padded = None

    @classmethod
    def around(cls, image, points, margin: float = 0.0, order: int = SPLINE_ORDER) -> "SplineImage":
        """The spline on the crop that covers the pixel points (..., 2) plus `margin` px (for
        later moves) plus WINDOW_MARGIN_PX."""
        x = np.asarray(points, dtype=float).reshape(-1, 2)
        pad = margin + WINDOW_MARGIN_PX + (3 if order == KEYS else order)
        lo, hi = np.floor(x.min(axis=0) - pad), np.ceil(x.max(axis=0) + pad) + 1
        return cls(image, (lo[1], hi[1], lo[0], hi[0]), order)

    @property
    def _cp(self) -> np.ndarray:
        """The coefficients padded by mirroring (the extension `spline_filter(mode="mirror")`
        assumes) so that the support of any point within 1 px outside the image is addressable;
        built on the first gradient asked for (`correlate_subsets` reads only `coeffs`)."""
        if self._padded is None:
            self._padded = np.pad(self.coeffs, self._pad, mode="reflect")
        return self._padded

    @property
    def valid(self) -> tuple:
        """(u0, u1, v0, v1): the part of the image where this (windowed) spline is the whole
        image's (`covers`)."""
        return self._valid

    def covers(self, x) -> bool:
        """Whether every point x (..., 2) lies where this (windowed) spline is the whole image's."""
        x = np.asarray(x, dtype=float).reshape(-1, 2)
        u0, u1, v0, v1 = self._valid
        return bool(np.all((x[:, 0] >= u0) & (x[:, 0] <= u1) & (x[:, 1] >= v0) & (x[:, 1] <= v1)))

    def _local(self, x):
        if not self.covers(x):
            raise ValueError("SplineImage: points outside the spline's window (or more than 1 px "
                             "outside the image)")
        return np.asarray(x, dtype=float) - self.origin

    def __call__(self, x) -> np.ndarray:
        x = self._local(x)
        return self.sample_local(x[..., 1], x[..., 0])

    def sample_local(self, rows, cols) -> np.ndarray:
        """The interpolant at (rows, cols) of the window (the coordinates less `origin`)."""
        if self.order != KEYS:
            return ndimage.map_coordinates(self.coeffs, [rows, cols], order=self.order,
                                           prefilter=False, mode="mirror")
        rows, cols = np.asarray(rows, dtype=float), np.asarray(cols, dtype=float)
        shape = rows.shape
        fu, fv = np.floor(cols.reshape(-1)), np.floor(rows.reshape(-1))
        wu, _ = self._weights(cols.reshape(-1) - fu)
        wv, _ = self._weights(rows.reshape(-1) - fv)
        taps = self._taps() + self._pad
        C = self._cp[(fv.astype(np.int64)[:, None] + taps)[:, :, None],
                     (fu.astype(np.int64)[:, None] + taps)[:, None, :]]
        return np.einsum("nrc,nc,nr->n", C, wu, wv).reshape(shape)

    def _taps(self) -> np.ndarray:
        """The offsets from floor(x) of the coefficients a point weighs: -(order - 1)/2 ..
        (order + 1)/2 (-1 .. 2 for Keys' kernel)."""
        n = 3 if self.order == KEYS else self.order
        return np.arange(-(n - 1) // 2, (n + 1) // 2 + 1)

    def _weights(self, t):
        """B-spline weights of the order + 1 coefficients floor(x) - (order - 1)/2 ..
        floor(x) + (order + 1)/2 and their derivatives (β_n' (x) = β_{n-1}(x + ½) - β_{n-1}(x - ½)),
        for t = x - floor(x); Keys' kernel: k(t - j) and k'(t - j), j = -1 .. 2."""
        d = t[:, None] - self._taps()[None, :]
        if self.order == KEYS:
            return keys_kernel(d), keys_kernel(d, derivative=True)
        w = bspline(d, self.order)
        dw = bspline(d + 0.5, self.order - 1) - bspline(d - 0.5, self.order - 1)
        return w, dw

    def value_and_gradient(self, x):
        """Spline value f (...) and its exact gradient (∂f/∂u, ∂f/∂v) (..., 2) in gray level per
        pixel at x = (u, v) (..., 2); valid up to 1 px outside the image."""
        x = self._local(x)
        shape = x.shape[:-1]
        u = x.reshape(-1, 2)[:, 0]
        v = x.reshape(-1, 2)[:, 1]
        fu, fv = np.floor(u), np.floor(v)
        wu, dwu = self._weights(u - fu)
        wv, dwv = self._weights(v - fv)
        taps = self._taps() + self._pad
        cols = fu.astype(np.int64)[:, None] + taps
        rows = fv.astype(np.int64)[:, None] + taps
        C = self._cp[rows[:, :, None], cols[:, None, :]]          # (N, rows, cols)
        Cu = np.einsum("nrc,nc->nr", C, wu)
        Cdu = np.einsum("nrc,nc->nr", C, dwu)
        f = np.einsum("nr,nr->n", Cu, wv)
        gu = np.einsum("nr,nr->n", Cdu, wv)
        gv = np.einsum("nr,nr->n", Cu, dwv)
        return f.reshape(shape), np.stack([gu, gv], -1).reshape(shape + (2,))

    def gradient(self, x) -> np.ndarray:
        return self.value_and_gradient(x)[1]

    def covers_each(self, u, v, w=1.0) -> np.ndarray:
        """(K,) whether every point (u[k], v[k]) (K, M) of weight w > 0 lies where this (windowed)
        spline is the whole image's (`covers`, subset by subset; points of weight 0 ignored)."""
        u0, u1, v0, v1 = self._valid
        return np.all((u >= u0) & (u <= u1) & (v >= v0) & (v <= v1) | (np.asarray(w) == 0), axis=1)

    def pixel_gradients(self):
        """The gradient (∂f/∂u, ∂f/∂v) at every pixel centre of the window, two images of the
        window's shape: the coefficients correlated with w(0) ⊗ w'(0) (`_weights` at t = 0, whose
        last tap is zero), what `value_and_gradient` sums at integer points."""
        w, dw = (a[0, :-1] for a in self._weights(np.zeros(1)))
        along = lambda C, wu, wv: ndimage.correlate1d(ndimage.correlate1d(C, wu, axis=1), wv, axis=0)
        return along(self.coeffs, dw, w), along(self.coeffs, w, dw)


class WindowedImage:
    """An image read by `SplineImage`s on windows around the points asked for: the spline of
    the last window is kept and rebuilt (around the new points, `margin` px beyond them) only
    when a call leaves it. What `correlate` interpolates, so that a subset or element of a
    24-megapixel image costs a window's spline, not the image's."""

    def __init__(self, image, margin: float = 8.0, order: int = SPLINE_ORDER):
        self.image = np.asarray(image)
        self.margin = float(margin)
        self.order = order if order == KEYS else int(order)
        self.spline: SplineImage | None = None

    def _at(self, x) -> SplineImage:
        if self.spline is None or not self.spline.covers(x):
            self.spline = SplineImage.around(self.image, x, self.margin, self.order)
        return self.spline

    def __call__(self, x) -> np.ndarray:
        return self._at(x)(x)

    def value_and_gradient(self, x):
        return self._at(x).value_and_gradient(x)

    def gradient(self, x) -> np.ndarray:
        return self._at(x).gradient(x)


class TextureSampler:
    """A pattern array on the patch, mapped as `vdo.render` maps it: texel (row i, column j) centred at
    ξ = ((j + ½) h, (i + ½) h), bilinear between texel centres, periodic."""

    def __init__(self, pattern, texel: float):
        self.pattern = np.asarray(pattern, dtype=np.float64)
        if self.pattern.ndim != 2:
            raise ValueError("pattern: expected a 2-D array")
        if not texel > 0:
            raise ValueError("texel: expected > 0")
        self.texel = float(texel)

    def __call__(self, xi) -> np.ndarray:
        xi = np.asarray(xi, dtype=float)
        col = xi[..., 0] / self.texel - 0.5
        row = xi[..., 1] / self.texel - 0.5
        return ndimage.map_coordinates(self.pattern, [row, col], order=1, mode="grid-wrap")

