"""What the Go1's 29 visual geoms would cost MJX: one short closed-loop trial (batch 4, 0.3 s + 0.9 s) on the model the
simulators run (``go1_model.load_model``, without them) and on the whole file (``load_visual_model``), timed in
interleaved rounds after compilation (best of each), plus the compile times.

    flock -x /tmp/cpu.lock python benchmarks/visual_geoms.py [--rounds 5]

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

from cpgjax import mjx_go1, provenance
from cpgjax.go1 import model as go1_model
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

TRIAL = protocol.TrialConfig(transition_steps=300, steady_steps=900)
BATCH = 4


def _backend(load) -> mjx_go1.MJXBackend:
    """An MJX backend built while ``go1_model.load_model`` is ``load``."""
    shipped = go1_model.load_model
    for cached in (go1_model.indices, go1_model.model_with_payload):
        cached.cache_clear()
    go1_model.load_model = load
    try:
        return mjx_go1.MJXBackend(go1_model.make_scenarios(friction=[0.6] * BATCH, physics="soft"), trial_config=TRIAL)
    finally:
        go1_model.load_model = shipped
        for cached in (go1_model.indices, go1_model.model_with_payload):
            cached.cache_clear()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    params = np.tile(param_space.midpoint(), (BATCH, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * BATCH)
    runs = {}
    for name, load in (("physics", go1_model.load_model), ("visual", go1_model.load_visual_model)):
        sim = _backend(load)
        t0 = time.perf_counter()
        state = sim.reset(params)
        state, record = sim.trial(state, params, gates)
        jax.block_until_ready(record)
        runs[name] = dict(
            sim=sim, state=state, compile_s=time.perf_counter() - t0, ngeom=int(sim.batch.model.ngeom), best_s=np.inf
        )
    for _ in range(args.rounds):
        for run in runs.values():
            t0 = time.perf_counter()
            run["state"], record = run["sim"].trial(run["state"], params, gates)
            jax.block_until_ready(record)
            run["best_s"] = min(run["best_s"], time.perf_counter() - t0)
    figures = {
        name: dict(ngeom=r["ngeom"], compile_and_first_trial_s=round(r["compile_s"], 2), trial_s=round(r["best_s"], 4))
        for name, r in runs.items()
    }
    figures["visual_over_physics"] = round(runs["visual"]["best_s"] / runs["physics"]["best_s"], 3)
    figures.update(
        machine=provenance.machine(),
        load_avg=os.getloadavg(),
        batch=BATCH,
        steps=TRIAL.transition_steps + TRIAL.steady_steps,
        rounds=args.rounds,
    )
    for name in ("physics", "visual"):
        f = figures[name]
        print(
            f"{name}: {f['ngeom']} geoms, trial {f['trial_s'] * 1e3:.1f} ms (best of {args.rounds}), compile and "
            f"first trial {f['compile_and_first_trial_s']:.1f} s"
        )
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
