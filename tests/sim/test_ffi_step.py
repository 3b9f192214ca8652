"""Building the native backend's FFI physics step (``cpgjax.sim.ffi_step``): a fresh cache gets a whole library
named by what it was built from, and a machine that cannot build it gets one log line and the per-tick stepping.
What the step computes is checked against the other steppings in tests/sim/test_native_physics.py. Also the one XLA
pool thread the native backend's commands ask for (``cpu_dispatch.request_one_pool_thread``)."""

import ctypes
import logging
import os
import subprocess
import sys

import pytest

from cpgjax.sim import ffi_step, native_physics


def test_a_fresh_cache_gets_the_library_with_its_entry_points(tmp_path, monkeypatch):
    compiler = ffi_step._compiler()
    if compiler is None:
        pytest.skip("no C++ compiler on this machine")
    monkeypatch.setenv("CPGJAX_CACHE_DIR", str(tmp_path / "cache"))
    path = ffi_step.library_path(compiler)
    assert path.parent == tmp_path / "cache" and path.name.startswith("batch_step-")
    ffi_step._build(compiler, path)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left behind
    lib = ctypes.CDLL(str(path))
    for name in (ffi_step.TARGET, "cpgjax_stepper_new", "cpgjax_stepper_step", "cpgjax_stepper_delete"):
        assert hasattr(lib, name), name


def test_the_cache_name_changes_with_the_compiler():
    assert ffi_step.library_path("/usr/bin/g++") != ffi_step.library_path("/usr/bin/clang++")


