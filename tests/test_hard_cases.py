"""The hard-case grid of docs/design-reference.md §6 as tests: each case on captures from the
project's simulator and from the independent NumPy writer (`independent_writer`), reconstructed
with the default options. Every output is finite, and no valid pixel lies beyond 6σ of the truth
folded into the stated window. The table of the same grid: `python -m
cohflash_experiments.hard_cases` (docs/physics.md)."""

import math
import zlib

import h5py
import numpy as np
import pytest

from cohflash_experiments.hard_cases import (
    CASES,
    HardCase,
    assess,
    instrument_for,
    saturation_dn,
    simulate_case,
    stated_window_m,
)
from cohflash_jax.cli import main
from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array

from .independent_writer import Writer, random_walk_rad

SIDE = 4
OPTIONS = ReconstructOptions(progress=False)


def _spoil(frames: np.ndarray) -> np.ndarray:
    """Bad pixels written independently: (0,0) saturated in one frame, (0,1) dead, (0,2) NaN in
    one frame, (0,3) constant per CCD, (1,0) hot."""
    out = frames.astype(np.float32)
    out[1, 5, 0, 0] = 16383
    out[:, :, 0, 1] = out[:, :1, 0, 1]
    out[2, 7, 0, 2] = np.nan
    out[:, :, 0, 3] = 400 + np.arange(4, dtype=np.float32)[:, None]
    out[:, :, 1, 0] += 3000
    return out


def _independent(case: HardCase, tmp_path) -> dict:
    # a seed of the case's name that every process computes alike (Python's str hash is
    # salted per process, so the noise, and the statistics checked, changed from run to run)
    rng = np.random.default_rng(zlib.crc32(case.name.encode()))
    f = case.frequencies_hz()
    writer = Writer(
        frequencies_hz=f,
        x=case.beta / 2,
        bias_rad=case.bias_rad,
        echo_scale=case.echo_scale * 3000 / f.size,
        drift_rad=random_walk_rad(f.size, case.drift_rad, rng) if case.drift_rad else None,
    )
    cap, out = tmp_path / "capture.h5", tmp_path / "depth.h5"
    writer.write(cap, np.full((SIDE, SIDE), case.truth_m()), rng, alter=_spoil if case.corrupt else None)
    assert main(["reconstruct", str(cap), "--out", str(out), "--quiet"]) == 0
    with h5py.File(out) as fh:
        result = {k: fh[k][()] for k in fh if fh[k].ndim == 2}  # every per-pixel output
        window = tuple(fh.attrs["depth_window_m"])
    return assess(result, case.truth_m(), window)


def _simulated(case: HardCase) -> dict:
    inst = instrument_for(case)
    out = reconstruct_array(simulate_case(case, SIDE), inst, OPTIONS, saturation_dn=saturation_dn(case))
    return assess(out, case.truth_m(), stated_window_m(case, OPTIONS))


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_hard_case_keeps_the_promise_of_a_valid_pixel(case, tmp_path):
    """Both writers in one test: the same uint16 frames' shapes and plan, so the independent
    capture reuses the programs the simulated one compiled."""
    for writer in ("simulator", "independent"):
        row = _simulated(case) if writer == "simulator" else _independent(case, tmp_path)
        row["writer"] = writer
        _check(case, row)


def _check(case: HardCase, row: dict) -> None:
    assert row["finite"], row
    assert row["beyond_6_sigma"] == 0, row
    if case.echo_scale == 0 or case.beta < 0.1:  # no signal: nothing may be valid
        assert row["valid_percent"] == 0, row
    answered = ("bin centre", "bin edge", "θb = π/2", "carrier drift", "random schedule", "x at J1 zero")
    if case.name in answered + ("long sweep", "30 GHz, 240 m"):
        assert row["valid_percent"] > 80, row  # cases the instrument should answer
    if not math.isnan(row["pull_std"]) and row["valid_percent"] >= 50:
        assert row["pull_std"] < 1.6, row
