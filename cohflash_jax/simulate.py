"""Simulator: composes exactly the effects a scene calls for into four-CCD frames.

The simulator simulates the true instrument, `Instrument.truth(effects)`: the described
parts with the departures (`InstrumentErrors`) whose effects the scene lists. Stages, each
one pure function:
  scene → `build_returns` (per-pixel returns: delays and complex amplitudes; speckle,
  mixed pixels, misregistration, range falloff act here, on the host, once per capture)
  → `expected_port_electrons` (sweep, modulator with sidebands and its roll-off, carrier
  drift, motion, hybrid; jittable, differentiable in every instrument parameter)
  → `sensor_readout` (shot/dark/read noise, saturation, gain, offset, ADC).

Precision per stage (measured, see tests/test_forward.py): the tone phase 2π·f·τ reaches
~10⁴ rad at 6 GHz and 30 m and ~10⁵ rad at 30 GHz and 240 m, where float32 (ulp ≈ 4e-3
and 1.6e-2 rad) is useless; the cycle count f·τ is formed in float64 and reduced mod 1
before any trigonometry. Electrons and noise are float32 (counts ≤ 1e5, relative
rounding 6e-8, far below shot noise).
"""

from __future__ import annotations

import collections
from collections.abc import Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, PRNGKeyArray

from .constants import SPEED_OF_LIGHT_M_PER_S
from .effects import EffectSettings, parse_effects
from .instrument import Instrument
from .modulator import beat_spectrum
from .runtime import async_filter_jit, place_on_devices, quick_compile, stream_devices
from .scenes import Scene
from .tiling import QUICK_COMPILE_MAX_PIXELS

# Streams of the PRNG key, one per effect, so an effect's draws never shift another's.
_KEY_SPECKLE, _KEY_TURBULENCE, _KEY_FRAMES = 11, 12, 13
_KEY_SHOT, _KEY_DARK, _KEY_READ = 1, 2, 3


class Returns(eqx.Module):
    """Per-pixel returns. C = 1 (all CCDs see the same point) or 4 (misregistration)."""

    delay_s: Float[Array, "C R P"]
    amplitude: Complex[Array, "C R P"]  # √(echo electrons)·e^{iφ} of each return
    echo_e: Float[Array, "C P"]  # mean echo electrons per pixel (its intensity term)


