"""What MuJoCo's profiling timers cost the native closed loop, measured in one process.

MuJoCo fills ``mjData.timer`` by reading the clock through its global callback ``mjcb_time`` (twice for each of the
14 timers a Go1 step counts), and the mujoco Python bindings install a clock there with their first ``MjData``. While
a native backend's stepper exists the callback returns 0 (``cpgjax/sim/batch_step.cc``). This benchmark runs the
controller ablation's batch (the four controllers × 5, paper physics, new parameters drawn from the box every trial,
full 1.5 s + 3 s trials) trial after trial, alternating the bindings' clock (written into ``mjcb_time``, MuJoCo's
exported global) with what the stepper set, and reports the trials' speed with each and the paired difference.

    JAX_PLATFORMS=cpu python benchmarks/mujoco_timers.py [--trials 30] [--batch 20]

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from cpgjax.robot import cpu_dispatch  # noqa: E402

cpu_dispatch.request_inline()  # as the cpgjax commands: before any JAX computation
cpu_dispatch.request_one_pool_thread()

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from cpgjax import cpg, provenance  # noqa: E402
from cpgjax.go1 import model as go1_model  # noqa: E402
from cpgjax.sim import ffi_step, native  # noqa: E402
from cpgjax.trial import params as param_space  # noqa: E402
from cpgjax.trial import protocol  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=30, help="timed trials, half with each callback (even, ≥ 4)")
    parser.add_argument("--batch", type=int, default=20, help="instances, a multiple of 4 (the four controllers)")
    args = parser.parse_args()
    if args.trials < 4 or args.trials % 2:
        parser.error(f"--trials {args.trials}: need an even number, at least 4")
    if args.batch < 4 or args.batch % 4:
        parser.error(f"--batch {args.batch}: need a multiple of 4, at least 4")
    if not ffi_step.available():
        sys.exit("benchmarks/mujoco_timers.py: the native physics step cannot be built here (see the log)")

    callback = ctypes.c_void_p.in_dll(ctypes.CDLL(str(ffi_step.mujoco_library())), "mjcb_time")
    mujoco.MjData(mujoco.MjModel.from_xml_string("<mujoco/>"))  # the bindings install their clock, if none is set
    clock = callback.value
    sim = native.NativeBackend(go1_model.make_scenarios(friction=np.full(args.batch, 0.6), physics="paper"))
    stepper_set = callback.value
    if not clock or stepper_set == clock:
        sys.exit(
            f"benchmarks/mujoco_timers.py: mjcb_time {clock} before the stepper, {stepper_set} with it: "
            "nothing to compare"
        )

    rng = np.random.default_rng(0)

    def drawn():  # parameters drawn from the box for every instance
        return param_space.from_unit(rng.uniform(size=(args.batch, param_space.NUM_PARAMS)))

    gates = protocol.batch_gates([c for c in cpg.CONTROLLERS for _ in range(args.batch // 4)])
    state, _ = sim.trial(sim.reset(drawn()), drawn(), gates)  # compiles
    seconds = {"clock": [], "stepper": []}
    for k in range(args.trials):
        kind = "clock" if k % 2 == 0 else "stepper"
        callback.value = clock if kind == "clock" else stepper_set
        params = drawn()
        t0 = time.perf_counter()
        state, _ = sim.trial(state, params, gates)
        seconds[kind].append(time.perf_counter() - t0)
    callback.value = stepper_set
    sim.physics.close()

    ticks = sim.trial_config.transition_steps + sim.trial_config.steady_steps
    on, off = np.array(seconds["clock"]), np.array(seconds["stepper"])
    diff = on - off  # each pair: a trial with the clock, then the next without
    half = 1.96 * diff.std(ddof=1) / np.sqrt(diff.size)
    rate = {k: args.batch * ticks / np.mean(v) for k, v in seconds.items()}
    print(
        f"batch {args.batch}, {diff.size} pairs of {ticks}-tick trials: with the bindings' clock "
        f"{rate['clock']:,.0f} env-steps/s, timers off {rate['stepper']:,.0f} env-steps/s; a trial "
        f"{diff.mean() * 1e3:.1f} ms [{(diff.mean() - half) * 1e3:.1f}, {(diff.mean() + half) * 1e3:.1f}] longer "
        f"with the clock ({on.mean() / off.mean() - 1:+.1%})"
    )
    print(
        json.dumps(
            {
                "benchmark": "mujoco_timers",
                "machine": provenance.machine(),
                "physics": "paper",
                "batch": args.batch,
                "pairs": int(diff.size),
                "ticks": ticks,
                "env_steps_per_s_clock": round(rate["clock"]),
                "env_steps_per_s_timers_off": round(rate["stepper"]),
                "trial_time_ratio_clock_vs_off": round(on.mean() / off.mean(), 4),
                "paired_diff_ms": round(diff.mean() * 1e3, 2),
                "paired_diff_ci95_ms": [round((diff.mean() - half) * 1e3, 2), round((diff.mean() + half) * 1e3, 2)],
                "load_avg_1min_end": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
