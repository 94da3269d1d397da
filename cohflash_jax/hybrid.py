"""Free-space 90° optical hybrid onto four CCDs: port signals and the I/Q combination."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .xp import namespace

NOMINAL_PHASES_RAD = (0.0, np.pi / 2, np.pi, 3 * np.pi / 2)


class Hybrid(eqx.Module):
    """Per-CCD hybrid phase θ_k (rad), relative gain g_k and offset o_k (DN).

    The gauge is CCD 1: its phase error and gain error are zero by convention
    (only differences between CCDs are observable).
    """

    phases_rad: Float[ArrayLike, "4"] = NOMINAL_PHASES_RAD
    relative_gains: Float[ArrayLike, "4"] = (1.0, 1.0, 1.0, 1.0)
    offsets_dn: Float[ArrayLike, "4"] = (0.0, 0.0, 0.0, 0.0)

    def __check_init__(self):
        for name in ("phases_rad", "relative_gains", "offsets_dn"):
            shape = np.shape(getattr(self, name))
            if shape != (4,):
                raise ValueError(f"Hybrid.{name} must have shape (4,), got {shape}")
        g = self.relative_gains
        if isinstance(g, (tuple, list, np.ndarray)) and not np.all(np.asarray(g) > 0):
            raise ValueError("Hybrid.relative_gains must be positive")

    def port_electrons(self, common_e, coherent_e) -> Float[Array, "4 ..."]:
        """n_k = common/4 + ½·Re(coherent·e^{iθ_k}) for the four ports.

        Inputs carry a leading CCD axis of length 1 (all CCDs see the same pixel) or 4.
        `common_e` holds everything split equally over the ports (reference and echo
        intensity, background, …); `coherent_e` is √N_l·Σ_r α_r·S(ψ_r), so a single
        return gives ¼[(N_l+N_e)S_0 + 2√(N_l N_e)·S·cos(φ+θ_k)] (docs/design-reference.md §1).
        """
        coherent_e = jnp.asarray(coherent_e)
        theta = jnp.asarray(self.phases_rad).reshape((4,) + (1,) * (coherent_e.ndim - 1))
        rotated = jnp.real(coherent_e) * jnp.cos(theta) - jnp.imag(coherent_e) * jnp.sin(theta)
        return 0.25 * jnp.asarray(common_e) + 0.5 * rotated

    def iq_weights(self) -> Float[Array, "2 4"]:
        """Rows giving (I, Q) from gain- and offset-corrected port signals.

        Least squares of v_k = C/4 + ½(I cos θ_k − Q sin θ_k) for (C, I, Q); the common
        term C is estimated and discarded, so common-mode signals cancel for any four
        distinct phases. Nominal phases give I = v_0 − v_2, Q = v_3 − v_1.
        """
        xp = namespace(self.phases_rad)
        theta = xp.asarray(self.phases_rad, dtype=xp.float64)
        design = xp.stack([xp.full(4, 0.25), 0.5 * xp.cos(theta), -0.5 * xp.sin(theta)], axis=1)
        return xp.linalg.pinv(design)[1:]

    def iq_matrix_dn(self, dn_per_electron: float = 1.0) -> tuple[Array, Array]:
        """(W, b) with [I, Q] = W @ DN + b in electrons, folding per-CCD gain and offset."""
        xp = namespace(self.phases_rad, self.relative_gains, self.offsets_dn, dn_per_electron)
        weights = self.iq_weights()
        gains = xp.asarray(self.relative_gains, dtype=xp.float64) * dn_per_electron
        w = weights / gains[None, :]
        b = -w @ xp.asarray(self.offsets_dn, dtype=xp.float64)
        return w, b

    def conditioning(self) -> float:
        """Condition number of the I/Q design: large when hybrid phases nearly coincide."""
        theta = np.asarray(self.phases_rad, dtype=np.float64)
        design = np.stack([np.full(4, 0.25), 0.5 * np.cos(theta), -0.5 * np.sin(theta)], axis=1)
        return float(np.linalg.cond(design))
