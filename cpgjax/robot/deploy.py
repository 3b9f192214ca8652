"""The ``cpgjax deploy`` command line: run the CPG on a Go1 (or the loopback simulated Go1), replaying parameters
or optimizing them online (:mod:`cpgjax.robot.trials`, re-exported here), and ``cpgjax deploy calibrate``
(:mod:`cpgjax.robot.calibrate`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
from pathlib import Path

import numpy as np

from cpgjax.robot import cpu_dispatch
from cpgjax.trial import params as param_space
from cpgjax.robot.trials import (
    OptimizerSpec, TrialTiming, load_params,
    online_optimization)
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import foot_force
from cpgjax.robot import safety as go1_safety
from cpgjax.robot import transport as go1_transport

log = logging.getLogger(__name__)


def add_robot_args(p: argparse.ArgumentParser) -> None:
    """The options that choose and reach the robot (``cpgjax deploy`` and ``cpgjax deploy calibrate``)."""

    p.add_argument("--robot", choices=("sim", "go1"), required=True,
                   help="sim: start the simulated Go1 on 127.0.0.1; go1: the robot (low-level mode, EDU)")
    p.add_argument("--transport", choices=("udp", "sdk"), help="default: sdk for go1, udp for sim")
    p.add_argument("--robot-ip", default=go1_transport.GO1_ROBOT_IP, help="go1 only")
    p.add_argument("--robot-port", type=int, default=go1_transport.GO1_ROBOT_PORT, help="go1 only")
    p.add_argument("--local-port", type=int, default=go1_transport.GO1_LOCAL_PORT, help="go1 only")
    p.add_argument("--power-level", type=int, default=9, help="power protection level 1…10 (100 W each)")
    p.add_argument("--sim-pacing", choices=("realtime", "lockstep"), default="realtime",
                   help="lockstep: one physics step per command, the loop waits for each answer (not real time)")
    p.add_argument("--payload-kg", type=float, default=0.0, help="payload carried (counts in CoT; sim: simulated)")
    p.add_argument("--friction", type=float, default=0.6, help="sim only")
    p.add_argument("--slope-deg", type=float, default=0.0, help="sim only")
    p.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    p.add_argument("--cpu", type=int, help="pin the loop to this CPU (sim: the simulated Go1 to the others)")
    p.add_argument("--busy-wait", action="store_true",
                   help="spin through each period instead of sleeping (with --cpu; with --no-realtime unless the "
                   "kernel's real-time throttling is off); fewer overruns on a VM (docs/hardware.md)")


def loop_and_safety(args):
    """(LoopConfig, SafetyConfig) of the command line's options."""
    from cpgjax import hardware_io as hio

    return (hio.LoopConfig(realtime_priority=None if args.no_realtime else 80, cpu=args.cpu,
                           busy_wait=args.busy_wait),
            go1_safety.SafetyConfig(power_level=args.power_level))


def robot_mass_kg(payload_kg: float) -> float:
    """The Go1's mass in cpgjax's model plus the payload it carries [kg]."""
    from cpgjax.go1 import model as go1_model

    return float(go1_model.load_model().body_subtreemass[go1_model.indices().trunk_body]) + payload_kg


@contextlib.contextmanager
def connect(args):
    """(transport, simulated Go1 client or None) for the robot of the command line; both closed on exit."""
    from cpgjax.robot import sim_server as sim

    server = None
    if args.robot == "sim":
        # The simulated robot shares this machine's CPUs: real-time priority (below the loop's) keeps other
        # processes, the optimizer included, from starving it. With --cpu it runs on the other CPUs.
        server = sim.SimGo1Client(pacing=args.sim_pacing, friction=args.friction, slope_deg=args.slope_deg,
                                  payload_kg=args.payload_kg, realtime_priority=None if args.no_realtime else 70,
                                  cpus=sim.cpus_besides(args.cpu))
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
    from cpgjax.robot import sim_server as sim

    return foot_force.FootForceCalibration(sim.FOOT_FORCE_OFFSET_COUNTS.astype(np.float64),
                                    np.full(4, sim.FOOT_FORCE_N_PER_COUNT))


def main(argv=None) -> int:
    """``cpgjax deploy`` (and ``cpgjax deploy calibrate``). Returns 0 after a clean end, 2 after a safety trip."""
    argv = sys.argv[1:] if argv is None else list(argv)
    cpu_dispatch.request_inline()  # before any JAX computation: the loop's controller step runs on its own thread
    if argv[:1] == ["calibrate"]:
        from cpgjax.robot import calibrate

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
        calibration = foot_force.FootForceCalibration.load(args.calibration)
    log.info("foot-force calibration: offsets %s counts, %s N/count", calibration.offset_counts,
             calibration.newton_per_count)
    calibration.save(args.log_dir / "calibration.json")
    with connect(args) as (transport, _):
        controller = compiled_controller.CompiledController()
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
