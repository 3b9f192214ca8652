"""The renderer of :mod:`cpgjax.studies.video`, run as its child process (``python -m cpgjax.studies.renderer
JOBS.npz``), and what each OpenGL backend needs.

MuJoCo loads its OpenGL backend (``MUJOCO_GL``) when it is imported, and an unusable one can fail that import itself
(PyOpenGL without its library, as OSMesa on a machine that lacks it). So this module imports nothing at the top
that loads MuJoCo, and MuJoCo and cpgjax where they are used, after :func:`main` has imported MuJoCo under a check:
a machine without a working backend gets one line, with what to install, and the exit status :data:`UNAVAILABLE`.
"""

from __future__ import annotations

import itertools
import json
import os
import pathlib
import sys
import time

import numpy as np

UNAVAILABLE = 3  # the child's exit status when no OpenGL context can be made
_OSMESA = "install OSMesa (Debian/Ubuntu: apt-get install libosmesa6 libgl1-mesa-dri)"
# What a machine needs for each OpenGL backend (Debian package names).
GL_HELP = {
    "osmesa": _OSMESA,
    "egl": "install EGL (an NVIDIA driver, or Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri)",
    "glx": f"it needs a display (DISPLAY); without one set MUJOCO_GL=osmesa and {_OSMESA}",
    "glfw": f"it needs a display (DISPLAY); without one set MUJOCO_GL=osmesa and {_OSMESA}",
}
STRIP_FRAMES = 4  # frames of each video kept for a figure's filmstrip
CAMERA_DISTANCE_M = 1.4
CAMERA_AZIMUTH_DEG = 120.0  # from the robot's left and front, looking back at it
CAMERA_ELEVATION_DEG = -18.0


def gl_backend(environ=os.environ) -> str:
    """The MUJOCO_GL the renderer uses: the environment's, else EGL with an NVIDIA GPU, else OSMesa."""
    chosen = environ.get("MUJOCO_GL", "").strip().lower()
    if chosen:
        return chosen
    return "egl" if pathlib.Path("/dev/nvidia0").exists() else "osmesa"


def unavailable(err: BaseException) -> int:
    """One line on stderr: this machine's OpenGL backend does not work, and what it needs; returns
    :data:`UNAVAILABLE`."""
    backend = gl_backend()
    what = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
    print(
        f"no video: MuJoCo's {backend!r} OpenGL backend (MUJOCO_GL) does not work here ({what[:120]}); "
        f"{GL_HELP.get(backend, _OSMESA)}",
        file=sys.stderr,
    )
    return UNAVAILABLE


def render_frames(qpos, slope_deg: float, width: int, height: int, ground=None, payload_kg: float = 0.0):
    """Frames (height, width, 3) uint8 of the visual model at each qpos row (T, nq) on ``ground`` (a
    ``terrain.Ground``; None: flat), camera following the trunk, with the payload's box (``go1_model.PAYLOAD_BOX_M``,
    a geom added to the scene, not to the model) where ``payload_kg`` is not zero. Needs a working OpenGL backend
    in this process (MUJOCO_GL)."""
    import mujoco

    from cpgjax.go1 import attitude
    from cpgjax.go1 import model as go1_model

    m = go1_model.load_visual_model() if ground is None else go1_model.visual_model(ground)
    d = mujoco.MjData(m)
    root = go1_model.indices().root_qpos
    tilt = go1_model.slope_quaternion(slope_deg)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.distance, camera.azimuth, camera.elevation = CAMERA_DISTANCE_M, CAMERA_AZIMUTH_DEG, CAMERA_ELEVATION_DEG
    renderer = mujoco.Renderer(m, height, width)
    try:
        for row in np.asarray(qpos, np.float64):
            d.qpos[:] = row
            mujoco.mj_kinematics(m, d)
            camera.lookat[:] = attitude.quat_rotate(tilt, row[root : root + 3])
            renderer.update_scene(d, camera)
            scene = renderer.scene
            if payload_kg > 0.0:
                _add_payload(scene, d, go1_model.indices().payload_body)
            scene.enabletransform = 1
            scene.rotate[:] = tilt
            scene.translate[:] = 0.0
            scene.scale = 1.0
            yield renderer.render()
    finally:
        renderer.close()


