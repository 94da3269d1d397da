"""What one compiled sub-tile program needs to know, built once per configuration from the
instrument and the options (`build_plan`): the I/Q stage, the sweep's geometry, the coarse
stage, the estimator and the validity policy."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..capture import frequency_problem
from ..estimate import (
    AbstractCoarseStage,
    AbstractDepthEstimator,
    DelayPeriodogram,
    EstimatorSetup,
    UniformSpectrum,
    choose_estimator,
)
from ..estimate.harmonics import HarmonicResolver, harmonic_note
from ..estimate.table import ToneTable
from ..estimate.window_model import UniformModel
from ..geometry import SweepGeometry
from ..instrument import Instrument
from ..runtime import device_value
from .policy import ReconstructOptions, ValidityPolicy, applied_snr_threshold_db

# Hybrid phases this close to one another (condition number of the I/Q design) cannot be separated
MAX_HYBRID_CONDITIONING = 1e3


class IQStage(eqx.Module):
    """Data checks, I/Q and carrier alignment: the I/Q matrix and bias (DN → electrons of I, Q
    with the hybrid's gains and offsets folded in), the ADC's saturation level (None: not
    checked), the arithmetic precision, and carrier tracking."""

    weights: jax.Array
    bias: jax.Array
    saturation_dn: float | None = eqx.field(static=True)
    dtype: str = eqx.field(static=True)
    tracking: bool = eqx.field(static=True)
    track_window: int = eqx.field(static=True)

    @property
    def real_dtype(self):
        """The type of the stage's arithmetic (`dtype`) as a JAX type."""
        return jnp.float64 if self.dtype == "float64" else jnp.float32


class TilePlan(eqx.Module):
    """Everything a sub-tile's programs need (`reconstruct.programs`)."""

    iq: IQStage
    model: UniformModel
    geometry: SweepGeometry
    coarse: AbstractCoarseStage
    estimator: AbstractDepthEstimator
    policy: ValidityPolicy
    method: str = eqx.field(static=True)
    harmonics: HarmonicResolver | None = None  # a starved fundamental (`estimate.harmonics`)

    @property
    def depth_window_m(self) -> tuple[float, float]:
        """The unambiguous depths this plan states: the orders' common window where the
        harmonics are resolved, else the dominant tone's."""
        return self.geometry.depth_window_m if self.harmonics is None else self.harmonics.depth_window_m

    @property
    def ambiguity_m(self) -> float:
        return self.geometry.ambiguity_m if self.harmonics is None else self.harmonics.ambiguity_m


def build_plan(
    instrument: Instrument,
    options: ReconstructOptions,
    saturation_dn: float | None = None,
    tracking: bool | None = None,
) -> TilePlan:
    """The plan for reconstructing captures of `instrument` (as described: nominal or
    calibrated) with `options`. `saturation_dn`: the DN that marks ADC saturation (None: no
    check); `tracking`: follow each pixel's carrier drift (default: where `options.carrier` asks)."""
    f = np.asarray(instrument.sweep.frequencies_hz, np.float64)
    problem = frequency_problem(f)
    if problem:
        raise ValueError(problem)
    hybrid = instrument.hybrid
    if hybrid.conditioning() > MAX_HYBRID_CONDITIONING:
        raise ValueError(
            f"hybrid phases {np.round(np.asarray(hybrid.phases_rad), 4)} are nearly equal: I/Q cannot be separated"
        )
    # sideband weights at the sweep's mean frequency: with a roll-off the fundamental's
    # amplitude tapers over the band, which to first order leaves the phase-locked depth
    # unbiased (the taper's odd part is in quadrature with the tone's even kernel)
    weights = np.asarray(instrument.modulator.weights(float(np.mean(f))), np.float64)
    delay = float(instrument.system_delay_s)
    geometry = SweepGeometry.of(f, weights, delay)
    model = UniformModel(float(f[0]), geometry.step_hz, device_value(weights), delay, num_frames=f.size)
    if geometry.uniform:
        coarse = UniformSpectrum.of(geometry, weights, geometry.first_bin(options.min_depth_m), options.false_alarm)
    else:
        if options.min_depth_m > 0:
            raise ValueError("min_depth_m applies to uniform sweeps only")
        coarse = DelayPeriodogram.of(geometry, weights, f, options.false_alarm)
    setup = EstimatorSetup(f, geometry, model, options.window_bins, options.max_steps)
    iq_w, iq_b = hybrid.iq_matrix_dn(1.0)
    iq = IQStage(
        iq_w,
        iq_b,
        saturation_dn,
        options.dtype,
        options.carrier == "tracked" if tracking is None else tracking,
        options.track_window_frames,
    )
    threshold = 10 ** (applied_snr_threshold_db(options.snr_threshold_db, f.size) / 10)
    estimator = choose_estimator(options.method, setup)
    # a peak read-out states the dominant tone's window; the ML resolves the orders' common one
    harmonics = HarmonicResolver.build(f, weights, geometry, options.max_steps) if estimator.refines else None
    window = geometry.depth_window_m if harmonics is None else harmonics.depth_window_m
    policy = ValidityPolicy(threshold, float(options.max_fit_chi2), (max(0.0, window[0]), window[1]))
    return TilePlan(iq, model, geometry, coarse, estimator, policy, options.method, harmonics)


def program_plan(plan: TilePlan) -> TilePlan:
    """The plan as the sub-tile programs take it: τ_sys, the depth windows it places, the tone
    table's start and the validity thresholds as float64 arrays, weakly typed like the Python
    floats they stand for (float32 arithmetic stays float32), not constants compiled into the
    programs. A calibration with a new τ_sys (within the same fold), or another SNR or χ²
    threshold, then runs the programs already compiled."""
    runtime = lambda x: device_value(float(x))

    def convert(node):
        if isinstance(node, SweepGeometry):
            return eqx.tree_at(
                lambda g: (g.system_delay_s, g.depth_window_m),
                node,
                (runtime(node.system_delay_s), tuple(map(runtime, node.depth_window_m))),
            )
        if isinstance(node, UniformModel):
            return eqx.tree_at(lambda m: m.system_delay_s, node, runtime(node.system_delay_s))
        if isinstance(node, ToneTable):
            return eqx.tree_at(lambda t: t.start_m, node, runtime(node.start_m))
        if isinstance(node, ValidityPolicy):
            return jax.tree.map(runtime, node)
        return node

    kinds = (SweepGeometry, UniformModel, ToneTable, ValidityPolicy)
    return jax.tree.map(convert, plan, is_leaf=lambda x: isinstance(x, kinds))


def frequency_path(plan: TilePlan) -> str:
    """Which stages a plan runs, in words (recorded in the depth file)."""
    parts = (plan.coarse.description, plan.estimator.description, harmonic_note(plan.harmonics))
    return "; ".join(part for part in parts if part)
