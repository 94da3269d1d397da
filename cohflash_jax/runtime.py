"""Process-level tuning for long reconstructions."""

from __future__ import annotations

import concurrent.futures
import contextlib
import contextvars
import ctypes
import functools
import os
import sys
import threading
import time
from pathlib import Path
from typing import NoReturn

import numpy as np

from .process import cli_capture_bytes, cli_command

_M_MXFAST, _M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = 1, -1, -3  # glibc mallopt parameters (malloc.h)
_applied = False

# bound of JAX's own compilation cache (least recently used out); the executable cache has its
# own (`ExecutableCache.MAX_BYTES`)
XLA_CACHE_MAX_BYTES = 512 * 2**20

# Programs first called inside `quick_compile()` are compiled for a short compile
# (`quick_compile_options`: XLA's lowest optimisation level, on the CPU its loop emitters): a small
# capture (a region of interest) runs each program once or twice, so the compile is most of its
# time and the program's speed hardly counts (docs/performance.md)
_QUICK_COMPILE: contextvars.ContextVar[bool] = contextvars.ContextVar("quick_compile", default=False)
QUICK_COMPILE_OPTIONS = {"xla_backend_optimization_level": 0}
# On the CPU a quick program is also emitted by XLA's older loop emitters: the fusion emitters'
# own lowering (MLIR, kernel by kernel) was most of a quick compile, even at the lowest level.
# Not for optimised programs, whose code the fusion emitters make faster, unless a program asks
# for them (`async_filter_jit`'s `loop_emitters`: the design's searches, as fast either way, and
# a long sweep's inversion, whose compile is most of a first run). The loop emitters
# repeat an operand for each read of it, so a long chain of steps each reading its input twice
# compiles in time doubling with each step: fit for the package's own programs, which the
# suite compiles, not for arbitrary ones (docs/performance.md)
QUICK_COMPILE_CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


def quick_compile_options(platform: str) -> dict:
    """XLA's options for a quick program (`quick_compile`) on `platform` ("cpu", "gpu", …)."""
    return QUICK_COMPILE_OPTIONS | (QUICK_COMPILE_CPU_OPTIONS if platform == "cpu" else {})


# Every program compiled for a GPU skips XLA's autotuning (its timed trials of each fusion's and
# product's kernels, at compile time): on an H100 a cold full-capture `cohflash reconstruct`
# took ~1 s less, warm runs as long and the depth files the same (docs/performance.md)
GPU_COMPILE_OPTIONS = {"xla_gpu_autotune_level": 0}


def compile_options(platform: str, quick: bool, loop_emitters: bool) -> dict:
    """XLA's options for a program on `platform`: a quick one's (`quick_compile_options`), else
    on the CPU the loop emitters alone where the program asks for them (`async_filter_jit`);
    on a GPU without autotuning (`GPU_COMPILE_OPTIONS`)."""
    if quick:
        options = quick_compile_options(platform)
    else:
        options = QUICK_COMPILE_CPU_OPTIONS if loop_emitters and platform == "cpu" else {}
    return options | (GPU_COMPILE_OPTIONS if platform == "gpu" else {})


# XLA options a compile refused as unknown in this process (`compile_lowered`)
UNKNOWN_XLA_OPTIONS: set[str] = set()

# What stands in for an option this XLA does not know, where the program's options do not set
# it themselves (`compile_lowered`). Without the loop emitters (jaxlib 0.11 and later) a program
# that asked for them (a long sweep's inversion, whose compile is most of a first run) is
# compiled by LLVM at level 1 instead of XLA's default 2: the fusion emitters' code as fast, in
# a shorter compile (on JAX 0.12 a first run 0.255 s sooner, the same depth files;
# docs/performance.md). A quick program keeps its level 0.
XLA_OPTION_STAND_INS = {"xla_cpu_use_fusion_emitters": {"xla_backend_optimization_level": 1}}


def compile_lowered(lowered, options: dict):
    """`lowered` (a `jax.jit(...).lower(...)`) compiled with XLA's `options`, less any this
    XLA does not know. Another jaxlib may drop an option (jaxlib 0.11.2 has no switch for the
    loop emitters of `QUICK_COMPILE_CPU_OPTIONS`): the program is then compiled without it,
    once found out for the whole process, rather than not compiled ahead (and not cached), with
    the option's stand-in (`XLA_OPTION_STAND_INS`) where it has one."""
    import re

    while True:
        known = {k: v for k, v in options.items() if k not in UNKNOWN_XLA_OPTIONS}
        for option in set(options) & UNKNOWN_XLA_OPTIONS:
            known = XLA_OPTION_STAND_INS.get(option, {}) | known
        try:
            return lowered.compile(compiler_options=known)
        except Exception as error:
            unknown = re.search(r"No such compile option: '(\w+)'", str(error))
            if unknown is None or unknown.group(1) not in known:
                raise
            UNKNOWN_XLA_OPTIONS.add(unknown.group(1))


@contextlib.contextmanager
def quick_compile(enabled: bool = True):
    """Compile the programs first called inside this block (in this thread) for a short
    compile rather than fast code. Programs compiled either way are kept apart."""
    token = _QUICK_COMPILE.set(bool(enabled))
    try:
        yield
    finally:
        _QUICK_COMPILE.reset(token)


def compiling_quick() -> bool:
    """Whether the program being traced now is compiled for a short compile (`quick_compile`):
    a model may then trace a smaller form of the same arithmetic, one that compiles faster
    and runs slower."""
    return _QUICK_COMPILE.get()


