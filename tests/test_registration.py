"""Four-CCD registration on synthetic chessboards with known cameras, its CLI and bad input,
and registration applied in reconstruction of a misregistered capture."""

import json
import shutil

import cv2
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_calibration.board import Board
from cohflash_calibration.registration import (
    RegistrationError,
    from_pixel_transforms,
    load_registration,
    register,
    write_registration,
)
from cohflash_calibration.synthetic import board_poses, default_rig, write_rig_views
from cohflash_jax.cli import main

# its module fixtures are costly: every test of the module on one xdist worker (make test: --dist loadgroup)
pytestmark = pytest.mark.xdist_group("test_registration")

BOARD = Board(9, 6, 25.0)


@pytest.fixture(scope="module")
def rig():
    return default_rig()


@pytest.fixture(scope="module")
def views(tmp_path_factory, rig):
    """16 low-contrast 16-bit views per CCD (SWIR-like), plus one view whose board is
    partly outside CCD 3's image and one blank view in CCD 2."""
    root = tmp_path_factory.mktemp("rig")
    rng = np.random.default_rng(0)
    poses = board_poses(16, rng, BOARD)
    poses.append((poses[0][0], poses[0][1] + np.array([330.0, 0.0, 0.0])))  # board off the right edge
    dirs = write_rig_views(
        root,
        rig,
        BOARD,
        poses,
        rng=rng,
        bit_depth=16,
        black=0.02,
        white=0.07,
        background=0.04,
        noise=0.0005,
        offset=0.01,
    )
    cv2.imwrite(str(dirs[1] / "view_000.png"), np.full((512, 640), 2000, np.uint16))  # no board at all
    return dirs


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory, views):
    """`cohflash calibrate registration` of the views with a report, run once for the module:
    (its registration as `register` returned it, the JSON file, the report, what it printed)."""
    import contextlib
    import io

    from cohflash_calibration import registration as module

    out = tmp_path_factory.mktemp("cli") / "registration.json"
    report = out.with_name("report.png")
    made = []

    def kept(*args, **kwargs):
        made.append(register(*args, **kwargs))
        return made[-1]

    printed = io.StringIO()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(printed):
        patch.setattr(module, "register", kept)
        argv = ["calibrate", "registration", "--images", *map(str, views), "--board", "9x6", "--square-mm", "25"]
        rc = main([*argv, "--out", str(out), "--report", str(report), "--quiet"])
    assert rc == 0 and len(made) == 1
    return made[0], out, report, printed.getvalue()


@pytest.fixture(scope="module")
def registration(cli_run):
    return cli_run[0]


def test_recovers_intrinsics_and_poses_of_known_cameras(rig, registration):
    for cam, est in zip(rig, registration.cameras):
        k, kt = est.camera_matrix, cam.camera_matrix
        for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)):  # fx, fy, cx, cy within 0.5 %
            assert abs(k[i, j] / kt[i, j] - 1) < 0.005
        assert est.rms_px < 0.3
        assert max(est.per_view_rms_px.values()) < 0.3
    for cam, r, t in zip(rig[1:], registration.R, registration.T):
        angle = np.rad2deg(np.linalg.norm(cv2.Rodrigues(r @ cam.R.T)[0]))
        assert angle < 0.1
        assert np.linalg.norm(t - cam.T) < 1.0
    assert all(s < 0.3 for s in registration.stereo_rms_px)


def test_failed_views_are_listed_and_left_out(views, registration):
    failed = set(registration.failed)
    assert str(views[1] / "view_000.png") in failed  # blank
    assert any(f.endswith("view_016.png") for f in failed)  # board partly outside
    assert "view_000" not in registration.cameras[1].views_used
    assert "view_000" in registration.cameras[0].views_used


