"""Depth reconstruction of a capture, streamed in pixel tiles.

Files, one job each: `policy` (options, SNR threshold, the order of the validity checks),
`plan` (what a sub-tile program needs, built once from the instrument and the options),
`programs` (the compiled per-sub-tile programs), `engine` (streaming tiles and sub-tiles onto
the devices), `api` (the entry points). The sweep's geometry is `cohflash_jax.geometry`, the
estimators `cohflash_jax.estimate`, the status codes `cohflash_jax.status`.
"""

from .api import (
    FileSetup,
    Reconstruction,
    align_carrier,
    capture_alignment,
    depth_meta,
    forget_setups,
    open_and_reconstruct,
    reconstruct_array,
    reconstruct_capture,
)
from .engine import BlockReader, PendingTile, TileDispatcher, aligned_copy, stream_devices, sub_tile_pixels
from .plan import IQStage, TilePlan, build_plan, frequency_path, program_plan
from .policy import (
    DEFAULT_MAX_FIT_CHI2,
    DEFAULT_SNR_THRESHOLD_DB,
    ReconstructOptions,
    ValidityPolicy,
    applied_snr_threshold_db,
    classify,
    snr_threshold_margin,
)
from .programs import process_tile

__all__ = [
    "FileSetup",
    "Reconstruction",
    "capture_alignment",
    "align_carrier",
    "depth_meta",
    "forget_setups",
    "open_and_reconstruct",
    "reconstruct_array",
    "reconstruct_capture",
    "BlockReader",
    "PendingTile",
    "TileDispatcher",
    "aligned_copy",
    "stream_devices",
    "sub_tile_pixels",
    "IQStage",
    "TilePlan",
    "build_plan",
    "frequency_path",
    "program_plan",
    "DEFAULT_MAX_FIT_CHI2",
    "DEFAULT_SNR_THRESHOLD_DB",
    "ReconstructOptions",
    "ValidityPolicy",
    "applied_snr_threshold_db",
    "classify",
    "snr_threshold_margin",
    "process_tile",
]
