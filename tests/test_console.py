"""What the person running a script sees (issue 46): a start line, a progress line in place on a terminal and a
line a minute in a file, a note once when a CPU run will take far longer than the README's CPU scale, and the
progress lines that experiments/grid.py reads its time-left estimate from."""

import os
import pty
import subprocess
import sys
import time

import pytest
import torch

import pebble
import prefppo
import rime
from experiments import grid
from tests.helpers import ENV, ROOT, run_script
from tests.test_pebble import TINY

# Pendulum, 400 steps: pre-training from step 101, sessions at 201, 251 and 301, an evaluation at the end
SHORT = ["--env-id", "Pendulum-v1", "--total-timesteps", "400", "--seed-steps", "100", "--unsup-steps", "100",
         "--feedback-every", "50", "--max-feedback", "30", "--feedback-per-session", "10", "--segment-len", "10",
         "--eval-every", "400", *TINY]


class Clock:
    """time.time() under the test's control."""

    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


@pytest.fixture
def clock(monkeypatch):
    fake = Clock()
    monkeypatch.setattr(time, "time", fake)  # the scripts' and the grid's
    return fake


def console(module, capsys, **fields):
    args = module.Args(**fields)
    progress = module.Progress()
    made = module.Console(args, progress, 1000, torch.device("cpu"))
    return made, progress, capsys.readouterr().out


@pytest.mark.parametrize("module", [pebble, rime, prefppo])
def test_start_line_names_the_device_steps_labels_and_directory(module, capsys, clock):
    _, _, out = console(module, capsys, total_timesteps=100_000, output_dir="runs/x")
    threads = torch.get_num_threads()
    assert out == (f"{module.Args.exp_name} on the CPU (torch threads: {threads}): 100000 steps, 1000 labels "
                   "planned; outputs in runs/x\n")
    _, _, out = console(module, capsys, ground_truth_reward=True, output_dir="runs/y")
    assert "the true reward" in out and "labels" not in out


@pytest.mark.parametrize("module", [pebble, rime, prefppo])
def test_in_a_file_a_progress_line_a_minute_and_at_the_end(module, capsys, clock):
    made, progress, _ = console(module, capsys, total_timesteps=10_000)
    for step in range(1, 10_001):  # 40 steps/s: 250 s in all
        clock.now += 0.025
        progress.global_step = step
        if step == 3000:
            progress.eval_rows.append({"episode_return": 123.45, "success_rate": 0.3})
            progress.feedback_used = 200
        made.update(progress)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 5  # minutes 1-4, and the last step
    assert lines[0] == "step 2400/10000 | 40 steps/s | 3 min left | labels 0/1000"
    assert lines[1] == "step 4800/10000 | 40 steps/s | 2 min left | eval return 123.5 | labels 200/1000"
    assert lines[-1].startswith("step 10000/10000 | 40 steps/s | 0 s left")
    assert progress.elapsed == pytest.approx(250)  # the run's clock, saved in checkpoints


def test_meta_world_lines_give_the_success_rate(capsys, clock):
    made, progress, _ = console(pebble, capsys, env_id="button-press", total_timesteps=100)
    clock.now += 1
    progress.global_step = 100
    progress.eval_rows.append({"episode_return": 812.0, "success_rate": 0.3})
    made.update(progress)
    assert capsys.readouterr().out.startswith("step 100/100 | 100 steps/s | 0 s left | eval return 812.0, "
                                              "success 30% | labels 0/1000")


def test_a_resumed_run_s_clock_goes_on_from_the_saved_elapsed_time(capsys, clock):
    args = pebble.Args(total_timesteps=1000)
    progress = pebble.Progress(global_step=500, elapsed=3600.0)
    made = pebble.Console(args, progress, 10, torch.device("cpu"))
    clock.now += 10
    progress.global_step = 501
    made.update(progress)
    assert progress.elapsed == pytest.approx(3610)


@pytest.mark.parametrize("rate, noted", [(2.0, True), (50.0, False)])
def test_a_cpu_run_of_more_than_12_hours_is_noted_once_after_two_minutes(capsys, clock, rate, noted):
    made, progress, _ = console(pebble, capsys, total_timesteps=500_000)
    for second in range(1, 301):
        clock.now += 1
        progress.global_step = int(second * rate)
        made.update(progress)
    out = capsys.readouterr().out
    notes = [line for line in out.splitlines() if line.startswith("note:")]
    assert len(notes) == int(noted)
    if noted:  # 500,000 steps at 2 steps/s: 69 h
        assert notes[0].startswith("note: on this CPU the run takes about 69 h; the README's CPU scale "
                                   f"({pebble.CPU_SCALE}) takes under an hour")
        assert out.splitlines().index(notes[0]) == 1  # after minute 1's line, before minute 2's


def test_no_note_on_a_gpu(capsys, clock):
    made, progress, _ = console(pebble, capsys, total_timesteps=500_000)
    made.on_cpu = False  # as Console sets it for a CUDA device
    for second in range(1, 301):
        clock.now += 1
        progress.global_step = second * 2
        made.update(progress)
    assert "note:" not in capsys.readouterr().out


def test_grid_reads_its_time_left_from_a_run_s_progress_lines(tmp_path, capsys, clock):
    made, progress, _ = console(pebble, capsys, total_timesteps=10_000)
    for step in range(1, 2501):
        clock.now += 0.025
        progress.global_step = step
        made.update(progress)
    log = tmp_path / "run.log"
    log.write_text(capsys.readouterr().out)
    tracker = grid.Progress(waiting=1, finished_before=0, refused=[], concurrency=1, every=60, logs={"run": log})
    tracker.start("run")
    tracker.running["run"] -= 60  # started a minute ago, 24% done: 190 s left
    assert tracker.fraction("run") == pytest.approx(0.24)
    assert tracker.time_left() == pytest.approx(60 / 0.24 - 60, abs=1)


def test_a_whole_run_s_log_ends_with_its_last_progress_line(tmp_path):
    out = tmp_path / "run"
    result = run_script("pebble.py", out, *SHORT, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    lines = result.stdout.splitlines()
    assert lines[0].startswith("pebble on the CPU (torch threads: 1): 400 steps, 30 labels planned; outputs in")
    assert lines[-2].startswith("step 400/400 | ") and lines[-2].endswith(" | labels 30/30")
    assert lines[-1].startswith("done: 3 feedback sessions")
    log = tmp_path / "run.log"
    log.write_text(result.stdout)
    tracker = grid.Progress(waiting=0, finished_before=0, refused=[], concurrency=1, every=60, logs={"run": log})
    assert tracker.fraction("run") == 1.0


def test_on_a_terminal_the_line_is_rewritten_in_place(tmp_path):
    """A real pseudo-terminal: the progress line starts with a carriage return and clears what is left of the old
    one; each other message first clears the progress line."""
    main, child = pty.openpty()
    cmd = [sys.executable, str(ROOT / "pebble.py"), "--output-dir", str(tmp_path / "run"), *SHORT]
    process = subprocess.Popen(cmd, stdout=child, stderr=subprocess.DEVNULL, env=ENV, cwd=ROOT)
    os.close(child)
    chunks = []
    while True:
        try:
            chunk = os.read(main, 4096)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        chunks.append(chunk)
    assert process.wait(timeout=300) == 0
    text = b"".join(chunks).decode()
    assert "\rstep 400/400 | " in text and "\x1b[K" in text
    assert "\r\x1b[Kdone: 3 feedback sessions" in text
    assert "\nstep 400/400" not in text  # never a line of its own
