"""File helpers: atomic writing (temporary file beside the target, then rename), JSON reading
with clear errors, figures."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path


def require_output_folders(*paths) -> None:
    """FileNotFoundError naming the first output path (None skipped) whose folder does not exist."""
    for path in paths:
        if path is not None and not Path(path).parent.exists():
            raise FileNotFoundError(f"output folder does not exist: {Path(path).parent}")


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path in the target's folder; rename it onto `path` on success.

    On any exception the temporary file is removed and an existing `path` is untouched,
    so an interrupted run never leaves a half-written file."""
    path = Path(path)
    require_output_folders(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


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
