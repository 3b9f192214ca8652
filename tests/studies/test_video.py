"""Videos of the Go1 (cpgjax/studies/video.py): frames at real-time pace, the slope's rotation against gravity, a camera
that follows the robot (a few rendered frames, read back from the MP4), one line where no OpenGL backend works, and
the gait files a study writes."""

import json

import imageio.v3 as iio
import numpy as np
import pytest

from cpgjax import cli
from cpgjax.go1 import attitude
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import terrain as terrains
from cpgjax.sim import walk
from cpgjax.studies import gaits as study_gaits
from cpgjax.studies import video
from cpgjax.study.spec import StudyError
from cpgjax.trial import params as param_space
from cpgjax.trial import tuned
from cpgjax.trial.condition import Condition


def test_frames_play_in_real_time():
    ticks = video.frame_ticks(3000, fps=25)
    assert len(ticks) == 75 and np.all(np.diff(ticks) == 40) and ticks[0] == 0  # 25 frames per 1000 ticks of 1 ms


@pytest.mark.parametrize("slope_deg", [-12.0, 0.0, 10.0, 30.0])
def test_the_slope_rotation_points_gravity_down(slope_deg):
    g = go1_model.gravity_vector(slope_deg)  # the floor frame's gravity
    up = attitude.quat_rotate(go1_model.slope_quaternion(slope_deg), g)
    np.testing.assert_allclose(up, [0.0, 0.0, -np.linalg.norm(g)], atol=1e-12)
    uphill = attitude.quat_rotate(go1_model.slope_quaternion(slope_deg), np.array([1.0, 0.0, 0.0]))
    assert uphill[2] == pytest.approx(np.sin(np.deg2rad(slope_deg)))  # the floor's x climbs at the slope


def _dark_centroid(frame):
    """Centre (row, column) of the dark pixels, as fractions of the frame: the trunk, rotors and feet (the floor and
    the sky are light)."""
    dark = frame.max(axis=2) < 70
    rows, cols = np.nonzero(dark)
    return rows.mean() / frame.shape[0], cols.mean() / frame.shape[1], dark.mean()


def test_the_camera_follows_the_robot(tmp_path):
    stand = go1_model.standing_qpos(go1_model.load_visual_model())
    far = stand.copy()
    far[go1_model.indices().root_qpos] += 3.0  # 3 m further along x
    qpos = np.concatenate([np.tile(stand, (40, 1)), np.tile(far, (40, 1))])  # two frames at 25 fps
    path = tmp_path / "two.mp4"
    try:
        (info,) = video.render_videos([video.Job(path=path, qpos=qpos)], width=320, height=240)
    except video.RenderUnavailable as err:
        pytest.skip(f"no OpenGL backend: {err}")
    assert info["frames"] == 2 and info["rollout_s"] == pytest.approx(0.08) and not list(tmp_path.glob(".*tmp*"))
    frames = iio.imread(path)
    assert frames.shape == (2, 240, 320, 3)
    for frame in frames:
        row, col, share = _dark_centroid(frame.astype(int))
        assert 0.01 < share < 0.3  # the robot is there, and not all of the picture
        assert abs(row - 0.5) < 0.15 and abs(col - 0.5) < 0.15, (row, col)  # ... in the middle
        assert frame.std() > 20  # not blank
    assert np.abs(frames[0].astype(int) - frames[1].astype(int)).mean() > 2  # the floor moved under it


def test_no_gl_backend_is_one_line_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "glx")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    stand = np.tile(go1_model.standing_qpos(), (80, 1))
    gait = video.Gait(
        group="vmc_tegotae",
        params=param_space.midpoint(),
        controller="vmc_tegotae",
        physics="soft",
        condition=Condition(friction=0.6),
        transition_steps=100,
        steady_steps=200,
    )
    lines = []
    log = type("Log", (), {"qpos": stand})
    assert video.write_videos(tmp_path, [gait, gait._replace(group="other")], [log, log], lines.append) == []
    assert len(lines) == 1 and "\n" not in lines[0]
    assert "'glx' OpenGL backend" in lines[0] and "apt-get install libosmesa6" in lines[0], lines[0]
    assert "Traceback" not in lines[0] and list(tmp_path.iterdir()) == []


