"""Posteriors of a set of pixels of a capture (`run_pixels`), the posterior file
(`write_posteriors`, `cohflash-posterior` v1, docs/formats.md) and the per-pixel figure."""

from __future__ import annotations

import warnings

import emcee
import jax
import jax.numpy as jnp
import numpy as np

from .calibration_file import PixelMaps
from .instrument import Instrument
from .reconstruct import ReconstructOptions, build_plan
from .status import UNUSABLE_DATA, Status
from .uncertainty import LABELS, PARAMETERS, Posterior, check_max_steps, pixel_data, sample_pixel, sample_pixels_of

POSTERIOR_FIELDS = (
    "row",
    "col",
    "ml_depth_m",
    "mean_m",
    "median_m",
    "lo68_m",
    "hi68_m",
    "lo95_m",
    "hi95_m",
    "crlb_m",
    "multimodal",
    "converged",
    "autocorr_steps",
    "acceptance",
    "steps",
)


def run_pixels(
    capture,
    pixels,
    options: ReconstructOptions,
    *,
    instrument: Instrument | None = None,
    maps: PixelMaps | None = None,
    seed: int = 0,
    max_steps: int = 20000,
    chains_path=None,
    progress: bool = True,
):
    """Posteriors of (row, col) pixels of an open capture for `instrument` (default: the
    capture's own; a calibrated one from `Calibration.apply`, with its `maps`, gives the
    posteriors `reconstruct --calibration` would give ML depths for) → (results, skipped): a
    list of (row, col, Posterior) and one of (row, col, reason) for pixels whose data are
    unusable (NaN/inf, saturated or dead: `status.UNUSABLE_DATA`), which are not sampled.
    Raises ValueError when no pixel is usable or a pixel is named twice.

    Frames of each pixel are read on their own (4 × N values), so any set of pixels costs
    what it reads. `chains_path` keeps every chain in emcee's HDF5 backend, one group per pixel."""
    from .progress import progress_bar

    check_max_steps(max_steps)
    n, h, w = capture.shape
    for r, c in pixels:
        if not (0 <= r < h and 0 <= c < w):
            raise ValueError(f"pixel ({r}, {c}) is outside the {h}×{w} capture")
    repeated = sorted({p for p in pixels if pixels.count(p) > 1})
    if repeated:
        raise ValueError("pixel(s) named more than once: " + ", ".join(f"({r}, {c})" for r, c in repeated))
    instrument = capture.instrument() if instrument is None else instrument
    maps = PixelMaps(capture.dark) if maps is None else maps
    maps.check_shape(h, w, "per-pixel maps")
    plan = build_plan(maps.apply(instrument), options, capture.saturation_dn)
    if not plan.geometry.uniform:
        raise ValueError("posteriors are implemented for uniform sweeps (the DFT-window likelihood)")
    rows, cols = np.asarray([r for r, _ in pixels]), np.asarray([c for _, c in pixels])
    frames = np.stack([capture.frames[:, :, r, c] for r, c in pixels], axis=-1)  # (4, N, P)
    per_pixel = lambda a: None if a is None else jnp.asarray(np.asarray(a, np.float32)[:, rows, cols])
    data = pixel_data(plan, jnp.asarray(frames), options.window_bins, per_pixel(maps.offset_dn), per_pixel(maps.gain))
    status = np.asarray(data.status)
    unusable = np.isin(status, UNUSABLE_DATA)
    skipped = [(*pixels[p], Status(int(status[p])).message) for p in np.flatnonzero(unusable)]
    usable = np.flatnonzero(~unusable)
    if not usable.size:
        raise ValueError(
            "no pixel with usable data: "
            + ", ".join(f"({r}, {c}) {why}" for r, c, why in skipped[:10])
            + (" …" if len(skipped) > 10 else "")
        )
    rng = np.random.default_rng(seed)
    g = plan.geometry
    geometry = dict(ambiguity_m=g.ambiguity_m, bin_depth_m=g.bin_depth_m, ripple_m=g.ripple_m)
    bar = progress_bar(total=usable.size, unit="px", desc="posterior", disable=not progress)
    with bar, warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # emcee's autocorrelation on short chains
        if chains_path is None:  # every pixel at once, the same posteriors (`sample_pixels_of`)
            usable_data = jax.tree.map(lambda x: x[usable], data)
            posts = sample_pixels_of(plan.model, usable_data, **geometry, rng=rng, max_steps=max_steps, done=bar.update)
        else:  # emcee's own sampler, pixel by pixel, each chain in emcee's HDF5 backend
            posts = []
            for p in usable:
                r, c = pixels[p]
                backend = emcee.backends.HDFBackend(str(chains_path), name=f"pixel_{r}_{c}")
                d = jax.tree.map(lambda x, p=p: x[p], data)
                posts.append(sample_pixel(plan.model, d, **geometry, rng=rng, max_steps=max_steps, backend=backend))
                bar.update(1)
    results = [(*pixels[p], post) for p, post in zip(usable, posts)]
    return results, skipped


