"""Wall time and real-time factor of the controller-ablation study (the paper's Table: 4 controllers × 5 seeds × 40
trials of 1.5 s + 3 s = 3,600 simulated robot-seconds) with the lockstep engine, against the paper's real-time
baseline (1×: Gazebo / the robot run in real time, ≈ 1 hour for this study).

    python benchmarks/ablation.py                   # the full study (engine only: no figures or rollouts)
    python benchmarks/ablation.py --quick           # 4 controllers × 5 seeds × 4 trials (< 2 min on 2 CPU cores)
    python benchmarks/ablation.py --sweep 1000      # ≥ 1,000 instances × 40 trials (GPU: --backend mjx)
    python benchmarks/ablation.py --physics soft,paper,go1   # the study once per physics profile (ratios vs first)
    python benchmarks/ablation.py --processes 2     # as 2 cooperating local processes (docs/scaling.md)
    srun python benchmarks/ablation.py --distributed --sweep 10000 --backend mjx   # one process per Slurm task

Target (issue 4): full study ≤ 5 minutes on 2 CPU cores, i.e. a real-time factor ≥ 12×. Reports env-steps/s, the
real-time factor and where the time goes (simulation, optimizer = propose + observe incl. GP refits, host
transfers, checkpoints, and with several processes the per-trial exchange of trial logs). The last line of the
output is a JSON object of the figures (process 0's).

The physics limit of the study's own steps (native backend, one process, not with ``--sweep``): the start states and
parameters of ``--limit-trials`` trials spread over the study (5 by default; 0 skips it) are kept, and after the study
each is run again with the trial's recorder swapped for the rollout log's (the same controller, transition and
physics), and its torques are replayed open loop from the trial's start state by the same FFI physics step on one
thread (every instance stepped by the calling thread, with the step's host arithmetic: the same trajectories, bit for
bit, which ``mujoco.rollout`` would not give, its warm start differing in the last bits and the study's trials
amplifying that within a few thousand steps; the step's copies and host arithmetic make it about 3 % slower than
``mujoco.rollout`` on the torques of a walking trial, where the two agree): the single-core physics time of the
study's steps is its env-steps at that replay's rate (each trial's replay timed ``REPLAY_REPEATS`` times, the fastest
kept, as ``benchmarks/rollout.py`` keeps the best of its rounds: a moment of other load on the machine slows one
replay, not the limit), and the JSON gives the study's wall time as a fraction of it (the issue's target: ≤ 0.8). A
fraction below 1 / cores, faster than the cores could step the physics, says the replay was still slowed, and the
run says so. The trials of a study are not the rollout benchmark's walking robot (random parameters at
first, falls, the open-loop controller), and their steps cost what they cost.

Like the ``cpgjax`` command, the benchmark keeps its compiled programs and loads those of an earlier run
(``cpgjax/compile_cache.py``); the JSON counts them (``compiled_programs``). The first run on
a machine, or ``JAX_ENABLE_COMPILATION_CACHE=false python benchmarks/ablation.py``, compiles everything.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import sys
import tempfile
import time
from typing import NamedTuple

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from cpgjax.robot import cpu_dispatch  # noqa: E402

cpu_dispatch.request_inline()  # before any JAX computation

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from cpgjax import ablation, compile_cache, cpg, provenance  # noqa: E402
from cpgjax.sim import backends, ffi_step, native_physics  # noqa: E402
from cpgjax.sim import native as native_go1  # noqa: E402
from cpgjax.studies import driver as study_driver  # noqa: E402
from cpgjax.studies import launch as study_launch  # noqa: E402
from cpgjax.study import files as study_io  # noqa: E402
from cpgjax.study import placement as study_placement  # noqa: E402

PAPER_SEEDS = 5  # the paper's controller table: 4 controllers × 5 seeds = 20 instances
REPLAY_REPEATS = 2  # times each sampled trial's torques are replayed for the physics limit (the fastest is kept)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--sweep", type=int, default=0, help="instances (4 controllers × seeds) instead of 20")
    parser.add_argument("--trials", type=int, default=None)
    parser.add_argument(
        "--physics",
        default=None,
        help="comma list of physics profiles, one run each, wall-time "
        "ratios against the first (default: the study's own, paper)",
    )
    parser.add_argument(
        "--distributed",
        action="store_true",
        help="one of several processes: jax.distributed."
        "initialize() first (coordinator, count and rank from the environment or Slurm)",
    )
    parser.add_argument("--processes", type=int, default=None, help="run as N cooperating local processes")
    parser.add_argument(
        "--limit-trials",
        type=int,
        default=5,
        help="trials replayed for the physics limit of the study's own steps (native backend, one process; 0: none)",
    )
    backends.add_backend_argument(parser)
    args = parser.parse_args()
    if args.backend != "mjx":
        cpu_dispatch.request_one_pool_thread()  # as the cpgjax commands: the cores for MuJoCo's threads
    compile_cache.enable()  # as the cpgjax commands
    if args.limit_trials < 0:
        parser.error(f"--limit-trials {args.limit_trials}: need 0 or more")
    if args.processes is not None:
        if args.processes < 1 or args.distributed:
            parser.error(f"--processes {args.processes}: need at least 1, and no --distributed")
        argv = [
            a for i, a in enumerate(sys.argv[1:]) if not a.startswith("--processes") and sys.argv[i] != "--processes"
        ]  # sys.argv[i]: the token before a
        outcome = study_launch.run([sys.executable, os.path.abspath(__file__), *argv, "--distributed"], args.processes)
        if outcome.returncode:
            print(f"benchmarks/ablation.py: {outcome.message}", file=sys.stderr)
        sys.exit(outcome.returncode)
    if args.distributed:
        study_placement.initialize_distributed()
    if args.physics:
        walls = {}
        for name in args.physics.split(","):
            walls[name] = run_once(args, name)
        first = next(iter(walls))
        print(
            json.dumps(
                {
                    "benchmark": "ablation_profiles",
                    **{f"study_wall_s_{k}": v for k, v in walls.items()},
                    **{f"wall_ratio_{k}_vs_{first}": round(v / walls[first], 3) for k, v in walls.items()},
                }
            )
        )
        return
    run_once(args, None)


def run_once(args, physics: str | None) -> float:
    """One study run (the physics profile replaced when given); prints its figures, returns its study wall time."""
    if args.sweep:
        seeds = -(-args.sweep // len(cpg.CONTROLLERS))
        spec = study_driver.read("controller_ablation", seeds=seeds, trials=args.trials or 40).spec
        mode = "sweep"
    elif args.quick:
        # the full batch (20 instances), 4 trials
        spec = study_driver.read("controller_ablation", seeds=PAPER_SEEDS, trials=args.trials or 4).spec
        mode = "quick"
    else:
        spec = study_driver.read("controller_ablation", seeds=PAPER_SEEDS, trials=args.trials).spec
        mode = "full"
    if physics is not None:
        spec = dataclasses.replace(spec, physics=(physics,))
    t0 = time.perf_counter()
    engine = ablation.Engine(spec, backend=args.backend)
    sampled = (
        _sample_trials(engine, spec.num_trials, args.limit_trials)
        if (args.limit_trials and not args.sweep and engine.backend_name == "native" and jax.process_count() == 1)
        else None
    )
    last = [None]

    def progress(p):
        last[0] = p
        print(
            f"{p.trial}/{p.num_trials} trials done: {p.env_steps_per_s:,.0f} env-steps/s, ETA "
            + ("after the first trial" if p.eta_s is None else f"{p.eta_s:.0f} s"),
            flush=True,
        )

    with tempfile.TemporaryDirectory() as out:
        result = engine.run(out, progress=progress)
    total_s = time.perf_counter() - t0
    if jax.process_index() > 0:
        return result.wall_s
    fig = study_io.run_figures(result)
    env = provenance.environment()
    summary = dict(
        benchmark="ablation",
        mode=mode,
        machine=f"{env['cpu']}, {env['cpu_count']} CPUs",
        device=env["devices"][0],
        backend=result.backend,
        instances=len(result.labels),
        trials=int(result.trials.objective.shape[0]),
        robot_s=fig["robot_s"],
        study_wall_s=fig["wall_s"],
        wall_with_setup_s=round(total_s, 2),
        env_steps_per_s=fig["env_steps_per_s"],
        real_time_factor=fig["real_time_factor"],
        paper_baseline_real_time_factor=1.0,
        simulation_s=fig["simulation_s"],
        optimizer_s=fig["optimizer_s"],
        propose_s=fig["propose_s"],
        observe_s=fig["observe_s"],
        transfer_s=fig["transfer_s"],
        checkpoint_s=fig["checkpoint_s"],
        processes=jax.process_count(),
        exchange_s=fig["exchange_s"],
        exchange_ms_per_trial=round(1e3 * fig["exchange_s"] / max(len(result.trials.objective), 1), 1),
        physics=spec.physics[0],
        compiled_programs=compile_cache.counts(),
        load_avg_1min_end=round(os.getloadavg()[0], 2),
        jax=jax.__version__,
    )
    if sampled:
        rate, diff, steps = _replay_rate(sampled)
        single_core_s = fig["env_steps"] / rate
        fraction = fig["wall_s"] / single_core_s
        print(
            f"physics limit of the study's own steps: {len(sampled)} trials ({steps:,} env-steps) replayed on one "
            f"thread at {rate:,.0f} env-steps/s (max |Δstate| against the logged run {diff:.1e}); the study's "
            f"{fig['env_steps']:,} env-steps take {single_core_s:.1f} s of single-core physics, its wall time "
            f"{fraction:.2f} of that"
        )
        cores = native_physics.available_cores()
        if fraction < 1 / cores:
            print(
                f"# the study took less than 1/{cores} of that single-core physics time on {cores} cores: the "
                "replay was slowed by other load on the machine, and this fraction is not the code's"
            )
        summary.update(
            limit_trials=len(sampled),
            replay_one_thread_env_steps_per_s=round(rate),
            replay_max_abs_state_diff=diff,
            single_core_physics_s=round(single_core_s, 2),
            wall_over_single_core_physics=round(fraction, 3),
        )
    print(json.dumps(summary))
    return fig["wall_s"]


class _Sample(NamedTuple):
    """What a sampled trial started from: its backend's scenario and configs, state, parameters and gates."""

    sim: native_go1.NativeBackend
    state: native_go1.NativeState
    new_params: np.ndarray
    gates: cpg.Gates


