"""Depth inversion against independent truth: noiseless exactness, CRLB, threshold,
harmonics, turbulence, precision paths, bad pixels, and the CLI end to end."""

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.capture import Capture
from cohflash_jax.cli import main
from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array
from cohflash_jax.status import Status

from .closed_forms import closed_form_noise_and_amplitude, crlb_frequency_only_m, crlb_phase_locked_m
from .conftest import N_FRAMES, depth_scene

OPTS = {m: ReconstructOptions(method=m, progress=False) for m in ("dft", "interp", "ml")}
# the fit's own checks, with the detection test switched off (noise peaks it would reject first)
FIT_CHECKS_ONLY = ReconstructOptions(method="ml", progress=False, false_alarm=1.0)


def _reconstruct(frames, instrument, method="ml", **kw):
    options = kw.pop("options", OPTS[method])
    return reconstruct_array(frames, instrument, options, **kw)


def _depth_at_cycles(cycles_per_frame, step_hz):
    return np.asarray(cycles_per_frame) / step_hz * C / 2


def test_noiseless_ml_is_exact_at_every_hard_depth(paper_instrument, simulate_pixels):
    step = paper_instrument.sweep.step_hz
    n = N_FRAMES
    hard = [
        _depth_at_cycles(700 / n, step),  # bin centre
        _depth_at_cycles(700.5 / n, step),  # bin edge
        _depth_at_cycles(1 / 3, step),  # 2nd harmonic aliases onto the fundamental
        _depth_at_cycles(1 / 4, step),  # 3rd harmonic aliases onto the fundamental
        0.05,
        0.12,  # near 0: the fundamental merges with DC
        paper_instrument.sweep.ambiguity_m - 0.006,  # ½ cycle per frame less a quarter bin
        30.5,
    ]
    rng = np.random.default_rng(0)
    depths = np.concatenate([hard, rng.uniform(0.2, 37.9, 64 - len(hard))])
    frames = simulate_pixels(depth_scene(depths, effects=("sidebands",)))
    out = _reconstruct(frames, paper_instrument)
    err = out["depth_m"].ravel() - depths
    assert np.all(out["valid"])
    assert np.max(np.abs(err)) < 1e-6, depths[np.argmax(np.abs(err))]
    # the plain DFT is right to half a bin and no better; interpolation to a few % of a bin
    bin_m = paper_instrument.sweep.bin_depth_m
    dft = _reconstruct(frames, paper_instrument, "dft")["depth_m"].ravel() - depths
    interp = _reconstruct(frames, paper_instrument, "interp")["depth_m"].ravel() - depths
    # near DC and near ½ cycle/frame the tone's mirror image overlaps it (a few bins): the
    # frequency-only estimates are allowed to be poor there
    far = (depths > 0.5) & (depths < paper_instrument.sweep.ambiguity_m - 0.5)
    assert np.max(np.abs(dft[far])) <= 0.5 * bin_m + 1e-9
    assert np.max(np.abs(interp[far])) < 0.1 * bin_m
    assert np.max(np.abs(dft)) > 0.2 * bin_m  # the test can tell DFT from ML


@pytest.fixture(scope="module")
def planar_monte_carlo(paper_instrument, noise_effects):
    """4 seeds × 64 pixels of the planar target at the paper's link budget."""
    scene = cf.planar(effects=noise_effects)
    frames = [cf.simulate(scene, paper_instrument, 8, 8, jax.random.key(100 + s)) for s in range(4)]
    return frames


def test_ml_reaches_the_crlb_at_the_paper_link_budget(paper_instrument, planar_monte_carlo):
    sigma, amp = closed_form_noise_and_amplitude(paper_instrument, 0.5)
    crlb = crlb_phase_locked_m(paper_instrument.sweep.frequencies_hz, amp, sigma)
    outs = [_reconstruct(f, paper_instrument) for f in planar_monte_carlo]
    err = np.concatenate([o["depth_m"].ravel() for o in outs]) - 30.5
    predicted = np.concatenate([o["sigma_m"].ravel() for o in outs])
    assert all(o["valid"].all() for o in outs)
    assert np.std(err) == pytest.approx(crlb, rel=0.2)
    assert abs(np.mean(err)) < 4 * crlb / np.sqrt(err.size)
    assert np.median(predicted) == pytest.approx(crlb, rel=0.1)  # the reported σ is the CRLB


def test_dft_and_interp_are_checked_against_truth_too(paper_instrument, planar_monte_carlo):
    sigma, amp = closed_form_noise_and_amplitude(paper_instrument, 0.5)
    freq_only = crlb_frequency_only_m(N_FRAMES, paper_instrument.sweep.step_hz, amp, sigma)
    phase_locked = crlb_phase_locked_m(paper_instrument.sweep.frequencies_hz, amp, sigma)
    assert 1.8 < freq_only / phase_locked < 2.2  # docs/design-reference.md §1: ≈ 2 for 0.1–6 GHz
    interp = (
        np.concatenate([_reconstruct(f, paper_instrument, "interp")["depth_m"].ravel() for f in planar_monte_carlo])
        - 30.5
    )
    dft = (
        np.concatenate([_reconstruct(f, paper_instrument, "dft")["depth_m"].ravel() for f in planar_monte_carlo]) - 30.5
    )
    bin_m = paper_instrument.sweep.bin_depth_m
    assert np.max(np.abs(dft)) <= 0.5 * bin_m + 5 * freq_only
    assert np.std(interp) < 2.5 * freq_only and abs(np.mean(interp)) < 0.05 * bin_m


def test_below_threshold_pixels_are_flagged_not_wild(paper_instrument, noise_effects):
    frames = [
        cf.simulate(cf.planar(reflectance=rho, effects=noise_effects), paper_instrument, 8, 8, jax.random.key(7))
        for rho in (0.02, 0.005)
    ]
    for f, max_valid in zip(frames, (0.7, 0.1)):
        out = _reconstruct(f, paper_instrument)
        valid = out["valid"]
        assert valid.mean() <= max_valid
        assert np.all(out["fit_status"][~valid] != 0)
        err = np.abs(out["depth_m"] - 30.5)
        assert np.all(err[valid] < 6 * out["sigma_m"][valid])  # nothing wild is marked valid
        for k in ("depth_m", "sigma_m", "amplitude", "snr"):
            assert np.all(np.isfinite(out[k]))
        # flagged pixels keep sane depths too: within the unambiguous interval ± a few bins
        ambiguity = C / (4 * np.diff(paper_instrument.sweep.frequencies_hz)[0])
        assert np.all((out["depth_m"] > -1.0) & (out["depth_m"] < ambiguity + 1.0))


def test_zero_echo_is_flagged_everywhere_without_nan(paper_instrument, noise_effects, simulate_pixels):
    frames = simulate_pixels(depth_scene([30.5], reflectance=0.0, effects=noise_effects))
    out = _reconstruct(frames, paper_instrument)
    assert not out["valid"].any()
    assert np.all(out["fit_status"] == Status.NOT_DETECTED)
    assert np.all(_reconstruct(frames, paper_instrument, options=FIT_CHECKS_ONLY)["fit_status"] == Status.LOW_SNR)
    assert all(np.all(np.isfinite(out[k])) for k in ("depth_m", "sigma_m", "amplitude", "snr"))


