"""experiments/: the grid runner on a tiny grid of both scripts (two teachers, two seeds, their ground-truth runs)
through the local pool and a local Ray instance, a rerun that skips, a killed run that is resumed, failures that
do not stop the grid; the report on it, and on a synthetic folder whose aggregates are computed by hand here."""

import csv
import json
import shlex
import signal
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch

import grid
import pebble
import prefppo
import report
from samplers import planned_labels, schedule_sizes, session_steps
from tests.helpers import ENV, ROOT, eval_curve, run_cli, wait_for

# Hopper-v5: positive returns (a ground-truth baseline that can normalise) and short random episodes. pebble: sessions
# at steps 101 and 151, evaluations at 100 and 200; prefppo: rollouts of 100, sessions at 100 and 200, 3 evaluations
COMMON = ("--unsup-steps 50 --feedback-every 50 --segment-len 5 --eval-every 100 --hidden-dim 16 --num-layers 1 "
          "--reward-epochs 2 --reward-batch-size 16 --eval-episodes 1")
PEBBLE = "--total-timesteps 200 --seed-steps 50 --batch-size 16 --buffer-size 1000 --critic-reset-updates 10"
PREFPPO = "--total-timesteps 300 --num-envs 2 --num-steps 50 --minibatch-size 50 --update-epochs 2"
TINY_GRID = ["--algorithms", "pebble", "prefppo", "--env-ids", "Hopper-v5", "--teachers", "oracle",
             "--budgets", "20/10", "--seeds", "1", "2", f"--flags={COMMON}", f"--pebble-flags={PEBBLE}",
             f"--prefppo-flags={PREFPPO}", "--progress-every", "5"]
TEACHER_RUNS = [f"{a}__Hopper-v5__oracle__fb20-10__disagreement__uniform__s{s}" for a in ("pebble", "prefppo")
                for s in (1, 2)]
GROUND_TRUTH_RUNS = [f"{a}__Hopper-v5__ground-truth__s{s}" for a in ("pebble", "prefppo") for s in (1, 2)]


def run_grid(root, *flags, timeout=600) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(ROOT / "experiments" / "grid.py"), "custom", "--root", str(root), *flags]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=ENV, cwd=ROOT)


def run_report(root, *flags) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(ROOT / "experiments" / "report.py"), str(root), *flags]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=ENV, cwd=ROOT)


