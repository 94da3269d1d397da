"""The joint solve of four cameras against truth: its stated σ tested as a claim (Monte Carlo pulls
of the poses, intrinsics and pixel maps, fixed seeds), and a bad corner rejected alone."""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from cohflash_calibration import joint
from cohflash_calibration.board import Board

from .jax_events import traces_counted

# its module fixtures are costly: every test of the module on one xdist worker (make test: --dist loadgroup)
pytestmark = pytest.mark.xdist_group("test_joint_solve")

BOARD = Board(9, 6, 25.0)
OBJ = BOARD.object_points().astype(np.float64)
LAYOUT = joint.Layout(4, 10)
NOISE_PX = 0.2


def truth() -> np.ndarray:
    rng = np.random.default_rng(7)
    x = np.zeros(LAYOUT.size)
    for c in range(4):
        x[LAYOUT.intrinsics(c)] = [530 + 5 * c, 531 + 5 * c, 320 + 3 * c, 240 - 2 * c, -0.25, 0.1, 1e-3, -5e-4, 0.0]
    for c in range(1, 4):
        x[LAYOUT.camera_pose(c)] = [0.01 * c, -0.008, 0.005 * c, -80.0 + c, 1.0 * c, -0.5]
    centre = OBJ.mean(axis=0)
    for v in range(LAYOUT.views):
        r = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        rot = cv2.Rodrigues(r)[0]
        t = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(380, 480)]) - rot @ centre
        x[LAYOUT.board_pose(v)] = [*r, *t]
    return x


@pytest.fixture(scope="module")
def monte_carlo():
    """20 noisy corner sets of one rig, each solved from a perturbed start."""
    x_true = truth()
    clean = np.asarray(joint.predict(jnp.asarray(x_true), LAYOUT, jnp.asarray(OBJ)))
    seen = np.ones(clean.shape[:3], bool)
    runs = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        observed = clean + NOISE_PX * rng.standard_normal(clean.shape)
        start = x_true * (1 + 1e-4 * rng.standard_normal(x_true.size))
        runs.append(joint.solve(start, LAYOUT, OBJ, observed, seen))
    return x_true, runs


def test_pose_and_intrinsic_pulls_have_unit_spread(monte_carlo):
    x_true, runs = monte_carlo
    idx = np.r_[[i for c in (1, 2, 3) for i in range(LAYOUT.camera_pose(c).start, LAYOUT.camera_pose(c).stop)]]
    idx = np.concatenate([idx, [LAYOUT.intrinsics(c).start + j for c in range(4) for j in range(4)]])
    pulls = np.array([(r.params[idx] - x_true[idx]) / np.sqrt(np.diag(r.covariance)[idx]) for r in runs])
    assert abs(pulls.mean()) < 0.15
    assert 0.85 < pulls.std() < 1.15, pulls.std(axis=0)
    assert np.abs(pulls).max() < 5
    # the noise it states is the noise it was given
    sigmas = np.array([r.sigma_px for r in runs])
    assert np.all(np.abs(sigmas / NOISE_PX - 1) < 0.05)
    assert not any(r.dropped_views for r in runs)
    assert np.mean([r.inliers.mean() for r in runs]) > 0.999


def test_pixel_map_sigma_covers_the_map_error_where_the_board_went(monte_carlo):
    """Over the part of CCD 1 the board covered; outside it the map is extrapolated and its σ,
    large there (tens of px), is a linearisation that the report shows but does not rely on."""
    x_true, runs = monte_carlo
    pix = np.stack(np.meshgrid(np.linspace(100, 450, 4), np.linspace(110, 360, 4)), -1).reshape(-1, 2)
    fn = joint.map_function(LAYOUT, 2, 450.0, None)
    truth_map = np.asarray(fn(jnp.asarray(x_true), jnp.asarray(pix)))
    pulls = []
    for r in runs:
        sigma = joint.map_sigma_at(r, 2, pix, 640, 450.0, False)
        err = np.asarray(fn(jnp.asarray(r.params), jnp.asarray(pix))) - truth_map
        pulls.append(np.linalg.norm(err, axis=1) / sigma)
    pulls = np.concatenate(pulls)
    # σ is the larger axis of the 2×2 covariance: the error's norm over it lies between |N(0,1)|
    # (a thin ellipse) and χ₂ (a circle): P(< 1) in [0.39, 0.68], P(< 2.5) in [0.956, 0.988]
    assert 0.3 < np.mean(pulls < 1.0) < 0.8
    assert np.mean(pulls < 2.5) > 0.92


