"""The estimators by name: what `--method` offers, and the one function that picks an
estimator for a configuration.

To add an estimator: write its class (an `AbstractDepthEstimator`, in a file of its own) and
add one line to `METHODS` below; the CLI's `--method` choices, the depth file's `method`
attribute and the reconstruction follow.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

from .base import AbstractDepthEstimator, EstimatorSetup
from .candan import CandanPeak
from .frequency_ml import FrequencyOnlyML
from .padded import ZeroPaddedPeak
from .peak import DFTPeak, InterpolatedPeak
from .quinn import QuinnPeak
from .table import TableML, table_fits
from .time_domain import TimeDomainML
from .window_ml import WindowML


def phase_locked_ml(setup: EstimatorSetup) -> AbstractDepthEstimator:
    """The phase-locked ML fit for the sweep: over every frame from a tone table for short
    uniform sweeps, on the DFT window for longer uniform ones, in the time domain otherwise."""
    if not setup.geometry.uniform:
        return TimeDomainML.build(setup)
    if table_fits(setup):
        return TableML.build(setup)
    return WindowML.build(setup)


@dataclasses.dataclass(frozen=True)
class Method:
    """A `--method` choice: how it builds its estimator for a configuration, and what it is."""

    build: Callable[[EstimatorSetup], AbstractDepthEstimator]
    help: str


METHODS: dict[str, Method] = {
    "dft": Method(DFTPeak.build, "depth of the strongest DFT bin (periodogram depth on a non-uniform schedule)"),
    "interp": Method(InterpolatedPeak.build, "the DFT peak interpolated between bins"),
    "dft-pad4": Method(functools.partial(ZeroPaddedPeak.build, pad=4), "the peak of the DFT zero-padded ×4"),
    "dft-pad16": Method(functools.partial(ZeroPaddedPeak.build, pad=16), "the peak of the DFT zero-padded ×16"),
    "candan": Method(CandanPeak.build, "the DFT peak interpolated from its complex neighbours (Jacobsen–Candan)"),
    "quinn": Method(QuinnPeak.build, "the DFT peak's offset from its complex neighbours (Quinn's first estimator)"),
    "ml-frequency": Method(
        FrequencyOnlyML.build, "the periodogram's maximum over continuous frequency (frequency-only ML, phase free)"
    ),
    "ml": Method(phase_locked_ml, "phase-locked maximum likelihood, σ at the CRLB"),
    "ml-time": Method(
        TimeDomainML.build,
        "the same likelihood fitted in the time domain over every frame, whatever the sweep (the slowest; "
        "`ml` picks it for non-uniform schedules)",
    ),
}


def choose_estimator(method: str, setup: EstimatorSetup) -> AbstractDepthEstimator:
    """The estimator `method` names, built for this configuration."""
    try:
        entry = METHODS[method]
    except KeyError:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}") from None
    return entry.build(setup)
