"""Design sweeps and gradient-based design: what bandwidth, steps, power and time buy.

`run_sweep` evaluates the depth CRLB (autodiff Fisher information, `fisher.py`) over a grid of
design parameters, vectorised per step count, optionally with Monte Carlo precision from
simulate + reconstruct (ML) at chosen points; rows are appended to a CSV atomically after
every chunk, so an interrupted sweep resumes without recomputing finished points, and Monte
Carlo points run in parallel worker processes.

`optimise_design` finds the shortest acquisition reaching a target precision: for a frame
count N, the continuous variables (start frequency, step, modulation index, bias, exposure,
probe power; a warp of the frequency schedule for non-uniform sweeps) are optimised by BFGS
(optimistix) on log CRLB through jax.grad, with the constraints built into the
parametrisation (box transforms): unambiguous range c/(4Δf_max) ≥ R, highest frequency ≤
f_max, power ≤ P_max, exposure ≤ frame period and below saturation. A penalty keeps the coarse
(frequency-only) stage precise enough to land in the right likelihood ripple. N is then the
smallest count whose optimum meets the target (bisection; one compiled function for every N,
frames beyond N masked).
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import itertools
import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from tqdm.auto import tqdm

from .constants import SPEED_OF_LIGHT_M_PER_S as C
from .fileio import atomic_path
from .fisher import crlb_from_fisher, depth_fisher
from .instrument import Instrument
from .modulator import MZM, mean_transmission
from .radiometry import LinkBudget
from .sensor import Sensor
from .sweep import FrequencySweep

NOISE = ("shot_noise", "dark_current", "read_noise", "quantization")

# Sweepable parameters: name → (help, paper value)
PARAMETERS: dict[str, tuple[str, float]] = {
    "bandwidth_ghz": ("sweep bandwidth N·Δf (GHz); sets the step with num_steps", 5.91),
    "start_ghz": ("first microwave frequency (GHz)", 0.1),
    "step_mhz": ("frequency step Δf (MHz); alternative to bandwidth_ghz", 1.97),
    "num_steps": ("frames per capture N (one per frequency step)", 3000),
    "distance_m": ("target distance (m)", 30.5),
    "probe_power_mw": ("probe optical power (mW)", 15.86),
    "exposure_ms": ("CCD exposure (ms)", 4.0),
    "modulation_index": ("MZM modulation index β", 2.0),
    "bias_rad": ("MZM bias angle θ_b (rad)", math.pi / 4),
    "reflectance": ("target reflectance", 0.5),
    "frame_rate_hz": ("camera frame rate (Hz): acquisition time = N / frame rate", 150.0),
    "range_falloff": ("1: echo power ∝ 1/distance²; 0: the 30.5 m link budget at any distance (depth "
                      "then only sets the tone's phase)", 1.0),
}
RESULT_COLUMNS = ("crlb_mm", "crlb_frequency_only_mm", "echo_fw", "acquisition_s", "ambiguity_m",
                  "mc_precision_mm", "mc_bias_mm", "mc_valid_fraction", "mc_trials")
_DUMMY_SWEEP = FrequencySweep.paper(2)


def parse_axis(spec: str) -> tuple[str, np.ndarray]:
    """'name=a:b:n' (linear), 'name=a:b:n:log', or 'name=v1,v2,…' → (name, values)."""
    if "=" not in spec:
        raise ValueError(f"sweep axis {spec!r}: expected NAME=START:STOP:COUNT[:log] or NAME=V1,V2,…")
    name, text = spec.split("=", 1)
    name = name.strip()
    if name not in PARAMETERS:
        raise ValueError(f"unknown sweep parameter {name!r}; known: {', '.join(PARAMETERS)}")
    try:
        if ":" in text:
            parts = text.split(":")
            lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
            log = len(parts) > 3 and parts[3] == "log"
            if n < 1 or (log and (lo <= 0 or hi <= 0)):
                raise ValueError
            values = np.geomspace(lo, hi, n) if log else np.linspace(lo, hi, n)
        else:
            values = np.array([float(v) for v in text.split(",") if v.strip()])
    except (ValueError, IndexError):
        raise ValueError(f"sweep axis {spec!r}: could not read the values") from None
    if name == "num_steps":
        values = np.round(values)
    if values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError(f"sweep axis {spec!r}: no finite values")
    return name, values


def complete_point(point: dict) -> dict:
    """Fill a design point from the paper's values and derive the step or bandwidth."""
    full = {k: v for k, (_, v) in PARAMETERS.items()}
    full.update(point)
    n = int(full["num_steps"])
    if n < 4:
        raise ValueError(f"num_steps must be ≥ 4, got {n}")
    if "bandwidth_ghz" in point and "step_mhz" in point:
        if not math.isclose(point["bandwidth_ghz"], point["step_mhz"] * n / 1e3, rel_tol=1e-9):
            raise ValueError("give either bandwidth_ghz or step_mhz, not both")
    elif "bandwidth_ghz" in point:
        full["step_mhz"] = full["bandwidth_ghz"] * 1e3 / n
    else:
        full["bandwidth_ghz"] = full["step_mhz"] * n / 1e3
    for name in ("distance_m", "probe_power_mw", "exposure_ms", "frame_rate_hz", "step_mhz"):
        if not full[name] > 0:
            raise ValueError(f"{name} must be positive, got {full[name]}")
    if full["exposure_ms"] > 1e3 / full["frame_rate_hz"]:
        raise ValueError(f"exposure {full['exposure_ms']} ms exceeds the frame period at {full['frame_rate_hz']} Hz")
    return full


