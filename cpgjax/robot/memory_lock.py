"""Keep a real-time process's memory resident (``mlockall``): no page of it is evicted, so no tick waits on a disk.

A process that must keep 1 kHz cannot take a major page fault: re-reading an evicted page of its code (the Python,
NumPy, XLA and MuJoCo libraries are file-backed, so the kernel may drop their pages whenever memory is reclaimed)
stops it for as long as the disk takes. On our development VM the kernel's proactive reclaim (DAMON, ``pageout`` of
pages not touched for a few seconds) does this all the time, and it was the cause of the loop's 0.1–0.5 s stalls in
the rehearsal (docs/hardware.md). Real-time robot software locks its memory for the same reason (the Linux
real-time wiki's "memory locking"; ROS 2's real-time guidelines).

Call :func:`lock` once everything is imported and compiled, before the loop starts; :func:`unlock` after it.
Needs CAP_IPC_LOCK or a large enough ``RLIMIT_MEMLOCK``: without them locking is refused and said so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4  # <sys/mman.h>, the same on every Linux architecture
LOCKED = "memory locked"  # lock()'s note when it succeeded


def _libc():
    return ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)


def lock() -> str:
    """Keep every page of the process that is in memory, now or later, in memory; return what was done, as a note
    (:data:`LOCKED`, or why not). Pages are locked as they are touched (``MCL_ONFAULT``, Linux ≥ 4.4): the
    address space that JAX and the allocators reserve but never use is not filled in (locking it all at once
    stalled a process for seconds)."""
    try:
        libc = _libc()
    except OSError as e:
        return f"memory not locked (no C library: {e})"
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE | _MCL_ONFAULT) != 0:
        return f"memory not locked (mlockall: {os.strerror(ctypes.get_errno())})"
    return LOCKED


def unlock() -> None:
    """Undo :func:`lock` (pages may be evicted again)."""
    try:
        _libc().munlockall()
    except OSError:
        pass
