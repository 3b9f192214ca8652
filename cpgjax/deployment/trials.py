"""Online optimization on the robot (the paper's Algorithm 1) inside the 1 kHz loop, and parameter files.

Trials run back to back in robot time (loop ticks): 1.5 s of transition, interpolating the parameters linearly from
the previous set to the new one, then 3 s of steady state whose per-tick signals (leg odometry velocity, power
⟨|τ|, |q̇|⟩, mean foot force, roll, pitch — all from the robot's own sensors) make the trial record; J, CoT and the
context come from ``cpgjax.trial.objective`` as in simulation. The optimizer runs in a separate process
(:func:`_optimizer_worker`), so the 1 kHz loop never waits for it: after a trial the robot keeps walking with the
current parameters until the next proposal arrives (the wait is logged per trial). The worker writes the per-trial
log (``trials.parquet``, ``trials.rrd`` for rerun) and the best parameters (``best_params.json``, which
``cpgjax deploy --params`` replays, :mod:`cpgjax.trial.tuned`).

A safety stop that a gait causes (the tilt stop or the power protection, ``robot.safety.is_gait_trip``) ends the
loop, as every trip does; with a ``recover`` callback :func:`online_optimization` then counts it as the outcome of
the trial being walked, an unsafe one (fallen, J at its minimum, its safety margin that of the stop), lets the
optimizer learn it, asks ``recover`` to put the robot back on its feet (the operator on a real Go1, a reset on the
simulated one) and starts the loop again, whose soft start stands the robot up before the next trial
(docs/decisions.md §17).

The optimizer is anything with ``propose(context) -> params`` and ``observe(params, context, record, objective)``
(:class:`OnlineOptimizer`): the contextual BO of ``cpgjax.optim.bo`` (:class:`BayesianOptimizer`, the default) or
:class:`RandomSearch` (a baseline, and the fast stand-in of the tests).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import multiprocessing
import os
import queue
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax import hardware_io as hio
from cpgjax import outputs
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1.constants import TICK_S
from cpgjax.optim import bo
from cpgjax.optim import config as optimizer_config
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import memory_lock
from cpgjax.robot import safety as go1_safety
from cpgjax.trial import objective, optimizer_setting, protocol, tuned
from cpgjax.trial import params as param_space

# Columns of the steady-phase buffer, taken from the controller's flat output each tick.
log = logging.getLogger(__name__)

RECORDING = "trials.rrd"  # the robot's trials as a rerun recording
OUTPUTS = (outputs.OutputFile(RECORDING, "rerun recording of the robot's trials", outputs.check_recording),)

_SIGNALS = ("v_x", "v_y", "power", "load", "roll", "pitch", "saturated")
# The robot's context normalization: its foot force is calibrated so that the feet carry its weight standing, the
# signal of the go1 physics profile, whose c_load range it takes (docs/decisions.md §3, §11).
CONTEXT_RANGES = optimizer_setting.profile_config(physics_profiles.ROBOT_PROFILE)


class OnlineOptimizer(Protocol):
    """What online optimization needs from an optimizer (runs in the worker process, never in the loop)."""

    def propose(self, context: np.ndarray) -> np.ndarray:
        """Next parameters (8,), physical units, for the context [c_load N, c_slope rad]."""

    def observe(self, params: np.ndarray, context: np.ndarray, record, objective: float) -> None:
        """One finished trial."""

    def warm_up(self, params: np.ndarray, context: np.ndarray, record, objective: float) -> None:
        """Do once, before the robot walks, whatever the first ``observe`` and ``propose`` would do only once
        (compilation), leaving the optimizer's state as it was."""


class RandomSearch:
    """Uniform random proposals in the paper's box (σ_N at the midpoint when Tegotae is off)."""

    def __init__(self, seed: int = 0, tegotae: bool = True):
        self._rng = np.random.default_rng(seed)
        self._active = param_space.active_parameters(tegotae)

    def propose(self, context: np.ndarray) -> np.ndarray:
        return param_space.hold_inactive(
            param_space.from_unit(self._rng.uniform(size=param_space.NUM_PARAMS)), self._active
        )

    def observe(self, params, context, record, objective) -> None:
        pass

    def warm_up(self, params, context, record, objective) -> None:
        pass