def _instrument(probe_power_w, exposure_s, modulation_index, bias_rad) -> Instrument:
    return Instrument(sweep=_DUMMY_SWEEP, modulator=MZM(modulation_index, bias_rad),
                      sensor=Sensor(exposure_s=exposure_s), link=LinkBudget(probe_power_w=probe_power_w))


@functools.partial(jax.jit, static_argnames="range_falloff")
def _crlb_points(start_hz, step_hz, distance_m, power_w, exposure_s, beta, bias, reflectance, mask,
                 range_falloff=True):
    """CRLBs (phase-locked, frequency-only) and echo power for a batch of points of one N."""
    m = jnp.arange(mask.shape[0], dtype=jnp.float64)

    def one(s0, df, d, p, te, b, th, rho):
        inst = _instrument(p, te, b, th)
        f = s0 + df * m
        locked = crlb_from_fisher(depth_fisher(inst, f, d, rho, NOISE, range_falloff=range_falloff, frame_weights=mask))
        freq_only = crlb_from_fisher(depth_fisher(inst, f, d, rho, NOISE, frequency_only=True, range_falloff=range_falloff,
                                                  frame_weights=mask))
        return locked, freq_only, inst.link.echo_power_w(d, rho, range_falloff)

    return jax.vmap(one)(start_hz, step_hz, distance_m, power_w, exposure_s, beta, bias, reflectance)


def crlb_rows(points: list[dict]) -> list[dict]:
    """CRLB columns for completed points, vectorised over points with the same N."""
    out = [None] * len(points)
    by_n: dict[tuple, list[int]] = {}
    for i, p in enumerate(points):
        by_n.setdefault((int(p["num_steps"]), bool(p["range_falloff"])), []).append(i)
    for (n, falloff), idx in by_n.items():
        col = lambda k, s=1.0: jnp.asarray([points[i][k] * s for i in idx], jnp.float64)
        locked, freq_only, echo = _crlb_points(col("start_ghz", 1e9), col("step_mhz", 1e6), col("distance_m"),
                                               col("probe_power_mw", 1e-3), col("exposure_ms", 1e-3),
                                               col("modulation_index"), col("bias_rad"), col("reflectance"),
                                               jnp.ones(n), range_falloff=falloff)
        for j, i in enumerate(idx):
            p = points[i]
            out[i] = {"crlb_mm": 1e3 * float(locked[j]), "crlb_frequency_only_mm": 1e3 * float(freq_only[j]),
                      "echo_fw": 1e15 * float(echo[j]), "acquisition_s": n / p["frame_rate_hz"],
                      "ambiguity_m": C / (4 * p["step_mhz"] * 1e6)}
    return out


def point_instrument(point: dict) -> tuple[Instrument, np.ndarray]:
    p = complete_point(point)
    n = int(p["num_steps"])
    sweep = FrequencySweep.uniform(p["start_ghz"] * 1e9, p["step_mhz"] * 1e6, n)
    inst = Instrument(sweep=sweep, modulator=MZM(p["modulation_index"], p["bias_rad"]),
                      sensor=Sensor(exposure_s=p["exposure_ms"] * 1e-3),
                      link=LinkBudget(probe_power_w=p["probe_power_mw"] * 1e-3), frame_rate_hz=p["frame_rate_hz"])
    return inst, sweep.frequencies_hz


