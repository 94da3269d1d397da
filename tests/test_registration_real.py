"""Registration on real photographs (OpenCV's stereo sample set, tests/data/opencv_stereo): four-CCD
folders built from the left and right cameras, plus the cases a real hybrid produces — a mirrored
CCD, one mounted at 180°, an out-of-sync view, a corrupt file, a missing view, a wrong --board —
each giving the right registration or a refusal that names the cause. And a mirrored CCD
resampled end to end through `reconstruct --registration`."""

import json
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from cohflash_calibration.board import Board
from cohflash_calibration.registration import (
    RegistrationError,
    from_pixel_transforms,
    load_registration,
    register,
    write_registration,
)
from cohflash_jax.cli import main

from .independent_writer import Writer

# its module fixtures are costly: every test of the module on one xdist worker (make test: --dist loadgroup)
pytestmark = pytest.mark.xdist_group("test_registration_real")

DATA = Path(__file__).parent / "data" / "opencv_stereo"
BOARD = Board(9, 6, 25.0)  # the sample's squares are about an inch; the size only scales T


def angle_deg(r) -> float:
    return float(np.rad2deg(np.linalg.norm(cv2.Rodrigues(np.asarray(r, np.float64))[0])))


def rz180() -> np.ndarray:
    return np.diag([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """Per camera, its views named view01…view14 (no 10), in several transformed copies."""
    root = tmp_path_factory.mktemp("real")

    def make(name, side, transform=None, suffix=".png"):
        d = root / name
        d.mkdir()
        for p in sorted(DATA.glob(f"{side}*.jpg")):
            target = d / (p.stem.replace(side, "view") + suffix)
            if transform is None and suffix == ".jpg":
                shutil.copy(p, target)
            else:
                img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
                assert cv2.imwrite(str(target), img if transform is None else np.ascontiguousarray(transform(img)))
        return d

    f = {
        "L": make("L", "left", suffix=".jpg"),
        "R": make("R", "right", suffix=".jpg"),
        "L_png": make("L_png", "left"),  # pixel-identical to L, other bytes
        "R_png": make("R_png", "right"),
        "L_180": make("L_180", "left", lambda i: i[::-1, ::-1]),
        "R_mirror": make("R_mirror", "right", lambda i: i[:, ::-1]),
        "R_sync": make("R_sync", "right", suffix=".jpg"),
    }
    shutil.copy(f["R_sync"] / "view08.jpg", f["R_sync"] / "view07.jpg")  # view 7 shows view 8's board
    (f["R_mirror"] / "view05.png").unlink()  # a view missing from one folder
    cut = f["R_mirror"] / "view03.png"  # a file cut short in copying
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    return f


@pytest.fixture(scope="module")
def plain(folders):
    return register([folders[k] for k in ("L", "R", "L_png", "R_png")], BOARD, progress=False)


def test_a_pixel_identical_copy_registers_as_the_identity(plain):
    assert not any(c.mirrored for c in plain.cameras)
    assert angle_deg(plain.R[1]) < 1e-3 and np.linalg.norm(plain.T[1]) < 1e-3
    np.testing.assert_allclose(plain.cameras[2].camera_matrix, plain.cameras[0].camera_matrix, rtol=1e-6)
    # CCD 4 is CCD 2's camera: the same pose
    assert angle_deg(plain.R[2] @ plain.R[0].T) < 1e-3 and np.linalg.norm(plain.T[2] - plain.T[0]) < 1e-3
    assert plain.corner_sigma_px < 0.3 and max(plain.stereo_rms_px) < 0.4
    assert not any(c.views_left_out for c in plain.cameras)


def test_the_joint_pose_agrees_with_opencvs_joint_stereo_solve_within_its_sigma(plain, folders):
    """An independent joint solve: `cv2.stereoCalibrate` refining both cameras' intrinsics with
    the pose, on the same corners. The difference stays within 3σ of the stated pose σ."""
    corners = plain.views.corners
    names = [n for n in corners[0] if n in corners[1]]
    obj = BOARD.object_points()
    k1, d1 = plain.cameras[0].camera_matrix, plain.cameras[0].dist_coeffs
    k2, d2 = plain.cameras[1].camera_matrix, plain.cameras[1].dist_coeffs
    rms, *_, r, t, _, _ = cv2.stereoCalibrate(
        [obj] * len(names),
        [corners[0][n].astype(np.float32).reshape(-1, 1, 2) for n in names],
        [corners[1][n].astype(np.float32).reshape(-1, 1, 2) for n in names],
        k1.copy(),
        d1.copy(),
        k2.copy(),
        d2.copy(),
        plain.image_size,
        flags=cv2.CALIB_USE_INTRINSIC_GUESS,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12),
    )
    rot_sd, t_sd = plain.pose_sigma(0)
    assert angle_deg(r @ plain.R[0].T) < 3 * np.linalg.norm(rot_sd)
    assert np.all(np.abs(t.ravel() - plain.T[0]) < 3 * t_sd + 1e-3)
    assert rms < 0.4


def test_mirrored_rotated_out_of_sync_corrupt_and_missing_views_in_one_rig(folders, plain, tmp_path, capsys):
    reg = register([folders[k] for k in ("L", "R_sync", "L_180", "R_mirror")], BOARD, progress=False)
    # CCD 3 is CCD 1 turned by 180°: exactly 180° about the optical axis, no translation
    assert angle_deg(reg.R[1] @ rz180().T) < 1e-3 and np.linalg.norm(reg.T[1]) < 1e-3
    assert not reg.cameras[2].mirrored
    # CCD 4 is CCD 2 seen through a mirror: detected, and its pose is CCD 2's
    assert reg.cameras[3].mirrored and not reg.cameras[1].mirrored
    rot_sd, t_sd = plain.pose_sigma(0)
    assert angle_deg(reg.R[2] @ plain.R[0].T) < 3 * np.linalg.norm(rot_sd)
    assert np.all(np.abs(reg.T[2] - plain.T[0]) < 3 * t_sd)
    # the out-of-sync view is dropped in CCD 2 alone, and named; nothing else is lost
    assert list(reg.cameras[1].views_left_out) == ["view07"]
    assert "out of sync" in reg.cameras[1].views_left_out["view07"]
    assert not any(c.views_left_out for k, c in enumerate(reg.cameras) if k != 1)
    assert angle_deg(reg.R[0] @ plain.R[0].T) < 3 * np.linalg.norm(rot_sd)
    # the cut file is named as corrupt, the missing view as missing
    (path, reason), *_ = [(p, r) for p, r in reg.failed.items() if p.endswith("view03.png")]
    assert "corrupt" in reason
    assert reg.missing_views == {"view05": [4]}
    assert max(reg.stereo_rms_px) < 0.4
    # the file says so, and `info` shows it
    path = write_registration(tmp_path / "rig.json", reg)
    assert load_registration(path).cameras[3].mirrored
    assert main(["info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "CCD 4 (mirrored)" in text and "CCD 2 view07: " in text and "views missing from a folder: 1" in text


@pytest.mark.parametrize("board", ["7x5", "8x6", "3x3"])
def test_a_wrong_board_is_refused_by_name(folders, board, tmp_path, capsys):
    out = tmp_path / "registration.json"
    args = ["calibrate", "registration", "--images", *(str(folders[k]) for k in ("L", "R", "L_png", "R_png"))]
    rc = main([*args, "--board", board, "--square-mm", "25", "--out", str(out), "--quiet"])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err
    # each names part of OpenCV's 9×6 board: the whole board, found in the views, is named
    assert f"--board {board} does not match the board" in err and "pass --board 9x6" in err, err


def test_a_board_larger_than_the_views_show_is_refused_after_the_first_folder(folders, tmp_path, capsys):
    """--board 10x7 on OpenCV's 9×6 board: no view of CCD 1 shows it, so the registration is
    refused once that folder is read (it cannot succeed), naming --board as the likely cause."""
    few = {}  # three views a CCD: each failed search is slow
    for k in ("L", "R", "L_png", "R_png"):
        few[k] = tmp_path / k
        few[k].mkdir()
        for p in sorted(folders[k].iterdir())[:3]:
            shutil.copy(p, few[k] / p.name)
    out = tmp_path / "registration.json"
    args = ["calibrate", "registration", "--images", *(str(few[k]) for k in ("L", "R", "L_png", "R_png"))]
    assert main([*args, "--board", "10x7", "--square-mm", "25", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert not out.exists() and "CCD 1" in err and "no view shows a 10x7 chessboard; check --board" in err, err
    assert str(few["R"]) not in err  # the other folders were not searched


def test_the_loader_refuses_a_registration_that_fails_the_gates(plain, tmp_path):
    path = write_registration(tmp_path / "reg.json", plain)
    assert load_registration(path).cameras[3].mirrored is False
    data = json.loads(path.read_text())
    data["relative_poses"][1]["stereo_rms_px"] = 48.5  # the 180° CCD before the fix
    path.write_text(json.dumps(data))
    with pytest.raises(RegistrationError, match="CCD 3 against CCD 1: stereo RMS 48.50 px"):
        load_registration(path)
    data["relative_poses"][1]["stereo_rms_px"] = 0.2
    data["cameras"][2]["std_intrinsics"][0] = float("nan")
    path.write_text(json.dumps(data))
    with pytest.raises(RegistrationError, match="CCD 3: σ of the intrinsics is NaN"):
        load_registration(path)


def test_a_mirrored_ccd_is_resampled_end_to_end_in_reconstruct(tmp_path):
    """A capture whose CCD 4 image is flipped left–right (a CCD behind a mirror), written by the
    independent writer: with a registration that says so, the depth map is the unflipped
    capture's; without it, CCD 4's pixels pair with the wrong scene points and depth is lost."""
    h, w = 8, 8  # test_carrier's shape: the plain programs compile once a run
    depth = 30.5 + 0.002 * np.arange(w)[None, :] + np.zeros((h, w))  # a ramp: mirroring matters
    writer = Writer()
    plain_cap, mirrored_cap = tmp_path / "plain.h5", tmp_path / "mirrored.h5"
    writer.write(plain_cap, depth, np.random.default_rng(3))

    def flip_ccd4(frames):
        frames = frames.copy()
        frames[3] = frames[3][..., ::-1]
        return frames

    writer.write(mirrored_cap, depth, np.random.default_rng(3), alter=flip_ccd4)
    reg_path = write_registration(
        tmp_path / "mirror.json", from_pixel_transforms((w, h), 500.0, [(0, 0, 0)] * 3, mirrored=(False, False, True))
    )
    results = {}
    for name, cap, extra in (
        ("plain", plain_cap, []),
        ("mirrored, registered", mirrored_cap, ["--registration", str(reg_path)]),
        ("mirrored, raw", mirrored_cap, []),
    ):
        out = tmp_path / f"depth {name}.h5"
        assert main(["reconstruct", str(cap), "--out", str(out), "--quiet", *extra]) == 0
        with h5py.File(out) as f:
            results[name] = (f["depth_m"][()], f["valid"][()].astype(bool), f["sigma_m"][()])
    d0, v0, s0 = results["plain"]
    d1, v1, _ = results["mirrored, registered"]
    assert v0.all() and v1.all()
    assert np.max(np.abs(d1 - d0)) < 1e-6  # the same frames, resampled at whole pixels
    d2, v2, _ = results["mirrored, raw"]
    # unregistered, CCD 4 carries the mirror pixel's tone and carrier (3 of the 4 CCDs still carry
    # the pixel's own): the depths move, far beyond the registered path's rounding
    moved = np.abs(d2 - d0)[v2]
    print(f"median |depth change| unregistered: {np.median(moved) * 1e3:.2f} mm, σ {np.median(s0) * 1e3:.2f} mm")
    assert np.max(moved) > max(1e-4, 100 * np.max(np.abs(d1 - d0)))


def test_mirrored_option_is_checked_before_any_work(folders, tmp_path, capsys):
    out = tmp_path / "registration.json"
    args = ["calibrate", "registration", "--images", *(str(folders[k]) for k in ("L", "R", "L_png", "R_png"))]
    rc = main([*args, "--board", "9x6", "--square-mm", "25", "--out", str(out), "--mirrored", "5=yes", "--quiet"])
    assert rc == 2 and not out.exists()
    assert "--mirrored '5=yes': expected CCD=yes|no with CCD 2, 3 or 4" in capsys.readouterr().err
