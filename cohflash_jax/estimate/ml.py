"""Maximum-likelihood depth beyond the DFT bin (uniform sweeps), with optimistix.

Model of the carrier-aligned sequence: r[m] = c + A·Σ_{n≥1} 2 w_n cos(2π n f_m τ) + noise,
where w_n are the sideband weights, c absorbs A·w_0 and any offset. For a uniform sweep
f_m = f_0 + mΔf, the unitary DFT of each tone is a Dirichlet kernel in closed form, so the
fit uses only the W ≈ 17 bins around the peak (white noise stays white; DESIGN.md §3
measured the same precision as the full time-domain fit from ~1 % of the residuals), and
the harmonics' kernels — aliases included, as the kernel is periodic — are modelled wherever
they fall in the window.

The model is linear in (c, A), so those are projected out (variable projection): the
nonlinear fit is one unknown, the depth offset from the coarse estimate in millimetres
(fitting τ in seconds stalls the optimiser; DESIGN.md §3). A grid of the projected cost
over ±1.5 bins picks the basin of the right likelihood ripple (period c/(2 f̄)) before
Newton's method polishes it (`polish_depth`). float64 throughout: it is ~20 numbers per pixel.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Complex, Float, Int

from ..constants import SPEED_OF_LIGHT_M_PER_S

C = SPEED_OF_LIGHT_M_PER_S
# A polish stops once its step is below this fraction of the pixel's predicted σ (finer steps
# move the depth by noise-irrelevant amounts), and never above 0.1 µm where σ is that small.
STEP_TOLERANCE_SIGMA = 1e-2
STEP_TOLERANCE_FLOOR_MM = 1e-4


def polish_depth(cost, start_mm, *, max_steps: int, tolerance_mm=STEP_TOLERANCE_FLOOR_MM,
                 report_step_limit: bool = False):
    """Minimise a 1-D least-squares cost (depth offset in mm) from a start inside the right
    basin: optimistix Newton on its slope, with the exact second derivative (forward over
    forward). Gauss–Newton drops the residual-curvature term, which at finite SNR makes its
    convergence linear: measured on the 35-frame 10 Hz mode (2560 px), Gauss–Newton took 5.4
    steps on average and 12–16 for the slowest pixel of a batch — and a vmapped solve runs as
    long as its slowest pixel — against 2.2 and 3–5 for Newton, to the same depths (≤ 1e-4 mm).
    Newton finds maxima as readily as minima: check the cost at the result with `descended`
    (the caller evaluates it there anyway). Returns (offset_mm, solver_succeeded, num_steps),
    and with `report_step_limit` also whether it stopped at `max_steps`."""
    slope = lambda x, _: jax.jvp(cost, (x,), (jnp.ones_like(x),))[1]
    solver = optx.Newton(rtol=1e-5, atol=tolerance_mm)
    sol = optx.root_find(slope, solver, start_mm, max_steps=max_steps, throw=False)
    out = sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]
    return out + (sol.result == optx.RESULTS.nonlinear_max_steps_reached,) if report_step_limit else out


def descended(final_cost, ceiling):
    """False where a polish climbed: its final cost exceeds `ceiling`, the cost at a point of
    the start's basin (e.g. its grid point)."""
    return final_cost <= ceiling * (1 + 1e-9) + 1e-300


# three unit phasors (cos, sin) of a tone at a depth: e^{ia}, e^{iθ}, e^{iNa} (`UniformModel.phasors`)
Phasors = tuple


def _cmul(p, q):
    """Product of complex numbers held as (re, im) pairs."""
    return p[0] * q[0] - p[1] * q[1], p[0] * q[1] + p[1] * q[0]


def shift_phasors(phasors: Phasors, rotation: Phasors) -> Phasors:
    return tuple(_cmul(p, r) for p, r in zip(phasors, rotation))


class WindowTables(eqx.Module):
    """Per-pixel constants of the DFT bins k0..k0+W−1: cos and sin of b_k = πk/N, and k."""

    cos_b: Float[Array, " W"]
    sin_b: Float[Array, " W"]
    bins: Float[Array, " W"]