def test_maps_match_the_true_cameras_and_xor_drops(rig, registration):
    from cohflash_calibration.registration import CameraCalibration, pixel_maps

    true = [CameraCalibration(c.camera_matrix, c.dist_coeffs, 0, {}, np.zeros(0), [], {}) for c in rig]
    for k in (2, 3, 4):
        mx, my = registration.maps(k)
        tx, ty = pixel_maps(
            true[0], true[k - 1], rig[k - 1].R, rig[k - 1].T, rig[0].image_size, registration.distance_mm
        )
        err = np.hypot(mx - tx, my - ty)
        # everywhere within 4 of its stated σ; where the board went, right to a tenth of a pixel
        hull = cv2.convexHull(np.concatenate(list(registration.views.corners[0].values())).astype(np.float32))
        m = registration.map_sigma_px[k - 2]
        covered = []
        for j, v in enumerate(np.round(m["v"]).astype(int)):
            for i, u in enumerate(np.round(m["u"]).astype(int)):
                assert err[v, u] < 4 * m["sigma"][j, i] + 0.05, (k, u, v, err[v, u], m["sigma"][j, i])
                if cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0:
                    covered.append(err[v, u])
        assert len(covered) > 300 and np.median(covered) < 0.1, (len(covered), np.median(covered))
    for before, after in zip(registration.xor_before, registration.xor_after):
        assert after < 0.02 < before  # the paper reports 1.5–2 % after registration


def test_cli_writes_registration_and_report_that_round_trip(tmp_path, cli_run):
    _, out, report, text = cli_run
    assert "XOR misalignment" in text and "view_000.png: chessboard not found" in text and "verdict: usable" in text
    data = json.loads(out.read_text())
    assert data["format"] == "cohflash-registration" and len(data["relative_poses"]) == 3
    reg = load_registration(out)
    np.testing.assert_allclose(reg.cameras[2].camera_matrix, np.array(data["cameras"][2]["camera_matrix"]))
    assert report.read_bytes()[:4] == b"\x89PNG"
    # a binary file in the JSON's place (the report PNG, an HDF5 capture) is named as such
    with pytest.raises(RegistrationError, match=f"{report.name}: not a registration JSON file"):
        load_registration(report)
    # tampered files: a NaN intrinsic, a pose missing (before: accepted, and an IndexError)
    bad = tmp_path / "bad.json"
    for change, match in (
        (lambda d: d["cameras"][1]["camera_matrix"][0].__setitem__(0, float("nan")), "NaN"),
        (lambda d: d["relative_poses"].pop(), "3 relative poses, got 4 and 2"),
    ):
        tampered = json.loads(out.read_text())
        change(tampered)
        bad.write_text(json.dumps(tampered))
        with pytest.raises(RegistrationError, match=match):
            load_registration(bad)


def test_bad_inputs_name_the_problem(tmp_path, views):
    with pytest.raises(RegistrationError, match="not found"):
        register([tmp_path / "nope"] + list(views[1:]), BOARD, progress=False)
    short = tmp_path / "short"
    shutil.copytree(views[0], short)
    first = sorted(short.iterdir())[0]
    first.unlink()
    # a view missing from one folder is named and used in the others (it used to abort the run)
    from cohflash_calibration.corners import list_views

    assert list_views([short] + list(views[1:])).missing == {first.stem: [1]}
    sized = tmp_path / "sized"
    shutil.copytree(views[3], sized)
    odd = sorted(sized.iterdir())[5]
    cv2.imwrite(str(odd), np.zeros((100, 120), np.uint16))
    with pytest.raises(RegistrationError, match=f"{odd.name}.*size"):
        register(list(views[:3]) + [sized], BOARD, progress=False)
    depth = tmp_path / "depth"
    shutil.copytree(views[3], depth)
    odd = sorted(depth.iterdir())[5]
    cv2.imwrite(str(odd), np.zeros((512, 640), np.uint8))
    with pytest.raises(RegistrationError, match=f"{odd.name}.*bit depth"):
        register(list(views[:3]) + [depth], BOARD, progress=False)
    few = [tmp_path / f"few{k}" for k in range(4)]
    for k, d in enumerate(few):
        d.mkdir()
        for i in range(3):
            cv2.imwrite(str(d / f"v{i}.png"), np.full((64, 64), 128 + k, np.uint8))
    with pytest.raises(RegistrationError, match="too few valid views"):
        register(few, BOARD, progress=False)
    # one folder four times, or four copies of it: refused (they registered as 0.000° apart)
    with pytest.raises(RegistrationError, match="CCD 2's folder .* is CCD 1's"):
        register([views[0]] * 4, BOARD, progress=False)
    copy = tmp_path / "copy"
    shutil.copytree(views[0], copy)
    with pytest.raises(RegistrationError, match="CCD 2's images .* byte-identical to CCD 1's"):
        register([views[0], copy] + list(views[2:]), BOARD, progress=False)
    with pytest.raises(ValueError, match="COLSxROWS"):
        Board.parse("9by6", 25)
    with pytest.raises(RegistrationError, match="working distance must be a positive"):
        register(list(views), BOARD, distance_mm=-5.0, progress=False)
    # colour and alpha channels are dropped to grey (BGRA used to fail inside OpenCV)
    from cohflash_calibration.registration import read_image

    grey = cv2.imread(str(sorted(views[0].iterdir())[0]), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(tmp_path / "bgra.png"), np.dstack([grey] * 4))
    np.testing.assert_array_equal(read_image(tmp_path / "bgra.png"), grey)


