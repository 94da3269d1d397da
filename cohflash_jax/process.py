"""What a `cohflash` process sets before JAX and NumPy load.

Read off the interpreter's own command line (`sys.orig_argv`), so a library user's process, a
test run or a Dask worker keeps its settings. Imports nothing but the standard library: the
package imports this module first, while NumPy's BLAS and JAX's backends still read their
environment."""

from __future__ import annotations

import contextlib
import gc
import json
import math
import os
import re
import sys

_PAUSED = False  # garbage collection paused by `pause_garbage_collection_for_cli`


def cli_command(argv) -> str | None:
    """The `cohflash` command an interpreter runs, read off its own command line
    (`sys.orig_argv`): `cohflash CMD …` (the console script) or `python … -m cohflash_jax.cli
    CMD …`; None for anything else (a library user, a test run, a Dask worker)."""
    argv = list(argv)
    for k, arg in enumerate(argv):
        if k >= 1 and os.path.basename(arg) == "cohflash":
            rest = argv[k + 1 :]
        elif arg == "-m" and argv[k + 1 : k + 2] == ["cohflash_jax.cli"]:
            rest = argv[k + 2 :]
        else:
            continue
        return rest[0] if rest and not rest[0].startswith("-") else None
    return None


def cli_input_path(argv) -> str | None:
    """The largest existing file named on a command line: a `cohflash` run's capture (the depth
    file it may overwrite, a calibration or a registration are smaller); None where none is."""
    sizes = {}
    for arg in argv[1:]:
        try:
            if not arg.startswith("-") and os.path.isfile(arg):
                sizes[arg] = os.path.getsize(arg)
        except (OSError, ValueError):
            continue
    return max(sizes, key=sizes.get, default=None)


def cli_input_bytes(argv) -> int | None:
    """The size of `cli_input_path`'s file (None where there is none)."""
    path = cli_input_path(argv)
    try:
        return None if path is None else os.path.getsize(path)
    except OSError:
        return None