def window_tables(k0: Int[Array, ""], width: int, n: int) -> WindowTables:
    """b_k = πk/N by angle addition from b_{k0}: two float64 cos/sin a pixel, not 2W."""
    step = np.pi * np.arange(width) / n
    k0 = jnp.asarray(k0)
    b0 = jnp.pi * k0.astype(jnp.float64) / n
    c0, s0 = jnp.cos(b0), jnp.sin(b0)
    k = (k0 + jnp.arange(width)).astype(jnp.float64)
    return WindowTables(c0 * np.cos(step) - s0 * np.sin(step), s0 * np.cos(step) + c0 * np.sin(step), k)


def dirichlet_window(x0: Float[Array, ""], tables: WindowTables, n: int) -> Complex[Array, " W"]:
    """Unitary DFT D(x0 − k/N) = (1/√N) Σ_m e^{i2π(x0 − k/N)m} at the window's bins k.

    Closed form e^{iπ(N−1)(x0 − k/N)}·sin(πN(x0 − k/N))/sin(π(x0 − k/N))/√N; the bin's share
    of the phase, e^{−iπ(N−1)k/N}, times the (−1)^k of sin(πN x0 − πk) is exactly e^{iπk/N}
    (no large argument to reduce). At integer x (a tone exactly on a bin) the value is √N;
    that branch is selected without a 0/0 so gradients stay finite."""
    a = jnp.pi * x0
    num = jnp.sin(n * a)
    den = jnp.sin(a) * tables.cos_b - jnp.cos(a) * tables.sin_b  # sin(π(x0 − k/N))
    on_bin = jnp.abs(den) < 1e-9
    safe = jnp.where(on_bin, 1.0, den)
    pre = jnp.exp(1j * (n - 1) * a) / math.sqrt(n)
    general = pre * (tables.cos_b + 1j * tables.sin_b) * (num / safe)
    return jnp.where(on_bin, math.sqrt(n) + 0j, general)


