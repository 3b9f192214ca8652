"""The per-step cost of each terrain against the flat plane, in both backends, as ratios of one run.

For each backend (native C MuJoCo, MJX) four batches of the same size walk the same trials (midpoint parameters,
``vmc_tegotae``, trials back to back from standing): all on the flat plane (the plane model, today's program), all
on rough ground 4 cm peak-to-peak (the terrain model: the feet against the height field, the rest of the robot
against the plane below it), all on blocks of 0.3 m and 4 cm (the same model), and all on flat heights in the
terrain model (what a flat instance costs in a batch that also holds a rough one). After a compiling trial the
backend runs ``--trials`` trials, best of ``--repeats``; the figure is µs per instance-step (wall time / (batch ×
ticks)), and each ratio is against the first terrain (the flat plane) of the same backend in the same run.

    JAX_PLATFORMS=cpu python benchmarks/terrain_cost.py [--batch 4] [--steps 500] [--trials 2] [--repeats 2]
        [--backends native,mjx] [--terrains flat,rough,blocks,flat_heights]

``--terrains flat`` times the flat plane alone, which runs on a checkout without terrains too (the same command
with that checkout first on PYTHONPATH): today's flat program against the flat plane of this one. Timings on a
shared VM drift by more than the difference sought, so ``--program-digest`` prints instead a digest of the flat
batch's compiled programs (the MJX trial, the native trial's ffi program) as StableHLO without source locations:
equal digests on two checkouts mean the same program, hence the same speed.

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import time

import jax
import numpy as np

from cpgjax import mjx_go1, provenance
from cpgjax.go1 import model as go1_model
from cpgjax.sim import native as native_go1
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

BACKENDS = {"native": native_go1.NativeBackend, "mjx": mjx_go1.MJXBackend}
# name → (label, scenario fields) of each batch; the first is the baseline.
TERRAINS = {
    "flat": ("flat plane", dict()),
    "rough": ("rough 4 cm", dict(terrain="rough", terrain_amplitude_m=0.04, terrain_seed=3)),
    "blocks": (
        "blocks 0.3 m, 4 cm",
        dict(terrain="blocks", terrain_amplitude_m=0.04, terrain_seed=3, terrain_step_m=0.3),
    ),
    "flat_heights": ("flat in the terrain model", dict(terrain="rough", terrain_amplitude_m=0.0)),
}


def time_per_step_us(backend: str, fields: dict, batch: int, steps: int, trials: int, repeats: int) -> float:
    """µs per instance-step of ``trials`` back-to-back trials of ``steps`` ticks (best of ``repeats``)."""
    config = protocol.TrialConfig(transition_steps=steps // 5, steady_steps=steps - steps // 5)
    sim = BACKENDS[backend](
        go1_model.make_scenarios(friction=[0.6] * batch, physics="soft", **{k: [v] * batch for k, v in fields.items()}),
        trial_config=config,
    )
    params = np.tile(param_space.midpoint(), (batch, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * batch)
    state = sim.reset(params)
    state, record = sim.trial(state, params, gates)  # compiles
    jax.block_until_ready(record)
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(trials):
            state, record = sim.trial(state, params, gates)
        jax.block_until_ready(record)
        best = min(best, time.perf_counter() - start)
    return 1e6 * best / (batch * trials * steps)


def program_digests(batch: int, steps: int) -> dict[str, str]:
    """SHA-256 (16 hex digits) of the flat batch's MJX trial and native ffi trial program, lowered to StableHLO
    without debug information and source locations."""

    def digest(lowered) -> str:
        text = re.sub(r"#loc\d*( = .*)?|loc\(.*?\)", "", lowered.as_text(debug_info=False))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    config = protocol.TrialConfig(transition_steps=steps // 5, steady_steps=steps - steps // 5)
    scenario = go1_model.make_scenarios(friction=[0.6] * batch, physics="soft")
    params = np.tile(param_space.midpoint(), (batch, 1))
    new_params = protocol.check_params(params, batch)
    gates = protocol.batch_gates(["vmc_tegotae"] * batch)
    mjx = mjx_go1.MJXBackend(scenario, trial_config=config)
    state = mjx.reset(params)
    digests = {
        "mjx trial": digest(
            mjx._trial.lower(
                mjx.batch.model,
                mjx.batch.profile,
                mjx._put(state),
                mjx._put(new_params),
                mjx._put(protocol.check_gates(gates, batch)),
            )
        )
    }
    native = native_go1.NativeBackend(scenario, trial_config=config, stepping="ffi")
    program = native._program(native_go1.TRIAL_RECORDER, config)
    state = native.reset(params)
    carry = native._first_carry(program, native_go1._Controller(state.cpg, state.io), steps, flat=False)
    digests["native ffi trial"] = digest(
        program.run.lower(
            native.physics.ffi_handle,
            native._constants(params, new_params, gates),
            carry,
            native._pack_host_inputs(np.zeros(batch, bool)),
        )
    )
    return digests


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--steps", type=int, default=500, help="ticks per trial")
    parser.add_argument("--trials", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--backends", default="native,mjx")
    parser.add_argument("--terrains", default=",".join(TERRAINS), help="the first is each ratio's baseline")
    parser.add_argument("--program-digest", action="store_true", help="print the flat programs' digests instead")
    args = parser.parse_args()
    if args.program_digest:
        print(
            json.dumps(
                {
                    "benchmark": "terrain_cost_program_digest",
                    "batch": args.batch,
                    "steps": args.steps,
                    **program_digests(args.batch, args.steps),
                }
            )
        )
        return
    backends, terrains = args.backends.split(","), args.terrains.split(",")
    for given, allowed, option in ((backends, BACKENDS, "--backends"), (terrains, TERRAINS, "--terrains")):
        unknown = [b for b in given if b not in allowed]
        if unknown:
            parser.error(f"{option} {unknown[0]!r}: allowed {tuple(allowed)}")
    print(
        f"# {provenance.machine()}, batch {args.batch}, {args.trials} trials of {args.steps} ticks, best of "
        f"{args.repeats}, load average {os.getloadavg()[0]:.2f}"
    )
    figures = {}
    for backend in backends:
        baseline = None
        for label, fields in (TERRAINS[name] for name in terrains):
            us = time_per_step_us(backend, fields, args.batch, args.steps, args.trials, args.repeats)
            baseline = us if baseline is None else baseline
            figures[f"{backend}: {label}"] = {"us_per_instance_step": us, "ratio_to_first": us / baseline}
            print(
                f"{backend:6s} {label:26s} {us:9.1f} µs per instance-step   {us / baseline:5.2f}× the first", flush=True
            )
    print(
        json.dumps(
            {
                "benchmark": "terrain_cost",
                "machine": provenance.machine(),
                "batch": args.batch,
                "steps": args.steps,
                "trials": args.trials,
                "repeats": args.repeats,
                "load_average": os.getloadavg()[0],
                "commit": provenance.git_commit(),
                "figures": figures,
            }
        )
    )


if __name__ == "__main__":
    main()
