"""emcee posteriors: coverage at high SNR, multimodality near the threshold, zero echo."""

import json

import h5py
import jax
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.cli import main
from cohflash_jax.uncertainty import sample_pixels

from .conftest import N_FRAMES

NOISE = ("shot_noise", "read_noise", "dark_current", "quantization")


def _posteriors(inst, frames, max_steps=20000, seed=0):
    return sample_pixels(inst, frames, rng=np.random.default_rng(seed), max_steps=max_steps, quiet=False)


@pytest.mark.runs_long
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_high_snr_intervals_cover_at_nominal_rates_with_crlb_widths(paper_instrument):
    """100 pixels of the planar target at the paper's link budget: 68 % and 95 % intervals cover
    the truth at their nominal rates within two binomial σ (4.7 and 2.2 points at 100 pixels;
    `experiments/posterior_coverage.py` measures it on thousands) and their widths match the
    CRLB (15 %): an interval 20 % too narrow or wide fails the width check. The slowest test."""
    frames = cf.simulate(cf.planar(effects=NOISE), paper_instrument, 10, 10, jax.random.key(42))
    posts = _posteriors(paper_instrument, frames)
    assert all(p.converged for p in posts)
    cover68 = np.mean([p.covers(30.5, 68) for p in posts])
    cover95 = np.mean([p.covers(30.5, 95) for p in posts])
    assert abs(cover68 - 0.68) <= 0.094 and abs(cover95 - 0.95) <= 0.044, (cover68, cover95)
    half68 = np.array([(p.interval68_m[1] - p.interval68_m[0]) / 2 for p in posts])
    crlb = np.array([p.crlb_m for p in posts])
    assert np.median(half68 / crlb) == pytest.approx(1.0, abs=0.15)
    assert not any(p.multimodal for p in posts)
    assert all(0.2 < p.acceptance < 0.8 for p in posts)


@pytest.mark.runs_long
@pytest.mark.filterwarnings("ignore::RuntimeWarning", "ignore::UserWarning")
def test_near_threshold_multimodality_is_detected_and_intervals_widen():
    """24–30 GHz: ripples (5.6 mm) much narrower than the envelope; near the threshold the
    neighbouring ripples hold real probability. The posterior must say so — multimodal, with
    intervals far wider than the CRLB — and still cover the truth where the coarse stage found
    the right DFT bin (the window the posterior describes); pixels whose coarse bin was wrong
    are the ML fit's flagged pixels."""
    inst = cf.Instrument(sweep=cf.FrequencySweep.uniform(24e9, 1.97e6, N_FRAMES))
    frames = cf.simulate(cf.planar(reflectance=0.03, effects=NOISE), inst, 4, 4, jax.random.key(9))
    posts = _posteriors(inst, frames, max_steps=8000)
    multi = [p for p in posts if p.multimodal]
    assert len(multi) >= 4
    widths = np.array([(p.interval95_m[1] - p.interval95_m[0]) / (2 * 1.96 * p.crlb_m) for p in multi])
    assert np.all(widths > 2.0)  # far wider than the CRLB Gaussian would claim
    inside = np.array([abs(p.ml_depth_m - 30.5) < 2 * inst.sweep.bin_depth_m for p in posts])
    assert inside.sum() >= 4
    assert np.mean([p.covers(30.5, 95) for p, i in zip(posts, inside) if i]) >= 0.75
    assert all(p.ml_status != 0 for p, i in zip(posts, inside) if not i)


