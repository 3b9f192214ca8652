"""Benchmark: cpgjax's two hand-written derivatives against JAX's automatic ones, in the same run.

- **The GP's marginal-likelihood gradient** (``gp._log_marginal_likelihood_gradient``, Rasmussen & Williams eq. 5.9),
  which each Adam step of the hyperparameter fit evaluates: ``gp.log_posterior_and_gradient`` against
  ``jax.value_and_grad(gp.log_posterior)``, vmapped over a batch of optimizers as the engine runs them, at several
  capacities with half the rows stored.
- **The legs' Jacobian** (``kinematics.leg_jacobian``), which VMC and the robot's leg odometry evaluate every tick:
  against ``jax.jacfwd(kinematics.leg_fk)``, alone over a batch of instances' 4 legs, and inside the vmapped
  controller step (``cpg.controller_step``, what a tick computes), each compiled with one or the other.

Each pair is first checked to agree (relative 1e-3 for the GP's float32 gradient, 1e-5 for the Jacobian), then timed
alternately, ``--rounds`` times each (the median of ``--repeats`` calls per round, ``benchmarks/timing.py``). Prints a
JSON line per pair with the ratio autodiff / hand-written (> 1: the hand-written one pays).

    JAX_PLATFORMS=cpu python benchmarks/derivatives.py [--quick]
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
from gp_batching import whole_batch_lapack
from timing import median_seconds

from cpgjax import cpg, gp, provenance
from cpgjax.go1 import kinematics, sensors
from cpgjax.trial import params, protocol

CONTEXT_DIMS = 2
INPUT_DIMS = 8 + CONTEXT_DIMS


def gp_problem(batch: int, capacity: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    stored = capacity // 2
    inputs = rng.uniform(size=(batch, capacity, INPUT_DIMS)).astype(np.float32)
    targets = (np.sin(6 * inputs[..., 0]) + inputs[..., 1] ** 2 - inputs[..., -1]).astype(np.float32)
    valid = np.zeros((batch, capacity), bool)
    valid[:, :stored] = True
    params = gp.GPParams(
        log_lengthscales=jnp.asarray(np.log(rng.uniform(0.2, 1.5, (batch, INPUT_DIMS))), jnp.float32),
        log_outputscale=jnp.asarray(np.log(rng.uniform(0.5, 3.0, batch)), jnp.float32),
        log_noise=jnp.asarray(np.log(rng.uniform(1e-3, 0.1, batch)), jnp.float32),
        mean=jnp.asarray(rng.uniform(-0.5, 0.5, batch), jnp.float32),
    )
    active = jnp.ones((batch, INPUT_DIMS), bool)
    return params, gp.Dataset(jnp.asarray(inputs), jnp.asarray(targets), jnp.asarray(valid)), active


def traced(fn, args):
    """``fn`` compiled now for ``args`` (so a patch in force while this runs is what it computes)."""
    return jax.jit(fn).lower(*args).compile()


def gp_pair(problem):
    """(the engine's hand-written gradient, the same with plain LAPACK, autodiff with plain LAPACK), compiled."""
    analytic = jax.vmap(lambda p, d, a: gp.log_posterior_and_gradient(p, d, a, CONTEXT_DIMS))
    autodiff = jax.vmap(jax.value_and_grad(lambda p, d, a: gp.log_posterior(p, d, a, CONTEXT_DIMS)))
    engine = traced(analytic, problem)
    with whole_batch_lapack():  # autodiff cannot pass the GP's one-matrix-per-call batching rule
        return engine, traced(analytic, problem), traced(autodiff, problem)


def legs_pair():
    analytic = jax.jit(jax.vmap(kinematics.legs_jacobian, in_axes=(0, None)))
    autodiff = jax.jit(jax.vmap(jax.vmap(jax.jacfwd(kinematics.leg_fk)), in_axes=(0, None)))
    return analytic, autodiff


def controller_pair(batch: int):
    """The vmapped controller step compiled with the hand-written Jacobian and with jacfwd's, and its inputs."""
    mid = jnp.asarray(np.tile(params.midpoint(), (batch, 1)), jnp.float32)
    obs = sensors.Observation(
        jnp.tile(jnp.asarray([0.0, 0.8, -1.6] * 4, jnp.float32), (batch, 1)),
        jnp.zeros((batch, 12)),
        jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0]), (batch, 1)),
        jnp.zeros((batch, 3)),
        jnp.full((batch, 4), 30.0),
    )
    state = jax.vmap(cpg.init_state)(obs)
    gates = protocol.batch_gates(["vmc_tegotae"] * batch)
    step = jax.vmap(lambda s, p, g, o: cpg.controller_step(cpg.CPGConfig(), s, p, g, o)[1])
    args = (state, mid, gates, obs)
    hand_written = traced(step, args)
    saved = kinematics.legs_jacobian
    kinematics.legs_jacobian = jax.vmap(jax.jacfwd(kinematics.leg_fk))  # read when the step is traced
    try:
        autodiff = traced(step, args)
    finally:
        kinematics.legs_jacobian = saved
    return hand_written, autodiff, args


