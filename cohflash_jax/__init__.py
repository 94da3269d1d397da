"""cohflash_jax: forward model, simulator and depth inversion for stepped-frequency
coherent flash LiDAR (four CCDs behind a 90° optical hybrid).

float64 is enabled on import: the tone phase 2π·f·τ needs it (see `simulate`), and each
stage then picks float32 or float64 explicitly.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from .capture import Capture, CaptureError, write_capture  # noqa: E402
from .constants import SPEED_OF_LIGHT_M_PER_S  # noqa: E402
from .effects import KNOWN_EFFECTS, EffectSettings, parse_effects  # noqa: E402
from .hybrid import NOMINAL_PHASES_RAD, Hybrid  # noqa: E402
from .instrument import Instrument, differentiable  # noqa: E402
from .modulator import MZM, beat_spectrum, bessel_j, mean_transmission, sideband_weights  # noqa: E402
from .radiometry import LinkBudget  # noqa: E402
from .scenes import BUILTIN_SCENES, Scene, from_arrays, from_files, get_scene, planar, staircase, traffic  # noqa: E402
from .sensor import Sensor  # noqa: E402
from .simulate import (Returns, build_returns, expected_port_electrons, iter_frame_chunks,  # noqa: E402
                       sensor_readout, simulate, simulation_truth)
from .sweep import FrequencySweep  # noqa: E402

__version__ = "0.1.0"
