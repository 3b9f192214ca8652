"""The deploy run's per-tick log: ``ticks.arrows``, an Arrow IPC stream written in batches as the 1 kHz loop runs, and
its summary (``cpgjax show`` on a robot run).

:class:`TickLogWriter` is the loop's :class:`~cpgjax.hardware_io.TickSink`: every ``LoopConfig.flush_ticks`` ticks
(and once at the end) the loop hands it a range of its tick buffer, and a thread of its own (deploy runs it on the
CPUs besides the loop's, at real-time priority below the loop's) writes it as one record batch straight to the
operating system (no user-space buffer). Handing over costs the loop
a queue put; the writing (≈ 0.4 ms per 1,000 ticks, once 254 ms when the file system stalled) happens while the
loop sleeps or on another CPU, with the GIL released during the file write. A trip keeps every tick up to it and
a killed process every batch written before the kill (at most a batch or two, 1–2 s, is lost).
:func:`read_tick_log` reads the complete batches of a file even when its writer was killed mid-batch.
:func:`summarize_run` tells what a run folder holds, including why the run ended.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import threading
from pathlib import Path

import numpy as np
import pyarrow as pa

from cpgjax import hardware_io as hio
from cpgjax import outputs
from cpgjax.go1 import constants
from cpgjax.robot.controller import OBSERVATION

FILE_NAME = "ticks.arrows"
RUN_FILE = "run.json"  # how a deploy run ended, its timing and what ran it (cpgjax.deployment.deploy writes it)
# Column (TickLog field, or derived) → Arrow type, for the columns that are written as they are.
_SCALARS = {
    "late_s": pa.float32(),
    "step_s": pa.float32(),
    "work_s": pa.float32(),
    "work_cpu_s": pa.float32(),
    "overrun": pa.bool_(),
    "phase": pa.int8(),
    "fresh": pa.bool_(),
    "robot_tick_ms": pa.uint32(),
    "stale_ticks": pa.int32(),
    "power_counter": pa.int16(),
    "trial": pa.int16(),
    "command_kp": pa.float32(),
    "command_kd": pa.float32(),
}
_VECTORS = {  # (n, width) fields, stored as fixed-size lists
    "q_rad": 12,
    "dq_rad_s": 12,
    "quaternion_wxyz": 4,
    "gyro_rad_s": 3,
    "foot_force_raw": 4,
    "obs": OBSERVATION.size,
    "command_q_rad": 12,
    "torque_nm": 12,
    "controller_torque_nm": 12,
}
_DESCRIPTION = {
    "tick": "loop tick since the start of the loop",
    "t_s": "start of the tick [s] since the loop's first tick",
    "late_s": "start of the tick − its deadline [s]",
    "phase": "loop phase: " + ", ".join(f"{i} {name}" for i, name in enumerate(hio.PHASE_NAMES)),
    "fresh": "a new robot state arrived this tick",
    "stale_ticks": "ticks without a new robot tick (watchdog)",
    "power_counter": "the power-protection counter",
    "trial": "the trial the parameters belong to",
    "q_rad": "latest robot state: joint angles",
    "obs": "observation given to the controller (run phase)",
    "torque_nm": "torque sent (after the guard)",
    "command_q_rad": "position target sent (PosStopF: off)",
    "controller_torque_nm": "torque the controller returned (run phase, before the guard)",
}


def schema() -> pa.Schema:
    fields = [pa.field("tick", pa.int64()), pa.field("t_s", pa.float64())]
    fields += [pa.field(name, kind) for name, kind in _SCALARS.items()]
    fields += [
        pa.field(name, pa.list_(pa.int16() if name == "foot_force_raw" else pa.float32(), width))
        for name, width in _VECTORS.items()
    ]
    return pa.schema(fields, metadata={"columns": json.dumps(_DESCRIPTION)})


class TickLogWriter:
    """Writes the loop's per-tick log to ``path`` (an Arrow IPC stream) in record batches; use as a context manager
    or call :meth:`close`."""

    def __init__(self, path: Path, cpus: set[int] | None = None, realtime_priority: int | None = None):
        self.path = Path(path)
        self._placement = cpus, realtime_priority
        self._schema = schema()
        self._file = pa.OSFile(str(self.path), "wb")  # unbuffered: each batch reaches the OS when written
        self._writer = pa.ipc.new_stream(self._file, self._schema)
        self._t0: float | None = None
        self.ticks = 0
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BaseException | None = None
        # Convert one tick of a log once, unwritten, before the loop runs: the first conversion's one-time work held
        # the GIL for milliseconds while the loop waited for it (3-8 ms stalls of the loop after its first batch).
        self._columns(hio.TickLog.allocate(1), slice(0, 1), range(1), 0.0)
        # Started here, before the loop takes real-time priority; the thread sets its own CPUs and priority.
        self._thread = threading.Thread(target=self._drain, name="tick-log-writer", daemon=True)
        self._thread.start()

    def write(self, log: hio.TickLog, rows: slice, ticks: range) -> None:
        """Queue ticks ``ticks`` (rows ``rows`` of the loop's ring buffer, which keeps them far longer than the
        writer takes) for writing."""
        self._queue.put((log, rows, ticks))

    def _drain(self) -> None:
        cpus, priority = self._placement  # each applies to this thread only (Linux: per-thread scheduling)
        with contextlib.suppress(OSError, AttributeError):
            if cpus:
                os.sched_setaffinity(0, cpus)
            if priority is not None:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        while (item := self._queue.get()) is not None:
            if self._error is None:
                try:
                    self._write_batch(*item)
                except BaseException as e:  # reported by close()
                    self._error = e

    def _columns(self, log: hio.TickLog, rows: slice, ticks: range, t0: float) -> pa.RecordBatch:
        columns = [pa.array(np.arange(ticks.start, ticks.stop)), pa.array(log.t_start_s[rows] - t0)]
        columns += [pa.array(getattr(log, name)[rows], kind) for name, kind in _SCALARS.items()]
        for name, width in _VECTORS.items():
            values = getattr(log, name)[rows]
            columns.append(pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), width))
        return pa.RecordBatch.from_arrays(columns, schema=self._schema)

    def _write_batch(self, log: hio.TickLog, rows: slice, ticks: range) -> None:
        if self._t0 is None:
            self._t0 = float(log.t_start_s[rows][0]) if len(ticks) else 0.0
        self._writer.write_batch(self._columns(log, rows, ticks, self._t0))
        self.ticks = ticks.stop

    def close(self) -> None:
        """Write what is queued, end the stream and close the file."""
        self._queue.put(None)
        self._thread.join()
        self._writer.close()
        self._file.close()
        if self._error is not None:
            raise OSError(f"the per-tick log {self.path} could not be written: {self._error}") from self._error

    def __enter__(self) -> TickLogWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_tick_log(path: Path) -> tuple[pa.Table, bool]:
    """(the complete record batches of a tick log, whether the file ended cleanly). A file whose writer was killed
    gives the batches written before the kill and False."""
    batches, complete = [], True
    with pa.OSFile(str(path), "rb") as f:
        try:
            reader = pa.ipc.open_stream(f)
        except pa.ArrowInvalid:
            return schema().empty_table(), False
        while True:
            try:
                batches.append(reader.read_next_batch())
            except StopIteration:
                break
            except (pa.ArrowInvalid, OSError):
                complete = False
                break
    return pa.Table.from_batches(batches, schema=schema()), complete


def end_reason(run: dict | None) -> str:
    """Why a run ended, from its ``run.json`` (None: there is none)."""
    if run is None:
        return "unknown: no run.json (the process was killed, or the run is still going)"
    if run.get("trip"):
        return f"safety trip: {run['trip']}"
    if run.get("stopped"):
        return "stopped by Ctrl-C (damped; not a trip)"
    return "clean end"


def summarize_run(run_dir: Path) -> str:
    """A few lines on a deploy run folder: how it ended, what ran it, its per-tick log (ticks, phases, trials,
    timing, the watchdog) and its per-trial rows."""
    run_dir = Path(run_dir)
    run_file = run_dir / RUN_FILE
    try:
        run = json.loads(run_file.read_text()) if run_file.exists() else None
    except (OSError, UnicodeDecodeError, ValueError) as err:
        run, damaged = None, f"{run_file} is corrupt or truncated ({type(err).__name__})"
    else:
        damaged = None
    if not isinstance(run, dict):
        run = None
    lines = [f"deploy run {run_dir}", f"ended: {damaged or end_reason(run)}"]
    if run is not None and run.get("command"):
        lines.append(
            f"command: {run['command']} (cpgjax {run.get('cpgjax_version')}, commit {run.get('git_commit')}, "
            f"scheduling: {run.get('realtime')})"
        )
    if run is not None and run.get("events"):
        tick, phase, message = run["events"][-1]
        lines.append(f"last event: tick {tick}, {phase} ({message})")
    path = run_dir / FILE_NAME
    if not path.exists():
        lines.append(f"no per-tick log ({FILE_NAME} missing)")
        return "\n".join(lines)
    table, complete = read_tick_log(path)
    n = table.num_rows
    lines.append(
        f"per-tick log {path.name}: {n} ticks ({constants.seconds(n):.1f} s)"
        + ("" if complete else ", truncated: its writer stopped mid-batch (the complete batches are shown)")
    )
    if n == 0:
        return "\n".join(lines)
    phase = table["phase"].to_numpy()
    spans = [
        f"{name} {constants.seconds(np.sum(phase == i)):.2f} s"
        for i, name in enumerate(hio.PHASE_NAMES)
        if np.any(phase == i)
    ]
    lines.append("time per phase: " + ", ".join(spans))
    last = table.slice(n - 1)
    lines.append(
        f"last tick: {last['tick'][0].as_py()}, phase {hio.PHASE_NAMES[last['phase'][0].as_py()]}, "
        f"trial {last['trial'][0].as_py()}"
    )
    active = phase > hio.CONNECT
    late_us = table["late_s"].to_numpy()[active] * 1e6
    work_us = table["work_s"].to_numpy()[active] * 1e6
    if late_us.size:
        lines.append(
            f"lateness p99 {np.percentile(late_us, 99):.0f} µs, max {late_us.max():.0f} µs; tick work p99 "
            f"{np.percentile(work_us, 99):.0f} µs; overruns {int(table['overrun'].to_numpy().sum())}"
        )
    stale = table["stale_ticks"].to_numpy()[active]
    lines.append(
        f"watchdog: longest wait for a new robot tick {int(stale.max()) if stale.size else 0} ticks; "
        f"trials reached {int(table['trial'].to_numpy().max()) + 1}"
    )
    trials_file = run_dir / outputs.TRIALS
    if trials_file.exists():
        import pyarrow.parquet as pq

        lines.append(f"per-trial rows: {pq.read_metadata(trials_file).num_rows} in {trials_file.name}")
    return "\n".join(lines)


def check_tick_log(path: Path) -> str | None:
    """A per-tick log's check: it ends after a complete batch."""
    return None if read_tick_log(path)[1] else "truncated (its writer stopped mid-batch)"


OUTPUTS = (
    outputs.OutputFile(FILE_NAME, "the 1 kHz loop's per-tick log", check_tick_log),
    outputs.OutputFile(RUN_FILE, "how the robot run ended, its timing and what ran it", outputs.check_json),
)
