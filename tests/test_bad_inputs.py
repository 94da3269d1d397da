"""Bad input, table-driven: every case runs a `cohflash` command line on a broken file or
option and asserts the exit code, a message naming the problem, and that the outputs of an
earlier run at the same paths are intact (and no temporary is left beside them)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from cohflash_jax.cli import main

from .independent_writer import Writer

SIDE = 4
FRAMES = 40


@dataclasses.dataclass(frozen=True)
class Case:
    """`argv(folder)` → the command line; `message`: what stderr must say (case-insensitive);
    `prepare(folder)`: breaks an input first."""

    name: str
    argv: Callable[[Path], list[str]]
    message: str
    prepare: Callable[[Path], None] | None = None


@pytest.fixture(scope="module")
def good_capture(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("good") / "capture.h5"
    writer = Writer(frequencies_hz=0.1e9 + 1.97e6 * np.arange(FRAMES), echo_scale=3000 / FRAMES)
    writer.write(path, np.full((SIDE, SIDE), 12.3), np.random.default_rng(5))
    return path


# -- breaking a capture ------------------------------------------------------------------------


def _attr(name, value):
    def prepare(folder):
        with h5py.File(folder / "cap.h5", "a") as f:
            if value is None:
                del f.attrs[name]
            else:
                f.attrs[name] = value

    return prepare


def _dataset(name, value):
    def prepare(folder):
        with h5py.File(folder / "cap.h5", "a") as f:
            del f[name]
            if value is not None:
                f[name] = value

    return prepare


def _frequencies(transform):
    def prepare(folder):
        with h5py.File(folder / "cap.h5", "a") as f:
            f0 = f["frequencies_hz"][()]
            del f["frequencies_hz"]
            f["frequencies_hz"] = transform(f0)

    return prepare


def _write(name, text: str | bytes):
    def prepare(folder):
        data = text.encode() if isinstance(text, str) else text
        (folder / name).write_bytes(data)

    return prepare


def _json(name, doc):
    return _write(name, json.dumps(doc))


def _calibration(**changes):
    doc = {
        "format": "cohflash-calibration",
        "format_version": 1,
        "hybrid": {
            "phases_rad": [0.0, 1.5708, 3.1416, 4.7124],
            "relative_gains": [1.0, 1.0, 1.0, 1.0],
            "offsets_dn": [200.0, 200.0, 200.0, 200.0],
        },
        "system_delay_s": 0.0,
    }
    for key, value in changes.items():
        if key in doc["hybrid"]:
            doc["hybrid"][key] = value
        else:
            doc[key] = value
    return _json("cal.json", doc)


def _truncate(folder):
    data = (folder / "cap.h5").read_bytes()
    (folder / "cap.h5").write_bytes(data[: len(data) // 3])


def _read_only_folder(folder):
    (folder / "ro").mkdir()
    (folder / "ro").chmod(0o555)


R = lambda *extra: lambda d: ["reconstruct", str(d / "cap.h5"), "--out", str(d / "out" / "depth.h5"), *extra]

CASES = [
    # the capture file
    Case(
        "capture missing", lambda d: ["reconstruct", str(d / "nope.h5"), "--out", str(d / "out/depth.h5")], "not found"
    ),
    Case("capture is text", R(), "not a readable HDF5", _write("cap.h5", "hello")),
    Case("capture truncated", R(), "not a readable HDF5", _truncate),
    Case("capture is a folder", lambda d: ["reconstruct", str(d / "out"), "--out", str(d / "x.h5")], "is a folder"),
    Case("format attribute", R(), "format", _attr("format", "something-else")),
    Case("format_version 2", R(), "format_version 2", _attr("format_version", 2)),
    Case("format_version 1.7", R(), "format_version 1.7", _attr("format_version", 1.7)),
    Case("format_version [1, 1]", R(), "format_version", _attr("format_version", [1, 1])),
    Case("format_version text", R(), "format_version", _attr("format_version", "one")),
    Case("format_version missing", R(), "format_version", _attr("format_version", None)),
    Case("exposure missing", R(), "exposure_s", _attr("exposure_s", None)),
    Case("exposure negative", R(), "exposure_s", _attr("exposure_s", -1.0)),
    Case("exposure NaN", R(), "exposure_s", _attr("exposure_s", float("nan"))),
    Case("exposure text", R(), "exposure_s", _attr("exposure_s", "long")),
    Case("frame rate zero", R(), "frame_rate_hz", _attr("frame_rate_hz", 0.0)),
    Case("wavelength missing", R(), "wavelength_m", _attr("wavelength_m", None)),
    Case("frames missing", R(), "frames", _dataset("frames", None)),
    Case("frames 3-D", R(), "shape", _dataset("frames", np.zeros((4, FRAMES, SIDE), np.uint16))),
    Case("frames of 3 CCDs", R(), "shape", _dataset("frames", np.zeros((3, FRAMES, SIDE, SIDE), np.uint16))),
    Case("frames int32", R(), "dtype", _dataset("frames", np.zeros((4, FRAMES, SIDE, SIDE), np.int32))),
    Case("frames float64", R(), "dtype", _dataset("frames", np.zeros((4, FRAMES, SIDE, SIDE), np.float64))),
    Case("one frame", R(), "frames", _dataset("frames", np.zeros((4, 1, SIDE, SIDE), np.uint16))),
    Case("frequencies missing", R(), "frequencies_hz", _dataset("frequencies_hz", None)),
    Case("frequencies too few", R(), "frequencies_hz", _frequencies(lambda f: f[:-1])),
    Case("frequencies float32", R(), "float64", _frequencies(lambda f: f.astype(np.float32))),
    Case("frequencies decreasing", R(), "increasing", _frequencies(lambda f: f[::-1].copy())),
    Case("frequencies repeated", R(), "increasing", _frequencies(lambda f: np.r_[f[:1], f[:-1]])),
    Case("frequencies negative", R(), "frequenc", _frequencies(lambda f: f - 1e9)),
    Case("frequencies NaN", R(), "frequenc", _frequencies(lambda f: np.r_[f[:-1], np.nan])),
    Case("hybrid phases (3,)", R(), "hybrid_phases_rad", _dataset("hybrid_phases_rad", np.zeros(3))),
    Case("hybrid phases NaN", R(), "hybrid_phases_rad", _dataset("hybrid_phases_rad", np.full(4, np.nan))),
    Case(
        "hybrid phases nearly equal",
        R(),
        "nearly equal",
        _dataset("hybrid_phases_rad", np.array([0, 0.03, 0.06, 0.09])),
    ),
    Case("field of view one value", R(), "field_of_view_deg", _attr("field_of_view_deg", [40.0])),
    Case("field of view text", R(), "field_of_view_deg", _attr("field_of_view_deg", "wide")),
    Case("field of view 200°", R(), "field_of_view_deg", _attr("field_of_view_deg", [200.0, 30.0])),
    Case("modulation index 0", R(), "modulation_index", _attr("modulation_index", 0.0)),
    Case("bias NaN", R(), "bias_rad", _attr("bias_rad", float("nan"))),
    Case("dn per electron negative", R(), "dn_per_electron", _attr("dn_per_electron", -0.1)),
    # reconstruct's options
    Case("method unknown", R("--method", "magic"), "--method"),
    Case("SNR threshold 1e6", R("--snr-threshold-db", "1e6"), "snr-threshold-db"),
    Case("SNR threshold NaN", R("--snr-threshold-db", "nan"), "snr-threshold-db"),
    Case("false alarm 0", R("--false-alarm", "0"), "false-alarm"),
    Case("false alarm 2", R("--false-alarm", "2"), "false-alarm"),
    Case("tile rows 0", R("--tile-rows", "0"), "tile-rows"),
    Case("tile rows text", R("--tile-rows", "many"), "tile rows must be a whole number"),
    Case("χ² limit negative", R("--max-fit-chi2", "-1"), "max-fit-chi2"),
    Case("min depth negative", R("--min-depth-m", "-5"), "min-depth-m"),
    Case("PNG range reversed", R("--png-range-mm", "5,1"), "HI must exceed LO"),
    Case("carrier unknown", R("--carrier", "wobbly"), "--carrier"),
    # output paths
    Case("out is a folder", lambda d: ["reconstruct", str(d / "cap.h5"), "--out", str(d / "out")], "is a folder"),
    Case("out folder missing", R("--png", "/nonexistent/folder/x.png"), "output folder does not exist"),
    Case("out is the capture", lambda d: ["reconstruct", str(d / "cap.h5"), "--out", str(d / "cap.h5")], "capture"),
    Case("png is the out", lambda d: R("--png", str(d / "out" / "depth.h5"))(d), "same file"),
    # calibration files
    Case("calibration missing", R("--calibration", "/nonexistent.json"), "not found"),
    Case("calibration is a list", R("--calibration", "CAL"), "JSON object", _json("cal.json", [1, 2])),
    Case("calibration not JSON", R("--calibration", "CAL"), "not valid JSON", _write("cal.json", "{oops")),
    Case("calibration binary", R("--calibration", "CAL"), "binary", _write("cal.json", b"\x89HDF\r\n\x1a\n\xff\xfe")),
    Case("calibration format", R("--calibration", "CAL"), "format", _calibration(format="other")),
    Case("calibration version 9", R("--calibration", "CAL"), "format_version 9", _calibration(format_version=9)),
    Case("calibration offsets 1e9", R("--calibration", "CAL"), "offsets_dn", _calibration(offsets_dn=[1e9] * 4)),
    Case("calibration gains 0", R("--calibration", "CAL"), "relative_gains", _calibration(relative_gains=[1, 0, 1, 1])),
    Case("calibration gains 50", R("--calibration", "CAL"), "implausible", _calibration(relative_gains=[1, 50, 1, 1])),
    Case("calibration phases NaN", R("--calibration", "CAL"), "phases_rad", _calibration(phases_rad=[0, "nan", 0, 0])),
    Case("calibration τ 1 s", R("--calibration", "CAL"), "system_delay_s", _calibration(system_delay_s=1.0)),
    Case("calibration τ text", R("--calibration", "CAL"), "system_delay_s", _calibration(system_delay_s="soon")),
    # registration files
    Case("registration missing", R("--registration", "/nonexistent.json"), "not found"),
    Case("registration not JSON", R("--registration", "REG"), "not valid JSON", _write("reg.json", "[")),
    Case("registration format", R("--registration", "REG"), "format", _json("reg.json", {"format": "x"})),
    # simulate
    Case("simulate huge", lambda d: ["simulate", "planar", "--size", "100000x100000", "--out", str(d / "s.h5")], "GB"),
    Case("simulate size 0", lambda d: ["simulate", "planar", "--size", "0x4", "--out", str(d / "s.h5")], "positive"),
    Case("simulate size text", lambda d: ["simulate", "planar", "--size", "big", "--out", str(d / "s.h5")], "HxW"),
    Case("simulate scene", lambda d: ["simulate", "moon", "--out", str(d / "s.h5")], "moon"),
    Case("simulate steps 1", lambda d: ["simulate", "planar", "--steps", "1", "--out", str(d / "s.h5")], "2 steps"),
    Case("simulate steps text", lambda d: ["simulate", "planar", "--steps", "x", "--out", str(d / "s.h5")], "steps"),
    Case("simulate effect", lambda d: ["simulate", "planar", "--effects", "rain", "--out", str(d / "s.h5")], "rain"),
    Case("simulate file no map", lambda d: ["simulate", "file", "--out", str(d / "s.h5")], "--depth-map"),
    # design and sweep
    Case("design reflectance 2", lambda d: _design("--reflectance", "2"), "reflectance"),
    Case("design precision 0", lambda d: _design("--target-precision-mm", "0"), "precision"),
    Case("design frames 1", lambda d: _design("--max-frames", "1"), "frames"),
    Case("sweep axis text", lambda d: _sweep(d, "--axis", "distance_m=a:b:3"), "distance_m"),
    Case("sweep unknown axis", lambda d: _sweep(d, "--axis", "colour=1:2:3"), "colour"),
    Case("sweep --mc not an axis", lambda d: _sweep(d, "--axis", "num_steps=35,70", "--mc", "distance_m=30"), "axis"),
    Case("sweep --mc off grid", lambda d: _sweep(d, "--axis", "num_steps=35,70", "--mc", "num_steps=50"), "grid"),
    Case("sweep --set text", lambda d: _sweep(d, "--axis", "num_steps=35,70", "--set", "distance_m=far"), "far"),
    Case("sweep negative start", lambda d: _sweep(d, "--axis", "start_ghz=-1,1"), "start_ghz"),
    Case("sweep trials 0", lambda d: _sweep(d, "--axis", "num_steps=35,70", "--mc-trials", "0"), "trials"),
    # uncertainty
    Case("pixel twice", lambda d: _posterior(d, "--pixel", "0,0", "--pixel", "0,0"), "more than once"),
    Case("pixel text", lambda d: _posterior(d, "--pixel", "a,b"), "ROW,COL"),
    Case("no pixel", lambda d: _posterior(d), "--pixel"),
    Case("steps 0", lambda d: _posterior(d, "--pixel", "0,0", "--max-steps", "0"), "steps"),
    # calibrate
    Case("known distance negative", lambda d: _hybrid(d, "--known-distance-m", "-3"), "known distance"),
    Case("square size 0", lambda d: _registration(d, "--square-mm", "0"), "square size"),
    Case("board text", lambda d: _registration(d, "--square-mm", "25", "--board", "big"), "board"),
    Case(
        "image file for folder", lambda d: _registration(d, "--square-mm", "25"), "not a folder", _write("img.png", "x")
    ),
    # info
    Case("info missing", lambda d: ["info", str(d / "nope.h5")], "not found"),
    Case("info on a PNG", lambda d: ["info", str(d / "img.png")], "not a cohflash file", _write("img.png", "x")),
    Case("info on other HDF5", lambda d: ["info", str(d / "other.h5")], "not a cohflash file", lambda d: _other(d)),
]


def _design(*extra):
    return ["design", "--target-precision-mm", "1", "--max-range-m", "40", *extra]


def _sweep(d, *extra):
    return ["sweep", "--out", str(d / "out" / "new.csv"), "--quiet", *extra]


def _posterior(d, *extra):
    return ["uncertainty", str(d / "cap.h5"), "--out", str(d / "out" / "post.h5"), "--quiet", *extra]


def _hybrid(d, *extra):
    return ["calibrate", "hybrid", str(d / "cap.h5"), "--out", str(d / "out" / "cal.json"), *extra]


def _registration(d, *extra):
    folders = [str(d / "img.png")] * 4
    args = ["calibrate", "registration", "--images", *folders, "--board", "9x6", "--out", str(d / "out" / "reg.json")]
    return args + list(extra)


def _other(d):
    with h5py.File(d / "other.h5", "w") as f:
        f["x"] = np.zeros(3)


def _digest(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def test_the_table_is_large_enough():
    assert len(CASES) >= 60
    assert len({c.name for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_is_refused_by_name_and_earlier_outputs_stay(case, good_capture, tmp_path, capsys):
    shutil.copy(good_capture, tmp_path / "cap.h5")
    out = tmp_path / "out"
    out.mkdir()
    for name in ("depth.h5", "depth.png", "sweep.csv", "post.h5", "cal.json", "reg.json"):
        (out / name).write_text(f"an earlier run's {name}")
    before = _digest(out)
    if case.prepare is not None:
        case.prepare(tmp_path)
    argv = [
        a.replace("CAL", str(tmp_path / "cal.json")).replace("REG", str(tmp_path / "reg.json"))
        for a in case.argv(tmp_path)
    ]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    assert case.message.lower() in err.lower(), err
    assert "Traceback" not in err
    assert _digest(out) == before  # nothing replaced, nothing half-written, no temporary left


def test_an_error_after_the_work_leaves_the_earlier_set_whole(good_capture, tmp_path, monkeypatch, capsys):
    """depth.h5 is written, then the PNG fails: neither replaces the earlier run's files."""
    import cohflash_jax.results as results

    out = tmp_path / "out"
    out.mkdir()
    for name in ("depth.h5", "depth.png"):
        (out / name).write_text(f"an earlier run's {name}")
    before = _digest(out)

    def fail(*args, **kwargs):
        raise OSError("disk full while writing the PNG")

    monkeypatch.setattr(results, "save_preview_png", fail)
    argv = ["reconstruct", str(good_capture), "--out", str(out / "depth.h5"), "--png", str(out / "depth.png")]
    assert main([*argv, "--quiet"]) == 2
    assert "disk full" in capsys.readouterr().err
    assert _digest(out) == before


def test_stale_temporaries_of_a_killed_run_are_removed(good_capture, tmp_path):
    out = tmp_path / "depth.h5"
    stale = tmp_path / ".depth.h5.tmp-999999999"  # no such process
    stale.write_bytes(b"x" * 1000)
    assert main(["reconstruct", str(good_capture), "--out", str(out), "--quiet"]) == 0
    assert out.exists() and not stale.exists()
    assert not list(tmp_path.glob(".depth.h5.tmp-*"))