def read_csv(path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def local_grid(tmp_path_factory):
    """The tiny grid, once, through the local backend with two workers."""
    root = tmp_path_factory.mktemp("local") / "grid"
    result = run_grid(root, *TINY_GRID, "--workers", "2")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return root, result


# ---------------------------------------------------------------- the grid, without running anything


def test_grid_is_the_cross_product_plus_one_ground_truth_run_per_algorithm_task_and_seed():
    spec = grid.Grid(algorithms=("pebble", "prefppo"), env_ids=("walker-walk", "button-press"),
                     teachers=("oracle", "stoc", "mistake"), budgets=("1000/100", "500"),
                     samplers=("uniform", "entropy"), schedules=("decay",), seeds=(1, 2, 3), flags="--hidden-dim 64",
                     pebble_flags="--batch-size 64")
    runs = grid.expand(spec)
    teacher_runs = [r for r in runs if "--ground-truth-reward" not in r.flags]
    truth_runs = [r for r in runs if "--ground-truth-reward" in r.flags]
    assert len(teacher_runs) == 2 * 2 * 3 * 2 * 2 * 1 * 3 and len(truth_runs) == 2 * 2 * 3
    assert len({r.name for r in runs}) == len(runs)
    assert not any("--teacher" in r.flags or "--max-feedback" in r.flags or "--sampler" in r.flags for r in truth_runs)
    for truth in truth_runs:  # each baseline runs before every teacher run of its algorithm and task
        algorithm, env_id = truth.name.split("__")[:2]
        assert all(runs.index(truth) < i for i, r in enumerate(runs) if r.name.startswith(f"{algorithm}__{env_id}__")
                   and r in teacher_runs)
    one = next(r for r in teacher_runs if r.name == "pebble__walker-walk__stoc__fb500__entropy__decay__s2")
    assert one.flags == ("--env-id", "walker-walk", "--seed", "2", "--teacher", "stoc", "--max-feedback", "500",
                         "--sampler", "entropy", "--schedule", "decay", "--hidden-dim", "64", "--batch-size", "64")
    assert all(("--batch-size" in r.flags) == (r.algorithm == "pebble") for r in runs)
    assert one.command(ROOT / "x", resume=True)[-2:] == ["--resume", str(ROOT / "x")]


BAD_GRIDS = [
    (["--teachers", "oracle", "sleepy"], "--teachers 'sleepy' is not one of oracle, stoc"),
    (["--algorithms", "dqn"], "--algorithms 'dqn' is not one of pebble, prefppo, rime"),
    (["--budgets", "100/200"], "--budgets '100/200' is not max_feedback[/feedback_per_session]"),
    (["--seeds", "1", "1"], "--seeds lists a value twice"),
    (["--flags=--seed 3"], "--flags sets --seed, which the grid sets itself"),
    (["--workers", "0"], "--workers and --cpus-per-run must be >= 1"),
]


@pytest.mark.parametrize("flags, message", BAD_GRIDS, ids=[" ".join(f) for f, _ in BAD_GRIDS])
def test_bad_grid_is_one_error_line_before_any_run(tmp_path, flags, message):
    result = run_grid(tmp_path / "grid", *flags)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [result.stderr.strip()] and message in result.stderr, result.stderr
    assert not (tmp_path / "grid").exists()


def test_edits_run_our_scripts_through_the_edits_runner_and_are_checked(tmp_path):
    result = run_grid(tmp_path / "grid", "--teachers", "oracle", "--seeds", "1", "--no-ground-truth",
                      "--edits", "raw-reward-inputs", "--dry-run")
    assert result.returncode == 0, result.stderr
    [command] = [shlex.split(line) for line in result.stdout.splitlines() if line.startswith("OMP_NUM_THREADS")]
    assert command[2].endswith("benchmarks/reference/edits.py") and command[3:5] == ["raw-reward-inputs", "--"]
    assert command[5].endswith("pebble.py") and "--teacher" in command
    wrong = run_grid(tmp_path / "grid", "--algorithms", "prefppo", "--edits", "raw-reward-input")
    assert wrong.returncode == 2 and "--edits 'raw-reward-input' is not an edit of prefppo.py" in wrong.stderr


def test_a_finished_run_without_the_grid_s_edits_is_refused_not_counted_as_done(tmp_path):
    [run, *_] = grid.expand(grid.Grid(env_ids=("walker-walk",), teachers=("equal",), seeds=(1,)))
    edited = replace(run, edits=("reference-thresholds",))
    (tmp_path / run.name).mkdir()
    (tmp_path / run.name / "config.json").write_text(json.dumps({"total_timesteps": 1000}))
    (tmp_path / run.name / "eval.csv").write_text("step,episode_return\n1000,500.0\n")
    (tmp_path / run.name / "final_model.pt").write_bytes(b"model")
    spec = {run.name: {"command": list(run.flags), "exit_code": 0}}  # written before grid.json kept edits: none
    assert grid.plan([run], tmp_path, spec) == ([], [], [run.name])
    todo, refused, finished = grid.plan([edited], tmp_path, spec)
    assert (todo, finished) == ([], []) and "holds a run with edits [] (this grid's: ['reference-thresholds'])" in \
        refused[0][1]
    spec[run.name]["edits"] = ["reference-thresholds"]
    assert grid.plan([edited], tmp_path, spec) == ([], [], [run.name])


def test_a_run_stopped_on_a_non_finite_value_is_resumed_only_when_asked(tmp_path):
    [run, *_] = grid.expand(grid.Grid(env_ids=("walker-walk",), teachers=("oracle",), seeds=(1,)))
    (tmp_path / run.name).mkdir()
    (tmp_path / run.name / "config.json").write_text(json.dumps({"total_timesteps": 1000}))
    (tmp_path / run.name / "checkpoint.pt").write_bytes(b"checkpoint")
    spec = {run.name: {"command": list(run.flags), "exit_code": 3}}
    todo, refused, finished = grid.plan([run], tmp_path, spec)
    assert (todo, finished) == ([], []) and "--retry-non-finite resumes it" in refused[0][1]
    assert grid.plan([run], tmp_path, spec, retry_non_finite=True) == ([(run, True)], [], [])
    spec[run.name]["exit_code"] = -15  # stopped by SIGTERM after a checkpoint: resumed without asking
    assert grid.plan([run], tmp_path, spec) == ([(run, True)], [], [])
    spec[run.name]["exit_code"] = 4  # a write failed (a full disk, since freed): resumed without asking
    assert grid.plan([run], tmp_path, spec) == ([(run, True)], [], [])
    assert grid.failure_of(4) == "exit code 4 (a write failed (a full disk?))"


def test_dry_run_prints_every_command_and_starts_nothing(tmp_path):
    result = run_grid(tmp_path / "grid", *TINY_GRID, "--dry-run")
    assert result.returncode == 0, result.stderr
    commands = [line for line in result.stdout.splitlines() if line.startswith("OMP_NUM_THREADS=1 python ")]
    assert len(commands) == 8
    assert "--ground-truth-reward" in commands[0]  # the baselines start first
    first = shlex.split(next(c for c in commands if "--teacher" in c))
    assert first[2].endswith("pebble.py") and first[first.index("--teacher") + 1] == "oracle"
    assert first[first.index("--output-dir") + 1] == str((tmp_path / "grid" / TEACHER_RUNS[0]).resolve())
    assert sum("--ground-truth-reward" in c for c in commands) == 4
    assert not (tmp_path / "grid").exists()


def keep_run(docs, name, config, wall_time, last_step=None):
    """A run as experiments/keep_runs.py keeps it: config.json and eval.csv, its last row at last_step."""
    (docs / name).mkdir(parents=True)
    (docs / name / "config.json").write_text(json.dumps(config))
    step = config["total_timesteps"] if last_step is None else last_step
    (docs / name / "eval.csv").write_text(f"step,episode_return,wall_time\n{step // 2},1.0,1.0\n{step},2.0,{wall_time}\n")


def test_dry_run_cost_is_the_median_wall_time_of_alike_kept_runs_and_a_resume_costs_its_steps_left(tmp_path):
    docs, root = tmp_path / "docs", tmp_path / "runs"
    walker = {"exp_name": "pebble", "env_id": "walker-walk", "total_timesteps": 100000, "hidden_dim": 256,
              "ground_truth_reward": False}
    for seed, minutes in enumerate([20, 30, 70], 1):  # median 30 min
        keep_run(docs, f"pebble_s{seed}", walker, minutes * 60)
    keep_run(docs, "shorter", walker | {"total_timesteps": 40000}, 9999.0)  # other steps: not alike
    keep_run(docs, "unfinished", walker, 9999.0, last_step=50000)  # never reached its last step: not counted
    keep_run(docs, "sac", walker | {"ground_truth_reward": True}, 9999.0)  # the baseline: not alike to a teacher's
    keep_run(docs, "rime", walker | {"exp_name": "rime"}, 9999.0)  # another algorithm
    flags = ("--env-id", "walker-walk", "--seed", "1", "--teacher", "oracle", "--total-timesteps", "100000",
             "--hidden-dim", "256")
    new = grid.Run("new", "pebble", flags)
    half = grid.Run("half", "pebble", flags)  # resumed at step 50000 of 100000: 15 min left
    keep_run(root, "half", walker, 900.0, last_step=50000)
    cheetah = grid.Run("cheetah", "pebble", ("--env-id", "cheetah-run", "--teacher", "oracle"))
    lines = grid.dry_run_cost([(new, False), (half, True), (cheetah, False)], root, 2, docs)
    assert lines[0].startswith("# about 1.5 core-hours for 2 runs")  # (30 + 15) min x 2 cores
    assert lines[1] == "# no kept run alike, so no estimate, for 1 runs: cheetah"


def test_dry_run_of_a_bpref_preset_estimates_its_core_hours_from_the_runs_kept_under_docs(tmp_path):
    cmd = [sys.executable, str(ROOT / "experiments" / "grid.py"), "bpref-walker-teachers", "--root",
           str(tmp_path / "grid"), "--dry-run"]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=ENV, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    hours = float(result.stdout.splitlines()[-1].split()[2])
    assert 20 * 15 / 60 < hours < 20 * 60 / 60  # 20 runs of 15-60 minutes each (walker-walk at CPU scale)


def test_keep_runs_counts_each_session_s_skipped_and_equal_answers_into_labels_csv(tmp_path):
    run = tmp_path / "run"
    keep_run(tmp_path, "run", {"total_timesteps": 100}, 5.0)
    (run / "labels").mkdir()
    nan = float("nan")  # a skipped query's label
    np.savez(run / "labels" / "session_0000.npz", step=11, y=np.array([1.0, 0.5, nan, 0.0, 0.5]),
             keep=np.array([True, True, False, True, True]))
    np.savez(run / "labels" / "session_0001.npz", step=61, y=np.array([0.0, 1.0]), keep=np.array([True, True]))
    kept = subprocess.run([sys.executable, str(ROOT / "experiments" / "keep_runs.py"), str(run), "--to",
                           str(tmp_path / "kept")], capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert kept.returncode == 0, kept.stderr[-2000:]
    assert sorted(path.name for path in (tmp_path / "kept" / "run").iterdir()) == ["config.json", "eval.csv",
                                                                                  "labels.csv"]
    assert (tmp_path / "kept" / "run" / "labels.csv").read_text().splitlines() == [
        "session,step,queries,skipped,equal", "0,11,5,1,2", "1,61,2,0,0"]


def test_keep_runs_with_labels_keeps_what_fit_teacher_reads_without_the_segments(tmp_path):
    import fit_teacher
    run = tmp_path / "run"
    keep_run(tmp_path, "run", {"total_timesteps": 100}, 5.0)
    (run / "labels").mkdir()
    rng = np.random.default_rng(0)
    sessions = []
    for session in range(2):
        arrays = {"step": np.array(10 + 50 * session), "y": np.array([1.0, 0.0, 0.5]), "keep": np.ones(3, bool),
                  "threshold_scale": np.array(2.5 + session)}
        for side in "01":
            arrays |= {f"rewards{side}": rng.random((3, 4), np.float32), f"obs{side}": rng.random((3, 4, 5)),
                       f"actions{side}": rng.random((3, 4, 2))}
        np.savez(run / "labels" / f"session_{session:04d}.npz", **arrays)
        sessions.append(arrays)
    cmd = [sys.executable, str(ROOT / "experiments" / "keep_runs.py"), str(run), "--to", str(tmp_path / "kept")]
    kept = subprocess.run([*cmd, "--labels"], capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert kept.returncode == 0, kept.stderr[-2000:]
    files = sorted((tmp_path / "kept" / "run" / "labels").iterdir())
    assert [file.name for file in files] == ["session_0000.npz", "session_0001.npz"]
    for file, arrays in zip(files, sessions):
        with np.load(file) as data:
            assert sorted(data.files) == ["keep", "rewards0", "rewards1", "step", "threshold_scale", "y"]
            for key in data.files:
                np.testing.assert_array_equal(data[key], arrays[key])
    assert fit_teacher.load_labels(str(tmp_path / "kept" / "run"))["threshold_scale"].tolist() == [2.5] * 3 + [3.5] * 3
    (run / "labels" / "session_0000.npz").unlink()
    (run / "labels" / "session_0001.npz").unlink()
    refused = subprocess.run([*cmd, "--labels"], capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert refused.returncode != 0 and "Traceback" not in refused.stderr
    assert refused.stderr.strip().splitlines() == [f"error: {run}: no label files (labels/session_*.npz) to keep "
                                                   "with --labels"]


def test_teacher_fit_table_says_whether_the_intervals_hold_each_run_s_teacher(tmp_path, monkeypatch):
    """Simulated runs' labels: the oracle's intervals hold it; a teacher leaning left gets the side bias, with beta,
    gamma and eps_mistake fitted again without intervals ("-"), so the table cannot say they hold it."""
    import fit_teacher
    from sim_teacher import SimTeacher
    for name, teacher in (("oracle", SimTeacher()), ("leaning", SimTeacher(bias=-0.3))):
        fit_teacher.simulate(str(tmp_path / name), teacher, pairs=400, sessions=4, seed=1)
        config = json.loads((tmp_path / name / "config.json").read_text())
        config |= {"exp_name": "pebble", "env_id": "walker-walk", "total_timesteps": 100, "seed": 1,
                   "max_feedback": 400, "feedback_per_session": 100, "sampler": "uniform", "schedule": "uniform"}
        (tmp_path / name / "config.json").write_text(json.dumps(config))
        (tmp_path / name / "eval.csv").write_text("step,episode_return,wall_time\n100,1.0,1.0\n")
    monkeypatch.setattr(report, "TEACHER_FIT_FOLDER", str(tmp_path))
    rows = [line.split(" | ") for line in report.teacher_fit_table().splitlines()[2:]]
    assert [row[0].removeprefix("| ") for row in rows] == ["oracle, uniform sampler, seed 1",
                                                           "oracle, bias -0.3, uniform sampler, seed 1"]
    assert rows[0][-2:] == ["yes", "yes |"]
    assert rows[1][2].endswith("[-, -]") and rows[1][-2] == "no"  # beta fitted again with the bias


def test_bpref_presets_vary_one_axis_of_the_kept_runs_they_are_compared_with():
    """Each block of B-Pref's findings changes only its axis (teacher, sampler, schedule, label smoothing) from the
    runs kept beside it: walker-walk's parity-pebble, button-press-cpu and quadruped-walk-cpu (oracle), rime-mistake
    (mistake); --checkpoint-every changes no result."""
    def flags(preset):
        five_seeds = replace(grid.PRESETS[preset][1], seeds=(1, 2, 3, 4, 5))  # the kept runs' seeds
        runs = [run for run in grid.expand(five_seeds) if "--teacher" in run.flags]
        by_name = {}
        for run in runs:
            words = list(run.flags)
            if "--checkpoint-every" in words:
                del words[words.index("--checkpoint-every"):words.index("--checkpoint-every") + 2]
            by_name[run.name] = tuple(words)
        return by_name

    oracle = flags("parity-pebble") | flags("button-press-cpu") | flags("quadruped-walk-cpu")
    for preset in ("bpref-walker-teachers", "bpref-button-press", "bpref-quadruped-walk"):
        for name, words in flags(preset).items():
            teacher = words[words.index("--teacher") + 1]
            base = tuple("oracle" if w == teacher else w for w in words)
            assert base == oracle[name.replace(f"__{teacher}__", "__oracle__")], (preset, name)
    for preset, option in (("bpref-walker-samplers", "--sampler"), ("bpref-walker-schedules", "--schedule")):
        default = {"--sampler": "disagreement", "--schedule": "uniform"}[option]
        for name, words in flags(preset).items():
            at = words.index(option) + 1
            base = words[:at] + (default,) + words[at + 1:]
            assert base == oracle[name.replace(f"__{words[at]}__", f"__{default}__", 1)], (preset, name)
    mistake = flags("rime-mistake")
    for name, words in flags("bpref-walker-smoothing").items():
        at = words.index("--label-smoothing")
        assert words[at + 1] == "0.1" and words[:at] + words[at + 2:] == mistake[name]
    equal = flags("bpref-walker-samplers-equal")
    assert {words[words.index("--sampler") + 1] for words in equal.values()} == set(grid.SAMPLERS)
    prefppo = flags("bpref-walker-prefppo")
    parity = flags("parity-prefppo")
    for name, words in prefppo.items():
        teacher = words[words.index("--teacher") + 1]
        base = tuple("oracle" if w == teacher else w for w in words)
        assert base == parity[name.replace(f"__{teacher}__", "__oracle__")], name


def test_the_reference_thresholds_presets_are_their_blocks_runs_with_the_edit_in_a_root_of_their_own():
    for preset, block in (("bpref-walker-reference-thresholds", "bpref-walker-teachers"),
                          ("bpref-quadruped-reference-thresholds", "bpref-quadruped-walk")):
        edited = grid.expand(grid.PRESETS[preset][1])
        plain = {run.name: run for run in grid.expand(grid.PRESETS[block][1])}
        assert len(edited) == 10 and {r.flags[r.flags.index("--teacher") + 1] for r in edited} == {"skip", "equal"}
        for run in edited:
            assert run.edits == ("reference-thresholds",) and run.flags == plain[run.name].flags
            assert plain[run.name].edits == ()
        assert grid.PRESETS[preset][1].root != grid.PRESETS[block][1].root


# ---------------------------------------------------------------- the tiny grid, run


@pytest.mark.slow
def test_local_grid_runs_every_run_to_its_end_with_its_own_directory_and_log(local_grid):
    root, result = local_grid
    assert "grid: 8 runs" in result.stdout and "8/8 done" in result.stdout
    spec = json.loads((root / "grid.json").read_text())["runs"]
    assert sorted(spec) == sorted(TEACHER_RUNS + GROUND_TRUTH_RUNS)
    for name in TEACHER_RUNS + GROUND_TRUTH_RUNS:
        assert grid.run_state(root / name)[0] == "finished"
        assert spec[name]["exit_code"] == 0
        log = (root / "logs" / f"{name}.log").read_text()
        assert log.count("=== exit code 0") == 1 and "done:" in log
        config = json.loads((root / name / "config.json").read_text())
        assert config["ground_truth_reward"] == (name in GROUND_TRUTH_RUNS)
        assert len(list((root / name / "labels").glob("session_*.npz"))) == (0 if name in GROUND_TRUTH_RUNS else 2)
        assert config["max_feedback"] == 20 or name in GROUND_TRUTH_RUNS  # the budget reaches each run


@pytest.mark.slow
def test_rerun_skips_the_finished_runs(local_grid):
    root, _ = local_grid
    before = {name: (root / name / "final_model.pt").stat().st_mtime_ns for name in TEACHER_RUNS}
    result = run_grid(root, *TINY_GRID)
    assert result.returncode == 0, result.stderr
    assert "8 finished, 0 to resume, 0 to start" in result.stdout
    assert before == {name: (root / name / "final_model.pt").stat().st_mtime_ns for name in TEACHER_RUNS}
    assert (root / "logs" / f"{TEACHER_RUNS[0]}.log").read_text().count("=== ") == 2  # start and exit, once


@pytest.mark.slow
def test_a_rerun_with_other_flags_is_refused_rather_than_mixed_into_the_runs(local_grid):
    root, _ = local_grid
    flags = [f.replace("--total-timesteps 200", "--total-timesteps 400") for f in TINY_GRID]
    result = run_grid(root, *flags)
    assert result.returncode == 1
    assert result.stdout.count("holds a run of other flags") == 4  # pebble's runs; prefppo's flags are unchanged
    assert "4 finished, 0 to resume, 0 to start, 4 refused" in result.stdout


@pytest.mark.slow
def test_ray_backend_runs_the_same_grid_with_the_same_results(local_grid, tmp_path):
    root = tmp_path / "ray"
    # a part of the tiny grid: pebble's run with the teacher, seed 1 (the backend runs a command, whichever script)
    part = [*TINY_GRID]
    part[part.index("--seeds") + 1:part.index("--seeds") + 3] = ["1"]
    part[part.index("--algorithms") + 1:part.index("--algorithms") + 3] = ["pebble"]
    result = run_grid(root, *part, "--no-ground-truth", "--backend", "ray", "--workers", "2", timeout=900)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "Started a local Ray instance" in result.stderr and "1/1 done" in result.stdout
    name = TEACHER_RUNS[0]
    assert grid.run_state(root / name)[0] == "finished"
    # the same command on CPU gives the same run, whichever backend started it
    np.testing.assert_allclose(np.array(eval_curve(root / name), float),
                               np.array(eval_curve(local_grid[0] / name), float), rtol=1e-6)


def resume_grid(env_ids: list[str], workers: int) -> list[str]:
    return ["--algorithms", "pebble", "--env-ids", *env_ids, "--teachers", "oracle", "--budgets", "20/10", "--seeds",
            "1", "2", "--no-ground-truth", f"--flags={COMMON} --checkpoint-every 100", f"--pebble-flags={PEBBLE}",
            "--workers", str(workers)]


@pytest.mark.slow
def test_stopped_grid_resumes_from_the_checkpoint_and_a_failed_run_does_not_stop_it(local_grid, tmp_path):
    root = tmp_path / "grid"
    first, second = (f"pebble__Hopper-v5__oracle__fb20-10__disagreement__uniform__s{s}" for s in (1, 2))
    cmd = [sys.executable, str(ROOT / "experiments" / "grid.py"), "custom", "--root", str(root),
           *resume_grid(["Hopper-v5"], workers=1)]
    stopped = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    wait_for(root / first / "checkpoint.pt", stopped)  # the periodic checkpoint at step 100
    stopped.send_signal(signal.SIGTERM)  # a batch system's time limit: the grid passes it on to its run
    stdout, _ = stopped.communicate()
    assert stopped.returncode == 128 + signal.SIGTERM
    assert f"interrupted: {first}: stopped by signal 15 after a checkpoint (exit code 143)" in stdout
    assert grid.run_state(root / first)[0] == "resumable" and not (root / second).exists()  # not started
    (root / second).mkdir()  # a run that died before its first checkpoint
    (root / second / "config.json").write_text("{}")

    result = run_grid(root, *resume_grid(["Hopper-v5", "NoSuchTask-v0"], workers=2))
    assert result.returncode == 1
    assert "1 to resume, 3 to start" in result.stdout
    log = (root / "logs" / f"{first}.log").read_text()
    assert "SIGTERM: checkpoint saved at step" in log and "resuming from the checkpoint at step" in log
    assert log.count("=== exit code 143") == 1 and log.count("=== exit code 0") == 1
    assert [p.name.split(".")[0] for p in (root / ".aside").iterdir()] == [second]
    for name in (first, second):  # the resumed run and the restarted one equal the uninterrupted runs
        assert grid.run_state(root / name)[0] == "finished"
        np.testing.assert_allclose(np.array(eval_curve(root / name), float),
                                   np.array(eval_curve(local_grid[0] / name), float), rtol=1e-6)
    for seed in (1, 2):  # an unknown task fails each of its runs, and the grid goes on
        name = f"pebble__NoSuchTask-v0__oracle__fb20-10__disagreement__uniform__s{seed}"
        log_path = root / "logs" / f"{name}.log"
        assert f"failed: {name}: exit code 2 (bad input); log {log_path}" in result.stdout
        assert "error: --env-id 'NoSuchTask-v0'" in log_path.read_text()


# ---------------------------------------------------------------- the report on the tiny grid


@pytest.mark.slow
def test_report_on_the_tiny_grid_writes_markdown_csv_and_pngs(local_grid, tmp_path):
    root, _ = local_grid
    out = tmp_path / "report"
    result = run_report(root, "--out", str(out), "--reps", "200")
    assert result.returncode == 0, result.stderr[-3000:]
    markdown = (out / "report.md").read_text()
    assert "## Normalised return per setting" in markdown and "Unfinished" not in markdown
    for png in ("figure2_Hopper-v5", "curves_pebble_Hopper-v5", "curves_prefppo_Hopper-v5",
                f"alignment_{TEACHER_RUNS[0]}", f"alignment_{TEACHER_RUNS[2]}"):
        assert (out / f"{png}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"({png}.png)" in markdown
    assert not list(out.glob("samplers_*")) and not list(out.glob("schedules_*"))  # one sampler, one schedule
    rows = {row["run"]: row for row in read_csv(out / "runs.csv")}
    final = {name: grid.read_eval(root / name)[-1]["episode_return"] for name in TEACHER_RUNS + GROUND_TRUTH_RUNS}
    for name in TEACHER_RUNS + GROUND_TRUTH_RUNS:
        baseline = np.mean([final[f"{name.split('__')[0]}__Hopper-v5__ground-truth__s{s}"] for s in (1, 2)])
        assert float(rows[name]["normalized"]) == pytest.approx(final[name] / baseline, rel=1e-9)
    aggregates = read_csv(out / "aggregates.csv")
    assert [(r["algorithm"], r["teacher"], r["runs"]) for r in aggregates] == [
        ("pebble", "oracle", "2"), ("prefppo", "oracle", "2")]


@pytest.mark.slow
@pytest.mark.parametrize("name", [TEACHER_RUNS[0], TEACHER_RUNS[2]], ids=["pebble", "prefppo"])
def test_reward_alignment_rebuilds_the_final_model_as_the_run_evaluated_it(local_grid, name):
    """The report rebuilds env, policy and reward model from config.json and final_model.pt. Replayed with the
    script's own evaluate() and the last evaluation's seeds, they give the run's own final evaluation row; the
    report's alignment episode is that evaluation's first episode."""
    torch.set_num_threads(1)  # as the run had
    run = next(r for r in report.find_runs(local_grid[0], local_grid[0] / "report") if r.path.name == name)
    module, env, actor, reward_model, obs_stats = report.load_final_model(run)
    policy = module.mean_policy(actor, "cpu") if module is pebble else module.mean_policy(actor, obs_stats, "cpu")
    seeds = report.final_evaluation_seeds(module, run)
    replayed = module.evaluate(policy, reward_model, env, seeds, "cpu")
    final = grid.read_eval(run.path)[-1]
    assert replayed["episode_return"] == pytest.approx(final["episode_return"], rel=1e-6)
    assert replayed["reward_correlation"] == pytest.approx(final["reward_correlation"], rel=1e-5)
    first = module.evaluate(policy, reward_model, env, seeds[:1], "cpu")
    true_rewards, learned_rewards = report.reward_alignment(run)
    assert true_rewards.sum() == pytest.approx(first["episode_return"], rel=1e-9)
    correlation = np.corrcoef(true_rewards, learned_rewards)[0, 1]
    assert correlation == pytest.approx(first["reward_correlation"], rel=1e-6)


# ---------------------------------------------------------------- the report on a synthetic folder


def write_run(root, name, env_id, seed, finals, teacher="oracle", sampler="disagreement", truth=False, total=10000,
              finished=True, metric="episode_return", budget=(1000, 100)):
    """A run folder as the scripts write it: config.json, eval.csv (two evaluations, the last one `finals`),
    final_model.pt when finished. `finals` is the final value of `metric`."""
    path = root / name
    path.mkdir(parents=True)
    config = {"env_id": env_id, "seed": seed, "teacher": teacher, "sampler": sampler, "schedule": "uniform",
              "max_feedback": budget[0], "feedback_per_session": budget[1], "ground_truth_reward": truth,
              "total_timesteps": total, **{k: None for k in report.TEACHER_OVERRIDES}}
    (path / "config.json").write_text(json.dumps(config))
    last_step = total if finished else total // 2
    rows = [{"step": total // 2, "episode_return": 1.0, "success_rate": 0.0},
            {"step": last_step, "episode_return": 1000.0, "success_rate": 0.0, metric: finals}]
    with open(path / "eval.csv", "w", newline="") as f:
        fields = ["step", "episode_return", "episode_return_std", "success_rate", "feedback", "reward_correlation",
                  "wall_time", "overhead_seconds"]
        writer = csv.DictWriter(f, fields, restval="0")
        writer.writeheader()
        writer.writerows(rows if finished else rows[:1])
    if finished:
        (path / "final_model.pt").write_bytes(b"")


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """walker-walk: ground truth 400, 600 (mean 500); oracle 100 ... 900 -> 0.2, 0.4, 0.6, 0.8, 1.0, 1.8; mistake 100,
    300 -> 0.2, 0.6; oracle with entropy sampling 500, 500 -> 1.0, 1.0. quadruped-walk: ground truth 100, 100; oracle
    10 ... 60 -> 0.1 ... 0.6. button-press (Meta-World: success rate; budget 10000/50): ground truth 0.8, 1.0;
    oracle 0.45, 0.9 -> 0.5, 1.0. cheetah-run: oracle runs and no ground truth. One unfinished run, one planned and
    missing."""
    root = tmp_path_factory.mktemp("synthetic") / "runs"
    for seed, value in enumerate([400, 600], 1):
        write_run(root, f"walker_truth_{seed}", "walker-walk", seed, value, truth=True)
    for seed, value in enumerate([100, 200, 300, 400, 500, 900], 1):
        write_run(root, f"walker_oracle_{seed}", "walker-walk", seed, value)
    for seed, value in enumerate([100, 300], 1):
        write_run(root, f"walker_mistake_{seed}", "walker-walk", seed, value, teacher="mistake")
        write_run(root, f"walker_entropy_{seed}", "walker-walk", seed, 500, sampler="entropy")
    write_run(root, "walker_mistake_3", "walker-walk", 3, 0, teacher="mistake", finished=False)
    for seed in (1, 2):
        write_run(root, f"quadruped_truth_{seed}", "quadruped-walk", seed, 100, truth=True)
    for seed, value in enumerate([10, 20, 30, 40, 50, 60], 1):
        write_run(root, f"quadruped_oracle_{seed}", "quadruped-walk", seed, value)
    for seed, value in enumerate([0.8, 1.0], 1):
        write_run(root, f"button_truth_{seed}", "button-press", seed, value, truth=True, metric="success_rate")
    for seed, value in enumerate([0.45, 0.9], 1):
        write_run(root, f"button_oracle_{seed}", "button-press", seed, value, metric="success_rate", budget=(10000, 50))
    for seed in (1, 2):
        write_run(root, f"cheetah_oracle_{seed}", "cheetah-run", seed, 300)
    (root / "grid.json").write_text(json.dumps({"runs": {"walker_oracle_7": {"command": [], "exit_code": None}}}))
    result = run_report(root, "--reps", "200", "--alignment-runs", "0")
    assert result.returncode == 0, result.stderr[-3000:]
    return root, result


def aggregate_rows(path) -> dict:
    return {(r["algorithm"], r["task"], r["teacher"], r["sampler"]): {k: float(v) for k, v in r.items()
                                                                     if k not in report.SETTING + ("metric",)}
            for r in read_csv(path)}


def test_aggregates_equal_the_values_computed_by_hand(synthetic):
    root, _ = synthetic
    rows = aggregate_rows(root / "report" / "aggregates.csv")
    oracle = rows[("pebble", "walker-walk", "oracle", "disagreement")]
    # normalised 0.2, 0.4, 0.6, 0.8, 1.0, 1.8: IQM drops one of six at each end (25%); gap = 1 - mean(min(x, 1));
    # rliable's median is the median over tasks of each task's mean, so on one task it is the mean
    assert oracle["iqm"] == pytest.approx((0.4 + 0.6 + 0.8 + 1.0) / 4)
    assert oracle["median"] == pytest.approx(0.8) and oracle["mean"] == pytest.approx(0.8)
    assert oracle["optimality_gap"] == pytest.approx(1 - 4.0 / 6)
    # two runs, 0.2 and 0.6: a bootstrap mean is 0.2, 0.4 or 0.6 with chances 1/4, 1/2, 1/4, so the 95% CI is [0.2, 0.6]
    mistake = rows[("pebble", "walker-walk", "mistake", "disagreement")]
    assert (mistake["mean_low"], mistake["mean"], mistake["mean_high"]) == pytest.approx((0.2, 0.4, 0.6))
    entropy = rows[("pebble", "walker-walk", "oracle", "entropy")]  # identical runs: a CI of width 0
    assert (entropy["iqm_low"], entropy["iqm_high"]) == pytest.approx((1.0, 1.0))
    assert rows[("pebble", "quadruped-walk", "oracle", "disagreement")]["mean"] == pytest.approx(0.35)
    button = rows[("pebble", "button-press", "oracle", "disagreement")]  # success rates 0.45, 0.9 over 0.9
    assert button["mean"] == pytest.approx(0.75) and button["optimality_gap"] == pytest.approx(0.25)
    # walker-walk and quadruped-walk together (button-press has another budget): IQM of the 12 scores = mean of the
    # middle 6 of 0.1 0.2 0.2 0.3 0.4 0.4 | 0.5 0.6 0.6 0.8 1.0 1.8 -> 0.3 0.4 0.4 0.5 0.6 0.6
    across = {r["teacher"] + r["sampler"]: r for r in read_csv(root / "report" / "aggregates_across_tasks.csv")}
    assert float(across["oracledisagreement"]["iqm"]) == pytest.approx(2.8 / 6)
    assert float(across["oracledisagreement"]["median"]) == pytest.approx((0.8 + 0.35) / 2)  # of the two task means
    assert across["oracledisagreement"]["tasks"] == "2" and across["oracledisagreement"]["runs"] == "12"


def test_bootstrap_intervals_repeat_for_a_seed_and_change_with_it():
    # nine distinct scores: two bootstraps of 2000 draws from other random numbers give other percentiles
    scores = {"arm": np.array([643, 98, 287, 603, 574, 552, 443, 752, 467.0])[:, None]}
    first = report.aggregate(scores, 2000, 0)
    assert report.aggregate(scores, 2000, 0) == first
    assert report.aggregate(scores, 2000, 1)["arm"]["iqm"][1:] != first["arm"]["iqm"][1:]


def test_normalised_return_is_divided_by_the_mean_of_the_same_algorithms_ground_truth_runs(synthetic):
    root, _ = synthetic
    runs = {row["run"]: row for row in read_csv(root / "report" / "runs.csv")}
    assert float(runs["walker_oracle_6"]["normalized"]) == pytest.approx(900 / 500)
    assert float(runs["walker_truth_1"]["normalized"]) == pytest.approx(400 / 500)
    assert float(runs["button_oracle_1"]["normalized"]) == pytest.approx(0.45 / 0.9)  # success, not the return 1000
    assert runs["button_oracle_1"]["metric"] == "success_rate"


def test_a_missing_baseline_is_named_and_nothing_is_divided_by_it(synthetic):
    root, result = synthetic
    message = "pebble on cheetah-run: no finished ground-truth run (--ground-truth-reward) to normalise by"
    assert message in result.stdout
    markdown = (root / "report" / "report.md").read_text()
    assert "## Not normalisable" in markdown and message in markdown
    runs = {row["run"]: row for row in read_csv(root / "report" / "runs.csv")}
    assert runs["cheetah_oracle_1"]["normalized"] == "" and float(runs["cheetah_oracle_1"]["score"]) == 300
    assert not any(task == "cheetah-run" for _, task, _, _ in aggregate_rows(root / "report" / "aggregates.csv"))


def test_unfinished_and_missing_runs_are_listed_not_aggregated(synthetic):
    root, _ = synthetic
    markdown = (root / "report" / "report.md").read_text()
    assert "`walker_mistake_3`: unfinished, last evaluation at step 5000 of 10000" in markdown
    assert "`walker_oracle_7`: missing (planned by the grid, not started)" in markdown
    rows = aggregate_rows(root / "report" / "aggregates.csv")
    assert len(read_csv(root / "report" / "aggregates.csv")) == 5
    assert rows[("pebble", "walker-walk", "mistake", "disagreement")]["mean"] == pytest.approx(0.4)  # 2 runs, not 3


def test_sampler_comparison_and_figure_2_are_drawn(synthetic):
    out = synthetic[0] / "report"
    for png in ("figure2_walker-walk", "figure2_button-press", "samplers_pebble_walker-walk",
                "curves_pebble_walker-walk"):
        assert (out / f"{png}.png").read_bytes()[:4] == b"\x89PNG"
    assert not (out / "samplers_pebble_quadruped-walk.png").exists()


def test_figure_axes_follow_the_paper_s_order():
    assert sorted(["entropy", "uniform", "entropy-coverage", "disagreement"], key=report.axis_order("sampler")) == [
        "uniform", "disagreement", "entropy", "entropy-coverage"]
    assert sorted(["increase", "uniform", "decay"], key=report.axis_order("schedule")) == ["uniform", "decay",
                                                                                           "increase"]
    assert sorted(["myopic", "mistake(label_smoothing=0.1)", "oracle"], key=report.axis_order("teacher")) == [
        "oracle", "mistake(label_smoothing=0.1)", "myopic"]


def test_a_teacher_is_named_with_the_overrides_that_change_it_and_label_smoothing():
    base = {"env_id": "walker-walk", "ground_truth_reward": False, "max_feedback": 500, "feedback_per_session": 50,
            "sampler": "entropy", "schedule": "decay"}
    # saved values equal to the named teacher's own (a script may save them resolved) are no override
    assert report.setting_of({**base, "teacher": "oracle", "teacher_beta": float("inf"), "teacher_gamma": 1.0,
                              "teacher_eps_mistake": 0.0}) == ("pebble", "walker-walk", "oracle", "500/50", "entropy",
                                                               "decay")
    assert report.setting_of({**base, "teacher": "myopic", "teacher_gamma": 0.9, "teacher_eps_mistake": 0.1,
                              "num_envs": 8})[:3] == ("prefppo", "walker-walk", "myopic(eps_mistake=0.1)")
    assert report.setting_of({**base, "teacher": "stoc", "ground_truth_reward": True})[2:] == ("ground-truth", "-",
                                                                                                "-", "-")
    assert report.setting_of({**base, "teacher": "mistake", "teacher_eps_mistake": 0.3, "rime_alpha": 0.5})[:3] == (
        "rime", "walker-walk", "mistake(eps_mistake=0.3)")
    # label smoothing trains on the same teacher's labels with another loss: a setting of its own, none at 0
    assert report.setting_of({**base, "teacher": "mistake", "label_smoothing": 0.1})[2] == \
        "mistake(label_smoothing=0.1)"
    assert report.setting_of({**base, "teacher": "mistake", "label_smoothing": 0.0})[2] == "mistake"
    assert report.setting_of({**base, "teacher": "oracle", "her_ratio": 0.5})[:3] == ("qpa", "walker-walk", "oracle")
    assert report.setting_of({**base, "teacher": "oracle", "her_ratio": 0.5, "implementation": "reference"})[0] == (
        "reference-qpa")


def test_rime_presets_run_pebble_and_rime_with_the_same_flags_and_seeds():
    for preset in ("rime-mistake", "rime-mistake-0.3", "rime-oracle", "rime-mini-bpref"):
        runs = grid.expand(grid.PRESETS[preset][1])
        pebble = {r.name.removeprefix("pebble__"): r.flags for r in runs if r.algorithm == "pebble"}
        rime = {r.name.removeprefix("rime__"): r.flags for r in runs if r.algorithm == "rime"}
        assert pebble and pebble == rime, preset
    eps = grid.expand(grid.PRESETS["rime-mistake-0.3"][1])[0].flags
    assert eps[eps.index("--teacher-eps-mistake") + 1] == "0.3"


def without_sampler(run):
    at = run.flags.index("--sampler")
    return run.flags[:at] + run.flags[at + 2:]


def test_qpa_presets_run_qpa_and_pebble_with_the_same_flags_and_seeds_each_asking_its_own_way():
    for preset in ("qpa-walker-100", "qpa-walker-1000", "qpa-button-press", "qpa-sweep-into", "qpa-mistake"):
        runs = grid.expand(grid.PRESETS[preset][1])
        flags = {algorithm: sorted(without_sampler(r) for r in runs if r.algorithm == algorithm)
                 for algorithm in ("pebble", "qpa")}
        assert len(flags["qpa"]) == 5 and flags["pebble"] == flags["qpa"], preset
        samplers = {r.algorithm: r.flags[r.flags.index("--sampler") + 1] for r in runs}
        assert samplers["qpa"] == "uniform" and samplers["pebble"] == "disagreement", preset
        assert {r.name.split("__")[4] for r in runs if r.algorithm == "qpa"} == {"uniform"}  # named as asked
    # beside the presets whose runs are kept: their PEBBLE (and RIME) runs are the same runs, by name and flags
    for preset, beside in (("qpa-walker-1000", "parity-pebble"), ("qpa-mistake", "rime-mistake"),
                           ("qpa-button-press", "button-press-cpu"), ("qpa-sweep-into", "sweep-into-cpu")):
        ours, theirs = grid.PRESETS[preset][1], replace(grid.PRESETS[beside][1], seeds=(1, 2, 3, 4, 5))
        earlier = {r.name: r.flags for r in grid.expand(theirs)}
        others = [r for r in grid.expand(ours) if r.algorithm != "qpa"]
        assert ours.root == theirs.root and others and all(earlier[r.name] == r.flags for r in others), preset
    # QPA's own code on qpa-walker-100's setting, in its root: report.py pairs them by setting
    walker = {r.name: r.flags for r in grid.expand(grid.PRESETS["qpa-walker-100"][1]) if r.algorithm == "qpa"}
    reference = grid.expand(grid.PRESETS["qpa-reference"][1])
    assert grid.PRESETS["qpa-reference"][1].root == grid.PRESETS["qpa-walker-100"][1].root
    assert {r.name.removeprefix("reference__"): r.flags for r in reference} == walker
    assert reference[0].command(ROOT / "x", resume=False)[1:3] == ["--algorithm", "qpa"]
    problem = grid.check(replace(grid.PRESETS["qpa-walker-100"][1], samplers=("default", "uniform")))
    assert problem == "--samplers default (each script's own sampler) stands alone"


def test_committed_data_without_final_model_is_reported_and_not_replayed(tmp_path):
    """docs/ keeps config.json and eval.csv only: a run evaluated to its last step counts as finished (scored and
    normalised), one that stopped before is not, and no reward alignment is tried without final_model.pt."""
    for seed, value in enumerate([0.4, 0.8], 1):
        write_run(tmp_path, f"truth_{seed}", "sweep-into", seed, value, truth=True, metric="success_rate")
    write_run(tmp_path, "oracle_1", "sweep-into", 1, 0.3, metric="success_rate")
    write_run(tmp_path, "oracle_2", "sweep-into", 2, 0.9, metric="success_rate", finished=False)
    for model in tmp_path.rglob("final_model.pt"):
        model.unlink()
    result = run_report(tmp_path, "--reps", "200", "--alignment-runs", "1")
    assert result.returncode == 0, result.stderr[-3000:]
    runs = {row["run"]: row for row in read_csv(tmp_path / "report" / "runs.csv")}
    assert runs["oracle_1"]["state"] == "finished" and float(runs["oracle_1"]["normalized"]) == pytest.approx(0.5)
    assert runs["oracle_2"]["state"] == "partial" and runs["oracle_2"]["score"] == ""
    markdown = (tmp_path / "report" / "report.md").read_text()
    assert "alignment" not in markdown and "`oracle_2`: unfinished" in markdown


def test_report_on_a_folder_without_runs_is_one_error_line(tmp_path):
    result = run_report(tmp_path)
    message = f"error: no runs (folders with a config.json) below {tmp_path.resolve()}"
    assert result.returncode == 2 and result.stderr.strip() == message
    assert not (tmp_path / "report").exists()


def test_progress_estimates_time_left_from_the_runs_so_far(tmp_path):
    progress = grid.Progress(waiting=3, finished_before=1, refused=[], concurrency=2, every=60,
                             logs={"a": tmp_path / "a.log"})  # no log yet: no fraction of the running run
    progress.start("a")
    progress.running["a"] -= 100  # started 100 s ago
    progress.durations = [300.0]  # one run of this grid took 300 s
    # a: 200 s left; two waiting runs of 300 s each; two workers share 800 s
    assert progress.time_left() == pytest.approx(400, abs=1)


def test_the_card_commands_projection_adds_its_phases_as_measured_by_hand():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import card_speed

    config = {"seed_steps": 1000, "unsup_steps": 9000, "eval_every": 10000, "total_timesteps": 100000,
              "max_feedback": 300, "feedback_per_session": 100, "feedback_every": 30000}  # sessions 10001, 40001, 70001
    walls = [(10000, 100.0), (20000, 180.0), (30000, 240.0), (40000, 300.0), (50000, 370.0)]
    rows = [{"step": step, "wall_time": wall} for step, wall in walls]
    blocks, total = card_speed.projection(rows, config)
    assert [kind for _, kind, _, _ in blocks] == ["pre-training", "session + SAC", "SAC on r_hat", "SAC on r_hat",
                                                  "session + SAC"]
    # pre-training 100 s; 9 blocks of SAC at the median 60 s; sessions 1-3 cost 20, 40 and 60 s over SAC
    assert total == pytest.approx(100 + 9 * 60 + 20 * (1 + 2 + 3))
    assert np.isnan(card_speed.projection(rows[:2], config)[1])  # no block of SAC alone yet: no projection


@pytest.mark.parametrize("preset", ["button-press-cpu", "sweep-into-cpu", "sweep-into-cpu-250k"])
def test_metaworld_cpu_presets_keep_the_papers_sessions_and_spend_their_budget(preset, monkeypatch):
    runs = grid.expand(grid.PRESETS[preset][1])
    assert sorted("--ground-truth-reward" in r.flags for r in runs) == [False] * 3 + [True] * 3
    (run,) = [r for r in runs if "--teacher" in r.flags and r.name.endswith("__s1")]
    monkeypatch.setattr(sys, "argv", ["pebble.py", *run.flags])
    args = pebble.parse_args()  # the preset's flags over the Meta-World task's defaults
    assert (args.feedback_per_session, args.feedback_every, args.segment_len) == (50, 4950, 50)
    first = args.seed_steps + args.unsup_steps + 1
    steps = session_steps(first, args.feedback_every, args.total_timesteps)
    sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session, steps - 1,
                           args.total_timesteps)
    spent = planned_labels(sizes, first, args.feedback_every, args.total_timesteps)
    assert spent == args.max_feedback == {100_000: 900, 150_000: 1400, 250_000: 2400}[args.total_timesteps]


def test_quadruped_cpu_preset_spends_its_1000_labels_in_10_sessions_within_250k_steps(monkeypatch):
    runs = grid.expand(grid.PRESETS["quadruped-walk-cpu"][1])
    assert sorted("--ground-truth-reward" in r.flags for r in runs) == [False] * 3 + [True] * 3
    (run,) = [r for r in runs if "--teacher" in r.flags and r.name.endswith("__s1")]
    monkeypatch.setattr(sys, "argv", ["pebble.py", *run.flags])
    args = pebble.parse_args()
    assert (args.learning_rate, args.hidden_dim, args.batch_size) == (1e-4, 256, 256)  # the preset's rate kept
    first = args.seed_steps + args.unsup_steps + 1
    steps = session_steps(first, args.feedback_every, args.total_timesteps)
    sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session, steps - 1,
                           args.total_timesteps)
    assert list(sizes) == [100] * 10 and steps[-1] == 10_001 + 9 * 24_000 < args.total_timesteps == 250_000
    assert planned_labels(sizes, first, args.feedback_every, args.total_timesteps) == 1000
    myopic = grid.expand(grid.PRESETS["quadruped-walk-myopic-cpu"][1])
    oracle = {r.name.replace("oracle", "myopic"): r.flags for r in runs if "--teacher" in r.flags}
    assert {r.name: r.flags for r in myopic} == {
        name: tuple(word.replace("oracle", "myopic") for word in flags) for name, flags in oracle.items()}


@pytest.mark.parametrize("preset, task_values, sessions", [
    ("quadruped-walk-cpu-prefppo", dict(num_envs=16, minibatch_size=128, gae_lambda=0.9, feedback_every=32_000), 10),
    ("button-press-cpu-prefppo", dict(num_envs=8, num_steps=250, minibatch_size=128, segment_len=25,
                                      learning_rate=3e-4, reward_epochs=50, feedback_every=16_000), 61),
    ("sweep-into-cpu-prefppo", dict(num_envs=32, num_steps=250, minibatch_size=256, segment_len=25,
                                    learning_rate=3e-4, reward_epochs=50, feedback_every=16_000), 61)])
def test_prefppo_cpu_presets_keep_the_task_s_preset_and_spend_sessions_of_100_in_1m_steps(monkeypatch, preset,
                                                                                         task_values, sessions):
    runs = grid.expand(grid.PRESETS[preset][1])
    assert sorted("--ground-truth-reward" in r.flags for r in runs) == [False] * 3 + [True] * 3
    assert all(r.algorithm == "prefppo" for r in runs)
    (run,) = [r for r in runs if "--teacher" in r.flags and r.name.endswith("__s1")]
    monkeypatch.setattr(sys, "argv", ["prefppo.py", *run.flags])
    args = prefppo.parse_args()
    assert {name: getattr(args, name) for name in task_values} == task_values  # the task's PrefPPO preset
    assert (args.total_timesteps, args.unsup_steps) == (1_000_000, 32_000)
    rollout = args.num_envs * args.num_steps
    steps = session_steps(args.unsup_steps, args.feedback_every, args.total_timesteps - 1, rollout)
    sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session, steps,
                           args.total_timesteps)
    assert list(sizes) == [100] * sessions and steps[sessions - 1] == 32_000 + (sessions - 1) * args.feedback_every
    labels = planned_labels(sizes, args.unsup_steps, args.feedback_every, args.total_timesteps - 1, rollout)
    assert labels == 100 * sessions == args.max_feedback


# ---------------------------------------------------------------- reward_check.py: r_hat on an expert's episodes


def reward_check(*args) -> subprocess.CompletedProcess:
    return run_cli("experiments/reward_check.py", *map(str, args))


@pytest.mark.slow
@pytest.mark.parametrize("algorithm, expert", [("pebble", "prefppo"), ("prefppo", "pebble")])
def test_reward_check_replays_the_last_evaluation_and_ranks_the_expert_s_episodes(local_grid, tmp_path, algorithm,
                                                                                    expert):
    """The own policy's episodes are the run's last evaluation, number for number (its return and r_hat's
    correlation); the ranking line counts the seeds on which each reward puts the expert's episode first. The
    expert may be a run of the other script (its own policy code plays it)."""
    root, _ = local_grid
    run = root / f"{algorithm}__Hopper-v5__oracle__fb20-10__disagreement__uniform__s1"
    expert = root / f"{expert}__Hopper-v5__ground-truth__s2"
    table = tmp_path / "episodes.csv"
    result = reward_check(run, "--expert", expert, "--csv", table)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = read_csv(table)
    last = grid.read_eval(run)[-1]
    own = [row for row in rows if row["policy"] == "own policy"]
    assert len(own) == 1 and float(own[0]["true_return"]) == pytest.approx(last["episode_return"], rel=1e-9)
    own_line = next(line for line in result.stdout.splitlines() if line.startswith("| own policy |"))
    assert own_line.split("|")[5].strip() == f"{last['reward_correlation']:.3f}"
    experts = [row for row in rows if row["policy"] == "expert run"]
    by_learned = sum(float(e["learned_return"]) > float(o["learned_return"]) for e, o in zip(experts, own))
    by_true = sum(float(e["true_return"]) > float(o["true_return"]) for e, o in zip(experts, own))
    agree = int(by_learned == by_true)  # one seed
    assert (f"by the learned reward in {by_learned} of 1, by the true reward in {by_true} of 1; the two agree on "
            f"{agree} of 1") in result.stdout
    assert {row["policy"] for row in rows} == {"own policy", "expert run", "random policy"}
    refused = [reward_check(run), reward_check(run, "--expert", root / "pebble__walker-walk__nothing"),
               reward_check(run, "--episodes", 2), reward_check(root / "logs"), reward_check(expert)]
    messages = ["no scripted policy for 'Hopper-v5' (Meta-World's only): give --expert RUN", "is not a run's folder",
                "--episodes must be in [0, 1]", "is not a run's folder", "learned from the true reward"]
    for result, message in zip(refused, messages):
        assert result.returncode == 2 and result.stderr.count("\n") == 1 and message in result.stderr, result.stderr


def test_reward_check_s_scripted_expert_sees_the_goal_that_the_agent_s_observations_hide(tmp_path):
    """Meta-World's scripted sweep-into policy moves the cube to the goal it reads from the observation: it succeeds
    on the run's evaluation seed although the agent's own episode (goal hidden) was played first, and r_hat is fed
    the hidden-goal observations it was trained on (a reward model that reads only the goal's entries gives every
    episode the same learned return)."""
    run = tmp_path / "sweep-into-run"
    run.mkdir()
    args = pebble.Args(env_id="sweep-into", hidden_dim=16, num_layers=1, eval_episodes=1, total_timesteps=20000,
                       output_dir=str(run))
    (run / "config.json").write_text(json.dumps(vars(args)))
    (run / "eval.csv").write_text("step,episode_return,episode_return_std,success_rate,reward_correlation,feedback,"
                                  "wall_time\n20000,0.0,0.0,0.0,0.0,0,1.0\n")
    torch.manual_seed(0)
    networks = {"actor": pebble.Actor(39, 4, 16, 1), "critic": pebble.TwinCritic(39, 4, 16, 1),
                "reward_model": pebble.RewardEnsemble(39, 4, 3)}
    with torch.no_grad():
        for member in networks["reward_model"].members:
            member[0][0].weight[:, :36] = 0  # the first layer reads the goal's entries (36-38) only
            member[0][0].weight[:, 39:] = 0
    torch.save({name: network.state_dict() for name, network in networks.items()}, run / "final_model.pt")
    result = reward_check(run, "--csv", tmp_path / "episodes.csv")
    assert result.returncode == 0, result.stderr[-3000:]
    rows = {row["policy"]: row for row in read_csv(tmp_path / "episodes.csv")}
    assert rows["scripted expert"]["success"] == "1" and rows["own policy"]["success"] == "0"
    assert float(rows["scripted expert"]["true_return"]) > 10 * float(rows["random policy"]["true_return"])
    assert rows["scripted expert"]["learned_return"] == rows["own policy"]["learned_return"]