def test_sidebands_leave_no_bias_even_where_harmonics_alias_onto_the_tone(
    paper_instrument, noise_effects, simulate_pixels
):
    step = paper_instrument.sweep.step_hz
    depths = [_depth_at_cycles(1 / 3, step) + 0.003, _depth_at_cycles(1 / 4, step) + 0.003]
    for d in depths:
        errs, sig = [], []
        for seed in range(2):
            frames = simulate_pixels(depth_scene([d], effects=noise_effects + ("sidebands",)), seed=seed)
            out = _reconstruct(frames, paper_instrument)
            assert out["valid"].all()
            errs.append(out["depth_m"].ravel() - d)
            sig.append(out["sigma_m"].ravel())
        e = np.concatenate(errs)
        assert abs(e.mean()) < 4 * np.median(np.concatenate(sig)) / np.sqrt(e.size)


def test_turbulence_with_tracking_keeps_precision_within_10_percent(paper_instrument, noise_effects):
    scene_static = cf.planar(effects=noise_effects)
    scene_turb = cf.planar(effects=noise_effects + ("turbulence",))
    tracked = ReconstructOptions(method="ml", carrier="tracked", progress=False)
    static_err, turb_err, untracked_err = [], [], []
    for seed in range(3):  # the same seeds: the noise draws are shared, only the drift differs
        key = jax.random.key(200 + seed)
        f_static = cf.simulate(scene_static, paper_instrument, 8, 8, key)
        f_turb = cf.simulate(scene_turb, paper_instrument, 8, 8, key)
        static_err.append(_reconstruct(f_static, paper_instrument)["depth_m"].ravel() - 30.5)
        out = _reconstruct(f_turb, paper_instrument, options=tracked)
        assert out["valid"].all()
        turb_err.append(out["depth_m"].ravel() - 30.5)
        static = ReconstructOptions(method="ml", carrier="static", false_alarm=1.0, progress=False)
        untracked_err.append(_reconstruct(f_turb, paper_instrument, options=static)["depth_m"].ravel() - 30.5)
    s_static, s_turb = np.std(np.concatenate(static_err)), np.std(np.concatenate(turb_err))
    assert s_turb < 1.1 * s_static
    assert np.std(np.concatenate(untracked_err)) > 1.5 * s_static  # tracking is what saves it


def test_float32_and_float64_paths_agree(paper_instrument, planar_monte_carlo):
    f = planar_monte_carlo[0]
    a = _reconstruct(f, paper_instrument)
    b = _reconstruct(f, paper_instrument, options=ReconstructOptions(method="ml", dtype="float64", progress=False))
    assert np.max(np.abs(a["depth_m"] - b["depth_m"])) < 0.01 * np.median(a["sigma_m"])
    np.testing.assert_array_equal(a["valid"], b["valid"])


def test_bad_pixels_are_flagged_and_the_batch_finishes(paper_instrument, planar_monte_carlo):
    f = planar_monte_carlo[1].astype(np.float32)
    f[2, 100, 0, 0] = np.nan
    f[1, 5, 0, 1] = np.inf
    f[0, 10, 0, 2] = 16383.0  # ADC maximum in one frame
    f[3, :, 0, 3] = 512.0  # dead pixel on one CCD
    out = _reconstruct(f, paper_instrument, saturation_dn=16383.0)
    assert out["fit_status"][0, 0] == Status.BAD_DATA and out["fit_status"][0, 1] == Status.BAD_DATA
    assert out["fit_status"][0, 2] == Status.SATURATED and out["fit_status"][0, 3] == Status.DEAD
    assert not out["valid"][0, :4].any() and out["valid"][1:].all()
    assert all(np.all(np.isfinite(out[k])) for k in ("depth_m", "sigma_m", "amplitude", "snr"))


def test_ml_finds_the_right_ripple_when_ripples_are_narrower_than_a_bin(noise_effects):
    """24–30 GHz: the likelihood ripple (c/2f̄ ≈ 5.6 mm) is much narrower than a DFT bin
    (25 mm); the basin search must still land on the right one (no cycle slips)."""
    inst = cf.Instrument(sweep=cf.FrequencySweep.uniform(24e9, 1.97e6, N_FRAMES))
    assert inst.sweep.ripple_period_m < 0.25 * inst.sweep.bin_depth_m
    frames = cf.simulate(cf.planar(effects=noise_effects), inst, 8, 8, jax.random.key(3))
    out = _reconstruct(frames, inst)
    err = out["depth_m"] - 30.5
    assert out["valid"].all()
    assert np.max(np.abs(err)) < 0.25 * inst.sweep.ripple_period_m


def test_reconstruct_cli_end_to_end(tmp_path, capsys):
    cap = tmp_path / "p.h5"
    assert main(["simulate", "planar", "--size", "8x8", "--steps", "3000", "--out", str(cap), "--quiet"]) == 0
    out = tmp_path / "depth.h5"
    rc = main(
        [
            "reconstruct",
            str(cap),
            "--out",
            str(out),
            "--png",
            str(tmp_path / "d.png"),
            "--ply",
            str(tmp_path / "d.ply"),
            "--tiff",
            str(tmp_path / "d.tiff"),
            "--quiet",
            "--tile-rows",
            "8",
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "unambiguous depths [0.000, 38.045) m" in text
    with h5py.File(out) as f:
        assert f.attrs["format"] == "cohflash-depth" and f.attrs["method"] == "ml"
        assert abs(float(f.attrs["ambiguity_m"]) - C / (4 * 1.97e6)) < 1e-9
        np.testing.assert_allclose(f.attrs["depth_window_m"], [0.0, C / (4 * 1.97e6)], rtol=1e-12)
        for k in ("depth_m", "amplitude", "valid", "sigma_m", "snr", "fit_status"):
            assert f[k].shape == (8, 8)
        assert "cohflash_version" in f.attrs["provenance"] and "jax_device" in f.attrs["provenance"]
        assert np.all(np.abs(f["depth_m"][()] - 30.5) < 5 * f["sigma_m"][()])
    assert (tmp_path / "d.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ply = (tmp_path / "d.ply").read_bytes()
    assert ply.startswith(b"ply\nformat binary_little_endian 1.0")
    assert (tmp_path / "d.tiff").stat().st_size > 8 * 8 * 4
    with Capture(cap) as c:
        assert c.shape == (3000, 8, 8)
    # bad input: clear error, exit code 2, nothing written
    assert main(["reconstruct", str(tmp_path / "none.h5"), "--out", str(tmp_path / "x.h5")]) == 2
    assert "not found" in capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists()
    # an export into a missing folder is refused before any work, not after depth.h5 is written
    assert (
        main(["reconstruct", str(cap), "--out", str(tmp_path / "x.h5"), "--ply", str(tmp_path / "no" / "c.ply")]) == 2
    )
    assert f"output folder does not exist: {tmp_path / 'no'}" in capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists()
    # an output onto the capture itself is refused: the capture stays as it was
    before = cap.read_bytes()
    assert main(["reconstruct", str(cap), "--out", str(tmp_path / "x.h5"), "--png", str(cap)]) == 2
    assert "is the capture file this command reads" in capsys.readouterr().err
    assert cap.read_bytes() == before and not (tmp_path / "x.h5").exists()


def test_calibration_file_applies_the_true_hybrid(tmp_path, paper_instrument, noise_effects):
    """A capture with injected hybrid phase/gain/offset errors: reconstruction with a
    calibration file holding the true hybrid matches the error-free precision; the file's bad
    forms are refused clearly."""
    import json

    from cohflash_jax.calibration_file import Calibration
    from cohflash_jax.simulate import simulate_to_file

    scene = cf.planar(effects=noise_effects + ("hybrid_errors",))
    cap = tmp_path / "errs.h5"
    simulate_to_file(cap, scene, paper_instrument, 8, 8, seed=5, progress=False)
    with Capture(cap) as c:
        t = c.truth_attrs
    gain = np.asarray(t["hybrid_relative_gains"]) * float(t["dn_per_electron"])
    calib = {
        "format": "cohflash-calibration",
        "format_version": 1,
        "hybrid": {
            "phases_rad": list(t["hybrid_phases_rad"]),
            "relative_gains": list(gain / gain[0]),
            "offsets_dn": list(t["hybrid_offsets_dn"]),
        },
    }
    path = tmp_path / "hybrid.json"
    path.write_text(json.dumps(calib))
    loaded = Calibration.load(path)
    np.testing.assert_allclose(loaded.hybrid.phases_rad, t["hybrid_phases_rad"])
    out = tmp_path / "d.h5"
    assert main(["reconstruct", str(cap), "--out", str(out), "--calibration", str(path), "--quiet"]) == 0
    with h5py.File(out) as f:
        err, sigma, valid = f["depth_m"][()] - 30.5, f["sigma_m"][()], f["valid"][()].astype(bool)
    assert valid.all() and np.all(np.abs(err) < 5 * sigma)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "something"}))
    assert main(["reconstruct", str(cap), "--out", str(tmp_path / "x.h5"), "--calibration", str(bad)]) == 2
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        Calibration.load(bad)


