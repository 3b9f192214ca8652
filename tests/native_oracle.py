"""The reference the native backend's steppings are checked against: :class:`RolloutPhysics`, the batch stepped by
one ``mujoco.rollout`` call per physics step (``nstep=1``) into a second state buffer.

``mujoco.rollout`` runs MuJoCo's own ``mj_step`` on each instance's model from the state, controls and warm start it
is given, with nothing of cpgjax's in between, so the steppings of ``cpgjax.sim.native_physics`` must equal it bit
for bit (docs/backends.md, "The `ffi` stepping"). It is ``BatchPhysics`` in everything but the step itself: the same
models, standing states, failure test and warm start recovered from the states.
"""

from __future__ import annotations

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from cpgjax.go1 import model as go1_model
from cpgjax.sim import native_physics

STEPPING = "rollout"  # the reference's name where tests list steppings beside native_physics.STEPPINGS


class RolloutPhysics(native_physics.BatchPhysics):
    """``native_physics.BatchPhysics`` whose physics step is ``mujoco.rollout``'s; it takes BatchPhysics's
    arguments (``stepping`` is ignored), so that it can stand in for it, e.g. inside a ``NativeBackend``, whose
    per-tick loop then drives it."""

    def __init__(
        self,
        scenario: go1_model.Scenario,
        *,
        nthread: int | None = None,
        stepping: str | None = None,
        stand_foot_shift_m: np.ndarray | None = None,
    ):
        del stepping
        self.stepping = STEPPING
        self._set_up_standing(scenario, nthread, stand_foot_shift_m)
        m, batch = self.models[0], scenario.batch_size
        self.sensordata = self.standing_sensordata.copy()
        self._chunk = -(-batch // self.nthread)  # one contiguous chunk per thread: least pool overhead
        self._pool = mj_rollout.Rollout(nthread=self.nthread if self.nthread > 1 else 0)
        self._data = [mujoco.MjData(m) for _ in range(self.nthread)]
        self.physics = self.standing_physics.copy()
        self._next = np.empty_like(self.physics)
        self._ctrl = np.zeros((batch, m.nu))
        self.warmstart = np.zeros((batch, m.nv))

    def _integrate(self) -> tuple[np.ndarray, np.ndarray]:
        """One ``mujoco.rollout`` step of every instance from ``physics`` into the other buffer, which becomes
        ``physics``: the states (before, after)."""
        before, after = self.physics, self._next
        self._pool.rollout(
            self.models,
            self._data,
            before,
            self._ctrl,
            control_spec=mujoco.mjtState.mjSTATE_CTRL.value,
            skip_checks=True,
            nstep=1,
            initial_warmstart=self.warmstart,
            state=after,
            sensordata=self.sensordata,
            chunk_size=self._chunk,
        )
        self.physics, self._next = after, before
        return before, after

    def close(self) -> None:
        """Release the thread pool."""
        self._pool.close()


def batch_physics(scenario: go1_model.Scenario, stepping: str, **kwargs) -> native_physics.BatchPhysics:
    """``native_physics.BatchPhysics`` with ``stepping``, or the reference where it is :data:`STEPPING`."""
    if stepping == STEPPING:
        return RolloutPhysics(scenario, **kwargs)
    return native_physics.BatchPhysics(scenario, stepping=stepping, **kwargs)
