"""Keep idle CPUs polling while the loop runs: a zero wake-up latency request to the kernel's PM QoS
(``LoopConfig.poll_idle``, on by default; ``cpgjax deploy --idle-halt`` turns it off).

Between two ticks the loop sleeps for most of a millisecond, and an idle CPU enters whichever idle state its governor
picks: on a robot's computer a deep C-state, which takes time to wake from; on our development VM ``haltpoll``'s
halt without polling first (the kernel's command line has ``haltpoll.guest_halt_poll_ns=0``), which hands the
virtual CPU back to the host, and the tick after it runs slower.

Writing a 32-bit 0 to ``/dev/cpu_dma_latency`` and keeping the file open asks every CPU to use only idle states that
wake up with zero latency: the POLL state, in which the CPU spins in the kernel's idle loop and the loop's timer
wakes it at once. The request lasts while the file is open and ends when it is closed, also when the process dies
(the kernel's PM QoS interface, Documentation/power/pm_qos_interface.rst). rt-tests' ``cyclictest`` makes the same
request unless it is told to save battery (``--laptop``). The cost is power: an idle CPU draws what a busy one draws,
which on a robot's computer comes from its battery. What it changed on our VM is in docs/hardware.md, "The floor".
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

LATENCY_FILE = "/dev/cpu_dma_latency"
REQUESTED = "idle CPUs polling"  # request_polling()'s note when the request was made


def request_polling(path: str = LATENCY_FILE) -> tuple[str, Callable[[], None]]:
    """Ask for zero CPU wake-up latency until the returned function is called; return (a note: :data:`REQUESTED`
    or why not, the release function). Needs write access to ``path`` (root, or a udev rule on the robot)."""
    try:
        fd = os.open(path, os.O_WRONLY)
    except OSError as e:
        return f"idle CPUs may halt ({path}: {e.strerror})", lambda: None
    try:
        os.write(fd, (0).to_bytes(4, sys.byteorder, signed=True))  # an s32 in the CPU's byte order
    except OSError as e:
        os.close(fd)
        return f"idle CPUs may halt (writing {path}: {e.strerror})", lambda: None
    return REQUESTED, lambda: os.close(fd)