def test_gait_files_round_trip_and_refuse_damage(tmp_path):
    condition = Condition(
        friction=0.3,
        slope_deg=5.0,
        payload_kg=7.5,
        target_velocity_mps=0.5,
        gait="bound",
        ground=terrains.Ground("rough", 0.04, 7),
    )
    gait = video.Gait(
        group="friction0.3",
        params=param_space.midpoint(),
        controller="vmc_tegotae",
        physics="paper",
        condition=condition,
        transition_steps=1500,
        steady_steps=3000,
        objective=1.9,
        instance=4,
        trial=11,
    )
    path = video.save_gait(tmp_path, gait, seed=3)
    assert path == tmp_path / "best_params" / "friction0.3.json"
    data = json.loads(path.read_text())
    assert list(data["params"]) == list(param_space.PARAM_NAMES) and data["seed"] == 3
    assert (data["terrain"], data["terrain_amplitude_m"], data["terrain_seed"]) == ("rough", 0.04, 7)
    replayed = tuned.load(path)  # what `cpgjax deploy --params` and `walk --params` read
    assert replayed.tuned_for == dict(
        controller="vmc_tegotae",
        gait="bound",
        physics="paper",
        friction=0.3,
        slope_deg=5.0,
        payload_kg=7.5,
        target_velocity_mps=0.5,
    )
    (back,) = video.load_gaits(tmp_path)
    np.testing.assert_array_equal(back.params, gait.params)
    assert back._replace(params=None) == gait._replace(params=None)
    path.write_text(json.dumps({k: v for k, v in data.items() if k != "steady_steps"}))
    with pytest.raises(StudyError, match="friction0.3.json is not a study's gait file .missing key 'steady_steps'"):
        video.load_gaits(tmp_path)
    data["params"]["sigma_n"] = 9.0
    path.write_text(json.dumps(data))
    with pytest.raises(StudyError, match="sigma_n"):
        video.load_gaits(tmp_path)
    path.write_text("{")
    with pytest.raises(StudyError, match="friction0.3.json: not valid JSON"):
        video.load_gaits(tmp_path)


def test_cli_show_video_films_the_gait_files(tmp_path, capsys):
    gait = video.Gait(
        group="vmc_tegotae",
        params=param_space.midpoint(),
        controller="vmc_tegotae",
        physics="soft",
        condition=Condition(friction=0.6, slope_deg=4.0),
        transition_steps=100,
        steady_steps=200,
    )
    video.save_gait(tmp_path, gait)
    (tmp_path / "best_vmc_tegotae.mp4").write_bytes(b"an older video")
    code = cli.main(["show", str(tmp_path), "--video", "--video-s", "0.08", "--backend", "native", "--no-viewer"])
    err = capsys.readouterr().err
    if "no video: " in err:
        pytest.skip(f"no OpenGL backend: {err.strip()}")
    assert code == 0 and "best_vmc_tegotae.mp4: 0.1 s of vmc_tegotae" in err, err
    assert f"replacing {tmp_path / 'best_vmc_tegotae.mp4'}" in err
    assert len(iio.imread(tmp_path / "best_vmc_tegotae.mp4")) == 2


def test_cli_video_options_are_checked_before_compute(tmp_path, capsys):
    assert cli.main(["show", str(tmp_path), "--video"]) == 2
    assert "has no best_params/<group>.json to film" in capsys.readouterr().err
    assert cli.main(["walk", "--controllers", "vmc,tegotae", "--video", str(tmp_path / "w.mp4")]) == 2
    assert "--controllers has 2 values (give one)" in capsys.readouterr().err
    (tmp_path / "w.mp4").write_bytes(b"keep")
    assert cli.main(["walk", "--controllers", "vmc", "--video", str(tmp_path / "w.mp4")]) == 2
    assert "w.mp4 exists: pass --overwrite" in capsys.readouterr().err
    assert (tmp_path / "w.mp4").read_bytes() == b"keep"
    with pytest.raises(SystemExit):
        cli.main(["walk", "--video-s", "0", "--video", str(tmp_path / "v.mp4")])
    assert "outside the allowed range [0.04, 120]" in capsys.readouterr().err


