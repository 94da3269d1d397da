"""An independent writer of captures: NumPy + SciPy + h5py only, following
docs/design-reference.md §1 and §4 (no cohflash code), so that what the package reads is not
what the package wrote. It writes the paper's link budget by default and can starve the
fundamental (bias, modulation index), drift the carrier, use any schedule and write pure noise.
"""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np
from scipy.special import jv

C = 299_792_458.0
HNU_J = 6.62607015e-34 * C / 1550e-9
PAPER_FREQUENCIES_HZ = 0.1e9 + 1.97e6 * np.arange(3000)


@dataclasses.dataclass
class Writer:
    """A capture's settings. `echo_scale` multiplies the echo power (0: pure noise);
    `drift_rad` (N,): a carrier phase common to all pixels; `x` = β/2, `bias_rad` θ_b."""

    frequencies_hz: np.ndarray = dataclasses.field(default_factory=lambda: PAPER_FREQUENCIES_HZ.copy())
    x: float = 1.0
    bias_rad: float = np.pi / 4
    echo_scale: float = 1.0
    drift_rad: np.ndarray | None = None
    read_noise_e: float = 30.0
    gain_dn_per_e: float = 0.16
    offset_dn: float = 200.0
    exposure_s: float = 4e-3
    orders: int = 8  # |c_n|² of n ≥ 8 is below 1e-7 of |c_0|² for any x ≤ 3.9

    def weights(self) -> np.ndarray:
        """|c_n|² for n = 0..orders−1 (design reference §1)."""
        n = np.arange(self.orders)
        return jv(n, self.x) ** 2 * np.where(n % 2 == 0, np.cos(self.bias_rad) ** 2, np.sin(self.bias_rad) ** 2)

    def electrons(self):
        """(N_l, N_e): reference and echo photoelectrons a frame (paper's 0.64 pW and 0.26 fW)."""
        eta = 0.8
        n_l = eta * 0.64e-12 * self.exposure_s / HNU_J
        return n_l, eta * 0.26e-15 * self.echo_scale * self.exposure_s / HNU_J

    def tone(self, depth_m: np.ndarray) -> np.ndarray:
        """S(2π f_m τ) (N, H, W) of depths (H, W)."""
        w = self.weights()
        psi = 2 * np.pi * np.mod(self.frequencies_hz[:, None, None] * (2 * depth_m / C)[None], 1.0)
        return w[0] + 2 * sum(w[k] * np.cos(k * psi) for k in range(1, self.orders))

    def frames(self, depth_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """uint16 frames (4, N, H, W): Gaussian shot noise, read noise, quantisation, offset."""
        depth_m = np.asarray(depth_m, np.float64)
        h, w = depth_m.shape
        n_l, n_e = self.electrons()
        s0 = self.weights().sum() + self.weights()[1:].sum()
        s = self.tone(depth_m)
        phi = rng.uniform(0, 2 * np.pi, (h, w))[None] + (
            0.0 if self.drift_rad is None else np.asarray(self.drift_rad)[:, None, None]
        )
        theta = np.array([0, np.pi / 2, np.pi, 1.5 * np.pi])
        out = np.empty((4, len(self.frequencies_hz), h, w), np.uint16)
        for k in range(4):
            mean = 0.25 * ((n_l + n_e) * s0 + 2 * np.sqrt(n_l * n_e) * s * np.cos(phi + theta[k]))
            e = mean + np.sqrt(mean + self.read_noise_e**2) * rng.standard_normal(mean.shape)
            out[k] = np.clip(np.round(self.offset_dn + self.gain_dn_per_e * e), 0, 16383)
        return out

    def write(self, path, depth_m: np.ndarray, rng: np.random.Generator, alter=None, chunks=None) -> None:
        """A version-1 capture file (design reference §4) with the modulator's settings;
        `alter`: a function applied to the frames before they are written (bad pixels);
        `chunks`: the frames' HDF5 chunk shape (default: stored contiguous)."""
        frames = self.frames(depth_m, rng)
        frames = frames if alter is None else alter(frames)
        with h5py.File(path, "w") as fh:
            fh.attrs.update(
                {
                    "format": "cohflash-capture",
                    "format_version": 1,
                    "exposure_s": self.exposure_s,
                    "frame_rate_hz": 150.0,
                    "wavelength_m": 1550e-9,
                    "modulation_index": 2 * self.x,
                    "bias_rad": self.bias_rad,
                    "sideband_max_order": self.orders - 1,
                    "adc_bits": 14,
                }
            )
            fh.create_dataset("frames", data=frames, chunks=chunks)
            fh["frequencies_hz"] = self.frequencies_hz
            fh["hybrid_phases_rad"] = np.array([0, np.pi / 2, np.pi, 1.5 * np.pi])

    def crlb_m(self) -> float:
        """Closed-form CRLB of the phase-locked fundamental (sidebands ignored: they only add
        information), I = V0 − V2 in DN."""
        n_l, n_e = self.electrons()
        w = self.weights()
        s0 = w.sum() + w[1:].sum()
        g = self.gain_dn_per_e
        sigma = g * np.sqrt(2 * (0.25 * (n_l + n_e) * s0 + self.read_noise_e**2) + 2 / 12 / g**2)
        amp = g * np.sqrt(n_l * n_e) * 2 * w[1]
        info = 0.5 * amp**2 * np.sum((2 * np.pi * self.frequencies_hz) ** 2) / sigma**2
        return C / 2 / np.sqrt(info)


def random_walk_rad(num_frames: int, total_rad: float, rng: np.random.Generator) -> np.ndarray:
    """A carrier random walk whose rms step makes ~`total_rad` over the sweep."""
    return np.cumsum(rng.standard_normal(num_frames) * total_rad / np.sqrt(num_frames))
