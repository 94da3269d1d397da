"""Four-CCD registration: chessboard corners (labelled by the board, `corners`) → a first guess
per camera (Zhang's method, OpenCV) → each CCD's orientation (normal or mirrored) and pose
against CCD 1 → the joint solve of all four cameras with per-corner outlier rejection and
covariance (`joint`) → pixel maps onto CCD 1's grid at the working distance, with their
uncertainty → quality gates → the paper's XOR check → registration JSON (this module owns the
format end to end) and report (`report`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from cohflash_jax.fileio import read_json
from cohflash_jax.registered import inside_image

from . import joint
from .board import Board
from .corners import (
    RegistrationError,
    board_continues,
    find_corners,
    label_by_board,
    larger_board_size,
    list_views,
    read_image,
    to_uint8,
)

MIN_VIEWS = 3
FORMAT_NAME = "cohflash-registration"
FORMAT_VERSION = 2
# Quality gates: a registration beyond any of these is refused, by `register` and by the loader
MAX_CORNER_RMS_PX = 2.0  # chessboard corners are good to 0.05–0.5 px; 2 px means a wrong model or board
MAX_REJECTED_FRACTION = 0.3  # of a CCD's detected corners, as outliers or in dropped views
MIN_COVERED_FRACTION = 0.1  # of CCD 1's pixels that a registered CCD must see
# Two orientations (normal, mirrored) of a CCD are told apart by how well its per-view poses
# against CCD 1 agree; the views' relative rotations agree to ~0.1° on a real rig
CONSENSUS_DEG = 2.0

__all__ = [
    "CameraCalibration",
    "Registration",
    "RegistrationError",
    "ViewImages",
    "load_registration",
    "pixel_maps",
    "register",
    "write_registration",
    "xor_image",
    "xor_ratio",
]


# -- first guess per camera -------------------------------------------------------------------
@dataclasses.dataclass
class CameraCalibration:
    """One CCD's intrinsics and distortion (OpenCV's model), in its own pixel frame, which is
    flipped left–right where `mirrored` (a CCD behind an odd number of mirrors)."""

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    rms_px: float
    per_view_rms_px: dict  # view name → RMS of its kept corners
    std_intrinsics: np.ndarray  # fx, fy, cx, cy, k1, k2, p1, p2, k3
    views_used: list
    views_left_out: dict  # view name → reason
    mirrored: bool = False
    corners_rejected: dict = dataclasses.field(default_factory=dict)  # view → corners left out


@dataclasses.dataclass
class FirstGuess:
    """Zhang's method on one CCD: intrinsics and a board pose per view it kept."""

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    poses: dict  # view → (R (3, 3), t (3,)) of the board in this camera's frame


def calibrate_camera(obj: np.ndarray, corners: dict, image_size) -> FirstGuess:
    """Zhang's method on one camera's views (a first guess for the joint solve); views whose RMS
    is an outlier (> max(3× median, median + 0.5 px)) are left out of the guess."""
    names = list(corners)
    for _ in range(2):
        if len(names) < MIN_VIEWS:
            raise RegistrationError(f"too few valid views ({len(names)}; at least {MIN_VIEWS} needed)")
        _, k, d, rvecs, tvecs, _, _, per_view = cv2.calibrateCameraExtended(
            [obj.astype(np.float32)] * len(names),
            [corners[n].reshape(-1, 1, 2).astype(np.float32) for n in names],
            image_size,
            None,
            None,
        )
        per_view = np.asarray(per_view).ravel()
        med = float(np.median(per_view))
        bad = [n for n, e in zip(names, per_view) if e > max(3 * med, med + 0.5)]
        if not bad:
            break
        names = [n for n in names if n not in bad]
    poses = {n: (cv2.Rodrigues(r)[0], np.asarray(t, np.float64).ravel()) for n, r, t in zip(names, rvecs, tvecs)}
    return FirstGuess(k, np.asarray(d, np.float64).ravel()[:5], poses)


def angle_deg(r: np.ndarray) -> float:
    return float(np.rad2deg(np.linalg.norm(cv2.Rodrigues(np.asarray(r, np.float64))[0])))


@dataclasses.dataclass
class Orientation:
    """How CCD k's views are labelled against CCD 1's: whether it is mirrored, the labelling
    chosen in each view, the pose guess (X_k = R·X_1 + T) and how well the views agree."""

    mirrored: bool
    corners: dict  # view → corners (N, 2) in the CCD's (possibly flipped) frame
    guess: FirstGuess
    R: np.ndarray
    T: np.ndarray
    spread_deg: float  # median disagreement of the views' relative rotations with R


