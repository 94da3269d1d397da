"""Reproducible studies: each module is a script (`python -m cohflash_experiments.NAME`)
that writes its figures (PNG) and tables (CSV, Markdown) to an output folder."""

import argparse


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """The study's docstring as written, and each option's default in its help."""


def study_parser(doc: str) -> argparse.ArgumentParser:
    """The argument parser of a study script: its module docstring as the description."""
    return argparse.ArgumentParser(description=doc.strip(), formatter_class=_HelpFormatter)
