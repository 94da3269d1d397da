"""The CRLB over a grid of design points, vectorised per frame count, and its resumable CSV:
rows are appended atomically after every chunk, so an interrupted sweep resumes without
recomputing finished points; Monte Carlo points run in parallel worker processes."""

from __future__ import annotations

import csv
import functools
import itertools
import math
import multiprocessing
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..fileio import atomic_path
from ..fisher import depth_crlb_m
from ..progress import progress_bar
from ..tiling import power_of_two_bucket
from .monte_carlo import monte_carlo
from .parameters import PARAMETERS, ambiguity_m, complete_point, design_instrument, to_si

RESULT_COLUMNS = (
    "crlb_mm",
    "crlb_frequency_only_mm",
    "echo_fw",
    "acquisition_s",
    "ambiguity_m",
    "beyond_ambiguity",
    "mc_precision_mm",
    "mc_bias_mm",
    "mc_valid_fraction",
    "mc_trials",
    "mc_truth_m",
    "mc_note",
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


# A batch of points of one N is padded to a power of two of at least this many points: a
# sweep's chunks group their points by N in varying numbers, and each number was a program
MIN_POINT_BUCKET = 8


def point_bucket(count: int) -> int:
    """The padded batch of `count` points of one N (`_crlb_points`): the next power of two,
    at least `MIN_POINT_BUCKET`."""
    return power_of_two_bucket(count, MIN_POINT_BUCKET)


def crlb_rows(points: list[dict]) -> list[dict]:
    """CRLB columns for completed points (paper units), vectorised over points with the same N."""
    out = [None] * len(points)
    by_n: dict[tuple, list[int]] = {}
    for i, p in enumerate(points):
        by_n.setdefault((int(p["num_steps"]), bool(p["range_falloff"])), []).append(i)
    for (n, falloff), idx in by_n.items():
        si = [to_si(points[i]) for i in idx]
        si += si[:1] * (point_bucket(len(si)) - len(si))  # the first point again: finite, discarded
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
                # the instrument measures such a target folded into [0, ambiguity): the CRLB
                # holds for the folded depth, and the Monte Carlo compares against it
                "beyond_ambiguity": float(p["distance_m"] >= ambiguity_m(p)),  # 1.0 or 0.0, as read back
            }
    return out


# A Monte Carlo point's row is written at most this often (and after every chunk)
CHECKPOINT_SECONDS = 2.0


def die_with_parent() -> None:
    """A worker's initializer: on Linux the kernel kills it when its parent dies (a SIGKILLed
    sweep left its workers running, holding gigabytes); elsewhere nothing."""
    import ctypes
    import signal
    import sys

    if sys.platform.startswith("linux"):
        pr_set_pdeathsig = 1
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle: it terminates us


def grid_points(mc_points: list[dict], axes) -> list[dict]:
    """`--mc` points checked against the grid: every axis named, nothing else, each value one
    the axis holds (snapped to it) → the points; ValueError naming what is wrong otherwise."""
    names = [n for n, _ in axes]
    out = []
    for m in mc_points:
        extra = sorted(set(m) - set(names))
        if extra:
            raise ValueError(f"--mc names {', '.join(extra)}, not a swept axis (axes: {', '.join(names)})")
        missing = [n for n in names if n not in m]
        if missing:
            raise ValueError(f"--mc must give a value for every axis; missing {', '.join(missing)}")
        point = {}
        for n, values in axes:
            values = np.asarray(values, float)
            hit = np.isclose(values, m[n], rtol=1e-9, atol=0)
            if not hit.any():
                nearest = values[np.argmin(np.abs(values - m[n]))]
                raise ValueError(f"--mc {n}={m[n]:g} is not on the grid (nearest value on the axis: {nearest:g})")
            point[n] = float(values[hit.argmax()])
        out.append(point)
    return out


def monte_carlo_job(args):
    """One Monte Carlo point, (point, trials, seed) → its result columns (a worker's task)."""
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
    client=None,
) -> list[dict]:
    """Evaluate the grid (cartesian product of `axes`, other parameters from `fixed` or the
    paper), append rows to `out_csv` after each chunk (atomically), skip points already there.
    `mc_points`: partial points (axis values) that also get a Monte Carlo run; `mc_all`: all.
    `stop_after`: stop after that many new points (what an interrupt does, for tests).
    `client`: a Dask client whose workers run the Monte Carlo points (`workers` is then unused);
    the rows are the same as in one process (each point's seed is its own)."""
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
    wanted_mc = {_key({**fixed, **m}, names) for m in grid_points(mc_points or [], axes)}
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
    on_grid = {_key(p, names) for p in points}
    # finished rows of other axis values are kept (after the grid's), never dropped
    kept = [r for r in previous if _key(r, names) not in on_grid]

    def needs_mc(p):
        return mc_all or _key(p, names) in wanted_mc

    def finished(p):
        row = done.get(_key(p, names))
        return row is not None and not (needs_mc(p) and row.get("mc_trials") in (None, ""))

    todo = [p for p in points if not finished(p)]
    if stop_after is not None:
        todo = todo[:stop_after]
    last_write = [0.0]

    def checkpoint(force: bool):
        """The CSV rewritten with every finished row: after each chunk, and after a Monte Carlo
        point at most every `CHECKPOINT_SECONDS` (so an interrupt loses little)."""
        if force or time.monotonic() - last_write[0] > CHECKPOINT_SECONDS:
            ordered = [done[_key(p, names)] for p in points if _key(p, names) in done]
            _write_rows(out_csv, ordered + kept, columns)
            last_write[0] = time.monotonic()

    pool = (
        multiprocessing.get_context("spawn").Pool(workers, initializer=die_with_parent)
        if workers > 1 and client is None and any(needs_mc(p) for p in todo)
        else None
    )
    try:
        with progress_bar(
            total=len(points), initial=len(points) - len(todo), desc="sweep", unit="pt", disable=not progress
        ) as bar:
            for start in range(0, len(todo), chunk):
                batch = todo[start : start + chunk]
                rows = [{"swept": swept, **p, **r} for p, r in zip(batch, crlb_rows(batch))]
                for r in rows:  # a point's CRLB row stands until its Monte Carlo replaces it
                    done.setdefault(_key(r, names), r)
                mc_jobs = [(i, (p, mc_trials, 0)) for i, p in enumerate(batch) if needs_mc(p)]
                jobs = [j for _, j in mc_jobs]
                if client is not None:
                    futures = client.map(monte_carlo_job, jobs, pure=False, retries=1)
                    results = (future.result() for future in futures)
                elif pool is not None:
                    results = pool.imap(monte_carlo_job, jobs)
                else:
                    results = map(monte_carlo_job, jobs)
                for (i, _), res in zip(mc_jobs, results):
                    rows[i].update(res)
                    done[_key(rows[i], names)] = rows[i]
                    checkpoint(force=False)
                for r in rows:
                    done[_key(r, names)] = r
                checkpoint(force=True)
                bar.update(len(batch))
    except KeyboardInterrupt:
        checkpoint(force=True)  # the points finished since the last write
        raise
    finally:
        if pool is not None:
            pool.terminate()  # at once: an interrupt must not wait for running points
            pool.join()
    return [done[_key(p, names)] for p in points if _key(p, names) in done] + kept