@pytest.fixture(scope="module")
def sparse_instrument():
    """400 frames drawn at random from the paper's 3000-step grid (a sparse schedule)."""
    rng = np.random.default_rng(11)
    f = 0.1e9 + 1.97e6 * np.sort(rng.choice(N_FRAMES, 400, replace=False))
    return cf.Instrument(sweep=cf.FrequencySweep(f))


def test_non_uniform_schedule_noiseless_and_at_the_crlb(sparse_instrument, noise_effects, simulate_pixels):
    inst = sparse_instrument
    assert not inst.sweep.is_uniform
    depths = np.linspace(2.0, 37.0, 64)
    clean = simulate_pixels(depth_scene(depths, effects=("sidebands",)), instrument=inst)
    out = _reconstruct(clean, inst)
    assert out["valid"].all()
    assert np.max(np.abs(out["depth_m"].ravel() - depths)) < 1e-6
    # noisy planar target: time-domain ML against the closed-form phase-locked CRLB of this schedule
    sigma, amp = closed_form_noise_and_amplitude(inst, 0.5)
    crlb = crlb_phase_locked_m(inst.sweep.frequencies_hz, amp, sigma)
    err = np.concatenate(
        [
            _reconstruct(cf.simulate(cf.planar(effects=noise_effects), inst, 8, 8, jax.random.key(s)), inst)[
                "depth_m"
            ].ravel()
            - 30.5
            for s in range(3)
        ]
    )
    assert np.std(err) == pytest.approx(crlb, rel=0.2)
    interp = _reconstruct(clean, inst, "interp")
    assert np.max(np.abs(interp["depth_m"].ravel() - depths)) < 0.25 * C / (2 * 5.9e9)


def test_sub_tiles_give_the_same_pixels_as_one_tile(paper_instrument, planar_monte_carlo, monkeypatch):
    """The streamed path cuts tiles into sub-tiles (the last one padded): per-pixel results
    must not depend on where the cuts fall, for frames and per-pixel maps alike. XLA's I/Q
    programs here (the native kernel's cuts: tests/test_native.py)."""
    from cohflash_jax import native
    from cohflash_jax.reconstruct import TileDispatcher, build_plan, process_tile
    from cohflash_jax.runtime import quick_compile

    monkeypatch.setattr(native, "available", lambda: False)

    f = np.asarray(planar_monte_carlo[2])
    n = f.shape[1]
    frames = f.reshape(4, n, -1)
    dark = np.random.default_rng(0).normal(0.0, 2.0, (4, frames.shape[-1])).astype(np.float32)
    frames[3, :, 5] = 512  # a dead pixel in the first sub-tile
    # the quick compile, as `reconstruct_array` compiles captures this small: the programs are
    # the ones the rest of the suite compiles (the cuts do not depend on XLA's optimisation)
    with quick_compile():
        plan = build_plan(paper_instrument, OPTS["ml"], 16383.0)
        whole = {
            k: np.asarray(v) for k, v in process_tile(plan, jax.numpy.asarray(frames), jax.numpy.asarray(dark)).items()
        }
        pending = TileDispatcher(plan, sub_px=24).dispatch(frames, dark)  # 24 + 24 + 16 (padded to 24)
        assert not pending.holds_frames  # pieces are copies: the frames' buffer may take the next tile
        parts = pending.gather()
        contiguous = np.ascontiguousarray(frames)
        assert TileDispatcher(plan, sub_px=contiguous.shape[-1]).dispatch(contiguous, dark).holds_frames
    assert parts.keys() == whole.keys()
    assert parts["fit_status"][5] == Status.DEAD and parts["valid"].sum() == frames.shape[-1] - 1
    np.testing.assert_array_equal(parts["fit_status"], whole["fit_status"])
    # float32 FFTs of different batch sizes round differently (~1e-7 relative), nothing more
    np.testing.assert_allclose(parts["depth_m"], whole["depth_m"], rtol=0, atol=1e-3 * np.median(whole["sigma_m"]))
    for k in whole:
        assert parts[k].shape == whole[k].shape
        np.testing.assert_allclose(parts[k], whole[k], rtol=1e-5, atol=1e-9, err_msg=k)


def test_a_long_sweep_read_twice_gives_the_pixels_of_its_stored_iq(paper_instrument, planar_monte_carlo):
    """A long sweep without a tracked carrier never stores I/Q: one pass over the frames gives
    the data checks and the carrier axis, a second the rotated sequence (`process_tile`). Its
    pixels must be those of the programs that keep I/Q (`iq_and_checks`, the carrier axis,
    the rotation), which a tracked carrier still runs, with a known drift and a dead pixel."""
    from cohflash_jax.reconstruct import build_plan, process_tile, programs
    from cohflash_jax.runtime import quick_compile

    f = np.asarray(planar_monte_carlo[2])
    n = f.shape[1]
    frames = f.reshape(4, n, -1).copy()
    frames[2, :, 7] = 300  # a dead pixel
    rng = np.random.default_rng(1)
    dark = jnp.asarray(rng.normal(0.0, 2.0, (4, frames.shape[-1])).astype(np.float32))
    gain = jnp.asarray(rng.normal(1.0, 0.01, (4, frames.shape[-1])).astype(np.float32))
    drift = jnp.asarray(0.3 * np.sin(np.linspace(0.0, 3.0, n)))
    with quick_compile():
        plan = build_plan(paper_instrument, OPTS["ml"], 16383.0)
        assert n >= programs.SPLIT_AXIS_MIN_FRAMES and not plan.iq.tracking
        x = jnp.asarray(frames)
        two_passes = process_tile(plan, x, dark, None, gain, drift)
        i, q, flags = programs.iq_and_checks(plan.iq, x, dark, gain, drift)
        c, s, noise_var, total_var = programs.carrier_axis_program(i, q)
        r = programs.rotate_program(i, q, c, s)
        stored = programs.invert_sequence(plan, r, noise_var, total_var, flags)
    assert int(two_passes["fit_status"][7]) == Status.DEAD and np.asarray(two_passes["valid"]).sum() > 50
    for k in stored:
        np.testing.assert_allclose(np.asarray(two_passes[k]), np.asarray(stored[k]), rtol=1e-6, atol=0, err_msg=k)


