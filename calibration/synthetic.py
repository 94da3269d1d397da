"""Synthetic chessboard captures of four virtual CCDs with known intrinsics, distortion and
poses — ground truth for the registration tests and studies.

Each image is rendered by inverse mapping: every output pixel (distorted) is undistorted to a
ray of its camera, intersected with the board plane and shaded by the board's texture, with
2×2 supersampling, optical blur and sensor noise, in 8 or 16 bits.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from .board import Board


@dataclasses.dataclass(frozen=True)
class VirtualCamera:
    """Pinhole camera with OpenCV distortion. (R, T) map CCD 1's frame to this camera's:
    X_k = R·X_1 + T (mm), as `cv2.stereoCalibrate` reports them."""

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    R: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))
    T: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    image_size: tuple[int, int] = (640, 512)  # (width, height)


def rotation(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    r, _ = cv2.Rodrigues(np.deg2rad(np.array([rx_deg, ry_deg, rz_deg], np.float64)))
    return r


def default_rig(image_size=(640, 512)) -> list[VirtualCamera]:
    """Four CCDs behind a hybrid: nearly coaxial, each misaligned by a fraction of a degree
    and a few millimetres, with individual focal lengths, principal points and distortion."""
    w, h = image_size
    cams = []
    specs = [
        (1.292, 0.500, 0.500, (-0.20, 0.08, 0, 0, 0), (0, 0, 0), (0, 0, 0)),
        (1.304, 0.510, 0.490, (-0.18, 0.05, 0, 0, 0), (0.4, -0.3, 0.6), (3.0, -2.0, 1.5)),
        (1.281, 0.495, 0.508, (-0.22, 0.10, 0, 0, 0), (-0.5, 0.2, -0.4), (-2.5, 1.5, -1.0)),
        (1.315, 0.505, 0.497, (-0.16, 0.04, 0, 0, 0), (0.3, 0.5, 0.3), (1.5, 2.5, 2.0)),
    ]
    for f, cx, cy, dist, rot_deg, t_mm in specs:
        k = np.array([[f * w, 0, cx * w], [0, f * w * 1.001, cy * h], [0, 0, 1]], np.float64)
        cams.append(
            VirtualCamera(k, np.array(dist, np.float64), rotation(*rot_deg), np.array(t_mm, np.float64), image_size)
        )
    return cams


def undistort_exact(pixels: np.ndarray, camera_matrix, dist_coeffs) -> np.ndarray:
    """Normalised image coordinates of distorted pixels, iterated to 1e-12 (OpenCV's default of
    five iterations leaves errors of ~0.1 px near the corners at k1 = −0.2)."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    return cv2.undistortPoints(pixels, camera_matrix, dist_coeffs, criteria=crit).reshape(-1, 2)


def board_poses(count: int, rng: np.random.Generator, board: Board, distance_mm: float = 450.0):
    """Board poses in CCD 1's frame: centred on the view within ±40 mm, tilted up to ±40°
    about x and y and ±20° about z, at 0.85–1.2× `distance_mm`."""
    centre = np.array([(board.cols - 1) * board.square_mm / 2, (board.rows - 1) * board.square_mm / 2, 0.0])
    poses = []
    for _ in range(count):
        r = rotation(rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(-20, 20))
        t = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), distance_mm * rng.uniform(0.85, 1.2)]) - r @ centre
        poses.append((r, t))
    return poses


def camera_rays(cam: VirtualCamera, supersample: int = 2) -> np.ndarray:
    """Unit-depth rays (S, 3, H·W) of every output pixel's sub-samples (pose-independent): a
    component of all the rays contiguous, as `render_view` reads them."""
    w, h = cam.image_size
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    rays = []
    for oy in offs:
        for ox in offs:
            v, u = np.meshgrid(np.arange(h) + oy, np.arange(w) + ox, indexing="ij")
            pts = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)[:, None, :]
            norm = undistort_exact(pts, cam.camera_matrix, cam.dist_coeffs)
            rays.append(np.concatenate([norm, np.ones((norm.shape[0], 1))], axis=1))
    return np.ascontiguousarray(np.stack(rays).transpose(0, 2, 1))


def render_view(
    cam: VirtualCamera,
    board: Board,
    board_R: np.ndarray,
    board_t: np.ndarray,
    *,
    rng: np.random.Generator,
    blur_px: float = 0.7,
    noise: float = 0.01,
    bit_depth: int = 8,
    black: float = 0.1,
    white: float = 0.9,
    background: float = 0.45,
    rays: np.ndarray | None = None,
    offset: float = 0.0,
) -> np.ndarray:
    """One image of the board at pose (board_R, board_t) in CCD 1's frame, seen by `cam`.

    `black`, `white`, `background` and `noise` are fractions of full scale; `offset` adds a
    pedestal (low-contrast 16-bit frames: e.g. black 0.02, white 0.06)."""
    w, h = cam.image_size
    rays = camera_rays(cam) if rays is None else rays
    rb, tb = cam.R @ board_R, cam.R @ board_t + cam.T  # board pose in this camera's frame
    normal, origin = rb[:, 2], tb
    acc = np.zeros(h * w)
    for r in rays:
        s = (origin @ normal) / (normal @ r)
        # board coordinates x, y (mm) of the ray's point on the board (z ≈ 0), column by column
        p = [r[j] * s - origin[j] for j in range(3)]
        x, y = (p[0] * rb[0, k] + p[1] * rb[1, k] + p[2] * rb[2, k] for k in range(2))
        acc += board.shade(x, y, black, white, background) * (s > 0)
    img = acc.reshape(h, w) / rays.shape[0] + offset
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img = img + noise * rng.standard_normal(img.shape)
    top = 255 if bit_depth == 8 else 65535
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    return np.clip(np.round(img * top), 0, top).astype(dtype)


def write_rig_views(
    folder: Path, cams: list[VirtualCamera], board: Board, poses, *, rng, bit_depth=8, **render_kw
) -> list[Path]:
    """Render every pose for every camera into folder/ccd{k}/view_{i:03d}.png; returns the folders."""
    dirs = []
    for k, cam in enumerate(cams, start=1):
        d = Path(folder) / f"ccd{k}"
        d.mkdir(parents=True, exist_ok=True)
        rays = camera_rays(cam)
        for i, (r, t) in enumerate(poses):
            img = render_view(cam, board, r, t, rng=rng, bit_depth=bit_depth, rays=rays, **render_kw)
            if not cv2.imwrite(str(d / f"view_{i:03d}.png"), img):
                raise OSError(f"could not write {d / f'view_{i:03d}.png'}")
        dirs.append(d)
    return dirs
