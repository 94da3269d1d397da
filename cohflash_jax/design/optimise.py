"""Gradient-based design: the shortest acquisition reaching a target precision.

For a frame count N, the continuous variables (start frequency, step, modulation index, bias,
exposure, probe power; a warp of the frequency schedule for non-uniform sweeps) are optimised
by BFGS (optimistix) on log CRLB through jax.grad. Box constraints are built into the
parametrisation (`problem.decode`): unambiguous range c/(4Δf_max) ≥ R, highest frequency ≤ f_max,
power ≤ P_max, exposure ≤ frame period and below saturation. The constraints the
parametrisation cannot hold are in one table (`CONSTRAINTS`), which gives the objective its
penalties, the feasibility test (`meets`) and the report of active constraints. N is then the
smallest count whose optimum meets the target (bisection; one compiled function for every N,
frames beyond N masked).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..fisher import SENSOR_NOISE, depth_crlb_m
from ..instrument import Instrument
from ..progress import progress_bar
from ..runtime import async_filter_jit
from .parameters import variables_instrument
from .problem import DesignProblem, carry_over, decode, schedule

# The ML fit ranks every likelihood ripple within ±1 DFT bin of the coarse estimate, so what
# limits it is the likelihood itself: its ripple-to-ripple contrast grows with (ripple/σ_f)²,
# σ_f the frequency-only CRLB. Keeping 4σ_f inside half a ripple c/(4f̄) makes a slip a
# < 1e-4 event per pixel (3σ gave one slip in 256 pixels at the margin: measured).
RIPPLE_SIGMAS = 4.0
MIN_MEAN_TERM_SNR = 25.0  # the sign is then wrong with probability < 3e-7 (5σ)
# The objective's penalty starts at SIGN_SNR_MARGIN × MIN_MEAN_TERM_SNR, so optima keep that
# margin (soft: they settle a fraction of a percent inside it) above the hard limit.
SIGN_SNR_MARGIN = 1.2
PENALTY_WEIGHT = 30.0  # penalties in log space: steep cliffs would stall the line search
MAX_BFGS_STEPS = 400


def mean_term_snr(inst: Instrument, mask, distance_m, reflectance):
    """N·(A·w_0)²/σ_I²: how well the tone's mean term fixes the sign of the carrier-aligned
    sequence. Near θ_b = π/2 the even sidebands vanish, S(ψ + π) = −S(ψ), and (A, τ) and
    (−A, τ + half a ripple) fit equally: depth is then ambiguous by half a ripple."""
    sensor, link = inst.sensor, inst.link
    n_ref = sensor.electrons(link.reference_power_per_pixel_w)
    n_echo = sensor.electrons(link.echo_power_w(distance_m, reflectance, True))
    w = inst.modulator.weights()
    port_var = sensor.port_variance_e2(0.25 * (n_ref + n_echo) * inst.modulator.mean_transmission(), SENSOR_NOISE)
    return jnp.sum(mask) * n_ref * n_echo * w[0] ** 2 / (2 * port_var)


class Evaluation(eqx.Module):
    """A design's bounds and the quantities its constraints judge (traced in the objective,
    floats on the host): phase-locked and frequency-only CRLB (m), mean frequency and largest
    step (Hz), the mean term's SNR, the variables and the used frequencies."""

    crlb_m: object
    coarse_crlb_m: object
    mean_frequency_hz: object
    max_step_hz: object
    mean_term_snr: object
    variables: dict
    frequencies_hz: object


def evaluate(z, n, n_cap: int, problem: DesignProblem) -> Evaluation:
    """Decode z for N = n (frames beyond n masked) and evaluate its bounds (traced: under jit,
    as the objective and `evaluate_compiled` run it)."""
    v = decode(z, n, problem)
    f = schedule(v, n, n_cap)
    mask = (jnp.arange(n_cap) < n).astype(jnp.float64)
    inst = variables_instrument(v, n_cap, frequencies_hz=f)
    crlb = lambda only: depth_crlb_m(
        inst, problem.distance_m, problem.reflectance, frequency_only=only, frame_weights=mask
    )
    locked, coarse = crlb(False), crlb(True)
    steps = jnp.where(mask[1:] > 0, jnp.diff(f), 0.0)
    snr = mean_term_snr(inst, mask, problem.distance_m, problem.reflectance)
    return Evaluation(locked, coarse, jnp.sum(f * mask) / n, jnp.max(steps), snr, v, f)