def orient(obj, ref: FirstGuess, detections: dict, image_size, mirrored: bool) -> Orientation:
    """CCD k's labelling and pose guess under one hypothesis (normal or mirrored): a first guess
    of its camera, each view's relative pose to CCD 1, and where the board left a 180° turn open,
    per view the labelling whose relative pose agrees with the consensus of the views."""
    primary = {n: d.corners for n, d in detections.items()}
    guess = calibrate_camera(obj, primary, image_size)
    candidates = {}  # view → [(corners, R_rel, T_rel)]
    for n, det in detections.items():
        if n not in ref.poses:
            continue
        r1, t1 = ref.poses[n]
        for c in (det.corners, *det.alternatives):
            ok, rv, tv = cv2.solvePnP(obj, c.astype(np.float64), guess.camera_matrix, guess.dist_coeffs)
            if ok:
                rk = cv2.Rodrigues(rv)[0]
                rel = rk @ r1.T
                candidates.setdefault(n, []).append((c, rel, tv.ravel() - rel @ t1))
    if len(candidates) < MIN_VIEWS:
        raise RegistrationError(f"too few views shared with CCD 1 ({len(candidates)}; at least {MIN_VIEWS} needed)")
    everything = [rel for cands in candidates.values() for _, rel, _ in cands]

    def support(r):
        return sum(min(angle_deg(rel @ r.T) for _, rel, _ in cands) < CONSENSUS_DEG for cands in candidates.values())

    consensus = max(everything, key=support)
    chosen, rels, ts, dev = dict(primary), [], [], []
    for n, cands in candidates.items():
        c, rel, t = min(cands, key=lambda x: angle_deg(x[1] @ consensus.T))
        chosen[n] = c
        dev.append(angle_deg(rel @ consensus.T))
        if dev[-1] < CONSENSUS_DEG:
            rels.append(rel)
            ts.append(t)
    if not rels:
        rels, ts = [consensus], [np.median([t for cands in candidates.values() for _, _, t in cands], axis=0)]
    rv = np.median([cv2.Rodrigues(r)[0].ravel() for r in rels], axis=0)
    return Orientation(mirrored, chosen, guess, cv2.Rodrigues(rv)[0], np.median(ts, axis=0), float(np.median(dev)))


