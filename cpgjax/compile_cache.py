"""What cpgjax compiles once and keeps: the native backend's physics library (``sim/ffi_step.py``) and XLA's compiled
programs (JAX's persistent compilation cache), so that a second run of a command skips compiling what the first did.

Both live under one folder: ``CPGJAX_CACHE_DIR``, else ``$XDG_CACHE_HOME/cpgjax``, else ``~/.cache/cpgjax``.
XLA's CPU programs are built for the instruction set of the CPU they were compiled on, so the programs go into a
subfolder named by the host's CPU (:func:`host_cpu`): machines that share a home folder never load each other's.
The ``cpgjax`` command enables the program cache for itself (:func:`enable`); JAX's own switch
``JAX_ENABLE_COMPILATION_CACHE=false`` turns it off, and a folder set with ``JAX_COMPILATION_CACHE_DIR`` is kept.
Like the library beside it, the cache is trusted code: it is created readable by its owner only.
"""

from __future__ import annotations

import collections
import hashlib
import logging
import os
import pathlib
import platform

import jax
import jax.monitoring

log = logging.getLogger(__name__)

_REQUESTS = "/jax/compilation_cache/compile_requests_use_cache"  # JAX's monitoring events: a program looked up,
_HITS = "/jax/compilation_cache/cache_hits"  # and found
_events: collections.Counter = collections.Counter()  # counted once enable() listens
_listening = False

# Programs of any compile time are kept: the trial, propose and observe programs take about a second of XLA each on
# two cores, and the many small ones a study's setup compiles add up to as much (benchmarks/RESULTS.md).
MIN_COMPILE_TIME_S = 0.0
# The least recently used programs are deleted beyond this size (a study's programs take about 1 MB).
MAX_SIZE_BYTES = 512 * 2**20


def directory() -> pathlib.Path:
    """The folder of everything cpgjax compiles once per machine (created by what writes into it)."""
    if os.environ.get("CPGJAX_CACHE_DIR"):
        return pathlib.Path(os.environ["CPGJAX_CACHE_DIR"])
    return pathlib.Path(os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache") / "cpgjax"


def host_cpu() -> str:
    """A short name for this host's CPU: its architecture, model and instruction-set flags (Linux's
    ``/proc/cpuinfo``, else what ``platform`` reports), hashed."""
    described = [platform.machine(), platform.processor()]
    cpuinfo = pathlib.Path("/proc/cpuinfo")
    if cpuinfo.exists():
        lines = cpuinfo.read_text(errors="replace").splitlines()
        for key in ("model name", "flags", "Features", "CPU part"):  # x86 and ARM spell them differently
            described += [line for line in lines if line.split(":")[0].strip() == key][:1]
    return platform.machine() + "-" + hashlib.sha256("\n".join(described).encode()).hexdigest()[:12]


def programs_directory() -> pathlib.Path:
    return directory() / f"xla-{host_cpu()}"


def enable() -> pathlib.Path | None:
    """Keep this process's compiled XLA programs in :func:`programs_directory` and load them from there (call
    before the first computation to spare them all). Returns the folder in use, or None where JAX's cache is
    switched off."""
    if not jax.config.jax_enable_compilation_cache:
        return None
    folder = jax.config.jax_compilation_cache_dir
    if not folder:
        path = programs_directory()
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", str(path))
        folder = str(path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    jax.config.update("jax_compilation_cache_max_size", MAX_SIZE_BYTES)
    global _listening
    if not _listening:
        jax.monitoring.register_event_listener(_count)
        _listening = True
    log.debug("compiled programs kept in %s", folder)
    return pathlib.Path(folder)


def _count(event: str, **_) -> None:
    if event in (_REQUESTS, _HITS):
        _events[event] += 1


def counts() -> dict[str, int] | None:
    """Since :func:`enable`: the programs this process loaded from the cache and those it compiled; None where the
    cache is not in use."""
    if not _listening or not jax.config.jax_enable_compilation_cache:
        return None
    return {"loaded": _events[_HITS], "compiled": _events[_REQUESTS] - _events[_HITS]}
