"""Long runs survive crashes and kills, in pebble.py, rime.py and prefppo.py: checkpoints, --resume after SIGKILL
and SIGTERM (compared with the uninterrupted run of the same seed), atomic checkpoint writes, --labels-from,
non-finite stops and output-directory failures."""

import errno
import io
import json
import re
import resource
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch

import pebble
import sim_teacher
from tests.helpers import ROOT, ENV, eval_curve, eval_rows, run_cli, run_in_one_interpreter, run_script, saved_labels, start_script, wait_for

# Tiny walker-walk runs. pebble: random steps to 700 (500 fewer SAC updates than from 200: the suite's time), then
# pre-training to 1000; sessions at 1001 (after the first episode: segments come from complete ones), 1101 and 1201, a
# checkpoint at 1050 (mid-episode), a teacher that draws its answers (myopic, beta 1, mistakes: a resumed or repeated
# run must draw the same); prefppo: sessions at 2000, 3000, 4000, checkpoints after the rollouts ending at 2000 and 4000
RUNS = {
    "pebble.py": ["--env-id", "walker-walk", "--total-timesteps", "1300", "--seed-steps", "700", "--unsup-steps", "300",
                  "--feedback-every", "100", "--max-feedback", "30", "--feedback-per-session", "10", "--segment-len", "10",
                  "--eval-every", "650", "--checkpoint-every", "1050", "--hidden-dim", "32", "--num-layers", "2",
                  "--batch-size", "32", "--reward-epochs", "3", "--reward-batch-size", "32", "--eval-episodes", "1",
                  "--teacher", "myopic", "--teacher-beta", "1", "--teacher-eps-mistake", "0.1"],
    "prefppo.py": ["--env-id", "walker-walk", "--total-timesteps", "5000", "--unsup-steps", "1000", "--num-envs", "2",
                   "--num-steps", "250", "--minibatch-size", "250", "--feedback-every", "1000", "--max-feedback", "40",
                   "--feedback-per-session", "10", "--segment-len", "10", "--eval-every", "1000", "--checkpoint-every",
                   "2000", "--hidden-dim", "32", "--num-layers", "2", "--reward-epochs", "3", "--reward-batch-size", "32",
                   "--eval-episodes", "1", "--update-epochs", "2", "--unsup-update-epochs", "2"],
}
SCRIPTS = list(RUNS)
# pebble.py's loop and plumbing with RIME's parts (one warm-start update a pre-training step, not 5: cheaper)
RUNS["rime.py"] = RUNS["pebble.py"] + ["--rime-warm-updates", "1"]
WITH_RIME = SCRIPTS + ["rime.py"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The reference: each tiny run once, from start to end. pebble.py's is run in a new interpreter (env), the others
    are forked from a server that has torch and the environments imported (tests/helpers.py ForkedRun), as the
    resumed runs are: pebble.py's resumed runs must equal it, so what a run writes does not depend on how it began."""
    runs = {}
    for script, flags in RUNS.items():
        out = tmp_path_factory.mktemp("uninterrupted") / script
        env = {"OMP_NUM_THREADS": "1"} if script == "pebble.py" else None  # env: a new interpreter
        result = run_script(script, out, *flags, env=env)
        assert result.returncode == 0, result.stderr[-3000:]
        runs[script] = out
    return runs


def assert_same_run(resumed, reference):
    """Equal evaluations (same steps, returns, labels, reward correlation), one row per step, same labels."""
    steps = [row["step"] for row in eval_rows(resumed)]
    assert len(steps) == len(set(steps))
    np.testing.assert_allclose(np.array(eval_curve(resumed), float), np.array(eval_curve(reference), float), rtol=1e-6)
    resumed_labels, reference_labels = saved_labels(resumed), saved_labels(reference)
    assert len(resumed_labels) == len(reference_labels)
    for a, b in zip(resumed_labels, reference_labels):
        np.testing.assert_array_equal(a["y"], b["y"])
        np.testing.assert_allclose(a["obs0"], b["obs0"], rtol=1e-6)


@pytest.mark.parametrize("script", WITH_RIME)
def test_sigterm_then_sigkill_and_resumes_equal_the_uninterrupted_run(script, tmp_path, uninterrupted):
    out = tmp_path / "run"
    # SIGTERM (a batch system's time limit) after the first session, without periodic checkpoints: it saves one
    process = start_script(script, out, *RUNS[script], "--checkpoint-every", "0")
    wait_for(out / "labels" / "session_0000.npz", process)
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    assert "SIGTERM: checkpoint saved at step" in stdout and "Traceback" not in stderr
    assert torch.load(out / "checkpoint.pt", weights_only=True)["progress"]["sessions_done"] >= 1

    # resumed, with the periodic checkpoints again; SIGKILL after the next session, which follows a checkpoint
    every = RUNS[script][RUNS[script].index("--checkpoint-every") + 1]
    process = start_script(script, out, "--resume", str(out), "--checkpoint-every", every)
    wait_for(out / "labels" / "session_0001.npz", process)
    process.send_signal(signal.SIGKILL)
    process.communicate()
    written_before_kill = len(eval_rows(out))

    result = run_script(script, out, "--resume", str(out))
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("resuming from the checkpoint at step") == 1
    assert len(eval_rows(out)) >= written_before_kill
    assert_same_run(out, uninterrupted[script])  # --checkpoint-every changes nothing in the experiment
    # the session asked after the checkpoint was asked again; its first answer is kept aside, not lost
    assert list((out / "labels").glob("before_resume_at_step_*/session_0001.npz"))


def test_a_kill_while_writing_a_checkpoint_leaves_the_previous_one_loadable(tmp_path):
    module = sim_teacher  # save_file: every file a run writes
    path = tmp_path / "checkpoint.pt"
    data = io.BytesIO()
    torch.save({"step": 1, "weights": torch.ones(10)}, data)
    module.save_file(str(path), data.getvalue())
    # a second write killed half-way (SIGKILL after some bytes are out)
    code = (f"import os, signal, torch, {module.__name__} as m\n"
            "real_open = open\n"
            "class HalfWritten:\n"  # the temporary file: some bytes reach the disk, then SIGKILL
            "    def __init__(self, path, mode): self.f = real_open(path, mode)\n"
            "    def __enter__(self): return self\n"
            "    def __exit__(self, *a): pass\n"
            "    def write(self, data): self.f.write(bytes(data)[:1000]); self.f.flush(); os.kill(os.getpid(), signal.SIGKILL)\n"
            "m.open = HalfWritten\n"
            f"m.save_file({str(path)!r}, bytes(5000))\n")
    killed = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=ENV, capture_output=True)
    assert killed.returncode == -signal.SIGKILL
    assert torch.load(path, weights_only=True)["step"] == 1


