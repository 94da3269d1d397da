"""Carrier drift handled by default (`--carrier auto`): a drift common to the capture is found
and removed, a static capture is aligned statically, the depth file says which ran and why,
and a depth that comes from untracked drift is never valid."""

import h5py
import jax
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.cli import main
from cohflash_jax.reconstruct import ReconstructOptions, align_carrier, reconstruct_array

from .independent_writer import Writer, random_walk_rad

NOISE = ("shot_noise", "read_noise", "dark_current", "quantization")


@pytest.fixture(scope="module")
def turbulent():
    """A 3000-frame planar capture whose carrier random-walks ~3 rad (simulator's turbulence),
    and the same noise draws without drift."""
    inst = cf.Instrument.paper(3000)
    key = jax.random.key(7)
    frames = {
        name: cf.simulate(cf.planar(effects=NOISE + extra), inst, 12, 12, key)
        for name, extra in (("static", ()), ("drift", ("turbulence",)))
    }
    return inst, frames


def test_auto_removes_a_common_drift_without_a_flag(turbulent):
    inst, frames = turbulent
    err = {}
    for name in ("static", "drift"):
        out = reconstruct_array(frames[name], inst, ReconstructOptions(progress=False))
        assert out["valid"].all(), name
        err[name] = out["depth_m"] - 30.5
        assert np.all(np.abs(err[name]) < 6 * out["sigma_m"])
    assert np.std(err["drift"]) < 1.1 * np.std(err["static"])


def test_untracked_drift_is_never_a_valid_depth(turbulent):
    inst, frames = turbulent
    out = reconstruct_array(frames["drift"], inst, ReconstructOptions(carrier="static", progress=False))
    valid = out["valid"]
    assert np.all(np.abs(out["depth_m"][valid] - 30.5) < 6 * out["sigma_m"][valid])


