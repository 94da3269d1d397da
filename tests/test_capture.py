"""Capture format v1: the CLI writes valid files; the reader rejects bad ones clearly."""

import os

import h5py
import jax
import numpy as np
import pytest

import cohflash_jax as cf
from cohflash_jax.capture import Capture, CaptureError, write_capture
from cohflash_jax.cli import main
from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
from cohflash_jax.tiling import PieceLayout


@pytest.fixture(scope="module")
def staircase_capture(tmp_path_factory):
    path = tmp_path_factory.mktemp("cap") / "x.h5"
    assert main(["simulate", "staircase", "--size", "64x64", "--steps", "512", "--out", str(path), "--quiet"]) == 0
    return path


def test_simulate_cli_writes_a_valid_v1_capture(staircase_capture):
    with h5py.File(staircase_capture) as f:
        assert f.attrs["format"] == "cohflash-capture" and int(f.attrs["format_version"]) == 1
        for k in ("exposure_s", "frame_rate_hz", "wavelength_m"):
            assert float(f.attrs[k]) > 0
        assert f["frames"].shape == (4, 512, 64, 64) and f["frames"].dtype == np.uint16
        assert f["frequencies_hz"].dtype == np.float64 and f["frequencies_hz"].shape == (512,)
        np.testing.assert_allclose(f["hybrid_phases_rad"][()], [0, np.pi / 2, np.pi, 1.5 * np.pi])
        assert f["truth/depth_m"].shape == (64, 64) and f["truth/depth_m"].dtype == np.float32
    assert not list(staircase_capture.parent.glob(".*tmp*"))  # no temporary file left


def test_independent_dft_peak_gives_true_depth_within_one_bin(staircase_capture):
    """Plain NumPy, written from docs/design-reference.md §1 only: I = V0 − V2, Q = V3 − V1, principal
    axis, rFFT peak → depth = k/(N·Δf)·c/2."""
    with Capture(staircase_capture) as cap:
        frames = cap.read_tile(slice(None)).astype(np.float64)
        freqs = cap.frequencies_hz
        truth = cap.truth("depth_m")
    n = frames.shape[1]
    z = (frames[0] - frames[2]) + 1j * (frames[3] - frames[1])
    z = z - z.mean(axis=0)
    axis = np.angle(np.sum(z**2, axis=0)) / 2
    r = np.real(z * np.exp(-1j * axis))
    k = np.argmax(np.abs(np.fft.rfft(r, axis=0))[1:], axis=0) + 1
    step = freqs[1] - freqs[0]
    depth = k / (n * step) * C / 2
    bin_m = C / (2 * n * step)
    within = np.abs(depth - truth) <= bin_m
    # pixels next to a depth edge hold two returns (mixed_pixels is on), which can cancel
    # each other: their "true depth" is not single-valued, so they are judged separately
    edge = np.zeros(truth.shape, bool)
    for axis in (0, 1):
        step_edge = np.abs(np.diff(truth, axis=axis)) > 0
        sl_a = [slice(None)] * 2
        sl_b = [slice(None)] * 2
        sl_a[axis], sl_b[axis] = slice(1, None), slice(None, -1)
        edge[tuple(sl_a)] |= step_edge
        edge[tuple(sl_b)] |= step_edge
    assert np.all(within[~edge])
    assert within.mean() > 0.99


def test_read_tile_reads_the_requested_pixels(staircase_capture):
    with Capture(staircase_capture) as cap:
        tile = cap.read_tile(slice(10, 14), slice(5, 8))
        assert tile.shape == (4, 512, 4, 3)
        np.testing.assert_array_equal(tile, cap.frames[:, :, 10:14, 5:8])
        # a partial tile read straight into the first rows of a larger reused buffer
        n, h, w = cap.shape
        buf = np.full((4, n, 6, w), 7, np.uint16)
        cap.read_tile_into(buf, slice(h - 4, h))
        np.testing.assert_array_equal(buf[:, :, :4], cap.frames[:, :, h - 4 : h])
        assert np.all(buf[:, :, 4:] == 7)


def _chunked(path, frames, unwritten=False, **dataset_options):
    """A minimal valid capture whose frames are stored as `dataset_options` say (h5py, not
    `write_capture`); `unwritten`: only the first frame's chunks are written."""
    n, h, w = frames.shape[1:]
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": "cohflash-capture", "format_version": 1, "exposure_s": 4e-3})
        f.attrs.update({"frame_rate_hz": 150.0, "wavelength_m": 1.55e-6})
        f["frequencies_hz"] = 1e8 + 2e6 * np.arange(n)
        f["hybrid_phases_rad"] = np.array([0, np.pi / 2, np.pi, 1.5 * np.pi])
        d = f.create_dataset("frames", shape=frames.shape, dtype=frames.dtype, **dataset_options)
        if unwritten:
            d[:, :1] = frames[:, :1]
        else:
            d[...] = frames
    return path


@pytest.mark.parametrize(
    "options,tile_rows,direct",
    [
        ({"chunks": (1, 4, 8, 7)}, 8, True),  # one chunk a band of a tile; the last frames' chunk part-filled
        ({"chunks": (1, 4, 8, 7)}, 16, True),  # two chunk bands a tile: a chunk's frames land apart
        ({"chunks": (1, 3, 5, 7)}, 5, True),  # 22 rows: the last tile cuts a chunk, read through HDF5
        ({"chunks": (1, 4, 8, 7), "compression": "gzip"}, 8, False),
        ({"chunks": (1, 4, 8, 4)}, 8, False),  # chunks cut rows
        ({}, 8, False),  # contiguous
        ({"chunks": (1, 4, 8, 7), "unwritten": True}, 8, False),  # HDF5's fill value stands in
    ],
)
def test_direct_chunk_reads_equal_hdf5_reads(tmp_path, options, tile_rows, direct):
    """Tiles read straight from the file's chunks (`chunk_reads`) are HDF5's, byte for byte,
    into a reused buffer with stale contents; layouts that cannot be read so go through HDF5."""
    rng = np.random.default_rng(5)
    frames = rng.integers(0, 2**16, (4, 10, 22, 7), dtype=np.uint16)
    path = _chunked(tmp_path / "c.h5", frames, **options)
    if options.get("unwritten"):
        frames[:, 1:] = 0  # HDF5's fill value
    with Capture(path) as cap:
        assert (cap.direct_reader is not None) == direct
        assert not direct or cap.direct_reader.covers(slice(0, tile_rows))
        buf = np.full((4, 10, tile_rows, 7), 7, np.uint16)
        for r0 in range(0, 22, tile_rows):
            r1 = min(22, r0 + tile_rows)
            cap.read_tile_into(buf, slice(r0, r1))
            np.testing.assert_array_equal(buf[:, :, : r1 - r0], frames[:, :, r0:r1])


def test_block_reader_reads_over_a_tile_only_once_it_is_released(tmp_path):
    """A tile still aliased by dispatched work (`hold_last(True)`) keeps its buffer: the next
    tile goes into another; a released one's buffer takes the next tile (one buffer in all)."""
    from cohflash_jax.reconstruct import BlockReader

    frames = np.random.default_rng(6).integers(0, 2**16, (4, 10, 22, 7), dtype=np.uint16)
    with Capture(_chunked(tmp_path / "c.h5", frames, chunks=(1, 4, 8, 7))) as cap:
        reader = BlockReader(cap, 8)
        first = reader.read(0)
        reader.hold_last(False)
        second = reader.read(8)
        assert np.shares_memory(first, second) and len(reader.buffers) == 1
        reader.hold_last(True)
        third = reader.read(16)
        assert not np.shares_memory(second, third) and len(reader.buffers) == 2
        np.testing.assert_array_equal(second.reshape(4, 10, 8, 7), frames[:, :, 8:16])  # intact
        np.testing.assert_array_equal(third.reshape(4, 10, 8, 7)[:, :, :6], frames[:, :, 16:])
        assert not third.reshape(4, 10, 8, 7)[:, :, 6:].any()  # the short last tile padded with zeros
        reader.hold_last(True)
        assert np.shares_memory(reader.read(0), second) and len(reader.buffers) == 2


