"""Benchmark: the deployed 1 kHz loop against the loopback simulated Go1 (127.0.0.1 only).

Runs ``hardware_io.run_loop`` (soft start, then the CPG walking with the midpoint parameters) against the simulated
Go1 in real-time pacing (a separate process stepping C MuJoCo at 1 kHz) and reports the controller-step latency
(pack + compiled call + unpack: median, p99, max) and the loop period (median, p1, p99, max) and overruns over the
run. Targets (issue 5): step p99 ≤ 200 µs; period p99 within ±100 µs of 1 ms; ≤ 1 overrun per 10,000 ticks.

An overrun is a tick whose work ended after the next deadline (``hardware_io.run_loop``); each is attributed to the
largest share of its time (``hardware_io.overrun_causes``): a late start, the loop thread not running during the
work, or the work's own CPU time. Before the loop, a probe measures this machine's floor: the same wait at the same
scheduling with no work in the ticks (``hardware_io.idle_loop_lateness_s``). A wake-up later than the period minus
the loop's median work is an overrun whatever the tick does (on a VM: the hypervisor stopping or waking the virtual
CPU late, which no code in the guest can prevent); the probe counts those per 10k ticks next to the loop's overruns.

In both modes the loop is pinned to the last CPU (or ``--cpu``), as ``cpgjax deploy`` pins it on the robot, and the
simulated Go1, which stands in for the robot's own computer, runs on the others. Idle CPUs poll instead of halting
(``LoopConfig.poll_idle``, as deploy; ``--idle-halt`` lets them halt). ``--poll-ab S`` compares the two within one
run, under the same host: the polling request is made and released every S seconds by a thread of the loop's
process, and the ticks of each kind are counted apart. Two ways to wait for the next deadline are
measured, one after the other:

- ``sleep``: SCHED_FIFO 80 (when permitted), sleep until ``--spin-us`` before the deadline, then spin (the default
  of ``cpgjax deploy``).
- ``busy-wait``: spin through the whole period (``LoopConfig.busy_wait``), normal priority (the kernel's
  real-time throttling would stop a SCHED_FIFO thread that never sleeps for 50 ms every second).

    python benchmarks/hardware_loop.py                     # 60 s of walking per mode (20 s floor probe)
    python benchmarks/hardware_loop.py --quick             # 10 s per mode (5 s floor probe)
    python benchmarks/hardware_loop.py --modes busy-wait   # one mode

The last line of the output is one JSON object with the figures (units in the names, mode as a key prefix).
"""

import argparse
import contextlib
import json
import os
import threading
import time

import numpy as np

from cpgjax import cpg, provenance
from cpgjax import hardware_io as hio
from cpgjax.deployment import deploy
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import cpu_dispatch, cpu_wakeup, wire
from cpgjax.robot import safety as go1_safety
from cpgjax.robot import sim_server as sim
from cpgjax.robot import transport as go1_transport
from cpgjax.trial import params


def voluntary_waits() -> int:
    """The calling thread's voluntary context switches so far (Linux; −1 elsewhere). The loop blocks once per tick
    in its sleep; more means it waits on something else (e.g. an XLA worker thread)."""
    try:
        with open("/proc/thread-self/status") as f:
            return int(next(line for line in f if line.startswith("voluntary_ctxt_switches")).split()[1])
    except OSError:
        return -1


class PollingToggle:
    """A thread that makes and releases the polling request (``robot.cpu_wakeup``) every ``period_s`` while the loop
    runs, so that both kinds of ticks see the same host; ``kinds(t)`` says which kind each tick start ``t`` was."""

    def __init__(self, period_s: float):
        self.period_s, self.switches, self._stop = period_s, [], threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        release = None
        while not self._stop.is_set():
            if release is None:
                _, release = cpu_wakeup.request_polling()
            else:
                release()
                release = None
            self.switches.append((time.perf_counter(), release is not None))
            self._stop.wait(self.period_s)
        if release is not None:
            release()

    def __enter__(self) -> "PollingToggle":
        note, release = cpu_wakeup.request_polling()  # permitted here? (the thread's requests then are too)
        release()
        if note != cpu_wakeup.REQUESTED:
            raise SystemExit(f"--poll-ab: {note}")
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def kinds(self, t_start_s: np.ndarray) -> np.ndarray:
        """1 polling, 0 halting, −1 before the first switch."""
        times = np.array([t for t, _ in self.switches])
        polling = np.array([p for _, p in self.switches], int)
        i = np.searchsorted(times, t_start_s, side="right") - 1
        return np.where(i >= 0, polling[np.maximum(i, 0)], -1)


