"""Writing a rendered 16-bit image as PNG (`vdo.model.sensor.save_image`): at vdo's zlib level
(`PNG_COMPRESS_LEVEL`) against PIL's default level 6, in the same run, on a speckle-like image of a
camera's size: a random field smoothed over `BLOB_PX` pixels, spread over 400..3600 DN of 12 bits,
plus Gaussian sensor noise of `NOISE_DN` (what a DIC or calibration render holds). Both files read
back equal to the counts written.
Run: .venv/bin/python benchmarks/image_write.py [--pixels 1500 1000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from vdo.model import sensor

BIT_DEPTH = 12
BLOB_PX = 3.0       # std of the smoothing (px): speckle dots a few pixels across
NOISE_DN = 8.0      # sensor noise (DN rms)


def timed(path: Path, dn: np.ndarray, level: int, repeats: int) -> tuple[float, int]:
    """Median seconds to write `dn` as `path` at zlib `level`, and the file's size (bytes)."""
    saved = sensor.PNG_COMPRESS_LEVEL
    sensor.PNG_COMPRESS_LEVEL = level
    try:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            sensor.save_image(path, dn, BIT_DEPTH)
            times.append(time.perf_counter() - t0)
    finally:
        sensor.PNG_COMPRESS_LEVEL = saved
    back = np.asarray(Image.open(path)).astype(np.int64) >> (16 - BIT_DEPTH)
    assert np.array_equal(back, dn), "the PNG does not read back the counts written"
    return statistics.median(times), path.stat().st_size


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pixels", type=int, nargs=2, default=[1500, 1000])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    w, h = args.pixels
    from scipy.ndimage import gaussian_filter

    field = gaussian_filter(rng.normal(size=(h, w)), BLOB_PX)
    field = (field - field.min()) / (field.max() - field.min())
    dn = 400 + 3200 * field + rng.normal(0, NOISE_DN, (h, w))
    dn = np.clip(dn.round(), 0, 2 ** BIT_DEPTH - 1).astype(np.uint16)
    with tempfile.TemporaryDirectory() as folder:
        rows = [(level, *timed(Path(folder) / f"level{level}.png", dn, level, args.repeats))
                for level in (6, sensor.PNG_COMPRESS_LEVEL)]
    print(f"{w} x {h} px, {BIT_DEPTH}-bit counts in 16-bit PNG, median of {args.repeats}")
    for level, seconds, size in rows:
        label = "(PIL's default)" if level == 6 else "(vdo's)"
        print(f"zlib level {level} {label:<16} {seconds:6.3f} s  {size / 1e6:5.2f} MB")
    print(f"ratio  {rows[0][1] / rows[1][1]:.1f}x faster, {rows[1][2] / rows[0][2]:.2f}x the size")


if __name__ == "__main__":
    main()
