"""Per-pixel depth posteriors with emcee: intervals that stay honest near the SNR threshold,
where the likelihood of the phase-locked model has several ripples and the CRLB's Gaussian lies.

Data of a pixel: the unitary DFT windows (the ML fit's W bins) of the carrier-aligned in-phase
sequence r and of its quadrature q. Model: Z·e^{−iφ̂} = e^{iδφ}·(c + A·T(τ)), i.e.
R̂ = cos δφ·M and Q̂ = sin δφ·M with M = c·D₀ + A·T the phase-locked window model of
`estimate.window_model`, and white Gaussian noise of the variance measured in q. Sampled: the depth
offset from the ML estimate (mm), the amplitude A ≥ 0 and the carrier-phase residual
δφ ∈ (−π, π]. The offset c — linear, flat prior — is marginalised analytically (for a Gaussian
likelihood that is its profile up to a constant); sampling it would leave emcee a flat
direction whenever the window excludes the DC bin. The depth prior is uniform over ±2 DFT
bins around the ML estimate (the window's reach) within [0, ambiguity).

Speed: the tone's window T(depth) is tabulated once per pixel on a grid fine enough for
linear interpolation to be exact to ~1e-7 of its amplitude, and reduced to the few dot products
the χ² needs (`_dot_tables`); each emcee call then costs a gather of those and a few NumPy
vector operations for all walkers (`vectorize=True`).
"""

from __future__ import annotations

import dataclasses
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .constants import SPEED_OF_LIGHT_M_PER_S as C
from .ensemble import DEMove, EnsembleSampler, LockstepEnsembles, SnookerMove, integrated_times
from .estimate.coarse import unitary_rfft
from .estimate.iq import align_carrier_static, derotate, iq_from_frames
from .estimate.window_model import UniformModel, bin_weights, window_tables
from .reconstruct import TilePlan, process_tile, program_plan
from .runtime import async_filter_jit, quick_compile
from .status import Status
from .tiling import QUICK_COMPILE_MAX_PIXELS, pixel_bucket

PARAMETERS = ("depth_offset_mm", "amplitude", "carrier_phase_rad")
LABELS = ("depth − ML (mm)", "amplitude A (DN)", "carrier phase δφ (rad)")


class PixelData(eqx.Module):
    """What the posterior of one pixel needs (float64; a leading pixel axis when batched;
    NumPy arrays as `pixel_data` gives them)."""

    r_window: np.ndarray  # (W,) complex
    q_window: np.ndarray  # (W,) complex
    k0: np.ndarray
    ml_depth_m: np.ndarray
    ml_amplitude: np.ndarray
    noise_var: np.ndarray
    crlb_m: np.ndarray
    status: np.ndarray


def pixel_data(plan: TilePlan, frames, window_bins: int, dark=None, gain=None) -> PixelData:
    """ML results and the DFT windows (`window_bins` wide) of r and q for pixels (4, N, P),
    with their per-pixel offsets and gains (4, P) where given → PixelData (leading P), in
    NumPy (a pixel is then taken out without a compiled indexing operation). The plan goes in
    as the programs take it (`program_plan`): another calibration's τ_sys or another
    threshold runs the program already compiled. A few pixels (what is sampled: each posterior
    takes a second or so) are compiled for a short compile (`runtime.quick_compile`), and
    padded with blank pixels to their `tiling.pixel_bucket`, as a region of interest is: one
    program serves any few pixels (each pixel's fields depend on its own frames alone)."""
    count = frames.shape[-1]
    few = count <= QUICK_COMPILE_MAX_PIXELS
    frames, dark, gain = pad_pixels(pixel_bucket(count) if few else count, frames, dark, gain)
    with quick_compile(few):
        fields = _pixel_data(program_plan(plan), frames, window_bins, dark, gain)
    return PixelData(*(np.asarray(x)[:count] for x in fields))