@pytest.mark.parametrize("script", WITH_RIME)
def test_a_checkpoint_of_another_version_is_refused_in_one_line(script, tmp_path, uninterrupted):
    """A checkpoint whose parts this script's version does not read (here the replay buffer's as the scripts wrote it
    before they kept its filled part only; PrefPPO: a renamed part) ends the resume with one line, exit code 2."""
    run = tmp_path / "run"
    shutil.copytree(uninterrupted[script], run)
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    if script == "prefppo.py":
        state["old_name"] = state.pop("optimizer")
    else:
        state["buffer"].pop("size")
    torch.save(state, run / "checkpoint.pt")
    result = run_cli(script, "--resume", str(run))
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr[-2000:]
    assert result.stderr.startswith("error: the checkpoint does not fit this script (written by another version?)")


@pytest.mark.parametrize("env_id", ["walker-walk", "button-press", "tests.toy_envs:ConstantPenalty-v0"])
def test_seeded_reset_and_replayed_actions_put_the_env_back_exactly(env_id):
    """pebble's resume: a fresh env, reset with the current episode's seed and given the episode's actions so far,
    continues exactly as the env that lived through earlier episodes (MuJoCo is deterministic)."""
    rng = np.random.default_rng(0)
    env, episode_len = pebble.make_env(env_id)
    env.reset(seed=pebble.episode_seed(1, 0, 0))
    for _ in range(episode_len):  # a whole earlier episode: the living env has history the fresh one lacks
        env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
    env.reset(seed=pebble.episode_seed(1, 0, 1))
    actions = rng.uniform(-1, 1, (episode_len, *env.action_space.shape)).astype(np.float32)
    for action in actions[:7]:
        env.step(action)
    replayed, _ = pebble.make_env(env_id)
    replayed.reset(seed=pebble.episode_seed(1, 0, 1))
    for action in actions[:7]:
        replayed.step(action)
    for action in actions[7:]:  # the rest of this episode
        step, replayed_step = env.step(action), replayed.step(action)
        np.testing.assert_array_equal(step[0], replayed_step[0])
        assert step[1:4] == replayed_step[1:4]
    other, _ = pebble.make_env(env_id)  # and the seed matters: another episode's seed starts elsewhere
    assert not np.array_equal(other.reset(seed=pebble.episode_seed(1, 0, 2))[0], replayed.reset(
        seed=pebble.episode_seed(1, 0, 1))[0])


