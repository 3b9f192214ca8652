"""The native backend's physics step as XLA FFI targets, so that a whole trial is one compiled JAX program.

``batch_step.cc`` steps a batch of C-MuJoCo Go1s in place, instance by instance on one thread per core (each with
its own one-thread MuJoCo batch, ``mujoco/mjbatch.h``, which runs the instance's model variant and traps MuJoCo's
errors), and does the step's host arithmetic of ``cpgjax.sim.native_physics.BatchPhysics.step`` (the failure test on the
clock, the recovered warm start, the reset of a failed instance) in the same order and precision. Registered with
``jax.ffi``, it is called from inside a ``lax.fori_loop`` over the trial's ticks: the controller, the physics step
and the record then alternate inside one XLA program, with no Python, dispatch or host copy between them. The
whole batch steps in one call (:func:`call`), or in two halves, one started while the other is finished
(:func:`alternate`, :func:`finish`): between two calls the program computes the controller of the half just
finished while the library's threads step the other (``native._run_ffi_overlapped``; docs/backends.md).

The library is compiled once per machine, with the system's C++ compiler, against the headers of the installed
``mujoco`` and ``jaxlib`` wheels, into cpgjax's cache folder (``compile_cache.directory``), under a name that hashes
the source, the compiler and both wheels' versions. Without a compiler (or if the build fails) :func:`load` logs why
in one line and returns None, and the native backend steps tick by tick from Python instead
(``native_physics.default_stepping``).

A process that calls :func:`request_accounts` before the library loads gets it built with each thread's accounts
(the steps it took, the time in them and in their ``mj_step``, the time it waited; :meth:`Stepper.accounts`), for
``benchmarks/native_tick.py --accounts``. Counting reads the clock a few times per step; without the request the
counting compiles to nothing.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import pathlib
import shutil
import subprocess
import tempfile

import jax
import jax.numpy as jnp
import jaxlib
import mujoco
import numpy as np

from cpgjax import compile_cache

log = logging.getLogger(__name__)

SOURCE = pathlib.Path(__file__).with_name("batch_step.cc")
TARGET = "cpgjax_batch_step"  # the FFI targets' names, as the library's symbols: the whole batch's step,
ALTERNATE = "cpgjax_step_alternate"  # one half's step started and the other's finished,
FINISH = "cpgjax_step_finish"  # a part's step finished
ACCOUNT_FIELDS = ("steps", "step_ns", "mj_step_ns", "wait_ns", "first_steps", "first_step_ns", "finishes")
"""What each thread's account counts (``LaneAccount`` in batch_step.cc): the instance steps it took, the time in them
(the lane's copies and the step's host arithmetic included) and in their ``mj_step``, the time it waited for work,
apart the first step it took after other work (the caller: the first of each finish, after the program's own
kernels; a worker: the first after a wait) and the time in those, and the finishes the caller ran."""

_accounts = False


def _compiler() -> str | None:
    return shutil.which(os.environ.get("CXX", "c++")) or shutil.which("g++") or shutil.which("clang++")


def mujoco_library() -> pathlib.Path:
    """The libmujoco shared library of the installed wheel (the one the ``mujoco`` module has loaded)."""
    found = sorted(pathlib.Path(mujoco.__file__).parent.glob("libmujoco.so*"))
    if not found:
        raise FileNotFoundError(f"no libmujoco.so* beside {mujoco.__file__}")
    return found[-1]


def request_accounts() -> None:
    """Build and load the library with each thread's accounts (:data:`ACCOUNT_FIELDS`); before it loads."""
    global _accounts
    if load.cache_info().currsize and not _accounts:
        raise RuntimeError("the native physics library is loaded already: request accounts before the first backend")
    _accounts = True


def _command(compiler: str, output: pathlib.Path) -> list[str]:
    lib = mujoco_library()
    accounts = ["-DCPGJAX_STEPPER_ACCOUNTS"] if _accounts else []
    return [
        compiler,
        "-O2",
        "-std=c++17",
        *accounts,
        "-shared",
        "-fPIC",
        "-w",
        f"-I{jax.ffi.include_dir()}",
        f"-I{lib.parent / 'include'}",
        str(SOURCE),
        "-o",
        str(output),
        f"-L{lib.parent}",
        f"-l:{lib.name}",
        f"-Wl,-rpath,{lib.parent}",
    ]


def library_path(compiler: str) -> pathlib.Path:
    digest = hashlib.sha256()
    for part in (SOURCE.read_bytes(), compiler.encode(), mujoco.__version__.encode(), jaxlib.__version__.encode()):
        digest.update(part)
    return compile_cache.directory() / f"batch_step-{'accounts-' if _accounts else ''}{digest.hexdigest()[:16]}.so"


