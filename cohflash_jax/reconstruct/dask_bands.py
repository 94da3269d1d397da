"""A capture reconstructed on Dask in bands of rows (`reconstruct_on_dask`).

The caller decides once what every band must share: the calibrated instrument and the carrier
alignment (from the first tile, as the single-process run decides it). Each band is one Dask
task (`reconstruct_band`), run inside a worker: it opens the capture (the workers read the
same path, on a shared file system for a cluster), builds its plan and programs there (the
programs compile once per worker and tile shape, or load from the shared cache) and
reconstructs its rows tile by tile exactly as the single-process run does, so the depths are
bit for bit the same. Bands come back as they finish and are placed into the whole map."""

from __future__ import annotations

import dataclasses
import math
import os
import time
import uuid
from pathlib import Path

import numpy as np

from ..capture import Capture, CaptureError
from ..estimate.drift import CarrierAlignment
from ..progress import progress_bar
from .api import FileSetup, Reconstruction, open_and_reconstruct, tile_rows
from .policy import ReconstructOptions

# a task that raises (a read error on a network file system) is run again this many times; a
# worker that dies is Dask's to handle: its tasks move to other workers, up to
# distributed.scheduler.allowed-failures deaths a task
TASK_RETRIES = 2
BANDS_PER_WORKER = 2  # enough to balance two workers' loads, few enough to keep tiles' reads overlapped


@dataclasses.dataclass(frozen=True)
class BandJob:
    """What every band of one reconstruction shares (small: sent with each task)."""

    capture_path: str
    options: ReconstructOptions
    calibration_path: str | None
    registration_path: str | None
    alignment: CarrierAlignment


@dataclasses.dataclass
class BandResult:
    """One band's outputs (rows r0:r1 of every map) and meta data, and the worker's figures."""

    row_band: tuple[int, int]
    outputs: dict
    meta: dict
    seconds: float
    worker_pid: int
    worker_peak_bytes: int


def reconstruct_band(job: BandJob, r0: int, r1: int) -> BandResult:
    """Rows r0:r1 of the job's capture (a Dask task, run inside a worker)."""
    from ..scaleout import prepare_worker, worker_peak_memory_bytes

    prepare_worker()
    t0 = time.perf_counter()
    result = open_and_reconstruct(
        job.capture_path,
        job.options,
        job.calibration_path,
        job.registration_path,
        row_band=(r0, r1),
        alignment=job.alignment,
    )
    return BandResult(
        (r0, r1), result.outputs, result.meta, time.perf_counter() - t0, os.getpid(), worker_peak_memory_bytes()
    )


@dataclasses.dataclass
class DaskRun:
    """How a distributed reconstruction went: bands, workers and their peak memory."""

    bands: int
    band_rows: int
    workers: dict  # worker pid → peak resident bytes
    band_seconds: list

    def describe(self) -> str:
        peak = max(self.workers.values(), default=0) / 2**20
        return (
            f"{self.bands} bands of {self.band_rows} rows in {len(self.workers)} worker processes; "
            f"median band {np.median(self.band_seconds):.2f} s; peak memory per worker {peak:.0f} MiB"
        )


def band_rows_for(height: int, rows_per_tile: int, num_threads: int) -> int:
    """Rows per band: whole tiles of `rows_per_tile` rows, about `BANDS_PER_WORKER` bands a
    worker thread."""
    tiles = math.ceil(height / rows_per_tile)
    return rows_per_tile * max(1, math.ceil(tiles / (BANDS_PER_WORKER * max(1, num_threads))))


def reconstruct_on_dask(
    path,
    options: ReconstructOptions,
    client,
    calibration_path=None,
    registration_path=None,
    *,
    band_rows: int | None = None,
    on_band=None,
) -> tuple[Reconstruction, DaskRun]:
    """Reconstruct a capture file on the Dask `client`'s workers → (the `Reconstruction`, as
    `open_and_reconstruct` gives it, and how the run went). `band_rows`: rows per task (a
    multiple of the tile rows; default `band_rows_for`); `on_band(done, total)`: called after
    each band is placed. A band that fails for good raises CaptureError naming its rows, and
    the other bands are cancelled: nothing is returned to be written."""
    from distributed import as_completed
    from distributed.scheduler import KilledWorker

    t0 = time.perf_counter()
    path = Path(path).resolve()
    with Capture(path) as cap:
        files = FileSetup.load(cap, calibration_path, registration_path)
        alignment = files.alignment(cap, options)
        _, h, w = cap.shape
        rows = tile_rows(cap, options)
    band_rows = band_rows or band_rows_for(h, rows, sum(client.nthreads().values()))
    if band_rows % rows:
        raise ValueError(f"band rows ({band_rows}) must be a multiple of the tile rows ({rows})")
    resolve = lambda p: None if p is None else str(Path(p).resolve())
    job = BandJob(
        str(path),
        dataclasses.replace(options, progress=False),
        resolve(calibration_path),
        resolve(registration_path),
        alignment,
    )
    token = uuid.uuid4().hex[:8]
    futures = {
        client.submit(
            reconstruct_band,
            job,
            r0,
            min(h, r0 + band_rows),
            key=f"cohflash-band-{token}-{r0}",
            retries=TASK_RETRIES,
            pure=False,
        ): r0
        for r0 in range(0, h, band_rows)
    }
    outputs: dict = {}
    meta: dict = {}
    run = DaskRun(len(futures), band_rows, {}, [])
    try:
        with progress_bar(
            total=h * w, unit="px", desc="reconstruct", disable=not options.progress, unit_scale=True
        ) as bar:
            for done, future in enumerate(as_completed(futures), start=1):
                r0 = futures[future]
                try:
                    band = future.result()
                except KilledWorker:
                    raise CaptureError(
                        f"{path}: the Dask workers reconstructing rows {r0}:{min(h, r0 + band_rows)} died "
                        "repeatedly (out of memory, or killed); nothing was written"
                    ) from None
                except Exception as exc:
                    raise CaptureError(
                        f"{path}: rows {r0}:{min(h, r0 + band_rows)} failed on a Dask worker, "
                        f"{TASK_RETRIES} retries included ({type(exc).__name__}: {exc}); nothing was written"
                    ) from exc
                future.release()  # its result leaves the worker's memory now, not at the end
                a, b = band.row_band
                for k, v in band.outputs.items():
                    outputs.setdefault(k, np.empty((h, w), v.dtype))[a:b] = v
                if a == 0:
                    meta = band.meta
                run.workers[band.worker_pid] = max(run.workers.get(band.worker_pid, 0), band.worker_peak_bytes)
                run.band_seconds.append(band.seconds)
                bar.update((b - a) * w)
                if on_band is not None:
                    on_band(done, len(futures))
    except BaseException:
        client.cancel(list(futures))
        raise
    from ..dask_cluster import describe_client

    meta = {**meta, "seconds": time.perf_counter() - t0, "scheduler": describe_client(client)}
    return Reconstruction(outputs, meta, files.setup.instrument), run
