"""Finding the target's inner corners in an image, as a lab's software does (OpenCV).

`cv2.findChessboardCorners` (adaptive threshold, normalised image) on the image scaled to 8 bits,
then `cv2.cornerSubPix` on the float image (window: `SUBPIX_FRACTION` of the smallest corner
spacing, at most `SUBPIX_MAX_HALF` px each side). On vdo's renders this is unbiased (mean error
against the true corners below 0.02 px on noise-free images); `findChessboardCornersSB` was
measured with per-image offsets up to 0.2 px and a 0.2 % stretch, so it is not used.

OpenCV may start its corner order at either end of the board. The board's corner square
(square (0, 0) of `vdo.calib.target`) is black and its neighbour along x white, and rows +
columns is odd, so the board turned by 180 deg starts at a white square: `orient` reads the image
at both squares' centres through the homography of the detected corners and reverses the order
when the first is the brighter.
"""

from __future__ import annotations

import numpy as np

SUBPIX_FRACTION = 0.35    # cornerSubPix half window / smallest corner spacing
SUBPIX_MAX_HALF = 7       # px
SUBPIX_MIN_HALF = 2       # px
SUBPIX_EPS = 1e-4         # px, cornerSubPix's stopping step


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    return ndimage.map_coordinates(image, [uv[:, 1], uv[:, 0]], order=1, mode="nearest")


def orient(corners: np.ndarray, image: np.ndarray, target) -> np.ndarray:
    """`corners` (n, 2) in the target's order (module docstring)."""
    import cv2

    obj = target.points()[:, :2]
    H, _ = cv2.findHomography(obj, corners)
    p = target.pitch
    probe = np.array([[-0.5 * p, -0.5 * p, 1.0], [0.5 * p, -0.5 * p, 1.0]]) @ H.T
    dark, light = _bilinear(image, probe[:, :2] / probe[:, 2:])
    return corners[::-1].copy() if dark > light else corners


def detect(image: np.ndarray, target, max_dn: float) -> np.ndarray | None:
    """The target's inner corners (rows x columns, 2) in pixels, in the target's order, or None
    when the board is not found. `image`: DN (any integer or float array), `max_dn` its top."""
    import cv2

    gray = np.asarray(image, dtype=np.float32) / float(max_dn)
    g8 = np.clip(gray * 255.0, 0, 255).astype(np.uint8)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(g8, target.pattern_size, flags=flags)
    if not ok:
        return None
    c = corners.reshape(target.rows, target.columns, 2)
    spacing = min(np.linalg.norm(np.diff(c, axis=0), axis=-1).min(),
                  np.linalg.norm(np.diff(c, axis=1), axis=-1).min())
    half = int(np.clip(SUBPIX_FRACTION * spacing, SUBPIX_MIN_HALF, SUBPIX_MAX_HALF))
    corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, SUBPIX_EPS))
    return orient(corners.reshape(-1, 2).astype(float), gray, target)


def detect_all(images: dict, target, max_dn: float) -> tuple[list, list]:
    """(observations, missed (camera, pose) keys) of `images` {(camera, pose): DN image}."""
    from vdo.calib.solve import Observation

    found, missed = [], []
    for (name, k), image in sorted(images.items()):
        corners = detect(image, target, max_dn)
        if corners is None:
            missed.append((name, k))
        else:
            found.append(Observation(name, k, corners))
    return found, missed
