"""Environment steps per second of the batched closed-loop trial (CPG controller + MJX) against bare ``mjx.step``,
against single-threaded C MuJoCo, and against the same trial on the native backend (C MuJoCo through
``mujoco.rollout``, ``benchmarks/backend_speed.py``), measured in the same run.

Two bare baselines (``measure``): *replay*, ``mjx.step`` driven by the torques the closed loop applied, which is the
same physics bit for bit and so isolates what the controller, the sensors and the bookkeeping add; and *constant
control* (1 N·m on every motor), under which the robot collapses onto its trunk and the solver works on other
contacts. The three are timed in interleaved rounds (best of each).

    python benchmarks/rollout.py            # full: batch 1, 4, 16, 64, 256; one device and every core
    python benchmarks/rollout.py --quick    # under 2 minutes on a 2-core CPU
    python benchmarks/rollout.py --profiles soft,paper,go1 [--quick]   # only: each physics profile's cost

``--profiles`` times the closed-loop trial (MJX, batch 16 on every device, and the native backend) under each physics
profile (docs/physics.md) in interleaved rounds, as ratios against the first profile of the list in the same run.

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
from backend_speed import trial_speed  # benchmarks/ is the script's directory
from mujoco import mjx

from cpgjax import mjx_go1
from cpgjax.go1 import model as go1_model
from cpgjax.sim import backends
from cpgjax.sim import native as native_go1
from cpgjax.study import files as study_io
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol


def _interleaved_best(runs: dict, repeats: int) -> dict:
    """Best wall time [s] of each zero-argument run over ``repeats`` rounds that run them in turn, so that drift of
    the machine's speed between rounds (up to ~40 % on this VM) biases none of them."""
    best = dict.fromkeys(runs, np.inf)
    for _ in range(repeats):
        for name, run in runs.items():
            best[name] = min(best[name], run())
    return best


def measure(batch: int, steps: int, repeats: int, devices: list) -> dict:
    """Env-steps/s of the closed-loop trial and of its two bare-``mjx.step`` baselines for ``batch`` instances sharded
    over ``devices`` (all three mapped per shard, as the backend maps its trial):

    - closed loop: the paper's trial (transition + steady phase, sensors, controller, bookkeeping) with constant
      parameters, from standing;
    - replay: ``mjx.step`` in a ``lax.scan`` driven by the torques that closed loop applied, recorded beforehand: the
      same physics, bit for bit (checked: ``replay_max_abs_qpos_diff``), without the controller;
    - constant control: the replay's program driven by ctrl = 1 N·m on every motor from standing; the robot
      collapses onto its trunk, so the solver works on other contacts than in walking.
    """
    transition = steps // 4
    config = protocol.TrialConfig(transition_steps=transition, steady_steps=steps - transition)
    sim = mjx_go1.MJXBackend(go1_model.make_scenarios(friction=np.full(batch, 0.6)), trial_config=config,
                             devices=devices)
    p = np.tile(param_space.midpoint(), (batch, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * batch)
    ids = go1_model.indices()
    model, axes = sim.batch.model, sim.batch.in_axes

    def closed_loop_run(first: bool = False):
        state = jax.block_until_ready(sim.reset(p))
        t0 = time.perf_counter()
        end = jax.block_until_ready(sim.trial(state, p, gates))[0]  # the trial consumes its input state
        return (time.perf_counter() - t0, end) if first else time.perf_counter() - t0

    first_call_s, trial_end = closed_loop_run(first=True)  # compiles

    def replay(m, data, torques_nm):
        def body(d, tau):
            return mjx.step(m, d.replace(ctrl=jnp.zeros(m.nu, tau.dtype).at[ids.actuator].set(tau))), None
        return jax.lax.scan(body, data, torques_nm)[0]

    start = sim.reset(p)
    torques = sim.rollout(start, p, gates, steps)[1].torque_nm  # (B, T, 12), what the closed loop applies
    t0 = time.perf_counter()
    replay_fn = jax.jit(mjx_go1.per_shard(replay, (axes, 0, 0), sim.mesh)).lower(model, start.data, torques).compile()
    replay_compile_s = time.perf_counter() - t0
    replay_diff = float(jnp.max(jnp.abs(replay_fn(model, start.data, torques).qpos - trial_end.data.qpos)))

    constant_torques = jnp.ones_like(torques)  # 1 N·m on every motor (model.nu = 12)

    def timed(fn, *args):
        def run():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*args))
            return time.perf_counter() - t0
        return run

    timed(replay_fn, model, start.data, torques)()  # warm
    best = _interleaved_best({"closed_loop": closed_loop_run, "replay": timed(replay_fn, model, start.data, torques),
                              "constant": timed(replay_fn, model, start.data, constant_torques)}, repeats)
    rate = {k: batch * steps / v for k, v in best.items()}
    return {"closed_loop_steps_per_s": rate["closed_loop"], "replay_steps_per_s": rate["replay"],
            "constant_steps_per_s": rate["constant"], "overhead_vs_replay": best["closed_loop"] / best["replay"] - 1,
            "overhead_vs_constant": best["closed_loop"] / best["constant"] - 1, "first_call_s": first_call_s,
            "replay_compile_s": replay_compile_s,
            "replay_max_abs_qpos_diff": replay_diff}


