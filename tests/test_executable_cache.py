"""The executable cache (issue #21): a program compiled in one process is loaded whole in the
next, without tracing, and gives the same results; a damaged entry is compiled afresh."""

import dataclasses
import json
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import numpy as np
import pytest

from .conftest import needs_two_cpu_streams

RUN = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from cohflash_jax.runtime import EXECUTABLES, enable_compilation_cache
    enable_compilation_cache(sys.argv[1])
    import cohflash_jax as cf
    from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array
    inst = cf.Instrument.paper(128)
    import jax
    frames = cf.simulate(cf.planar(12.0, 0.9, effects=("shot_noise",)), inst, 4, 4, jax.random.key(3))
    out = reconstruct_array(np.asarray(frames), inst, ReconstructOptions(method="dft", progress=False))
    np.save(sys.argv[2], np.stack([out["depth_m"], out["sigma_m"], out["fit_status"]]))
    print(json.dumps({"loaded": EXECUTABLES.loaded, "compiled": EXECUTABLES.compiled}))
    """
)


def run(cache, out):
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    done = subprocess.run(
        [sys.executable, "-c", RUN, str(cache), str(out)], capture_output=True, text=True, env=env, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1]), np.load(out)


def test_programs_load_in_a_fresh_process_and_damaged_entries_are_replaced(tmp_path):
    cache = tmp_path / "cache"
    first, a = run(cache, tmp_path / "a.npy")
    assert first["compiled"] >= 2 and first["loaded"] == 0
    entries = sorted((cache / "executables").glob("*.exe"))
    assert len(entries) == first["compiled"]
    second, b = run(cache, tmp_path / "b.npy")
    assert second == {"loaded": first["compiled"], "compiled": 0}
    np.testing.assert_array_equal(a, b)
    for e in entries:  # damaged on disk: compiled afresh, same results
        e.write_bytes(b"not an executable")
    third, c = run(cache, tmp_path / "c.npy")
    assert third == {"loaded": 0, "compiled": first["compiled"]}
    np.testing.assert_array_equal(a, c)
    assert all(e.read_bytes() != b"not an executable" for e in entries)


def test_a_static_half_without_stable_text_stays_in_memory():
    """A static argument, or a module's static field, printed with its address has no key:
    its program is never written to disk (another process could not find it)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from cohflash_jax.runtime import EXECUTABLES

    fun = test_a_static_half_without_stable_text_stays_in_memory
    assert EXECUTABLES.key(fun, (lambda: 0,), None, ()) is None

    class Part(eqx.Module):
        rule: object = eqx.field(static=True)
        value: jax.Array

    structure = lambda rule: jax.tree.structure(((Part(rule, jnp.ones(2)),), ()))
    assert EXECUTABLES.key(fun, ((), ()), structure(lambda v: v), ()) is None
    assert EXECUTABLES.key(fun, ((), ()), structure("named"), ()) is not None


def test_an_entry_is_named_by_element_type_not_by_how_a_dtype_spells_its_byte_order():
    """A Zarr store's frames come as dtype('<u2'), an HDF5 file's as dtype('uint16'): the same
    program, one entry (its name once took the dtype's text, so a Zarr store's first run wrote
    an entry its next run, reading the first tile another way, did not find)."""
    from cohflash_jax.runtime import EXECUTABLES

    fun = test_an_entry_is_named_by_element_type_not_by_how_a_dtype_spells_its_byte_order
    spelled = np.zeros(4, np.dtype("uint16").newbyteorder("<"))
    assert repr(spelled.dtype) != repr(np.dtype("uint16"))  # the two spellings
    name = lambda x: EXECUTABLES.key(fun, (), None, ((x.shape, x.dtype, False, None),))  # as a call signs a NumPy input
    assert name(spelled) == name(np.zeros(4, np.uint16)) != name(np.zeros(4, np.int16))
    assert name(np.zeros(4, np.float16)) != name(np.zeros(4, jax.numpy.bfloat16))


class Halves(eqx.Module):
    """A program's output as a module (`test_a_program_returning_a_module_stays_in_memory…`):
    defined at module level, as the package's modules are, so that pickle finds its class."""

    low: jax.Array
    high: jax.Array


