"""--capture-video: a clear error without a renderer, and one video per evaluation that leaves the
evaluation itself unchanged."""

import json
import subprocess
import sys
from dataclasses import asdict

import imageio_ffmpeg
import pytest

import pebble
import prefppo
from tests.helpers import ENV, assert_rejected, eval_curve, eval_rows, run_script

NO_DISPLAY = {"MUJOCO_GL": "glfw", "DISPLAY": "", "WAYLAND_DISPLAY": ""}
PEBBLE_TINY = ["--env-id", "Reacher-v5", "--total-timesteps", "400", "--seed-steps", "100", "--unsup-steps", "100",
               "--feedback-every", "100", "--max-feedback", "20", "--feedback-per-session", "10", "--segment-len", "10",
               "--eval-every", "400", "--hidden-dim", "32", "--num-layers", "2", "--batch-size", "32",
               "--reward-epochs", "3", "--reward-batch-size", "32", "--eval-episodes", "1"]
PREFPPO_TINY = ["--env-id", "InvertedPendulum-v5", "--ground-truth-reward", "--total-timesteps", "1000", "--unsup-steps", "500",
                "--num-envs", "2", "--num-steps", "250", "--minibatch-size", "125", "--eval-every", "1000",
                "--hidden-dim", "32", "--num-layers", "2", "--eval-episodes", "1", "--update-epochs", "2",
                "--unsup-update-epochs", "2"]


def egl_renders() -> bool:
    probe = "import mujoco; mujoco.Renderer(mujoco.MjModel.from_xml_string('<mujoco/>'), 8, 8).render()"
    return subprocess.run([sys.executable, "-c", probe], env=ENV | {"MUJOCO_GL": "egl"}, capture_output=True).returncode == 0


needs_egl = pytest.mark.skipif(not egl_renders(), reason="no EGL renderer (libEGL) on this machine")


def video_frames(path) -> int:
    return imageio_ffmpeg.count_frames_and_secs(str(path))[0]


@pytest.mark.parametrize("script", ["pebble.py", "prefppo.py"])
def test_capture_video_without_a_renderer_is_a_one_line_error(tmp_path, script):
    out = tmp_path / "run"
    result = run_script(script, out, "--capture-video", timeout=120, env=NO_DISPLAY)
    assert_rejected(result, "--capture-video cannot render", out)
    assert result.returncode == 2


@needs_egl
def test_pebble_records_a_video_and_evaluates_as_without(tmp_path):
    with_video, without = tmp_path / "video", tmp_path / "plain"
    result = run_script("pebble.py", with_video, *PEBBLE_TINY, "--capture-video", env={"MUJOCO_GL": "egl"})
    assert result.returncode == 0, result.stderr[-2000:]
    assert run_script("pebble.py", without, *PEBBLE_TINY).returncode == 0
    assert [row["step"] for row in eval_rows(with_video)] == ["400"]
    # RecordVideo on the evaluation env: the first evaluation episode, named by the step and the env's episode number
    assert [p.name for p in (with_video / "videos").iterdir()] == ["step_400-episode-0.mp4"]
    assert video_frames(with_video / "videos" / "step_400-episode-0.mp4") == 51  # the reset frame + 50 steps
    assert eval_curve(with_video) == eval_curve(without)  # rendering does not move the simulation


@needs_egl
def test_prefppo_records_a_video_of_an_episode_that_terminates(tmp_path):
    out = tmp_path / "video"
    result = run_script("prefppo.py", out, *PREFPPO_TINY, "--capture-video", env={"MUJOCO_GL": "egl"})
    assert result.returncode == 0, result.stderr[-2000:]
    assert [row["step"] for row in eval_rows(out)] == ["1000"]
    assert [p.name for p in (out / "videos").iterdir()] == ["step_1000-episode-0.mp4"]  # RecordVideo's name
    # the pole falls early: the file is still written, at the evaluation's end
    assert 1 <= video_frames(out / "videos" / "step_1000-episode-0.mp4") <= 1001
    without = tmp_path / "plain"
    assert run_script("prefppo.py", without, *PREFPPO_TINY).returncode == 0
    assert eval_curve(out) == eval_curve(without)  # rendering does not move the simulation


@needs_egl
@pytest.mark.parametrize("env_id", ["walker-walk", "button-press"])
def test_make_env_renders_rgb_frames(env_id):
    """RecordVideo records whatever render() returns: DMC through dm_control, Meta-World through Gymnasium."""
    code = (f"import pebble; env, _ = pebble.make_env({env_id!r}, render_mode='rgb_array'); env.reset(seed=0); "
            "frame = env.render(); print(frame.shape, frame.dtype, int(frame.std() > 0))")
    probe = subprocess.run([sys.executable, "-c", code], env=ENV | {"MUJOCO_GL": "egl"}, capture_output=True, text=True)
    height, width = (240, 320) if env_id == "walker-walk" else (480, 480)
    assert probe.stdout.strip() == f"({height}, {width}, 3) uint8 1", probe.stderr[-2000:]


@pytest.mark.parametrize("script", [pebble, prefppo])
def test_capture_video_may_be_switched_on_when_resuming(tmp_path, script, monkeypatch, capsys):
    """Rendering the evaluation's first episode does not change the experiment: videos may be switched on."""
    saved = asdict(script.task_defaults("walker-walk", "oracle")) | {"output_dir": str(tmp_path)}
    (tmp_path / "config.json").write_text(json.dumps(saved))
    monkeypatch.setattr(sys, "argv", ["script", "--resume", str(tmp_path), "--capture-video"])
    resumed = script.parse_args()
    assert asdict(resumed) == saved | {"capture_video": True, "resume": str(tmp_path)}
    monkeypatch.setattr(sys, "argv", ["script", "--resume", str(tmp_path), "--seed", "2"])
    with pytest.raises(SystemExit):
        script.parse_args()
    assert "error: --seed cannot change when resuming" in capsys.readouterr().err