class UniformModel(eqx.Module):
    """What the ML fit needs to know of a uniform sweep and the modulator (float64)."""

    start_hz: float
    step_hz: float
    weights: Float[Array, " K"]  # sideband weights w_0..w_nmax
    system_delay_s: float = 0.0
    num_frames: int = eqx.field(static=True, default=0)

    def sum_angular_frequency_sq(self) -> float:
        """Σ_m (2π f_m)² over the sweep (rad²/s²), the sum in the phase-locked Fisher information."""
        n, f0, df = self.num_frames, self.start_hz, self.step_hz
        return (2 * math.pi) ** 2 * (n * f0**2 + f0 * df * n * (n - 1) + df**2 * (n - 1) * n * (2 * n - 1) / 6)

    def delay(self, depth_m):
        return self.system_delay_s + 2.0 * depth_m / C

    def phasors(self, depth_m) -> Phasors:
        """The first-order phasors at a depth: e^{ia} (a = πΔfτ), e^{iθ} (θ = 2πf₀τ) and
        e^{iNa}, their angles reduced modulo 2π in float64 before the cos/sin."""
        tau = self.delay(depth_m)
        turn = lambda cycles: 2 * jnp.pi * (cycles - jnp.floor(cycles))
        angles = (turn(0.5 * self.step_hz * tau), turn(self.start_hz * tau), turn(0.5 * self.num_frames * self.step_hz * tau))
        return tuple((jnp.cos(v), jnp.sin(v)) for v in angles)

    def rotation(self, delta_m, xp=jnp) -> Phasors:
        """The factors that move `phasors` by `delta_m` of depth: e^{iκδ} for each angle's rate
        κ (rad/m). With xp=np and a fixed δ (the basin grid) they are constants of the
        compiled program."""
        rate_a = 2 * math.pi * self.step_hz / C
        rates = (rate_a, 4 * math.pi * self.start_hz / C, self.num_frames * rate_a)
        return tuple((xp.cos(k * delta_m), xp.sin(k * delta_m)) for k in rates)

    def tone_from_phasors(self, phasors: Phasors, tables: WindowTables, max_order: int | None = None):
        """Real and imaginary parts (each (W,)) of the DFT over the window of
        Σ_{n≥1} 2 w_n cos(2π n f_m τ) (unit amplitude A), from the depth's `phasors`.

        Each order's cosine is e^{iθ}·D(x) + e^{−iθ}·D(−x) (θ = 2π n f_0 τ, x = n Δf τ), with D
        the `dirichlet_window` kernel. The two kernels share their numerator and per-bin phase,
        so the pair is u·e^{ib_k}·(1/sin(πx − b_k) + ū/u·1/sin(πx + b_k)) with u = e^{iθ}·
        e^{iπ(N−1)x}·sin(πNx)/√N, and e^{ib_k} is applied once after the sum over orders.
        Bins where a kernel sits exactly on the tone take their limit √N·e^{±iθ}.

        Order n's phasors are the first order's to the n-th power, and everything is real
        arithmetic: XLA's CPU float64 sin/cos cost more than the rest of a 17-bin window
        together (measured: the projected cost 0.70 µs a pixel with per-order sin/cos in
        complex128, 0.45 µs with per-order cos/sin in reals, ~0.2 µs with powers)."""
        n = self.num_frames
        top = self.weights.shape[0] - 1 if max_order is None else min(max_order, self.weights.shape[0] - 1)
        e_a, e_theta, e_na = phasors
        e_phase = _cmul(_cmul(e_theta, e_na), (e_a[0], -e_a[1]))  # e^{i(θ + (N−1)a)}
        pow_a, pow_theta, pow_na, pow_phase = e_a, e_theta, e_na, e_phase
        acc_re = acc_im = on_re = on_im = 0.0
        for order in range(1, top + 1):
            if order > 1:
                pow_a, pow_theta = _cmul(pow_a, e_a), _cmul(pow_theta, e_theta)
                pow_na, pow_phase = _cmul(pow_na, e_na), _cmul(pow_phase, e_phase)
            weight = self.weights[order]
            w_num = weight * pow_na[1] / math.sqrt(n)  # w_n sin(πNx)/√N
            u_re, u_im = w_num * pow_phase[0], w_num * pow_phase[1]
            p, q = pow_a[1] * tables.cos_b, pow_a[0] * tables.sin_b
            den_pos, den_neg = p - q, p + q  # sin(πx − b_k), sin(πx + b_k)
            on_pos, on_neg = jnp.abs(den_pos) < 1e-9, jnp.abs(den_neg) < 1e-9
            g_pos = jnp.where(on_pos, 0.0, 1 / jnp.where(on_pos, 1.0, den_pos))
            g_neg = jnp.where(on_neg, 0.0, 1 / jnp.where(on_neg, 1.0, den_neg))
            acc_re = acc_re + u_re * (g_pos + g_neg)
            acc_im = acc_im + u_im * (g_pos - g_neg)
            on_amp = weight * math.sqrt(n)
            rot_re, rot_im = on_amp * pow_theta[0], on_amp * pow_theta[1]
            on_re = on_re + jnp.where(on_pos | on_neg, rot_re, 0.0)
            on_im = on_im + jnp.where(on_pos, rot_im, 0.0) - jnp.where(on_neg, rot_im, 0.0)
        c, s = tables.cos_b, tables.sin_b
        return c * acc_re - s * acc_im + on_re, s * acc_re + c * acc_im + on_im

    def tone_column(self, depth_m, tables: WindowTables, max_order: int | None = None) -> Complex[Array, " W"]:
        """`tone_from_phasors` at a depth, as one complex array."""
        re, im = self.tone_from_phasors(self.phasors(depth_m), tables, max_order)
        return re + 1j * im

    def dc_column(self, tables: WindowTables) -> Float[Array, " W"]:
        """DFT of the constant 1 over the window: √N at bin 0, zero elsewhere (real)."""
        return jnp.where(tables.bins == 0, math.sqrt(self.num_frames), 0.0)


def _bin_weights(tables: WindowTables, n: int) -> Float[Array, " W"]:
    """Residual weights: the DC and Nyquist bins of a real sequence are real with twice the
    variance per component, so they get 1/√2."""
    edge = (tables.bins == 0) | (tables.bins == n / 2)
    return jnp.where(edge, 1 / math.sqrt(2), 1.0)


