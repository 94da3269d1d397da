"""The compiled programs of one sub-tile of pixels: data checks and I/Q, the carrier axis,
the rotation onto it, and the inversion (coarse stage, estimator, validity).

They are separate programs, dispatched asynchronously, because XLA's CPU compiler fuses them
badly: within one program it recomputed the per-pixel cos/sin of the carrier axis for every
frame, and computed the rotated sequence straight into the transposed layout, reading I/Q
with a stride. For long sweeps (`SPLIT_AXIS_MIN_FRAMES`) the carrier axis is a program of its
own too: fused with I/Q, its moments recomputed I/Q from the frames. So a long sweep reads
its frames twice instead and never stores I/Q: the data checks and the axis's moments
(`axis_and_checks`), then the rotated sequence (`rotated_from_frames`); only a tracked carrier,
whose drift follows the I/Q sequence, keeps I/Q (`iq_and_checks`). For short sweeps the
rotation and the inversion are one program (`rotate_and_invert`): there the calls' own cost
counts, and the fusion costs nothing. On the CPU the native kernel (`cohflash_jax.native`)
computes the I/Q half of 16-bit frames instead, for long and short sweeps, and only the
inversion (`invert_sequence`) runs here. Timings of each split: docs/performance.md.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..estimate.base import estimate_detected
from ..estimate.iq import carrier_axis, derotate, iq_from_frames, rotate_onto_axis, track_carrier_drift
from ..fisher import reported_sigma_m
from ..runtime import async_filter_jit, first_device, xla_cpu_has_avx512
from .plan import IQStage, TilePlan
from .policy import MAX_FIT_EXCURSION_BINS, classify

SPLIT_AXIS_MIN_FRAMES = 512


def run_program(program, *arguments):
    """Run `program` on `arguments`: how `process_stages` and its halves call each program
    unless told otherwise (`prepare_stages` only gets them ready)."""
    return program(*arguments)


def process_tile(plan: TilePlan, frames, dark, data_status=None, gain=None, carrier_phase_rad=None):
    """Depth and companions for a tile of pixels: frames (4, N, P) → dict of (P,) arrays.
    `dark` (4, P): per-pixel offsets (DN); `gain` (4, P): per-pixel gains relative to the
    hybrid's global ones; `data_status` (P,) int8: codes found upstream (e.g. registration);
    `carrier_phase_rad` (N,): a known carrier drift common to all pixels, removed first.
    Three programs for a long sweep (`SPLIT_AXIS_MIN_FRAMES`; four with a tracked carrier), two
    for a short one, dispatched asynchronously (none waits for its result)."""
    return process_stages(plan.iq, inversion_plan(plan), frames, dark, data_status, gain, carrier_phase_rad)


def process_stages(
    stage: IQStage,
    plan: TilePlan,
    frames,
    dark,
    data_status=None,
    gain=None,
    carrier_phase_rad=None,
    *,
    run=run_program,
    halves: bool | None = None,
):
    """`process_tile` with its plan already split into the I/Q stage and the `inversion_plan`:
    a dispatcher splits it once, not once a sub-tile (a 10 Hz map has ten). `run(program,
    *arguments)` calls each program (default: runs it; `prepare_stages` passes another).
    `halves`: whether to run it as its two halves (`iq_half`, `inversion_half`) whatever its
    length (default: `in_two_halves`), as where the native kernel computes the first."""
    if in_two_halves(stage, frames) if halves is None else halves:
        iq = iq_half(stage, frames, dark, gain, carrier_phase_rad, run=run)
        return inversion_half(plan, iq, data_status, run=run)
    if frames.shape[1] >= SPLIT_AXIS_MIN_FRAMES:
        i, q, flags = run(iq_and_checks, stage, frames, dark, gain, carrier_phase_rad)
        c, s, noise_var, total_var = run(carrier_axis_program, i, q)
        r = run(rotate_program, i, q, c, s)
        return run(invert_sequence, plan, r, noise_var, total_var, flags, data_status)
    i, q, (c, s, noise_var, total_var), flags = run(iq_and_carrier_axis, stage, frames, dark, gain, carrier_phase_rad)
    return run(rotate_and_invert, plan, i, q, c, s, noise_var, total_var, flags, data_status)


def in_two_halves(stage: IQStage, frames) -> bool:
    """Whether a sub-tile's programs split into an I/Q half that reads its frames (`iq_half`)
    and an inversion half that does not (`inversion_half`): a long sweep without a tracked
    carrier. Where the native kernel computes the first half on the host, a sweep of any
    length runs the second alone (`engine.TileDispatcher.host_iq`)."""
    return frames.shape[1] >= SPLIT_AXIS_MIN_FRAMES and not stage.tracking


def iq_half(stage: IQStage, frames, dark, gain=None, carrier_phase_rad=None, *, run=run_program):
    """The data checks, the carrier axis and the rotated sequence of a sub-tile (`in_two_halves`)
    → the inversion's inputs (r, noise variance, total variance, flags)."""
    (c, s, noise_var, total_var), flags = run(axis_and_checks, stage, frames, dark, gain, carrier_phase_rad)
    r = run(rotated_from_frames, stage, frames, dark, c, s, gain, carrier_phase_rad)
    return r, noise_var, total_var, flags