def test_options_out_of_range_are_refused():
    """A NaN SNR threshold would pass every pixel (NaN compares false): refused, like the rest."""
    for bad, match in (
        ({"snr_threshold_db": float("nan")}, "snr_threshold_db"),
        ({"max_fit_chi2": 0.0}, "max_fit_chi2"),
        ({"max_fit_chi2": float("nan")}, "max_fit_chi2"),
        ({"method": "fft"}, "unknown method"),
        ({"window_bins": 2}, "window_bins"),
        ({"max_steps": 0}, "max_steps"),
        ({"min_depth_m": -1.0}, "min_depth_m"),
        ({"tile_rows": 0}, "tile_rows"),
    ):
        with pytest.raises(ValueError, match=match):
            ReconstructOptions(**bad)


def test_reconstruct_array_refuses_inputs_that_do_not_fit():
    """In-memory frames get the checks a capture file gets. Two or three frames leave no DFT
    bin beyond DC with neighbours (an IndexError before); a frequency list of another length
    ran silently with the wrong N."""
    frames = np.full((4, 3, 2, 2), 100, np.uint16)
    with pytest.raises(ValueError, match="3 frames are too few"):
        reconstruct_array(frames, cf.Instrument(sweep=cf.FrequencySweep(1e8 + 2e6 * np.arange(3))), OPTS["ml"])
    frames, f = np.full((4, 8, 2, 2), 100, np.uint16), 1e8 + 2e6 * np.arange(8)
    inst = cf.Instrument(sweep=cf.FrequencySweep(f))
    with pytest.raises(ValueError, match=r"frequencies_hz must have shape \(8,\)"):
        reconstruct_array(frames, cf.Instrument(sweep=cf.FrequencySweep(f[:5])), OPTS["ml"])
    for bad, match in ((f[::-1], "strictly increasing"), (np.where(np.arange(8) == 2, np.nan, f), "NaN")):
        with pytest.raises(ValueError, match=match):
            cf.FrequencySweep(bad)
    for kwargs, match in (
        ({"maps": cf.PixelMaps(offset_dn=np.zeros((4, 3, 3)))}, r"offset_dn has shape \(4, 3, 3\)"),
        ({"carrier_phase_rad": np.zeros(3)}, "carrier_phase_rad"),
    ):
        with pytest.raises(ValueError, match=match):
            reconstruct_array(frames, inst, OPTS["ml"], **kwargs)


def test_sub_tile_size_follows_the_platform():
    """CPU: cache-sized sub-tiles of at most 8192 px, at least 4 a tile; a GPU takes the tile
    whole up to 256 MiB of frames. A region of interest is padded to its pixel bucket on both."""
    from cohflash_jax.reconstruct import sub_tile_pixels

    assert sub_tile_pixels(10240, 3000, platform="cpu") == 12 * 2**20 // (8 * 3000) == 524
    assert sub_tile_pixels(81920, 35, platform="cpu") == 8192
    assert sub_tile_pixels(10240, 35, platform="cpu") == 2560
    assert sub_tile_pixels(2000, 35, platform="cpu") == 500
    assert sub_tile_pixels(81920, 35, platform="gpu") == sub_tile_pixels(10240, 3000, platform="cuda") * 8 == 81920
    assert sub_tile_pixels(81920, 3000, platform="gpu") == 256 * 2**20 // (8 * 3000) == 11184
    assert sub_tile_pixels(25, 3000, platform="cpu") == sub_tile_pixels(25, 3000, platform="gpu") == 64
    assert sub_tile_pixels(200, 3000, platform="gpu") == 256 and sub_tile_pixels(1500, 3000, platform="gpu") == 1500


def test_polish_converges_in_few_newton_steps_and_never_reports_a_maximum_as_converged():
    """`polish_depth` minimises a 1-D cost by Newton on its slope: quadratic convergence, so a
    start a sixth of a ripple off lands in ≤ 5 steps to the floor tolerance even where the
    residuals are noisy (Gauss–Newton is linear there); a start past the ripple's inflection
    climbs to the maximum, which must be flagged, not reported as a fit."""

    from cohflash_jax.estimate.polish import descended, polish_depth

    rng = np.random.default_rng(1)
    x_mm = np.linspace(-30.0, 30.0, 34)
    period_mm, truth_mm = 24.0, 1.3
    data = np.cos(2 * np.pi * (x_mm - truth_mm) / period_mm) + 0.3 * rng.normal(size=x_mm.size)
    cost = lambda d: jnp.sum((jnp.asarray(data) - jnp.cos(2 * jnp.pi * (jnp.asarray(x_mm) - d) / period_mm)) ** 2)
    grid = np.linspace(-5.0, 7.0, 120001)  # brute force on a 0.1 µm grid
    costs = np.sum((data - np.cos(2 * np.pi * (x_mm - grid[:, None]) / period_mm)) ** 2, axis=1)
    best = grid[np.argmin(costs)]
    assert abs(best - truth_mm) < 1.0
    start = jnp.asarray(best + period_mm / 6)
    p = polish_depth(cost, start, max_steps=16)
    value, ok, steps = p.value, p.succeeded, p.num_steps
    assert bool(ok & descended(cost(value), cost(start))) and int(steps) <= 5
    assert abs(float(value) - best) < 2e-4
    # cos: minimum at π, maximum at 0; starting at 0.3 Newton goes to the maximum
    p = polish_depth(jnp.cos, jnp.asarray(0.3), max_steps=16)
    value, ok = p.value, p.succeeded
    assert abs(float(value)) < 1e-6 and not bool(ok & descended(jnp.cos(value), np.cos(0.3)))
    p = polish_depth(jnp.cos, jnp.asarray(2.5), max_steps=16)
    value, ok = p.value, p.succeeded
    assert abs(float(value) - np.pi) < 1e-6 and bool(ok & descended(jnp.cos(value), np.cos(2.5)))


def test_newton_polish_with_unrolled_steps_takes_the_same_steps():
    """`newton_polish`'s `unrolled_steps` write its first steps out before the loop: each
    start, batched under `vmap`, ends at the same bits, steps and flags with none, some or more
    unrolled than it needs, a start that climbs to the maximum and one that hits the step
    limit included."""
    from cohflash_jax.estimate.polish import newton_polish

    slope_and_curvature = lambda x: (-jnp.sin(x), -jnp.cos(x))  # of cos: minimum at π, maximum at 0
    starts = jnp.asarray([0.3, 2.5, 3.0, np.pi, 4.4, 1.55, np.nan])

    def run(unrolled, max_steps=16):
        polish = lambda x: newton_polish(
            slope_and_curvature, x, max_steps=max_steps, tolerance_mm=1e-9, unrolled_steps=unrolled
        )
        return jax.tree.map(np.asarray, jax.jit(jax.vmap(polish))(starts))

    for max_steps in (16, 2):
        plain = run(0, max_steps)
        assert plain.at_step_limit.any() if max_steps == 2 else plain.succeeded[:-1].all()
        for unrolled in (1, 3, 20):
            other = run(unrolled, max_steps)
            for name in ("value", "succeeded", "num_steps", "at_step_limit"):
                np.testing.assert_array_equal(getattr(other, name), getattr(plain, name), err_msg=name)


