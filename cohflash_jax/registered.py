"""Resampling CCDs 2–4 onto CCD 1's pixel grid while streaming row tiles (registration).

Each CCD k ≥ 2 has a map (map_x, map_y): for every CCD 1 pixel, the CCD k pixel coordinates
(OpenCV convention: pixel centres at integers) that see the same scene point. For a tile of
CCD 1 rows, only a band of CCD k rows is needed (the tile ± the maps' largest row offset), so
memory stays bounded; the band is resampled bilinearly for all frames at once."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .status import Status

# Bilinear resampling reads a pixel's row and the next: a band needs this many rows beyond the
# maps' largest row offset
BAND_MARGIN_ROWS = 2
# A map this close outside the image still samples its edge pixel: projection's rounding puts an
# edge column's map at −1e-7 px, which must not flag the whole column outside the registration
EDGE_TOLERANCE_PX = 1e-3


def inside_image(map_x, map_y, width: int, height: int) -> np.ndarray:
    """Where a map lands inside a width × height image (pixel centres at integers), to
    `EDGE_TOLERANCE_PX`: the pixels another CCD sees."""
    tol = EDGE_TOLERANCE_PX
    return (map_x >= -tol) & (map_x <= width - 1 + tol) & (map_y >= -tol) & (map_y <= height - 1 + tol)


@jax.jit
def _bilinear(band, index, weight):
    """band (N, B·W), index/weight (P, 4) → (N, P) float32."""
    x = band.astype(jnp.float32)
    return sum(weight[:, j] * jnp.take(x, index[:, j], axis=1) for j in range(4))


class RegisteredTiles:
    """Reads row tiles of a capture with CCDs 2–4 resampled onto CCD 1's grid."""

    def __init__(self, capture, maps, rows: int):
        n, h, w = capture.shape
        self.capture, self.rows, self.h, self.w, self.n = capture, rows, h, w, n
        if len(maps) != 3:
            raise ValueError("registration needs maps for CCDs 2, 3 and 4")
        for mx, my in maps:
            if mx.shape != (h, w) or my.shape != (h, w):
                raise ValueError(f"registration maps are {mx.shape[1]}×{mx.shape[0]} px but the capture is {w}×{h}")
        self.maps = [(np.asarray(mx, np.float64), np.asarray(my, np.float64)) for mx, my in maps]
        rows_idx = np.arange(h)[:, None]
        self.margin = int(math.ceil(max(np.max(np.abs(my - rows_idx)) for _, my in self.maps))) + BAND_MARGIN_ROWS
        self.band = rows + 2 * self.margin
        sat = capture.saturation_dn
        self.saturation = None if sat is None else float(sat)

    def _plan(self, k, r0):
        """Band start row and bilinear (index, weight, outside) for CCD k's tile at r0."""
        mx, my = self.maps[k]
        r1 = min(self.h, r0 + self.rows)
        x = np.zeros((self.rows, self.w))
        y = np.zeros((self.rows, self.w))
        x[: r1 - r0], y[: r1 - r0] = mx[r0:r1], my[r0:r1]
        start = r0 - self.margin
        outside = ~inside_image(x, y, self.w, self.h)
        x, y = np.clip(x, 0, self.w - 1), np.clip(y, 0, self.h - 1)
        x0 = np.minimum(np.floor(x), self.w - 2).astype(np.int64)
        y0 = np.minimum(np.floor(y), self.h - 2).astype(np.int64)
        fx, fy = x - x0, y - y0
        by = y0 - start
        idx = np.stack(
            [by * self.w + x0, by * self.w + x0 + 1, (by + 1) * self.w + x0, (by + 1) * self.w + x0 + 1], axis=-1
        ).reshape(-1, 4)
        wts = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=-1).reshape(-1, 4)
        return start, idx.astype(np.int32), wts.astype(np.float32), outside.ravel()

    def _band(self, k, start):
        lo, hi = max(0, start), min(self.h, start + self.band)
        block = self.capture.frames[k, :, lo:hi, :]
        out = np.zeros((self.n, self.band, self.w), block.dtype)
        out[:, lo - start : hi - start] = block
        return out.reshape(self.n, -1)

    def tile(self, r0):
        """(r1, frames (4, N, P) float32, status (P,) int8)."""
        r1 = min(self.h, r0 + self.rows)
        first = self.capture.frames[0, :, r0:r1, :]
        if r1 - r0 < self.rows:
            first = np.concatenate([first, np.zeros((self.n, self.rows - (r1 - r0), self.w), first.dtype)], axis=1)
        ccds = [jnp.asarray(first.reshape(self.n, -1)).astype(jnp.float32)]
        status = np.zeros(self.rows * self.w, np.int8)
        for k in range(3):
            start, idx, wts, outside = self._plan(k, r0)
            band = self._band(k + 1, start)
            if self.saturation is not None:  # saturation is judged on the source pixels
                sat_src = np.any(band >= self.saturation, axis=0)
                status[np.any(sat_src[idx] & (wts > 0), axis=1)] = Status.SATURATED
            ccds.append(_bilinear(jnp.asarray(band), jnp.asarray(idx), jnp.asarray(wts)))
            status[outside] = Status.OUTSIDE_REGISTRATION
        return r1, jnp.stack(ccds), jnp.asarray(status)


def register_pixel_map(per_ccd: np.ndarray, maps) -> np.ndarray:
    """A per-CCD pixel map (4, H, W) — dark frame, offset or gain map — with CCDs 2–4
    resampled onto CCD 1's grid (bilinear)."""
    import cv2

    out = per_ccd.astype(np.float32).copy()
    for k, (mx, my) in enumerate(maps, start=1):
        out[k] = cv2.remap(
            out[k], mx.astype(np.float32), my.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
    return out