# -- pixel maps and the XOR check -------------------------------------------------------------
def pixel_maps(
    cam1: CameraCalibration, camk: CameraCalibration, R, T, image_size, distance_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """For every CCD 1 pixel, the CCD k pixel that sees the same point of a fronto-parallel plane
    at `distance_mm`: back-project (undistorted), move to CCD k's frame (X_k = R·X_1 + T),
    project with CCD k's intrinsics and distortion, and un-flip a mirrored CCD's column.
    float32 maps for `cv2.remap`."""
    w, h = image_size
    v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    pts = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    norm = cv2.undistortPoints(pts, cam1.camera_matrix, cam1.dist_coeffs, criteria=crit).reshape(-1, 2)
    x1 = np.concatenate([norm, np.ones((norm.shape[0], 1))], axis=1) * distance_mm
    xk = x1 @ np.asarray(R).T + np.asarray(T).ravel()
    proj, _ = cv2.projectPoints(xk, np.zeros(3), np.zeros(3), camk.camera_matrix, camk.dist_coeffs)
    proj = proj.reshape(h, w, 2)
    if camk.mirrored:
        proj[..., 0] = w - 1 - proj[..., 0]
    proj = proj.astype(np.float32)
    return proj[..., 0], proj[..., 1]


def covered(map_x: np.ndarray, map_y: np.ndarray, shape) -> np.ndarray:
    """CCD 1 pixels whose map lands inside CCD k's image of `shape` (H, W)."""
    return inside_image(map_x, map_y, shape[1], shape[0])


def otsu_on(img8: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Otsu binarisation with the threshold taken from the pixels `where` only."""
    if not where.any():
        return np.zeros(img8.shape, bool)
    thr, _ = cv2.threshold(img8[where].reshape(-1, 1), 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return img8 > thr


def xor_image(img1_8: np.ndarray, imgk_8: np.ndarray, map_x=None, map_y=None) -> tuple[np.ndarray, np.ndarray]:
    """The paper's check: Otsu-binarise both images (CCD k resampled onto CCD 1's grid when maps
    are given) and XOR them → (differing pixels, pixels both images cover). Both thresholds come
    from the covered pixels only: the zeros `remap` fills in elsewhere used to pull the
    threshold down and read 60.8 % for 34.7 % on low-contrast frames."""
    if map_x is not None:
        valid = covered(map_x, map_y, imgk_8.shape)
        imgk_8 = cv2.remap(imgk_8, map_x, map_y, cv2.INTER_LINEAR)
    else:
        valid = np.ones(img1_8.shape, bool)
    return (otsu_on(img1_8, valid) != otsu_on(imgk_8, valid)) & valid, valid


def xor_ratio(img1_8: np.ndarray, imgk_8: np.ndarray, map_x=None, map_y=None) -> float:
    """Fraction of misaligned pixels (XOR of the binarised images) among those both cover."""
    diff, valid = xor_image(img1_8, imgk_8, map_x, map_y)
    return float(diff.sum() / max(valid.sum(), 1))


# -- the registration -------------------------------------------------------------------------
@dataclasses.dataclass
class ViewImages:
    """What the report shows of the views: each CCD's 8-bit images (in the CCD's own frame, not
    flipped) and labelled corners (in its solve frame), keyed by view name, and the joint solve.
    Not stored in the registration file."""

    images8: list[dict]
    corners: list[dict]
    solution: joint.JointSolution | None = None
    view_names: list = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Registration:
    image_size: tuple[int, int]
    board: Board
    cameras: list[CameraCalibration]
    R: list[np.ndarray]  # CCD 2–4 relative to CCD 1
    T: list[np.ndarray]  # mm
    stereo_rms_px: list[float]
    distance_mm: float
    xor_before: list[float]
    xor_after: list[float]
    failed: dict  # file → reason
    seconds_per_view: float
    views: ViewImages | None = dataclasses.field(default=None, repr=False, compare=False)  # for the report
    pose_covariance: list = dataclasses.field(default_factory=list)  # (6, 6): rvec (rad), T (mm)
    map_sigma_px: list = dataclasses.field(default_factory=list)  # per CCD 2–4: {"u", "v", "sigma"}
    corner_sigma_px: float = float("nan")
    covered_fraction: list = dataclasses.field(default_factory=list)
    missing_views: dict = dataclasses.field(default_factory=dict)  # view → CCDs whose folder lacks it

    def maps(self, ccd_index: int):
        """(map_x, map_y) of CCD `ccd_index` (2–4) onto CCD 1's grid."""
        k = ccd_index - 1
        return pixel_maps(
            self.cameras[0], self.cameras[k], self.R[k - 1], self.T[k - 1], self.image_size, self.distance_mm
        )

    def pose_sigma(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """1σ of CCD k+2's Rodrigues vector (deg) and translation (mm), NaN where not stated."""
        if k >= len(self.pose_covariance):
            return np.full(3, np.nan), np.full(3, np.nan)
        sd = np.sqrt(np.clip(np.diag(np.asarray(self.pose_covariance[k])), 0, None))
        return np.rad2deg(sd[:3]), sd[3:]

    def summary(self) -> dict:
        """The poses this registration applies (CCDs 2–4 against CCD 1), for a result's provenance."""
        poses = []
        for k, (r, t, s) in enumerate(zip(self.R, self.T, self.stereo_rms_px)):
            rot_sd, t_sd = self.pose_sigma(k)
            poses.append(
                {
                    "ccd": k + 2,
                    "mirrored": bool(self.cameras[k + 1].mirrored),
                    "rotation_deg": angle_deg(r),
                    "T_mm": np.asarray(t).ravel().tolist(),
                    "stereo_rms_px": s,
                    "rotation_sigma_deg": rot_sd.tolist(),
                    "T_sigma_mm": t_sd.tolist(),
                }
            )
        return {"working_distance_mm": self.distance_mm, "relative_poses": poses}

    def quality_problems(self) -> list[str]:
        """What makes this registration unusable, each with its remedy; empty when it passes."""
        problems = []
        for k, c in enumerate(self.cameras, start=1):
            kk = c.camera_matrix
            w, h = self.image_size
            # a field of view between 0.01° (a long telescope) and 170°
            if not (0.04 * w < kk[0, 0] < 5000 * w and 0.04 * w < kk[1, 1] < 5000 * w):
                problems.append(
                    f"CCD {k}: focal length {kk[0, 0]:.0f} px is implausible for a {w}-px wide image "
                    "(check --board: a wrong corner count can match another pattern in the views)"
                )
            if not (0 <= kk[0, 2] <= w - 1 and 0 <= kk[1, 2] <= h - 1):
                problems.append(
                    f"CCD {k}: principal point ({kk[0, 2]:.0f}, {kk[1, 2]:.0f}) px lies outside the "
                    f"{w}×{h} image (check --board, or add views that fill the image's corners)"
                )
            if c.std_intrinsics.size and not np.all(np.isfinite(c.std_intrinsics)):
                problems.append(
                    f"CCD {k}: σ of the intrinsics is NaN (the views do not constrain the camera: "
                    "add views with the board tilted in different directions)"
                )
            if c.rms_px > MAX_CORNER_RMS_PX:
                problems.append(
                    f"CCD {k}: corners fit to {c.rms_px:.2f} px RMS, far above a chessboard's 0.05–0.5 px "
                    "(check --board and that the views are in focus)"
                )
        for k, (s, cov) in enumerate(zip(self.stereo_rms_px, self.pose_covariance or [None] * 3), start=2):
            if not math.isfinite(s) or s > MAX_CORNER_RMS_PX:
                problems.append(
                    f"CCD {k} against CCD 1: stereo RMS {s:.2f} px (check the CCD's orientation, --board, "
                    "and that views with one name show one board position in every folder)"
                )
            if cov is not None and not np.all(np.isfinite(cov)):
                problems.append(f"CCD {k}: σ of its pose is NaN (too few views shared with CCD 1)")
        for k, f in enumerate(self.covered_fraction, start=2):
            if f < MIN_COVERED_FRACTION:
                problems.append(
                    f"CCD {k} sees only {f:.1%} of CCD 1's pixels at {self.distance_mm:.0f} mm "
                    "(no overlap: check --distance-mm and the CCD's orientation)"
                )
        return problems

    def to_json(self) -> dict:
        cam = lambda c: {
            "camera_matrix": c.camera_matrix.tolist(),
            "dist_coeffs": c.dist_coeffs.tolist(),
            "mirrored": bool(c.mirrored),
            "rms_px": c.rms_px,
            "per_view_rms_px": c.per_view_rms_px,
            "std_intrinsics": c.std_intrinsics.tolist(),
            "views_used": c.views_used,
            "views_left_out": c.views_left_out,
            "corners_rejected": c.corners_rejected,
        }
        poses = []
        for k, (r, pose) in enumerate(zip(self.R, self.summary()["relative_poses"])):
            entry = {"R": np.asarray(r).tolist()} | pose
            if k < len(self.pose_covariance):
                entry["covariance_rvec_rad_T_mm"] = np.asarray(self.pose_covariance[k]).tolist()
            poses.append(entry)
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "image_size": list(self.image_size),
            "board": dataclasses.asdict(self.board),
            "working_distance_mm": self.distance_mm,
            "solve": "joint: intrinsics, distortion, CCD poses and board poses together, outlier corners rejected",
            "corner_sigma_px": self.corner_sigma_px,
            "cameras": [cam(c) for c in self.cameras],
            "relative_poses": poses,
            "map_sigma_px": [
                {"ccd": k + 2, "u": m["u"].tolist(), "v": m["v"].tolist(), "sigma": m["sigma"].tolist()}
                for k, m in enumerate(self.map_sigma_px)
            ],
            "covered_fraction": self.covered_fraction,
            "xor_misalignment_before": self.xor_before,
            "xor_misalignment_after": self.xor_after,
            "failed_views": self.failed,
            "missing_views": self.missing_views,
            "seconds_per_view": self.seconds_per_view,
        }

    @classmethod
    def from_json(cls, data: dict, source="registration") -> "Registration":
        if data.get("format") != FORMAT_NAME:
            raise RegistrationError(f"{source}: format is {data.get('format')!r}, expected {FORMAT_NAME!r}")
        if data.get("format_version") not in (1, 2):
            raise RegistrationError(
                f"{source}: format_version {data.get('format_version')!r} is not one this cohflash reads (1 or 2)"
            )
        try:
            cams = [
                CameraCalibration(
                    np.array(c["camera_matrix"], np.float64),
                    np.array(c["dist_coeffs"], np.float64),
                    float(c["rms_px"]),
                    dict(c.get("per_view_rms_px", {})),
                    np.array(c.get("std_intrinsics", []), np.float64),
                    list(c.get("views_used", [])),
                    dict(c.get("views_left_out", {})),
                    bool(c.get("mirrored", False)),
                    dict(c.get("corners_rejected", {})),
                )
                for c in data["cameras"]
            ]
            poses = data["relative_poses"]
            reg = cls(
                tuple(int(v) for v in data["image_size"]),
                Board(**data["board"]),
                cams,
                [np.array(p["R"], np.float64) for p in poses],
                [np.array(p["T_mm"], np.float64) for p in poses],
                [float(p.get("stereo_rms_px", 0.0)) for p in poses],
                float(data["working_distance_mm"]),
                list(data.get("xor_misalignment_before", [])),
                list(data.get("xor_misalignment_after", [])),
                dict(data.get("failed_views", {})),
                float(data.get("seconds_per_view", 0.0)),
                pose_covariance=[
                    np.array(p["covariance_rvec_rad_T_mm"], np.float64)
                    for p in poses
                    if "covariance_rvec_rad_T_mm" in p
                ],
                map_sigma_px=[
                    {k: np.array(m[k], np.float64) for k in ("u", "v", "sigma")} for m in data.get("map_sigma_px", [])
                ],
                corner_sigma_px=float(data.get("corner_sigma_px", float("nan"))),
                covered_fraction=[float(f) for f in data.get("covered_fraction", [])],
                missing_views=dict(data.get("missing_views", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise RegistrationError(f"{source}: malformed registration file ({exc})") from None
        if len(reg.cameras) != 4 or len(reg.R) != 3:
            raise RegistrationError(
                f"{source}: expected 4 cameras and 3 relative poses, got {len(reg.cameras)} and {len(reg.R)}"
            )
        shaped = [(f"camera {k + 1} camera_matrix", c.camera_matrix, (3, 3)) for k, c in enumerate(reg.cameras)]
        shaped += [
            (f"camera {k + 1} dist_coeffs", c.dist_coeffs, c.dist_coeffs.shape) for k, c in enumerate(reg.cameras)
        ]
        shaped += [(f"CCD {k + 2} R", r, (3, 3)) for k, r in enumerate(reg.R)]
        shaped += [(f"CCD {k + 2} T_mm", t, (3,)) for k, t in enumerate(reg.T)]
        for name, arr, shape in shaped:
            if arr.shape != shape or not np.all(np.isfinite(arr)):
                raise RegistrationError(
                    f"{source}: {name} must be a finite array of shape {shape}, got {arr.shape}"
                    + ("" if arr.shape != shape else " with NaN/inf")
                )
        if (
            len(reg.image_size) != 2
            or min(reg.image_size) < 2
            or not (reg.distance_mm > 0 and math.isfinite(reg.distance_mm))
        ):
            raise RegistrationError(
                f"{source}: image_size {reg.image_size} or working distance {reg.distance_mm} mm out of range"
            )
        for r in reg.R:
            if abs(np.linalg.det(r) - 1) > 1e-6 or not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
                raise RegistrationError(f"{source}: a relative pose's R is not a rotation matrix")
        problems = reg.quality_problems()
        if problems:
            raise RegistrationError(f"{source}: registration fails its quality checks: " + "; ".join(problems))
        return reg


def load_registration(path) -> Registration:
    return Registration.from_json(read_json(path, "registration", RegistrationError), path)


def write_registration(path, reg: Registration) -> Path:
    from cohflash_jax.fileio import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(reg.to_json(), indent=1))
    return path


# -- register ---------------------------------------------------------------------------------
# views whose whole chessboard, larger than --board, agrees on one size before --board is refused
LARGER_BOARD_VIEWS = 3


def refuse_larger_board(board: Board, larger: dict) -> None:
    """Refuse --board once `LARGER_BOARD_VIEWS` views show one larger chessboard ({(cols, rows):
    [view files]}, `larger_board_size`), naming its size."""
    for (cols, rows), paths in larger.items():
        if len(paths) >= LARGER_BOARD_VIEWS:
            raise RegistrationError(
                f"--board {board.cols}x{board.rows} does not match the board: {len(paths)} views show a "
                f"chessboard of {cols}x{rows} inner corners (e.g. {paths[0]}); pass --board {cols}x{rows}"
            )


def refuse_empty_folder(k: int, files: dict, board: Board, found: int, failed: dict, continues: list) -> None:
    """Refuse as soon as CCD k's folder is read if fewer than `MIN_VIEWS` of its views show the
    board (the views of the other folders could not change that): where none showed a board of
    --board's size, say so, --board being the likely cause. A folder with views whose pattern
    continues past the grid is left to the wrong-board verdict (`wrong_board`)."""
    paths = [str(p) for p in files.values()]
    if found >= MIN_VIEWS or any(p in continues for p in paths):
        return
    reasons = [failed.get(p) for p in paths]
    folder = Path(paths[0]).parent
    hint = ""
    if reasons and all(r == "chessboard not found" for r in reasons):
        hint = (
            f": no view shows a {board.cols}x{board.rows} chessboard; check --board (the board's inner corners, "
            "COLSxROWS) and that the board is in view"
        )
    raise RegistrationError(
        f"CCD {k + 1} ({folder}): too few valid views ({found}; at least {MIN_VIEWS} needed){hint}; failed: "
        + (", ".join(p for p in paths if p in failed) or "none")
    )


def wrong_board(continues: list, found: int) -> bool:
    """Whether the views say --board is not the board: at least three (and a quarter of the
    `found` boards) show the pattern continuing past the grid found."""
    return bool(continues) and len(continues) >= max(3, found // 4)


def detect_all(view_files, board: Board, progress: bool):
    """Read and detect every view: (image size, 8-bit images, raw corners, failed {file: reason})."""
    size, depth = None, None
    images8 = [dict() for _ in view_files.files]
    raw = [dict() for _ in view_files.files]
    failed = {}
    continues = []
    larger = {}  # a larger board's size → the views that show it
    confirmed = 0  # views whose grid of --board's size is the whole board
    fruitless = 0  # searches for a larger board that found none
    views = [(k, name, path) for k, files in enumerate(view_files.files) for name, path in files.items()]
    with tqdm(total=len(views), unit="view", desc="detecting corners", disable=not progress) as bar:
        for seen, (k, name, path) in enumerate(views, start=1):
            if k > 0 and name == next(iter(view_files.files[k])):  # the folder before is read
                refuse_empty_folder(k - 1, view_files.files[k - 1], board, len(raw[k - 1]), failed, continues)
            bar.update()
            try:
                img = read_image(path)
            except RegistrationError as exc:
                failed[str(path)] = str(exc).removeprefix(f"{path}: ")
                continue
            if size is None:
                size, depth = (img.shape[1], img.shape[0]), img.dtype
            if (img.shape[1], img.shape[0]) != size:
                raise RegistrationError(
                    f"{path}: image size {img.shape[1]}×{img.shape[0]} differs from "
                    f"{size[0]}×{size[1]} of the first image"
                )
            if img.dtype != depth:
                raise RegistrationError(f"{path}: bit depth {img.dtype} differs from {depth} of the first image")
            img8 = to_uint8(img)
            images8[k][name] = img8
            corners = find_corners(img8, board, None if img.dtype == np.uint8 else img.astype(np.float32))
            side = None if corners is None else board_continues(img8, corners, board)
            # no board of this size, or part of a larger one: looked for a larger one until the
            # board is confirmed in as many views as would refuse it (a failed view costs a search)
            # (or until as many searches found none twice over: a --board larger than the board)
            searching = confirmed < LARGER_BOARD_VIEWS and fruitless < 2 * LARGER_BOARD_VIEWS
            if (corners is None or side is not None) and searching:
                size_seen = larger_board_size(img8, board)
                fruitless += size_seen is None
                if size_seen is not None:
                    larger.setdefault(size_seen, []).append(str(path))
                    refuse_larger_board(board, larger)
            if corners is None:
                failed[str(path)] = "chessboard not found"
                continue
            if side is not None:
                continues.append(str(path))
                failed[str(path)] = (
                    f"the chessboard pattern continues past the {board.cols}x{board.rows} grid found ({side})"
                )
                # refused as soon as the views left could not change the verdict below (a
                # wrong --board is otherwise told after every view's slow failed search)
                if wrong_board(continues, sum(len(r) for r in raw) + len(views) - seen):
                    break
                continue
            raw[k][name] = corners
            confirmed += 1
    if wrong_board(continues, sum(len(r) for r in raw)):
        raise RegistrationError(
            f"--board {board.cols}x{board.rows} does not match the board: in {len(continues)} views the chessboard "
            f"pattern continues past the grid found (e.g. {continues[0]}); count the board's inner corners"
        )
    if size is None:
        raise RegistrationError(
            "no readable image in the folders: " + "; ".join(f"{p}: {r}" for p, r in failed.items())
        )
    return size, images8, raw, failed


def register(
    folders, board: Board, distance_mm: float | None = None, progress: bool = True, mirrored: dict | None = None
) -> Registration:
    """Register four CCDs from chessboard views (folder k = CCD k; a view is the same file name
    in every folder). Whether CCDs 2–4 are mirrored is found from the views (their poses agree
    with CCD 1's under one hypothesis only), or taken from `mirrored` ({ccd: bool}) where the
    views cannot tell. Refuses, naming the cause, where the result fails its quality checks."""
    if len(folders) != 4:
        raise RegistrationError(f"four image folders are needed (CCD 1–4), got {len(folders)}")
    if distance_mm is not None and not (math.isfinite(distance_mm) and distance_mm > 0):
        raise RegistrationError(f"the working distance must be a positive number of mm, got {distance_mm}")
    view_files = list_views(folders)
    t0 = time.perf_counter()
    size, images8, raw, failed = detect_all(view_files, board, progress)
    obj = board.object_points().astype(np.float64)
    w = size[0]

    def labelled(k: int, flipped: bool) -> dict:
        flip = lambda c: np.stack([w - 1 - c[:, 0], c[:, 1]], axis=1)
        return {
            n: label_by_board(images8[k][n][:, ::-1] if flipped else images8[k][n], flip(c) if flipped else c, board)
            for n, c in raw[k].items()
        }

    def failed_in(k):
        return ", ".join(f for f in failed if Path(f).parent == Path(folders[k])) or "none"

    ccd1 = labelled(0, False)
    try:
        ref = calibrate_camera(obj, {n: d.corners for n, d in ccd1.items()}, size)
    except RegistrationError as exc:
        raise RegistrationError(f"CCD 1 ({folders[0]}): {exc}; failed: {failed_in(0)}") from None
    orientations = []
    for k in range(1, 4):
        tried = []
        hypotheses = (False, True) if mirrored is None or k + 1 not in mirrored else (mirrored[k + 1],)
        for flip in hypotheses:
            try:
                tried.append(orient(obj, ref, labelled(k, flip), size, flip))
            except RegistrationError as exc:
                error = exc
        if not tried:
            raise RegistrationError(f"CCD {k + 1} ({folders[k]}): {error}; failed: {failed_in(k)}") from None
        if len(tried) == 2 and max(o.spread_deg for o in tried) < CONSENSUS_DEG:
            raise RegistrationError(
                f"CCD {k + 1} ({folders[k]}): cannot tell whether it is mirrored — its views agree with CCD 1's "
                f"either way ({tried[0].spread_deg:.2f}° normal, {tried[1].spread_deg:.2f}° mirrored): the board was "
                "held at too few orientations. Tilt it in different directions across the views, or state it "
                f"with --mirrored {k + 1}=yes|no"
            )
        orientations.append(min(tried, key=lambda o: o.spread_deg))
    # the joint solve over every view any CCD saw
    names = sorted(set().union(*(r.keys() for r in raw)))
    labels = [{n: d.corners for n, d in ccd1.items()}] + [o.corners for o in orientations]
    observed = np.full((4, len(names), obj.shape[0], 2), np.nan)
    for k in range(4):
        for v, n in enumerate(names):
            if n in labels[k]:
                observed[k, v] = labels[k][n]
    seen = np.isfinite(observed[..., 0])
    layout = joint.Layout(4, len(names))
    x0 = np.zeros(layout.size)
    guesses = [ref] + [o.guess for o in orientations]
    for k, g in enumerate(guesses):
        kk = g.camera_matrix
        x0[layout.intrinsics(k)] = [kk[0, 0], kk[1, 1], kk[0, 2], kk[1, 2], *g.dist_coeffs]
    for k, o in enumerate(orientations, start=1):
        x0[layout.camera_pose(k)] = [*cv2.Rodrigues(o.R)[0].ravel(), *o.T]
    for v, n in enumerate(names):
        pose = ref.poses.get(n)
        if pose is None:  # CCD 1 missed it: the board pose through another CCD's guess
            for o in orientations:
                if n in o.guess.poses:
                    rk, tk = o.guess.poses[n]
                    pose = (o.R.T @ rk, o.R.T @ (tk - o.T))
                    break
        if pose is None:  # no camera's first guess kept this view: the joint solve leaves it out
            seen[:, v] = False
            pose = (np.eye(3), np.array([0.0, 0.0, 1000.0]))
        x0[layout.board_pose(v)] = [*cv2.Rodrigues(pose[0])[0].ravel(), *pose[1]]
    solution = joint.solve(x0, layout, obj, observed, seen)
    # the cameras, in the registration's terms
    sd_all = [solution.intrinsics_sigma(k) for k in range(4)]
    cams = []
    for k in range(4):
        used = [n for v, n in enumerate(names) if solution.inliers[k, v].any()]
        left_out = {names[v]: reason for (c, v), reason in solution.dropped_views.items() if c == k}
        lost_corners = seen[k].sum(axis=1) - solution.inliers[k].sum(axis=1)
        rejected = {
            names[v]: int(lost_corners[v])
            for v in range(len(names))
            if lost_corners[v] > 0 and (k, v) not in solution.dropped_views
        }
        err = solution.residuals_px[k]
        per_view = {
            names[v]: joint.rms_px(err[v][solution.inliers[k, v]])
            for v in range(len(names))
            if solution.inliers[k, v].any()
        }
        inl = solution.inliers[k]
        rms = joint.rms_px(err[inl]) if inl.any() else float("nan")
        cams.append(
            CameraCalibration(
                solution.camera_matrix(k),
                solution.dist_coeffs(k),
                rms,
                per_view,
                sd_all[k],
                used,
                left_out,
                k > 0 and orientations[k - 1].mirrored,
                rejected,
            )
        )
        lost = 1 - inl.sum() / max(seen[k].sum(), 1)
        if lost > MAX_REJECTED_FRACTION:
            raise RegistrationError(
                f"CCD {k + 1} ({folders[k]}): {lost:.0%} of its corners disagree with the joint solve of the four "
                "CCDs (check the CCD's orientation, --board, and that views with one name show one board "
                "position in every folder)"
            )
    if distance_mm is None:  # median board distance seen by CCD 1
        centre = obj.mean(axis=0)
        poses = [solution.board_pose(v) for v in np.nonzero(solution.inliers[0].any(axis=1))[0]]
        dists = [np.linalg.norm(r @ centre + t) for r, t in poses]
        distance_mm = float(np.median(dists))
    Rs, Ts, stereo_rms, covs = [], [], [], []
    for k in range(1, 4):
        R, T = solution.pose(k)
        Rs.append(R)
        Ts.append(T)
        covs.append(solution.pose_covariance(k))
        shared = solution.inliers[0].any(axis=1) & solution.inliers[k].any(axis=1)
        if shared.sum() < MIN_VIEWS:
            raise RegistrationError(
                f"CCD 1 and CCD {k + 1} share {int(shared.sum())} valid views; at least {MIN_VIEWS} needed"
            )
        both = np.concatenate([solution.residuals_px[c][shared][solution.inliers[c][shared]] for c in (0, k)])
        stereo_rms.append(joint.rms_px(both))
    reg = Registration(
        size,
        board,
        cams,
        Rs,
        Ts,
        stereo_rms,
        distance_mm,
        [],
        [],
        failed,
        0.0,
        pose_covariance=covs,
        corner_sigma_px=solution.sigma_px,
        missing_views={n: ks for n, ks in view_files.missing.items()},
    )
    for k in range(1, 4):
        u, v, sigma = joint.map_sigma_px(solution, k, size, distance_mm, cams[k].mirrored)
        reg.map_sigma_px.append({"u": u, "v": v, "sigma": sigma})
        mx, my = reg.maps(k + 1)
        reg.covered_fraction.append(float(covered(mx, my, (size[1], size[0])).mean()))
        common = [n for n in cams[0].views_used if n in cams[k].views_used]
        reg.xor_before.append(float(np.mean([xor_ratio(images8[0][n], images8[k][n]) for n in common])))
        reg.xor_after.append(float(np.mean([xor_ratio(images8[0][n], images8[k][n], mx, my) for n in common])))
    reg.seconds_per_view = (time.perf_counter() - t0) / max(sum(len(f) for f in view_files.files), 1)
    reg.views = ViewImages(images8, labels, solution, names)
    problems = reg.quality_problems()
    if problems:
        raise RegistrationError("registration refused: " + "; ".join(problems))
    return reg


def from_pixel_transforms(
    image_size, focal_px: float, transforms, distance_mm: float = 30500.0, mirrored=(False, False, False)
) -> Registration:
    """Registration of four identical distortion-free cameras whose CCDs 2–4 see the scene
    through an in-plane shift (dx, dy px) and rotation (deg) about the image centre — the
    simulator's `misregistration` effect — expressed as poses (R about the optical axis, T in
    the image plane) at `distance_mm`; `mirrored[k]` flips CCD k+2's image left–right after."""
    w, h = image_size
    k = np.array([[focal_px, 0, w / 2 - 0.5], [0, focal_px, h / 2 - 0.5], [0, 0, 1]], np.float64)
    cams = [CameraCalibration(k, np.zeros(5), 0.0, {}, np.zeros(0), [], {}, m) for m in (False, *mirrored)]
    Rs, Ts = [], []
    for dx, dy, rot_deg in transforms:
        b = -np.deg2rad(rot_deg)
        r2 = np.array([[np.cos(b), -np.sin(b)], [np.sin(b), np.cos(b)]])
        R = np.eye(3)
        R[:2, :2] = r2
        t = np.zeros(3)
        t[:2] = -(distance_mm / focal_px) * (r2 @ np.array([dx, dy]))
        Rs.append(R)
        Ts.append(t)
    return Registration((w, h), Board(3, 3, 1.0), cams, Rs, Ts, [0.0] * 3, float(distance_mm), [], [], {}, 0.0)
