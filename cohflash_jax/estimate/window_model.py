"""The phase-locked tone of a uniform sweep over a window of DFT bins, in closed form.

Model of the carrier-aligned sequence: r[m] = c + A·Σ_{n≥1} 2 w_n cos(2π n f_m τ) + noise,
where w_n are the sideband weights and c absorbs A·w_0 and any offset. For a uniform sweep
f_m = f_0 + mΔf, the unitary DFT of each tone is a Dirichlet kernel in closed form, so a fit
can use only the W ≈ 17 bins around the peak (white noise stays white), with the harmonics'
kernels — aliases included, as the kernel is periodic — wherever they fall in the window.
The model is linear in (c, A), which are projected out (variable projection).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..fisher import sum_angular_frequency_sq_uniform
from ..runtime import compiling_quick

# three unit phasors (cos, sin) of a tone at a depth: e^{ia}, e^{iθ}, e^{iNa} (`UniformModel.phasors`)
Phasors = tuple


def computed_once(values):
    """`values` (a pytree of arrays) unchanged, each computed once per element. XLA's CPU
    fusion otherwise recomputes a per-pixel value inside every kernel that spreads it over the
    window's bins or the basin grid: the inversion's 10 float64 sines and cosines became 113
    each, every one evaluated per bin, and XLA drops optimisation barriers before it fuses. A
    product with a constant, [x, 0]·[1, 0] = x (exactly, but for a negative zero's sign; a NaN
    or an infinity stays in its own element), is not fused into elementwise kernels, so each
    value is computed once and read where it is used (docs/performance.md). Other backends get
    `values` as they are."""
    if jax.default_backend() != "cpu":
        return values
    leaves, tree = jax.tree.flatten(values)

    def once(x):  # x (K, ...): K values of one shape and type, in one product
        unit = jnp.array([1.0, 0.0], x.dtype)
        return jnp.matmul(jnp.stack([x, jnp.zeros_like(x)], axis=-1), unit, precision=jax.lax.Precision.HIGHEST)

    if len({(jnp.shape(x), jnp.result_type(x)) for x in leaves}) == 1:
        return jax.tree.unflatten(tree, list(once(jnp.stack(leaves))))
    return jax.tree.unflatten(tree, [once(jnp.asarray(x)[None])[0] for x in leaves])


def cmul(p, q):
    """Product of complex numbers held as (re, im) pairs."""
    return p[0] * q[0] - p[1] * q[1], p[0] * q[1] + p[1] * q[0]


def shift_phasors(phasors: Phasors, rotation: Phasors) -> Phasors:
    return tuple(cmul(p, r) for p, r in zip(phasors, rotation))


def powers(z, top: int):
    """z¹ … z^top of a complex number held as a (re, im) pair, each part stacked on a leading
    axis (top,): by repeated products, not cos/sin of multiples of its angle."""
    out = [z]
    for _ in range(top - 1):
        out.append(cmul(out[-1], z))
    return jnp.stack([v[0] for v in out]), jnp.stack([v[1] for v in out])


# Jets: a quantity and its derivatives in one unknown, (value, first, second), truncated to
# the derivatives asked for; constants multiply them as `jet_scale`.


def phasor_jet(z, rate, derivatives: int):
    """Jets of Re and Im of a unit phasor z = (cos, sin) turning at `rate`: z, iφz, −φ²z."""
    re, im = z
    terms = ((re, im), (-rate * im, rate * re), (-(rate**2) * re, -(rate**2) * im))[: derivatives + 1]
    return tuple(t[0] for t in terms), tuple(t[1] for t in terms)


def jet_add(a, b):
    return tuple(x + y for x, y in zip(a, b))


def jet_sub(a, b):
    return tuple(x - y for x, y in zip(a, b))


def jet_scale(constant, a):
    return tuple(constant * x for x in a)


def jet_mul(a, b):
    """Leibniz's rule: (ab)′ = a′b + ab′, (ab)″ = a″b + 2a′b′ + ab″."""
    out = (a[0] * b[0],)
    if len(a) > 1:
        out += (a[1] * b[0] + a[0] * b[1],)
    if len(a) > 2:
        out += (a[2] * b[0] + 2 * a[1] * b[1] + a[0] * b[2],)
    return out


