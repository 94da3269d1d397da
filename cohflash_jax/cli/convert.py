"""`cohflash convert`: a capture from HDF5 to Zarr or back, streaming."""

from __future__ import annotations

from .common import HelpFormatter, add_quiet, number_in


def add_parser(sub) -> None:
    c = sub.add_parser(
        "convert",
        help="copy a capture between HDF5 (.h5) and Zarr (.zarr), either way, streaming band by band",
        formatter_class=HelpFormatter,
    )
    c.add_argument("capture", help="capture to read (.h5 file or .zarr store)")
    c.add_argument("--out", required=True, help="capture to write: NAME.zarr for Zarr, else HDF5")
    c.add_argument(
        "--rows-per-chunk",
        type=number_in(1, 10**6, "rows per chunk", False, True),
        default=32,
        help="Zarr: rows of a chunk (each chunk holds every frame of rows × 64 pixels); also the band streamed",
    )
    add_quiet(c)
    c.set_defaults(func=run)


def run(args) -> int:
    from ..capture import Capture
    from ..capture_zarr import convert_capture

    out = convert_capture(args.capture, args.out, progress=not args.quiet, rows_per_chunk=args.rows_per_chunk)
    with Capture(args.capture) as cap:
        n, h, w = cap.shape
        kind = "hdf5" if cap.store == "zarr" else "zarr"
        print(f"wrote {out}: {kind} capture, 4 × {n} frames of {h}×{w} pixels ({cap.frames.dtype})")
    return 0