@pytest.mark.parametrize("name", ["static", "drift"])
def test_the_survey_leaves_out_pixels_with_a_non_finite_frame_after_the_ranked_ones(turbulent, name):
    """Integer frames are ranked on their first frames (`drift.DRIFT_RANK_FRAMES`); floating
    ones (a registered capture's) on all of them, so that a pixel with a NaN frame anywhere is
    left out of the sample, not only one with a NaN among the first frames: a NaN at frame 2000
    in 50 of the 144 pixels leaves 94 in the sample, and the verdict is the one without them."""
    import warnings

    from cohflash_jax.estimate.drift import DRIFT_RANK_FRAMES, choose_carrier_alignment

    inst, frames = turbulent
    x = np.asarray(frames[name], np.float32).reshape(4, 3000, -1)
    assert DRIFT_RANK_FRAMES < 2000
    x[:, 2000, 10:60] = np.nan
    weights, bias = inst.hybrid.iq_matrix_dn(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no NaN reaches the survey's arithmetic
        alignment = choose_carrier_alignment("auto", x, weights, bias)
        without = choose_carrier_alignment("auto", np.delete(x, np.s_[10:60], axis=2), weights, bias)
    assert "in 94 sample pixels" in alignment.reason, alignment.reason
    assert alignment.mode == without.mode == ("static" if name == "static" else "common")
    if name == "drift":
        np.testing.assert_allclose(alignment.phase_rad, without.phase_rad, rtol=0, atol=1e-12)


def _meta(path):
    with h5py.File(path) as f:
        meta = dict(f.attrs)
        return meta, f["depth_m"][()], f["valid"][()].astype(bool), f["sigma_m"][()]


def test_independent_drifting_capture_reconstructs_by_default_and_says_why(tmp_path):
    rng = np.random.default_rng(11)
    writer = Writer(drift_rad=random_walk_rad(3000, 3.0, rng))
    cap, out = tmp_path / "drift.h5", tmp_path / "depth.h5"
    writer.write(cap, np.full((12, 12), 30.5), rng)
    assert main(["reconstruct", str(cap), "--out", str(out), "--quiet"]) == 0
    meta, depth, valid, sigma = _meta(out)
    assert meta["carrier_alignment"] == "common"
    assert "drift found" in meta["carrier_reason"]
    assert valid.all()
    assert np.std(depth - 30.5) < 1.3 * writer.crlb_m()
    assert np.all(np.abs(depth - 30.5) < 6 * sigma)


def test_a_drift_the_survey_finds_after_the_first_tile_is_dispatched_reaches_its_pixels(tmp_path):
    """A capture read straight into its sub-tiles is dispatched from a thread while the next
    tile is read (`reconstruct.api.TileFeeder`), and the carrier survey is waited for only once
    the second tile is read: the first tile is dispatched as static before the survey has
    found the drift, and must be dispatched again with it. Every pixel of both tiles is then
    valid and within 6 σ; a first tile left static would have no valid pixel."""
    from cohflash_jax.capture import Capture
    from cohflash_jax.reconstruct.engine import PieceReader

    from .independent_writer import PAPER_FREQUENCIES_HZ

    rng = np.random.default_rng(3)
    n = 1200  # a long sweep (its carrier surveyed), short enough to write and compile quickly
    writer = Writer(frequencies_hz=PAPER_FREQUENCIES_HZ[:n], drift_rad=random_walk_rad(n, 3.0, rng))
    cap, out = tmp_path / "drift.h5", tmp_path / "depth.h5"
    writer.write(cap, np.full((64, 64), 30.5), rng, chunks=(1, 4, 32, 64))
    with Capture(cap) as c:
        assert PieceReader.of(c, 32) is not None  # tiles of 32 rows read into their sub-tiles
    assert main(["reconstruct", str(cap), "--out", str(out), "--tile-rows", "32", "--quiet"]) == 0
    meta, depth, valid, sigma = _meta(out)
    assert meta["carrier_alignment"] == "common"
    assert valid[:32].all() and valid[32:].all()
    assert np.all(np.abs(depth - 30.5) < 6 * sigma)


def test_auto_on_a_static_capture_aligns_statically(tmp_path):
    rng = np.random.default_rng(12)
    cap, out = tmp_path / "static.h5", tmp_path / "depth.h5"
    Writer().write(cap, np.full((8, 8), 30.5), rng)
    assert main(["reconstruct", str(cap), "--out", str(out), "--quiet"]) == 0
    meta, *_ = _meta(out)
    assert meta["carrier_alignment"] == "static"
    assert "no common carrier drift" in meta["carrier_reason"]
    tracked = align_carrier(ReconstructOptions(carrier="tracked"), cf.Instrument.paper(3000), None)
    assert tracked.mode == "tracked" and "requested" in tracked.reason


def test_a_rolling_off_modulator_is_not_taken_for_a_drift():
    """A static capture of a target at one depth through the study's hybrid errors and a
    modulator rolling off along the sweep: the mean term's amplitude changes slowly, in every
    pixel alike, and traced a line the circle fit took for an arc (a 0.8 rad "drift"). Removed,
    it failed every pixel's fit (χ² 14). The tones' axis does not turn: static, and valid."""
    inst = cf.Instrument.paper(3000, system_delay_s=2 * 1.9 / cf.SPEED_OF_LIGHT_M_PER_S)
    noise = ("shot_noise", "read_noise", "dark_current", "quantization")
    scene = cf.planar(
        30.5, 0.9, tilt_m_per_fov=(2e-4, 1.3e-4), effects=noise + ("hybrid_errors", "beta_rolloff", "sidebands")
    )
    frames = np.asarray(cf.simulate(scene, inst, 16, 16, jax.random.key(4)))
    out_alignment = align_carrier(ReconstructOptions(), inst, frames.reshape(4, 3000, -1))
    assert out_alignment.mode == "static", out_alignment.reason
    assert "axis does not turn" in out_alignment.reason
    assert reconstruct_array(frames, inst, ReconstructOptions(progress=False))["valid"].mean() > 0.95


@pytest.mark.parametrize("seed", [6, 21])
def test_a_strong_drift_through_the_hybrid_errors_is_found(seed):
    """The same capture with the simulator's turbulence, at seeds whose drift spans ~5 rad: the
    drift test once read the tones' axis from a moving-average high-pass, which also passed the
    mean term's drift-induced wobble (its square lies on the opposite axis) and cancelled the
    turn (0.06 rad against a 1.1 rad drift): the drift was rejected and 7 in 50 turbulent
    calibrations refused. Read from the tone's own band, the axis follows the drift."""
    from cohflash_jax.estimate.drift import initial_common_drift, tone_axis_rotation
    from cohflash_jax.estimate.iq import iq_from_frames
    from cohflash_jax.simulate import turbulence_phase

    inst = cf.Instrument.paper(3000, system_delay_s=2 * 1.9 / cf.SPEED_OF_LIGHT_M_PER_S)
    scene = cf.planar(
        30.5,
        0.9,
        tilt_m_per_fov=(2e-4, 1.3e-4),
        effects=NOISE + ("hybrid_errors", "beta_rolloff", "sidebands", "turbulence"),
    )
    key = jax.random.key(seed)
    frames = np.asarray(cf.simulate(scene, inst, 16, 16, key), np.float64).reshape(4, 3000, -1)
    frames -= frames.mean(axis=1, keepdims=True)
    i, q = iq_from_frames(frames, *cf.Hybrid().iq_matrix_dn(1.0))
    phi, note = initial_common_drift(i, q)
    true = np.asarray(turbulence_phase(key, 3000, 0.05))
    assert "drift found" in note, note
    assert np.corrcoef(phi, true)[0, 1] > 0.95
    axis_turn, phase_turn = tone_axis_rotation(np.asarray(i) + 1j * np.asarray(q), phi)
    assert axis_turn == pytest.approx(phase_turn, rel=0.2)


def test_short_sweeps_align_statically_and_say_so():
    inst = cf.Instrument.ten_hz_mode()
    frames = cf.simulate(cf.planar(effects=NOISE), inst, 4, 4, jax.random.key(0))
    alignment = align_carrier(ReconstructOptions(progress=False), inst, np.asarray(frames).reshape(4, 35, -1))
    assert alignment.mode == "static" and "frames are too few" in alignment.reason


def test_the_carrier_axis_without_trigonometry_is_half_the_angle_of_its_moments():
    """`iq.half_angle` gives cos and sin of ½·atan2(y, x) ∈ (−π/2, π/2], in float64 to a few
    ulp, on random points and where a branch or cancellation could fail: on the axes, near
    the negative x axis (r + x cancels), and at the origin (φ = 0, as atan2 gives)."""
    import jax.numpy as jnp

    from cohflash_jax.estimate.iq import half_angle

    rng = np.random.default_rng(5)
    edge_x = [0.0, 0.0, 1.0, -1.0, 0.0, -2.0, -2.0, 3.0, 1e-300, -1e6, 5e-8]
    edge_y = [0.0, 1.0, 0.0, 1e-12, -1.0, 1e-9, -1e-9, -1e-30, 0.0, 1.0, 5e-8]
    x = np.concatenate([rng.normal(size=20000) * rng.lognormal(0, 3, 20000), edge_x])
    y = np.concatenate([rng.normal(size=20000) * rng.lognormal(0, 3, 20000), edge_y])
    c, s = (np.asarray(v) for v in half_angle(jnp.asarray(x), jnp.asarray(y)))
    phi = 0.5 * np.arctan2(y, x)
    np.testing.assert_allclose(c, np.cos(phi), rtol=0, atol=1e-15)
    np.testing.assert_allclose(s, np.sin(phi), rtol=0, atol=1e-15)
    np.testing.assert_allclose(c * c + s * s, 1.0, rtol=0, atol=1e-15)


def test_the_surveys_frame_means_are_the_float64_means_exactly():
    """`drift.frame_means` sums integer frames as integers: the same float64 values as NumPy's
    float64 mean (whose partial sums are exact integers too), for unsigned and signed 16-bit
    frames at full scale, 8-bit frames, and float frames (averaged in float64)."""
    from cohflash_jax.estimate.drift import frame_means

    rng = np.random.default_rng(8)
    for dtype in (np.uint16, np.int16, np.uint8, np.float32):
        info = np.iinfo(dtype) if np.issubdtype(dtype, np.integer) else np.finfo(dtype)
        x = rng.integers(max(info.min, -60000), min(info.max, 60000), (4, 3001, 3, 7), endpoint=True).astype(dtype)
        x[0, :, 0, 0] = info.max if np.issubdtype(dtype, np.integer) else 65535.0  # a saturated pixel
        x[1, :, 0, 0] = info.min if np.issubdtype(dtype, np.integer) else -1.5
        means = frame_means(x)
        assert means.dtype == np.float64 and means.shape == (4, 3, 7)
        np.testing.assert_array_equal(means, np.mean(x, axis=1, dtype=np.float64))


@pytest.mark.parametrize("drift_rad", [0.0, 0.3, 3.0])
def test_the_surveys_sampled_gram_gives_the_leading_singular_pairs_of_every_row(drift_rad):
    """The survey finds the moving average's leading singular directions from every 8th row
    (`drift.GRAM_ROW_STEP`) and measures them on every row: its two largest singular values are
    the full SVD's to 0.5 %, and where a drift stands out, its left vector is the full SVD's,
    whether there is no drift (nearly equal values: pure noise), a weak one or a strong one."""
    from cohflash_jax.estimate.drift import GRAM_ROW_STEP, leading_singular_pairs
    from cohflash_jax.estimate.iq import DRIFT_WINDOW_FRAMES, moving_average

    rng = np.random.default_rng(3)
    n, p, half = 3000, 256, DRIFT_WINDOW_FRAMES // 2
    phi = np.cumsum(rng.normal(0.0, 0.05, n))
    phi *= drift_rad / np.std(phi)
    echoes = rng.normal(size=p) + 1j * rng.normal(size=p)
    z = 0.5 * echoes * np.exp(1j * phi)[:, None] + 3.0 * (rng.normal(size=(n, p)) + 1j * rng.normal(size=(n, p)))
    m = moving_average(z, DRIFT_WINDOW_FRAMES)[half : n - half]
    m = m - m.mean(axis=0)
    u, sv = leading_singular_pairs(m, row_step=GRAM_ROW_STEP)
    full_u, full_sv, _ = np.linalg.svd(m, full_matrices=False)
    np.testing.assert_allclose(sv, full_sv[:2], rtol=5e-3)
    assert sv[0] <= full_sv[0] * (1 + 1e-12)  # measured along a direction: never above the largest
    if drift_rad > 0:
        assert sv[0] > 2 * sv[1]
        assert abs(np.vdot(u[:, 0], full_u[:, 0])) > 0.999
    np.testing.assert_allclose(np.linalg.norm(u, axis=0), 1.0, rtol=1e-12)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_surveys_window_means_a_block_of_pixels_at_a_time_are_the_whole_arrays(dtype):
    """`drift.centred_window_means` averages Z a block of pixels at a time (`WINDOW_MEANS_BLOCK_PIXELS`)
    so that its temporaries stay small: each pixel's centred whole-window means are those of
    the whole array's moving average, bit for bit, and the noise variance its mean high-passed
    power over every frame (a last block narrower than the rest, float32 I/Q kept complex64)."""
    from cohflash_jax.estimate.drift import WINDOW_MEANS_BLOCK_PIXELS, centred_window_means
    from cohflash_jax.estimate.iq import DRIFT_WINDOW_FRAMES, moving_average

    rng = np.random.default_rng(5)
    n, p, half = 1200, 2 * WINDOW_MEANS_BLOCK_PIXELS + 7, DRIFT_WINDOW_FRAMES // 2
    i, q = (rng.normal(size=(n, p)) * 40 + 300).astype(dtype), (rng.normal(size=(n, p)) * 40 - 100).astype(dtype)
    z = i + 1j * q
    average = moving_average(z, DRIFT_WINDOW_FRAMES)
    whole = average[half : n - half]
    m, noise_var = centred_window_means(i, q, DRIFT_WINDOW_FRAMES)
    assert m.dtype == z.dtype and m.shape == (n - 2 * half, p)
    np.testing.assert_array_equal(m, whole - whole.mean(axis=0))
    expected = np.mean(np.abs(z.astype(np.complex128) - average) ** 2) / DRIFT_WINDOW_FRAMES
    np.testing.assert_allclose(noise_var, expected, rtol=1e-5 if dtype == np.float32 else 1e-12)
