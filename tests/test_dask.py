"""Scale-out on Dask and Zarr captures (issue #24): a local `dask.distributed` cluster of two
worker processes started here; captures written by the tests' own NumPy writer."""

import multiprocessing
import os
import signal

import numpy as np
import pytest

from cohflash_jax.capture import Capture, CaptureError, CaptureHeader
from cohflash_jax.capture_zarr import ZarrCaptureWriter, convert_capture, create_zarr_capture, finish_zarr_capture
from cohflash_jax.cli import main
from cohflash_jax.reconstruct import ReconstructOptions, open_and_reconstruct
from cohflash_jax.results import read_depth
from tests.independent_writer import Writer

pytestmark = pytest.mark.xdist_group("dask")

HEIGHT, WIDTH, FRAMES = 32, 24, 256
TILE_ROWS = 4  # eight tiles: enough bands to kill a worker while others remain


@pytest.fixture(scope="module")
def capture_h5(tmp_path_factory):
    rng = np.random.default_rng(24)
    depth = 30.0 + 0.01 * rng.standard_normal((HEIGHT, WIDTH))
    writer = Writer(frequencies_hz=0.1e9 + 1.97e6 * np.arange(FRAMES), echo_scale=20.0)
    path = tmp_path_factory.mktemp("dask") / "capture.h5"
    writer.write(path, depth, rng)
    return path


@pytest.fixture(scope="module")
def single_process(capture_h5):
    options = ReconstructOptions(progress=False, tile_rows=TILE_ROWS)
    return open_and_reconstruct(capture_h5, options).outputs


@pytest.fixture(scope="module")
def client():
    from cohflash_jax.dask_cluster import dask_client

    with dask_client("processes", 2) as c:
        yield c


def assert_same(a: dict, b: dict):
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k


def test_two_workers_give_the_single_process_depths_bit_for_bit(capture_h5, single_process, client):
    from cohflash_jax.reconstruct.dask_bands import reconstruct_on_dask

    options = ReconstructOptions(progress=False, tile_rows=TILE_ROWS)
    result, run = reconstruct_on_dask(capture_h5, options, client, band_rows=2 * TILE_ROWS)
    assert_same(result.outputs, single_process)
    assert single_process["valid"].mean() > 0.9  # a real comparison: the depths are measured ones
    assert run.bands == HEIGHT // (2 * TILE_ROWS)
    assert len(run.workers) == 2 and all(peak > 0 for peak in run.workers.values())


def test_a_worker_killed_mid_run_is_replaced_and_the_run_completes_equal(capture_h5, single_process, client):
    from cohflash_jax.reconstruct.dask_bands import reconstruct_on_dask

    pids = client.run(os.getpid)
    victim = next(iter(pids.values()))
    killed = []

    def kill_once(done, total):
        if not killed:
            os.kill(victim, signal.SIGKILL)
            killed.append(done)

    options = ReconstructOptions(progress=False, tile_rows=TILE_ROWS)
    result, run = reconstruct_on_dask(capture_h5, options, client, band_rows=TILE_ROWS, on_band=kill_once)
    assert killed == [1] and run.bands == HEIGHT // TILE_ROWS
    assert_same(result.outputs, single_process)
    client.wait_for_workers(2, timeout=60)  # the nanny restarts it for the tests after this one


def test_cli_on_dask_threads_writes_a_zarr_depth_store_equal_to_the_h5(tmp_path, capture_h5, single_process, capsys):
    out = tmp_path / "depth.zarr"
    args = ["reconstruct", str(capture_h5), "--out", str(out), "--tile-rows", str(TILE_ROWS), "--quiet"]
    assert main(args + ["--scheduler", "threads", "--workers", "2"]) == 0
    assert "Dask at inproc://" in capsys.readouterr().out
    outputs, meta = read_depth(out)
    assert sorted(outputs) == sorted(single_process)
    for k, v in single_process.items():  # the file's dtypes: compare values
        assert np.array_equal(outputs[k], v.astype(outputs[k].dtype)), k
    assert meta["format"] == "cohflash-depth" and meta["method"] == "ml"


