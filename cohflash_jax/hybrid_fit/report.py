"""The calibration's report figure."""

from __future__ import annotations

import numpy as np


def save_hybrid_report(path, result: dict):
    """Report figure: I/Q of the strongest pixel with the nominal and the calibrated hybrid,
    the carrier drift, and the fitted sideband weights over the sweep."""
    from ..fileio import headless_pyplot, save_figure

    plt = headless_pyplot()

    diag = result["diagnostics"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5), constrained_layout=True)
    ax = axes[0]
    for name, colour in (("nominal", "tab:red"), ("calibrated", "tab:blue")):
        z = diag["iq"][name] - np.mean(diag["iq"][name])
        z = z * np.exp(-1j * diag["drift_rad"])
        ax.plot(z.real, z.imag, ".", ms=1.5, alpha=0.4, color=colour, label=f"{name} hybrid")
    ax.set_aspect("equal")
    ax.set(title=f"I/Q of pixel {diag['pixel']} (drift removed, centred)", xlabel="I (DN)", ylabel="Q (DN)")
    ax.legend(markerscale=6)
    ax = axes[1]
    ax.plot(diag["drift_rad"])
    ax.set(title="common carrier drift", xlabel="frame", ylabel="phase (rad)")
    ax = axes[2]
    f = diag["frequencies_hz"]
    w = np.asarray(diag["modulator"].weights(f))
    for n in range(1, w.shape[1]):
        ax.semilogy(f / 1e9, w[:, n], label=f"|c_{n}|²")
    doc = result["document"]["modulator"]
    ax.set(
        title=f"fitted sideband weights (β = {doc['modulation_index']['value']}, "
        f"f_3dB = {doc['rolloff_3db_hz']['value']})",
        xlabel="frequency (GHz)",
        ylabel="weight",
    )
    ax.title.set_fontsize(8)
    ax.legend()
    return save_figure(fig, path)