@pytest.mark.filterwarnings("ignore::RuntimeWarning", "ignore::UserWarning")
def test_zero_echo_ends_with_a_clear_result(paper_instrument, tmp_path, capsys):
    from cohflash_jax.simulate import simulate_to_file

    cap = tmp_path / "dark.h5"
    simulate_to_file(
        cap,
        cf.from_arrays(np.full((2, 2), 30.5), np.zeros((2, 2)), effects=NOISE),
        paper_instrument,
        2,
        2,
        progress=False,
    )
    out = tmp_path / "posterior.h5"
    rc = main(
        [
            "uncertainty",
            str(cap),
            "--pixel",
            "0,0",
            "--pixel",
            "1,1",
            "--out",
            str(out),
            "--plot",
            str(tmp_path / "p.png"),
            "--max-steps",
            "2000",
            "--quiet",
        ]
    )
    assert rc == 0
    assert "ML fit flagged" in capsys.readouterr().out
    with h5py.File(out) as f:
        assert f.attrs["format"] == "cohflash-posterior" and list(f["row"][()]) == [0, 1]
        assert np.all(np.isfinite(f["lo95_m"][()])) and np.all(f["hi95_m"][()] > f["lo95_m"][()])
        assert f["samples/pixel_0_0"].shape[1] == 3
    assert (tmp_path / "p_0_0.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["uncertainty", str(cap), "--pixel", "5,5", "--out", str(out)]) == 2
    assert main(["uncertainty", str(cap), "--out", str(out)]) == 2
    with pytest.raises(SystemExit) as refused:  # argparse refuses it, naming the option
        main(["uncertainty", str(cap), "--pixel", "0,0", "--out", str(out), "--max-steps", "0"])
    assert refused.value.code == 2 and "--max-steps" in capsys.readouterr().err
    # --chains writes OUT.chains.h5: refused where that is the capture itself
    twin = tmp_path / "p.chains.h5"
    twin.write_bytes(cap.read_bytes())
    assert main(["uncertainty", str(twin), "--pixel", "0,0", "--out", str(tmp_path / "p.h5"), "--chains"]) == 2
    assert twin.read_bytes() == cap.read_bytes()
    # a dead pixel (constant frames) gets no posterior: it is skipped and named, the rest sampled
    with h5py.File(cap, "r+") as f:
        f["frames"][:, :, 1, 0] = 200
    rc = main(
        [
            "uncertainty",
            str(cap),
            "--pixel",
            "0,0",
            "--pixel",
            "1,0",
            "--out",
            str(out),
            "--max-steps",
            "2000",
            "--quiet",
        ]
    )
    assert rc == 0 and "skipped 1 pixel(s) with unusable data (no posterior): (1,0) dead" in capsys.readouterr().out
    with h5py.File(out) as f:
        assert list(f["row"][()]) == [0] and json.loads(f.attrs["skipped_pixels"]) == [[1, 0, "dead (constant)"]]
    # nothing usable: a clear error (two dead pixels keep the compiled two-pixel shape)
    with h5py.File(cap, "r+") as f:
        f["frames"][:, :, 1, 1] = 300
    assert main(["uncertainty", str(cap), "--pixel", "1,0", "--pixel", "1,1", "--out", str(out)]) == 2
    assert "no pixel with usable data: (1, 0) dead" in capsys.readouterr().err
    # a pixel named twice is refused before any sampling, naming it
    assert main(["uncertainty", str(cap), "--pixel", "0,0", "--pixel", "0,0", "--out", str(out)]) == 2
    assert "named more than once: (0, 0)" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_posterior_is_reproducible_for_its_seed(paper_instrument):
    """emcee draws its moves from NumPy's global generator unless seeded: the same pixel and
    seed must give the same chain, whatever ran before in the process."""
    frames = cf.simulate(cf.planar(effects=NOISE), paper_instrument, 1, 1, jax.random.key(4))
    first = _posteriors(paper_instrument, frames, max_steps=500, seed=9)[0]
    np.random.default_rng().standard_normal(10)  # what a library might do in between
    np.random.seed(None)
    second = _posteriors(paper_instrument, frames, max_steps=500, seed=9)[0]
    np.testing.assert_array_equal(first.samples, second.samples)


def test_the_log_posterior_is_the_window_models_gaussian_likelihood(paper_instrument):
    """emcee's log-posterior reduces each pixel to a few dot products on a depth grid; it must
    equal −χ²/σ² of the window model evaluated directly at each walker's exact depth (the
    carrier-phase split into r and q, the bin weights, the offset fitted by least squares),
    to the grid's interpolation error, and be −∞ outside the prior."""
    from cohflash_jax.estimate.window_model import bin_weights, window_tables
    from cohflash_jax.reconstruct import ReconstructOptions, build_plan
    from cohflash_jax.uncertainty import make_log_prob, pixel_data

    inst = paper_instrument
    n = N_FRAMES
    # at 30.5 m the window is far from DC; at 8 cm (three bins) it holds the offset's column
    scenes = [cf.planar(distance, effects=NOISE) for distance in (30.5, 0.08)]
    frames = np.concatenate(
        [np.asarray(cf.simulate(sc, inst, 1, 2, jax.random.key(3))).reshape(4, n, -1) for sc in scenes], axis=-1
    )
    options = ReconstructOptions(method="ml")
    plan = build_plan(inst, options, float(inst.sensor.adc_max_dn))
    data = pixel_data(plan, jax.numpy.asarray(frames), options.window_bins)
    g = plan.geometry
    half = 2 * g.bin_depth_m
    rng = np.random.default_rng(0)
    with_offset_column = 0
    for p in range(4):
        d = jax.tree_util.tree_map(lambda x, p=p: x[p], data)
        log_prob = make_log_prob(plan.model, d, depth_half_range_m=half, ambiguity_m=g.ambiguity_m, ripple_m=g.ripple_m)
        width = int(d.r_window.shape[0])
        tables = window_tables(d.k0, width, n)
        dc = np.asarray(plan.model.dc_column(tables))
        omega = np.asarray(bin_weights(tables, n))
        y = np.concatenate([d.r_window, d.q_window])
        thetas = np.stack(
            [
                rng.uniform(-0.9e3 * half, 0.9e3 * half, 30),
                float(d.ml_amplitude) * rng.uniform(0.5, 1.5, 30),
                rng.uniform(-np.pi, np.pi, 30),
            ],
            axis=-1,
        )
        direct = []
        for offset_mm, amp, phase in thetas:
            tone = np.asarray(plan.model.tone_column(d.ml_depth_m + 1e-3 * offset_mm, tables))
            split = np.array([np.cos(phase), np.sin(phase)])
            model = np.concatenate(split[:, None] * amp * tone[None]).astype(complex)
            column = np.concatenate(split[:, None] * dc[None])
            weight = np.tile(omega, 2)
            real = lambda z: np.concatenate([z.real, z.imag])
            a, b = real(weight * column), real(weight * (y - model))
            resid = b - a * (a @ b) / (a @ a) if a @ a > 0 else b
            direct.append(-(resid @ resid) / float(d.noise_var))
        direct = np.array(direct)
        with_offset_column += bool(np.any(dc != 0))
        np.testing.assert_allclose(log_prob(thetas), direct, rtol=1e-6, atol=1e-3)
        outside = thetas[:4].copy()
        outside[0, 0], outside[1, 1], outside[2, 2], outside[3, 0] = 1.2e3 * half, -1.0, 3.5, -1.2e3 * half
        assert np.all(log_prob(outside) == -np.inf)
    assert with_offset_column == 2


def test_acceptance_in_one_draw_walks_emcees_own_chains():
    """`AcceptanceInOneDraw` and our `EnsembleSampler` change how emcee's step is computed, not
    what it draws: from the same seed, emcee's stock moves and sampler and ours walk the same
    chains to the bit, for the differential-evolution move and for the snooker move (whose
    Metropolis factors are not zero), on a two-mode target with walkers proposed outside it."""
    import emcee

    from cohflash_jax.ensemble import AcceptanceInOneDraw, DEMove, EnsembleSampler

    class Snooker(AcceptanceInOneDraw, emcee.moves.DESnookerMove):
        pass

    def log_prob(x):  # vectorised; −inf beyond |x₀| = 2.5
        modes = np.logaddexp(-0.5 * np.sum((x - 1) ** 2, axis=1), -2.0 * np.sum((x + 1) ** 2, axis=1))
        return np.where(np.abs(x[:, 0]) < 2.5, modes, -np.inf)

    start = np.random.default_rng(0).normal(0.0, 0.5, (16, 3))

    def chain(sampler, moves):
        s = sampler(16, 3, log_prob, vectorize=True, moves=moves)
        s.random_state = np.random.RandomState(7).get_state()
        s.run_mcmc(start, 400)
        return s.get_chain(), s.get_log_prob(), s.acceptance_fraction

    stock = [(emcee.moves.DEMove(), 0.7), (emcee.moves.DESnookerMove(), 0.3)]
    ours = [(DEMove(), 0.7), (Snooker(), 0.3)]
    expected, got = chain(emcee.EnsembleSampler, stock), chain(EnsembleSampler, ours)
    for a, b in zip(expected, got):
        np.testing.assert_array_equal(a, b)
    assert 0.1 < got[2].mean() < 0.9 and np.isfinite(got[1]).all()


def test_lockstep_ensembles_walk_each_targets_own_emcee_chain():
    """`LockstepEnsembles` steps several targets together, each from its own seed: each
    target's chain, log-probabilities and acceptance must be those emcee's sampler walks for
    it alone, to the bit, with both moves drawn, some targets stepped longer than others (as a
    posterior run retires converged pixels) and a target that starts later."""

    from cohflash_jax.ensemble import DEMove, EnsembleSampler, LockstepEnsembles, SnookerMove

    centres = np.array([-1.0, 0.0, 0.5, 2.0])

    def log_prob(targets, x):  # (n, k, 3) → (n, k): two modes a target, −inf beyond |x₀ − c| = 2.5
        shift = x - centres[np.asarray(targets)][:, None, None]
        modes = np.logaddexp(-0.5 * np.sum((shift - 1) ** 2, axis=-1), -2.0 * np.sum((shift + 1) ** 2, axis=-1))
        return np.where(np.abs(shift[..., 0]) < 2.5, modes, -np.inf)

    starts = np.random.default_rng(0).normal(0.0, 0.5, (4, 16, 3)) + centres[:, None, None]
    seeds = [7, 8, 9, 10]
    moves = lambda: [(DEMove(), 0.6), (SnookerMove(), 0.4)]
    lockstep = LockstepEnsembles(log_prob, 4, 16, 3, moves())
    lockstep.start(np.arange(3), starts[:3], seeds[:3])
    lockstep.run(np.arange(3), 150)
    lockstep.start(3, starts[3:], seeds[3])
    lockstep.run(np.array([0, 2, 3]), 100)  # target 1 retired, target 3 started
    lockstep.run(np.array([2]), 50)
    for t, steps in enumerate((250, 150, 300, 100)):
        alone = EnsembleSampler(16, 3, lambda x, t=t: log_prob([t], x[None])[0], vectorize=True, moves=moves())
        alone.random_state = np.random.RandomState(seeds[t]).get_state()
        alone.run_mcmc(starts[t], steps)
        np.testing.assert_array_equal(lockstep.chain(t), alone.get_chain())
        np.testing.assert_array_equal(lockstep.log_prob[t], alone.get_log_prob()[-1])
        np.testing.assert_array_equal(lockstep.acceptance_fraction(t), alone.acceptance_fraction)
    assert 0.1 < np.mean([lockstep.acceptance_fraction(t) for t in range(4)]) < 0.9


def test_integrated_times_are_emcees():
    """`integrated_times` takes every walker's transform in one call: the same τ as emcee's
    `autocorr.integrated_time`, to the bit, for short, power-of-two and long chains."""
    import emcee

    from cohflash_jax.ensemble import integrated_times

    rng = np.random.default_rng(1)
    for steps in (2, 250, 256, 257, 1750):
        chain = np.cumsum(rng.normal(size=(steps, 32, 3)), axis=0) * [1.0, 1e3, 1e-3]
        np.testing.assert_array_equal(integrated_times(chain), emcee.autocorr.integrated_time(chain, tol=0))


@pytest.mark.filterwarnings("ignore::RuntimeWarning", "ignore::UserWarning")
def test_pixels_sampled_together_get_the_posteriors_of_pixels_sampled_alone(paper_instrument):
    """`sample_pixels_of` (the pixels stepped together) and `sample_pixel` (emcee's own
    sampler, a pixel at a time) give each pixel the same posterior from the same seed: samples,
    intervals, τ, acceptance and steps, where one pixel converges sooner than another and a
    third, near the threshold, never does."""
    import dataclasses

    from cohflash_jax.reconstruct import ReconstructOptions, build_plan
    from cohflash_jax.runtime import EXECUTABLES
    from cohflash_jax.uncertainty import pixel_data, sample_pixel, sample_pixels_of

    inst = paper_instrument
    scene = cf.from_arrays(np.full((1, 3), 30.5), np.array([[0.5, 0.3, 0.004]]), effects=NOISE)
    frames = cf.simulate(scene, inst, 1, 3, jax.random.key(5))
    options = ReconstructOptions(method="ml")
    plan = build_plan(inst, options, float(inst.sensor.adc_max_dn))
    flat = np.asarray(frames).reshape(4, N_FRAMES, -1)
    data = pixel_data(plan, jax.numpy.asarray(flat), options.window_bins)
    # a few pixels are padded to their pixel bucket: two of them run the three's program, and
    # each pixel's data are its own, bit for bit
    made = EXECUTABLES.compiled + EXECUTABLES.loaded
    first_two = pixel_data(plan, jax.numpy.asarray(flat[..., :2]), options.window_bins)
    assert EXECUTABLES.compiled + EXECUTABLES.loaded == made, "two pixels made a program of their own"
    for field in dataclasses.fields(first_two):
        np.testing.assert_array_equal(getattr(first_two, field.name), getattr(data, field.name)[:2])
    g = plan.geometry
    geometry = dict(ambiguity_m=g.ambiguity_m, bin_depth_m=g.bin_depth_m, ripple_m=g.ripple_m)
    together = sample_pixels_of(plan.model, data, **geometry, rng=np.random.default_rng(6), max_steps=1500)
    rng = np.random.default_rng(6)
    alone = [
        sample_pixel(plan.model, jax.tree.map(lambda x, p=p: x[p], data), **geometry, rng=rng, max_steps=1500)
        for p in range(3)
    ]
    for a, b in zip(together, alone):
        np.testing.assert_array_equal(a.samples, b.samples)
        assert (a.interval68_m, a.interval95_m, a.steps, a.converged) == (
            b.interval68_m,
            b.interval95_m,
            b.steps,
            b.converged,
        )
        np.testing.assert_array_equal([a.autocorr_steps, a.acceptance], [b.autocorr_steps, b.acceptance])
    # the case this test is for: a pixel released, converged, while the others step on (which
    # step it converges at depends on the last bits of the log-probability: JAX's version, the
    # device), and the faint pixel runs to the limit
    assert [p.converged for p in together] == [True, True, False]
    assert min(p.steps for p in together[:2]) < 1500 and together[2].steps == 1500


def test_the_vectorised_snooker_move_proposes_as_emcees_own():
    """`SnookerMove` draws emcee's `DESnookerMove` proposal for all walkers at once: from the
    same walkers and complementary sub-ensembles, 4,000 proposals each, the two laws of every
    coordinate and of the Metropolis factor agree (two-sample KS). Leaving out emcee's random
    order of the three chosen walkers, or its 1/√|x − z| scaling, fails this."""
    import emcee
    from scipy.stats import ks_2samp

    from cohflash_jax.ensemble import SnookerMove

    rng = np.random.default_rng(3)
    walkers = rng.normal(size=(8, 3)) * [1.0, 5.0, 0.2]
    complement = [rng.normal(size=(8, 3)) * [1.0, 5.0, 0.2] + k for k in range(3)]

    def draws(move, seed):
        state = np.random.RandomState(seed)
        out = [move.get_proposal(walkers, complement, state) for _ in range(4000)]
        return np.stack([q for q, _ in out]), np.stack([f for _, f in out])  # (4000, 8, 3), (4000, 8)

    (q_emcee, f_emcee), (q_ours, f_ours) = draws(emcee.moves.DESnookerMove(), 1), draws(SnookerMove(), 2)
    for walker in (0, 5):
        for axis in range(3):
            assert ks_2samp(q_emcee[:, walker, axis], q_ours[:, walker, axis]).pvalue > 1e-4, (walker, axis)
        assert ks_2samp(f_emcee[:, walker], f_ours[:, walker]).pvalue > 1e-4, walker
