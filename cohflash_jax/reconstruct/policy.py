"""What makes a pixel valid: the options a reconstruction takes, the SNR threshold and the
order in which the reasons for invalidity are judged (`classify`)."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp

from ..estimate import METHODS
from ..estimate.detection import DEFAULT_FALSE_ALARM
from ..estimate.drift import CARRIER_ALIGNMENTS
from ..estimate.iq import DRIFT_WINDOW_FRAMES
from ..status import Status
from ..tiling import rows_per_tile

DEFAULT_SNR_THRESHOLD_DB = 14.0
# Reduced χ² of the ML fit above which the model does not describe the pixel (measured:
# ≤ 2.9 at 30 dB peak-bin SNR with sidebands and roll-off; ~18 when carrier tracking failed
# through an uncalibrated hybrid and the "tone" found was drift clutter near DC)
DEFAULT_MAX_FIT_CHI2 = 5.0
# A fit that ran further than this from its coarse depth (in DFT bins) left the coarse
# stage's basin: seen at ~7 dB, where fits ran off to 1e14 m
MAX_FIT_EXCURSION_BINS = 2.0
DEFAULT_WINDOW_BINS = 17
DEFAULT_MAX_STEPS = 16
DEFAULT_TRACK_WINDOW_FRAMES = DRIFT_WINDOW_FRAMES


def snr_threshold_margin(num_frames: int) -> float:
    """Factor on the SNR threshold for the noise variance's own estimation error: σ² comes from
    the pixel's N frames, with relative standard deviation √(2/(N−1)), and a pixel is valid when
    its SNR with σ² one standard deviation above the estimate clears the threshold (N = 3000:
    +0.11 dB; N = 35: +1.2 dB). Measured on the 35-frame 10 Hz mode at falling reflectance
    (112 k pixels): the fits more than 5 CRLB off reached 14.16 dB of measured SNR, so a bare
    14 dB threshold passed 4 of 5051 such pixels; none reached 15 dB."""
    return 1.0 / max(1.0 - math.sqrt(2.0 / max(num_frames - 1, 1)), 0.25)


# beyond this, a threshold passes every pixel or none (and 10^(dB/10) overflows near 3000 dB)
SNR_THRESHOLD_LIMIT_DB = 100.0


def applied_snr_threshold_db(threshold_db: float, num_frames: int) -> float:
    """The SNR threshold (dB) a reconstruction of N frames applies for a requested one."""
    return threshold_db + 10 * math.log10(snr_threshold_margin(num_frames))


@dataclasses.dataclass
class ReconstructOptions:
    """How to reconstruct: the estimator (`method`, one of `estimate.METHODS`), carrier
    alignment, validity thresholds, the I/Q precision and streaming."""

    method: str = "ml"
    carrier: str = "auto"  # `estimate.drift.CARRIER_ALIGNMENTS`: auto, static or tracked
    track_window_frames: int = DEFAULT_TRACK_WINDOW_FRAMES
    tile_rows: int | None = None  # rows per streamed tile; None: `rows_per_tile` chooses
    window_bins: int = DEFAULT_WINDOW_BINS
    max_steps: int = DEFAULT_MAX_STEPS
    snr_threshold_db: float = DEFAULT_SNR_THRESHOLD_DB
    dtype: str = "float32"
    progress: bool = True
    min_depth_m: float = 0.0  # coarse search ignores shallower depths (slow drift / leakage lives near DC)
    max_fit_chi2: float = DEFAULT_MAX_FIT_CHI2  # ml: pixels whose fit is worse are flagged poor_fit
    false_alarm: float = DEFAULT_FALSE_ALARM  # per pixel, under pure noise (`estimate.detection`); 1: no test

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")
        if self.carrier not in CARRIER_ALIGNMENTS:
            raise ValueError(f"carrier must be one of {', '.join(CARRIER_ALIGNMENTS)}, got {self.carrier!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError("dtype must be float32 or float64")
        if self.tile_rows is not None and self.tile_rows < 1:
            raise ValueError("tile_rows must be ≥ 1")
        if not self.min_depth_m >= 0:
            raise ValueError(f"min_depth_m must be ≥ 0, got {self.min_depth_m}")
        # NaN compares false: a NaN threshold would pass every pixel, a NaN χ² limit none
        if not -SNR_THRESHOLD_LIMIT_DB <= self.snr_threshold_db <= SNR_THRESHOLD_LIMIT_DB:
            raise ValueError(
                f"snr_threshold_db must be within ±{SNR_THRESHOLD_LIMIT_DB:g} dB, got {self.snr_threshold_db}"
            )
        if not (0 < self.false_alarm <= 1):
            raise ValueError(
                f"false_alarm must be a probability in (0, 1] (1: no detection test), got {self.false_alarm}"
            )
        if not (self.max_fit_chi2 > 0):
            raise ValueError(f"max_fit_chi2 must be positive, got {self.max_fit_chi2}")
        if self.window_bins < 3 or self.max_steps < 1 or self.track_window_frames < 3:
            raise ValueError(
                f"window_bins (≥ 3), max_steps (≥ 1) and track_window_frames (≥ 3) out of range: "
                f"{self.window_bins}, {self.max_steps}, {self.track_window_frames}"
            )

    def rows_per_tile(self, shape: tuple[int, int, int], itemsize: int = 2) -> int:
        """Rows per streamed tile of a capture of `shape` (frames, height, width) stored with
        `itemsize` bytes a value (`tiling.rows_per_tile`, with these options' `tile_rows`)."""
        return rows_per_tile(shape, itemsize, self.tile_rows)


class ValidityPolicy(eqx.Module):
    """The thresholds a pixel must pass: SNR (linear, the applied one), reduced χ² of a fit,
    and the depths a valid pixel may have. Python floats on the host; the reconstruction's
    programs take them as arrays (`plan.program_plan`), so another threshold or calibration
    runs the programs already compiled."""

    snr_threshold: float
    max_fit_chi2: float
    valid_window_m: tuple[float, float]


def classify(
    policy: ValidityPolicy,
    depth,
    snr,
    *,
    detected,
    out_of_range,
    edge_bias,
    poor_fit,
    ambiguous=None,
    dc_edge,
    converged,
    fit_ok,
    dead,
    saturated,
    finite,
    data_status=None,
):
    """Per-pixel `Status`: later conditions win, so the status names the most basic reason a
    pixel is invalid (bad data before no detection before a failed fit before low SNR before a
    poor fit)."""
    lo, hi = policy.valid_window_m
    out_of_range = (depth < lo) | (depth >= hi) | out_of_range
    status = jnp.full(depth.shape, Status.OK, jnp.int8)
    for cond, code in (
        (out_of_range, Status.OUT_OF_RANGE),
        (edge_bias, Status.EDGE_BIAS),
        (jnp.zeros(depth.shape, bool) if ambiguous is None else ambiguous, Status.AMBIGUOUS),
        (poor_fit, Status.POOR_FIT),
        (dc_edge, Status.DC_EDGE),
        (~converged, Status.NOT_CONVERGED),
        (snr < policy.snr_threshold, Status.LOW_SNR),
        (~fit_ok, Status.FIT_FAILED),
        (~detected, Status.NOT_DETECTED),
        (dead, Status.DEAD),
        (saturated, Status.SATURATED),
        (~finite, Status.BAD_DATA),
    ):
        status = jnp.where(cond, jnp.int8(code), status)
    if data_status is not None:
        status = jnp.where(data_status != 0, data_status.astype(jnp.int8), status)
    return status
