"""The basics a metrologist expects of the command line: `info` on every format, `--version`,
`simulate --set/--design/--tilt-m`, provenance in depth.h5, and a sweep honest about the
unambiguous range and about Monte Carlo points with nothing valid."""

from __future__ import annotations

import csv
import hashlib
import json
import os
import subprocess
import sys

import h5py
import jax
import numpy as np
import pytest

from cohflash_jax.cli import main


def _run(argv, capsys) -> str:
    assert main(argv) == 0, capsys.readouterr().err
    return capsys.readouterr().out


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("cohflash ")


def test_simulate_set_and_tilt_make_the_instrument_and_target_asked_for(tmp_path, capsys):
    out = tmp_path / "s.h5"
    _run(
        [
            "simulate",
            "planar",
            "--size",
            "6x8",
            "--set",
            "num_steps=64,step_mhz=20,start_ghz=0.5,exposure_ms=2,distance_m=3.2,reflectance=0.25",
            "--tilt-m",
            "0.01,0",
            "--out",
            str(out),
            "--quiet",
        ],
        capsys,
    )
    with h5py.File(out) as f:
        freqs = f["frequencies_hz"][()]
        depth, reflectance = f["truth/depth_m"][()], f["truth/reflectance"][()]
        exposure = f.attrs["exposure_s"]
    np.testing.assert_allclose(freqs, 0.5e9 + 20e6 * np.arange(64))
    assert exposure == pytest.approx(2e-3)
    assert np.allclose(reflectance, 0.25)
    # the tilt: 1 cm across the width, none across the height
    assert depth.mean() == pytest.approx(3.2, abs=1e-3)
    assert np.ptp(depth[0]) == pytest.approx(0.01 * 7 / 8, rel=0.2) and np.ptp(depth[:, 0]) < 1e-9
    text = _run(["info", str(out)], capsys)
    assert "64 frequency steps" in text and "6×8 pixels" in text and "uniform step 20 MHz" in text
    assert "truth: depth_m, reflectance" in text


def test_simulate_design_simulates_the_optimum(tmp_path, capsys):
    design = {
        "format": "cohflash-design",
        "format_version": 1,
        "problem": {"frame_rate_hz": 350.0, "distance_m": 5.0, "reflectance": 0.4},
        "feasible": True,
        "num_frames": 48,
        "variables": {
            "start_hz": 0.2e9,
            "step_hz": 30e6,
            "modulation_index": 1.6,
            "bias_rad": 0.7,
            "exposure_s": 1e-3,
            "probe_power_w": 5e-3,
        },
    }
    path = tmp_path / "design.json"
    path.write_text(json.dumps(design))
    out = tmp_path / "d.h5"
    _run(["simulate", "planar", "--size", "4x4", "--design", str(path), "--out", str(out), "--quiet"], capsys)
    with h5py.File(out) as f:
        np.testing.assert_allclose(f["frequencies_hz"][()], 0.2e9 + 30e6 * np.arange(48))
        assert f.attrs["frame_rate_hz"] == 350.0 and f.attrs["modulation_index"] == pytest.approx(1.6)
        assert np.allclose(f["truth/depth_m"][()], 5.0)
    assert "feasible" in _run(["info", str(path)], capsys)
    design["feasible"] = False
    design["note"] = "too far"
    path.write_text(json.dumps(design))
    assert main(["simulate", "planar", "--design", str(path), "--out", str(tmp_path / "x.h5")]) == 2
    assert "not feasible" in capsys.readouterr().err


def test_depth_records_every_input_and_the_values_applied_and_info_shows_it(tmp_path, capsys):
    capture, depth = tmp_path / "c.h5", tmp_path / "depth.h5"
    _run(["simulate", "planar", "--size", "4x4", "--steps", "64", "--out", str(capture), "--quiet"], capsys)
    calibration = tmp_path / "cal.json"
    calibration.write_text(
        json.dumps(
            {
                "format": "cohflash-calibration",
                "format_version": 1,
                "hybrid": {"phases_rad": [0, 1.6, 3.1, 4.7], "relative_gains": [1, 1.1, 0.9, 1], "offsets_dn": [0] * 4},
                "system_delay_s": 1e-9,
            }
        )
    )
    summary = _run(["reconstruct", str(capture), "--out", str(depth), "--calibration", str(calibration)], capsys)
    assert "CRLB (phase-locked, any method)" in summary or "valid pixels 0" in summary
    with h5py.File(depth) as f:
        provenance = json.loads(f.attrs["provenance"])
        applied = json.loads(f.attrs["calibration_applied"])
    record = provenance["inputs"]["calibration"]
    assert record["sha256"] == hashlib.sha256(calibration.read_bytes()).hexdigest()
    assert record["size_bytes"] == calibration.stat().st_size
    assert provenance["inputs"]["capture"]["sha256"] == hashlib.sha256(capture.read_bytes()).hexdigest()
    assert applied["hybrid_relative_gains"] == [1, 1.1, 0.9, 1] and applied["system_delay_s"] == 1e-9
    text = _run(["info", str(depth)], capsys)
    assert "method ml" in text and "input calibration" in text and "statuses" in text
    assert f"JAX {jax.__version__} on {jax.devices()[0]}" in text  # the device it ran on
    assert "gains [1.0, 1.1, 0.9, 1.0]" in _run(["info", str(calibration)], capsys)