def monte_carlo(point: dict, trials: int = 256, seed: int = 0, frequencies_hz=None) -> dict:
    """Precision of simulate + reconstruct (ML) on a planar target at the point: `trials`
    pixels (a square tile, independent noise), range falloff as the point says. Optional non-uniform schedule."""
    from .reconstruct import ReconstructOptions, reconstruct_array
    from .scenes import planar
    from .simulate import simulate

    p = complete_point(point)
    inst, f = point_instrument(p)
    if frequencies_hz is not None:
        f = np.asarray(frequencies_hz, np.float64)
        inst = Instrument(sweep=FrequencySweep(f), modulator=inst.modulator, sensor=inst.sensor, link=inst.link,
                          frame_rate_hz=inst.frame_rate_hz)
    side = max(2, int(math.ceil(math.sqrt(trials))))
    scene = planar(p["distance_m"], p["reflectance"], effects=NOISE + (("range_falloff",) if p["range_falloff"] else ()))
    frames = simulate(scene, inst, side, side, jax.random.key(seed))
    out = reconstruct_array(frames, f, ReconstructOptions(method="ml", progress=False))
    ok = out["valid"]
    err = out["depth_m"][ok] - p["distance_m"]
    return {"mc_precision_mm": 1e3 * float(np.std(err)) if err.size > 1 else float("nan"),
            "mc_bias_mm": 1e3 * float(np.mean(err)) if err.size else float("nan"),
            "mc_valid_fraction": float(ok.mean()), "mc_trials": int(side * side)}


def _mc_worker(args):
    point, trials, seed = args
    return monte_carlo(point, trials, seed)


def _key(point: dict, names) -> tuple:
    return tuple(f"{float(point[n]):.10g}" for n in names)