def _solve_normal(g00, g01, g11, r0, r1):
    """(c, A) from the 2×2 normal equations [[g00, g01], [g01, g11]]·(c, A) = (r0, r1)."""
    ridge = 1e-12 * (g00 + g11) + 1e-300
    g00, g11 = g00 + ridge, g11 + ridge
    det = g00 * g11 - g01 * g01
    return jnp.stack([(g11 * r0 - g01 * r1) / det, (g00 * r1 - g01 * r0) / det])


class WindowData(eqx.Module):
    """One pixel's window weighted by the bin weights ω: data y (Re, Im parts) and the DC
    column (real); all (W,). The tone column enters as (Re, Im) parts weighted alike."""

    y_re: Float[Array, " W"]
    y_im: Float[Array, " W"]
    dc: Float[Array, " W"]

    def project(self, tone_re, tone_im):
        """Least-squares (c, A) on [dc, tone] (both ω-weighted) and the residual parts."""
        dc = self.dc
        coef = _solve_normal(dc @ dc, dc @ tone_re, tone_re @ tone_re + tone_im @ tone_im,
                             dc @ self.y_re, tone_re @ self.y_re + tone_im @ self.y_im)
        return coef, self.y_re - dc * coef[0] - tone_re * coef[1], self.y_im - tone_im * coef[1]


class FitResult(eqx.Module):
    depth_m: Float[Array, "..."]
    offset: Float[Array, "..."]
    amplitude: Float[Array, "..."]
    sigma_depth_m: Float[Array, "..."]
    converged: Array
    num_steps: Array
    cost: Float[Array, "..."]
    # False where the tone cancels against the offset (`tone_cancels_offset`) or trades off with it
    # (`variance_inflation` above `MAX_VARIANCE_INFLATION`)
    well_posed: Array


# A fit is ill-posed where the offset and amplitude inflate the depth's variance by more than
# this factor, F_dd·[F⁻¹]_dd (see `variance_inflation`).
MAX_VARIANCE_INFLATION = 4.0


def variance_inflation(f_dd, schur):
    """F_dd·[F⁻¹]_dd = F_dd / (F_dd − F_dr F_rr⁻¹ F_rd): how much not knowing the offset and
    amplitude inflates the depth's variance. ≈ 1 wherever the tone is a tone; it grows without
    bound within about half a bin of depth 0, where the tone flattens into a constant and
    trades off against the offset (noiseless, 3000 and 35 frames alike: 1.06 at 20 mm = 0.8
    bin, 1.5 at 15 mm, 19 at 10 mm, 550 at 5 mm). Measured on the 35-frame 10 Hz mode at low
    reflectance: inliers ≤ 1.014; pixels whose fit slid from a noise peak near DC to ~4 mm
    reported SNR 17–21 dB, amplitudes 3–7× the echo's and errors of ~100 mm (6σ) with
    inflations of 670–1240. Such fits are not valid (`MAX_VARIANCE_INFLATION`)."""
    return jnp.where(schur > 0, f_dd / jnp.where(schur > 0, schur, 1.0), jnp.inf)


def tone_cancels_offset(amplitude_coef, tone_norm_sq, data_norm_sq, factor: float = 4.0):
    """True where the fitted tone (coefficient `amplitude_coef` on a column of squared norm
    `tone_norm_sq`) carries more than `factor` × the data's energy: the tone column has become
    nearly collinear with the offset column (depth → 0, where the tone flattens into a
    constant) and the two cancel with huge coefficients. Seen at 35 frames on a noise peak
    near DC: amplitude 3·10⁵ against ~90 for real echoes, SNR 86 dB, σ 0.2 mm — a wild fit
    that every other check passed. A real echo's tone carries at most the data's energy plus
    noise."""
    return amplitude_coef**2 * tone_norm_sq > factor * data_norm_sq


