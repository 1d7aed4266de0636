"""benchmarks/reference/: the compatibility edits on a small fake tree of the reference code, the translation of our
flags into the reference's settings, its results read back in our eval.csv columns, the grid's implementation axis
and the report's side-by-side. No network and no reference code needed (CI has neither)."""

import csv
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import types
from dataclasses import replace

import numpy as np
import pytest

import grid
import pebble
import report
from tests.helpers import ENV, ROOT

sys.path.insert(0, str(ROOT / "benchmarks" / "reference"))
import patch  # noqa: E402
import run as reference_run  # noqa: E402
import stale_inputs  # noqa: E402
import trace_prefppo  # noqa: E402

RUNNER = ROOT / "benchmarks" / "reference" / "run.py"


def fake_tree(root):
    """The lines of the reference's files that the edits change, among lines they must leave alone."""
    for name, old, _, _ in patch.EDITS:
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        text = path.read_text() if path.exists() else "import torch\n"
        path.write_text(text + old + "x = 1\n" + (old if name.endswith("wrappers.py") else ""))
    return root


def test_edits_apply_once_and_change_only_their_text(tmp_path):
    tree = fake_tree(tmp_path / "BPref")
    before = {name: (tree / name).read_text() for name, *_ in patch.EDITS}
    done = patch.apply(tree)
    assert len(done) == len(patch.EDITS) and all(line.startswith("edited ") for line in done)
    for name, old, new, _ in patch.EDITS:
        text = (tree / name).read_text()
        assert old not in text.replace(new, "") and new in text
        assert text == before[name].replace(old, new) or name == "utils.py"  # utils.py: two edits
    wrappers = (tree / "custom_dmc2gym/dmc2gym/wrappers.py").read_text()
    assert wrappers.count("dim = int(np.prod(s.shape))") == 2 and "np.int(" not in wrappers
    assert "device = 'cuda' if torch.cuda.is_available() else 'cpu'" in (tree / "reward_model.py").read_text()
    again = {name: (tree / name).read_text() for name, *_ in patch.EDITS}
    assert all(line.startswith("already edited") for line in patch.apply(tree))
    assert again == {name: (tree / name).read_text() for name, *_ in patch.EDITS}


def test_a_tree_that_is_not_the_reference_is_refused(tmp_path):
    tree = fake_tree(tmp_path / "BPref")
    (tree / "reward_model.py").write_text("device = 'cpu'\n")
    with pytest.raises(ValueError, match="reward_model.py: the text to edit is not there"):
        patch.apply(tree)
    with pytest.raises(FileNotFoundError, match="not found"):
        patch.apply(tmp_path / "elsewhere")
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks/reference/patch.py"), str(tmp_path / "none")],
                            capture_output=True, text=True, env=ENV)
    assert result.returncode == 1 and result.stderr.startswith("error: ") and len(result.stderr.splitlines()) == 1


def test_rimes_tree_gets_only_the_utils_edits(tmp_path):
    tree = tmp_path / "RIME"
    tree.mkdir()
    (tree / "train_RIME.py").write_text("import utils\n")
    (tree / "reward_model.py").write_text("device = 'cuda:0'\n")  # set from --device: left alone
    utils_edits = [edit for edit in patch.EDITS if edit[0] == "utils.py"]
    (tree / "utils.py").write_text("import torch\n" + "".join(old for _, old, _, _ in utils_edits) + "x = 1\n")
    done = patch.apply(tree)
    assert len(done) == 2 and all(line.startswith("edited utils.py") for line in done)
    text = (tree / "utils.py").read_text()
    assert "except ImportError:\n    metaworld = None" in text and "set_default_validate_args(False)" in text
    assert (tree / "reward_model.py").read_text() == "device = 'cuda:0'\n"
    assert all(line.startswith("already edited") for line in patch.apply(tree))
    (tree / "utils.py").unlink()
    with pytest.raises(FileNotFoundError, match="a copy of RIME's code at 4ad03f4"):
        patch.apply(tree)


def test_qpas_tree_gets_the_utils_edits_an_optional_wandb_and_its_evaluations_written(tmp_path):
    tree = tmp_path / "QPA"
    (tree / "agent").mkdir(parents=True)
    utils_edits = [edit for edit in patch.EDITS if edit[0] == "utils.py"]
    (tree / "utils.py").write_text("import torch\n" + "".join(old for _, old, _, _ in utils_edits) + "x = 1\n")
    (tree / "agent" / "sac.py").write_text("import torch\nimport wandb\n")
    evaluation = "                        ep_reward, ep_reward_hat, success_rate  = self.evaluate()\n"
    (tree / "train_QPA.py").write_text("import os\nimport wandb\n\nclass Workspace(object):\n    def run(self):\n"
                                       "        self.step, self.total_feedback = 20000, 30\n"
                                       "        self.evaluate = lambda: (812.5, -3.0, 0.0)\n"
                                       "        if True:\n" + evaluation + "\nWorkspace().run()\n")
    done = patch.apply(tree)
    assert len(done) == 6 and all(line.startswith("edited ") for line in done)
    assert all(line.startswith("already edited") for line in patch.apply(tree))
    assert "except ImportError:\n    wandb = None" in (tree / "agent" / "sac.py").read_text()
    result = subprocess.run([sys.executable, "train_QPA.py"], cwd=tree, capture_output=True, text=True, env=ENV)
    assert result.returncode == 0 and result.stdout == "| eval | S: 20000 | TR: 812.5000 | FB: 30\n", result.stderr
    rows = reference_run.converted_rows(tree, [42.0])  # what run.py reads back: the true return, the labels so far
    assert [(r["step"], r["episode_return"], r["feedback"], r["success_rate"], r["wall_time"]) for r in rows] == [
        (20000, 812.5, 30.0, 0.0, 42.0)]
    (tree / "agent" / "sac.py").unlink()
    with pytest.raises(FileNotFoundError, match="a copy of QPA's code at 7e9e49e"):
        patch.apply(tree)


def test_qpa_flags_become_the_overrides_of_qpas_walker_run():
    args = reference_run.Args(output_dir="x", algorithm="qpa", seed=2, total_timesteps=100000, hidden_dim=256,
                              num_layers=2, batch_size=256, feedback_every=9000, max_feedback=100,
                              feedback_per_session=10)
    assert reference_run.resolve(args) is None and args.sampler == "uniform"  # qpa.py's own
    command = reference_run.qpa_command(args)
    assert command[0] == "train_QPA.py"
    # run_QPA.sh's walker_walk line (lr 0.0005, reward_update 2000, segment 50, max_reward_buffer_size 10,
    # data_aug_ratio 20, ensemble_size 1, explore false, her_ratio 0.5) at the README's CPU scale
    expected = {"env": "walker_walk", "seed": "2", "device": "cpu", "num_train_steps": "100001",
                "num_seed_steps": "1000", "num_unsup_steps": "9000", "agent.params.actor_lr": "0.0005",
                "agent.params.critic_lr": "0.0005", "agent.params.batch_size": "256",
                "diag_gaussian_actor.params.hidden_dim": "256", "diag_gaussian_actor.params.hidden_depth": "2",
                "double_q_critic.params.hidden_dim": "256", "double_q_critic.params.hidden_depth": "2",
                "eval_frequency": "10000", "num_eval_episodes": "10", "num_interact": "9000", "max_feedback": "100",
                "reward_batch": "10", "reward_update": "2000", "segment": "50", "gradient_update": "1",
                "activation": "tanh", "teacher_beta": "-1", "teacher_gamma": "1.0", "teacher_eps_mistake": "0.0",
                "teacher_eps_skip": "0.0", "teacher_eps_equal": "0.0", "max_reward_buffer_size": "10",
                "data_aug_ratio": "20", "ensemble_size": "1", "explore": "false", "her_ratio": "0.5",
                "wandb": "false"}
    assert settings(command) == expected
    config = reference_run.our_config(args, command)
    assert config["her_ratio"] == 0.5 and "rime_alpha" not in config and "num_envs" not in config
    assert report.setting_of(config) == ("reference-qpa", "walker-walk", "oracle", "100/10", "uniform", "uniform")
    for flags, error in (({"sampler": "disagreement"}, "--sampler disagreement: QPA's code has uniform only"),
                         ({"reward_updates": 0}, "--reward-updates and --query-recent-episodes: QPA's code needs"),
                         ({"ground_truth_reward": True}, "--ground-truth-reward: only with --algorithm pebble"),
                         ({"rime_alpha": 0.5}, "--rime-alpha is not a setting of qpa"),
                         ({"total_timesteps": 4000}, "--total-timesteps 4000: the reference evaluates every")):
        assert reference_run.resolve(reference_run.Args(output_dir="x", algorithm="qpa", **flags)).startswith(error)
    assert reference_run.resolve(reference_run.Args(output_dir="x", her_ratio=0.5)) == "--her-ratio is not a " \
                                                                                     "setting of pebble"
    pebble = reference_run.Args(output_dir="x")
    assert reference_run.resolve(pebble) is None and pebble.sampler == "disagreement"  # pebble.py's own


