"""One instrument: every stage takes the same `Instrument`, so a parameter set on it acts in
the simulator, the Fisher bound, the reconstruction, calibration, the posteriors and the
design's Monte Carlo alike; a capture describes its instrument and a calibration turns it
into the calibrated one; estimators come from one registry; status codes from one enum."""

import json

import h5py
import jax
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.capture import Capture, CaptureError
from cohflash_jax.cli import main
from cohflash_jax.estimate import METHODS, AbstractDepthEstimator, DepthEstimate, Method
from cohflash_jax.fisher import depth_crlb_m
from cohflash_jax.reconstruct import ReconstructOptions, build_plan, reconstruct_array
from cohflash_jax.simulate import simulate_to_file

from .conftest import depth_scene

ML = ReconstructOptions(method="ml", progress=False)


def test_a_rolloff_set_on_the_instrument_acts_in_simulation_fisher_and_reconstruction():
    """`MZM(rolloff_3db_hz=5 GHz)` on the instrument: the simulated frames change (the tone
    tapers over the band), the Fisher bound grows (less modulation at high frequencies), and
    the reconstruction models it (its amplitude of the tapered tone matches the flat one's;
    the flat model reads it low by the roll-off's share of the fundamental's weight)."""
    flat = cf.Instrument.paper(3000)
    rolled = flat.replace(modulator=cf.MZM(rolloff_3db_hz=5e9))
    scene = depth_scene([30.5], effects=("sidebands",))
    frames = {
        name: cf.simulate(scene, inst, 8, 8, jax.random.key(0)) for name, inst in (("flat", flat), ("rolled", rolled))
    }
    assert not np.array_equal(frames["flat"], frames["rolled"])
    crlb_flat, crlb_rolled = (float(depth_crlb_m(i, 30.5, 0.5)) for i in (flat, rolled))
    assert crlb_rolled > 1.3 * crlb_flat
    w_flat, w_rolled = (np.asarray(build_plan(i, ML).model.weights) for i in (flat, rolled))
    assert w_rolled[1] < 0.8 * w_flat[1]
    amp = {
        (f, i): float(np.median(reconstruct_array(frames[f], inst, ML)["amplitude"]))
        for f in ("flat", "rolled")
        for i, inst in (("flat", flat), ("rolled", rolled))
    }
    assert amp[("rolled", "rolled")] == pytest.approx(amp[("flat", "flat")], rel=0.03)
    assert amp[("rolled", "flat")] == pytest.approx(amp[("flat", "flat")] * w_rolled[1] / w_flat[1], rel=0.05)


def test_instrument_errors_act_only_where_the_scene_lists_their_effect():
    """Hybrid errors and the true roll-off live on the instrument (`InstrumentErrors`); a scene
    that does not list their effects gets the described instrument."""
    inst = cf.Instrument.paper(64, errors=cf.InstrumentErrors(modulator_rolloff_3db_hz=2e9))
    assert inst.truth(()).hybrid == inst.hybrid and inst.truth(()).modulator == inst.modulator
    true = inst.truth(("hybrid_errors", "beta_rolloff"))
    np.testing.assert_allclose(
        np.asarray(true.hybrid.phases_rad) - np.asarray(inst.hybrid.phases_rad), inst.errors.hybrid_phase_error_rad
    )
    assert true.modulator.rolloff_3db_hz == 2e9
    scene = depth_scene([10.0])
    plain = cf.simulate(scene, inst, 8, 8, jax.random.key(1))
    with_errors = cf.simulate(scene.with_effects(("beta_rolloff",)), inst, 8, 8, jax.random.key(1))
    assert not np.array_equal(plain, with_errors)