def build_returns(scene: Scene, instrument: Instrument, height: int, width: int, effects, key: PRNGKeyArray) -> Returns:
    """Sample the scene into per-pixel returns (host side, once per capture); CCDs 2–4 sample
    it through the instrument's misregistration where `misregistration` is listed."""
    effects = parse_effects(effects)
    settings = scene.settings
    sensor, link = instrument.sensor, instrument.link
    s = settings.mixed_pixel_subsamples if "mixed_pixels" in effects else 1
    offsets = (np.arange(s) + 0.5) / s - 0.5
    oy, ox = [a.ravel() for a in np.meshgrid(offsets, offsets, indexing="ij")]
    y, x = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    cx, cy = width / 2, height / 2
    depth_c, rho_c = [], []
    for dx, dy, rot_deg in instrument.errors.ccd_transforms(effects):
        a = np.deg2rad(rot_deg)
        d_sub, r_sub = [], []
        for sx, sy in zip(ox, oy):
            xs, ys = x + sx - cx, y + sy - cy
            xr = cx + np.cos(a) * xs - np.sin(a) * ys + dx
            yr = cy + np.sin(a) * xs + np.cos(a) * ys + dy
            d, r = scene.sample(xr / width, yr / height)
            d_sub.append(d)
            r_sub.append(r)
        depth_c.append(np.stack(d_sub))
        rho_c.append(np.stack(r_sub))
    depth = np.stack(depth_c)  # (C, S, H, W)
    rho = np.stack(rho_c)
    power = link.echo_power_w(depth, rho, range_falloff="range_falloff" in effects)
    echo_sub = np.asarray(sensor.electrons(power), dtype=np.float64) / depth.shape[1]
    if np.any(~np.isfinite(echo_sub)) or np.any(echo_sub < 0):
        raise ValueError("echo electrons are negative or not finite: check powers and distances")
    C, S = depth.shape[:2]
    wavelength = float(sensor.wavelength_m)
    if "speckle" in effects:
        k = settings.speckle_scatterers
        if k < 1:
            raise ValueError("speckle_scatterers must be ≥ 1")
        gy, gx = np.gradient(depth, axis=(2, 3))
        slope_span = np.clip(np.abs(gx) + np.abs(gy), 0, 0.01)  # depth across one pixel, edges capped
        with quick_compile(height * width <= QUICK_COMPILE_MAX_PIXELS):
            draws = _speckle_draws(jax.random.fold_in(key, _KEY_SPECKLE), (C, S, k, height, width))
        roughness, across, gauss = (np.asarray(d) for d in draws)
        spread = float(settings.surface_roughness_m) * roughness + slope_span[:, :, None] * (across - 0.5)
        depth_r = depth[:, :, None] + spread
        speckle = (gauss[..., 0] + 1j * gauss[..., 1]) / np.sqrt(2 * k)  # E|Σ a|² = 1
        amp = np.sqrt(echo_sub)[:, :, None] * speckle
        depth_r = depth_r.reshape(C, S * k, height * width)
        amp = amp.reshape(C, S * k, height * width)
    else:
        depth_r = depth.reshape(C, S, height * width)
        cycles = np.mod(2.0 * depth_r / wavelength, 1.0)  # optical phase 4πd/λ, reduced in float64
        amp = np.sqrt(echo_sub.reshape(C, S, -1)) * np.exp(2j * np.pi * cycles)
    delay = 2.0 * depth_r / SPEED_OF_LIGHT_M_PER_S + float(instrument.system_delay_s)
    echo_e = echo_sub.sum(axis=1).reshape(C, height * width)
    return Returns(jnp.asarray(delay), jnp.asarray(amp), jnp.asarray(echo_e))


@async_filter_jit
def _speckle_draws(key: PRNGKeyArray, shape: tuple[int, ...]):
    """The speckle's random draws for scatterers of `shape` (C, S, k, H, W): each one's depth
    within the surface's roughness (standard normal) and across the pixel's slope (uniform), and
    its complex Gaussian amplitude (…, 2). One program, kept on disk: drawn op by op, each was a
    program of its own compiled in every process."""
    kd, kp, ka = jax.random.split(key, 3)
    return jax.random.normal(kd, shape), jax.random.uniform(kp, shape), jax.random.normal(ka, shape + (2,))


def turbulence_phase(key: PRNGKeyArray, num_frames: int, rad_per_sqrt_frame: float) -> Float[Array, " N"]:
    """Slow carrier-phase drift: a random walk over the frames, common to all pixels."""
    steps = rad_per_sqrt_frame * jax.random.normal(jax.random.fold_in(key, _KEY_TURBULENCE), (num_frames,))
    return jnp.cumsum(steps) - steps[0]