@async_filter_jit(loop_emitters=True)
def evaluate_program(z, n, *, n_cap: int, problem: DesignProblem) -> tuple:
    """`evaluate` compiled (one program per frame cap and schedule, kept on disk; `problem`
    with its numbers as values): the `Evaluation`'s fields in order."""
    ev = evaluate(z, n, n_cap, problem)
    return tuple(getattr(ev, field.name) for field in dataclasses.fields(ev))


@dataclasses.dataclass(frozen=True)
class Constraint:
    """A constraint as a quantity q(evaluation, problem): the objective's penalty grows as
    log(q/soft)² beyond `soft` (None: held by the parametrisation), a design is feasible when
    q ≤ `hard` (None: always), and it is reported active when q ≥ `active`."""

    quantity: Callable
    soft: float | None
    hard: float | None
    active: float
    report: Callable  # (evaluation, problem) → what to say when active
    infeasible: Callable | None = None  # (evaluation, problem) → why a design fails it


def _ripple(ev, pb):
    return RIPPLE_SIGMAS * ev.coarse_crlb_m / (C / (4 * ev.mean_frequency_hz))


CONSTRAINTS: dict[str, Constraint] = {
    "ripple": Constraint(
        _ripple,
        0.9,
        1.0,
        0.85,
        lambda ev, pb: (
            f"coarse stage near its ripple margin ({RIPPLE_SIGMAS:g}σ of the frequency-only bound = "
            f"{RIPPLE_SIGMAS * ev.coarse_crlb_m * 1e3:.3g} mm vs half a ripple c/(4f̄) = "
            f"{C / (4 * ev.mean_frequency_hz) * 1e3:.3g} mm)"
        ),
        lambda ev, pb: (
            f"the frequency-only bound ({ev.coarse_crlb_m * 1e3:.3g} mm) cannot keep the ML fit in its ripple"
        ),
    ),
    "step": Constraint(
        lambda ev, pb: ev.max_step_hz / (C / (4 * pb.max_range_m)),
        1.0,
        1.0 + 1e-9,
        0.99,
        lambda ev, pb: f"largest step at the unambiguous-range limit c/(4R) = {C / (4 * pb.max_range_m) / 1e6:.4g} MHz",
        lambda ev, pb: f"a step exceeds the unambiguous-range limit c/(4R) = {C / (4 * pb.max_range_m) / 1e6:.4g} MHz",
    ),
    "sign": Constraint(
        lambda ev, pb: SIGN_SNR_MARGIN * MIN_MEAN_TERM_SNR / ev.mean_term_snr,
        1.0,
        SIGN_SNR_MARGIN,
        SIGN_SNR_MARGIN / 1.5,
        lambda ev, pb: (
            f"bias limited by the sign of the tone (mean-term SNR {ev.mean_term_snr:.3g} ≥ {MIN_MEAN_TERM_SNR:g})"
        ),
        lambda ev, pb: f"the tone's sign is not resolved (mean-term SNR {ev.mean_term_snr:.3g})",
    ),
    "power": Constraint(
        lambda ev, pb: ev.variables["probe_power_w"] / pb.max_power_w,
        None,
        None,
        0.99,
        lambda ev, pb: f"probe power at its maximum {pb.max_power_w * 1e3:g} mW",
    ),
    "exposure": Constraint(
        lambda ev, pb: ev.variables["exposure_s"] / pb.max_exposure_s(),
        None,
        None,
        0.99,
        lambda ev, pb: (
            "exposure at the "
            + ("frame period" if pb.max_exposure_s() == 1 / pb.frame_rate_hz else "saturation limit")
            + f" ({pb.max_exposure_s() * 1e3:.3g} ms)"
        ),
    ),
    "max_frequency": Constraint(
        lambda ev, pb: ev.frequencies_hz[-1] / pb.max_frequency_hz,
        None,
        None,
        0.99,
        lambda ev, pb: f"highest frequency at f_max = {pb.max_frequency_hz / 1e9:g} GHz",
    ),
    "modulation_index": Constraint(
        lambda ev, pb: ev.variables["modulation_index"] / pb.max_modulation_index,
        None,
        None,
        0.99,
        lambda ev, pb: f"modulation index at its maximum {pb.max_modulation_index:g}",
    ),
}


