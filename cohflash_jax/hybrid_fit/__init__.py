"""Calibration of the hybrid (per-CCD phase, gain, offset), the modulator (β, roll-off) and
τ_sys from a stepped-frequency capture of a calibration target, with optimistix.

Model of CCD k at pixel p and frame m (DN; docs/design-reference.md §1, gauge CCD 1: θ error 0, g = 1):

    v_k[m] = o_k + g_k·L_p + ½·g_k·Re(e^{iθ_k}·z_p·s_p[m]),
    s_p[m] = S(2π f_m τ_p; β(f_m))·e^{iφ̃_p[m]}

with L_p the common level (reference, echo intensity, dark), z_p the pixel's complex tone
amplitude (carrier phase included) and φ̃_p the tracked carrier drift (zero when static).

Stage 1, hybrid: given s_p (from a reconstruction), each pixel's centred port sequences are
linear in (Re z_p, Im z_p), so z_p is projected out (variable projection) and only six global
unknowns remain (three phase errors, three log gains). The fit needs only each pixel's
sufficient statistics — the 2×2 Gram matrix of (Re s, Im s) and the 4×2 cross products —
so it costs nothing per frame once those are formed. A static pixel (Im s ≡ 0) carries its
line's direction in the four-port space; pixels with different carrier phases (speckle, a
target tilted by more than a wavelength, carrier drift) make phases and gains identifiable.
Offsets follow from the per-pixel means: only o_k − g_k·o_1 is observable (a common term
∝ g_k is cancelled by the I/Q combination), so the gauge is o_1 = 0 unless a dark capture
gives o_1.

Stage 2, modulator: with the calibrated hybrid, each pixel's carrier-aligned real sequence
r_p[m] = A_p·S(2π f_m τ_p; x(f_m)) + b_p is fitted in the time domain for per-pixel depth
(A_p, b_p projected out) and the global x_0 = β/2 and roll-off u = (f_max/f_3dB)², where
x(f) = x_0/√(1 + u·(f/f_max)²). The harmonic ratios identify β, the fundamental's taper
over the band identifies the roll-off; the bias θ_b stays fixed (from the capture), since β
and θ_b are nearly degenerate through the 2nd-harmonic ratio.

Stage 3, τ_sys: depths reconstructed with the calibration and τ_sys = 0, against a known
target distance.

Uncertainties: from the Jacobian at the optimum, cov = (JᵀJ)⁻¹·χ²/dof, with residuals
whitened by each pixel's (and CCD's) measured noise. A parameter whose uncertainty exceeds
what the data can support is reported as not identified, with the reason.
"""

from .calibrate import calibrate_hybrid, initial_common_drift, read_mean_frame
from .common import Estimate, tone_sequences
from .hybrid_stage import HybridFit, common_carrier, fit_hybrid, fit_offsets, pixel_statistics
from .modulator_stage import ModulatorFit, fit_modulator
from .report import save_hybrid_report

__all__ = [
    "calibrate_hybrid",
    "initial_common_drift",
    "read_mean_frame",
    "Estimate",
    "tone_sequences",
    "HybridFit",
    "common_carrier",
    "fit_hybrid",
    "fit_offsets",
    "pixel_statistics",
    "ModulatorFit",
    "fit_modulator",
    "save_hybrid_report",
]
