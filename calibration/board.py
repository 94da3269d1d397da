"""Chessboard geometry: inner-corner grid, object points and texture."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Board:
    """A chessboard with `cols`×`rows` inner corners and squares of `square_mm`.

    Object points lie on z = 0 with the first inner corner at the origin, x along columns."""

    cols: int
    rows: int
    square_mm: float

    def __post_init__(self):
        if self.cols < 3 or self.rows < 3:
            raise ValueError(f"a board needs at least 3×3 inner corners, got {self.cols}x{self.rows}")
        if not self.square_mm > 0:
            raise ValueError(f"square size must be positive, got {self.square_mm} mm")

    @classmethod
    def parse(cls, text: str, square_mm: float) -> "Board":
        try:
            cols, rows = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise ValueError(f"board must look like COLSxROWS (inner corners, e.g. 9x6), got {text!r}") from None
        return cls(cols, rows, float(square_mm))

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    def object_points(self) -> np.ndarray:
        """(cols·rows, 3) float32, row-major as OpenCV orders detected corners."""
        j, i = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square_mm
        return pts.astype(np.float32)

    def shade(self, x_mm, y_mm, black: float, white: float, background: float) -> np.ndarray:
        """Texture at board coordinates: squares, a one-square white border, then background.

        Looked up by square index in a small table of the board's shades (one gather instead
        of a chain of comparisons over every sample: the synthetic views render 2–3× faster);
        a non-finite coordinate (a ray parallel to the board) gets the background."""
        s = self.square_mm
        # square indices −2 … cols (rows) are the border and squares; −3 and cols + 1 stand for beyond
        col = np.fmin(np.fmax(np.floor(np.asarray(x_mm) / s), -3), self.cols + 1).astype(np.intp) + 3
        row = np.fmin(np.fmax(np.floor(np.asarray(y_mm) / s), -3), self.rows + 1).astype(np.intp) + 3
        return self.shade_table(black, white, background)[row, col]

    def shade_table(self, black: float, white: float, background: float) -> np.ndarray:
        """The shade of every square index (row + 3, column + 3): −1 … cols − 1 (rows − 1) the
        squares, −2 and cols (rows) the white border, −3 and cols + 1 the background."""
        ix = np.arange(-3, self.cols + 2)[None, :]
        iy = np.arange(-3, self.rows + 2)[:, None]
        inside = (ix >= -1) & (ix <= self.cols - 1) & (iy >= -1) & (iy <= self.rows - 1)
        border = (ix >= -2) & (ix <= self.cols) & (iy >= -2) & (iy <= self.rows)
        squares = np.where((ix + iy) % 2 == 0, black, white)
        return np.where(inside, squares, np.where(border, white, background)).astype(np.float64)
