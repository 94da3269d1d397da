"""Design: what bandwidth, steps, power and time buy.

Files, one job each: `parameters` (the parameter registry, units at the edge, the one point →
Instrument builder), `grid` (the CRLB over a grid and its resumable CSV), `monte_carlo`
(simulate + reconstruct with the designed instrument), `problem` (targets, limits and the
parametrisation that holds the box constraints), `optimise` (gradient design with one
constraint table), `report` (the design command's document), `plots`. Every bound comes from
`cohflash_jax.fisher`.
"""

import importlib

# a function named as its module: bound now, or importing the module (grid does) would leave
# the package attribute pointing at the module instead of the function
from .monte_carlo import monte_carlo as monte_carlo

# Loaded on first use (PEP 562): `cohflash reconstruct` imports the CLI's design and sweep
# commands to build its parser, and the optimiser's imports (optimistix, lineax) cost ~0.3 s of
# every process's start-up otherwise.
_HOMES = {
    "grid": ("RESULT_COLUMNS", "crlb_rows", "read_rows", "run_sweep"),
    "optimise": (
        "CONSTRAINTS",
        "MIN_MEAN_TERM_SNR",
        "RIPPLE_SIGMAS",
        "SIGN_SNR_MARGIN",
        "Constraint",
        "DesignResult",
        "Evaluation",
        "active_constraints",
        "evaluate",
        "frame_cap",
        "mean_term_snr",
        "meets",
        "optimise_design",
        "solve_for_n",
    ),
    "parameters": (
        "PARAMETERS",
        "Parameter",
        "complete_point",
        "design_instrument",
        "parse_axis",
        "point_instrument",
        "to_si",
    ),
    "plots": ("plot_sweep", "sweep_heat_map"),
    "problem": ("DesignProblem",),
    "report": ("design_point", "design_report"),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}


def __getattr__(name):
    if name in _HOME_OF:
        return getattr(importlib.import_module(f".{_HOME_OF[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = sorted([*_HOME_OF, "monte_carlo"])