def polling_ab_figures(log: hio.TickLog, kinds: np.ndarray, period_s: float) -> dict:
    """The run phase's ticks of each kind of :class:`PollingToggle`: overruns (per 10k, by cause), wake-ups more
    than a period late (per 10k), tick work median and p99."""
    figures = {}
    for name, kind in (("polling", 1), ("halting", 0)):
        ticks = (log.phase == hio.RUN) & (kinds == kind)
        part = hio.TickLog(*(a[ticks] for a in log))
        n = max(int(ticks.sum()), 1)
        causes = np.bincount(hio.overrun_causes(part), minlength=len(hio.OVERRUN_CAUSES))
        figures.update(
            {
                f"ab_{name}_ticks": int(ticks.sum()),
                f"ab_{name}_overruns_per_10k_ticks": round(float(part.overrun.sum()) / n * 1e4, 2),
                **{f"ab_{name}_overruns_{c}": int(k) for c, k in zip(hio.OVERRUN_CAUSES, causes, strict=True)},
                f"ab_{name}_wakeups_later_than_period_per_10k": round(
                    float(np.sum(part.late_s > period_s)) / n * 1e4, 2
                ),
                f"ab_{name}_work_median_us": round(float(np.median(part.work_s)) * 1e6, 1),
                f"ab_{name}_work_p99_us": round(float(np.percentile(part.work_s, 99)) * 1e6, 1),
            }
        )
    return figures


STAGES = ("receive", "decode", "checks", "controller step", "guard", "encode", "send", "log")


class StageTimer:
    """Wall time per call of the tick's stages [s], by wrapping the functions the loop calls (≈ 0.3 µs each):
    receive (the transport's, less decode), decode, checks, controller step (pack + compiled call + unpack, as the
    loop's own ``step_s``), guard, encode, send (less encode), log."""

    def __init__(self, transport, controller, n: int):
        self.times = {name: np.zeros(n) for name in STAGES}
        self.calls = dict.fromkeys(STAGES, 0)
        self._patches = []
        self._wrap(transport, "receive", "receive", inner="decode")
        self._wrap(wire, "decode_low_state", "decode")
        self._wrap(hio, "_trip_reason", "checks")
        self._wrap(hio, "guard_command", "guard")
        self._wrap(wire, "encode_low_cmd", "encode")
        self._wrap(transport, "send", "send", inner="encode")
        self._wrap(hio, "_log_tick", "log")

    def _wrap(self, owner, attr: str, stage: str, inner: str | None = None) -> None:
        original = getattr(owner, attr)
        times, calls, clock = self.times[stage], self.calls, time.perf_counter
        inner_times = self.times[inner] if inner else None

        def timed(*a, **k):
            i = calls[stage]
            inner_before = calls[inner] if inner else 0
            t = clock()
            out = original(*a, **k)
            dt = clock() - t
            if inner and calls[inner] > inner_before:
                dt -= inner_times[calls[inner] - 1]
            if i < times.shape[0]:
                times[i] = dt
            calls[stage] = i + 1
            return out

        setattr(owner, attr, timed)
        self._patches.append((owner, attr, original))

    def restore(self) -> None:
        for owner, attr, original in reversed(self._patches):
            setattr(owner, attr, original)

    def table(self, step_s: np.ndarray, work_s: np.ndarray) -> tuple[str, dict]:
        """Median / p99 [µs] and share of the 1 ms period per stage, and the whole tick's work."""
        lines = ["| stage | median [µs] | p99 [µs] | p99 / period |", "|---|---|---|---|"]
        figures = {}
        rows = [(name, self.times[name][: min(self.calls[name], self.times[name].shape[0])]) for name in STAGES]
        rows[STAGES.index("controller step")] = ("controller step", step_s)
        for name, t in rows + [("tick work (all)", work_s)]:
            if t.size == 0:
                continue
            median, p99 = float(np.median(t)) * 1e6, float(np.percentile(t, 99)) * 1e6
            lines.append(f"| {name} | {median:.1f} | {p99:.1f} | {p99 / 1000:.3f} |")
            figures[f"stage_{name.split(' (')[0].replace(' ', '_')}_median_us"] = round(median, 1)
            figures[f"stage_{name.split(' (')[0].replace(' ', '_')}_p99_us"] = round(p99, 1)
        return "\n".join(lines), figures


