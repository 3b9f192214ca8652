"""The native backend's physics: B C-MuJoCo Go1s stepped together on the CPU (:class:`BatchPhysics`).

One ``MjModel`` variant per instance from ``go1_model.scenario_model``, the whole batch stepped one control tick per
call, in place, on one thread per core: through ``cpgjax.sim.ffi_step`` (C++ on MuJoCo's batch API, callable from a
compiled program) or ``mujoco.batch`` from Python. Its host arrays are allocated once and reused; the solver is
warm-started from the previous step's acceleration as a persistent ``mj_step`` loop would be. The tick program that
drives it (sensors, controller, records) is ``cpgjax.sim.native``.

Non-finite states: C MuJoCo resets an instance itself (``mj_resetData``, time → 0) when it meets a NaN, Inf or
huge value. The simulator clock therefore starts at ``CLOCK_START_S`` after every reset, and a step that does not
advance it by exactly one time step is a failure: the instance is put back to the standing pose and the step
reports it.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import mujoco
import numpy as np
from mujoco import batch as mj_batch

from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.sim import ffi_step

# The simulator clock after a reset [s]. Any value > 0 works: MuJoCo's own reset sets the clock to 0, so a step
# that does not advance it from here by one time step reveals that MuJoCo reset a diverged instance.
CLOCK_START_S = 1.0
_PHYSICS_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS.value  # time, qpos, qvel (the Go1 has no act, mocap, ...)
# How BatchPhysics steps (see there): the FFI step inside one program per trial, or mujoco.batch from Python.
STEPPINGS = ("ffi", "batch")


def default_stepping() -> str:
    """``"ffi"`` where its library builds on this machine (``ffi_step.available``), else ``"batch"``."""
    return "ffi" if ffi_step.available() else "batch"


def available_cores() -> int:
    """CPU cores this process may run on (affinity-aware)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class PhysicsLayout(NamedTuple):
    """Where time, qpos and qvel sit in a ``mjSTATE_FULLPHYSICS`` vector (MuJoCo orders components by bit)."""

    time: int
    qpos: slice
    qvel: slice
    size: int


def physics_layout(model: mujoco.MjModel) -> PhysicsLayout:
    qpos_at = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_TIME.value)
    qvel_at = qpos_at + model.nq
    return PhysicsLayout(
        time=0,
        qpos=slice(qpos_at, qvel_at),
        qvel=slice(qvel_at, qvel_at + model.nv),
        size=mujoco.mj_stateSize(model, _PHYSICS_SPEC),
    )


