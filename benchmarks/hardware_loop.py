"""Benchmark: the deployed 1 kHz loop against the loopback simulated Go1 (127.0.0.1 only).

Runs ``hardware_io.run_loop`` (soft start, then the CPG walking with the midpoint parameters) against the simulated
Go1 in real-time pacing (a separate process stepping C MuJoCo at 1 kHz) and reports the controller-step latency
(pack + compiled call + unpack: median, p99, max) and the loop period (median, p1, p99, max) and overruns over the
run. Targets (issue 5): step p99 ≤ 200 µs; period p99 within ±100 µs of 1 ms; ≤ 1 overrun per 10,000 ticks.

    python benchmarks/hardware_loop.py            # 60 s of walking
    python benchmarks/hardware_loop.py --quick    # 10 s

The last line of the output is one JSON object with the figures (units in the names).
"""

import argparse
import json
import os
import time

from cpgjax import cpg, deploy, params, study_io
from cpgjax import hardware_io as hio
from cpgjax import sim_go1_server as sim


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="10 s instead of 60 s")
    parser.add_argument("--duration-s", type=float, help="walking time (default 60, --quick 10)")
    parser.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    parser.add_argument("--cpu", type=int, help="pin the loop to this CPU")
    parser.add_argument("--transport", choices=("udp", "sdk"), default="udp")
    args = parser.parse_args()
    duration_s = args.duration_s or (10.0 if args.quick else 60.0)

    load_start = os.getloadavg()[0]
    # The simulated robot gets real-time priority too (just below the loop's): a real Go1 is not starved by this
    # machine's other processes, but its simulation on the same 2 CPUs would be.
    with sim.SimGo1Client(pacing="realtime", realtime_priority=None if args.no_realtime else 70) as robot:
        controller = hio.CompiledController()
        transport = (hio.SdkTransport("127.0.0.1", robot.port, deploy._free_port()) if args.transport == "sdk"
                     else hio.UdpTransport(robot.address))
        loop = hio.LoopConfig(realtime_priority=None if args.no_realtime else 80, cpu=args.cpu,
                              log_ticks=round((duration_s + 5.0) * 1000))
        t0 = time.perf_counter()
        result = hio.run_loop(transport, controller, hio.FixedParams(params.midpoint(), round(duration_s * 1000)),
                              deploy.sim_calibration(), cpg.controller_gates("vmc_tegotae"), loop,
                              hio.SafetyConfig(watchdog_ticks=50))
        wall_s = time.perf_counter() - t0
        transport.close()
        walked_m = robot.stats()["trunk_xy_m"][0]
    timing = result.timing()
    print(f"events: {result.events}")
    print(f"scheduling: {result.realtime}; load average at start {load_start:.2f}, at end {os.getloadavg()[0]:.2f}")
    print(f"controller step  median {timing['step_median_us']:.1f} µs  p99 {timing['step_p99_us']:.1f} µs  "
          f"max {timing['step_max_us']:.1f} µs   (target p99 ≤ 200 µs)")
    print(f"loop period      median {timing['period_median_us']:.1f} µs  p1 {timing['period_p1_us']:.1f} µs  "
          f"p99 {timing['period_p99_us']:.1f} µs  max {timing['period_max_us']:.1f} µs   (target p99 ≤ 1100 µs)")
    print(f"overruns         {timing['overruns']} in {timing['ticks']} ticks = "
          f"{timing['overruns_per_10k_ticks']:.2f} per 10k   (target ≤ 1)")
    figures = {
        "benchmark": "hardware_loop", "machine": study_io.machine(), "transport": args.transport,
        "scheduling": result.realtime, "walk_s": duration_s, "wall_s": round(wall_s, 1),
        "walked_m": round(walked_m, 2), "trip": result.trip, "load_avg_1min_start": round(load_start, 2),
        "load_avg_1min_end": round(os.getloadavg()[0], 2),
        **{k: round(v, 2) if isinstance(v, float) else v for k, v in timing.items()},
        "skipped_ticks": result.skipped_ticks,
    }
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
