"""Forward model and simulator against independent truth."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
from cohflash_jax.simulate import build_returns, expected_port_electrons, sensor_readout

from .conftest import depth_scene


def _iq(frames):
    f = np.asarray(frames, np.float64)
    return f[0] - f[2], f[3] - f[1]


def _peak_cycles_per_frame(z, pad=16):
    z = z - z.mean(axis=0)
    n = z.shape[0]
    spec = np.abs(np.fft.fft(z, n * pad, axis=0))
    k = np.argmax(spec[: n * pad // 2], axis=0)
    return k / (n * pad)


def test_noiseless_pixel_tone_is_at_delta_f_tau(paper_instrument, simulate_pixels):
    depths = np.linspace(3.0, 37.0, 64)
    frames = simulate_pixels(depth_scene(depths))
    i, q = _iq(frames.reshape(4, frames.shape[1], -1))
    got = _peak_cycles_per_frame(i + 1j * q)
    expect = paper_instrument.sweep.step_hz * 2 * depths / C
    assert np.max(np.abs(got - expect)) < 1 / (16 * frames.shape[1])


def test_second_harmonic_aliases_as_in_the_paper(paper_instrument):
    """56.2 Hz fundamental at 150 frames/s → 2nd harmonic at 112.4 Hz aliases to 150 − 112.4
    = 37.6 Hz. (The paper reports 37.4 Hz: consistent with a true frame rate of 149.8 Hz,
    or rounding; 150 Hz exactly gives 37.6 Hz.)"""
    fs, f_fund = 150.0, 56.2
    tau = f_fund / fs / paper_instrument.sweep.step_hz
    depth = C * tau / 2
    spectra = {}
    for effects in (("sidebands",), ()):
        frames = cf.simulate(
            cf.from_arrays(np.full((1, 1), depth), effects=effects), paper_instrument, 1, 1, jax.random.key(0)
        )
        i, q = _iq(frames[:, :, 0, 0])
        r = np.real((i + 1j * q) * np.exp(-1j * np.angle(np.sum((i + 1j * q) ** 2)) / 2))
        spectra[effects] = np.abs(np.fft.rfft(r - r.mean()))
    hz = np.fft.rfftfreq(frames.shape[1], 1 / fs)
    spec = spectra[("sidebands",)]
    fund = hz[np.argmax(spec)]
    away = np.abs(hz - fund) > 1.0
    second = hz[away][np.argmax(spec[away])]
    assert abs(fund - 56.2) <= 0.05 and abs(second - 37.6) <= 0.05
    ratio = spec[np.argmin(np.abs(hz - 37.6))] / spec.max()
    w = np.asarray(paper_instrument.modulator.weights())
    assert ratio == pytest.approx(w[2] / w[1], rel=0.05)  # harmonic strength = w2/w1
    # without the sidebands effect there is no harmonic at all
    off = spectra[()]
    assert off[np.argmin(np.abs(hz - 37.6))] / off.max() < 1e-3


@pytest.mark.parametrize("model,mean_e", [("gaussian", 2000.0), ("poisson", 3.0), ("poisson", 2000.0)])
def test_shot_noise_mean_and_variance_in_electrons(paper_instrument, model, mean_e):
    inst = eqx.tree_at(
        lambda i: i.sensor, paper_instrument, cf.Sensor(dn_per_electron=1.0, adc_offset_dn=0.0, shot_noise_model=model)
    )
    e = jnp.full((4, 250_000), mean_e)
    dn = np.asarray(sensor_readout(jax.random.key(3), e, inst, ("shot_noise",)), np.float64)
    n = dn.size
    assert dn.mean() == pytest.approx(mean_e, abs=4 * np.sqrt(mean_e / n))
    assert dn.var() == pytest.approx(mean_e, rel=4 * np.sqrt(2 / n))
    if model == "poisson":
        assert np.all(dn == np.round(dn))


def test_read_and_dark_noise_add_their_variances(paper_instrument):
    inst = eqx.tree_at(lambda i: i.sensor, paper_instrument, cf.Sensor(dn_per_electron=1.0, adc_offset_dn=0.0))
    s = inst.sensor
    dn = np.asarray(
        sensor_readout(
            jax.random.key(4), jnp.full((4, 250_000), 500.0), inst, ("dark_current", "read_noise", "shot_noise")
        ),
        np.float64,
    )
    dark = float(s.dark_electrons)
    assert dn.mean() == pytest.approx(500 + dark, abs=0.5)
    assert dn.var() == pytest.approx(500 + dark + float(s.read_noise_e) ** 2, rel=0.01)


def _ports(instrument, scene, effects, frames=64):
    returns = build_returns(scene, instrument, 8, 8, effects, jax.random.key(0))
    f = jnp.asarray(instrument.sweep.frequencies_hz[:frames])
    return expected_port_electrons(
        instrument.truth(effects), scene.settings, returns, f, jnp.arange(frames, dtype=float), None, effects
    )


def test_common_mode_cancels_in_iq(paper_instrument):
    scene = depth_scene(np.linspace(10, 30, 64))
    base = np.asarray(_ports(paper_instrument, scene, ()))
    bright = np.asarray(_ports(paper_instrument, scene, ("background_light",)))
    assert np.min(bright - base) > 1.0  # background raises every port
    for a, b in zip(_iq(base), _iq(bright)):
        np.testing.assert_allclose(a, b, atol=1e-9 * np.abs(base).max())


def test_hybrid_errors_are_undone_by_the_matching_iq_matrix(paper_instrument):
    scene = depth_scene(np.linspace(10, 30, 64))
    ideal_i, ideal_q = _iq(np.asarray(_ports(paper_instrument, scene, ())))
    ports = np.asarray(_ports(paper_instrument, scene, ("hybrid_errors",)))
    true = paper_instrument.truth(("hybrid_errors",)).hybrid
    dn = ports * np.asarray(true.relative_gains)[:, None, None] + np.asarray(true.offsets_dn)[:, None, None]
    w, b = true.iq_matrix_dn(1.0)
    i = np.einsum("k,knp->np", np.asarray(w[0]), dn) + float(b[0])
    q = np.einsum("k,knp->np", np.asarray(w[1]), dn) + float(b[1])
    scale = np.abs(ideal_i).max()
    np.testing.assert_allclose(i, ideal_i, atol=1e-9 * scale)
    np.testing.assert_allclose(q, ideal_q, atol=1e-9 * scale)
    # the nominal combination would not: the errors are real
    assert np.max(np.abs(_iq(dn)[0] - ideal_i)) > 0.01 * scale


def _electron_gradients(instrument, returns, effects):
    def loss(params):
        inst, ret = params
        e = expected_port_electrons(
            inst.truth(effects), cf.EffectSettings(), ret, inst.sweep.as_array()[:32], jnp.arange(32.0), None, effects
        )
        return jnp.sum((e[0] - e[2]) ** 2 + (e[3] - e[1]) ** 2)

    # one compiled program a case, not hundreds of operations compiled one by one
    return eqx.filter_jit(eqx.filter_grad(loss))((cf.differentiable(instrument), returns))


@pytest.mark.parametrize("case", ["zero_echo", "index_to_zero", "high_order"])
def test_gradients_are_finite_at_hard_points(paper_instrument, case):
    inst = paper_instrument
    reflectance = 0.5
    if case == "zero_echo":
        reflectance = 0.0
    if case == "index_to_zero":
        inst = eqx.tree_at(lambda i: i.modulator, inst, cf.MZM(modulation_index=0.0))
    if case == "high_order":
        inst = eqx.tree_at(lambda i: i.modulator, inst, cf.MZM(modulation_index=6.0, max_order=24))
    effects = ("sidebands", "beta_rolloff", "background_light", "range_falloff")
    scene = depth_scene(np.linspace(0.01, 30.0, 64), reflectance=reflectance)
    returns = build_returns(scene, inst, 8, 8, effects, jax.random.key(0))
    grads = _electron_gradients(inst, returns, effects)
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(grads) if eqx.is_inexact_array_like(x)]
    assert len(leaves) >= 20 and all(np.all(np.isfinite(x)) for x in leaves)
    assert np.any(np.asarray(grads[1].delay_s) != 0) or case == "zero_echo"  # depth is differentiable too
    # the gradient with respect to the modulation index is non-zero unless x = 0 exactly
    g_beta = float(grads[0].modulator.modulation_index)
    assert np.isfinite(g_beta)


def test_effect_left_out_costs_nothing(paper_instrument):
    """Effects not asked for are not computed: no random number generation in the traced
    program, no key consumed for speckle, and fewer sideband orders without `sidebands`."""
    e = jnp.ones((4, 16, 8))
    settings = cf.EffectSettings()
    quiet = str(jax.make_jaxpr(lambda k: sensor_readout(k, e, paper_instrument, ()))(jax.random.key(0)))
    noisy = str(jax.make_jaxpr(lambda k: sensor_readout(k, e, paper_instrument, ("shot_noise",)))(jax.random.key(0)))
    for marker in ("random_bits", "threefry", "random_wrap"):
        assert marker not in quiet
    assert any(m in noisy for m in ("random_bits", "threefry"))
    # build_returns without speckle never touches the key (None would fail if it did)
    build_returns(depth_scene([10.0]), paper_instrument, 8, 8, ("mixed_pixels",), key=None)
    returns = build_returns(depth_scene([10.0]), paper_instrument, 8, 8, (), None)
    f = jnp.asarray(paper_instrument.sweep.frequencies_hz[:16])

    def program(effects):
        return str(
            jax.make_jaxpr(
                lambda r: expected_port_electrons(paper_instrument, settings, r, f, jnp.arange(16.0), None, effects)
            )(returns)
        )

    assert len(program(())) < len(program(("sidebands",)))


def test_tone_phase_needs_float64_cycles_then_float32_is_enough():
    """At 30 GHz and 240 m the tone phase is ~3e5 rad: naive float32 is off by ~1e-2 rad;
    forming f·τ in float64 and reducing mod 1 first (as the simulator does) keeps float32
    trigonometry within 1e-6 rad."""
    f = np.linspace(24e9, 30e9, 1001)
    tau = 2 * 240.0 / C
    exact = np.mod(f * tau, 1.0)  # cycles, float64
    naive = np.asarray(jnp.asarray(f, jnp.float32) * jnp.float32(tau), np.float64)
    naive_err = np.abs(np.angle(np.exp(2j * np.pi * (naive - exact))))
    assert naive_err.max() > 1e-3
    cycles = np.asarray(jnp.asarray(f, jnp.float64) * tau)
    reduced = jnp.asarray(cycles - np.floor(cycles), jnp.float32)
    err32 = np.abs(np.asarray(jnp.cos(2 * jnp.pi * reduced), np.float64) - np.cos(2 * np.pi * exact))
    assert err32.max() < 2e-6


def test_float32_electrons_stage_agrees_with_float64(paper_instrument):
    scene = depth_scene(np.linspace(5, 35, 64))
    e64 = np.asarray(_ports(paper_instrument, scene, ("sidebands",)))
    e32 = np.asarray(jnp.asarray(e64, jnp.float32), np.float64)
    assert np.max(np.abs(e32 - e64) / np.abs(e64)) < 1e-7  # float32 storage of electrons: 6e-8 relative
    i64, _ = _iq(e64)
    i32, _ = _iq(e32)
    assert np.max(np.abs(i32 - i64)) < 1e-3 * np.std(i64)


def test_default_link_budget_reproduces_the_paper():
    link = cf.LinkBudget()
    p = float(link.echo_power_w(30.5, 0.5))
    assert p == pytest.approx(0.26e-15, rel=1e-9)
    assert float(link.echo_power_w(61.0, 0.5)) == pytest.approx(p / 4)
    assert float(link.echo_power_w(61.0, 0.5, range_falloff=False)) == pytest.approx(p)
    s = cf.Sensor()
    assert float(s.photon_energy_j) == pytest.approx(6.62607015e-34 * C / 1550e-9)
    assert float(s.electrons(0.64e-12)) == pytest.approx(0.8 * 0.64e-12 * 4e-3 / float(s.photon_energy_j))


def test_speckle_conserves_mean_power_and_is_rayleigh(paper_instrument):
    scene = cf.planar(effects=("speckle",))
    r = build_returns(scene, paper_instrument, 64, 64, ("speckle",), jax.random.key(7))
    field = np.abs(np.asarray(r.amplitude).sum(axis=1)) ** 2 / np.asarray(r.echo_e)
    assert field.mean() == pytest.approx(1.0, abs=0.05)
    assert field.std() == pytest.approx(1.0, abs=0.1)  # exponential intensity: std = mean (K=4: close)


def test_misregistration_gives_each_ccd_its_own_view(paper_instrument):
    scene = cf.staircase(effects=("misregistration",))
    r = build_returns(scene, paper_instrument, 32, 32, ("misregistration",), jax.random.key(0))
    assert r.delay_s.shape[0] == 4
    d = np.asarray(r.delay_s)[:, 0]
    assert np.array_equal(d[0], build_returns(scene, paper_instrument, 32, 32, (), None).delay_s[0, 0])
    assert all(np.any(d[k] != d[0]) for k in (1, 2, 3))


def test_turbulence_is_a_random_walk_of_the_stated_size():
    from cohflash_jax.simulate import turbulence_phase

    phi = np.asarray(turbulence_phase(jax.random.key(1), 20000, 0.05))
    assert np.std(np.diff(phi)) == pytest.approx(0.05, rel=0.03)


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: cf.from_arrays(np.full((4, 4), -1.0)), "depth"),
        (lambda: cf.from_arrays(np.ones((4, 4)), np.full((4, 4), 2.0)), "reflectance"),
        (lambda: cf.from_arrays(np.ones(4)), "2-D"),
        (lambda: cf.LinkBudget(probe_power_w=-1.0), "negative"),
        (lambda: cf.Sensor(read_noise_e=-3.0), "read_noise"),
        (lambda: cf.FrequencySweep.uniform(1e8, 2e6, 1), "at least 2"),
        (lambda: cf.FrequencySweep([1e9, 2e9, 2e9]), "increasing"),
        (lambda: cf.FrequencySweep([1e9, np.nan]), "NaN"),
        (lambda: cf.parse_effects("shot_noise,fog"), "known effects: sidebands"),
        (lambda: cf.get_scene("moon"), "built-in scenes"),
        (lambda: cf.Hybrid(phases_rad=(0.0, 1.0)), "shape"),
    ],
)
def test_bad_input_gives_a_clear_error(make, match):
    with pytest.raises(ValueError, match=match):
        make()