def read_rows(path) -> list[dict]:
    """The rows of a sweep CSV (none where the file does not exist). A file that is not a
    sweep CSV raises ValueError: a sweep never overwrites what it cannot resume."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            header = reader.fieldnames or []
    except (UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"{path} exists and is not a sweep CSV ({exc}): choose another --out") from None
    missing = [c for c in ("swept",) + tuple(PARAMETERS) if c not in header]
    if missing:
        raise ValueError(f"{path} exists and is not a sweep CSV (no column {', '.join(missing[:3])}"
                         f"{' …' if len(missing) > 3 else ''}): choose another --out")
    out = []
    for line, r in enumerate(rows, start=2):  # empty cells (no Monte Carlo at that point) are left out
        try:
            out.append({k: (v if k == "swept" else float(v)) for k, v in r.items() if v not in ("", None)})
        except (TypeError, ValueError):
            raise ValueError(f"{path}, line {line}: not a number where one is expected") from None
    return out


def _write_rows(path, rows, columns):
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            writer.writerow({c: r.get(c, "") for c in columns})


def run_sweep(axes: list[tuple[str, np.ndarray]], out_csv, *, fixed: dict | None = None,
              mc_points: list[dict] | None = None, mc_all: bool = False, mc_trials: int = 256,
              workers: int = 1, chunk: int = 32, progress: bool = True, stop_after: int | None = None) -> list[dict]:
    """Evaluate the grid (cartesian product of `axes`, other parameters from `fixed` or the
    paper), append rows to `out_csv` after each chunk (atomically), skip points already there.
    `mc_points`: partial points (axis values) that also get a Monte Carlo run; `mc_all`: all.
    `stop_after`: stop after that many new points (what an interrupt does, for tests)."""
    fixed = dict(fixed or {})
    names = [n for n, _ in axes]
    if len(set(names)) != len(names):
        raise ValueError("a parameter appears twice among the sweep axes")
    for n in names:
        fixed.pop(n, None)
    grid = [dict(zip(names, combo)) for combo in itertools.product(*[v for _, v in axes])]
    points = [complete_point({**fixed, **g}) for g in grid]
    columns = ["swept"] + list(PARAMETERS) + list(RESULT_COLUMNS)
    swept = ",".join(names)
    previous = read_rows(out_csv)
    if previous and any(r.get("swept") != swept for r in previous):
        raise ValueError(f"{out_csv} holds a sweep over other parameters ({previous[0].get('swept')}): "
                         "choose another --out")
    if previous and points:
        derived = {"bandwidth_ghz", "step_mhz"} if {"bandwidth_ghz", "step_mhz", "num_steps"} & set(names) else set()
        for k in PARAMETERS:
            if k in names or k in derived or k not in previous[0]:
                continue
            if not math.isclose(float(previous[0][k]), float(points[0][k]), rel_tol=1e-9):
                raise ValueError(f"{out_csv} was swept with {k} = {previous[0][k]:g}, now {points[0][k]:g}: "
                                 "choose another --out (the file's rows are kept)")
    done = {_key(r, names): r for r in previous}
    wanted_mc = {_key({**fixed, **m}, names) for m in (mc_points or [])}

    def needs_mc(p):
        return mc_all or _key(p, names) in wanted_mc

    todo = [p for p in points if _key(p, names) not in done
            or (needs_mc(p) and "mc_trials" not in done[_key(p, names)])]
    if stop_after is not None:
        todo = todo[:stop_after]
    pool = ProcessPoolExecutor(workers, mp_context=__import__("multiprocessing").get_context("spawn")) \
        if workers > 1 and any(needs_mc(p) for p in todo) else None
    try:
        with tqdm(total=len(points), initial=len(points) - len(todo), desc="sweep", unit="pt",
                  disable=not progress) as bar:
            for start in range(0, len(todo), chunk):
                batch = todo[start:start + chunk]
                rows = [{"swept": swept, **p, **r} for p, r in zip(batch, crlb_rows(batch))]
                mc_jobs = [(i, (p, mc_trials, 0)) for i, p in enumerate(batch) if needs_mc(p)]
                results = (pool.map(_mc_worker, [j for _, j in mc_jobs]) if pool is not None
                           else map(_mc_worker, [j for _, j in mc_jobs]))
                for (i, _), res in zip(mc_jobs, results):
                    rows[i].update(res)
                for r in rows:
                    done[_key(r, names)] = r
                ordered = [done[_key(p, names)] for p in points if _key(p, names) in done]
                _write_rows(out_csv, ordered, columns)
                bar.update(len(batch))
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    return [done[_key(p, names)] for p in points if _key(p, names) in done]


# ----------------------------------------------------------------------------- figures
def sweep_heat_map(rows: list[dict], names: list[str]):
    """The CRLB (mm) over the first two swept axes → (xs, ys, grid (len(ys), len(xs)), at):
    beyond two axes, the slice at the smallest value of each further axis, `at` {name: value}."""
    at = {n: min(float(r[n]) for r in rows) for n in names[2:]}
    rows = [r for r in rows if all(float(r[n]) == v for n, v in at.items())]
    xs = np.unique([float(r[names[0]]) for r in rows])
    ys = np.unique([float(r[names[1]]) for r in rows])
    grid = np.full((ys.size, xs.size), np.nan)
    for r in rows:
        grid[np.searchsorted(ys, float(r[names[1]])), np.searchsorted(xs, float(r[names[0]]))] = float(r["crlb_mm"])
    return xs, ys, grid, at


def plot_sweep(rows: list[dict], names: list[str], path) -> Path:
    """Heat map with precision contours (two axes) or precision against the swept parameter
    (one axis; against frames and acquisition time when it is num_steps), CRLB and Monte Carlo
    on the same axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .fileio import save_figure

    crlb = np.array([float(r["crlb_mm"]) for r in rows])
    if len(names) >= 2:
        xs, ys, grid, at = sweep_heat_map(rows, names)
        fig, ax = plt.subplots(figsize=(7, 5.5), constrained_layout=True)
        mesh = ax.pcolormesh(xs, ys, grid, shading="nearest", norm=matplotlib.colors.LogNorm(), cmap="viridis")
        fig.colorbar(mesh, ax=ax, label="CRLB of depth (mm)")
        levels = np.array([0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10])
        levels = levels[(levels > np.nanmin(grid)) & (levels < np.nanmax(grid))]
        if levels.size and xs.size > 1 and ys.size > 1:
            cs = ax.contour(xs, ys, grid, levels=levels, colors="w", linewidths=0.8)
            ax.clabel(cs, fmt=lambda v: f"{v:g} mm", fontsize=8)
        ax.set(xlabel=names[0], ylabel=names[1], title="depth precision bound (phase-locked CRLB)")
        if at:
            ax.set_title(ax.get_title() + "\nat " + ", ".join(f"{n} = {v:g}" for n, v in at.items()), fontsize=10)
        return save_figure(fig, path)
    name = names[0]
    x = np.array([float(r[name]) for r in rows])
    order = np.argsort(x)
    fig, ax = plt.subplots(figsize=(7, 5), constrained_layout=True)
    # markers, so that a sweep of one point shows
    ax.loglog(x[order], crlb[order], "-", marker=".", label="CRLB, phase-locked (autodiff Fisher)")
    ax.loglog(x[order], np.array([float(r["crlb_frequency_only_mm"]) for r in rows])[order], "--", marker=".",
              label="CRLB, frequency only")
    mc = np.array([float(r.get("mc_precision_mm", float("nan"))) for r in rows])
    trials = np.array([float(r.get("mc_trials", float("nan"))) for r in rows])
    valid = np.array([float(r.get("mc_valid_fraction", float("nan"))) for r in rows])
    has = np.isfinite(mc) & (valid >= 0.5)  # a spread over a few surviving pixels would mislead
    if has.any():
        used = trials[has] * valid[has]
        err = mc[has] / np.sqrt(2 * np.maximum(used - 1, 1))
        ax.errorbar(x[has], mc[has], yerr=err, fmt="o",
                    label=f"Monte Carlo (ML), {int(np.nanmax(trials))} px each (points with ≥ 50 % valid)")
    ax.set(xlabel=name, ylabel="depth precision (mm)")
    if name == "num_steps":
        rate = np.array([float(r["frame_rate_hz"]) for r in rows])
        if np.allclose(rate, rate[0]):
            top = ax.secondary_xaxis("top", functions=(lambda n: n / rate[0], lambda t: t * rate[0]))
            top.set_xlabel(f"acquisition time (s) at {rate[0]:g} frames/s")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return save_figure(fig, path)


