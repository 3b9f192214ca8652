"""What looping the GP's LAPACK calls over the batch costs (cpgjax.gp, docs/backends.md "LAPACK calls, one matrix at a
time"): a vmapped fit + posterior of many instances with the loop against the same program handing whole batches to
jaxlib's LAPACK kernels, same machine, same run, unpinned (the whole batch's LAPACK work is what jaxlib would split
over the intra-op threads).

    python benchmarks/gp_batching.py [--batches 20,80] [--points 40,150] [--repeats 5]

The whole-batch variant is the same module with the batching rule switched off. It can deadlock (independent
batched solves of one program on both intra-op threads), so each measurement runs in a child process with a time
limit (``--timeout-s``), and a child that does not finish is reported as stalled. The last line is a JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys

import jax
import jax.numpy as jnp
import jax.scipy as jsp
from timing import median_seconds  # benchmarks/timing.py

from cpgjax import gp


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", default="20,80")
    parser.add_argument("--points", default="40,150")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--timeout-s", type=float, default=300.0, help="per measurement (compile included)")
    parser.add_argument("--child", nargs=3, metavar=("VARIANT", "BATCH", "POINTS"), help=argparse.SUPPRESS)
    return parser.parse_args()


def program(batch: int, points: int):
    dims = 10
    inputs = jax.random.uniform(jax.random.PRNGKey(0), (batch, points, dims))
    data = gp.Dataset(inputs, jnp.sin(inputs.sum(-1)), jnp.ones((batch, points), bool))
    active = jnp.ones(dims, bool)

    def one(x, y, valid):
        dataset = gp.Dataset(x, y, valid)
        params = gp.fit(dataset, active, gp.default_params(dims), 2)
        return gp.posterior(params, dataset, active, 2).weights

    return jax.vmap(one), data


def seconds(batch: int, points: int, repeats: int) -> float:
    fn, data = program(batch, points)
    return median_seconds(jax.jit(fn), *data, repeats=repeats)


@contextlib.contextmanager
def whole_batch_lapack():
    """The module's one-matrix-per-call wrappers swapped for the plain LAPACK calls (for timing only)."""
    saved = gp._lower_cholesky, gp._solve_lower, gp._cholesky_solve
    gp._lower_cholesky = lambda m: jax.lax.linalg.cholesky(m, symmetrize_input=False)
    gp._solve_lower = lambda lower, rhs: jsp.linalg.solve_triangular(lower, rhs, lower=True)
    gp._cholesky_solve = lambda lower, rhs: jsp.linalg.cho_solve((lower, True), rhs)
    try:
        yield
    finally:
        gp._lower_cholesky, gp._solve_lower, gp._cholesky_solve = saved


def measure(variant: str, batch: int, points: int, args) -> float | None:
    """Seconds of one variant in a child process, or None if it did not finish within the time limit."""
    command = [sys.executable, __file__, "--child", variant, str(batch), str(points), "--repeats", str(args.repeats)]
    try:
        child = subprocess.run(command, capture_output=True, text=True, timeout=args.timeout_s, check=True)
    except subprocess.TimeoutExpired:
        return None
    return float(child.stdout.strip().splitlines()[-1])


def main() -> None:
    args = parse_args()
    if args.child:
        variant, batch, points = args.child[0], int(args.child[1]), int(args.child[2])
        with whole_batch_lapack() if variant == "whole" else contextlib.nullcontext():
            print(seconds(batch, points, args.repeats))
        return
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs (unpinned); "
        f"jax {jax.__version__}"
    )
    figures = {}
    for points in (int(p) for p in args.points.split(",")):
        for batch in (int(b) for b in args.batches.split(",")):
            looped, whole = measure("looped", batch, points, args), measure("whole", batch, points, args)
            figures[f"{batch} x {points} points"] = {
                "looped_s": looped,
                "whole_batch_s": whole,
                "ratio": None if looped is None or whole is None else looped / whole,
            }
            shown = lambda t: "stalled" if t is None else f"{t * 1e3:.1f} ms"  # noqa: E731
            ratio = "" if looped is None or whole is None else f", ratio {looped / whole:.2f}"
            print(
                f"{batch} instances, {points} points: looped {shown(looped)}, whole batch {shown(whole)}{ratio}",
                flush=True,
            )
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