def run_mode(mode: str, duration_s: float, probe_s: float, args) -> dict:
    """Walk ``duration_s`` against a fresh real-time simulated Go1 with the loop waiting as ``mode``; print and return
    the figures."""
    busy = mode == "busy-wait"
    cpu = args.cpu if args.cpu is not None else deploy.last_cpu()  # as deploy places it on the robot
    sim_cpus = hio.cpus_besides(cpu)
    loop_priority = None if args.no_realtime or busy else 80
    load_start = os.getloadavg()[0]
    # The simulated robot gets real-time priority too (just below the loop's): a real Go1 is not starved by this
    # machine's other processes, but its simulation on the same 2 CPUs would be.
    with sim.SimGo1Client(
        pacing="realtime", realtime_priority=None if args.no_realtime else 70, cpus=sim_cpus
    ) as robot:
        controller = compiled_controller.CompiledController()
        loop = hio.LoopConfig(
            spin_s=args.spin_us * 1e-6,
            realtime_priority=loop_priority,
            cpu=cpu,
            busy_wait=busy,
            poll_idle=not (args.idle_halt or args.poll_ab),  # --poll-ab: the toggle's
            log_ticks=round((duration_s + 5.0) * 1000),
        )
        floor_late_s = hio.idle_loop_lateness_s(probe_s, loop) if probe_s > 0 else np.zeros(0)
        transport = (
            go1_transport.SdkTransport("127.0.0.1", robot.port, deploy._free_port())
            if args.transport == "sdk"
            else go1_transport.UdpTransport(robot.address)
        )
        stages = StageTimer(transport, controller, loop.log_ticks) if args.stages else None
        toggle = PollingToggle(args.poll_ab) if args.poll_ab else contextlib.nullcontext()
        t0, waits0 = time.perf_counter(), voluntary_waits()
        try:
            with toggle:
                schedule = hio.FixedParams(params.midpoint(), round(duration_s * 1000))
                result = hio.run_loop(
                    transport,
                    controller,
                    schedule,
                    deploy.sim_calibration(),
                    cpg.controller_gates("vmc_tegotae"),
                    loop,
                    go1_safety.SafetyConfig(watchdog_ticks=50),
                )
        finally:
            if stages is not None:
                stages.restore()
        wall_s, waits = time.perf_counter() - t0, voluntary_waits() - waits0
        transport.close()
        walked_m = robot.stats()["trunk_xy_m"][0]
    timing = result.timing()
    log = result.log
    print(f"## {mode}")
    print(f"events: {result.events}")
    print(
        f"scheduling: {result.realtime}; simulated Go1 on CPUs {sorted(sim_cpus) if sim_cpus else 'any'}; "
        f"spin {'the whole period' if busy else f'{args.spin_us:.0f} µs'}; load average at start {load_start:.2f}, "
        f"at end {os.getloadavg()[0]:.2f}"
    )
    period_s, work_median_s = loop.period_s, timing["work_median_us"] * 1e-6
    floor = dict.fromkeys(
        (
            "floor_wakeups_later_than_period_per_10k",
            "floor_overruns_per_10k_ticks",
            "floor_late_p99_us",
            "floor_late_max_us",
        )
    )  # None without a probe
    if floor_late_s.size:
        floor.update(
            floor_wakeups_later_than_period_per_10k=round(float(np.mean(floor_late_s > period_s)) * 1e4, 2),
            floor_overruns_per_10k_ticks=round(float(np.mean(floor_late_s + work_median_s > period_s)) * 1e4, 2),
            floor_late_p99_us=round(float(np.percentile(floor_late_s, 99)) * 1e6, 1),
            floor_late_max_us=round(float(floor_late_s.max()) * 1e6, 1),
        )
        print(
            f"floor (probe)    {probe_s:.0f} s of the same wait with no work: wake-ups p99 "
            f"{floor['floor_late_p99_us']:.0f} µs late, max {floor['floor_late_max_us']:.0f} µs; later than the "
            f"period {floor['floor_wakeups_later_than_period_per_10k']:.2f} per 10k, later than the period less "
            f"the loop's median work {floor['floor_overruns_per_10k_ticks']:.2f} per 10k (the overruns of a loop "
            f"with that work from its wake-ups alone)"
        )
    print(
        f"controller step  median {timing['step_median_us']:.1f} µs  p99 {timing['step_p99_us']:.1f} µs  "
        f"max {timing['step_max_us']:.1f} µs   (target p99 ≤ 200 µs)"
    )
    print(
        f"loop period      median {timing['period_median_us']:.1f} µs  p1 {timing['period_p1_us']:.1f} µs  "
        f"p99 {timing['period_p99_us']:.1f} µs  max {timing['period_max_us']:.1f} µs   (target p99 ≤ 1100 µs)"
    )
    print(
        f"blocking waits   {waits / result.ticks:.2f} per tick (the sleep: ≤ 1; XLA dispatch "
        f"{'inline' if controller.inline_dispatch else 'ASYNCHRONOUS'})"
    )
    print(f"tick work        median {timing['work_median_us']:.1f} µs  p99 {timing['work_p99_us']:.1f} µs")
    print(
        f"overruns         {timing['overruns']} in {timing['ticks']} ticks = "
        f"{timing['overruns_per_10k_ticks']:.2f} per 10k   (target ≤ 1); by cause: "
        + ", ".join(f"{name} {timing[f'overruns_{name}']}" for name in hio.OVERRUN_CAUSES)
    )
    stage_figures = {}
    if stages is not None:
        active = log.phase > hio.CONNECT
        text, stage_figures = stages.table(log.step_s[log.phase == hio.RUN], log.work_s[active])
        print(f"time per stage (wall, every tick after connecting; the stage timers add ≈ 0.3 µs per call)\n{text}")
    ab_figures = polling_ab_figures(log, toggle.kinds(log.t_start_s), loop.period_s) if args.poll_ab else {}
    for name in ("polling", "halting") if args.poll_ab else ():
        print(
            f"{name:7s} ticks   {ab_figures[f'ab_{name}_ticks']} (idle CPUs {name}, every other {args.poll_ab:g} s): "
            f"overruns {ab_figures[f'ab_{name}_overruns_per_10k_ticks']:.2f} per 10k ("
            + ", ".join(f"{c} {ab_figures[f'ab_{name}_overruns_{c}']}" for c in hio.OVERRUN_CAUSES)
            + f"), wake-ups later than the period {ab_figures[f'ab_{name}_wakeups_later_than_period_per_10k']:.2f} "
            f"per 10k, tick work median {ab_figures[f'ab_{name}_work_median_us']:.1f} µs p99 "
            f"{ab_figures[f'ab_{name}_work_p99_us']:.1f} µs"
        )
    for k in np.flatnonzero(log.overrun)[:20]:
        print(
            f"  tick {k}: started {log.late_s[k] * 1e6:7.0f} µs late, work {log.work_s[k] * 1e6:6.0f} µs wall "
            f"/ {log.work_cpu_s[k] * 1e6:5.0f} µs CPU ({hio.PHASE_NAMES[log.phase[k]]})"
        )
    return {
        "scheduling": result.realtime,
        "sim_cpus": sorted(sim_cpus) if sim_cpus else None,
        "spin_us": duration_s * 1e6 if busy else args.spin_us,
        "wall_s": round(wall_s, 1),
        "walked_m": round(walked_m, 2),
        "trip": result.trip,
        "load_avg_1min_start": round(load_start, 2),
        "load_avg_1min_end": round(os.getloadavg()[0], 2),
        **floor,
        **{k: round(v, 2) if isinstance(v, float) else v for k, v in timing.items()},
        "skipped_ticks": result.skipped_ticks,
        "inline_dispatch": controller.inline_dispatch,
        "blocking_waits_per_tick": round(waits / result.ticks, 3),
        **stage_figures,
        **ab_figures,
    }


