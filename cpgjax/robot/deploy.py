"""``cpgjax deploy``: run the CPG on a Go1 (or the loopback simulated Go1), replaying parameters or optimizing them
online (:mod:`cpgjax.robot.trials`), and what ``cpgjax deploy calibrate`` (:mod:`cpgjax.robot.calibrate`) shares
with it: reaching the robot and the loop's configuration. The options are defined in :mod:`cpgjax.cli`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket

import numpy as np

from cpgjax import cpg
from cpgjax import hardware_io as hio
from cpgjax.go1 import model as go1_model
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import foot_force, tick_log
from cpgjax.robot import safety as go1_safety
from cpgjax.robot import sim_server as sim
from cpgjax.robot import transport as go1_transport
from cpgjax.robot.trials import OptimizerSpec, online_optimization
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

log = logging.getLogger(__name__)


def loop_and_safety(args):
    """(LoopConfig, SafetyConfig) of the command line's options, the safety limits checked
    (:func:`go1_safety.check_safety`)."""
    return (hio.LoopConfig(realtime_priority=None if args.no_realtime else 80, cpu=args.cpu,
                           busy_wait=args.busy_wait),
            go1_safety.check_safety(go1_safety.SafetyConfig(power_level=args.power_level)))


def robot_mass_kg(payload_kg: float) -> float:
    """The Go1's mass in cpgjax's model plus the payload it carries [kg]."""
    return float(go1_model.load_model().body_subtreemass[go1_model.indices().trunk_body]) + payload_kg


@contextlib.contextmanager
def connect(args):
    """(transport, simulated Go1 client or None) for the robot of the command line; both closed on exit."""
    server = None
    if args.robot == "sim":
        # The simulated robot shares this machine's CPUs: real-time priority (below the loop's) keeps other
        # processes, the optimizer included, from starving it. With --cpu it runs on the other CPUs.
        server = sim.SimGo1Client(pacing=args.sim_pacing, friction=args.friction, slope_deg=args.slope_deg,
                                  payload_kg=args.payload_kg, realtime_priority=None if args.no_realtime else 70,
                                  cpus=sim.cpus_besides(args.cpu), physics=args.physics)
        ip, port, local_port = server.address[0], server.port, 0
    else:
        ip, port, local_port = args.robot_ip, args.robot_port, args.local_port
    try:
        if (args.transport or ("sdk" if args.robot == "go1" else "udp")) == "sdk":
            transport = go1_transport.SdkTransport(ip, port, local_port or _free_port(), power_level=args.power_level)
        elif args.robot == "sim" and args.sim_pacing == "lockstep":
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
    return foot_force.FootForceCalibration(sim.FOOT_FORCE_OFFSET_COUNTS.astype(np.float64),
                                    np.full(4, sim.FOOT_FORCE_N_PER_COUNT))


def run(args) -> int:
    """``cpgjax deploy`` with its parsed options (checked by the parser: ``params`` an array, ``calibration`` a
    :class:`foot_force.FootForceCalibration` or None, ``log_dir`` a folder it may write). Returns 0 after a clean
    end, 2 after a safety trip."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    gates = cpg.controller_gates(args.controller)
    # Replay: --params or the middle of the box. Optimizing: --params as trial 0, else the optimizer's first random
    # proposal (docs/decisions.md §16).
    params = args.params if args.params is not None or args.optimize else param_space.midpoint()
    loop, safety = loop_and_safety(args)
    args.log_dir.mkdir(parents=True, exist_ok=True)
    calibration = sim_calibration() if args.calibration is None else foot_force.check_calibration(args.calibration)
    log.info("foot-force calibration: offsets %s counts, %s N/count", calibration.offset_counts,
             calibration.newton_per_count)
    calibration.save(args.log_dir / "calibration.json")
    hint = stale_hint(args)
    with connect(args) as (transport, _), tick_log.TickLogWriter(args.log_dir / tick_log.FILE_NAME) as ticks:
        controller = compiled_controller.CompiledController()
        if args.optimize:
            spec = OptimizerSpec(args.optimizer, args.seed, args.target_velocity_mps, bool(gates.tegotae),
                                 robot_mass_kg(args.payload_kg), str(args.log_dir), args.controller)
            timing = protocol.TrialConfig(round(args.transition_s * 1000), round(args.steady_s * 1000))
            result, _ = online_optimization(transport, controller, calibration, gates, spec, params,
                                            args.trials, timing, loop, safety, ticks, hint)
        else:
            result = hio.run_loop(transport, controller, hio.FixedParams(params, round(args.duration_s * 1000)),
                                  calibration, gates, loop, safety, ticks, hint)
    return report(args, result)


def stale_hint(args) -> str:
    """What a stale-state trip adds to its reason: with the simulated Go1 in real time, where lockstep goes."""
    if args.robot != "sim" or args.sim_pacing != "realtime":
        return ""
    return (" (the simulated Go1 shares this machine's CPUs and did not keep time; `--sim-pacing lockstep` runs "
            "without deadlines, docs/hardware.md)")


def report(args, result: hio.LoopResult) -> int:
    """Write ``run.json`` and print how the run ended and its timing. Returns the exit status: 0 after a clean end,
    130 after Ctrl-C (a stop), 2 after a safety trip."""
    lockstep = args.robot == "sim" and args.sim_pacing == "lockstep"
    summary = {"trip": result.trip, "stopped": result.stopped, "events": result.events, "realtime": result.realtime,
               "pacing": "lockstep" if lockstep else "realtime", "rejected_packets": result.rejected_packets,
               "timing": result.timing()}
    (args.log_dir / "run.json").write_text(json.dumps(summary, indent=1))
    ended = (f"safety trip: {result.trip}" if result.trip else "stopped by Ctrl-C (damped)" if result.stopped
             else "clean end")
    log.info("%s; per-tick log %s\n%s", ended, args.log_dir / tick_log.FILE_NAME,
             hio.timing_table(summary["timing"], deadlines=not lockstep))
    return 2 if result.trip else 130 if result.stopped else 0


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]

