"""The coarse stage, shared by every estimator: where each pixel's tone is, to a grid point.

Uniform sweeps (`UniformSpectrum`): the Hann-windowed DFT over the frame index, its peak and a
Gaussian interpolation. Non-uniform schedules (`DelayPeriodogram`): there is no "frequency
over the frame index" when f_m is not f_0 + mΔf, so the stage is a periodogram over delay,
|Σ_m (r[m] − r̄)·e^{−i2π f_m τ}|², on a depth grid (one matrix product per tile). Its
magnitude is smooth on the envelope scale c/(2B) (the tone's phase ripple cancels in |·|), so
the grid needs ~4 points per c/(2B).

float32: a 3000-point FFT of float32 data has relative error ~1e-6 of the peak, far below
noise at any SNR where a peak can be found; the position is then refined in float64 by the
ML estimators.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Complex, Float, Int

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..fisher import crlb_frequency_only_m, frequency_only_sigma_m
from ..geometry import POINTS_PER_ENVELOPE, SweepGeometry
from ..runtime import MATMUL_PRECISION, device_value
from .detection import Detection, delay_detection, uniform_detection, uniform_sums


def unitary_rfft(seq: Float[Array, "N P"]) -> Complex[Array, "P K"]:
    """Unitary rFFT over the frame index (white noise stays white): (N, P) → (P, N//2 + 1).
    The 1/√N is applied in the transpose that precedes the FFT (it fuses there), not in a
    pass of its own over the complex spectrum."""
    n = seq.shape[0]
    return jnp.fft.rfft(seq.T * (1 / math.sqrt(n)), axis=-1)


def hann_power(spec: Complex[Array, "P K"], n: int, axis: int = -1) -> Float[Array, "P K"]:
    """Power spectrum of the mean-removed, periodic-Hann-windowed sequence, from the
    unwindowed rFFT bins (along `axis`).

    The periodic Hann window ½ − ½cos(2πm/N) is a 3-tap convolution in frequency,
    H[k] = ½X[k] − ¼(X[k−1] + X[k+1]), evaluated from shifted slices (no concatenation of
    the complex spectrum). Bin 0 (the mean) is set to zero; bins beyond the rFFT's ends
    use X[−k] = conj(X[k])."""
    k = spec.shape[axis]
    at = lambda start, stop: jax.lax.slice_in_dim(spec, start, stop, axis=axis)
    first_bin = tuple(0 if d == axis % spec.ndim else slice(None) for d in range(spec.ndim))
    x1 = at(1, 2)
    interior = 0.5 * at(1, k - 1) - 0.25 * (at(0, k - 2).at[first_bin].set(0) + at(2, k))
    mirror = at(k - 2, k - 1) if n % 2 == 0 else at(k - 1, k)
    last = 0.5 * at(k - 1, k) - 0.25 * (at(k - 2, k - 1) + jnp.conj(mirror))
    first = -0.25 * (x1 + jnp.conj(x1))  # mean removed: X[0] = 0
    sq = lambda z: jnp.real(z) ** 2 + jnp.imag(z) ** 2
    return jnp.concatenate([sq(first), sq(interior), sq(last)], axis=axis)


# Sweeps of at most this many frames take their spectrum as one matrix product with the DFT
# matrix, frames by pixels, and keep the bins on the first axis until the peak is found: an
# rFFT of a few dozen points along the pixels' last axis, and the window and peak search over
# ~18 bins there, vectorise poorly on a CPU (docs/performance.md).
DFT_MATRIX_MAX_FRAMES = 64


def unitary_dft_matrix(n: int) -> np.ndarray:
    """The unitary real DFT of n points as a (2·(n//2 + 1), n) matrix: the rFFT bins' real
    parts, then their imaginary parts (angles reduced modulo n exactly, in integers)."""
    angle = 2 * np.pi * ((np.arange(n // 2 + 1)[:, None] * np.arange(n)[None, :]) % n) / n
    return np.concatenate([np.cos(angle), -np.sin(angle)]) / math.sqrt(n)


def first_argmax(x: Float[Array, "P K"], axis: int = -1) -> Int[Array, " P"]:
    """`jnp.argmax` along `axis` (first index of the maximum) as two vectorised reductions, a
    max and a min over indices: XLA's CPU argmax is a variadic reduce that does not vectorise
    (docs/performance.md). A NaN row gives index 0."""
    k = x.shape[axis]
    top = jnp.max(x, axis=axis, keepdims=True)
    index = jnp.expand_dims(jnp.arange(k, dtype=jnp.int32), tuple(range(1, x.ndim - (axis % x.ndim))))
    first = jnp.min(jnp.where(x == top, index, k), axis=axis)
    return jnp.where(first < k, first, 0)


def coarse_peak(power: Float[Array, "P K"], min_bin: int = 1, axis: int = -1) -> Int[Array, " P"]:
    """Index of the strongest bin at or above `min_bin` (DC leakage lies below), bins along `axis`."""
    searched = jax.lax.slice_in_dim(power, min_bin, power.shape[axis], axis=axis)
    return first_argmax(searched, axis=axis) + min_bin


def interpolate_peak(power: Float[Array, "P K"], peak: Int[Array, " P"], axis: int = -1) -> Float[Array, " P"]:
    """Sub-bin peak position by a parabola through the log power of the peak and its
    neighbours (Gaussian interpolation; bias < 2 % of a bin for a Hann window); bins along `axis`."""
    tiny = jnp.finfo(power.dtype).tiny
    return peak + parabolic_offset(power, peak, lambda v: jnp.log(jnp.maximum(v, tiny)), axis)


def at_grid_point(values: Array, index: Int[Array, " P"], axis: int = -1) -> Array:
    """Each pixel's value of `values` (P, K) or (K, P) at its own grid point `index` (a bin, a
    window point: along `axis`, the pixels along the other)."""
    return jnp.squeeze(jnp.take_along_axis(values, jnp.expand_dims(index, axis), axis=axis), axis)


def parabolic_offset(power: Float[Array, "P K"], peak: Int[Array, " P"], transform=lambda v: v, axis: int = -1):
    """Sub-grid offset in [−½, ½] of a peak by a parabola through `transform`(power) at the peak
    and its neighbours; 0 where the peak is on an edge or the parabola does not open downwards."""
    k = power.shape[axis]
    take = lambda idx: transform(at_grid_point(power, jnp.clip(idx, 0, k - 1), axis))
    a, b, c = take(peak - 1), take(peak), take(peak + 1)
    den = a - 2 * b + c
    interior = (den < 0) & (peak > 0) & (peak < k - 1)
    return jnp.clip(jnp.where(interior, 0.5 * (a - c) / jnp.where(interior, den, -1.0), 0.0), -0.5, 0.5)


class CoarseSpectrum(eqx.Module):
    """The coarse stage's result for a batch of pixels: power over its grid (DFT bins, or
    depths of a periodogram), the strongest searched grid point, and — uniform sweeps — the
    unitary rFFT bins themselves (the window ML fits them)."""

    power: Float[Array, "P K"]
    peak: Int[Array, " P"]
    spectrum: Complex[Array, "P K"] | None = None


class AbstractCoarseStage(eqx.Module):
    """Where each pixel's tone is, and what its peak says: depth (at the peak, or
    interpolated), the tone's amplitude A and the frequency-only bound σ."""

    geometry: eqx.AbstractVar[SweepGeometry]
    weights: eqx.AbstractVar[Float[Array, " K"]]  # sideband weights (the dominant one scales A)
    detection: eqx.AbstractVar[Detection]  # the test of its ordinates against noise

    @abc.abstractmethod
    def __call__(self, sequence: Float[Array, "N P"]) -> CoarseSpectrum:
        """The spectrum of carrier-aligned sequences (N, P) and its peaks."""

    @abc.abstractmethod
    def detection_energy(self, coarse: CoarseSpectrum) -> Float[Array, "P G"]:
        """The energies the detection test bounds, one per ordinate (`estimate.detection`)."""

    @abc.abstractmethod
    def depth(self, coarse: CoarseSpectrum, interpolate: bool) -> Float[Array, " P"]:
        """Depth (m) at the peak grid point, or between grid points (`interpolate`)."""

    @abc.abstractmethod
    def tone_amplitude(self, coarse: CoarseSpectrum) -> Float[Array, " P"]:
        """The tone amplitude A (DN of I/Q) from the peak's power."""

    @abc.abstractmethod
    def frequency_only_sigma(self, amplitude, noise_var) -> Float[Array, " P"]:
        """The frequency-only CRLB (m) at amplitude A and the measured noise."""

    @property
    @abc.abstractmethod
    def grid_step_m(self):
        """Depth between grid points: a depth read off the grid is uniform within ±½ of it."""

    def rival_exclusion_points(self) -> int:
        """Grid points either side of a peak that belong to its tone (main lobe and first
        sidelobes): a rival peak lies beyond them."""
        return RIVAL_EXCLUSION_POINTS

    def candidates(self, coarse: CoarseSpectrum, count: int) -> Float[Array, "K P"]:
        """Depths (m) of the peak and the next `count` − 1 strongest grid points, each beyond
        `rival_exclusion_points` of those before it: the rivals a schedule's sidelobes offer
        (the time-domain ML fits each, `TimeDomainML`)."""
        g = jnp.arange(coarse.power.shape[-1])
        power, peak, depths = coarse.power, coarse.peak, []
        exclusion = self.rival_exclusion_points()
        for _ in range(count):
            depths.append(self.depth(CoarseSpectrum(power, peak), interpolate=True))
            power = jnp.where(jnp.abs(g[None, :] - peak[:, None]) <= exclusion, -1.0, power)
            peak = first_argmax(power)
        return jnp.stack(depths)

    @property
    @abc.abstractmethod
    def description(self) -> str:
        """The stage in words (recorded in the depth file's `frequency_path`)."""

    def dc_edge(self, coarse: CoarseSpectrum) -> Bool[Array, " P"]:
        """Pixels whose peak is the tail of a spectrum rising towards DC (none by default)."""
        return jnp.zeros(coarse.peak.shape, bool)

    @property
    def dominant_weight(self):
        return self.weights[self.geometry.dominant_order]


