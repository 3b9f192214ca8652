"""The machine's measured study rate: every study run that writes its metadata records its env-steps per second,
per backend, in the cache folder of this machine (``compile_cache.directory()/study_rates.json``), and a study's
``--dry-run`` estimates its wall time from the latest such run here.

The rate is a whole run's: simulation, optimizer, checkpoints and compilation over its wall time, so it estimates a
run of like size (native: the threads a batch keeps busy; MJX: the devices a batch fills) best.
"""

from __future__ import annotations

import json
import os
import pathlib
import time

from cpgjax import compile_cache

FILE_NAME = "study_rates.json"


def path() -> pathlib.Path:
    return compile_cache.directory() / FILE_NAME


def record(backend: str, figures: dict, study: str, instances: int) -> None:
    """Keep ``figures``' ``env_steps_per_s`` (``files.run_figures``) as ``backend``'s latest rate on this machine; a
    cache folder that cannot be written keeps its old record (the rate is a convenience, not an output)."""
    rates = _read()
    rates[backend] = dict(
        env_steps_per_s=figures["env_steps_per_s"],
        study=study,
        instances=instances,
        wall_s=figures["wall_s"],
        when=time.strftime("%Y-%m-%d %H:%M", time.localtime()),
    )
    target = path()
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f"{FILE_NAME}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(rates, indent=1))
        os.replace(tmp, target)
    except OSError:
        pass


def _read() -> dict:
    try:
        rates = json.loads(path().read_text())
    except (OSError, ValueError):
        return {}
    return rates if isinstance(rates, dict) else {}


def estimate(backend: str, env_steps: int) -> str:
    """The wall time of ``env_steps`` on ``backend`` at this machine's latest measured rate, as a phrase; without
    one, says that none is measured here."""
    latest = _read().get(backend)
    if (
        not isinstance(latest, dict)
        or not isinstance(latest.get("env_steps_per_s"), (int, float))
        or latest["env_steps_per_s"] <= 0
    ):
        return (
            f"no {backend} study has run on this machine yet, so no wall-time estimate (any run, e.g. `make "
            "demo`, measures the rate)"
        )
    wall_s = env_steps / latest["env_steps_per_s"]
    shown = f"{wall_s / 60:.1f} min" if wall_s < 5400 else f"{wall_s / 3600:.1f} h"
    return (
        f"about {shown} at this machine's latest measured rate ({latest['env_steps_per_s']:,.0f} env-steps/s: "
        f"{latest['study']}, {latest['instances']} instances, {latest['when']})"
    )