class PixelFit(eqx.Module):
    """One pixel's fit between its stages (`prepare_pixel`, the polish, `finish_pixel`): the
    ω-weighted window, its tables, the tone's phasors at the coarse depth, the data scale, the
    polish's starts (mm from the coarse depth) and ceilings (`descended`), one per basin
    candidate, and the polish's step tolerance (mm)."""

    data: WindowData
    tables: WindowTables
    omega: Float[Array, " W"]
    base: Phasors
    scale: Float[Array, ""]
    starts_mm: Float[Array, " C"]
    ceilings: Float[Array, " C"]
    tolerance_mm: Float[Array, ""]

    def weighted_tone(self, model: UniformModel, rotation: Phasors, max_order: int | None = None):
        """The ω-weighted tone (Re, Im) with the phasors moved by `rotation` (`UniformModel.rotation`)."""
        re, im = model.tone_from_phasors(shift_phasors(self.base, rotation), self.tables, max_order)
        return re * self.omega, im * self.omega

    def cost_at(self, model: UniformModel, rotation: Phasors, max_order: int | None = None):
        """Projected cost: residual energy after the least-squares (c, A)."""
        _, res_re, res_im = self.data.project(*self.weighted_tone(model, rotation, max_order))
        return res_re @ res_re + res_im @ res_im

    def cost(self, model: UniformModel):
        """The projected cost as a function of the depth offset (mm), every order modelled."""
        return lambda offset_mm: self.cost_at(model, model.rotation(1e-3 * offset_mm))


def prepare_pixel(model: UniformModel, window: Complex[Array, " W"], k0, coarse_depth_m, noise_var, *,
                  grid_half_width_m: float, grid_points: int, candidates: int = 1,
                  grid_max_order: int | None = None) -> PixelFit:
    """The window's data and the basin search: the projected cost on a grid over
    ±grid_half_width around the coarse depth picks where the polish starts. The grid models
    the orders up to `grid_max_order` (all where None)."""
    n = model.num_frames
    tables = window_tables(k0, window.shape[0], n)
    omega = _bin_weights(tables, n)
    scale = jnp.maximum(jnp.max(jnp.abs(window)), 1e-30)
    data = WindowData(jnp.real(window) * omega / scale, jnp.imag(window) * omega / scale,
                      model.dc_column(tables) * omega)
    # the tone at the coarse depth; an offset δ rotates its phasors by e^{iκδ} (`rotation`)
    pix = PixelFit(data, tables, omega, model.phasors(coarse_depth_m), scale, jnp.zeros(candidates),
                   jnp.zeros(candidates), jnp.zeros(()))

    # basin search: projected cost on a grid spanning ±grid_half_width around the coarse
    # depth (its rotations are constants). Where a strong harmonic's alias falls inside the
    # window the fundamental-only cost misjudges the ripples (measured: 6× the full cost at the
    # minima on a 5.1–5.7 GHz sweep), so the grid models every order down to `grid_max_order`
    grid_mm = np.linspace(-1e3 * grid_half_width_m, 1e3 * grid_half_width_m, grid_points)
    grid_rotations = jax.tree.map(jnp.asarray, model.rotation(1e-3 * grid_mm, xp=np))
    costs = jax.vmap(lambda r: pix.cost_at(model, r, grid_max_order))(grid_rotations)
    # polish the best `candidates` local minima of the grid and keep the lowest: where the
    # ripple is narrower than the grid can resolve, the best grid point may sit on the wrong one
    padded = jnp.concatenate([jnp.array([jnp.inf]), costs, jnp.array([jnp.inf])])
    left, right = padded[:-2], padded[2:]
    local_min = (costs <= left) & (costs <= right)
    # rank the minima by the minimum of the cosine through each and its neighbours, not by the
    # grid value: with a signed amplitude the projected cost ripples with period c/(4f̄) (half
    # the likelihood's ripple) as a − b·cos(2π·depth/period + φ), and at high SNR the grid's
    # sampling error (up to half a spacing off the minimum) outweighs the cost difference
    # between adjacent ripples — the wrong ripple would win (measured on a 5.1–5.7 GHz sweep)
    spacing = float(grid_mm[1] - grid_mm[0]) if grid_points > 1 else 1.0
    mean_f = model.start_hz + 0.5 * model.step_hz * (n - 1)
    theta = min(max(2 * math.pi * 1e-3 * spacing / (C / (4 * mean_f)), 1e-3), 3.0)  # grid step in cost phase
    interior = jnp.isfinite(left) & jnp.isfinite(right)
    l_, r_ = jnp.where(interior, left, costs), jnp.where(interior, right, costs)
    b_cos = (l_ + r_ - 2 * costs) / (2 * (1 - math.cos(theta)))
    b_sin = (r_ - l_) / (2 * math.sin(theta))
    amplitude = jnp.hypot(b_cos, b_sin)
    vertex = jnp.where(local_min, costs + b_cos - amplitude, jnp.inf)
    order = jnp.argmin(vertex)[None] if candidates == 1 else jax.lax.top_k(-vertex, candidates)[1]
    shift = jnp.where(amplitude[order] > 0, -jnp.arctan2(b_sin[order], b_cos[order]) / theta, 0.0)  # in spacings
    starts = jnp.asarray(grid_mm)[order] + jnp.clip(shift, -1.0, 1.0) * spacing
    # a polish must not end above its grid point's cost with every order modelled (`descended`)
    if grid_max_order is None or grid_max_order >= model.weights.shape[0] - 1:
        ceilings = costs[order]
    else:
        ceilings = jax.vmap(lambda r: pix.cost_at(model, r))(jax.tree.map(lambda v: v[order], grid_rotations))
    # step tolerance from the closed-form phase-locked bound at the window's peak amplitude
    # (a tone a·cos has unitary DFT peak a·√N/2 on a bin)
    tone_amplitude = 2 * scale / math.sqrt(n)
    sigma_pred_mm = 1e3 * phase_locked_sigma_m(model.sum_angular_frequency_sq(), tone_amplitude, noise_var)
    tolerance_mm = jnp.maximum(STEP_TOLERANCE_FLOOR_MM, STEP_TOLERANCE_SIGMA * sigma_pred_mm)
    return eqx.tree_at(lambda f: (f.starts_mm, f.ceilings, f.tolerance_mm), pix, (starts, ceilings, tolerance_mm))


