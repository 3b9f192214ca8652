"""Deploy the CPG on a Go1 (or the loopback simulated Go1): replay parameters, or optimize them online on the
robot (the paper's Algorithm 1), and the ``cpgjax deploy`` command line.

Online optimization runs trials back to back in robot time (loop ticks): 1.5 s of transition, interpolating the
parameters linearly from the previous set to the new one, then 3 s of steady state whose per-tick signals (leg
odometry velocity, power ⟨|τ|, |q̇|⟩, mean foot force, roll, pitch — all from the robot's own sensors) make the trial
record; J, CoT and the context come from ``cpgjax.objective`` as in simulation. The optimizer runs in a separate
process (:func:`_optimizer_worker`), so the 1 kHz loop never waits for it: after a trial the robot keeps walking
with the current parameters until the next proposal arrives (the wait is logged per trial). The worker writes the
per-trial log (``trials.parquet``, ``trials.rrd`` for rerun) and the best parameters (``best_params.json``, which
``--params`` replays).

The optimizer is anything with ``propose(context) -> params`` and ``observe(params, context, record, objective)``
(:class:`OnlineOptimizer`): the contextual BO of ``cpgjax.bo`` (:class:`BayesianOptimizer`, the default) or
:class:`RandomSearch` (a baseline, and the fast stand-in of the tests).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import multiprocessing
import os
import sys
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np

from cpgjax import params as param_space

log = logging.getLogger(__name__)

# Columns of the steady-phase buffer, taken from the controller's flat output each tick.
_SIGNALS = ("v_x", "v_y", "power", "load", "roll", "pitch", "saturated")


class TrialTiming(NamedTuple):
    transition_ticks: int = 1500  # 1.5 s at 1 kHz
    steady_ticks: int = 3000  # 3 s


class OnlineOptimizer(Protocol):
    """What online optimization needs from an optimizer (runs in the worker process, never in the loop)."""

    def propose(self, context: np.ndarray) -> np.ndarray:
        """Next parameters (8,), physical units, for the context [c_load N, c_slope rad]."""

    def observe(self, params: np.ndarray, context: np.ndarray, record, objective: float) -> None:
        """One finished trial."""


class RandomSearch:
    """Uniform random proposals in the paper's box (σ_N at the midpoint when Tegotae is off)."""

    def __init__(self, seed: int = 0, tegotae: bool = True):
        self._rng = np.random.default_rng(seed)
        self._tegotae = tegotae

    def propose(self, context: np.ndarray) -> np.ndarray:
        x = param_space.from_unit(self._rng.uniform(size=param_space.NUM_PARAMS))
        if not self._tegotae:
            x[param_space.SIGMA_N_INDEX] = param_space.midpoint()[param_space.SIGMA_N_INDEX]
        return x

    def observe(self, params, context, record, objective) -> None:
        pass


class BayesianOptimizer:
    """Adapter from ``cpgjax.bo``'s pure functions (``init`` / ``propose`` / ``observe``, scalar objectives) to
    :class:`OnlineOptimizer`. σ_N is an inactive input when Tegotae is off (decisions.md §13)."""

    def __init__(self, seed: int, tegotae: bool):
        import jax
        import jax.numpy as jnp

        from cpgjax import bo

        active = np.ones(param_space.NUM_PARAMS, bool)
        active[param_space.SIGMA_N_INDEX] = tegotae
        self._jax, self._jnp = jax, jnp
        self._key = jax.random.PRNGKey(seed)
        self._opt = bo.make_optimizer(bo.paper_config())
        self._state = self._opt.init(active_dims=jnp.asarray(active))

    def propose(self, context: np.ndarray) -> np.ndarray:
        self._key, key = self._jax.random.split(self._key)
        return np.asarray(self._opt.propose(self._state, self._jnp.asarray(context, self._jnp.float32), key),
                          np.float64)

    def observe(self, params, context, record, objective) -> None:
        jnp = self._jnp
        self._state, _ = self._opt.observe(self._state, jnp.asarray(params, jnp.float32),
                                           jnp.asarray(context, jnp.float32), jnp.asarray(objective, jnp.float32))