def expected_port_electrons(
    instrument: Instrument,
    settings: EffectSettings,
    returns: Returns,
    frequencies_hz: Float[Array, " F"],
    frame_index: Float[Array, " F"],
    carrier_phase_rad: Float[Array, " F"] | None,
    effects,
    beat_dtype=jnp.float64,
) -> Float[Array, "4 F P"]:
    """Mean electrons per port, frame and pixel of `instrument` as given (the simulator passes
    the true one, `Instrument.truth`; differentiable, jittable). The beat phase is reduced
    modulo 2π in float64 (it reaches ~10⁵ rad); `beat_dtype` is the precision of what follows
    it, per return and frame: the cosine, its harmonics and the sum over returns. The Fisher
    information keeps float64; the simulator uses float32, whose 1e-7 relative error is far
    below a frame's float32 rounding and its noise, at a fraction of the cost (a float64
    cosine costs ~10 ns on a CPU)."""
    mzm, sensor, link = instrument.modulator, instrument.sensor, instrument.link
    f = jnp.asarray(frequencies_hz, jnp.float64)
    extra_phase = jnp.zeros_like(f) if carrier_phase_rad is None else carrier_phase_rad
    extra_cycles = jnp.zeros_like(f)
    if "motion" in effects:
        t = frame_index / instrument.frame_rate_hz
        dd = settings.radial_velocity_m_per_s * t  # depth change (m)
        extra_cycles = f * (2 * dd / SPEED_OF_LIGHT_M_PER_S)
        extra_phase = extra_phase + 4 * jnp.pi * dd / sensor.wavelength_m
    order = mzm.max_order if "sidebands" in effects else min(mzm.max_order, 1)
    if mzm.flat:  # one set of weights for the whole sweep
        weights = jnp.asarray(mzm.weights(max_order=order)).astype(beat_dtype)
    else:  # the roll-off: weights per frequency, (1, F, 1, K) against ψ's (C, F, P)
        weights = jnp.asarray(mzm.weights(f, max_order=order)).astype(beat_dtype)[None, :, None, :]
    s0 = jnp.broadcast_to(mzm.mean_transmission(None if mzm.flat else f), f.shape)
    complex_dtype = jnp.result_type(beat_dtype, jnp.complex64)
    amplitude = returns.amplitude.astype(complex_dtype)

    def add_return(r, total):
        # one return's beat for every frame and pixel, (C, F, P): a loop over the returns keeps
        # each one's phase, cosine, harmonics and product in one fused pass, where a (C, F, R, P)
        # array contracted by `einsum` over R ran 3× slower on a CPU (docs/performance.md)
        cycles = f[None, :, None] * returns.delay_s[:, None, r] + extra_cycles[None, :, None]
        psi = 2 * jnp.pi * (cycles - jnp.floor(cycles))
        beat = beat_spectrum(psi.astype(beat_dtype), weights)
        return total + beat.astype(complex_dtype) * amplitude[:, None, r]

    c, num_returns, p = returns.delay_s.shape
    summed = jax.lax.fori_loop(0, num_returns, add_return, jnp.zeros((c, f.shape[0], p), complex_dtype))
    reference_e = sensor.electrons(link.reference_power_per_pixel_w)
    coherent = jnp.sqrt(reference_e) * summed.astype(jnp.complex128)
    coherent = coherent * jnp.exp(1j * extra_phase)[None, :, None]
    common = (reference_e + returns.echo_e[:, None, :]) * s0[None, :, None]
    if "background_light" in effects:
        common = common + sensor.electrons(settings.background_power_per_pixel_w)
    return instrument.hybrid.port_electrons(common, coherent)


def sensor_readout(key: PRNGKeyArray, electrons: Float[Array, "4 ..."], instrument: Instrument, effects) -> Array:
    """Noise, clipping, gain, offset and ADC → DN (uint16 with quantization, else float32),
    with the gains and offsets of `instrument.hybrid` (the simulator passes the true one).

    Gaussian-limit noises (shot in 'gaussian' mode, dark shot, read) are independent, so
    they are drawn as one normal with the summed variance (`Sensor.port_variance_e2`): one
    draw per sample, not three.
    """
    sensor = instrument.sensor
    e = electrons.astype(jnp.float32)
    gaussian = set(effects) & {"dark_current", "read_noise"}
    if "shot_noise" in effects:
        if sensor.shot_noise_model == "poisson":
            e = jax.random.poisson(jax.random.fold_in(key, _KEY_SHOT), jnp.maximum(e, 0)).astype(jnp.float32)
        else:
            gaussian.add("shot_noise")
    variance = sensor.port_variance_e2(e, gaussian, quantization=False)  # the mean, before dark is added
    if "dark_current" in effects:
        e = e + jnp.asarray(sensor.dark_electrons, jnp.float32)
    if gaussian:
        e = e + jnp.sqrt(variance) * jax.random.normal(jax.random.fold_in(key, _KEY_READ), e.shape, jnp.float32)
    if "saturation" in effects:
        e = jnp.clip(e, 0.0, sensor.full_well_e)
    hybrid = instrument.hybrid
    shape = (4,) + (1,) * (e.ndim - 1)
    gain = (jnp.asarray(hybrid.relative_gains, jnp.float32) * sensor.dn_per_electron).reshape(shape)
    offset = (sensor.adc_offset_dn + jnp.asarray(hybrid.offsets_dn, jnp.float32)).reshape(shape)
    dn = offset + gain * e
    if "quantization" in effects:
        return jnp.clip(jnp.round(dn), 0, sensor.adc_max_dn).astype(jnp.uint16)
    if "saturation" in effects:
        dn = jnp.clip(dn, 0, sensor.adc_max_dn)
    return dn.astype(jnp.float32)


