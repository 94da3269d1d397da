"""ML for short uniform sweeps (the paper's 35-frame 10 Hz mode) from a tone table
(`estimate.table`), against independent truth: the explicit model and its derivatives, the
time-domain ML fit of `estimate.time_domain` (trigonometry per frame, no table), noiseless
exactness across the unambiguous window, and the CRLB in Monte Carlo."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
from cohflash_jax.estimate import TableML
from cohflash_jax.estimate import table as tt
from cohflash_jax.estimate.time_domain import refine_time_domain
from cohflash_jax.estimate.window_ml import grid_for
from cohflash_jax.geometry import reflect_into_window
from cohflash_jax.reconstruct import ReconstructOptions, build_plan, reconstruct_array
from cohflash_jax.status import Status

from .closed_forms import closed_form_noise_and_amplitude, crlb_phase_locked_m
from .conftest import depth_scene, needs_two_cpu_streams

N = 35
STEP_HZ = 6e9 / N  # the 10 Hz mode's comb: f_m = (m + 1)·Δf, 0.17–6 GHz
ML = ReconstructOptions(method="ml", progress=False)


@pytest.fixture(scope="module")
def comb():
    inst = cf.Instrument.ten_hz_mode()
    return inst, build_plan(inst, ML)


def _tone(f, weights, depths_m, system_delay_s=0.0):
    """t(d)[m] = Σ_{n≥1} 2 w_n cos(2π n f_m τ), explicitly (G, N)."""
    tau = system_delay_s + 2 * np.asarray(depths_m)[:, None] / C
    return sum(2 * weights[n] * np.cos(2 * np.pi * n * f[None, :] * tau) for n in range(1, len(weights)))


def _table_fit(plan, r, coarse_depth_m, noise_var, projection_dtype):
    """The plan's table fit (`refine_ml_table`) of r (N, P) about the coarse depths, its
    projections in `projection_dtype`."""
    est = plan.estimator
    return tt.refine_ml_table(
        est.table,
        plan.model,
        r,
        coarse_depth_m,
        noise_var,
        half_width_m=est.half_width_m,
        max_steps=est.max_steps,
        projection_dtype=projection_dtype,
    )


def test_tone_table_holds_the_tone_and_its_derivatives(comb):
    inst, plan = comb
    table = plan.estimator.table
    f = np.asarray(inst.sweep.frequencies_hz)
    weights = np.asarray(plan.model.weights)
    assert table.num_points <= tt.TABLE_MAX_POINTS
    s = table.spacing_m
    depths = table.start_m + s * np.arange(table.num_points)
    assert depths[0] < plan.geometry.depth_window_m[0] - plan.estimator.half_width_m
    assert depths[-1] > plan.geometry.depth_window_m[1] + plan.estimator.half_width_m
    g = np.array([0, 17, 101, table.num_points - 1])
    rows = np.asarray(table.rows, np.float64)[g] + np.asarray(table.means)[g][..., None]  # raw R_j
    np.testing.assert_allclose(rows[:, 0], _tone(f, weights, depths[g]), atol=1e-6)
    h = 1e-7  # R_1 = s·∂t/∂d and R_2 = s²·∂²t/∂d² by central differences
    up, down, mid = (_tone(f, weights, depths[g] + d) for d in (h, -h, 0.0))
    scale = np.abs(rows[:, 1]).max()
    np.testing.assert_allclose(rows[:, 1], s * (up - down) / (2 * h), atol=1e-6 * scale)
    h2 = 1e-5
    up2, down2 = (_tone(f, weights, depths[g] + d) for d in (h2, -h2))
    np.testing.assert_allclose(rows[:, 2], s**2 * (up2 - 2 * mid + down2) / h2**2, atol=1e-4 * np.abs(rows[:, 2]).max())
    # |Σ u^j/j!·R_j|² (mean-removed) against its tabulated polynomial
    u = 0.37
    centred = np.asarray(table.rows, np.float64)[g]
    taylor = sum(u**j / math.factorial(j) * centred[:, j] for j in range(centred.shape[1]))
    np.testing.assert_allclose(
        np.sum(taylor**2, -1), np.polynomial.polynomial.polyval(u, np.asarray(table.norm_coeffs)[g].T), rtol=1e-9
    )
    # and |∂/∂u Σ u^j/j!·R_j|² (the final fit's Fisher information) against its own
    slope = sum(u ** (j - 1) / math.factorial(j - 1) * centred[:, j] for j in range(1, centred.shape[1]))
    np.testing.assert_allclose(
        np.sum(slope**2, -1), np.polynomial.polynomial.polyval(u, np.asarray(table.slope_norm_coeffs)[g].T), rtol=1e-9
    )
    # the Taylor sum half a spacing off a grid point is the tone there to the stated tolerance
    np.testing.assert_allclose(
        taylor
        + (np.asarray(table.means)[g] * [u**j / math.factorial(j) for j in range(centred.shape[1])]).sum(-1)[:, None],
        _tone(f, weights, depths[g] + u * s),
        atol=20 * tt.TAYLOR_TOLERANCE * 2 * weights[1],
    )


def test_table_path_is_used_for_short_uniform_ml_only(comb):
    inst, plan = comb
    assert isinstance(plan.estimator, TableML)
    assert type(build_plan(inst, ReconstructOptions(method="dft")).estimator).__name__ == "DFTPeak"
    paper = cf.Instrument(sweep=cf.FrequencySweep.uniform(0.1e9, 5.9e9 / 3000, 3000))
    assert type(build_plan(paper, ML).estimator).__name__ == "WindowML"
    # a narrow sweep high in frequency would need a table of thousands of depths: DFT window
    narrow = cf.Instrument(sweep=cf.FrequencySweep.uniform(5.1e9, 0.6e9 / 34, 35))
    assert type(build_plan(narrow, ML).estimator).__name__ == "WindowML"


def test_table_fit_matches_the_time_domain_ml_fit(comb):
    """Same pixels, same likelihood: the table fit (grid product, polynomial polish) and
    `refine_time_domain` (the tone per frame, its own basin grid) agree to 1e-3 σ in
    depth and 1e-4 in amplitude and σ; at zero noise both are exact to 0.1 µm (at the window's
    edge, where the comb's model is mirror-symmetric, to ~10 nm; elsewhere to ~1 nm)."""
    inst, plan = comb
    est, geometry = plan.estimator, plan.geometry
    f = np.asarray(inst.sweep.frequencies_hz)
    weights = np.asarray(plan.model.weights)
    grid_points = grid_for(geometry.bin_depth_m, geometry.ripple_m)[1]
    rng = np.random.default_rng(7)
    lo, hi = geometry.depth_window_m
    bin_m = geometry.bin_depth_m
    depths = np.concatenate(
        [
            rng.uniform(0.05, hi - 0.005, 60),
            (np.arange(2, 6) + 0.5) * bin_m,
            np.arange(2, 6) * bin_m,  # bin edges, centres
            [hi - 1e-3, hi - 1e-4],
        ]
    )  # at the ambiguity limit
    amp, offset, noise_sigma = 80.0, 400.0, 2.0
    clean = offset + amp * _tone(f, weights, depths)  # (P, N)
    coarse = depths + rng.uniform(-0.4, 0.4, depths.size) * bin_m

    # each fit one program for both noise levels, not op by op (~250 small compiles otherwise)
    @jax.jit
    def fits(r, coarse, noise_var):
        table_fit = _table_fit(plan, r.T, coarse, noise_var, jnp.float64)  # float32 projections: the next test
        direct = jax.vmap(
            lambda rr, d, v: refine_time_domain(
                rr,
                jnp.asarray(f),
                plan.model.weights,
                d,
                v,
                system_delay_s=0.0,
                grid_half_width_m=est.half_width_m,
                grid_points=grid_points,
                max_steps=est.max_steps,
            )
        )(r, coarse, noise_var)
        return table_fit, direct

    for noise in (0.0, noise_sigma):
        r = clean + noise * rng.standard_normal(clean.shape)
        noise_var = np.full(depths.size, max(noise, 1e-3) ** 2)
        table_fit, direct = fits(jnp.asarray(r), jnp.asarray(coarse), jnp.asarray(noise_var))
        assert np.all(table_fit.converged & table_fit.well_posed)
        # compared where the reference polish converged too (it can miss its step tolerance on a noiseless pixel)
        ok = np.asarray(direct.converged & direct.well_posed)
        assert ok.mean() > 0.95
        sigma = np.asarray(direct.sigma_depth_m)[ok]
        # the comb's model is symmetric about the window's edges: a fit may land on the mirror image
        found = np.asarray(reflect_into_window(table_fit.depth_m, geometry.depth_window_m))
        if noise == 0:
            np.testing.assert_allclose(found, depths, rtol=0, atol=1e-7)
        np.testing.assert_allclose(
            found[ok],
            np.asarray(reflect_into_window(direct.depth_m, geometry.depth_window_m))[ok],
            rtol=0,
            atol=max(1e-3 * sigma.min(), 1e-7),
        )
        pick = lambda a: np.asarray(a)[ok]
        np.testing.assert_allclose(pick(table_fit.amplitude), pick(direct.amplitude), rtol=1e-4)
        np.testing.assert_allclose(pick(table_fit.sigma_depth_m), sigma, rtol=1e-3)  # σ grows 50× at the mirror edge
        np.testing.assert_allclose(pick(table_fit.offset), pick(direct.offset), rtol=1e-4)
        np.testing.assert_allclose(
            pick(table_fit.cost), pick(direct.cost), rtol=1e-4, atol=1e-9 * np.sum(clean**2, -1).max()
        )


def test_float32_projections_agree_with_float64_ones(comb):
    """The table fit's float32 projections (the reconstruction's) against float64 ones, on the
    same pixels across the window, the mirror edge included: at zero noise, at ~15 dB a frame
    and at ~55 dB (a bright target at the quantisation noise), the same flags; depths within
    1e-3 of σ (1e-2 in the last 0.1 mm before the window's mirror edge, where the cost is
    flat; at zero noise within 1 nm, and 1 µm there), σ within 1e-4 and the reduced χ²
    within 1e-3 (at zero noise both below 1e-3: the cost is the residual's own, not |y|²
    less the rounded projections' share)."""
    from cohflash_jax.estimate.base import reduced_chi2

    inst, plan = comb
    geometry = plan.geometry
    f = np.asarray(inst.sweep.frequencies_hz)
    rng = np.random.default_rng(11)
    hi = geometry.depth_window_m[1]
    depths = np.concatenate([rng.uniform(0.05, hi - 0.005, 60), [hi - 1e-3, hi - 1e-4]])
    tone = _tone(f, np.asarray(plan.model.weights), depths)  # (P, N)
    coarse = depths + rng.uniform(-0.4, 0.4, depths.size) * geometry.bin_depth_m

    @jax.jit
    def fits(r, noise_var):
        fit = lambda dtype: _table_fit(plan, r, coarse, noise_var, dtype)
        mean_square = jnp.mean(jnp.square(r.astype(jnp.float64)), axis=0)
        chi2 = lambda fit: reduced_chi2(fit.cost, noise_var, mean_square, N - 3)
        single, double = fit(jnp.float32), fit(jnp.float64)
        return single, double, chi2(single), chi2(double)

    for amp, noise in ((80.0, 0.0), (80.0, 2.0), (2000.0, 0.5)):
        r = (400.0 + amp * tone + noise * rng.standard_normal(tone.shape)).T.astype(np.float32)
        noise_var = np.full(depths.size, max(noise, 1e-3) ** 2, np.float32)
        single, double, chi2_single, chi2_double = jax.tree.map(np.asarray, fits(jnp.asarray(r), noise_var))
        for name in ("converged", "well_posed"):
            np.testing.assert_array_equal(getattr(single, name), getattr(double, name), err_msg=name)
        assert single.converged.all() and single.well_posed.all()
        moved = np.abs(single.depth_m - double.depth_m)
        if noise == 0:
            assert moved[:-2].max() < 1e-9 and moved.max() < 1e-6
            assert chi2_single.max() < 1e-3 and chi2_double.max() < 1e-3
            continue
        # measured: 1e-6 σ (1e-4 at 55 dB a frame) and 1e-3 σ in the flat last 0.1 mm
        within = lambda part, share: np.all(moved[part] < share * double.sigma_depth_m[part])
        assert within(slice(None, -2), 1e-3) and within(slice(-2, None), 1e-2)
        # σ: 1e-5, and 7e-3 at the edge's last point, whose σ is 10⁴× the rest (the depth barely shows)
        np.testing.assert_allclose(single.sigma_depth_m[:-1], double.sigma_depth_m[:-1], rtol=1e-4)
        np.testing.assert_allclose(single.sigma_depth_m[-1], double.sigma_depth_m[-1], rtol=3e-2)
        np.testing.assert_allclose(chi2_single, chi2_double, rtol=0, atol=1e-3)


def test_short_sweep_ml_reaches_the_crlb_and_is_exact_without_noise(comb):
    """Through `reconstruct_array` (simulated frames, 35-frame comb): noiseless depths across
    the window exact to 1 µm; with shot and read noise at ~25 dB, the depth spread over 256
    pixels at one depth within 20 % of the closed-form phase-locked CRLB and of the reported σ."""
    inst, plan = comb
    f = inst.sweep.frequencies_hz
    hi = plan.geometry.depth_window_m[1]
    depths = np.concatenate([np.linspace(0.02, hi - 0.002, 60), [hi - 1e-3, hi - 3e-4, hi - 1e-4, 0.4]])
    clean = reconstruct_array(
        cf.simulate(depth_scene(depths, effects=("sidebands",)), inst, 8, 8, jax.random.key(0)), inst, ML
    )
    assert clean["valid"].all()
    np.testing.assert_allclose(clean["depth_m"].ravel(), depths, rtol=0, atol=1e-6)

    # 100× the paper's probe power (10× the 10 Hz benchmark's): ~25 dB, every pixel valid
    from cohflash_jax.radiometry import PAPER_PROBE_POWER_W, LinkBudget

    bright = dataclasses.replace(inst, link=LinkBudget(probe_power_w=100 * PAPER_PROBE_POWER_W))
    target = 0.2371
    scene = depth_scene([target], reflectance=0.5, effects=("shot_noise", "read_noise"))
    runs = [reconstruct_array(cf.simulate(scene, bright, 8, 8, jax.random.key(seed)), bright, ML) for seed in range(4)]
    depth, valid, sigma, snr = (
        np.concatenate([o[k].ravel() for o in runs]) for k in ("depth_m", "valid", "sigma_m", "snr")
    )
    assert valid.all() and 20 < 10 * np.log10(np.median(snr)) < 32
    noise_sigma, tone_amp = closed_form_noise_and_amplitude(bright, 0.5)
    crlb = crlb_phase_locked_m(f, tone_amp, noise_sigma)
    spread = np.std(depth - target)
    assert spread == pytest.approx(crlb, rel=0.2)
    assert np.median(sigma) == pytest.approx(crlb, rel=0.1)  # the reported σ is the CRLB
    assert abs(np.mean(depth - target)) < 4 * crlb / np.sqrt(depth.size)


def test_table_fit_where_ripples_are_narrower_than_a_bin():
    """35 frames over 1.0–1.6 GHz: the likelihood ripples every c/(2f̄) ≈ 116 mm, the bin is
    243 mm, so the basin search must pick the right ripple among near-equal ones (the positive
    amplitude is preferred, as the carrier alignment makes A·w_0 > 0). Noiseless: exact to
    0.1 µm across the window. At 100× the paper's probe power (CRLB 0.87 mm): no pixel off by
    a ripple or half of one (the sign-flipped fit, 58 mm = 66 CRLB), spread within 20 % of the
    closed-form CRLB."""
    from cohflash_jax.radiometry import PAPER_PROBE_POWER_W, LinkBudget

    inst = cf.Instrument(
        sweep=cf.FrequencySweep.uniform(1.0e9, 0.6e9 / 34, N),
        frame_rate_hz=350.0,
        sensor=cf.Sensor(exposure_s=2e-3),
        link=LinkBudget(probe_power_w=100 * PAPER_PROBE_POWER_W),
    )
    f = inst.sweep.frequencies_hz
    plan = build_plan(inst, ML)
    assert isinstance(plan.estimator, TableML) and plan.estimator.prefer_positive
    assert not plan.geometry.mirror_symmetric
    depths = np.linspace(0.3, plan.geometry.depth_window_m[1] - 0.3, 64)
    clean = reconstruct_array(
        cf.simulate(depth_scene(depths, effects=("sidebands",)), inst, 8, 8, jax.random.key(0)), inst, ML
    )
    assert clean["valid"].all()
    np.testing.assert_allclose(clean["depth_m"].ravel(), depths, rtol=0, atol=1e-7)

    target = 2.0371
    scene = depth_scene([target], reflectance=0.5, effects=("shot_noise", "read_noise"))
    runs = [reconstruct_array(cf.simulate(scene, inst, 8, 8, jax.random.key(seed)), inst, ML) for seed in range(4)]
    depth, valid = (np.concatenate([o[k].ravel() for o in runs]) for k in ("depth_m", "valid"))
    noise_sigma, tone_amp = closed_form_noise_and_amplitude(inst, 0.5)
    crlb = crlb_phase_locked_m(f, tone_amp, noise_sigma)
    assert valid.all() and np.max(np.abs(depth - target)) < 5 * crlb  # no slip
    assert np.std(depth - target) == pytest.approx(crlb, rel=0.2)


def test_table_fit_flags_dead_nan_and_signal_free_pixels_without_nan(comb):
    """Through the table path: a dead pixel, a pixel with a NaN frame, one with no echo (noise
    only) and one of zero amplitude and zero noise are flagged, every output finite."""
    inst, _ = comb
    rng = np.random.default_rng(3)
    frames = 400 + rng.normal(0, 3.0, (4, N, 1, 4)).astype(np.float32)
    frames[:, :, 0, 0] = 400.0  # dead
    frames[1, 7, 0, 1] = np.nan  # corrupt frame
    frames[:, :, 0, 3] = 400.0 + np.arange(4)[:, None]  # constant per CCD, no noise: dead too
    out = reconstruct_array(frames, inst, ML)
    for k, v in out.items():
        assert np.all(np.isfinite(v)), k
    assert not out["valid"].any()
    assert out["fit_status"][0, 0] == Status.DEAD and out["fit_status"][0, 1] == Status.BAD_DATA
    assert out["fit_status"][0, 3] == Status.DEAD


@needs_two_cpu_streams
def test_two_cpu_streams_give_the_same_bits(comb, tmp_path):
    """The CLI gives JAX two CPU devices and deals sub-tiles out to them in turn
    (`runtime.use_cpu_streams`, `reconstruct.stream_devices`), so that two programs run at once.
    A process with two devices must reconstruct the same frames to the same bits as this one."""
    if jax.default_backend() != "cpu":
        pytest.skip("two CPU streams are the CPU's: on a GPU the sub-tiles go to the GPU")
    import subprocess
    import sys

    from cohflash_jax.radiometry import PAPER_PROBE_POWER_W, LinkBudget
    from cohflash_jax.reconstruct import TileDispatcher

    inst, plan = comb
    bright = dataclasses.replace(inst, link=LinkBudget(probe_power_w=100 * PAPER_PROBE_POWER_W))  # most pixels valid
    frames = np.asarray(
        cf.simulate(cf.planar(reflectance=0.5, effects=("shot_noise", "read_noise")), bright, 8, 8, jax.random.key(5))
    ).reshape(4, N, 64)
    np.save(tmp_path / "frames.npy", frames)
    script = f"""
import numpy as np
from cohflash_jax.runtime import use_cpu_streams
assert use_cpu_streams(2) == 2
import equinox as eqx
import jax
import cohflash_jax as cf
from cohflash_jax.reconstruct import ReconstructOptions, TileDispatcher, build_plan, stream_devices
assert len(stream_devices()) == 2
plan = build_plan(cf.Instrument.ten_hz_mode(), ReconstructOptions(method="ml"))
out = TileDispatcher(plan, sub_px=16).dispatch(np.load({str(tmp_path / "frames.npy")!r})).gather()
np.savez({str(tmp_path / "two.npz")!r}, **out)
"""
    subprocess.run([sys.executable, "-c", script], check=True)
    one = TileDispatcher(plan, sub_px=16).dispatch(frames).gather()
    two = np.load(tmp_path / "two.npz")
    assert set(two.files) == set(one) and one["valid"].sum() > 10
    for key, value in one.items():
        np.testing.assert_array_equal(two[key], value, err_msg=key)


@pytest.mark.parametrize("num_frames", [35, 64])
def test_short_sweep_spectrum_from_the_dft_matrix_matches_numpy(num_frames):
    """Short sweeps' coarse spectrum is a DFT-matrix product with the bins on the first axis
    (`coarse.DFT_MATRIX_MAX_FRAMES`): against NumPy's float64 rFFT and an explicit periodic-
    Hann window, on noisy tones at random frequencies, even and odd N."""
    from cohflash_jax.estimate.coarse import DFT_MATRIX_MAX_FRAMES, UniformSpectrum

    assert num_frames <= DFT_MATRIX_MAX_FRAMES
    rng = np.random.default_rng(num_frames)
    p = 512
    m = np.arange(num_frames)[:, None]
    freq = rng.uniform(0.05, 0.45, p)
    seq = 40 * np.cos(2 * np.pi * freq * m + rng.uniform(0, 2 * np.pi, p)) + 7 + rng.normal(0, 3, (num_frames, p))
    inst = cf.Instrument(sweep=cf.FrequencySweep.uniform(6e9 / num_frames, 6e9 / num_frames, num_frames))
    stage = build_plan(inst, ML).coarse
    assert isinstance(stage, UniformSpectrum)
    out = eqx.filter_jit(lambda stage, x: stage(x))(stage, jnp.asarray(seq, jnp.float32))
    spec = np.fft.rfft(seq, axis=0).T / math.sqrt(num_frames)  # (P, K)
    hann = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(num_frames) / num_frames)
    power = np.abs(np.fft.rfft((seq - seq.mean(0)) * hann[:, None], axis=0).T / math.sqrt(num_frames)) ** 2
    scale = power.max(axis=1, keepdims=True)
    np.testing.assert_allclose(np.asarray(out.spectrum), spec, atol=2e-6 * np.abs(spec).max())
    assert np.all(np.abs(np.asarray(out.power) - power) <= 2e-6 * scale)  # each pixel to its peak's power
    np.testing.assert_array_equal(np.asarray(out.peak), 1 + np.argmax(power[:, 1:], axis=1))
    # the readouts, taken where the bins come first (`UniformSpectrum.power_as_computed`), are
    # those of the pixels-first arrays the stage returns, to the bit
    from cohflash_jax.estimate.coarse import interpolate_peak
    from cohflash_jax.estimate.detection import uniform_sums

    def both(stage, out):
        readouts = stage.depth(out, True), stage.tone_amplitude(out), stage.dc_edge(out), stage.detection_energy(out)
        power, peak, n = out.power, out.peak, num_frames
        pixels_first = (
            stage.geometry.depth_from_folded(interpolate_peak(power, peak).astype(jnp.float64) / n),
            2 * jnp.sqrt(power[jnp.arange(p), peak]).astype(jnp.float64) / (math.sqrt(n) * stage.dominant_weight),
            (peak == stage.min_bin) & (power[:, stage.min_bin - 1] > power[:, stage.min_bin]),
            uniform_sums(out.spectrum, n),
        )
        return readouts, pixels_first

    readouts, pixels_first = eqx.filter_jit(both)(stage, out)
    for got, want in zip(readouts, pixels_first):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_a_full_frame_sub_tile_fits_only_its_detected_pixels_where_they_are_few():
    """The 10 Hz mode near its threshold: where at most an eighth of a full-frame sub-tile
    (8192 px) holds a tone, the ML fit runs on those pixels alone (`estimate_detected`). They
    get the same depths, σ, amplitudes and flags as fitting every pixel; the others report the
    coarse stage's depth and no χ² (their status is not_detected either way). A sub-tile where
    most pixels hold a tone is fitted whole, as before."""
    from cohflash_jax.estimate.base import DETECTED_FEW_SHARE, DETECTED_ONLY_MIN_PIXELS, estimate_detected
    from cohflash_jax.reconstruct import programs

    inst = cf.Instrument.ten_hz_mode()
    plan = build_plan(inst, ReconstructOptions(progress=False))
    rows, cols = 64, 128  # as a full frame's 8192-px sub-tile in memory
    assert rows * cols >= DETECTED_ONLY_MIN_PIXELS
    lit = np.zeros((rows, cols))
    lit[::4, ::4] = 1.0  # one pixel in 16 holds a tone, the rest see nothing
    noise = ("shot_noise", "read_noise")

    def fits(reflectance, power=1.0):
        scene = cf.from_arrays(np.full((rows, cols), 30.5), reflectance, effects=noise)
        link = cf.LinkBudget(probe_power_w=power * inst.link.probe_power_w)
        frames = cf.simulate(scene, cf.Instrument.ten_hz_mode(link=link), rows, cols, jax.random.key(2))
        frames = np.asarray(frames).reshape(4, 35, rows * cols)
        i, q, (c, s, noise_var, total_var), flags = programs.iq_and_carrier_axis(
            plan.iq, frames, np.zeros((4, rows * cols), np.float32)
        )
        r = programs.rotate_program(i, q, c, s)

        def both(r, noise_var, total_var):
            coarse = plan.coarse(r)
            ratio = plan.coarse.detection.ratio(plan.coarse.detection_energy(coarse), 35 * total_var)
            detected = plan.coarse.detection.detected(ratio)
            whole = plan.estimator.estimate(plan.coarse, coarse, r, noise_var)
            alone = estimate_detected(plan.estimator, plan.coarse, coarse, r, noise_var, detected)
            return detected, plan.coarse.depth(coarse, interpolate=True), whole, alone

        return jax.tree.map(np.asarray, jax.jit(both)(r, noise_var, total_var))

    # the same bits on a CPU; a GPU compiles the two ways' kernels apart (rounding, 1e-13)
    same = lambda a, b, name: np.testing.assert_allclose(a, b, rtol=1e-12, atol=0, err_msg=name)
    detected, coarse_depth, whole, alone = fits(lit)
    assert 0.5 * lit.mean() < detected.mean() <= 1 / DETECTED_FEW_SHARE
    for name in ("depth_m", "sigma_m", "amplitude", "coarse_depth_m", "fit_chi2", "converged", "fit_ok"):
        same(getattr(alone, name)[detected], getattr(whole, name)[detected], name)
    np.testing.assert_array_equal(alone.depth_m[~detected], coarse_depth[~detected])
    assert np.all(alone.fit_chi2[~detected] == -1) and np.all(np.isfinite(alone.sigma_m))

    detected, _, whole, alone = fits(np.ones((rows, cols)), power=30.0)
    assert detected.mean() > 0.9
    for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(whole)):
        same(a, b, "every pixel fitted")