class BayesianOptimizer:
    """Adapter from ``cpgjax.optim.bo``'s pure functions (``init`` / ``propose`` / ``observe``, scalar objectives) to
    :class:`OnlineOptimizer`. σ_N is an inactive input when Tegotae is off (docs/decisions.md §13). ``safe``: the safe
    optimizer, learning each trial's safety margin (the tilt stop's, from the IMU; docs/decisions.md §17)."""

    def __init__(self, seed: int, tegotae: bool, safe: bool = False):
        active = param_space.active_parameters(tegotae)
        self._key = jax.random.PRNGKey(seed)
        self._safe = safe
        self._opt = bo.make_optimizer(dataclasses.replace(CONTEXT_RANGES, safe=safe))
        self._state = self._opt.init(active_dims=jnp.asarray(active))

    def propose(self, context: np.ndarray) -> np.ndarray:
        self._key, key = jax.random.split(self._key)
        x, fell_back = self._opt.propose_with_fallback(self._state, jnp.asarray(context, jnp.float32), key)
        if bool(fell_back):
            log.info(
                "no parameters certified safe for context (%.1f N, %.3f rad): the safe trial with the highest "
                "expected margin there is repeated",
                *np.asarray(context, np.float64),
            )
        return np.asarray(x, np.float64)

    def _margin(self, record):
        return jnp.asarray(record.safety_margin, jnp.float32) if self._safe else None

    def observe(self, params, context, record, objective) -> None:
        self._state, _ = self._opt.observe(
            self._state,
            jnp.asarray(params, jnp.float32),
            jnp.asarray(context, jnp.float32),
            jnp.asarray(objective, jnp.float32),
            self._margin(record),
        )

    def warm_up(self, params, context, record, objective) -> None:
        """Compile ``observe`` and ``propose`` on a throwaway state, and the key's split (13.4 s on a 2-core
        machine), before the robot walks: compiled during a trial, they would hold the robot on its old parameters
        and take the CPUs from the loop (and from a simulated robot on the same machine). The state and the key stay
        as they were."""
        state, _ = self._opt.observe(
            self._state,
            jnp.asarray(params, jnp.float32),
            jnp.asarray(context, jnp.float32),
            jnp.asarray(objective, jnp.float32),
            self._margin(record),
        )
        _, key = jax.random.split(self._key)  # as propose splits it (the split and the unpacking are compiled)
        jax.block_until_ready(self._opt.propose_with_fallback(state, jnp.asarray(context, jnp.float32), key))


class OptimizerSpec(NamedTuple):
    """Everything the worker process needs (picklable)."""

    kind: str  # "random" or "bo"
    seed: int
    target_velocity_mps: float
    tegotae: bool
    total_mass_kg: float
    log_dir: str
    tuned_for: dict  # what best_params.json records it was tuned for (cpgjax.trial.tuned.TUNED_FOR)
    dt_s: float = TICK_S
    steady_steps: int = protocol.TrialConfig().steady_steps  # ticks of a trial's steady phase (its record's length)
    cpus: tuple[int, ...] | None = None  # the CPUs the worker may use (None: any); keep it off the loop's CPU
    safe: bool = False  # the safe BO (kind "bo" only; docs/decisions.md §17)


def trial_record(
    signals: np.ndarray,
    total_mass_kg: float,
    dt_s: float = TICK_S,
    timing: protocol.TrialConfig = protocol.TrialConfig(),
) -> protocol.TrialRecord:
    """The trial record of the steady phase's per-tick robot signals (T, len(_SIGNALS)), summarized by
    ``protocol.summarize`` exactly as in simulation.

    A fall ends the run through the safety layer (tilt stop) before a trial completes, so ``fell`` and ``failed``
    are 0 for every completed trial. The safety margin is the tilt stop's, from the IMU's roll and pitch
    (``protocol.safety_margin``: the robot measures neither its trunk's height nor the floor).
    """
    s = jnp.asarray(signals, jnp.float32)
    zero = jnp.zeros(s.shape[0], jnp.float32)
    margin = protocol.safety_margin(timing, s[:, 4], s[:, 5])
    ticks = protocol.Tick(
        velocity_xy_mps=s[:, 0:2],
        power_w=s[:, 2],
        load_n=s[:, 3],
        roll_rad=s[:, 4],
        pitch_rad=s[:, 5],
        saturated=s[:, 6],
        fell=zero,
        failed=zero,
        margin=margin,
    )
    return protocol.summarize(ticks, jnp.float32(total_mass_kg), dt_s, protocol.TransitionSummary.nothing())


