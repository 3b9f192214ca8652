"""What cpgjax needs from JAX that JAX's public API does not give, in one place.

- :func:`cpu_client_exists`: whether JAX's CPU client has been created. Inline CPU dispatch
  (``robot.cpu_dispatch``) must be chosen before it exists, and the public calls that would tell
  (``jax.devices()``, ``jax.extend.backend.backends()``) create it.
- :func:`coordinator_client`: the distributed runtime's client, whose key-value store carries a multi-process
  study's trial logs (``study.placement.exchange``). The public all-gathers (``jax.experimental.multihost_utils``) block
  until every process arrives and cannot name a process that never does; the store's timed gets can.

Both read JAX internals (``jax._src``); ``tests/test_jax_internals.py`` fails loudly when a JAX upgrade moves them.
"""

from __future__ import annotations

from jax._src import distributed, xla_bridge


def cpu_client_exists() -> bool:
    """Whether JAX has created its backends (at its first computation or device query)."""
    return xla_bridge.backends_are_initialized()


def coordinator_client():
    """The ``jax.distributed`` client of this process (None before ``jax.distributed.initialize``)."""
    return distributed.global_state.client
