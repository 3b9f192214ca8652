"""Wall time of a JAX call as the benchmarks measure it: one call to compile and warm up, then the median of
``repeats`` calls, each waited for with ``jax.block_until_ready``. Imported by the benchmark scripts (run as
``python benchmarks/<name>.py``, so this folder is on the path) after any CPU pinning they do."""

import time

import jax
import numpy as np


def median_seconds(fn, *args, repeats: int) -> float:
    """Median wall seconds of ``fn(*args)`` over ``repeats`` calls after a first, compiling call."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))