# Every product of float32 matrices in the programs at full float32 precision. XLA's default on
# a GPU is TF32 (a 10-bit mantissa, ~5e-4 relative): measured on an H200, a noiseless target's
# DFT window (a float32 product) then left the ML fit a reduced χ² above 5 (poor_fit), where the
# CPU's and full precision's fit is exact. On a CPU the default already is full precision.
MATMUL_PRECISION = "highest"


def async_filter_jit(fun=None, *, loop_emitters: bool = False):
    """`jax.jit` of `fun` with its non-array arguments static, as `eqx.filter_jit` does, but
    returning as soon as the work is queued. `eqx.filter_jit` (equinox 0.13) waits for every
    call to finish (it blocks on a marker output, for its runtime-error reporting), so a
    pipeline of filter-jitted programs never overlapped file reads and host copies with
    computation. Outputs: arrays in plain containers (dicts, tuples, lists: an equinox
    module's structure does not come back from the executable cache, `trees_come_back`); no
    runtime errors are raised from inside, so `eqx.error_if` does not belong in `fun`. Its
    matrix products run at `MATMUL_PRECISION`.

    Each program (one per static half and argument shapes, types and devices) is compiled
    once per process, and where the executable cache is on (`enable_compilation_cache`) it is
    loaded from disk in later processes without tracing or lowering `fun` at all
    (`ExecutableCache`).

    `loop_emitters`: on the CPU, emitted by XLA's loop emitters even where not quick
    (`QUICK_COMPILE_CPU_OPTIONS`), for programs whose compile is long and whose speed the
    fusion emitters do not change (the design's searches: their compile is most of a first
    run, docs/performance.md): `@async_filter_jit(loop_emitters=True)`."""
    import functools

    import equinox as eqx
    import jax

    if fun is None:  # @async_filter_jit(loop_emitters=True)
        return functools.partial(async_filter_jit, loop_emitters=loop_emitters)
    programs = {}

    def flat_fun(static_leaves, mask, treedef):
        """`fun` of the array leaves alone, the other leaves (`mask` False) closed over."""

        def flat(*xs):
            arrays, others = iter(xs), iter(static_leaves)
            a, k = jax.tree.unflatten(treedef, [next(arrays) if m else next(others) for m in mask])
            with jax.default_matmul_precision(MATMUL_PRECISION):
                return fun(*a, **dict(k))

        flat.__name__ = flat.__qualname__ = getattr(fun, "__name__", "flat")  # compile logs and profiles name it
        return flat

    @functools.cache
    def traced(static_leaves, mask, treedef, quick):
        """The program as a plain `jax.jit`, for calls under another transformation (a
        compiled executable takes concrete arrays only); one per `quick` (`compiling_quick`
        may choose what it traces)."""
        return jax.jit(flat_fun(static_leaves, mask, treedef))

    def split(args, kwargs, is_array):
        # one flatten of every argument, its leaves split into arrays (the program's inputs)
        # and the rest (static: part of the program's key, so hashable), as `eqx.partition`
        # would split them but without its per-call tree maps (the 10 Hz stream: ~100 calls a map)
        leaves, treedef = jax.tree.flatten((args, tuple(sorted(kwargs.items()))))
        mask = tuple(map(is_array, leaves))
        arrays = [x for x, m in zip(leaves, mask) if m]
        static_leaves = tuple(x for x, m in zip(leaves, mask) if not m)
        return arrays, static_leaves, mask, treedef

    def get_program(arrays, static_leaves, mask, treedef, quick, wait: bool = True):
        """The program for these arrays: compiled, loaded, or (`wait`) waited for where another
        thread is getting it; None where another thread is and `wait` is False. A thread that
        gets a program holds a future of it in `programs` meanwhile, so that of the threads
        asking for one program (a call and a `prepare`), one compiles or loads it."""
        signature = host_arrays_placed(tuple(map(_argument_signature, arrays)))
        key = (static_leaves, mask, treedef, signature, quick)
        program = programs.get(key)
        if program is not None and not isinstance(program, concurrent.futures.Future):
            return program
        pending = concurrent.futures.Future()
        found = programs.setdefault(key, pending)
        if found is not pending:
            if not isinstance(found, concurrent.futures.Future):
                return found
            if not wait:
                return None
            try:
                return found.result()
            except Exception:  # that thread failed: got here afresh
                return get_program(arrays, static_leaves, mask, treedef, quick)
        try:
            flat = flat_fun(static_leaves, mask, treedef)
            parts = ((static_leaves, mask), treedef, signature)
            program = EXECUTABLES.program(fun, flat, parts, arrays, quick, loop_emitters)
        except BaseException as exc:
            programs.pop(key, None)
            pending.set_exception(exc)
            raise
        programs[key] = program
        pending.set_result(program)
        return program

    @functools.wraps(fun)
    def call(*args, **kwargs):
        arrays, static_leaves, mask, treedef = split(args, kwargs, eqx.is_array)
        quick = _QUICK_COMPILE.get()
        if any(isinstance(x, jax.core.Tracer) for x in arrays):  # inside another transformation
            return traced(static_leaves, mask, treedef, quick)(*arrays)
        return get_program(arrays, static_leaves, mask, treedef, quick)(*arrays)

    def prepare(*args, **kwargs) -> None:
        """Get the program a call with arguments like these would run (loaded from the
        executable cache or compiled), without running it: arrays may be given as
        `jax.ShapeDtypeStruct`s with their sharding. Meant for another thread than the caller's
        (`reconstruct.engine.TileDispatcher.prepare`): a call for the same program made
        meanwhile waits for it rather than compiling it a second time, and a program another
        thread is getting already is left to it."""
        like_array = lambda x: eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)
        arrays, static_leaves, mask, treedef = split(args, kwargs, like_array)
        get_program(arrays, static_leaves, mask, treedef, _QUICK_COMPILE.get(), wait=False)

    call.prepare = prepare
    return call


