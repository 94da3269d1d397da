"""The hard-case grid (docs/design-reference.md §6) as a table: does a valid pixel keep its
promise where the physics is hardest?

    python -m cohflash_experiments.hard_cases [--out out/hard_cases] [--side 8] [--seed 0]

Each case is a small capture from the project's simulator (sensor noise and sidebands; the
test suite writes the same cases with an independent NumPy writer too, tests/test_hard_cases.py),
reconstructed with the default options. For each: the valid fraction, the standard deviation
of the pulls (error/σ) of valid pixels against the truth folded into the stated window, how
many valid pixels lie beyond 6σ, whether every output is finite, and the statuses. Writes
hard_cases.csv and hard_cases.md.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import numpy as np

import cohflash_jax as cf
from cohflash_experiments import study_parser
from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
from cohflash_jax.fileio import write_csv
from cohflash_jax.radiometry import PAPER_PROBE_POWER_W, LinkBudget
from cohflash_jax.reconstruct import ReconstructOptions, build_plan, reconstruct_array
from cohflash_jax.status import Status

NOISE = ("shot_noise", "read_noise", "dark_current", "quantization", "sidebands")
PAPER_STEP_HZ = 1.97e6
J1_FIRST_ZERO = 3.8317


@dataclasses.dataclass(frozen=True)
class HardCase:
    """One case: the sweep (`frames` uniform steps over `band_hz`, the paper's 0.1–6 GHz by
    default, or a named `schedule`), the modulator (β, θ_b), the target's depth as a fraction of the
    unambiguous window of the fundamental, c/(4Δf) (or in metres, `depth_m`), the echo's
    power relative to the paper's (`echo_scale`; 0: pure noise), a common carrier random walk
    of about `drift_rad` over the sweep, and whether bad pixels are written in (`corrupt`)."""

    name: str
    what: str
    frames: int = 3000
    schedule: str = "uniform"
    band_hz: tuple[float, float] = (0.1e9, 6e9)
    beta: float = 2.0
    bias_rad: float = math.pi / 4
    window_fraction: float | None = None
    depth_m: float | None = 30.5
    echo_scale: float = 1.0
    drift_rad: float = 0.0
    corrupt: bool = False

    def frequencies_hz(self) -> np.ndarray:
        """The sweep: uniform over the band in `frames` steps, or a seeded random schedule."""
        low, high = self.band_hz
        if self.schedule == "random":
            rng = np.random.default_rng(1900)
            f = np.sort(rng.uniform(low, high, self.frames))
            f[0], f[-1] = low, high
            return f
        return low + (high - low) / (self.frames - 1) * np.arange(self.frames)

    def fundamental_window_m(self) -> float:
        f = self.frequencies_hz()
        return C / (4 * (f[1] - f[0])) if self.schedule == "uniform" else C / (4 * np.median(np.diff(f)))

    def truth_m(self) -> float:
        return self.depth_m if self.window_fraction is None else self.window_fraction * self.fundamental_window_m()

    def probe_power_w(self) -> float:
        """Scaled so that shorter sweeps keep the paper's total SNR (power ∝ 3000/N)."""
        return PAPER_PROBE_POWER_W * self.echo_scale * 3000 / self.frames


def _bins(n: int, k: float) -> float:
    """A depth at `k` DFT bins of an n-frame sweep over the paper's band, as a window fraction."""
    return 2 * k / n


CASES = (
    HardCase("bin centre", "depth at a DFT bin centre", window_fraction=_bins(3000, 1202.5)),
    HardCase("bin edge", "depth on a DFT bin edge", window_fraction=_bins(3000, 1202.0)),
    HardCase("near zero", "3 bins from DC: the fundamental merges with DC", window_fraction=_bins(3000, 3.0)),
    HardCase("ambiguity limit", "1 mm inside c/(4Δf)", depth_m=C / (4 * PAPER_STEP_HZ) - 1e-3),
    HardCase("2nd harmonic alias", "f = 1/3 cycle per frame", window_fraction=2 / 3),
    HardCase("3rd harmonic alias", "f = 1/4 cycle per frame", window_fraction=1 / 2),
    HardCase("threshold SNR", "echo 11.5 dB below the paper's (SNR ≈ 15.5 dB)", echo_scale=0.07),
    HardCase("below threshold", "echo 17 dB below the paper's (SNR ≈ 10 dB)", echo_scale=0.02),
    HardCase("pure noise", "no echo", echo_scale=0.0),
    HardCase("θb = 0", "odd orders vanish: the tone at 2f", bias_rad=0.0, echo_scale=30.0, depth_m=12.0),
    HardCase("θb = π/2", "even orders vanish (w0 = 0)", bias_rad=math.pi / 2),
    HardCase(
        "x at J1 zero",
        "fundamental starved: orders 2, 3 alike",
        frames=350,
        beta=2 * J1_FIRST_ZERO,
        depth_m=3.0,
        echo_scale=3.0,
    ),
    HardCase("x → 0", "β = 0.02: almost no signal", beta=0.02),
    HardCase("10 Hz mode", "35 frames", frames=35, window_fraction=0.37),
    HardCase("long sweep", "30 000 frames", frames=30000, depth_m=123.4),
    HardCase("30 GHz, 240 m", "24–30 GHz, tone phase ~3·10⁵ rad", band_hz=(24e9, 30e9), depth_m=240.0),
    HardCase("random schedule", "300 random steps", frames=300, schedule="random", depth_m=11.3),
    HardCase("carrier drift", "≈3 rad random walk of the carrier", drift_rad=3.0),
    HardCase("bad pixels", "saturated, dead, NaN, constant and hot pixels", corrupt=True),
)


