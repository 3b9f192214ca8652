"""Environment steps per second of the batched closed-loop trial (CPG controller + MJX) against bare ``mjx.step``,
and of the same trial on the native backend (C MuJoCo, ``cpgjax.sim.native``) against its physics limit, measured
in the same run.

The native backend's limit (``native_limit``): the torques its closed loop applied, recorded, then replayed open
loop on the same per-instance models from the same start, one thread, C MuJoCo's own ``mj_step`` loop
(``mujoco.rollout`` with the whole control sequence, one instance after the other: no Python per step). The closed
loop is reported as a fraction of cores × that rate, the most its physics could give on this machine's cores. The
same replay on every core (MuJoCo's thread pool, instances split between the threads) says how much of that limit
the physics alone reaches; where it falls short of ``INDEPENDENT_CORES`` the cores did not run independently (another
process, or a neighbour on a virtual machine's host, which the load average does not show), and where it exceeds
``SLOWED_REPLAY`` the one-thread replay itself ran slowed; the run says so.

Two bare baselines (``measure``): *replay*, ``mjx.step`` driven by the torques the closed loop applied, which is the
same physics bit for bit and so isolates what the controller, the sensors and the bookkeeping add; and *constant
control* (1 N·m on every motor), under which the robot collapses onto its trunk and the solver works on other
contacts. The three are timed in interleaved rounds (best of each).

    python benchmarks/rollout.py            # full: batch 1, 4, 16, 64, 256; one device and every core
    python benchmarks/rollout.py --quick    # under 2 minutes on a 2-core CPU
    python benchmarks/rollout.py --profiles soft,paper,go1 [--quick]   # only: each physics profile's cost
    python benchmarks/rollout.py --quick --native-only --batch-sizes 16,64   # only: the native closed loop vs its limit

``--profiles`` times the closed-loop trial (MJX, batch 16 on every device, and the native backend) under each physics
profile (docs/physics.md) in interleaved rounds, as ratios against the first profile of the list in the same run.

On a CPU, XLA runs one device's program on one thread, so the batch is sharded over one host device per core
(``jax_num_cpu_devices``, ``--cpu-devices``; not with ``--native-only``, which runs as the cpgjax commands do, on
one host device with one XLA pool thread); the full run also measures the one-device layout. The last line of the
output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from backend_speed import trial_speed  # benchmarks/ is the script's directory
from mujoco import mjx
from mujoco import rollout as mj_rollout

from cpgjax import mjx_go1, provenance
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.robot import cpu_dispatch
from cpgjax.sim import backends, native_physics
from cpgjax.sim import native as native_go1
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

INDEPENDENT_CORES = 0.9
"""The least fraction of cores × the one-thread replay that the replay on every core reaches when the cores run
independently: quiet runs on a 2-core EPYC VM gave 0.94–1.01 at batch 16 and 64 (benchmarks/RESULTS.md, "Native
stepping against the physics limit"); a run below it measured the machine's other load as much as the code."""

SLOWED_REPLAY = 1.05
"""The largest such fraction taken as a one-thread replay at the machine's speed: the quiet runs above gave 1.01 at
most; above it the one-thread replay was slowed by other load (e.g. 41.5k against 58–59k env-steps/s in one run,
which put the replay on both cores at 1.11), so the run's limit is too low and its closed-loop fractions too high."""


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
    sim = mjx_go1.MJXBackend(
        go1_model.make_scenarios(friction=np.full(batch, 0.6), physics="soft"), trial_config=config, devices=devices
    )
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
    best = _interleaved_best(
        {
            "closed_loop": closed_loop_run,
            "replay": timed(replay_fn, model, start.data, torques),
            "constant": timed(replay_fn, model, start.data, constant_torques),
        },
        repeats,
    )
    rate = {k: batch * steps / v for k, v in best.items()}
    return {
        "closed_loop_steps_per_s": rate["closed_loop"],
        "replay_steps_per_s": rate["replay"],
        "constant_steps_per_s": rate["constant"],
        "overhead_vs_replay": best["closed_loop"] / best["replay"] - 1,
        "overhead_vs_constant": best["closed_loop"] / best["constant"] - 1,
        "first_call_s": first_call_s,
        "replay_compile_s": replay_compile_s,
        "replay_max_abs_qpos_diff": replay_diff,
    }


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
        for kind, sim in (
            ("mjx", mjx_go1.MJXBackend(scenario, trial_config=config)),
            ("native", native_go1.NativeBackend(scenario, trial_config=config)),
        ):

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


def native_limit(batch: int, steps: int, repeats: int, physics: str, steppings: list[str]) -> dict:
    """The native backend's closed-loop trial with each of ``steppings`` (``native_physics.STEPPINGS``) against the
    replay of its torques (see the module docstring), timed in interleaved rounds (best of each): env-steps/s of each,
    and the closed loops as fractions of ``available_cores()`` × the one-thread replay."""
    transition = steps // 4
    config = protocol.TrialConfig(transition_steps=transition, steady_steps=steps - transition)
    scenario = go1_model.make_scenarios(friction=np.full(batch, 0.6), physics=physics)
    sims = {name: native_go1.NativeBackend(scenario, trial_config=config, stepping=name) for name in steppings}
    sim = sims[steppings[0]]
    p = np.tile(param_space.midpoint(), (batch, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * batch)

    def closed_loop(sim):
        state = sim.reset(p)
        t0 = time.perf_counter()
        jax.block_until_ready(sim.trial(state, p, gates)[1])
        return time.perf_counter() - t0

    runs = {name: functools.partial(closed_loop, s) for name, s in sims.items()}
    for run in runs.values():
        run()  # compiles
    # The trial's parameters do not change (p → p), so a logged run with constant p applies the trial's torques.
    log = sim.rollout(sim.reset(p), p, gates, steps)[1]
    models, phys = sim.physics.models, sim.physics
    control = np.zeros((batch, steps, models[0].nu))
    control[..., go1_model.indices().actuator] = np.asarray(log.torque_nm)
    replayed = np.empty((batch, steps, phys.layout.size))  # the one-thread replay's states, compared below
    cores = native_physics.available_cores()

    def replay(nthread: int, states: np.ndarray):
        pool = mj_rollout.Rollout(nthread=nthread)  # 0: the calling thread only
        data = [mujoco.MjData(models[0]) for _ in range(max(nthread, 1))]

        def run():
            t0 = time.perf_counter()
            pool.rollout(
                models,
                data,
                phys.standing_physics,
                control,
                control_spec=mujoco.mjtState.mjSTATE_CTRL.value,
                skip_checks=True,
                nstep=steps,
                state=states,
            )
            return time.perf_counter() - t0

        return run

    # The same replay on every core (MuJoCo's pool, instances split between the threads): how much of the limit
    # the physics alone reaches, with no controller to run.
    runs.update(replay=replay(0, replayed), replay_all_cores=replay(cores, np.empty_like(replayed)))
    best = _interleaved_best(runs, repeats)
    rate = {k: batch * steps / v for k, v in best.items()}
    # The replay warm-starts with MuJoCo's own qacc, the backend with the same qacc recovered from the states: the
    # trajectories agree to the solver's sensitivity to that rounding.
    diff = float(np.max(np.abs(replayed[:, :, phys.layout.qpos] - np.asarray(log.qpos, np.float64))))
    for s in sims.values():
        s.physics.close()
    return {
        "replay_one_thread_env_steps_per_s": rate["replay"],
        "cores": cores,
        "replay_max_abs_qpos_diff": diff,
        "replay_all_cores_fraction_of_limit": rate["replay_all_cores"] / (cores * rate["replay"]),
        **{f"closed_loop_env_steps_per_s_{name}": rate[name] for name in steppings},
        **{f"fraction_of_limit_{name}": rate[name] / (cores * rate["replay"]) for name in steppings},
    }


def c_mujoco(steps: int) -> float:
    """Single-threaded C MuJoCo, one instance of the default model standing under 1 N·m on every motor: env-steps/s.
    Not the trial's physics (see ``native_limit`` for that)."""
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
    parser.add_argument(
        "--cpu-devices", type=int, default=os.cpu_count(), help="host devices on a CPU (default: one per core)"
    )
    parser.add_argument(
        "--profiles", help="comma list of physics profiles: time only their closed loops (ratios against the first)"
    )
    parser.add_argument("--native-only", action="store_true", help="only the native closed loop against its limit")
    parser.add_argument(
        "--steppings",
        type=lambda s: s.split(","),
        default=[native_physics.default_stepping()],
        help="comma list of the native backend's steppings to time against the limit "
        f"(of {native_physics.STEPPINGS}; default {native_physics.default_stepping()})",
    )
    parser.add_argument(
        "--physics",
        default=physics_profiles.DEFAULT_PROFILE,
        choices=physics_profiles.PROFILES,
        help="physics profile of the native closed loop and its limit (default: the studies')",
    )
    args = parser.parse_args()
    unknown = [name for name in args.steppings if name not in native_physics.STEPPINGS]
    if unknown:
        parser.error(f"--steppings {','.join(args.steppings)}: unknown {unknown}; allowed: {native_physics.STEPPINGS}")
    if args.native_only:
        # As the cpgjax commands: per-tick calls inline, the cores for MuJoCo's threads, one host device (with two,
        # the native trial's program runs 1.8x slower on 2 cores: docs/backends.md).
        cpu_dispatch.request_inline()
        cpu_dispatch.request_one_pool_thread()
    else:
        jax.config.update("jax_num_cpu_devices", args.cpu_devices)  # before JAX's first computation
    batches = args.batch_sizes or ([16] if args.quick else [1, 4, 16, 64, 256])
    steps = args.steps or (400 if args.quick else 2000)
    repeats = 2 if args.quick else 3
    if args.profiles:
        profiles = args.profiles.split(",")
        figures = {
            "benchmark": "rollout_profiles",
            "machine": provenance.machine(),
            "batch": batches[0],
            "steps_per_instance": steps,
            "repeats": repeats,
            "num_devices": len(jax.devices()),
            **profile_costs(profiles, batches[0], steps, repeats),
        }
        print(
            "| profile | MJX closed loop [env-steps/s] | time vs " + profiles[0] + " | native closed loop "
            "[env-steps/s] | time vs " + profiles[0] + " |\n|---|---|---|---|---|"
        )
        for name in profiles:
            print(
                f"| {name} | {figures[f'mjx_{name}_env_steps_per_s']:,} | "
                f"{figures[f'mjx_{name}_time_ratio_vs_{profiles[0]}']:.2f}× | "
                f"{figures[f'native_{name}_env_steps_per_s']:,} | "
                f"{figures[f'native_{name}_time_ratio_vs_{profiles[0]}']:.2f}× |"
            )
        print(json.dumps(figures))
        return

    print(
        f"# native backend ({args.physics} physics, {provenance.machine()}, load average {os.getloadavg()[0]:.1f}): "
        "closed loop against the one-thread replay of its torques"
    )
    print(
        "| batch | stepping | native closed loop [env-steps/s] | replay, 1 thread [env-steps/s] | cores "
        "| closed loop / (cores × replay) | replay on every core / (cores × replay) "
        "| replay max abs Δqpos [m or rad] |\n|---|---|---|---|---|---|---|---|"
    )
    native_figures = {}
    for b in batches:
        r = native_limit(b, steps, repeats, args.physics, args.steppings)
        for name in args.steppings:
            print(
                f"| {b} | {name} | {r[f'closed_loop_env_steps_per_s_{name}']:,.0f} "
                f"| {r['replay_one_thread_env_steps_per_s']:,.0f} | {r['cores']} "
                f"| {r[f'fraction_of_limit_{name}']:.2f} | {r['replay_all_cores_fraction_of_limit']:.2f} "
                f"| {r['replay_max_abs_qpos_diff']:.1e} |",
                flush=True,
            )
            native_figures.update(
                {
                    f"native_{name}_closed_loop_env_steps_per_s_b{b}": round(r[f"closed_loop_env_steps_per_s_{name}"]),
                    f"native_{name}_fraction_of_limit_b{b}": round(r[f"fraction_of_limit_{name}"], 3),
                }
            )
        native_figures.update(
            {
                f"native_replay_one_thread_env_steps_per_s_b{b}": round(r["replay_one_thread_env_steps_per_s"]),
                f"native_replay_max_abs_qpos_diff_b{b}": r["replay_max_abs_qpos_diff"],
                f"native_replay_all_cores_fraction_of_limit_b{b}": round(r["replay_all_cores_fraction_of_limit"], 3),
            }
        )
    # Only where the instances split evenly between the cores can the replay on every core reach the limit.
    cores = native_physics.available_cores()
    shared = {
        b: f
        for b in batches
        if b % cores == 0
        and not INDEPENDENT_CORES
        <= (f := native_figures[f"native_replay_all_cores_fraction_of_limit_b{b}"])
        <= SLOWED_REPLAY
    }
    if shared:
        print(
            "# the replay on every core reached "
            + ", ".join(f"{f:.2f} at batch {b}" for b, f in shared.items())
            + f" of cores × the one-thread replay (outside {INDEPENDENT_CORES}–{SLOWED_REPLAY}"
            + ("; above it the one-thread replay ran slowed" if max(shared.values()) > 1 else "")
            + "): the cores did not run independently in this run, so its closed-loop fractions measure the "
            "machine's other load as well as the code"
        )
    if args.native_only:
        print(
            json.dumps(
                {
                    "benchmark": "rollout_native",
                    "machine": provenance.machine(),
                    "physics": args.physics,
                    "steps_per_instance": steps,
                    "repeats": repeats,
                    "cores": cores,
                    **native_figures,
                    "load_avg_1min_end": round(os.getloadavg()[0], 2),
                }
            )
        )
        return

    device = jax.devices()[0]
    print(
        f"# devices: {len(jax.devices())} x {device.platform} {device.device_kind}; host: {provenance.machine()}; "
        f"jax {jax.__version__}, mujoco {mujoco.__version__}; {steps} steps per instance"
    )
    print(
        "| batch | devices | closed loop [env-steps/s] | bare replay [env-steps/s] | controller overhead (vs replay) "
        "| bare constant control [env-steps/s] | overhead vs constant control | first call (compile) [s] "
        "| native closed loop (C MuJoCo, the same profile as MJX) [env-steps/s] |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    figures: dict = {
        "device": f"{device.platform}:{device.device_kind}",
        "num_devices": len(jax.devices()),
        "machine": provenance.machine(),
        "steps_per_instance": steps,
        "repeats": repeats,
        "native_physics": args.physics,
        **native_figures,
    }
    for b in batches:
        native = trial_speed("native", b, steps, repeats)  # the same trial as MJX's below (soft profile)
        for devices in layouts(b, args.quick):
            r = measure(b, steps, repeats, devices)
            print(
                f"| {b} | {len(devices)} | {r['closed_loop_steps_per_s']:,.0f} | {r['replay_steps_per_s']:,.0f} "
                f"| {r['overhead_vs_replay']:+.1%} | {r['constant_steps_per_s']:,.0f} "
                f"| {r['overhead_vs_constant']:+.1%} "
                f"| {r['first_call_s']:.1f} | {native['env_steps_per_s']:,.0f} |",
                flush=True,
            )
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
    print(f"C MuJoCo, single thread, one default-profile Go1 standing under 1 N·m per motor: {c_rate:,.0f} env-steps/s")
    figures["c_mujoco_standing_single_thread_env_steps_per_s"] = round(c_rate)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