def test_registration_reduces_depth_errors_at_edges(tmp_path):
    """The simulator's misregistration effect on, then reconstruction with and without the
    registration that undoes it: depth errors on the staircase's edges drop."""
    from cohflash_jax.simulate import simulate_to_file

    transforms = ((4.0, -3.0, 0.8), (-3.5, 2.5, -0.6), (2.5, 4.0, 0.5))
    scene = cf.staircase(effects=("sidebands", "shot_noise", "read_noise", "quantization", "misregistration"))
    h, w = 48, 64
    inst = cf.Instrument.paper(3000, errors=cf.InstrumentErrors(misregistration_px_px_deg=transforms))
    cap = tmp_path / "mis.h5"
    simulate_to_file(cap, scene, inst, h, w, seed=4, progress=False)
    focal = (w / 2) / np.tan(np.deg2rad(inst.field_of_view_deg[0]) / 2)
    reg_path = tmp_path / "reg.json"
    write_registration(reg_path, from_pixel_transforms((w, h), focal, transforms))
    results = {}
    for name, extra in (("raw", []), ("registered", ["--registration", str(reg_path)])):
        out = tmp_path / f"{name}.h5"
        assert main(["reconstruct", str(cap), "--out", str(out), "--quiet", *extra]) == 0
        import h5py

        with h5py.File(out) as f:
            results[name] = {k: f[k][()] for k in ("depth_m", "valid", "fit_status")}
        with h5py.File(cap) as f:
            truth = f["truth/depth_m"][()].astype(np.float64)
    gy, gx = np.gradient(truth)
    step = ((np.abs(gx) > 0) | (np.abs(gy) > 0)).astype(np.uint8)
    edge = cv2.dilate(step, np.ones((9, 9), np.uint8)).astype(bool)  # within 4 px of a depth edge
    b = 8  # image border: not all CCDs see it
    edge[:b], edge[-b:], edge[:, :b], edge[:, -b:] = False, False, False, False

    def edge_error(r):
        err = np.abs(r["depth_m"] - truth)
        err[~r["valid"].astype(bool)] = 0.2  # an invalid edge pixel counts as a 200 mm error
        return np.mean(err[edge])

    raw, reg = edge_error(results["raw"]), edge_error(results["registered"])
    print(f"mean |depth error| within 4 px of edges: {raw * 1e3:.1f} mm unregistered, {reg * 1e3:.1f} mm registered")
    assert reg < 0.5 * raw, (raw, reg)
    assert np.all(results["registered"]["fit_status"][:2] == 8)  # CCD 2 (dy = −3 px) does not see the top rows
