"""cpgjax/jax_internals.py against the JAX it runs on: each internal it reads still exists and means what cpgjax
takes it to mean. A JAX upgrade that moves one fails here, by name, rather than in a robot run or a distributed
study."""

import os
import subprocess
import sys

from cpgjax import jax_internals


def test_the_cpu_client_is_reported_missing_before_the_first_computation_and_present_after():
    code = (
        "from cpgjax import jax_internals\n"
        "before = jax_internals.cpu_client_exists()\n"
        "import jax.numpy as jnp\n"
        "jnp.zeros(1).block_until_ready()\n"
        "print(before, jax_internals.cpu_client_exists())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["False", "True"]


def test_the_coordinator_client_is_none_outside_a_distributed_run():
    """(Inside one, tests/test_ablation_distributed.py runs the key-value exchange through it across processes.)"""
    assert jax_internals.coordinator_client() is None
