"""Running cohflash's work on Dask (`dask.distributed`): what every worker process sets up
before its first task (`prepare_worker`), and how local workers share the cores. The clients
and the worker plugins, which import Dask: `dask_cluster`; the options: `cli.common`.

A worker runs the same JAX programs as the single-process CLI, compiled inside the worker once
per tile shape (never pickled) and kept in the persistent compilation cache, which workers on
one file system share (`runtime.enable_compilation_cache`: $COHFLASH_JAX_CACHE). The traps:
- XLA's CPU thread pools size themselves from the CPUs a process may run on and ignore most
  caps, so local worker processes are each pinned to their own set of cores (`PinnedWorker`)
  before JAX starts in them; on a cluster, start one worker per core set (`taskset`).
- JAX preallocates 75 % of a GPU's memory per process: local workers on a GPU machine are one
  per GPU, each shown only its own GPU and given a stated fraction of its memory.
- Dask keeps a finished task's result (and the scheduler its metadata) until released, so the
  caller releases each band as soon as it is placed.
"""

from __future__ import annotations

import os

SCHEDULERS = ("threads", "processes")
ADDRESS_PREFIXES = ("tcp://", "tls://", "ucx://", "inproc://")
GPU_MEMORY_FRACTION = 0.7  # of each worker's one GPU


def available_cores() -> list[int]:
    """The CPUs this process may run on."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return list(range(os.cpu_count() or 1))


def core_sets(num_workers: int, cores: list[int] | None = None) -> list[list[int]]:
    """`cores` split into `num_workers` disjoint sets as even as they go (a worker beyond the
    number of cores shares one)."""
    cores = available_cores() if cores is None else cores
    if num_workers <= len(cores):
        return [cores[i * len(cores) // num_workers : (i + 1) * len(cores) // num_workers] for i in range(num_workers)]
    return [[cores[i % len(cores)]] for i in range(num_workers)]


_prepared = False


def prepare_worker() -> None:
    """Once per process, before the first task's JAX work: the persistent compilation cache
    (shared by the workers of one file system), and the CLI's number of JAX CPU devices
    (`runtime.use_cpu_streams`). The CLI's own process has done both already."""
    global _prepared
    if _prepared:
        return
    from .runtime import enable_compilation_cache, use_cpu_streams

    enable_compilation_cache()
    use_cpu_streams()
    _prepared = True


def worker_peak_memory_bytes() -> int:
    """The peak resident memory of this process so far (bytes)."""
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)
