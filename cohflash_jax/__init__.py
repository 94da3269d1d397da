"""cohflash_jax: forward model, simulator and depth inversion for stepped-frequency
coherent flash LiDAR (four CCDs behind a 90° optical hybrid).

The `Instrument` is the currency every stage takes: the simulator (`simulate`), the Fisher
information (`fisher`), reconstruction (`reconstruct`), calibration (`hybrid_fit`,
`Calibration.apply`), the posteriors (`uncertainty`) and the design (`design`). A capture
describes its instrument (`Capture.instrument`).

float64 is enabled on import: the tone phase 2π·f·τ needs it (see `simulate`), and each
stage then picks float32 or float64 explicitly.
"""

import sys as _sys

# a `cohflash` process: `reconstruct` started again on mimalloc where it is installed (first,
# before any import or thread), `reconstruct`'s first tile read by a child process while the
# imports run (`early_read`: forked here, before any thread), no garbage collection until the
# command module is imported (`cli`), NumPy's BLAS on one thread (set before NumPy loads it), a
# GPU's memory taken on demand and a small capture reconstructed on the CPU (both set before
# JAX's backends start), JAX's search for a ROCm plugin by folder names while it imports
from .early_read import start_for_cli as _start_early_read_for_cli
from .process import gpu_memory_on_demand_for_cli as _gpu_memory_on_demand_for_cli
from .process import pause_garbage_collection_for_cli as _pause_garbage_collection_for_cli
from .process import preload_allocator_for_cli as _preload_allocator_for_cli
from .process import rocm_plugin_scan_by_folder_names_for_cli as _rocm_plugin_scan_by_folder_names_for_cli
from .process import single_threaded_blas_for_cli as _single_threaded_blas_for_cli
from .process import small_captures_on_cpu_for_cli as _small_captures_on_cpu_for_cli

_preload_allocator_for_cli(getattr(_sys, "orig_argv", _sys.argv))
_start_early_read_for_cli(getattr(_sys, "orig_argv", _sys.argv))
_pause_garbage_collection_for_cli(getattr(_sys, "orig_argv", _sys.argv))
_single_threaded_blas_for_cli(getattr(_sys, "orig_argv", _sys.argv))
_gpu_memory_on_demand_for_cli(getattr(_sys, "orig_argv", _sys.argv))
_small_captures_on_cpu_for_cli(getattr(_sys, "orig_argv", _sys.argv))

with _rocm_plugin_scan_by_folder_names_for_cli(getattr(_sys, "orig_argv", _sys.argv)):
    import jax as _jax  # noqa: E402

_jax.config.update("jax_enable_x64", True)

# for `reconstruct` (or `stream`) its last run's programs loaded in a thread while the imports
# below run
from .runtime import prefetch_for_cli as _prefetch_for_cli  # noqa: E402

_prefetch_for_cli(getattr(_sys, "orig_argv", _sys.argv))

from .calibration_file import Calibration, PixelMaps  # noqa: E402
from .capture import Capture, CaptureError, write_capture  # noqa: E402
from .constants import SPEED_OF_LIGHT_M_PER_S  # noqa: E402
from .effects import KNOWN_EFFECTS, EffectSettings, parse_effects  # noqa: E402
from .geometry import SweepGeometry  # noqa: E402
from .hybrid import NOMINAL_PHASES_RAD, Hybrid  # noqa: E402
from .instrument import Instrument, InstrumentErrors, differentiable  # noqa: E402
from .modulator import MZM, beat_spectrum, bessel_j, mean_transmission, sideband_weights  # noqa: E402
from .radiometry import LinkBudget  # noqa: E402
from .scenes import BUILTIN_SCENES, Scene, from_arrays, from_files, get_scene, planar, staircase, traffic  # noqa: E402
from .sensor import Sensor  # noqa: E402
from .simulate import (  # noqa: E402
    Returns,
    build_returns,
    expected_port_electrons,
    iter_frame_chunks,
    sensor_readout,
    simulate,
    simulation_truth,
)
from .status import Status  # noqa: E402
from .sweep import FrequencySweep  # noqa: E402

__version__ = "0.2.0"

__all__ = [
    "BUILTIN_SCENES",
    "KNOWN_EFFECTS",
    "MZM",
    "NOMINAL_PHASES_RAD",
    "SPEED_OF_LIGHT_M_PER_S",
    "Calibration",
    "Capture",
    "CaptureError",
    "EffectSettings",
    "FrequencySweep",
    "Hybrid",
    "Instrument",
    "InstrumentErrors",
    "LinkBudget",
    "PixelMaps",
    "Returns",
    "Scene",
    "Sensor",
    "Status",
    "SweepGeometry",
    "beat_spectrum",
    "bessel_j",
    "build_returns",
    "differentiable",
    "expected_port_electrons",
    "from_arrays",
    "from_files",
    "get_scene",
    "iter_frame_chunks",
    "mean_transmission",
    "parse_effects",
    "planar",
    "sensor_readout",
    "sideband_weights",
    "simulate",
    "simulation_truth",
    "staircase",
    "traffic",
    "write_capture",
    "__version__",
]
