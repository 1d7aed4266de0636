"""Running pebble.py / prefppo.py as a user would, and reading what a run wrote."""

import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONWARNINGS="ignore", OMP_NUM_THREADS="1")


def run_script(script: str, out: Path, *flags: str, timeout: int = 600, env: dict | None = None) -> subprocess.CompletedProcess:
    """The script as a user runs it; `env` adds or overrides environment variables."""
    cmd = [sys.executable, str(ROOT / script), "--output-dir", str(out), *flags]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=ENV | (env or {}), cwd=ROOT)


# Runs each command line of argv (a JSON list) through the script's __main__, as `python SCRIPT ARGS` does,
# and prints (exit code, stdout, stderr) per command line as JSON: the exit code as the interpreter gives it
# (SystemExit's code, 1 and the message or the traceback otherwise)
ONE_INTERPRETER = """
import contextlib, io, json, runpy, sys, traceback
script, argvs = sys.argv[1], json.loads(sys.argv[2])
results = []
for argv in argvs:
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        sys.argv = [script, *argv]
        try:
            runpy.run_path(script, run_name="__main__")
            code = 0
        except SystemExit as end:
            code = 0 if end.code is None else end.code
            if not isinstance(code, int):  # sys.exit("message")
                print(code, file=sys.stderr)
                code = 1
        except BaseException:
            traceback.print_exc()
            code = 1
    results.append([code, stdout.getvalue(), stderr.getvalue()])
print(json.dumps(results))
"""


def run_in_one_interpreter(script: str, runs: list[tuple[Path, list[str]]]) -> list[subprocess.CompletedProcess]:
    """Command lines that must end before any work (a user's mistakes), each `script --output-dir OUT FLAGS`, run
    one after another in one Python process so that torch is imported once, not once per command line."""
    argvs = [["--output-dir", str(out), *flags] for out, flags in runs]
    cmd = [sys.executable, "-c", ONE_INTERPRETER, str(ROOT / script), json.dumps(argvs)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=ENV, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return [subprocess.CompletedProcess(argv, code, stdout, stderr)
            for argv, (code, stdout, stderr) in zip(argvs, json.loads(done.stdout))]


def scalars(out: Path) -> dict[str, list[tuple[int, float]]]:
    """The run's TensorBoard scalars: tag -> [(step, value), ...]."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(out), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def assert_pebble_phases(out: Path, seed_steps: int, first_session: int, total: int, critic_reset_updates: int = 100):
    """What a pebble.py run wrote proves each phase: SAC updates on the kNN reward during pre-training (logged
    losses, the normalised kNN reward positive), then on r_hat (in (-1, 1)); the critic reset once, at the first
    reward update (the critics' Adam counts exactly the updates since then); every stored transition relabelled
    with the final r_hat (pre-training's zeros included)."""
    import torch

    import pebble

    rewards = scalars(out)["losses/batch_reward"]
    pretraining = [value for step, value in rewards if seed_steps < step < first_session]
    learned = [value for step, value in rewards if step > first_session]
    assert pretraining and all(value > 0 for value in pretraining), rewards
    assert learned and all(-1 < value < 1 for value in learned), rewards
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert state["progress"]["global_step"] == total
    adam_steps = {int(s["step"]) for s in state["critic_optimizer"]["state"].values()}
    assert adam_steps == {total - first_session + 1 + critic_reset_updates}
    buffer = state["buffer"]
    members = len({key.split(".")[1] for key in state["reward_model"] if key.startswith("members.")})
    reward_model = pebble.RewardEnsemble(buffer["obs"].shape[1], buffer["actions"].shape[1], members)
    reward_model.load_state_dict(state["reward_model"])
    with torch.no_grad():
        r_hat = reward_model(torch.cat([buffer["obs"], buffer["actions"]], -1)).mean(0)
    torch.testing.assert_close(buffer["rewards"], r_hat)
    return state


def session_lines(stdout: str) -> list[str]:
    return re.findall(r"feedback session \d+:.*", stdout)


def eval_rows(out: Path) -> list[dict]:
    with open(out / "eval.csv") as f:
        return list(csv.DictReader(f))


def saved_labels(out: Path) -> list[dict]:
    return [dict(np.load(path)) for path in sorted((out / "labels").glob("session_*.npz"))]


def eval_curve(out: Path) -> list[list[str]]:
    """The columns of eval.csv that must not depend on timing."""
    return [[row[c] for c in ("step", "episode_return", "feedback", "reward_correlation")] for row in eval_rows(out)]


def assert_rejected(result, message: str, out: Path):
    """A user's mistake: non-zero exit, one 'error: ...' line that names it, no traceback, nothing written."""
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], result.stderr
    assert not out.exists()


def assert_refused_by_tyro(result, message: str, out: Path):
    """A flag tyro cannot parse: tyro's own error box (exit code 2) that says it, no traceback, nothing written."""
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    text = " ".join(re.sub("[│╭╰╮╯─]", " ", result.stderr).split())  # the box's text, unwrapped
    assert message in text, result.stderr
    assert not out.exists()


def start_script(script: str, out: Path, *flags: str, **popen_kwargs) -> subprocess.Popen:
    """A run in the background, to be killed or signalled."""
    cmd = [sys.executable, str(ROOT / script), "--output-dir", str(out), *flags]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT, **popen_kwargs)


def wait_for(path: Path, process: subprocess.Popen, timeout: float = 300):
    """Poll until `path` exists (the run reached a point); fails if the run ends first."""
    import time

    deadline = time.time() + timeout
    while not path.exists():
        assert process.poll() is None, f"the run ended before writing {path}: {process.communicate()}"
        assert time.time() < deadline, f"{path} not written within {timeout} s"
        time.sleep(0.02)


def assert_inputs_standardised_by_labelled_states(out: Path, obs_dim: int):
    """The final reward model of the finished run in `out` standardises observations by the mean and std of every
    state of the kept labelled segments (D after the last session), clips at 10, and leaves actions as they are."""
    import torch

    labels = saved_labels(out)
    states = np.concatenate([s[f"obs{side}"][s["keep"]] for s in labels for side in (0, 1)]).reshape(-1, obs_dim)
    saved = torch.load(out / "final_model.pt", weights_only=True)["reward_model"]
    np.testing.assert_allclose(saved["input_mean"][:obs_dim].numpy(), states.mean(0), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(saved["input_std"][:obs_dim].numpy(), states.std(0), rtol=1e-4, atol=1e-5)
    assert not saved["input_mean"][obs_dim:].any() and (saved["input_std"][obs_dim:] == 1).all()
    assert saved["input_clip"].item() == 10.0