def test_walk_films_the_feet_it_walked(tmp_path, monkeypatch):
    """`walk --video` films the walk's conditions, the feet's μ of --foot-friction among them (and the profile's own
    feet, −1, without it)."""
    filmed = []
    monkeypatch.setattr(walk, "run_walk", lambda options, progress: None)
    monkeypatch.setattr(
        study_gaits,
        "film",
        lambda path, gait, backend, seconds: (
            filmed.append(gait) or {"rollout_s": seconds, "frames": 1, "render_s": 0.0, "backend": "stand-in"}
        ),
    )
    base = ["walk", "--controllers", "vmc", "--friction", "0.9", "--slope-deg", "5", "--overwrite"]
    assert cli.main([*base, "--foot-friction", "1.2", "--video", str(tmp_path / "a.mp4")]) == 0
    assert cli.main([*base, "--video", str(tmp_path / "b.mp4")]) == 0
    assert [(g.condition.friction, g.condition.slope_deg, g.condition.foot_friction) for g in filmed] == [
        (0.9, 5.0, 1.2),
        (0.9, 5.0, -1.0),
    ]


def test_show_names_a_study_video_and_a_cut_one(tmp_path, capsys):
    gait = video.Gait(
        group="vmc",
        params=param_space.midpoint(),
        controller="vmc",
        physics="soft",
        condition=Condition(friction=0.6),
        transition_steps=100,
        steady_steps=200,
    )
    video.save_gait(tmp_path, gait)
    stand = np.tile(go1_model.standing_qpos(), (80, 1))
    lines = []
    if not video.write_videos(tmp_path, [gait], [type("Log", (), {"qpos": stand})], lines.append):
        pytest.skip(f"no OpenGL backend: {lines}")
    assert cli.main(["show", str(tmp_path), "--no-viewer"]) == 0
    (listed,) = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("  best_vmc.mp4 ")]
    assert "video of the group's best gait" in listed and "[" not in listed
    data = video.video_file(tmp_path, "vmc").read_bytes()
    cut = data[: len(data) // 2] if data.find(b"moov") > len(data) // 2 else data.replace(b"moov", b"free")
    video.video_file(tmp_path, "vmc").write_bytes(cut)
    assert cli.main(["show", str(tmp_path), "--no-viewer"]) == 1
    (listed,) = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("  best_vmc.mp4 ")]
    assert "[best_vmc.mp4: not a complete MP4 video" in listed, listed


def test_a_payload_is_drawn_on_the_trunk(tmp_path):
    """The same standing frame with and without a 15 kg payload: the payload's box (a geom of the scene, not of the
    model) changes the picture around the trunk, in the payload's colour, and nothing away from the robot."""
    stand = np.tile(go1_model.standing_qpos(go1_model.load_visual_model()), (40, 1))
    jobs = [
        video.Job(path=tmp_path / "unladen.mp4", qpos=stand),
        video.Job(path=tmp_path / "laden.mp4", qpos=stand, condition=Condition(payload_kg=15.0)),
    ]
    try:
        unladen, laden = (info["strip"][0].astype(int) for info in video.render_videos(jobs, width=320, height=240))
    except video.RenderUnavailable as err:
        pytest.skip(f"no OpenGL backend: {err}")
    changed = np.abs(laden - unladen).max(axis=2) > 30
    rows, cols = np.nonzero(changed)
    assert changed.mean() > 0.005, changed.mean()  # the box shows
    assert abs(rows.mean() / 240 - 0.5) < 0.15 and abs(cols.mean() / 320 - 0.5) < 0.15  # where the trunk is
    assert not changed[:40].any() and not changed[-20:].any()  # the sky and the floor in front stay as they were
    orange = np.array(go1_model.PAYLOAD_RGBA[:3]) * 255
    hue = laden[changed] / np.maximum(laden[changed].max(axis=1, keepdims=True), 1)
    assert np.median(np.abs(hue - orange / orange.max()).max(axis=1)) < 0.25  # lit, but the payload's colour