def finish_pixel(model: UniformModel, pix: PixelFit, coarse_depth_m, noise_var, offsets_mm: Float[Array, " C"],
                 solved: Bool[Array, " C"], num_steps: Int[Array, " C"]) -> FitResult:
    """The fit at the polished depth of each candidate, the best candidate, and its σ from
    the Fisher information."""
    data = pix.data

    def final_fit(offset_mm):
        """The fit at a depth: (c, A), cost, the weighted tone and its derivative in depth
        (one JVP: the Jacobian's depth column)."""
        tone, d_tone_per_mm = jax.jvp(lambda x: pix.weighted_tone(model, model.rotation(1e-3 * x)), (offset_mm,),
                                      (jnp.ones_like(offset_mm),))
        coef, res_re, res_im = data.project(*tone)
        return coef, res_re @ res_re + res_im @ res_im, tone, jax.tree.map(lambda v: 1e3 * v, d_tone_per_mm)

    coefs, finals, tones, d_tones = jax.vmap(final_fit)(offsets_mm)
    oks = solved & descended(finals, pix.ceilings)
    if offsets_mm.shape[0] > 1:
        ranked = jnp.where(jnp.isfinite(finals), finals, jnp.inf)
        # Where ripples are narrower than a bin, (A, τ) and (−A, τ + half a ripple) fit almost
        # equally: the carrier alignment made A·w_0 > 0, so prefer a positive amplitude.
        amps = coefs[:, 1]
        best = jnp.argmin(jnp.where((amps >= 0) | jnp.all(amps < 0), ranked, jnp.inf))
    else:  # one basin: no comparison
        best = 0
    pick = lambda tree: jax.tree.map(lambda leaf: leaf[best], tree)
    offset_mm, ok, steps, coef, cost_final, tone, d_tone = pick((offsets_mm, oks, num_steps, coefs, finals, tones,
                                                                  d_tones))
    depth = coarse_depth_m + 1e-3 * offset_mm
    (t_re, t_im), (dt_re, dt_im) = tone, d_tone
    # Fisher information of (depth, c, A): components of a unitary DFT of white noise of
    # variance σ² carry σ²/2 each (the weights ω already account for DC/Nyquist bins).
    # Jacobian columns (in units of the scaled data): depth A·∂tone/∂depth, offset dc, amplitude tone
    amp = coef[1]
    tone_sq = t_re @ t_re + t_im @ t_im
    f_dd = amp**2 * (dt_re @ dt_re + dt_im @ dt_im)
    f_dc, f_da = amp * (dt_re @ data.dc), amp * (dt_re @ t_re + dt_im @ t_im)
    f_cc, f_ca, f_aa = data.dc @ data.dc, data.dc @ t_re, tone_sq
    # σ² of depth = [F⁻¹]₀₀ = 1/(F₀₀ − F₀ᵣ F_rr⁻¹ F_r0): Schur complement with an explicit 2×2 inverse
    ridge = 1e-12 * (f_cc + f_aa) + 1e-300
    f_cc, f_aa = f_cc + ridge, f_aa + ridge
    det = f_cc * f_aa - f_ca**2
    schur_scaled = f_dd - (f_aa * f_dc**2 - 2 * f_ca * f_dc * f_da + f_cc * f_da**2) / det
    scale = pix.scale
    schur = schur_scaled * scale**2 / (0.5 * jnp.maximum(noise_var, 1e-30))
    sigma = jnp.where(schur > 0, 1 / jnp.sqrt(jnp.maximum(schur, 1e-300)), jnp.inf)
    data_sq = data.y_re @ data.y_re + data.y_im @ data.y_im
    well_posed = ~tone_cancels_offset(amp, tone_sq, data_sq) & (
        variance_inflation(f_dd, schur_scaled) <= MAX_VARIANCE_INFLATION)
    return FitResult(depth, coef[0] * scale, amp * scale, sigma, ok & jnp.isfinite(cost_final), steps,
                     cost_final * scale**2, well_posed)