def zarr_frames_bytes(folder) -> int | None:
    """The frames' size in bytes of a Zarr capture store (`capture_zarr`): their shape times
    their item size, from `frames/zarr.json` (whatever the chunks on disk hold, compressed or
    not written yet); None where the folder is not such a store."""
    try:
        with open(os.path.join(folder, "frames", "zarr.json"), encoding="utf-8") as f:
            meta = json.load(f)
        bits = int("".join(ch for ch in str(meta["data_type"]) if ch.isdigit()) or 8)
        return math.prod(int(n) for n in meta["shape"]) * max(1, bits // 8)
    except (OSError, ValueError, KeyError, TypeError):
        return None


def cli_capture_bytes(argv) -> int | None:
    """The size of the capture a command line names: a Zarr store's frames (`zarr_frames_bytes`)
    where it names one, else its largest file's (`cli_input_bytes`); None where it names
    neither. A store's depth file may be larger than a small store's frames, and exists only
    after the run: the store decides."""
    stores = [zarr_frames_bytes(arg) for arg in argv[1:] if not arg.startswith("-") and os.path.isdir(arg)]
    return max((size for size in stores if size is not None), default=None) or cli_input_bytes(argv)


# The allocator a `cohflash` command runs on where the system has it (`preload_allocator_for_cli`),
# as the dynamic loader names it, in the folders Linux distributions install it to
ALLOCATOR_LIBRARIES = ("libmimalloc.so.2", "libmimalloc.so.3", "libmimalloc.so")
ALLOCATOR_FOLDERS = (
    "/usr/lib/{machine}-linux-gnu",
    "/lib/{machine}-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
)
# Set to "system" to keep the C library's allocator
ALLOCATOR_ENV = "COHFLASH_ALLOCATOR"
# The commands that run on it: measured faster there (a first run's compile); `simulate` and
# `stream` ran slower (mimalloc hands their large buffers back to the system between chunks,
# and they are faulted in again)
ALLOCATOR_COMMANDS = ("reconstruct",)


def allocator_library() -> str | None:
    """The path of mimalloc's shared library where it is installed (Debian and Ubuntu:
    `libmimalloc2.0`), else None. Looked for by name in the usual library folders: asking the
    loader's cache (`ctypes.util.find_library`) starts subprocesses, slower than the lookups."""
    machine = os.uname().machine if hasattr(os, "uname") else ""
    for folder in ALLOCATOR_FOLDERS:
        for name in ALLOCATOR_LIBRARIES:
            path = os.path.join(folder.format(machine=machine), name)
            if os.path.isfile(path):
                return path
    return None


def preload_allocator_for_cli(argv) -> bool:
    """Where this interpreter runs a command of `ALLOCATOR_COMMANDS` on Linux and mimalloc is
    installed (`allocator_library`), run the command again, at once, in this process
    (`os.execve`) with mimalloc preloaded (`LD_PRELOAD`) in place of the C library's allocator,
    unless it is preloaded already or `COHFLASH_ALLOCATOR=system` asks for the C library's.

    XLA builds and frees many small objects as it compiles a program and as it loads a compiled
    one, where glibc's `malloc` and `free` were a large share of the time; on mimalloc a first
    full-capture run is shorter, a warm one the same, the depth files identical (measured:
    docs/performance.md). Only a preload replaces the allocator of the libraries already
    loaded (Python's own among them), hence the new start: the package calls this first,
    before any import or thread of its own. A library user's process, a test run or
    a Dask worker (not a command), and a script that imitates a command (`started_as`), keep
    their allocator. Returns False where nothing is done (or the new start failed); a new start
    does not return."""
    if cli_command(argv) not in ALLOCATOR_COMMANDS or not sys.platform.startswith("linux") or not started_as(argv):
        return False
    env = allocator_environment()
    if env is None:
        return False
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        # the interpreter named by its path: started as a bare `python`, the new start would
        # look for itself on PATH, which may lead to another installation
        os.execve(sys.executable, [sys.executable, *argv[1:]], env)
    except OSError:  # e.g. the interpreter cannot be run again: the command runs on as it is
        return False
    return True  # not reached


def allocator_environment(environ=None) -> dict | None:
    """`environ` (default: this process's) with mimalloc added to LD_PRELOAD, as a `cohflash`
    command's process runs (`preload_allocator_for_cli`); None where it runs as `environ` says
    already: mimalloc is not installed, is preloaded already, or `COHFLASH_ALLOCATOR=system`."""
    environ = os.environ if environ is None else environ
    if not mimalloc_asked(environ):
        return None
    library = allocator_library()
    preloaded = environ.get("LD_PRELOAD", "")
    if library is None or os.path.basename(library) in preloaded:
        return None
    return dict(environ, LD_PRELOAD=f"{library}:{preloaded}" if preloaded else library)


def mimalloc_asked(environ) -> bool:
    """Whether `environ` leaves `cohflash` commands to mimalloc: the default, unless
    `COHFLASH_ALLOCATOR` names another allocator (e.g. "system")."""
    return environ.get(ALLOCATOR_ENV, "mimalloc").lower() == "mimalloc"


def allocator_description() -> str:
    """The allocator `cohflash` commands run on here, as benchmarks print it."""
    if not mimalloc_asked(os.environ):
        return f"allocator: the C library's ({ALLOCATOR_ENV}={os.environ[ALLOCATOR_ENV]})"
    library = allocator_library()
    if library is None or not sys.platform.startswith("linux"):
        return "allocator: the C library's (mimalloc is not installed)"
    return f"allocator: mimalloc ({library}), preloaded into `cohflash {'`, `'.join(ALLOCATOR_COMMANDS)}`"


# The packages a `cohflash` process imports from this checkout (an editable install)
PACKAGE_NAMES = ("cohflash_jax", "cohflash_calibration", "cohflash_experiments")


def compile_package_bytecode() -> str:
    """Compile the installed packages' modules to bytecode where theirs is missing or stale,
    as a regular (non-editable) `pip install` does, and say so, as benchmarks print it.

    An editable install runs the checkout's sources: Python writes their bytecode at the first
    import, unless told not to (`PYTHONDONTWRITEBYTECODE`, set on some CI machines and VMs);
    then every process compiles the package's ~70 modules again (~0.07 s of a warm full-capture
    run, docs/performance.md). `make` runs this when it installs; a benchmark runs it first, so
    that it times the package as installed."""
    import compileall
    import importlib.util

    folders = []
    for name in PACKAGE_NAMES:
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations:
            folders.extend(spec.submodule_search_locations)
    compiled = [compileall.compile_dir(folder, quiet=1) for folder in folders]  # every folder, even after a failure
    writes = "not written by Python here (PYTHONDONTWRITEBYTECODE)" if sys.dont_write_bytecode else "written by Python"
    state = "compiled ahead" if all(compiled) else "compiled ahead in part (a module could not be compiled or written)"
    return f"package bytecode: {state}; at imports {writes}"


def started_as(argv) -> bool:
    """Whether this interpreter was started with the command line `argv` (Linux: its
    /proc/self/cmdline). A script that sets `sys.orig_argv` to look like a command (a test, a
    benchmark) then runs as itself, not started again as the command it imitates."""
    try:
        with open("/proc/self/cmdline", "rb") as f:
            started = [os.fsdecode(a) for a in f.read().split(b"\0")[:-1]]
    except OSError:
        return False
    return started == list(argv)


def gpu_memory_on_demand_for_cli(argv) -> bool:
    """Where this interpreter runs a `cohflash` command (`cli_command`), let a GPU's memory be
    taken as the programs ask for it instead of JAX's default of three quarters of the card
    reserved as its backend starts (`XLA_PYTHON_CLIENT_PREALLOCATE=false`, unless the user set
    it). A command's programs need a few GB; on an H200, reserving ~105 GB made each warm
    full-capture `cohflash reconstruct` 1.4 s slower, its reconstruction 2.4 s against 1.0 s
    (docs/performance.md). A library user's process or a test run keeps JAX's setting (local
    Dask workers a command starts inherit the command's). Called on import, before JAX's
    backends start; returns whether the command's process takes memory on demand."""
    if cli_command(argv) is None:
        return False
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    return os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"].lower() in ("false", "0")


# A `cohflash reconstruct` of a capture (a file, or a Zarr store's frames) smaller than this runs
# on the CPU even where JAX has a GPU (`small_captures_on_cpu_for_cli`): 128×128 pixels of 3000
# frames (376 MB) and less
GPU_MIN_CAPTURE_BYTES = 512 * 2**20
# The commands that do: `stream` keeps the GPU, whose maps are faster once its process is warm
CPU_FOR_SMALL_CAPTURES_COMMANDS = ("reconstruct",)


def small_captures_on_cpu_for_cli(argv) -> bool:
    """Where this interpreter runs `cohflash reconstruct` on a capture (a file or a Zarr store,
    `cli_capture_bytes`) smaller than `GPU_MIN_CAPTURE_BYTES`, run it on the CPU alone
    (`JAX_PLATFORMS=cpu`, unless the user set `JAX_PLATFORMS`). A one-off process spends more
    starting a GPU's backend and moving the frames to it than the CPU spends on a region of
    interest's whole reconstruction: on an H200's 16-core host, whole warm processes from
    16×16 to 128×128 pixels of 3000 frames took 1.9–2.3 s on the CPU against 2.5–2.8 s on the
    GPU, cold 4.4–6.5 s against 6.4–7.7 s (docs/performance.md). The depth file records the device
    (`provenance`); CPU and GPU results agree to ~1e-6 mm. Called on import, before JAX's
    backends start; returns whether the command runs on the CPU alone."""
    if cli_command(argv) not in CPU_FOR_SMALL_CAPTURES_COMMANDS or "JAX_PLATFORMS" in os.environ:
        return False
    size = cli_capture_bytes(argv)
    if size is None or size >= GPU_MIN_CAPTURE_BYTES:
        return False
    os.environ["JAX_PLATFORMS"] = "cpu"
    return True


def single_threaded_blas_for_cli(argv) -> bool:
    """Where this interpreter runs a `cohflash` command, NumPy's BLAS on one thread
    (`OPENBLAS_NUM_THREADS=1`, unless the user set it). A command's NumPy products are small
    (the carrier survey's Gram matrix and its eigenvectors, a calibration's covariance) and run
    beside XLA's own threads: OpenBLAS's pool then spun on cores the compiled programs were
    using (docs/performance.md). Called on import, before NumPy loads OpenBLAS, which reads it
    then; returns whether the command's BLAS runs on one thread."""
    if cli_command(argv) is None:
        return False
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    return os.environ["OPENBLAS_NUM_THREADS"] == "1"


def pause_garbage_collection_for_cli(argv) -> bool:
    """Where this interpreter runs a `cohflash` command, no garbage collection while the
    package and its dependencies are imported (`resume_garbage_collection`). Importing JAX
    and equinox makes ~2·10⁵ objects the collector tracks, all of them alive for the whole
    process, and its passes over them as they are made were part of every command's start
    (docs/performance.md). Returns whether collection was paused."""
    global _PAUSED
    if cli_command(argv) is None or not gc.isenabled():
        return False
    gc.disable()
    _PAUSED = True
    return True


def resume_garbage_collection() -> bool:
    """Collection on again after the imports (where `pause_garbage_collection_for_cli` paused
    it), the objects made so far frozen: they live as long as the process, so later full
    passes need not walk them. Returns whether it resumed."""
    global _PAUSED
    if not _PAUSED:
        return False
    gc.freeze()
    gc.enable()
    _PAUSED = False
    return True


# the installed folder of a ROCm PJRT plugin's distribution, e.g. `jax_rocm7_plugin-0.8.0.dist-info`
# (installers write the project's name with "-" and "." as "_"; any case matches)
ROCM_PLUGIN_FOLDER = re.compile(r"jax_rocm\w*_plugin-[^/]*\.(dist|egg)-info", re.IGNORECASE)


def rocm_plugin_distributions(paths) -> list:
    """The distributions installed in the folders `paths` (as `sys.path`) whose folder names
    are a ROCm PJRT plugin's (`ROCM_PLUGIN_FOLDER`), as `importlib.metadata` gives them."""
    import importlib.metadata
    import pathlib

    found = []
    for entry in paths:
        try:
            names = sorted(os.listdir(entry or "."))
        except (OSError, TypeError):  # a zip file, a missing folder, a non-path entry
            continue
        found += [
            importlib.metadata.PathDistribution(pathlib.Path(entry or ".", name))
            for name in names
            if ROCM_PLUGIN_FOLDER.fullmatch(name)
        ]
    return found


@contextlib.contextmanager
def rocm_plugin_scan_by_folder_names_for_cli(argv):
    """Where this interpreter runs a `cohflash` command and JAX is not yet imported: while it
    is (the `with` block), `importlib.metadata.distributions()` lists only the ROCm plugins'
    distributions (`rocm_plugin_distributions`). JAX's import looks for a ROCm plugin by
    reading the metadata of every installed distribution (github.com/jax-ml/jax/issues/37879):
    ~20 ms of each start among 60 distributions, 250 ms in a large environment; the plugins'
    folder names find the same ones. Nothing else runs in the process meanwhile (no thread is
    started before JAX is imported); the function is restored on leaving."""
    if cli_command(argv) is None or "jax" in sys.modules:
        yield
        return
    import importlib.metadata

    every = importlib.metadata.distributions
    importlib.metadata.distributions = lambda **kwargs: iter(
        rocm_plugin_distributions(kwargs.get("path", sys.path)) if not kwargs.keys() - {"path"} else every(**kwargs)
    )
    try:
        yield
    finally:
        importlib.metadata.distributions = every
