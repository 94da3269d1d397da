"""Chessboard views of four CCDs: files paired by name, images read (corrupt files named),
corners detected and labelled by the board's own geometry.

Why labelling matters: the stereo solve pairs corner *k* of CCD 1 with corner *k* of CCD *j*.
OpenCV's detectors order corners by image direction, so a CCD mounted at 180°, or one behind
an odd number of mirrors (normal in a free-space hybrid), gets its corners in another physical
order than CCD 1's, and the solve returns a confident wrong pose. Here the order comes from
the board: of the grid's symmetries (180° turn, two mirrors, and the quarter turns of a
square grid), the label kept is the one that (1) is right-handed in the image, as the front
of a board always is to a camera that is not mirrored, and (2) puts a dark square between
corners (0, 0) and (1, 1). For a board with one odd and one even count of inner corners
(9×6, OpenCV's advice) this fixes every corner; on other boards a 180° turn is left open
(`Detection.alternatives`) and is settled against CCD 1 in the solve. A mirrored CCD is
handled as a normal camera looking at the image flipped left–right (`Orientation`)."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import cv2
import numpy as np

from cohflash_jax.fileio import read_gray_image

from .board import Board

IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".bmp", ".pgm", ".jpg", ".jpeg"}


class RegistrationError(ValueError):
    """Registration input is unusable; the message names the file or folder and the remedy."""


# -- files ------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ViewFiles:
    """Each CCD's images keyed by view name (the file name without suffix), and the views
    some folders lack (skipped in those CCDs, named in the report)."""

    files: list[dict[str, Path]]
    missing: dict[str, list[int]]  # view → CCDs (1-based) whose folder lacks it

    @property
    def names(self) -> list[str]:
        return sorted(set().union(*self.files))


def list_views(folders) -> ViewFiles:
    """Images of each CCD folder, paired by identical file name (without suffix)."""
    files = []
    for d in map(Path, folders):
        if not d.is_dir():
            what = "is a file, not a folder of images" if d.exists() else "not found"
            raise RegistrationError(f"image folder {d}: {what}")
        found = {}
        for p in sorted(d.iterdir()):
            if p.suffix.lower() in IMAGE_SUFFIXES:
                if p.stem in found:
                    raise RegistrationError(f"{d}: two images of view {p.stem!r} ({found[p.stem].name}, {p.name})")
                found[p.stem] = p
        if not found:
            raise RegistrationError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in {d}")
        files.append(found)
    same_as_earlier(folders, files)
    names = sorted(set().union(*files))
    missing = {n: [k + 1 for k, f in enumerate(files) if n not in f] for n in names}
    return ViewFiles(files, {n: ks for n, ks in missing.items() if ks})


def same_as_earlier(folders, files: list[dict[str, Path]]) -> None:
    """RegistrationError where two CCDs' folders are one folder, or hold byte-identical images
    (four copies of CCD 1's folder registered as 0.000° apart, with no warning)."""
    seen = {}
    for k, (folder, found) in enumerate(zip(folders, files)):
        key = (Path(folder).resolve(),)
        if key in seen:
            raise RegistrationError(f"CCD {k + 1}'s folder {folder} is CCD {seen[key] + 1}'s: give each CCD its own")
        seen[key] = k
        content = tuple(hashlib.sha256(p.read_bytes()).hexdigest() for p in found.values())
        if content in seen:
            raise RegistrationError(
                f"CCD {k + 1}'s images in {folder} are byte-identical to CCD {seen[content] + 1}'s: "
                "the same views copied twice? Each CCD must photograph the board itself"
            )
        seen[content] = k


def truncated(path: Path) -> bool:
    """True where a JPEG lacks its end-of-image marker or a PNG its IEND chunk: decoders fill a
    cut-off file with grey and only warn, and the view would then read as 'board not found'."""
    data = path.read_bytes()
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        return not data.rstrip(b"\x00\r\n ").endswith(b"\xff\xd9")
    if suffix == ".png":
        return b"IEND" not in data[-32:]
    return False


def read_image(path: Path) -> np.ndarray:
    """A view as an 8- or 16-bit grey image; RegistrationError naming a corrupt or unreadable file."""
    path = Path(path)
    if truncated(path):
        raise RegistrationError(f"{path}: corrupt image (the file is cut short); copy it again or remove the view")
    img = read_gray_image(path)
    if img is None:
        raise RegistrationError(f"{path}: corrupt or unreadable image (OpenCV cannot decode it)")
    if img.dtype not in (np.uint8, np.uint16):
        raise RegistrationError(f"{path}: unsupported pixel type {img.dtype} (8- or 16-bit expected)")
    return img


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Contrast-stretch (0.5–99.5 percentile) to 8 bits: low-contrast 16-bit SWIR frames too."""
    if img.dtype == np.uint8:
        return img
    lo, hi = np.percentile(img, [0.5, 99.5])
    scaled = (img.astype(np.float64) - lo) / max(hi - lo, 1.0)
    return np.clip(np.round(255 * scaled), 0, 255).astype(np.uint8)


# -- corners ----------------------------------------------------------------------------------
def find_corners(img8: np.ndarray, board: Board, refine_on: np.ndarray | None = None) -> np.ndarray | None:
    """Inner corners (N, 2) float32 with sub-pixel accuracy in the detector's order, or None.

    The classic detector refined by `cornerSubPix` comes first: on our synthetic boards it is
    unbiased (focal length within 0.03 %), while the sector-based `findChessboardCornersSB`
    biased the focal length by 0.3–0.8 %. SB, more robust on hard images, is the fallback.
    `refine_on` (float32, e.g. the 16-bit original) is used for the sub-pixel step so that the
    8-bit stretch used for detection does not quantise the corners."""
    ok, corners = cv2.findChessboardCorners(
        img8, board.pattern_size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    )
    if ok:
        src = img8 if refine_on is None else refine_on
        corners = cv2.cornerSubPix(
            src,
            np.asarray(corners, np.float32).reshape(-1, 1, 2),
            (5, 5),
            (-1, -1),
            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4),
        )
    else:
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        ok, corners = cv2.findChessboardCornersSB(img8, board.pattern_size, flags=flags)
        if not ok:
            return None
    corners = np.asarray(corners, np.float32).reshape(-1, 2)
    return corners if corners.shape[0] == board.cols * board.rows else None


def larger_board_size(img8: np.ndarray, board: Board) -> tuple[int, int] | None:
    """The inner-corner count (cols, rows) of a chessboard in the view with more corners than
    `board`, in `board`'s orientation (its longer side first where `board`'s is), or None.

    `findChessboardCornersSB` allowed a larger pattern than asked for (`CALIB_CB_LARGER`) finds
    the whole board and says its size: where `--board` names part of the board, one view
    (~0.1–0.3 s) tells the true size, where failed searches with the wrong size took every view."""
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_LARGER
    ok, _, meta = cv2.findChessboardCornersSBWithMeta(img8, board.pattern_size, flags)
    if not ok or meta is None or meta.size <= board.cols * board.rows:
        return None
    small, large = sorted(meta.shape[:2])
    return (large, small) if board.cols >= board.rows else (small, large)


def grid_symmetries(board: Board) -> list:
    """Relabellings of a rows×cols corner grid (as index arrays into the flat corner list) that
    map the grid onto itself: identity, 180° turn, two mirrors; and on a square grid the
    transposes as well (quarter turns and diagonal mirrors)."""
    idx = np.arange(board.rows * board.cols).reshape(board.rows, board.cols)
    out = [idx, idx[::-1, ::-1], idx[:, ::-1], idx[::-1, :]]
    if board.rows == board.cols:
        out += [g.T for g in list(out)]
    return [g.ravel() for g in out]


def signed_area(corners: np.ndarray, board: Board) -> float:
    """Signed area (px²) of the grid's outline in label order (0,0)→(cols−1,0)→(cols−1,rows−1)
    →(0,rows−1); positive where the labels run right-handed in the image (u right, v down)."""
    g = corners.reshape(board.rows, board.cols, 2)
    p = np.array([g[0, 0], g[0, -1], g[-1, -1], g[-1, 0]], np.float64)
    x, y = p[:, 0], p[:, 1]
    return float(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def square_contrast(img8: np.ndarray, corners: np.ndarray, board: Board) -> float:
    """Mean over the inner squares of (−1)^(i+j) × the grey level at square (i, j)'s centre:
    negative where the square between corners (0, 0) and (1, 1) is dark."""
    g = corners.reshape(board.rows, board.cols, 2).astype(np.float64)
    centre = (g[:-1, :-1] + g[1:, 1:] + g[:-1, 1:] + g[1:, :-1]) / 4
    grey = cv2.remap(
        img8.astype(np.float32),
        centre[..., 0].astype(np.float32),
        centre[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
    )
    sign = (-1.0) ** (np.arange(board.rows - 1)[:, None] + np.arange(board.cols - 1)[None, :])
    return float(np.mean(grey * sign))


@dataclasses.dataclass(frozen=True)
class Detection:
    """One view's corners in the board's labelling (N, 2) float64, in the pixel frame of the
    CCD's `Orientation` (flipped left–right for a mirrored CCD). `alternatives` holds the other
    labellings the board's pattern cannot tell apart (a 180° turn on boards whose two corner
    counts are both odd or both even); empty for a 9×6 board."""

    corners: np.ndarray
    alternatives: tuple = ()


def label_by_board(img8: np.ndarray, corners: np.ndarray, board: Board) -> Detection:
    """The detector's corners relabelled by the board's geometry (see the module docstring)."""
    candidates = [corners[g] for g in grid_symmetries(board)]
    kept = [c for c in candidates if signed_area(c, board) > 0]
    contrast = [square_contrast(img8, c, board) for c in kept]
    dark_first = [c for c, s in zip(kept, contrast) if s < 0]
    kept = dark_first or kept
    return Detection(kept[0].astype(np.float64), tuple(c.astype(np.float64) for c in kept[1:]))


def board_continues(img8: np.ndarray, corners: np.ndarray, board: Board) -> str | None:
    """Which side of the detected grid the chessboard pattern goes on past the board's outer
    squares, or None. A board with exactly `board`'s corners has one row of squares beyond the
    outer corners and then its plain border; where squares still alternate two rows out, the
    grid found is part of a bigger board (a wrong `--board`). Each side is extrapolated with a
    homography fitted to its three nearest corner lines only, so lens distortion does not carry
    the samples off the squares."""
    g = corners.reshape(board.rows, board.cols, 2).astype(np.float64)
    jj, ii = np.meshgrid(np.arange(board.rows), np.arange(board.cols), indexing="ij")
    grid = np.stack([ii, jj], -1).astype(np.float64)  # board (x, y) of each corner
    h, w = img8.shape
    last_x, last_y = board.cols - 1, board.rows - 1
    # side → (corner lines used, sample points d squares beyond the edge line)
    sides = {
        "first column": (np.s_[:, :3], lambda d: [(-d, j + 0.5) for j in range(board.rows - 1)]),
        "last column": (np.s_[:, -3:], lambda d: [(last_x + d, j + 0.5) for j in range(board.rows - 1)]),
        "first row": (np.s_[:3, :], lambda d: [(i + 0.5, -d) for i in range(board.cols - 1)]),
        "last row": (np.s_[-3:, :], lambda d: [(i + 0.5, last_y + d) for i in range(board.cols - 1)]),
    }

    def samples(pts, hom):
        img_pts = cv2.perspectiveTransform(np.array(pts, np.float64)[None], hom)[0]
        if np.any(img_pts < 1) or np.any(img_pts[:, 0] > w - 2) or np.any(img_pts[:, 1] > h - 2):
            return None  # off the image: nothing to tell
        return cv2.remap(
            img8.astype(np.float32),
            img_pts[:, 0:1].astype(np.float32),
            img_pts[:, 1:2].astype(np.float32),
            cv2.INTER_LINEAR,
        ).ravel()

    for side, (lines, ring) in sides.items():
        hom, _ = cv2.findHomography(grid[lines].reshape(-1, 2), g[lines].reshape(-1, 2))
        if hom is None:
            continue
        squares, beyond = samples(ring(0.5), hom), samples(ring(1.5), hom)
        if squares is None or beyond is None:
            continue
        # a continuing board: each step along the ring beyond changes grey level opposite to the
        # step along the outer squares (the next row of a checkerboard), by a like amount
        step_in, step_out = np.diff(squares), np.diff(beyond)
        like = (np.sign(step_out) == -np.sign(step_in)) & (np.abs(step_out) > 0.3 * np.median(np.abs(step_in)))
        if like.mean() >= 0.8:
            return side
    return None
