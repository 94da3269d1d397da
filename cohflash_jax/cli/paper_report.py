"""`cohflash report`: the accuracy–time study and the paper's figures in one report
(`cohflash_experiments.report`)."""

from __future__ import annotations


def add_parser(sub) -> None:
    p = sub.add_parser(
        "report",
        help="what accuracy costs in time, and the paper's Figs. 2, 3, 4a–c and 4f reproduced → DIR/report.md",
        description="Simulate the paper's scenes and the estimators' study, and write report.md with its PNG "
        "figures and CSV tables: every estimator's precision, reliability and time; precision against "
        "acquisition time; the paper's figures; the paper's numbers beside ours with the reasons they "
        "differ; the provenance. The full run takes tens of minutes; --quick runs every section on small "
        "captures in under a minute.",
    )
    from cohflash_experiments.report import add_arguments

    add_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from cohflash_experiments.report import run as write_report

    write_report(args.out, args.quick, args.seed)
    return 0