def jet_reciprocal(a, zero_where):
    """1/a, (1/a)′ = −a′/a², (1/a)″ = 2a′²/a³ − a″/a²; zero where `zero_where` (no 0/0, so
    gradients stay finite)."""
    g = jnp.where(zero_where, 0.0, 1 / jnp.where(zero_where, 1.0, a[0]))
    out = (g,)
    if len(a) > 1:
        out += (-a[1] * g * g,)
    if len(a) > 2:
        out += ((2 * a[1] * a[1] * g - a[2]) * g * g,)
    return out


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
    c0, s0 = computed_once((jnp.cos(b0), jnp.sin(b0)))
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
        return sum_angular_frequency_sq_uniform(self.num_frames, self.start_hz, self.step_hz)

    def delay(self, depth_m):
        return self.system_delay_s + 2.0 * depth_m / C

    def phasors(self, depth_m) -> Phasors:
        """The first-order phasors at a depth: e^{ia} (a = πΔfτ), e^{iθ} (θ = 2πf₀τ) and
        e^{iNa}, their angles reduced modulo 2π in float64 before the cos/sin."""
        tau = self.delay(depth_m)
        turn = lambda cycles: 2 * jnp.pi * (cycles - jnp.floor(cycles))
        angles = (
            turn(0.5 * self.step_hz * tau),
            turn(self.start_hz * tau),
            turn(0.5 * self.num_frames * self.step_hz * tau),
        )
        return computed_once(tuple((jnp.cos(v), jnp.sin(v)) for v in angles))

    def rotation(self, delta_m, xp=jnp) -> Phasors:
        """The factors that move `phasors` by `delta_m` of depth: e^{iκδ} for each angle's rate
        κ (rad/m). With xp=np and a fixed δ (the basin grid) they are constants of the
        compiled program."""
        rotation = tuple((xp.cos(k * delta_m), xp.sin(k * delta_m)) for k in self.angle_rates())
        return rotation if xp is np else computed_once(rotation)

    def angle_rates(self) -> tuple[float, float, float]:
        """How fast the three `phasors`' angles turn with depth (rad/m): a = πΔfτ, θ = 2πf₀τ
        and Na, with τ = 2·depth/c."""
        rate_a = 2 * math.pi * self.step_hz / C
        return rate_a, 4 * math.pi * self.start_hz / C, self.num_frames * rate_a

    def tone_from_phasors(self, phasors: Phasors, tables: WindowTables, max_order: int | None = None):
        """Real and imaginary parts (each (W,)) of the DFT over the window of
        Σ_{n≥1} 2 w_n cos(2π n f_m τ) (unit amplitude A), from the depth's `phasors`
        (`tone_jets` without derivatives)."""
        (re,), (im,) = self.tone_jets(phasors, tables, max_order)
        return re, im

    def tone_jets(
        self,
        phasors: Phasors,
        tables: WindowTables,
        max_order: int | None = None,
        rates: tuple[float, float, float] | None = None,
        derivatives: int = 0,
    ):
        """The tone's real and imaginary parts as jets (value, first, second derivative; up to
        `derivatives`) in an offset along which the phasors' angles turn at `rates` (rad per
        unit of offset: `angle_rates` scaled to the offset's unit).

        Each order's cosine is e^{iθ}·D(x) + e^{−iθ}·D(−x) (θ = 2π n f_0 τ, x = n Δf τ), with D
        the `dirichlet_window` kernel. The two kernels share their numerator and per-bin phase,
        so the pair is u·e^{ib_k}·(1/sin(πx − b_k) + ū/u·1/sin(πx + b_k)) with u = e^{iθ}·
        e^{iπ(N−1)x}·sin(πNx)/√N, and e^{ib_k} is applied once after the sum over orders.
        Bins where a kernel sits exactly on the tone take their limit √N·e^{±iθ}.

        Order n's phasors are the first order's to the n-th power, and everything is real
        arithmetic: XLA's CPU float64 sin/cos cost more than the rest of a 17-bin window
        together (docs/performance.md). A phasor turning at rate φ has derivatives iφ·z and
        −φ²·z, so the derivatives come in closed form: the polish's Newton steps need the
        second, and forward-over-forward differentiation of the tone made that program
        several times the size for XLA to compile."""
        n = self.num_frames
        top = self.weights.shape[0] - 1 if max_order is None else min(max_order, self.weights.shape[0] - 1)
        rate_a, rate_theta, rate_na = rates if rates is not None else (0.0, 0.0, 0.0)
        e_a, e_theta, e_na = phasors
        e_phase = cmul(cmul(e_theta, e_na), (e_a[0], -e_a[1]))  # e^{i(θ + (N−1)a)}
        jet = lambda z, rate: phasor_jet(z, rate, derivatives)

        def orders_terms(pow_a, pow_theta, pow_na, pow_phase, order, weight):
            """The window terms of the orders `order` (phasors to that power, weights w_n):
            the kernels' sum and difference times u, and the on-bin limits, as jets."""
            a_re, a_im = jet(pow_a, order * rate_a)
            _, na_im = jet(pow_na, order * rate_na)
            phase_re, phase_im = jet(pow_phase, order * (rate_theta + rate_na - rate_a))
            w_num = jet_scale(weight / math.sqrt(n), na_im)  # w_n sin(πNx)/√N
            u_re, u_im = jet_mul(w_num, phase_re), jet_mul(w_num, phase_im)
            p, q = jet_scale(tables.cos_b, a_im), jet_scale(tables.sin_b, a_re)
            den_pos, den_neg = jet_sub(p, q), jet_add(p, q)  # sin(πx − b_k), sin(πx + b_k)
            on_pos, on_neg = jnp.abs(den_pos[0]) < 1e-9, jnp.abs(den_neg[0]) < 1e-9
            g_pos, g_neg = jet_reciprocal(den_pos, on_pos), jet_reciprocal(den_neg, on_neg)
            rot_re, rot_im = (jet_scale(weight * math.sqrt(n), v) for v in jet(pow_theta, order * rate_theta))
            on_either = on_pos | on_neg
            return (
                jet_mul(u_re, jet_add(g_pos, g_neg)),
                jet_mul(u_im, jet_sub(g_pos, g_neg)),
                tuple(jnp.where(on_either, v, 0.0) for v in rot_re),
                tuple(jnp.where(on_pos, v, 0.0) - jnp.where(on_neg, v, 0.0) for v in rot_im),
            )

        if compiling_quick():
            # every order at once on a leading axis (K, W), summed over the orders: one copy
            # of the arithmetic, which XLA's lowest optimisation level compiles much faster
            # than the loop below. Optimised code runs slower so: the sums over the orders
            # split what the loop's additions keep in one fused pass (docs/performance.md)
            column = lambda z: tuple(v[:, None] for v in powers(z, top))
            terms = orders_terms(
                column(e_a),
                column(e_theta),
                column(e_na),
                column(e_phase),
                np.arange(1, top + 1, dtype=np.float64)[:, None],
                self.weights[1 : top + 1, None],
            )
            acc_re, acc_im, on_re, on_im = (tuple(jnp.sum(v, axis=0) for v in jets) for jets in terms)
        else:
            pow_a, pow_theta, pow_na, pow_phase = e_a, e_theta, e_na, e_phase
            acc_re = acc_im = on_re = on_im = (0.0,) * (derivatives + 1)
            for order in range(1, top + 1):
                if order > 1:
                    pow_a, pow_theta = cmul(pow_a, e_a), cmul(pow_theta, e_theta)
                    pow_na, pow_phase = cmul(pow_na, e_na), cmul(pow_phase, e_phase)
                terms = orders_terms(pow_a, pow_theta, pow_na, pow_phase, order, self.weights[order])
                acc_re, acc_im, on_re, on_im = (jet_add(a, b) for a, b in zip((acc_re, acc_im, on_re, on_im), terms))
        c, s = tables.cos_b, tables.sin_b
        re = tuple(c * ar - s * ai + o for ar, ai, o in zip(acc_re, acc_im, on_re))
        im = tuple(s * ar + c * ai + o for ar, ai, o in zip(acc_re, acc_im, on_im))
        return re, im

    def tone_column(self, depth_m, tables: WindowTables, max_order: int | None = None) -> Complex[Array, " W"]:
        """`tone_from_phasors` at a depth, as one complex array."""
        re, im = self.tone_from_phasors(self.phasors(depth_m), tables, max_order)
        return re + 1j * im

    def dc_column(self, tables: WindowTables) -> Float[Array, " W"]:
        """DFT of the constant 1 over the window: √N at bin 0, zero elsewhere (real)."""
        return jnp.where(tables.bins == 0, math.sqrt(self.num_frames), 0.0)


