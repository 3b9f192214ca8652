"""``cpgjax deploy``: run the CPG on a Go1 (or the loopback simulated Go1), replaying parameters or optimizing them
online (:mod:`cpgjax.deployment.trials`), and what ``cpgjax deploy calibrate``
(:mod:`cpgjax.deployment.calibrate`) shares with it: reaching the robot and the loop's configuration. It reads its
typed, checked options (:mod:`cpgjax.deployment.options`), which :mod:`cpgjax.cli` builds from the command line.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket

import numpy as np

import cpgjax
from cpgjax import cpg, outputs, provenance
from cpgjax import hardware_io as hio
from cpgjax.deployment import tick_log
from cpgjax.deployment.options import DeployOptions, RobotOptions
from cpgjax.deployment.trials import OptimizerSpec, ReplayTrials, online_optimization
from cpgjax.go1 import constants
from cpgjax.go1 import model as go1_model
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import foot_force
from cpgjax.robot import safety as go1_safety
from cpgjax.robot import sim_server as sim
from cpgjax.robot import transport as go1_transport
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

log = logging.getLogger(__name__)


def loop_and_safety(options: RobotOptions) -> tuple[hio.LoopConfig, go1_safety.SafetyConfig]:
    """(LoopConfig, SafetyConfig) of the run's options (their safety limits checked when the options were
    made)."""
    return (
        hio.LoopConfig(
            realtime_priority=None if options.no_realtime else LOOP_PRIORITY,
            cpu=loop_cpu(options),
            busy_wait=options.busy_wait,
            poll_idle=not options.idle_halt,
        ),
        options.safety,
    )


LOOP_PRIORITY = 80  # SCHED_FIFO of the 1 kHz loop
SIM_PRIORITY = 85  # the simulated Go1's, above the loop's: it stands in for the robot, whose clock nothing stops
LOG_WRITER_PRIORITY = 75  # the per-tick log's writer thread, when the loop is real time (see tick_log)


def loop_cpu(options: RobotOptions) -> int | None:
    """The CPU the loop is pinned to: ``--cpu``; else the machine's last CPU, the loop's own on the robot (the
    optimizer and the per-tick log's writer run on the others). A simulated Go1 in real time shares it with the loop
    (a stall of that virtual CPU stops the simulated robot's clock with the loop's, docs/hardware.md). Not pinned
    in lockstep (no deadlines) or on a machine with one CPU."""
    if options.cpu is not None or (options.robot == "sim" and options.sim_pacing != "realtime"):
        return options.cpu
    return last_cpu()


def last_cpu() -> int | None:
    """The last CPU this process may use, the loop's by default; None on a machine with one CPU."""
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[-1] if len(cpus) > 1 else None


def tick_log_writer(path, loop: hio.LoopConfig) -> tick_log.TickLogWriter:
    """The per-tick log's writer for ``loop``: on the other CPUs, and at real-time priority below the loop's when
    the loop has one (a writer thread that holds the GIL must not be preempted by the simulated Go1 while the loop
    waits for it)."""
    return tick_log.TickLogWriter(
        path,
        cpus=hio.cpus_besides(loop.cpu),
        realtime_priority=None if loop.realtime_priority is None else LOG_WRITER_PRIORITY,
    )


def robot_mass_kg(payload_kg: float) -> float:
    """The Go1's mass in cpgjax's model plus the payload it carries [kg]."""
    return float(go1_model.load_model().body_subtreemass[go1_model.indices().trunk_body]) + payload_kg


@contextlib.contextmanager
def connect(options: RobotOptions):
    """(transport, simulated Go1 client or None) for the robot of the command line; both closed on exit."""
    server = None
    if options.robot == "sim":
        # The simulated robot shares the loop's CPU (loop_cpu), at a real-time priority above the loop's: nothing on
        # the machine delays its ticks, as nothing on the robot's computer delays the robot's, and a stall of that
        # virtual CPU stops both. Its clock's phase is locked to the loop's commands (sim_server.phase_correction),
        # so in the steady state its tick falls between the loop's command and the loop's next tick.
        cpu = loop_cpu(options)
        server = sim.SimGo1Client(
            pacing=options.sim_pacing,
            friction=options.friction,
            slope_deg=options.slope_deg,
            payload_kg=options.payload_kg,
            realtime_priority=None if options.no_realtime else SIM_PRIORITY,
            cpus=None if cpu is None else {cpu},
            physics=options.physics,
            noise_seed=options.seed,
        )
        ip, port, local_port = server.address[0], server.port, 0
    else:
        ip, port, local_port = options.robot_ip, options.robot_port, options.local_port
    try:
        if (options.transport or ("sdk" if options.robot == "go1" else "udp")) == "sdk":
            transport = go1_transport.SdkTransport(
                ip, port, local_port or _free_port(), power_level=options.power_level
            )
        elif options.robot == "sim" and options.sim_pacing == "lockstep":
            transport = go1_transport.LockstepTransport((ip, port))
        else:
            transport = go1_transport.UdpTransport((ip, port), local_port)
        try:
            yield transport, server
        finally:
            transport.close()
    finally:
        if server is not None:
            server.close()


def sim_calibration():
    """The simulated Go1's foot-sensor calibration (its offsets and scale are known by construction)."""
    return foot_force.FootForceCalibration(
        sim.FOOT_FORCE_OFFSET_COUNTS.astype(np.float64), np.full(4, sim.FOOT_FORCE_N_PER_COUNT)
    )


def run(options: DeployOptions) -> int:
    """``cpgjax deploy`` with its checked options (``log_dir`` a folder it may write). Returns 0 after a clean end,
    2 after a safety trip."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    gates = cpg.controller_gates(options.controller, options.gait)
    params, timing = first_params(options), trial_timing(options)
    loop, safety = loop_and_safety(options)
    options.log_dir.mkdir(parents=True, exist_ok=True)
    calibration = sim_calibration() if options.calibration is None else options.calibration
    log.info(
        "foot-force calibration: offsets %s counts, %s N/count", calibration.offset_counts, calibration.newton_per_count
    )
    calibration.save(options.log_dir / CALIBRATION_FILE)
    hint = stale_hint(options)
    with connect(options) as (transport, server), tick_log_writer(options.log_dir / tick_log.FILE_NAME, loop) as ticks:
        controller = compiled_controller.CompiledController(cpg.with_startup(cpg.CPGConfig(), options.startup))
        start_xy = None if server is None else server.stats()["trunk_xy_m"]
        if options.optimize:
            spec = OptimizerSpec(
                options.optimizer,
                options.seed,
                options.target_velocity_mps,
                bool(gates.tegotae),
                robot_mass_kg(options.payload_kg),
                str(options.log_dir),
                tuned_for(options),
                safe=options.safe,
            )
            result, rows, windows = online_optimization(
                transport,
                controller,
                calibration,
                gates,
                spec,
                params,
                options.trials,
                timing,
                loop,
                safety,
                ticks,
                hint,
                recover=stand_up(server),
            )
        else:
            replay = ReplayTrials(params, constants.ticks(options.duration_s), timing)
            result = hio.run_loop(transport, controller, replay, calibration, gates, loop, safety, ticks, hint)
            windows = replay.steady_windows
        truth = None
        if server is not None:
            truth = dict(trunk_start_xy_m=start_xy, trunk_end_xy_m=server.stats()["trunk_xy_m"])
            server.save_truth(options.log_dir / TRUTH_FILE)
    if not options.optimize:  # the figures after the loop: the robot is damped
        rows = replay.rows(
            robot_mass_kg(options.payload_kg), options.target_velocity_mps, options.seed, tuned_for(options)
        )
    if server is not None:
        rows = with_truth(rows, windows, options.log_dir)
    if rows:
        import pyarrow as pa
        import pyarrow.parquet as pq

        pq.write_table(pa.Table.from_pylist(rows), options.log_dir / outputs.TRIALS)
    return report(options, result, rows, truth)


TRUTH_FILE = "sim_truth.parquet"
CALIBRATION_FILE = "calibration.json"  # the foot-force calibration a run used, copied into its folder
OUTPUTS = (
    outputs.OutputFile(
        TRUTH_FILE, "the simulated Go1's true trunk state, one row per physics step", outputs.check_parquet
    ),
    outputs.OutputFile(CALIBRATION_FILE, "the foot-force calibration the run used", outputs.check_json),
)


def first_params(options: DeployOptions) -> np.ndarray | None:
    """The parameters the run walks first: a replay's --params, else the middle of the box; an optimization's
    --params as trial 0, else None (the optimizer's first random proposal, docs/decisions.md §16)."""
    return options.params if options.params is not None or options.optimize else param_space.midpoint()


def trial_timing(options: DeployOptions) -> protocol.TrialConfig:
    """Each trial's timing in loop ticks (1 ms): --transition-s and --steady-s with --optimize; a replay's run is cut
    into the protocol's trials (1.5 s settling, 3 s measured)."""
    if options.optimize:
        return protocol.TrialConfig(constants.ticks(options.transition_s), constants.ticks(options.steady_s))
    return protocol.TrialConfig()


def what_ran(options: DeployOptions, rows: list[dict]) -> dict:
    """What the run walked, from its options after a --params file's tuned-for values filled those the command line
    did not give: replay or optimization, the robot, the controller, the physics profile ("robot" on the Go1), the
    conditions (friction and slope the simulated Go1's, null on the Go1), v*, each trial's timing, the parameter
    file, the first parameters by name (:func:`first_params`) and each trial's (``rows``) with --optimize."""
    timing, params = trial_timing(options), first_params(options)
    return {
        "mode": "optimize" if options.optimize else "replay",
        "robot": options.robot,
        **tuned_for(options),
        "physics": options.physics if options.robot == "sim" else "robot",
        "startup": options.startup,
        "transition_s": constants.seconds(timing.transition_steps),
        "steady_s": constants.seconds(timing.steady_steps),
        "duration_s": None if options.optimize else options.duration_s,
        "num_trials": options.trials if options.optimize else None,
        "optimizer": options.optimizer if options.optimize else None,
        "seed": options.seed,
        "params_file": options.params_path,
        "params": None if params is None else param_space.as_dict(params),
        "trial_params": [
            {"trial": row["trial"], **{name: row[name] for name in param_space.PARAM_NAMES}} for row in rows
        ]
        if options.optimize
        else None,
    }


def stand_up(server: sim.SimGo1Client | None):
    """How an online optimization recovers from a safety stop that its gait caused (``trials.Recover``): the
    simulated Go1 is put back on its feet; on a real Go1 the operator is asked to, and nothing moves until they
    press Enter (end of input or Ctrl-C ends the run). The loop's soft start then stands the robot up."""

    def recover(trial: int, reason: str) -> bool:
        if server is not None:
            server.upright()
            return True
        try:
            input(
                f"trial {trial} ended with a safety stop ({reason}); the motors are damped. Put the robot on its "
                "feet, then press Enter to stand it up for the next trial (Ctrl-C ends the run): "
            )
        except (EOFError, KeyboardInterrupt):
            log.info("no recovery: the run ends after trial %d", trial)
            return False
        return True

    return recover


def with_truth(rows: list[dict], steady_windows: list[tuple[int, int]], log_dir) -> list[dict]:
    """Each trial's row with the simulated Go1's true figures beside the robot's estimate (``sim_server.trial_truth``
    over the robot ticks its steady phase observed: the per-tick log's run-phase ticks map a run tick to the robot
    tick of its observation; the truth is the simulated Go1's ``sim_truth.parquet``)."""
    import pyarrow.parquet as pq

    ticks, _ = tick_log.read_tick_log(log_dir / tick_log.FILE_NAME)
    run = ticks["robot_tick_ms"].to_numpy()[ticks["phase"].to_numpy() == hio.RUN]  # run tick → robot tick
    table = pq.read_table(log_dir / TRUTH_FILE)
    truth = {name: table[name].to_numpy() for name in table.column_names}
    out = []
    for i, row in enumerate(rows):  # a trial whose steady window the logs do not hold gets nulls
        first, last = steady_windows[i] if i < len(steady_windows) else (0, len(run))
        robot_ticks = (int(run[first]), int(run[last])) if last < len(run) else None
        out.append({**row, **sim.trial_truth(truth, robot_ticks)})
    return out


def tuned_for(options: DeployOptions) -> dict:
    """What a run's ``best_params.json`` records it was tuned for (:mod:`cpgjax.trial.tuned`): on the simulated Go1
    its physics profile and scenario; on the robot only the payload, the floor's friction and slope being unknown."""
    sim_only = dict(physics=options.physics, friction=options.friction, slope_deg=options.slope_deg)
    return dict(
        controller=options.controller,
        gait=options.gait,
        target_velocity_mps=options.target_velocity_mps,
        payload_kg=options.payload_kg,
        **(sim_only if options.robot == "sim" else dict.fromkeys(sim_only)),
    )


def stale_hint(options: RobotOptions) -> str:
    """What a stale-state trip adds to its reason: with the simulated Go1 in real time, where lockstep goes."""
    if options.robot != "sim" or options.sim_pacing != "realtime":
        return ""
    return (
        " (the simulated Go1 shares this machine's CPUs and did not keep time; `--sim-pacing lockstep` runs "
        "without deadlines, docs/hardware.md)"
    )


WALKED = ("trial", "objective", "velocity_x_mps", "distance_m", "cost_of_transport", "c_load_n", "c_slope_rad")
TRUE = ("true_velocity_x_mps", "true_velocity_y_mps", "true_distance_m")  # the simulated Go1's, beside the estimate


def walked_line(row: dict) -> str:
    if row.get("safety_stop"):
        return f"trial {row['trial']}: ended by a safety stop ({row['safety_stop']}), learned as unsafe"
    line = (
        f"trial {row['trial']}: J {row['objective']:.3f}, v_x {row['velocity_x_mps']:.3f} m/s, "
        f"{row['distance_m']:.2f} m in its steady phase, CoT {row['cost_of_transport']:.3f}"
    )
    if row.get("true_velocity_x_mps") is not None:
        line += (
            f" (the simulated Go1's truth: v_x {row['true_velocity_x_mps']:.3f} m/s, {row['true_distance_m']:.2f} m)"
        )
    return line


def report(options: DeployOptions, result: hio.LoopResult, rows: list[dict] = (), truth: dict | None = None) -> int:
    """Write ``run.json`` (how the run ended, how the robot walked in each complete trial, its timing, what it walked
    (:func:`what_ran`), and what ran it: the command line, cpgjax's version and commit, the machine) and print how
    the run ended, each trial's J, velocity, distance and CoT (from the robot's own sensors) and the timing. Returns
    the exit status: 0 after a clean end, 130 after Ctrl-C (a stop), 2 after a safety trip. ``truth``: the
    simulated Go1's true trunk position before and after the loop (its own state, beside the robot's estimate),
    None on the robot."""
    lockstep = options.robot == "sim" and options.sim_pacing == "lockstep"
    summary = {
        "trip": result.trip,
        "stopped": result.stopped,
        "events": result.events,
        "safety_stops": [{"tick": tick, "reason": reason} for tick, reason in result.safety_stops],
        "realtime": result.realtime,
        "pacing": "lockstep" if lockstep else "realtime",
        "rejected_packets": result.rejected_packets,
        "trials": [{k: _finite_or_none(row[k]) for k in (*WALKED, *TRUE) if k in row} for row in rows],
        "sim_truth": truth,
        "ran": what_ran(options, rows),
        "timing": result.timing(),
        "command": options.command_line,
        "cpgjax_version": cpgjax.__version__,
        "git_commit": provenance.git_commit(),
        "environment": provenance.environment(),
    }
    (options.log_dir / tick_log.RUN_FILE).write_text(json.dumps(summary, indent=1, default=str))
    ended = (
        f"safety trip: {result.trip}"
        if result.trip
        else "stopped by Ctrl-C (damped)"
        if result.stopped
        else "clean end"
    )
    if result.safety_stops:
        ended += (
            f" after {len(result.safety_stops)} safety stop(s) learned as unsafe trials, each followed by a "
            "stand-up: " + "; ".join(reason for _, reason in result.safety_stops)
        )
    shared = (
        "\nthe simulated Go1 shared the loop's CPU: its ticks are in these figures "
        "(the loop on a CPU of its own: benchmarks/hardware_loop.py)"
        if options.robot == "sim" and not lockstep and loop_cpu(options) is not None
        else ""
    )
    if truth is not None:
        moved = np.subtract(truth["trunk_end_xy_m"], truth["trunk_start_xy_m"])
        truth_line = (
            f"\nthe simulated Go1's true trunk moved {moved[0]:+.2f} m along x, {moved[1]:+.2f} m along y "
            f"over the whole run"
        )
    else:
        truth_line = ""
    walked = (
        "\n".join(walked_line(row) for row in rows)
        if rows
        else "no trial completed (a trial is 1.5 s of settling then 3 s measured)"
        if not options.optimize
        else "no trial completed"
    )
    # the run's outcome on stdout (its progress was logged on stderr)
    print(
        f"{ended}; per-tick log {options.log_dir / tick_log.FILE_NAME}\nhow the robot walked (its own sensors):\n"
        f"{walked}{truth_line}\n{hio.timing_table(summary['timing'], deadlines=not lockstep)}{shared}",
        flush=True,
    )
    return 2 if result.trip else 130 if result.stopped else 0


def _finite_or_none(value):
    """JSON has no NaN: a figure a trial did not measure (a safety stop before its steady phase) is null."""
    return None if isinstance(value, float) and not np.isfinite(value) else value


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
