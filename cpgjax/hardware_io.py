"""Run the jitted CPG controller at 1 kHz on a Go1 (or the loopback simulated Go1), with safety.

:func:`run_loop` is the 1 kHz loop — absolute deadlines with a short spin, overrun counting, frozen GC, real-time
priority and CPU affinity when permitted — driving the safety layer (:mod:`cpgjax.robot.safety`): soft start (hold the
measured pose while the gains ramp, then move to the standing pose), clamps on torque, gains and joint positions
checked *before* encoding, the SDK's power protection rule, tilt stop, stale-state watchdog, remote stop buttons,
non-finite command guard, motor temperature limit, and a clean shutdown to damping on Ctrl-C. Every trip is logged
with its reason and latches damping.

The pieces it drives live in their own modules: transports (:mod:`cpgjax.robot.transport`), the foot-force
calibration (:mod:`cpgjax.robot.foot_force`), the compiled controller and its flat layout
(:mod:`cpgjax.robot.controller`) and the safety layer (:mod:`cpgjax.robot.safety`).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1.constants import CONTROL_HZ, JOINT_LOWER_RAD, JOINT_UPPER_RAD, TICK_S
from cpgjax.robot import cpu_wakeup, memory_lock, wire
from cpgjax.robot.controller import (
    INPUT,
    OBSERVATION,
    OUTPUT,
    CompiledController,
    ControllerInput,
    pack_observation,
)
from cpgjax.robot.foot_force import FootForceCalibration
from cpgjax.robot.safety import (
    SafetyConfig,
    damping_command,
    guard_command,
    pd_command,
    power_protect,
    state_trip_reason,
    torque_command,
)
from cpgjax.robot.transport import Transport

log = logging.getLogger(__name__)

# While the loop runs, a thread holding the GIL (the per-tick log's writer) gives it up after this long when the
# loop wants it (Python's default: 5 ms, five periods).
GIL_SWITCH_S = 50e-6

# Loop phases (logged per tick).
CONNECT, HOLD, RAMP, STAND, RUN, DAMP = range(6)
PHASE_NAMES = ("connect", "hold", "ramp", "stand", "run", "damp")


class ParamSchedule(Protocol):
    """Supplies the CPG parameters during the run phase and sees every controller output (robot time = ticks)."""

    finished: bool
    trial: int  # the trial the parameters belong to (logged per tick)
    failure: str | None  # why the schedule finished early, if it failed (the run ends with this trip), else None

    def params(self, run_tick: int) -> np.ndarray:
        """Parameters (8,) for this tick of the run phase.

        Args:
          run_tick: the run phase's tick, from 0.

        Returns:
          (8,) CPG parameters, copied into the controller's float32 input.
        """

    def record(self, run_tick: int, out: np.ndarray) -> None:
        """The controller's flat output (``robot.controller.OUTPUT``) of this tick.

        Args:
          run_tick: the run phase's tick, from 0 (that of :meth:`params`).
          out: (OUTPUT.size,) float32, the compiled controller step's output.
        """


class FixedParams:
    """One parameter set for ``run_ticks`` ticks (None: until stopped; 0: the run phase is skipped)."""

    trial = 0
    failure = None

    def __init__(self, params: np.ndarray, run_ticks: int | None = None):
        self._params = np.asarray(params, np.float32)
        self._run_ticks = run_ticks
        self.finished = run_ticks == 0

    def params(self, run_tick: int) -> np.ndarray:
        """The one parameter set, at every tick.

        Args:
          run_tick: the run phase's tick (unused).

        Returns:
          The parameters given, as float32 (the same array at every tick).
        """
        return self._params

    def record(self, run_tick: int, out: np.ndarray) -> None:
        """Finish once ``run_ticks`` ticks have run (never with ``run_ticks`` None).

        Args:
          run_tick: the run phase's tick, from 0.
          out: the controller's flat output (unused).
        """
        if self._run_ticks is not None and run_tick + 1 >= self._run_ticks:
            self.finished = True


class LoopConfig(NamedTuple):
    """Timing and soft start of the 1 kHz loop."""

    period_s: float = TICK_S
    spin_s: float = 0.0002  # sleep until this long before the deadline, then spin
    # Spin through the whole period, never sleep: the CPU stays awake (on a VM, the virtual CPU is not halted and
    # handed back to the host). Needs a CPU of its own (``cpu``) and, at SCHED_FIFO, the kernel's real-time
    # throttling off; benchmarks/hardware_loop.py compares it with sleeping.
    busy_wait: bool = False
    connect_timeout_s: float = 2.0  # no robot state by then → give up
    hold_s: float = 0.5  # hold the measured pose while Kp ramps from hold_kp_fraction to stand_kp
    ramp_s: float = 1.0  # then move linearly to the standing pose
    stand_s: float = 0.0  # then hold the standing pose this long before the run phase
    stand_kp_nm_rad: float = 70.0
    stand_kd_nm_s_rad: float = 1.5
    hold_kp_fraction: float = 0.2
    damping_kd_nm_s_rad: float = 3.0
    end_damping_s: float = 1.0  # damping sent after a trip, Ctrl-C or the end of the run, before returning
    realtime_priority: int | None = 80  # SCHED_FIFO priority when permitted (None: leave the scheduler alone)
    cpu: int | None = None  # pin the loop thread to this CPU when permitted
    lock_memory: bool = True  # mlockall while the loop runs, when permitted: no page fault waits on a disk
    poll_idle: bool = True  # idle CPUs poll instead of halting while the loop runs, when permitted (robot.cpu_wakeup)
    log_ticks: int = 120_000  # per-tick log ring buffer (the newest ticks are kept); a multiple of flush_ticks
    flush_ticks: int = CONTROL_HZ  # hand the per-tick log to the sink in batches of this many ticks (1 s)


class TickLog(NamedTuple):
    """Per-tick records, chronological (the newest ``LoopConfig.log_ticks``)."""

    t_start_s: np.ndarray  # perf_counter at the start of the tick
    late_s: np.ndarray  # start of the tick − its deadline (the wait before it overshot by this much)
    step_s: np.ndarray  # controller step latency (pack + compiled call + unpack)
    work_s: np.ndarray  # whole tick before waiting (wall clock)
    work_cpu_s: np.ndarray  # the loop thread's CPU time during that work (excludes time it was not running)
    overrun: np.ndarray  # the tick's work ended after the next deadline
    phase: np.ndarray  # CONNECT … DAMP
    fresh: np.ndarray  # a new robot state arrived this tick
    robot_tick_ms: np.ndarray
    foot_force_raw: np.ndarray  # (n, 4) the latest robot state's raw foot-sensor counts
    obs: np.ndarray  # (n, OBSERVATION.size) observation given to the controller (run phase), flat
    torque_nm: np.ndarray  # (n, 12) torque sent (after clamping)
    controller_torque_nm: np.ndarray  # (n, 12) torque returned by the controller (before clamping)
    q_rad: np.ndarray  # (n, 12) the latest robot state's joint angles (every phase)
    dq_rad_s: np.ndarray  # (n, 12) its joint velocities
    quaternion_wxyz: np.ndarray  # (n, 4) its IMU attitude
    gyro_rad_s: np.ndarray  # (n, 3) its IMU angular velocity
    command_q_rad: np.ndarray  # (n, 12) position target sent (PosStopF: off)
    command_kp: np.ndarray  # Kp sent (motor 0; every phase sends one Kp and one Kd to all motors)
    command_kd: np.ndarray
    stale_ticks: np.ndarray  # ticks since the last new robot tick (the watchdog's count)
    power_counter: np.ndarray  # the power-protection counter
    trial: np.ndarray  # the schedule's trial

    @classmethod
    def allocate(cls, n: int) -> TickLog:
        """Every page written before the loop starts. ``np.zeros`` maps zero pages that are faulted in on first write,
        which inside the loop would take the tick's CPU time (docs/hardware.md, "Overruns on the 2-vCPU virtual
        machine (measured, 2026-11-22)").

        Args:
          n: the ticks it holds (``LoopConfig.log_ticks``).

        Returns:
          A log of ``n`` rows, every value 0 but ``phase``, −1 (no tick).
        """
        zeros = lambda shape, dtype=np.float32: np.full(shape, 0, dtype)  # noqa: E731 (np.full writes every page)
        return cls(
            zeros(n, np.float64),
            zeros(n),
            zeros(n),
            zeros(n),
            zeros(n),
            zeros(n, bool),
            np.full(n, -1, np.int8),
            zeros(n, bool),
            zeros(n, np.uint32),
            zeros((n, 4), np.int16),
            zeros((n, OBSERVATION.size)),
            zeros((n, 12)),
            zeros((n, 12)),
            zeros((n, 12)),
            zeros((n, 12)),
            zeros((n, 4)),
            zeros((n, 3)),
            zeros((n, 12)),
            zeros(n),
            zeros(n),
            zeros(n, np.int32),
            zeros(n, np.int16),
            zeros(n, np.int16),
        )

    def chronological(self, ticks: int) -> TickLog:
        """The ring buffer's rows in tick order after a loop of ``ticks`` ticks (tick k at row k mod n): the first
        ``ticks`` rows, or once the ring has wrapped, all n rows from the oldest tick's.

        Args:
          ticks: the ticks the loop ran.

        Returns:
          A log of min(``ticks``, n) rows, the oldest first.
        """
        n = self.phase.shape[0]
        if ticks <= n:
            return TickLog(*(a[:ticks] for a in self))
        order = (np.arange(n) + ticks) % n
        return TickLog(*(a[order] for a in self))


class LoopResult(NamedTuple):
    trip: str | None  # the first safety trip, or None (clean end, or stopped)
    events: list  # (tick, phase name, message)
    ticks: int
    overruns: int  # ticks whose work ended after the next deadline
    skipped_ticks: int  # deadlines dropped after an overrun longer than a period
    rejected_packets: dict
    realtime: str  # what scheduling the loop actually got
    log: TickLog
    stopped: bool = False  # Ctrl-C (SIGINT) stopped the run: damped, not a trip
    loop_starts: tuple[int, ...] = (0,)  # rows of ``log`` where a loop began (several: ``joined``)
    safety_stops: tuple = ()  # (tick, reason) of each trip that ended a loop of a joined run but the last

    def timing(self) -> dict:
        """:func:`timing_stats` of this run: its log, overruns, ticks and loop starts.

        Returns:
          The statistics of :func:`timing_stats`.
        """
        return timing_stats(self.log, self.overruns, self.ticks, self.loop_starts)

    def trip_tick(self) -> int:
        """The loop tick at which the trip was detected (its event's).

        Returns:
          The tick of the last event whose message is :attr:`trip`.
        """
        return next(tick for tick, _, message in reversed(self.events) if message == self.trip)


def joined(results: list[LoopResult]) -> LoopResult:
    """One run's result from the results of the loops it ran one after the other (an online optimization that stood
    the robot up after a safety stop): ticks, events and logs follow on, the trip and the stop are the last loop's,
    and each earlier loop's trip is a safety stop.

    Args:
      results: each loop's result (at least one), in the order they ran.

    Returns:
      The run's result; a single loop's is returned as it is.
    """
    if len(results) == 1:
        return results[0]
    offsets = np.cumsum([0] + [r.ticks for r in results[:-1]])
    rows = np.cumsum([0] + [len(r.log.phase) for r in results[:-1]])
    rejected: dict = {}
    for r in results:
        for name, n in r.rejected_packets.items():
            rejected[name] = rejected.get(name, 0) + n
    last = results[-1]
    return LoopResult(
        trip=last.trip,
        events=[
            (tick + int(o), phase, msg) for r, o in zip(results, offsets, strict=True) for tick, phase, msg in r.events
        ],
        ticks=sum(r.ticks for r in results),
        overruns=sum(r.overruns for r in results),
        skipped_ticks=sum(r.skipped_ticks for r in results),
        rejected_packets=rejected,
        realtime=last.realtime,
        log=TickLog(*(np.concatenate(fields) for fields in zip(*(r.log for r in results), strict=True))),
        stopped=last.stopped,
        loop_starts=tuple(int(v) for v in rows),
        safety_stops=tuple((int(o) + r.trip_tick(), r.trip) for r, o in zip(results[:-1], offsets[:-1], strict=True)),
    )


OVERRUN_CAUSES = ("late_start", "not_running", "work_cpu")
# The loop's target: at most this many overruns per 10k ticks, about what an empty loop achieves on a VM (its
# measured floor, docs/hardware.md "The floor").
OVERRUN_TARGET_PER_10K = 1.0


def overrun_causes(log: TickLog) -> np.ndarray:
    """Index into :data:`OVERRUN_CAUSES` of the largest share of each overrun tick's time (late start + work): the
    tick started late (the wait before it overshot: a late wake-up, or the previous tick's overrun), the thread was
    not running during the work (wall − thread CPU time: preempted, or its virtual CPU descheduled by the
    hypervisor, which the guest accounts as steal and not as thread time), or the work itself took the CPU time.

    Args:
      log: the per-tick log.

    Returns:
      (overrun ticks,) int, one cause per logged overrun tick, in the log's order.
    """
    late = np.maximum(log.late_s[log.overrun], 0.0)
    cpu = log.work_cpu_s[log.overrun]
    not_running = np.maximum(log.work_s[log.overrun] - cpu, 0.0)
    return np.argmax(np.stack([late, not_running, cpu]), axis=0) if late.size else np.zeros(0, int)


def timing_stats(log: TickLog, overruns: int, ticks: int, loop_starts: tuple[int, ...] = (0,)) -> dict:
    """Controller-step latency and loop-period statistics [µs] over the logged ticks after connection, and the
    overruns by cause (:func:`overrun_causes`, logged ticks only). ``loop_starts``: the rows where a loop began
    (a period is measured within one loop).

    Args:
      log: the per-tick log (chronological, :meth:`TickLog.chronological`).
      overruns: the overruns of every tick, logged or not (``LoopResult.overruns``).
      ticks: the ticks the loop ran (``LoopResult.ticks``).
      loop_starts: the rows of ``log`` where a loop began (``LoopResult.loop_starts``).

    Returns:
      ``ticks``, ``overruns``, ``overruns_per_10k_ticks``, ``overruns_<cause>`` for each of :data:`OVERRUN_CAUSES`,
      and the median, p99 and max [µs] of ``step`` (run phase), ``period`` (also p1) and ``work``, each
      ``<name>_<statistic>_us``; NaN where no logged tick measures it.
    """
    active = log.phase > CONNECT
    step_us = log.step_s[active & (log.phase == RUN)] * 1e6
    loop = np.cumsum(np.isin(np.arange(len(log.phase)), loop_starts))[active]  # the loop of each active tick
    period_us = np.diff(log.t_start_s[active])[np.diff(loop) == 0] * 1e6
    pct = lambda a, q: float(np.percentile(a, q)) if a.size else float("nan")  # noqa: E731
    causes = np.bincount(overrun_causes(log), minlength=len(OVERRUN_CAUSES))
    return {
        "ticks": int(ticks),
        "overruns": int(overruns),
        "overruns_per_10k_ticks": 1e4 * overruns / max(ticks, 1),
        **{f"overruns_{name}": int(n) for name, n in zip(OVERRUN_CAUSES, causes, strict=True)},
        "step_median_us": pct(step_us, 50),
        "step_p99_us": pct(step_us, 99),
        "step_max_us": float(step_us.max()) if step_us.size else float("nan"),
        "period_median_us": pct(period_us, 50),
        "period_p1_us": pct(period_us, 1),
        "period_p99_us": pct(period_us, 99),
        "period_max_us": float(period_us.max()) if period_us.size else float("nan"),
        "work_median_us": pct(log.work_s[active] * 1e6, 50),
        "work_p99_us": pct(log.work_s[active] * 1e6, 99),
        "work_max_us": float(log.work_s[active].max() * 1e6) if active.any() else float("nan"),
    }


def timing_table(timing: dict, deadlines: bool = True) -> str:
    """:func:`timing_stats` as a few aligned lines (µs, and as a fraction of the 1 ms period). ``deadlines``
    False (a lockstep simulated robot, which answers each command instead of keeping time): periods and overruns
    measure the simulation's speed, not the loop's, and are left out.

    Args:
      timing: the statistics of :func:`timing_stats`.
      deadlines: whether the loop kept deadlines (False: lockstep pacing).

    Returns:
      The lines, joined by newlines; with ``deadlines`` the last is :func:`overrun_verdict`'s.
    """
    rows = [("controller step", "step"), ("tick work", "work")] + ([("period", "period")] if deadlines else [])
    lines = [f"{'':16s} {'median':>9s} {'p99':>9s} {'max':>9s}   [µs]"]
    for label, key in rows:
        median, p99 = timing[f"{key}_median_us"], timing[f"{key}_p99_us"]
        worst = timing.get(f"{key}_max_us", float("nan"))
        lines.append(f"{label:16s} {median:9.1f} {p99:9.1f} {worst:9.1f}   (p99 {p99 / 1000:.2f} of the period)")
    if deadlines:
        causes = ", ".join(f"{name.replace('_', ' ')} {timing[f'overruns_{name}']}" for name in OVERRUN_CAUSES)
        lines.append(
            f"overruns         {timing['overruns']} in {timing['ticks']} ticks "
            f"({timing['overruns_per_10k_ticks']:.2f} per 10k; {causes})"
        )
        lines.append(overrun_verdict(timing))
    else:
        lines.append(f"overruns         do not apply: lockstep pacing has no deadlines ({timing['ticks']} ticks)")
    return "\n".join(lines)


def overrun_verdict(timing: dict) -> str:
    """One line: whether the run's overruns met the loop's target (:data:`OVERRUN_TARGET_PER_10K`), and where they
    did not, their largest cause and what helps against it (docs/hardware.md).

    Args:
      timing: the statistics of :func:`timing_stats`.

    Returns:
      "verdict: met …", or "verdict: missed …" with the rate, the largest cause and what helps against it.
    """
    rate = timing["overruns_per_10k_ticks"]
    target = f"the loop's target of at most {OVERRUN_TARGET_PER_10K:g} per 10k ticks"
    if rate <= OVERRUN_TARGET_PER_10K:
        return f"verdict: met {target}"
    cause = max(OVERRUN_CAUSES, key=lambda name: timing[f"overruns_{name}"])
    helps = {
        "late_start": "--busy-wait, or a CPU of its own (--cpu) with idle CPUs polling",
        "not_running": "a machine whose host does not stall it (a VM's virtual CPU was descheduled)",
        "work_cpu": "a CPU of its own (--cpu) and SCHED_FIFO (without --no-realtime)",
    }[cause]
    return f"verdict: missed {target} ({rate:.2f}); most were {cause.replace('_', ' ')}: {helps} (docs/hardware.md)"


def _enter_realtime(loop: LoopConfig):
    """Apply SCHED_FIFO, CPU affinity, memory locking and polling idle CPUs where permitted; return (description,
    restore function)."""
    notes, restores = [], []

    def restore() -> None:
        for undo in reversed(restores):
            undo()

    if loop.cpu is not None:
        try:
            old = os.sched_getaffinity(0)
            os.sched_setaffinity(0, {loop.cpu})
            restores.append(lambda: os.sched_setaffinity(0, old))
            notes.append(f"pinned to CPU {loop.cpu}")
        except (OSError, AttributeError) as e:
            notes.append(f"affinity not permitted ({e})")
    if loop.realtime_priority is not None:
        throttle = rt_throttling()
        if loop.busy_wait and throttle is not None:
            restore()
            raise ValueError(
                f"busy_wait at SCHED_FIFO {loop.realtime_priority}: the kernel's real-time throttling "
                f"(kernel.sched_rt_runtime_us = {throttle[0]} of sched_rt_period_us = {throttle[1]}) would stop the "
                f"loop for {(throttle[1] - throttle[0]) / 1000:.0f} ms every {throttle[1] / 1000:.0f} ms. Busy-wait "
                "without real-time priority on a CPU of its own (realtime_priority=None, cpu=N), or turn the "
                "throttling off (sysctl kernel.sched_rt_runtime_us=-1)"
            )
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(loop.realtime_priority))
            restores.append(lambda: os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0)))
            notes.append(f"SCHED_FIFO {loop.realtime_priority}")
        except (OSError, AttributeError) as e:
            notes.append(f"real-time priority not permitted ({e})")
    if loop.busy_wait:
        notes.append("busy-wait")
    if loop.lock_memory:
        note = memory_lock.lock()
        notes.append(note)
        if note == memory_lock.LOCKED:
            restores.append(memory_lock.unlock)
    if loop.poll_idle:
        note, release = cpu_wakeup.request_polling()
        notes.append(note)
        restores.append(release)
    return ", ".join(notes) or "default scheduling", restore


def cpus_besides(loop_cpu: int | None) -> set[int] | None:
    """The CPUs this process may use other than the loop's (for the optimizer, the per-tick log's writer, or a
    simulated Go1 kept apart), or None: no loop CPU given, or no other CPU left.

    Args:
      loop_cpu: the loop's CPU (``LoopConfig.cpu``), or None.

    Returns:
      The CPUs of this process's affinity but ``loop_cpu``, or None.
    """
    if loop_cpu is None:
        return None
    return (set(os.sched_getaffinity(0)) - {loop_cpu}) or None


def rt_throttling() -> tuple[int, int] | None:
    """(sched_rt_runtime_us, sched_rt_period_us) when the kernel throttles real-time threads, None when it does
    not (runtime −1) or the setting cannot be read.

    Returns:
      (runtime [µs], period [µs]) read from /proc/sys/kernel; None where the runtime is negative or not below the
      period, or either file cannot be read or parsed.
    """
    try:
        runtime = int(Path("/proc/sys/kernel/sched_rt_runtime_us").read_text())
        period = int(Path("/proc/sys/kernel/sched_rt_period_us").read_text())
    except (OSError, ValueError):
        return None
    return None if runtime < 0 or runtime >= period else (runtime, period)


class _StopRequest:
    """Ctrl-C (SIGINT) while the loop runs asks for a clean shutdown to damping instead of raising."""

    def __init__(self):
        self.requested = False
        self._old = None

    def __enter__(self) -> _StopRequest:
        try:
            self._old = signal.signal(signal.SIGINT, self._handle)
        except ValueError:  # not the main thread: no handler, the caller stops the loop otherwise
            self._old = None
        return self

    def _handle(self, signum, frame) -> None:
        self.requested = True

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def _spin_s(loop: LoopConfig) -> float:
    """How long before each deadline the wait spins instead of sleeping: the whole period when busy-waiting."""
    return loop.period_s if loop.busy_wait else loop.spin_s


def _wait_until(deadline: float, spin_s: float) -> None:
    remaining = deadline - time.perf_counter()
    if remaining > spin_s:
        time.sleep(remaining - spin_s)
    while time.perf_counter() < deadline:
        pass


@contextlib.contextmanager
def _realtime_section(loop: LoopConfig) -> Iterator[str]:
    """The loop's surroundings: real-time scheduling where permitted (:func:`_enter_realtime`), the garbage
    collector collected, frozen and off, and a short GIL switch interval (:data:`GIL_SWITCH_S`); yields what
    scheduling the loop got. On exit all three are restored."""
    realtime, restore = _enter_realtime(loop)
    gc.collect()
    gc.freeze()
    gc.disable()
    switch_s = sys.getswitchinterval()
    sys.setswitchinterval(GIL_SWITCH_S)
    try:
        yield realtime
    finally:
        sys.setswitchinterval(switch_s)
        gc.enable()
        gc.unfreeze()
        restore()


def idle_loop_lateness_s(seconds: float, loop: LoopConfig = LoopConfig()) -> np.ndarray:
    """How late each wake-up of the loop's wait is [s] with no work in its ticks: ``loop``'s scheduling (priority,
    CPU, locked memory, polling idle CPUs) and wait (sleep then spin, or busy-wait) for ``seconds``.

    The floor under :func:`run_loop`'s timing on this machine: a wake-up later than the period minus a tick's work
    is an overrun whatever the tick does, and one later than the period is an overrun even with no work at all. On a
    VM these come from the host (a virtual CPU stopped or woken late), and no code in the guest removes them.

    Args:
      seconds: how long to wait [s].
      loop: the scheduling, wait and period of the loop measured.

    Returns:
      (max(1, round(``seconds`` / ``loop.period_s``)),) float64: each wake-up's time after its deadline [s], the
      first taken at the start.
    """
    period_s, wait_spin_s = loop.period_s, _spin_s(loop)
    late = np.full(max(1, round(seconds / period_s)), 0.0)  # every page written before the wait starts
    with _realtime_section(loop):
        deadline = time.perf_counter()
        for k in range(late.shape[0]):
            now = time.perf_counter()
            late[k] = now - deadline
            deadline += period_s
            if now > deadline + period_s:  # as run_loop: drop the missed deadlines
                deadline += int((now - deadline) / period_s) * period_s
            _wait_until(deadline, wait_spin_s)
    return late


def _phase_ticks(loop: LoopConfig) -> tuple[int, ...]:
    """How many ticks each phase lasts, indexed by phase: hold, ramp and the final damping at least one, stand
    possibly none; connect and run end on events (0 here)."""
    period_s = loop.period_s
    return (
        0,
        max(1, round(loop.hold_s / period_s)),
        max(1, round(loop.ramp_s / period_s)),
        round(loop.stand_s / period_s),
        0,
        max(1, round(loop.end_damping_s / period_s)),
    )


def _controller_input(gates: cpg.Gates) -> tuple[np.ndarray, ControllerInput]:
    """The controller's flat input (``robot.controller.INPUT``) with the gates set, and its named views; the loop
    writes the rest each run tick."""
    x = INPUT.zeros()
    views = INPUT.unravel(x)
    views.gates.vmc[...], views.gates.tegotae[...] = float(gates.vmc), float(gates.tegotae)
    views.gates.phase_lag_rad[...] = np.asarray(gates.phase_lag_rad, np.float32)
    return x, views


def _enter_phase(events: list, tick: int, phase: int, message: str) -> tuple[int, int]:
    """Record the loop entering ``phase`` at ``tick`` (an event and a log line); returns the loop's new
    (phase, tick its phase time counts from)."""
    events.append((tick, PHASE_NAMES[phase], message))
    log.info("tick %d: %s (%s)", tick, PHASE_NAMES[phase], message)
    return phase, tick


def _trip_reason(
    power_counter: int,
    state: wire.RobotState | None,
    fresh: bool,
    stale_ticks: int,
    transport: Transport,
    safety: SafetyConfig,
    stop_mask: int,
    stale_hint: str,
) -> tuple[int, str | None]:
    """The safety checks of one tick once connected, in order: the stale-state watchdog or, on a fresh state, tilt,
    stop buttons, motor temperature and the power-protection counter; then the SDK's power trip.
    Returns (power-protection counter, the first trip reason or None)."""
    reason = None
    if stale_ticks > safety.watchdog_ticks:
        reason = f"stale state: no new robot tick for {stale_ticks} ticks{stale_hint}"
    elif fresh:
        reason = state_trip_reason(state, safety, stop_mask)
        if reason is None:
            power_counter, reason = power_protect(power_counter, state, safety)
    if reason is None and transport.power_tripped:
        reason = "the SDK's power protection tripped"
    return power_counter, reason


def _soft_start_command(
    phase: int,
    ticks_in_phase: int,
    hold_q_rad: np.ndarray,
    stand_q_rad: np.ndarray,
    phase_ticks: tuple[int, ...],
    loop: LoopConfig,
) -> wire.MotorCommand:
    """The motor PD command of one soft-start tick: hold the measured pose while Kp ramps from
    ``loop.hold_kp_fraction`` of the standing Kp up to it, move linearly to the standing pose, stand."""
    kp, kd = loop.stand_kp_nm_rad, loop.stand_kd_nm_s_rad
    if phase == HOLD:
        a = ticks_in_phase / phase_ticks[HOLD]
        return pd_command(hold_q_rad, kp * min(1.0, loop.hold_kp_fraction + (1 - loop.hold_kp_fraction) * a), kd)
    if phase == RAMP:
        a = min(1.0, (ticks_in_phase + 1) / phase_ticks[RAMP])
        return pd_command(hold_q_rad + a * (stand_q_rad - hold_q_rad), kp, kd)
    return pd_command(stand_q_rad, kp, kd)


def _after_soft_start_phase(phase: int, stand_ticks: int, schedule: ParamSchedule) -> tuple[int, str]:
    """The phase that follows the hold, ramp or stand phase, and its event message (a schedule finished from the
    start skips the run phase)."""
    if phase == HOLD:
        return RAMP, "moving to the standing pose"
    if phase == RAMP and stand_ticks:
        return STAND, "standing"
    return (DAMP, "run complete") if schedule.finished else (RUN, "CPG running")


def _log_tick(
    tick_log: TickLog,
    i: int,
    t0: float,
    cpu0: float,
    late_s: float,
    step_s: float,
    phase: int,
    fresh: bool,
    robot_tick_ms: int,
    state: wire.RobotState | None,
    cmd: wire.MotorCommand,
    stale_ticks: int,
    power_counter: int,
    trial: int,
) -> None:
    """Write one tick's record at ring index i (the run phase's obs and controller torque are written by the
    loop); its work time (wall and thread CPU since t0, cpu0) last."""
    tick_log.t_start_s[i] = t0
    tick_log.late_s[i] = late_s
    tick_log.step_s[i] = step_s
    tick_log.phase[i] = phase
    tick_log.fresh[i] = fresh
    tick_log.robot_tick_ms[i] = robot_tick_ms
    if state is not None:
        tick_log.foot_force_raw[i] = state.foot_force_raw
        tick_log.q_rad[i] = state.q_rad
        tick_log.dq_rad_s[i] = state.dq_rad_s
        tick_log.quaternion_wxyz[i] = state.quaternion_wxyz
        tick_log.gyro_rad_s[i] = state.gyro_rad_s
    tick_log.torque_nm[i] = cmd.tau_nm
    tick_log.command_q_rad[i] = cmd.q_rad
    tick_log.command_kp[i] = cmd.kp_nm_rad[0]
    tick_log.command_kd[i] = cmd.kd_nm_s_rad[0]
    tick_log.stale_ticks[i] = stale_ticks
    tick_log.power_counter[i] = power_counter
    tick_log.trial[i] = trial
    tick_log.work_s[i] = time.perf_counter() - t0
    tick_log.work_cpu_s[i] = time.thread_time() - cpu0


class TickSink(Protocol):
    """Takes the per-tick log as the loop runs (e.g. :class:`cpgjax.deployment.tick_log.TickLogWriter`)."""

    def write(self, log: TickLog, rows: slice, ticks: range) -> None:
        """Rows ``rows`` of the ring buffer ``log`` hold loop ticks ``ticks`` (called every
        ``LoopConfig.flush_ticks`` ticks, inside a tick after its command was sent, and once at the end).

        Args:
          log: the loop's ring buffer (``LoopConfig.log_ticks`` rows), whose rows the loop writes again after
            ``LoopConfig.log_ticks`` more ticks.
          rows: contiguous rows of ``log``, at most ``LoopConfig.flush_ticks`` of them.
          ticks: the loop ticks those rows hold, one per row.
        """


class _OffsetSink:
    """A sink whose ticks follow those of the loops before (``offset`` of them)."""

    def __init__(self, sink: TickSink, offset: int):
        self._sink, self._offset = sink, offset

    def write(self, log: TickLog, rows: slice, ticks: range) -> None:
        """The sink's ``write`` with ``ticks`` shifted by the offset.

        Args:
          log: the loop's ring buffer.
          rows: contiguous rows of ``log``.
          ticks: this loop's ticks those rows hold, one per row.
        """
        self._sink.write(log, rows, range(ticks.start + self._offset, ticks.stop + self._offset))


def offset_sink(sink: TickSink | None, offset: int) -> TickSink | None:
    """``sink`` for a loop that follows ``offset`` ticks of earlier loops of the same run (``sink`` itself at 0).

    Args:
      sink: the run's sink, or None.
      offset: the ticks of the earlier loops.

    Returns:
      ``sink`` itself where it is None or ``offset`` is 0, else a sink that writes this loop's ticks as the run's.
    """
    return sink if sink is None or offset == 0 else _OffsetSink(sink, offset)


def run_loop(
    transport: Transport,
    controller: CompiledController | None,
    schedule: ParamSchedule,
    calibration: FootForceCalibration | None,
    gates: cpg.Gates,
    loop: LoopConfig = LoopConfig(),
    safety: SafetyConfig = SafetyConfig(),
    sink: TickSink | None = None,
    stale_hint: str = "",
) -> LoopResult:
    """Connect, soft-start (hold, ramp, ``loop.stand_s`` of standing), run the CPG at 1 kHz until
    ``schedule.finished``, Ctrl-C (a stop, not a trip) or a safety trip; then damp for ``loop.end_damping_s`` and
    return. ``sink`` gets the per-tick log in batches as the loop runs, the last one before returning (a trip or a
    stop keeps every tick up to it); ``stale_hint`` is appended to a stale-state trip's reason.

    Each tick: take the newest valid state (non-blocking) → watchdog and state checks → the phase's command (hold /
    ramp / stand: motor PD; run: the compiled controller's torques; damp) → guard (finite, clamped) → power
    protection → send → wait for the next absolute deadline. A schedule finished from the start skips the run phase
    (``controller`` and ``calibration`` are then unused and may be None; see :func:`stand`).

    Args:
      transport: the robot's (or the simulated Go1's) packets.
      controller: the compiled controller step; None only with a schedule finished from the start.
      schedule: the run phase's parameters; the run phase ends when it finishes (its ``failure``, if any, the trip).
      calibration: the foot-force calibration turning raw counts into N in the observation; None as ``controller``.
      gates: the controller's gates, set in its input once.
      loop: the timing, soft start, scheduling and per-tick log of the loop.
      safety: the limits and trips of the safety layer.
      sink: takes the per-tick log in batches of ``loop.flush_ticks`` ticks (None: the log is only in the result).
      stale_hint: appended to a stale-state trip's reason.

    Returns:
      The run's :class:`LoopResult`, its log the newest ``loop.log_ticks`` ticks (all of them, if fewer ran).

    Raises:
      ValueError: before the first tick, ``loop.log_ticks`` is not a multiple of ``loop.flush_ticks``, or
        ``loop.busy_wait`` at SCHED_FIFO (``loop.realtime_priority`` set) while the kernel throttles real-time
        threads (:func:`rt_throttling`).
    """
    period_s, wait_spin_s = loop.period_s, _spin_s(loop)
    stand_q_rad = go1_model.standing_qpos()[go1_model.indices().joint_qpos]
    stop_mask = sum(wire.REMOTE_BUTTON_BITS[b] for b in safety.stop_buttons)
    phase_ticks = _phase_ticks(loop)
    damp = damping_command(loop.damping_kd_nm_s_rad)
    n_log, flush = loop.log_ticks, loop.flush_ticks
    if n_log % flush:
        raise ValueError(f"log_ticks {n_log} must be a multiple of flush_ticks {flush}")
    tick_log = TickLog.allocate(n_log)
    x, inputs = _controller_input(gates)

    events: list = []
    trip, stopped = None, False
    phase, phase_tick = CONNECT, 0
    last_state, last_robot_tick, stale_ticks = None, None, 0
    power_counter, hold_q_rad, run_tick = 0, None, 0
    overruns = skipped = k = 0
    # The tick stays written out here: its state lives in locals, and each split would cost a call on the 1 ms path.
    with _realtime_section(loop) as realtime, _StopRequest() as stop:
        deadline = time.perf_counter()
        while True:
            t0, cpu0 = time.perf_counter(), time.thread_time()
            i = k % n_log
            state = transport.receive()
            fresh = state is not None and state.tick_ms != last_robot_tick
            if fresh:
                last_state, last_robot_tick, stale_ticks = state, state.tick_ms, 0
            else:
                stale_ticks += 1

            reason = None
            if phase == CONNECT:
                if fresh:
                    hold_q_rad = np.clip(state.q_rad, JOINT_LOWER_RAD, JOINT_UPPER_RAD)
                    if controller is not None:  # the start-up's standing pose (leaning into a slope)
                        stand_q_rad = controller.standing_pose_rad(state.quaternion_wxyz)
                    phase, phase_tick = _enter_phase(events, k, HOLD, "first robot state; holding the measured pose")
                elif k * period_s > loop.connect_timeout_s:
                    reason = f"no robot state within {loop.connect_timeout_s} s"
            elif phase != DAMP:
                power_counter, reason = _trip_reason(
                    power_counter, state, fresh, stale_ticks, transport, safety, stop_mask, stale_hint
                )
            if reason is not None:
                trip = trip or reason
                phase, phase_tick = _enter_phase(events, k, DAMP, reason)
            elif stop.requested and phase != DAMP:
                stopped = True
                phase, phase_tick = _enter_phase(events, k, DAMP, "stopped (Ctrl-C)")

            step_s = 0.0
            guarded = False  # the run phase's torque command was guarded inside the compiled step
            command_phase = phase  # the phase whose command this tick sends (logged)
            if phase == RUN:  # whole: step_s must time exactly pack + compiled call + unpack
                ts = time.perf_counter()
                pack_observation(last_state, calibration, inputs.obs)
                if run_tick == 0:  # start the CPG from the observation of its first tick (as the simulator)
                    x[INPUT.slices.state] = controller.initial_state(x[INPUT.slices.obs], x[INPUT.slices.gates])
                inputs.params[:] = schedule.params(run_tick)
                out = controller.step(x)
                x[INPUT.slices.state] = out[OUTPUT.slices.state]
                step_s = time.perf_counter() - ts
                schedule.record(run_tick, out)
                cmd, guarded = torque_command(out[OUTPUT.slices.guarded_torque_nm].astype(np.float64)), True
                tick_log.obs[i] = x[INPUT.slices.obs]
                tick_log.controller_torque_nm[i] = out[OUTPUT.slices.torque_nm]
                run_tick += 1
                if schedule.finished:
                    trip = trip or schedule.failure
                    phase, phase_tick = _enter_phase(events, k, DAMP, schedule.failure or "run complete")
            elif HOLD <= phase <= STAND:
                cmd = _soft_start_command(phase, k - phase_tick, hold_q_rad, stand_q_rad, phase_ticks, loop)
                if k - phase_tick + 1 >= phase_ticks[phase]:  # the phase's last tick
                    next_phase, message = _after_soft_start_phase(phase, phase_ticks[STAND], schedule)
                    phase, phase_tick = _enter_phase(events, k, next_phase, message)
            elif phase == DAMP and k - phase_tick >= phase_ticks[DAMP]:
                break
            else:  # connecting, or damping
                cmd = damp

            if guarded:  # safety.guard_command of a torque command: finite, clamped to the motor limits
                reason = None if out[OUTPUT.slices.finite][0] else "non-finite command (tau)"
            else:
                cmd, reason = guard_command(cmd, safety)
            if reason is not None:
                trip = trip or reason
                phase, phase_tick = _enter_phase(events, k, DAMP, reason)
                cmd = damp
            transport.send(cmd, last_state)
            _log_tick(
                tick_log,
                i,
                t0,
                cpu0,
                t0 - deadline,
                step_s,
                DAMP if reason is not None else command_phase,
                fresh,
                last_robot_tick or 0,
                last_state,
                cmd,
                stale_ticks,
                power_counter,
                schedule.trial,
            )
            k += 1

            deadline += period_s
            now = time.perf_counter()
            tick_log.overrun[i] = now > deadline
            if sink is not None and k % flush == 0:  # in this tick's slack, before waiting
                sink.write(tick_log, slice(i + 1 - flush, i + 1), range(k - flush, k))
            if now > deadline:
                overruns += 1
                if now > deadline + period_s:  # more than a period late: drop the missed deadlines
                    missed = int((now - deadline) / period_s)
                    skipped += missed
                    deadline += missed * period_s
            else:
                _wait_until(deadline, wait_spin_s)
    if sink is not None and k % flush:
        first = k - k % flush
        sink.write(tick_log, slice(first % n_log, first % n_log + k % flush), range(first, k))
    return LoopResult(
        trip=trip,
        events=events,
        ticks=k,
        overruns=overruns,
        skipped_ticks=skipped,
        rejected_packets=dict(getattr(transport, "rejected", {})),
        realtime=realtime,
        log=tick_log.chronological(k),
        stopped=stopped,
    )


def stand(
    transport: Transport,
    stand_s: float,
    loop: LoopConfig = LoopConfig(),
    safety: SafetyConfig = SafetyConfig(),
    sink: TickSink | None = None,
    stale_hint: str = "",
) -> LoopResult:
    """The loop without the controller: connect, soft start, hold the standing pose for ``stand_s``, damp (with
    every safety check of :func:`run_loop`). What the foot-force calibration measures the sensors with.

    Args:
      transport: the robot's (or the simulated Go1's) packets.
      stand_s: how long to hold the standing pose [s] (replaces ``loop.stand_s``).
      loop: the timing, soft start, scheduling and per-tick log of the loop.
      safety: the limits and trips of the safety layer.
      sink: takes the per-tick log as in :func:`run_loop`.
      stale_hint: appended to a stale-state trip's reason.

    Returns:
      The loop's :class:`LoopResult` (no run phase).
    """
    return run_loop(
        transport,
        None,
        FixedParams(np.zeros(8), 0),
        None,
        cpg.Gates(0.0, 0.0),
        loop._replace(stand_s=stand_s),
        safety,
        sink,
        stale_hint,
    )
