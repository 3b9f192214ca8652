"""The interface of every physics backend: :class:`Backend`, which the MJX backend (``cpgjax.mjx_go1.MJXBackend``) and
the native one (``cpgjax.sim.native.NativeBackend``) declare, and ``cpgjax.sim.backends.make_backend`` returns.

The lockstep engine (``cpgjax.ablation``), the studies' evaluations and rollouts (``cpgjax.studies.registry``) and
``cpgjax walk`` (``cpgjax.sim.walk``) use a backend through this interface only. A new backend subclasses
:class:`Backend` (its abstract members must then all be defined) and runs the shared trial of
``cpgjax.trial.protocol``, so that its records mean what every other backend's mean.

What holds for every member:

* A backend simulates a batch of B Go1s, instance i under ``scenario``'s i-th entry; every array in or out has the
  leading batch axis B.
* Parameters are (B, 8) in physical units, ordered as ``cpgjax.trial.params.PARAM_NAMES``. They are validated on
  entry (``protocol.check_params``): a wrong shape, a non-finite value or one outside the box raises ``ValueError``
  before any simulation.
* Gates are a ``cpg.Gates`` of (B,) module gates and (B, 4, 4) phase lags (``protocol.batch_gates``), which select
  the controller and the gait per instance.
* The simulator state is the backend's own pytree, opaque to callers but for what the engine's checkpoint needs: every
  leaf is an array with the leading batch axis, and a leaf that is a NumPy array in the state ``reset`` returns is one
  in every state (a checkpointed state is restored into ``reset``'s structure, NumPy leaves as NumPy and the others as
  JAX arrays, which the backend places on its devices).
* A state given to :meth:`Backend.trial` is consumed (the MJX backend donates its buffers): continue from the state it
  returns.
* An instance that falls or whose state stops being finite is put back standing at the end of its trial and its record
  says so (``fell``, ``failed``); the other instances are not affected.
"""

from __future__ import annotations

import abc
from typing import Any, Protocol, runtime_checkable

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.trial import protocol


@runtime_checkable
class Backend(Protocol):
    """A batch of simulated Go1s behind the paper's trial (the module docstring states the conventions).

    >>> state = sim.reset(params)                                # params (B, 8)
    >>> state, record = sim.trial(state, new_params, gates)      # protocol.TrialRecord of (B, ...) arrays
    """

    name: str  # which backend: "mjx" or "native" (one of cpgjax.sim.backends.BACKENDS but "auto")
    scenario: go1_model.Scenario  # the batch's conditions, one entry per instance
    cpg_config: cpg.CPGConfig  # the controller's static configuration
    trial_config: protocol.TrialConfig  # the trial's timing (transition and steady ticks)

    @property
    @abc.abstractmethod
    def batch_size(self) -> int:
        """B, the number of instances (``scenario.batch_size``)."""

    @abc.abstractmethod
    def reset(self, params, gates: cpg.Gates | None = None) -> Any:
        """Every instance standing at rest at the origin with its CPG at rest in its gait's phases (``gates``' phase
        lags; None: the trot); ``params`` (B, 8) become the previous parameters, which the next trial's transition
        starts from. Returns the state."""

    @abc.abstractmethod
    def trial(self, state, new_params, gates: cpg.Gates) -> tuple[Any, protocol.TrialRecord]:
        """One trial of every instance from ``state`` (consumed): the transition from the state's parameters to
        ``new_params`` (B, 8), then the steady phase with ``new_params``. Returns the next state (with ``new_params``
        as its parameters) and the trial records (``protocol.TrialRecord`` of (B, ...) arrays)."""

    @abc.abstractmethod
    def rollout(self, state, params, gates: cpg.Gates, num_steps: int) -> tuple[Any, protocol.StepLog]:
        """``num_steps`` control ticks of every instance with constant ``params`` (B, 8), logging every tick (no
        trial record; an instance that falls is not put back standing). Returns the state after them and the log
        (``protocol.StepLog`` of (B, num_steps, ...) arrays)."""

    @abc.abstractmethod
    def with_scenario(self, scenario: go1_model.Scenario) -> Backend:
        """This backend for another batch of scenarios of the same batch size, reusing what it compiled (a scenario
        reaches the compiled code as data). A state of this backend carries over unchanged to the one returned; use
        the returned backend from then on (the native backend releases this one's thread pool)."""
