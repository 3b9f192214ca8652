"""Run JAX's CPU computations on the calling thread (``jax_cpu_enable_async_dispatch = False``), and give XLA's CPU
thread pool one thread, with the kernel order that suits it, where C MuJoCo's threads need the cores
(:func:`request_one_pool_thread`).

Two parts of cpgjax make one small JAX call per 1 ms control tick: the native backend's controller step and the
robot loop's compiled controller. With JAX's default asynchronous CPU dispatch each call is handed to an XLA worker
thread and the caller blocks until it is done: on a busy 2-core machine the hand-off costs more than the computation
(docs/backends.md), and on the robot the loop thread (real-time priority) waits for a worker at normal priority, a
priority inversion that a loaded machine turns into milliseconds. MJX rollouts are unaffected (one call per trial).
"""

from __future__ import annotations

import os

import jax

from cpgjax import jax_internals

# XLA sizes its CPU client's intra-op thread pool from this environment variable when it is set, else from the cores
# it may use (``DefaultThreadPoolSize`` in XLA's xla/pjrt/utils.cc); it reads it once, when JAX creates the client.
POOL_SIZE_VARIABLE = "NPROC"
# XLA's CPU compiler orders each program's kernels breadth first by default, to give a pool of several threads
# independent kernels to run at once; false selects its depth-first order (``CreateHloSchedule`` in XLA's
# xla/service/cpu/cpu_compiler.cc). XLA reads XLA_FLAGS once, when JAX creates its CPU client.
SCHEDULE_FLAG_NAME = "xla_cpu_enable_concurrency_optimized_scheduler"


def request_inline() -> bool:
    """Ask for inline CPU dispatch; return whether it is in effect.

    JAX reads the setting once, when it creates its CPU client at the first computation, so call this at program
    start. Called after JAX has computed anything it returns False (unless the setting was already off): the client
    keeps dispatching asynchronously. Process-wide.
    """
    # jax.config holds only the flag, which the client reads when it is created; whether it exists yet no public API
    # tells without creating it (cpgjax.jax_internals).
    was_inline = not jax.config.read("jax_cpu_enable_async_dispatch")
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    return was_inline or not jax_internals.cpu_client_exists()


def request_one_pool_thread() -> bool:
    """Ask for an XLA CPU thread pool of one thread; return whether it is in effect. Call at program start, as
    :func:`request_inline` (after JAX has computed anything it returns False); a size the environment already sets
    is kept.

    The native backend runs its trial as one XLA program whose physics step runs on MuJoCo's batch threads, one per
    core (``cpgjax.sim.ffi_step``). XLA's own pool, one thread per core by default, wakes for the controller's small
    kernels between the steps, and its threads hold the cores that MuJoCo's need: on 2 cores a tick takes 1.4-1.6x
    as long (docs/backends.md). So cpgjax commands that run the native backend ask for one pool thread; commands on
    MJX keep XLA's default.

    It also asks XLA for the depth-first order of each program's kernels (``SCHEDULE_FLAG_NAME`` false, appended to
    XLA_FLAGS unless they name it). The controller called once per tick from Python (the ``batch`` stepping, where
    the native step cannot be built) then takes about half as long (96 against 191-231 µs a call at batch 16 on
    2 cores), with the same results bit for bit; the trial compiled as one program (the ``ffi`` stepping) runs as
    fast either way (docs/backends.md).
    """
    if jax_internals.cpu_client_exists():
        return False
    os.environ.setdefault(POOL_SIZE_VARIABLE, "1")
    flags = os.environ.get("XLA_FLAGS", "")
    if SCHEDULE_FLAG_NAME not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --{SCHEDULE_FLAG_NAME}=false".strip()
    return os.environ[POOL_SIZE_VARIABLE] == "1"