def inversion_half(plan: TilePlan, iq: tuple, data_status=None, *, run=run_program):
    """The inversion of a sub-tile from its I/Q half (`iq_half`, or the native kernel's)."""
    return run(invert_sequence, plan, *iq, data_status)


def prepare_stages(
    stage: IQStage,
    plan: TilePlan,
    frames,
    dark,
    data_status=None,
    gain=None,
    carrier_phase_rad=None,
    *,
    halves: bool | None = None,
):
    """Get the inversion program `process_stages` would run on arguments like these (each
    array or `jax.ShapeDtypeStruct` placed on one device; `halves` as it takes it), loaded or
    compiled, without running anything: the programs before it are only traced for their
    outputs' shapes. The inversion's compile is most of a cold run's (2.4 s of a full
    capture's 3.4 s), so a dispatcher starts it in a thread while the first tile is read and
    the I/Q programs compile (`engine.TileDispatcher.prepare`)."""
    sharding = jax.sharding.SingleDeviceSharding(first_device(jax.tree.leaves((frames, dark, data_status, gain))))

    def run(program, *arguments):
        if program in (invert_sequence, rotate_and_invert):
            return program.prepare(*arguments)
        shapes = eqx.filter_eval_shape(program, *arguments)
        placed = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding, weak_type=x.weak_type)
        return jax.tree.map(placed, shapes)

    process_stages(stage, plan, frames, dark, data_status, gain, carrier_phase_rad, run=run, halves=halves)


def inversion_plan(plan: TilePlan) -> TilePlan:
    """The plan as the inversion programs take it: without its I/Q stage, which only the I/Q
    programs read (the hybrid's matrices, the saturation level, the input's type). Captures
    that differ only there (another ADC depth, a registered capture's resampled frames, an
    in-memory array) then run the inversion programs already compiled."""
    return eqx.tree_at(lambda p: p.iq, plan, None)


rotate_program = async_filter_jit(rotate_onto_axis)


def _axis(i, q):
    """`carrier_axis`'s cos φ, sin φ, and the noise and total variances (float64, as the
    estimators and the detection test use them)."""
    axis = carrier_axis(i, q)
    return axis.cos, axis.sin, axis.noise_var.astype(jnp.float64), axis.total_var.astype(jnp.float64)


carrier_axis_program = async_filter_jit(_axis)


# `frame_extremes` halves the frame axis by elementwise max/min down to fewer than this many frames
# before the last reduction
EXTREMES_FOLD_TO_FRAMES = 16


def frame_extremes(frames):
    """Each pixel's highest and lowest value over the frames: frames (4, N, P) → (4, P) twice.

    Halved by elementwise max/min of the two halves of the frame axis, then reduced. XLA's
    CPU reduction over the frame axis of 16-bit integers vectorises under AVX-512 (used there)
    but runs scalar when held to AVX2 (12× slower: most of the long sweeps' I/Q program there);
    elementwise max/min vectorise on both (docs/performance.md). A NaN need not propagate."""

    def fold(x, op, reduce):
        odd_ones = []  # the frame left over by each halving of an odd count, joined at the end
        while x.shape[1] >= EXTREMES_FOLD_TO_FRAMES:
            half = x.shape[1] // 2
            if x.shape[1] % 2:
                odd_ones.append(x[:, 2 * half])
            x = op(x[:, :half], x[:, half : 2 * half])
        out = reduce(x, axis=1)
        for frame in odd_ones:
            out = op(out, frame)
        return out

    return fold(frames, jnp.maximum, jnp.max), fold(frames, jnp.minimum, jnp.min)