def write_posteriors(path, results, meta: dict):
    """posterior.h5: one row per pixel (POSTERIOR_FIELDS) plus every pixel's thinned samples."""
    import json

    import h5py

    from .fileio import atomic_path

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = "cohflash-posterior"
        f.attrs["format_version"] = 1
        f.attrs["parameters"] = json.dumps(PARAMETERS)
        for k, v in meta.items():
            f.attrs[k] = v
        rows = {k: [] for k in POSTERIOR_FIELDS}
        for r, c, post in results:
            values = dict(
                row=r,
                col=c,
                ml_depth_m=post.ml_depth_m,
                mean_m=post.mean_m,
                median_m=post.median_m,
                lo68_m=post.interval68_m[0],
                hi68_m=post.interval68_m[1],
                lo95_m=post.interval95_m[0],
                hi95_m=post.interval95_m[1],
                crlb_m=post.crlb_m,
                multimodal=post.multimodal,
                converged=post.converged,
                autocorr_steps=post.autocorr_steps,
                acceptance=post.acceptance,
                steps=post.steps,
            )
            for k in POSTERIOR_FIELDS:
                rows[k].append(values[k])
            g = f.create_dataset(f"samples/pixel_{r}_{c}", data=post.samples.astype(np.float32))
            g.attrs["note"] = post.note
        for k, v in rows.items():
            f.create_dataset(k, data=np.asarray(v))


def plot_posterior(path, post: Posterior, title: str = ""):
    """Marginal of depth with the CRLB Gaussian over it, beside a corner plot of the parameters."""
    import corner

    from .fileio import headless_pyplot, save_figure

    plt = headless_pyplot()

    fig = plt.figure(figsize=(13, 5.5), dpi=100)
    ax = fig.add_axes([0.06, 0.12, 0.36, 0.78])
    depth_mm = 1e3 * (post.ml_depth_m + 1e-3 * post.samples[:, 0] - post.ml_depth_m)
    ax.hist(depth_mm, bins=80, density=True, color="0.6", label="posterior (emcee)")
    if np.isfinite(post.crlb_m) and post.crlb_m > 0:
        s = 1e3 * post.crlb_m
        x = np.linspace(depth_mm.min(), depth_mm.max(), 400)
        ax.plot(x, np.exp(-0.5 * (x / s) ** 2) / (s * np.sqrt(2 * np.pi)), "r-", label=f"CRLB Gaussian σ={s:.3f} mm")
    for (lo, hi), ls in ((post.interval68_m, "--"), (post.interval95_m, ":")):
        for v in (lo, hi):
            ax.axvline(1e3 * (v - post.ml_depth_m), color="k", ls=ls, lw=1)
    ax.set_xlabel("depth − ML estimate (mm)")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)
    ax.set_title(
        title
        or f"68 % (--) and 95 % (:) intervals; {'multimodal' if post.multimodal else 'unimodal'}"
        + ("" if post.converged else ", NOT converged"),
        fontsize=9,
    )
    sub = plt.figure(figsize=(6, 6))
    corner.corner(post.samples, labels=list(LABELS), fig=sub, quantiles=(0.16, 0.5, 0.84), show_titles=False)
    sub.canvas.draw()
    img = np.asarray(sub.canvas.buffer_rgba())
    plt.close(sub)
    ax2 = fig.add_axes([0.48, 0.02, 0.5, 0.96])
    ax2.imshow(img)
    ax2.axis("off")
    return save_figure(fig, path)
