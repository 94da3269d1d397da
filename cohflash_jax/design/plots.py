"""Figures of a design sweep: a heat map with precision contours over two axes, or precision
against one axis (frames and acquisition time for num_steps), CRLB and Monte Carlo together."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def sweep_heat_map(rows: list[dict], names: list[str]):
    """The CRLB (mm) over the first two swept axes → (xs, ys, grid (len(ys), len(xs)), at):
    beyond two axes, the slice at the smallest value of each further axis, `at` {name: value}."""
    at = {n: min(float(r[n]) for r in rows) for n in names[2:]}
    rows = [r for r in rows if all(float(r[n]) == v for n, v in at.items())]
    xs = np.unique([float(r[names[0]]) for r in rows])
    ys = np.unique([float(r[names[1]]) for r in rows])
    grid = np.full((ys.size, xs.size), np.nan)
    for r in rows:
        grid[np.searchsorted(ys, float(r[names[1]])), np.searchsorted(xs, float(r[names[0]]))] = float(r["crlb_mm"])
    return xs, ys, grid, at


def beyond_ambiguity(rows: list[dict]) -> np.ndarray:
    """Points whose target lies beyond the unambiguous range (the instrument reads it folded)."""
    return np.array([float(r["distance_m"]) >= float(r["ambiguity_m"]) for r in rows], bool)


def plot_sweep(rows: list[dict], names: list[str], path) -> Path:
    """Heat map with precision contours (two axes) or precision against the swept parameter
    (one axis; against frames and acquisition time when it is num_steps), CRLB and Monte Carlo
    on the same axes."""
    from matplotlib.colors import LogNorm

    from ..fileio import headless_pyplot, save_figure

    plt = headless_pyplot()

    crlb = np.array([float(r["crlb_mm"]) for r in rows])
    if len(names) >= 2:
        xs, ys, grid, at = sweep_heat_map(rows, names)
        fig, ax = plt.subplots(figsize=(7, 5.5), constrained_layout=True)
        mesh = ax.pcolormesh(xs, ys, grid, shading="nearest", norm=LogNorm(), cmap="viridis")
        fig.colorbar(mesh, ax=ax, label="CRLB of depth (mm)")
        levels = np.array([0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10])
        levels = levels[(levels > np.nanmin(grid)) & (levels < np.nanmax(grid))]
        if levels.size and xs.size > 1 and ys.size > 1:
            cs = ax.contour(xs, ys, grid, levels=levels, colors="w", linewidths=0.8)
            ax.clabel(cs, fmt=lambda v: f"{v:g} mm", fontsize=8)
        beyond = beyond_ambiguity(rows)
        if beyond.any():
            bx = np.array([float(r[names[0]]) for r in rows])[beyond]
            by = np.array([float(r[names[1]]) for r in rows])[beyond]
            ax.plot(bx, by, "x", color="r", ms=4, label="beyond the unambiguous range (folded depth)")
            ax.legend(loc="upper right", fontsize=8)
        ax.set(xlabel=names[0], ylabel=names[1], title="depth precision bound (phase-locked CRLB)")
        if at:
            ax.set_title(ax.get_title() + "\nat " + ", ".join(f"{n} = {v:g}" for n, v in at.items()), fontsize=10)
        return save_figure(fig, path)
    name = names[0]
    x = np.array([float(r[name]) for r in rows])
    order = np.argsort(x)
    fig, ax = plt.subplots(figsize=(7, 5), constrained_layout=True)
    beyond = beyond_ambiguity(rows)
    if beyond.any():
        ax.plot(
            x[beyond], crlb[beyond], "x", color="r", ms=7, zorder=5, label="beyond the unambiguous range (folded depth)"
        )
    # markers, so that a sweep of one point shows
    ax.loglog(x[order], crlb[order], "-", marker=".", label="CRLB, phase-locked (autodiff Fisher)")
    ax.loglog(
        x[order],
        np.array([float(r["crlb_frequency_only_mm"]) for r in rows])[order],
        "--",
        marker=".",
        label="CRLB, frequency only",
    )
    mc = np.array([float(r.get("mc_precision_mm", float("nan"))) for r in rows])
    trials = np.array([float(r.get("mc_trials", float("nan"))) for r in rows])
    valid = np.array([float(r.get("mc_valid_fraction", float("nan"))) for r in rows])
    has = np.isfinite(mc) & (valid >= 0.5)  # a spread over a few surviving pixels would mislead
    if has.any():
        used = trials[has] * valid[has]
        err = mc[has] / np.sqrt(2 * np.maximum(used - 1, 1))
        ax.errorbar(
            x[has],
            mc[has],
            yerr=err,
            fmt="o",
            label=f"Monte Carlo (ML), {int(np.nanmax(trials))} px each (points with ≥ 50 % valid)",
        )
    ax.set(xlabel=name, ylabel="depth precision (mm)")
    if name == "num_steps":
        rate = np.array([float(r["frame_rate_hz"]) for r in rows])
        if np.allclose(rate, rate[0]):
            top = ax.secondary_xaxis("top", functions=(lambda n: n / rate[0], lambda t: t * rate[0]))
            top.set_xlabel(f"acquisition time (s) at {rate[0]:g} frames/s")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return save_figure(fig, path)