def _sample_trials(engine: ablation.Engine, num_trials: int, count: int) -> list[_Sample]:
    """Keep the start of ``count`` trials spread over the study (filled in as the engine runs them)."""
    chosen = set(np.linspace(0, num_trials - 1, min(count, num_trials)).round().astype(int).tolist())
    sampled, seen, simulator, kept = [], [0], engine.simulator, set()

    def keeping(sim):
        trial = sim.trial

        def run(state, new_params, gates):
            if seen[0] in chosen:
                host = jax.tree.map(np.array, state)
                sampled.append(_Sample(sim, host, np.array(new_params), jax.tree.map(np.array, gates)))
            seen[0] += 1
            return trial(state, new_params, gates)

        return run

    def wrapped(t, conditions=None):
        sim = simulator(t, conditions)
        if id(sim) not in kept:
            sim.trial = keeping(sim)
            kept.add(id(sim))
        return sim

    engine.simulator = wrapped
    return sampled


@functools.partial(jax.jit, static_argnums=2)
def _replay(handle, torque_nm, width: int):
    """Step the stepper ``handle`` names with ``torque_nm`` (N, B, 12), tick after tick (``ffi_step.call``)."""
    batch = torque_nm.shape[1]
    return jax.lax.fori_loop(
        0,
        torque_nm.shape[0],
        lambda k, _: ffi_step.call(handle, torque_nm[k], (batch, width)),
        jnp.zeros((batch, width), jnp.float32),
    )