def test_sweep_marks_folded_points_keeps_rows_and_says_why_nothing_was_valid(tmp_path, capsys):
    """num_steps 64 at 20 MHz: unambiguous to 3.75 m, so 10 m is beyond it. A second run with
    other distances keeps the first run's rows. A Monte Carlo far below threshold says why."""
    out = tmp_path / "sweep.csv"
    fixed = ["--set", "num_steps=64,step_mhz=20,reflectance=0.5", "--quiet"]
    text = _run(["sweep", "--axis", "distance_m=2,10", *fixed, "--out", str(out)], capsys)
    assert "1 of 2 points put the target beyond the unambiguous range" in text
    rows = list(csv.DictReader(open(out)))
    assert [float(r["beyond_ambiguity"]) for r in rows] == [0.0, 1.0]
    _run(["sweep", "--axis", "distance_m=3", *fixed, "--out", str(out)], capsys)
    assert sorted(float(r["distance_m"]) for r in csv.DictReader(open(out))) == [2.0, 3.0, 10.0]
    dim = ["--set", "num_steps=64,step_mhz=20,probe_power_mw=0.001", "--mc-trials", "9", "--quiet"]
    text = _run(
        ["sweep", "--axis", "distance_m=2", "--mc", "distance_m=2", *dim, "--out", str(tmp_path / "d.csv")], capsys
    )
    assert "no valid pixel" in text and "dB threshold" in text
    (row,) = csv.DictReader(open(tmp_path / "d.csv"))
    assert row["mc_note"].startswith("no valid pixel") and float(row["mc_truth_m"]) == pytest.approx(2.0)
    info = _run(["info", str(out)], capsys)
    assert "3 points over distance_m" in info and "1 points beyond the unambiguous range" in info