def bin_weights(tables: WindowTables, n: int) -> Float[Array, " W"]:
    """Residual weights: the DC and Nyquist bins of a real sequence are real with twice the
    variance per component, so they get 1/√2."""
    edge = (tables.bins == 0) | (tables.bins == n / 2)
    return jnp.where(edge, 1 / math.sqrt(2), 1.0)


def solve_normal_2x2(g00, g01, g11, r0, r1):
    """(c, A) from the 2×2 normal equations [[g00, g01], [g01, g11]]·(c, A) = (r0, r1), ridged so
    a vanishing column gives a zero coefficient, not NaN."""
    ridge = 1e-12 * (g00 + g11) + 1e-300
    g00, g11 = g00 + ridge, g11 + ridge
    det = g00 * g11 - g01 * g01
    return jnp.stack([(g11 * r0 - g01 * r1) / det, (g00 * r1 - g01 * r0) / det])


def gram_matrix(vectors) -> Float[Array, "K K"]:
    """Gram matrix of `vectors`, each a (Re, Im) pair of equal-length arrays (Im None for a
    real one): every inner product a fit needs, each computed once (the upper triangle)."""
    dot = lambda u, v: u[0] @ v[0] + (u[1] @ v[1] if u[1] is not None and v[1] is not None else 0.0)
    upper = {(i, j): dot(vectors[i], vectors[j]) for i in range(len(vectors)) for j in range(i, len(vectors))}
    return jnp.stack(
        [jnp.stack([upper[min(i, j), max(i, j)] for j in range(len(vectors))]) for i in range(len(vectors))]
    )