def settings(command: list[str]) -> dict:
    return dict(item.split("=", 1) for item in command[1:])


def test_our_flags_become_the_reference_settings_of_the_same_experiment():
    args = reference_run.Args(output_dir="x", seed=3, total_timesteps=100000, hidden_dim=256, num_layers=2,
                              batch_size=256, feedback_every=9000, max_feedback=1000, feedback_per_session=100,
                              teacher="mistake", sampler="disagreement", learning_rate=5e-4, segment_len=50,
                              reward_epochs=50)
    assert reference_run.resolve(args) is None
    command = reference_run.reference_command(args)
    assert command[0] == "train_PEBBLE.py"
    got = settings(command)
    assert got | {"teacher_eps_mistake": float(got["teacher_eps_mistake"])} == got | {"teacher_eps_mistake": 0.1}
    expected = {"env": "walker_walk", "seed": "3", "num_train_steps": "100001", "num_seed_steps": "1000",
                "num_unsup_steps": "9000", "num_interact": "9000", "max_feedback": "1000", "reward_batch": "100",
                "reward_schedule": "0", "feed_type": "1", "segment": "50", "reward_update": "50", "teacher_beta": "-1",
                "agent.params.batch_size": "256", "agent.params.actor_lr": "0.0005",
                "agent.params.critic_lr": "0.0005", "diag_gaussian_actor.params.hidden_dim": "256",
                "double_q_critic.params.hidden_depth": "2", "eval_frequency": "10000", "num_eval_episodes": "10",
                "device": "cpu"}
    assert {key: got[key] for key in expected} == expected
    # the reference's walker scripts ask 2x (decay) or 0.5x (increase) the per-session count as reward_batch
    for schedule, code, batch in (("decay", "1", "200"), ("increase", "2", "50")):
        args.schedule = schedule
        got = settings(reference_run.reference_command(args))
        assert (got["reward_schedule"], got["reward_batch"]) == (code, batch)
    args.teacher, args.schedule = "stoc", "uniform"
    assert settings(reference_run.reference_command(args))["teacher_beta"] == "1.0"
    args.ground_truth_reward = True
    sac = reference_run.reference_command(args)
    assert sac[0] == "train_SAC.py" and "max_feedback" not in settings(sac)
    assert settings(sac)["num_unsup_steps"] == "9000"  # the same pre-training as ours


def reference_files(tmp_path, eval_csv: str, train_csv: str):
    """A reference run's own folder (bpref/) holding these eval.csv and train.csv."""
    bpref = tmp_path / "bpref"
    bpref.mkdir()
    (bpref / "eval.csv").write_text(eval_csv)
    (bpref / "train.csv").write_text(train_csv)
    return bpref


def test_a_meta_world_task_becomes_the_reference_v2_task_with_the_task_preset():
    args = reference_run.Args(output_dir="x", env_id="button-press", seed=2, teacher="oracle", max_feedback=900,
                              feedback_per_session=50, total_timesteps=100000)
    assert reference_run.resolve(args) is None
    got = settings(reference_run.reference_command(args))
    expected = {"env": "metaworld_button-press-v2", "agent.params.actor_lr": "0.0003", "reward_batch": "50",
                "num_interact": "4950", "segment": "50", "reward_update": "10", "max_feedback": "900"}
    assert {key: got[key] for key in expected} == expected
    assert reference_run.reference_env("sweep-into-v3") == "metaworld_sweep-into-v2"
    assert reference_run.reference_env("quadruped-walk") == "quadruped_walk"


def test_meta_world_success_is_read_back_as_a_rate_and_the_loggers_empty_rows_are_skipped(tmp_path):
    bpref = reference_files(tmp_path, "episode,episode_reward,step,success_rate\n"
                                      "20.0,300.0,10000,30.0\n40.0,900.0,20000,100.0\n",
                            "episode,step,total_feedback\n20.0,10000,0.0\n21.0,10500,50.0\n"
                            "40.0,20000,100.0\n0.0,20000,0.0\n")  # its last train row: an empty dump
    rows = reference_run.converted_rows(bpref, [1.0, 2.0])
    assert [(r["success_rate"], r["feedback"]) for r in rows] == [(0.3, 50.0), (1.0, 100.0)]


def test_the_reference_on_meta_world_needs_its_own_environment_and_runs_pebble_and_sac_only(tmp_path):
    def run(*flags):
        result = subprocess.run([sys.executable, str(RUNNER), "--env-id", "button-press", "--output-dir",
                                 str(tmp_path / "out"), *flags], capture_output=True, text=True, env=ENV)
        return result.returncode, result.stderr.strip()

    assert run("--reference-dir", str(tmp_path / "ref")) == (
        2, f"error: no reference code in {tmp_path / 'ref'}: run benchmarks/reference/setup_metaworld.sh first")
    (tmp_path / "ref" / ".venv-metaworld" / "bin").mkdir(parents=True)
    (tmp_path / "ref" / ".venv-metaworld" / "bin" / "python").write_text("")
    (tmp_path / "ref" / "BPref-metaworld").mkdir()
    (tmp_path / "ref" / "BPref-metaworld" / "train_PEBBLE.py").write_text("")
    assert run("--reference-dir", str(tmp_path / "ref"), "--algorithm", "prefppo") == (
        2, "error: --env-id 'button-press': Meta-World runs with --algorithm pebble only here")
    assert not (tmp_path / "out").exists()


