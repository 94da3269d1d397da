"""`cohflash sweep`: depth precision (CRLB, and Monte Carlo) over a grid of design parameters
→ CSV (+ figure); resumable."""

from __future__ import annotations

import functools

import numpy as np

from ..design.grid import DEFAULT_CHUNK_POINTS
from ..design.parameters import PARAMETERS
from .common import WORKERS, HelpFormatter, add_quiet, add_scheduler_options, number_in

DEFAULT_MC_TRIALS = 256


def add_parser(sub) -> None:
    sw = sub.add_parser(
        "sweep",
        help="depth precision (CRLB from the autodiff Fisher information, and Monte "
        "Carlo) over a grid of design parameters → CSV (+ figure); resumable",
        formatter_class=HelpFormatter,
    )
    sw.add_argument(
        "--axis",
        action="append",
        required=True,
        metavar="NAME=START:STOP:COUNT[:log] | NAME=V1,V2,…",
        help="a swept parameter (repeat for a grid): " + ", ".join(PARAMETERS),
    )
    sw.add_argument("--set", action="append", metavar="NAME=VALUE[,…]", help="fixed parameters (default: the paper's)")
    sw.add_argument("--mc", action="append", metavar="NAME=VALUE,…", help="grid point that also gets a Monte Carlo run")
    sw.add_argument("--mc-all", action="store_true", help="Monte Carlo at every grid point")
    sw.add_argument(
        "--mc-trials",
        type=number_in(1, 10**8, "Monte Carlo trials", False, True),
        default=DEFAULT_MC_TRIALS,
        help="pixels (independent trials) per Monte Carlo point",
    )
    sw.add_argument(
        "--workers",
        type=WORKERS,
        default=None,
        help="processes for Monte Carlo points (the CRLB grid is vectorised in one process) (default: 1); with "
        "--scheduler threads or processes, the local Dask workers (default: one per core)",
    )
    add_scheduler_options(sw)
    sw.add_argument(
        "--out",
        required=True,
        help="CSV; an existing file is resumed (finished points are kept); "
        f"rows are written after every {DEFAULT_CHUNK_POINTS} points",
    )
    sw.add_argument("--plot", help="figure (PNG): heat map with contours, or precision against the axis")
    add_quiet(sw)
    sw.set_defaults(func=run)


def assignments(items) -> dict:
    """NAME=VALUE[,NAME=VALUE…] items → {name: value} (paper units), names and numbers checked."""
    out = {}
    for item in items or []:
        for part in item.split(","):
            if "=" not in part:
                raise ValueError(f"expected NAME=VALUE, got {part!r}")
            k, v = (t.strip() for t in part.split("=", 1))
            if k not in PARAMETERS:
                raise ValueError(f"unknown parameter {k!r}; known: {', '.join(PARAMETERS)}")
            try:
                out[k] = float(v)
            except ValueError:
                raise ValueError(f"{k}: {v!r} is not a number") from None
    return out


def run(args) -> int:
    from ..design import parse_axis, plot_sweep, run_sweep
    from ..design.plots import beyond_ambiguity

    axes = [parse_axis(a) for a in args.axis]
    mc_points = [assignments([m]) for m in args.mc or []]
    sweep = functools.partial(
        run_sweep,
        axes,
        args.out,
        fixed=assignments(args.set),
        mc_points=mc_points,
        mc_all=args.mc_all,
        mc_trials=args.mc_trials,
        progress=not args.quiet,
    )
    if args.scheduler is None:
        rows = sweep(workers=args.workers or 1)
    else:
        from ..dask_cluster import dask_client, describe_client

        with dask_client(args.scheduler, args.workers) as client:
            print(f"Monte Carlo points on {describe_client(client)}")
            rows = sweep(client=client)
    names = [n for n, _ in axes]
    if args.plot:
        plot_sweep(rows, names, args.plot)
    crlb = np.array([float(r["crlb_mm"]) for r in rows])
    print(f"wrote {args.out}: {len(rows)} points over {', '.join(names)}; CRLB {crlb.min():.4g} … {crlb.max():.4g} mm")
    beyond = beyond_ambiguity(rows)
    if beyond.any():
        print(
            f"  {int(beyond.sum())} of {len(rows)} points put the target beyond the unambiguous range "
            "(column beyond_ambiguity): the instrument reads their depth folded into it"
        )
    for r in rows:
        if r.get("mc_trials") not in (None, ""):
            where = ", ".join(f"{n}={float(r[n]):g}" for n in names)
            print(
                f"  Monte Carlo at {where}: {float(r['mc_precision_mm']):.4g} mm over {int(r['mc_trials'])} pixels "
                f"(CRLB {float(r['crlb_mm']):.4g} mm, bias {float(r['mc_bias_mm']):+.3g} mm, "
                f"valid {float(r['mc_valid_fraction']):.0%})" + (f"; {r['mc_note']}" if r.get("mc_note") else "")
            )
    return 0
