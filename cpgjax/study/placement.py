r"""Where a study's batch runs: its placement on the devices and the exchange between the processes of a
multi-process run (docs/scaling.md).

The batch is padded to a multiple of the device count and laid along a 1-D mesh over every device, ordered by process
(:class:`Placement`, :func:`make_placement`); each process owns the contiguous block of rows on its devices
(:attr:`Placement.rows`). Between the processes of a run (``jax.distributed``, :func:`initialize_distributed`) travel
only what :func:`exchange` sends, through the coordinator's key-value store, and what :func:`fetch` gathers.
"""

from __future__ import annotations

import io
import os
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

# jax_internals: the coordinator's client, for its key-value store (exchange). No public API exposes the store, and
# the public all-gathers (jax.experimental.multihost_utils.process_allgather, broadcast_one_to_all) are collectives: a
# process that is alive but never joins holds every other one inside the collective for as long as it stays away (jax
# 0.10.2, CPU: rank 0 waited the 20 s that rank 1 slept before joining), and nothing says which rank is missing. One
# key per rank and a bounded wait for each name the rank that did not deliver (ProcessLost).
from cpgjax import jax_internals

# ----------------------------------------------------------------------------------------------- processes

EXCHANGE_TIMEOUT_ENV = "CPGJAX_EXCHANGE_TIMEOUT_S"  # how long a process waits for another's trial logs
DEFAULT_EXCHANGE_TIMEOUT_S = 600.0  # generous: the first trial compiles, unevenly on a shared machine


class ProcessLost(RuntimeError):
    """Another process of a multi-process run stopped or did not answer in time (the message names its rank)."""


def initialize_distributed() -> None:
    """Join a multi-process run before any JAX computation: ``jax.distributed.initialize()`` with the coordinator
    from ``JAX_COORDINATOR_ADDRESS``, the count and rank from ``JAX_NUM_PROCESSES`` / ``JAX_PROCESS_ID`` when set,
    else from JAX's cluster detection (Slurm, Open MPI, ...). CPU collectives go through gloo. A coordinator on
    127.0.0.1 or localhost listens on that address only (JAX's default binds every interface)."""
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    address = os.environ.get("JAX_COORDINATOR_ADDRESS")
    count, rank = os.environ.get("JAX_NUM_PROCESSES"), os.environ.get("JAX_PROCESS_ID")
    loopback = address is not None and address.rsplit(":", 1)[0] in ("127.0.0.1", "localhost")
    jax.distributed.initialize(
        address,
        None if count is None else int(count),
        None if rank is None else int(rank),
        coordinator_bind_address=address if loopback else None,
    )


def exchange_timeout_s() -> float:
    return float(os.environ.get(EXCHANGE_TIMEOUT_ENV, DEFAULT_EXCHANGE_TIMEOUT_S))


def exchange(local: np.ndarray | Any, timeout_s: float | None = None) -> list:
    """Every process's ``local`` pytree of NumPy arrays, in rank order (an all-gather through the JAX
    coordinator's key-value store, so that a process that does not answer shows as a timeout naming its rank, not a
    hang). A process that dies is noticed sooner by the coordinator, which then stops every process (its message
    names the lost task); ``cpgjax study --processes`` names the rank that died first.

    Every process makes the same sequence of exchanges: the n-th exchange of each process (counted in the
    coordinator's store, so the count lasts as long as the distributed run) meets the n-th of every other.

    Raises:
      ProcessLost: a process did not deliver within ``timeout_s`` (default :func:`exchange_timeout_s`).
    """
    rank, count = jax.process_index(), jax.process_count()
    if count == 1:
        return [local]
    client = jax_internals.coordinator_client()
    timeout_s = exchange_timeout_s() if timeout_s is None else timeout_s
    n = client.key_value_increment(f"cpgjax/exchanges/{rank}", 1) - 1
    leaves, treedef = jax.tree.flatten(local)
    buf = io.BytesIO()
    np.savez(buf, *leaves)
    client.key_value_set_bytes(f"cpgjax/exchange/{n}/{rank}", buf.getvalue())
    if n > 1:  # every process has read it: each set its exchange n − 1 after finishing n − 2
        client.key_value_delete(f"cpgjax/exchange/{n - 2}/{rank}")
    out = []
    for other in range(count):
        if other == rank:
            out.append(local)
            continue
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                data = client.blocking_key_value_get_bytes(f"cpgjax/exchange/{n}/{other}", 1000)
                break
            except Exception as err:  # the coordinator's DEADLINE_EXCEEDED; anything else is fatal
                if "DEADLINE_EXCEEDED" not in str(err):
                    raise ProcessLost(f"process {rank}: exchange {n} with process {other} failed: {err}") from err
            if time.monotonic() > deadline:
                raise ProcessLost(
                    f"process {rank}: no trial data from process {other} of {count} within "
                    f"{timeout_s:g} s ({EXCHANGE_TIMEOUT_ENV}); is it hung?"
                )
        with np.load(io.BytesIO(data)) as z:
            out.append(jax.tree.unflatten(treedef, [z[f"arr_{i}"] for i in range(len(leaves))]))
    return out