class UniformSpectrum(AbstractCoarseStage):
    """Unwindowed unitary rFFT over the frame index; its periodic-Hann power (a 3-tap
    convolution of the same bins) gives the peak, searched from `min_bin` up (DC leakage and
    slow drift live below)."""

    geometry: SweepGeometry
    weights: Float[Array, " K"]
    detection: Detection
    min_bin: int = eqx.field(static=True, default=1)

    def rival_exclusion_points(self) -> int:
        return UNIFORM_RIVAL_EXCLUSION_BINS

    @classmethod
    def of(cls, geometry: SweepGeometry, weights, min_bin: int, false_alarm: float) -> UniformSpectrum:
        """The stage of a uniform sweep, its detection test over the bins it searches."""
        detection = uniform_detection(geometry.num_frames, min_bin, false_alarm)
        return cls(geometry, device_value(weights), detection, min_bin)

    def detection_energy(self, coarse):
        n = self.geometry.num_frames
        if self.bins_first:  # summed where the spectrum's bins came first
            return uniform_sums(coarse.spectrum.T, n, axis=0).T
        return uniform_sums(coarse.spectrum, n)

    def __call__(self, sequence) -> CoarseSpectrum:
        n = sequence.shape[0]
        if not self.bins_first:
            spec = unitary_rfft(sequence)  # (P, K)
            power = hann_power(spec, n)
            return CoarseSpectrum(power, coarse_peak(power, self.min_bin), spec)
        k = n // 2 + 1
        # at the programs' full float32 precision wherever it is called from (a GPU's default is
        # TF32: its ~5e-4 relative error reaches the window fit)
        dft = jnp.asarray(unitary_dft_matrix(n), sequence.dtype)
        parts = jnp.matmul(dft, sequence, precision=MATMUL_PRECISION)  # (2K, P)
        spec = jax.lax.complex(parts[:k], parts[k:])  # (K, P)
        power = hann_power(spec, n, axis=0)
        return CoarseSpectrum(power.T, coarse_peak(power, self.min_bin, axis=0), spec.T)

    @property
    def bins_first(self) -> bool:
        """Whether `__call__` computes the spectrum with its bins on the first axis (a DFT-matrix
        product, `DFT_MATRIX_MAX_FRAMES`), before returning it pixels-first."""
        return self.geometry.num_frames <= DFT_MATRIX_MAX_FRAMES

    def power_as_computed(self, coarse) -> tuple[Float[Array, "..."], int]:
        """The power and its bins' axis as `__call__` computed it: bins first for short sweeps
        (the DFT matrix's), where read so XLA need not transpose it back."""
        if self.bins_first:
            return coarse.power.T, 0
        return coarse.power, -1

    def depth(self, coarse, interpolate):
        n = self.geometry.num_frames
        frac = interpolate_peak(*self._power_with_peak(coarse)) if interpolate else coarse.peak
        return self.geometry.depth_from_folded(frac.astype(jnp.float64) / n)

    def _power_with_peak(self, coarse):
        power, axis = self.power_as_computed(coarse)
        return power, coarse.peak, axis

    def tone_amplitude(self, coarse):
        # |H| = a·w·√N/4 at the Hann peak for a tone a·2w·cos (Hann gain ½)
        peak_power = at_grid_point(*self._power_with_peak(coarse))
        return (
            2 * jnp.sqrt(peak_power).astype(jnp.float64) / (math.sqrt(self.geometry.num_frames) * self.dominant_weight)
        )

    def frequency_only_sigma(self, amplitude, noise_var):
        g = self.geometry
        return crlb_frequency_only_m(
            g.num_frames, g.step_hz, amplitude * 2 * self.dominant_weight, jnp.sqrt(noise_var), g.dominant_order
        )

    @property
    def grid_step_m(self):
        return self.geometry.bin_depth_m

    @property
    def description(self) -> str:
        return "uniform sweep: rFFT over the frame index"

    def dc_edge(self, coarse):
        """A peak on the first searched bin with more power just below it: the tail of a
        spectrum rising towards DC. Slow drift looks exactly so (at 35 frames a quadratic drift
        and no echo gave 16 of 64 pixels "valid" at one bin, χ² < 5, all with this signature),
        and so does an untracked turbulent carrier, whose mean term wanders."""
        power, axis = self.power_as_computed(coarse)
        at = lambda k: jax.lax.index_in_dim(power, k, axis=axis, keepdims=False)
        return (coarse.peak == self.min_bin) & (at(self.min_bin - 1) > at(self.min_bin))


