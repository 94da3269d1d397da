"""Depth inversion: I/Q and carrier alignment, coarse DFT, ML refinement, CRLB."""

from .coarse import coarse_peak, hann_power, interpolate_peak
from .iq import align_carrier_static, derotate, iq_from_frames, track_carrier_drift
from .ml import dirichlet_window, refine_ml_uniform
from .table import ToneTable, build_tone_table, refine_ml_table

__all__ = ["iq_from_frames", "align_carrier_static", "track_carrier_drift", "derotate", "coarse_peak", "hann_power",
           "interpolate_peak", "dirichlet_window", "refine_ml_uniform", "ToneTable", "build_tone_table",
           "refine_ml_table"]
