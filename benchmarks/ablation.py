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

Like the ``cpgjax`` command, the benchmark keeps its compiled programs and loads those of an earlier run
(``cpgjax/compile_cache.py``); the JSON counts them (``compiled_programs``). The first run on
a machine, or ``JAX_ENABLE_COMPILATION_CACHE=false python benchmarks/ablation.py``, compiles everything.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from cpgjax.robot import cpu_dispatch  # noqa: E402

cpu_dispatch.request_inline()  # before any JAX computation

import jax  # noqa: E402

from cpgjax import ablation, compile_cache, cpg, provenance  # noqa: E402
from cpgjax.sim import backends  # noqa: E402
from cpgjax.studies import launch as study_launch  # noqa: E402
from cpgjax.studies import registry  # noqa: E402
from cpgjax.study import files as study_io  # noqa: E402

PAPER_SEEDS = 5  # the paper's controller table: 4 controllers × 5 seeds = 20 instances


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--sweep", type=int, default=0, help="instances (4 controllers × seeds) instead of 20")
    parser.add_argument("--trials", type=int, default=None)
    parser.add_argument("--physics", default=None, help="comma list of physics profiles, one run each, wall-time "
                        "ratios against the first (default: the study's own, paper)")
    parser.add_argument("--distributed", action="store_true", help="one of several processes: jax.distributed."
                        "initialize() first (coordinator, count and rank from the environment or Slurm)")
    parser.add_argument("--processes", type=int, default=None, help="run as N cooperating local processes")
    backends.add_backend_argument(parser)
    args = parser.parse_args()
    if args.backend != "mjx":
        cpu_dispatch.request_one_pool_thread()  # as the cpgjax commands: the cores for MuJoCo's threads
    compile_cache.enable()  # as the cpgjax commands
    if args.processes is not None:
        if args.processes < 1 or args.distributed:
            parser.error(f"--processes {args.processes}: need at least 1, and no --distributed")
        argv = [a for i, a in enumerate(sys.argv[1:]) if not a.startswith("--processes")
                and sys.argv[i] != "--processes"]  # sys.argv[i]: the token before a
        outcome = study_launch.run([sys.executable, os.path.abspath(__file__), *argv, "--distributed"], args.processes)
        if outcome.returncode:
            print(f"benchmarks/ablation.py: {outcome.message}", file=sys.stderr)
        sys.exit(outcome.returncode)
    if args.distributed:
        ablation.initialize_distributed()
    if args.physics:
        walls = {}
        for name in args.physics.split(","):
            walls[name] = run_once(args, name)
        first = next(iter(walls))
        print(json.dumps({"benchmark": "ablation_profiles", **{f"study_wall_s_{k}": v for k, v in walls.items()},
                          **{f"wall_ratio_{k}_vs_{first}": round(v / walls[first], 3) for k, v in walls.items()}}))
        return
    run_once(args, None)


def run_once(args, physics: str | None) -> float:
    """One study run (the physics profile replaced when given); prints its figures, returns its study wall time."""
    if args.sweep:
        seeds = -(-args.sweep // len(cpg.CONTROLLERS))
        spec = registry.ablation_spec(seeds=seeds, trials=args.trials or 40)
        mode = "sweep"
    elif args.quick:
        # the full batch (20 instances), 4 trials
        spec = registry.ablation_spec(seeds=PAPER_SEEDS, trials=args.trials or 4)
        mode = "quick"
    else:
        spec = registry.ablation_spec(seeds=PAPER_SEEDS, trials=args.trials)
        mode = "full"
    if physics is not None:
        spec = dataclasses.replace(spec, physics=(physics,))
    t0 = time.perf_counter()
    engine = ablation.Engine(spec, backend=args.backend)
    last = [None]

    def progress(p):
        last[0] = p
        print(f"{p.trial}/{p.num_trials} trials done: {p.env_steps_per_s:,.0f} env-steps/s, ETA "
              + ("after the first trial" if p.eta_s is None else f"{p.eta_s:.0f} s"),
              flush=True)

    with tempfile.TemporaryDirectory() as out:
        result = engine.run(out, progress=progress)
    total_s = time.perf_counter() - t0
    if jax.process_index() > 0:
        return result.wall_s
    fig = study_io.run_figures(result)
    env = provenance.environment()
    summary = dict(
        benchmark="ablation", mode=mode, machine=f"{env['cpu']}, {env['cpu_count']} CPUs",
        device=env["devices"][0], backend=result.backend, instances=len(result.labels),
        trials=int(result.trials.objective.shape[0]), robot_s=fig["robot_s"], study_wall_s=fig["wall_s"],
        wall_with_setup_s=round(total_s, 2), env_steps_per_s=fig["env_steps_per_s"],
        real_time_factor=fig["real_time_factor"], paper_baseline_real_time_factor=1.0,
        simulation_s=fig["simulation_s"], optimizer_s=fig["optimizer_s"], propose_s=fig["propose_s"],
        observe_s=fig["observe_s"], transfer_s=fig["transfer_s"], checkpoint_s=fig["checkpoint_s"],
        processes=jax.process_count(), exchange_s=fig["exchange_s"],
        exchange_ms_per_trial=round(1e3 * fig["exchange_s"] / max(len(result.trials.objective), 1), 1),
        physics=spec.physics[0], compiled_programs=compile_cache.counts(),
        load_avg_1min_end=round(os.getloadavg()[0], 2), jax=jax.__version__)
    print(json.dumps(summary))
    return fig["wall_s"]


if __name__ == "__main__":
    main()
