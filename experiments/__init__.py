"""Reproducible studies: each module is a script (`python -m cohflash_experiments.NAME`)
that writes its figures (PNG) and tables (CSV, Markdown) to an output folder."""