@pytest.mark.parametrize(
    "chunks,tile_rows,rows_per_piece",
    [
        ((1, 4, 8, 7), 8, 1),  # a piece a row: 8 runs per chunk frame; the last frames' chunk part-filled
        ((1, 4, 8, 7), 8, 4),
        ((1, 4, 8, 7), 16, 4),  # two chunk bands a tile
        ((1, 3, 5, 7), 10, 2),  # a piece across two chunk bands; the last tile (rows 20:22) through HDF5
    ],
)
@pytest.mark.parametrize("native_reads", [True, False])
def test_tiles_read_straight_into_their_sub_tiles_equal_hdf5_reads(
    tmp_path, monkeypatch, chunks, tile_rows, rows_per_piece, native_reads
):
    """A tile read as its sub-tiles (`PieceReader`: each chunk scattered by one `preadv` to the
    pieces its rows belong to; the tile's reads in one native call, `native.read_chunks`, or
    a call a chunk where it is not built) holds HDF5's frames, piece by piece, in aligned C-contiguous
    pieces (a CPU device array aliases them); the short last tile is padded with zeros; a tile
    still in use keeps its buffer, the next tile going into the other."""
    from cohflash_jax import native
    from cohflash_jax.reconstruct.engine import PieceReader
    from cohflash_jax.tiling import BUFFER_ALIGNMENT_BYTES

    if native_reads and not native.reads_chunks():
        pytest.skip("the native kernel was not built (no C compiler)")
    monkeypatch.setattr(native, "reads_chunks", lambda: native_reads)
    frames = np.random.default_rng(8).integers(0, 2**16, (4, 10, 22, 7), dtype=np.uint16)
    with Capture(_chunked(tmp_path / "c.h5", frames, chunks=chunks)) as cap:
        reader = PieceReader(cap, PieceLayout(cap.shape, cap.frames.dtype, tile_rows, rows_per_piece))
        assert reader.new_buffer() is not None
        sub = rows_per_piece * 7
        for r0 in range(0, 22, tile_rows):
            r1 = min(22, r0 + tile_rows)
            expected = np.zeros((4, 10, tile_rows, 7), np.uint16)
            expected[:, :, : r1 - r0] = frames[:, :, r0:r1]
            expected = expected.reshape(4, 10, -1)
            tile = reader.read(r0)
            reader.hold_last(True)
            assert len(tile.pieces) == tile_rows // rows_per_piece and tile.num_pixels == tile_rows * 7
            for k, piece in enumerate(tile.pieces):
                assert piece.flags.c_contiguous and piece.ctypes.data % BUFFER_ALIGNMENT_BYTES == 0
                np.testing.assert_array_equal(piece, expected[..., k * sub : (k + 1) * sub], err_msg=f"{r0} {k}")
            np.testing.assert_array_equal(tile.frames.reshape(4, 10, -1), expected)
        assert len(reader.buffers) == 2  # each tile held while the next was read


def test_a_region_of_interest_is_read_whole_a_larger_capture_in_pieces(tmp_path):
    """A region of interest keeps its pixel bucket, one sub-tile, and the programs its
    neighbours in size run, though two pieces of half its rows would fit it; a larger capture
    of the same sweep is read straight into its sub-tiles, of the size a copied tile's have."""
    from cohflash_jax.reconstruct.engine import PieceReader, sub_tile_pixels

    if jax.default_backend() != "cpu":
        pytest.skip("sub-tiles are the CPU's: on a GPU a tile is one piece")
    rng = np.random.default_rng(9)
    small = _chunked(tmp_path / "s.h5", rng.integers(0, 99, (4, 3000, 16, 16), np.uint16), chunks=(1, 8, 16, 16))
    with Capture(small) as cap:
        assert PieceReader.of(cap, 16) is None  # two 8-row pieces of 128 px would fit its 256 px
    large = _chunked(tmp_path / "l.h5", rng.integers(0, 99, (4, 3000, 32, 48), np.uint16), chunks=(1, 8, 32, 48))
    with Capture(large) as cap:
        reader = PieceReader.of(cap, 32)
        assert reader is not None and reader.layout.sub == sub_tile_pixels(32 * 48, 3000) == 384