class BatchPhysics:
    """B C-MuJoCo Go1s (one scenario each) stepped together, one physics step per :meth:`step`.

    The current state lives in host arrays allocated once: ``physics`` (B, nstate), ``sensordata`` (B, nsensordata)
    and ``warmstart`` (B, nv). ``stepping`` chooses how a step runs (``STEPPINGS``; default :func:`default_stepping`):

    - ``"ffi"``: ``ffi_step.Stepper``, MuJoCo's batch API in C (``mjbatch.h``) with this method's host arithmetic in
      C++ (batch_step.cc), its rows and sensor data these arrays; the native backend calls it from inside the
      compiled trial, :meth:`step` from Python;
    - ``"batch"``: ``mujoco.batch.Batch``, whose state rows (``mjSTATE_INTEGRATION``: clock, qpos, qvel,
      warm start, controls, ...) *are* these arrays, stepped in place on a persistent pool of one thread per core
      with one model variant per instance (``set_models``).

    Both warm-start the solver with the step's acceleration recovered from the states, (q̇' − q̇)/h (see
    :meth:`step`), so they run the same arithmetic as each other and as the tests' ``mujoco.rollout`` reference
    (tests/native_oracle.py). Used by the native backend only (the loopback simulated Go1 steps its own
    ``mj_step``).
    """

    def __init__(
        self,
        scenario: go1_model.Scenario,
        *,
        nthread: int | None = None,
        stepping: str | None = None,
        stand_foot_shift_m: np.ndarray | None = None,
    ):
        stepping = default_stepping() if stepping is None else stepping
        if stepping not in STEPPINGS:
            raise ValueError(f"stepping {stepping!r}: allowed {STEPPINGS}")
        self.stepping = stepping
        self._set_up_standing(scenario, nthread, stand_foot_shift_m)
        m, batch = self.models[0], scenario.batch_size
        if stepping == "ffi":
            rows = _RowLayout.of(m, mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_INTEGRATION.value))
            offsets = ffi_step.RowOffsets(
                nphysics=self.layout.size,
                qvel_at=self.layout.qvel.start,
                nv=m.nv,
                warmstart_at=rows.warmstart.start,
                ctrl_at=rows.ctrl.start,
                nsensordata=m.nsensordata,
                substeps=self.substeps,
            )
            self._stepper = ffi_step.Stepper(
                self.models, self.nthread, offsets, self.actuator, self.standing_physics, self.standing_sensordata
            )
            self.physics = self._stepper.rows[:, rows.physics]  # views of the library's arrays
            self.warmstart = self._stepper.rows[:, rows.warmstart]
            self.sensordata = self._stepper.sensordata
            np.copyto(self.physics, self.standing_physics)
            np.copyto(self.sensordata, self.standing_sensordata)
        else:
            self.sensordata = self.standing_sensordata.copy()
            self._batch = mj_batch.Batch(m, batch, nthread=self.nthread)
            self._batch.set_models(self.models)
            rows = _RowLayout.of(m, self._batch.nstate)
            state = self._batch.state
            self.physics = state[:, rows.physics]  # views of the batch's rows: the batch steps them in place
            self.warmstart = state[:, rows.warmstart]
            self._ctrl = state[:, rows.ctrl]
            self._step_sensordata = self._batch.bind("sensordata")  # refreshed by every step
            self._before = np.empty((batch, self.layout.size))  # the state before the step
            np.copyto(self.physics, self.standing_physics)
        self.warmstart[:] = 0.0

    def _set_up_standing(
        self, scenario: go1_model.Scenario, nthread: int | None, stand_foot_shift_m: np.ndarray | None
    ) -> None:
        """What every stepping shares: the instances' models, the physics rate, the thread count and the standing
        states (each instance at rest on its ground, its feet shifted by ``stand_foot_shift_m`` (B,) [m])."""
        self.scenario = scenario
        # Instances with the same scenario share one MjModel (read-only during a step): less memory traffic.
        # (friction, slope, payload, physics) per instance
        keys = list(zip(*(field.tolist() for field in scenario), strict=True))
        unique = {key: go1_model.scenario_model(scenario, keys.index(key)) for key in dict.fromkeys(keys)}
        self.models = [unique[key] for key in keys]
        m = self.models[0]
        self.layout = physics_layout(m)
        substeps = {physics_profiles.get(str(name)).physics_substeps for name in scenario.physics}
        if len(substeps) > 1:
            names = sorted(set(scenario.physics.tolist()))
            raise ValueError(
                f"one batch steps its physics at one rate: profiles {names} take {sorted(substeps)} "
                "physics steps per tick"
            )
        self.substeps = substeps.pop()  # physics steps per step() (per control tick), the torques held
        self.timestep_s = float(m.opt.timestep)  # of one physics step
        self.actuator = go1_model.indices().actuator
        batch = scenario.batch_size
        self.nthread = max(min(available_cores() if nthread is None else nthread, batch), 1)

        self.gravity_mps2 = np.stack([mi.opt.gravity for mi in self.models])  # (B, 3)
        self.total_mass_kg = np.array([mi.body_subtreemass[go1_model.indices().trunk_body] for mi in self.models])
        self.standing_physics = np.empty((batch, self.layout.size))
        self.standing_sensordata = np.empty((batch, m.nsensordata))
        shift = np.zeros(batch) if stand_foot_shift_m is None else np.broadcast_to(stand_foot_shift_m, (batch,))
        for i, mi in enumerate(self.models):  # once per backend, not per tick
            d = mujoco.MjData(mi)
            d.qpos[:] = go1_model.standing_qpos(mi, shift[i])
            mujoco.mj_forward(mi, d)
            d.time = CLOCK_START_S
            mujoco.mj_getState(mi, d, self.standing_physics[i], _PHYSICS_SPEC)
            self.standing_sensordata[i] = d.sensordata

    @property
    def batch_size(self) -> int:
        return self.scenario.batch_size

    @property
    def ffi_handle(self) -> np.ndarray:
        """The stepper's name for ``ffi_step.call`` (the ``ffi`` stepping only)."""
        return self._stepper.handle

    def accounts(self, reset: bool = False) -> np.ndarray | None:
        """The ``ffi`` stepper's per-thread accounts (``ffi_step.Stepper.accounts``); None for the other steppings
        or where the library counts nothing (``ffi_step.request_accounts``)."""
        return self._stepper.accounts(reset) if self.stepping == "ffi" else None

    def set_state(self, physics: np.ndarray, warmstart: np.ndarray, sensordata: np.ndarray) -> None:
        np.copyto(self.physics, physics)
        np.copyto(self.warmstart, warmstart)
        np.copyto(self.sensordata, sensordata)

    def get_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copies of (physics, warmstart, sensordata)."""
        return self.physics.copy(), self.warmstart.copy(), self.sensordata.copy()

    def reset(self, mask: np.ndarray | None = None) -> None:
        """Put the instances selected by ``mask`` (B,) bool (all if None) back to standing at rest."""
        if mask is None:
            mask = np.ones(self.batch_size, bool)
        self.physics[mask] = self.standing_physics[mask]
        self.sensordata[mask] = self.standing_sensordata[mask]
        self.warmstart[mask] = 0.0

    def step(self, torque_nm) -> np.ndarray:
        """One control tick of every instance with joint torques (B, 12) [N·m] in motor order: ``substeps`` physics
        steps, the torques held.

        Returns the (B,) bool mask of instances that diverged during the step; they are already reset to standing.
        """
        if self.stepping == "ffi":
            return self._stepper.step(torque_nm)
        self._ctrl[:, self.actuator] = torque_nm
        failed = np.zeros(self.batch_size, bool)
        for _ in range(self.substeps):
            failed |= self._physics_step(~failed)
        return failed

    def _physics_step(self, live: np.ndarray) -> np.ndarray:
        """One physics step; the instances not ``live`` (failed in an earlier substep, already standing) are stepped
        and put back to standing again. Returns the mask of the instances that failed in it."""
        before, after = self._integrate()
        lay = self.layout
        # MuJoCo checks positions, velocities and accelerations itself and resets a diverged instance (clock → 0)
        # before integrating, so the states it returns are finite and the clock tells which ones it reset.
        failed = np.abs(after[:, lay.time] - before[:, lay.time] - self.timestep_s) > 0.5 * self.timestep_s
        # Euler without implicit damping: qvel' = qvel + h·qacc, so the step's qacc is recovered from the two states
        # and warm-starts the next step in place of MuJoCo's own (which the batch's rows hold here and the tests'
        # mujoco.rollout reference does not return): one formula for every stepping keeps their results equal bit
        # for bit.
        np.subtract(after[:, lay.qvel], before[:, lay.qvel], out=self.warmstart)
        self.warmstart *= 1.0 / self.timestep_s
        if failed.any() or not live.all():
            self.reset(failed | ~live)
        return failed & live

    def _integrate(self) -> tuple[np.ndarray, np.ndarray]:
        """One physics step of every instance by ``mujoco.batch`` from ``_ctrl``, the sensor data refreshed: the
        states (B, nstate) before and after it (``after`` is ``physics``)."""
        before, after = self._before, self.physics
        np.copyto(before, after)
        self._batch.step()
        np.copyto(self.sensordata, self._step_sensordata)
        return before, after

    def close(self) -> None:
        """Release the thread pool (the batch's goes with the object)."""
        if self.stepping == "ffi":
            self._stepper.close()


class _RowLayout(NamedTuple):
    """Where the physics state (``mjSTATE_FULLPHYSICS``), the warm start and the controls sit in a
    ``mujoco.batch`` state row (``mjSTATE_INTEGRATION``; MuJoCo orders components by bit)."""

    physics: slice
    warmstart: slice
    ctrl: slice

    @staticmethod
    def of(model: mujoco.MjModel, nstate: int) -> _RowLayout:
        spec = mujoco.mjtState.mjSTATE_INTEGRATION.value
        if mujoco.mj_stateSize(model, spec) != nstate:
            raise ValueError(
                f"mujoco.batch rows of {nstate} numbers, expected mjSTATE_INTEGRATION's "
                f"{mujoco.mj_stateSize(model, spec)}"
            )

        def at(component: mujoco.mjtState) -> int:  # the size of every component ordered before it
            return mujoco.mj_stateSize(model, spec & (component.value - 1))

        warmstart_at, ctrl_at = at(mujoco.mjtState.mjSTATE_WARMSTART), at(mujoco.mjtState.mjSTATE_CTRL)
        physics_size = mujoco.mj_stateSize(model, _PHYSICS_SPEC)
        if warmstart_at != physics_size:  # e.g. plugin state, which FULLPHYSICS holds and the row keeps further on
            raise ValueError("the model's mjSTATE_FULLPHYSICS is not the start of a mujoco.batch row")
        return _RowLayout(
            physics=slice(0, physics_size),
            warmstart=slice(warmstart_at, warmstart_at + model.nv),
            ctrl=slice(ctrl_at, ctrl_at + model.nu),
        )