def _build(compiler: str, path: pathlib.Path) -> None:
    """Compile into a temporary file beside ``path`` and move it there: processes that build at once each finish
    with a whole library."""
    path.parent.mkdir(parents=True, exist_ok=True)
    log.info("building the native physics step (once per machine): %s", path)
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        output = pathlib.Path(tmp) / path.name
        done = subprocess.run(_command(compiler, output), capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"{compiler} exited with {done.returncode}: {done.stderr.strip()[-500:]}")
        os.replace(output, path)


@functools.cache
def load() -> ctypes.CDLL | None:
    """The built library with its FFI target registered, or None (logged) where it cannot be built."""
    compiler = _compiler()
    if compiler is None:
        log.warning(
            "no C++ compiler (CXX, c++, g++, clang++): the native backend steps tick by tick from Python, "
            "slower (docs/backends.md)"
        )
        return None
    path = library_path(compiler)
    try:
        if not path.exists():
            _build(compiler, path)
        lib = ctypes.CDLL(str(path))
    except (OSError, RuntimeError, FileNotFoundError) as err:
        log.warning(
            "the native physics step could not be built (%s): the native backend steps tick by tick from "
            "Python instead (docs/backends.md)",
            err,
        )
        return None
    lib.cpgjax_stepper_new.restype = ctypes.c_void_p
    lib.cpgjax_stepper_new.argtypes = [
        ctypes.c_void_p,
        ctypes.c_int,
        ctypes.c_int,
        ctypes.c_void_p,
        ctypes.c_void_p,
        ctypes.c_int,
        ctypes.c_void_p,
        ctypes.c_void_p,
        ctypes.c_char_p,
        ctypes.c_int,
    ]
    for name in ("cpgjax_stepper_rows", "cpgjax_stepper_sensordata"):
        getattr(lib, name).restype = ctypes.POINTER(ctypes.c_double)
        getattr(lib, name).argtypes = [ctypes.c_void_p]
    for name in ("cpgjax_stepper_nstate", "cpgjax_stepper_nthread"):
        getattr(lib, name).argtypes = [ctypes.c_void_p]
    lib.cpgjax_stepper_step.argtypes = [
        ctypes.c_void_p,
        ctypes.c_void_p,
        ctypes.c_void_p,
        ctypes.c_char_p,
        ctypes.c_int,
    ]
    lib.cpgjax_stepper_accounts.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
    lib.cpgjax_stepper_delete.argtypes = [ctypes.c_void_p]
    for target in (TARGET, ALTERNATE, FINISH):
        jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, target)), platform="cpu")
    return lib


def available() -> bool:
    return load() is not None


class RowOffsets(ctypes.Structure):
    """Where a ``mujoco.batch`` state row keeps what the step reads and writes (``Offsets`` in batch_step.cc)."""

    _fields_ = [
        ("nphysics", ctypes.c_int),
        ("qvel_at", ctypes.c_int),
        ("nv", ctypes.c_int),
        ("warmstart_at", ctypes.c_int),
        ("ctrl_at", ctypes.c_int),
        ("nsensordata", ctypes.c_int),
        ("substeps", ctypes.c_int),
    ]