def test_a_short_sweep_is_streamed_in_tiles_of_many_rows_to_the_same_bits(tmp_path):
    """By default a tile holds whole 32-row chunks up to `TILE_FRAME_BYTES` of frames: a long
    sweep 32 rows, a short one its whole frame (the 10 Hz mode's 256 rows in one tile, not 8),
    an explicit `tile_rows` as given; never more than the height. Tiling never changes a
    pixel: a 70-row, 35-frame capture in one tile and in 32-row tiles gives the same bits."""
    from cohflash_jax.capture import Capture
    from cohflash_jax.reconstruct import reconstruct_capture
    from cohflash_jax.simulate import simulate_to_file
    from cohflash_jax.tiling import TILE_FRAME_BYTES

    auto = ReconstructOptions(progress=False)
    assert auto.rows_per_tile((3000, 256, 320)) == 32
    assert auto.rows_per_tile((35, 256, 320)) == 256
    assert auto.rows_per_tile((35, 2048, 2048)) == 96 and 4 * 35 * 2048 * 2 * 96 <= TILE_FRAME_BYTES
    assert auto.rows_per_tile((3000, 16, 16)) == 16
    assert ReconstructOptions(tile_rows=8).rows_per_tile((35, 256, 320)) == 8
    inst = cf.Instrument.ten_hz_mode()
    path = tmp_path / "short.h5"
    scene = cf.from_arrays(np.linspace(0.5, 3.0, 70 * 12).reshape(70, 12), np.full((70, 12), 0.8))
    simulate_to_file(path, scene, inst, 70, 12, progress=False)
    with Capture(path) as capture:
        assert auto.rows_per_tile(capture.shape) == 70
        whole = reconstruct_capture(capture, auto).outputs
        chunked = reconstruct_capture(capture, dataclasses.replace(auto, tile_rows=32)).outputs
    assert whole["valid"].mean() > 0.9
    for name in ("depth_m", "sigma_m", "fit_status", "snr"):
        np.testing.assert_array_equal(whole[name], chunked[name])
