"""Design: what bandwidth, steps, power and time buy.

Files, one job each: `parameters` (the parameter registry, units at the edge, the one point →
Instrument builder), `grid` (the CRLB over a grid and its resumable CSV), `monte_carlo`
(simulate + reconstruct with the designed instrument), `problem` (targets, limits and the
parametrisation that holds the box constraints), `optimise` (gradient design with one
constraint table), `report` (the design command's document), `plots`. Every bound comes from
`cohflash_jax.fisher`.
"""

from .grid import RESULT_COLUMNS, crlb_rows, read_rows, run_sweep
from .monte_carlo import monte_carlo
from .optimise import (
    CONSTRAINTS,
    MIN_MEAN_TERM_SNR,
    RIPPLE_SIGMAS,
    SIGN_SNR_MARGIN,
    Constraint,
    DesignResult,
    Evaluation,
    active_constraints,
    evaluate,
    frame_cap,
    mean_term_snr,
    meets,
    optimise_design,
    solve_for_n,
)
from .parameters import PARAMETERS, Parameter, complete_point, design_instrument, parse_axis, point_instrument, to_si
from .plots import plot_sweep, sweep_heat_map
from .problem import DesignProblem
from .report import design_point, design_report

__all__ = [
    "RESULT_COLUMNS",
    "crlb_rows",
    "read_rows",
    "run_sweep",
    "monte_carlo",
    "CONSTRAINTS",
    "MIN_MEAN_TERM_SNR",
    "RIPPLE_SIGMAS",
    "SIGN_SNR_MARGIN",
    "Constraint",
    "DesignProblem",
    "DesignResult",
    "Evaluation",
    "active_constraints",
    "design_point",
    "design_report",
    "evaluate",
    "frame_cap",
    "mean_term_snr",
    "meets",
    "optimise_design",
    "solve_for_n",
    "PARAMETERS",
    "Parameter",
    "complete_point",
    "design_instrument",
    "parse_axis",
    "point_instrument",
    "to_si",
    "plot_sweep",
    "sweep_heat_map",
]