# rows of the Gram matrices the fits build: the DC column, the data, the tone, then the tone's
# first and second derivatives in the unknown
GRAM_DC, GRAM_DATA, GRAM_TONE, GRAM_SLOPE, GRAM_CURVATURE = 0, 1, 2, 3, 4


def projected_coefficients(g):
    """Least-squares (c, A) on [dc, t], from the Gram matrix of (dc, y, t, …) (`GRAM_*` rows)."""
    dc, y, t = GRAM_DC, GRAM_DATA, GRAM_TONE
    return solve_normal_2x2(g[dc, dc], g[dc, t], g[t, t], g[dc, y], g[t, y])


def projected_residual_energy(g, dc_t, y_t, t_t):
    """|y − c·dc − A·t|² at the least-squares (c, A), from the Gram matrix's dc and data rows
    and the tone's products dc·t, y·t, t·t (given apart: `projected_cost_slope_and_curvature`
    moves the tone along its expansion, `time_domain.TimeDomainModel.grid_starts` has them for
    a whole grid). Elementwise: arrays broadcast."""
    dc, y = GRAM_DC, GRAM_DATA
    c, a = solve_normal_2x2(g[dc, dc], dc_t, t_t, g[dc, y], y_t)
    return g[y, y] - 2 * (c * g[dc, y] + a * y_t) + c * c * g[dc, dc] + 2 * c * a * dc_t + a * a * t_t


def projected_cost(g):
    """|y − c·dc − A·t|² at the least-squares (c, A), from the Gram matrix of (dc, y, t)."""
    dc, y, t = GRAM_DC, GRAM_DATA, GRAM_TONE
    return projected_residual_energy(g, g[dc, t], g[y, t], g[t, t])


def projected_cost_slope_and_curvature(g):
    """The projected cost's first and second derivatives in the tone's unknown, from the Gram
    matrix of (dc, y, t, t′, t″) (`GRAM_*` rows). Along the tone's second-order expansion
    t(s) = t + s·t′ + s²/2·t″ the cost has the cost's first two derivatives at s = 0, and each
    product it needs is a polynomial in s over the Gram matrix: scalar arithmetic, where
    differentiating the residuals made a chain of small reductions that XLA compiles as
    dozens of separate kernels."""
    dc, y, t, d1, d2 = GRAM_DC, GRAM_DATA, GRAM_TONE, GRAM_SLOPE, GRAM_CURVATURE

    def along(s):
        dc_t = g[dc, t] + s * (g[dc, d1] + 0.5 * s * g[dc, d2])
        y_t = g[y, t] + s * (g[y, d1] + 0.5 * s * g[y, d2])
        t_t = g[t, t] + s * (2 * g[t, d1] + s * (g[d1, d1] + g[t, d2] + s * (g[d1, d2] + 0.25 * s * g[d2, d2])))
        return projected_residual_energy(g, dc_t, y_t, t_t)  # |y − c·dc − a·t(s)|²

    slope = lambda s: jax.jvp(along, (s,), (jnp.ones_like(s),))[1]
    origin = jnp.zeros_like(g[dc, dc])
    return jax.jvp(slope, (origin,), (jnp.ones_like(origin),))


class WindowData(eqx.Module):
    """One pixel's window weighted by the bin weights ω: data y (Re, Im parts) and the DC
    column (real); all (W,). The tone column enters as (Re, Im) parts weighted alike."""

    y_re: Float[Array, " W"]
    y_im: Float[Array, " W"]
    dc: Float[Array, " W"]

    def gram(self, columns) -> Float[Array, "K K"]:
        """Gram matrix of (dc, y, *columns), each column a weighted complex column as (Re, Im)
        (`gram_matrix`; rows as `GRAM_*`)."""
        return gram_matrix([(self.dc, None), (self.y_re, self.y_im)] + list(columns))

    def project(self, tone_re, tone_im):
        """Least-squares (c, A) on [dc, tone] (both ω-weighted) and the residual parts."""
        dc = self.dc
        coef = solve_normal_2x2(
            dc @ dc,
            dc @ tone_re,
            tone_re @ tone_re + tone_im @ tone_im,
            dc @ self.y_re,
            tone_re @ self.y_re + tone_im @ self.y_im,
        )
        return coef, self.y_re - dc * coef[0] - tone_re * coef[1], self.y_im - tone_im * coef[1]