@pytest.mark.runs_long
def test_straggler_pass_gives_each_pixel_its_uninterrupted_polish():
    """The polish runs every pixel for a few Newton steps, then resumes the stragglers a few at
    a time (`refine_ml_uniform`). Each pixel must end exactly as an uninterrupted polish ends
    it — same steps, same convergence, same depth — whatever its batch: 96 low-SNR pixels
    (up to three straggler groups, and empty slots), synthetic windows of the phase-locked model."""

    from cohflash_jax.estimate.polish import STRAGGLER_GROUP
    from cohflash_jax.estimate.window_ml import grid_for, refine_ml_uniform
    from cohflash_jax.estimate.window_model import UniformModel, window_tables
    from cohflash_jax.modulator import MZM
    from cohflash_jax.runtime import compile_lowered, quick_compile, quick_compile_options

    n, start_hz, step_hz, width = 3000, 0.1e9, 5.9e9 / 3000, 17
    model = UniformModel(start_hz, step_hz, jnp.asarray(MZM().weights(3e9)), num_frames=n)
    rng = np.random.default_rng(3)
    pixels = 3 * STRAGGLER_GROUP
    bin_m = C / (2 * n * step_hz)
    depth = rng.uniform(5.0, 60.0, pixels)
    coarse = depth + rng.normal(0.0, 0.1 * bin_m, pixels)
    k0 = np.round(2 * coarse / C * step_hz * n).astype(int) - width // 2
    tables = jax.vmap(lambda k: window_tables(k, width, n))(jnp.asarray(k0))
    tones = jax.vmap(model.tone_column)(jnp.asarray(depth), tables)
    noise_var = 1.0
    snr_db = rng.uniform(-10.0, 12.0, pixels)  # SNR n(A·w₁)²/σ² from noise-like to just below the threshold
    amplitude = np.sqrt(10 ** (snr_db / 10) * noise_var / n) / float(model.weights[1])
    windows = amplitude[:, None] * tones + np.sqrt(noise_var / 2) * (
        rng.normal(size=tones.shape) + 1j * rng.normal(size=tones.shape)
    )
    half, points, candidates = grid_for(bin_m, C / (2 * (start_hz + 0.5 * step_hz * n)))

    # jitted (one program a pass count), not op by op: hundreds of small compiles otherwise;
    # compiled as a region of interest's programs are (`quick_compile`), in half the time
    def fit(first):
        refine = lambda: refine_ml_uniform(
            model,
            windows,
            jnp.asarray(k0),
            jnp.asarray(coarse),
            jnp.full(pixels, noise_var),
            grid_half_width_m=half,
            grid_points=points,
            candidates=candidates,
            max_steps=16,
            first_pass_steps=first,
        )
        with quick_compile():
            return compile_lowered(jax.jit(refine).lower(), quick_compile_options(jax.default_backend()))()

    whole, resumed = fit(16), fit(1)
    steps = np.asarray(whole.num_steps)
    assert steps.max() >= 4 and (steps > 1).sum() > 2 * STRAGGLER_GROUP  # with first_pass_steps = 1: three groups
    np.testing.assert_array_equal(np.asarray(resumed.num_steps), steps)
    np.testing.assert_array_equal(np.asarray(resumed.converged), np.asarray(whole.converged))
    np.testing.assert_allclose(np.asarray(resumed.depth_m), np.asarray(whole.depth_m), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(resumed.sigma_depth_m), np.asarray(whole.sigma_depth_m), rtol=1e-9)


@pytest.mark.parametrize("system_delay_half_periods", [0.3, 2.8])
def test_system_delay_moves_the_unambiguous_window_and_depths_stay_exact(system_delay_half_periods, paper_instrument):
    """τ_sys = 0.3 P/2 puts depth 0 in the first half-period of total delay (window
    [−0.3, 0.7)·ambiguity); τ_sys = 2.8 P/2 in the fourth, where the folded tone runs
    backwards (window [0.2, 1.2)·ambiguity). Noiseless, with sidebands: ML exact to 1 µm
    across the window, and the window reported."""
    from cohflash_jax.geometry import delay_window
    from cohflash_jax.reconstruct import build_plan

    sweep = paper_instrument.sweep
    period_s = 1 / sweep.step_hz
    amb = sweep.ambiguity_m
    delay = system_delay_half_periods * period_s / 2
    fold, (start, end) = delay_window(period_s, delay)
    assert start == pytest.approx((round(system_delay_half_periods) - system_delay_half_periods) * amb, abs=1e-6)
    assert end - start == pytest.approx(amb, rel=1e-12)
    lo, hi = max(0.0, start), end
    depths = np.random.default_rng(5).uniform(lo + 0.2, hi - 0.2, 64)
    inst = cf.Instrument.paper(N_FRAMES, system_delay_s=delay)
    frames = cf.simulate(depth_scene(depths, effects=("sidebands",)), inst, 8, 8, jax.random.key(0))
    out = _reconstruct(frames, inst)
    err = out["depth_m"].ravel() - depths
    assert np.all(out["valid"]) and np.max(np.abs(err)) < 1e-6
    geometry = build_plan(inst, OPTS["ml"]).geometry
    assert geometry.depth_window_m == (start, end) and geometry.fold_index == fold


def _two_kernel_tone(model, depth, tables):
    """Σ_n w_n (e^{iθ_n} D(x_n) + e^{−iθ_n} D(−x_n)) over the window: the tone column written
    out with `dirichlet_window`, two kernels an order (the reference for `tone_column`)."""

    from cohflash_jax.estimate import window_model as ml

    tau = model.delay(depth)
    total = 0
    for order in range(1, model.weights.shape[0]):
        x, cycles = order * model.step_hz * tau, order * model.start_hz * tau
        rot = jnp.exp(2j * jnp.pi * (cycles - jnp.floor(cycles)))
        total = total + model.weights[order] * (
            rot * ml.dirichlet_window(x, tables, model.num_frames)
            + jnp.conj(rot) * ml.dirichlet_window(-x, tables, model.num_frames)
        )
    return total


