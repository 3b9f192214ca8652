"""Reproducer of a deadlock that cpgjax refuses to run into: an MJX reset of the Go1 batch sharded over two CPU host
devices on two cores never completes at 128 instances per device (jax 0.10.2, mujoco 4.0.0; 64 per device complete).

Cause (gdb on the stuck process): both of XLA's intra-op CPU threads, one per device program, wait in
``BlockingCounter::Wait`` under ``jax::ParallelBatchMap`` in ``lapack_spotrf_ffi``: jaxlib's batched Cholesky (in
MJX's solver) splits a large batch into pieces for the same thread pool and waits for them, and no thread is free to
run them. ``cpgjax.sim.backends.check_mjx_layout`` refuses that layout (with the workarounds); this script calls
``MJXBackend`` directly, so it tells whether a newer jaxlib lifts ``MAX_MJX_INSTANCES_PER_CPU_DEVICE``. Each batch size
runs in a subprocess with a time limit, so this script always ends.

    python benchmarks/cpu_devices_hang.py [--batch-sizes 128,256] [--timeout-s 120]

The batch is split over the 2 devices. The last line is a JSON object: batch size → completed (true/false).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CHILD = """
import sys, jax, numpy as np
from cpgjax.go1 import model as go1_model
from cpgjax import mjx_go1
from cpgjax.trial import params
batch = int(sys.argv[1])
sim = mjx_go1.MJXBackend(go1_model.make_scenarios(friction=np.full(batch, 0.6), physics="soft"))
assert len(sim.mesh.devices.ravel()) == 2
jax.block_until_ready(sim.reset(np.tile(params.midpoint(), (batch, 1))))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch-sizes", type=lambda s: [int(v) for v in s.split(",")], default=[128, 256])
    parser.add_argument("--timeout-s", type=float, default=120.0)
    args = parser.parse_args()
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES="2")
    completed = {}
    for batch in args.batch_sizes:
        try:
            subprocess.run(
                [sys.executable, "-c", CHILD, str(batch)],
                env=env,
                check=True,
                timeout=args.timeout_s,
                capture_output=True,
            )
            completed[batch] = True
        except subprocess.TimeoutExpired:
            completed[batch] = False
        print(
            f"batch {batch} on 2 CPU devices: {'completed' if completed[batch] else 'no result within the limit'}",
            flush=True,
        )
    print(json.dumps({f"completed_b{b}": ok for b, ok in completed.items()}))


if __name__ == "__main__":
    main()