def test_map_sigma_is_the_whole_covariance_propagated_and_one_program_serves_every_camera(monte_carlo, monkeypatch):
    """σ from the map's 24 parameters alone equals the whole joint covariance propagated
    through the Jacobian of the whole parameter vector (the board poses do not move the map),
    mirrored CCDs included; other cameras, distances and flips make no new program."""
    import jax

    _, runs = monte_carlo
    r = runs[0]
    pix = np.stack(np.meshgrid(np.linspace(0, 639, 5), np.linspace(0, 479, 4)), -1).reshape(-1, 2)
    for camera, distance, mirrored in [(1, 450.0, False), (3, 900.0, True)]:
        fn = joint.map_function(LAYOUT, camera, distance, 640 if mirrored else None)
        jac = np.asarray(jax.jit(jax.jacfwd(fn))(jnp.asarray(r.params), jnp.asarray(pix)))  # one program, not op by op
        assert np.count_nonzero(np.abs(jac).sum(axis=(0, 1))) == 24
        cov = np.einsum("pin,nm,pjm->pij", jac, r.covariance, jac)
        whole = np.sqrt(np.linalg.eigvalsh(cov)[:, -1])
        np.testing.assert_allclose(joint.map_sigma_at(r, camera, pix, 640, distance, mirrored), whole, rtol=1e-9)
    traces = []  # the map traced again: a new program
    unproject = joint.unproject
    monkeypatch.setattr(joint, "unproject", lambda *a: traces.append(1) or unproject(*a))
    for camera in (1, 2, 3):
        for distance in (300.0, 700.0):
            joint.map_sigma_at(r, camera, pix, 640, distance, camera == 2)
    assert not traces


def test_one_bad_corner_is_rejected_alone_and_the_view_kept():
    x_true = truth()
    clean = np.asarray(joint.predict(jnp.asarray(x_true), LAYOUT, jnp.asarray(OBJ)))
    rng = np.random.default_rng(99)
    observed = clean + NOISE_PX * rng.standard_normal(clean.shape)
    observed[2, 4, 17] += [4.0, -3.0]  # a glint moves one corner of CCD 3's view 4 by 5 px
    observed[0, 7, 40] += [0.0, 6.0]
    seen = np.ones(clean.shape[:3], bool)
    sol = joint.solve(x_true, LAYOUT, OBJ, observed, seen)
    rejected = np.argwhere(~sol.inliers)
    assert sorted(map(tuple, rejected)) == [(0, 7, 40), (2, 4, 17)]
    assert not sol.dropped_views
    # a whole view of CCD 2 showing another board position (out of sync) is dropped and named
    moved = observed.copy()
    moved[1, 3] = clean[1, 5] + NOISE_PX * rng.standard_normal(clean[1, 5].shape)
    sol = joint.solve(x_true, LAYOUT, OBJ, moved, seen)
    assert list(sol.dropped_views) == [(1, 3)]
    assert "out of sync" in sol.dropped_views[(1, 3)]
    assert np.linalg.norm(sol.params[LAYOUT.camera_pose(1)] - x_true[LAYOUT.camera_pose(1)]) < 0.5


def test_xor_thresholds_come_from_covered_pixels_only():
    """A low-contrast board (grey 30–60, normal for SWIR) resampled by a map that leaves 40 % of
    CCD 1 uncovered: `remap` fills those with 0, which used to drag CCD k's Otsu threshold down
    and make every covered pixel 'white' (60.8 % read for 34.7 %). The same image must XOR to 0."""
    from cohflash_calibration.registration import xor_ratio

    h, w = 60, 80
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.where(((xx // 10) + (yy // 10)) % 2 == 0, 30, 60).astype(np.uint8)
    map_x = (xx + 0.0).astype(np.float32)
    map_x[:, : int(0.4 * w)] = -5.0  # not covered
    map_y = yy.astype(np.float32)
    assert xor_ratio(img, img, map_x, map_y) == 0.0


def test_blank_views_pad_the_solve_to_its_bucket_and_change_nothing(monkeypatch):
    """`solve` pads the views to a multiple of `VIEW_BUCKET` with blank ones, so that rigs of
    9 and 13 views run the programs 10 views compiled (no program traced), and the blank
    views change nothing: the solution, its covariance, σ and inliers equal those of the solve
    without padding (`VIEW_BUCKET` 1) to rounding."""
    x_true = truth()
    clean = np.asarray(joint.predict(jnp.asarray(x_true), LAYOUT, jnp.asarray(OBJ)))
    observed = clean + NOISE_PX * np.random.default_rng(3).standard_normal(clean.shape)
    seen = np.ones(clean.shape[:3], bool)
    start = x_true * (1 + 1e-4 * np.random.default_rng(4).standard_normal(x_true.size))
    padded = joint.solve(start, LAYOUT, OBJ, observed, seen)
    with traces_counted() as traced:
        for views in (9, 13):
            layout = joint.Layout(4, views)
            reps = -(-views // LAYOUT.views)
            poses = np.tile(start[LAYOUT.board_pose(0).start :], reps)[: views * 6]
            more = np.concatenate([start[: LAYOUT.board_pose(0).start], poses])
            obs = np.concatenate([observed] * reps, axis=1)[:, :views]
            joint.solve(more, layout, OBJ, obs, np.ones(obs.shape[:3], bool))
    assert not traced, "a rig of another number of views traced programs of its own"
    monkeypatch.setattr(joint, "VIEW_BUCKET", 1)
    alone = joint.solve(start, LAYOUT, OBJ, observed, seen)
    np.testing.assert_allclose(padded.params, alone.params, rtol=1e-9, atol=1e-9)
    # the covariance of an ill-conditioned JᵀJ: to rounding of its largest entries, its σ closer
    scale = np.abs(alone.covariance).max()
    np.testing.assert_allclose(padded.covariance, alone.covariance, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(np.diag(padded.covariance), np.diag(alone.covariance), rtol=1e-5)
    assert padded.sigma_px == pytest.approx(alone.sigma_px, rel=1e-9)
    np.testing.assert_array_equal(padded.inliers, alone.inliers)
