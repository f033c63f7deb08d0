"""The calibration target: its points in its own frame, its printed image and its description.

Frame of the target (OpenCV's object points): the first inner corner at the origin, x along
a row of `columns` points, y along a column of `rows` points, z = 0 on the target, all spaced by
the pitch p. The printed checkerboard has (columns + 1) x (rows + 1) squares, the square that
holds the origin's upper-left neighbour black ((i + j) even is black for square (i, j), i along
x), inside a white margin of one square. The front face (printed side) looks along -z (the camera that
sees the print looks along +z of the target frame, as OpenCV's calibration assumes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TEXELS_PER_PITCH = 32     # texels per square of the printed image (nearest-texel lookup)
MARGIN_PITCHES = 1        # white border around the printed pattern, in pitches (quiet zone)
WHITE_ALBEDO = 0.8        # matte white paper / ceramic print
BLACK_ALBEDO = 0.05       # matte black print


@dataclass(frozen=True)
class Target:
    """A planar target: `kind` ("checkerboard"), `rows` x `columns` inner corners, `pitch` (m)."""

    kind: str
    rows: int
    columns: int
    pitch: float

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(columns, rows): OpenCV's patternSize."""
        return self.columns, self.rows

    @property
    def count(self) -> int:
        return self.rows * self.columns

    def points(self) -> np.ndarray:
        """(rows x columns, 3) points in the target frame, row by row (OpenCV's order: x fastest)."""
        j, i = np.mgrid[0:self.rows, 0:self.columns]
        return np.stack([i.ravel() * self.pitch, j.ravel() * self.pitch,
                         np.zeros(self.count)], axis=-1)

    @property
    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) corners (x, y) in metres of the printed sheet in the target frame: the
        pattern (one square beyond the outer corners) plus `MARGIN_PITCHES`."""
        beyond = 1.0 + MARGIN_PITCHES
        low = -beyond * self.pitch * np.ones(2)
        high = np.array([(self.columns - 1), (self.rows - 1)]) * self.pitch + beyond * self.pitch
        return low, high

    @property
    def centre(self) -> np.ndarray:
        """The pattern's centre in the target frame, (3,)."""
        return np.array([(self.columns - 1) / 2, (self.rows - 1) / 2, 0.0]) * self.pitch

    @property
    def size(self) -> tuple[float, float]:
        low, high = self.extent
        return float(high[0] - low[0]), float(high[1] - low[1])

    def albedo_image(self) -> np.ndarray:
        """The printed sheet as an albedo image (H, W) float32, row 0 at the sheet's lowest y
        (the texture's v = 0), `TEXELS_PER_PITCH` texels per pitch; texel (r, c) covers
        x in low_x + [c, c + 1) t, y in low_y + [r, r + 1) t, t = pitch / TEXELS_PER_PITCH."""
        low, high = self.extent
        n = TEXELS_PER_PITCH
        width, height = (int(round((high[k] - low[k]) / self.pitch * n)) for k in (0, 1))
        x = low[0] / self.pitch + (np.arange(width) + 0.5) / n          # in pitches
        y = low[1] / self.pitch + (np.arange(height) + 0.5) / n
        X, Y = np.meshgrid(x, y)
        inside = (X > -1) & (X < self.columns) & (Y > -1) & (Y < self.rows)
        i, j = np.floor(X).astype(int) + 1, np.floor(Y).astype(int) + 1
        black = inside & ((i + j) % 2 == 0)
        return np.where(black, BLACK_ALBEDO, WHITE_ALBEDO).astype(np.float32)

    def description(self) -> dict:
        """The target as a lab's software reads it (written as target.yml by `vdo calibrate`)."""
        return {"kind": self.kind, "rows": self.rows, "columns": self.columns,
                "pitch_mm": self.pitch * 1e3}


def description_yaml(target: Target) -> str:
    """target.yml in OpenCV FileStorage YAML (`cv2.FileStorage(path, cv2.FILE_STORAGE_READ)`):
    board_width = columns and board_height = rows (inner corners, OpenCV's patternSize),
    square_size in mm, pattern "CHESSBOARD" (the name OpenCV's calibration sample uses)."""
    return ("%YAML:1.0\n---\n"
            f"board_width: {target.columns}\nboard_height: {target.rows}\n"
            f"square_size: {target.pitch * 1e3:.17g}\nunits: \"mm\"\npattern: \"CHESSBOARD\"\n")