def test_cli_on_a_cluster_at_an_address(tmp_path, capture_h5, single_process, client, capsys):
    address = client.scheduler.address
    out = tmp_path / "depth.h5"
    args = ["reconstruct", str(capture_h5), "--out", str(out), "--tile-rows", str(TILE_ROWS), "--quiet"]
    assert main(args + ["--scheduler", address]) == 0
    assert f"Dask at {address}: 2 workers" in capsys.readouterr().out
    outputs, _ = read_depth(out)
    for k, v in single_process.items():
        assert np.array_equal(outputs[k], v.astype(outputs[k].dtype)), k
    assert main(args + ["--scheduler", address, "--workers", "2"]) == 2
    assert "a cluster at an address has the workers it was started with" in capsys.readouterr().err


def test_a_registered_reconstruction_on_dask_equals_the_single_process(tmp_path, capture_h5):
    """Every band resamples CCDs 2–4 from its own rows and margin: the same as one process."""
    from cohflash_calibration.registration import from_pixel_transforms, write_registration

    with Capture(capture_h5) as cap:
        fov = cap.instrument().field_of_view_deg
    focal = (WIDTH / 2) / np.tan(np.deg2rad(fov[0]) / 2)
    transforms = ((1.0, -0.5, 0.3), (-0.8, 0.6, -0.2), (0.5, 1.0, 0.1))
    reg = write_registration(tmp_path / "reg.json", from_pixel_transforms((WIDTH, HEIGHT), focal, transforms))
    args = ["reconstruct", str(capture_h5), "--tile-rows", str(TILE_ROWS), "--quiet", "--registration", str(reg)]
    assert main(args + ["--out", str(tmp_path / "one.h5")]) == 0
    assert main(args + ["--out", str(tmp_path / "dask.h5"), "--scheduler", "threads", "--workers", "2"]) == 0
    one, meta = read_depth(tmp_path / "one.h5")
    on_dask, _ = read_depth(tmp_path / "dask.h5")
    assert meta["registered"] and 0.5 < one["valid"].mean() < 1  # the border CCDs 2–4 do not see is flagged
    for k in one:
        assert np.array_equal(one[k], on_dask[k]), k


def test_a_band_that_fails_for_good_names_its_rows_and_writes_nothing(tmp_path, capture_h5, monkeypatch, capsys):
    import cohflash_jax.reconstruct.dask_bands as bands

    real = bands.open_and_reconstruct

    def failing(*args, row_band, **kwargs):
        if row_band[0] >= 16:
            raise OSError("read error on the shared file system")
        return real(*args, row_band=row_band, **kwargs)

    monkeypatch.setattr(bands, "open_and_reconstruct", failing)
    out = tmp_path / "depth.h5"
    out.write_bytes(b"an earlier result")
    args = ["reconstruct", str(capture_h5), "--out", str(out), "--tile-rows", str(TILE_ROWS), "--quiet"]
    assert main(args + ["--scheduler", "threads", "--workers", "2"]) == 2
    err = capsys.readouterr().err
    assert "failed on a Dask worker" in err and "read error on the shared file system" in err
    assert "rows 16:24" in err or "rows 16:32" in err or "rows 24:32" in err
    assert out.read_bytes() == b"an earlier result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["depth.h5"]


def test_convert_round_trip_keeps_every_frame_and_attribute(tmp_path, capture_h5, single_process):
    zarr_path = convert_capture(capture_h5, tmp_path / "c.zarr", progress=False, rows_per_chunk=8)
    back = convert_capture(zarr_path, tmp_path / "back.h5", progress=False)
    with Capture(capture_h5) as a, Capture(zarr_path) as z, Capture(back) as b:
        assert z.store == "zarr" and z.frames.chunks == (1, FRAMES, 8, WIDTH)  # pixel-major: all frames
        for cap in (z, b):
            assert np.array_equal(cap.read_tile(slice(None)), a.read_tile(slice(None)))
            assert np.array_equal(cap.frequencies_hz, a.frequencies_hz)
            assert np.array_equal(cap.hybrid_phases_rad, a.hybrid_phases_rad)
            assert cap.attrs.keys() - {"complete", "chunking"} == a.attrs.keys()
            assert cap.instrument() == a.instrument()
    options = ReconstructOptions(progress=False, tile_rows=TILE_ROWS)
    assert_same(open_and_reconstruct(zarr_path, options).outputs, single_process)