def test_a_program_returning_a_module_stays_in_memory_and_one_returning_a_dict_is_written(tmp_path, monkeypatch):
    """An executable whose output is an equinox module does not come back from the cache (its
    output structure is not the same after pickle: the loaded program failed at its first call
    and was compiled again in every process). Such a program is not written; one returning a
    dict of the same arrays is, and loads."""
    import jax.numpy as jnp

    from cohflash_jax import runtime

    assert not runtime.trees_come_back([jax.tree.structure(Halves(jnp.zeros(1), jnp.ones(1)))])
    assert runtime.trees_come_back([jax.tree.structure({"low": 0, "high": (1, 2)})])

    def halves_module(x):
        return Halves(x - 1.0, x + 1.0)

    def halves_dict(x):
        return {"low": x - 1.0, "high": x + 1.0}

    monkeypatch.setattr(runtime.EXECUTABLES, "folder", tmp_path)
    x = jnp.arange(3.0)
    assert float(runtime.async_filter_jit(halves_module)(x).high[2]) == 3.0
    assert float(runtime.async_filter_jit(halves_dict)(x)["low"][0]) == -1.0
    assert [p.name.split("-")[0] for p in tmp_path.glob("*.exe")] == ["halves_dict"]
    loaded, compiled = runtime.EXECUTABLES.loaded, runtime.EXECUTABLES.compiled
    # as a later process finds them (a new wrapper keeps no program in memory)
    np.testing.assert_array_equal(runtime.async_filter_jit(halves_dict)(x)["high"], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(runtime.async_filter_jit(halves_module)(x).low, [-1.0, 0.0, 1.0])
    assert (runtime.EXECUTABLES.loaded - loaded, runtime.EXECUTABLES.compiled - compiled) == (1, 1)


def test_quick_compiled_programs_are_kept_apart_and_agree_with_optimised_ones():
    """A region of interest is compiled for a short compile (`quick_compile`: XLA's lowest
    optimisation level, on the CPU through its loop emitters): its programs have entries of
    their own, and its depths agree with the optimised programs' to far below σ."""
    import jax

    import cohflash_jax as cf
    from cohflash_jax.reconstruct import ReconstructOptions, TileDispatcher, build_plan
    from cohflash_jax.runtime import (
        EXECUTABLES,
        GPU_COMPILE_OPTIONS,
        QUICK_COMPILE_CPU_OPTIONS,
        compile_options,
        quick_compile,
        quick_compile_options,
    )

    fun = test_quick_compiled_programs_are_kept_apart_and_agree_with_optimised_ones
    keys = {EXECUTABLES.key(fun, (1,), None, (), quick, loops) for quick in (False, True) for loops in (False, True)}
    assert len(keys) == 4  # quick, and loop-emitted (`async_filter_jit(loop_emitters=True)`), each apart
    # a program that asks for the loop emitters gets them on the CPU alone, and quick ones stay quick
    assert compile_options("cpu", False, True) == QUICK_COMPILE_CPU_OPTIONS
    assert compile_options("cpu", False, False) == {}
    assert compile_options("cpu", True, True) == compile_options("cpu", True, False) == quick_compile_options("cpu")
    # on a GPU, every program without XLA's autotuning, and no CPU option
    assert compile_options("gpu", False, True) == GPU_COMPILE_OPTIONS
    assert compile_options("gpu", True, False) == quick_compile_options("gpu") | GPU_COMPILE_OPTIONS
    inst = cf.Instrument.paper(256)
    frames = cf.simulate(cf.planar(12.0, 0.9, effects=("shot_noise", "read_noise")), inst, 4, 8, jax.random.key(5))
    plan = build_plan(inst, ReconstructOptions(progress=False))
    tile = np.ascontiguousarray(np.asarray(frames).reshape(4, 256, 32))
    outputs = []
    for quick in (False, True):
        with quick_compile(quick):
            outputs.append(TileDispatcher(plan, 32).dispatch(tile).gather())
    optimised, quick = outputs
    np.testing.assert_array_equal(optimised["fit_status"], quick["fit_status"])
    assert optimised["valid"].all()
    assert np.max(np.abs(optimised["depth_m"] - quick["depth_m"]) / optimised["sigma_m"]) < 1e-3


def test_small_captures_of_one_bucket_and_methods_of_one_capture_share_programs():
    """A region of interest is padded to its pixel bucket (`tiling.pixel_bucket`), so captures
    of 5×5 and 6×6 pixels run the same programs; and the I/Q programs take the plan's I/Q stage
    alone, so a second method on the same capture makes its inversion program only (and the
    inversion programs take no I/Q stage, so another saturation level makes its I/Q program
    only; and a status array whether or not anything upstream set one). The padded
    pixels change nothing: the 5×5 capture's depths equal those of its pixels reconstructed
    within a larger one."""
    import jax

    import cohflash_jax as cf
    from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array
    from cohflash_jax.runtime import EXECUTABLES
    from cohflash_jax.tiling import pixel_bucket

    assert [pixel_bucket(p) for p in (1, 25, 36, 64, 65, 200)] == [64, 64, 64, 64, 128, 256]
    made = lambda: EXECUTABLES.compiled + EXECUTABLES.loaded
    inst = cf.Instrument.paper(96)
    frames = np.asarray(
        cf.simulate(cf.planar(12.0, 0.9, effects=("shot_noise", "read_noise")), inst, 6, 6, jax.random.key(7))
    )
    dft = ReconstructOptions(method="dft", progress=False)
    six = reconstruct_array(frames, inst, dft)
    before = made()
    five = reconstruct_array(np.ascontiguousarray(frames[..., :5, :5]), inst, dft)
    assert made() == before, "a 5×5 capture made programs of its own after a 6×6 one"
    for name in ("depth_m", "sigma_m", "fit_status"):
        np.testing.assert_array_equal(five[name], six[name][:5, :5])
    before = made()
    reconstruct_array(frames, inst, ReconstructOptions(method="interp", progress=False))
    assert made() == before + 1, "a second method made more than its inversion program"
    # and the inversion programs take the plan without its I/Q stage (`programs.inversion_plan`):
    # a saturation level (a capture's ADC) makes its I/Q program only, the same depths
    before = made()
    deeper = reconstruct_array(frames, inst, dft, saturation_dn=65535.0)
    assert made() == before + 1, "another saturation level made more than its I/Q program"
    for name in ("depth_m", "sigma_m", "fit_status"):
        np.testing.assert_array_equal(deeper[name], six[name])
    # a status found upstream (a registered capture's pixels outside a CCD's view) runs the
    # programs of a capture without one, and marks its pixels alone
    from cohflash_jax.reconstruct.api import align_carrier, plan_and_dispatcher
    from cohflash_jax.reconstruct.engine import sub_tile_pixels
    from cohflash_jax.runtime import quick_compile
    from cohflash_jax.status import Status

    flat = frames.reshape(4, 96, 36)
    _, dispatcher = plan_and_dispatcher(inst, dft, None, align_carrier(dft, inst, flat), sub_tile_pixels(36, 96))
    status = np.zeros(36, np.int8)
    status[[3, 20]] = Status.OUTSIDE_REGISTRATION
    before = made()
    with quick_compile():
        marked = dispatcher.dispatch(flat, None, status, None).gather()
    assert made() == before, "an upstream status made programs of its own"
    expected = six["fit_status"].ravel().copy()
    expected[[3, 20]] = Status.OUTSIDE_REGISTRATION
    np.testing.assert_array_equal(marked["fit_status"], expected)
    np.testing.assert_array_equal(marked["depth_m"], six["depth_m"].ravel())


def test_a_new_system_delay_or_threshold_runs_the_programs_already_compiled():
    """τ_sys, the depth window it places and the validity thresholds reach the programs as
    arrays (`reconstruct.program_plan`), not as constants compiled in: a calibration with a
    new τ_sys (the paper's sweep, and the 10 Hz mode's tone table), or another SNR or χ²
    threshold, makes no program, and the new values act (the depths move by τ_sys·c/2; an
    unreachable threshold flags every pixel)."""
    import jax

    import cohflash_jax as cf
    from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array
    from cohflash_jax.runtime import EXECUTABLES
    from cohflash_jax.status import Status

    made = lambda: EXECUTABLES.compiled + EXECUTABLES.loaded
    ml = ReconstructOptions(method="ml", progress=False)
    for inst, depth_m, delay_s in (
        (cf.Instrument.paper(256), 12.0, 2.5e-9),
        (cf.Instrument.ten_hz_mode(link=cf.LinkBudget(probe_power_w=1.0)), 0.2, 0.5e-9),
    ):
        scene = cf.planar(depth_m, 0.9, effects=("shot_noise", "read_noise"))
        frames = np.asarray(cf.simulate(scene, inst, 6, 6, jax.random.key(7)))
        nominal = reconstruct_array(frames, inst, ml)
        assert nominal["valid"].all()
        before = made()
        delayed = reconstruct_array(frames, inst.replace(system_delay_s=delay_s), ml)
        assert made() == before, "a new τ_sys compiled programs afresh"
        np.testing.assert_array_equal(delayed["fit_status"], nominal["fit_status"])
        shift_m = delay_s * cf.SPEED_OF_LIGHT_M_PER_S / 2
        np.testing.assert_allclose(delayed["depth_m"], nominal["depth_m"] - shift_m, rtol=0, atol=1e-9)
    for options, status in (
        (dataclasses.replace(ml, snr_threshold_db=90.0), Status.LOW_SNR),
        (dataclasses.replace(ml, max_fit_chi2=1e-6), Status.POOR_FIT),
    ):
        flagged = reconstruct_array(frames, inst, options)
        assert made() == before, "another threshold compiled programs afresh"
        assert np.all(flagged["fit_status"] == status)


def test_processes_started_together_compile_each_program_once(tmp_path):
    """Two processes that need the same programs at once, sharing a cache folder: one compiles
    each program, the other waits for its entry and loads it (`runtime.entry_lock`), and both
    give the same results. No lock file is left behind."""
    cache = tmp_path / "cache"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", RUN, str(cache), str(tmp_path / f"{k}.npy")],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for k in range(2)
    ]
    counts = []
    for proc in runs:
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-2000:]
        counts.append(json.loads(out.strip().splitlines()[-1]))
    programs = len(list((cache / "executables").glob("*.exe")))
    assert programs >= 2
    assert sum(c["compiled"] for c in counts) == programs, counts
    assert sum(c["loaded"] for c in counts) == programs, counts
    np.testing.assert_array_equal(np.load(tmp_path / "0.npy"), np.load(tmp_path / "1.npy"))
    assert not list((cache / "executables").glob(".*.lock"))