def test_a_tile_source_states_its_tiles_before_reading_them(tmp_path):
    """`TileSource.tile_like`, from which a first run compiles its inversion before any tile is
    read (`TileDispatcher.prepare`), states what `inputs` then gives: the frames' pixels, shape
    and type, the dark and gain maps and the upstream status, for a capture read in pieces, one
    read whole with per-pixel maps, and a registered one (resampled float32 frames, a status)."""
    from cohflash_jax.calibration_file import PixelMaps
    from cohflash_jax.reconstruct.api import TileSource
    from cohflash_jax.reconstruct.engine import TilePieces

    def described(x):  # pixels, the rest of the shape, type
        if x is None:
            return None
        if isinstance(x, TilePieces):
            return x.num_pixels, x.pieces[0].shape[:-1], x.pieces[0].dtype
        return x.shape[-1], x.shape[:-1], np.dtype(x.dtype)

    def stated_and_read(path, maps, registration_maps=None):
        with Capture(path) as cap:
            source = TileSource(cap, maps, registration_maps, cap.shape[1])
            _, frames, status, dark, gain = source.inputs(0)
            pieces.append(isinstance(frames, TilePieces))
            return [described(x) for x in source.tile_like()], [described(x) for x in (frames, dark, status, gain)]

    rng, pieces = np.random.default_rng(4), []
    large = _chunked(tmp_path / "l.h5", rng.integers(0, 99, (4, 64, 32, 48), np.uint16), chunks=(1, 8, 32, 48))
    stated, read = stated_and_read(large, PixelMaps())
    assert stated == read and read[0][0] == 32 * 48 and pieces == [jax.default_backend() == "cpu"]
    small = _chunked(tmp_path / "s.h5", rng.integers(0, 99, (4, 64, 6, 5), np.uint16), chunks=(1, 8, 6, 5))
    maps = PixelMaps(rng.normal(100, 1, (4, 6, 5)), rng.normal(1, 0.01, (4, 6, 5)))
    stated, read = stated_and_read(small, maps)
    assert stated == read and read[1] == (30, (4,), np.float32) and read[3] == read[1]
    rows, cols = np.mgrid[0:6, 0:5].astype(np.float64)
    stated, read = stated_and_read(small, PixelMaps(), [(cols + 0.25, rows)] * 3)
    assert stated == read and read[0][2] == np.float32 and read[2] == (30, (), np.int8)


@pytest.mark.parametrize("native_reads", [True, False])
def test_a_capture_truncated_after_it_was_opened_fails_naming_the_rows(tmp_path, monkeypatch, native_reads):
    from cohflash_jax import native

    if native_reads and not native.reads_chunks():
        pytest.skip("the native kernel was not built (no C compiler)")
    monkeypatch.setattr(native, "reads_chunks", lambda: native_reads)
    frames = np.random.default_rng(7).integers(0, 2**16, (4, 10, 16, 7), dtype=np.uint16)
    path = _chunked(tmp_path / "c.h5", frames, chunks=(1, 4, 8, 7))
    with Capture(path) as cap:
        last = int(cap.direct_reader.offsets.max())
        os.truncate(path, last + 10)  # the last chunk cut short
        buf = np.zeros((4, 10, 8, 7), np.uint16)
        cap.read_tile_into(buf, slice(0, 8))  # that chunk's rows are elsewhere: still read
        with pytest.raises(CaptureError, match=r"rows 8:16 could not be read .*bytes read"):
            cap.read_tile_into(buf, slice(8, 16))
        from cohflash_jax.reconstruct.engine import PieceReader

        # read straight into sub-tiles: the same error
        reader = PieceReader(cap, PieceLayout(cap.shape, cap.frames.dtype, 8, 2))
        reader.read(0)
        with pytest.raises(CaptureError, match=r"rows 8:16 could not be read \(chunk \(\d, 8, 8, 0\): .*bytes read"):
            reader.read(8)


def _write(path, **over):
    n, h, w = 8, 2, 3
    f = h5py.File(path, "w")
    f.attrs.update(
        {
            "format": "cohflash-capture",
            "format_version": 1,
            "exposure_s": 4e-3,
            "frame_rate_hz": 150.0,
            "wavelength_m": 1.55e-6,
        }
    )
    data = {
        "frames": np.zeros((4, n, h, w), np.uint16),
        "frequencies_hz": 1e8 + 2e6 * np.arange(n),
        "hybrid_phases_rad": np.array([0, np.pi / 2, np.pi, 1.5 * np.pi]),
    }
    for k, v in over.items():
        if k.startswith("attr_"):
            if v is None:
                del f.attrs[k[5:]]
            else:
                f.attrs[k[5:]] = v
        else:
            data[k] = v
    for k, v in data.items():
        if v is not None:
            f.create_dataset(k, data=v)
    f.close()
    return path


