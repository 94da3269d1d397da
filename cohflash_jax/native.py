"""The package's native kernels, in C (`native_kernels.c`), loaded with ctypes: a sub-tile's
I/Q half (data checks, carrier axis, rotated sequence) in one pass over its frames, read in
place (`iq_half`), and a tile's chunks read from the file in one call (`read_chunks`).

XLA's CPU code for the same arithmetic (`reconstruct.programs.axis_and_checks` and
`rotated_from_frames`) materialises I and Q and sums them in separate passes: ~60 MB of
memory traffic for 7.7 MB of frames, most of a full capture's I/Q time (docs/performance.md).
The kernel reads the frames twice. It is built with the package where a C compiler is found
(`setup.py`, optional); without it, or with `COHFLASH_NATIVE=0`, the XLA programs run, and
the two agree to float32 rounding (tests/test_native.py).

Its moments are summed in float32 over 64 frames and in float64 across them (XLA's in float32),
and centred, so the results differ from the XLA programs' in the last bits of float32."""

from __future__ import annotations

import ctypes
import functools
import importlib.machinery
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .tiling import aligned_empty

LIBRARY_STEM = "native_kernels"  # setup.py's extension: cohflash_jax/native_kernels<suffix>
# the kernels' calling convention this module calls them with (`cohflash_kernel_abi` in the C
# source): a library built from an older source is not loaded
KERNEL_ABI = 2


class IQHalf(NamedTuple):
    """A sub-tile's I/Q half: the rotated sequence r (N, P) float32, cos φ and sin φ (P,)
    float32, the orthogonal and total variances (P,) float64, the dead and saturated flags (P,)."""

    r: np.ndarray
    cos_phase: np.ndarray
    sin_phase: np.ndarray
    noise_var: np.ndarray
    total_var: np.ndarray
    dead: np.ndarray
    saturated: np.ndarray


KERNEL_ERRORS = {1: "out of memory", 2: "empty frames, or rows that overlap"}


def library_path() -> Path | None:
    """The built kernel library beside this module, or None where it was not built."""
    here = Path(__file__).parent
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = here / (LIBRARY_STEM + suffix)
        if path.exists():
            return path
    return None


def turned_off() -> bool:
    """Whether the environment turns the kernels off (`COHFLASH_NATIVE=0`)."""
    return os.environ.get("COHFLASH_NATIVE", "1") == "0"


@functools.cache
def library():
    """The loaded library (ctypes), or None where it is not built or `COHFLASH_NATIVE=0`."""
    if turned_off():
        return None
    path = library_path()
    if path is None:
        return None
    try:
        lib = ctypes.CDLL(str(path), use_errno=True)
    except OSError:
        return None
    if not hasattr(lib, "cohflash_kernel_abi") or lib.cohflash_kernel_abi() != KERNEL_ABI:
        return None  # built from another version of the source: `make` (pip install -e .) rebuilds it
    pointer = ctypes.c_void_p
    if hasattr(lib, "cohflash_read_chunks"):
        lib.cohflash_read_chunks.restype = ctypes.c_int64
        lib.cohflash_read_chunks.argtypes = [ctypes.c_int, ctypes.c_int64] + [pointer] * 5
    for name in ("cohflash_iq_half_u16", "cohflash_iq_half_u16_avx2"):
        if hasattr(lib, name):
            kernel = getattr(lib, name)
            kernel.restype = ctypes.c_int
            kernel.argtypes = [pointer] + [ctypes.c_int64] * 4 + [pointer, ctypes.c_int64, pointer]
            kernel.argtypes += [ctypes.c_double] + [pointer] * 7
    return lib


def available() -> bool:
    """Whether the kernel can run here."""
    return library() is not None


@functools.cache
def kernel():
    """The kernel for this CPU: the AVX2 build where the CPU has AVX2 and FMA and XLA is not
    held below AVX2 (`--xla_cpu_max_isa`, so that both run on the same ISA), else the baseline."""
    from .runtime import cpu_model_and_flags

    lib = library()
    flags = cpu_model_and_flags()[1]
    avx2 = lib.cohflash_has_x86_kernels() and {"avx2", "fma"} <= set(flags)
    for flag in os.environ.get("XLA_FLAGS", "").split():
        if flag.startswith("--xla_cpu_max_isa="):
            avx2 = avx2 and flag.split("=", 1)[1].upper().startswith(("AVX2", "AVX512", "AMX"))
    return lib.cohflash_iq_half_u16_avx2 if avx2 else lib.cohflash_iq_half_u16


def reads_chunks() -> bool:
    """Whether `read_chunks` can run here (the library is built, on a system with `preadv`)."""
    return library() is not None and hasattr(library(), "cohflash_read_chunks")


