"""The detection test (`estimate.detection`) as a claim: its null distribution, its bound for
every carrier phase, its false-alarm rate on pure noise through the whole reconstruction, and
its power against a closed-form SNR. Frames are written here with NumPy (four ports of a
nominal hybrid: I = V₀ − V₂, Q = V₃ − V₁), sharing no code with the simulator."""

import math

import numpy as np
import pytest
from scipy import stats

import cohflash_jax as cf
from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
from cohflash_jax.estimate.detection import (
    beta_tail,
    delay_moments,
    projection_bounds,
    share_threshold,
    uniform_sums,
)
from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array
from cohflash_jax.status import Status


def _ports(z: np.ndarray, rng, port_sigma: float) -> np.ndarray:
    """(4, N, H, W) port frames whose I + i·Q is z (N, H, W) — up to conjugation — plus white
    Gaussian noise of `port_sigma` on each port (I and Q then carry 2·port_sigma²)."""
    ports = np.stack([0.5 * np.real(z * np.exp(-0.5j * math.pi * k)) for k in range(4)])
    return (400.0 + ports + rng.normal(0.0, port_sigma, ports.shape)).astype(np.float32)


@pytest.mark.parametrize(("dim", "frames"), [(2, 35), (4, 35), (4, 3000), (2, 400)])
def test_beta_tail_is_the_beta_distribution(dim, frames):
    for x in (1e-4, 0.01, 0.1, 0.5):
        want = stats.beta.sf(x, dim, frames - 1 - dim)
        assert beta_tail(x, dim, frames) == pytest.approx(want, rel=1e-9, abs=1e-300)
    x = share_threshold(dim, frames, 1e-8)
    assert stats.beta.sf(x, dim, frames - 1 - dim) == pytest.approx(1e-8, rel=1e-6)


def test_two_bin_share_of_noise_is_beta_4():
    """Under white circular noise (mean removed) four complex DFT bins — ±j, ±(j+1) — hold a
    Beta(4, N − 5) share of the energy, whatever σ."""
    rng = np.random.default_rng(1)
    n = 35
    z = rng.normal(size=(20000, n)) + 1j * rng.normal(size=(20000, n))
    z *= rng.uniform(0.1, 10.0, (20000, 1))  # the share does not depend on the level
    z -= z.mean(axis=1, keepdims=True)
    spec = np.abs(np.fft.fft(z, axis=1)) ** 2 / n
    share = spec[:, [5, 6, n - 5, n - 6]].sum(axis=1) / spec.sum(axis=1)
    assert stats.kstest(share, stats.beta(4, n - 5).cdf).pvalue > 1e-3


