"""Design sweeps (#5): autodiff Fisher against closed forms, CRLB scaling laws, the gradient
design's constraints and optimum against exhaustive search, resumable sweeps."""

import csv
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax import design
from cohflash_jax.cli import main
from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
from cohflash_jax.fisher import depth_crlb_m

from .closed_forms import closed_form_noise_and_amplitude, crlb_frequency_only_m, crlb_phase_locked_m
from .jax_events import traces_counted

# its module fixtures are costly: every test of the module on one xdist worker (make test: --dist loadgroup)
pytestmark = pytest.mark.xdist_group("test_design")


def test_autodiff_fisher_equals_closed_form(paper_instrument):
    """Single tone (no sidebands), paper link budget: the 4-port autodiff Fisher gives the
    closed-form phase-locked and frequency-only bounds of a real tone in white noise."""
    f = paper_instrument.sweep.frequencies_hz
    sigma, amp = closed_form_noise_and_amplitude(paper_instrument, 0.5)
    locked = float(depth_crlb_m(paper_instrument, 30.5, 0.5, range_falloff=False))
    freq_only = float(depth_crlb_m(paper_instrument, 30.5, 0.5, frequency_only=True, range_falloff=False))
    assert locked == pytest.approx(crlb_phase_locked_m(f, amp, sigma), rel=2e-3)
    assert freq_only == pytest.approx(
        float(crlb_frequency_only_m(f.size, paper_instrument.sweep.step_hz, amp, sigma)), rel=2e-3
    )
    assert 1.9 < freq_only / locked < 2.2  # docs/design-reference.md §1: about 2 for 0.1–6 GHz


def _crlb(**point):
    full = design.complete_point(point)
    return design.crlb_rows([full])[0]


def test_a_bound_on_the_host_is_one_program_per_sweep_length():
    """`depth_crlb_m` called outside a transformation: a new sweep length traces one program (op
    by op, the forward model's Jacobian traced and compiled ~100), an instrument of other numbers
    (power, β, roll-off, target) none, and its bound is the one traced inline in a caller's
    program (the design's)."""
    first = cf.Instrument.paper(47)
    with traces_counted() as traced:
        depth_crlb_m(first, 30.5, 0.5).block_until_ready()
    assert len(traced) <= 2
    other = first.replace(
        modulator=cf.MZM(modulation_index=2.5, rolloff_3db_hz=4e9),
        link=cf.LinkBudget(probe_power_w=0.03),
    )
    with traces_counted() as traced:
        on_host = float(depth_crlb_m(other, 12.0, 0.3))
    assert not traced
    inline = float(jax.jit(lambda inst, d, rho: depth_crlb_m(inst, d, rho))(other, 12.0, 0.3))
    assert on_host == pytest.approx(inline, rel=1e-12) and on_host != pytest.approx(
        float(depth_crlb_m(first, 30.5, 0.5))
    )


def test_crlb_scaling_laws():
    """From f = 0: doubling the bandwidth halves both bounds (1/B, to 1 %: the tone also moves in
    cycles per frame, which shifts its coupling to the nuisances slightly); doubling N at fixed B
    divides them by √2 (1/√N); four times the echo power halves them (shot noise of the
    reference dominates, so SNR ∝ echo power)."""
    base = dict(start_ghz=0.0, num_steps=512, distance_m=30.5)
    a = _crlb(bandwidth_ghz=3.0, **base)
    b = _crlb(bandwidth_ghz=6.0, **base)
    assert b["crlb_mm"] / a["crlb_mm"] == pytest.approx(0.5, rel=1e-2)
    assert b["crlb_frequency_only_mm"] / a["crlb_frequency_only_mm"] == pytest.approx(0.5, rel=1e-2)
    n2 = _crlb(bandwidth_ghz=3.0, **{**base, "num_steps": 1024})
    assert n2["crlb_mm"] / a["crlb_mm"] == pytest.approx(1 / np.sqrt(2), rel=1e-2)
    p4 = _crlb(bandwidth_ghz=3.0, probe_power_mw=4 * 15.86, **base)
    assert p4["crlb_mm"] / a["crlb_mm"] == pytest.approx(0.5, rel=1e-2)
    far = _crlb(bandwidth_ghz=3.0, **{**base, "distance_m": 61.0})  # 1/d² falloff: SNR/4
    assert far["crlb_mm"] / a["crlb_mm"] == pytest.approx(2.0, rel=2e-2)