# ----------------------------------------------------------------------------------------------- devices


class Placement(NamedTuple):
    """How the batch sits on the devices: a 1-D mesh over axis ``batch``, devices ordered by process; the batch is
    padded to a multiple of the device count with copies of the last instance (their results are dropped)."""

    mesh: Mesh
    padded_size: int
    rows: tuple[int, int]  # [first, stop): the padded batch's rows on this process's devices

    @property
    def sharding(self) -> NamedSharding:
        return NamedSharding(self.mesh, PartitionSpec("batch"))

    @property
    def local_devices(self) -> list:
        return [d for d in self.mesh.devices.flat if d.process_index == jax.process_index()]

    def per_instance(self, fn: Callable, in_axes=0) -> Callable:
        """``fn`` of one instance as a jitted function of the whole sharded batch (``in_axes`` as ``jax.vmap``'s:
        0 for a batched argument, None for one shared by every instance), each device computing its own rows
        (``jax.shard_map``). The instances are independent, so no device needs another's data; left to jit's
        partitioner, the GP's loop over its instances' matrices (``cpgjax.gp``, one matrix per LAPACK call) made
        every device gather the whole batch and compute all of it (all-gathers in propose and observe: on 2 CPU
        devices 1.9× slower, and each process of a multi-process run computed every instance's optimizer)."""
        specs = (
            tuple(PartitionSpec() if axis is None else PartitionSpec("batch") for axis in in_axes)
            if isinstance(in_axes, tuple)
            else PartitionSpec("batch")
        )
        # check_vma=False: the optimizer's scans carry values that the mesh's manual axis would otherwise have to
        # mark as varying by hand (jax.lax.pcast); every value here varies along the batch.
        return jax.jit(
            jax.shard_map(
                jax.vmap(fn, in_axes=in_axes),
                mesh=self.mesh,
                in_specs=specs,
                out_specs=PartitionSpec("batch"),
                check_vma=False,
            )
        )

    def instance_rows(self, batch_size: int) -> tuple[int, int]:
        """[first, stop): the rows of :attr:`rows` that hold instances of a batch of ``batch_size``, not the padding's
        copies of the last one (first = stop where this process holds none)."""
        first, stop = self.rows
        return min(first, batch_size), min(stop, batch_size)

    def pad(self, array) -> np.ndarray:
        """Rows of the batch → the padded batch's: the last row repeated up to :attr:`padded_size`."""
        array = np.asarray(array)
        extra = self.padded_size - array.shape[0]
        return array if extra == 0 else np.concatenate([array, np.repeat(array[-1:], extra, axis=0)])

    def put(self, tree):
        """Host arrays of the whole (padded) batch → arrays sharded along it (each process places its own rows)."""
        sharding = self.sharding

        def one(x):
            x = np.asarray(x)
            return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

        return jax.tree.map(one, tree)

    def put_local(self, tree):
        """Host arrays of this process's rows → arrays of the whole batch sharded along it."""

        def one(x):
            x = np.asarray(x)
            return jax.make_array_from_process_local_data(self.sharding, x, (self.padded_size,) + x.shape[1:])

        return jax.tree.map(one, tree)

    def local(self, tree):
        """Arrays of the whole batch → NumPy of this process's rows (no communication)."""
        first, stop = self.rows

        def one(x):
            if not isinstance(x, jax.Array) or x.is_fully_addressable:
                return np.asarray(x)[first:stop]
            out = np.empty((stop - first,) + x.shape[1:], x.dtype)
            for shard in x.addressable_shards:
                lo, hi, _ = shard.index[0].indices(x.shape[0]) if shard.index else (0, x.shape[0], 1)
                a, b = max(lo, first), min(hi, stop)
                if a < b:
                    out[a - first : b - first] = np.asarray(shard.data)[a - lo : b - lo]
            return out

        return jax.tree.map(one, tree)


def make_placement(batch_size: int, devices=None) -> Placement:
    devices = sorted(jax.devices() if devices is None else devices, key=lambda d: (d.process_index, d.id))
    padded = -(-batch_size // len(devices)) * len(devices)
    per_device = padded // len(devices)
    mine = [i for i, d in enumerate(devices) if d.process_index == jax.process_index()]
    if not mine:
        raise ValueError(f"process {jax.process_index()} has no device among {devices}")
    return Placement(Mesh(np.array(devices), ("batch",)), padded, (mine[0] * per_device, (mine[-1] + 1) * per_device))


def fetch(tree):
    """Arrays → NumPy on this host; arrays sharded over several processes are gathered (every process must call)."""

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree.map(one, tree)