class _TrialLog:
    """Per-trial rows → ``trials.parquet`` (rewritten after every trial) and ``trials.rrd`` (rerun)."""

    def __init__(self, log_dir: Path):
        import rerun as rr

        self._rr = rr
        self.dir = log_dir
        self.rows: list[dict] = []
        self._rec = rr.RecordingStream("cpgjax_deploy")
        self._rec.save(str(log_dir / RECORDING))

    def append(self, row: dict) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        self.rows.append(row)
        pq.write_table(pa.Table.from_pylist(self.rows), self.dir / outputs.TRIALS)
        rr, rec = self._rr, self._rec
        rec.set_time("trial", sequence=row["trial"])
        for key in ("objective", "cost_of_transport", "velocity_x_mps", "c_load_n", "c_slope_rad", "wait_s"):
            rec.log(f"trial/{key}", rr.Scalars(row[key]))
        for name in param_space.PARAM_NAMES:
            rec.log(f"params/{name}", rr.Scalars(row[name]))

    def close(self) -> None:
        """Finish the recording (rerun writes its footer on disconnect; `cpgjax show` calls one without it
        truncated)."""
        self._rec.flush()
        self._rec.disconnect()


def trial_row(
    trial: int,
    x: np.ndarray,
    record: protocol.TrialRecord,
    j: float,
    c: np.ndarray,
    seed: int,
    tuned_for: dict,
    safety_stop: str | None = None,
) -> dict:
    """One trial on the robot as a row of its ``trials.parquet``: the columns of a study's where they apply
    (docs/outputs.md). ``safety_stop``: the reason of the stop that ended the trial (an unsafe trial, which fell)."""
    return {
        "trial": trial,
        "seed": seed,
        **tuned_for,
        **param_space.as_dict(x),
        "c_load_n": float(c[0]),
        "c_slope_rad": float(c[1]),
        "objective": float(j),
        "velocity_x_mps": float(np.mean(record.velocity_xy_mps[:, 0])),
        "velocity_y_mps": float(np.mean(record.velocity_xy_mps[:, 1])),
        "cost_of_transport": float(objective.cost_of_transport(record)),
        "roll_std_rad": float(record.roll_std_rad),
        "pitch_std_rad": float(record.pitch_std_rad),
        "saturation_fraction": float(record.saturation_fraction),
        "energy_j": float(record.energy_j),
        "distance_m": float(record.distance_m),
        "total_mass_kg": float(record.total_mass_kg),
        "safety_margin": float(record.safety_margin),
        "fell": safety_stop is not None,
        "failed": False,
        "safety_stop": safety_stop,
    }


def stopped_trial_record(
    signals: np.ndarray,
    stop_margin: float,
    total_mass_kg: float,
    dt_s: float = TICK_S,
    timing: protocol.TrialConfig = protocol.TrialConfig(),
) -> protocol.TrialRecord:
    """The record of a trial that a safety stop ended: fallen, so J is at its minimum (``objective.objective``), and
    its safety margin the worst of its steady ticks (``signals``, possibly none) and of the stop's
    (``stop_margin``, ≤ 0). Its walking figures are those of the steady ticks it walked, NaN without any."""
    if len(signals):
        record = trial_record(signals, total_mass_kg, dt_s, timing)
    else:  # stopped during the transition: nothing was measured
        record = jax.tree.map(
            lambda leaf: jnp.full_like(leaf, jnp.nan),  # every field is a float
            trial_record(np.zeros((1, len(_SIGNALS)), np.float32), total_mass_kg, dt_s, timing),
        )
        record = record._replace(total_mass_kg=jnp.float32(total_mass_kg))
    margin = jnp.fmin(record.safety_margin, jnp.float32(stop_margin))  # fmin: the stop's where nothing was measured
    return record._replace(fell=jnp.float32(1.0), safety_margin=margin)


def stop_margin(result: hio.LoopResult, timing: protocol.TrialConfig = protocol.TrialConfig()) -> float:
    """The safety margin of the stop that ended a loop: the tilt stop's margin (``protocol.safety_margin``) at the
    tick the trip was detected, from the IMU, and at most 0 (a stop is at or beyond a threshold; the power
    protection trips at any tilt)."""
    row = len(result.log.quaternion_wxyz) - (result.ticks - result.trip_tick())  # the log holds the newest ticks
    roll, pitch = go1_safety.tilt_rad(result.log.quaternion_wxyz[row])
    return min(float(protocol.safety_margin(timing, roll, pitch)), 0.0)