def test_a_sweeps_batches_of_any_size_run_one_bound_program_per_frame_count():
    """`crlb_rows` pads the points of one N to their `point_bucket` (the first point again): a
    sweep's chunks group their points by N in varying numbers, and batches of one, three and
    five points of one N trace one program between them; each row is the point's row alone."""
    targets = ((3.0, 30.5), (4.0, 12.0), (5.0, 20.0), (6.0, 7.0), (2.0, 40.0))
    points = [
        design.complete_point(dict(start_ghz=0.0, num_steps=384, bandwidth_ghz=b, distance_m=d)) for b, d in targets
    ]
    alone = [design.crlb_rows([p])[0] for p in points]
    with traces_counted() as traced:
        three, five = design.crlb_rows(points[:3]), design.crlb_rows(points)
    assert not traced, "a batch of another size traced a program of its own"
    assert three == alone[:3] and five == alone


def test_a_new_target_power_or_frame_rate_runs_the_compiled_design_programs():
    """The design programs take a problem's numbers as values (`DesignProblem.as_values`): a
    user trying another target, power, frame rate or most frames waits for no compile (only the
    schedule and the frames the programs hold make a program), and the answer is the new
    problem's."""
    from cohflash_jax.runtime import EXECUTABLES

    assert EXECUTABLES.folder is not None  # the tests' cache counts every program made
    first = design.DesignProblem(target_precision_m=1e-3, max_range_m=38.0, max_frequency_hz=6e9, max_frames=64)
    cap = design.frame_cap(first, 24)
    _, ev_first = design.solve_for_n(24, cap, first)
    made = (EXECUTABLES.loaded, EXECUTABLES.compiled)
    second = dataclasses.replace(
        first, target_precision_m=0.5e-3, max_power_w=8e-3, frame_rate_hz=100.0, max_frames=128
    )
    assert design.frame_cap(second, 24) == cap
    _, ev_second = design.solve_for_n(24, cap, second)
    assert (EXECUTABLES.loaded, EXECUTABLES.compiled) == made
    assert ev_second.variables["probe_power_w"] <= second.max_power_w < ev_first.variables["probe_power_w"]
    assert ev_second.variables["exposure_s"] <= 1 / second.frame_rate_hz
    assert ev_second.crlb_m > ev_first.crlb_m  # half the power


def test_carry_over_keeps_a_designs_start_and_step_at_other_frame_counts():
    """The search's warm starts: the design of one frame count at another keeps its start
    frequency, step and other variables (the same z would scale them to the frames)."""
    from cohflash_jax.design.problem import carry_over, decode

    problem = design.DesignProblem(target_precision_m=1e-3, max_range_m=38.0, max_frequency_hz=6e9, max_frames=256)
    z = np.array([0.5, -0.3, 0.2, 0.1, 1.0, 2.0, 0.0])
    was = decode(z, 100, problem)
    for frames in (60, 100, 180):
        now = decode(carry_over(z, 100, frames, problem), frames, problem)
        for name in ("step_hz", "start_hz", "modulation_index", "bias_rad", "exposure_s", "probe_power_w"):
            assert float(now[name]) == pytest.approx(float(was[name]), rel=1e-9), (frames, name)


@pytest.fixture(scope="module")
def small_design():
    problem = design.DesignProblem(
        target_precision_m=1.0e-3, max_range_m=38.0, max_frequency_hz=6e9, frame_rate_hz=150.0, max_frames=256
    )
    return problem, design.optimise_design(problem, progress=False)