def first_device(leaves):
    """The device the first placed array (or `jax.ShapeDtypeStruct` with a sharding) among
    `leaves` is on, or None where none is placed (NumPy arrays: JAX's default device runs them)."""
    for x in leaves:
        sharding = None if isinstance(x, np.ndarray) else getattr(x, "sharding", None)
        if sharding is not None:
            return next(iter(sharding.device_set))
    return None


def host_arrays_placed(signature: tuple) -> tuple:
    """An argument signature (`_argument_signature` of each array) with its host (NumPy) arrays
    taken as placed on the device of the first placed array, where there is one: a compiled
    program places a host array on its own device (aliased where it is aligned, not copied),
    so a call with host arrays runs the program a call with them placed runs, without the
    caller's `jax.device_put` of each (docs/performance.md). A program over several devices
    keeps host arrays apart."""
    if all(s[3] is not None for s in signature):
        return signature
    import jax

    sharding = next((s[3] for s in signature if s[3] is not None), None)
    if not isinstance(sharding, jax.sharding.SingleDeviceSharding):
        return signature
    return tuple(s if s[3] is not None else s[:3] + (sharding,) for s in signature)


def _argument_signature(x):
    """What a compiled program depends on in an argument: shape, dtype, weak type and, for a
    placed array, its sharding (device). Read from the attributes, the dtype as it is: both
    `jax.typeof` and `str` of a dtype cost more than the rest of a call (docs/performance.md)."""
    if isinstance(x, np.ndarray):
        return (x.shape, x.dtype, False, None)
    return (x.shape, x.dtype, bool(getattr(x, "weak_type", False)), getattr(x, "sharding", None))


_LAPACK_BOUND = False


def bind_lapack_kernels():
    """Bind LAPACK's kernels in this process, once. JAX binds them when it lowers a program
    that uses one; an executable loaded from disk into a process that has lowered none calls
    an unbound kernel and crashes (a segmentation fault in `eigh`, tested). Lowering a 2×2
    Cholesky binds them all; nothing is compiled."""
    global _LAPACK_BOUND
    if not _LAPACK_BOUND:
        import jax

        jax.jit(jax.lax.linalg.cholesky).lower(np.eye(2))
        _LAPACK_BOUND = True


class CpuRebindError(RuntimeError):
    """An executable compiled for one CPU device could not be loaded for another."""


# An entry compiled for one CPU device is loaded for the process's other CPU devices
# (`load_on_cpu_device`), unless this is off or a load found that this JAX cannot
CPU_ENTRIES_SHARED = True


def load_on_cpu_device(payload: bytes, in_tree, out_tree, device):
    """An executable serialised for one CPU device (`jax.experimental.serialize_executable`)
    loaded for `device`, another CPU device of this process: the same machine code, its device
    assignment replaced. `deserialize_and_load` keeps the assignment it was compiled with and
    refuses arguments placed elsewhere; without this, two CPU streams compile every program
    twice (docs/performance.md). The pickle is read as `deserialize_and_load` reads it (its
    persistent ids: the executable's bytes, devices by id, the client), each device read as
    `device`; where that fails (another JAX), `CpuRebindError`."""
    import io
    import pickle

    import jax
    from jaxlib import xla_client

    options = xla_client.CompileOptions()
    options.device_assignment = xla_client.DeviceAssignment.create(np.array([[device.id]]))
    devices = xla_client.DeviceList((device,))

    class Unpickler(pickle.Unpickler):
        def persistent_load(self, pid):
            if pid[0] == "exec":
                return device.client.deserialize_executable(pid[1], devices, options)
            if pid[0] == "device":
                return device
            if pid[0] == "client":
                return device.client
            raise pickle.UnpicklingError(f"unknown persistent id {pid[0]!r}")

    try:
        unloaded, args_info_flat, no_kwargs = Unpickler(io.BytesIO(payload)).load()
        return jax.stages.Compiled(
            unloaded.load(), [], in_tree.unflatten(args_info_flat), out_tree, no_kwargs=no_kwargs
        )
    except Exception as exc:
        raise CpuRebindError(f"an executable could not be moved to {device}: {exc}") from exc


