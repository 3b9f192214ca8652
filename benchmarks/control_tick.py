"""The shared control tick (``trial.protocol.control``: sensors with the profile's noise → controller → motors),
jitted and vmapped over a batch, as the native backend runs it every 1 ms — and what its sensor-noise draws cost.

Baseline in the same run: the same tick with the noise drawn by ``jax.random`` (threefry: ``fold_in(PRNGKey(seed),
tick)``), the obvious way to write it, against cpgjax's counter-based SplitMix32 draws (``physics.noise_draws``).

    JAX_PLATFORMS=cpu python benchmarks/control_tick.py [--batch 20] [--calls 1000] [--repeats 7]
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from cpgjax import cpg, provenance
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics, sensors
from cpgjax.trial import params, protocol


def threefry_draws(profile: physics.ProfileArrays, tick) -> physics.NoisyReadings:
    key = jax.random.fold_in(jax.random.PRNGKey(profile.noise_seed), tick)
    return physics.NOISE_DRAWS.unravel(jax.random.uniform(key, (physics.NUM_NOISY_READINGS,), jnp.float32, -1.0, 1.0))


def tick_inputs(batch: int):
    m = go1_model.model_with_payload(0.0, physics.ROBOT_PROFILE).__copy__()
    d = mujoco.MjData(m)
    d.qpos[:] = go1_model.standing_qpos(m)
    mujoco.mj_forward(m, d)

    def rep(a):
        return jnp.asarray(np.tile(np.asarray(a, np.float32), (batch,) + (1,) * np.ndim(a)))

    qpos, qvel, sens, gravity = rep(d.qpos), rep(d.qvel), rep(d.sensordata), rep(m.opt.gravity)
    profile = jax.tree.map(
        jnp.asarray, physics.batch_arrays([physics.ROBOT_PROFILE] * batch, noise_seed=np.arange(batch))
    )
    obs = jax.vmap(sensors.observe)(qpos, qvel, sens, gravity)
    return (
        profile,
        jax.vmap(physics.init_state)(obs.foot_force_n),
        jax.vmap(cpg.init_state)(obs),
        rep(params.midpoint()),
        protocol.batch_gates(["vmc_tegotae"] * batch),
        qpos,
        qvel,
        sens,
        gravity,
    )


def time_tick(args, calls: int, repeats: int) -> float:
    """Best over ``repeats`` of the mean µs per call of the jitted, vmapped tick."""
    tick = jax.jit(jax.vmap(lambda *a: protocol.control(cpg.CPGConfig(), *a).torque_nm))
    tick(*args).block_until_ready()
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            out = tick(*args)
        out.block_until_ready()
        best = min(best, (time.perf_counter() - start) / calls * 1e6)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=20, help="instances per tick (the controller ablation's 20)")
    parser.add_argument("--calls", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=7)
    a = parser.parse_args()
    args = tick_inputs(a.batch)
    splitmix_draws = physics.noise_draws
    results = {}
    for _ in range(2):  # interleaved rounds: the best of each
        for name, draws in (("splitmix", splitmix_draws), ("threefry", threefry_draws)):
            physics.noise_draws = draws  # the tick looks the function up when it is traced
            results[name] = min(results.get(name, np.inf), time_tick(args, a.calls, a.repeats))
    physics.noise_draws = splitmix_draws
    print(f"control tick, batch {a.batch}, {provenance.machine()}:")
    for name, us in results.items():
        print(f"  noise by {name}: {us:.1f} µs per tick ({us / results['splitmix']:.2f}× splitmix)")
    print(
        json.dumps(
            {
                "benchmark": "control_tick",
                "machine": provenance.machine(),
                "batch": a.batch,
                **{f"{k}_us_per_tick": round(v, 1) for k, v in results.items()},
                "threefry_vs_splitmix": round(results["threefry"] / results["splitmix"], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