def main() -> None:
    cpu_dispatch.request_inline()  # before any JAX computation (hardware_io.CompiledController)
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="10 s instead of 60 s per mode")
    parser.add_argument("--duration-s", type=float, help="walking time per mode (default 60, --quick 10)")
    parser.add_argument(
        "--probe-s",
        type=float,
        help="floor probe (the same wait with no work) before each loop (default 20, --quick 5; 0: off)",
    )
    parser.add_argument(
        "--idle-halt",
        action="store_true",
        help="let idle CPUs halt while the loop runs (LoopConfig.poll_idle off; default: polling)",
    )
    parser.add_argument(
        "--poll-ab",
        type=float,
        metavar="S",
        help="compare polling and halting idle CPUs within each run: the polling request is made and "
        "released every S seconds, and the ticks of each kind are reported apart",
    )
    parser.add_argument("--modes", default="sleep,busy-wait", help="comma list of sleep, busy-wait")
    parser.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    parser.add_argument(
        "--cpu", type=int, help="pin the loop to this CPU (default: the last) and the simulated Go1 to the others"
    )
    parser.add_argument(
        "--spin-us",
        type=float,
        default=hio.LoopConfig().spin_s * 1e6,
        help="sleep mode: spin this long before each deadline instead of sleeping",
    )
    parser.add_argument("--transport", choices=("udp", "sdk"), default="udp")
    parser.add_argument(
        "--stages",
        action="store_true",
        help="time each stage of the tick (receive, decode, checks, controller step, guard, encode, send, log)",
    )
    args = parser.parse_args()
    modes = args.modes.split(",")
    if not set(modes) <= {"sleep", "busy-wait"}:
        parser.error(f"--modes {args.modes!r}: each of sleep, busy-wait")
    duration_s = args.duration_s or (10.0 if args.quick else 60.0)
    probe_s = args.probe_s if args.probe_s is not None else (5.0 if args.quick else 20.0)
    figures = {
        "benchmark": "hardware_loop",
        "machine": provenance.machine(),
        "transport": args.transport,
        "walk_s": duration_s,
        "probe_s": probe_s,
    }
    for mode in modes:
        mode_figures = run_mode(mode, duration_s, probe_s, args)
        figures.update({f"{mode.replace('-', '_')}_{k}": v for k, v in mode_figures.items()})
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