@pytest.mark.parametrize("script", WITH_RIME)
def test_labels_from_an_earlier_run_join_the_preference_dataset(script, tmp_path, uninterrupted):
    flags = [f for f in RUNS[script]]
    flags[flags.index("--max-feedback") + 1] = "10"
    flags[flags.index("--total-timesteps") + 1] = "3000" if script == "prefppo.py" else "1100"
    result = run_script(script, tmp_path / "run", *flags, "--labels-from", str(uninterrupted[script]))
    assert result.returncode == 0, result.stderr[-3000:]
    imported = sum(int(session["keep"].sum()) for session in saved_labels(uninterrupted[script]))
    assert f"reward model trained on {imported + 10} labels" in result.stdout  # + the 10 of this run's session
    assert result.stdout.splitlines()[-1].startswith("done: 1 feedback sessions")
    assert len(saved_labels(tmp_path / "run")) == 1  # only this run's own session is saved as its labels


@pytest.mark.parametrize("script", SCRIPTS)
def test_labels_from_with_another_segment_length_is_refused(script, tmp_path, uninterrupted):
    flags = [f for f in RUNS[script]]
    flags[flags.index("--segment-len") + 1] = "20"
    result = run_script(script, tmp_path / "run", *flags, "--labels-from", str(uninterrupted[script]))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.startswith("error: --labels-from") and "do not fit this run" in result.stderr
    assert not (tmp_path / "run").exists()


TOY = ["--seed-steps", "100", "--unsup-steps", "100", "--total-timesteps", "600", "--ground-truth-reward",
       "--hidden-dim", "16", "--num-layers", "1", "--batch-size", "16", "--eval-every", "200", "--eval-episodes", "1",
       "--segment-len", "10"]
TOY_PPO = ["--unsup-steps", "80", "--total-timesteps", "640", "--num-envs", "2", "--num-steps", "40", "--minibatch-size",
           "40", "--ground-truth-reward", "--hidden-dim", "16", "--num-layers", "1", "--eval-every", "200",
           "--eval-episodes", "1", "--segment-len", "10", "--update-epochs", "1", "--unsup-update-epochs", "1"]


def test_a_diverging_loss_stops_the_run_before_the_next_checkpoint(tmp_path):
    # SAC learns from the true reward 1e30 from step 201 (after pre-training): the critic loss overflows. The losses
    # are checked where they reach the host and before each checkpoint (here every 100 steps), not at every step: the
    # run stops at 300, and the checkpoint of step 200 stays the last one, with finite networks
    out = tmp_path / "run"
    result = run_script("pebble.py", out, "--env-id", "tests.toy_envs:HugeReward-v0", *TOY, "--checkpoint-every",
                        "100")
    assert result.returncode == 3 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and re.match(r"error: non-finite critic_loss.* at step 300;", lines[0]), lines
    assert f"its last checkpoint in {out} is intact" in lines[0]
    good = torch.load(out / "checkpoint.pt", weights_only=True)
    assert good["progress"]["global_step"] == 200
    for name in ("actor", "critic"):
        assert all(torch.isfinite(t).all() for t in good[name].values())


@pytest.mark.parametrize("script, flags", [("pebble.py", TOY)])
def test_a_nan_from_the_environment_stops_the_run(script, flags, tmp_path):
    result = run_script(script, tmp_path / "run", "--env-id", "tests.toy_envs:NaNReward-v0", *flags)
    assert result.returncode == 3 and "Traceback" not in result.stderr
    assert "error: non-finite reward or observation from the environment at step" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def prefppo_stopped_by(env_id: str, checkpoint_every: int, out) -> subprocess.CompletedProcess:
    result = run_script("prefppo.py", out, "--env-id", env_id, *TOY_PPO, "--checkpoint-every", str(checkpoint_every))
    assert result.returncode == 3 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert f"its last checkpoint in {out} is intact" in result.stderr
    return result


def test_prefppo_diverging_loss_keeps_the_last_good_checkpoint(tmp_path):
    # rollouts of 80 steps: checkpoint after the first (pre-training); the update after the second, on the true
    # reward 1e30, overflows the value loss
    out = tmp_path / "run"
    result = prefppo_stopped_by("tests.toy_envs:HugeReward-v0", 80, out)
    assert re.match(r"error: non-finite .*(policy|value)_loss.* at step 160;", result.stderr), result.stderr
    good = torch.load(out / "checkpoint.pt", weights_only=True)
    assert good["progress"]["global_step"] == 80  # untouched, and finite: checked before it was saved
    for name in ("actor", "critic"):
        assert all(torch.isfinite(t).all() for t in good[name].values())