class OptimizerSpec(NamedTuple):
    """Everything the worker process needs (picklable)."""

    kind: str  # "random" or "bo"
    seed: int
    target_velocity_mps: float
    tegotae: bool
    total_mass_kg: float
    log_dir: str
    controller: str
    dt_s: float = 0.001


def trial_record(signals: np.ndarray, total_mass_kg: float, dt_s: float = 0.001):
    """``objective.TrialRecord`` from the steady phase's per-tick robot signals (T, len(_SIGNALS)).

    A fall ends the run through the safety layer (tilt stop) before a trial completes, so ``fell`` and ``failed``
    are 0 for every completed trial.
    """
    from cpgjax.objective import TrialRecord

    v = signals[:, 0:2].astype(np.float64)
    roll, pitch = signals[:, 4], signals[:, 5]
    return TrialRecord(
        velocity_xy_mps=v, energy_j=float(np.sum(signals[:, 2]) * dt_s), distance_m=float(np.sum(v[:, 0]) * dt_s),
        total_mass_kg=float(total_mass_kg), c_load_n=float(np.mean(signals[:, 3])),
        c_slope_rad=float(np.mean(pitch)), roll_mean_rad=float(np.mean(roll)), roll_std_rad=float(np.std(roll)),
        pitch_std_rad=float(np.std(pitch)), saturation_fraction=float(np.sum(signals[:, 6]) / (12.0 * len(v))),
        fell=0.0, failed=0.0)


class _TrialLog:
    """Per-trial rows → ``trials.parquet`` (rewritten after every trial) and ``trials.rrd`` (rerun)."""

    def __init__(self, log_dir: Path):
        import rerun as rr

        self._rr = rr
        self.dir = log_dir
        self.rows: list[dict] = []
        self._rec = rr.RecordingStream("cpgjax_deploy")
        self._rec.save(str(log_dir / "trials.rrd"))

    def append(self, row: dict) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        self.rows.append(row)
        pq.write_table(pa.Table.from_pylist(self.rows), self.dir / "trials.parquet")
        rr, rec = self._rr, self._rec
        rec.set_time("trial", sequence=row["trial"])
        for key in ("objective", "cost_of_transport", "v_x_mps", "c_load_n", "c_slope_rad", "wait_s"):
            rec.log(f"trial/{key}", rr.Scalars(row[key]))
        for name in param_space.PARAM_NAMES:
            rec.log(f"params/{name}", rr.Scalars(row[name]))

    def close(self) -> None:
        self._rec.flush()


def save_params(path, params: np.ndarray, **info) -> None:
    """Parameters as JSON {names: values, ...info}; :func:`load_params` reads it back."""
    Path(path).write_text(json.dumps({"params": param_space.as_dict(params), **info}, indent=1))


def load_params(path) -> np.ndarray:
    """Parameters (8,) from a :func:`save_params` file (or a JSON list of 8 numbers), validated."""
    data = json.loads(Path(path).read_text())
    if isinstance(data, dict):
        data = [data["params"][name] for name in param_space.PARAM_NAMES]
    return param_space.validate(np.asarray(data, np.float64), what=str(path))


def _optimizer_worker(conn, spec: OptimizerSpec) -> None:
    """The optimizer's process: observe each finished trial, answer the next proposal at once, then log."""
    import jax

    os.nice(10)  # the robot's loop (and, on one machine, the simulated robot) come first
    jax.config.update("jax_platforms", "cpu")
    from cpgjax import objective

    optimizer = (BayesianOptimizer(spec.seed, spec.tegotae) if spec.kind == "bo"
                 else RandomSearch(spec.seed, spec.tegotae))
    trial_log = _TrialLog(Path(spec.log_dir))
    best = -np.inf
    conn.send(("ready",))
    while True:
        message = conn.recv()
        if message[0] == "stop":
            break
        _, trial, x, signals, wait_ticks = message
        record = trial_record(signals, spec.total_mass_kg, spec.dt_s)
        j = float(objective.objective(record, spec.target_velocity_mps))
        c = np.asarray(objective.context(record), np.float64)
        optimizer.observe(x, c, record, j)
        conn.send(("params", optimizer.propose(c)))
        row = {"trial": trial, "objective": j, "cost_of_transport": float(objective.cost_of_transport(record)),
               "v_x_mps": float(np.mean(record.velocity_xy_mps[:, 0])),
               "v_y_mps": float(np.mean(record.velocity_xy_mps[:, 1])), "c_load_n": float(c[0]),
               "c_slope_rad": float(c[1]), "roll_std_rad": record.roll_std_rad, "pitch_std_rad": record.pitch_std_rad,
               "saturation_fraction": record.saturation_fraction, "wait_s": wait_ticks * spec.dt_s,
               **param_space.as_dict(x)}
        trial_log.append(row)
        if j > best:
            best = j
            save_params(Path(spec.log_dir) / "best_params.json", x, objective=j, trial=trial,
                        controller=spec.controller, target_velocity_mps=spec.target_velocity_mps)
    trial_log.close()
    conn.send(("done", trial_log.rows))


