"""Every strictly increasing schedule reconstructs with bounded memory: the coarse search is
sized by the depth resolution and the schedule's own ambiguity, never by its smallest gap, and
the ML reaches the schedule's CRLB (`fisher.depth_crlb_m`)."""

import dataclasses

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.cli import main
from cohflash_jax.fisher import depth_crlb_m
from cohflash_jax.geometry import MIN_HORIZON_POINTS, SweepGeometry, schedule_period_s
from cohflash_jax.radiometry import PAPER_PROBE_POWER_W, LinkBudget
from cohflash_jax.reconstruct import ReconstructOptions, build_plan, reconstruct_array

from .independent_writer import PAPER_FREQUENCIES_HZ, Writer

C = 299_792_458.0
NOISE = ("shot_noise", "read_noise", "dark_current", "quantization", "sidebands")
OPTIONS = ReconstructOptions(progress=False)


def _random_schedule(n, rng, tiny_gaps=0):
    f = np.sort(rng.uniform(0.1e9, 6e9, n - tiny_gaps))
    f[0], f[-1] = 0.1e9, 6e9
    if tiny_gaps:  # a run of frequencies a few hertz apart
        f = np.sort(np.concatenate([f, f[n // 2] + 3.0 * np.arange(1, tiny_gaps + 1)]))
    return f


def _instrument(f, power=1.0):
    inst = cf.Instrument.paper(3000)
    return dataclasses.replace(
        inst, sweep=cf.FrequencySweep(f), link=LinkBudget(probe_power_w=power * PAPER_PROBE_POWER_W)
    )


def _schedules():
    rng = np.random.default_rng(19)
    comb = PAPER_FREQUENCIES_HZ
    t = np.sort(np.r_[0.0, 1.0, rng.uniform(0, 1, 298)])
    centres = np.linspace(0.2e9, 5.9e9, 12)
    return {
        "random 3000, 3 Hz gaps": _random_schedule(3000, rng, tiny_gaps=10),
        "sparse 35 of the paper's comb": comb[np.sort(np.r_[0, 2999, rng.choice(np.arange(1, 2999), 33, False)])],
        "band-edge weighted 300": np.unique(0.1e9 + 5.9e9 * (1 - np.cos(np.pi * t)) / 2),
        "clustered 240": np.sort((centres[:, None] + rng.uniform(-20e6, 20e6, (12, 20))).ravel()),
        "random 20": _random_schedule(20, rng),
    }


SCHEDULES = _schedules()


def test_the_coarse_search_is_sized_by_resolution_and_ambiguity_not_the_smallest_gap():
    for name, f in SCHEDULES.items():
        geometry = SweepGeometry.of(f, np.array([0.3, 0.2, 0.05]))
        plan = build_plan(_instrument(f), OPTIONS)
        points = len(plan.coarse.depths_m)
        assert points <= max(2 * (f.size - 1), MIN_HORIZON_POINTS) + 1, name
        assert geometry.ambiguity_m == pytest.approx(plan.geometry.ambiguity_m)
    # a subset of one comb keeps the comb's ambiguity; a uniform sweep's is c/(4Δf)
    comb = PAPER_FREQUENCIES_HZ[:350]
    assert schedule_period_s(comb[::7]) == pytest.approx(1 / (7 * 1.97e6), rel=1e-6)
    assert schedule_period_s(comb[np.r_[0, 3, 4, 9, 20, 21, 40, 77, 200, 349]]) == pytest.approx(1 / 1.97e6, rel=1e-6)


@pytest.mark.parametrize("name", list(SCHEDULES))
def test_every_schedule_reconstructs_honestly(name):
    """Finite outputs; valid pixels within 6σ of the truth; the ML at the schedule's CRLB
    (within 20 %) for the random 3000-step and the sparse 35-step schedules."""
    f = SCHEDULES[name]
    inst = _instrument(f, power=max(1.0, 3000 / f.size))
    # 20 frames over 2048 delays leave the union-bound test at 1e-6 little power (the largest
    # share a pure tone can reach is ~1.2 × its limit): this case tests at 1e-3
    options = dataclasses.replace(OPTIONS, false_alarm=1e-3) if f.size < 35 else OPTIONS
    window = build_plan(inst, options).geometry.valid_window_m
    rng = np.random.default_rng(3)
    depth = rng.uniform(window[0] + 0.2 * (window[1] - window[0]), window[1] - 0.2 * (window[1] - window[0]))
    scene = cf.from_arrays(np.full((12, 12), depth), np.full((12, 12), 0.5), effects=NOISE)
    out = reconstruct_array(cf.simulate(scene, inst, 12, 12, jax.random.key(4)), inst, options)
    for k, v in out.items():
        assert np.all(np.isfinite(v)), k
    valid = out["valid"]
    err = out["depth_m"] - depth
    assert np.all(np.abs(err[valid]) < 6 * out["sigma_m"][valid])
    assert valid.mean() > (0.6 if f.size < 35 else 0.9)
    crlb = float(depth_crlb_m(inst, depth, 0.5, effects=NOISE, range_falloff=False))
    if name.startswith(("random 3000", "sparse 35")):
        assert np.std(err[valid]) == pytest.approx(crlb, rel=0.2)


def test_independent_random_schedule_with_hertz_gaps_reconstructs_at_its_crlb(tmp_path):
    rng = np.random.default_rng(20)
    writer = Writer(frequencies_hz=_random_schedule(3000, rng, tiny_gaps=10))
    cap, out = tmp_path / "random.h5", tmp_path / "depth.h5"
    writer.write(cap, np.full((12, 12), 17.3), rng)
    assert main(["reconstruct", str(cap), "--out", str(out), "--quiet"]) == 0
    with h5py.File(out) as fh:
        depth, valid, sigma = fh["depth_m"][()], fh["valid"][()].astype(bool), fh["sigma_m"][()]
        assert fh.attrs["depth_window_m"][1] > 17.3
    assert valid.all()
    assert np.std(depth - 17.3) < 1.3 * writer.crlb_m()
    assert np.all(np.abs(depth - 17.3) < 6 * sigma)


def explicit_tone(f, weights, delay_s, depth_m):
    """Σ_n 2 w_n cos(2π n f τ) from explicit cosines (the NumPy reference of the time-domain tests)."""
    tau = delay_s + 2 * depth_m / C
    return sum(2 * weights[n] * np.cos(2 * np.pi * n * f * tau) for n in range(1, weights.size))


def lstsq_fit(tone, r):
    """(c, A) on [1, tone] by `lstsq` and the residual energy."""
    design = np.stack([np.ones_like(tone), tone], axis=1)
    coef = np.linalg.lstsq(design, r, rcond=None)[0]
    return coef, np.sum((r - design @ coef) ** 2)


@pytest.mark.parametrize("schedule", ["uniform 3000", "random 40"])
def test_time_domain_fit_equals_a_brute_force_least_squares_fit(schedule):
    """The time-domain ML (closed-form tone jets, costs from Gram matrices) against NumPy: the
    tone and its depth derivative summed order by order from explicit cosines and sines,
    (c, A) by `lstsq`, and the depth where the residual is orthogonal to A·∂t/∂d (the cost's
    slope, by the envelope theorem) by SciPy's `brentq`; σ from that Jacobian. Seven sideband
    orders, noisy pixels; depths agree to 1e-3 σ, σ to 1e-6."""
    from scipy.optimize import brentq

    from cohflash_jax.estimate.time_domain import refine_time_domain

    rng = np.random.default_rng(7)
    f = 1e9 + 1.97e6 * np.arange(3000) if schedule == "uniform 3000" else np.sort(rng.uniform(1e9, 7e9, 40))
    weights = np.array([0.1, 0.5, 0.2, 0.3, 0.05, 0.02, 0.01, 0.005])
    delay_s, half_width_m = 3e-9, 0.004

    def tone(depth):
        return explicit_tone(f, weights, delay_s, depth)

    def tone_slope(depth):
        tau = delay_s + 2 * depth / C
        return sum(
            -2 * weights[n] * (4 * np.pi * n * f / C) * np.sin(2 * np.pi * n * f * tau) for n in range(1, weights.size)
        )

    def fit(depth, r):
        return lstsq_fit(tone(depth), r)

    noise_var = 4.0
    truths = rng.uniform(10.0, 20.0, 6)
    frames = np.stack([7.0 + 30.0 * tone(d) + np.sqrt(noise_var) * rng.standard_normal(f.size) for d in truths], 1)
    starts = truths + rng.uniform(-0.3, 0.3, truths.size) * half_width_m
    out = jax.jit(
        jax.vmap(
            lambda r, d: refine_time_domain(
                r,
                np.asarray(f),
                np.asarray(weights),
                d,
                noise_var,
                system_delay_s=delay_s,
                grid_half_width_m=half_width_m,
                grid_points=41,
                max_steps=16,
            )
        )
    )(frames.T, starts)
    assert np.all(np.asarray(out.converged)) and np.all(np.asarray(out.well_posed))
    for k, (truth, start) in enumerate(zip(truths, starts)):
        r = frames[:, k]
        # the cost ripples at c/(4 f_max·7): bracket the JAX fit's basin by a fine scan first
        scan = start + np.linspace(-half_width_m, half_width_m, 4001)
        best = scan[np.argmin([fit(d, r)[1] for d in scan])]
        step = scan[1] - scan[0]
        residual_slope = lambda d: (r - fit(d, r)[0] @ [np.ones_like(f), tone(d)]) @ tone_slope(d)
        ref = brentq(residual_slope, best - step, best + step, xtol=1e-15, rtol=1e-15)
        coef, cost = fit(ref, r)
        jac = np.stack([coef[1] * tone_slope(ref), np.ones_like(f), tone(ref)], axis=1)
        sigma = np.sqrt(noise_var * np.linalg.inv(jac.T @ jac)[0, 0])
        assert abs(float(out.depth_m[k]) - ref) < 1e-3 * sigma, (schedule, k)
        assert float(out.sigma_depth_m[k]) == pytest.approx(sigma, rel=1e-6)
        assert float(out.amplitude[k]) == pytest.approx(coef[1], rel=1e-7)
        assert float(out.cost[k]) == pytest.approx(cost, rel=1e-9)
        assert abs(ref - truth) < 6 * sigma


def test_time_domain_basin_grid_equals_explicit_least_squares_costs():
    """The basin grid's costs come from matrix products of the grid's and the fits' phasor
    powers (`TimeDomainModel.grid_starts`: t·t from the orders' sum and difference terms).
    Against NumPy: at every grid point the tone from explicit cosines, (c, A) by `lstsq`; the
    best grid point and its cost agree (cost to 1e-9). Seven orders, a 40-step random schedule,
    noisy fits from several depths; dropping a difference term shifts the costs by percents."""
    from cohflash_jax.estimate.time_domain import TimeDomainModel, TimeDomainPixel

    rng = np.random.default_rng(11)
    f = np.sort(rng.uniform(1e9, 7e9, 40))
    weights = np.array([0.1, 0.5, 0.2, 0.3, 0.05, 0.02, 0.01, 0.005])
    delay_s, half_width_m, points = 3e-9, 0.004, 41

    def tone(depth):
        return explicit_tone(f, weights, delay_s, depth)

    depths = rng.uniform(10.0, 20.0, 5)
    frames = np.stack([7.0 + 30.0 * tone(d + 1e-3) + 2.0 * rng.standard_normal(f.size) for d in depths])
    pixels = jax.vmap(TimeDomainPixel.of)(jnp.asarray(frames))
    model = TimeDomainModel(jnp.asarray(f), jnp.asarray(weights), delay_s)
    best_mm, ceiling = model.grid_starts(pixels, jnp.asarray(depths), half_width_m, points)
    grid_mm = np.linspace(-1e3 * half_width_m, 1e3 * half_width_m, points)
    for k, depth in enumerate(depths):
        y = np.asarray(pixels.y[k])
        costs = [lstsq_fit(tone(depth + 1e-3 * offset), y)[1] for offset in grid_mm]
        assert float(best_mm[k]) == pytest.approx(grid_mm[np.argmin(costs)], abs=1e-9)
        assert float(ceiling[k]) == pytest.approx(min(costs), rel=1e-9)


def test_time_domain_fits_in_two_passes_end_as_one_uninterrupted_polish():
    """`TimeDomainML.fit_each` polishes its batch in two passes (`polish_in_passes`): each fit
    must end exactly as `refine_time_domain`'s uninterrupted polish ends it — same steps, same
    convergence, same depth. Low-SNR pixels of a 40-step random schedule from six starts
    each, so that stragglers fill more than one group."""
    from cohflash_jax.estimate.polish import FIRST_PASS_STEPS, STRAGGLER_GROUP
    from cohflash_jax.estimate.time_domain import TimeDomainML, refine_time_domain

    rng = np.random.default_rng(11)
    f = np.sort(rng.uniform(1e9, 7e9, 40))
    weights = np.array([0.1, 0.5, 0.2, 0.3])
    pixels, starts_per_pixel, half_width_m, points = 48, 6, 0.02, 33
    truth = rng.uniform(10.0, 20.0, pixels)
    tau = 2 * truth / C
    tone = sum(2 * weights[n] * np.cos(2 * np.pi * n * f[:, None] * tau[None]) for n in range(1, weights.size))
    frames = 5.0 + rng.uniform(0.5, 3.0, pixels) * tone + rng.standard_normal(tone.shape)
    starts = truth[None] + rng.uniform(-3, 3, (starts_per_pixel, pixels)) * half_width_m
    noise_var = np.ones(pixels)
    est = TimeDomainML(jnp.asarray(f), jnp.asarray(weights), 0.0, half_width_m, points, 16, starts_per_pixel)
    fit_each = jax.jit(lambda e, r, s, v: e.fit_each(r, s, v))
    batch = fit_each(est, jnp.asarray(frames), jnp.asarray(starts), jnp.asarray(noise_var))
    one = jax.jit(
        jax.vmap(
            jax.vmap(
                lambda r, d, v: refine_time_domain(
                    r,
                    jnp.asarray(f),
                    jnp.asarray(weights),
                    d,
                    v,
                    system_delay_s=0.0,
                    grid_half_width_m=half_width_m,
                    grid_points=points,
                    max_steps=16,
                )
            ),
            in_axes=(None, 0, None),
        )
    )(jnp.asarray(frames.T), jnp.asarray(starts), jnp.asarray(noise_var))
    steps = np.asarray(one.num_steps)
    assert (steps > FIRST_PASS_STEPS).sum() > STRAGGLER_GROUP  # stragglers in two groups at least
    np.testing.assert_array_equal(np.asarray(batch.num_steps), steps)
    np.testing.assert_array_equal(np.asarray(batch.converged), np.asarray(one.converged))
    np.testing.assert_allclose(np.asarray(batch.depth_m), np.asarray(one.depth_m), rtol=0, atol=1e-12)
    posed = np.asarray(one.well_posed) & np.asarray(one.converged)
    np.testing.assert_array_equal(np.asarray(batch.well_posed), np.asarray(one.well_posed))
    assert posed.mean() > 0.5
    sigma = lambda fit: np.asarray(fit.sigma_depth_m)[posed]
    np.testing.assert_allclose(sigma(batch), sigma(one), rtol=1e-9)


def test_delay_periodogram_equals_the_explicit_float64_periodogram():
    """The non-uniform coarse stage's power (its basis as products of two phasor tables, one
    real product with the data, float32) against |Σ_m (r[m] − r̄)·e^{−i2πf_m τ_g}|² in NumPy
    float64 on every grid delay, with a system delay: within 1e-5 of each pixel's peak power,
    and the same peak."""
    rng = np.random.default_rng(5)
    inst = _instrument(_random_schedule(700, rng))
    inst = inst.replace(system_delay_s=4.3e-9)
    plan = build_plan(inst, OPTIONS)
    coarse = plan.coarse
    f, depths = np.asarray(coarse.frequencies_hz), np.asarray(coarse.depths_m)
    assert depths.size > 2 * 64  # several of the basis' blocks
    delays = 4.3e-9 + 2 * depths / C
    truth = rng.uniform(depths[0], depths[-1], 32)
    r = 3 * np.cos(2 * np.pi * f[:, None] * (4.3e-9 + 2 * truth[None] / C))
    r = (r + rng.standard_normal(r.shape)).astype(np.float32)
    power = np.asarray(jax.jit(lambda c, x: c(x).power)(coarse, jnp.asarray(r)))
    centred = r.astype(np.float64) - r.astype(np.float64).mean(0)
    reference = np.abs(centred.T @ np.exp(-2j * np.pi * np.outer(f, delays))) ** 2
    assert np.max(np.abs(power - reference) / reference.max(axis=1, keepdims=True)) < 1e-5
    np.testing.assert_array_equal(power.argmax(axis=1), reference.argmax(axis=1))
