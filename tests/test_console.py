"""What the person running a script sees: a start line, a progress line in place on a terminal and a line a minute
in a file (steps/s and time left from the last full minute of learning, a dash before one has passed), a note once
when a CPU run will take far longer than the task's CPU scale, and the progress lines that experiments/grid.py reads
its time-left estimate from."""

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


def console(module, capsys, random_steps=0, **fields):
    args = module.Args(**fields)
    progress = module.Progress()
    made = module.Console(args, progress, 1000, torch.device("cpu"), random_steps)
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
    assert capsys.readouterr().out.startswith("step 100/100 | - steps/s | - left | eval return 812.0, "
                                              "success 30% | labels 0/1000")


def test_a_resumed_run_s_clock_goes_on_from_the_saved_elapsed_time(capsys, clock):
    args = pebble.Args(total_timesteps=1000)
    progress = pebble.Progress(global_step=500, elapsed=3600.0)
    made = pebble.Console(args, progress, 10, torch.device("cpu"))
    clock.now += 10
    progress.global_step = 501
    made.update(progress)
    assert progress.elapsed == pytest.approx(3610)


@pytest.mark.parametrize("module", [pebble, rime, prefppo])
def test_the_rate_and_time_left_come_from_the_last_minute_of_learning_only(module, capsys, clock):
    """1000 random-action steps at 1000 steps/s, then learning at 0.5 steps/s: a dash until a minute of learning has
    passed (not 18 min left from the random steps' pace), then 0.5 steps/s, one decimal, and the time left from it."""
    made, progress, _ = console(module, capsys, random_steps=1000, total_timesteps=10_000)
    for step in range(1, 1001):
        clock.now += 0.001
        progress.global_step = step
        made.update(progress)
    for second in range(1, 241):  # 4 minutes of learning, 2 s a step
        clock.now += 1
        progress.global_step = 1000 + second // 2
        made.update(progress)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "step 1030/10000 | - steps/s | - left | labels 0/1000"  # a minute of the run, not of learning
    assert lines[1] == "step 1060/10000 | 0.5 steps/s | 5.0 h left | labels 0/1000"  # 8940 steps at 0.5/s
    assert lines[-1] == "step 1120/10000 | 0.5 steps/s | 4.9 h left | labels 0/1000"


@pytest.mark.parametrize("rate, shown", [(0.3, "0.3"), (9.5, "9.5"), (12.0, "12"), (2600.0, "2600")])
def test_below_10_steps_per_second_the_rate_has_one_decimal(capsys, clock, rate, shown):
    args = pebble.Args(total_timesteps=10**9)
    progress = pebble.Progress(global_step=1)  # a step done: learning from the start
    made = pebble.Console(args, progress, 10, torch.device("cpu"))
    for second in range(1, 61):
        clock.now += 1
        progress.global_step = 1 + round(second * rate)
        made.update(progress)
    line = capsys.readouterr().out.splitlines()[1]
    assert line.startswith(f"step {1 + round(60 * rate)}/{10**9} | {shown} steps/s |")


def test_a_resumed_run_shows_a_dash_until_a_minute_has_passed_again(capsys, clock):
    args = pebble.Args(total_timesteps=100_000)
    progress = pebble.Progress(global_step=50_000, elapsed=3600.0)
    made = pebble.Console(args, progress, 10, torch.device("cpu"), 1000)
    made.terminal = True  # a line each second
    for second in range(1, 121):
        clock.now += 1
        progress.global_step = 50_000 + 10 * second
        made.update(progress)
    lines = capsys.readouterr().out.split("\r")
    assert lines[1] == "step 50010/100000 | - steps/s | - left | labels 0/10\033[K"
    assert lines[59] == "step 50590/100000 | - steps/s | - left | labels 0/10\033[K"
    assert lines[60] == "step 50600/100000 | 10 steps/s | 82 min left | labels 0/10\033[K"


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
    if noted:  # 500,000 steps at 2 steps/s: 69 h; walker-walk's scale, 22-29 min a run (docs/parity/data/ours)
        assert notes[0] == ("note: on this CPU the run takes about 69 h; the CPU scale of walker-walk, "
                            "experiments/grid.py learning-cpu-pebble (--total-timesteps 100000 --hidden-dim 256 "
                            "--num-layers 2 --batch-size 256 --feedback-every 9000), took 22-29 min a run on a core "
                            "of a 2-core machine; the run goes on")
        assert out.splitlines().index(notes[0]) == 1  # after minute 1's line, before minute 2's


@pytest.mark.parametrize("module, env_id, scale", [
    (pebble, "quadruped-walk", "quadruped-walk, experiments/grid.py quadruped-walk-cpu (--total-timesteps 250000"),
    (pebble, "button-press-v3", "button-press, experiments/grid.py button-press-cpu (--total-timesteps 100000"),
    (pebble, "sweep-into", "sweep-into, experiments/grid.py sweep-into-cpu-250k (--total-timesteps 250000"),
    (pebble, "cheetah-run", "walker-walk, experiments/grid.py learning-cpu-pebble (--total-timesteps 100000"),
    (rime, "quadruped-walk", "walker-walk, experiments/grid.py rime-oracle (--total-timesteps 100000"),
    (prefppo, "quadruped-walk", "quadruped-walk, experiments/grid.py quadruped-walk-cpu-prefppo "
                                "(--total-timesteps 1000000), took 23-59 min a run"),
    (prefppo, "button-press", "button-press, experiments/grid.py button-press-cpu-prefppo (--total-timesteps "
                              "1000000 --max-feedback 6100), took 1.5-2.8 h a run")])
def test_the_note_names_the_task_s_own_cpu_scale(module, env_id, scale, capsys, clock):
    made, progress, _ = console(module, capsys, env_id=env_id, total_timesteps=10**7)
    for second in range(1, 121):
        clock.now += 1
        progress.global_step = second
        made.update(progress)
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and notes[0].startswith(f"note: on this CPU the run takes about 2778 h; the CPU scale of "
                                                   f"{scale}")


def test_each_cpu_scale_is_a_grid_preset_with_those_flags():
    """The note's flags run what the preset runs: the preset's flags and budget, but for evaluations at the script's
    defaults and checkpoints."""
    for module in (pebble, rime, prefppo):
        for task, scale in module.CPU_SCALES.items():
            preset, flags = scale.split(" (")[0].split()[-1], scale.split(" (")[1].split(")")[0]
            run = grid.PRESETS[preset][1]
            assert module.__name__ in run.algorithms and task in run.env_ids
            given = dict(zip(flags.split()[::2], flags.split()[1::2]))
            ran = dict(zip(run.flags.split()[::2], run.flags.split()[1::2]))
            ran["--max-feedback"] = run.budgets[0].split("/")[0]
            defaults = module.task_defaults(task, "oracle")
            for flag, value in ran.items():
                name = flag[2:].replace("-", "_")
                if flag in given:
                    assert given[flag] == value, (preset, flag)
                elif flag != "--checkpoint-every":
                    assert str(getattr(defaults, name)) == value, (preset, flag)