# The polish runs every pixel of a batch for at most this many Newton steps, then only the
# pixels still going, a few at a time (`STRAGGLER_GROUP`): a vmapped loop runs as long as its
# slowest pixel. Measured on the 35-frame 10 Hz mode (81 920 px): 98.8 % of the pixels
# converge in 2–3 steps and 57 need 4–9, one of those in most 2048-px batches.
FIRST_PASS_STEPS = 3
STRAGGLER_GROUP = 32


def refine_ml_uniform(model: UniformModel, windows, k0, coarse_depth_m, noise_var, *,
                      grid_half_width_m: float, grid_points: int, max_steps: int = 16,
                      candidates: int = 1, grid_max_order: int | None = None,
                      first_pass_steps: int | None = None) -> FitResult:
    """ML depth of a batch of pixels (the leading axis of every array argument) from their DFT
    windows (unitary bins k0..k0+W−1): `prepare_pixel`, the polish, `finish_pixel`.

    The polish (`polish_depth`, up to `max_steps` Newton steps a pixel) runs in two passes:
    every pixel and candidate for `first_pass_steps` (default `FIRST_PASS_STEPS`), then those
    that hit that limit resume where they stopped, `STRAGGLER_GROUP` at a time, for the
    remaining steps. A pixel's result depends on its own data only, never on its batch. The
    straggler pass is a `lax.while_loop`, which reverse-mode differentiation cannot pass through."""
    prep = lambda w, k, d, v: prepare_pixel(model, w, k, d, v, grid_half_width_m=grid_half_width_m,
                                            grid_points=grid_points, candidates=candidates,
                                            grid_max_order=grid_max_order)
    pix = jax.vmap(prep)(windows, k0, coarse_depth_m, noise_var)
    num_pixels = windows.shape[0]
    # one polish per (pixel, candidate), flattened
    owner = jnp.repeat(jnp.arange(num_pixels), candidates)
    starts = pix.starts_mm.reshape(-1)

    def polish(index, start, steps):
        one = jax.tree.map(lambda leaf: leaf[index], pix)
        return polish_depth(one.cost(model), start, max_steps=steps, tolerance_mm=one.tolerance_mm,
                            report_step_limit=True)

    first = min(FIRST_PASS_STEPS if first_pass_steps is None else first_pass_steps, max_steps)
    values, solved, num_steps, at_limit = jax.vmap(lambda i, x: polish(i, x, first))(owner, starts)
    if max_steps > first:
        total = starts.shape[0]
        group = min(STRAGGLER_GROUP, total)

        def resume(state):
            values, solved, num_steps, pending = state
            # `total` marks an empty slot: its polish runs on a clamped index, its writes are dropped
            slots = jnp.nonzero(pending, size=group, fill_value=total)[0]
            idx = jnp.minimum(slots, total - 1)
            v, ok, steps, _ = jax.vmap(lambda i, x: polish(i, x, max_steps - first))(owner[idx], values[idx])
            put = lambda arr, new: arr.at[slots].set(new, mode="drop")
            return (put(values, v), put(solved, ok), put(num_steps, num_steps[idx] + steps),
                    pending.at[slots].set(False, mode="drop"))

        values, solved, num_steps, _ = jax.lax.while_loop(lambda state: jnp.any(state[3]), resume,
                                                          (values, solved, num_steps, at_limit))
    shape = (num_pixels, candidates)
    fin = lambda p, d, v, x, ok, steps: finish_pixel(model, p, d, v, x, ok, steps)
    return jax.vmap(fin)(pix, coarse_depth_m, noise_var, values.reshape(shape), solved.reshape(shape),
                         num_steps.reshape(shape))


