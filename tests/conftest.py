"""Shared, session-scoped fixtures: small shapes so JAX compiles each once."""

import os
import shutil
import tempfile
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.runtime import enable_compilation_cache, several_cpu_streams_run

# The CLI keeps compiled programs in ~/.cache/cohflash/jax. The tests keep theirs in a folder of
# this run alone, shared by its xdist workers (one compiles a program, the other loads it),
# removed when the run ends: hermetic, and programs that several tests and both workers build
# are compiled once a run.
RUN_CACHE = (
    Path(tempfile.gettempdir())
    / f"cohflash-test-jax-cache-{os.getppid() if os.environ.get('PYTEST_XDIST_WORKER') else os.getpid()}"
)
os.environ["COHFLASH_JAX_CACHE"] = str(RUN_CACHE)
enable_compilation_cache(RUN_CACHE)


# tests of a process over two CPU devices, which a jaxlib that hangs with them does not get
needs_two_cpu_streams = pytest.mark.skipif(
    not several_cpu_streams_run(), reason="this jaxlib hangs with two CPU devices: its processes get one"
)


def pin_worker_to_its_cores() -> list[int] | None:
    """An xdist worker on its own share of the CPUs (gw0 the 1st, 3rd, … where two workers
    share them), before JAX's backends start: XLA sizes each process's thread pools from the
    CPUs it may run on, and two workers each spreading its programs over every core spent CPU
    on each other's threads. None where nothing was pinned."""
    worker, count = os.environ.get("PYTEST_XDIST_WORKER", ""), int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if not worker.startswith("gw") or count < 2 or not hasattr(os, "sched_setaffinity"):
        return None
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < count:
        return None
    mine = cpus[int(worker[2:]) % count :: count]
    os.sched_setaffinity(0, mine)
    return mine


pin_worker_to_its_cores()
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


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "runs_long: one of the suite's slowest tests (20–95 s on 2 cores); scheduled first"
    )


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """The slowest tests (`runs_long`) first: xdist hands out grouped modules first and then
    single tests in collection order, so a long test collected last (test_uncertainty,
    test_report) would run alone at the end while the other worker idles.

    `--dist loadgroup` keeps a module's tests on one worker by suffixing their ids with the
    `xdist_group` name; where a pytest/xdist pair stops doing so (pytest-dev/pytest-xdist#1386)
    every costly module fixture is built once per worker, without a failure: say so."""
    items.sort(key=lambda item: item.get_closest_marker("runs_long") is None)  # stable: the rest keep their order
    if not (os.environ.get("PYTEST_XDIST_WORKER") and getattr(config.option, "loadgroup", False)):
        return
    lost = [item.nodeid for item in items if item.get_closest_marker("xdist_group") and "@" not in item.nodeid]
    if lost:
        warnings.warn(
            f"--dist loadgroup did not group {len(lost)} tests marked xdist_group (e.g. {lost[0]}): "
            "their module fixtures are built on each worker; pytest-xdist#1386, pin pytest<9.2",
            pytest.PytestWarning,
            stacklevel=1,
        )


def pytest_sessionfinish(session):
    """The run's compilation cache goes with the run (the controller, or a run without xdist)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        shutil.rmtree(RUN_CACHE, ignore_errors=True)