RIVAL_EXCLUSION_POINTS = 2 * POINTS_PER_ENVELOPE  # the main lobe and its first sidelobes
UNIFORM_RIVAL_EXCLUSION_BINS = 2  # a tone's Hann main lobe spans ±2 DFT bins


def delay_grid(
    frequencies_hz: np.ndarray, depth_window_m: tuple[float, float], points_per_envelope: int = POINTS_PER_ENVELOPE
):
    """Depths (m) over the unambiguous window [max(0, start), end), spaced c/(2B)/points_per_envelope."""
    f = np.asarray(frequencies_hz, np.float64)
    envelope = C / (2 * (f[-1] - f[0]))
    return np.arange(max(0.0, depth_window_m[0]), depth_window_m[1], envelope / points_per_envelope)


# The periodogram's basis e^{−i2πf_m τ_g} is formed as products of two tables of phasors: delays a
# whole block apart, and the delays within a block (`delay_basis_tables`, `delay_basis`)
DELAY_BASIS_BLOCK = 64


def delay_basis_tables(frequencies_hz, first_delay_s: float, delay_step_s: float, count: int):
    """The two tables of `delay_basis` for τ_g = first + g·step (g < `count`), NumPy float64
    angles (reduced modulo 2π) to float32 (cos, −sin): e^{−i2πf_m(first + a·B·step)} (2, A, N)
    and e^{−i2πf_m·b·step} (2, B, N), B = `DELAY_BASIS_BLOCK`, A = ⌈count/B⌉."""
    f = np.asarray(frequencies_hz, np.float64)
    blocks = -(-count // DELAY_BASIS_BLOCK)

    def phasors(delays):
        cycles = np.asarray(delays, np.float64)[:, None] * f[None, :]
        angle = 2 * np.pi * (cycles - np.floor(cycles))
        return np.stack([np.cos(angle), -np.sin(angle)]).astype(np.float32)

    outer = phasors(first_delay_s + delay_step_s * DELAY_BASIS_BLOCK * np.arange(blocks))
    return outer, phasors(delay_step_s * np.arange(DELAY_BASIS_BLOCK))


def delay_basis(outer: Float[Array, "2 A N"], inner: Float[Array, "2 B N"], count: int) -> Float[Array, "G2 N"]:
    """The periodogram's basis e^{−i2πf_m τ_g} (g < `count`) as float32 real parts then
    imaginary parts, delays by frames (2·count, N): entry (a·B + b) is the product of the
    tables' (`delay_basis_tables`) phasors a and b. The tables' cos/sin are computed once per
    plan: evaluated in the program, every entry's float64 exponential took as long as the
    product with the data (0.23 of 0.50 s for a 256-px sub-tile of 3000 frames and 5998
    delays), and XLA's CPU compiler fuses table cos/sin into the products that use them."""
    (o_re, o_im), (i_re, i_im) = outer[:, :, None, :], inner[:, None, :, :]
    re = o_re * i_re - o_im * i_im  # (A, B, N)
    im = o_re * i_im + o_im * i_re
    n = outer.shape[-1]
    return jnp.concatenate([re.reshape(-1, n)[:count], im.reshape(-1, n)[:count]], axis=0)


class DelayPeriodogram(AbstractCoarseStage):
    """Periodogram over delay on a depth grid (non-uniform schedules), O(N·G) a pixel: suited
    to regions of interest and moderate N, not to full frames at video rate."""

    geometry: SweepGeometry
    weights: Float[Array, " K"]
    detection: Detection
    frequencies_hz: Float[Array, " N"]
    depths_m: Float[Array, " G"]
    basis_outer: Float[Array, "2 A N"]  # `delay_basis_tables`
    basis_inner: Float[Array, "2 B N"]

    @classmethod
    def of(cls, geometry: SweepGeometry, weights, frequencies_hz, false_alarm: float) -> DelayPeriodogram:
        """The stage of a schedule, its detection test over every depth of its grid."""
        depths = delay_grid(frequencies_hz, geometry.depth_window_m)
        delays = geometry.system_delay_s + 2 * depths / C
        detection = delay_detection(frequencies_hz, delays, false_alarm)
        step = 2 * (depths[1] - depths[0]) / C if depths.size > 1 else 0.0
        outer, inner = delay_basis_tables(frequencies_hz, delays[0], step, depths.size)
        return cls(
            geometry,
            device_value(weights),
            detection,
            device_value(frequencies_hz),
            device_value(depths),
            device_value(outer),
            device_value(inner),
        )

    def __call__(self, sequence) -> CoarseSpectrum:
        g = self.depths_m.shape[0]
        basis = delay_basis(self.basis_outer, self.basis_inner, g)  # (2G, N): Re, then Im
        centred = (sequence - jnp.mean(sequence, axis=0)).astype(jnp.float32)
        # one real product (a complex one would do twice the work), at full float32 precision
        parts = jnp.matmul(basis, centred, precision=MATMUL_PRECISION)  # (2G, P)
        power = (parts[:g] ** 2 + parts[g:] ** 2).T
        return CoarseSpectrum(power, first_argmax(power))

    def detection_energy(self, coarse):
        return coarse.power

    def depth(self, coarse, interpolate):
        at_peak = self.depths_m[coarse.peak]
        return at_peak + parabolic_offset(coarse.power, coarse.peak) * self.grid_step_m if interpolate else at_peak

    def tone_amplitude(self, coarse):
        peak_power = at_grid_point(coarse.power, coarse.peak)
        return 2 * jnp.sqrt(peak_power) / self.geometry.num_frames / (2 * self.dominant_weight)

    def frequency_only_sigma(self, amplitude, noise_var):
        return frequency_only_sigma_m(self.frequencies_hz, amplitude * 2 * self.dominant_weight, noise_var)

    @property
    def grid_step_m(self):
        return self.depths_m[1] - self.depths_m[0]

    @property
    def description(self) -> str:
        return "non-uniform schedule: periodogram over a depth grid"