def _objective(z, args):
    """log CRLB(depth) + the constraint table's penalties."""
    n, n_cap, problem = args
    ev = evaluate(z, n, n_cap, problem)
    penalty = sum(
        jax.nn.relu(jnp.log(c.quantity(ev, problem) / c.soft)) ** 2 for c in CONSTRAINTS.values() if c.soft is not None
    )
    return jnp.log(ev.crlb_m) + PENALTY_WEIGHT * penalty


def meets(ev: Evaluation, problem: DesignProblem) -> bool:
    """Target met and every hard constraint of the table held."""
    return ev.crlb_m <= problem.target_precision_m and all(
        c.quantity(ev, problem) <= c.hard for c in CONSTRAINTS.values() if c.hard is not None
    )


def active_constraints(ev: Evaluation, problem: DesignProblem) -> list[str]:
    """The constraints a design presses against, in words."""
    return [c.report(ev, problem) for c in CONSTRAINTS.values() if c.quantity(ev, problem) >= c.active]


@dataclasses.dataclass
class DesignResult:
    num_frames: int
    acquisition_s: float
    crlb_m: float
    coarse_crlb_m: float
    variables: dict
    frequencies_hz: np.ndarray
    active_constraints: list
    feasible: bool
    note: str = ""


# Starts of the BFGS search (z, unconstrained): low and high in the band, small and large
# index; the objective is not convex in the start frequency, where ripple margin and f̄ trade off
_STARTS = (
    (3.0, 3.0, 0.0, 0.0, 3.0, 3.0, 0.0),
    (3.0, -3.0, 0.0, 0.0, 3.0, 3.0, 0.0),
    (3.0, 0.0, 1.0, 1.0, 3.0, 3.0, -1.0),
    (0.0, -3.0, -1.0, 0.0, 3.0, 3.0, 1.0),
)


def _on_host(ev: Evaluation, n: int) -> Evaluation:
    """An evaluation's values as floats, its frequencies the first n."""
    v = {k: float(val) for k, val in ev.variables.items()}
    v["mean_term_snr"] = float(ev.mean_term_snr)
    f = np.asarray(ev.frequencies_hz)[:n]
    return Evaluation(
        float(ev.crlb_m),
        float(ev.coarse_crlb_m),
        float(np.mean(f)),
        float(np.max(np.diff(f))) if n > 1 else 0.0,
        float(ev.mean_term_snr),
        v,
        f,
    )


@async_filter_jit(loop_emitters=True)
def solve_starts(n, starts, *, n_cap: int, problem: DesignProblem):
    """BFGS from each row of `starts` for N = n frames → (z, objective) per start: one compiled
    program per frame cap, schedule and number of starts, kept on disk (`problem` with its
    numbers as values: `DesignProblem.as_values`). The starts run one after another
    (`lax.map`), not in lockstep (`vmap`): a batched BFGS loop steps every start until the
    slowest has converged, and its batching rule traces the whole solve a second time."""

    def solve(z_start):
        solver = optx.BFGS(rtol=1e-7, atol=1e-9)
        args = (n, n_cap, problem)
        sol = optx.minimise(_objective, solver, z_start, args=args, max_steps=MAX_BFGS_STEPS, throw=False)
        return sol.value, _objective(sol.value, args)

    return jax.lax.map(solve, starts)


# warm starts a search takes beside `_STARTS` (fewer are padded: one program for any number)
WARM_STARTS = 2


def solve_for_n(n: int, n_cap: int, problem: DesignProblem, warm=()):
    """The best design with n frames (several BFGS starts, and up to `WARM_STARTS` warm
    starts `warm`; one that meets the problem before one that does not) → (z, Evaluation).
    `n_cap` ≥ n: the frames the programs hold (`frame_cap`)."""
    warm = [np.clip(np.asarray(z, np.float64), -6, 6) for z in warm][:WARM_STARTS]
    starts = [list(s) for s in _STARTS] + [list(z) for z in warm]
    starts += [list(_STARTS[0])] * (len(_STARTS) + WARM_STARTS - len(starts))
    n_frames = np.asarray(n, np.int32)
    values_of = problem.as_values()  # the programs take its numbers as values
    zs, values = solve_starts(n_frames, np.asarray(starts, np.float64), n_cap=n_cap, problem=values_of)
    # the lowest objective among the starts whose design meets the target and every hard
    # constraint, else the lowest of all: the penalties are soft, so the lowest objective can
    # lie just past a hard limit where another start found a design within it
    values = np.where(np.isfinite(np.asarray(values)), np.asarray(values), np.inf)
    found = []
    for z, value in zip(np.asarray(zs), values):
        ev = _on_host(Evaluation(*evaluate_program(z, n_frames, n_cap=n_cap, problem=values_of)), n)
        found.append((not (np.isfinite(value) and meets(ev, problem)), value, z, ev))
    _, _, z, ev = min(found, key=lambda candidate: candidate[:2])
    return z, ev