def test_design_monte_carlo_reconstructs_with_the_designed_instrument(monkeypatch):
    """A 35-frame point with β = 3, θ_b = 0.5 (strong harmonics): the Monte Carlo simulates and
    reconstructs with that instrument — its modulator, with its sidebands — and is unbiased;
    the default modulator's model of the same frames (what the Monte Carlo used to reconstruct
    with) is biased by several standard errors and scatters wider."""
    from cohflash_jax import reconstruct
    from cohflash_jax.design import monte_carlo, point_instrument

    point = {
        "num_steps": 35,
        "bandwidth_ghz": 5.91,
        "frame_rate_hz": 350.0,
        "exposure_ms": 2.5,
        "distance_m": 0.13,
        "range_falloff": 0.0,
        "modulation_index": 3.0,
        "bias_rad": 0.5,
        "probe_power_mw": 800.0,
    }
    seen = []
    original = reconstruct.reconstruct_array
    monkeypatch.setattr(
        reconstruct,
        "reconstruct_array",
        lambda frames, inst, *a, **k: (seen.append(inst), original(frames, inst, *a, **k))[1],
    )
    mc = monte_carlo(point, trials=256, seed=2)
    designed = point_instrument(point)
    assert len(seen) == 1 and seen[0].modulator == designed.modulator and seen[0].sensor == designed.sensor
    assert mc["mc_valid_fraction"] > 0.8
    frames = cf.simulate(
        cf.planar(0.13, 0.5, effects=("shot_noise", "dark_current", "read_noise", "quantization", "sidebands")),
        designed,
        16,
        16,
        jax.random.key(2),
    )
    err = {}
    for name, inst in (("designed", designed), ("default", designed.replace(modulator=cf.MZM()))):
        out = original(frames, inst, ML)
        err[name] = out["depth_m"][out["valid"]] - 0.13
    stderr = lambda e: np.std(e) / np.sqrt(e.size)
    assert abs(np.mean(err["designed"])) < 4 * stderr(err["designed"])
    assert abs(np.mean(err["default"])) > 4 * stderr(err["default"])
    assert np.std(err["default"]) > 1.2 * np.std(err["designed"])


def test_capture_describes_its_instrument_and_a_calibration_applies_to_it(tmp_path):
    """`Capture.instrument` reads back what the simulator wrote from the described instrument;
    `Calibration.apply` replaces what the calibration identified."""
    inst = cf.Instrument(
        sweep=cf.FrequencySweep.uniform(0.5e9, 4e6, 64),
        modulator=cf.MZM(2.5, 0.6, max_order=4),
        sensor=cf.Sensor(exposure_s=2e-3, adc_bits=12, dn_per_electron=0.2),
        frame_rate_hz=250.0,
        field_of_view_deg=(1.0, 0.8),
    )
    path = tmp_path / "c.h5"
    simulate_to_file(path, depth_scene([5.0], effects=("hybrid_errors",)), inst, 4, 4, progress=False)
    with Capture(path) as cap:
        read = cap.instrument()
    np.testing.assert_array_equal(read.sweep.frequencies_hz, inst.sweep.frequencies_hz)
    assert read.modulator == inst.modulator and read.hybrid == inst.hybrid  # the nominal hybrid, not the true one
    for name in ("exposure_s", "wavelength_m", "adc_bits", "dn_per_electron"):
        assert getattr(read.sensor, name) == getattr(inst.sensor, name)
    assert read.frame_rate_hz == 250.0 and read.field_of_view_deg == (1.0, 0.8) and read.system_delay_s == 0.0
    calib = cf.Calibration.from_document(
        {
            "format": "cohflash-calibration",
            "format_version": 1,
            "hybrid": {"phases_rad": [0, 1.6, 3.1, 4.7]},
            "system_delay_s": 2e-9,
        }
    )
    applied = calib.apply(read)
    assert applied.hybrid.phases_rad == (0, 1.6, 3.1, 4.7) and applied.system_delay_s == 2e-9
    assert applied.modulator == read.modulator and applied.sensor == read.sensor
    with h5py.File(path, "r+") as f:
        f.attrs["field_of_view_deg"] = [0.72]
    with pytest.raises(CaptureError, match="field_of_view_deg"):
        Capture(path)