def test_design_meets_constraints_and_is_optimal(small_design):
    """Every constraint holds at the optimum; one frame fewer cannot meet them; and the
    modulation index and bias it chose match an exhaustive grid search of the bound over the
    same feasible set (the sign SNR at the optimiser's margin, SIGN_SNR_MARGIN × the limit)."""
    problem, result = small_design
    assert result.feasible, result.note
    f, v = result.frequencies_hz, result.variables
    assert result.crlb_m <= problem.target_precision_m
    assert np.max(np.diff(f)) <= C / (4 * problem.max_range_m) * (1 + 1e-9)
    assert f[-1] <= problem.max_frequency_hz * (1 + 1e-12) and f[0] >= problem.min_frequency_hz
    assert v["probe_power_w"] <= problem.max_power_w and v["exposure_s"] <= 1 / problem.frame_rate_hz
    assert design.RIPPLE_SIGMAS * result.coarse_crlb_m <= C / (4 * np.mean(f))
    assert v["mean_term_snr"] >= design.MIN_MEAN_TERM_SNR
    # the monotone resources sit at their limits, as they must for the shortest acquisition
    assert any("probe power" in a for a in result.active_constraints)
    assert any("exposure" in a for a in result.active_constraints)
    _, fewer = design.solve_for_n(result.num_frames - 1, design.frame_cap(problem), problem)
    assert not design.meets(fewer, problem)
    # exhaustive search over (β, θ_b) at the optimum's sweep, power and exposure
    mask = jnp.ones(result.num_frames)
    fj = jnp.asarray(f)

    snr_floor = design.SIGN_SNR_MARGIN * design.MIN_MEAN_TERM_SNR

    @jax.jit
    @jax.vmap
    def bound(beta, bias):
        inst = design.design_instrument(
            start_hz=0.0,
            step_hz=0.0,
            num_steps=fj.size,
            probe_power_w=v["probe_power_w"],
            exposure_s=v["exposure_s"],
            modulation_index=beta,
            bias_rad=bias,
            frequencies_hz=fj,
        )
        fisher = cf.fisher.depth_fisher(inst, problem.distance_m, problem.reflectance, frame_weights=mask)
        snr = design.mean_term_snr(inst, mask, problem.distance_m, problem.reflectance)
        return jnp.where(snr >= snr_floor, cf.fisher.crlb_from_fisher(fisher), jnp.inf)

    def grid_min(betas, biases):
        b, t = np.meshgrid(betas, biases)
        values = np.asarray(bound(jnp.asarray(b.ravel()), jnp.asarray(t.ravel())))
        k = int(np.argmin(values))
        return values[k], b.ravel()[k], t.ravel()[k]

    _, beta0, bias0 = grid_min(np.linspace(0.5, 5.0, 46), np.linspace(0.1, 1.5, 57))  # spacing 0.1, 0.025 rad
    best, _, _ = grid_min(np.linspace(beta0 - 0.2, beta0 + 0.2, 41), np.linspace(bias0 - 0.05, bias0 + 0.05, 41))
    # the margin's penalty is soft (the optimum sits ~0.3 % inside it), so it may beat the
    # grid slightly; measured ratio 1.0001. (Checked against the hard limit on the coarse grid
    # alone, the ratio was 1.0095 on a CPU, against a 1.01 bound, and the test failed on a GPU.)
    assert best * 0.99 <= result.crlb_m <= best * 1.002


def test_design_validated_by_monte_carlo(small_design):
    """Simulate + reconstruct at the optimum: the Monte Carlo precision is within 25 % of the
    bound it was designed for (256 pixels: σ of a std estimate ≈ 4.4 %), no slips, all valid."""
    problem, result = small_design
    mc = design.monte_carlo(design.design_point(result, problem), trials=256, seed=3)
    assert mc["mc_valid_fraction"] > 0.99
    assert mc["mc_precision_mm"] / (result.crlb_m * 1e3) == pytest.approx(1.0, abs=0.25)


def test_resumed_sweep_equals_uninterrupted(tmp_path):
    axes = [("bandwidth_ghz", np.array([2.0, 4.0, 6.0])), ("distance_m", np.array([30.0, 60.0]))]
    fixed = {"num_steps": 256.0}
    mc = [{"bandwidth_ghz": 4.0, "distance_m": 30.0}]
    whole = design.run_sweep(axes, tmp_path / "whole.csv", fixed=fixed, mc_points=mc, mc_trials=16, progress=False)
    part = tmp_path / "part.csv"
    first = design.run_sweep(axes, part, fixed=fixed, mc_points=mc, mc_trials=16, progress=False, stop_after=2, chunk=1)
    assert len(first) == 2 and len(list(csv.DictReader(open(part)))) == 2
    resumed = design.run_sweep(axes, part, fixed=fixed, mc_points=mc, mc_trials=16, progress=False)
    assert (tmp_path / "whole.csv").read_text() == part.read_text()
    assert len(resumed) == len(whole) == 6
    with_mc = [r for r in resumed if "mc_trials" in r]
    assert len(with_mc) == 1 and with_mc[0]["mc_trials"] == 16
    # a sweep over other parameters refuses the file rather than mixing rows
    with pytest.raises(ValueError, match="other parameters"):
        design.run_sweep([("exposure_ms", np.array([1.0]))], part, fixed=fixed, progress=False)
    with pytest.raises(ValueError, match="num_steps"):
        design.run_sweep(axes, part, fixed={"num_steps": 512.0}, progress=False)
    assert part.read_text() == (tmp_path / "whole.csv").read_text()  # nothing lost
    # a file that is not a sweep CSV (here only a header line, or binary) is refused, never overwritten
    for name, content in (("notes.csv", b"run,comment\n"), ("blob.csv", b"\xff\xfe\x00")):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match="not a sweep CSV"):
            design.run_sweep(axes, tmp_path / name, fixed=fixed, progress=False)
        assert (tmp_path / name).read_bytes() == content


