"""Videos of the simulated Go1: MuJoCo's offscreen renderer (``mujoco.Renderer``) draws the visual model
(``go1_model.load_visual_model``) along a rollout's qpos, with a camera that follows the trunk, and imageio encodes
the frames as H.264 MP4 with imageio-ffmpeg's packaged ffmpeg.

Rendering runs in a child process (``python -m cpgjax.studies.renderer``): MuJoCo chooses its OpenGL backend from
``MUJOCO_GL`` once, when it is imported, which the parent did long before; the child gets EGL where an NVIDIA GPU is
and OSMesa (software) otherwise, unless ``MUJOCO_GL`` is set. Where no backend works the child says so in one line
(:class:`RenderUnavailable`, with the package to install) and nothing else of the caller is touched. A sloped trial
is drawn with the floor tilted: the scene is rotated from the floor frame, in which the simulation runs with tilted
gravity (docs/decisions.md §4), to one whose z is against gravity.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import tempfile
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from cpgjax import outputs
from cpgjax.go1 import terrain as terrains
from cpgjax.go1.constants import TICK_S
from cpgjax.studies import renderer
from cpgjax.study.files import BEST_PARAMS
from cpgjax.study.spec import StudyError
from cpgjax.trial import limits, tuned
from cpgjax.trial.condition import Condition

FPS = 25  # frames per second of video; one frame every 1000 / FPS ticks of 1 ms, so the video plays in real time
WIDTH, HEIGHT = 640, 480
DURATION_S = limits.Range(0.04, 120.0, "at least one frame, at most two minutes of video")


class RenderUnavailable(RuntimeError):
    """No OpenGL backend works here; the message is one line naming the backend and what to install."""


class Gait(NamedTuple):
    """A gait to film: fixed parameters in one condition, rolled out after a settling trial of the given lengths.
    A study writes one per group as ``best_params/<group>.json`` (:func:`save_gait`: a :mod:`cpgjax.trial.tuned`
    file, which ``cpgjax deploy --params`` and ``cpgjax walk --params`` replay as tuned) and films it as
    ``best_<group>.mp4``."""

    group: str  # the group's name in file names (``cpgjax.studies.gaits.group_name``)
    params: np.ndarray  # (8,) physical units
    controller: str
    physics: str
    condition: Condition  # what it walked in (its file: the condition's fields, the ground's among them)
    transition_steps: int
    steady_steps: int
    objective: float | None = None  # J of the trial the parameters come from
    instance: int | None = None
    trial: int | None = None
    phase: str | None = None  # the phase of the study the trial is from (``cpgjax.studies.gaits.phase_text``)
    walked: bool | None = None  # false: no trial of its group walked (``cpgjax.studies.gaits``)


# A gait file's fields besides what the parameters were tuned for (tuned.TUNED_FOR), required to film it again.
_FILM_FIELDS = ("transition_steps", "steady_steps")
_RECORD_FIELDS = ("group", "params", "controller", "physics", "condition")  # a Gait's fields its file keeps otherwise


def gait_file(out, group: str) -> pathlib.Path:
    return pathlib.Path(out) / BEST_PARAMS / f"{group}.json"


def video_file(out, group: str) -> pathlib.Path:
    return pathlib.Path(out) / f"best_{group}.mp4"


VIDEO = outputs.OutputFile(
    video_file("", "<group>").name,
    "video of the group's best gait (show --video films it again)",
    outputs.check_mp4,
    pattern=r"best_.+\.mp4",
)
OUTPUTS = (VIDEO,)


def save_gait(out, gait: Gait, **info) -> pathlib.Path:
    """``best_params/<group>.json`` of ``gait`` in the :mod:`cpgjax.trial.tuned` format, with the trial lengths, its
    objective, instance and trial, the feet's μ and the ground, and ``info`` (e.g. seed, study)."""
    condition = gait.condition._asdict()
    fields = {**gait._asdict(), **condition}
    tuned_for = {name: fields[name] for name in tuned.TUNED_FOR}
    rest = {k: v for k, v in gait._asdict().items() if k not in _RECORD_FIELDS}
    rest.update(foot_friction=gait.condition.foot_friction, **gait.condition.ground._asdict())
    path = gait_file(out, gait.group)
    path.parent.mkdir(parents=True, exist_ok=True)
    tuned.save(path, gait.params, tuned_for, **rest, **info)
    return path


def load_gaits(out) -> list[Gait]:
    """Every ``best_params/<group>.json`` of the study folder ``out``.

    Raises:
      StudyError: a file that is not such a gait (the message names it and the key).
    """
    gaits = []
    for path in sorted((pathlib.Path(out) / BEST_PARAMS).glob("*.json")):
        try:
            read = tuned.load(path)
            data = json.loads(path.read_text())
            missing = [k for k in tuned.TUNED_FOR if k not in read.tuned_for] + [
                k for k in _FILM_FIELDS if data.get(k) is None
            ]
            if missing:
                raise StudyError(f"{path} is not a study's gait file (missing key {missing[0]!r}); run the study again")
            fields = {k: data[k] for k in Gait._fields if k not in _RECORD_FIELDS and k in data}
            ground = terrains.Ground(**{k: data[k] for k in terrains.Ground._fields if k in data})
            terrains.check_terrain(
                [ground.terrain], [ground.terrain_amplitude_m], [ground.terrain_seed], [ground.terrain_step_m]
            )
            condition = Condition(
                **{k: read.tuned_for[k] for k in Condition._fields if k in read.tuned_for},
                **{k: data[k] for k in ("foot_friction",) if k in data},
                ground=ground,
            )
            gaits.append(
                Gait(
                    group=path.stem,
                    params=read.params,
                    controller=read.tuned_for["controller"],
                    physics=read.tuned_for["physics"],
                    condition=condition,
                    **fields,
                )
            )
        except ValueError as err:  # tuned.load's one line: unreadable, bad JSON, a value out of range
            raise StudyError(str(err)) from None
    return gaits