def test_rime_flags_become_the_flags_of_rimes_walker_runs():
    args = reference_run.Args(output_dir="x", algorithm="rime", seed=2, teacher="mistake", teacher_eps_mistake=0.3,
                              total_timesteps=100000, hidden_dim=256, num_layers=2, batch_size=256,
                              feedback_every=9000, max_feedback=1000, feedback_per_session=100)
    assert reference_run.resolve(args) is None
    command = reference_run.rime_command(args)
    assert command[0] == "train_RIME.py"
    got = dict(item.split("=", 1) for item in command[1:])
    # run_parallel.sh's walker_walk line (lr 0.0005, 9000 unsupervised steps, reward_update 50, feed_type 1,
    # least_reward_update 15, alpha 0.5, beta 3 -> 1) at the README's CPU scale
    expected = {"--env": "walker_walk", "--seed": "2", "--device": "cpu", "--steps": "100001", "--unsup_steps": "9000",
                "--num_interact": "9000", "--max_feedback": "1000", "--reward_batch": "100", "--reward_update": "50",
                "--feed_type": "1", "--actor_lr": "0.0005", "--critic_lr": "0.0005", "--batch_size": "256",
                "--actor_hidden_dim": "256", "--critic_hidden_dim": "256", "--actor_hidden_depth": "2",
                "--critic_hidden_depth": "2", "--least_reward_update": "15", "--threshold_variance": "kl",
                "--threshold_alpha": "0.5", "--threshold_beta_init": "3.0", "--threshold_beta_min": "1.0",
                "--eps_mistake": "0.3", "--eps_skip": "0.0", "--eps_equal": "0.0", "--teacher_gamma": "1.0"}
    assert got == expected
    config = reference_run.our_config(args, command)
    assert config["teacher_eps_mistake"] == 0.3 and config["rime_alpha"] == 0.5 and "num_envs" not in config
    assert report.setting_of(config)[:3] == ("reference-rime", "walker-walk", "mistake(eps_mistake=0.3)")
    for flags, error in (({"teacher": "stoc"}, "--teacher stoc: RIME's code has rational teachers only"),
                         ({"eval_every": 5000}, "--eval-every 5000: RIME's code has 10000 only"),
                         ({"rime_flip_eps": 0.01}, "--rime-flip-eps 0.01: RIME's code has 0.001 only"),
                         ({"ground_truth_reward": True}, "--ground-truth-reward: only with --algorithm pebble"),
                         ({"num_envs": 4}, "--num-envs is not a setting of rime")):
        assert reference_run.resolve(reference_run.Args(output_dir="x", algorithm="rime", **flags)).startswith(error)
    assert reference_run.resolve(reference_run.Args(output_dir="x", rime_alpha=1.0)) == "--rime-alpha is not a " \
                                                                                       "setting of pebble"


def test_rimes_results_are_read_back_from_its_own_layout(tmp_path):
    logs = tmp_path / "bpref" / "RIME" / "walker_walk"
    (logs / "test").mkdir(parents=True)
    (logs / "train").mkdir()
    (logs / "test" / "eval_RIME_mistake_0.3_seed_1.csv").write_text(
        "episode,step,episode_reward,true_episode_reward,true_episode_success\n10,10000,-3.0,150.5,0\n")
    (logs / "train" / "train_RIME_mistake_0.3_seed_1.csv").write_text("step,total_feedback\n10000,0\n11000,100\n")
    rows = reference_run.converted_rows(tmp_path / "bpref", [30.0])
    assert [(r["step"], r["episode_return"], r["feedback"], r["wall_time"]) for r in rows] == [(10000, 150.5, 100.0,
                                                                                             30.0)]


def test_prefppo_flags_become_the_reference_walker_script_flags(tmp_path):
    args = reference_run.Args(output_dir="x", algorithm="prefppo", seed=2, total_timesteps=1000000)
    assert reference_run.resolve(args) is None
    command = reference_run.prefppo_command(args, tmp_path)
    assert command[0] == "train_PrefPPO.py"
    got = dict(zip(command[1::2], command[2::2]))
    # BPref's scripts/walker_walk/1000/oracle/run_PrefPPO.sh, with our preset's 32000 steps between sessions
    script = {"--env": "walker_walk", "--lr": "5e-05", "--batch-size": "64", "--n-envs": "32", "--ent-coef": "0.0",
              "--n-steps": "500", "--num-layer": "3", "--hidden-dim": "256", "--clip-init": "0.4",
              "--gae-lambda": "0.92", "--re-feed-type": "1", "--re-num-interaction": "32000", "--teacher-beta": "-1",
              "--teacher-gamma": "1.0", "--teacher-eps-mistake": "0.0", "--teacher-eps-skip": "0.0",
              "--teacher-eps-equal": "0.0", "--re-segment": "50",
              "--unsuper-step": "32000", "--unsuper-n-epochs": "50", "--re-max-feed": "1000", "--re-batch": "100",
              "--total-timesteps": "1000000", "--seed": "2", "--use-sde": "1", "--sde-freq": "4", "--n-epochs": "20",
              "--re-update": "100", "--tensorboard-log": f"{tmp_path}/"}
    assert got == script
    for flags, error in (({"batch_size": 256}, "--batch-size is not a setting of prefppo"),
                         ({"schedule": "decay"}, "--schedule: the reference's PrefPPO has the uniform schedule only"),
                         ({"sampler": "coverage"}, "--sampler: the reference's PrefPPO has uniform, disagreement and "
                                                   "entropy sampling only"),
                         ({"ground_truth_reward": True}, "--ground-truth-reward: only with --algorithm pebble")):
        wrong = reference_run.Args(output_dir="x", algorithm="prefppo", **flags)
        assert reference_run.resolve(wrong).startswith(error)
    assert reference_run.resolve(reference_run.Args(output_dir="x", num_envs=8)) == "--num-envs is not a setting " \
                                                                                    "of pebble"
    config = reference_run.our_config(args, command)
    assert config["episode_returns"] == "training" and config["num_envs"] == 32 and "batch_size" not in config
    assert report.setting_of(config)[0] == "reference-prefppo"


def test_the_reference_prefppo_training_episodes_become_rows_per_wave(tmp_path):
    # two envs in lockstep, 1000-step episodes: waves at global steps 2000 and 4000; a short last episode of env 1
    for env, (returns, times, lengths) in enumerate(((( 10.0, 30.0), (5.0, 9.0), (1000, 1000)),
                                                     ((20.0, 50.0, 7.0), (5.5, 9.5, 12.0), (1000, 1000, 500)))):
        lines = ['#{"t_start": 0, "env_id": "dmc"}', "r,l,t"]
        lines += [f"{r},{length},{t}" for r, t, length in zip(returns, times, lengths)]
        (tmp_path / f"{env}.monitor.csv").write_text("\n".join(lines) + "\n")
    rows = reference_run.training_rows(tmp_path)
    assert [(r["step"], r["episode_return"], r["episode_return_std"], r["wall_time"]) for r in rows] == [
        (2000, 15.0, 5.0, 5.5), (4000, 40.0, 10.0, 9.5), (5000, 7.0, 0.0, 12.0)]


def test_the_reference_results_are_read_back_in_our_columns(tmp_path):
    bpref = reference_files(tmp_path, "episode,episode_reward,step,true_episode_reward\n"
                                      "10.0,-3.0,10000,150.5\n20.0,-1.0,20000,300.25\n",
                            "step,total_feedback,true_episode_reward\n10000,0.0,1\n11000,100.0,1\n"
                            "20000,100.0,1\n21000,200.0,1\n")
    rows = reference_run.converted_rows(bpref, [61.5])
    assert [(r["step"], r["episode_return"], r["feedback"]) for r in rows] == [(10000, 150.5, 100.0),
                                                                             (20000, 300.25, 200.0)]
    assert rows[0]["wall_time"] == 61.5 and math.isnan(rows[1]["wall_time"])  # the second evaluation: no time yet
    reference_run.write_eval(tmp_path, rows)
    with open(tmp_path / "eval.csv") as f:
        read = list(csv.DictReader(f))
    assert list(read[0]) == list(reference_run.EVAL_COLUMNS) and float(read[1]["episode_return"]) == 300.25


