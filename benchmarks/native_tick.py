"""Where a native-backend tick's time goes: the closed-loop trial split into the controller (the tick's jitted
``_advance``), the physics step (``BatchPhysics.step``: the batch step plus its host arithmetic) and the rest, per
batch size.

With the ``ffi`` stepping (the default where it builds) the closed loop is one compiled program per trial, whose
ticks run the controller and call the physics step through XLA's FFI; its controller is the "controller in a scan"
column below, and the rest is what the loop, the FFI calls and the alternation (caches, the two kinds of threads)
add, less what the overlap hides: with two threads and an even batch, one half's controller runs while the other
half steps (``native.overlapped``), and the rest is then negative. With the ``batch`` stepping (``--stepping
batch``) the host calls the controller once per tick ("controller call") and steps the batch between calls; the
rest is then the glue (record completion, packing the host input, the loop) and the alternation.

Each part is timed on its own over as many calls as the trial has ticks, with the inputs the closed-loop trial gave
it, tick by tick (the controller with the host inputs the trial packed, the physics with the torques it applied),
best of ``--repeats``; the closed loop is timed as a whole, and "rest" is what the two parts leave of it: the glue,
and what the parts cost each other when they alternate (caches, the two thread pools waking).

"Controller in a scan" is the same ``_advance`` with the same per-tick inputs run as the body of one ``lax.scan``
over the trial's ticks, a single XLA call, on the pytree carry the ffi stepping's loop carries: its arithmetic,
without what XLA's CPU runtime and the Python dispatch cost per call, nor the packing of the flat carry that the
per-tick calls take (``native._Carry``). The inputs must vary from
tick to tick as in the trial: with one input for every tick, XLA hoists the observation of it out of the loop, and
the scan then times a part of the controller only (about 0.6 of it at batch 64).

    JAX_PLATFORMS=cpu python benchmarks/native_tick.py [--batch-sizes 16,20,64] [--steps 400] [--repeats 3]
                                                        [--stepping ffi|batch] [--accounts]

``--accounts`` (the ``ffi`` stepping) loads the physics library built with each thread's accounts
(``ffi_step.request_accounts``) and splits the closed loop's best run by thread, inside the loop itself: per tick, the
instances each thread stepped, what a step cost it (and its ``mj_step``), what the first step after other work cost
(the caller's first of each finish, after the controller's kernels), how long a worker was idle, and what the calling
thread spent outside the library (the controller's program, XLA's runtime, the trial's set-up) and waiting in it for
a worker's last instances; beside it, what a step cost in the physics-alone run, with no controller between. The
counting reads the clock four times a step and twice a wait or a finish.

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from cpgjax.robot import cpu_dispatch  # noqa: E402

cpu_dispatch.request_inline()  # as every cpgjax command: the per-tick JAX call runs inline,
cpu_dispatch.request_one_pool_thread()  # and XLA's pool leaves the cores to MuJoCo's threads

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

from cpgjax import provenance  # noqa: E402
from cpgjax.go1 import model as go1_model  # noqa: E402
from cpgjax.go1 import physics as physics_profiles  # noqa: E402
from cpgjax.sim import ffi_step, native_physics  # noqa: E402
from cpgjax.sim import native as native_go1  # noqa: E402
from cpgjax.trial import params as param_space  # noqa: E402
from cpgjax.trial import protocol  # noqa: E402


def _best(run, repeats: int) -> float:
    return min(run() for _ in range(repeats))


def _fields(accounts: np.ndarray) -> dict:
    """The accounts (threads, fields) by field name (``ffi_step.ACCOUNT_FIELDS``): each a (threads,) array."""
    return {name: accounts[:, k] for k, name in enumerate(ffi_step.ACCOUNT_FIELDS)}


def _us_each(ns, count) -> float:
    """µs per counted event: ``ns`` over ``count`` events (at least one)."""
    return round(ns / max(int(count), 1) / 1e3, 2)


def _lanes(accounts: np.ndarray, seconds: float, steps: int) -> dict:
    """Per-thread figures of an accounted run of ``steps`` ticks over ``seconds`` (the module docstring): worker t
    as ``w{t}_``, the caller as ``caller_``."""
    f = _fields(accounts)
    out = {}
    for t in range(accounts.shape[0]):
        who = "caller" if t == accounts.shape[0] - 1 else f"w{t}"
        out.update(
            {
                f"{who}_instances_per_tick": round(f["steps"][t] / steps, 2),
                f"{who}_step_us": _us_each(f["step_ns"][t], f["steps"][t]),
                f"{who}_mj_step_us": _us_each(f["mj_step_ns"][t], f["steps"][t]),
                f"{who}_first_step_us": _us_each(f["first_step_ns"][t], f["first_steps"][t]),
            }
        )
        if who == "caller":
            out["caller_waited_us_per_tick"] = round(f["wait_ns"][t] / steps / 1e3, 1)
            out["caller_outside_us_per_tick"] = round(
                (seconds * 1e9 - f["step_ns"][t] - f["wait_ns"][t]) / steps / 1e3, 1
            )
        else:  # a worker's wait is counted when it ends, so one that began before the run counts: wall − steps
            out[f"{who}_idle_us_per_tick"] = round((seconds * 1e9 - f["step_ns"][t]) / steps / 1e3, 1)
    return out


def breakdown(batch: int, steps: int, repeats: int, physics: str, stepping: str) -> dict:
    """µs per tick of the closed loop, its controller call and its physics step (see the module docstring); with
    accounts, the closed loop's best run and the physics alone split by thread."""
    transition = steps // 4
    config = protocol.TrialConfig(transition_steps=transition, steady_steps=steps - transition)
    sim = native_go1.NativeBackend(
        go1_model.make_scenarios(friction=np.full(batch, 0.6), physics=physics), trial_config=config, stepping=stepping
    )
    p = np.tile(param_space.midpoint(), (batch, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * batch)

    best = {}  # the accounted runs with the fewest seconds: "closed_loop" / "physics" → (seconds, accounts)

    def accounted(name: str, run):
        def timed():
            sim.physics.accounts(reset=True)
            seconds = run()
            accounts = sim.physics.accounts()
            if accounts is not None and seconds < best.get(name, (np.inf,))[0]:
                best[name] = (seconds, accounts)
            return seconds

        return timed

    @functools.partial(accounted, "closed_loop")
    def closed_loop():
        state = sim.reset(p)
        t0 = time.perf_counter()
        jax.block_until_ready(sim.trial(state, p, gates)[1])
        return time.perf_counter() - t0

    closed_loop()  # compiles
    program = sim._program(native_go1.TRIAL_RECORDER, config)
    state = sim.reset(p)
    consts = sim._constants(state.params, jnp.asarray(p, jnp.float32), gates)
    consts_flat = ravel_pytree(consts)[0]
    controller = native_go1._Controller(state.cpg, state.io)

    def fresh_carry(flat: bool):
        return sim._first_carry(program, controller, steps, flat)

    # The host inputs and torques of the closed-loop trial, tick by tick (the per-tick loop of NativeBackend._run,
    # recorded; with the ffi stepping its step is called from Python).
    host_inputs = np.empty((steps, *sim._host_in.shape), np.float32)
    torques = np.empty((steps, batch, 12))
    sim.physics.set_state(state.physics, state.warmstart, state.sensordata)
    carry, failed = fresh_carry(flat=True), np.zeros(batch, bool)
    for k in range(steps):
        host_inputs[k] = sim._pack_host_inputs(failed)
        carry, torque = program.advance(consts_flat, carry, host_inputs[k])
        torques[k] = torque
        failed = sim.physics.step(torques[k])

    def controller_calls():
        carry = fresh_carry(flat=True)
        t0 = time.perf_counter()
        for k in range(steps):
            carry, torque = program.advance(consts_flat, carry, host_inputs[k])
            np.asarray(torque)
        return time.perf_counter() - t0

    @jax.jit
    def scanned(carry, host_inputs):  # the tick of the ffi stepping's loop, on pytrees
        def body(c, host_in):
            c, torque = program.tick(consts, c, host_in)
            return c, torque[0, 0]

        return jax.lax.scan(body, carry, host_inputs)

    host_inputs_device = jnp.asarray(host_inputs)
    jax.block_until_ready(scanned(fresh_carry(flat=False), host_inputs_device))  # compiles

    def controller_scan():
        carry = fresh_carry(flat=False)
        t0 = time.perf_counter()
        jax.block_until_ready(scanned(carry, host_inputs_device))
        return time.perf_counter() - t0

    @functools.partial(accounted, "physics")
    def physics_steps():
        sim.physics.set_state(state.physics, state.warmstart, state.sensordata)
        t0 = time.perf_counter()
        for k in range(steps):
            sim.physics.step(torques[k])
        return time.perf_counter() - t0

    per_tick = {
        name: 1e6 * _best(run, repeats) / steps
        for name, run in (
            ("closed_loop", closed_loop),
            ("controller", controller_calls),
            ("physics", physics_steps),
            ("controller_scan", controller_scan),
        )
    }
    controller = per_tick["controller_scan" if stepping == "ffi" else "controller"]  # what the closed loop runs
    per_tick["rest"] = per_tick["closed_loop"] - controller - per_tick["physics"]
    sim.physics.close()
    lanes = {}
    if "closed_loop" in best:
        lanes = _lanes(best["closed_loop"][1], best["closed_loop"][0], steps)
        alone = _fields(best["physics"][1])
        lanes["physics_alone_step_us"] = _us_each(alone["step_ns"].sum(), alone["steps"].sum())
    return {
        **{f"{k}_us": round(v, 1) for k, v in per_tick.items()},
        "env_steps_per_s": round(batch * 1e6 / per_tick["closed_loop"]),
        "threads": sim.physics.nthread,
        **lanes,
    }


def _print_lanes(lanes: list[tuple[int, dict]]) -> None:
    print(
        "\n# the closed loop's best run by thread (accounts; µs per tick unless said)\n"
        "| batch | thread | instances stepped | µs per step (its mj_step) | first step after other work [µs] "
        "| idle | outside the library | waiting in a finish | µs per step, physics alone |\n"
        "|---|---|---|---|---|---|---|---|---|"
    )
    for b, r in lanes:
        threads = sorted({k.split("_", 1)[0] for k in r if k.endswith("_instances_per_tick")}, key="caller".__eq__)
        for who in threads:
            caller = who == "caller"
            idle = "" if caller else f"{r[who + '_idle_us_per_tick']:.1f}"
            outside = f"{r['caller_outside_us_per_tick']:.1f}" if caller else ""
            waited = f"{r['caller_waited_us_per_tick']:.1f}" if caller else ""
            print(
                f"| {b} | {who} | {r[who + '_instances_per_tick']:.2f} | {r[who + '_step_us']:.1f} "
                f"({r[who + '_mj_step_us']:.1f}) | {r[who + '_first_step_us']:.1f} | {idle} | {outside} | {waited} "
                f"| {r['physics_alone_step_us']:.1f} |"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch-sizes", type=lambda s: [int(v) for v in s.split(",")], default=[16, 20, 64])
    parser.add_argument("--steps", type=int, default=400, help="ticks per timed run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--physics", default=physics_profiles.DEFAULT_PROFILE, choices=physics_profiles.PROFILES)
    parser.add_argument(
        "--stepping",
        choices=("ffi", "batch"),
        default=None,
        help="the native backend's stepping (default: native_physics.default_stepping())",
    )
    parser.add_argument(
        "--accounts",
        action="store_true",
        help="split the closed loop by thread, from the physics library's accounts (ffi stepping)",
    )
    args = parser.parse_args()
    if args.accounts:
        if args.stepping == "batch":
            parser.error("--accounts: the ffi stepping's library keeps the accounts, not --stepping batch")
        ffi_step.request_accounts()
    stepping = args.stepping or native_physics.default_stepping()
    if args.accounts and stepping != "ffi":
        parser.error("--accounts: the ffi stepping is not available on this machine (see the log)")
    if min(args.batch_sizes) < 1 or args.steps < 4 or args.repeats < 1:
        parser.error(
            f"--batch-sizes {args.batch_sizes}, --steps {args.steps}, --repeats {args.repeats}: need "
            "batch sizes ≥ 1, steps ≥ 4, repeats ≥ 1"
        )
    load_start = os.getloadavg()[0]
    print(
        f"# {provenance.machine()}, {native_physics.available_cores()} cores, {args.physics} physics, {stepping} "
        f"stepping, {args.steps} ticks, best of {args.repeats}, load average {load_start:.1f}"
    )
    print(
        "| batch | threads | closed loop [µs/tick] | controller call [µs] | controller in a scan [µs/tick] "
        "| physics step [µs] | rest [µs] | env-steps/s |\n|---|---|---|---|---|---|---|---|"
    )
    lanes = []
    figures = {
        "benchmark": "native_tick",
        "machine": provenance.machine(),
        "physics": args.physics,
        "stepping": stepping,
        "steps": args.steps,
        "repeats": args.repeats,
    }
    for b in args.batch_sizes:
        r = breakdown(b, args.steps, args.repeats, args.physics, stepping)
        print(
            f"| {b} | {r['threads']} | {r['closed_loop_us']:.0f} | {r['controller_us']:.0f} "
            f"| {r['controller_scan_us']:.0f} | {r['physics_us']:.0f} | {r['rest_us']:.0f} "
            f"| {r['env_steps_per_s']:,} |",
            flush=True,
        )
        figures.update({f"{k}_b{b}": v for k, v in r.items()})
        if args.accounts:
            lanes.append((b, r))
    if lanes:
        _print_lanes(lanes)
    figures.update(load_avg_1min_start=round(load_start, 2), load_avg_1min_end=round(os.getloadavg()[0], 2))
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
