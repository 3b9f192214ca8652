"""Environment steps per second of the batched closed-loop trial (CPG controller + MJX) against bare ``mjx.step``
with a constant control, against single-threaded C MuJoCo, and against the same trial on the native backend (C MuJoCo
through ``mujoco.rollout``, ``benchmarks/backend_speed.py``), measured in the same run.

    python benchmarks/rollout.py            # full: batch 1, 4, 16, 64, 256; one device and every core
    python benchmarks/rollout.py --quick    # under 2 minutes on a 2-core CPU

On a CPU, XLA runs one device's program on one thread, so the batch is sharded over one host device per core
(``jax_num_cpu_devices``, ``--cpu-devices``); the full run also measures the one-device layout. The last line of the
output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from backend_speed import trial_speed  # benchmarks/ is the script's directory
from cpgjax import go1_model, mjx_go1, params as param_space, study_io


def _timed(fn, *args, repeats: int):
    """(compile+first-run seconds, best run seconds) of a jitted function."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return first, best


def closed_loop(batch: int, steps: int, repeats: int, devices: list) -> dict:
    """The paper's trial (transition + steady phase, sensors, controller, bookkeeping) for ``batch`` instances
    sharded over ``devices``."""
    transition = steps // 4
    config = mjx_go1.TrialConfig(transition_steps=transition, steady_steps=steps - transition)
    sim = mjx_go1.MJXBackend(go1_model.make_scenarios(friction=np.full(batch, 0.6)), trial_config=config,
                             devices=devices)
    p = np.tile(param_space.midpoint(), (batch, 1))
    gates = mjx_go1.batch_gates(["vmc_tegotae"] * batch)
    state = jax.block_until_ready(sim.reset(p))
    t0 = time.perf_counter()
    jax.block_until_ready(sim.trial(state, p, gates))  # compiles; the trial consumes its input state
    first_call = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        state = jax.block_until_ready(sim.reset(p))
        t0 = time.perf_counter()
        jax.block_until_ready(sim.trial(state, p, gates))
        best = min(best, time.perf_counter() - t0)
    return {"steps_per_s": batch * steps / best, "first_call_s": first_call}


def bare_mjx(batch: int, steps: int, repeats: int, devices: list) -> dict:
    """``mjx.step`` in a scan with a constant control, vmapped, on the same batched model and devices."""
    sim = mjx_go1.MJXBackend(go1_model.make_scenarios(friction=np.full(batch, 0.6)), devices=devices)
    qpos = jnp.asarray(go1_model.standing_qpos(), jnp.float32)

    def run(model):
        data = mjx.make_data(model).replace(qpos=qpos, ctrl=jnp.full(model.nu, 1.0))
        return jax.lax.scan(lambda d, _: (mjx.step(model, d), None), data, None, length=steps)[0].qpos

    fn = jax.jit(mjx_go1.per_shard(run, (sim.batch.in_axes,), sim.mesh))  # mapped as the backend maps its trial
    t0 = time.perf_counter()
    compiled = fn.lower(sim.batch.model).compile()
    compile_s = time.perf_counter() - t0
    _, best = _timed(compiled, sim.batch.model, repeats=repeats)
    return {"steps_per_s": batch * steps / best, "compile_s": compile_s}


def c_mujoco(steps: int) -> float:
    """Single-threaded C MuJoCo, one instance, constant control: env-steps/s."""
    m = go1_model.load_model()
    d = mujoco.MjData(m)
    d.qpos[:] = go1_model.standing_qpos()
    d.ctrl[:] = 1.0
    t0 = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(m, d)
    return steps / (time.perf_counter() - t0)


# Known issue (jax 0.10.2 CPU): an MJX reset with 128 instances on each of two host devices never completes (all XLA
# threads idle; 64 per device run). benchmarks/cpu_devices_hang.py reproduces it; larger batches run on one device.
MAX_INSTANCES_PER_CPU_DEVICE = 64


def layouts(batch: int, quick: bool) -> list[list]:
    """Device lists to measure ``batch`` on: every device (when the batch divides among them and, on a CPU, stays
    within the known-good size per device) and, in a full run, also one device."""
    every = jax.devices()
    too_big = every[0].platform == "cpu" and batch // len(every) > MAX_INSTANCES_PER_CPU_DEVICE
    if len(every) == 1 or batch % len(every) or too_big:
        return [every[:1]]
    return [every] if quick else [every[:1], every]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="batch 1 and 16, short rollouts (< 2 min)")
    parser.add_argument("--batch-sizes", type=lambda s: [int(v) for v in s.split(",")], default=None)
    parser.add_argument("--steps", type=int, default=None, help="env steps per instance per timed run")
    parser.add_argument("--cpu-devices", type=int, default=os.cpu_count(),
                        help="host devices on a CPU (default: one per core)")
    args = parser.parse_args()
    jax.config.update("jax_num_cpu_devices", args.cpu_devices)  # before JAX's first computation
    batches = args.batch_sizes or ([1, 16] if args.quick else [1, 4, 16, 64, 256])
    steps = args.steps or (400 if args.quick else 2000)
    repeats = 1 if args.quick else 3

    device = jax.devices()[0]
    print(f"# devices: {len(jax.devices())} x {device.platform} {device.device_kind}; host: {study_io.machine()}; "
          f"jax {jax.__version__}, mujoco {mujoco.__version__}; {steps} steps per instance")
    print("| batch | devices | closed loop [env-steps/s] | bare mjx.step [env-steps/s] | controller overhead "
          "| first call (compile) [s] | bare compile [s] | native closed loop (C MuJoCo) [env-steps/s] |")
    print("|---|---|---|---|---|---|---|---|")
    figures: dict = {"device": f"{device.platform}:{device.device_kind}", "num_devices": len(jax.devices()),
                     "machine": study_io.machine(), "steps_per_instance": steps}
    for b in batches:
        native = trial_speed("native", b, steps, repeats)  # the same trial with the native backend
        figures[f"native_closed_loop_env_steps_per_s_b{b}"] = round(native["env_steps_per_s"])
        for devices in layouts(b, args.quick):
            loop = closed_loop(b, steps, repeats, devices)
            bare = bare_mjx(b, steps, repeats, devices)
            overhead = bare["steps_per_s"] / loop["steps_per_s"] - 1.0
            print(f"| {b} | {len(devices)} | {loop['steps_per_s']:,.0f} | {bare['steps_per_s']:,.0f} | {overhead:+.1%} "
                  f"| {loop['first_call_s']:.1f} | {bare['compile_s']:.1f} | {native['env_steps_per_s']:,.0f} |",
                  flush=True)
            key = f"b{b}_d{len(devices)}"
            figures[f"closed_loop_env_steps_per_s_{key}"] = round(loop["steps_per_s"])
            figures[f"bare_mjx_env_steps_per_s_{key}"] = round(bare["steps_per_s"])
            figures[f"controller_overhead_ratio_{key}"] = round(overhead, 4)
            figures[f"bare_mjx_compile_s_{key}"] = round(bare["compile_s"], 2)
            figures[f"closed_loop_first_call_s_{key}"] = round(loop["first_call_s"], 2)
    c_rate = c_mujoco(5 * steps)
    print(f"C MuJoCo, single thread, batch 1: {c_rate:,.0f} env-steps/s")
    figures["c_mujoco_single_thread_env_steps_per_s"] = round(c_rate)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
