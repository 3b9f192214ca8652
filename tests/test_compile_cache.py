"""Where the cache of compiled programs goes and how it is switched off (``cpgjax/compile_cache.py``); that a study
from loaded programs equals a fresh compilation is tests/test_ablation.py's. Each case enables the cache in a child
process: it is process-wide JAX configuration."""

from __future__ import annotations

import json
import os
import pathlib
import stat
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
# Enable, compile one small program, report the folder in use and the counts.
CHILD = """
import json, jax.numpy as jnp
from cpgjax import compile_cache
folder = compile_cache.enable()
(jnp.arange(3.0) * 2.0).block_until_ready()
print(json.dumps({"folder": None if folder is None else str(folder), "counts": compile_cache.counts()}))
"""


def _child(**env) -> dict:
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_ENABLE_COMP"))}
    done = subprocess.run(
        [sys.executable, "-c", CHILD],
        env=dict(clean, JAX_PLATFORMS="cpu", **env),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_programs_go_to_a_private_folder_per_host_cpu_and_load_in_the_next_process(tmp_path):
    first = _child(CPGJAX_CACHE_DIR=str(tmp_path))
    folder = pathlib.Path(first["folder"])
    assert folder.parent == tmp_path and folder.name.startswith("xla-"), folder
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert first["counts"]["compiled"] >= 1 and first["counts"]["loaded"] == 0, first
    assert any(folder.glob("*-cache")), sorted(p.name for p in folder.iterdir())
    second = _child(CPGJAX_CACHE_DIR=str(tmp_path))
    assert second["folder"] == first["folder"]
    assert second["counts"] == {"loaded": first["counts"]["compiled"], "compiled": 0}, second


@pytest.mark.parametrize("switch", ["false", "0"])
def test_jax_switch_turns_the_cache_off(tmp_path, switch):
    off = _child(CPGJAX_CACHE_DIR=str(tmp_path), JAX_ENABLE_COMPILATION_CACHE=switch)
    assert off == {"folder": None, "counts": None}
    assert not any(tmp_path.iterdir())


def test_a_folder_named_for_jax_is_kept(tmp_path):
    mine = tmp_path / "mine"
    used = _child(CPGJAX_CACHE_DIR=str(tmp_path / "cpgjax"), JAX_COMPILATION_CACHE_DIR=str(mine))
    assert used["folder"] == str(mine) and any(mine.glob("*-cache"))
    assert not (tmp_path / "cpgjax").exists()