def frame_values(stage: IQStage, frames):
    """The frames in the stage's arithmetic type, a non-finite value as 0 (flagged apart)."""
    floating = jnp.issubdtype(frames.dtype, jnp.floating)
    return (jnp.where(jnp.isfinite(frames), frames, 0.0) if floating else frames).astype(stage.real_dtype)


def stage_iq(stage: IQStage, values, dark, gain=None, carrier_phase_rad=None):
    """I, Q (N, P) of `frame_values`, a known carrier drift removed."""
    i, q = iq_from_frames(values, stage.weights, stage.bias, dark, gain)
    if carrier_phase_rad is not None:
        i, q = derotate(i, q, jnp.asarray(carrier_phase_rad, i.dtype)[:, None])
    return i, q


def _checks_and_iq(stage: IQStage, frames, dark, gain=None, carrier_phase_rad=None):
    """Data checks and I/Q: frames (4, N, P) → I, Q (N, P) (drift removed where asked) and the
    data flags (dead, saturated, finite), each (P,). It takes the plan's I/Q stage alone, so
    plans that differ only beyond it (another method, sweep geometry or policy) share it."""
    real = stage.real_dtype
    floating = jnp.issubdtype(frames.dtype, jnp.floating)
    finite = jnp.all(jnp.isfinite(frames), axis=(0, 1)) if floating else jnp.ones(frames.shape[-1], bool)
    values = frame_values(stage, frames)
    # each pixel's highest and lowest value (a pixel with a non-finite value is bad data
    # whatever they are). Where XLA's CPU code has AVX-512, integer frames' own reduction over
    # the frames vectorises, and is fastest for every sweep. Under AVX2 it runs scalar: a
    # short sweep's program (fused with the carrier axis) takes them from the converted values
    # its I/Q reads anyway, where the conversion is exact; a long sweep's from the frames as
    # stored by `frame_extremes`: measured fastest each way (docs/performance.md). Off the CPU,
    # the frames' own reduction: on an H200 this program took 46 s to compile for a whole
    # 10 240-px tile with the fold in it
    exact = jnp.dtype(frames.dtype).itemsize <= (2 if not floating else jnp.dtype(real).itemsize)
    cpu = jax.default_backend() == "cpu"
    vectorised_integers = cpu and not floating and xla_cpu_has_avx512()
    if frames.shape[1] < SPLIT_AXIS_MIN_FRAMES and exact and not vectorised_integers:
        high, low = jnp.max(values, axis=1), jnp.min(values, axis=1)  # (4, P)
    elif not cpu or vectorised_integers:
        high, low = jnp.max(frames, axis=1), jnp.min(frames, axis=1)
    else:
        high, low = frame_extremes(frames)
    dead = jnp.any(high == low, axis=0)
    saturated = (
        jnp.zeros(dead.shape, bool) if stage.saturation_dn is None else jnp.any(high >= stage.saturation_dn, axis=0)
    )
    i, q = stage_iq(stage, values, dark, gain, carrier_phase_rad)
    if stage.tracking:  # remove a slow carrier drift first (turbulence)
        i, q = derotate(i, q, track_carrier_drift(i, q, stage.track_window))
    return i, q, (dead, saturated, finite)


iq_and_checks = async_filter_jit(_checks_and_iq)


@async_filter_jit
def axis_and_checks(stage: IQStage, frames, dark, gain=None, carrier_phase_rad=None):
    """Data checks and the carrier axis (`carrier_axis_program`'s outputs) of a long sweep
    without a tracked carrier, → ((cos φ, sin φ, noise variance, total variance), flags): I/Q
    computed and reduced to the axis's moments as the frames are read, not stored."""
    i, q, flags = _checks_and_iq(stage, frames, dark, gain, carrier_phase_rad)
    return _axis(i, q), flags


@async_filter_jit
def rotated_from_frames(stage: IQStage, frames, dark, cos_phase, sin_phase, gain=None, carrier_phase_rad=None):
    """The carrier-aligned sequence r (N, P) straight from the frames: I/Q computed again (as
    `axis_and_checks` did) and rotated as they are read."""
    return rotate_onto_axis(
        *stage_iq(stage, frame_values(stage, frames), dark, gain, carrier_phase_rad), cos_phase, sin_phase
    )