def test_an_entry_lock_excludes_a_second_holder_until_the_first_is_done(tmp_path):
    """`entry_lock` holds a second taker (here a thread, with a lock file of its own opening)
    until the first releases it, leaves no lock file, and past its time limit goes on
    unlocked rather than wait for ever."""
    import threading
    import time

    from cohflash_jax.runtime import entry_lock

    entry = tmp_path / "program.exe"
    order = []

    def take(label, wait_s=60.0):
        with entry_lock(entry, wait_s):
            order.append(label)

    for label, wait_s, expected in (
        ("waiter", 60.0, ["holder done", "waiter"]),
        ("impatient", 0.2, ["impatient", "holder done"]),
    ):
        order.clear()
        with entry_lock(entry):
            taker = threading.Thread(target=take, args=(label, wait_s))
            taker.start()
            time.sleep(0.6)
            order.append("holder done")
        taker.join(10)
        assert order == expected
    assert not list(tmp_path.glob(".*.lock"))


LAPACK_RUN = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from cohflash_jax.runtime import EXECUTABLES, async_filter_jit, enable_compilation_cache
    enable_compilation_cache(sys.argv[1])
    import jax.numpy as jnp

    @async_filter_jit
    def spectrum(gram):
        return jnp.linalg.eigh(gram)[0]  # LAPACK's syevd

    a = np.random.default_rng(0).normal(size=(5, 5))
    evals = spectrum(jnp.asarray(a @ a.T))
    print(json.dumps({"loaded": EXECUTABLES.loaded, "compiled": EXECUTABLES.compiled,
                      "evals": np.asarray(evals).tolist()}))
    """
)


def test_a_program_calling_lapack_loads_into_a_fresh_process(tmp_path):
    """A program whose kernels come from LAPACK (`eigh`), loaded from the cache into a process
    that has lowered nothing yet, runs (its kernels are bound first: `bind_lapack_kernels`;
    unbound, the process crashed with a segmentation fault) and gives the same numbers."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    results = []
    for _ in range(2):
        done = subprocess.run(
            [sys.executable, "-c", LAPACK_RUN, str(tmp_path / "cache")],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
        results.append(json.loads(done.stdout.strip().splitlines()[-1]))
    first, second = results
    assert first["compiled"] >= 1 and second == {**first, "loaded": first["compiled"], "compiled": 0}


PREFETCHED_RUN = textwrap.dedent(
    """
    import json, sys
    # as `python -m cohflash_jax.cli COMMAND …` starts: the package's import sees the command
    argv = json.loads(sys.argv[1])
    sys.orig_argv = [sys.executable, "-m", "cohflash_jax.cli", *argv]
    import jax.experimental.serialize_executable as serialized
    load, refused = serialized.deserialize_and_load, []
    def counted(*args, **kwargs):  # an executable loaded whole, then refused for its device
        try:
            return load(*args, **kwargs)
        except KeyError:
            refused.append(1)
            raise
    serialized.deserialize_and_load = counted
    import cohflash_jax
    from cohflash_jax.runtime import EXECUTABLES
    started = len(EXECUTABLES.prefetched)
    from cohflash_jax.cli import main
    assert main([*argv, "--quiet"]) == 0
    print(json.dumps({"started": started, "used": EXECUTABLES.prefetched_used, "loaded": EXECUTABLES.loaded,
                      "compiled": EXECUTABLES.compiled, "refused": len(refused)}))
    """
)


def prefetched_run(argv: list, cache) -> dict:
    """`cohflash ARGV` in a fresh process on the executable cache `cache`: how many entries its
    import started loading, how many of those it used, how many it loaded and compiled, and
    how many loads were refused for their device after loading (work thrown away)."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "COHFLASH_JAX_CACHE": str(cache)}
    done = subprocess.run(
        [sys.executable, "-c", PREFETCHED_RUN, json.dumps([str(a) for a in argv])],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def programs_of_a_run(iq_programs: int) -> int:
    """The programs a `cohflash` run on 16-bit frames compiles: its inversion, and its
    `iq_programs` I/Q programs where the native kernel does not compute I/Q on the host."""
    from cohflash_jax import native

    return 1 + (0 if native.available() else iq_programs)


def test_a_reconstruct_process_loads_its_last_runs_programs_while_it_imports(tmp_path):
    """`cohflash reconstruct` notes the entries it used; the next run's import of the package
    starts loading them in a thread, and the run takes them instead of loading them again:
    the same depth file. An entry damaged in between is compiled afresh, the rest still taken."""
    import h5py

    from cohflash_jax.cli import main
    from cohflash_jax.process import cli_command, cli_input_bytes

    capture = tmp_path / "c.h5"
    assert main(["simulate", "planar", "--size", "4x4", "--steps", "128", "--out", str(capture), "--quiet"]) == 0
    cache = tmp_path / "cache"

    def run(k):
        out = tmp_path / f"d{k}.h5"
        counts = prefetched_run(["reconstruct", capture, "--out", out], cache)
        with h5py.File(out) as f:
            return counts, f["depth_m"][()], f["fit_status"][()]

    first, depth, status = run(1)
    # the inversion, and where the native kernel does not compute I/Q, XLA's I/Q programs
    assert first["started"] == 0 and first["compiled"] == programs_of_a_run(2)
    notes = list((cache / "executables").glob("recent-reconstruct-*.txt"))
    assert [p.name for p in notes] == [f"recent-reconstruct-{capture.stat().st_size}.txt"]
    names = notes[0].read_text().split()
    assert len(names) == first["compiled"] and all((cache / "executables" / n).exists() for n in names)
    second, depth2, status2 = run(2)
    assert second["started"] == len(names) and second["used"] == len(names) == second["loaded"]
    assert second["compiled"] == 0
    np.testing.assert_array_equal(depth2, depth)
    np.testing.assert_array_equal(status2, status)
    (cache / "executables" / names[-1]).write_bytes(b"damaged")
    third, depth3, _ = run(3)
    assert third["used"] == len(names) - 1 and third["compiled"] == 1
    np.testing.assert_array_equal(depth3, depth)

    assert cli_command(["/usr/bin/python3", "/venv/bin/cohflash", "reconstruct", "c.h5"]) == "reconstruct"
    assert cli_command(["python", "-X", "importtime", "-m", "cohflash_jax.cli", "stream", "a.h5"]) == "stream"
    assert cli_command(["python", "/venv/bin/cohflash", "--version"]) is None
    assert cli_command(["python", "-m", "pytest", "tests"]) is None
    assert cli_command(["cohflash"]) is None
    # the capture, not the (smaller) depth file it overwrites, decides which programs load
    assert cli_input_bytes(["cohflash", "reconstruct", str(capture), "--out", str(tmp_path / "d1.h5")]) == (
        capture.stat().st_size
    )


def test_a_zarr_store_run_loads_its_last_runs_programs_while_it_imports(tmp_path):
    """A Zarr store (a folder) is known by its frames' size, not by a depth file the run writes
    (larger than so small a store's frames), so its runs, each to a new depth file, start
    loading their last run's programs too."""
    from cohflash_jax.cli import main

    capture, store, cache = tmp_path / "c.h5", tmp_path / "c.zarr", tmp_path / "cache"
    assert main(["simulate", "planar", "--size", "4x4", "--steps", "128", "--out", str(capture), "--quiet"]) == 0
    assert main(["convert", str(capture), "--out", str(store), "--quiet"]) == 0
    zarr_runs = [prefetched_run(["reconstruct", store, "--out", tmp_path / f"z{k}.h5"], cache) for k in (1, 2)]
    first, second = zarr_runs
    assert first["started"] == 0 and first["compiled"] == programs_of_a_run(2)
    assert (cache / "executables" / f"recent-reconstruct-{4 * 128 * 4 * 4 * 2}.txt").exists()
    # every program the first run compiled is the one the second loads and runs
    assert second["started"] == second["used"] == second["loaded"] == first["compiled"]
    assert second["compiled"] == 0


@needs_two_cpu_streams
def test_a_stream_over_two_cpu_streams_takes_its_last_runs_programs(tmp_path):
    """`cohflash stream` runs on two CPU devices (`runtime.COMMAND_CPU_STREAMS`), a short
    sweep's sub-tiles dealt out to both: each program is compiled once, for the first device,
    and its entry loaded for the second (`runtime.load_on_cpu_device`); the next run takes
    every program from the import's loads, each onto its device, compiling none. (Loaded for
    every device, the prefetched programs refused one device's arguments and were compiled
    again every run; loaded first as compiled, an entry for the second device was loaded
    whole, refused, and loaded again.)"""
    from cohflash_jax.cli import main

    capture = tmp_path / "c.h5"  # 512 px of 35 frames: two sub-tiles, one on each device
    assert main(["simulate", "planar", "--size", "16x32", "--steps", "35", "--out", str(capture), "--quiet"]) == 0
    cache, argv = tmp_path / "cache", ["stream", capture, "--out-dir", tmp_path / "maps"]
    first = prefetched_run(argv, cache)
    # the inversion (and I/Q with the carrier axis where the native kernel does not compute them):
    # compiled for one device, loaded for the other
    programs = programs_of_a_run(1)
    assert first["compiled"] == programs and first["loaded"] == programs
    assert len(list((cache / "executables").glob("*.exe"))) == programs
    second = prefetched_run(argv, cache)
    assert second["compiled"] == 0 and second["started"] == second["used"] == second["loaded"] == 2 * programs
    assert first["refused"] == second["refused"] == 0


def test_an_option_this_xla_does_not_know_is_left_out_not_the_compile():
    """Another jaxlib may not know an option of `quick_compile_options` (jaxlib 0.11.2 has no
    switch for the loop emitters): the program still compiles ahead, without it, and the option
    is left out of the process's later compiles; an option XLA does know is kept, and other
    errors still raise."""
    import jax
    import jax.numpy as jnp
    import pytest

    from cohflash_jax import runtime

    lowered = jax.jit(lambda x: jnp.sin(x) * 2.0).lower(jnp.arange(4.0))
    unknown = "xla_cpu_an_option_no_xla_has"
    compiled = runtime.compile_lowered(lowered, {unknown: True, "xla_backend_optimization_level": 0})
    np.testing.assert_allclose(np.asarray(compiled(jnp.arange(4.0))), 2 * np.sin(np.arange(4.0)))
    assert unknown in runtime.UNKNOWN_XLA_OPTIONS
    assert "xla_backend_optimization_level" not in runtime.UNKNOWN_XLA_OPTIONS
    with pytest.raises(Exception, match="xla_backend_optimization_level"):  # a known option's bad value
        runtime.compile_lowered(lowered, {"xla_backend_optimization_level": "not a level"})


def test_an_unknown_option_s_stand_in_is_taken_unless_the_program_sets_it(monkeypatch):
    """An option this XLA does not know compiles with its stand-in (`XLA_OPTION_STAND_INS`:
    the loop emitters' is LLVM's level 1), unless the program's own options set what the
    stand-in would (a quick program's level 0 stays 0); and this XLA's loop emitters' switch is
    found out as XLA itself answers it."""
    import jax
    import jax.numpy as jnp
    import pytest

    from cohflash_jax import runtime

    lowered = jax.jit(lambda x: jnp.cumsum(jnp.sin(x))).lower(jnp.arange(5.0))
    unknown = "xla_cpu_another_option_no_xla_has"
    # a stand-in XLA refuses shows that it was asked for
    monkeypatch.setitem(runtime.XLA_OPTION_STAND_INS, unknown, {"xla_backend_optimization_level": "not a level"})
    with pytest.raises(Exception, match="xla_backend_optimization_level"):
        runtime.compile_lowered(lowered, {unknown: True})
    assert unknown in runtime.UNKNOWN_XLA_OPTIONS
    compiled = runtime.compile_lowered(lowered, {unknown: True, "xla_backend_optimization_level": 0})
    np.testing.assert_allclose(np.asarray(compiled(jnp.arange(5.0))), np.cumsum(np.sin(np.arange(5.0))), rtol=1e-6)
    # the loop emitters: known to this XLA, or left out for their stand-in
    switch = runtime.QUICK_COMPILE_CPU_OPTIONS
    try:
        lowered.compile(compiler_options=switch)
        has_loop_emitters = True
    except Exception as error:
        assert "No such compile option" in str(error), error
        has_loop_emitters = False
    runtime.compile_lowered(lowered, switch)
    assert (set(switch) & runtime.UNKNOWN_XLA_OPTIONS == set()) is has_loop_emitters
    assert set(switch) <= set(runtime.XLA_OPTION_STAND_INS)


def test_a_program_prepared_in_a_thread_is_got_once_and_a_call_meanwhile_waits(tmp_path, monkeypatch):
    """`prepare` gets a program from its arguments' shapes (`jax.ShapeDtypeStruct`s placed on
    a device) in another thread; a call made while it compiles waits for that compile instead
    of compiling the program again, and runs it; a preparation made while a call compiles
    leaves the program to the call (it neither compiles nor loads it). A preparation that
    fails leaves the call to compile the program itself."""
    import threading

    import jax
    import jax.numpy as jnp

    from cohflash_jax import runtime

    monkeypatch.setattr(runtime.EXECUTABLES, "folder", tmp_path)  # a cold cache of this test's own
    started, compiled_in = threading.Event(), []
    compile_now = runtime.compile_lowered

    def slow_compile(*args, **kwargs):  # the compile takes long enough for a call to arrive
        compiled_in.append(threading.current_thread().name)
        started.set()
        threading.Event().wait(0.5)
        return compile_now(*args, **kwargs)

    monkeypatch.setattr(runtime, "compile_lowered", slow_compile)

    @runtime.async_filter_jit
    def scaled_sums(x, factor):
        return jnp.cumsum(jnp.sin(x) * factor)

    x = jnp.linspace(0.0, 3.0, 999)
    like = jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding)
    thread = threading.Thread(target=scaled_sums.prepare, args=(like, 2.0), name="preparing")
    thread.start()
    assert started.wait(60)
    out = scaled_sums(x, 2.0)  # while the thread compiles
    thread.join()
    assert compiled_in == ["preparing"] and len(list(tmp_path.glob("scaled_sums-*.exe"))) == 1
    np.testing.assert_allclose(np.asarray(out), np.cumsum(np.sin(np.asarray(x)) * 2.0), rtol=1e-12)
    scaled_sums.prepare(like, 2.0)  # already there: nothing to do
    assert compiled_in == ["preparing"]
    # the other way round: a preparation made while a call compiles leaves the program to it
    started.clear()
    loaded = runtime.EXECUTABLES.loaded
    thread = threading.Thread(target=scaled_sums, args=(x, 4.0), name="calling")
    thread.start()
    assert started.wait(60)
    scaled_sums.prepare(like, 4.0)
    thread.join()
    assert compiled_in == ["preparing", "calling"] and runtime.EXECUTABLES.loaded == loaded

    monkeypatch.setattr(runtime, "compile_lowered", compile_now)
    get_program, asked = runtime.EXECUTABLES.program, len(compiled_in)

    def failing_get(*args, **kwargs):
        compiled_in.append(threading.current_thread().name)
        if threading.current_thread().name == "failing":
            raise RuntimeError("no program here")
        return get_program(*args, **kwargs)

    monkeypatch.setattr(runtime.EXECUTABLES, "program", failing_get)
    other, raised = jax.ShapeDtypeStruct((7,), x.dtype, sharding=x.sharding), []
    thread = threading.Thread(
        target=lambda: raised.append(pytest.raises(RuntimeError, scaled_sums.prepare, other, 3.0))
    )
    thread.name = "failing"
    thread.start()
    thread.join()
    assert raised  # the preparation raised in its thread
    np.testing.assert_allclose(np.asarray(scaled_sums(jnp.ones(7), 3.0)), 3 * np.sin(1.0) * np.arange(1, 8))
    assert compiled_in[asked:] == ["failing", "MainThread"]


def test_a_dispatcher_prepares_the_inversion_a_tile_of_a_long_sweep_runs(tmp_path, monkeypatch):
    """`TileDispatcher.prepare` compiles, from a tile's shapes alone, the very inversion program
    each device then runs on its sub-tiles (a long sweep: the I/Q programs are traced for their
    outputs' shapes only): dispatching the tile compiles the two I/Q programs, not a second
    inversion, and the results are the unprepared run's."""
    import jax

    import cohflash_jax as cf
    from cohflash_jax import runtime
    from cohflash_jax.reconstruct import ReconstructOptions, TileDispatcher, build_plan
    from cohflash_jax.reconstruct.programs import SPLIT_AXIS_MIN_FRAMES

    inst = cf.Instrument.paper(SPLIT_AXIS_MIN_FRAMES)
    frames = np.asarray(cf.simulate(cf.planar(12.0, 0.9, effects=("shot_noise",)), inst, 4, 8, jax.random.key(5)))
    frames = frames.reshape(4, SPLIT_AXIS_MIN_FRAMES, -1)
    monkeypatch.setattr(runtime.EXECUTABLES, "folder", tmp_path)
    with runtime.quick_compile():
        plan = build_plan(inst, ReconstructOptions(method="ml", progress=False), 16383.0)
        dispatcher = TileDispatcher(plan, sub_px=16)  # two sub-tiles: one a device where there are two
        before = runtime.EXECUTABLES.compiled
        like = jax.ShapeDtypeStruct(frames.shape, frames.dtype)
        dispatcher.prepare(like).result(timeout=600)
        assert runtime.EXECUTABLES.compiled - before == 1  # the inversion alone
        assert [p.name.split("-")[0] for p in tmp_path.glob("*.exe")] == ["invert_sequence"]
        prepared = dispatcher.dispatch(frames).gather()
        assert runtime.EXECUTABLES.compiled - before == 3  # and the two I/Q programs
    monkeypatch.setattr(runtime.EXECUTABLES, "folder", None)  # no cache: compiled afresh, unprepared
    with runtime.quick_compile():
        plain = TileDispatcher(plan, sub_px=16).dispatch(frames).gather()
    for k in plain:
        np.testing.assert_array_equal(prepared[k], plain[k], err_msg=k)


def test_an_executable_cache_compile_leaves_no_entry_in_jaxs_own_cache(tmp_path, monkeypatch):
    """An executable cache compile has a key of its own in JAX's persistent cache, never read
    again (`ExecutableCache._compile`): its executable goes to the executable cache alone
    (`runtime.JAX_CACHE_ENTRIES`), not serialised a second time into JAX's, while a plain
    `jax.jit` program of the same process still gets JAX's entry."""
    from pathlib import Path

    import jax.numpy as jnp

    from cohflash_jax import runtime

    folder = Path(jax.config.jax_compilation_cache_dir)

    def only_in_the_executable_cache(x):
        return x * 3.0 + 1.0

    def also_in_jaxs_own_cache(x):
        return x * 5.0 - 1.0

    monkeypatch.setattr(runtime.EXECUTABLES, "folder", tmp_path)
    x = jnp.arange(7.0)
    np.testing.assert_array_equal(runtime.async_filter_jit(only_in_the_executable_cache)(x), x * 3.0 + 1.0)
    np.testing.assert_array_equal(jax.jit(also_in_jaxs_own_cache)(x), x * 5.0 - 1.0)
    assert [p.name.split("-")[0] for p in tmp_path.glob("*.exe")] == ["only_in_the_executable_cache"]
    jax_entries = [p.name for p in folder.glob("jit_*")]
    assert any("also_in_jaxs_own_cache" in name for name in jax_entries), jax_entries
    assert not any("only_in_the_executable_cache" in name for name in jax_entries), jax_entries
    assert runtime.JAX_CACHE_ENTRIES.holders == 0  # JAX's threshold as it was
    assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0


def cpuinfo_names_the_model() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            return any(line.startswith("model name") for line in f)
    except OSError:
        return False


@pytest.mark.skipif(not cpuinfo_names_the_model(), reason="the CPU is read from /proc/cpuinfo's model name")
def test_the_cpu_is_read_without_running_uname(monkeypatch):
    """Each `reconstruct` asks for the CPU's features (the programs' form, the cache's key):
    read from /proc/cpuinfo, without `platform.processor`, which on Linux runs `uname -p` in a
    child process of a process by then holding a GB of memory."""
    import platform

    from cohflash_jax import runtime

    def refuse():
        raise AssertionError("platform.processor was called")

    monkeypatch.setattr(platform, "processor", refuse)
    runtime.cpu_model_and_flags.cache_clear()
    try:
        model, _ = runtime.cpu_model_and_flags()
    finally:
        runtime.cpu_model_and_flags.cache_clear()
    assert model and model != "unknown CPU"


def test_the_cpu_is_named_with_its_family_and_model_numbers():
    """Benchmarks name the CPU by family and model as well as by name: two VMs' "AMD EPYC"
    were a Zen 4 and a Zen 5."""
    from cohflash_jax import runtime

    entry = (
        "processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\n"
        "model name\t: AMD EPYC\nflags\t\t: fpu avx2\n\nprocessor\t: 1\ncpu family\t: 99\nmodel\t\t: 9\n"
    )
    assert runtime.cpu_family_and_model(entry) == "family 25 model 17"
    assert runtime.cpu_family_and_model("processor\t: 0\nmodel name\t: a CPU without numbers\n") is None
    numbers = runtime.cpu_family_and_model()
    if numbers is not None:  # Linux on x86 lists them
        assert f"({numbers})" in runtime.cpu_description()