@pytest.mark.parametrize(
    "over,match",
    [
        ({"attr_format": "something-else"}, "format"),
        ({"attr_format_version": 2}, "format_version 2"),
        ({"attr_exposure_s": None}, "exposure_s"),
        ({"attr_frame_rate_hz": -1.0}, "frame_rate_hz"),
        ({"attr_exposure_s": "fast"}, "exposure_s must be a number, got 'fast'"),
        ({"attr_adc_bits": 40}, "adc_bits must be an integer from 1 to 16"),
        ({"frames": np.zeros((3, 8, 2, 3), np.uint16)}, r"shape \(4, N, H, W\)"),
        ({"frames": np.zeros((4, 8, 2, 3), np.int32)}, "dtype"),
        ({"frames": None}, "frames"),
        ({"frequencies_hz": np.arange(8.0)[::-1].copy()}, "increasing"),
        ({"frequencies_hz": np.array([1, 2, 3, np.nan, 5, 6, 7, 8.0])}, "NaN"),
        ({"frequencies_hz": np.arange(7.0)}, "match frames"),
        ({"frequencies_hz": np.arange(8, dtype=np.float32)}, "float64"),
        ({"hybrid_phases_rad": np.zeros(3)}, "hybrid_phases_rad"),
        ({"dark": np.zeros((4, 5, 5), np.float32)}, "dark"),
    ],
)
def test_reader_rejects_malformed_files_naming_the_problem(tmp_path, over, match):
    path = _write(tmp_path / "bad.h5", **over)
    with pytest.raises(CaptureError, match=match):
        Capture(path)


def test_reader_rejects_missing_and_non_hdf5_files(tmp_path):
    with pytest.raises(CaptureError, match="not found"):
        Capture(tmp_path / "nope.h5")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"definitely not hdf5")
    with pytest.raises(CaptureError, match="not a readable HDF5"):
        Capture(junk)


def test_interrupted_write_keeps_the_old_file_and_leaves_no_partial(tmp_path):
    path = tmp_path / "cap.h5"
    path.write_bytes(b"previous result")

    def chunks():
        yield 0, 4, np.zeros((4, 4, 2, 2), np.uint16)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_capture(
            path,
            chunks(),
            frequencies_hz=1e8 + 2e6 * np.arange(8),
            height=2,
            width=2,
            dtype=np.uint16,
            attrs={"exposure_s": 4e-3, "frame_rate_hz": 150.0, "wavelength_m": 1.55e-6},
            progress=False,
        )
    assert path.read_bytes() == b"previous result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap.h5"]


def test_simulate_cli_rejects_bad_arguments(tmp_path, capsys):
    assert main(["simulate", "staircase", "--effects", "fog", "--out", str(tmp_path / "a.h5")]) == 2
    assert "known effects" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["simulate", "staircase", "--steps", "1", "--out", str(tmp_path / "a.h5")])
    with pytest.raises(SystemExit):
        main(["simulate", "staircase", "--size", "64by64", "--out", str(tmp_path / "a.h5")])
    assert (
        main(
            [
                "simulate",
                "staircase",
                "--out",
                str(tmp_path / "missing" / "a.h5"),
                "--steps",
                "4",
                "--size",
                "2x2",
                "--quiet",
            ]
        )
        == 2
    )
    assert not (tmp_path / "a.h5").exists()


def test_scene_from_image_files_and_arrays(tmp_path):
    import cv2

    depth_mm = np.full((20, 30), 30500, np.uint16)
    depth_mm[5:15, 10:20] = 30480
    rho = np.full((20, 30), 128, np.uint8)
    cv2.imwrite(str(tmp_path / "d.png"), depth_mm)
    cv2.imwrite(str(tmp_path / "r.png"), rho)
    np.save(tmp_path / "d.npy", depth_mm / 1000.0)
    from_png = cf.from_files(tmp_path / "d.png", tmp_path / "r.png", depth_scale_m=1e-3)  # 8-bit: reflectance /255
    from_npy = cf.from_files(tmp_path / "d.npy")
    d_png, r_png = from_png.render(20, 30)
    d_npy, _ = from_npy.render(20, 30)
    np.testing.assert_allclose(d_png, depth_mm / 1000.0)
    np.testing.assert_allclose(d_npy, depth_mm / 1000.0)
    np.testing.assert_allclose(r_png, 128 / 255)
    d_low, _ = from_png.render(10, 15)  # any output size: nearest-neighbour sampling
    assert d_low[5, 7] == pytest.approx(30.48) and d_low[0, 0] == pytest.approx(30.5)
    with pytest.raises(FileNotFoundError, match="not found"):
        cf.from_files(tmp_path / "missing.png")
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match="could not read image"):
        cf.from_files(tmp_path / "junk.png")
    (tmp_path / "junk.npy").write_text("not an array")
    with pytest.raises(ValueError, match="junk.npy: not a readable .npy array"):
        cf.from_files(tmp_path / "junk.npy")
    np.save(tmp_path / "words.npy", np.array(["a", "b"]))
    with pytest.raises(ValueError, match="words.npy: a map must hold real numbers"):
        cf.from_files(tmp_path / "words.npy")
