"""Four-CCD registration with Zhang's method (OpenCV): chessboard corners → intrinsics and
distortion per CCD → pose of CCDs 2–4 relative to CCD 1 → pixel maps onto CCD 1's grid at the
working distance → the paper's XOR misalignment check → registration JSON and report figure.
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

from cohflash_jax.fileio import read_gray_image, read_json

from .board import Board

IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".bmp", ".pgm", ".jpg", ".jpeg"}
MIN_VIEWS = 3
FORMAT_NAME = "cohflash-registration"


class RegistrationError(ValueError):
    """Registration input is unusable; the message names the file or folder."""


# -- images -----------------------------------------------------------------------------------
def list_views(folders) -> list[list[Path]]:
    """Sorted image files of each CCD folder; all folders must hold the same number."""
    views = []
    for d in map(Path, folders):
        if not d.is_dir():
            what = "is a file, not a folder of images" if Path(d).exists() else "not found"
            raise RegistrationError(f"image folder {d}: {what}")
        files = sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise RegistrationError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in {d}")
        views.append(files)
    counts = [len(v) for v in views]
    if len(set(counts)) > 1:
        raise RegistrationError(
            "unequal numbers of views: " + ", ".join(f"{d} has {c}" for d, c in zip(folders, counts))
        )
    same_as_earlier(folders, views)
    return views


def same_as_earlier(folders, views) -> None:
    """RegistrationError where two CCDs' folders are one folder, or hold byte-identical images
    (four copies of CCD 1's folder registered as 0.000° apart, with no warning)."""
    import hashlib

    digest = lambda files: tuple(hashlib.sha256(f.read_bytes()).hexdigest() for f in files)
    seen = {}
    for k, (folder, files) in enumerate(zip(folders, views)):
        key = (Path(folder).resolve(),)
        if key in seen:
            raise RegistrationError(f"CCD {k + 1}'s folder {folder} is CCD {seen[key] + 1}'s: give each CCD its own")
        seen[key] = k
        content = digest(files)
        if content in seen:
            raise RegistrationError(
                f"CCD {k + 1}'s images in {folder} are byte-identical to CCD {seen[content] + 1}'s: "
                "the same views copied twice? Each CCD must photograph the board itself"
            )
        seen[content] = k


def read_image(path: Path) -> np.ndarray:
    img = read_gray_image(path)
    if img is None:
        raise RegistrationError(f"cannot read image {path}")
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


def detect_corners(img8: np.ndarray, board: Board, refine_on: np.ndarray | None = None) -> np.ndarray | None:
    """Inner corners (N, 2) float32 with sub-pixel accuracy, or None if the board is not found.

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


# -- calibration ------------------------------------------------------------------------------
@dataclasses.dataclass
class CameraCalibration:
    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    rms_px: float
    per_view_rms_px: dict  # view name → RMS
    std_intrinsics: np.ndarray  # fx, fy, cx, cy, k1, k2, p1, p2, k3, …
    views_used: list
    views_left_out: dict  # view name → reason


def calibrate_camera(obj: np.ndarray, detections: dict, image_size) -> CameraCalibration:
    """Zhang's method on the detected views; views whose RMS is an outlier (> max(3× median,
    median + 0.5 px)) are left out and the calibration is repeated once."""
    names = list(detections)
    left_out = {}
    for _ in range(2):
        if len(names) < MIN_VIEWS:
            raise RegistrationError(f"too few valid views ({len(names)}; at least {MIN_VIEWS} needed)")
        rms, k, d, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
            [obj] * len(names), [detections[n].reshape(-1, 1, 2) for n in names], image_size, None, None
        )
        per_view = np.asarray(per_view).ravel()
        med = float(np.median(per_view))
        bad = [n for n, e in zip(names, per_view) if e > max(3 * med, med + 0.5)]
        if not bad:
            break
        for n in bad:
            left_out[n] = f"outlier: reprojection RMS {per_view[names.index(n)]:.2f} px (median {med:.2f})"
        names = [n for n in names if n not in bad]
    return CameraCalibration(
        k, d.ravel(), float(rms), dict(zip(names, map(float, per_view))), np.asarray(std_in).ravel(), names, left_out
    )


def _oriented(reference: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Corner order of `corners` made to agree with `reference` (same board, other CCD)."""
    a, b = reference[-1] - reference[0], corners[-1] - corners[0]
    return corners[::-1].copy() if a @ b < 0 else corners


