"""Harmonic ambiguity resolved by the model: with the fundamental starved (x = β/2 at the
first zero of J₁) the orders 2 and 3 together fix depth over c/(4Δf); the inversion fits every
order from each reading of the peak and never gives a confident depth that explains one peak
and ignores another."""

import dataclasses

import jax
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.estimate.harmonics import window_order
from cohflash_jax.modulator import MZM
from cohflash_jax.reconstruct import ReconstructOptions, build_plan, reconstruct_array
from cohflash_jax.status import Status

C = 299_792_458.0
NOISE = ("shot_noise", "read_noise", "dark_current", "quantization", "sidebands")
STARVED = MZM(7.663, np.pi / 4, max_order=7)  # the β: x = 3.83, J₁(x) ≈ 0


def test_the_window_is_the_orders_common_one():
    assert window_order(STARVED.weights()) == 1  # orders 2, 3 (and 4) present
    assert window_order(MZM(2.0, 0.0, max_order=7).weights()) == 2  # only even orders
    assert window_order(MZM(2.0, np.pi / 2, max_order=7).weights()) == 1
    plan = build_plan(dataclasses.replace(cf.Instrument.paper(3000), modulator=STARVED), ReconstructOptions())
    assert plan.geometry.dominant_order == 3
    assert plan.policy.valid_window_m[1] == pytest.approx(C / (4 * 1.97e6))
    # a peak read-out cannot tell the orders' readings apart: it states the dominant tone's window
    dft = build_plan(dataclasses.replace(cf.Instrument.paper(3000), modulator=STARVED), ReconstructOptions("dft"))
    assert dft.policy.valid_window_m[1] == pytest.approx(C / (12 * 1.97e6))


@pytest.mark.parametrize("depth_m", [15.0, 5.0])
def test_starved_fundamental_gives_the_true_depth_or_a_flag(depth_m):
    inst = dataclasses.replace(cf.Instrument.paper(3000), modulator=STARVED)
    scene = cf.from_arrays(np.full((4, 4), depth_m), np.full((4, 4), 0.5), effects=NOISE)
    out = reconstruct_array(cf.simulate(scene, inst, 4, 4, jax.random.key(2)), inst, ReconstructOptions(progress=False))
    valid = out["valid"]
    assert valid.mean() > 0.8
    assert np.all(np.abs(out["depth_m"][valid] - depth_m) < 6 * out["sigma_m"][valid])
    flagged = out["fit_status"][~valid]
    assert np.all(np.isin(flagged, [Status.AMBIGUOUS, Status.LOW_SNR, Status.NOT_DETECTED, Status.POOR_FIT]))