@async_filter_jit
def iq_and_carrier_axis(stage: IQStage, frames, dark, gain=None, carrier_phase_rad=None):
    """`iq_and_checks` and the carrier axis in one program → I, Q, (cos φ, sin φ, noise
    variance), flags."""
    i, q, flags = _checks_and_iq(stage, frames, dark, gain, carrier_phase_rad)
    return i, q, _axis(i, q), flags


@async_filter_jit
def rotate_and_invert(plan: TilePlan, i, q, cos_phase, sin_phase, noise_var, total_var, flags, data_status=None):
    """`rotate_program` and `invert_sequence` in one program, for short sweeps: one program
    call a sub-tile fewer, where the calls' own cost is a good part of a 10 Hz map."""
    r = rotate_onto_axis(i, q, cos_phase, sin_phase)
    return _invert_sequence(plan, r, noise_var, total_var, flags, data_status)


def _invert_sequence(plan: TilePlan, r, noise_var, total_var, flags, data_status=None):
    """Depth, its σ, amplitude, SNR and status per pixel from the carrier-aligned sequence
    r (N, P), the carrier axis's noise variance, the total I/Q variance and the data flags
    (`iq_and_checks`): the coarse stage and its detection test, the plan's estimator, then
    `policy.classify`."""
    dead, saturated, finite = flags
    n = r.shape[0]
    coarse = plan.coarse(r)
    detection_ratio = plan.coarse.detection.ratio(plan.coarse.detection_energy(coarse), n * total_var)
    detected = plan.coarse.detection.detected(detection_ratio)
    if plan.estimator.detected_only:
        est = estimate_detected(plan.estimator, plan.coarse, coarse, r, noise_var, detected)
    else:
        est = plan.estimator.estimate(plan.coarse, coarse, r, noise_var)
    if plan.harmonics is not None:  # a starved fundamental: every order picks the unfolding
        est = plan.harmonics.resolve(est, r, noise_var)
    depth, coarse_depth = est.depth_m, est.coarse_depth_m
    dc_edge = plan.coarse.dc_edge(coarse)
    if plan.estimator.refines and plan.harmonics is None:
        depth = plan.geometry.reflect(depth)
        # a fit that ran off (seen at ~7 dB: 1e14 m) is flagged out_of_range
        wandered = jnp.abs(depth - coarse_depth) > MAX_FIT_EXCURSION_BINS * plan.geometry.bin_depth_m
    else:
        wandered = jnp.zeros(depth.shape, bool)
    # flagged pixels that left the coarse stage report the coarse depth, so depth maps stay in range
    depth = jnp.where(wandered | dc_edge, coarse_depth, depth)
    amplitude = est.amplitude
    snr = n * (amplitude * plan.model.weights[plan.geometry.dominant_order]) ** 2 / jnp.maximum(noise_var, 1e-30)
    sigma = reported_sigma_m(est.sigma_m, n, snr)
    start, end = plan.depth_window_m
    edge_bias = jnp.minimum(depth - start, end - depth) < plan.estimator.edge_bins * plan.geometry.bin_depth_m
    status = classify(
        plan.policy,
        depth,
        snr,
        out_of_range=wandered,
        edge_bias=edge_bias,
        poor_fit=est.fit_chi2 > plan.policy.max_fit_chi2,
        ambiguous=est.ambiguous,
        dc_edge=dc_edge,
        converged=est.converged,
        fit_ok=est.fit_ok,
        detected=detected,
        dead=dead,
        saturated=saturated,
        finite=finite,
        data_status=data_status,
    )
    safe = lambda a: jnp.where(jnp.isfinite(a), a, 0.0)
    return {
        "depth_m": safe(depth),
        "amplitude": safe(amplitude),
        "sigma_m": safe(sigma),
        "snr": safe(snr),
        "fit_status": status,
        "valid": status == 0,
        "coarse_depth_m": safe(coarse_depth),
        "fit_chi2": safe(est.fit_chi2),
        "detection_ratio": safe(detection_ratio),
    }


# A long sweep's inversion is compiled through XLA's CPU loop emitters (`async_filter_jit`'s
# `loop_emitters`): its compile, most of a first run's time, is about a third shorter, for an
# inversion a few per cent slower: each warm run pays a little of what a first run saves. Short
# sweeps' `rotate_and_invert`, whose speed is a 10 Hz stream's, keeps the fusion emitters.
# Measured: docs/performance.md
invert_sequence = async_filter_jit(_invert_sequence, loop_emitters=True)
