"""Dask clients for cohflash's work (`dask_client`): local worker threads or processes, each
process pinned to its own cores (or GPU), or a cluster at an address. The traps this designs
around are listed in `scaleout`."""

from __future__ import annotations

import contextlib
import logging
import os

from distributed import Client, LocalCluster, WorkerPlugin

from .scaleout import GPU_MEMORY_FRACTION, SCHEDULERS, available_cores, core_sets, prepare_worker

CONNECT_TIMEOUT_S = 10  # a scheduler's address that does not answer in this time is an error


class PinnedWorker(WorkerPlugin):
    """A Dask worker plugin for local worker processes: worker k runs on `cores[k]` only (every
    thread of the process, so the XLA thread pools JAX makes later size themselves to it), and
    where `gpus` are given sees only GPU `gpus[k]`, with `GPU_MEMORY_FRACTION` of its memory.
    Registered before any task, so JAX has not started in the worker yet."""

    name = "cohflash-pinned-worker"

    def __init__(self, cores: list[list[int]], gpus: list[int] | None = None):
        self.cores, self.gpus = cores, gpus

    def setup(self, worker) -> None:
        try:
            index = int(worker.name)
        except (TypeError, ValueError):
            index = abs(hash(worker.name))
        if self.gpus:
            os.environ["CUDA_VISIBLE_DEVICES"] = str(self.gpus[index % len(self.gpus)])
            os.environ["XLA_PYTHON_CLIENT_MEM_FRACTION"] = str(GPU_MEMORY_FRACTION)
        cores = set(self.cores[index % len(self.cores)])
        if hasattr(os, "sched_setaffinity"):
            for tid in os.listdir("/proc/self/task"):
                with contextlib.suppress(OSError):
                    os.sched_setaffinity(int(tid), cores)
        prepare_worker()

    def teardown(self, worker) -> None:
        pass


def local_gpus() -> list[int]:
    """The GPUs of this machine JAX sees (none on a CPU machine)."""
    import jax

    try:
        return [d.id for d in jax.devices("gpu")]
    except RuntimeError:
        return []


@contextlib.contextmanager
def dask_client(scheduler: str, workers: int | None = None):
    """A `dask.distributed.Client` for `scheduler` → yields it; local workers are shut down
    on leaving. 'threads': one worker process-free, `workers` threads (default: one per
    core); 'processes': `workers` worker processes (default: one per core, or one per GPU),
    each pinned to its own cores; an address: that cluster's scheduler (its workers are its
    own, started as its operator chose)."""
    if scheduler not in SCHEDULERS:
        if workers is not None:
            raise ValueError(
                "--workers sets local workers: a cluster at an address has the workers it was started with"
            )
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except OSError as exc:
            raise OSError(f"no Dask scheduler answered at {scheduler} ({exc}): is the cluster running?") from None
        with client:
            client.register_plugin(CompilationCacheOnWorkers())
            yield client
        return
    gpus = local_gpus() if scheduler == "processes" else []
    count = workers or len(gpus) or len(available_cores())
    if count < 1:
        raise ValueError(f"--workers must be at least 1, got {count}")
    common = dict(dashboard_address=":0", silence_logs=logging.CRITICAL)  # no fixed port: runs side by side
    if scheduler == "threads":
        cluster = LocalCluster(n_workers=1, threads_per_worker=count, processes=False, **common)
    else:
        cluster = LocalCluster(n_workers=count, threads_per_worker=1, processes=True, **common)
    with cluster, Client(cluster) as client:
        if scheduler == "processes":
            client.register_plugin(PinnedWorker(core_sets(count), gpus[:count] or None))
        yield client


class CompilationCacheOnWorkers(WorkerPlugin):
    """A worker plugin for a cluster's own workers: `prepare_worker` at start-up (their
    cores and GPUs are the cluster operator's to assign)."""

    name = "cohflash-compilation-cache"

    def setup(self, worker) -> None:
        prepare_worker()

    def teardown(self, worker) -> None:
        pass


def describe_client(client) -> str:
    """The workers a client has, in words."""
    threads = client.nthreads()
    return f"Dask at {client.scheduler.address}: {len(threads)} workers, {sum(threads.values())} threads"