class ExecutableCache:
    """Compiled programs kept on disk whole, keyed by everything that determines them.

    JAX's persistent compilation cache saves XLA's compile, but a fresh process must still
    trace and lower every program to find its key: on the full capture's `ml` programs that
    was 1.4 s of tracing and 0.2 s of lowering in every run (docs/performance.md). Here the
    key is computed without tracing: the function's module and name, the static half's
    structure and values, the arguments' shapes, types and devices, the package's own source
    (any edit to it changes every key), the JAX and jaxlib versions, the XLA flags, the 64-bit
    setting and the CPU's features. A static half whose text is not stable across processes
    (an object printed with its address) is not written to disk; programs that cannot be
    serialised (closed-over constants) compile as usual. Entries are `<name>-<sha256>.exe`
    pickles written atomically; the folder is bounded (`MAX_BYTES`, oldest used first out)."""

    MAX_BYTES = 512 * 2**20

    def __init__(self):
        self.folder: Path | None = None
        self._environment: str | None = None
        self.loaded = self.compiled = 0  # programs this process loaded and compiled
        self.load_seconds = self.compile_seconds = 0.0
        # the entries this process loaded or compiled on the default backend's devices, each
        # with the index of the device (in `jax.devices()`) it ran on, in order (an entry may run
        # on several CPU devices: `placement`)
        self.used: dict[tuple[str, int], None] = {}
        self.prefetched: dict = {}  # (entry path, device) → the future of its load (`prefetch`)
        self.cpu_rebind_failed = False  # an entry could not be moved between CPU devices (`placement`)
        self.prefetched_used = 0

    def environment(self) -> str:
        """The process-wide half of every key."""
        if self._environment is None:
            import hashlib
            import platform

            import jax
            import jaxlib

            source = hashlib.sha256()
            package = Path(__file__).resolve().parent
            for path in sorted(package.rglob("*.py")):
                source.update(str(path.relative_to(package)).encode())
                source.update(path.read_bytes())
            cpu = ""
            try:
                for line in Path("/proc/cpuinfo").read_text().splitlines():
                    if line.startswith(("flags", "model name", "Features")):
                        cpu += line
            except OSError:
                cpu = platform.processor()
            self._environment = "|".join(
                (
                    source.hexdigest(),
                    jax.__version__,
                    jaxlib.__version__,
                    os.environ.get("XLA_FLAGS", ""),
                    str(jax.config.jax_enable_x64),
                    platform.machine(),
                    hashlib.sha256(cpu.encode()).hexdigest(),
                )
            )
        return self._environment

    def key(self, fun, static, treedef, signature, quick: bool = False, loop_emitters: bool = False) -> str | None:
        """The entry's file name, or None where the static leaves (and the array mask:
        `async_filter_jit`) or the arguments' structure, whose nodes hold the modules' static
        fields, have no stable text."""
        import hashlib

        text = f"{static!r}|{treedef}"
        if " at 0x" in text:
            return None
        # element types by name (JAX's key types too): a program takes the native type whatever
        # byte order an input's dtype spells out (a Zarr store's frames are dtype('<u2'), an
        # HDF5 file's dtype('uint16'))
        shapes = repr([(shape, str(dtype.name), weak, self.placement(sh)) for shape, dtype, weak, sh in signature])
        parts = (self.environment(), fun.__module__, fun.__qualname__, text, shapes)
        whole = "|".join(parts + (("quick",) if quick else ()) + (("loop-emitters",) if loop_emitters else ()))
        return f"{fun.__name__.strip('_')}-{hashlib.sha256(whole.encode()).hexdigest()[:40]}.exe"

    def placement(self, sharding) -> str | None:
        """An argument's placement as its entry's name reads it: a single CPU device stands
        for any of this process's CPU devices (an entry compiled for one is loaded for another,
        `load_on_cpu_device`: two CPU streams compile each program once), any other
        placement for itself."""
        import jax

        if sharding is None:
            return None
        if (
            isinstance(sharding, jax.sharding.SingleDeviceSharding)
            and CPU_ENTRIES_SHARED
            and not self.cpu_rebind_failed
        ):
            (device,) = sharding.device_set
            if device.platform == "cpu":
                return "SingleDeviceSharding(cpu)"
        return repr(sharding)

    def program(self, fun, flat, parts, leaves, quick: bool = False, loop_emitters: bool = False):
        """The compiled `flat` for these leaves: from disk, else compiled (and written);
        `quick`: compiled for a short compile (`quick_compile`); `loop_emitters`: see
        `async_filter_jit`."""
        import jax

        jitted = jax.jit(flat)
        name = self.key(fun, *parts, quick, loop_emitters) if self.folder is not None else None
        if name is None:
            return self._compile(jitted, leaves, None, quick, loop_emitters) if quick or loop_emitters else jitted
        path = self.folder / name
        device, devices = first_device(leaves), jax.devices()
        if device is None or device in devices:  # what the next run's `prefetch` can load
            self.used[name, 0 if device is None else devices.index(device)] = None
        program = self._load(path, jitted, leaves, quick, loop_emitters)
        if program is None:
            # processes sharing the folder (test workers, Dask workers, two runs started
            # together) compile a program once: the others wait for its entry and load it
            with entry_lock(path):
                program = self._load(path, jitted, leaves, quick, loop_emitters)
                if program is None:
                    program = self._compile(jitted, leaves, path, quick, loop_emitters)
        return program

    def _load(self, path: Path, jitted, leaves, quick: bool, loop_emitters: bool = False):
        """The entry at `path` loaded for these leaves, or None where there is none (a damaged
        or foreign entry is removed)."""
        if not path.exists():
            return None
        started = time.perf_counter()
        device = first_device(leaves)
        devices = None if device is None else [device]
        program = self._prefetched_program(path, devices)
        try:
            if program is None:
                program = self._deserialize(path, devices)
            os.utime(path)  # recently used: the bound removes the oldest first
        except CpuRebindError:  # another CPU device's entry that cannot be moved: kept, and
            self.cpu_rebind_failed = True  # this program compiled here alone (later ones per device)
            return self._compile(jitted, leaves, None, quick, loop_emitters)
        except Exception:  # a damaged or foreign entry: compiled afresh and replaced
            path.unlink(missing_ok=True)
            return None
        self.loaded += 1
        self.load_seconds += time.perf_counter() - started
        return self._checked(program, path, lambda: self._compile(jitted, leaves, path, quick, loop_emitters))

    @staticmethod
    def _deserialize(path: Path, devices=None):
        """The executable of the entry at `path`, loaded for `devices` (None: those it was
        compiled for)."""
        import pickle

        from jax.experimental.serialize_executable import deserialize_and_load

        payload, in_tree, out_tree = pickle.loads(path.read_bytes())
        if b"lapack_" in payload:  # it calls LAPACK kernels: bound before it runs
            bind_lapack_kernels()
        if devices is None or len(devices) != 1 or devices[0].platform != "cpu" or not CPU_ENTRIES_SHARED:
            return deserialize_and_load(payload, in_tree, out_tree, execution_devices=devices)
        # one CPU device: the entry may have been compiled for another of this process's
        # (`placement`), which `deserialize_and_load` finds out only after loading the whole
        # executable, so it is loaded for this device at once, whichever it was compiled for
        try:
            return load_on_cpu_device(payload, in_tree, out_tree, devices[0])
        except CpuRebindError as cannot_move:
            try:  # another JAX: loadable still on the device it was compiled for
                return deserialize_and_load(payload, in_tree, out_tree, execution_devices=devices)
            except KeyError:
                raise cannot_move from None

    def _prefetched_program(self, path: Path, devices):
        """The executable `prefetch` loaded for `path` (waiting for it), where it was loaded
        onto the device the arguments are on (None: the default device); else None."""
        import jax

        future = self.prefetched.pop((path, jax.devices()[0] if devices is None else devices[0]), None)
        if future is None:
            return None
        try:
            program = future.result()
        except Exception:  # damaged: loaded the usual way
            return None
        self.prefetched_used += 1
        return program

    def prefetch(self, names) -> bool:
        """Load the entries `names` (as `recent` gives them: `NAME` runs on the default device,
        `NAME@K` on device K of `jax.devices()`, e.g. a second CPU stream) in a thread, each
        onto its device, for `_load` to take when the programs are asked for.
        `deserialize_and_load` releases the GIL, so the load overlaps the caller's Python.
        Returns whether any load started."""
        import concurrent.futures

        import jax

        devices, wanted = jax.devices(), []
        for note in names:
            name, _, index = note.partition("@")
            k = int(index) if index.isdigit() else 0
            if self.folder is not None and name.endswith(".exe") and "/" not in name and k < len(devices):
                wanted.append((self.folder / name, devices[k]))
        wanted = [(p, d) for p, d in dict.fromkeys(wanted) if p.exists() and (p, d) not in self.prefetched]
        if not wanted:
            return False
        # each onto its device by name: left to the entry, an executable loads for every local
        # device where there are several (two CPU streams) and refuses one device's arguments.
        # A thread a device: the first sub-tiles of a tile go to every device at once
        for device in dict.fromkeys(d for _, d in wanted):
            pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="executable-prefetch")
            self.prefetched.update({(p, d): pool.submit(self._deserialize, p, [d]) for p, d in wanted if d == device})
            pool.shutdown(wait=False)  # its thread ends with its last load
        return True

    def loading(self) -> bool:
        """Whether entries `prefetch` started loading are still to be taken: the programs this
        process is about to run are then most likely on disk already."""
        return bool(self.prefetched)

    # bound of the notes of recent runs (`remember`): a few hundred
    MAX_NOTE_BYTES = 64 * 2**10

    def recent(self, command: str, input_bytes: int | None) -> list[str]:
        """The entries the last `remember`ed run of `command` on an input of `input_bytes`
        used (programs follow the capture's shape, which its size stands for)."""
        if self.folder is None or input_bytes is None:
            return []
        try:
            return (self.folder / f"recent-{command}-{input_bytes}.txt").read_text().split()
        except OSError:
            return []

    def remember(self, command: str, input_bytes: int | None) -> None:
        """Note the entries this process used as `command`'s most recent on an input of
        `input_bytes` (`recent`)."""
        if self.folder is None or input_bytes is None or not self.used:
            return
        path = self.folder / f"recent-{command}-{input_bytes}.txt"
        notes = [name if k == 0 else f"{name}@{k}" for name, k in self.used]
        if replace_file(path, ("\n".join(notes) + "\n").encode()):
            bound_folder(self.folder, "recent-*.txt", self.MAX_NOTE_BYTES)

    def _checked(self, program, path: Path, recompile):
        """`program`, whose first call waits for its result: an entry that loads but cannot
        run (an executable missing a kernel reports so only when it runs) is removed and the
        program compiled afresh, instead of failing the run."""
        import jax

        state = {"program": program, "checked": False}

        def run(*xs):
            if state["checked"]:
                return state["program"](*xs)
            state["checked"] = True
            try:
                return jax.block_until_ready(program(*xs))
            except Exception:
                path.unlink(missing_ok=True)
                state["program"] = recompile()
                return state["program"](*xs)

        return run

    def _compile(self, jitted, leaves, path: Path | None, quick: bool = False, loop_emitters: bool = False):
        """Compile `jitted` for these leaves and write the executable to `path` (None: kept in
        this process only); `quick`: for a short compile (`quick_compile_options`);
        `loop_emitters`: see `async_filter_jit`."""
        import jax

        started = time.perf_counter()
        try:
            # an executable that came from JAX's own cache serialises without its kernels
            # (measured: "Function wrapped_is-finite not found" when loaded in the next
            # process), so this compile must not be served from there: a debugging option
            # (how many buffers a buffer-assignment dump lists) with a value of its own gives
            # it a key of its own in that cache
            options = {"xla_debug_buffer_assignment_show_max": 1_000_000 + time.monotonic_ns() % 1_000_000_000}
            device = first_device(leaves)
            platform = jax.default_backend() if device is None else device.platform
            options |= compile_options(platform, quick, loop_emitters)
            with JAX_CACHE_ENTRIES.held_off():
                compiled = compile_lowered(jitted.lower(*leaves), options)
        except Exception:  # e.g. an argument jit accepts but lowering with it does not
            return jitted
        self.compiled += 1
        if path is not None:
            self._write(path, compiled)
        self.compile_seconds += time.perf_counter() - started
        return compiled

    def _write(self, path: Path, compiled):
        """Write `compiled` to `path`, where a later process can load it (`trees_come_back`)."""
        import pickle

        try:
            from jax.experimental.serialize_executable import serialize

            serialized = serialize(compiled)
            if not trees_come_back(serialized[1:]):
                return
            blob = pickle.dumps(serialized)
        except Exception:  # not serialisable (closed-over constants, …): stays in this process
            return
        if replace_file(path, blob):
            self.bound()

    def bound(self):
        bound_folder(self.folder, "*.exe", self.MAX_BYTES)