def read_chunks(fd: int, offsets: np.ndarray, wants: np.ndarray, iovec_addresses: np.ndarray, iovec_counts: np.ndarray):
    """Chunks read straight into place, chunk i by one `preadv` of `iovec_counts[i]` buffers
    described by the `struct iovec`s at `iovec_addresses[i]`, at file offset `offsets[i]`, all
    in one call with the interpreter lock released. Returns None where every chunk gave its
    `wants[i]` bytes, else (the index of the first that did not, what `preadv` returned, errno)."""
    offsets, wants = np.ascontiguousarray(offsets, np.int64), np.ascontiguousarray(wants, np.int64)
    addresses = np.ascontiguousarray(iovec_addresses, np.uint64)
    counts = np.ascontiguousarray(iovec_counts, np.int32)
    if not offsets.size == wants.size == addresses.size == counts.size:
        raise ValueError(
            f"one offset, length, scatter table and count a chunk: {offsets.size}, {wants.size}, "
            f"{addresses.size}, {counts.size}"
        )
    got = ctypes.c_int64(0)
    first_short = library().cohflash_read_chunks(
        fd,
        offsets.size,
        offsets.ctypes.data,
        wants.ctypes.data,
        addresses.ctypes.data,
        counts.ctypes.data,
        ctypes.byref(got),
    )
    return None if first_short < 0 else (int(first_short), got.value, ctypes.get_errno())


def description() -> str:
    """The kernel in words, for benchmarks and depth files: built or not, and for which ISA."""
    if library() is None:
        if turned_off():
            why = "off (COHFLASH_NATIVE=0)"
        elif library_path() is None:
            why = "not built"
        else:
            why = "built from another version of native_kernels.c (`make` rebuilds it)"
        return f"native I/Q kernel {why}: XLA's I/Q programs run"
    isa = "AVX2" if kernel() is library().cohflash_iq_half_u16_avx2 else "baseline ISA"
    return f"native I/Q kernel ({isa})"


def readable_in_place(frames: np.ndarray) -> bool:
    """Whether the kernel reads `frames` (4, N, P) where they are: each frame row's pixels
    contiguous, rows and CCD planes at positive strides, no two rows overlapping."""
    plane, row, pixel = frames.strides
    size = frames.itemsize
    _, n, p = frames.shape
    return pixel == size and row % size == 0 and plane % size == 0 and row >= p * size and plane >= n * row


def iq_half(
    frames: np.ndarray, weights: np.ndarray, bias: np.ndarray, saturation_dn, out: np.ndarray | None = None
) -> IQHalf:
    """A sub-tile's I/Q half from its frames (4, N, P) uint16, read in place: C-contiguous, or
    a view whose pixels are contiguous (a sub-tile's columns of a wider tile). `weights`
    (2, 4), or (2, 4, P) per pixel, and `bias` (2, P) float32 make I and Q = W·x + b;
    `saturation_dn` (None: none) flags a pixel any of whose values reaches it; `out`: an
    aligned (N, P) float32 buffer for r (default: a new one). Runs with the interpreter lock
    released (ctypes)."""
    if frames.ndim == 3 and 0 in frames.shape[1:]:
        raise ValueError(f"frames are empty: {frames.shape}")
    if frames.dtype != np.uint16 or frames.ndim != 3 or frames.shape[0] != 4 or not readable_in_place(frames):
        raise ValueError(
            f"frames must be uint16 (4, N, P) with contiguous pixels, not {frames.dtype} {frames.shape} "
            f"strides {frames.strides}"
        )
    _, n, p = frames.shape
    plane_stride, row_stride = (stride // frames.itemsize for stride in frames.strides[:2])
    weights = np.ascontiguousarray(weights, np.float32)
    bias = np.ascontiguousarray(np.broadcast_to(bias, (2, p)), np.float32)
    if weights.shape not in ((2, 4), (2, 4, p)):
        raise ValueError(f"weights must be (2, 4) or (2, 4, {p}), not {weights.shape}")
    if out is not None and (out.shape != (n, p) or out.dtype != np.float32 or not out.flags.c_contiguous):
        raise ValueError(f"out must be a C-contiguous float32 ({n}, {p}) array, not {out.dtype} {out.shape}")
    out = IQHalf(
        aligned_empty((n, p), np.float32) if out is None else out,
        aligned_empty((p,), np.float32),
        aligned_empty((p,), np.float32),
        aligned_empty((p,), np.float64),
        aligned_empty((p,), np.float64),
        np.empty(p, np.uint8),
        np.empty(p, np.uint8),
    )
    status = kernel()(
        frames.ctypes.data,
        n,
        p,
        row_stride,
        plane_stride,
        weights.ctypes.data,
        int(weights.ndim == 3),
        bias.ctypes.data,
        -1.0 if saturation_dn is None else float(saturation_dn),
        *(a.ctypes.data for a in out),
    )
    if status != 0:
        raise RuntimeError(f"the native I/Q kernel failed: {KERNEL_ERRORS.get(status, status)}")
    return out