def test_prefppo_nan_mid_rollout_keeps_the_last_good_checkpoint(tmp_path):
    # a NaN in an episode that its seed decides (seed 1: in the rollout from step 320, the 5th of 80 steps), after
    # the checkpoint at 240; the envs have moved past 240, so checkpoint.pt must stay the one of step 240
    out = tmp_path / "run"
    result = prefppo_stopped_by("tests.toy_envs:NaNSeededEpisode-v0", 240, out)
    assert result.stderr.startswith("error: non-finite reward or observation from the environment at step 320;")
    assert torch.load(out / "checkpoint.pt", weights_only=True)["progress"]["global_step"] == 240
    # the last good checkpoint resumes: the envs replay their episodes and meet the NaN at the same step again
    resumed = run_script("prefppo.py", out, "--resume", str(out))
    assert resumed.returncode == 3 and "resuming from the checkpoint at step 240" in resumed.stdout
    assert "observation from the environment at step 320;" in resumed.stderr


@pytest.mark.parametrize("script", SCRIPTS)
def test_output_directory_failures_are_one_line_and_destroy_nothing(script, tmp_path, uninterrupted):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    existing = uninterrupted[script]
    stopped = tmp_path / "stopped"  # a run stopped before its first checkpoint
    stopped.mkdir()
    (stopped / "config.json").write_text((existing / "config.json").read_text())
    older = tmp_path / "older"  # a run of an older version, without a field it has now
    older.mkdir()
    (older / "checkpoint.pt").write_bytes(b"")
    config = json.loads((existing / "config.json").read_text())
    del config["total_timesteps"]
    (older / "config.json").write_text(json.dumps(config))
    lacking = tmp_path / "lacking"  # an older run without a flag that may change on resume (--compile's way in)
    shutil.copytree(existing, lacking)
    config = json.loads((existing / "config.json").read_text())
    del config["capture_video"]
    (lacking / "config.json").write_text(json.dumps(config))
    damaged = tmp_path / "damaged"  # a checkpoint copied only in part (torch.load would raise RuntimeError)
    shutil.copytree(existing, damaged)
    half = (existing / "checkpoint.pt").read_bytes()[:100_000]
    (damaged / "checkpoint.pt").write_bytes(half)
    before = {p: p.stat().st_mtime_ns for p in existing.rglob("*")}
    into_file, into_run, new_seed, no_config, no_checkpoint, other_version, lacking_flag, unreadable = \
        run_in_one_interpreter(script, [
            (blocker / "run", RUNS[script]), (existing, RUNS[script]),
            (tmp_path / "x", ["--resume", str(existing), "--seed", "7"]), (tmp_path / "x", ["--resume", str(tmp_path)]),
            (tmp_path / "x", ["--resume", str(stopped)]), (tmp_path / "x", ["--resume", str(older)]),
            (tmp_path / "x", ["--resume", str(lacking)]), (tmp_path / "x", ["--resume", str(damaged)])])

    assert into_file.returncode == 2 and into_file.stderr.startswith("error: [Errno 20] Not a directory")
    assert len(into_file.stderr.strip().splitlines()) == 1 and "Traceback" not in into_file.stderr
    assert into_run.returncode == 2 and "already holds a run" in into_run.stderr
    assert {p: p.stat().st_mtime_ns for p in existing.rglob("*")} == before
    assert new_seed.returncode == 2 and "error: --seed cannot change when resuming" in new_seed.stderr
    assert no_config.returncode == 2 and "its config.json cannot be read ([Errno 2]" in no_config.stderr
    assert no_checkpoint.returncode == 2 and "no checkpoint.pt there" in no_checkpoint.stderr
    assert other_version.returncode == 2 and "Traceback" not in other_version.stderr
    assert "its config.json is of another version of this script" in other_version.stderr
    assert lacking_flag.returncode == 2 and "has already finished" in lacking_flag.stderr  # accepted, then finished
    assert unreadable.returncode == 2 and len(unreadable.stderr.strip().splitlines()) == 1, unreadable.stderr[-3000:]
    assert unreadable.stderr.startswith(f"error: {damaged / 'checkpoint.pt'} cannot be read (RuntimeError)")
    assert (damaged / "checkpoint.pt").read_bytes() == half


