"""Modulator physics: Bessel functions, sideband weights, S(ψ) against brute force."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import jv

import cohflash_jax as cf


@pytest.mark.parametrize("order", [0, 1, 2, 3, 7, 15, 32])
def test_bessel_matches_scipy_float64(order):
    x = np.linspace(0, 20, 401)
    assert np.max(np.abs(np.asarray(cf.bessel_j(order, x)) - jv(order, x))) < 1e-14


@pytest.mark.parametrize("max_order", [1, 3, 8, 32])
def test_fewer_nodes_for_low_orders_keep_float64_accuracy(max_order):
    """`bessel_nodes(max_order)` (the sideband weights' node count) gives every order up to
    `max_order` to rounding over the whole argument range; a rule with too few nodes does not
    (the check can fail)."""
    from cohflash_jax.modulator import bessel_nodes

    x = np.linspace(0, 20, 2001)
    for n in range(-max_order, max_order + 1):
        assert np.max(np.abs(np.asarray(cf.bessel_j(n, x, bessel_nodes(max_order))) - jv(n, x))) < 1e-14, n
    too_few = np.asarray(cf.bessel_j(max_order, x, max_order + 20))
    assert np.max(np.abs(too_few - jv(max_order, x))) > 1e-10


def test_bessel_float32_small_and_zero_argument_is_finite_and_accurate():
    # over the whole documented domain (orders ≤ 32, |x| ≤ 20): n·t is reduced exactly, so
    # float32 stays at a few ulp of 1 at every order (measured 2.5e-7)
    x = np.array([0.0, 1e-30, 1e-8, 1e-3, 0.5, 3.83, 7.0, 15.0, 19.9], np.float32)
    for n in range(0, 33):
        got = np.asarray(cf.bessel_j(n, jnp.asarray(x)))
        assert got.dtype == np.float32
        assert np.all(np.isfinite(got))
        assert np.max(np.abs(got - jv(n, x.astype(np.float64)))) < 1e-6
    # jax.scipy's own bessel_jn is NaN at 0 — ours is J_n(0) = δ_n0 to rounding
    at_zero = np.asarray(cf.bessel_j(jnp.arange(33), jnp.float32(0.0)))
    np.testing.assert_allclose(at_zero, np.eye(33)[0], rtol=0, atol=1e-7)
    assert np.max(np.abs(np.asarray(cf.bessel_j(jnp.arange(33), 0.0)) - np.eye(33)[0])) < 1e-15


def test_bessel_gradient_is_finite_and_matches_recurrence():
    # d/dx J_n = (J_{n-1} − J_{n+1})/2, including at x = 0 and for high orders
    for n in (1, 2, 10, 30):
        for x in (0.0, 1e-6, 2.0, 15.0):
            g = jax.grad(lambda v: cf.bessel_j(n, v))(jnp.float64(x))
            expect = 0.5 * (jv(n - 1, x) - jv(n + 1, x))
            assert np.isfinite(g) and abs(float(g) - expect) < 1e-13


def _brute_force_beat(x, bias, psi, samples=4096):
    """⟨t(t)·t(t − τ)⟩ over one modulation period, t = cos(θ_b + x cos Ωt)."""
    wt = 2 * np.pi * np.arange(samples) / samples
    return np.mean(np.cos(bias + x * np.cos(wt)) * np.cos(bias + x * np.cos(wt - psi)))


@pytest.mark.parametrize("x,bias", [(1.0, np.pi / 4), (1.84, 0.3), (3.0, 1.2), (0.2, np.pi / 4), (2.5, 0.0)])
def test_beat_equals_time_average_of_mzm_field(x, bias):
    psi = np.linspace(-7, 13, 23)
    w = cf.sideband_weights(x, bias, 24)
    model = np.asarray(cf.beat_spectrum(jnp.asarray(psi), w))
    brute = np.array([_brute_force_beat(x, bias, p) for p in psi])
    assert np.max(np.abs(model - brute)) < 1e-12
    # S(0) is the mean transmission, and it has the closed form ½ + ½cos 2θ_b J0(2x)
    assert abs(float(cf.mean_transmission(x, bias)) - _brute_force_beat(x, bias, 0.0)) < 1e-12


def test_bias_states_starve_sidebands():
    w = np.asarray(cf.sideband_weights(1.0, 0.0, 5))  # θ_b = 0: odd orders vanish
    assert np.all(w[1::2] == 0) and np.all(w[0::2] > 0)
    w = np.asarray(cf.sideband_weights(1.0, np.pi / 2, 5))  # θ_b = π/2: even orders vanish
    assert np.all(np.abs(w[0::2]) < 1e-30) and np.all(w[1::2] > 0)
    # near the first zero of J1 (x ≈ 3.8317) the fundamental starves
    assert float(cf.sideband_weights(3.8317059702, np.pi / 4, 1)[1]) < 1e-18


def test_rolloff_reduces_index_by_design():
    mzm = cf.MZM(modulation_index=2.0, rolloff_3db_hz=8e9)
    x = np.asarray(mzm.x_at(jnp.array([0.0, 6e9])))
    assert x[0] == pytest.approx(1.0) and x[1] == pytest.approx(0.8)


def test_invalid_modulator_settings_are_rejected():
    with pytest.raises(ValueError, match="max_order"):
        cf.MZM(max_order=40)
    with pytest.raises(ValueError, match="modulation_index"):
        cf.MZM(modulation_index=-1.0)