def _replay_rate(sampled: list[_Sample]) -> tuple[float, float, int]:
    """One-thread env-steps/s of the sampled trials' physics: each trial run again with the rollout log's recorder
    (the same controller and physics), then its torques replayed from the trial's start state by the same FFI step on
    one thread (a ``BatchPhysics`` with ``nthread=1``: every instance stepped by the calling thread, with the step's
    host arithmetic) inside one compiled loop; also the largest |Δ| between the replay's final states and the logged
    run's (0: the same trajectories), and the env-steps replayed. Each trial's replay is timed ``REPLAY_REPEATS``
    times from its start state, the fastest kept."""
    replayers = {}  # the study's backend → (one like it, the one-thread physics, its compiled replay by shape)
    seconds, diff, steps = 0.0, 0.0, 0
    for s in sampled:
        if id(s.sim) not in replayers:
            again = native_go1.NativeBackend(s.sim.scenario, s.sim.cpg_config, s.sim.trial_config)
            replayers[id(s.sim)] = (again, native_physics.BatchPhysics(again.scenario, nthread=1, stepping="ffi"), {})
        again, one, compiled = replayers[id(s.sim)]
        consts = again._constants(s.state.params, s.new_params, s.gates)
        _, rows = again._run(s.state, native_go1.LOG_RECORDER, again.trial_config, consts)
        logged_end = again.physics.physics.copy()
        torque = jax.block_until_ready(jnp.asarray(rows.torque_nm))  # (N, B, 12) float32, as applied
        width = again._host_in.shape[1]  # the controller's input row: [physics state | sensor data | failed]
        if torque.shape not in compiled:
            compiled[torque.shape] = _replay.lower(one.ffi_handle, torque, width).compile()
        fastest = np.inf
        for _ in range(REPLAY_REPEATS):
            one.set_state(s.state.physics, s.state.warmstart, s.state.sensordata)
            t0 = time.perf_counter()
            jax.block_until_ready(compiled[torque.shape](one.ffi_handle, torque))
            fastest = min(fastest, time.perf_counter() - t0)
            diff = max(diff, float(np.max(np.abs(one.physics - logged_end))))
        seconds += fastest
        steps += torque.shape[0] * torque.shape[1]
    for again, one, _ in replayers.values():
        one.close()
        again.physics.close()
    return steps / seconds, diff, steps


if __name__ == "__main__":
    main()