def test_the_reference_networks_load_into_our_classes_and_are_evaluated_as_ours(tmp_path):
    import pebble
    import torch

    torch.manual_seed(0)
    # the reference's modules as it saves them: actor.trunk, critic.Q1/Q2, reward members as bare Sequentials
    actor = torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.ReLU(), torch.nn.Linear(8, 2))
    torch.save({f"trunk.{key}": value for key, value in actor.state_dict().items()}, tmp_path / "actor_11.pt")
    critic = pebble.TwinCritic(3, 1, 8, 1)
    torch.save({key.replace("q1.", "Q1.").replace("q2.", "Q2."): value for key, value in critic.state_dict().items()},
               tmp_path / "critic_11.pt")
    reward = pebble.RewardEnsemble(3, 1, 2)
    for i, member in enumerate(reward.members):
        torch.save(member[0].state_dict(), tmp_path / f"reward_model_11_{i}.pt")
    model = reference_run.final_model(tmp_path, 11)
    ours = pebble.Actor(3, 1, 8, 1)
    ours.load_state_dict(model["actor"])
    loaded = reference_run.loaded_reward_model(model["reward_model"], 3, 1)  # 2 members, identity normaliser
    pebble.TwinCritic(3, 1, 8, 1).load_state_dict(model["critic"])
    x = torch.randn(5, 3)
    assert torch.equal(ours.net(x), actor(x))
    obs_action = torch.randn(5, 4)
    assert torch.equal(loaded(obs_action), reward(obs_action))
    torch.save(model, tmp_path / "final_model.pt")
    assert set(torch.load(tmp_path / "final_model.pt", weights_only=True)) == {"actor", "critic", "reward_model"}


def test_runner_without_the_reference_code_is_one_error_line(tmp_path):
    result = subprocess.run([sys.executable, str(RUNNER), "--output-dir", str(tmp_path / "out"), "--reference-dir",
                             str(tmp_path / "nothing")], capture_output=True, text=True, env=ENV)
    assert result.returncode == 2
    assert result.stderr.strip() == f"error: no reference code in {tmp_path / 'nothing'}: run " \
                                    "benchmarks/reference/setup.sh first"
    assert not (tmp_path / "out").exists()
    (tmp_path / "ref" / ".venv" / "bin").mkdir(parents=True)
    (tmp_path / "ref" / ".venv" / "bin" / "python").write_text("")
    (tmp_path / "ref" / "BPref").mkdir()
    (tmp_path / "ref" / "BPref" / "train_PEBBLE.py").write_text("")
    result = subprocess.run([sys.executable, str(RUNNER), "--algorithm", "rime", "--output-dir", str(tmp_path / "out"),
                             "--reference-dir", str(tmp_path / "ref")], capture_output=True, text=True, env=ENV)
    assert result.returncode == 2
    assert result.stderr.strip() == f"error: no RIME code in {tmp_path / 'ref'}: run " \
                                    "benchmarks/reference/setup_rime.sh first"


