"""Monte Carlo precision of a design point: simulate a planar target with the designed
instrument, reconstruct it (ML) with that same instrument, and compare with the truth."""

from __future__ import annotations

import math

import jax
import numpy as np

from ..fisher import SENSOR_NOISE
from .parameters import complete_point, point_instrument


def monte_carlo(point: dict, trials: int = 256, seed: int = 0, frequencies_hz=None) -> dict:
    """Precision of simulate + reconstruct (ML) on a planar target at the point (paper units):
    `trials` pixels (a square tile, independent noise), range falloff as the point says, the
    point's instrument (its modulator with its sidebands, sensor and link) in both. Optional
    non-uniform schedule."""
    from ..reconstruct import ReconstructOptions, build_plan, reconstruct_array
    from ..scenes import planar
    from ..simulate import simulate

    p = complete_point(point)
    inst = point_instrument(p, frequencies_hz)
    side = max(2, int(math.ceil(math.sqrt(trials))))
    # the designed modulator's harmonics are part of what it designed: the truth has them
    effects = SENSOR_NOISE + ("sidebands",) + (("range_falloff",) if p["range_falloff"] else ())
    scene = planar(p["distance_m"], p["reflectance"], effects=effects)
    frames = simulate(scene, inst, side, side, jax.random.key(seed))
    options = ReconstructOptions(method="ml", progress=False)
    out = reconstruct_array(frames, inst, options)
    ok = out["valid"]
    policy = build_plan(inst, options).policy
    # beyond the unambiguous window the instrument measures the folded depth: that is its truth
    start, end = policy.valid_window_m
    truth_m = start + (p["distance_m"] - start) % (end - start)
    err = out["depth_m"][ok] - truth_m
    return {
        "mc_precision_mm": 1e3 * float(np.std(err)) if err.size > 1 else float("nan"),
        "mc_bias_mm": 1e3 * float(np.mean(err)) if err.size else float("nan"),
        "mc_valid_fraction": float(ok.mean()),
        "mc_trials": int(side * side),
        "mc_truth_m": truth_m,
        "mc_note": no_valid_reason(out, policy.snr_threshold) if not ok.any() else "",
    }


def no_valid_reason(out: dict, snr_threshold: float) -> str:
    """Why a Monte Carlo found no valid pixel: the commonest status, and the median SNR against
    the threshold applied."""
    from ..status import Status

    status = np.bincount(out["fit_status"].astype(int).ravel(), minlength=len(Status))
    worst = Status(int(np.argmax(status)))
    snr_db = 10 * np.log10(max(float(np.median(out["snr"])), 1e-30))
    threshold_db = 10 * math.log10(snr_threshold)
    return (
        f"no valid pixel: mostly {worst.message} ({status[worst]} of {out['fit_status'].size}); "
        f"median SNR {snr_db:.1f} dB against the {threshold_db:.1f} dB threshold"
    )