@pytest.mark.runs_long
@pytest.mark.filterwarnings("ignore:not converged")
def test_uncertainty_and_reconstruct_agree_under_the_same_calibration(tmp_path, capsys):
    """A capture with a system delay (0.6 m of path) and hybrid errors, one calibration file:
    `uncertainty --calibration` centres each posterior on the depth `reconstruct --calibration`
    gives, to well within σ; without the calibration the posterior sits the path offset away."""
    path_offset_m = 0.6
    inst = cf.Instrument.paper(3000, system_delay_s=2 * path_offset_m / cf.SPEED_OF_LIGHT_M_PER_S)
    cap = tmp_path / "cap.h5"
    scene = cf.planar(30.5, 0.5, effects=("shot_noise", "read_noise", "sidebands", "hybrid_errors"))
    simulate_to_file(cap, scene, inst, 4, 4, seed=3, progress=False)
    with Capture(cap) as c:
        t = c.truth_attrs
    gain = np.asarray(t["hybrid_relative_gains"]) * float(t["dn_per_electron"])
    doc = {
        "format": "cohflash-calibration",
        "format_version": 1,
        "system_delay_s": float(t["system_delay_s"]),
        "hybrid": {
            "phases_rad": list(t["hybrid_phases_rad"]),
            "relative_gains": list(gain / gain[0]),
            "offsets_dn": list(t["hybrid_offsets_dn"]),
        },
    }
    calib = tmp_path / "cal.json"
    calib.write_text(json.dumps(doc))
    assert main(["reconstruct", str(cap), "--out", str(tmp_path / "d.h5"), "--calibration", str(calib), "--quiet"]) == 0
    with h5py.File(tmp_path / "d.h5") as f:
        depth, sigma, valid = f["depth_m"][()], f["sigma_m"][()], f["valid"][()].astype(bool)
    assert valid.all() and np.all(np.abs(depth - 30.5) < 5 * sigma)
    pixels = [(1, 1), (2, 3)]
    args = ["uncertainty", str(cap), "--max-steps", "3000", "--quiet"] + [
        a for r, c in pixels for a in ("--pixel", f"{r},{c}")
    ]
    assert main(args + ["--out", str(tmp_path / "p.h5"), "--calibration", str(calib)]) == 0
    assert main(args + ["--out", str(tmp_path / "raw.h5")]) == 0
    with h5py.File(tmp_path / "p.h5") as f, h5py.File(tmp_path / "raw.h5") as g:
        medians, raw = f["median_m"][()], g["median_m"][()]
        assert f.attrs["system_delay_s"] == pytest.approx(float(t["system_delay_s"]))
    for k, (r, c) in enumerate(pixels):
        assert abs(medians[k] - depth[r, c]) < 0.3 * sigma[r, c]
        assert abs(raw[k] - medians[k] - path_offset_m) < 0.01


class _BinCentre(AbstractDepthEstimator):
    """A test estimator: the depth of the strongest bin's centre, σ one bin."""

    @classmethod
    def build(cls, setup):
        return cls()

    def estimate(self, stage, coarse, sequence, noise_var):
        depth = stage.depth(coarse, interpolate=False)
        sigma = np.float64(stage.grid_step_m) * jax.numpy.ones_like(depth)
        return DepthEstimate(
            depth,
            stage.tone_amplitude(coarse),
            sigma,
            depth,
            jax.numpy.ones(depth.shape, bool),
            jax.numpy.isfinite(depth),
            jax.numpy.full(depth.shape, -1.0),
        )


def test_an_estimator_registered_by_one_line_runs_end_to_end(monkeypatch, paper_instrument, simulate_pixels):
    """Adding an estimator is its class plus one `METHODS` entry: options, the CLI's choices
    and the reconstruction take it from there."""
    monkeypatch.setitem(METHODS, "bin_centre", Method(_BinCentre.build, "the strongest bin's centre"))
    frames = simulate_pixels(depth_scene([30.5], effects=("shot_noise", "read_noise")))
    out = reconstruct_array(frames, paper_instrument, ReconstructOptions(method="bin_centre", progress=False))
    assert out["valid"].all() and np.all(np.abs(out["depth_m"] - 30.5) <= paper_instrument.sweep.bin_depth_m)
    from cohflash_jax.cli import build_parser

    args = build_parser().parse_args(["reconstruct", "x.h5", "--out", "y.h5", "--method", "bin_centre"])
    assert args.method == "bin_centre"


def test_status_codes_are_one_enumeration_with_the_documented_numbers():
    assert cf.Status.table() == {
        0: "ok",
        1: "low_snr",
        2: "not_converged",
        3: "fit_failed",
        4: "bad_data (NaN/inf)",
        5: "saturated",
        6: "dead (constant)",
        7: "out_of_range",
        8: "outside_registration",
        9: "poor_fit (reduced χ² above max_fit_chi2)",
        10: "dc_edge (power rises towards DC: slow drift)",
        11: "not_detected (no tone beyond what noise gives at the stated false-alarm rate)",
        12: "edge_bias (a peak read-out near the window's ends, where the tone's mirror image biases it)",
        13: "ambiguous (another depth the model predicts fits the frames nearly as well)",
    }
    assert json.loads(cf.Status.table_json())["8"] == "outside_registration"