# captures of at most this many pixel-frames are simulated by programs compiled for a short
# compile (`runtime.quick_compile`; `iter_frame_chunks`)
QUICK_SIMULATION_MAX_SAMPLES = 2**18


@async_filter_jit  # returns at once: the next chunk computes while the caller writes this one
def _frames_chunk(
    instrument,
    settings,
    returns,
    frequencies_padded,
    carrier_padded,
    frame_start,
    key,
    *,
    num_frames: int,
    effects: tuple[str, ...],
):
    f = jax.lax.dynamic_slice(frequencies_padded, (frame_start,), (num_frames,))
    idx = (frame_start + jnp.arange(num_frames)).astype(jnp.float64)
    carrier = None if carrier_padded is None else jax.lax.dynamic_slice(carrier_padded, (frame_start,), (num_frames,))
    electrons = expected_port_electrons(instrument, settings, returns, f, idx, carrier, effects, jnp.float32)
    return sensor_readout(jax.random.fold_in(key, frame_start), electrons, instrument, effects)


def frame_chunk_size(returns: Returns, num_frames: int, budget_elements: int = 6_000_000) -> int:
    """Frames per chunk so that one chunk's float64 intermediates stay ~100 MB."""
    c, r, p = returns.delay_s.shape
    size = max(4, min(64, budget_elements // max(1, c * r * p)))
    size = 1 << (size.bit_length() - 1)  # power of two
    return int(min(size, num_frames))


def iter_frame_chunks(
    scene: Scene,
    instrument: Instrument,
    height: int,
    width: int,
    key: PRNGKeyArray,
    effects=None,
    chunk_frames: int | None = None,
    returns: Returns | None = None,
) -> Iterator[tuple[int, int, np.ndarray]]:
    """Yield (m0, m1, frames[4, m1−m0, H, W]) over the sweep, one chunk at a time, of the true
    instrument (`Instrument.truth`). `returns`: the scene's returns where the caller already
    sampled them (`build_returns` with the same key).

    The next chunk is dispatched before the current one is handed out, so simulation
    overlaps with whatever the caller does with the chunk (e.g. writing it)."""
    effects = scene.effects if effects is None else parse_effects(effects)
    if height < 1 or width < 1:
        raise ValueError(f"image size must be positive, got {height}×{width}")
    if returns is None:
        returns = build_returns(scene, instrument, height, width, effects, key)
    true = instrument.truth(effects)
    n = instrument.sweep.num_steps
    chunk = chunk_frames or frame_chunk_size(returns, n)
    padded = -(-n // chunk) * chunk
    freqs = np.pad(instrument.sweep.frequencies_hz, (0, padded - n), mode="edge")
    carrier = None
    if "turbulence" in effects:
        carrier = jnp.pad(
            turbulence_phase(key, n, scene.settings.turbulence_rad_per_sqrt_frame), (0, padded - n), mode="edge"
        )
    frames_key = jax.random.fold_in(key, _KEY_FRAMES)
    # chunks in turn on each stream device (`simulate` asks for two, `runtime.COMMAND_CPU_STREAMS`): one
    # chunk's program leaves a core idle; the chunks are the same on any device
    devices = stream_devices()
    placed = place_on_devices((true, scene.settings, returns, jnp.asarray(freqs), carrier, frames_key), devices)
    # a small capture (a test's, a region of interest): compiling its chunk program is most of
    # its time; a larger one runs slower so than it saves (docs/performance.md)
    quick = height * width * n <= QUICK_SIMULATION_MAX_SAMPLES

    def launch(m0):
        k = m0 // chunk
        inst, settings, ret, f, carrier_on, key_on = placed[k % len(placed)]
        start = jax.device_put(jnp.asarray(m0), devices[k % len(devices)])
        with quick_compile(quick):
            return _frames_chunk(inst, settings, ret, f, carrier_on, start, key_on, num_frames=chunk, effects=effects)

    starts = list(range(0, n, chunk))
    pending = collections.deque(launch(m0) for m0 in starts[: len(devices)])
    for i, m0 in enumerate(starts):
        current = pending.popleft()
        if i + len(devices) < len(starts):  # one chunk ahead on every device
            pending.append(launch(starts[i + len(devices)]))
        m1 = min(n, m0 + chunk)
        yield m0, m1, np.asarray(current)[:, : m1 - m0].reshape(4, m1 - m0, height, width)


def simulate(
    scene: Scene, instrument: Instrument, height: int, width: int, key: PRNGKeyArray, effects=None
) -> np.ndarray:
    """All frames (4, N, H, W) in memory — for small captures and tests."""
    chunks = [c for _, _, c in iter_frame_chunks(scene, instrument, height, width, key, effects)]
    return np.concatenate(chunks, axis=1)


def simulation_truth(scene: Scene, instrument: Instrument, height: int, width: int, effects) -> dict:
    """Ground truth and the true settings a simulated capture was made with (for `truth/`)."""
    effects = parse_effects(effects)
    depth, rho = scene.render(height, width)
    true = instrument.truth(effects)
    hybrid = true.hybrid
    s = scene.settings
    return {
        "depth_m": depth.astype(np.float32),
        "reflectance": rho.astype(np.float32),
        "attrs": {
            "scene": scene.name,
            "effects": ",".join(effects),
            "system_delay_s": float(instrument.system_delay_s),
            "hybrid_phases_rad": np.asarray(hybrid.phases_rad, np.float64),
            "hybrid_relative_gains": np.asarray(hybrid.relative_gains, np.float64),
            "hybrid_offsets_dn": np.asarray(hybrid.offsets_dn, np.float64) + float(instrument.sensor.adc_offset_dn),
            "dn_per_electron": float(instrument.sensor.dn_per_electron),
            "beta_rolloff_3db_hz": float(true.modulator.rolloff_3db_hz),
            "misregistration_px_px_deg": np.asarray(instrument.errors.ccd_transforms(effects)[1:] or np.zeros((0, 3))),
            "turbulence_rad_per_sqrt_frame": float(s.turbulence_rad_per_sqrt_frame) if "turbulence" in effects else 0.0,
            "radial_velocity_m_per_s": float(s.radial_velocity_m_per_s) if "motion" in effects else 0.0,
        },
    }


def simulate_to_file(
    path,
    scene: Scene,
    instrument: Instrument,
    height: int,
    width: int,
    seed: int = 0,
    effects=None,
    progress: bool = True,
):
    """Simulate a capture and write it as format v1 (atomically, in frame chunks): the frames
    of the true instrument, the header of the described one (`capture.capture_attributes`),
    the truth under `truth/`."""
    from .capture import capture_attributes, write_capture
    from .runtime import retain_freed_memory

    # each chunk's ~20 MB intermediates are reused from the heap instead of mapped afresh (page
    # faults were most of the kernel time: docs/performance.md)
    retain_freed_memory()
    effects = scene.effects if effects is None else parse_effects(effects)
    key = jax.random.key(seed)
    returns = build_returns(scene, instrument, height, width, effects, key)
    chunk = frame_chunk_size(returns, instrument.sweep.num_steps)
    dtype = np.uint16 if "quantization" in effects else np.float32
    chunks = iter_frame_chunks(scene, instrument, height, width, key, effects, chunk_frames=chunk, returns=returns)
    return write_capture(
        path,
        chunks,
        frequencies_hz=instrument.sweep.frequencies_hz,
        height=height,
        width=width,
        dtype=dtype,
        attrs={**capture_attributes(instrument), "simulated": True},
        hybrid_phases_rad=np.asarray(instrument.hybrid.phases_rad),
        truth=simulation_truth(scene, instrument, height, width, effects),
        frames_per_chunk=chunk,
        progress=progress,
    )