def pad_pixels(width: int, frames, dark=None, gain=None) -> tuple:
    """Frames (4, N, P) and per-pixel maps (4, P) with blank pixels appended up to `width`
    (frames and offsets 0, gains 1), on the host: the padding compiles nothing."""
    count = frames.shape[-1]
    if width == count:
        return frames, dark, gain
    pad = lambda a, value: (
        None
        if a is None
        else np.pad(np.asarray(a), [(0, 0)] * (np.ndim(a) - 1) + [(0, width - count)], constant_values=value)
    )
    return pad(frames, 0), pad(dark, 0), pad(gain, 1)


@async_filter_jit
def _pixel_data(plan: TilePlan, frames, window_bins: int, dark=None, gain=None) -> tuple:
    """`pixel_data`'s fields, in one compiled program kept on disk (a warm process neither
    traces nor lowers the reconstruction inside it)."""
    out = process_tile(plan, frames, dark, None, gain)
    n = frames.shape[1]
    i, q = iq_from_frames(frames.astype(jnp.float32), plan.iq.weights, plan.iq.bias, dark, gain)
    _, _, phase = align_carrier_static(i, q)
    r, qr = derotate(i, q, phase[None, :])
    spec_r, spec_q = unitary_rfft(r), unitary_rfft(qr)
    k_count = spec_r.shape[-1]
    w = min(window_bins, k_count)
    m = plan.model
    tau = 2 * out["depth_m"] / C + m.system_delay_s
    frac = jnp.mod(tau * m.step_hz * plan.geometry.dominant_order, 1.0)  # cycles per frame of the dominant tone
    peak = jnp.round(jnp.minimum(frac, 1 - frac) * n).astype(int)
    k0 = jnp.clip(peak - w // 2, 0, k_count - w)
    take = lambda s: jnp.take_along_axis(s, k0[:, None] + jnp.arange(w), axis=-1).astype(jnp.complex128)
    noise_var = jnp.var(qr, axis=0).astype(jnp.float64)
    return (
        take(spec_r),
        take(spec_q),
        k0,
        out["depth_m"],
        out["amplitude"],
        noise_var,
        out["sigma_m"],
        out["fit_status"],
    )


@async_filter_jit
def _tone_table(model: UniformModel, k0, depths_m, width: int):
    """The tone's window T(depth) (G, W) for unit amplitude, the DC column and bin weights
    (one compiled program, kept on disk)."""
    tables = window_tables(k0, width, model.num_frames)
    tone = jax.vmap(lambda d: model.tone_column(d, tables))(depths_m)
    return tone, model.dc_column(tables), bin_weights(tables, model.num_frames)


def _dot_tables(table, dc, omega, r_window, q_window) -> dict:
    """What the log-posterior needs of a pixel, as dot products on the depth grid.

    Stack each window's real and imaginary parts, weighted by the bin weights: the tone rows
    t_g (G, 2W), the DC column d, and the data y_r (of r) and y_q (of q). The model at a walker
    is, for r, c·A·t(u) and for q, s·A·t(u) (c, s = cos, sin δφ), with t(u) linear in the grid
    between rows i and i+1, and the offset projected out along (c·d, s·d). So its χ² needs only
    t_g·y_r, t_g·y_q, t_g·d, |t_g|², t_g·t_{g+1} and the data's own products: a handful of
    gathered numbers a walker instead of (B, 4W) arrays (emcee calls it twice a step)."""
    weight = np.tile(np.asarray(omega, np.float64), 2)
    parts = lambda z: np.concatenate([np.real(z), np.imag(z)], axis=-1) * weight
    t, d, y_r, y_q = parts(np.asarray(table)), parts(np.asarray(dc)), parts(r_window), parts(q_window)
    rows = np.stack([t @ y_r, t @ y_q, t @ d, np.sum(t * t, axis=-1)], axis=-1)
    return {
        # (G, 5): t_g·y_r, t_g·y_q, t_g·d, |t_g|², t_g·t_{g+1} (one gather a walker and row)
        "rows": np.concatenate([rows, np.append(np.sum(t[:-1] * t[1:], axis=-1), 0.0)[:, None]], axis=-1),
        "yy": float(y_r @ y_r + y_q @ y_q),
        "yd_r": float(y_r @ d),
        "yd_q": float(y_q @ d),
        "dd": float(d @ d),
    }


@dataclasses.dataclass(frozen=True)
class PixelLikelihoods:
    """The log-posteriors of P pixels (`log_prob`), each from its `_dot_tables`: the rows
    (P, G, 5) on a depth grid shared by the pixels (`table_start_mm`, `table_step_mm`), and
    each pixel's data products, noise variance and ML depth (P,). The amplitude is in the
    units of the data.

    NumPy, not jitted JAX: emcee calls it twice a step on ~16 walkers, where a jitted call's
    dispatch and transfer cost far more than the microseconds of work (docs/performance.md)."""

    rows: np.ndarray
    yy: np.ndarray
    yd_r: np.ndarray
    yd_q: np.ndarray
    dd: np.ndarray
    noise_var: np.ndarray
    ml_depth_m: np.ndarray
    table_start_mm: float
    table_step_mm: float
    depth_half_range_m: float
    ambiguity_m: float

    @classmethod
    def stack(cls, pixels: list[PixelLikelihoods]) -> PixelLikelihoods:
        """One object of several (their grid, prior and bounds are the plan's, hence shared)."""
        joined = {
            f.name: np.concatenate([getattr(p, f.name) for p in pixels])
            for f in dataclasses.fields(cls)
            if isinstance(getattr(pixels[0], f.name), np.ndarray)
        }
        return dataclasses.replace(pixels[0], **joined)

    def put(self, slot: int, pixel: PixelLikelihoods):
        """Hold one pixel's log-posterior (`pixel_likelihood`) at `slot`, in place."""
        for f in dataclasses.fields(self):
            if isinstance(getattr(self, f.name), np.ndarray):
                getattr(self, f.name)[slot] = getattr(pixel, f.name)[0]

    def first_pixel_log_prob(self, thetas):
        """The first pixel's log-posterior of walkers (B, 3) → (B,): emcee's vectorised form."""
        return self.log_prob([0], np.asarray(thetas, np.float64)[None])[0]

    def log_prob(self, pixels, thetas):
        """Log-posterior (n, K) of walkers `thetas` (n, K, 3) of the `pixels` (n,)."""
        pixels = np.asarray(pixels)[:, None]
        offset_mm, amp, dphi = thetas[..., 0], thetas[..., 1], thetas[..., 2]
        pos = (offset_mm - self.table_start_mm) / self.table_step_mm
        idx = np.clip(np.floor(pos).astype(int), 0, self.rows.shape[1] - 2)
        f = pos - idx
        g = 1 - f
        lo, hi = self.rows[pixels, idx], self.rows[pixels, idx + 1]  # (n, K, 5) each
        model_dots = amp[..., None] * (g[..., None] * lo[..., :3] + f[..., None] * hi[..., :3])
        my_r, my_q, md = model_dots[..., 0], model_dots[..., 1], model_dots[..., 2]
        mm = amp * amp * (g * g * lo[..., 3] + 2 * f * g * lo[..., 4] + f * f * hi[..., 3])
        c, s = np.cos(dphi), np.sin(dphi)
        unit = c * c + s * s
        # |y − model|², then the offset's column (c·d, s·d) projected out
        ee = self.yy[pixels] - 2 * (c * my_r + s * my_q) + unit * mm
        ce = c * self.yd_r[pixels] + s * self.yd_q[pixels] - unit * md
        chi2 = ee - ce * ce / (unit * self.dd[pixels] + 1e-300)
        depth = self.ml_depth_m[pixels] + 1e-3 * offset_mm
        ok = (
            (amp >= 0)
            & (np.abs(dphi) <= np.pi)
            & (np.abs(1e-3 * offset_mm) <= self.depth_half_range_m)
            & (depth >= 0)
            & (depth < self.ambiguity_m)
        )
        return np.where(ok, -chi2 / self.noise_var[pixels], -np.inf)


def pixel_likelihood(
    model: UniformModel, data: PixelData, *, depth_half_range_m: float, ambiguity_m: float, ripple_m: float
) -> PixelLikelihoods:
    """One pixel's log-posterior (`PixelLikelihoods` of one pixel; the table is built with JAX)."""
    order = max(1, model.weights.shape[0] - 1)
    step_mm = 1e3 * min(ripple_m, depth_half_range_m) / (order * 1000)
    half_mm = 1e3 * depth_half_range_m
    grid = np.arange(-half_mm, half_mm + 2 * step_mm, step_mm)
    table, dc, omega = _tone_table(
        model, np.asarray(data.k0), data.ml_depth_m + 1e-3 * grid, int(data.r_window.shape[0])
    )
    dots = _dot_tables(table, dc, omega, np.asarray(data.r_window), np.asarray(data.q_window))
    one = lambda x: np.array([x], np.float64)
    return PixelLikelihoods(
        rows=dots["rows"][None],
        yy=one(dots["yy"]),
        yd_r=one(dots["yd_r"]),
        yd_q=one(dots["yd_q"]),
        dd=one(dots["dd"]),
        noise_var=one(data.noise_var),
        ml_depth_m=one(data.ml_depth_m),
        table_start_mm=float(grid[0]),
        table_step_mm=float(step_mm),
        depth_half_range_m=depth_half_range_m,
        ambiguity_m=ambiguity_m,
    )


def make_log_prob(
    model: UniformModel, data: PixelData, *, depth_half_range_m: float, ambiguity_m: float, ripple_m: float
):
    """Vectorised log-posterior over walkers (B, 3) → (B,) of one pixel, for emcee."""
    likelihood = pixel_likelihood(
        model, data, depth_half_range_m=depth_half_range_m, ambiguity_m=ambiguity_m, ripple_m=ripple_m
    )
    return likelihood.first_pixel_log_prob


@dataclasses.dataclass
class Posterior:
    """Summary of one pixel's posterior. Depths in metres; `samples` in PARAMETERS units."""

    samples: np.ndarray
    ml_depth_m: float
    mean_m: float
    median_m: float
    interval68_m: tuple[float, float]
    interval95_m: tuple[float, float]
    crlb_m: float
    multimodal: bool
    converged: bool
    autocorr_steps: float
    acceptance: float
    steps: int
    note: str
    ml_status: int = 0  # the ML fit's status code for this pixel (0 = valid)

    def covers(self, depth_m: float, level: int = 68) -> bool:
        lo, hi = self.interval68_m if level == 68 else self.interval95_m
        return lo <= depth_m <= hi


def check_max_steps(max_steps: int):
    if max_steps < 1:
        raise ValueError(f"max_steps must be ≥ 1 (emcee steps a pixel), got {max_steps}")


# differential-evolution moves (emcee's recipe for multimodal targets, a snooker share for jumps
# between modes): on the high-SNR planar target τ fell so that chains converge in 1500–2000
# steps against 2500–3000 with the default stretch move, at the same widths
MOVE_WEIGHTS = (0.8, 0.2)
# a posterior run steps at most this many pixels together (`LockstepEnsembles`), and fewer where
# their chains could hold more than `LOCKSTEP_CHAIN_BYTES` at `max_steps`: each pixel keeps its
# whole chain until it ends (1.5 MB at 2,000 steps of 32 walkers, 15 MB at 20,000)
LOCKSTEP_PIXELS = 32
LOCKSTEP_CHAIN_BYTES = 512 * 2**20


def lockstep_pixels(max_steps: int, nwalkers: int, batch: int) -> int:
    """How many pixels `sample_pixels_of` steps together: `LOCKSTEP_PIXELS`, fewer where their
    chains (grown a batch of steps at a time, float64) could pass `LOCKSTEP_CHAIN_BYTES`."""
    steps = batch * -(-max_steps // batch)
    return max(1, min(LOCKSTEP_PIXELS, LOCKSTEP_CHAIN_BYTES // (steps * nwalkers * len(PARAMETERS) * 8)))


def _moves():
    return list(zip((DEMove(), SnookerMove()), MOVE_WEIGHTS))


def _start(
    model: UniformModel,
    data: PixelData,
    *,
    ambiguity_m: float,
    bin_depth_m: float,
    ripple_m: float,
    rng: np.random.Generator,
    nwalkers: int,
) -> tuple[PixelLikelihoods, np.ndarray, int]:
    """A pixel's log-posterior, its walkers' start (nwalkers, 3) and its sampler's seed, drawn
    from `rng` in this order."""
    half_range = 2 * bin_depth_m
    likelihood = pixel_likelihood(
        model, data, depth_half_range_m=half_range, ambiguity_m=ambiguity_m, ripple_m=ripple_m
    )
    log_prob = likelihood.first_pixel_log_prob
    amp0 = (
        float(data.ml_amplitude)
        if np.isfinite(data.ml_amplitude) and data.ml_amplitude > 0
        else float(np.sqrt(data.noise_var))
    )
    crlb = float(data.crlb_m)
    sigma_mm = 1e3 * crlb if np.isfinite(crlb) and crlb > 0 else 100 * ripple_m
    sigma_mm = min(sigma_mm, 0.25e3 * ripple_m)
    # probe the neighbouring ripples and the half-ripple (sign-flipped) solutions: every one
    # within 15 log-units of the best gets a share of the walkers
    probe = np.array([0.0, -1.0, 1.0, -2.0, 2.0, -0.5, 0.5]) * ripple_m * 1e3
    probe = probe[np.abs(probe) <= 0.9e3 * half_range]
    trial = np.zeros((probe.size, 3))
    trial[:, 0], trial[:, 1] = probe, amp0
    lp = log_prob(trial)
    trial[:, 2] = np.pi
    lp = np.maximum(lp, log_prob(trial))
    keep = np.isfinite(lp) & (lp >= np.max(lp[np.isfinite(lp)], initial=-np.inf) - 15.0)
    centres = probe[keep] if keep.any() else np.zeros(1)
    p0 = np.empty((nwalkers, 3))
    p0[:, 0] = centres[np.arange(nwalkers) % centres.size] + rng.normal(0, sigma_mm, nwalkers)
    p0[:, 0] = np.clip(p0[:, 0], -0.95e3 * half_range, 0.95e3 * half_range)
    p0[:, 1] = amp0 * np.abs(1 + 0.05 * rng.standard_normal(nwalkers))
    p0[:, 2] = 0.05 * rng.standard_normal(nwalkers)
    flip = np.abs(np.abs(p0[:, 0]) - 0.5e3 * ripple_m) < 0.25e3 * ripple_m
    p0[flip, 2] = np.angle(np.exp(1j * (p0[flip, 2] + np.pi)))
    bad = ~np.isfinite(log_prob(p0))
    p0[bad, 0], p0[bad, 2] = rng.normal(0, min(sigma_mm, 0.1 * half_range * 1e3), bad.sum()), 0.0
    # emcee seeds its moves from NumPy's global generator unless told: seed it from `rng`, so a
    # posterior is reproducible for a given seed
    return likelihood, p0, int(rng.integers(2**32))


def _converged(iteration: int, tau: np.ndarray, old_tau: np.ndarray) -> bool:
    """emcee's guidance: the chain is ≥ 50 integrated autocorrelation times long and τ has
    settled (changed by < 5 % since the last check)."""
    return bool(
        np.all(np.isfinite(tau)) and iteration >= 50 * np.max(tau) and np.all(np.abs(old_tau - tau) / tau < 0.05)
    )


def _summary(
    chain: np.ndarray,
    acceptance_fraction: np.ndarray,
    tau: np.ndarray,
    converged: bool,
    data: PixelData,
    ripple_m: float,
) -> Posterior:
    """A pixel's `Posterior` from its chain (steps, W, 3), as emcee's sampler leaves it."""
    iteration = chain.shape[0]
    tau_max = float(np.max(tau)) if np.all(np.isfinite(tau)) else float("nan")
    burn = min(int(2 * tau_max), iteration // 2) if np.isfinite(tau_max) else iteration // 2
    thin = max(1, int(tau_max / 2)) if np.isfinite(tau_max) else 1
    samples = chain[burn + thin - 1 :: thin].reshape(-1, chain.shape[-1])  # emcee's get_chain(discard, thin, flat)
    note = ""
    if not converged:
        note = (
            f"not converged after {iteration} steps (τ ≈ {tau_max:.0f} steps; 50τ needed): "
            "treat the intervals as indicative"
        )
        warnings.warn(note, stacklevel=3)
    if int(data.status) != Status.OK:
        note = (note + "; " if note else "") + "the ML fit flagged this pixel (low SNR or bad data)"
    depth = float(data.ml_depth_m) + 1e-3 * samples[:, 0]
    q = np.percentile(depth, [2.5, 16, 50, 84, 97.5])
    # the likelihood's modes sit a ripple (or half a ripple, with the carrier sign flipped)
    # apart: count half-ripple cells holding ≥ 2 % of the samples, in separate clusters
    cell = np.round((depth - np.median(depth)) / (0.5 * ripple_m)).astype(int)
    counts = np.bincount(cell - cell.min())
    occupied = np.flatnonzero(counts >= 0.02 * depth.size)
    multimodal = bool(occupied.size > 1 and np.any(np.diff(occupied) > 1)) or bool(
        occupied.size > 1 and (q[4] - q[0]) > 0.75 * ripple_m
    )
    return Posterior(
        samples,
        float(data.ml_depth_m),
        float(depth.mean()),
        float(q[2]),
        (float(q[1]), float(q[3])),
        (float(q[0]), float(q[4])),
        float(data.crlb_m),
        multimodal,
        converged,
        tau_max,
        float(np.mean(acceptance_fraction)),
        int(iteration),
        note,
        int(data.status),
    )


def sample_pixel(
    model: UniformModel,
    data: PixelData,
    *,
    ambiguity_m: float,
    bin_depth_m: float,
    ripple_m: float,
    rng: np.random.Generator,
    nwalkers: int = 32,
    batch: int = 250,
    max_steps: int = 20000,
    backend=None,
) -> Posterior:
    """emcee posterior of one pixel, by emcee's own sampler (its chain kept in `backend`, an
    emcee backend, where given). Runs until the chain is ≥ 50 integrated autocorrelation times
    long and τ has settled (emcee's guidance), else warns at `max_steps`. `sample_pixels_of`
    gives the same posterior, for many pixels at once."""
    check_max_steps(max_steps)
    likelihood, p0, seed = _start(
        model, data, ambiguity_m=ambiguity_m, bin_depth_m=bin_depth_m, ripple_m=ripple_m, rng=rng, nwalkers=nwalkers
    )
    sampler = EnsembleSampler(
        nwalkers, 3, likelihood.first_pixel_log_prob, vectorize=True, backend=backend, moves=_moves()
    )
    sampler.random_state = np.random.RandomState(seed).get_state()
    state, old_tau, converged, tau = p0, np.full(3, np.inf), False, np.full(3, np.nan)
    while sampler.iteration < max_steps:
        state = sampler.run_mcmc(state, batch, progress=False)
        tau = sampler.get_autocorr_time(tol=0)
        if _converged(sampler.iteration, tau, old_tau):
            converged = True
            break
        old_tau = tau
    return _summary(sampler.get_chain(), sampler.acceptance_fraction, tau, converged, data, ripple_m)


def sample_pixels_of(
    model: UniformModel,
    data: PixelData,
    *,
    ambiguity_m: float,
    bin_depth_m: float,
    ripple_m: float,
    rng: np.random.Generator,
    nwalkers: int = 32,
    batch: int = 250,
    max_steps: int = 20000,
    done=None,
) -> list[Posterior]:
    """emcee posteriors of every pixel of `data` (PixelData with a leading pixel axis): for
    each pixel the posterior `sample_pixel` gives (its start drawn from `rng` in pixel order,
    its chain emcee's to the bit), but up to `LOCKSTEP_PIXELS` pixels stepped together
    (`ensemble.LockstepEnsembles`, `lockstep_pixels`), a finished pixel's place taken by the next.
    `done(count)` is called as pixels finish."""
    check_max_steps(max_steps)
    count = int(np.shape(data.status)[0])
    pixel = lambda p: jax.tree.map(lambda x: x[p], data)
    geometry = dict(ambiguity_m=ambiguity_m, bin_depth_m=bin_depth_m, ripple_m=ripple_m)
    together = min(count, lockstep_pixels(max_steps, nwalkers, batch))
    # the running pixels' log-posteriors, a slot each; a pixel's start (drawn from `rng`) is
    # made as it takes a slot, so `rng` is drawn in pixel order and only running pixels' tables are held
    slots: PixelLikelihoods | None = None
    slot_of, free = np.zeros(count, dtype=int), list(range(together))[::-1]
    sampler = LockstepEnsembles(
        lambda targets, thetas: slots.log_prob(slot_of[targets], thetas), count, nwalkers, len(PARAMETERS), _moves()
    )
    old_tau, tau = np.full((count, 3), np.inf), np.full((count, 3), np.nan)
    posts: dict[int, Posterior] = {}
    waiting, active = list(range(count))[::-1], []
    while waiting or active:
        while waiting and free:
            t = waiting.pop()
            likelihood, start, seed = _start(model, pixel(t), **geometry, rng=rng, nwalkers=nwalkers)
            if slots is None:
                slots = PixelLikelihoods.stack([likelihood] * together)
            slot_of[t] = free.pop()
            slots.put(slot_of[t], likelihood)
            sampler.start(t, start[None], seed)
            active.append(t)
        sampler.run(np.asarray(active), batch)
        going = []
        for t in active:
            tau[t] = integrated_times(sampler.chain(t))
            converged = _converged(int(sampler.iteration[t]), tau[t], old_tau[t])
            if converged or sampler.iteration[t] >= max_steps:
                accepted = sampler.acceptance_fraction(t)
                posts[t] = _summary(sampler.chain(t), accepted, tau[t], converged, pixel(t), ripple_m)
                sampler.release(t)
                free.append(slot_of[t])
                if done is not None:
                    done(1)
            else:
                old_tau[t] = tau[t]
                going.append(t)
        active = going
    return [posts[t] for t in range(count)]


def sample_pixels(
    instrument,
    frames,
    *,
    pixels: int | None = None,
    rng: np.random.Generator | None = None,
    max_steps: int = 20000,
    quiet: bool = True,
) -> list[Posterior]:
    """emcee posteriors of the first `pixels` pixels (row-major; all by default) of in-memory
    frames (4, N, H, W) or (4, N, P), under the nominal calibration of `instrument`: what
    studies and tests sample (the CLI's `uncertainty` reads a capture file instead).
    `quiet` silences the not-converged warnings (each posterior records it)."""
    from .reconstruct import ReconstructOptions, build_plan

    options = ReconstructOptions(method="ml")
    plan = build_plan(instrument, options, float(instrument.sensor.adc_max_dn))
    frames = np.asarray(frames)
    flat = frames.reshape(4, frames.shape[1], -1)
    count = flat.shape[-1] if pixels is None else min(pixels, flat.shape[-1])
    data = pixel_data(plan, jnp.asarray(flat[:, :, :count]), options.window_bins)
    with warnings.catch_warnings():
        if quiet:
            warnings.simplefilter("ignore")
        return sample_pixels_of(
            plan.model,
            data,
            ambiguity_m=plan.geometry.ambiguity_m,
            bin_depth_m=plan.geometry.bin_depth_m,
            ripple_m=plan.geometry.ripple_m,
            rng=np.random.default_rng(0) if rng is None else rng,
            max_steps=max_steps,
        )