def test_sweep_cli_and_bad_axes(tmp_path):
    out = tmp_path / "s.csv"
    assert (
        main(
            [
                "sweep",
                "--axis",
                "num_steps=64,128,256",
                "--set",
                "bandwidth_ghz=5.91",
                "--out",
                str(out),
                "--plot",
                str(tmp_path / "s.png"),
                "--quiet",
            ]
        )
        == 0
    )
    rows = list(csv.DictReader(open(out)))
    crlb = [float(r["crlb_mm"]) for r in rows]
    assert len(rows) == 3 and crlb[0] > crlb[1] > crlb[2]
    assert (tmp_path / "s.png").stat().st_size > 10_000
    assert (
        main(
            [
                "sweep",
                "--axis",
                "bandwidth_ghz=2:6:3",
                "--axis",
                "distance_m=30:240:3",
                "--set",
                "num_steps=256",
                "--out",
                str(tmp_path / "m.csv"),
                "--plot",
                str(tmp_path / "m.png"),
                "--quiet",
            ]
        )
        == 0
    )
    assert main(["sweep", "--axis", "warp_speed=1:2:3", "--out", str(tmp_path / "x.csv")]) == 2
    assert main(["sweep", "--axis", "distance_m=a:b", "--out", str(tmp_path / "x.csv")]) == 2
    assert main(["sweep", "--axis", "bandwidth_ghz=2,3", "--set", "step_mhz=1", "--out", str(tmp_path / "x.csv")]) == 2
    assert not (tmp_path / "x.csv").exists()


def test_sweep_heat_map_of_three_axes_is_the_first_slice():
    """Beyond two axes the heat map shows the slice at each further axis's smallest value
    (it used to overwrite the cells with whichever row came last)."""
    rows = [
        {"bandwidth_ghz": b, "distance_m": d, "reflectance": r, "crlb_mm": b + 10 * d + 100 * r}
        for r in (0.2, 0.1)
        for d in (30.0, 40.0)
        for b in (6.0, 7.0)
    ]
    xs, ys, grid, at = design.sweep_heat_map(rows, ["bandwidth_ghz", "distance_m", "reflectance"])
    assert at == {"reflectance": 0.1}
    np.testing.assert_allclose(grid, xs[None, :] + 10 * ys[:, None] + 10.0)


def test_design_cli(small_design, tmp_path):
    """The command reports the optimum and its active constraints, validates it, writes JSON;
    an unreachable target says why and exits 1."""
    import json

    out = tmp_path / "design.json"
    assert (
        main(
            [
                "design",
                "--target-precision-mm",
                "1.0",
                "--max-range-m",
                "38",
                "--max-frequency-ghz",
                "6",
                "--max-frames",
                "256",
                "--validate-trials",
                "64",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    doc = json.loads(out.read_text())
    assert doc["feasible"] and doc["num_frames"] == small_design[1].num_frames
    assert doc["unambiguous_range_m"] >= 38.0 and doc["validation"]["mc_trials"] == 64
    assert (
        main(
            [
                "design",
                "--target-precision-mm",
                "0.001",
                "--max-range-m",
                "38",
                "--max-frequency-ghz",
                "6",
                "--max-frames",
                "256",
                "--validate-trials",
                "0",
                "--quiet",
            ]
        )
        == 1
    )


@pytest.mark.parametrize(
    "study",
    [
        "paper_fig4",
        "precision_table",
        "posterior_coverage",
        "hybrid_calibration_study",
        "registration_synthetic",
        "detection",
        "pulls",
        "hard_cases",
    ],
)
def test_study_scripts_explain_themselves(study):
    """`python -m cohflash_experiments.NAME --help`: the whole docstring and every option's default."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", f"cohflash_experiments.{study}", "--help"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert f"python -m cohflash_experiments.{study}" in out.stdout and "--out OUT" in out.stdout
    lines = out.stdout.splitlines() + [""]
    # an option's help (with its default) is on its own line or the next
    helps = [line + nxt for line, nxt in zip(lines, lines[1:]) if line.strip().startswith("--")]
    assert helps and all("(default:" in h for h in helps)
