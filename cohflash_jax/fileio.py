"""File helpers: atomic writing (temporary file beside the target, then rename) of one file or
of a command's whole set of outputs, JSON reading with clear errors, figures."""

from __future__ import annotations

import contextlib
import contextvars
import glob
import os
import shutil
from pathlib import Path


def is_store_folder(path) -> bool:
    """Whether `path` names a folder-shaped output (a Zarr store, `NAME.zarr`), which is
    written and replaced whole like a file."""
    return Path(path).suffix == ".zarr"


def require_output_folders(*paths) -> None:
    """Before any work: each output path (None skipped) is a file name (or a Zarr store's
    name) in an existing folder this process may write in (FileNotFoundError or
    PermissionError naming it otherwise)."""
    for path in paths:
        if path is None:
            continue
        path = Path(path)
        if not path.parent.is_dir():
            raise FileNotFoundError(f"output folder does not exist: {path.parent}")
        if path.is_dir() and not is_store_folder(path):
            raise IsADirectoryError(f"output {path} is a folder: give a file name in it")
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise PermissionError(f"output folder {path.parent} is not writable (for {path.name})")


class OutputSet:
    """The outputs of one command, written as a set: inside `with OutputSet():` every
    `atomic_path` writes its temporary file and the renames onto the targets wait for the
    block to end without an exception. An error or Ctrl-C anywhere leaves every previous
    output as it was (a new depth.h5 beside an old PNG is a mixed set); Ctrl-C during the
    renames themselves is held until they finish."""

    def __init__(self):
        self._pending: dict[Path, Path] = {}  # target → its temporary (a target written twice: once)
        self._token = None

    def add(self, tmp: Path, path: Path) -> None:
        self._pending[path] = tmp

    def __enter__(self) -> OutputSet:
        self._token = _ACTIVE_SET.set(self)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        _ACTIVE_SET.reset(self._token)
        if exc_type is None:
            with _interrupts_held():
                for path, tmp in self._pending.items():
                    replace_path(tmp, path)
        for tmp in self._pending.values():
            remove_path(tmp)


_ACTIVE_SET: contextvars.ContextVar[OutputSet | None] = contextvars.ContextVar("output_set", default=None)


@contextlib.contextmanager
def _interrupts_held():
    """SIGINT held (and then dropped: the work it would stop is done) while files are renamed."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def remove_path(path: Path) -> None:
    """Remove a file or a whole folder (a Zarr store); nothing where it does not exist."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def replace_path(tmp: Path, path: Path) -> None:
    """Rename `tmp` onto `path`. A folder (a Zarr store) cannot be renamed onto a non-empty
    one: the old one is moved aside first and removed after, so `path` is never half old."""
    if tmp.is_dir() and path.is_dir():
        aside = path.with_name(f".{path.name}.old-{os.getpid()}")
        remove_path(aside)
        os.replace(path, aside)
        os.replace(tmp, path)
        remove_path(aside)
    else:
        os.replace(tmp, path)


def temporary_name(path: Path) -> Path:
    """The temporary file beside `path` this process writes before renaming: .NAME.tmp-PID."""
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def remove_stale_temporaries(path) -> list[Path]:
    """Remove the temporaries beside `path` left by processes that no longer run (a killed
    run's .NAME.tmp-PID can hold gigabytes) → the files removed."""
    path = Path(path)
    removed = []
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.tmp-*"):
        pid = tmp.name.rsplit("-", 1)[-1]
        if not pid.isdigit() or int(pid) == os.getpid() or _alive(int(pid)):
            continue
        with contextlib.suppress(OSError):
            remove_path(tmp)
            removed.append(tmp)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path in the target's folder; rename it onto `path` on success (at the
    end of the enclosing `OutputSet`, where there is one).

    On any exception the temporary file is removed and an existing `path` is untouched,
    so an interrupted run never leaves a half-written file. The temporary may be made a
    folder (a Zarr store): it then replaces `path` whole."""
    path = Path(path)
    require_output_folders(path)
    remove_stale_temporaries(path)
    tmp = temporary_name(path)
    outputs = _ACTIVE_SET.get()
    handed_on = False
    try:
        yield tmp
        if outputs is None:
            replace_path(tmp, path)
        else:
            outputs.add(tmp, path)
            handed_on = True
    finally:
        if not handed_on:
            remove_path(tmp)


def json_value(value):
    """An HDF5 attribute's value (NumPy scalar or array, bytes) as a JSON value: Zarr
    attributes are JSON."""
    if isinstance(value, bytes):
        return value.decode()
    return value.tolist() if hasattr(value, "tolist") else value


def read_json(path, what: str, error=ValueError) -> dict:
    """Parse a JSON file, raising FileNotFoundError or `error` with the path in the message."""
    import json

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {path}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc})") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a {what} JSON file (binary content; an HDF5 file given in its place?)") from None


def headless_pyplot():
    """matplotlib's pyplot on the Agg backend (files, no display), imported when first needed:
    matplotlib costs ~0.3 s to import, which a run that draws nothing should not pay."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path) -> Path:
    """Save a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def write_csv(path, rows: list[dict]) -> Path:
    """A table (list of same-keyed dicts) as CSV, atomically."""
    import csv

    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


def read_gray_image(path):
    """An image file as a 2-D array of its own dtype (colour and alpha dropped to grey), or
    None where OpenCV cannot decode it."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is not None and img.ndim == 3:
        if img.shape[2] == 1:
            return img[..., 0]
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return img
