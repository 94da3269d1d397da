"""NumPy on the host, jax.numpy under tracing: one namespace for a function's inputs.

Small host-side computations (the I/Q weights of a hybrid, a modulator's sideband weights at
one frequency, a survey of 256 pixels) run once per process. Through jax.numpy each
operation is a program of its own to trace, lower and compile or load: in a fresh process ~70
of them cost ~0.6 s before the first pixel (docs/performance.md). The same code in NumPy costs
microseconds; under `jit`, `grad` or `vmap` (any input a JAX array or tracer) it stays JAX."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def namespace(*values):
    """`jax.numpy` if any value is a JAX array (a tracer included), else `numpy`."""
    return jnp if any(isinstance(v, jax.Array) for v in jax.tree.leaves(values)) else np