def limit_file_size():
    """A full disk, as seen by the writer: writes past 1 MiB fail with EFBIG (SIGXFSZ ignored)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (2**20, 2**20))


# the first evaluation, then the first checkpoint (over 1 MiB: the reward model) at the same step
FIRST_CHECKPOINT = {"pebble.py": ["--eval-every", "200", "--checkpoint-every", "200"],
                    "prefppo.py": ["--eval-every", "1000", "--checkpoint-every", "1000"]}


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_full_disk_ends_with_one_line_and_no_partial_checkpoint(script, tmp_path):
    out = tmp_path / "run"
    process = start_script(script, out, *RUNS[script], *FIRST_CHECKPOINT[script], before=limit_file_size)
    stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 4 and "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "File too large" in lines[0] and f"its last checkpoint in {out} is intact" in lines[0]
    assert not (out / "checkpoint.pt").exists() and not (out / "checkpoint.pt.tmp").exists()
    assert eval_rows(out)  # what was written before is there


def refuse_final_model():
    """A full disk when the run writes final_model.pt, and only then (save_file: every file a run writes)."""
    sys.path.insert(0, str(ROOT))
    import sim_teacher as module
    write = module.save_file

    def save_file(path, data):
        if path.endswith("final_model.pt"):
            raise OSError(errno.ENOSPC, "No space left on device", path)
        write(path, data)

    module.save_file = save_file


@pytest.mark.parametrize("script", WITH_RIME)
def test_a_failed_final_model_write_is_one_line_and_resume_finishes_the_run(script, tmp_path, uninterrupted):
    """final_model.pt is written whole, before the last checkpoint: if it fails, the last checkpoint is an earlier
    one, which --resume continues to the same end (the grid would have called a half-written file finished)."""
    out = tmp_path / "run"
    total = int(RUNS[script][RUNS[script].index("--total-timesteps") + 1])
    process = start_script(script, out, *RUNS[script], before=refuse_final_model)
    stdout, stderr = process.communicate(timeout=300)
    lines = stderr.strip().splitlines()
    assert process.returncode == 4 and "Traceback" not in stderr, stderr[-3000:]
    assert len(lines) == 1 and "No space left on device" in lines[0] and f"at step {total};" in lines[0], lines
    assert not (out / "final_model.pt").exists() and not (out / "final_model.pt.tmp").exists()
    assert torch.load(out / "checkpoint.pt", weights_only=True)["progress"]["global_step"] < total

    result = run_script(script, out, "--resume", str(out))
    assert result.returncode == 0, result.stderr[-3000:]
    assert_same_run(out, uninterrupted[script])
    final, reference = (torch.load(run / "final_model.pt", weights_only=True) for run in (out, uninterrupted[script]))
    torch.testing.assert_close(final, reference)


BEFORE = "0cfa25a"  # the scripts before the progress line, the checkpoints and the main loop's calls were reworked


@pytest.mark.parametrize("script", WITH_RIME)
def test_fixed_seed_runs_write_what_the_scripts_wrote_before_the_rework(script, tmp_path, uninterrupted):
    """The rework changed no result: each tiny run writes the eval.csv (all but its wall times) and the label files
    of the same run of the scripts at BEFORE (with their sim_teacher.py and samplers.py), value for value."""
    old = tmp_path / "old"
    old.mkdir()
    files = [script, "sim_teacher.py", "samplers.py"]
    archive = subprocess.run(["git", "archive", BEFORE, *files], cwd=ROOT, capture_output=True)
    if archive.returncode:
        pytest.skip(f"no git history with {BEFORE} here")
    subprocess.run(["tar", "-x", "-C", str(old)], input=archive.stdout, check=True)
    result = run_script(str(old / script), old / "run", *RUNS[script])
    assert result.returncode == 0, result.stderr[-3000:]
    new_rows, old_rows = eval_rows(uninterrupted[script]), eval_rows(old / "run")
    assert len(new_rows) == len(old_rows) > 0
    for new, before in zip(new_rows, old_rows):
        assert {k: v for k, v in new.items() if k != "wall_time"} == {k: v for k, v in before.items()
                                                                       if k != "wall_time"}
    new_labels, old_labels = saved_labels(uninterrupted[script]), saved_labels(old / "run")
    assert len(new_labels) == len(old_labels) == 3
    for new, before in zip(new_labels, old_labels):
        assert new.keys() == before.keys()
        for key in new:
            np.testing.assert_array_equal(new[key], before[key], err_msg=key)