# The basin grid leaves out sideband orders whose weight is below this fraction of the
# dominant tone's: a tone of relative amplitude ε left unmodelled adds ε²·(signal energy) to
# every grid cost alike (1e-4 of it at ε = 1 %), far below both the noise near the SNR
# threshold and the differences between ripples at high SNR; the polish models every order.
GRID_MIN_RELATIVE_WEIGHT = 1e-2


def grid_orders(weights) -> int:
    """The highest sideband order the basin grid models (`GRID_MIN_RELATIVE_WEIGHT`)."""
    w = np.abs(np.asarray(weights, np.float64))[1:]
    keep = np.nonzero(w >= GRID_MIN_RELATIVE_WEIGHT * w.max())[0]
    return int(keep.max() + 1)


def grid_for(sweep_bin_depth_m: float, ripple_m: float, half_width_bins: float = 1.0,
             points_per_ripple: int = 6, max_points: int = 257) -> tuple[float, int, int]:
    """Basin search: half-width (m), odd number of grid points, and how many of the grid's
    best local minima to polish (3 where the ripple is narrower than a bin, else 1)."""
    half = half_width_bins * sweep_bin_depth_m
    # the grid must resolve the likelihood's ripple; where the ripple is wider than a bin
    # (0.1–6 GHz: 49 mm vs 25 mm) a quarter-bin spacing already lands in the right basin
    spacing = min(sweep_bin_depth_m / 4, ripple_m / points_per_ripple)
    points = int(min(max_points, 2 * math.ceil(half / spacing) + 1))
    return half, points, (3 if ripple_m < sweep_bin_depth_m else 1)


def crlb_phase_locked_m(frequencies_hz, tone_amplitude, noise_sigma) -> float:
    """Closed-form CRLB (m) of depth for r = c + a·cos(2π f_m τ) + white noise, when the
    tone's phase is locked to τ (uses all f_m): σ_τ² ≈ σ²/(a²/2 · Σ(2π f_m)²) — valid
    when amplitude and offset decouple from τ (many cycles over the sweep)."""
    f = np.asarray(frequencies_hz, np.float64)
    return float(phase_locked_sigma_m(np.sum((2 * np.pi * f) ** 2), tone_amplitude, noise_sigma**2))


def phase_locked_sigma_m(sum_angular_frequency_sq, tone_amplitude, noise_var):
    """`crlb_phase_locked_m` from Σ(2π f_m)² (rad²/s²) and the noise variance (NumPy or JAX)."""
    return C / 2 / (0.5 * tone_amplitude**2 * sum_angular_frequency_sq / noise_var) ** 0.5


def crlb_frequency_only_m(num_frames: int, step_hz: float, tone_amplitude, noise_sigma, order: int = 1):
    """Closed-form CRLB (m) of depth from the tone's frequency alone (real sinusoid,
    unknown amplitude and phase; Kay, Example 3.14): var(ω) = 24σ²/(a²·N(N²−1)), ω in rad/frame."""
    n = num_frames
    var_omega = 24 * noise_sigma**2 / (tone_amplitude**2 * n * (n**2 - 1))
    return jnp.sqrt(var_omega) / (2 * np.pi * order * step_hz) * C / 2