# ----------------------------------------------------------------------------- gradient-based design
@dataclasses.dataclass(frozen=True)
class DesignProblem:
    """Targets and constraints of `optimise_design` (SI units)."""

    target_precision_m: float
    max_range_m: float
    distance_m: float = 30.5
    reflectance: float = 0.5
    max_power_w: float = 15.86e-3
    frame_rate_hz: float = 150.0
    min_frequency_hz: float = 0.1e9
    max_frequency_hz: float = 30e9
    max_modulation_index: float = 5.0
    schedule: str = "uniform"  # or "warped": f = start + span·u^p, p optimised
    max_frames: int = 32768
    saturation_fraction: float = 0.8  # exposure keeps the brightest port below this share of full well

    def __post_init__(self):
        for name in ("target_precision_m", "max_range_m", "distance_m", "max_power_w", "frame_rate_hz",
                     "max_frequency_hz", "reflectance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.max_frequency_hz <= self.min_frequency_hz:
            raise ValueError("max_frequency_hz must exceed min_frequency_hz")
        if self.schedule not in ("uniform", "warped"):
            raise ValueError("schedule must be 'uniform' or 'warped'")
        sensor = Sensor()
        ref_rate = float(sensor.electrons(LinkBudget().reference_power_per_pixel_w)) / float(sensor.exposure_s)
        # brightest port: a quarter of the reference ideally; budget half of it (hybrid imbalance)
        t_sat = self.saturation_fraction * float(sensor.full_well_e) / (0.5 * ref_rate + float(sensor.dark_current_e_per_s))
        object.__setattr__(self, "_max_exposure_s", min(1.0 / self.frame_rate_hz, t_sat))

    def max_step_hz(self, n):
        """Largest step: the unambiguous range, and the band's room for n frames (n may be traced)."""
        room = (self.max_frequency_hz - self.min_frequency_hz) / jnp.maximum(n - 1, 1)
        return jnp.minimum(C / (4 * self.max_range_m), room)

    def max_exposure_s(self) -> float:
        """Longest exposure: the frame period, or where the brightest port nears full well."""
        return self._max_exposure_s


_sig = jax.nn.sigmoid


def _decode(z, n, problem: DesignProblem):
    """Unconstrained z → design variables inside their bounds (constraints by construction)."""
    step_max = problem.max_step_hz(n)
    span_max = problem.max_frequency_hz - problem.min_frequency_hz
    step = step_max * _sig(z[0])
    start = problem.min_frequency_hz + (span_max - (n - 1) * step) * _sig(z[1])
    x = 0.05 + (0.5 * problem.max_modulation_index - 0.05) * _sig(z[2])
    bias = 0.05 + (math.pi / 2 - 0.1) * _sig(z[3])
    exposure = problem.max_exposure_s() * (0.01 + 0.99 * _sig(z[4]))
    power = problem.max_power_w * _sig(z[5])
    warp = jnp.exp(0.7 * jnp.tanh(z[6])) if problem.schedule == "warped" else 1.0
    return {"step_hz": step, "start_hz": start, "modulation_index": 2 * x, "bias_rad": bias,
            "exposure_s": exposure, "probe_power_w": power, "warp": warp}


def _schedule(v, n, n_cap):
    """Frequencies (n_cap,) of which the first n are used: uniform (warp 1), or warped
    f = start + span·u^p over the same band (p < 1 crowds frames towards the top)."""
    m = jnp.arange(n_cap, dtype=jnp.float64)
    span = (n - 1) * v["step_hz"]
    u = jnp.clip(m / jnp.maximum(n - 1, 1), 0.0, 1.0)
    return v["start_hz"] + span * u ** v["warp"]


def _objective(z, args):
    """log CRLB(depth) + penalties: frequency-only bound within half a ripple (RIPPLE_SIGMAS σ); steps ≤ c/(4R); the
    mean term strong enough to fix the tone's sign."""
    n, n_cap, problem = args
    v = _decode(z, n, problem)
    f = _schedule(v, n, n_cap)
    mask = (jnp.arange(n_cap) < n).astype(jnp.float64)
    inst = _instrument(v["probe_power_w"], v["exposure_s"], v["modulation_index"], v["bias_rad"])
    locked = crlb_from_fisher(depth_fisher(inst, f, problem.distance_m, problem.reflectance, NOISE, frame_weights=mask))
    coarse = crlb_from_fisher(depth_fisher(inst, f, problem.distance_m, problem.reflectance, NOISE, frequency_only=True,
                                             frame_weights=mask))
    mean_f = jnp.sum(f * mask) / n
    ripple_margin = RIPPLE_SIGMAS * coarse / (C / (4 * mean_f))  # must stay < 1
    steps = jnp.where(mask[1:] > 0, jnp.diff(f), 0.0)
    step_excess = jnp.max(steps) / (C / (4 * problem.max_range_m))  # must stay ≤ 1
    sign_margin = SIGN_SNR_MARGIN * MIN_MEAN_TERM_SNR / mean_term_snr(inst, f, mask, problem.distance_m, problem.reflectance)
    # penalties in log space: steep cliffs would stall the line search
    penalty = 30 * (jax.nn.relu(jnp.log(ripple_margin / 0.9)) ** 2 + jax.nn.relu(jnp.log(step_excess)) ** 2
                    + jax.nn.relu(jnp.log(sign_margin)) ** 2)
    return jnp.log(locked) + penalty


def mean_term_snr(inst: Instrument, frequencies, mask, distance_m, reflectance):
    """N·(A·w_0)²/σ_I²: how well the tone's mean term fixes the sign of the carrier-aligned
    sequence. Near θ_b = π/2 the even sidebands vanish, S(ψ + π) = −S(ψ), and (A, τ) and
    (−A, τ + half a ripple) fit equally: depth is then ambiguous by half a ripple."""
    sensor, link = inst.sensor, inst.link
    n_ref = sensor.electrons(link.reference_power_per_pixel_w)
    n_echo = sensor.electrons(link.echo_power_w(distance_m, reflectance, True))
    x = 0.5 * inst.modulator.modulation_index
    w = inst.modulator.weights()
    s0 = mean_transmission(x, inst.modulator.bias_rad)
    port_var = 0.25 * (n_ref + n_echo) * s0 + sensor.dark_electrons + sensor.read_noise_e**2 \
        + (1 / sensor.dn_per_electron) ** 2 / 12
    return jnp.sum(mask) * n_ref * n_echo * w[0] ** 2 / (2 * port_var)


# The ML fit ranks every likelihood ripple within ±1 DFT bin of the coarse estimate, so what
# limits it is the likelihood itself: its ripple-to-ripple contrast grows with (ripple/σ_f)²,
# σ_f the frequency-only CRLB. Keeping 3σ_f inside half a ripple c/(4f̄) keeps slips rare
# σ_f the frequency-only CRLB. Keeping 4σ_f inside half a ripple c/(4f̄) makes a slip a
# < 1e-4 event per pixel (3σ gave one slip in 256 pixels at the margin: measured).
RIPPLE_SIGMAS = 4.0
MIN_MEAN_TERM_SNR = 25.0  # the sign is then wrong with probability < 3e-7 (5σ)
# The objective's penalty starts at SIGN_SNR_MARGIN × MIN_MEAN_TERM_SNR, so optima keep that
# margin (soft: they settle a fraction of a percent inside it) above the hard limit.
SIGN_SNR_MARGIN = 1.2


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


_compiled_cache: dict = {}


def _solve_for_n(n: int, n_cap: int, problem: DesignProblem, z0=None):
    key = (n_cap, problem)
    if key not in _compiled_cache:
        def solve(nn, z_start):
            solver = optx.BFGS(rtol=1e-7, atol=1e-9)
            sol = optx.minimise(_objective, solver, z_start, args=(nn, n_cap, problem), max_steps=400, throw=False)
            return sol.value, _objective(sol.value, (nn, n_cap, problem))

        _compiled_cache[key] = jax.jit(jax.vmap(solve, in_axes=(None, 0)))
    # several starts (low and high in the band, small and large index; the warm start): the
    # objective is not convex in the start frequency, where ripple margin and f̄ trade off
    starts = [[3.0, 3.0, 0.0, 0.0, 3.0, 3.0, 0.0], [3.0, -3.0, 0.0, 0.0, 3.0, 3.0, 0.0],
              [3.0, 0.0, 1.0, 1.0, 3.0, 3.0, -1.0], [0.0, -3.0, -1.0, 0.0, 3.0, 3.0, 1.0]]
    if z0 is not None:
        starts.append(list(np.clip(np.asarray(z0), -6, 6)))
    zs, values = _compiled_cache[key](jnp.asarray(n, jnp.int32), jnp.asarray(starts, jnp.float64))
    values = jnp.where(jnp.isfinite(values), values, jnp.inf)
    z = zs[int(jnp.argmin(values))]
    return z, _evaluate(z, n, n_cap, problem)


def _evaluate(z, n, n_cap, problem):
    v = _decode(z, n, problem)
    f = _schedule(v, n, n_cap)
    mask = (jnp.arange(n_cap) < n).astype(jnp.float64)
    inst = _instrument(v["probe_power_w"], v["exposure_s"], v["modulation_index"], v["bias_rad"])
    locked = float(crlb_from_fisher(depth_fisher(inst, f, problem.distance_m, problem.reflectance, NOISE, frame_weights=mask)))
    coarse = float(crlb_from_fisher(depth_fisher(inst, f, problem.distance_m, problem.reflectance, NOISE, frequency_only=True,
                                             frame_weights=mask)))
    v = {k: float(val) for k, val in v.items()}
    v["mean_term_snr"] = float(mean_term_snr(inst, f, mask, problem.distance_m, problem.reflectance))
    return locked, coarse, v, np.asarray(f)[:n]


def _meets(crlb, coarse, f, problem: DesignProblem, variables: dict) -> bool:
    """Target met, frequency-only bound inside half a ripple (RIPPLE_SIGMAS σ), every step within c/(4R), and
    the mean term strong enough to fix the tone's sign."""
    ok_ripple = RIPPLE_SIGMAS * coarse <= C / (4 * float(np.mean(f)))
    ok_steps = len(f) < 2 or float(np.max(np.diff(f))) <= C / (4 * problem.max_range_m) * (1 + 1e-9)
    ok_sign = variables["mean_term_snr"] >= MIN_MEAN_TERM_SNR
    return crlb <= problem.target_precision_m and ok_ripple and ok_steps and ok_sign


def _active(v: dict, f: np.ndarray, n: int, coarse: float, problem: DesignProblem) -> list[str]:
    act = []
    if v["probe_power_w"] > 0.99 * problem.max_power_w:
        act.append(f"probe power at its maximum {problem.max_power_w * 1e3:g} mW")
    if v["exposure_s"] > 0.99 * problem.max_exposure_s():
        which = "frame period" if problem.max_exposure_s() == 1 / problem.frame_rate_hz else "saturation limit"
        act.append(f"exposure at the {which} ({problem.max_exposure_s() * 1e3:.3g} ms)")
    max_step = float(np.max(np.diff(f))) if n > 1 else 0.0
    if max_step > 0.99 * C / (4 * problem.max_range_m):
        act.append(f"largest step at the unambiguous-range limit c/(4R) = {C / (4 * problem.max_range_m) / 1e6:.4g} MHz")
    if f[-1] > 0.99 * problem.max_frequency_hz:
        act.append(f"highest frequency at f_max = {problem.max_frequency_hz / 1e9:g} GHz")
    spread = RIPPLE_SIGMAS * coarse
    if spread > 0.85 * C / (4 * float(np.mean(f))):
        act.append(f"coarse stage near its ripple margin ({RIPPLE_SIGMAS:g}σ of the frequency-only bound = {spread * 1e3:.3g} mm vs half "
                   f"a ripple c/(4f̄) = {C / (4 * float(np.mean(f))) * 1e3:.3g} mm)")
    if v["mean_term_snr"] < 1.5 * MIN_MEAN_TERM_SNR:
        act.append(f"bias limited by the sign of the tone (mean-term SNR {v['mean_term_snr']:.3g} ≥ {MIN_MEAN_TERM_SNR:g})")
    if v["modulation_index"] > 0.99 * problem.max_modulation_index:
        act.append(f"modulation index at its maximum {problem.max_modulation_index:g}")
    return act


def optimise_design(problem: DesignProblem, progress: bool = True) -> DesignResult:
    """Shortest acquisition (fewest frames at the given frame rate) whose gradient-optimised
    design meets the target precision; bisection over N with warm starts."""
    n_cap = 1 << int(math.ceil(math.log2(max(problem.max_frames, 8))))
    lo, hi = 4, problem.max_frames
    z_hi, (crlb_hi, coarse_hi, v_hi, f_hi) = _solve_for_n(hi, n_cap, problem)
    if not _meets(crlb_hi, coarse_hi, f_hi, problem, v_hi):
        why = []
        if crlb_hi > problem.target_precision_m:
            why.append(f"best bound {crlb_hi * 1e3:.3g} mm")
        if RIPPLE_SIGMAS * coarse_hi > C / (4 * float(np.mean(f_hi))):
            why.append(f"the frequency-only bound ({coarse_hi * 1e3:.3g} mm) cannot keep the ML fit in its ripple")
        if v_hi["mean_term_snr"] < MIN_MEAN_TERM_SNR:
            why.append(f"the tone's sign is not resolved (mean-term SNR {v_hi['mean_term_snr']:.3g})")
        return DesignResult(hi, hi / problem.frame_rate_hz, crlb_hi, coarse_hi, v_hi, f_hi,
                            _active(v_hi, f_hi, hi, coarse_hi, problem), False,
                            f"target {problem.target_precision_m * 1e3:g} mm not reachable within {hi} frames ("
                            + "; ".join(why) + "): allow more frames, power or bandwidth")
    best = (hi, z_hi, crlb_hi, coarse_hi, v_hi, f_hi)
    steps = int(math.ceil(math.log2(hi - lo + 1)))
    with tqdm(total=steps, desc="design (bisection over N)", disable=not progress) as bar:
        while hi - lo > 1:
            mid = (lo + hi) // 2
            z, (crlb, coarse, v, f) = _solve_for_n(mid, n_cap, problem, best[1])
            if _meets(crlb, coarse, f, problem, v):
                hi, best = mid, (mid, z, crlb, coarse, v, f)
            else:
                lo = mid
            bar.update(1)
    n, z, crlb, coarse, v, f = best
    return DesignResult(n, n / problem.frame_rate_hz, crlb, coarse, v, f, _active(v, f, n, coarse, problem), True)



def design_point(result: DesignResult, problem: DesignProblem) -> dict:
    """The optimum as a sweep/Monte Carlo point (paper units)."""
    v = result.variables
    return {"start_ghz": v["start_hz"] / 1e9, "step_mhz": v["step_hz"] / 1e6, "num_steps": result.num_frames,
            "distance_m": problem.distance_m, "reflectance": problem.reflectance,
            "probe_power_mw": v["probe_power_w"] * 1e3, "exposure_ms": v["exposure_s"] * 1e3,
            "modulation_index": v["modulation_index"], "bias_rad": v["bias_rad"], "frame_rate_hz": problem.frame_rate_hz}


def design_report(problem: DesignProblem, compare_warped: bool = False, validate_trials: int = 256,
                  progress: bool = True) -> dict:
    """Optimise, optionally compare a warped schedule at the same frame count, validate by
    Monte Carlo at the optimum → {"document": JSON-able dict, "text": summary}."""
    result = optimise_design(problem, progress)
    v = result.variables
    doc = {"problem": dataclasses.asdict(problem), "feasible": result.feasible, "note": result.note,
           "num_frames": result.num_frames, "acquisition_s": result.acquisition_s,
           "crlb_mm": result.crlb_m * 1e3, "coarse_crlb_mm": result.coarse_crlb_m * 1e3,
           "variables": v, "active_constraints": result.active_constraints,
           "unambiguous_range_m": C / (4 * float(np.max(np.diff(result.frequencies_hz)))),
           "frequencies_hz": {"first": float(result.frequencies_hz[0]), "last": float(result.frequencies_hz[-1])}}
    lines = [("optimum" if result.feasible else "NOT FEASIBLE: " + result.note),
             f"  {result.num_frames} frames = {result.acquisition_s:.4g} s at {problem.frame_rate_hz:g} frames/s; "
             f"CRLB {result.crlb_m * 1e3:.4g} mm (target {problem.target_precision_m * 1e3:g} mm)",
             f"  sweep {result.frequencies_hz[0] / 1e9:.4f} … {result.frequencies_hz[-1] / 1e9:.4f} GHz, step "
             f"{v['step_hz'] / 1e6:.4g} MHz (unambiguous to {doc['unambiguous_range_m']:.4g} m)",
             f"  modulation index {v['modulation_index']:.3f}, bias {v['bias_rad']:.3f} rad, exposure "
             f"{v['exposure_s'] * 1e3:.4g} ms, probe power {v['probe_power_w'] * 1e3:.4g} mW",
             "  active constraints: " + ("; ".join(result.active_constraints) or "none")]
    if compare_warped and result.feasible:
        warped_problem = dataclasses.replace(problem, schedule="warped")
        n_cap = 1 << int(math.ceil(math.log2(max(problem.max_frames, 8))))
        _, (crlb_w, coarse_w, v_w, f_w) = _solve_for_n(result.num_frames, n_cap, warped_problem)
        meets = _meets(crlb_w, coarse_w, f_w, problem, v_w)
        doc["warped"] = {"crlb_mm": crlb_w * 1e3, "coarse_crlb_mm": coarse_w * 1e3, "warp": v_w["warp"],
                         "meets_constraints": meets, "frames": result.num_frames}
        verdict = "beats" if (meets and crlb_w < 0.99 * result.crlb_m) else "does not beat"
        lines.append(f"  warped schedule (f = start + span·u^p, p = {v_w['warp']:.3f}) at the same {result.num_frames} "
                     f"frames: CRLB {crlb_w * 1e3:.4g} mm{'' if meets else ' (violates the range/ripple constraints)'}"
                     f" — {verdict} the uniform one ({result.crlb_m * 1e3:.4g} mm)")
    if validate_trials > 0 and result.feasible:
        mc = monte_carlo(design_point(result, problem), validate_trials, seed=1)
        doc["validation"] = mc
        lines.append(f"  Monte Carlo (simulate + ML reconstruct, {mc['mc_trials']} pixels): precision "
                     f"{mc['mc_precision_mm']:.4g} mm = {mc['mc_precision_mm'] / (result.crlb_m * 1e3):.2f}× CRLB, "
                     f"bias {mc['mc_bias_mm']:+.3g} mm, valid {mc['mc_valid_fraction']:.0%}")
    return {"document": doc, "text": "\n".join(lines)}