def test_tone_column_equals_the_two_dirichlet_kernels_of_each_order():
    """`UniformModel.tone_column` folds each order's e^{iθ}D(x) + e^{−iθ}D(−x) into one pass;
    it must equal the two kernels evaluated apart (`dirichlet_window`), on and off a bin, with
    finite first and second derivatives on a bin (Newton differentiates it twice). The form a
    quick-compiled program traces (every order at once, `runtime.compiling_quick`) gives the
    same tone and the same closed-form derivatives as the loop over orders."""

    from cohflash_jax.estimate import window_model as ml
    from cohflash_jax.runtime import quick_compile

    n, width = N_FRAMES, 17
    model = ml.UniformModel(0.1e9, 1.97e6, jnp.asarray([0.29, 0.097, 0.0066, 1.9e-4]), 0.0, num_frames=n)

    bin_depth = C / (2 * n * model.step_hz)
    depths = [700 * bin_depth, 0.05, 12.68, 37.9, 21.123456, 1e-4]  # on a bin, near DC, alias, edge
    for depth in depths:
        peak = int(round(depth / bin_depth))
        tables = ml.window_tables(jnp.asarray(min(max(peak - width // 2, 0), n // 2 + 1 - width)), width, n)
        d = jnp.asarray(depth)
        expected = _two_kernel_tone(model, d, tables)
        np.testing.assert_allclose(
            model.tone_column(d, tables), expected, rtol=0, atol=1e-11 * np.max(np.abs(expected))
        )
        second = jax.jvp(
            lambda z: jax.jvp(lambda y: model.tone_column(y, tables), (z,), (jnp.ones(()),))[1], (d,), (jnp.ones(()),)
        )[1]
        assert np.all(np.isfinite(second))
        with quick_compile():
            np.testing.assert_allclose(
                model.tone_column(d, tables), expected, rtol=0, atol=1e-11 * np.max(np.abs(expected))
            )
        rates = tuple(1e-3 * rate for rate in model.angle_rates())
        jets = lambda: model.tone_jets(model.phasors(d), tables, rates=rates, derivatives=2)
        loop = jets()
        with quick_compile():
            stacked = jets()
        for part_loop, part_stacked in zip(loop, stacked):  # Re, Im: value, ′, ″ per mm
            for a, b in zip(part_loop, part_stacked):
                np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * max(np.max(np.abs(a)), 1.0))


def test_dirichlet_kernel_phasor_shift_and_grid_orders_against_direct_evaluation():
    """The closed-form kernel equals the DFT sum it stands for; rotating a depth's phasors by
    `rotation(δ)` equals the phasors at depth + δ (the polish and the grid move by rotation);
    the basin grid keeps the orders of at least 1 % of the dominant weight."""

    from cohflash_jax.estimate import window_ml
    from cohflash_jax.estimate import window_model as ml

    n, width = 3000, 17
    m_idx = np.arange(n)
    for x0, k0 in ((0.2371, 700), (0.23333333333333334, 692), (701 / n, 695), (1e-7, 0)):
        tables = ml.window_tables(jnp.asarray(k0), width, n)
        bins = k0 + np.arange(width)
        direct = np.exp(2j * np.pi * np.outer(x0 - bins / n, m_idx)).sum(axis=1) / np.sqrt(n)
        np.testing.assert_allclose(ml.dirichlet_window(jnp.asarray(x0), tables, n), direct, rtol=0, atol=1e-9)
    model = ml.UniformModel(0.1e9, 1.97e6, jnp.asarray([0.29, 0.097, 0.0066, 1.9e-4]), 3e-9, num_frames=n)
    for depth, delta in ((30.5, 4.7e-3), (12.68, -0.0251), (0.0, 1e-6)):
        moved = ml.shift_phasors(model.phasors(jnp.asarray(depth)), model.rotation(jnp.asarray(delta)))
        np.testing.assert_allclose(
            np.asarray(moved), np.asarray(model.phasors(jnp.asarray(depth + delta))), rtol=0, atol=1e-9
        )
    assert window_ml.grid_orders(model.weights) == 2
    assert window_ml.grid_orders([0.3, 0.1, 0.0, 0.002]) == 3
    assert window_ml.grid_orders([0.3, 0.1, 0.0005, 0.0009]) == 1


def test_a_fit_whose_tone_cancels_the_offset_is_flagged_not_valid():
    """A pixel of the 35-frame 10 Hz benchmark (0.17–6 GHz comb, 10× probe power; frames in
    tests/data): its coarse peak was noise near DC, the fit slid to depth ≈ 0 where the tone
    flattens into a constant, and tone and offset cancelled with an amplitude of 3·10⁵ (real
    echoes: ~90), SNR 86 dB and σ 0.2 mm — reported valid 104 mm from the surface. It must be
    flagged fit_failed."""
    from pathlib import Path

    frames = np.load(Path(__file__).parent / "data" / "degenerate_pixel_35_frames.npy")[:, :, None, None]
    n = frames.shape[1]
    inst = cf.Instrument(sweep=cf.FrequencySweep.uniform(6e9 / n, 6e9 / n, n))
    out = reconstruct_array(frames, inst, FIT_CHECKS_ONLY)
    assert out["fit_status"][0, 0] == Status.FIT_FAILED and not out["valid"][0, 0]
    assert np.isfinite(out["depth_m"][0, 0])
    # with the detection test on, the noise peak is not taken for a tone in the first place
    assert reconstruct_array(frames, inst, OPTS["ml"])["fit_status"][0, 0] == Status.NOT_DETECTED


@pytest.mark.parametrize("path", ["table", "window"])
def test_fits_that_trade_depth_against_the_offset_near_dc_are_flagged(path, monkeypatch, request):
    """35 frames (10 Hz mode): four pixels at 5 % and 3 % reflectance (frames in tests/data)
    whose fits slid from noise peaks ~1 bin deep to 4–8 mm, ~100 mm off. The DFT-window fit
    reported SNRs of 16–21 dB and amplitudes 3–7× the echo's there, so the SNR threshold does
    not catch them. There the tone trades off with the offset: the depth's variance inflation
    F_dd·[F⁻¹]_dd is ~10³. Both ML paths for short sweeps (the tone table, and the DFT window
    it replaced there) must flag them. Noiseless targets show where the check bites: computed
    independently (3×3 Fisher of the explicit two-kernel model), the inflation exceeds 4
    within ~½ bin of 0 and is ≈ 1 beyond, and exactly those pixels are flagged; the others
    are exact to 1 µm."""
    from pathlib import Path

    from cohflash_jax.estimate import table
    from cohflash_jax.estimate import window_model as ml
    from cohflash_jax.fisher import MAX_VARIANCE_INFLATION

    if path == "window":
        from cohflash_jax.reconstruct import forget_setups

        monkeypatch.setattr(table, "TABLE_MAX_FRAMES", 0)
        forget_setups()  # the plans kept from earlier captures chose the table...
        request.addfinalizer(forget_setups)  # ...and this one's must not outlive the patch
    frames = np.load(Path(__file__).parent / "data" / "near_dc_fits_35_frames.npy")[:, :, None, :]
    inst = cf.Instrument.ten_hz_mode()
    sweep, n = inst.sweep, frames.shape[1]
    out = reconstruct_array(frames, inst, FIT_CHECKS_ONLY)
    assert np.all(out["fit_status"] == Status.FIT_FAILED) and not out["valid"].any()
    assert not reconstruct_array(frames, inst, OPTS["ml"])["valid"].any()
    assert np.all(out["depth_m"] < 0.01) and np.all(out["coarse_depth_m"] > 0.025)
    if path == "window":
        assert np.all(10 * np.log10(out["snr"]) > 16)

    depths = np.array([0.004, 0.009, 0.02, 0.05, 0.3])
    clean = reconstruct_array(
        cf.simulate(depth_scene(depths, effects=("sidebands",)), inst, 8, 8, jax.random.key(0)), inst, OPTS["ml"]
    )
    status, valid, found = (clean[k].ravel()[:5] for k in ("fit_status", "valid", "depth_m"))
    weights = cf.MZM().weights(float(np.mean(sweep.frequencies_hz)))
    model = ml.UniformModel(
        float(sweep.frequencies_hz[0]), float(sweep.step_hz), jnp.asarray(weights), 0.0, num_frames=n
    )
    tables = ml.window_tables(jnp.asarray(0), 17, n)

    def window(params):  # c·DC + A·Σ_n 2w_n cos(2π n f_m τ) over bins 0..16, two kernels an order
        depth, offset, amp = params
        col = offset * ml.dirichlet_window(jnp.zeros(()), tables, n) + amp * _two_kernel_tone(model, depth, tables)
        return jnp.concatenate([jnp.real(col), jnp.imag(col)]) * jnp.tile(ml.bin_weights(tables, n), 2)

    for depth, code in zip(depths, status):
        jac = jax.jacfwd(window)(jnp.asarray([depth, 1.0, 1.0]))
        fisher = np.asarray(jac.T @ jac)
        inflation = fisher[0, 0] * np.linalg.inv(fisher)[0, 0]
        assert (inflation > MAX_VARIANCE_INFLATION) == (code == Status.FIT_FAILED), (depth, inflation, code)
        assert (inflation > 30) if depth < 0.01 else (inflation < 1.2)
    assert np.all(valid[2:]) and np.max(np.abs(found[2:] - depths[2:])) < 1e-6


def test_snr_threshold_is_raised_for_the_noise_estimate_from_few_frames():
    """The SNR's σ² comes from the pixel's own N frames (relative error √(2/(N−1))): the
    threshold applied is raised by 1/(1 − √(2/(N−1))) and recorded; a 35-frame pixel between
    14 dB and the raised threshold is low_snr."""
    from cohflash_jax.reconstruct import DEFAULT_SNR_THRESHOLD_DB, snr_threshold_margin

    assert 10 * np.log10(snr_threshold_margin(3000)) == pytest.approx(0.114, abs=1e-3)
    assert 10 * np.log10(snr_threshold_margin(35)) == pytest.approx(1.206, abs=1e-3)
    inst = cf.Instrument.ten_hz_mode()
    n = inst.sweep.num_steps
    frames = cf.simulate(
        cf.planar(reflectance=0.5, effects=("shot_noise", "read_noise")), inst, 16, 16, jax.random.key(3)
    )
    out = reconstruct_array(frames, inst, FIT_CHECKS_ONLY)
    snr_db = 10 * np.log10(out["snr"])
    applied = DEFAULT_SNR_THRESHOLD_DB + 10 * np.log10(snr_threshold_margin(n))
    assert np.all(snr_db[out["valid"]] >= applied)
    between = (snr_db >= DEFAULT_SNR_THRESHOLD_DB) & (snr_db < applied)
    assert between.sum() >= 5 and np.all(out["fit_status"][between] == Status.LOW_SNR)


def test_compilation_cache_folder_is_created_set_and_can_be_turned_off(tmp_path, monkeypatch):
    from cohflash_jax.runtime import enable_compilation_cache

    monkeypatch.setenv("COHFLASH_JAX_CACHE", "off")
    assert enable_compilation_cache() is None
    monkeypatch.setenv("COHFLASH_JAX_CACHE", str(tmp_path / "from-env"))
    previous = jax.config.jax_compilation_cache_dir
    try:
        assert enable_compilation_cache() == tmp_path / "from-env" and (tmp_path / "from-env").is_dir()
        folder = enable_compilation_cache(tmp_path / "a" / "jax")
        assert folder.is_dir() and jax.config.jax_compilation_cache_dir == str(folder)
        blocker = tmp_path / "file"
        blocker.write_text("")
        assert enable_compilation_cache(blocker / "jax") is None  # cannot be created: stays off
    finally:
        jax.config.update("jax_compilation_cache_dir", previous)


def test_slow_drift_without_an_echo_is_not_reported_as_a_target():
    """A quadratic drift on one CCD and no echo, 35 frames (0.17–6 GHz comb): the spectrum
    rises towards DC, the coarse peak sits on the first searched bin, and before the DC-edge
    check 16 of 64 pixels came out valid at one bin (≈ 25 mm) with χ² < 5. None may."""
    n = 35
    inst = cf.Instrument(sweep=cf.FrequencySweep.uniform(6e9 / n, 6e9 / n, n))
    sweep = inst.sweep
    rng = np.random.default_rng(0)
    m = np.arange(n)[:, None, None]
    strength = rng.uniform(5, 200, (8, 8))
    frames = 400 + rng.normal(0, 2.0, (4, n, 8, 8))
    frames[0] += strength * (4 * ((m - n / 2) / n) ** 2 + 0.3 * m / n)
    out = reconstruct_array(frames.astype(np.float32), inst, OPTS["ml"])
    assert not out["valid"].any()
    assert np.sum(out["fit_status"] == Status.DC_EDGE) >= 16  # the ones that passed every other check
    assert np.all((out["depth_m"] >= 0) & (out["depth_m"] < sweep.ambiguity_m))


def test_async_filter_jit_keeps_filter_jit_semantics():
    """`runtime.async_filter_jit` (the reconstruct programs' jit, which does not wait for its
    result as `eqx.filter_jit` does): non-array arguments, keyword ones included, are static
    — a Python branch on them works and a new value recompiles — and arrays are traced."""
    import equinox as eqx

    from cohflash_jax.runtime import async_filter_jit

    class Settings(eqx.Module):
        scale: jax.Array
        power: int = eqx.field(static=True)
        offset: float = 0.0  # a plain float leaf: static, as eqx.filter_jit treats it

    traces = []

    def f(settings, x, *, negate: bool):
        traces.append(1)
        y = settings.scale * x**settings.power + settings.offset
        return -y if negate else y

    g = async_filter_jit(f)
    x = jnp.arange(4.0)
    s = Settings(jnp.asarray(2.0), 2, 1.0)
    np.testing.assert_allclose(g(s, x, negate=True), -(2 * x**2 + 1))
    np.testing.assert_allclose(g(s, x + 1, negate=True), -(2 * (x + 1) ** 2 + 1))
    assert len(traces) == 1  # same shapes and statics: compiled once
    np.testing.assert_allclose(g(Settings(jnp.asarray(2.0), 2, 3.0), x, negate=False), 2 * x**2 + 3)
    assert len(traces) == 2
    # arguments held in dicts (a fit's `args`): the static half is keyed by its leaves
    h = async_filter_jit(lambda args: args["scale"] * args["x"] ** args["power"])
    np.testing.assert_allclose(h({"scale": jnp.asarray(3.0), "x": x, "power": 2}), 3 * x**2)
    np.testing.assert_allclose(h({"scale": jnp.asarray(3.0), "x": x, "power": 3}), 3 * x**3)


def test_candan_interpolation_is_exact_to_a_small_fraction_of_a_bin_and_near_the_frequency_only_bound(
    paper_instrument, planar_monte_carlo, simulate_pixels
):
    """The Jacobsen–Candan estimator (`--method candan`): on noiseless single tones away from DC
    and the Nyquist edge its depth is within 1 % of a bin of the truth (the Hann log-parabola
    of `interp` is allowed 10 %); on the planar target it is unbiased and its spread within
    twice the frequency-only CRLB (measured 1.2–1.6× depending on where the tone falls in its
    bin: a three-point estimator does not reach the bound)."""
    bin_m = paper_instrument.sweep.bin_depth_m
    depths = np.random.default_rng(3).uniform(1.0, paper_instrument.sweep.ambiguity_m - 1.0, 64)
    frames = simulate_pixels(depth_scene(depths))
    options = ReconstructOptions(method="candan", progress=False)
    clean = _reconstruct(frames, paper_instrument, options=options)
    assert clean["valid"].all() and np.max(np.abs(clean["depth_m"].ravel() - depths)) < 0.01 * bin_m
    sigma, amp = closed_form_noise_and_amplitude(paper_instrument, 0.5)
    freq_only = crlb_frequency_only_m(N_FRAMES, paper_instrument.sweep.step_hz, amp, sigma)
    err = (
        np.concatenate(
            [_reconstruct(f, paper_instrument, options=options)["depth_m"].ravel() for f in planar_monte_carlo]
        )
        - 30.5
    )
    assert freq_only < np.std(err) < 2.0 * freq_only
    assert abs(np.mean(err)) < 4 * np.std(err) / np.sqrt(err.size)


@pytest.mark.parametrize("num_frames", [1, 35, 64, 65, 127, 3001])
def test_frame_extremes_equal_the_highest_and_lowest_frame(num_frames):
    """The data checks' per-pixel highest and lowest values (dead: equal; saturated: the
    highest at the ceiling) come from a fold over halves of the frame axis: the same values
    as a reduction, for odd and even frame counts, integers and floats with ±inf. (A pixel
    with a NaN is flagged bad data whatever its extremes: XLA's CPU max/min, reduction and
    elementwise alike, need not propagate NaN.)"""
    from cohflash_jax.reconstruct.programs import frame_extremes

    rng = np.random.default_rng(num_frames)
    counts = rng.integers(0, 65536, (4, num_frames, 37), dtype=np.uint16)
    counts[:, :, 0] = 7  # a dead pixel: every frame alike
    counts[1, -1, 1] = 65535  # saturated in the last frame only (the odd one out of a fold)
    counts[2, 0, 2] = 0  # the lowest value in the first frame
    floats = counts.astype(np.float32)
    floats[3, -1, 4], floats[1, 0, 5] = np.inf, -np.inf
    for frames in (counts, floats):
        high, low = jax.jit(frame_extremes)(jnp.asarray(frames))
        np.testing.assert_array_equal(np.asarray(high), frames.max(axis=1))
        np.testing.assert_array_equal(np.asarray(low), frames.min(axis=1))


@pytest.mark.parametrize("long_sweep", [False, True])
def test_data_checks_flag_the_same_pixels_in_every_form(monkeypatch, long_sweep):
    """The data checks take each pixel's extremes in the form fastest where they run: on a CPU
    whose XLA code has AVX-512 the frames' own reduction, under AVX2 a short sweep's converted
    values or a long sweep's fold (`frame_extremes`), off the CPU the frames' own reduction (a
    GPU compiled the fold for 46 s). Every form flags the same dead and saturated pixels and
    gives the same I/Q. Traced under `jax.jit`, so the other forms' programs never enter the
    executable cache under this machine's key."""
    from cohflash_jax.reconstruct import programs
    from cohflash_jax.reconstruct.plan import build_plan

    n = programs.SPLIT_AXIS_MIN_FRAMES + 1 if long_sweep else 35
    plan = build_plan(cf.Instrument.paper(num_steps=n), OPTS["ml"], 4095.0, tracking=False)
    counts = np.random.default_rng(3).integers(100, 4000, (4, n, 16), dtype=np.uint16)
    counts[:, :, 0] = 7  # dead
    counts[2, -1, 1] = 4095  # saturated in the last frame only
    dark = jnp.zeros((4, 16), jnp.float32)
    outputs = []
    for backend, avx512 in (("cpu", True), ("cpu", False), ("gpu", False)):
        monkeypatch.setattr(programs.jax, "default_backend", lambda backend=backend: backend)
        monkeypatch.setattr(programs, "xla_cpu_has_avx512", lambda avx512=avx512: avx512)
        jax.clear_caches()  # the program's trace is kept: trace it again, in this form
        try:
            outputs.append(jax.jit(lambda f: programs.iq_and_checks(plan.iq, f, dark))(jnp.asarray(counts)))
        finally:
            jax.clear_caches()  # and keep no trace of it for later tests
    for other in outputs[1:]:
        for a, b in zip(jax.tree.leaves(outputs[0]), jax.tree.leaves(other)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    dead, saturated, _ = outputs[0][2]
    assert np.flatnonzero(dead).tolist() == [0] and np.flatnonzero(saturated).tolist() == [1]


def _dot_precisions(jaxpr):
    """The (operand dtype, precision) of every matrix product in a jaxpr and its sub-jaxprs."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append((str(eqn.invars[0].aval.dtype), eqn.params["precision"]))
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    found += _dot_precisions(inner)
    return found


@pytest.mark.parametrize("method,frames", [("ml", 35), ("ml", 600), ("dft", 3000)])
def test_every_matrix_product_of_the_programs_runs_at_full_float32_precision(method, frames):
    """A GPU's default float32 product is TF32 (a 10-bit mantissa): measured on an H200, the
    short-sweep DFT window (a float32 product) then left noiseless targets a reduced χ² above 5
    (poor_fit). A CPU computes full precision whatever is asked, so this reads what each
    program asks for: every product in the traced programs of a tile at HIGHEST."""
    from cohflash_jax.reconstruct import programs
    from cohflash_jax.reconstruct.plan import build_plan

    inst = cf.Instrument.ten_hz_mode() if frames == 35 else cf.Instrument.paper(num_steps=frames)
    plan = build_plan(inst, ReconstructOptions(method=method, progress=False), None, tracking=False)
    tile = jnp.zeros((4, frames, 64), jnp.uint16)
    jaxpr = jax.make_jaxpr(lambda f: programs.process_tile(plan, f, jnp.zeros((4, 64), jnp.float32)))(tile)
    products = _dot_precisions(jaxpr.jaxpr)
    assert products, "no matrix product found: the walk missed the programs"
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    assert all(precision == highest for _, precision in products), products


def test_a_value_computed_once_is_not_recomputed_in_every_kernel_that_spreads_it():
    """`window_model.computed_once` leaves its values exactly as they are (a NaN in its own
    element), and XLA's CPU code then computes a per-pixel sine and cosine once, in a kernel of
    their own, instead of inside each kernel that spreads them over a window's bins (the
    inversion's 10 float64 sines and cosines became 113 each there)."""
    import re

    from cohflash_jax.estimate.window_model import computed_once

    x = jnp.linspace(0.0, 3.0, 64).at[5].set(jnp.nan)
    bins_re, bins_im = jnp.linspace(0.0, 1.0, 17), jnp.linspace(1.0, 2.0, 17)

    def spread(once: bool):
        def over_bins(x):
            c, s = (jnp.cos(x), jnp.sin(x) + 1.0)
            if once:
                c, s = computed_once((c, s))
            a = c[:, None] * bins_re - s[:, None] * bins_im
            b = s[:, None] * bins_re + c[:, None] * bins_im
            return (a * b).sum(axis=1), (a + b).max(axis=1)

        return jax.jit(over_bins).lower(x).compile()

    def trig_in_bin_kernels(compiled) -> int:
        """Sines and cosines inside computations that also touch the 17 bins (a kernel
        that evaluates them once per bin)."""
        blocks = re.split(r"\n(?=(?:ENTRY )?%\S+ \()", compiled.as_text())
        trig = lambda block: len(re.findall(r" (?:sine|cosine)\(", block))
        return sum(trig(block) for block in blocks if re.search(r"\[(?:\d+,)*17\]", block))

    plain, once = spread(False), spread(True)
    for a, b in zip(plain(x), once(x)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    values = (jnp.array([np.nan, 1.0, -0.0, np.inf]), jnp.array([2.0, -0.5, 3.0, 1e308]))
    kept = jax.jit(computed_once)(values)
    np.testing.assert_array_equal(np.asarray(kept[0]), [np.nan, 1.0, 0.0, np.inf])
    np.testing.assert_array_equal(np.asarray(kept[1]), [2.0, -0.5, 3.0, 1e308])  # another value's NaN does not spread
    mixed = computed_once((jnp.float32(1.5), jnp.arange(3.0)))  # values of other shapes and types
    assert mixed[0].dtype == jnp.float32 and mixed[0].shape == () and mixed[1].shape == (3,)
    np.testing.assert_array_equal(np.asarray(mixed[1]), [0.0, 1.0, 2.0])
    assert trig_in_bin_kernels(plain) > 0 and trig_in_bin_kernels(once) == 0
