"""What JAX does while a block runs, counted from its monitoring events (no private API)."""

import contextlib

import jax

TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"


@contextlib.contextmanager
def traces_counted():
    """The programs JAX traces inside the block, one event each (a jitted call traced before
    traces nothing): a list that grows while the block runs."""
    traced = []
    listen = lambda event, duration, **_: traced.append(event) if event == TRACE_EVENT else None
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield traced
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
