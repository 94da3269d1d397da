"""Shared, session-scoped fixtures: small shapes so JAX compiles each once."""

import os

import jax
import numpy as np
import pytest

import cohflash_jax as cf

# the CLI keeps compiled programs in ~/.cache/cohflash/jax; tests stay hermetic
os.environ.setdefault("COHFLASH_JAX_CACHE", "off")
# JAX's backends start now, with one CPU device: the CLI's `use_cpu_streams` (run by tests that
# call `cohflash` in-process) then changes nothing, and every test compiles for one device; the
# two-device path has a test of its own, in a subprocess (test_short_sweeps)
jax.devices()

N_FRAMES = 3000  # the paper's sweep: keeps Δf, bin width and ripple as in the paper
PIXELS = (8, 8)


@pytest.fixture(scope="session")
def paper_instrument():
    return cf.Instrument.paper(N_FRAMES)


@pytest.fixture(scope="session")
def noise_effects():
    return ("shot_noise", "read_noise", "dark_current", "quantization")


def depth_scene(depths_m, reflectance=0.5, effects=()):
    """A scene whose 8×8 pixels take the given depths (row-major, repeated to fill)."""
    d = np.resize(np.asarray(depths_m, np.float64), PIXELS[0] * PIXELS[1]).reshape(PIXELS)
    return cf.from_arrays(d, np.full(PIXELS, reflectance), effects=effects)


@pytest.fixture(scope="session")
def simulate_pixels(paper_instrument):
    def run(scene, seed=0, instrument=None):
        inst = instrument or paper_instrument
        return cf.simulate(scene, inst, *PIXELS, jax.random.key(seed))

    return run