class JaxCacheEntries:
    """Holds off JAX's own persistent-cache entries while executable cache compiles run
    (`held_off`). Such a compile has a key of its own in JAX's cache, never read again
    (`ExecutableCache._compile`): its entry would serialise and compress the executable a
    second time, on a first run's way to its first dispatch, and fill the cache's folder. JAX's
    threshold for writing an entry is set per process (`jax.config`), so while any thread
    holds entries off, a plain `jax.jit` compile elsewhere in the process is not written
    either: it is compiled again by a later process, nothing worse."""

    OPTION = "jax_persistent_cache_min_compile_time_secs"

    def __init__(self):
        self.lock = threading.Lock()
        self.holders = 0
        self.threshold_s = None  # the threshold the first holder replaced

    @contextlib.contextmanager
    def held_off(self):
        import jax

        with self.lock:
            if self.holders == 0:
                try:
                    self.threshold_s = getattr(jax.config, self.OPTION)
                    jax.config.update(self.OPTION, float("inf"))
                except (AttributeError, KeyError, ValueError):  # another JAX: entries as before
                    self.threshold_s = None
            self.holders += 1
        try:
            yield
        finally:
            with self.lock:
                self.holders -= 1
                if self.holders == 0 and self.threshold_s is not None:
                    jax.config.update(self.OPTION, self.threshold_s)


