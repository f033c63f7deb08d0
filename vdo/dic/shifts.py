"""Whole-pixel image shifts by cross-correlation: where the correlations start.

`image_shifts` takes, around each of K pixel centres, the (2 half + 1)² window of the reference
and of the deformed image, removes each window's mean, tapers both by a Hann window and returns
the shift (du, dv) of the peak of their circular cross-correlation (rfft2 of the deformed window
times the conjugate of the reference's), the whole-pixel image motion at the centre. The
windows are gathered, transformed and searched START_CHUNK at a time (they stay in cache), the
chunks on `workers` threads (SciPy's FFTs release the GIL).

The lowest module of `vdo.dic` with `vdo.dic.images` and `vdo.dic.patch`: it imports nothing of the
package.
"""

from __future__ import annotations

import numpy as np

__all__ = ["START_CHUNK", "image_shifts"]

START_CHUNK = 256    # windows cross-correlated together (their windows stay in cache)


def image_shifts(reference, deformed, centres, half: int = 24, workers: int = 1,
                 subpixel: bool = False) -> np.ndarray:
    """The whole-pixel shifts (K, 2) (du, dv) of the windows (2 half + 1)² around the pixel
    centres `centres` (K, 2) int (u, v), each at least `half` px inside the images (module
    docstring). With `subpixel`, each axis's peak is refined by the parabola through it and its
    two neighbours, δ = (c₋ - c₊) / (2 (c₋ - 2 c₀ + c₊)), clipped to ±½ px (a start within about
    a tenth of a pixel on a well-sampled speckle)."""
    from concurrent.futures import ThreadPoolExecutor

    from scipy import fft

    n = 2 * half + 1
    u, v = (np.asarray(centres, dtype=int).reshape(-1, 2)[:, i] for i in (0, 1))
    taper = np.outer(*(2 * [np.hanning(n)])).astype(np.float32)
    views = [np.lib.stride_tricks.sliding_window_view(np.asarray(img), (n, n))
             for img in (reference, deformed)]
    shifts = np.zeros((len(u), 2))

    def chunk(lo):
        """The shifts of the centres lo .. lo + START_CHUNK."""
        cu, cv = u[lo:lo + START_CHUNK], v[lo:lo + START_CHUNK]
        a, b = (view[cv - half, cu - half].astype(np.float32) for view in views)   # copies (m, n, n)
        for x in (a, b):
            x -= x.mean(axis=(1, 2), keepdims=True)
            x *= taper
        spectrum = fft.rfft2(b) * np.conj(fft.rfft2(a))               # real: half
        c = fft.irfft2(spectrum, s=(n, n))
        peak = np.argmax(c.reshape(len(cu), -1), axis=1)
        i, j = np.divmod(peak, n)
        dv, du = ((k + n // 2) % n - n // 2 for k in (i, j))
        if subpixel:
            m = np.arange(len(cu))
            du = du + _vertex(c[m, i, (j - 1) % n], c[m, i, j], c[m, i, (j + 1) % n])
            dv = dv + _vertex(c[m, (i - 1) % n, j], c[m, i, j], c[m, (i + 1) % n, j])
        shifts[lo:lo + START_CHUNK, 0], shifts[lo:lo + START_CHUNK, 1] = du, dv

    starts = range(0, len(u), START_CHUNK)
    if workers > 1 and len(starts) > 1:
        with ThreadPoolExecutor(min(int(workers), len(starts))) as pool:
            list(pool.map(chunk, starts))
    else:
        for lo in starts:
            chunk(lo)
    return shifts


def _vertex(before, peak, after) -> np.ndarray:
    """The offset of the vertex of the parabola through (-1, before), (0, peak), (1, after),
    clipped to ±½ (0 where the three do not bend down)."""
    bend = before - 2 * peak + after
    safe = np.where(bend < 0, bend, -1.0)
    return np.where(bend < 0, np.clip((before - after) / (2 * safe), -0.5, 0.5), 0.0)
