"""The whole calibration: pick the strongest pixels of a survey, alternate the hybrid and the
common carrier drift, fit the modulator, then τ_sys against a known distance → a
`cohflash-calibration` document."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..capture import Capture, CaptureError
from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..estimate.drift import initial_common_drift
from ..estimate.iq import align_carrier_static, derotate, iq_from_frames
from ..hybrid import Hybrid
from ..runtime import async_filter_jit, quick_compile
from ..status import Status
from ..tiling import QUICK_COMPILE_MAX_PIXELS
from .common import MIN_FRAMES, MIN_PIXELS, Estimate, tone_sequences
from .hybrid_stage import common_carrier, fit_hybrid, fit_offsets, pixel_statistics
from .modulator_stage import exact_model_depths_m, fit_modulator

iq_program = async_filter_jit(iq_from_frames)


@async_filter_jit
def carrier_aligned_sequences(frames, iq_weights, iq_bias, carrier_rad):
    """I/Q of frames (4, N, P) through a hybrid's matrix, the common carrier drift
    `carrier_rad` (N,) removed, rotated onto each pixel's carrier axis → r (N, P) and the
    noise variances (P,). One compiled program, kept on disk."""
    i, q = iq_from_frames(frames, iq_weights, iq_bias)
    i, q = derotate(i, q, carrier_rad[:, None])
    r, noise_var, _ = align_carrier_static(i, q)
    return r, noise_var


# Survey statuses of pixels a calibration may use. dc_edge pixels are usable: through an
# uncalibrated hybrid the untracked turbulent carrier makes the survey's mean term wander near
# DC, which the calibration's drift model removes. edge_bias pixels are usable too: the survey's
# peak read-out only seeds the ML fit, which has no mirror bias.
USABLE_SURVEY_STATUS = (Status.OK, Status.DC_EDGE, Status.EDGE_BIAS)


def _select_pixels(capture: Capture, max_pixels: int, snr_map: np.ndarray, status_map: np.ndarray):
    ok = np.isin(status_map, USABLE_SURVEY_STATUS) & np.isfinite(snr_map)
    if int(ok.sum()) < MIN_PIXELS:
        counts = ", ".join(f"{Status(int(c)).message} {int((status_map == c).sum())}" for c in np.unique(status_map))
        raise CaptureError(
            f"{capture.path}: only {int(ok.sum())} pixels are usable for calibration (need ≥ "
            f"{MIN_PIXELS}); survey statuses: {counts}"
        )
    idx = np.flatnonzero(ok.ravel())
    idx = idx[np.argsort(-snr_map.ravel()[idx])][:max_pixels]
    return np.sort(idx)


def stand_in_depths(depth_m: np.ndarray, fitted: np.ndarray) -> np.ndarray:
    """`depth_m` with the pixels that did not fit given the fitted pixels' median: finite values.

    Every selected pixel stays in the calibration's arrays, those that did not fit weighted out
    (`fit_hybrid`'s `used`) or their results left unread: the programs' shapes then depend only
    on the number of pixels selected (`max_pixels` where a capture has that many usable ones),
    so a later capture, or a later pass where another count fits, loads them from the compile
    cache instead of compiling anew."""
    return np.where(fitted, depth_m, np.median(depth_m[fitted]))


def _gather(capture: Capture, flat_idx: np.ndarray) -> np.ndarray:
    """Frames (4, N, P) float64 of the chosen pixels, read row by row."""
    n, h, w = capture.shape
    rows, cols = np.divmod(flat_idx, w)
    out = np.empty((4, n, flat_idx.size), np.float64)
    for r in np.unique(rows):
        sel = rows == r
        tile = capture.read_tile(slice(int(r), int(r) + 1))[:, :, 0, :]
        out[:, :, sel] = tile[:, :, cols[sel]]
    return out


def read_mean_frame(path) -> np.ndarray:
    """Mean frame (4, H, W) of a dark or flat capture (its `dark` dataset if frames are absent)."""
    with Capture(path) as cap:
        n, h, w = cap.shape
        total = np.zeros((4, h, w), np.float64)
        for m0 in range(0, n, 256):
            block = cap.frames[:, m0 : m0 + 256].astype(np.float64)
            if not np.all(np.isfinite(block)):
                raise CaptureError(f"{path}: frames contain NaN or inf")
            total += block.sum(axis=1)
        return total / n


# runs of frames the modulator's block jackknife leaves out in turn (`block_jackknife_sigma`)
MODULATOR_JACKKNIFE_BLOCKS = 16

# |mean of z_p/|z_p|| over the calibration pixels above which the hybrid is not identified
MAX_CARRIER_PHASE_COHERENCE = 0.5


def carrier_phase_coherence(amplitudes) -> float:
    """|⟨z_p/|z_p|⟩|: 1 where every pixel's complex amplitude has one phase (a mirror-flat target
    facing the camera), ~1/√P where the optical carrier phases are spread (speckle, tilt)."""
    z = np.asarray(amplitudes)
    z = z[np.abs(z) > 0]
    return float(np.abs(np.mean(z / np.abs(z)))) if z.size else 1.0


def calibrate_hybrid(
    capture_path,
    *,
    dark_path=None,
    flat_path=None,
    known_distance_m: float | None = None,
    max_pixels: int = 1024,
    modulator_pixels: int = 48,
    iterations: int = 2,
    inner_iterations: int = 3,
    min_depth_m: float = 1.0,
    progress: bool = True,
) -> dict:
    """The whole calibration → a `cohflash-calibration` document (dict) plus per-pixel maps.

    Returns {"document": JSON-able dict, "maps": {name: array} (may be empty)}.

    The fits run on at most `max_pixels` selected pixels, a few times each: where those are
    few (`tiling.QUICK_COMPILE_MAX_PIXELS`), compiling their programs is most of a first run,
    so they are compiled for a short compile (the survey of the whole capture decides for
    itself, by its size)."""
    from ..reconstruct import ReconstructOptions, reconstruct_array, reconstruct_capture

    if known_distance_m is not None and not (math.isfinite(known_distance_m) and known_distance_m > 0):
        raise ValueError(f"known distance must be a positive number of metres, got {known_distance_m}")
    if max_pixels < 1 or modulator_pixels < 1:
        raise ValueError(f"max_pixels and modulator_pixels must be ≥ 1, got {max_pixels} and {modulator_pixels}")
    with quick_compile(max_pixels <= QUICK_COMPILE_MAX_PIXELS):
        with Capture(capture_path) as cap:
            n, h, w = cap.shape
            if n < MIN_FRAMES:
                raise CaptureError(
                    f"{capture_path}: {n} frames are too few to calibrate (need ≥ {MIN_FRAMES}: the tone's "
                    "harmonics and the roll-off need a resolved spectrum)"
                )
            instrument = cap.instrument()
            freqs = cap.frequencies_hz
            unambiguous_m = instrument.sweep.ambiguity_m
            if known_distance_m is not None and known_distance_m >= unambiguous_m:
                raise ValueError(
                    f"--known-distance-m {known_distance_m:g} m lies beyond this capture's unambiguous range "
                    f"{unambiguous_m:.4g} m: the data give the depth only modulo {unambiguous_m:.4g} m, so τ_sys "
                    "would be off by a whole number of periods; calibrate on a target nearer than that"
                )
            nominal = np.asarray(cap.hybrid_phases_rad, np.float64)
            modulator = instrument.modulator
            dark = read_mean_frame(dark_path) if dark_path is not None else None
            if dark is not None and dark.shape != (4, h, w):
                raise CaptureError(f"{dark_path}: dark frame has shape {dark.shape}, the capture needs (4, {h}, {w})")
            # static: the calibration finds and fits the common drift itself, below
            options = ReconstructOptions(method="interp", carrier="static", progress=progress)
            survey = reconstruct_capture(cap, options, instrument).outputs
            idx = _select_pixels(cap, max_pixels, survey["snr"], survey["fit_status"])
            frames = _gather(cap, idx)
        p = idx.size
        hybrid = Hybrid(tuple(nominal))
        # remove each port's mean: common mode leaking through the uncalibrated hybrid is constant,
        # but once the carrier drift is derotated it would wander near DC and swamp the tone
        port_means = frames.mean(axis=1)  # (4, P) DN, for the offsets
        frames = frames - port_means[:, None]
        data = jnp.asarray(frames)
        iq_w, iq_b = hybrid.iq_matrix_dn(1.0)
        drift, drift_note = initial_common_drift(*iq_program(data, iq_w, iq_b))
        drifting = bool(np.any(drift != 0))  # without a drift u ≡ 1: fitting it would only fit noise
        u = jnp.asarray(np.exp(1j * drift))
        params = None
        ml = ReconstructOptions(method="ml", progress=False, dtype="float64", min_depth_m=min_depth_m)

        def reconstruct_selected(hyb, mod, carrier):
            hyb = Hybrid(hyb.phases_rad, hyb.relative_gains, (0.0,) * 4)  # the frames are centred
            out = reconstruct_array(
                frames.reshape(4, n, 1, p), instrument.replace(hybrid=hyb, modulator=mod), ml, carrier_phase_rad=carrier
            )
            return out["depth_m"][0], out["fit_status"][0]

        def aligned_sequences(hyb, carrier, uncentred):
            """Carrier-aligned sequences r (N, P) and their noise variances through `hyb`, the
            drift removed. A time-domain fit needs the uncentred I/Q where the hybrid (offsets
            included) is calibrated: a mean removed before derotation would wander after it, and
            pass for a roll-off; a calibrated hybrid cancels the common mode, so no leakage."""
            source = frames + port_means[:, None] if uncentred else frames  # host arrays both: one program
            r, noise_var = carrier_aligned_sequences(source, *hyb.iq_matrix_dn(1.0), np.asarray(carrier, np.float64))
            return np.asarray(r), np.asarray(noise_var)

        for iteration in range(iterations):
            last_pass = iteration == iterations - 1
            depth, status = reconstruct_selected(hybrid, modulator, drift)
            good = np.flatnonzero(status == Status.OK)
            if good.size < MIN_PIXELS:
                why = (
                    f"with the carrier drift found (rms {np.std(drift):.2f} rad) removed they do not fit: a target "
                    "flat to a fraction of the wavelength facing the camera (one carrier phase in every pixel) leaves "
                    "that drift undetermined; tilt it by a few wavelengths across the view or use a diffuse target"
                    if drifting
                    else f"too little signal, or a carrier drift the survey did not accept ({drift_note}); a "
                    "turbulent capture whose drift is missed cannot be calibrated"
                )
                raise CaptureError(f"{capture_path}: only {good.size} of {p} pixels reconstruct validly: {why}")
            usable = status == Status.OK
            tone = tone_sequences(freqs, 2 * stand_in_depths(depth, usable) / C, modulator)
            for _ in range(inner_iterations):  # alternate: hybrid given the drift, drift given the hybrid
                stats = pixel_statistics(data, np.asarray(tone) * np.asarray(u)[:, None])
                fit = fit_hybrid(stats, nominal, params, usable)
                params = fit.params
                hybrid_h = jnp.asarray(0.5 * fit.relative_gains * np.exp(1j * fit.phases_rad))
                if drifting:
                    # the pixels weighted out have zero amplitudes: they add nothing
                    u = common_carrier(data, hybrid_h, jnp.asarray(fit.amplitudes), tone, stats["noise_var"])
            if drifting:
                drift = np.unwrap(np.angle(np.asarray(u)))
                drift = drift - np.mean(drift)
            # stage 2 on the strongest pixels, with the current hybrid and drift
            if fit.identified:
                offsets = fit_offsets(port_means, stats, fit, None)[0]
                hybrid = Hybrid(tuple(fit.phases_rad), tuple(fit.relative_gains), tuple(offsets))
            r, noise_var = aligned_sequences(hybrid, drift, fit.identified)
            amp = np.abs(fit.amplitudes)  # zero where a pixel is weighted out
            strongest = good[np.argsort(-amp[good])][:modulator_pixels]
            # under a drift, the σ of the last pass also from a block jackknife over the frames
            blocks = MODULATOR_JACKKNIFE_BLOCKS if drifting and last_pass else None
            mod_fit = fit_modulator(
                freqs, r[:, strongest], noise_var[strongest], 2 * depth[strongest] / C, modulator, blocks
            )
            modulator = mod_fit.modulator
        coherence = carrier_phase_coherence(fit.amplitudes)
        if fit.identified and coherence > MAX_CARRIER_PHASE_COHERENCE:
            fit = dataclasses.replace(
                fit,
                identified=False,
                note=(
                    f"phases and gains are not identifiable from this target: every pixel sees nearly the same "
                    f"optical carrier phase (coherence {coherence:.2f} > {MAX_CARRIER_PHASE_COHERENCE}), as a "
                    "target flat to a fraction of the wavelength and facing the camera gives. Errors of the "
                    "modulator model are then common to all pixels and map into the hybrid in one direction "
                    "(measured on such a target: 3° and 15 % at a stated 0.12° and 0.25 %). A diffusely "
                    "scattering target (speckle) or one tilted by a few wavelengths across the view gives each "
                    "pixel its own carrier phase (`cohflash simulate planar --tilt-m 2e-4,1.3e-4` or "
                    "`--effects …,speckle`)"
                ),
            )
            hybrid = Hybrid(tuple(nominal))
            if drifting:  # the modulator was fitted through that hybrid and a drift it cannot separate
                why = (
                    "not identifiable from this target with a drifting carrier: every pixel sees one optical "
                    "carrier phase, so the drift, the hybrid and the sideband weights trade off in every pixel "
                    "alike (measured on such targets: β pulls to 4σ, roll-off to 15σ); see the hybrid's note"
                )
                mod_fit = dataclasses.replace(
                    mod_fit, modulation_index=Estimate(None, None, why), rolloff_3db_hz=Estimate(None, None, why)
                )
                modulator = instrument.modulator
        offsets, offset_sigma, offset_note = fit_offsets(port_means, stats, fit, dark)
        if fit.identified:
            hybrid = Hybrid(tuple(fit.phases_rad), tuple(fit.relative_gains), tuple(offsets))
        depth, status = reconstruct_selected(hybrid, modulator, drift)
        ok = status == Status.OK
        if known_distance_m is None:
            delay_est = Estimate(
                None,
                None,
                "not identifiable without --known-distance-m (τ_sys and the target "
                "distance enter the data only as their sum)",
            )
        elif ok.sum() < MIN_PIXELS:
            delay_est = Estimate(None, None, f"only {int(ok.sum())} pixels reconstructed validly")
        else:
            # the window fit's depths refined with the sideband weights at every frequency: their
            # mean is what τ_sys needs to a fraction of its σ (`exact_model_depths_m`)
            r, _ = aligned_sequences(hybrid, drift, fit.identified)
            d = exact_model_depths_m(freqs, r, stand_in_depths(depth, ok), modulator, float(instrument.system_delay_s))[
                ok
            ]
            delay_est = Estimate(
                float(2 * (np.mean(d) - known_distance_m) / C), float(2 * np.std(d, ddof=1) / math.sqrt(d.size) / C)
            )
        maps = {}
        if dark is not None:
            maps["offset_map_dn"] = dark.astype(np.float32)
        if flat_path is not None:
            if dark is None:
                raise ValueError("--flat needs --dark: the flat field is measured above the dark level")
            flat = read_mean_frame(flat_path)
            if flat.shape != (4, h, w):
                raise CaptureError(f"{flat_path}: flat frame has shape {flat.shape}, the capture needs (4, {h}, {w})")
            above = flat - dark
            if np.any(above[0] <= 0):
                raise CaptureError(
                    f"{flat_path}: the flat field is not above the dark level on CCD 1 "
                    f"({int((above[0] <= 0).sum())} pixels)"
                )
            maps["gain_map"] = (above / (above[:1] * fit.relative_gains[:, None, None])).astype(np.float32)
        hyb_note = fit.note
        doc = {
            "format": "cohflash-calibration",
            "format_version": 1,
            "gauge": "CCD 1: phase error 0, gain 1" + ("; offsets: " + offset_note),
            "hybrid": {
                "phases_rad": fit.phases_rad.tolist() if fit.identified else None,
                "phases_sigma_rad": fit.phase_sigma_rad.tolist() if fit.identified else None,
                "relative_gains": fit.relative_gains.tolist() if fit.identified else None,
                "relative_gains_sigma": fit.gain_sigma.tolist() if fit.identified else None,
                "offsets_dn": offsets.tolist() if fit.identified else None,
                "offsets_sigma_dn": offset_sigma.tolist() if fit.identified else None,
                **({"note": hyb_note} if hyb_note else {}),
            },
            "modulator": {
                "modulation_index": mod_fit.modulation_index.as_dict(),
                "rolloff_3db_hz": mod_fit.rolloff_3db_hz.as_dict(),
                "bias_rad": mod_fit.bias_rad.as_dict(),
                "max_order": int(modulator.max_order),
                "sideband_weights": {
                    name: np.asarray(modulator.weights(fq)).tolist()
                    for name, fq in (("start", freqs[0]), ("centre", np.mean(freqs)), ("end", freqs[-1]))
                },
            },
            "system_delay_s": delay_est.as_dict(),
            "fit": {
                "pixels": int(p),
                "frames": int(n),
                "modulator_pixels": mod_fit.pixels,
                "hybrid_chi2_per_dof": fit.chi2_per_dof,
                "modulator_chi2_per_dof": mod_fit.chi2_per_dof,
                "carrier_drift_rms_rad": float(np.std(drift)),
                "carrier_drift": drift_note,
                "known_distance_m": known_distance_m,
                "depth_spread_m": float(np.std(depth[ok])) if ok.any() else None,
                "carrier_phase_coherence": coherence,
            },
            "maps": sorted(maps),
        }
        strongest = int(np.argmax(np.abs(fit.amplitudes)))  # zero where a pixel is weighted out
        calibrated = Hybrid(hybrid.phases_rad, hybrid.relative_gains, (0.0,) * 4)
        views = {}
        for name, hyb in (("nominal", Hybrid(tuple(nominal))), ("calibrated", calibrated)):
            w_iq, b_iq = hyb.iq_matrix_dn(1.0)
            i, q = iq_program(frames[:, :, strongest : strongest + 1], w_iq, b_iq)
            views[name] = np.asarray(i[:, 0]) + 1j * np.asarray(q[:, 0])
        diagnostics = {
            "frequencies_hz": np.asarray(freqs),
            "drift_rad": np.asarray(drift),
            "iq": views,
            "modulator": modulator,
            "pixel": divmod(int(idx[strongest]), w),
        }
        return {"document": doc, "maps": maps, "diagnostics": diagnostics}
