"""How long the paper studies at their default size would take if the native backend ran at its physics limit, and
at the speed its closed loop runs now, on this machine.

Each study's physics is its env-steps, instances × trials × ticks per trial, from its default spec
(their study files, ``studies/*.toml``: 20 seeds). The physics limit is ``rollout.native_limit``'s: the closed
loop's torques replayed open loop on the same per-instance models, one thread, times the cores this process may
use. The same run times the closed loop, so the two figures share the machine's speed of the moment (on a VM it
drifts by up to 2× between hours). Both rates are those of one batch (``--batch``, midpoint parameters on flat
ground, `vmc_tegotae`), not of each study's gaits, falls and floors: an estimate of the studies' simulation time,
not of their wall time (the optimizer, the outputs and the compilation come on top).

    JAX_PLATFORMS=cpu python benchmarks/physics_floor.py [--batch 64] [--steps 400] [--repeats 2]

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import json
import os

from rollout import native_limit  # benchmarks/ is the script's directory

from cpgjax import provenance
from cpgjax.go1 import physics as physics_profiles
from cpgjax.robot import cpu_dispatch
from cpgjax.sim import native_physics
from cpgjax.studies import driver as study_driver
from cpgjax.studies import transfer
from cpgjax.study import spec as study_spec
from cpgjax.trial import protocol

TARGET_S = 30 * 60  # docs/REPRODUCTION.md, "Cost": every paper study at 20 seeds within 30 minutes on 2 cores


def study_env_steps() -> dict[str, int]:
    """Env-steps of each registered study at its default size (instances × trials × ticks per trial)."""
    timing = protocol.TrialConfig()
    ticks = timing.transition_steps + timing.steady_steps
    steps = {}
    for name in study_driver.paper_studies():
        if name == transfer.NAME:  # its arms are three studies
            continue
        spec = study_driver.read(name).spec
        steps[name] = len(study_spec.instances(spec)) * spec.num_trials * ticks
    return steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=64, help="instances of the timed batch (default 64)")
    parser.add_argument("--steps", type=int, default=400, help="ticks per timed run (default 400)")
    parser.add_argument("--repeats", type=int, default=2, help="interleaved rounds, best of each (default 2)")
    args = parser.parse_args()
    if args.batch < 1 or args.steps < 4 or args.repeats < 1:
        parser.error(
            f"--batch {args.batch}, --steps {args.steps}, --repeats {args.repeats}: need batch ≥ 1, "
            "steps ≥ 4, repeats ≥ 1"
        )
    cpu_dispatch.request_inline()  # as every cpgjax command on the native backend
    cpu_dispatch.request_one_pool_thread()
    stepping = native_physics.default_stepping()
    physics = physics_profiles.DEFAULT_PROFILE
    r = native_limit(args.batch, args.steps, args.repeats, physics, [stepping])
    limit = r["cores"] * r["replay_one_thread_env_steps_per_s"]
    closed = r[f"closed_loop_env_steps_per_s_{stepping}"]
    steps = study_env_steps()
    print(
        f"# {provenance.machine()}, {r['cores']} cores, {physics} physics, batch {args.batch}, load average "
        f"{os.getloadavg()[0]:.1f}: physics limit {limit:,.0f} env-steps/s ({r['cores']} × the one-thread replay), "
        f"native closed loop {closed:,.0f} env-steps/s ({closed / limit:.2f} of the limit)"
    )
    print("| study | env-steps [M] | at the physics limit [min] | at the closed loop's rate [min] |\n|---|---|---|---|")
    for name, n in steps.items():
        print(f"| {name} | {n / 1e6:.1f} | {n / limit / 60:.1f} | {n / closed / 60:.1f} |")
    total = sum(steps.values())
    print(f"| all | {total / 1e6:.1f} | {total / limit / 60:.1f} | {total / closed / 60:.1f} |")
    print(
        f"30 minutes for all of them needs {total / TARGET_S:,.0f} env-steps/s: "
        f"{total / TARGET_S / limit:.2f} of this run's physics limit"
    )
    print(
        json.dumps(
            {
                "benchmark": "physics_floor",
                "machine": provenance.machine(),
                "physics": physics,
                "stepping": stepping,
                "batch": args.batch,
                "steps_per_instance": args.steps,
                "repeats": args.repeats,
                "cores": r["cores"],
                "replay_one_thread_env_steps_per_s": round(r["replay_one_thread_env_steps_per_s"]),
                "closed_loop_env_steps_per_s": round(closed),
                "fraction_of_limit": round(closed / limit, 3),
                **{f"env_steps_{name}": n for name, n in steps.items()},
                "env_steps_all": total,
                "minutes_at_limit_all": round(total / limit / 60, 1),
                "minutes_at_closed_loop_all": round(total / closed / 60, 1),
                "fraction_of_limit_needed_for_30_min": round(total / TARGET_S / limit, 3),
                "load_avg_1min_end": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