def _add_payload(scene, d, body: int) -> None:
    """The payload's box at the carrier body's pose, appended to the scene's geoms (the scene's transform, the
    slope's rotation, applies to it as to the model's)."""
    import mujoco

    from cpgjax.go1 import model as go1_model

    if scene.ngeom >= scene.maxgeom:
        raise RuntimeError(f"the scene holds its most geoms ({scene.maxgeom}): no room for the payload's box")
    half_m = np.asarray(go1_model.PAYLOAD_BOX_M) / 2
    mujoco.mjv_initGeom(
        scene.geoms[scene.ngeom],
        int(mujoco.mjtGeom.mjGEOM_BOX),
        half_m,
        d.xpos[body],
        d.xmat[body],
        np.asarray(go1_model.PAYLOAD_RGBA, np.float32),
    )
    scene.ngeom += 1


def _encode(path: str, frames, fps: int, keep: np.ndarray) -> tuple[int, np.ndarray]:
    """Encode ``frames`` into the MP4 ``path``; returns their count and the frames at indices ``keep``."""
    import imageio.v2 as imageio

    count, kept = 0, {}
    with imageio.get_writer(
        path, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=7, pixelformat="yuv420p", macro_block_size=16
    ) as writer:
        for frame in frames:
            writer.append_data(frame)
            if count in keep:
                kept[count] = frame
            count += 1
    return count, np.stack([kept[k] for k in keep])


def render_jobs(jobs_file: str) -> int:
    """Each video of the jobs file (written by ``video.render_videos``), one JSON line per finished one on stdout,
    and its filmstrip (:data:`STRIP_FRAMES` frames spread over it, as rendered) in a ``.npy`` file beside the jobs
    file; MuJoCo's OpenGL backend is loaded."""
    from cpgjax.go1 import terrain as terrains

    with np.load(jobs_file) as z:
        slopes, fps, width, height = z["slope_deg"], int(z["fps"]), int(z["width"]), int(z["height"])
        payloads = z["payload_kg"]
        paths, qpos = [str(p) for p in z["paths"]], [z[f"qpos_{k}"] for k in range(len(z["paths"]))]
        grounds = [
            terrains.Ground(str(kind), float(a), int(s), float(d))
            for kind, a, s, d in zip(
                z["terrain"], z["terrain_amplitude_m"], z["terrain_seed"], z["terrain_step_m"], strict=True
            )
        ]
    for k, path in enumerate(paths):
        t0 = time.perf_counter()
        frames = render_frames(qpos[k], float(slopes[k]), width, height, grounds[k], float(payloads[k]))
        try:
            first = next(frames)
        except Exception as err:  # the GL backends fail with many types (ImportError, OSError, GL errors...)
            return unavailable(err)
        keep = np.linspace(0, len(qpos[k]) - 1, STRIP_FRAMES).astype(int)
        count, strip = _encode(path, itertools.chain([first], frames), fps, keep)
        strip_file = pathlib.Path(jobs_file).with_name(f"strip_{k}.npy")
        np.save(strip_file, strip)
        print(
            json.dumps(dict(frames=count, render_s=round(time.perf_counter() - t0, 3), strip=str(strip_file))),
            flush=True,
        )
    return 0


def main(argv: list[str]) -> int:
    try:
        import mujoco  # noqa: F401  (loads the OpenGL backend MUJOCO_GL names)
    except Exception as err:  # the GL backends fail with many types (ImportError, OSError, AttributeError...)
        return unavailable(err)
    return render_jobs(argv[0])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