class TrialRunner:
    """A :class:`~cpgjax.hardware_io.ParamSchedule` running Algorithm 1's trials inside the 1 kHz loop.

    Cheap per tick: an interpolation, one row copy, and (only while waiting for a proposal) a pipe poll.
    """

    def __init__(self, conn, initial_params: np.ndarray, num_trials: int, timing: TrialTiming = TrialTiming()):
        from cpgjax import hardware_io as hio

        self._conn = conn
        self._timing = timing
        self._columns = np.array([hio.OUT_VELOCITY.start, hio.OUT_VELOCITY.start + 1, hio.OUT_POWER, hio.OUT_LOAD,
                                  hio.OUT_RPY.start, hio.OUT_RPY.start + 1, hio.OUT_SATURATED])
        self._signals = np.zeros((timing.steady_ticks, len(_SIGNALS)), np.float32)
        self._previous = self._current = np.asarray(initial_params, np.float32)
        self._num_trials = num_trials
        self.trials_done = 0
        self._tick_in_trial = 0
        self._waiting_since = None  # run tick at which the last trial was handed to the optimizer
        self._wait_ticks = 0  # ticks spent waiting for the current trial's parameters
        self.finished = num_trials == 0

    def params(self, run_tick: int) -> np.ndarray:
        k = self._tick_in_trial
        if self._waiting_since is None and k < self._timing.transition_ticks:
            blend = (k + 1.0) / self._timing.transition_ticks
            return self._previous + np.float32(blend) * (self._current - self._previous)
        return self._current

    def record(self, run_tick: int, out: np.ndarray) -> None:
        if self._waiting_since is not None:
            if self._conn.poll():
                _, proposal = self._conn.recv()
                self._previous, self._current = self._current, np.asarray(proposal, np.float32)
                self._wait_ticks = run_tick - self._waiting_since
                self._waiting_since, self._tick_in_trial = None, 0
            return
        steady = self._tick_in_trial - self._timing.transition_ticks
        if steady >= 0:
            self._signals[steady] = out[self._columns]
        self._tick_in_trial += 1
        if steady + 1 == self._timing.steady_ticks:
            self._conn.send(("trial", self.trials_done, self._current.astype(np.float64), self._signals.copy(),
                             self._wait_ticks))
            self.trials_done += 1
            self.finished = self.trials_done >= self._num_trials
            self._waiting_since = run_tick


def online_optimization(transport, controller, calibration, gates, spec: OptimizerSpec, initial_params: np.ndarray,
                        num_trials: int, timing: TrialTiming = TrialTiming(), loop=None, safety=None):
    """Algorithm 1 on the robot: ``num_trials`` trials back to back, the optimizer in its own process.

    Returns (LoopResult, per-trial rows). The log files are in ``spec.log_dir``.
    """
    from cpgjax import hardware_io as hio

    Path(spec.log_dir).mkdir(parents=True, exist_ok=True)
    context = multiprocessing.get_context("spawn")  # never fork a process that has started JAX
    conn, worker_conn = context.Pipe()
    worker = context.Process(target=_optimizer_worker, args=(worker_conn, spec), daemon=True)
    worker.start()
    try:
        if not conn.poll(120.0):
            raise RuntimeError("the optimizer process did not start")
        conn.recv()  # ready: its imports are done before the loop starts
        runner = TrialRunner(conn, initial_params, num_trials, timing)
        result = hio.run_loop(transport, controller, runner, calibration, gates, loop or hio.LoopConfig(),
                              safety or hio.SafetyConfig())
        conn.send(("stop",))
        rows = []
        while conn.poll(120.0):
            message = conn.recv()
            if message[0] == "done":
                rows = message[1]
                break
        worker.join(timeout=30.0)
    finally:
        if worker.is_alive():
            worker.kill()
    return result, rows


