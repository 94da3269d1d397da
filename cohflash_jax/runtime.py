"""Process-level tuning for long reconstructions."""

from __future__ import annotations

import ctypes
import os
import sys
from pathlib import Path

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters (malloc.h)
_applied = False


def async_filter_jit(fun):
    """`jax.jit` of `fun` with its non-array arguments static, as `eqx.filter_jit` does, but
    returning as soon as the work is queued. `eqx.filter_jit` (equinox 0.13) waits for every
    call to finish (it blocks on a marker output, for its runtime-error reporting), so a
    pipeline of filter-jitted programs never overlapped file reads and host copies with
    computation. Outputs: arrays only; no runtime errors are raised from inside, so
    `eqx.error_if` does not belong in `fun`."""
    import functools

    import equinox as eqx
    import jax

    @functools.partial(jax.jit, static_argnums=0)
    def run(static, dynamic):
        args, kwargs = eqx.combine(dynamic, static)
        return fun(*args, **dict(kwargs))

    @functools.wraps(fun)
    def call(*args, **kwargs):
        # keyword arguments as a tuple of pairs: the static half must be hashable
        dynamic, static = eqx.partition((args, tuple(sorted(kwargs.items()))), eqx.is_array)
        return run(static, dynamic)

    return call


def use_cpu_streams(count: int = 2) -> int:
    """Give JAX `count` CPU devices, over which a reconstruction spreads its sub-tiles
    (`reconstruct.stream_devices`), so that two sub-tiles' programs run at once. Takes effect
    only before JAX's first computation in the process (the CLI calls it first thing);
    afterwards it changes nothing. Returns the number of CPU devices in force."""
    import jax

    try:
        jax.config.update("jax_num_cpu_devices", int(count))
    except RuntimeError:  # JAX already initialised its backends: keep what it has
        pass
    return len(jax.devices("cpu"))


def retain_freed_memory(threshold_bytes: int = 1 << 30) -> bool:
    """Ask glibc to serve blocks below `threshold_bytes` from its heap and to keep freed
    memory for reuse, instead of mapping each large block afresh and unmapping it on free.

    Every sub-tile of a reconstruction allocates ~20 MB of short-lived buffers (I/Q, the
    rotated sequence, spectra); with glibc's defaults much of it goes back to the kernel and
    every reuse page-faults again (docs/performance.md). Peak memory is unchanged (freed blocks
    are reused, not added), but up to `threshold_bytes` of freed memory stays with the process
    afterwards instead of returning to the system.
    Applied once per process; a no-op off Linux/glibc. Returns whether the settings are in force."""
    global _applied
    if _applied or not sys.platform.startswith("linux"):
        return _applied
    try:
        libc = ctypes.CDLL("libc.so.6")
        _applied = bool(libc.mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes))) and bool(
            libc.mallopt(_M_TRIM_THRESHOLD, int(threshold_bytes))
        )
    except (OSError, AttributeError):  # not glibc (e.g. musl): leave the allocator alone
        _applied = False
    return _applied


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Keep XLA's compiled programs on disk between runs (the CLI turns this on).

    A `cohflash reconstruct` run would otherwise compile its sub-tile programs afresh in every
    process (docs/performance.md). Where: `path`, else $COHFLASH_JAX_CACHE, else
    $XDG_CACHE_HOME/cohflash/jax (~/.cache/cohflash/jax); COHFLASH_JAX_CACHE=off disables it.
    A directory that cannot be created leaves the cache off. Returns the directory used."""
    import jax

    setting = path if path is not None else os.environ.get("COHFLASH_JAX_CACHE")
    if setting is not None and str(setting).lower() in ("off", "0", "none", ""):
        return None
    if setting is None:
        setting = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "cohflash" / "jax"
    folder = Path(setting).expanduser()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder
