"""Run provenance: what a run records about the code and the machine it ran on (the commit of the checkout, the
library versions, the CPU and the devices). Study metadata (cpgjax.study.files), the robot's run.json
(cpgjax.deployment.deploy), walks and the benchmarks all write it; it sits below them all, so that neither the
studies nor the robot import each other for it.
"""

from __future__ import annotations

import os
import pathlib
import platform
import subprocess
import sys
from typing import Any

import numpy as np

import cpgjax


def cpu_model() -> str:
    """The CPU's model name (what lscpu reports), or the platform's processor string where it cannot be read."""
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown CPU"


def machine() -> str:
    """'<CPU model>, <n> CPUs': how benchmarks and study metadata name the machine."""
    return f"{cpu_model()}, {os.cpu_count()} CPUs"


def environment() -> dict[str, Any]:
    """This process's Python, JAX, MuJoCo and NumPy versions, platform, CPU, load average, JAX backend and devices, and
    XLA_FLAGS. Imports JAX and MuJoCo when called (importing this module stays cheap); ``jax.devices()`` creates JAX's
    backend if nothing has yet."""
    import jax
    import mujoco

    cpu = cpu_model()
    return dict(
        python=sys.version.split()[0],
        jax=jax.__version__,
        mujoco=mujoco.__version__,
        numpy=np.__version__,
        platform=platform.platform(),
        cpu=cpu,
        cpu_count=os.cpu_count(),
        load_avg=os.getloadavg() if hasattr(os, "getloadavg") else None,
        jax_backend=jax.default_backend(),
        devices=[str(d) for d in jax.devices()],
        xla_flags=os.environ.get("XLA_FLAGS", ""),
    )


def git_commit() -> str | None:
    """The commit of the cpgjax checkout that runs ("<hash>-dirty" with uncommitted changes), None outside git."""
    root = pathlib.Path(cpgjax.__file__).resolve().parent.parent
    try:
        commit = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10
        )
        if commit.returncode != 0:
            return None
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return commit.stdout.strip() + ("-dirty" if dirty else "")