def add_robot_args(p: argparse.ArgumentParser) -> None:
    """The options that choose and reach the robot (``cpgjax deploy`` and ``cpgjax deploy calibrate``)."""
    from cpgjax import hardware_io as hio

    p.add_argument("--robot", choices=("sim", "go1"), required=True,
                   help="sim: start the simulated Go1 on 127.0.0.1; go1: the robot (low-level mode, EDU)")
    p.add_argument("--transport", choices=("udp", "sdk"), help="default: sdk for go1, udp for sim")
    p.add_argument("--robot-ip", default=hio.GO1_ROBOT_IP, help="go1 only")
    p.add_argument("--robot-port", type=int, default=hio.GO1_ROBOT_PORT, help="go1 only")
    p.add_argument("--local-port", type=int, default=hio.GO1_LOCAL_PORT, help="go1 only")
    p.add_argument("--power-level", type=int, default=9, help="power protection level 1…10 (100 W each)")
    p.add_argument("--sim-pacing", choices=("realtime", "lockstep"), default="realtime",
                   help="lockstep: one physics step per command, the loop waits for each answer (not real time)")
    p.add_argument("--payload-kg", type=float, default=0.0, help="payload carried (counts in CoT; sim: simulated)")
    p.add_argument("--friction", type=float, default=0.6, help="sim only")
    p.add_argument("--slope-deg", type=float, default=0.0, help="sim only")
    p.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    p.add_argument("--cpu", type=int, help="pin the loop to this CPU (sim: the simulated Go1 to the others)")


def loop_and_safety(args):
    """(LoopConfig, SafetyConfig) of the command line's options."""
    from cpgjax import hardware_io as hio

    return (hio.LoopConfig(realtime_priority=None if args.no_realtime else 80, cpu=args.cpu),
            hio.SafetyConfig(power_level=args.power_level))


def robot_mass_kg(payload_kg: float) -> float:
    """The Go1's mass in cpgjax's model plus the payload it carries [kg]."""
    from cpgjax import go1_model

    return float(go1_model.load_model().body_subtreemass[go1_model.indices().trunk_body]) + payload_kg


@contextlib.contextmanager
def connect(args):
    """(transport, simulated Go1 client or None) for the robot of the command line; both closed on exit."""
    from cpgjax import hardware_io as hio
    from cpgjax import sim_go1_server as sim

    server = None
    if args.robot == "sim":
        # The simulated robot shares this machine's CPUs: real-time priority (below the loop's) keeps other
        # processes, the optimizer included, from starving it. With --cpu it runs on the other CPUs.
        sim_cpus = None if args.cpu is None else (set(os.sched_getaffinity(0)) - {args.cpu}) or None
        server = sim.SimGo1Client(pacing=args.sim_pacing, friction=args.friction, slope_deg=args.slope_deg,
                                  payload_kg=args.payload_kg, realtime_priority=None if args.no_realtime else 70,
                                  cpus=sim_cpus)
        ip, port, local_port = server.address[0], server.port, 0
    else:
        ip, port, local_port = args.robot_ip, args.robot_port, args.local_port
    try:
        if (args.transport or ("sdk" if args.robot == "go1" else "udp")) == "sdk":
            transport = hio.SdkTransport(ip, port, local_port or _free_port(), power_level=args.power_level)
        elif args.robot == "sim" and args.sim_pacing == "lockstep":
            transport = hio.LockstepTransport((ip, port))
        else:
            transport = hio.UdpTransport((ip, port), local_port)
        try:
            yield transport, server
        finally:
            transport.close()
    finally:
        if server is not None:
            server.close()


