"""The executable cache (issue #21): a program compiled in one process is loaded whole in the
next, without tracing, and gives the same results; a damaged entry is compiled afresh."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np

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
    from cohflash_jax.runtime import EXECUTABLES

    key = EXECUTABLES.key(test_a_static_half_without_stable_text_stays_in_memory, (lambda: 0,), None, ())
    assert key is None


def test_quick_compiled_programs_are_kept_apart_and_agree_with_optimised_ones():
    """A region of interest is compiled at XLA's lowest optimisation level (`quick_compile`):
    its programs have entries of their own, and its depths agree with the optimised
    programs' to far below σ."""
    import jax

    import cohflash_jax as cf
    from cohflash_jax.reconstruct import ReconstructOptions, TileDispatcher, build_plan
    from cohflash_jax.runtime import EXECUTABLES, quick_compile

    fun = test_quick_compiled_programs_are_kept_apart_and_agree_with_optimised_ones
    assert EXECUTABLES.key(fun, (1,), None, (), False) != EXECUTABLES.key(fun, (1,), None, (), True)
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
    """A region of interest is padded to its pixel bucket (`engine.pixel_bucket`), so captures
    of 5×5 and 6×6 pixels run the same programs; and the I/Q programs take the plan's I/Q stage
    alone, so a second method on the same capture makes its inversion program only. The padded
    pixels change nothing: the 5×5 capture's depths equal those of its pixels reconstructed
    within a larger one."""
    import jax

    import cohflash_jax as cf
    from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array
    from cohflash_jax.reconstruct.engine import pixel_bucket
    from cohflash_jax.runtime import EXECUTABLES

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