def dry_run(preset: str, root) -> tuple[list[list[str]], list[list[str]]]:
    """The command lines a grid preset's --dry-run prints: all of them, and the reference's."""
    result = subprocess.run([sys.executable, str(ROOT / "experiments/grid.py"), preset, "--root", str(root),
                             "--dry-run"], capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    lines = [shlex.split(line) for line in result.stdout.splitlines() if line.startswith("OMP_NUM_THREADS")]
    return lines, [line for line in lines if line[2] == str(RUNNER)]


def test_grid_runs_the_reference_with_the_same_flags_under_its_own_name(tmp_path):
    spec = grid.Grid(implementations=("ours", "reference"), teachers=("oracle",), budgets=("1000/100",), seeds=(1, 2),
                     flags="--total-timesteps 100000 --hidden-dim 256")
    runs = grid.expand(spec)
    ours = {r.name: r for r in runs if r.implementation == "ours"}
    reference = {r.name: r for r in runs if r.implementation == "reference"}
    assert len(ours) == len(reference) == 4  # 2 ground-truth + 2 oracle runs each
    assert {f"reference__{name}" for name in ours} == set(reference)
    for name, run in ours.items():
        assert reference[f"reference__{name}"].flags == run.flags
    command = reference["reference__pebble__walker-walk__oracle__fb1000-100__disagreement__uniform__s2"].command(
        tmp_path / "r", resume=True)
    assert command[0] == str(RUNNER) and command[-2:] == ["--output-dir", str(tmp_path / "r")]  # never --resume
    checkpoints = replace(spec, flags=spec.flags + " --checkpoint-every 10000")  # ours only: the reference has none
    run = next(r for r in grid.expand(checkpoints) if r.implementation == "reference")
    assert "--checkpoint-every" not in run.command(tmp_path / "r", resume=False)
    assert "10000" not in run.command(tmp_path / "r", resume=False)
    lines, printed = dry_run("parity-pebble", tmp_path / "g")
    assert len(printed) == 5 and len(lines) == 10
    assert printed[0][printed[0].index("--feedback-every") + 1] == "9000"
    refused = subprocess.run([sys.executable, str(ROOT / "experiments/grid.py"), "custom", "--implementations",
                              "reference", "--algorithms", "prefppo", "--root", str(tmp_path / "h")],
                             capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert refused.returncode == 2 and "runs PrefPPO, not PPO on the true reward" in refused.stderr
    lines, printed = dry_run("parity-prefppo", tmp_path / "p")
    assert len(printed) == 3 and len(lines) == 6
    assert all(line[3:5] == ["--algorithm", "prefppo"] for line in printed)
    assert printed[0][printed[0].index("--total-timesteps") + 1] == "1000000"
    refused = subprocess.run([sys.executable, str(ROOT / "experiments/grid.py"), "custom", "--implementations",
                              "reference", "--algorithms", "rime", "--root", str(tmp_path / "h")],
                             capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert refused.returncode == 2 and "runs RIME's code, not SAC on the true reward" in refused.stderr
    lines, printed = dry_run("rime-reference", tmp_path / "r")
    assert len(printed) == 5 == len(lines) and all(line[3:5] == ["--algorithm", "rime"] for line in printed)
    assert printed[0][printed[0].index("--teacher-eps-mistake") + 1] == "0.3"
    lines, printed = dry_run("parity-pebble-cheetah", tmp_path / "c")
    assert len(printed) == 3 and len(lines) == 6
    assert all(line[line.index("--env-id") + 1] == "cheetah-run" for line in printed)


def test_parity_script_runs_every_parity_preset_and_stops_before_the_report_on_a_dry_run(tmp_path):
    script = ROOT / "benchmarks" / "reference" / "parity.sh"
    result = subprocess.run([str(script), "--dry-run"], capture_output=True, text=True, cwd=tmp_path,
                            env=ENV | {"PARITY_ROOT": str(tmp_path / "runs"), "PYTHON": sys.executable})
    assert result.returncode == 0, result.stderr[-2000:]
    presets = [name for name in grid.PRESETS if name.startswith("parity-")]
    expected = [len(grid.expand(grid.PRESETS[name][1])) for name in presets]
    grids = [line for line in result.stdout.splitlines() if line.startswith("grid: ")]
    assert [int(line.split()[1]) for line in grids] == expected  # each preset once, in the grid's order
    assert all(f" in {tmp_path / 'runs'}:" in line for line in grids)
    assert result.stdout.count("# start: reference__") == sum(expected) // 2
    assert not (tmp_path / "runs" / "report").exists()


def write_run(root, name, seed, curve, implementation="ours", extra=None, steps=(10000, 20000), success=(0, 0)):
    path = root / name
    path.mkdir(parents=True)
    config = {"env_id": "walker-walk", "seed": seed, "teacher": "oracle", "sampler": "disagreement",
              "schedule": "uniform", "max_feedback": 1000, "feedback_per_session": 100, "ground_truth_reward": False,
              "total_timesteps": 20000, "implementation": implementation} | (extra or {})
    (path / "config.json").write_text(json.dumps(config))
    if implementation == "ours":
        steps = (steps[0], config["total_timesteps"])
    rows = [{"step": steps[i], "episode_return": value, "success_rate": success[i], "wall_time": 60.0 * (i + 1),
             "reward_correlation": 0.5 if implementation == "ours" else "nan"} for i, value in enumerate(curve)]
    with open(path / "eval.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, reference_run.EVAL_COLUMNS, restval="0")
        writer.writeheader()
        writer.writerows(rows)
    (path / "final_model.pt").write_bytes(b"")


def parity_report(root, target) -> None:
    """report.py ROOT --parity TARGET, as a user runs it; it must succeed."""
    result = subprocess.run([sys.executable, str(ROOT / "experiments/report.py"), str(root), "--reps", "200",
                             "--alignment-runs", "0", "--parity", str(target)], capture_output=True, text=True,
                            env=ENV, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]


def test_report_sets_both_implementations_side_by_side_with_a_verdict(tmp_path):
    root = tmp_path / "parity"
    for seed, final in enumerate([100, 110, 120], 1):
        write_run(root, f"ours_{seed}", seed, [50, final])
    for seed, final in enumerate([900, 910, 920], 1):
        write_run(root, f"ref_{seed}", seed, [60, final], implementation="reference")
    target = tmp_path / "docs" / "parity.md"
    target.parent.mkdir()
    parity_report(root, target)
    text = target.read_text()
    assert "**Verdict: lower: ours - reference = -800.0 (88% of the reference's mean), 95% CI [" in text
    assert "| ours | 1 2 3 | 110.0 ± 8.2 | 100 110 120 | 80.0 |" in text
    assert "| reference | 1 2 3 | 910.0 ± 8.2 | 900 910 920 | 485.0 |" in text
    with open(root / "report" / "parity.csv") as f:
        row = next(csv.DictReader(f))
    assert float(row["difference"]) == pytest.approx(-800) and float(row["difference_high"]) < 0
    assert float(row["ours_wall_minutes"]) == 2.0 and float(row["ours_reward_correlation"]) == 0.5
    assert row["reference_reward_correlation"] == "nan"
    figure = root / "report" / "parity_pebble_walker-walk_oracle_1000-100_disagreement_uniform.png"
    assert figure.read_bytes()[:4] == b"\x89PNG"
    assert "(../parity/report/parity_pebble_walker-walk" in text


def test_metaworld_parity_decides_by_success_rate_and_sets_the_returns_side_by_side_too(tmp_path):
    root = tmp_path / "parity"
    button = {"env_id": "button-press"}
    for seed, (final, rate) in enumerate([(4000, 1.0), (4100, 0.9), (4200, 1.0)], 1):
        write_run(root, f"ours_{seed}", seed, [50, final], extra=button, success=(0, rate))
    for seed, (final, rate) in enumerate([(900, 0.2), (1000, 0.0), (1100, 0.3)], 1):
        write_run(root, f"ref_{seed}", seed, [60, final], implementation="reference", extra=button, success=(0, rate))
    target = tmp_path / "parity.md"
    parity_report(root, target)
    text = target.read_text()
    setting = "## pebble on button-press, teacher oracle, budget 1000/100, disagreement, uniform"
    success, returns = text.index(f"{setting}: success rate\n"), text.index(f"{setting}: episode return\n")
    assert success < returns  # the paper's measure first
    by_success, by_return = text[success:returns], text[returns:]
    assert "**Verdict: higher: ours - reference = +0.80 (" in by_success
    assert "| ours | 1 2 3 | 0.97 ± 0.05 | 1.0 0.9 1.0 | 0.48 |" in by_success  # two decimals, per seed one
    assert "| reference | 1 2 3 | 0.17 ± 0.12 | 0.2 0.0 0.3 | 0.08 |" in by_success
    assert "**Verdict: higher: ours - reference = +3100.0 (" in by_return
    assert "| ours | 1 2 3 | 4100.0 ± 81.6 | 4000 4100 4200 | 2075.0 |" in by_return
    with open(root / "report" / "parity.csv") as f:
        assert [row["metric"] for row in csv.DictReader(f)] == ["success_rate", "episode_return"]
    for prefix in ("parity", "parity_return"):
        figure = root / "report" / f"{prefix}_pebble_button-press_oracle_1000-100_disagreement_uniform.png"
        assert figure.read_bytes()[:4] == b"\x89PNG"


def test_report_compares_two_algorithms_on_the_settings_both_ran(tmp_path):
    root = tmp_path / "rime"
    for seed, final in enumerate([700, 720, 740], 1):
        write_run(root, f"rime_{seed}", seed, [50, final], extra={"rime_alpha": 0.5})
        (root / f"rime_{seed}" / "labels").mkdir()
        for session in (1, 2):  # the last session's record is reported
            np.savez(root / f"rime_{seed}" / "labels" / f"session_000{session}.npz", step=9000 * session + 1,
                     trusted=800, flipped=90 * (session - 1) + seed, dropped=110, precision=0.6, recall=0.4)
    (root / "rime_3" / "labels" / "session_0002.npz").unlink()
    np.savez(root / "rime_3" / "labels" / "session_0002.npz", step=19001, trusted=185, flipped=3, dropped=12,
             precision=0.75, recall=0.5)
    kept = subprocess.run([sys.executable, str(ROOT / "experiments/keep_runs.py"), str(root / "rime_3"), "--to",
                           str(tmp_path / "kept")], capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert kept.returncode == 0, kept.stderr[-2000:]
    shutil.rmtree(root / "rime_3")  # kept without labels, as in docs/: its discriminator.csv is read
    shutil.move(tmp_path / "kept" / "rime_3", root / "rime_3")
    assert sorted(path.name for path in (root / "rime_3").iterdir()) == ["config.json", "discriminator.csv",
                                                                        "eval.csv"]
    assert (root / "rime_3" / "discriminator.csv").read_text().splitlines() == [
        "session,step,trusted,flipped,dropped,precision,recall", "0,9001,800.0,3.0,110.0,0.6,0.4",
        "1,19001,185.0,3.0,12.0,0.75,0.5"]
    refused = subprocess.run([sys.executable, str(ROOT / "experiments/keep_runs.py"), str(root / "rime_4"), "--to",
                              str(tmp_path / "kept")], capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert refused.returncode == 1 and refused.stderr == f"error: {root / 'rime_4'}: no config.json or eval.csv: " \
        "not a run folder\n"
    for seed, final in enumerate([100, 110, 120], 1):
        write_run(root, f"pebble_{seed}", seed, [60, final])
    write_run(root, "rime_oracle_1", 1, [50, 900], extra={"rime_alpha": 0.5, "max_feedback": 500})  # no twin
    result = subprocess.run([sys.executable, str(ROOT / "experiments/report.py"), str(root), "--reps", "200",
                             "--alignment-runs", "0", "--compare", "rime", "pebble"], capture_output=True, text=True,
                            env=ENV, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    text = (root / "report" / "compare_rime_pebble.md").read_text()
    assert text.count("## walker-walk, teacher oracle") == 1  # the setting without a pebble twin is left out
    assert "**Verdict: higher: rime - pebble = +610.0 (555% of pebble's mean), 95% CI [" in text
    assert "| rime | 1 2 3 | 720.0 ± 16.3 | 700 720 740 | 385.0 |" in text
    assert "| pebble | 1 2 3 | 110.0 ± 8.2 | 100 110 120 | 85.0 |" in text
    assert "| 2 | 800 | 92 | 110 | 0.60 | 0.40 |" in text
    assert "| 3 | 185 | 3 | 12 | 0.75 | 0.50 |" in text
    assert "compare: walker-walk / oracle / 1000/100 / disagreement / uniform: higher: rime - pebble" in result.stdout
    figure = root / "report" / "compare_rime_pebble_rime_walker-walk_oracle_1000-100_disagreement_uniform.png"
    assert figure.read_bytes()[:4] == b"\x89PNG"
    refused = subprocess.run([sys.executable, str(ROOT / "experiments/report.py"), str(root), "--compare", "rime",
                              "prefppo"], capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert refused.returncode != 0 and "--compare rime prefppo: no setting below" in refused.stderr


def test_report_compares_qpa_asking_uniformly_with_pebble_asking_by_disagreement(tmp_path):
    root = tmp_path / "qpa"
    for seed, final in enumerate([700, 720, 740], 1):
        write_run(root, f"qpa_{seed}", seed, [50, final], extra={"her_ratio": 0.5, "sampler": "uniform"})
        write_run(root, f"pebble_{seed}", seed, [60, [100, 110, 120][seed - 1]])
    write_run(root, "qpa_500_1", 1, [50, 900], extra={"her_ratio": 0.5, "sampler": "uniform", "max_feedback": 500})
    result = subprocess.run([sys.executable, str(ROOT / "experiments/report.py"), str(root), "--reps", "200",
                             "--alignment-runs", "0", "--compare", "qpa", "pebble"], capture_output=True, text=True,
                            env=ENV, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    text = (root / "report" / "compare_qpa_pebble.md").read_text()
    assert text.count("## walker-walk") == 1  # the budget without a pebble twin is left out
    assert "## walker-walk, teacher oracle, budget 1000/100, uniform (qpa) and disagreement (pebble), uniform" in text
    assert "| qpa | 1 2 3 | 720.0 ± 16.3 | 700 720 740 | 385.0 |" in text
    assert "| pebble | 1 2 3 | 110.0 ± 8.2 | 100 110 120 | 85.0 |" in text
    write_run(root, "pebble_uniform_1", 1, [60, 100], extra={"sampler": "entropy"})  # two other samplers: ambiguous
    result = subprocess.run([sys.executable, str(ROOT / "experiments/report.py"), str(root), "--reps", "200",
                             "--alignment-runs", "0", "--compare", "qpa", "pebble"], capture_output=True, text=True,
                            env=ENV, cwd=ROOT)
    assert result.returncode != 0 and "--compare qpa pebble: no setting below" in result.stderr


def test_report_sets_each_preference_setting_beside_its_algorithm_s_ground_truth_runs(tmp_path):
    root = tmp_path / "tasks"
    button = {"env_id": "button-press"}
    for seed, (final, rate) in enumerate([(900, 0.2), (1000, 0.0), (1100, 0.3)], 1):
        write_run(root, f"pebble_{seed}", seed, [60, final], extra=button, success=(0, rate))
    for seed, (final, rate) in enumerate([(4000, 1.0), (4100, 0.9), (4200, 1.0)], 1):
        write_run(root, f"sac_{seed}", seed, [50, final], extra=button | {"ground_truth_reward": True},
                  success=(0, rate))
    write_run(root, "rime_1", 1, [50, 300], extra=button | {"rime_alpha": 0.5})  # no rime.py run on the true reward
    write_run(root, "walker_1", 1, [50, 300])  # no run on the true reward on walker-walk
    command = [sys.executable, str(ROOT / "experiments/report.py"), str(root), "--reps", "200", "--alignment-runs",
               "0", "--against-ground-truth"]
    result = subprocess.run(command, capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    text = (root / "report" / "against_ground_truth.md").read_text()
    assert text.count("\n## ") == 2  # pebble on button-press only: by success rate, then by return
    setting = "## pebble on button-press, teacher oracle, budget 1000/100, disagreement, uniform"
    success, returns = text.index(f"{setting}: success rate\n"), text.index(f"{setting}: episode return\n")
    by_success, by_return = text[success:returns], text[returns:]
    assert "**Verdict: lower: preferences - true reward = -0.80 (83% of true reward's mean), 95% CI [" in by_success
    assert "| preferences | 1 2 3 | 0.17 ± 0.12 | 0.2 0.0 0.3 | 0.08 |" in by_success
    assert "| true reward | 1 2 3 | 0.97 ± 0.05 | 1.0 0.9 1.0 | 0.48 |" in by_success
    assert "**Verdict: lower: preferences - true reward = -3100.0 (" in by_return
    assert "against the true reward: pebble / button-press / oracle / 1000/100 / disagreement / uniform, " \
           "success_rate: lower" in result.stdout
    with open(root / "report" / "against_ground_truth.csv") as f:
        assert [row["metric"] for row in csv.DictReader(f)] == ["success_rate", "episode_return"]
    refused = subprocess.run([*command[:2], str(root / "rime_1"), *command[3:]], capture_output=True, text=True,
                             env=ENV, cwd=ROOT)
    assert refused.returncode == 2 and "--against-ground-truth: no preference setting below" in refused.stderr


def test_a_verdict_is_higher_lower_or_no_difference_detected_and_level_only_with_a_narrow_ci():
    ours, reference = np.array([500.0, 700.0, 600.0]), np.array([650.0, 550.0, 600.0])
    point, low, high = report.difference_ci(ours, reference, 4000, 0)
    assert point == 0 and low < 0 < high
    row = {"difference": (point, low, high), "reference_final_mean": 600.0, "welch_p": report.welch_p(ours, reference),
           "metric": "episode_return"}
    assert report.verdict(row).startswith("no difference detected: ours - reference = +0.0, 95% CI [")
    # a CI inside +-15% of the reference's mean (+-90 of 600) is level as well; one edge outside it is not
    narrow = row | {"difference": (-10.0, -90.0, +60.0)}
    assert report.verdict(narrow).startswith("no difference detected, level (the CI within ±15% of the reference's")
    assert "level" not in report.verdict(row | {"difference": (-10.0, -91.0, +60.0)})
    # -270 with a CI of [-563, +28]: wide, no difference detected, not level
    wide = {"difference": (-270.3, -563.4, 28.3), "reference_final_mean": 613.2, "welch_p": 0.236,
            "metric": "episode_return"}
    assert report.verdict(wide) == ("no difference detected: ours - reference = -270.3, 95% CI [-563.4, +28.3], "
                                    "Welch p = 0.236")
    higher = {"difference": (88.5, 45.7, 146.0), "reference_final_mean": 501.3, "welch_p": 0.021,
              "metric": "episode_return"}
    assert report.verdict(higher) == ("higher: ours - reference = +88.5 (18% of the reference's mean), 95% CI "
                                      "[+45.7, +146.0], Welch p = 0.021")
    assert report.verdict(higher, ("rime", "pebble")).startswith("higher: rime - pebble = +88.5 (18% of pebble's mean)")
    rate = {"difference": (0.267, 0.0, 0.8), "reference_final_mean": 0.733, "welch_p": 0.42, "metric": "success_rate"}
    assert report.verdict(rate) == ("no difference detected: ours - reference = +0.27, 95% CI [+0.00, +0.80], Welch p "
                                    "= 0.420")  # a success rate with two decimals
    # a bootstrap CI that excludes 0 beside a Welch p above 0.05 (three seeds a side): said in those words
    row = {"difference": (-176.7, -320.0, -26.7), "reference_final_mean": 783.3, "welch_p": 0.134,
           "metric": "episode_return"}
    assert report.verdict_word(row) == "lower by the CI, not by Welch's test"
    assert report.verdict(row).startswith("lower by the CI, not by Welch's test: ours - reference = -176.7")
    assert report.verdict(row).endswith("(Welch's p >= 0.05: more seeds needed)")
    assert report.verdict_word(row | {"difference": (176.7, 26.7, 320.0)}) == "higher by the CI, not by Welch's test"
    assert report.verdict_word(row | {"welch_p": 0.049}) == "lower"
    assert report.verdict_word(wide) == "no difference detected"
    assert report.verdict_word(narrow | {"welch_p": 0.5}) == "no difference detected, level"
    one_each = row | {"difference": (-50.0, -50.0, -50.0), "welch_p": report.welch_p(np.array([550.0]), np.array([600.0]))}
    assert report.verdict(one_each).endswith("(a single run on a side: no test; more seeds needed)")


def test_a_gap_too_small_for_each_setting_shows_when_the_settings_are_pooled():
    from types import SimpleNamespace

    def arm(scores):
        return [SimpleNamespace(score=score) for score in scores]

    reference = [900.0, 1000.0, 1100.0]
    ours = [810.0, 900.0, 990.0]  # 10% lower in every setting
    pairs = [(("pebble", task), arm(ours), arm(reference)) for task in ("a", "b", "c")]
    pairs.append((("prefppo", "a"), arm(ours), arm(reference)))  # one setting: nothing to pool
    [row] = report.pooled_differences(pairs, 4000, 0)
    assert row["algorithm"] == "pebble" and row["settings"] == 3
    assert row["relative_difference"] == pytest.approx(-0.1)
    assert row["low"] < -0.1 < row["high"] < 0
    alone = report.welch_p(np.array(ours), np.array(reference)) / 2  # one-sided, ours lower
    assert alone > 0.1 and row["p_lower"] < alone / 2 and row["p_higher"] == pytest.approx(1 - row["p_lower"])
    same = [(("pebble", task), arm(reference), arm(reference)) for task in ("a", "b")]
    [row] = report.pooled_differences(same, 4000, 0)
    assert row["relative_difference"] == 0 and row["low"] < 0 < row["high"] and row["p_lower"] == pytest.approx(0.5)


def test_paired_text_pairs_the_seeds_both_arms_ran():
    from types import SimpleNamespace

    def arm(scores):  # seed -> final score
        return [SimpleNamespace(score=score, config={"seed": seed}) for seed, score in scores.items()]

    new = arm({1: 10.0, 2: 5.0, 3: 9.0, 4: 100.0})  # seed 4: the base did not run it
    base = arm({3: 7.0, 1: 4.0, 2: 6.0})  # another order: pairs by seed, not by position
    # differences 6, -1, 2: mean 7/3, sample variance 37/3, t = (7/3) / sqrt((37/3) / 3) = 7 / sqrt(37), 2 dof
    t = 7 / np.sqrt(37)
    p = 2 * (1 - (0.5 + t / (2 * np.sqrt(2 + t * t))))  # Student's t with 2 dof: closed-form CDF
    assert report.paired_text(new, base) == f"2 of 3 (p = {p:.3f})"


def test_moving_normaliser_statistics_cover_every_observation_up_to_each_step():
    # 2 envs, episodes of 2 steps, 2 waves; one observation dimension: episode e holds [10 e, 10 e + 1]
    episodes = [(np.array([[10.0 * e], [10.0 * e + 1]]), None, None, e) for e in range(4)]
    mean, std = stale_inputs.running_stats(episodes, num_envs=2)
    assert mean.shape == std.shape == (2, 2, 1)
    seen = [[0, 10], [0, 10, 1, 11], [0, 10, 1, 11, 20, 30], [0, 10, 1, 11, 20, 30, 21, 31]]
    for i, values in enumerate(seen):  # in collection order: wave 0 step 0, step 1, wave 1 step 0, step 1
        assert mean[i // 2, i % 2, 0] == pytest.approx(np.mean(values))
        assert std[i // 2, i % 2, 0] == pytest.approx(np.std(values), rel=1e-6)
    assert stale_inputs.normalized(np.array([1000.0]), np.zeros(1), np.ones(1))[0] == 10  # clipped as VecNormalize


def test_compare_logs_sets_the_diagnostics_of_both_side_by_side(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    base = {"teacher": "oracle", "ground_truth_reward": False}
    for seed, alpha in ((1, 0.1), (2, 0.3)):  # ours: alpha 0.1 and 0.3 -> mean 0.2 in the first window
        run = tmp_path / f"ours{seed}"
        run.mkdir()
        (run / "config.json").write_text(json.dumps(base))
        writer = SummaryWriter(str(run))
        writer.add_scalar("losses/alpha", alpha, 1000)
        writer.add_scalar("losses/alpha", 9.0, 3000)
        writer.close()
    ref = tmp_path / "ref" / "bpref"
    ref.mkdir(parents=True)
    (ref.parent / "config.json").write_text(json.dumps(base | {"implementation": "reference"}))
    (ref / "train.csv").write_text("step,alpha_value,actor_entropy,batch_reward,critic_loss,true_episode_reward\n"
                                   "1000,0.05,1,2,3,4\n2000,0.07,1,2,3,4\n3000,0.5,1,2,3,4\n")
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks/reference/compare_logs.py"), str(tmp_path),
                             "--window", "2000"], capture_output=True, text=True, env=ENV)
    assert result.returncode == 0, result.stderr
    rows = [line.split(" | ") for line in result.stdout.splitlines() if line.startswith("| 1-2000")
            or line.startswith("| 2001-4000")]
    assert "runs: {'ours': 2, 'reference': 1}" in result.stdout
    header = next(line for line in result.stdout.splitlines() if line.startswith("| steps"))
    assert header.split(" | ")[1:3] == ["alpha (ours)", "alpha (reference)"]
    assert rows[0][1:3] == ["0.2", "0.06"] and rows[1][1:3] == ["9", "0.5"]


def test_compare_logs_sets_prefppo_returns_and_reward_correlations_side_by_side(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    for name, exp_name, correlation in (("ours", "prefppo", 0.7), ("pebble", "pebble", 0.1)):  # pebble: left out
        run = tmp_path / name
        run.mkdir()
        (run / "config.json").write_text(json.dumps({"teacher": "oracle", "exp_name": exp_name}))
        writer = SummaryWriter(str(run))
        writer.add_scalar("charts/episodic_return", 100.0, 32000)
        writer.add_scalar("reward/rollout_correlation", correlation, 48000)
        writer.add_scalar("reward/rollout_correlation", correlation + 0.1, 64000)
        writer.close()
    ref = tmp_path / "ref"
    ref.mkdir()
    (ref / "config.json").write_text(json.dumps({"teacher": "oracle", "implementation": "reference",
                                                 "episode_returns": "training"}))
    (ref / "eval.csv").write_text("step,episode_return\n32000,80\n64000,90\n")
    (ref / "rollouts.csv").write_text("step,correlation,learned_mean\n48000,0.6,0\n64000,0.65,0\n")
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks/reference/compare_logs.py"), str(tmp_path),
                             "--algorithm", "prefppo", "--window", "64000"], capture_output=True, text=True, env=ENV)
    assert result.returncode == 0, result.stderr
    assert "runs: {'ours': 1, 'reference': 1}" in result.stdout
    header = next(line for line in result.stdout.splitlines() if line.startswith("| steps"))
    assert header.rstrip(" |").split(" | ")[1:] == ["train_return (ours)", "train_return (reference)",
                                        "rollout_correlation (ours)", "rollout_correlation (reference)"]
    row = next(line for line in result.stdout.splitlines() if line.startswith("| 1-64000"))
    assert row.rstrip(" |").split(" | ")[1:] == ["100", "85", "0.75", "0.625"]


def test_reward_learning_check_splits_the_sessions_and_judges_a_perfect_reward_perfectly(tmp_path):
    import reward_learning

    rng = np.random.default_rng(0)
    (tmp_path / "labels").mkdir()
    for session in range(3):  # reward = first observation entry; the teacher prefers the larger return
        obs = rng.normal(size=(2, 4, 5, 3)).astype(np.float32)
        actions = rng.normal(size=(2, 4, 5, 1)).astype(np.float32)
        rewards = obs[..., 0]
        y = (rewards[1].sum(1) > rewards[0].sum(1)).astype(np.float64)
        np.savez(tmp_path / "labels" / f"session_{session:04d}.npz", obs0=obs[0], obs1=obs[1], actions0=actions[0],
                 actions1=actions[1], rewards0=rewards[0], rewards1=rewards[1], y=y, keep=np.ones(4, bool))
    data = reward_learning.labelled(str(tmp_path), 2)
    assert data["train0"].shape == (8, 5, 4) and data["later0"].shape == (4, 5, 4) and len(data["y"]) == 8
    assert reward_learning.judged(lambda x: x[:, 0], data) == pytest.approx((1.0, 1.0))
    assert reward_learning.judged(lambda x: -x[:, 0], data) == pytest.approx((-1.0, 0.0))
    result = reward_learning.ours(data, seed=0)
    assert 1 <= result["epochs"] <= 50 and -1 <= result["correlation"] <= 1


def test_prefppo_parity_compares_both_arms_on_training_episodes(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    root = tmp_path / "parity"
    prefppo = {"num_envs": 2, "num_steps": 500, "total_timesteps": 5000}
    for seed, (first, last) in enumerate(((10.0, 30.0), (20.0, 50.0)), 1):
        write_run(root, f"ours_{seed}", seed, [999.0, 999.0], extra=prefppo)  # evaluations: not compared
        if seed == 1:  # a process killed after step 4000: its run resumed from step 0, whose file replaces this one
            killed = SummaryWriter(str(root / "ours_1"), filename_suffix=".killed")
            killed.add_scalar("charts/episodic_return", 500.0, 4000)
            killed.close()
        writer = SummaryWriter(str(root / f"ours_{seed}"))
        for step, value in ((2000, first), (2000, first + 2), (4000, last), (4000, last + 2)):
            writer.add_scalar("charts/episodic_return", value, step)
        writer.close()
        # the reference's rows: a wave each (run.py's training_rows), the last one before the last step
        write_run(root, f"ref_{seed}", seed, [first + 1, last - 9], implementation="reference",
                  extra=prefppo | {"episode_returns": "training"}, steps=(2000, 4000))
    assert grid.run_state(root / "ref_1")[0] == "finished" and grid.run_state(root / "ours_1")[0] == "finished"
    # kept as in docs/: no final_model.pt (the reference's last wave, at 4000, is in its last rollout of 2 x 500
    # steps), and the files' mtimes from a checkout: the killed process's file is still the one replaced
    for final_model in root.glob("*/final_model.pt"):
        final_model.unlink()
    for killed in (root / "ours_1").glob("*.killed"):
        os.utime(killed, (4e9, 4e9))
    target = tmp_path / "parity.md"
    parity_report(root, target)
    text = target.read_text()
    assert "## prefppo on walker-walk" in text and "Measured on training episodes" in text
    assert "| ours | 1 2 | 41.0 ± 10.0 | 31 51 |" in text  # the waves' means at 4000: 31 and 51
    assert "| reference | 1 2 | 31.0 ± 10.0 | 21 41 |" in text
    assert "**Verdict: no difference detected: ours - reference = +10.0" in text


def test_report_loads_a_final_model_saved_before_the_input_normaliser_as_raw_inputs(tmp_path):
    import torch

    config = {"env_id": "Pendulum-v1", "hidden_dim": 8, "num_layers": 1, "reward_ensemble_size": 2, "seed": 1,
              "eval_episodes": 1}
    reward = pebble.RewardEnsemble(3, 1, 2)
    old = {key: value for key, value in reward.state_dict().items() if not key.startswith("input_")}
    torch.save({"actor": pebble.Actor(3, 1, 8, 1).state_dict(), "reward_model": old}, tmp_path / "final_model.pt")
    run = report.Run(tmp_path, config, [], "finished", "", ("pebble",), "episode_return")
    _, env, _, loaded, _ = report.load_final_model(run)
    env.close()
    x = torch.randn(4, 4) * 50
    assert loaded.input_clip.item() == math.inf and torch.equal(loaded(x), reward(x))


def fake_reference_prefppo(monkeypatch):
    """The three reference classes trace_prefppo wraps, as modules of their names: a rollout steps the env, then asks
    the reward model for r_hat of the step (the reference's order), and returns "collected"."""
    class VecNormalize:
        def __init__(self, rewards):
            self.rewards = iter(rewards)

        def step_wait(self):
            return None, next(self.rewards), None, None

    class RewardModel:
        def r_hat_batch(self, x):
            return 2 * x + 1  # a perfect reward up to scale: correlation 1

    class OnPolicyRewardAlgorithm:
        def collect_rollouts(self, env, n_rollout_steps):
            for _ in range(n_rollout_steps):
                _, rewards, _, _ = env.step_wait()
                self.reward_model.r_hat_batch(np.array(rewards))
                self.num_timesteps += len(rewards)
            return "collected"

    modules = {"reward_model": {"RewardModel": RewardModel}, "stable_baselines3": {}, "stable_baselines3.common": {},
               "stable_baselines3.common.on_policy_with_reward_algorithm":
                   {"OnPolicyRewardAlgorithm": OnPolicyRewardAlgorithm},
               "stable_baselines3.common.vec_env": {"VecNormalize": VecNormalize}}
    for name, members in modules.items():
        module = types.ModuleType(name)
        module.__dict__.update(members)
        monkeypatch.setitem(sys.modules, name, module)
    return VecNormalize, RewardModel, OnPolicyRewardAlgorithm


def test_the_reference_trace_records_each_rollouts_learned_and_true_rewards(tmp_path, monkeypatch):
    VecNormalize, RewardModel, OnPolicyRewardAlgorithm = fake_reference_prefppo(monkeypatch)
    trace = tmp_path / "rollouts.csv"
    trace_prefppo.install(str(trace))
    algorithm = OnPolicyRewardAlgorithm()
    algorithm.reward_model, algorithm.num_timesteps = RewardModel(), 0
    RewardModel().r_hat_batch(np.array([100.0, -100.0]))  # outside a rollout: not recorded
    env = VecNormalize([[1.0, 2.0], [3.0, 5.0], [0.0, 1.0], [4.0, 2.0]])
    assert algorithm.collect_rollouts(env, 2) == "collected"
    assert algorithm.collect_rollouts(env, 2) == "collected"
    rows = list(csv.DictReader(trace.open()))
    assert [int(row["step"]) for row in rows] == [4, 8]
    assert [float(row["correlation"]) for row in rows] == pytest.approx([1.0, 1.0])
    assert float(rows[0]["true_mean"]) == pytest.approx(2.75) and float(rows[1]["learned_mean"]) == pytest.approx(4.5)
    assert float(rows[0]["learned_std"]) == pytest.approx(2 * np.std([1, 2, 3, 5]))


def test_the_reference_trace_refuses_rewards_it_cannot_pair():
    row = trace_prefppo.rollout_row(10, [np.array([1.0, 0.0]), np.array([0.0, 1.0])], [[0.0, 1.0], [1.0, 0.0]])
    assert row["correlation"] == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="3 learned rewards against 2"):
        trace_prefppo.rollout_row(10, [np.zeros(3)], [np.zeros(2)])
