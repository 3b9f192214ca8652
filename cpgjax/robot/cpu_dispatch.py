"""Run JAX's CPU computations on the calling thread (``jax_cpu_enable_async_dispatch = False``).

Two parts of cpgjax make one small JAX call per 1 ms control tick: the native backend's controller step and the
robot loop's compiled controller. With JAX's default asynchronous CPU dispatch each call is handed to an XLA worker
thread and the caller blocks until it is done: on a busy 2-core machine the hand-off costs more than the computation
(docs/backends.md), and on the robot the loop thread (real-time priority) waits for a worker at normal priority, a
priority inversion that a loaded machine turns into milliseconds. MJX rollouts are unaffected (one call per trial).
"""

from __future__ import annotations

import jax

from cpgjax import jax_internals


def request_inline() -> bool:
    """Ask for inline CPU dispatch; return whether it is in effect.

    JAX reads the setting once, when it creates its CPU client at the first computation, so call this at program
    start. Called after JAX has computed anything it returns False (unless the setting was already off): the client
    keeps dispatching asynchronously. Process-wide.
    """
    # jax.config holds only the flag, which the client reads when it is created; whether it exists yet no public API
    # tells without creating it (cpgjax.jax_internals).
    was_inline = not jax.config.read("jax_cpu_enable_async_dispatch")
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    return was_inline or not jax_internals.cpu_client_exists()
