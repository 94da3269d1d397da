"""Depth estimation: I/Q and carrier alignment (`iq`), the coarse stage shared by every
estimator (`coarse`), and the estimators behind one interface (`base`), chosen by name
(`registry`): DFT peak and interpolated peak (`peak`), the zero-padded DFT's peak (`padded`),
three-point complex interpolations (`candan`, `quinn`), frequency-only ML (`frequency_ml`), and
the phase-locked ML fits: window ML (`window_ml`), table ML (`table`), time-domain ML
(`time_domain`)."""

from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup, FitResult
from .candan import CandanPeak
from .coarse import AbstractCoarseStage, CoarseSpectrum, DelayPeriodogram, UniformSpectrum
from .frequency_ml import FrequencyOnlyML
from .padded import ZeroPaddedPeak
from .peak import DFTPeak, InterpolatedPeak
from .quinn import QuinnPeak
from .registry import METHODS, Method, choose_estimator
from .table import TableML
from .time_domain import TimeDomainML
from .window_ml import WindowML

__all__ = [
    "AbstractDepthEstimator",
    "DepthEstimate",
    "EstimatorSetup",
    "FitResult",
    "AbstractCoarseStage",
    "CoarseSpectrum",
    "DelayPeriodogram",
    "UniformSpectrum",
    "DFTPeak",
    "InterpolatedPeak",
    "METHODS",
    "Method",
    "choose_estimator",
    "CandanPeak",
    "FrequencyOnlyML",
    "QuinnPeak",
    "ZeroPaddedPeak",
    "TableML",
    "TimeDomainML",
    "WindowML",
]
