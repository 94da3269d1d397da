"""`cohflash report --quick`: every section runs, every figure and table is written, every
number in the report's tables is finite, and the paper's numbers stand beside ours."""

import csv
import math

import pytest

from cohflash_jax.cli import main


@pytest.mark.runs_long
def test_quick_report_writes_every_figure_and_table_with_finite_numbers(tmp_path):
    out = tmp_path / "report"
    assert main(["report", "--out", str(out), "--quick"]) == 0
    for name in (
        "report.md",
        "fig2_staircase.png",
        "fig3_traffic.png",
        "fig4abc_planar.png",
        "fig4f_acquisition.png",
        "accuracy_time/pareto.png",
    ):
        assert (out / name).stat().st_size > 1000, name
    for name in ("paper_numbers.csv", "fig4abc_planar.csv", "fig4f_acquisition.csv"):
        with open(out / name) as f:
            rows = list(csv.DictReader(f))
        assert rows, name
        for row in rows:
            for value in row.values():
                try:
                    number = float(value)
                except ValueError:
                    continue
                assert math.isfinite(number), (name, row)
    numbers = {row["quantity"]: float(row["value"]) for row in csv.DictReader(open(out / "paper_numbers.csv"))}
    # the staircase's 5 mm steps are resolved, and the spectrum's two peaks are where the physics puts them
    assert abs(numbers["mean_step_mm"] - 5.0) < 1.0 and numbers["steps_resolved"] >= 5
    assert abs(numbers["fundamental_hz"] - numbers["predicted_fundamental_hz"]) < 0.1
    assert abs(numbers["second_peak_hz"] - numbers["predicted_second_harmonic_hz"]) < 0.1
    text = (out / "report.md").read_text()
    for paper_value in ("56.2", "37.4", "0.47 mm", "1.33 mm", "0.35 mm", "0.37 mm"):
        assert paper_value in text, paper_value
    assert "JAX device" in text and "seed 0" in text
