"""Running pebble.py / prefppo.py as a user would, and reading what a run wrote."""

import atexit
import contextlib
import csv
import io
import json
import multiprocessing
import multiprocessing.forkserver
import os
import re
import runpy
import signal
import subprocess
import sys
import tempfile
import traceback
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONWARNINGS="ignore", OMP_NUM_THREADS="1")


def run_script(script: str, out: Path, *flags: str, timeout: int = 600, env: dict | None = None) -> subprocess.CompletedProcess:
    """The script as a user runs it (forked, ForkedRun); `env` adds or overrides environment variables (then a new
    interpreter: they are read when it starts)."""
    return run_cli(script, "--output-dir", str(out), *flags, timeout=timeout, env=env)


def run_cli(script: str, *args: str, timeout: int = 600, env: dict | None = None) -> subprocess.CompletedProcess:
    """`python SCRIPT ARGS` (a path relative to the repository), forked as run_script's runs are."""
    cmd = [sys.executable, str(ROOT / script), *args]
    if env:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=ENV | env, cwd=ROOT)
    process = ForkedRun(cmd)
    try:
        stdout, stderr = process.communicate(timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        raise
    return subprocess.CompletedProcess(cmd, process.returncode, stdout, stderr)


# Each script run in a new interpreter pays about 4 s of imports (torch, then torch._dynamo when Adam is built) before
# its first step, most of the suite's time. A fork server per pytest worker, started once with ENV, has them imported;
# each run is a child forked from it: its own process, running the script as `python SCRIPT FLAGS` does
PRELOAD = ["torch", "torch._dynamo", "torch.utils.tensorboard", "gymnasium", "tyro", "dm_control.suite", "metaworld"]
FORK_SERVER = multiprocessing.get_context("forkserver")
FORK_SERVER.set_forkserver_preload(PRELOAD)


def forked(target, *args) -> multiprocessing.Process:
    """target(*args), started in a child of the fork server (which starts once, with the scripts' environment)."""
    with mock.patch.dict(os.environ, ENV):
        multiprocessing.forkserver.ensure_running()
    process = FORK_SERVER.Process(target=target, args=args)
    process.start()
    return process


def run_as_main(cmd: list[str], stdout: str, stderr: str, before=None):
    """In the forked child: before() if given (as Popen's preexec_fn), then `python SCRIPT FLAGS` (cmd), its output
    to the two files, its exit code as the interpreter's (SystemExit's code; 1 and the traceback for an exception)."""
    if before:
        before()
    for fd, path in ((1, stdout), (2, stderr)):
        os.dup2(os.open(path, os.O_WRONLY), fd)
    os.chdir(ROOT)
    sys.argv = cmd[1:]
    sys.path.insert(0, str(Path(cmd[1]).parent))
    try:
        runpy.run_path(cmd[1], run_name="__main__")
    except Exception:
        traceback.print_exc()
        sys.exit(1)
    finally:
        atexit._run_exitfuncs()


class ForkedRun:
    """`subprocess.Popen(cmd, stdout=PIPE, stderr=PIPE, text=True, env=ENV, cwd=ROOT)` as the tests use it (pid, poll,
    send_signal, kill, wait, communicate, returncode), for a script forked from the fork server."""

    def __init__(self, cmd: list[str], before=None):
        self.args = cmd
        self.files = [tempfile.mkstemp(prefix="run_")[1] for _ in ("stdout", "stderr")]
        self.process = forked(run_as_main, cmd, *self.files, before)
        self.pid = self.process.pid
        self.returncode = None

    def poll(self) -> int | None:
        self.returncode = self.process.exitcode
        return self.returncode

    def send_signal(self, signum: int):
        if self.poll() is None:  # as Popen: nothing to signal once it has ended (the server reaps it)
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signum)

    def kill(self):
        self.send_signal(signal.SIGKILL)

    def wait(self, timeout: float | None = None) -> int:
        self.process.join(timeout)
        if self.poll() is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        return self.returncode

    def communicate(self, timeout: float | None = None) -> tuple[str, str]:
        self.wait(timeout)
        output = [Path(path).read_text() for path in self.files]
        for path in self.files:
            os.remove(path)
        return output[0], output[1]


def run_each(script: str, argvs: list[list[str]], results: str):
    """In the forked child: each command line of argvs through the script's __main__, one after another, as
    `python SCRIPT ARGS` runs it; (exit code, stdout, stderr) of each to the file results as JSON, the exit code as
    the interpreter gives it (SystemExit's code; 1 and the message or the traceback otherwise)."""
    os.chdir(ROOT)
    sys.path.insert(0, str(Path(script).parent))
    outcomes = []
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
        outcomes.append([code, stdout.getvalue(), stderr.getvalue()])
    atexit._run_exitfuncs()  # as the interpreter would at its end
    Path(results).write_text(json.dumps(outcomes))


def run_in_one_interpreter(script: str, runs: list[tuple[Path, list[str]]]) -> list[subprocess.CompletedProcess]:
    """Command lines that must end before any work (a user's mistakes), each `script --output-dir OUT FLAGS`, run
    one after another in one process forked from the fork server (torch imported once, not once per command line)."""
    argvs = [["--output-dir", str(out), *flags] for out, flags in runs]
    results = tempfile.mkstemp(prefix="runs_")[1]
    process = forked(run_each, str(ROOT / script), argvs, results)
    process.join(600)
    assert process.exitcode == 0, f"the forked runs ended with {process.exitcode}"
    outcomes = json.loads(Path(results).read_text())
    os.remove(results)
    return [subprocess.CompletedProcess(argv, code, stdout, stderr)
            for argv, (code, stdout, stderr) in zip(argvs, outcomes)]


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


def start_script(script: str, out: Path, *flags: str, before=None) -> ForkedRun:
    """A run in the background, to be killed or signalled; before() runs first in its process (Popen's
    preexec_fn)."""
    return ForkedRun([sys.executable, str(ROOT / script), "--output-dir", str(out), *flags], before)


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
