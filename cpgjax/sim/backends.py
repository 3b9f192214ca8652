"""Choosing the physics backend: MJX on accelerators, C MuJoCo (native) on CPU-only machines.

Both backends are a ``cpgjax.sim.base.Backend``: they run the same trial with the same jitted controller and sensor
model and return the same ``protocol.TrialRecord`` (see docs/backends.md for speeds and the differences between the
two physics engines).

>>> sim = make_backend(go1_model.make_scenarios(friction=[0.3, 0.6, 0.9]))   # "auto"
>>> sim.name                                                                  # "native" on a laptop
"""

from __future__ import annotations

import argparse

import jax

from cpgjax import cpg, mjx_go1
from cpgjax.go1 import model as go1_model
from cpgjax.sim import native as native_go1
from cpgjax.sim import native_physics
from cpgjax.sim.base import Backend
from cpgjax.trial import protocol

BACKENDS = ("auto", "mjx", "native")


def default_backend() -> str:
    """ "mjx" when JAX's default backend is an accelerator (GPU, TPU, ...), else "native"."""
    return "native" if jax.default_backend() == "cpu" else "mjx"


def resolve_backend(backend: str = "auto") -> str:
    """The concrete backend name ("mjx" or "native") for a choice among ``BACKENDS``."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; allowed: {BACKENDS}")
    return default_backend() if backend == "auto" else backend


# jaxlib's CPU LAPACK kernels split a large batch into pieces for XLA's intra-op thread pool (one thread per core)
# and block until the pieces are done (jax::ParallelBatchMap). The batched Cholesky in MJX's solver is one of them.
# When each pool thread runs one device's program and all of them are inside that Cholesky at the same time, no
# thread is left to run the pieces, and the program never finishes. The most instances per device seen to complete
# (docs/backends.md, "Devices: MJX uses every core only as several host devices"):
MAX_MJX_INSTANCES_PER_CPU_DEVICE = 64


def check_mjx_layout(instances_per_device: int, devices) -> None:
    """Refuse an MJX layout that deadlocks on a CPU: more than ``MAX_MJX_INSTANCES_PER_CPU_DEVICE`` instances on
    each of at least as many CPU devices as this process has cores (the note above).

    Raises:
      ValueError: naming the cause and the workarounds.
    """
    devices = list(devices)
    cores = native_physics.available_cores()
    if (
        len(devices) > 1
        and devices[0].platform == "cpu"
        and len(devices) >= cores
        and instances_per_device > MAX_MJX_INSTANCES_PER_CPU_DEVICE
    ):
        raise ValueError(
            f"MJX with {instances_per_device} instances on each of {len(devices)} CPU devices ({cores} cores) never "
            f"finishes: above {MAX_MJX_INSTANCES_PER_CPU_DEVICE} per device jaxlib's batched Cholesky waits for "
            "XLA CPU threads that are all busy running the devices' programs. Use one CPU device per process "
            f"(cpgjax study --processes {len(devices)}), at most {MAX_MJX_INSTANCES_PER_CPU_DEVICE} instances per "
            "device, or the native backend"
        )


def make_backend(
    scenario: go1_model.Scenario,
    backend: str = "auto",
    cpg_config: cpg.CPGConfig = cpg.CPGConfig(),
    trial_config: protocol.TrialConfig = protocol.TrialConfig(),
    *,
    devices=None,
) -> Backend:
    """A batch simulator (``MJXBackend`` or ``NativeBackend``) for ``scenario``; its ``.name`` says which one.
    ``devices``: what MJX shards the batch over (default: all of this process's that divide it: a simulator never
    spans processes); the native backend's physics runs on host threads and ignores it."""
    if devices is None and jax.process_count() > 1:
        local = jax.local_devices()
        devices = local if scenario.batch_size % len(local) == 0 else local[:1]
    if resolve_backend(backend) == "mjx":
        shown = jax.devices() if devices is None else list(devices)  # what MJXBackend shards over by default
        shown = shown if scenario.batch_size % len(shown) == 0 else shown[:1]
        check_mjx_layout(scenario.batch_size // len(shown), shown)
        return mjx_go1.MJXBackend(scenario, cpg_config=cpg_config, trial_config=trial_config, devices=devices)
    return native_go1.NativeBackend(scenario, cpg_config=cpg_config, trial_config=trial_config)


def add_backend_argument(parser: argparse.ArgumentParser) -> None:
    """``--backend {auto,mjx,native}`` for command-line tools (default auto)."""
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default="auto",
        help="physics backend: auto = MJX with an accelerator, C MuJoCo (native) on CPU only",
    )
