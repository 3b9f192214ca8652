"""Native (C MuJoCo stepped by ``mujoco.batch``) against MJX on the CPU, in the same run: env-steps/s of the closed-loop
trial (sensors, jitted controller, physics, trial bookkeeping) per batch size, and the wall time of the
controller-ablation study's simulation with each backend.

    python benchmarks/backend_speed.py                  # full: batch 1, 16, 64, 256 + ablation study
    python benchmarks/backend_speed.py --quick          # under 2 minutes on a 2-core CPU
    python benchmarks/backend_speed.py --sync-dispatch  # JAX CPU computations inline (no async dispatch)

The ablation figure is the study's simulation only: 40 trials × 20 instances (4 controllers × 5 seeds) of the full
1.5 s + 3 s trial, each trial with fixed parameters drawn at random per instance (no optimizer). ``--quick`` times
2 native trials (the first compiles) and extrapolates to 40 from the second (reported as such), and skips the MJX
ablation.

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

from cpgjax import cpg, mjx_go1, provenance
from cpgjax.go1 import model as go1_model
from cpgjax.sim import native as native_go1
from cpgjax.sim import native_physics
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

ABLATION_TRIALS = 40
ABLATION_SEEDS = 5


def _make(backend: str, scenario, trial_config):
    cls = {"mjx": mjx_go1.MJXBackend, "native": native_go1.NativeBackend}[backend]
    return cls(scenario, trial_config=trial_config)


def trial_speed(backend: str, batch: int, steps: int, repeats: int, physics: str = "soft") -> dict:
    """Closed-loop trial env-steps/s (best of ``repeats`` after a warm-up call that compiles) for one backend
    (``physics``: the profile, default ``soft``, that of the figures in RESULTS.md)."""
    transition = steps // 4
    config = protocol.TrialConfig(transition_steps=transition, steady_steps=steps - transition)
    sim = _make(backend, go1_model.make_scenarios(friction=np.full(batch, 0.6), physics=physics), config)
    p = np.tile(param_space.midpoint(), (batch, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * batch)
    state = jax.block_until_ready(sim.reset(p))
    t0 = time.perf_counter()
    state, _ = jax.block_until_ready(sim.trial(state, p, gates))
    first_call_s = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        state, _ = jax.block_until_ready(sim.trial(state, p, gates))
        best = min(best, time.perf_counter() - t0)
    return {"env_steps_per_s": batch * steps / best, "first_call_s": first_call_s}


def ablation_wall_time(backend: str, trials: int) -> dict:
    """Wall time [s] of the ablation batch (4 controllers × 5 seeds) for ``ABLATION_TRIALS`` full trials with random
    fixed parameters per trial and instance, construction and compilation included. With ``trials`` smaller than
    that, the trials after the first (compiling) one are timed and the rest extrapolated from their mean."""
    controllers = [c for c in cpg.CONTROLLERS for _ in range(ABLATION_SEEDS)]
    batch = len(controllers)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    sim = _make(backend, go1_model.make_scenarios(friction=np.full(batch, 0.6), physics="soft"), protocol.TrialConfig())
    gates = protocol.batch_gates(controllers)
    state = sim.reset(np.tile(param_space.midpoint(), (batch, 1)))
    ends = []
    for _ in range(trials):
        params = param_space.from_unit(rng.random((batch, param_space.NUM_PARAMS)))
        state, record = sim.trial(state, params, gates)
        jax.block_until_ready(record)
        ends.append(time.perf_counter() - t0)
    per_trial_s = (ends[-1] - ends[0]) / (trials - 1) if trials > 1 else ends[0]
    wall_s = ends[0] + per_trial_s * (ABLATION_TRIALS - 1)
    return {"wall_s": wall_s, "env_steps_per_s": batch * 4500 / per_trial_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="batch 16, short trials, extrapolated ablation (< 2 min)")
    parser.add_argument("--batch-sizes", type=lambda s: [int(v) for v in s.split(",")], default=None)
    parser.add_argument("--steps", type=int, default=None, help="env steps per instance per timed trial")
    parser.add_argument(
        "--sync-dispatch",
        action="store_true",
        help="set jax_cpu_enable_async_dispatch=False (JAX CPU computations run inline)",
    )
    parser.add_argument(
        "--backends",
        type=lambda s: s.split(","),
        default=["native", "mjx"],
        help="comma-separated subset of native,mjx (default both)",
    )
    parser.add_argument("--no-ablation", action="store_true", help="skip the ablation-study wall time")
    args = parser.parse_args()
    if args.sync_dispatch:
        jax.config.update("jax_cpu_enable_async_dispatch", False)
    batches = args.batch_sizes or ([16] if args.quick else [1, 16, 64, 256])
    steps = args.steps or (400 if args.quick else 2000)
    repeats = 1 if args.quick else 3
    load_start = os.getloadavg()[0]

    device = jax.devices()[0]
    print(
        f"# {provenance.machine()}; JAX device {device.platform}; {native_physics.available_cores()} cores for the "
        "native physics threads; "
        f"{steps} steps per instance; async dispatch {'off' if args.sync_dispatch else 'on'}; "
        f"load average {load_start:.1f}"
    )
    print(
        "| batch | native [env-steps/s] | MJX [env-steps/s] | native / MJX | native first call [s] "
        "| MJX first call (compile) [s] |"
    )
    print("|---|---|---|---|---|---|")
    figures: dict = {
        "benchmark": "backend_speed",
        "machine": provenance.machine(),
        "jax_device": device.platform,
        "steps_per_instance": steps,
        "async_dispatch": not args.sync_dispatch,
        "rollout_threads": native_physics.available_cores(),
    }
    missing = {"env_steps_per_s": float("nan"), "first_call_s": float("nan")}
    for b in batches:
        native, mjx = (
            trial_speed(name, b, steps, repeats) if name in args.backends else missing for name in ("native", "mjx")
        )
        ratio = native["env_steps_per_s"] / mjx["env_steps_per_s"]
        print(
            f"| {b} | {native['env_steps_per_s']:,.0f} | {mjx['env_steps_per_s']:,.0f} | {ratio:.2f}× "
            f"| {native['first_call_s']:.1f} | {mjx['first_call_s']:.1f} |",
            flush=True,
        )
        for name, result in (("native", native), ("mjx", mjx)):
            if name in args.backends:
                figures[f"{name}_env_steps_per_s_b{b}"] = round(result["env_steps_per_s"])
                figures[f"{name}_first_call_s_b{b}"] = round(result["first_call_s"], 2)
        if len(args.backends) == 2:
            figures[f"native_over_mjx_b{b}"] = round(ratio, 3)

    if not args.no_ablation:
        trials = 2 if args.quick else ABLATION_TRIALS
        for backend in [b for b in (("native",) if args.quick else ("native", "mjx")) if b in args.backends]:
            result = ablation_wall_time(backend, trials)
            wall_40 = result["wall_s"]
            note = f" (extrapolated from {trials} trials)" if trials != ABLATION_TRIALS else ""
            print(
                f"ablation study simulation, {backend}: {wall_40:.1f} s for {ABLATION_TRIALS} trials × 20 "
                f"instances{note}; {result['env_steps_per_s']:,.0f} env-steps/s",
                flush=True,
            )
            figures[f"ablation_wall_s_{backend}"] = round(wall_40, 1)
            figures[f"ablation_extrapolated_{backend}"] = trials != ABLATION_TRIALS
    figures["load_avg_1min_start"] = round(load_start, 2)
    figures["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