def pixel_maps(cam1: CameraCalibration, camk: CameraCalibration, R, T, image_size, distance_mm: float):
    """For every CCD 1 pixel, the CCD k pixel that sees the same point of a fronto-parallel plane
    at `distance_mm`: back-project (undistorted), move to CCD k's frame (X_k = R·X_1 + T),
    project with CCD k's intrinsics and distortion. float32 maps for `cv2.remap`."""
    w, h = image_size
    v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    pts = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    norm = cv2.undistortPoints(pts, cam1.camera_matrix, cam1.dist_coeffs, criteria=crit).reshape(-1, 2)
    x1 = np.concatenate([norm, np.ones((norm.shape[0], 1))], axis=1) * distance_mm
    xk = x1 @ np.asarray(R).T + np.asarray(T).ravel()
    proj, _ = cv2.projectPoints(xk, np.zeros(3), np.zeros(3), camk.camera_matrix, camk.dist_coeffs)
    proj = proj.reshape(h, w, 2).astype(np.float32)
    return proj[..., 0], proj[..., 1]


def xor_image(img1_8: np.ndarray, imgk_8: np.ndarray, map_x=None, map_y=None) -> tuple[np.ndarray, np.ndarray]:
    """The paper's check: Otsu-binarize both images (CCD k resampled onto CCD 1's grid when
    maps are given) and XOR them → (differing pixels, pixels both images cover)."""
    if map_x is not None:
        valid = (map_x >= 0) & (map_x <= imgk_8.shape[1] - 1) & (map_y >= 0) & (map_y <= imgk_8.shape[0] - 1)
        imgk_8 = cv2.remap(imgk_8, map_x, map_y, cv2.INTER_LINEAR)
    else:
        valid = np.ones(img1_8.shape, bool)
    _, b1 = cv2.threshold(img1_8, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    _, bk = cv2.threshold(imgk_8, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return (b1 != bk) & valid, valid


def xor_ratio(img1_8: np.ndarray, imgk_8: np.ndarray, map_x=None, map_y=None) -> float:
    """Fraction of misaligned pixels (XOR of the binarized images) among those both cover."""
    diff, valid = xor_image(img1_8, imgk_8, map_x, map_y)
    return float(diff.sum() / max(valid.sum(), 1))


@dataclasses.dataclass
class ViewImages:
    """What the report figure shows of the views: each CCD's 8-bit images and detected corners,
    keyed by view name. Not stored in the registration file."""

    images8: list[dict]
    detections: list[dict]


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

    def maps(self, ccd_index: int):
        """(map_x, map_y) of CCD `ccd_index` (2–4) onto CCD 1's grid."""
        k = ccd_index - 1
        return pixel_maps(
            self.cameras[0], self.cameras[k], self.R[k - 1], self.T[k - 1], self.image_size, self.distance_mm
        )

    def summary(self) -> dict:
        """The poses this registration applies (CCDs 2–4 against CCD 1), for a result's provenance."""
        return {
            "working_distance_mm": self.distance_mm,
            "relative_poses": [
                {
                    "ccd": k + 2,
                    "rotation_deg": float(np.rad2deg(np.linalg.norm(cv2.Rodrigues(np.asarray(r))[0]))),
                    "T_mm": np.asarray(t).ravel().tolist(),
                    "stereo_rms_px": s,
                }
                for k, (r, t, s) in enumerate(zip(self.R, self.T, self.stereo_rms_px))
            ],
        }

    def to_json(self) -> dict:
        cam = lambda c: {
            "camera_matrix": c.camera_matrix.tolist(),
            "dist_coeffs": c.dist_coeffs.tolist(),
            "rms_px": c.rms_px,
            "per_view_rms_px": c.per_view_rms_px,
            "std_intrinsics": c.std_intrinsics.tolist(),
            "views_used": c.views_used,
            "views_left_out": c.views_left_out,
        }
        return {
            "format": FORMAT_NAME,
            "format_version": 1,
            "image_size": list(self.image_size),
            "board": dataclasses.asdict(self.board),
            "working_distance_mm": self.distance_mm,
            "cameras": [cam(c) for c in self.cameras],
            "relative_poses": [
                {"R": np.asarray(r).tolist()} | pose for r, pose in zip(self.R, self.summary()["relative_poses"])
            ],
            "xor_misalignment_before": self.xor_before,
            "xor_misalignment_after": self.xor_after,
            "failed_views": self.failed,
            "seconds_per_view": self.seconds_per_view,
        }

    @classmethod
    def from_json(cls, data: dict, source="registration") -> "Registration":
        if data.get("format") != FORMAT_NAME:
            raise RegistrationError(f"{source}: format is {data.get('format')!r}, expected {FORMAT_NAME!r}")
        try:
            cams = [
                CameraCalibration(
                    np.array(c["camera_matrix"], np.float64),
                    np.array(c["dist_coeffs"], np.float64),
                    float(c["rms_px"]),
                    dict(c.get("per_view_rms_px", {})),
                    np.array(c.get("std_intrinsics", [])),
                    list(c.get("views_used", [])),
                    dict(c.get("views_left_out", {})),
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
        return reg


def load_registration(path) -> Registration:
    return Registration.from_json(read_json(path, "registration", RegistrationError), path)


def register(folders, board: Board, distance_mm: float | None = None, progress: bool = True) -> Registration:
    """Calibrate four CCDs from chessboard views (folder k = CCD k, views paired by sorted name)."""
    if len(folders) != 4:
        raise RegistrationError(f"four image folders are needed (CCD 1–4), got {len(folders)}")
    if distance_mm is not None and not (math.isfinite(distance_mm) and distance_mm > 0):
        raise RegistrationError(f"the working distance must be a positive number of mm, got {distance_mm}")
    views = list_views(folders)
    t0 = time.perf_counter()
    size, depth = None, None
    detections = [dict() for _ in range(4)]
    images8 = [dict() for _ in range(4)]
    failed = {}
    total = sum(len(v) for v in views)
    with tqdm(total=total, unit="view", desc="detecting corners", disable=not progress) as bar:
        for k, files in enumerate(views):
            for path in files:
                img = read_image(path)
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
                corners = detect_corners(img8, board, None if img.dtype == np.uint8 else img.astype(np.float32))
                name = path.stem
                images8[k][name] = img8
                if corners is None:
                    failed[str(path)] = "chessboard not found"
                else:
                    detections[k][name] = corners
                bar.update()
    obj = board.object_points()
    cams = []
    for k in range(4):
        try:
            cams.append(calibrate_camera(obj, detections[k], size))
        except RegistrationError as exc:
            raise RegistrationError(
                f"CCD {k + 1} ({folders[k]}): {exc}; failed: "
                + ", ".join(f for f in failed if Path(f).parent == Path(folders[k]))
            ) from None
    if distance_mm is None:  # median board distance seen by CCD 1
        dists = []
        for n in cams[0].views_used:
            ok, rvec, tvec = cv2.solvePnP(obj, detections[0][n], cams[0].camera_matrix, cams[0].dist_coeffs)
            if ok:
                dists.append(float(np.linalg.norm(tvec)))
        distance_mm = float(np.median(dists))
    Rs, Ts, stereo_rms, before, after = [], [], [], [], []
    for k in range(1, 4):
        common = [n for n in cams[0].views_used if n in cams[k].views_used]
        if len(common) < MIN_VIEWS:
            raise RegistrationError(
                f"CCD 1 and CCD {k + 1} share {len(common)} valid views; at least {MIN_VIEWS} needed"
            )
        pts1 = [detections[0][n].reshape(-1, 1, 2) for n in common]
        ptsk = [_oriented(detections[0][n], detections[k][n]).reshape(-1, 1, 2) for n in common]
        rms, *_, R, T, _, _ = cv2.stereoCalibrate(
            [obj] * len(common),
            pts1,
            ptsk,
            cams[0].camera_matrix,
            cams[0].dist_coeffs,
            cams[k].camera_matrix,
            cams[k].dist_coeffs,
            size,
            flags=cv2.CALIB_FIX_INTRINSIC,
        )
        Rs.append(R)
        Ts.append(T.ravel())
        stereo_rms.append(float(rms))
    reg = Registration(size, board, cams, Rs, Ts, stereo_rms, distance_mm, [], [], failed, 0.0)
    for k in range(1, 4):
        mx, my = reg.maps(k + 1)
        common = [n for n in cams[0].views_used if n in cams[k].views_used]
        before.append(float(np.mean([xor_ratio(images8[0][n], images8[k][n]) for n in common])))
        after.append(float(np.mean([xor_ratio(images8[0][n], images8[k][n], mx, my) for n in common])))
    reg.xor_before, reg.xor_after = before, after
    reg.seconds_per_view = (time.perf_counter() - t0) / total
    reg.views = ViewImages(images8, detections)
    return reg


def write_registration(path, reg: Registration) -> Path:
    from cohflash_jax.fileio import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(reg.to_json(), indent=1))
    return path


def from_pixel_transforms(image_size, focal_px: float, transforms, distance_mm: float = 30500.0) -> Registration:
    """Registration of four identical distortion-free cameras whose CCDs 2–4 see the scene
    through an in-plane shift (dx, dy px) and rotation (deg) about the image centre — the
    simulator's `misregistration` effect — expressed as poses (R about the optical axis, T in
    the image plane) at `distance_mm`."""
    w, h = image_size
    k = np.array([[focal_px, 0, w / 2 - 0.5], [0, focal_px, h / 2 - 0.5], [0, 0, 1]], np.float64)
    cam = CameraCalibration(k, np.zeros(5), 0.0, {}, np.zeros(0), [], {})
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
    return Registration((w, h), Board(3, 3, 1.0), [cam] * 4, Rs, Ts, [0.0] * 3, float(distance_mm), [], [], {}, 0.0)