def test_energy_bounds_hold_for_every_carrier_phase():
    """E_g of r = Re(e^{−iφ}z) ≤ c_g·‖P_g z‖² for any φ, on DFT windows and on delays."""
    rng = np.random.default_rng(2)
    n = 35
    z = rng.normal(size=(400, n)) + 1j * rng.normal(size=(400, n))
    z -= z.mean(axis=1, keepdims=True)
    bins = np.abs(np.fft.fft(z, axis=1)) ** 2 / n
    phases = rng.uniform(0, 2 * math.pi, 64)
    # uniform: two adjacent bins k, k+1 of the real sequence's unitary rFFT
    for phi in phases[:8]:
        r = np.real(np.exp(-1j * phi) * z)
        spectrum = np.fft.rfft(r, axis=1) / math.sqrt(n)
        sums = np.asarray(uniform_sums(spectrum, n))
        # the same sums with the bins on the first axis (the 10 Hz programs' layout)
        np.testing.assert_array_equal(np.asarray(uniform_sums(spectrum.T, n, axis=0)).T, sums)
        for k in range(1, n // 2 - 1):
            bound = bins[:, [k, k + 1, n - k, n - k - 1]].sum(axis=1)
            assert np.all(sums[:, k] <= bound * (1 + 1e-9))
    # non-uniform: one periodogram delay
    f = np.sort(rng.uniform(0.1e9, 6e9, n))
    delays = rng.uniform(0, 2e-9, 16)
    norm_sq, mean, sum_sq = delay_moments(f, delays)
    scale, rank = projection_bounds(norm_sq, mean, sum_sq, n)
    assert np.all(rank == 2)
    for g, tau in enumerate(delays):
        v = np.exp(2j * math.pi * f * tau)
        a = v - v.mean()
        basis, _ = np.linalg.qr(np.stack([a, np.conj(a)], axis=1))
        proj = np.sum(np.abs(z @ np.conj(basis)) ** 2, axis=1)
        worst = max(np.max(np.abs(np.real(np.exp(-1j * phi) * z) @ v) ** 2 / proj) for phi in phases)
        assert worst <= scale[g] * (1 + 1e-9)
        assert worst >= 0.9 * scale[g]  # and nearly reached: the bound is the sup over φ


def test_delay_moments_of_an_evenly_spaced_grid_equal_the_exponentials():
    """`delay_moments` takes an evenly spaced grid's phasors as powers of one step's; a grid of
    delays over a 38 m window (steps equal only to 2e-12 of a step, from rounding) takes that
    path too, and its moments equal those of e^{i2πfτ} per entry to 1e-12 of their size."""
    rng = np.random.default_rng(3)
    f = np.sort(rng.uniform(0.1e9, 6e9, 500))
    delays = 3e-9 + 2 * np.arange(0.0, 38.0, 0.00635) / 299_792_458.0
    norm_sq, mean, sum_sq = delay_moments(f, delays)
    v = np.exp(2j * math.pi * np.multiply.outer(delays, f))
    assert np.allclose(norm_sq, f.size)
    assert np.max(np.abs(mean - v.mean(axis=1))) < 1e-12
    assert np.max(np.abs(sum_sq - (v * v).sum(axis=1))) < 1e-12 * f.size


def _false_alarms(inst: cf.Instrument, alpha: float, seed: int, side: int = 64) -> int:
    rng = np.random.default_rng(seed)
    n = inst.sweep.num_steps
    frames = _ports(np.zeros((n, side, side)), rng, 20.0)
    out = reconstruct_array(frames, inst, ReconstructOptions(method="dft", progress=False, false_alarm=alpha))
    assert np.all(np.isfinite(out["detection_ratio"]))
    assert np.all(out["valid"][out["detection_ratio"] <= 1] == 0)
    return int(np.sum(out["detection_ratio"] > 1))


@pytest.mark.parametrize("schedule", ["uniform 35", "sparse 120"])
def test_false_alarm_rate_on_pure_noise_is_at_most_alpha(schedule):
    """4096 pure-noise pixels at α = 5 %: the count stays within 6σ of a binomial at α (the
    bound is conservative: ~α/10 is measured; `cohflash_experiments.detection`)."""
    if schedule == "uniform 35":
        inst = cf.Instrument.ten_hz_mode()
    else:
        f = 0.1e9 + 50e6 * np.sort(np.random.default_rng(3).choice(118, 120 - 2, replace=False))
        inst = cf.Instrument(sweep=cf.FrequencySweep(np.concatenate([[0.09e9, 0.095e9], f])))
    alpha, pixels = 0.05, 64 * 64
    count = _false_alarms(inst, alpha, seed=4)
    assert count <= alpha * pixels + 6 * math.sqrt(alpha * (1 - alpha) * pixels)


def test_detection_power_against_the_closed_form_snr():
    """At α = 1e-6 and 35 frames a tone of SNR N·a²/(4σ_I²) = 23 dB is detected and one
    of 10 dB is not (measured: 50 % near 16 dB; a tone midway between bins loses ~1 dB):
    catching a limit a few dB off either way."""
    inst = cf.Instrument.ten_hz_mode()
    f = inst.sweep.frequencies_hz
    n, side = f.size, 32
    rng = np.random.default_rng(5)
    depth = rng.uniform(0.03, 0.40, (side, side))
    port_sigma = 10.0
    sigma_i = math.sqrt(2) * port_sigma
    detected = {}
    for snr_db in (10.0, 23.0):
        a = math.sqrt(10 ** (snr_db / 10) * 4 * sigma_i**2 / n)
        r = 50.0 + a * np.cos(2 * math.pi * f[:, None, None] * 2 * depth / C)
        z = np.exp(1j * rng.uniform(0, 2 * math.pi)) * r
        out = reconstruct_array(_ports(z, rng, port_sigma), inst, ReconstructOptions(method="dft", progress=False))
        detected[snr_db] = np.mean(out["fit_status"] != Status.NOT_DETECTED)
    assert detected[23.0] >= 0.99 and detected[10.0] <= 0.01
