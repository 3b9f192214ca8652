"""N cooperating processes on this machine: what ``cpgjax study NAME --processes N`` runs (docs/scaling.md).

:func:`run` starts the same command N times with JAX's coordinator on 127.0.0.1 (a free port) and each process's count
and rank in ``JAX_NUM_PROCESSES`` / ``JAX_PROCESS_ID`` (read by ``study.placement.initialize_distributed``), forwards
every line of their output prefixed with ``[rank i]``, and watches them: when one exits with an error or is killed, the
others are stopped and the message names it. With N no more than the CPU cores each process is pinned to its own block
of cores, so the native backend's threads do not compete.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import NamedTuple

STOP_GRACE_S = 10.0  # after SIGTERM, the time a process has to exit before SIGKILL


class Outcome(NamedTuple):
    returncode: int  # 0 when every process succeeded, else the first failure's code (1 for a signal)
    message: str  # empty on success; else which rank failed first and how


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def process_env(rank: int, num_processes: int, port: int, base: dict | None = None) -> dict:
    """The environment of process ``rank``: the coordinator on 127.0.0.1:``port``, the count and the rank."""
    return dict(
        os.environ if base is None else base,
        JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}",
        JAX_NUM_PROCESSES=str(num_processes),
        JAX_PROCESS_ID=str(rank),
        PYTHONUNBUFFERED="1",
    )


def core_blocks(num_processes: int) -> list[set[int]] | None:
    """This process's CPU cores split into ``num_processes`` contiguous blocks (None when there are fewer cores than
    processes, or no affinity API)."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < num_processes:
        return None
    per = len(cores) // num_processes
    return [set(cores[i * per : (i + 1) * per]) for i in range(num_processes)]


def _describe(rank: int, num_processes: int, code: int) -> str:
    how = f"was killed by signal {signal.Signals(-code).name}" if code < 0 else f"exited with code {code}"
    return f"process rank {rank} of {num_processes} {how}"


def _forward(rank: int, stream, out) -> None:
    for line in iter(stream.readline, b""):
        out.write(f"[rank {rank}] {line.decode(errors='replace')}")
        out.flush()
    stream.close()


def run(command: list[str], num_processes: int, *, env: dict | None = None, out=None, poll_s: float = 0.05) -> Outcome:
    """Run ``command`` as ranks 0 … ``num_processes`` − 1 and wait for all; stop every process as soon as one fails.

    Raises:
      ValueError: ``num_processes`` < 1.
    """
    if num_processes < 1:
        raise ValueError(f"--processes {num_processes}: need at least 1")
    out = sys.stdout if out is None else out
    port = free_port()
    blocks = core_blocks(num_processes)
    procs, threads = [], []
    for rank in range(num_processes):
        proc = subprocess.Popen(
            command, env=process_env(rank, num_processes, port, env), stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )
        if blocks is not None:  # pinned long before its interpreter has imported JAX and started threads
            try:
                os.sched_setaffinity(proc.pid, blocks[rank])
            except ProcessLookupError:  # it has already exited: the watch below reports it
                pass
        thread = threading.Thread(target=_forward, args=(rank, proc.stdout, out), daemon=True)
        thread.start()
        procs.append(proc)
        threads.append(thread)
    try:
        while True:
            codes = [p.poll() for p in procs]
            failed = [(r, c) for r, c in enumerate(codes) if c not in (None, 0)]  # (rank, code)
            if failed or None not in codes:
                break
            time.sleep(poll_s)
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        deadline = time.monotonic() + STOP_GRACE_S
        for p in procs:
            try:
                p.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for t in threads:
            t.join(5.0)
    if not failed:
        return Outcome(0, "")
    # A process that died takes the others down with it (JAX's coordinator aborts them, SIGABRT): seen in the same
    # poll, the one that did not abort is the cause.
    rank, code = sorted(failed, key=lambda f: f[1] == -signal.SIGABRT)[0]
    others = "; stopped the other processes" if num_processes > 1 else ""
    return Outcome(code if code > 0 else 1, _describe(rank, num_processes, code) + others)