def alternate(a, b, args, rounds: int, repeats: int) -> tuple[float, float]:
    """Median seconds of a and of b, measured in alternating rounds."""
    ta, tb = [], []
    for _ in range(rounds):
        ta.append(median_seconds(a, *args, repeats=repeats))
        tb.append(median_seconds(b, *args, repeats=repeats))
    return float(np.median(ta)), float(np.median(tb))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer sizes, rounds and repeats")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args(argv)
    rounds, repeats = (2, 5) if args.quick else (args.rounds, args.repeats)
    common = {"machine": provenance.machine(), "commit": provenance.git_commit()}

    for batch, capacity in [(20, 40)] if args.quick else [(20, 40), (80, 40), (20, 80), (20, 160)]:
        problem = gp_problem(batch, capacity)
        engine, analytic, autodiff = gp_pair(problem)
        (v_a, g_a), (v_b, g_b) = analytic(*problem), autodiff(*problem)
        np.testing.assert_allclose(v_a, v_b, rtol=1e-4)
        for x, y in zip(jax.tree.leaves(g_a), jax.tree.leaves(g_b), strict=True):
            np.testing.assert_allclose(x, y, rtol=1e-3, atol=1e-3 * float(np.abs(y).max()))
        t_a, t_b = alternate(analytic, autodiff, problem, rounds, repeats)
        t_e = median_seconds(engine, *problem, repeats=repeats)
        print(
            json.dumps(
                {
                    "benchmark": "derivatives",
                    "what": "GP log-posterior and gradient",
                    "batch": batch,
                    "capacity": capacity,
                    "stored": capacity // 2,
                    "hand_written_us": round(t_a * 1e6, 1),
                    "autodiff_us": round(t_b * 1e6, 1),
                    "autodiff_over_hand_written": round(t_b / t_a, 2),
                    "hand_written_looped_lapack_us": round(t_e * 1e6, 1),
                    **common,
                }
            ),
            flush=True,
        )

    analytic, autodiff = legs_pair()
    side = jnp.asarray(kinematics.SIDE_SIGN, jnp.float32)
    for batch in [20] if args.quick else [1, 20, 64]:
        q = jnp.asarray(np.random.default_rng(1).uniform(-1.0, 1.0, (batch, 4, 3)), jnp.float32)
        np.testing.assert_allclose(analytic(q, side), autodiff(q, side), rtol=1e-5, atol=1e-6)
        t_a, t_b = alternate(analytic, autodiff, (q, side), rounds, repeats * 10)
        print(
            json.dumps(
                {
                    "benchmark": "derivatives",
                    "what": "legs' Jacobian",
                    "batch": batch,
                    "hand_written_us": round(t_a * 1e6, 2),
                    "autodiff_us": round(t_b * 1e6, 2),
                    "autodiff_over_hand_written": round(t_b / t_a, 2),
                    **common,
                }
            ),
            flush=True,
        )
        hand_written, autodiff_step, step_args = controller_pair(batch)
        np.testing.assert_allclose(hand_written(*step_args), autodiff_step(*step_args), rtol=1e-5, atol=1e-4)
        t_a, t_b = alternate(hand_written, autodiff_step, step_args, rounds, repeats * 10)
        print(
            json.dumps(
                {
                    "benchmark": "derivatives",
                    "what": "controller step with the legs' Jacobian",
                    "batch": batch,
                    "hand_written_us": round(t_a * 1e6, 2),
                    "autodiff_us": round(t_b * 1e6, 2),
                    "autodiff_over_hand_written": round(t_b / t_a, 2),
                    **common,
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