@pytest.mark.parametrize("case", ["no compiler", "failing compiler"])
def test_without_a_working_compiler_one_line_says_so_and_the_backend_steps_tick_by_tick(
    case, tmp_path, monkeypatch, caplog
):
    monkeypatch.setenv("CPGJAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(ffi_step, "_compiler", lambda: None if case == "no compiler" else "false")
    monkeypatch.setattr(ffi_step, "load", ffi_step.load.__wrapped__)  # not the process's cached library
    with caplog.at_level(logging.WARNING, logger=ffi_step.log.name):
        assert ffi_step.load() is None
        assert native_physics.default_stepping() == "batch"
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2  # once per load() call: load() above, then default_stepping()'s
    expected = "no C++ compiler" if case == "no compiler" else "could not be built (false exited with 1"
    assert expected in messages[0] and "steps tick by tick" in messages[0]
    assert list(tmp_path.iterdir()) == []  # a failed build leaves nothing in the cache


@pytest.mark.parametrize("preset", [None, "3"])
def test_one_pool_thread_is_asked_for_before_the_client_and_a_preset_size_is_kept(preset):
    """In a fresh interpreter: ``request_one_pool_thread`` before any computation sets NPROC=1 and XLA's CPU client
    then has one pool thread (``tf_XLAEigen``); after a computation it reports False. A size the environment sets is
    kept (3 threads, although this machine may have fewer cores). It appends the depth-first schedule to XLA_FLAGS,
    which XLA accepts (it aborts the process on a flag it does not know), unless XLA_FLAGS already name it."""
    code = (
        "import glob, os\n"
        "from cpgjax.robot import cpu_dispatch\n"
        "first = cpu_dispatch.request_one_pool_thread()\n"
        "import jax.numpy as jnp\n"
        "(jnp.ones((256, 256)) @ jnp.ones((256, 256))).block_until_ready()\n"
        "names = [open(f).read().strip() for f in glob.glob('/proc/self/task/*/comm')]\n"
        "print(first, os.environ['NPROC'], cpu_dispatch.request_one_pool_thread(), names.count('tf_XLAEigen'))\n"
        "print(os.environ['XLA_FLAGS'])\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("NPROC", "XLA_FLAGS")} | {"JAX_PLATFORMS": "cpu"}
    if preset:  # a size and a schedule of the user's, beside another flag
        env |= {
            "NPROC": preset,
            "XLA_FLAGS": "--xla_cpu_enable_fast_min_max=true --xla_cpu_enable_concurrency_optimized_scheduler=true",
        }
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    threads, flags = out.stdout.splitlines()
    assert threads.split() == (["True", "1", "False", "1"] if preset is None else ["False", "3", "False", "3"])
    assert flags == ("--xla_cpu_enable_concurrency_optimized_scheduler=false" if preset is None else env["XLA_FLAGS"])


def test_mujoco_timers_are_off_while_a_stepper_exists_and_the_callback_found_comes_back():
    """In a fresh interpreter (the callback is process-wide): a Go1 stepped with MuJoCo's timers on, then while a
    native backend's stepper exists (the bindings' clock, then a Python clock set before it), then after it is
    closed. While it exists no timer adds time and the clock set before it is not called; the trajectories are the
    same bit for bit; after it the clock found is back."""
    if not ffi_step.available():
        pytest.skip("the native physics step cannot be built on this machine")
    code = """
import mujoco, numpy as np
from cpgjax.go1 import model as go1_model
from cpgjax.sim import native_physics
scenario = go1_model.make_scenarios(friction=np.array([0.6, 0.6]))
m = go1_model.scenario_model(scenario, 0)
def run():  # (time the step timer added, final qpos) over 50 steps from standing, torques on every motor
    d = mujoco.MjData(m)
    d.qpos[:] = go1_model.standing_qpos(m)
    d.ctrl[:] = 1.0
    for _ in range(50):
        mujoco.mj_step(m, d)
    return d.timer[mujoco.mjtTimer.mjTIMER_STEP].duration, d.qpos.copy()
calls = []
def clock():
    calls.append(1)
    return float(len(calls))
on, q_on = run()
physics = native_physics.BatchPhysics(scenario, stepping="ffi")
off, q_off = run()
mujoco.set_mjcb_time(clock)
physics.close()
physics = native_physics.BatchPhysics(scenario, stepping="ffi")
before = len(calls)
off_again, _ = run()
calls_during = len(calls) - before
physics.close()
after, _ = run()
print(on > 0, off, off_again, calls_during, after > 0, len(calls) > 0, np.array_equal(q_on, q_off))
"""
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env=os.environ | {"JAX_PLATFORMS": "cpu"},
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["True", "0.0", "0.0", "0", "True", "True", "True"]


def test_the_accounts_build_counts_every_step_and_steps_the_same_physics():
    """In fresh interpreters (the library a process loads is the one it keeps): 2 Go1s on 2 threads stepped 30 times
    from Python with the accounts build (``ffi_step.request_accounts``) and with the plain one. The accounts count
    every instance step once, a finish per step on the caller's thread, no more time in mj_step than in the steps;
    the plain build counts nothing (None); the states are the same bytes."""
    if not ffi_step.available():
        pytest.skip("the native physics step cannot be built on this machine")
    code = """
import sys, numpy as np
from cpgjax.sim import ffi_step
if sys.argv[1] == "accounts":
    ffi_step.request_accounts()
from cpgjax.go1 import model as go1_model
from cpgjax.sim import native_physics
scenario = go1_model.make_scenarios(friction=np.array([0.4, 0.9]))
physics = native_physics.BatchPhysics(scenario, nthread=2, stepping="ffi")
torque = np.linspace(-2.0, 2.0, 24, dtype=np.float32).reshape(2, 12)
for _ in range(30):
    physics.step(torque)
accounts = physics.accounts(reset=True)
if accounts is None:
    print("none", physics.physics.tobytes().hex())
else:
    f = dict(zip(ffi_step.ACCOUNT_FIELDS, accounts.T))
    print(accounts.shape, int(f["steps"].sum()), int(f["finishes"][-1]), int(f["finishes"][0]),
          bool(np.all(f["step_ns"] >= f["mj_step_ns"])), bool(f["mj_step_ns"].sum() > 0),
          int(physics.accounts().sum()), physics.physics.tobytes().hex())
"""
    env = os.environ | {"JAX_PLATFORMS": "cpu"}
    out = {
        build: subprocess.run([sys.executable, "-c", code, build], capture_output=True, text=True, timeout=300, env=env)
        for build in ("accounts", "plain")
    }
    for build, done in out.items():
        assert done.returncode == 0, (build, done.stderr[-2000:])
    counted, plain = out["accounts"].stdout.split("\n")[0], out["plain"].stdout.split()
    assert counted.rsplit(" ", 1)[0] == "(2, 7) 60 30 0 True True 0"  # zeroed by the reset read
    assert plain[0] == "none" and counted.rsplit(" ", 1)[1] == plain[1]


def test_accounts_are_refused_once_the_plain_library_is_loaded():
    if not ffi_step.available():
        pytest.skip("the native physics step cannot be built on this machine")
    with pytest.raises(RuntimeError, match="loaded already"):
        ffi_step.request_accounts()