# The programs hold the frames in powers of this, from the second (frames beyond N masked):
# a design's cost grows with the frames held, so a search among few frames runs programs of
# few, at one program for every power visited
FRAME_CAP_BASE = 8


def frame_cap(problem: DesignProblem, n: int | None = None) -> int:
    """The frames the compiled programs hold for N = n (default: the problem's most, its
    `max_frames`): the smallest power of `FRAME_CAP_BASE` (≥ its square) at or above n, at
    most the power of two at or above `max_frames`."""
    most = 1 << int(math.ceil(math.log2(max(problem.max_frames, 8))))
    if n is None:
        return most
    return min(most, FRAME_CAP_BASE ** max(2, math.ceil(math.log(max(n, 1), FRAME_CAP_BASE) - 1e-9)))


def _result(n: int, ev: Evaluation, problem: DesignProblem, feasible: bool, note: str = "") -> DesignResult:
    return DesignResult(
        n,
        n / problem.frame_rate_hz,
        ev.crlb_m,
        ev.coarse_crlb_m,
        ev.variables,
        ev.frequencies_hz,
        active_constraints(ev, problem),
        feasible,
        note,
    )


# The frame counts the search doubles from, and the count below it taken as too few
FIRST_FRAMES = 8
FEWEST_FRAMES = 4


def optimise_design(problem: DesignProblem, progress: bool = True) -> DesignResult:
    """Shortest acquisition (fewest frames at the given frame rate) whose gradient-optimised
    design meets the target precision: N doubled from `FIRST_FRAMES` until a design meets it
    (a design's cost grows with the frames its programs hold, `frame_cap`, so the search
    stays among few frames where the answer lies; once the programs would hold more than a
    `FRAME_CAP_BASE`-th of `max_frames`' frames, straight to `max_frames`, so that a target
    out of reach costs little more than one search there), then bisection between the last
    two, with warm starts. Not met within `max_frames`: the best design there, and why."""
    most = problem.max_frames
    doublings = max(0, math.ceil(math.log2(max(most, 1) / FIRST_FRAMES))) + 1
    lo, n = FEWEST_FRAMES, min(FIRST_FRAMES, most)
    # warm starts, carried over to the frames searched (`carry_over`): the design of the most
    # frames found short of the target (more frames keep it within the limits and improve it)
    # and, once one met it, that of the fewest frames that did
    below = None  # (frames, z)
    carried = lambda found, frames: [] if found is None else [carry_over(found[1], found[0], frames, problem)]
    with progress_bar(total=doublings, desc="design (frames doubled, then bisected)", disable=not progress) as bar:
        while True:
            z, ev = solve_for_n(n, frame_cap(problem, n), problem, carried(below, n))
            bar.update(1)
            if meets(ev, problem) or n >= most:
                break
            below = (n, z)
            lo, n = n, min(2 * n, most)
            if frame_cap(problem, n) * FRAME_CAP_BASE > frame_cap(problem, most):
                n = most  # programs within a power of the most frames: straight to a search there
        if not meets(ev, problem):
            why = [f"best bound {ev.crlb_m * 1e3:.3g} mm"] if ev.crlb_m > problem.target_precision_m else []
            why += [
                c.infeasible(ev, problem)
                for c in CONSTRAINTS.values()
                if c.hard is not None and c.quantity(ev, problem) > c.hard and c.infeasible is not None
            ]
            return _result(
                n,
                ev,
                problem,
                False,
                f"target {problem.target_precision_m * 1e3:g} mm not reachable within {n} frames ("
                + "; ".join(why)
                + "): allow more frames, power or bandwidth",
            )
        hi, best = n, (n, z, ev)
        bar.total = bar.n + max(0, math.ceil(math.log2(max(hi - lo, 1))))
        while hi - lo > 1:
            mid = (lo + hi) // 2
            warm = carried(best, mid) + carried(below, mid)
            z, ev = solve_for_n(mid, frame_cap(problem, mid), problem, warm)
            if meets(ev, problem):
                hi, best = mid, (mid, z, ev)
            else:
                lo, below = mid, (mid, z)
            bar.update(1)
    n, _, ev = best
    return _result(n, ev, problem, True)