def profile_costs(profiles: list[str], batch: int, steps: int, repeats: int) -> dict:
    """Closed-loop env-steps/s per physics profile on MJX (every device) and on the native backend, timed in
    interleaved rounds; ratios against ``profiles[0]``."""
    transition = steps // 4
    config = protocol.TrialConfig(transition_steps=transition, steady_steps=steps - transition)
    p = np.tile(param_space.midpoint(), (batch, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * batch)
    runs = {}
    for name in profiles:
        scenario = go1_model.make_scenarios(friction=np.full(batch, 0.6), physics=name)
        for kind, sim in (("mjx", mjx_go1.MJXBackend(scenario, trial_config=config)),
                          ("native", native_go1.NativeBackend(scenario, trial_config=config))):
            def run(sim=sim):
                state = jax.block_until_ready(sim.reset(p))
                t0 = time.perf_counter()
                jax.block_until_ready(sim.trial(state, p, gates)[1])
                return time.perf_counter() - t0
            run()  # compiles
            runs[f"{kind}:{name}"] = run
    best = _interleaved_best(runs, repeats)
    out = {}
    for kind in ("mjx", "native"):
        base = best[f"{kind}:{profiles[0]}"]
        for name in profiles:
            out[f"{kind}_{name}_env_steps_per_s"] = round(batch * steps / best[f"{kind}:{name}"])
            out[f"{kind}_{name}_time_ratio_vs_{profiles[0]}"] = round(best[f"{kind}:{name}"] / base, 3)
    return out


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


# Larger batches run on one CPU device: above this many per device, MJX on as many CPU devices as cores deadlocks
# (jaxlib's batched Cholesky, see cpgjax/sim/backends.py).
MAX_INSTANCES_PER_CPU_DEVICE = backends.MAX_MJX_INSTANCES_PER_CPU_DEVICE


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
    parser.add_argument("--quick", action="store_true", help="batch 16 on every device, short rollouts (< 2 min)")
    parser.add_argument("--batch-sizes", type=lambda s: [int(v) for v in s.split(",")], default=None)
    parser.add_argument("--steps", type=int, default=None, help="env steps per instance per timed run")
    parser.add_argument("--cpu-devices", type=int, default=os.cpu_count(),
                        help="host devices on a CPU (default: one per core)")
    parser.add_argument("--profiles", help="comma list of physics profiles: time only their closed loops (ratios "
                        "against the first)")
    args = parser.parse_args()
    jax.config.update("jax_num_cpu_devices", args.cpu_devices)  # before JAX's first computation
    batches = args.batch_sizes or ([16] if args.quick else [1, 4, 16, 64, 256])
    steps = args.steps or (400 if args.quick else 2000)
    repeats = 2 if args.quick else 3
    if args.profiles:
        profiles = args.profiles.split(",")
        figures = {"benchmark": "rollout_profiles", "machine": study_io.machine(), "batch": batches[0],
                   "steps_per_instance": steps, "repeats": repeats, "num_devices": len(jax.devices()),
                   **profile_costs(profiles, batches[0], steps, repeats)}
        print("| profile | MJX closed loop [env-steps/s] | time vs " + profiles[0] + " | native closed loop "
              "[env-steps/s] | time vs " + profiles[0] + " |\n|---|---|---|---|---|")
        for name in profiles:
            print(f"| {name} | {figures[f'mjx_{name}_env_steps_per_s']:,} | "
                  f"{figures[f'mjx_{name}_time_ratio_vs_{profiles[0]}']:.2f}× | "
                  f"{figures[f'native_{name}_env_steps_per_s']:,} | "
                  f"{figures[f'native_{name}_time_ratio_vs_{profiles[0]}']:.2f}× |")
        print(json.dumps(figures))
        return

    device = jax.devices()[0]
    print(f"# devices: {len(jax.devices())} x {device.platform} {device.device_kind}; host: {study_io.machine()}; "
          f"jax {jax.__version__}, mujoco {mujoco.__version__}; {steps} steps per instance")
    print("| batch | devices | closed loop [env-steps/s] | bare replay [env-steps/s] | controller overhead (vs replay) "
          "| bare constant control [env-steps/s] | overhead vs constant control | first call (compile) [s] "
          "| native closed loop (C MuJoCo) [env-steps/s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    figures: dict = {"device": f"{device.platform}:{device.device_kind}", "num_devices": len(jax.devices()),
                     "machine": study_io.machine(), "steps_per_instance": steps, "repeats": repeats}
    for b in batches:
        native = trial_speed("native", b, steps, repeats)  # the same trial with the native backend
        figures[f"native_closed_loop_env_steps_per_s_b{b}"] = round(native["env_steps_per_s"])
        for devices in layouts(b, args.quick):
            r = measure(b, steps, repeats, devices)
            print(f"| {b} | {len(devices)} | {r['closed_loop_steps_per_s']:,.0f} | {r['replay_steps_per_s']:,.0f} "
                  f"| {r['overhead_vs_replay']:+.1%} | {r['constant_steps_per_s']:,.0f} "
                  f"| {r['overhead_vs_constant']:+.1%} "
                  f"| {r['first_call_s']:.1f} | {native['env_steps_per_s']:,.0f} |", flush=True)
            key = f"b{b}_d{len(devices)}"
            figures[f"closed_loop_env_steps_per_s_{key}"] = round(r["closed_loop_steps_per_s"])
            figures[f"bare_replay_env_steps_per_s_{key}"] = round(r["replay_steps_per_s"])
            figures[f"bare_constant_env_steps_per_s_{key}"] = round(r["constant_steps_per_s"])
            figures[f"controller_overhead_ratio_{key}"] = round(r["overhead_vs_replay"], 4)
            figures[f"overhead_vs_constant_control_ratio_{key}"] = round(r["overhead_vs_constant"], 4)
            figures[f"replay_max_abs_qpos_diff_{key}"] = r["replay_max_abs_qpos_diff"]
            figures[f"closed_loop_first_call_s_{key}"] = round(r["first_call_s"], 2)
            figures[f"bare_compile_s_{key}"] = round(r["replay_compile_s"], 2)
    c_rate = c_mujoco(5 * steps)
    print(f"C MuJoCo, single thread, batch 1: {c_rate:,.0f} env-steps/s")
    figures["c_mujoco_single_thread_env_steps_per_s"] = round(c_rate)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
