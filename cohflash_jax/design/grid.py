"""The CRLB over a grid of design points, vectorised per frame count, and its resumable CSV:
rows are appended atomically after every chunk, so an interrupted sweep resumes without
recomputing finished points; Monte Carlo points run in parallel worker processes."""

from __future__ import annotations

import csv
import functools
import itertools
import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ..fileio import atomic_path
from ..fisher import depth_crlb_m
from .monte_carlo import monte_carlo
from .parameters import PARAMETERS, ambiguity_m, complete_point, design_instrument, to_si

RESULT_COLUMNS = (
    "crlb_mm",
    "crlb_frequency_only_mm",
    "echo_fw",
    "acquisition_s",
    "ambiguity_m",
    "mc_precision_mm",
    "mc_bias_mm",
    "mc_valid_fraction",
    "mc_trials",
)
DEFAULT_CHUNK_POINTS = 32


@functools.partial(jax.jit, static_argnames=("num_steps", "range_falloff"))
def _crlb_points(
    start_hz,
    step_hz,
    distance_m,
    power_w,
    exposure_s,
    beta,
    bias,
    reflectance,
    *,
    num_steps: int,
    range_falloff: bool = True,
):
    """CRLBs (phase-locked, frequency-only) and echo power for a batch of points of one N."""

    def one(s0, df, d, p, te, b, th, rho):
        inst = design_instrument(
            start_hz=s0,
            step_hz=df,
            num_steps=num_steps,
            probe_power_w=p,
            exposure_s=te,
            modulation_index=b,
            bias_rad=th,
        )
        mask = jnp.ones(num_steps)
        crlb = lambda only: depth_crlb_m(
            inst, d, rho, frequency_only=only, range_falloff=range_falloff, frame_weights=mask
        )
        locked, freq_only = crlb(False), crlb(True)
        return locked, freq_only, inst.link.echo_power_w(d, rho, range_falloff)

    return jax.vmap(one)(start_hz, step_hz, distance_m, power_w, exposure_s, beta, bias, reflectance)


def crlb_rows(points: list[dict]) -> list[dict]:
    """CRLB columns for completed points (paper units), vectorised over points with the same N."""
    out = [None] * len(points)
    by_n: dict[tuple, list[int]] = {}
    for i, p in enumerate(points):
        by_n.setdefault((int(p["num_steps"]), bool(p["range_falloff"])), []).append(i)
    for (n, falloff), idx in by_n.items():
        si = [to_si(points[i]) for i in idx]
        col = lambda k, si=si: jnp.asarray([s[k] for s in si], jnp.float64)
        locked, freq_only, echo = _crlb_points(
            col("start_hz"),
            col("step_hz"),
            col("distance_m"),
            col("probe_power_w"),
            col("exposure_s"),
            col("modulation_index"),
            col("bias_rad"),
            col("reflectance"),
            num_steps=n,
            range_falloff=falloff,
        )
        for j, i in enumerate(idx):
            p = points[i]
            out[i] = {
                "crlb_mm": 1e3 * float(locked[j]),
                "crlb_frequency_only_mm": 1e3 * float(freq_only[j]),
                "echo_fw": 1e15 * float(echo[j]),
                "acquisition_s": n / p["frame_rate_hz"],
                "ambiguity_m": ambiguity_m(p),
            }
    return out


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
        raise ValueError(
            f"{path} exists and is not a sweep CSV (no column {', '.join(missing[:3])}"
            f"{' …' if len(missing) > 3 else ''}): choose another --out"
        )
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


def run_sweep(
    axes: list[tuple[str, np.ndarray]],
    out_csv,
    *,
    fixed: dict | None = None,
    mc_points: list[dict] | None = None,
    mc_all: bool = False,
    mc_trials: int = 256,
    workers: int = 1,
    chunk: int = DEFAULT_CHUNK_POINTS,
    progress: bool = True,
    stop_after: int | None = None,
) -> list[dict]:
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
        raise ValueError(
            f"{out_csv} holds a sweep over other parameters ({previous[0].get('swept')}): choose another --out"
        )
    if previous and points:
        derived = {"bandwidth_ghz", "step_mhz"} if {"bandwidth_ghz", "step_mhz", "num_steps"} & set(names) else set()
        for k in PARAMETERS:
            if k in names or k in derived or k not in previous[0]:
                continue
            if not math.isclose(float(previous[0][k]), float(points[0][k]), rel_tol=1e-9):
                raise ValueError(
                    f"{out_csv} was swept with {k} = {previous[0][k]:g}, now {points[0][k]:g}: "
                    "choose another --out (the file's rows are kept)"
                )
    done = {_key(r, names): r for r in previous}
    wanted_mc = {_key({**fixed, **m}, names) for m in (mc_points or [])}

    def needs_mc(p):
        return mc_all or _key(p, names) in wanted_mc

    todo = [
        p for p in points if _key(p, names) not in done or (needs_mc(p) and "mc_trials" not in done[_key(p, names)])
    ]
    if stop_after is not None:
        todo = todo[:stop_after]
    pool = (
        ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
        if workers > 1 and any(needs_mc(p) for p in todo)
        else None
    )
    try:
        with tqdm(
            total=len(points), initial=len(points) - len(todo), desc="sweep", unit="pt", disable=not progress
        ) as bar:
            for start in range(0, len(todo), chunk):
                batch = todo[start : start + chunk]
                rows = [{"swept": swept, **p, **r} for p, r in zip(batch, crlb_rows(batch))]
                mc_jobs = [(i, (p, mc_trials, 0)) for i, p in enumerate(batch) if needs_mc(p)]
                results = (
                    pool.map(_mc_worker, [j for _, j in mc_jobs])
                    if pool is not None
                    else map(_mc_worker, [j for _, j in mc_jobs])
                )
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