class Stepper:
    """B Go1s on ``nthread`` threads (the caller's and ``nthread`` − 1 workers, each with a MuJoCo batch of the B
    models: ``mjb_makeBatch`` on ``models[0]`` with one thread, ``mjb_setModels(models)``), stepped by :meth:`step`
    from Python or by :func:`call` (or :func:`alternate`, :func:`finish`) inside a jitted program. ``rows``
    (B, nstate) and ``sensordata`` (B, nsensordata) are views of the library's arrays: the state the next step
    starts from."""

    def __init__(
        self,
        models: list[mujoco.MjModel],
        nthread: int,
        offsets: RowOffsets,
        actuator: np.ndarray,
        standing_physics: np.ndarray,
        standing_sensordata: np.ndarray,
    ):
        self._handle = 0  # what close() (and so __del__) frees: nothing until the library made the batch
        lib = load()
        if lib is None:
            raise RuntimeError("the native physics step is not available (see the log)")
        self._lib = lib
        # The batch reads the models on every step: they and the array of their addresses live as long as it does.
        self._models = list(models)
        batch = len(self._models)
        self._pointers = (ctypes.c_void_p * batch)(*(m._address for m in self._models))
        actuator = np.ascontiguousarray(actuator, np.int32)
        standing_physics = np.ascontiguousarray(standing_physics, np.float64)
        standing_sensordata = np.ascontiguousarray(standing_sensordata, np.float64)
        error = ctypes.create_string_buffer(1000)
        self._handle = lib.cpgjax_stepper_new(
            self._pointers,
            batch,
            nthread,
            ctypes.byref(offsets),
            actuator.ctypes.data,
            actuator.size,
            standing_physics.ctypes.data,
            standing_sensordata.ctypes.data,
            error,
            len(error),
        )
        if not self._handle:
            raise RuntimeError(f"the native physics step refused the batch: {error.value.decode()}")
        self.nthread = lib.cpgjax_stepper_nthread(self._handle)  # its threads, as it clamped them
        self.rows = np.ctypeslib.as_array(
            lib.cpgjax_stepper_rows(self._handle), shape=(batch, lib.cpgjax_stepper_nstate(self._handle))
        )
        self.sensordata = np.ctypeslib.as_array(
            lib.cpgjax_stepper_sensordata(self._handle), shape=(batch, offsets.nsensordata)
        )
        self._failed = np.zeros(batch, np.bool_)
        self._error = error
        # The pointer as two uint32 (JAX's default integers are 32-bit): an argument of the compiled trial, so that
        # one program serves every stepper of its batch size.
        self.handle = np.array([self._handle & 0xFFFFFFFF, self._handle >> 32], np.uint32)

    def step(self, torque_nm: np.ndarray) -> np.ndarray:
        """One step with joint torques (B, 12) float32; returns the (B,) bool mask of failed instances (reset)."""
        torque = np.ascontiguousarray(torque_nm, np.float32)
        if (
            self._lib.cpgjax_stepper_step(
                self._handle, torque.ctypes.data, self._failed.ctypes.data, self._error, len(self._error)
            )
            < 0
        ):
            raise RuntimeError(f"MuJoCo: {self._error.value.decode()}")
        return self._failed.copy()

    def accounts(self, reset: bool = False) -> np.ndarray | None:
        """Each thread's account since the stepper was made or last reset, (threads, len(ACCOUNT_FIELDS)) int64, the
        caller's thread last; None where the library was built without accounts (:func:`request_accounts`). Read
        between steps, after the program that steps has finished."""
        out = np.zeros((self.nthread, len(ACCOUNT_FIELDS)), np.int64)
        return out if self._lib.cpgjax_stepper_accounts(self._handle, out.ctypes.data, int(reset)) else None

    def close(self) -> None:
        """Free the batch and its threads; ``rows`` and ``sensordata`` must not be used after."""
        if self._handle:
            self._lib.cpgjax_stepper_delete(self._handle)
            self._handle = 0

    def __del__(self):
        self.close()


def call(handle: jax.Array, torque_nm: jax.Array, host_in_shape: tuple[int, int]) -> jax.Array:
    """Inside a jitted program: step the stepper ``handle`` names with ``torque_nm`` (B, 12) and return the next
    controller input (B, W) float32, [physics state | sensor data | failed] (``native._host_inputs``)."""
    step = jax.ffi.ffi_call(TARGET, jax.ShapeDtypeStruct(host_in_shape, jnp.float32), has_side_effect=True)
    return step(handle, torque_nm)


def alternate(handle: jax.Array, torque_nm: jax.Array, which: jax.Array, width: int) -> jax.Array:
    """Inside a jitted program, the batch in two halves of H instances: start the step of half ``which`` (int, 0
    or 1; traced) with ``torque_nm`` (H, 12) on the stepper's threads, then finish the other half's step if one is
    started (step on this thread what the threads have not taken, of that half, then of this one) and return the
    other half's controller input after its last step (H, ``width``) float32, as :func:`call`. Halves are started
    in turn, 0 first."""
    half = torque_nm.shape[0]
    step = jax.ffi.ffi_call(ALTERNATE, jax.ShapeDtypeStruct((half, width), jnp.float32), has_side_effect=True)
    return step(handle, torque_nm, jnp.asarray(which, jnp.int32), half=np.int32(half))


def finish(handle: jax.Array, after: jax.Array, part: tuple[int, int], width: int) -> jax.Array:
    """Inside a jitted program: finish the started step of the instances ``part`` = [lo, hi) (as
    :func:`alternate`, starting nothing), after what computes the float32 ``after`` (not read)."""
    end = jax.ffi.ffi_call(FINISH, jax.ShapeDtypeStruct((part[1] - part[0], width), jnp.float32), has_side_effect=True)
    return end(handle, after, lo=np.int32(part[0]), hi=np.int32(part[1]))