def frame_ticks(num_ticks: int, fps: int = FPS) -> np.ndarray:
    """The ticks drawn: every ``1 / (fps · TICK_S)``-th, from the first."""
    stride = max(int(round(1.0 / (fps * TICK_S))), 1)
    return np.arange(0, num_ticks, stride)


class Job(NamedTuple):
    """One video to make: the MP4 ``path`` of ``qpos`` (T, nq; 1 ms ticks) in ``condition``: on a floor of its slope
    and ground, carrying its payload (drawn as the payload's box where not zero)."""

    path: pathlib.Path
    qpos: np.ndarray
    condition: Condition = Condition()


def render_videos(jobs: list[Job], *, fps: int = FPS, width: int = WIDTH, height: int = HEIGHT) -> list[dict]:
    """Render every ``frame_ticks`` row of each job's qpos to its MP4 in one child process (each written to a
    temporary name, then renamed). Returns per job {path, frames, rollout_s, render_s (in the child, without its
    start), backend, strip: ``renderer.STRIP_FRAMES`` frames (H, W, 3) spread over the video, as rendered, for a
    figure}.

    Raises:
      RenderUnavailable: no OpenGL backend here (one line: the backend tried and what to install); nothing written.
      RuntimeError: the child failed otherwise (its last error line); the videos it finished are kept.
    """
    backend = renderer.gl_backend()
    env = dict(os.environ, MUJOCO_GL=backend, JAX_PLATFORMS="cpu")
    if backend in ("osmesa", "egl"):
        env["PYOPENGL_PLATFORM"] = backend
    tmps = [str(pathlib.Path(j.path).with_name(f".{pathlib.Path(j.path).name}.tmp.mp4")) for j in jobs]
    with tempfile.TemporaryDirectory() as folder:
        frames_file = pathlib.Path(folder) / "jobs.npz"
        arrays = {
            f"qpos_{k}": np.asarray(j.qpos, np.float64)[frame_ticks(len(j.qpos), fps)] for k, j in enumerate(jobs)
        }
        grounds = terrains.ground_fields(j.condition.ground for j in jobs)
        np.savez(
            frames_file,
            slope_deg=np.array([float(j.condition.slope_deg) for j in jobs]),
            payload_kg=np.array([float(j.condition.payload_kg) for j in jobs]),
            fps=fps,
            width=width,
            height=height,
            paths=np.array(tmps),
            **grounds,
            **arrays,
        )
        child = subprocess.run(
            [sys.executable, "-m", "cpgjax.studies.renderer", str(frames_file)], env=env, capture_output=True, text=True
        )
        done = [json.loads(line) for line in child.stdout.splitlines() if line.startswith("{")]
        for info in done:
            info["strip"] = np.load(info["strip"])
    last = (child.stderr.strip().splitlines() or [""])[-1]
    infos = []
    for job, tmp, info in zip(jobs, tmps, done, strict=False):  # done: the videos the child finished, a prefix
        os.replace(tmp, job.path)
        infos.append(dict(info, path=str(job.path), rollout_s=len(job.qpos) * TICK_S, backend=backend))
    for tmp in tmps[len(done) :]:
        pathlib.Path(tmp).unlink(missing_ok=True)
    if child.returncode == renderer.UNAVAILABLE:
        raise RenderUnavailable(last)
    if child.returncode != 0:
        raise RuntimeError(f"rendering failed (status {child.returncode}): {last}")
    return infos


def write_videos(out, gaits: list[Gait], logs: list, notify: Callable[[str], None]) -> list[dict]:
    """``best_<group>.mp4`` of each gait from its rollout log (``protocol.StepLog``, arrays (T, ...)), a line to
    ``notify`` for each. Where no OpenGL backend works, one line says so and no video is written; another rendering
    failure is one line too. Either way the caller's other files are left as they are."""
    jobs = [
        Job(path=video_file(out, g.group), qpos=log.qpos, condition=g.condition)
        for g, log in zip(gaits, logs, strict=True)
    ]
    try:
        infos = render_videos(jobs)
    except (RenderUnavailable, RuntimeError) as err:
        notify(str(err))
        return []
    for gait, info in zip(gaits, infos, strict=True):
        c, g = gait.condition, gait.condition.ground
        ground = (
            ""
            if g.terrain == terrains.FLAT
            else f", {g.terrain} ground {g.terrain_amplitude_m:g} m (seed {g.terrain_seed})"
        )
        notify(
            f"{info['path']}: {info['rollout_s']:.1f} s of {gait.controller} ({c.gait}) at friction "
            f"{c.friction:g}, slope {c.slope_deg:g}°, payload {c.payload_kg:g} kg{ground}; "
            f"{info['frames']} frames rendered in {info['render_s']:.1f} s ({info['backend']})"
        )
    return infos
