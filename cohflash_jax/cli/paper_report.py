"""`cohflash report`: the accuracy–time study and the paper's figures in one report
(`cohflash_experiments.report`, imported only when the command runs: it pulls in emcee and
SciPy, half a second that no other command should pay)."""

from __future__ import annotations

from pathlib import Path

from .common import HelpFormatter


def add_arguments(p) -> None:
    """The report's options (shared with `python -m cohflash_experiments.report`)."""
    p.add_argument("--out", type=Path, default=Path("report"), help="output folder")
    p.add_argument("--quick", action="store_true", help="small captures: every section, in about a minute")
    p.add_argument("--seed", type=int, default=0, help="seed of every simulated capture")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "report",
        help="what accuracy costs in time, and the paper's Figs. 2, 3, 4a–c and 4f reproduced → DIR/report.md",
        description="Simulate the paper's scenes and the estimators' study, and write report.md with its PNG "
        "figures and CSV tables: every estimator's precision, reliability and time; precision against "
        "acquisition time; the paper's figures; the paper's numbers beside ours with the reasons they "
        "differ; the provenance. The full run takes tens of minutes; --quick runs every section on small "
        "captures in about a minute.",
        formatter_class=HelpFormatter,
    )
    add_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from cohflash_experiments.report import run as write_report

    write_report(args.out, args.quick, args.seed)
    return 0