def signal_columns() -> np.ndarray:
    """The columns of the controller's flat output that make a trial's per-tick signals (:data:`_SIGNALS`)."""
    column = compiled_controller.OUTPUT.unravel(np.arange(compiled_controller.OUTPUT.size))  # each field's columns
    return np.array([*column.velocity_mps, column.power_w, column.load_n, *column.rpy_rad[:2], column.saturated])


class ReplayTrials:
    """A :class:`~cpgjax.hardware_io.ParamSchedule` replaying one parameter set for ``run_ticks`` ticks, cut into
    back-to-back trials of ``timing`` (its transition, with nothing to blend, settles the gait; then the measured
    steady phase), as ``cpgjax walk`` cuts a walk. Per tick it copies one row of signals into a buffer allocated
    here; :meth:`rows` makes each complete trial's figures after the loop."""

    def __init__(self, params: np.ndarray, run_ticks: int, timing: protocol.TrialConfig = protocol.TrialConfig()):
        self._fixed = hio.FixedParams(params, run_ticks)
        self._timing = timing
        self._columns = signal_columns()
        period = timing.transition_steps + timing.steady_steps
        self._signals = np.zeros((run_ticks // period, timing.steady_steps, len(_SIGNALS)), np.float32)
        self.steady_windows: list[tuple[int, int]] = []  # per complete trial: its steady phase's first, last run tick
        self.trials_done = 0
        self.trial = 0  # the trial being walked (logged per tick)
        self.failure = None  # a replay does not fail (hardware_io.ParamSchedule)

    @property
    def finished(self) -> bool:
        return self._fixed.finished

    def params(self, run_tick: int) -> np.ndarray:
        return self._fixed.params(run_tick)

    def record(self, run_tick: int, out: np.ndarray) -> None:
        self._fixed.record(run_tick, out)
        period = self._timing.transition_steps + self._timing.steady_steps
        steady = run_tick % period - self._timing.transition_steps
        if steady >= 0 and self.trials_done < self._signals.shape[0]:
            self._signals[self.trials_done, steady] = out[self._columns]
            if steady + 1 == self._timing.steady_steps:
                self.steady_windows.append((run_tick - steady, run_tick))
                self.trials_done += 1
                self.trial = self.trials_done

    def rows(
        self, total_mass_kg: float, target_velocity_mps: float, seed: int, tuned_for: dict, dt_s: float = TICK_S
    ) -> list[dict]:
        """Each complete trial's row (:func:`trial_row`): J, velocity, distance, CoT and the context from the
        robot's own sensors, summarized as in simulation."""
        rows = []
        x = np.asarray(self._fixed.params(0), np.float64)
        for trial in range(self.trials_done):
            record = trial_record(self._signals[trial], total_mass_kg, dt_s)
            j = float(objective.objective(record, target_velocity_mps))
            rows.append(
                trial_row(trial, x, record, j, np.asarray(objective.context(record), np.float64), seed, tuned_for)
            )
        return rows


def _evaluate(signals: np.ndarray, spec: OptimizerSpec, observe, trial: int, x: np.ndarray | None = None):
    """A trial's record, objective J, context and the optimizer's (clipped) context, given to ``observe``
    (``OnlineOptimizer.observe``, or ``warm_up`` with trial −1 and the midpoint parameters)."""
    record = trial_record(signals, spec.total_mass_kg, spec.dt_s)
    j = float(objective.objective(record, spec.target_velocity_mps))
    c = np.asarray(objective.context(record), np.float64)
    # docs/decisions.md §11: never silently
    c_gp, messages = optimizer_config.clip_context(CONTEXT_RANGES, c, objective.CONTEXT_NAMES, objective.CONTEXT_UNITS)
    for message in messages if trial >= 0 else ():
        log.warning("trial %d: %s", trial, message)
    observe(param_space.midpoint() if x is None else x, c_gp, record, j)
    return record, j, c, c_gp


def _optimizer_worker(conn, spec: OptimizerSpec) -> None:
    """The optimizer's process: observe each finished trial, answer the next proposal at once, then log."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the loop, which then stops this process
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")  # a line per trial
    os.nice(10)  # the robot's loop (and, on one machine, the simulated robot) come first
    if spec.cpus:
        os.sched_setaffinity(0, spec.cpus)  # before JAX starts its threads (they inherit it)
    jax.config.update("jax_platforms", "cpu")  # before this process's first JAX computation
    optimizer: OnlineOptimizer = (
        BayesianOptimizer(spec.seed, spec.tegotae, spec.safe)
        if spec.kind == "bo"
        else RandomSearch(spec.seed, spec.tegotae)
    )
    _, _, _, c_gp = _evaluate(np.zeros((spec.steady_steps, len(_SIGNALS)), np.float32), spec, optimizer.warm_up, -1)
    # Idle while each trial walks: unlocked, its pages were evicted and the next proposal waited on the disk.
    log.info("optimizer process: %s", memory_lock.lock())
    trial_log = _TrialLog(Path(spec.log_dir))
    best = -np.inf
    # Trial 0's parameters: the optimizer's first proposal, uniform random with nothing stored (docs/decisions.md
    # §16: trials 0 and 1 random); the context does not enter a random proposal.
    conn.send(("ready", optimizer.propose(c_gp)))
    while True:
        message = conn.recv()
        if message[0] == "stop":
            break
        if message[0] == "unsafe":  # a safety stop ended the trial (online_optimization)
            _, trial, x, signals, margin, reason, wait_ticks = message
            # The context the parameters were proposed for: a stopped trial's few steady ticks, if any, do not
            # estimate it (the robot was falling).
            record = stopped_trial_record(signals, margin, spec.total_mass_kg, spec.dt_s)
            j = float(objective.objective(record, spec.target_velocity_mps))
            c = c_gp
            optimizer.observe(x, c_gp, record, j)
        else:
            _, trial, x, signals, wait_ticks = message
            reason = None
            record, j, c, c_gp = _evaluate(signals, spec, optimizer.observe, trial, x)
        conn.send(("params", optimizer.propose(c_gp)))
        row = {
            **trial_row(trial, x, record, j, c, spec.seed, spec.tuned_for, reason),
            "optimizer": spec.kind,
            "wait_s": wait_ticks * spec.dt_s,
        }
        trial_log.append(row)
        if reason is not None:
            log.info(
                "trial %d: stopped by the safety layer (%s): learned as unsafe, safety margin %.3f, J = %.3f",
                trial,
                reason,
                row["safety_margin"],
                j,
            )
            continue
        log.info(
            "trial %d: J = %.3f, v_x = %.2f m/s, CoT = %.2f, context (%.1f N, %.3f rad); its parameters came "
            "%.2f s after the previous trial",
            trial,
            j,
            row["velocity_x_mps"],
            row["cost_of_transport"],
            c[0],
            c[1],
            row["wait_s"],
        )
        if j > best:
            best = j
            tuned.save(Path(spec.log_dir) / tuned.FILE_NAME, x, spec.tuned_for, objective=j, trial=trial)
    trial_log.close()
    conn.send(("done", trial_log.rows))


class _Mailer:
    """Sends messages on a connection from a thread of its own, so the loop never blocks on it: a finished trial's
    signals (≈ 100 kB) exceed the connection's buffer, and the loop would wait until the optimizer's process has
    read them (1.9 s once, its memory paged out after a trial of idling, while the robot walked on a stale
    command). ``cpus``: where the thread runs (off the loop's CPU)."""

    def __init__(self, conn, cpus: tuple[int, ...] | None):
        self._conn, self._cpus = conn, cpus
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._drain, name="trial-mailer", daemon=True)
        self._thread.start()

    def send(self, message) -> None:
        self._queue.put(message)

    def _drain(self) -> None:
        if self._cpus:
            with contextlib.suppress(OSError):
                os.sched_setaffinity(0, self._cpus)  # this thread only
        while (message := self._queue.get()) is not None:
            with contextlib.suppress(OSError):  # the optimizer's process is gone: the loop notices on its own
                self._conn.send(message)

    def close(self) -> None:
        """Send what is queued, then stop."""
        self._queue.put(None)
        self._thread.join()


class TrialRunner:
    """A :class:`~cpgjax.hardware_io.ParamSchedule` running Algorithm 1's trials inside the 1 kHz loop.

    Cheap per tick: an interpolation, one row copy, and (only while waiting for a proposal) a pipe poll. A
    finished trial is handed to ``mailer`` (a queue put).
    """

    def __init__(
        self,
        conn,
        initial_params: np.ndarray,
        num_trials: int,
        timing: protocol.TrialConfig = protocol.TrialConfig(),
        mailer: _Mailer | None = None,
        first_trial: int = 0,
    ):
        self._conn = conn
        self._mailer = mailer or conn
        self._timing = timing
        self._columns = signal_columns()
        self._signals = np.full((timing.steady_steps, len(_SIGNALS)), 0, np.float32)  # written now, not in the loop
        self._previous = self._current = np.asarray(initial_params, np.float32)
        self._num_trials = num_trials
        self.steady_windows: list[tuple[int, int]] = []  # per complete trial: its steady phase's first, last run tick
        self.trials_done = first_trial  # trials before this loop's (a run restarted after a safety stop) count
        self.trial = first_trial  # the trial whose parameters the robot walks with (logged per tick)
        self.run_ticks = 0  # run-phase ticks so far
        self._tick_in_trial = 0
        self._waiting_since = None  # run tick at which the last trial was handed to the optimizer
        self._wait_ticks = 0  # ticks spent waiting for the current trial's parameters
        self.finished = first_trial >= num_trials
        self.failure: str | None = None  # the optimizer process was lost (hardware_io.ParamSchedule.failure)

    @property
    def walked_params(self) -> np.ndarray:
        """The parameters the robot walks with once the current trial's transition is over."""
        return self._current

    @property
    def waiting(self) -> bool:
        """Whether the last complete trial's successor is still to come from the optimizer."""
        return self._waiting_since is not None

    def steady_signals(self) -> np.ndarray:
        """The current trial's steady-phase signals so far (none while waiting or in its transition)."""
        done = 0 if self.waiting else max(self._tick_in_trial - self._timing.transition_steps, 0)
        return self._signals[:done].copy()

    def params(self, run_tick: int) -> np.ndarray:
        k = self._tick_in_trial
        if self._waiting_since is None and k < self._timing.transition_steps:
            fraction = np.float32(protocol.transition_fraction(k, self._timing.transition_steps))
            return protocol.transition_params(self._previous, self._current, fraction)
        return self._current

    def record(self, run_tick: int, out: np.ndarray) -> None:
        self.run_ticks = run_tick + 1
        if self._waiting_since is not None:
            try:
                answered = self._conn.poll()
                _, proposal = self._conn.recv() if answered else (None, None)
            except (EOFError, OSError):  # the optimizer process is gone: no parameters will come
                self.failure = (
                    f"the optimizer process ended while trial {self.trials_done} waited for its "
                    "parameters (its log is above)"
                )
                self.finished = True
                return
            if answered:
                self._previous, self._current = self._current, np.asarray(proposal, np.float32)
                self._wait_ticks = run_tick - self._waiting_since
                self._waiting_since, self._tick_in_trial = None, 0
                self.trial = self.trials_done
            return
        steady = self._tick_in_trial - self._timing.transition_steps
        if steady >= 0:
            self._signals[steady] = out[self._columns]
        self._tick_in_trial += 1
        if steady + 1 == self._timing.steady_steps:
            self.steady_windows.append((run_tick - steady, run_tick))
            self._mailer.send(
                ("trial", self.trials_done, self._current.astype(np.float64), self._signals.copy(), self._wait_ticks)
            )
            self.trials_done += 1
            self.finished = self.trials_done >= self._num_trials
            self._waiting_since = run_tick


def _answer(conn, worker, timeout_s: float = 600.0):
    """The optimizer process's next message, while the robot is damped; one line if the process is gone."""
    while not conn.poll(1.0):
        timeout_s -= 1.0
        if not worker.is_alive() or timeout_s <= 0:
            raise RuntimeError(
                "the optimizer process ended or stopped answering after a safety stop (its log is "
                "above); the robot is damped"
            )
    return conn.recv()


Recover = Callable[[int, str], bool]  # (the stopped trial, the stop's reason) → whether to stand up and go on


def online_optimization(
    transport,
    controller,
    calibration,
    gates,
    spec: OptimizerSpec,
    initial_params: np.ndarray | None,
    num_trials: int,
    timing: protocol.TrialConfig = protocol.TrialConfig(),
    loop=None,
    safety=None,
    sink=None,
    stale_hint: str = "",
    recover: Recover | None = None,
):
    """Algorithm 1 on the robot: ``num_trials`` trials back to back, the optimizer in its own process (its
    compilation done before the robot walks, off the loop's CPU when the loop has one). Trial 0 walks with
    ``initial_params``, or with None with the optimizer's first (random) proposal, as in simulation
    (docs/decisions.md §16). ``sink`` and ``stale_hint``: as for ``hardware_io.run_loop``.

    A safety stop that the gait caused (``robot.safety.is_gait_trip``) during the run phase is, with ``recover``,
    the outcome of the trial being walked (while the robot waits for a proposal, that of the next trial, with the
    parameters it walks): the optimizer learns it as unsafe (:func:`stopped_trial_record`, :func:`stop_margin`) and
    proposes the next trial's parameters; then, if trials remain, ``recover(trial, reason)`` is asked to put the
    robot on its feet (True) or to end the run (False), and the loop starts again: connect, soft start, stand, next
    trial. Without ``recover``, or after any other trip, the run ends at the trip as the loop does.

    Returns (LoopResult of the whole run (``hardware_io.joined``), per-trial rows, each complete trial's steady
    phase as its (first, last) run tick, counted over the run's loops). The log files are in ``spec.log_dir``.
    """
    Path(spec.log_dir).mkdir(parents=True, exist_ok=True)
    loop = loop or hio.LoopConfig()
    others = hio.cpus_besides(loop.cpu)
    spec = spec._replace(steady_steps=timing.steady_steps, cpus=tuple(sorted(others)) if others else None)
    context = multiprocessing.get_context("spawn")  # never fork a process that has started JAX
    conn, worker_conn = context.Pipe()
    worker = context.Process(target=_optimizer_worker, args=(worker_conn, spec), daemon=True)
    worker.start()
    try:
        if not conn.poll(600.0):
            raise RuntimeError("the optimizer process did not start")
        _, first = conn.recv()  # ready: its imports and compilation are done before the robot walks
        initial_params = first if initial_params is None else initial_params
        log.info(
            "trial 0 walks with %s parameters",
            "the given" if initial_params is not first else "the optimizer's first (random, docs/decisions.md §16)",
        )
        mailer = _Mailer(conn, spec.cpus)
        results, windows = [], []
        params, first_trial, run_ticks = initial_params, 0, 0
        try:
            while True:
                runner = TrialRunner(conn, params, num_trials, timing, mailer, first_trial)
                ticks = sum(r.ticks for r in results)
                result = hio.run_loop(
                    transport,
                    controller,
                    runner,
                    calibration,
                    gates,
                    loop,
                    safety or go1_safety.SafetyConfig(),
                    hio.offset_sink(sink, ticks),
                    stale_hint,
                )
                results.append(result)
                windows += [(first + run_ticks, last + run_ticks) for first, last in runner.steady_windows]
                run_ticks += runner.run_ticks
                if (
                    recover is None
                    or not go1_safety.is_gait_trip(result.trip)
                    or runner.run_ticks == 0
                    or runner.trials_done >= num_trials
                ):
                    break
                stopped = runner.trials_done
                if runner.waiting:
                    _answer(conn, worker)  # the proposal for this trial, made before its stop: superseded
                mailer.send(
                    (
                        "unsafe",
                        stopped,
                        runner.walked_params.astype(np.float64),
                        runner.steady_signals(),
                        stop_margin(result, timing),
                        result.trip,
                        0,
                    )
                )
                _, params = _answer(conn, worker)  # proposed once the stop was learned
                first_trial = stopped + 1
                if first_trial >= num_trials or not recover(stopped, result.trip):
                    break
                log.info(
                    "trial %d ended with a safety stop (%s), learned as unsafe; standing up for trial %d",
                    stopped,
                    result.trip,
                    first_trial,
                )
        finally:
            mailer.close()
        result = hio.joined(results)
        rows = []
        # A lost optimizer process (the loop ended on runner.failure) wrote trials.parquet up to its last trial.
        with contextlib.suppress(EOFError, OSError):
            conn.send(("stop",))
            while conn.poll(120.0):
                message = conn.recv()
                if message[0] == "done":
                    rows = message[1]
                    break
        worker.join(timeout=30.0)
    finally:
        if worker.is_alive():
            worker.kill()
    return result, rows, windows