def test_sweep_workers_die_with_their_parent(tmp_path):
    """A SIGKILLed sweep left its worker processes running, holding gigabytes: its pool's
    workers now ask the kernel to kill them when their parent dies."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = (
        "import multiprocessing, time\n"
        "from cohflash_jax.design.grid import die_with_parent\n"
        "if __name__ == '__main__':\n"
        "    pool = multiprocessing.get_context('spawn').Pool(1, initializer=die_with_parent)\n"
        "    pid = pool.apply(__import__('os').getpid)\n"
        "    pool.apply_async(time.sleep, (60,))  # busy: it would not notice its parent's death\n"
        "    time.sleep(0.5)\n"
        "    print(pid, flush=True)\n"
        "    time.sleep(60)\n"
    )
    (tmp_path / "parent.py").write_text(script)
    parent = subprocess.Popen([sys.executable, str(tmp_path / "parent.py")], stdout=subprocess.PIPE, text=True)
    worker = int(parent.stdout.readline())
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            return
        time.sleep(0.05)
    os.kill(worker, signal.SIGKILL)
    raise AssertionError("the worker outlived its killed parent")


def test_every_option_has_help_and_shows_its_default():
    import argparse

    from cohflash_jax.cli import build_parser

    def parsers(p):
        yield p
        for action in p._actions:  # noqa: SLF001 (argparse has no public list of actions)
            if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
                for sub in action.choices.values():
                    yield from parsers(sub)

    missing = []
    for parser in parsers(build_parser()):
        text = parser.format_help()
        for action in parser._actions:  # noqa: SLF001
            if isinstance(action, argparse._SubParsersAction) or action.dest in ("help", "version"):  # noqa: SLF001
                continue
            if not action.help:
                missing.append(f"{parser.prog} {'/'.join(action.option_strings) or action.dest}")
            elif action.default not in (None, False, argparse.SUPPRESS) and not action.required:
                assert "default" in text, parser.prog
    assert not missing, missing


def test_an_interrupted_sweep_keeps_every_finished_monte_carlo_point(tmp_path, monkeypatch):
    """Ctrl-C during the Monte Carlo points of a chunk: the points finished before it are in
    the CSV (a checkpoint at the interrupt), and a rerun resumes the rest."""
    import cohflash_jax.design.grid as grid

    calls = []

    def fake(args):
        calls.append(args)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return {"mc_precision_mm": 1.0, "mc_bias_mm": 0.0, "mc_valid_fraction": 1.0, "mc_trials": 4}

    monkeypatch.setattr(grid, "monte_carlo_job", fake)
    axes = [("distance_m", np.array([10.0, 20.0, 30.0, 40.0]))]
    out = tmp_path / "s.csv"
    with pytest.raises(KeyboardInterrupt):
        grid.run_sweep(axes, out, fixed={"num_steps": 64.0}, mc_all=True, progress=False)
    rows = list(csv.DictReader(open(out)))
    assert sorted(float(r["distance_m"]) for r in rows if r["mc_trials"]) == [10.0, 20.0]
    grid.run_sweep(axes, out, fixed={"num_steps": 64.0}, mc_all=True, progress=False)
    assert len(calls) == 3 + 2  # only the two unfinished points ran again
    assert all(r["mc_trials"] for r in csv.DictReader(open(out)))


def test_stream_reconstructs_a_sequence_in_one_process_and_goes_on_past_a_bad_capture(tmp_path, capsys):
    """`cohflash stream`: a depth file per capture, the rate in maps/s; a corrupt capture is
    reported by name and the others are still written (exit status 1)."""
    settings = (  # the 10 Hz mode (its unambiguous range is 0.44 m)
        "num_steps=35,step_mhz=171.4,start_ghz=0.1714,exposure_ms=2,frame_rate_hz=350,probe_power_mw=158.6,"
        "distance_m=0.3"
    )
    captures = []
    for k in range(2):
        captures.append(tmp_path / f"c{k}.h5")
        _run(
            [
                "simulate",
                "planar",
                "--size",
                "4x4",
                "--set",
                settings,
                "--seed",
                str(k),
                "--out",
                str(captures[k]),
                "--quiet",
            ],
            capsys,
        )
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not HDF5")
    out_dir = tmp_path / "maps"
    assert main(["stream", str(captures[0]), str(bad), str(captures[1]), "--out-dir", str(out_dir)]) == 1
    out, err = capsys.readouterr()
    assert "bad.h5" in err and "1 of 3 captures failed" in err
    assert "2 maps in" in out and "maps/s" in out
    for k in range(2):
        with h5py.File(out_dir / f"c{k}.depth.h5") as f:
            assert f["depth_m"].shape == (4, 4) and f["valid"][()].mean() > 0.9
            assert np.median(f["depth_m"][()]) == pytest.approx(0.3, abs=0.01)
            # each depth file records its own capture, hashed whole (the records are made ahead)
            record = json.loads(f.attrs["provenance"])["inputs"]["capture"]
        assert record["path"] == str(captures[k].resolve())
        assert record["sha256"] == hashlib.sha256(captures[k].read_bytes()).hexdigest()
    assert not (out_dir / "bad.depth.h5").exists()
    # two captures of one name would overwrite each other: refused before any work
    assert main(["stream", str(captures[0]), str(captures[0]), "--out-dir", str(tmp_path / "again")]) == 2
    assert "would both write" in capsys.readouterr().err


def test_a_streams_records_are_made_ahead_at_idle_priority_or_by_the_caller(tmp_path, monkeypatch):
    """`cohflash stream` hashes its captures ahead in a thread that runs only where a core
    would idle (Linux's SCHED_IDLE); a record that thread has not made in time (a busy
    machine starves it) is made by the caller, and without the priority there is no thread."""
    import threading

    from cohflash_jax.cli import stream
    from cohflash_jax.cli.common import file_record

    paths = []
    for k in range(4):
        paths.append(tmp_path / f"f{k}.bin")
        paths[-1].write_bytes(bytes([k]) * (1000 + k))
    if not hasattr(os, "SCHED_IDLE"):
        pytest.skip("no SCHED_IDLE here")
    makers = []

    def logged_record(path):
        makers.append(threading.current_thread().name)
        return file_record(path)

    monkeypatch.setattr(stream, "file_record", logged_record)
    records = stream.RecordsAhead(paths)
    made = []
    try:
        assert records.pool.submit(os.sched_getscheduler, 0).result(timeout=60) == os.SCHED_IDLE
        for k in range(4):
            records.futures[k].result(timeout=60)  # made ahead (the other tests' workers may keep it waiting)
            if k == 3:  # a file changed after its record was made: recorded as it is now
                paths[3].write_bytes(b"changed")
                os.utime(paths[3], (1e9, 1e9))
            made.append(records.record(k)())
    finally:
        records.close()
    assert made == [file_record(p) for p in paths] and made[3]["size_bytes"] == 7
    assert [name.startswith("records-ahead") for name in makers] == [True] * 4 + [False]

    # a thread that never gets to run: each record is made by the caller after the grace
    stalled, makers[:] = threading.Event(), []
    monkeypatch.setattr(stream, "lowest_cpu_priority", lambda: stalled.wait(30))
    records = stream.RecordsAhead(paths)
    try:
        made = [records.record(k)() for k in range(4)]
    finally:
        stalled.set()
        records.close()
    assert made == [file_record(p) for p in paths]
    assert makers[:4] == [threading.current_thread().name] * 4

    monkeypatch.delattr(os, "SCHED_IDLE")
    records = stream.RecordsAhead(paths)
    assert records.pool is None and records.record(0) is None
    records.close()


def test_the_cohflash_process_ends_with_its_status_and_complete_outputs(tmp_path):
    """`cohflash` skips the interpreter's teardown (`runtime.exit_process`): the whole process
    still exits with the command's status, its outputs complete and readable, an error's
    message printed; where teardown has work left (a thread still running, an HDF5 file open
    for writing) it is done, not cut off."""
    import subprocess
    import sys

    command = [sys.executable, "-m", "cohflash_jax.cli"]
    capture, depth = tmp_path / "x.h5", tmp_path / "d.h5"
    for argv in (
        ["simulate", "planar", "--size", "4x4", "--steps", "64", "--out", str(capture), "--quiet"],
        ["reconstruct", str(capture), "--out", str(depth), "--method", "dft"],
    ):
        done = subprocess.run(command + argv, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    assert "valid pixels" in done.stdout  # the summary reached the pipe before the process ended
    with h5py.File(depth) as f:
        assert f["depth_m"].shape == (4, 4) and np.all(np.isfinite(f["depth_m"][()]))
    done = subprocess.run(
        command + ["reconstruct", str(tmp_path / "missing.h5"), "--out", str(depth)], text=True, capture_output=True
    )
    assert done.returncode == 2 and "missing.h5" in done.stderr

    script = (
        "import sys, threading, time, h5py\n"
        "from cohflash_jax.runtime import exit_process\n"
        "mode, target = sys.argv[1:]\n"
        "if mode == 'thread':  # a non-daemon thread still writing when the command returns\n"
        "    threading.Thread(target=lambda: (time.sleep(0.5), open(target, 'w').write('done'))).start()\n"
        "elif mode == 'hdf5':  # a file left open for writing, its data not yet flushed\n"
        "    f = h5py.File(target, 'w'); f['x'] = list(range(1000))\n"
        "else:\n"
        "    import atexit; atexit.register(lambda: open(target, 'w').write('handler ran'))\n"
        "print('out', end='')\n"
        "exit_process(3)\n"
    )
    (tmp_path / "ends.py").write_text(script)
    for mode, check in (
        ("thread", lambda p: p.read_text() == "done"),
        ("hdf5", lambda p: h5py.File(p)["x"][-1] == 999),
        ("atexit", lambda p: p.read_text() == "handler ran"),
    ):
        target = tmp_path / f"{mode}.out"
        done = subprocess.run(
            [sys.executable, str(tmp_path / "ends.py"), mode, str(target)], capture_output=True, text=True
        )
        assert done.returncode == 3 and done.stdout == "out", (mode, done.stderr)
        assert check(target), mode


def test_a_cohflash_process_runs_numpys_blas_on_one_thread_unless_told_otherwise(monkeypatch, tmp_path):
    """A `cohflash` command's interpreter sets OPENBLAS_NUM_THREADS=1 before NumPy loads
    OpenBLAS (its pool spun beside XLA's threads during the carrier survey); a user's own
    setting stands, and a library user's or a test run's process is left as it is. Checked
    in a process run as `cohflash`: the thread count OpenBLAS itself reports, where it can."""
    from cohflash_jax.process import single_threaded_blas_for_cli

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    assert not single_threaded_blas_for_cli(["python", "-m", "pytest", "tests"])
    assert "OPENBLAS_NUM_THREADS" not in os.environ
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    assert not single_threaded_blas_for_cli(["/venv/bin/cohflash", "/venv/bin/cohflash", "reconstruct", "c.h5"])
    assert os.environ["OPENBLAS_NUM_THREADS"] == "2"
    monkeypatch.delenv("OPENBLAS_NUM_THREADS")
    script = tmp_path / "cohflash"  # the console script's name: `cli_command` reads "info"
    names = ("scipy_openblas_get_num_threads64_", "openblas_get_num_threads64_", "openblas_get_num_threads")
    script.write_text(
        "import ctypes, os\n"
        "import cohflash_jax\n"
        "threads = None\n"
        "for line in open('/proc/self/maps'):\n"
        "    if 'openblas' in line and threads is None:\n"
        "        lib = ctypes.CDLL(line.split()[-1])\n"
        f"        for name in {names!r}:\n"
        "            if hasattr(lib, name):\n"
        "                threads = getattr(lib, name)()\n"
        "                break\n"
        "print(os.environ.get('OPENBLAS_NUM_THREADS'), threads)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    done = subprocess.run([sys.executable, str(script), "info"], capture_output=True, text=True, env=env, check=True)
    setting, threads = done.stdout.split()
    assert setting == "1"
    assert threads in ("1", "None"), done.stdout  # None: no OpenBLAS found in this process (another BLAS)


def test_a_jaxlib_that_hangs_with_two_cpu_devices_gets_one():
    """jaxlib 0.11's CPU client hung a reconstruction over two CPU devices: a process under it
    gets one (`runtime.SINGLE_CPU_STREAM_JAXLIBS`); the versions measured not to hang keep two."""
    from cohflash_jax.runtime import several_cpu_streams_run

    assert not several_cpu_streams_run("0.11.2")
    assert several_cpu_streams_run("0.10.2") and several_cpu_streams_run("0.12.0.1")
    script = "from cohflash_jax.runtime import use_cpu_streams\nprint(use_cpu_streams(2))\n"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert done.stdout.split()[-1] == ("2" if several_cpu_streams_run() else "1")


def test_a_cohflash_process_collects_no_garbage_while_it_imports(tmp_path):
    """In a process run as `cohflash`, garbage collection is off while the package loads and
    on again, the imports' objects frozen, once the command module is loaded; a library
    user's process keeps its collector as it was throughout."""
    # Python 3.12 starts with objects of its own in the permanent generation
    probe = (
        "import gc\n"
        "at_start = gc.get_freeze_count()\n"
        "import cohflash_jax\n"
        "print(gc.isenabled())\n"
        "import cohflash_jax.cli\n"
        "print(gc.isenabled(), gc.get_freeze_count() > at_start)\n"
    )
    script = tmp_path / "cohflash"
    script.write_text(probe)
    as_command = subprocess.run([sys.executable, str(script), "info"], capture_output=True, text=True, check=True)
    assert as_command.stdout.split() == ["False", "True", "True"]
    as_library = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert as_library.stdout.split() == ["True", "True", "False"]


def _pieceable_capture(path, n=1200, seed=5, extra_bytes=0):
    """A 64×64 capture from the independent writer, chunked as cohflash writes (one CCD, 4
    frames, 32 rows, whole rows), whose 32-row tiles are read into pieces of 8 rows; with a
    dataset of `extra_bytes` of the user's own beside the frames (a larger file)."""
    from .independent_writer import PAPER_FREQUENCIES_HZ, Writer

    rng = np.random.default_rng(seed)
    depth = 30.5 + 0.2 * rng.random((64, 64))
    Writer(frequencies_hz=PAPER_FREQUENCIES_HZ[:n]).write(path, depth, rng, chunks=(1, 4, 32, 64))
    if extra_bytes:
        with h5py.File(path, "a") as f:
            f.create_dataset("notes/padding", data=np.ones(extra_bytes, np.uint8))
    return path


def test_the_first_tile_read_early_is_laid_out_as_the_reader_lays_it_out(tmp_path):
    """`early_read.read_first_tile` (a `cohflash reconstruct` process's child, run here in
    this process) puts the capture's first tile where `engine.PieceReader` puts it in a buffer
    at the same place, byte for byte, and reports that layout and the frames' chunk index,
    which a reader of the same file, unchanged, takes (and lists again otherwise); the report
    survives its way through the pipe, and a report cut short is none. A capture whose tiles
    are not read into pieces (too small, compressed) is left, with the reason, and a
    `--tile-rows` the command line gives is the one it reads."""
    import mmap

    from cohflash_jax import early_read
    from cohflash_jax.capture import Capture
    from cohflash_jax.chunk_reads import DirectChunkReader
    from cohflash_jax.reconstruct.engine import PieceReader

    capture = _pieceable_capture(tmp_path / "c.h5")
    mapping = mmap.mmap(-1, 64 * 2**20)
    report = early_read.read_first_tile(mapping, str(capture), 32)
    assert report["read"], report
    with h5py.File(capture) as f:
        listed = DirectChunkReader(f["frames"], capture)
        np.testing.assert_array_equal(report["index"], listed.offsets)
        assert report["index"].shape == (4, 300, 2) and (report["index"] > 0).all()
        known = (report["file"], report["index"])
        taken = DirectChunkReader(f["frames"], capture, known=known)
        assert taken.offsets is report["index"]
        stale = DirectChunkReader(f["frames"], capture, known=([0, 0, 0, 0, 0], report["index"] + 1))
        np.testing.assert_array_equal(stale.offsets, listed.offsets)  # another file's: listed again
        for reader in (listed, taken, stale):
            reader.close()
    data = early_read.encode_report(report)  # as the child sends it
    back = early_read.parse_report(data)
    np.testing.assert_array_equal(back.pop("index"), report["index"])
    assert back == {k: v for k, v in report.items() if k != "index"}
    assert early_read.parse_report(data[:-8]) == {} and early_read.parse_report(b"") == {}
    with Capture(capture) as c:
        reader = PieceReader.of(c, 32)
        tile = reader.read(0)  # read by the reader itself, into a buffer of its own
        layout = reader.layout.key
        assert report["layout"] == layout == [1200, 64, 64, "uint16", 32, 8, 4 * 1200 * 512 * 2]
        assert report["file"] == early_read.file_identity(c.direct_reader.fd)
        raw = np.frombuffer(mapping, np.uint8)
        base = report["address"] - raw.ctypes.data
        for k, piece in enumerate(tile.pieces):
            start = base + k * reader.layout.stride
            np.testing.assert_array_equal(raw[start : start + piece.nbytes].view(np.uint16).reshape(piece.shape), piece)
        np.testing.assert_array_equal(tile.frames[:, :, 1, :].reshape(4, 1200, 8, 64), c.frames[:, :, 8:16, :])
    # a small capture's tiles, and a compressed capture's, are read as before
    small = tmp_path / "small.h5"
    assert main(["simulate", "planar", "--size", "8x8", "--steps", "64", "--out", str(small), "--quiet"]) == 0
    said = early_read.read_first_tile(mapping, str(small))
    assert not said["read"] and said["why"] == "its tiles are not read in pieces"
    packed = tmp_path / "packed.h5"
    with h5py.File(capture) as f, h5py.File(packed, "w") as g:
        g.create_dataset("frames", data=f["frames"][()], chunks=(1, 4, 32, 64), compression="gzip")
    assert early_read.read_first_tile(mapping, str(packed))["why"] == "frames are filtered (compressed)"
    argv = ["cohflash", "reconstruct", "c.h5", "--out", "d.h5"]
    assert early_read.tile_rows_option(argv) is None
    assert early_read.tile_rows_option([*argv, "--tile-rows", "16"]) == 16
    assert early_read.tile_rows_option([*argv, "--tile-rows=48"]) == 48
    assert early_read.tile_rows_option([*argv, "--tile-rows", "x"]) is None


def test_a_reconstruct_process_reads_its_first_tile_while_it_imports(tmp_path):
    """`cohflash reconstruct FILE` forks a child as the package starts importing, which reads
    the first tile into shared memory the tile reader then takes as read: the same depth file
    as a process that reads the tile itself, the file having changed after its child read it.
    Other commands, a library user's or a test run's process, a Dask run, a registered capture
    (read elsewhere) and a small file fork nothing."""
    from cohflash_jax import early_read

    # above `EARLY_READ_MIN_BYTES` with a dataset of the user's own; its sub-tiles' programs
    # those of tests/test_carrier.py
    capture = _pieceable_capture(tmp_path / "c.h5", extra_bytes=early_read.EARLY_READ_MIN_BYTES)
    assert capture.stat().st_size >= early_read.EARLY_READ_MIN_BYTES
    cli = ["python", "-m", "cohflash_jax.cli", "reconstruct", str(capture), "--out", "d.h5"]
    for argv in (["python", "-m", "pytest"], [*cli[:3], "info", str(capture)], [*cli, "--scheduler", "processes"]):
        assert not early_read.start_for_cli(argv)
    assert not early_read.start_for_cli([*cli, "--registration", str(capture)])
    assert not early_read.start_for_cli(cli[:4] + [str(tmp_path / "missing.h5")])
    small = tmp_path / "small.h5"  # read in a few hundredths of a second: no child
    assert main(["simulate", "planar", "--size", "8x8", "--steps", "64", "--out", str(small), "--quiet"]) == 0
    assert not early_read.start_for_cli(cli[:4] + [str(small)])
    assert early_read.take_mapping(1) is None and early_read.outcome() is None  # nothing started
    probe = (
        "import os, sys\n"
        "sys.orig_argv = [sys.executable, '-m', 'cohflash_jax.cli', *sys.argv[2:]]  # as the command starts\n"
        "import cohflash_jax\n"
        "from cohflash_jax import early_read\n"
        "if sys.argv[1] == 'touched':  # the capture written again once the child read it\n"
        "    early_read.wait_for_child()\n"
        "    st = os.stat(sys.argv[3])\n"
        "    os.utime(sys.argv[3], ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))\n"
        "from cohflash_jax.cli import main\n"
        "assert main(sys.argv[2:]) == 0\n"
        "outcome = early_read.outcome()\n"
        "print(None if outcome is None else outcome['held'], outcome and outcome['report'].get('read'))\n"
    )
    outs = {}
    expected = {"early": "True True", "touched": "False True"}  # the latter read by the process itself
    for name, said in expected.items():
        out = tmp_path / f"{name}.h5"
        args = [name, "reconstruct", str(capture), "--out", str(out), "--tile-rows", "32", "--quiet"]
        done = subprocess.run([sys.executable, "-c", probe, *args], capture_output=True, text=True, check=False)
        assert done.returncode == 0, done.stderr[-2000:]
        assert done.stdout.split("\n")[-2] == said, done.stdout
        with h5py.File(out) as f:
            outs[name] = f["depth_m"][()], f["fit_status"][()], f["sigma_m"][()]
    for a, b in zip(outs["early"], outs["touched"], strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_cohflash_process_finds_a_rocm_plugin_by_its_folder_name(tmp_path):
    """While a `cohflash` command imports JAX, JAX's search for a ROCm plugin (which reads the
    metadata of every installed distribution) is given only the distributions whose folders are
    a ROCm plugin's: a plugin installed where Python looks is still found and imported, the
    scan's function is restored after, and a library user's import is left as it is."""
    from cohflash_jax import process

    site = tmp_path / "site"
    (site / "jax_rocm9_plugin").mkdir(parents=True)
    (site / "jax_rocm9_plugin" / "__init__.py").write_text("")
    (site / "jax_rocm9_plugin" / "rocm_plugin_extension.py").write_text("FOUND = True\n")
    info = site / "jax_rocm9_plugin-0.1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: jax-rocm9-plugin\nVersion: 0.1.0\n")
    (site / "other_tool-1.0.dist-info").mkdir()  # not a plugin: not listed
    (site / "other_tool-1.0.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: other-tool\n")
    found = process.rocm_plugin_distributions([str(site), str(tmp_path / "missing"), ""])
    assert [d.metadata["Name"] for d in found] == ["jax-rocm9-plugin"]
    probe = (  # counts the calls that list every distribution
        "import sys, importlib.metadata\n"
        "listed, every = [], importlib.metadata.distributions\n"
        "importlib.metadata.distributions = lambda **kw: (listed.append(kw), every(**kw))[1]\n"
        "counted = importlib.metadata.distributions\n"
        "sys.orig_argv = [sys.executable, '-m', 'cohflash_jax.cli', *sys.argv[1:]]  # as the command starts\n"
        "import cohflash_jax\n"
        "from jax._src.numpy import array_constructors\n"
        "found = getattr(array_constructors.rocm_plugin_extension, 'FOUND', None)\n"
        "print(found, importlib.metadata.distributions is counted, len(listed) > 0)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    for argv, said in ((["info", "x.h5"], "True True False"), ([], "True True True")):
        command = [sys.executable, "-c", probe, *argv]
        done = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
        assert done.returncode == 0, done.stderr[-2000:]
        assert done.stdout.strip().split("\n")[-1] == said, done.stdout
    import importlib.metadata

    every = importlib.metadata.distributions
    # not a command, or JAX already imported (as in this test run): the scan is left as it is
    for argv in (["python", "-m", "pytest"], ["python", "-m", "cohflash_jax.cli", "reconstruct", "x.h5"]):
        with process.rocm_plugin_scan_by_folder_names_for_cli(argv):
            assert importlib.metadata.distributions is every
            assert len(list(importlib.metadata.distributions())) > 1


def test_a_cohflash_process_takes_gpu_memory_on_demand_unless_told_otherwise(monkeypatch):
    """A `cohflash` command's interpreter sets XLA_PYTHON_CLIENT_PREALLOCATE=false before JAX
    starts (reserving three quarters of an H200 cost each full-capture run 1.4 s); a user's own setting
    stands, and a library user's or a test run's process is left as it is."""
    from cohflash_jax.process import gpu_memory_on_demand_for_cli

    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    assert not gpu_memory_on_demand_for_cli(["python", "-m", "pytest", "tests"])
    assert "XLA_PYTHON_CLIENT_PREALLOCATE" not in os.environ
    assert gpu_memory_on_demand_for_cli(["python", "-m", "cohflash_jax.cli", "reconstruct", "c.h5"])
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    monkeypatch.setenv("XLA_PYTHON_CLIENT_PREALLOCATE", "true")
    assert not gpu_memory_on_demand_for_cli(["/venv/bin/cohflash", "/venv/bin/cohflash", "simulate", "traffic"])
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "true"


def test_a_small_capture_is_reconstructed_on_the_cpu_unless_told_otherwise(monkeypatch, tmp_path):
    """`cohflash reconstruct` on a capture (a file or a Zarr store) under `GPU_MIN_CAPTURE_BYTES` sets
    JAX_PLATFORMS=cpu before JAX starts (a GPU's backend start cost more than a region of
    interest's whole run); a larger capture, another command, a library user's or a test run's
    process, and a user's own JAX_PLATFORMS are left as they are."""
    from cohflash_jax.process import GPU_MIN_CAPTURE_BYTES, small_captures_on_cpu_for_cli

    small, large = tmp_path / "roi.h5", tmp_path / "full.h5"
    small.write_bytes(b"\0" * 4096)
    with open(large, "wb") as f:  # sparse: its size without writing it
        f.truncate(GPU_MIN_CAPTURE_BYTES)
    cli = ["python", "-m", "cohflash_jax.cli"]
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    assert not small_captures_on_cpu_for_cli(["python", "-m", "pytest", str(small)])
    assert not small_captures_on_cpu_for_cli([*cli, "reconstruct", str(large), "--out", str(small)])
    assert not small_captures_on_cpu_for_cli([*cli, "stream", str(small)])
    assert not small_captures_on_cpu_for_cli([*cli, "reconstruct", str(tmp_path / "missing.h5")])
    assert "JAX_PLATFORMS" not in os.environ
    assert small_captures_on_cpu_for_cli([*cli, "reconstruct", str(small), "--out", str(tmp_path / "d.h5")])
    assert os.environ["JAX_PLATFORMS"] == "cpu"
    monkeypatch.setenv("JAX_PLATFORMS", "cuda")
    assert not small_captures_on_cpu_for_cli([*cli, "reconstruct", str(small)])
    assert os.environ["JAX_PLATFORMS"] == "cuda"
    # a Zarr store counts by its frames' size (shape × item size), not by what its folder holds
    from cohflash_jax.capture import CaptureHeader
    from cohflash_jax.capture_zarr import create_zarr_capture

    attrs = {"exposure_s": 4e-3, "frame_rate_hz": 200.0, "wavelength_m": 1550e-9}
    frequencies = np.linspace(0.1e9, 6e9, 3000)
    monkeypatch.delenv("JAX_PLATFORMS")
    for side, on_cpu in ((16, True), (320, False)):  # uint16 frames: 6 MB; 1.97 GB (no chunk written)
        store = create_zarr_capture(tmp_path / f"{side}.zarr", CaptureHeader(frequencies, side, side, np.uint16, attrs))
        assert small_captures_on_cpu_for_cli([*cli, "reconstruct", str(store), "--out", str(small)]) is on_cpu
        assert os.environ.pop("JAX_PLATFORMS", None) == ("cpu" if on_cpu else None)


def test_the_packages_bytecode_is_compiled_ahead_where_python_may_not_write_it(monkeypatch, tmp_path):
    """`compile_package_bytecode` (what `make` and the benchmarks run) leaves every module of the
    packages bytecode that a process told not to write any (`PYTHONDONTWRITEBYTECODE`, as on
    some CI machines) loads instead of compiling the sources again; a module edited since is
    compiled again by the next call."""
    from cohflash_jax import process

    package = tmp_path / "bytecode_probe"
    package.mkdir()
    (package / "__init__.py").write_text("from . import part\n")
    (package / "part.py").write_text("VALUE = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(process, "PACKAGE_NAMES", ("bytecode_probe", "no_such_package_here"))

    def loaded_from() -> dict:
        """Each module's file that a fresh interpreter, told not to write bytecode, takes its
        code from (by the module file's stem)."""
        env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "PYTHONPATH": str(tmp_path)}
        done = subprocess.run(
            [sys.executable, "-v", "-c", "import bytecode_probe"], capture_output=True, text=True, env=env, check=True
        )
        paths = [line.split()[-1].strip("'") for line in done.stderr.splitlines() if "code object from" in line]
        return {os.path.basename(p).split(".")[0]: os.path.basename(p) for p in paths if "bytecode_probe" in p}

    assert loaded_from() == {"__init__": "__init__.py", "part": "part.py"}  # no bytecode yet: compiled
    assert "compiled ahead" in process.compile_package_bytecode()
    tag = sys.implementation.cache_tag
    assert loaded_from() == {"__init__": f"__init__.{tag}.pyc", "part": f"part.{tag}.pyc"}
    edited = package / "part.py"
    edited.write_text("VALUE = 22  # edited: another size\n")
    later = edited.stat().st_mtime + 10  # compileall tells stale bytecode by whole seconds
    os.utime(edited, (later, later))
    assert loaded_from()["part"] == "part.py"  # stale bytecode is not used
    process.compile_package_bytecode()
    assert loaded_from() == {"__init__": f"__init__.{tag}.pyc", "part": f"part.{tag}.pyc"}


def test_a_cohflash_process_starts_again_on_mimalloc_where_it_is_installed(monkeypatch, tmp_path):
    """A `cohflash reconstruct` interpreter runs itself again (`os.execve`, the same command line)
    with mimalloc preloaded, where the library is installed: once (not where LD_PRELOAD names it
    already), not where `COHFLASH_ALLOCATOR=system` asks for the C library's allocator, and
    never for a library user's or a test run's process, nor for a script that only sets
    `sys.orig_argv` to look like a command; a failed new start lets the command run on. Where
    mimalloc is installed, a real command's process has it mapped, and its output is the same."""
    from cohflash_jax import process

    started = []
    monkeypatch.setattr(process.os, "execve", lambda *args: started.append(args))
    assert not process.started_as(["python", "-m", "cohflash_jax.cli", "reconstruct", "c.h5"])
    assert process.started_as(sys.orig_argv)  # this test run's own command line
    monkeypatch.setattr(process, "started_as", lambda argv: True)
    library = tmp_path / "libmimalloc.so.2"
    library.write_bytes(b"")
    monkeypatch.setattr(process, "allocator_library", lambda: str(library))
    monkeypatch.delenv(process.ALLOCATOR_ENV, raising=False)
    monkeypatch.setenv("LD_PRELOAD", "/opt/libother.so")
    cli = ["/venv/bin/python", "-m", "cohflash_jax.cli", "reconstruct", "c.h5"]
    assert not process.preload_allocator_for_cli(["python", "-m", "pytest", "tests"]) and not started
    # `simulate` and `stream` ran slower on it: only the commands measured faster start again
    assert not process.preload_allocator_for_cli(["/venv/bin/python", "/venv/bin/cohflash", "simulate", "traffic"])
    assert not started
    assert process.preload_allocator_for_cli(cli)
    ((executable, argv, env),) = started
    assert executable == sys.executable and argv == [sys.executable, *cli[1:]]
    assert env["LD_PRELOAD"] == f"{library}:/opt/libother.so"
    monkeypatch.setenv("LD_PRELOAD", str(library))  # the new start: preloaded already
    assert not process.preload_allocator_for_cli(cli)
    monkeypatch.delenv("LD_PRELOAD")
    monkeypatch.setenv(process.ALLOCATOR_ENV, "system")
    assert not process.preload_allocator_for_cli(cli)
    monkeypatch.delenv(process.ALLOCATOR_ENV)
    monkeypatch.setattr(process, "allocator_library", lambda: None)  # not installed
    assert not process.preload_allocator_for_cli(cli)
    monkeypatch.setattr(process, "allocator_library", lambda: str(library))

    def refused(*args):
        raise OSError("exec format error")

    monkeypatch.setattr(process.os, "execve", refused)
    assert not process.preload_allocator_for_cli(cli) and len(started) == 1
    monkeypatch.setattr(process, "started_as", lambda argv: False)  # `sys.orig_argv` set by a script
    monkeypatch.setattr(process.os, "execve", lambda *args: started.append(args))
    assert not process.preload_allocator_for_cli(cli) and len(started) == 1
    monkeypatch.undo()

    installed = process.allocator_library()
    if installed is None:
        pytest.skip("mimalloc is not installed here: no real process to look at")
    capture = tmp_path / "c.h5"
    assert main(["simulate", "planar", "--size", "4x4", "--steps", "64", "--out", str(capture), "--quiet"]) == 0
    probe = tmp_path / "cohflash"  # a script named as the console script is: a command's process
    probe.write_text(
        "import sys\n"
        "from cohflash_jax.cli import main\n"
        "assert main(sys.argv[1:]) == 0\n"
        "print('mimalloc' in open('/proc/self/maps').read())\n"
    )
    mapped = {}
    for allocator in ("mimalloc", "system"):
        out = tmp_path / f"{allocator}.h5"
        env = dict(os.environ, COHFLASH_ALLOCATOR=allocator)
        env.pop("LD_PRELOAD", None)
        args = ["reconstruct", str(capture), "--out", str(out), "--quiet"]
        done = subprocess.run([sys.executable, str(probe), *args], capture_output=True, text=True, env=env)
        assert done.returncode == 0, done.stderr[-2000:]
        mapped[allocator] = done.stdout.split()[-1]
    assert mapped == {"mimalloc": "True", "system": "False"}
    with h5py.File(tmp_path / "mimalloc.h5") as a, h5py.File(tmp_path / "system.h5") as b:
        np.testing.assert_array_equal(a["depth_m"][()], b["depth_m"][()])


def test_a_platform_list_without_the_cpu_gives_no_cpu_streams_not_an_error(monkeypatch):
    """With `JAX_PLATFORMS=cuda` JAX has no CPU backend, and asking for its CPU devices raises
    ("Unknown backend cpu"): `use_cpu_streams`, which every `cohflash` command calls first,
    reports none instead of ending the command (seen on a lent GPU machine)."""
    import jax

    from cohflash_jax.runtime import use_cpu_streams

    def devices(backend=None):
        if backend == "cpu":
            raise RuntimeError("Unknown backend cpu. Available backends are ['cuda']")
        return []

    monkeypatch.setattr(jax, "devices", devices)
    assert use_cpu_streams(1) == 0