def instrument_for(case: HardCase) -> cf.Instrument:
    """The instrument of a case: the paper's, with the case's sweep, modulator and power."""
    base = cf.Instrument.paper(3000)
    return dataclasses.replace(
        base,
        sweep=cf.FrequencySweep(case.frequencies_hz()),
        modulator=cf.MZM(case.beta, case.bias_rad, max_order=7),
        link=LinkBudget(probe_power_w=max(case.probe_power_w(), 1e-30)),
    )


def corrupt_frames(frames: np.ndarray, adc_max_dn: float) -> np.ndarray:
    """Pixel (0,0) saturated in one frame, (0,1) dead, (0,2) NaN in one frame, (0,3) constant
    per CCD, (1,0) hot (+3000 DN): float32 frames (4, N, H, W), a copy."""
    out = np.array(frames, np.float32)
    out[1, 5, 0, 0] = adc_max_dn
    out[:, :, 0, 1] = out[:, :1, 0, 1]
    out[2, 7, 0, 2] = np.nan
    out[:, :, 0, 3] = np.arange(4, dtype=np.float32)[:, None] + 400
    out[:, :, 1, 0] += 3000
    return out


def simulate_case(case: HardCase, side: int, seed: int = 0) -> np.ndarray:
    """Frames (4, N, side, side) of a case from the project's simulator (turbulence for drift)."""
    inst = instrument_for(case)
    effects = NOISE + (("turbulence",) if case.drift_rad else ())
    scene = cf.from_arrays(np.full((side, side), case.truth_m()), np.full((side, side), 0.5), effects=effects)
    if case.drift_rad:
        settings = dataclasses.replace(
            scene.settings, turbulence_rad_per_sqrt_frame=case.drift_rad / math.sqrt(case.frames)
        )
        scene = dataclasses.replace(scene, settings=settings)
    frames = np.asarray(cf.simulate(scene, inst, side, side, jax.random.key(seed)))
    if case.corrupt:
        return corrupt_frames(frames, float(inst.sensor.adc_max_dn))
    return np.clip(np.rint(frames), 0, inst.sensor.adc_max_dn).astype(np.uint16)  # as a capture stores them


def saturation_dn(case: HardCase) -> float:
    """The ADC level a case's reconstruction checks, as a capture's `adc_bits` gives it."""
    return float(instrument_for(case).sensor.adc_max_dn)


def fold_into_window(depth_m: float, window_m: tuple[float, float]) -> float:
    """A true depth as the reconstruction states it: folded, with the real tone's mirror, into
    the unambiguous window [lo, hi) (period 2·(hi − lo))."""
    lo, hi = window_m
    width = hi - lo
    t = (depth_m - lo) % (2 * width)
    return lo + (2 * width - t if t >= width else t)


def assess(outputs: dict, truth_m: float, window_m: tuple[float, float]) -> dict:
    """The grid's row for one reconstruction (`outputs` as `reconstruct_array` returns them)."""
    valid = np.asarray(outputs["valid"]).astype(bool)
    truth = fold_into_window(truth_m, window_m)
    pulls = (np.asarray(outputs["depth_m"])[valid] - truth) / np.asarray(outputs["sigma_m"])[valid]
    status = np.asarray(outputs["fit_status"]).astype(int).ravel()
    finite = all(bool(np.all(np.isfinite(np.asarray(v, np.float64)))) for v in outputs.values())
    counts = np.bincount(status, minlength=len(Status))
    return {
        "valid_percent": 100 * float(valid.mean()),
        "pull_std": float(np.std(pulls)) if pulls.size > 1 else float("nan"),
        "beyond_6_sigma": int(np.sum(np.abs(pulls) > 6)),
        "finite": finite,
        "statuses": "; ".join(f"{Status(k).message.split(' ')[0]} {c}" for k, c in enumerate(counts) if c),
    }


def stated_window_m(case: HardCase, options: ReconstructOptions) -> tuple[float, float]:
    """The window a reconstruction of the case states (its depth file's `depth_window_m`)."""
    return build_plan(instrument_for(case), options).policy.valid_window_m


def run(out: Path, side: int, seed: int) -> list[dict]:
    out.mkdir(parents=True, exist_ok=True)
    options = ReconstructOptions(progress=False)
    rows = []
    for case in CASES:
        inst = instrument_for(case)
        result = reconstruct_array(simulate_case(case, side, seed), inst, options, saturation_dn=saturation_dn(case))
        row = {"case": case.name, "what": case.what, "truth_m": case.truth_m()}
        row.update(assess(result, case.truth_m(), stated_window_m(case, options)))
        rows.append(row)
        print(
            f"{case.name:20s} valid {row['valid_percent']:5.1f} %  pull std {row['pull_std']:.2f}  "
            f"beyond 6σ {row['beyond_6_sigma']}  finite {row['finite']}  {row['statuses']}"
        )
    write_csv(out / "hard_cases.csv", rows)
    lines = [
        "| case | what | valid % | pull std | beyond 6σ | finite | statuses |",
        "|---|---|---:|---:|---:|---|---|",
    ]
    lines += [
        f"| {r['case']} | {r['what']} | {r['valid_percent']:.1f} | {r['pull_std']:.2f} | {r['beyond_6_sigma']} | "
        f"{r['finite']} | {r['statuses']} |"
        for r in rows
    ]
    (out / "hard_cases.md").write_text("\n".join(lines) + "\n")
    return rows


def main():
    p = study_parser(__doc__)
    p.add_argument("--out", default="out/hard_cases", help="output folder")
    p.add_argument("--side", type=int, default=8, help="pixels per side of each capture")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    args = p.parse_args()
    run(Path(args.out), args.side, args.seed)


if __name__ == "__main__":
    main()