def _parse_args(argv):
    from cpgjax import cpg

    p = argparse.ArgumentParser(prog="cpgjax deploy", description="Run the CPG controller at 1 kHz on a Go1 or on "
                                "the loopback simulated Go1; replay parameters or optimize them online. "
                                "`cpgjax deploy calibrate --help`: the foot-force calibration.")
    add_robot_args(p)
    what = p.add_mutually_exclusive_group()
    what.add_argument("--params", type=Path, help="replay these parameters (JSON from save_params / best_params)")
    what.add_argument("--optimize", action="store_true", help="online optimization (Algorithm 1)")
    p.add_argument("--trials", type=int, default=10, help="trials of online optimization")
    p.add_argument("--optimizer", choices=("bo", "random"), default="bo")
    p.add_argument("--controller", choices=cpg.CONTROLLERS, default="vmc_tegotae")
    p.add_argument("--target-velocity", type=float, default=0.5, help="v_x* [m/s] of the objective")
    p.add_argument("--duration-s", type=float, default=10.0, help="run time when replaying parameters")
    p.add_argument("--transition-s", type=float, default=1.5)
    p.add_argument("--steady-s", type=float, default=3.0)
    p.add_argument("--log-dir", type=Path, default=Path("runs/deploy"))
    p.add_argument("--calibration", type=Path, help="foot-force calibration JSON from `cpgjax deploy calibrate` "
                   "(required with --robot go1; sim: the simulated sensor's exact calibration by default)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.robot == "go1" and args.calibration is None:
        p.error("--robot go1 needs --calibration FILE (run `cpgjax deploy calibrate` first, see docs/hardware.md)")
    return args


def sim_calibration():
    """The simulated Go1's foot-sensor calibration (its offsets and scale are known by construction)."""
    from cpgjax import hardware_io as hio
    from cpgjax import sim_go1_server as sim

    return hio.FootForceCalibration(sim.FOOT_FORCE_OFFSET_COUNTS.astype(np.float64),
                                    np.full(4, sim.FOOT_FORCE_N_PER_COUNT))


def main(argv=None) -> int:
    """``cpgjax deploy`` (and ``cpgjax deploy calibrate``). Returns 0 after a clean end, 2 after a safety trip."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["calibrate"]:
        from cpgjax import calibrate

        return calibrate.main(argv[1:])
    from cpgjax import cpg
    from cpgjax import hardware_io as hio

    args = _parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    gates = cpg.controller_gates(args.controller)
    params = load_params(args.params) if args.params else param_space.midpoint()
    loop, safety = loop_and_safety(args)
    args.log_dir.mkdir(parents=True, exist_ok=True)
    if args.calibration is None:
        calibration = sim_calibration()
    else:
        calibration = hio.FootForceCalibration.load(args.calibration)
    log.info("foot-force calibration: offsets %s counts, %s N/count", calibration.offset_counts,
             calibration.newton_per_count)
    calibration.save(args.log_dir / "calibration.json")
    with connect(args) as (transport, _):
        controller = hio.CompiledController()
        if args.optimize:
            spec = OptimizerSpec(args.optimizer, args.seed, args.target_velocity, bool(gates.tegotae),
                                 robot_mass_kg(args.payload_kg), str(args.log_dir), args.controller)
            timing = TrialTiming(round(args.transition_s * 1000), round(args.steady_s * 1000))
            result, rows = online_optimization(transport, controller, calibration, gates, spec, params,
                                               args.trials, timing, loop, safety)
            for row in rows:
                log.info("trial %d: J = %.3f, v_x = %.2f m/s, context = (%.1f N, %.3f rad)", row["trial"],
                         row["objective"], row["v_x_mps"], row["c_load_n"], row["c_slope_rad"])
        else:
            result = hio.run_loop(transport, controller, hio.FixedParams(params, round(args.duration_s * 1000)),
                                  calibration, gates, loop, safety)
    summary = {"trip": result.trip, "events": result.events, "realtime": result.realtime,
               "rejected_packets": result.rejected_packets, "timing": result.timing()}
    (args.log_dir / "run.json").write_text(json.dumps(summary, indent=1))
    log.info("%s; timing %s", f"safety trip: {result.trip}" if result.trip else "clean end", summary["timing"])
    return 2 if result.trip else 0


def _free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


if __name__ == "__main__":
    sys.exit(main())