JAX_CACHE_ENTRIES = JaxCacheEntries()


def trees_come_back(trees) -> bool:
    """Whether the argument and output structures of an executable (`serialize`'s in_tree,
    out_tree) are the same after a trip through pickle. An equinox module's structure is not
    (its field sentinel comes back a copy): an entry of a program returning one would load,
    fail at its first call and be compiled again in every process (`_checked`), so such a
    program stays in its process, and programs return plain containers of arrays."""
    import pickle

    try:
        return all(pickle.loads(pickle.dumps(tree)) == tree for tree in trees)
    except Exception:
        return False


# How long a process waits for another one's compile of the same program before compiling it too
ENTRY_LOCK_WAIT_S = 600.0


@contextlib.contextmanager
def entry_lock(path: Path, wait_s: float = ENTRY_LOCK_WAIT_S):
    """Hold the lock of a cache entry's compile: an advisory `flock` on `.<name>.lock` beside
    it, so that of the processes (or threads) that need one program, one compiles it and the
    others wait. The system releases the lock of a process that dies; the holder removes the
    file, and a waiter that locked a removed file tries again. Where locks are not supported,
    or after `wait_s`, it goes on unlocked: at worst a program is compiled twice."""
    try:
        import fcntl
    except ImportError:  # not a POSIX system
        yield
        return
    lock_path = path.with_name(f".{path.name}.lock")
    deadline = time.monotonic() + wait_s
    fd = None
    try:
        while time.monotonic() < deadline:
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:  # another process is compiling it
                os.close(fd)
                fd = None
                time.sleep(0.05)
                continue
            try:
                current = os.stat(lock_path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                current = False
            if current:
                break
            os.close(fd)  # locked a file its holder had removed: lock the new one
            fd = None
    except OSError:  # no locks on this file system
        if fd is not None:
            os.close(fd)
        fd = None
    try:
        yield
    finally:
        if fd is not None:
            try:
                os.unlink(lock_path)
            except OSError:
                pass
            os.close(fd)


def replace_file(path: Path, data: bytes) -> bool:
    """Write `data` to `path` whole or not at all (a temporary beside it, renamed over it), so
    that processes sharing the cache never read half an entry. Returns whether it was written."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        temporary.write_bytes(data)
        os.replace(temporary, path)
    except OSError:
        temporary.unlink(missing_ok=True)
        return False
    return True


def bound_folder(folder: Path, pattern: str, max_bytes: int):
    """Remove the files matching `pattern` in `folder`, oldest modified first, until those left
    hold ≤ max_bytes (a cache's bound; entries in use are rewritten or touched)."""
    try:
        entries = sorted(folder.glob(pattern), key=lambda p: p.stat().st_mtime)
        total = sum(p.stat().st_size for p in entries)
        for p in entries:
            if total <= max_bytes:
                break
            total -= p.stat().st_size
            p.unlink(missing_ok=True)
    except OSError:  # a cache that cannot be tidied is still a cache
        pass


EXECUTABLES = ExecutableCache()


# CPU devices the CLI asks for, unless a command asks otherwise (`COMMAND_CPU_STREAMS`): one.
# Two let two programs run at once, which pays where one program leaves a core idle; a program
# is compiled once and loaded for the second device (`load_on_cpu_device`); measured in
# docs/performance.md
CLI_CPU_STREAMS = 1
# the simulator's frame chunks gain from two (one chunk's program leaves a core idle); so do a
# stream of short captures (the 10 Hz maps: small programs, a core idle while the other
# dispatches) and a capture's sub-tiles read straight into place (`engine.PieceReader`)
COMMAND_CPU_STREAMS = {"simulate": 2, "stream": 2, "reconstruct": 2}


# jaxlib versions whose CPU client hangs with several CPU devices: under jaxlib 0.11.2 a
# `cohflash reconstruct` over two CPU devices waited for ever on a result in 3 of 4 runs (a 64×64
# capture of 1,200 frames; no thread working, with or without the compile cache and the native
# kernel), where 0.10.2 and 0.12.0.1 never did (docs/performance.md). They get one CPU device.
SINGLE_CPU_STREAM_JAXLIBS = ("0.11.",)


def several_cpu_streams_run(jaxlib_version: str | None = None) -> bool:
    """Whether this jaxlib (or `jaxlib_version`) runs several CPU devices without hanging
    (`SINGLE_CPU_STREAM_JAXLIBS`)."""
    if jaxlib_version is None:
        import jaxlib

        jaxlib_version = jaxlib.__version__
    return not jaxlib_version.startswith(SINGLE_CPU_STREAM_JAXLIBS)


def cli_cpu_streams(command: str | None) -> int:
    """The number of JAX CPU devices the `cohflash` command `command` runs with."""
    return COMMAND_CPU_STREAMS.get(command, CLI_CPU_STREAMS)


def use_cpu_streams(count: int = CLI_CPU_STREAMS) -> int:
    """Give JAX `count` CPU devices, over which a reconstruction spreads its sub-tiles and a
    simulation its frame chunks (`stream_devices`), so that several programs run at once.
    Every program is compiled once per device. Takes effect only before JAX's first
    computation in the process (the CLI calls it first thing); afterwards it changes nothing.
    Returns the number of CPU devices in force (0 where `JAX_PLATFORMS` leaves the CPU out); one
    where this jaxlib hangs with more (`several_cpu_streams_run`)."""
    import jax

    if not several_cpu_streams_run():
        count = min(int(count), 1)
    try:
        jax.config.update("jax_num_cpu_devices", int(count))
    except RuntimeError:  # JAX already initialised its backends: keep what it has
        pass
    try:
        return len(jax.devices("cpu"))
    except RuntimeError:  # JAX_PLATFORMS leaves the CPU out (e.g. "cuda"): no CPU devices
        return 0


def device_value(value):
    """A NumPy array or Python number as a JAX array on the default device, typed as
    `jnp.asarray` types it (a Python float weakly), by a copy: `jnp.asarray` stages the
    conversion as an XLA program of its own, one per shape, which every process compiles or
    loads from JAX's cache before its first use, on its way to its first dispatch
    (docs/performance.md)."""
    import jax

    return jax.device_put(value)


def stream_devices() -> list:
    """The devices sub-tiles of a reconstruction (and chunks of a simulation) are spread over,
    in turn: every local CPU device where JAX has several (`use_cpu_streams`), else the
    default device alone. One CPU device runs its programs one at a time, so where a program
    has serial stretches that leave cores idle (the simulator's chunks), two devices run two
    programs at once."""
    import jax

    devices = jax.local_devices()
    return devices if devices[0].platform == "cpu" else devices[:1]


def place_on_devices(tree, devices: list) -> list:
    """`tree` with its arrays placed on each of `devices` (the tree itself where there is one)."""
    import equinox as eqx
    import jax

    if len(devices) == 1:
        return [tree]
    put = lambda tree, d: jax.tree.map(lambda x: jax.device_put(x, d) if eqx.is_array(x) else x, tree)
    return [put(tree, d) for d in devices]


def retain_freed_memory(threshold_bytes: int = 1 << 30) -> bool:
    """Ask glibc to serve blocks below `threshold_bytes` from its heap and to keep freed
    memory for reuse, instead of mapping each large block afresh and unmapping it on free.

    Every sub-tile of a reconstruction allocates ~20 MB of short-lived buffers (I/Q, the
    rotated sequence, spectra); with glibc's defaults much of it goes back to the kernel and
    every reuse page-faults again (docs/performance.md). Peak memory is unchanged (freed blocks
    are reused, not added), but up to `threshold_bytes` of freed memory stays with the process
    afterwards instead of returning to the system. glibc's fast bins are turned off too: loading
    a compiled program builds and frees a large module of small objects, whose fast bins glibc
    consolidates again and again (a full capture's inversion program: 0.207 → 0.185 s a load).
    Applied once per process; a no-op off Linux/glibc. Returns whether the settings are in force."""
    global _applied
    if _applied or not sys.platform.startswith("linux"):
        return _applied
    try:
        libc = ctypes.CDLL("libc.so.6")
        _applied = (
            bool(libc.mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)))
            and bool(libc.mallopt(_M_TRIM_THRESHOLD, int(threshold_bytes)))
            and bool(libc.mallopt(_M_MXFAST, 0))
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
    # JAX's own bound needs the `filelock` package; the folder is bounded here instead
    bound_folder(folder, "jit_*", XLA_CACHE_MAX_BYTES)
    executables = folder / "executables"
    try:
        executables.mkdir(exist_ok=True)
        EXECUTABLES.folder = executables
    except OSError:
        EXECUTABLES.folder = None
    return folder


# Commands whose runs load the same executables run after run (one capture size's programs):
# the next run of one loads its last run's entries while the package is still being imported
PREFETCH_COMMANDS = ("reconstruct", "stream")


def prefetch_for_cli(argv) -> bool:
    """Where this interpreter runs a `cohflash` command of `PREFETCH_COMMANDS` with the
    executable cache on: JAX's CPU devices and the cache set up as the CLI will, and the
    entries that command's last run on a capture of the same size (a file's, or a Zarr store's
    frames: `process.cli_capture_bytes`) used loaded in a thread (`ExecutableCache.prefetch`).
    The package calls it on import, just after importing JAX: the rest of its imports and the
    command's start (~0.4 s) then hide most of the load (0.36 s for a full capture's
    programs). Returns whether a load started."""
    command = cli_command(argv)
    if command not in PREFETCH_COMMANDS:
        return False
    try:  # a speed-up only: whatever goes wrong here, the command runs as it would without
        use_cpu_streams(cli_cpu_streams(command))
        if enable_compilation_cache() is None:
            return False
        retain_freed_memory()  # before the loads (their allocations)
        return EXECUTABLES.prefetch(EXECUTABLES.recent(command, cli_capture_bytes(argv)))
    except Exception:
        return False


def cpuinfo_fields(cpuinfo: str | None = None) -> dict[str, str]:
    """The first processor's entry of /proc/cpuinfo (or of the text `cpuinfo`) as a dict of its
    fields ("model name", "flags", "cpu family", …); empty where it cannot be read."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return {}
    fields = {}
    for line in cpuinfo.splitlines():
        if not line.strip():
            break  # the first processor's entry ends
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    return fields


@functools.cache
def cpu_model_and_flags() -> tuple[str, frozenset[str]]:
    """The CPU's model name and feature flags as /proc/cpuinfo lists them (the platform's
    processor name and no flags where it cannot be read). The platform's name is asked for
    only then: on Linux `platform.processor` runs `uname -p` in a child process."""
    import platform

    fields = cpuinfo_fields()
    model, flags = fields.get("model name"), frozenset(fields.get("flags", "").split())
    return model or platform.processor() or "unknown CPU", flags


def xla_cpu_has_avx512() -> bool:
    """Whether XLA's CPU code may use AVX-512's byte and word instructions here: the CPU has
    them (avx512bw) and XLA_FLAGS does not hold XLA to a narrower ISA (`--xla_cpu_max_isa`).
    Some reductions vectorise under AVX-512 only, and programs choose their form by it (the
    executable cache's key holds the CPU's features and XLA_FLAGS)."""
    if "avx512bw" not in cpu_model_and_flags()[1]:
        return False
    for flag in os.environ.get("XLA_FLAGS", "").split():
        if flag.startswith("--xla_cpu_max_isa="):
            return flag.split("=", 1)[1].upper().startswith(("AVX512", "AMX"))
    return True


def cpu_family_and_model(cpuinfo: str | None = None) -> str | None:
    """The CPU's family and model numbers as /proc/cpuinfo (or the text `cpuinfo`) lists them,
    e.g. "family 25 model 17"; None where they cannot be read. They tell apart CPUs whose model
    name does not: a VM's "AMD EPYC" was a Zen 4 (family 25) on one machine and a Zen 5 (family
    26) on another, whose speeds differ (docs/performance.md)."""
    fields = cpuinfo_fields(cpuinfo)
    family, model = fields.get("cpu family"), fields.get("model")
    return f"family {family} model {model}" if family and model else None


def cpu_description() -> str:
    """The CPU as benchmarks and studies name it: model name with its family and model numbers,
    logical CPUs, the widest vector ISA XLA can use, and XLA_FLAGS where set
    (`--xla_cpu_max_isa=AVX2` holds XLA to AVX2)."""
    model, flags = cpu_model_and_flags()
    numbers = cpu_family_and_model()
    isa = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "SSE/other"
    xla = os.environ.get("XLA_FLAGS", "")
    named = f"{model} ({numbers})" if numbers else model
    return f"{named}; {os.cpu_count()} logical CPUs; ISA {isa}" + (f"; XLA_FLAGS={xla}" if xla else "")


def open_hdf5_files_for_writing() -> list[str]:
    """Names of the HDF5 files this process holds open for writing (none where h5py was never
    imported): such a file is flushed and closed only when its object is destroyed."""
    h5py = sys.modules.get("h5py")
    if h5py is None:
        return []
    names = []
    for file_id in h5py.h5f.get_obj_ids(types=h5py.h5f.OBJ_FILE):
        if file_id.get_intent() != h5py.h5f.ACC_RDONLY:
            names.append(file_id.name.decode(errors="replace"))
    return names


def exit_process(code: int | None) -> NoReturn:
    """End a command-line process with exit status `code`, as `sys.exit` would, without the
    interpreter's teardown where nothing depends on it.

    Teardown destroys every module and object in turn: JAX's client and compiled programs,
    the buffers of a whole capture, thousands of modules. A `cohflash` command's outputs are
    complete by then, so it is time the user waits for nothing (docs/performance.md has the
    measured share). Kept: the atexit handlers run first (logging's flush, JAX's wait for
    pending effects, finalizers of temporary folders), and the standard streams are flushed.
    Where teardown still has work to do, `sys.exit` does it: another Python thread running
    (teardown joins it), an HDF5 file open for writing (teardown closes and flushes it), a
    stream that cannot be flushed (a closed pipe: Python reports it and sets the status), or
    an interpreter without `atexit._run_exitfuncs`."""
    import atexit
    import threading

    code = 0 if code is None else int(code)
    others = [t for t in threading.enumerate() if t is not threading.current_thread() and not t.daemon]
    run_handlers = getattr(atexit, "_run_exitfuncs", None)
    main_thread = threading.current_thread() is threading.main_thread()
    if others or run_handlers is None or not main_thread or open_hdf5_files_for_writing():
        sys.exit(code)
    run_handlers()
    try:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None and not stream.closed:
                stream.flush()
    except (OSError, ValueError):
        sys.exit(code)
    os._exit(code)