def fill_rows(path, bands):
    """A writer process: rows r0:r1 of the reference capture for each band."""
    with Capture(path.with_name("capture.h5")) as source:
        writer = ZarrCaptureWriter(path)
        for r0, r1 in bands:
            writer.write(source.read_tile(slice(r0, r1)), rows=slice(r0, r1))


def test_a_zarr_capture_filled_by_two_processes_at_once_reads_back_complete(tmp_path, capture_h5):
    (tmp_path / "capture.h5").symlink_to(capture_h5)
    path = tmp_path / "two.zarr"
    with Capture(capture_h5) as cap:
        header, reference = CaptureHeader.of(cap), cap.read_tile(slice(None))
    create_zarr_capture(path, header, rows_per_chunk=4, cols_per_chunk=8)
    with pytest.raises(CaptureError, match="incomplete"):
        Capture(path)
    with pytest.raises(CaptureError, match="whole chunks"):  # a band that would share a chunk
        ZarrCaptureWriter(path).write(reference[:, :, 2:6], rows=slice(2, 6))
    # interleaved bands, so both writers work on every part of the array at once
    bands = [(r0, r0 + 4) for r0 in range(0, HEIGHT, 4)]
    context = multiprocessing.get_context("spawn")
    writers = [context.Process(target=fill_rows, args=(path, bands[k::2])) for k in range(2)]
    for w in writers:
        w.start()
    for w in writers:
        w.join(120)
        assert w.exitcode == 0
    finish_zarr_capture(path)
    with Capture(path) as cap:
        assert np.array_equal(cap.read_tile(slice(None)), reference)


def test_finishing_a_capture_with_a_missing_band_names_what_is_missing(tmp_path, capture_h5):
    with Capture(capture_h5) as cap:
        header, reference = CaptureHeader.of(cap), cap.read_tile(slice(None))
    path = create_zarr_capture(tmp_path / "partial.zarr", header, rows_per_chunk=8)
    ZarrCaptureWriter(path).write(reference[:, :, :24], rows=slice(0, 24))
    with pytest.raises(CaptureError, match="4 of 16 chunks of frames were never written"):
        finish_zarr_capture(path)
    ZarrCaptureWriter(path).write(reference[:, :, 24:], rows=slice(24, 32))
    finish_zarr_capture(path)
    chunk_file = next(p for p in (path / "frames" / "c").rglob("*") if p.is_file())  # deleted after finishing
    chunk_file.unlink()
    with pytest.raises(CaptureError, match="1 of 16 chunks of frames are missing"):
        Capture(path)


def test_writers_owning_bands_of_frames_and_a_simulated_zarr_capture(tmp_path, capture_h5):
    with Capture(capture_h5) as cap:
        header, reference = CaptureHeader.of(cap), cap.read_tile(slice(None))
    path = create_zarr_capture(tmp_path / "frames.zarr", header, frames_per_chunk=FRAMES // 4)
    for m0 in (FRAMES // 2, 0):  # two writers' halves, in either order
        ZarrCaptureWriter(path).write(reference[:, m0 : m0 + FRAMES // 2], frames=slice(m0, m0 + FRAMES // 2))
    finish_zarr_capture(path)
    with Capture(path) as cap:
        assert np.array_equal(cap.read_tile(slice(None)), reference)
    # `simulate --out NAME.zarr` writes a store (chunks of the simulator's frame bands)
    assert (
        main(["simulate", "planar", "--size", "8x8", "--steps", "64", "--out", str(tmp_path / "s.zarr"), "--quiet"])
        == 0
    )
    with Capture(tmp_path / "s.zarr") as cap:
        assert cap.store == "zarr" and cap.shape == (64, 8, 8) and cap.truth_names == ["depth_m", "reflectance"]


def test_sweep_monte_carlo_on_dask_gives_the_same_rows(tmp_path, client):
    from cohflash_jax.design.grid import run_sweep

    axes = [("num_steps", np.array([64.0, 128.0]))]
    kwargs = dict(fixed={"distance_m": 10.0}, mc_all=True, mc_trials=16, progress=False)
    local = run_sweep(axes, tmp_path / "local.csv", **kwargs)
    on_dask = run_sweep(axes, tmp_path / "dask.csv", client=client, **kwargs)
    assert (tmp_path / "local.csv").read_text() == (tmp_path / "dask.csv").read_text()
    assert [r["mc_trials"] for r in on_dask] == [r["mc_trials"] for r in local] == [16.0, 16.0]
