"""One run of the reference code (rll-research/BPref, set up by benchmarks/reference/setup.sh) from pebble.py's flags,
its results written as pebble.py writes them, so that experiments/grid.py and experiments/report.py treat both
implementations alike (docs/parity.md):

    python benchmarks/reference/run.py --env-id walker-walk --seed 3 --teacher oracle --max-feedback 1000 \\
        --feedback-per-session 100 --feedback-every 9000 --total-timesteps 100000 --hidden-dim 256 --num-layers 2 \\
        --batch-size 256 --output-dir runs/parity/reference__s3
    python benchmarks/reference/run.py ... --ground-truth-reward    # the reference's train_SAC.py
    python benchmarks/reference/run.py --algorithm prefppo --total-timesteps 1000000 ...   # its train_PrefPPO.py
    python benchmarks/reference/run.py --algorithm rime --teacher mistake --teacher-eps-mistake 0.3 ...  # RIME's code
    python benchmarks/reference/run.py --algorithm qpa --max-feedback 100 --feedback-per-session 10 ...  # QPA's code

The output directory gets config.json (pebble.py's fields, with "implementation": "reference" and the reference's
command line), bpref/ (the reference's own files), eval.csv in pebble.py's columns (wall_time from this wrapper's
clock at each evaluation line; the reference records no std: nan) and, at the end, final_model.pt (the
reference's actor, critic and reward models as pebble.py's state dicts) and, in the last row, the final reward
correlation measured by pebble.py's evaluate on those networks. A Meta-World task (button-press) runs its v2 class
(metaworld_button-press-v2) in the tree and environment of setup_metaworld.sh; eval.csv's success_rate is its
percentage / 100. The reference cannot resume: a run stopped part-way
is started afresh by the grid.

RIME (--algorithm rime, rime.py's flags): RIME's own code (CJReinforce/RIME_ICML2024, set up by setup_rime.sh), its
train_RIME.py with the flags of its walker runs (run_parallel.sh); it is written as the reference is, and its results
are read back the same way. Settings its code fixes (10 evaluation episodes every 10000 steps, segments of 50, 1000
seed steps, the uniform schedule, a rational teacher) are refused when asked otherwise.

QPA (--algorithm qpa, qpa.py's flags): QPA's own code (huxiao09/QPA, set up by setup_qpa.sh), its train_QPA.py with
the overrides of its walker_walk run (run_QPA.sh) and these flags; patch.py's edits make it write eval.csv in the
reference's columns and print each evaluation. Its code asks uniformly from the pool (explore=false), with the uniform
schedule, and learns rewards by iterations on DMC: other settings are refused.

PrefPPO (--algorithm prefppo, prefppo.py's flags): the reference evaluates no policy and saves none, so its eval.csv
rows are the true returns of its stochastic training episodes, from its Monitor files: one row per wave of episodes
(its envs step in lockstep, so with fixed-length episodes every env ends one at the same step), mean and std over the
wave, wall time from the Monitor's clock; config.json says "episode_returns": "training", and experiments/report.py
then compares prefppo.py's training episodes (charts/episodic_return) in the same way. final_model.pt holds its
reward models only. It runs through trace_prefppo.py, which adds rollouts.csv: the correlation of the reference's
learned reward with the true one over each rollout (prefppo.py's reward/rollout_correlation).
"""

import csv
import importlib
import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Literal

import numpy as np
import tyro

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT))

from sim_teacher import make_teacher, save_file  # noqa: E402

FEED_TYPES = {"uniform": 0, "disagreement": 1, "entropy": 2, "coverage": 3, "disagreement-coverage": 4,
              "entropy-coverage": 5}  # the reference's feed_type
REWARD_SCHEDULES = {"uniform": (0, 1.0), "decay": (1, 2.0), "increase": (2, 0.5)}
"""schedule -> (the reference's reward_schedule, the factor its walker scripts apply to the per-session count)"""
PEBBLE_ONLY = ("seed_steps", "batch_size")  # and rime, qpa
RIME_ONLY = ("rime_alpha", "rime_beta_max", "rime_beta_min", "rime_decay_epochs", "rime_flip_eps", "rime_min_epochs",
             "rime_warm_updates")
RIME_FIXED = {"eval_every": 10000, "eval_episodes": 10, "segment_len": 50, "seed_steps": 1000, "schedule": "uniform",
              "rime_decay_epochs": 60, "rime_flip_eps": 0.001, "rime_warm_updates": 5}
"""what RIME's train_RIME.py fixes for DMC tasks (its config and k=60, tau=0.001, 5 warm-start updates per step)"""
QPA_ONLY = ("her_ratio", "data_aug_ratio", "reward_updates", "query_recent_episodes", "reward_ensemble_size")
QPA_FIXED = {"sampler": "uniform", "schedule": "uniform"}
"""what train_QPA.py fixes: uniform sampling from its episode store (explore=false), the uniform schedule"""
TEACHER_FIELDS = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal")
PREFPPO_ONLY = ("num_envs", "num_steps", "minibatch_size", "gae_lambda", "update_epochs", "unsup_update_epochs",
                "clip_coef", "ent_coef", "use_sde", "sde_freq")


@dataclass
class Args:
    """pebble.py's flags that the reference has a setting for (same names; None = pebble.py's preset of the task);
    anything else is refused."""

    output_dir: str
    """where the run's files go (must be empty or absent)"""
    algorithm: Literal["pebble", "prefppo", "rime", "qpa"] = "pebble"
    """pebble: train_PEBBLE.py (train_SAC.py with --ground-truth-reward); prefppo: train_PrefPPO.py; rime: RIME's
    train_RIME.py; qpa: QPA's train_QPA.py"""
    env_id: str = "walker-walk"
    """a DMC task, domain-task (the reference's Meta-World needs MuJoCo 2.0)"""
    seed: int = 1
    """the reference's seed"""
    teacher: Literal["oracle", "stoc", "mistake", "skip", "equal", "myopic"] = "oracle"
    """simulated teacher: the reference's teacher_* settings of that name"""
    teacher_beta: float | None = None
    """override the teacher's beta (None: the named teacher's)"""
    teacher_gamma: float | None = None
    """override the teacher's gamma"""
    teacher_eps_mistake: float | None = None
    """override the teacher's eps_mistake"""
    teacher_eps_skip: float | None = None
    """override the teacher's eps_skip"""
    teacher_eps_equal: float | None = None
    """override the teacher's eps_equal"""
    sampler: Literal[
        "uniform", "disagreement", "entropy", "coverage", "disagreement-coverage", "entropy-coverage"
    ] | None = None
    """query selection (feed_type; None: the script's, qpa.py's uniform, the others' disagreement)"""
    schedule: Literal["uniform", "decay", "increase"] = "uniform"
    """feedback schedule (reward_schedule; per-session count x2 / x0.5 as the reference's walker scripts)"""
    max_feedback: int | None = None
    """total number of queries"""
    feedback_per_session: int | None = None
    """queries per session (reward_batch)"""
    feedback_every: int | None = None
    """steps between sessions (num_interact)"""
    segment_len: int | None = None
    """segment length (segment)"""
    total_timesteps: int | None = None
    """environment steps (num_train_steps = this + 1, so that the last evaluation happens)"""
    seed_steps: int | None = None
    """PEBBLE: random-action steps (num_seed_steps)"""
    unsup_steps: int | None = None
    """unsupervised pre-training steps (num_unsup_steps; PrefPPO: --unsuper-step)"""
    hidden_dim: int | None = None
    """actor and critic width"""
    num_layers: int | None = None
    """actor and critic depth (hidden_depth; PrefPPO: --num-layer)"""
    batch_size: int | None = None
    """PEBBLE: SAC batch"""
    learning_rate: float | None = None
    """actor and critic learning rate (PrefPPO: --lr)"""
    num_envs: int | None = None
    """PrefPPO: parallel environments (--n-envs)"""
    num_steps: int | None = None
    """PrefPPO: steps per environment per rollout (--n-steps)"""
    minibatch_size: int | None = None
    """PrefPPO: PPO minibatch (--batch-size)"""
    gae_lambda: float | None = None
    """PrefPPO: GAE lambda (--gae-lambda)"""
    update_epochs: int | None = None
    """PrefPPO: PPO epochs per rollout (--n-epochs)"""
    unsup_update_epochs: int | None = None
    """PrefPPO: PPO epochs per rollout in pre-training (--unsuper-n-epochs)"""
    clip_coef: float | None = None
    """PrefPPO: initial clip range, decayed linearly (--clip-init)"""
    ent_coef: float | None = None
    """PrefPPO: entropy coefficient (--ent-coef)"""
    use_sde: bool | None = None
    """PrefPPO: gSDE exploration (--use-sde)"""
    sde_freq: int | None = None
    """PrefPPO: steps between gSDE noise draws (--sde-freq)"""
    rime_alpha: float | None = None
    """RIME: alpha of the lower bound (--threshold_alpha)"""
    rime_beta_max: float | None = None
    """RIME: beta at the first epoch (--threshold_beta_init)"""
    rime_beta_min: float | None = None
    """RIME: beta's floor (--threshold_beta_min)"""
    rime_decay_epochs: int | None = None
    """RIME: epochs of beta's decay (fixed: 60)"""
    rime_flip_eps: float | None = None
    """RIME: the upper bound's epsilon (fixed: 0.001)"""
    rime_min_epochs: int | None = None
    """RIME: epochs before the early stop (--least_reward_update)"""
    rime_warm_updates: int | None = None
    """RIME: warm-start updates per pre-training step (fixed: 5)"""
    reward_epochs: int | None = None
    """most reward epochs per session (reward_update)"""
    her_ratio: float | None = None
    """QPA: share of the batch from the recent episodes (her_ratio)"""
    data_aug_ratio: int | None = None
    """QPA: crops per labelled pair (data_aug_ratio)"""
    reward_updates: int | None = None
    """QPA: reward-learning steps per label per batch (reward_update on DMC)"""
    query_recent_episodes: int | None = None
    """QPA: episodes of the query pool (max_reward_buffer_size)"""
    reward_ensemble_size: int | None = None
    """QPA: reward models (ensemble_size)"""
    eval_every: int = 10000
    """steps between evaluations (eval_frequency)"""
    eval_episodes: int = 10
    """episodes per evaluation"""
    ground_truth_reward: bool = False
    """run the reference's train_SAC.py (SAC on the true reward, same pre-training and critic reset)"""
    cuda: bool = False
    """run the reference on the GPU (device=cuda)"""
    reference_dir: str = str(ROOT / "reference")
    """where setup.sh put BPref/ and .venv/"""


def resolve(args: Args) -> str | None:
    """Every field left None from the algorithm's preset for the task and its script's defaults, as pebble.py and
    prefppo.py resolve them; the first flag the algorithm has no setting for, as an error line, or None."""
    module = importlib.import_module(args.algorithm)
    other = not_settings(args.algorithm)
    if given := [name for name in other if getattr(args, name) is not None]:
        return f"--{given[0].replace('_', '-')} is not a setting of {args.algorithm}"
    if args.algorithm == "prefppo" and args.ground_truth_reward:
        return "--ground-truth-reward: only with --algorithm pebble (the reference's train_SAC.py)"
    if args.algorithm == "prefppo" and args.schedule != "uniform":
        return "--schedule: the reference's PrefPPO has the uniform schedule only"
    if args.algorithm in ("rime", "qpa") and args.ground_truth_reward:
        return "--ground-truth-reward: only with --algorithm pebble (the reference's train_SAC.py)"
    defaults = module.task_defaults(args.env_id, args.teacher)  # the script's values for the task
    for field in fields(Args):
        if getattr(args, field.name) is None and field.name not in other and not field.name.startswith("teacher_"):
            setattr(args, field.name, getattr(defaults, field.name))
    if args.algorithm == "prefppo" and args.sampler not in ("uniform", "disagreement", "entropy"):
        return "--sampler: the reference's PrefPPO has uniform, disagreement and entropy sampling only"
    if args.algorithm == "rime" and math.isfinite(teacher_of(args).beta):
        return f"--teacher {args.teacher}: RIME's code has rational teachers only (beta = inf)"
    for name, value in RIME_FIXED.items() if args.algorithm == "rime" else ():
        if getattr(args, name) != value:
            return f"--{name.replace('_', '-')} {getattr(args, name)}: RIME's code has {value} only"
    for name, value in QPA_FIXED.items() if args.algorithm == "qpa" else ():
        if getattr(args, name) != value:
            return f"--{name.replace('_', '-')} {getattr(args, name)}: QPA's code has {value} only"
    if args.algorithm == "qpa" and not (args.reward_updates and args.query_recent_episodes):
        return "--reward-updates and --query-recent-episodes: QPA's code needs both >= 1 on DMC"
    if args.algorithm != "prefppo" and args.total_timesteps < args.eval_every:
        return (f"--total-timesteps {args.total_timesteps}: the reference evaluates every --eval-every "
                f"{args.eval_every} steps only, so a run this short has no evaluation")
    return None


def not_settings(algorithm: str) -> tuple[str, ...]:
    """Args fields that are no setting of this algorithm."""
    return {"pebble": PREFPPO_ONLY + RIME_ONLY + QPA_ONLY, "prefppo": PEBBLE_ONLY + RIME_ONLY + QPA_ONLY,
            "rime": PREFPPO_ONLY + QPA_ONLY, "qpa": PREFPPO_ONLY + RIME_ONLY}[algorithm]


def teacher_of(args: Args):
    """The named simulated teacher with the flags' overrides (the --teacher-* fields; None = the teacher's own)."""
    overrides = {name: getattr(args, f"teacher_{name}") for name in TEACHER_FIELDS}
    return make_teacher(args.teacher, **{name: value for name, value in overrides.items() if value is not None})


def rime_command(args: Args) -> list[str]:
    """RIME's train_RIME.py and its flags for rime.py's (its walker runs' flags in run_parallel.sh)."""
    domain, task = args.env_id.split("-", 1)
    teacher = teacher_of(args)
    flags = {"--env": f"{domain}_{task.replace('-', '_')}", "--seed": args.seed,
             "--device": "cuda" if args.cuda else "cpu", "--steps": args.total_timesteps + 1,
             "--unsup_steps": args.unsup_steps, "--num_interact": args.feedback_every,
             "--max_feedback": args.max_feedback, "--reward_batch": args.feedback_per_session,
             "--reward_update": args.reward_epochs, "--feed_type": FEED_TYPES[args.sampler],
             "--actor_lr": args.learning_rate, "--critic_lr": args.learning_rate, "--batch_size": args.batch_size,
             "--actor_hidden_dim": args.hidden_dim, "--critic_hidden_dim": args.hidden_dim,
             "--actor_hidden_depth": args.num_layers, "--critic_hidden_depth": args.num_layers,
             "--least_reward_update": args.rime_min_epochs, "--threshold_variance": "kl",
             "--threshold_alpha": args.rime_alpha, "--threshold_beta_init": args.rime_beta_max,
             "--threshold_beta_min": args.rime_beta_min, "--eps_mistake": teacher.eps_mistake,
             "--eps_skip": teacher.eps_skip, "--eps_equal": teacher.eps_equal, "--teacher_gamma": teacher.gamma}
    return ["train_RIME.py", *[f"{flag}={value}" for flag, value in flags.items()]]


def qpa_command(args: Args) -> list[str]:
    """train_QPA.py and its hydra overrides for qpa.py's flags (its walker_walk run in run_QPA.sh: tanh rewards,
    explore=false, one gradient update a step)."""
    teacher = teacher_of(args)
    overrides = {"env": reference_env(args.env_id), "seed": args.seed, "device": "cuda" if args.cuda else "cpu",
                 "num_train_steps": args.total_timesteps + 1, "num_seed_steps": args.seed_steps,
                 "num_unsup_steps": args.unsup_steps, "agent.params.actor_lr": args.learning_rate,
                 "agent.params.critic_lr": args.learning_rate, "agent.params.batch_size": args.batch_size,
                 **{f"{net}.params.{key}": value for net in ("diag_gaussian_actor", "double_q_critic")
                    for key, value in (("hidden_dim", args.hidden_dim), ("hidden_depth", args.num_layers))},
                 "eval_frequency": args.eval_every, "num_eval_episodes": args.eval_episodes,
                 "num_interact": args.feedback_every, "max_feedback": args.max_feedback,
                 "reward_batch": args.feedback_per_session, "reward_update": args.reward_updates,
                 "segment": args.segment_len, "gradient_update": 1, "activation": "tanh",
                 "teacher_beta": -1 if math.isinf(teacher.beta) else teacher.beta, "teacher_gamma": teacher.gamma,
                 "teacher_eps_mistake": teacher.eps_mistake, "teacher_eps_skip": teacher.eps_skip,
                 "teacher_eps_equal": teacher.eps_equal, "max_reward_buffer_size": args.query_recent_episodes,
                 "data_aug_ratio": args.data_aug_ratio, "ensemble_size": args.reward_ensemble_size,
                 "explore": "false", "her_ratio": args.her_ratio, "wandb": "false"}
    return ["train_QPA.py", *[f"{key}={value}" for key, value in overrides.items()]]


def prefppo_command(args: Args, log_dir: Path) -> list[str]:
    """train_PrefPPO.py and its flags for prefppo.py's (its walker script's flags: run_PrefPPO.sh)."""
    domain, task = args.env_id.split("-", 1)
    teacher = teacher_of(args)
    flags = {"--env": f"{domain}_{task.replace('-', '_')}", "--seed": args.seed, "--tensorboard-log": f"{log_dir}/",
             "--n-envs": args.num_envs, "--n-steps": args.num_steps, "--lr": args.learning_rate,
             "--total-timesteps": args.total_timesteps, "--batch-size": args.minibatch_size,
             "--ent-coef": args.ent_coef, "--hidden-dim": args.hidden_dim, "--num-layer": args.num_layers,
             "--use-sde": int(args.use_sde), "--sde-freq": args.sde_freq, "--gae-lambda": args.gae_lambda,
             "--clip-init": args.clip_coef, "--n-epochs": args.update_epochs, "--unsuper-step": args.unsup_steps,
             "--unsuper-n-epochs": args.unsup_update_epochs, "--re-segment": args.segment_len,
             "--re-num-interaction": args.feedback_every, "--re-batch": args.feedback_per_session,
             "--re-update": args.reward_epochs, "--re-feed-type": FEED_TYPES[args.sampler],
             "--re-max-feed": args.max_feedback, "--teacher-beta": -1 if math.isinf(teacher.beta) else teacher.beta,
             "--teacher-gamma": teacher.gamma, "--teacher-eps-mistake": teacher.eps_mistake,
             "--teacher-eps-skip": teacher.eps_skip, "--teacher-eps-equal": teacher.eps_equal}
    return ["train_PrefPPO.py", *[str(item) for flag, value in flags.items() for item in (flag, value)]]


def reference_env(env_id: str) -> str:
    """The reference's name of a task: walker_walk (DMC), metaworld_button-press-v2 (its Meta-World v2 class for our
    v3 task)."""
    if is_metaworld(env_id):
        return f"metaworld_{env_id.removesuffix('-v3')}-v2"
    domain, task = env_id.split("-", 1)
    return f"{domain}_{task.replace('-', '_')}"


def is_metaworld(env_id: str) -> bool:
    import pebble

    return pebble.env_kind(env_id) == "metaworld"


def reference_command(args: Args) -> list[str]:
    """The reference's script and hydra overrides for these flags."""
    common = [f"env={reference_env(args.env_id)}", f"seed={args.seed}", f"device={'cuda' if args.cuda else 'cpu'}",
              "log_save_tb=false", f"num_train_steps={args.total_timesteps + 1}",
              f"num_seed_steps={args.seed_steps}", f"num_unsup_steps={args.unsup_steps}",
              f"agent.params.actor_lr={args.learning_rate}", f"agent.params.critic_lr={args.learning_rate}",
              f"agent.params.batch_size={args.batch_size}",
              *[f"{net}.params.{key}={value}" for net in ("diag_gaussian_actor", "double_q_critic")
                for key, value in (("hidden_dim", args.hidden_dim), ("hidden_depth", args.num_layers))],
              f"eval_frequency={args.eval_every}", f"num_eval_episodes={args.eval_episodes}"]
    if args.ground_truth_reward:
        return ["train_SAC.py", *common]
    teacher = teacher_of(args)
    schedule, factor = REWARD_SCHEDULES[args.schedule]
    return ["train_PEBBLE.py", *common, f"num_interact={args.feedback_every}", f"max_feedback={args.max_feedback}",
            f"reward_batch={int(args.feedback_per_session * factor)}", f"reward_schedule={schedule}",
            f"reward_update={args.reward_epochs}", f"feed_type={FEED_TYPES[args.sampler]}", f"segment={args.segment_len}",
            f"teacher_beta={-1 if math.isinf(teacher.beta) else teacher.beta}", f"teacher_gamma={teacher.gamma}",
            f"teacher_eps_mistake={teacher.eps_mistake}", f"teacher_eps_skip={teacher.eps_skip}",
            f"teacher_eps_equal={teacher.eps_equal}"]


def our_config(args: Args, command: list[str]) -> dict:
    """config.json as pebble.py (prefppo.py) would write it for these flags, marked as the reference's run."""
    other = not_settings(args.algorithm)
    config = {key: value for key, value in asdict(args).items() if key not in ("reference_dir", "algorithm", *other)}
    if args.algorithm == "prefppo":
        config["episode_returns"] = "training"
    teacher = teacher_of(args)
    config |= {f"teacher_{name}": getattr(teacher, name) for name in TEACHER_FIELDS}
    return config | {"implementation": "reference", "reference_command": command}


def converted_rows(bpref_dir: Path, wall_times: list[float]) -> list[dict]:
    """The reference's eval.csv in pebble.py's eval.csv columns; the i-th evaluation gets wall_times[i] (nan where
    unknown)."""
    def read(name):  # RIME's code: RIME/<env>/test/eval_*.csv and RIME/<env>/train/train_*.csv
        path = bpref_dir / name
        if not path.exists():
            path = next(bpref_dir.glob(f"RIME/*/{'test' if name == 'eval.csv' else 'train'}/*.csv"), path)
        try:
            with open(path) as f:
                return list(csv.DictReader(f))
        except OSError:
            return []

    # train.csv's total_feedback at step S is what was asked before the episode that ended at S began: the labels
    # at an evaluation are on the first train row after it (the last row for the final evaluation)
    # (rows of episode 0 are its logger's empty dumps, all zeros: at the end of a Meta-World run)
    feedback = [(int(float(row["step"])), float(row.get("total_feedback") or 0)) for row in read("train.csv")
                if float(row.get("episode") or 1) > 0]
    rows = []
    for i, row in enumerate(read("eval.csv")):
        step = int(float(row["step"]))
        later = [value for at, value in feedback if at > step] or [value for _, value in feedback[-1:]] or [0.0]
        returns = row.get("true_episode_reward") or row["episode_reward"]
        success = float(row["success_rate"]) / 100 if row.get("success_rate") else math.nan  # Meta-World: percent
        asked = float(row["total_feedback"]) if row.get("total_feedback") else later[0]  # QPA's (patch.py)
        rows.append({"step": step, "episode_return": float(returns), "episode_return_std": math.nan,
                     "success_rate": success, "feedback": asked,
                     "reward_correlation": math.nan, "wall_time": wall_times[i] if i < len(wall_times) else math.nan})
    return rows


def training_rows(log_dir: Path) -> list[dict]:
    """PrefPPO: the true returns of the reference's training episodes (its Monitor files, one per env) in pebble.py's
    eval.csv columns, one row per step at which episodes ended: the envs step in lockstep, so an episode of env i
    that ends after its n-th step ends at global step n x envs. wall_time: the Monitor's clock (seconds since the
    envs were made)."""
    waves = {}
    monitors = sorted(log_dir.glob("*.monitor.csv"))
    for monitor in monitors:
        with open(monitor) as f:
            episodes = list(csv.DictReader(line for line in f if not line.startswith("#")))
        steps = 0
        for episode in episodes:
            steps += int(episode["l"])
            waves.setdefault(steps * len(monitors), []).append((float(episode["r"]), float(episode["t"])))
    return [{"step": step, "episode_return": float(np.mean([r for r, _ in wave])),
             "episode_return_std": float(np.std([r for r, _ in wave])), "success_rate": math.nan,
             "feedback": math.nan, "reward_correlation": math.nan,
             "wall_time": round(max(t for _, t in wave), 1)}
            for step, wave in sorted(waves.items())]


def write_eval(out: Path, rows: list[dict]):
    """eval.csv as pebble.py writes it (its columns, written whole and atomically)."""
    save_file(str(out / "eval.csv"), eval_csv(rows))


EVAL_COLUMNS = ("step", "episode_return", "episode_return_std", "success_rate", "reward_correlation", "feedback",
                "wall_time")  # pebble.py's eval.csv


def eval_csv(rows: list[dict]) -> bytes:
    lines = [EVAL_COLUMNS] + [[row[column] for column in EVAL_COLUMNS] for row in rows]
    return "".join(",".join(map(str, line)) + "\n" for line in lines).encode()


def final_model(bpref_dir: Path, step: int) -> dict:
    """The reference's saved networks at its last step as pebble.py's final_model.pt: the same architectures, so
    only the keys are renamed (its actor's trunk is our net, Q1/Q2 our q1/q2, reward member i our members.i.0)."""
    import torch

    def load(name):
        return torch.load(bpref_dir / name, map_location="cpu", weights_only=True)

    model = {"actor": {key.replace("trunk.", "net.", 1): value for key, value in load(f"actor_{step}.pt").items()},
             "critic": {key.replace("Q1.", "q1.", 1).replace("Q2.", "q2.", 1): value
                        for key, value in load(f"critic_{step}.pt").items()}}
    members = sorted(bpref_dir.glob(f"reward_model_{step}_*.pt"))
    if members:
        model["reward_model"] = raw_inputs({f"members.{i}.0.{key}": value for i, path in enumerate(members)
                                            for key, value in load(path.name).items()})
    return model


def raw_inputs(reward_model: dict) -> dict:
    """The reward ensemble's state with the identity as its input normaliser (our RewardEnsemble's buffers before
    the first session; the reference's networks take their inputs as they come)."""
    import torch

    in_dim = reward_model["members.0.0.0.weight"].shape[1]
    return reward_model | {"input_mean": torch.zeros(in_dim), "input_std": torch.ones(in_dim),
                           "input_clip": torch.tensor(math.inf)}


def prefppo_reward_model(log_dir: Path, total_timesteps: int) -> dict:
    """The reference PrefPPO's final reward models (all it saves) as prefppo.py's final_model.pt key "reward_model"
    (its inputs were VecNormalize'd observations, whose statistics it does not save: kept for the record)."""
    import torch

    members = sorted(log_dir.glob(f"reward_model_{total_timesteps}_*.pt"))
    return {"reward_model": raw_inputs({f"members.{i}.0.{key}": value for i, path in enumerate(members)
                                        for key, value in torch.load(path, map_location="cpu",
                                                                     weights_only=True).items()})}


def loaded_reward_model(state: dict, obs_dim: int, action_dim: int):
    """Our RewardEnsemble holding this state (as many members as it has; its input normaliser's buffers too)."""
    import pebble

    size = len({key.split(".")[1] for key in state if key.startswith("members.")})
    reward_model = pebble.RewardEnsemble(obs_dim, action_dim, size)
    reward_model.load_state_dict(state)
    return reward_model


def final_reward_correlation(model: dict, args: Args) -> float:
    """The Pearson correlation of the reference's final learned reward with the true one along --eval-episodes
    episodes of its final actor's mean action, measured by pebble.py's evaluate (the episodes of ours' first
    evaluation seeds), so that both implementations' correlations are the same measure."""
    import pebble
    import torch

    env, _ = pebble.make_env(args.env_id)
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    actor = pebble.Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers)
    actor.load_state_dict(model["actor"])
    reward_model = loaded_reward_model(model["reward_model"], obs_dim, action_dim)
    seeds = [pebble.episode_seed(args.seed, pebble.EVAL_STREAM, j) for j in range(args.eval_episodes)]
    policy = pebble.mean_policy(actor, torch.device("cpu"))
    return pebble.evaluate(policy, reward_model, env, seeds, torch.device("cpu"))["reward_correlation"]


def main(args: Args) -> int:
    if error := resolve(args):
        print(f"error: {error}", file=sys.stderr)
        return 2
    out, reference = Path(args.output_dir), Path(args.reference_dir)
    python, tree = reference / ".venv" / "bin" / "python", reference / "BPref"
    metaworld = is_metaworld(args.env_id)
    if metaworld:  # its Meta-World v2 on mujoco-py: a tree and an environment of their own
        python, tree = reference / ".venv-metaworld" / "bin" / "python", reference / "BPref-metaworld"
    if not (python.exists() and (tree / "train_PEBBLE.py").exists()):
        setup = "setup_metaworld.sh" if metaworld else "setup.sh"
        print(f"error: no reference code in {reference}: run benchmarks/reference/{setup} first", file=sys.stderr)
        return 2
    if args.algorithm == "rime":
        tree = reference / "RIME"
        if not (tree / "train_RIME.py").exists():
            print(f"error: no RIME code in {reference}: run benchmarks/reference/setup_rime.sh first",
                  file=sys.stderr)
            return 2
    if args.algorithm == "qpa":
        tree = reference / "QPA"
        if not (tree / "train_QPA.py").exists():
            print(f"error: no QPA code in {reference}: run benchmarks/reference/setup_qpa.sh first", file=sys.stderr)
            return 2
    with warnings.catch_warnings(action="ignore"):  # GLFW's "failed to open display" on a headless machine
        from dm_control import suite
    if metaworld and args.algorithm != "pebble":
        print(f"error: --env-id {args.env_id!r}: Meta-World runs with --algorithm pebble only here", file=sys.stderr)
        return 2
    if tuple(args.env_id.split("-", 1)) not in suite.ALL_TASKS and not metaworld:
        print(f"error: --env-id {args.env_id!r}: the reference runs DMC and Meta-World tasks only here",
              file=sys.stderr)
        return 2
    if out.exists() and any(out.iterdir()):
        print(f"error: --output-dir {out} is not empty (the reference cannot resume)", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    bpref = (out / "bpref").resolve()
    if args.algorithm == "prefppo":
        command = prefppo_command(args, bpref)
    elif args.algorithm == "rime":  # it writes under its working directory: RIME/<env>/
        command = rime_command(args)
        bpref.mkdir()
    elif args.algorithm == "qpa":
        command = qpa_command(args) + [f"hydra.run.dir={bpref}"]
    else:
        command = reference_command(args) + [f"hydra.run.dir={bpref}"]
    (out / "config.json").write_text(json.dumps(our_config(args, command), indent=2))
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONWARNINGS="ignore")
    if args.algorithm == "qpa":  # its tqdm bar: a line a minute in the log
        env["TQDM_MININTERVAL"] = "60"
    start, wall_times = time.time(), []
    launch = command
    if args.algorithm == "prefppo":  # its r_hat against the true reward per rollout, as prefppo.py logs it
        launch = [str(HERE / "trace_prefppo.py"), "--trace-out", str((out / "rollouts.csv").resolve()), *command[1:]]
    if args.algorithm == "rime":
        launch = [str((tree / command[0]).resolve()), *command[1:]]
    print(f"reference: {python} {' '.join(launch)}", flush=True)
    cwd = bpref if args.algorithm == "rime" else tree
    process = subprocess.Popen([str(python), *launch], cwd=cwd, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    signal.signal(signal.SIGTERM, lambda signum, frame: process.terminate())  # a grid's stop: end the reference too
    try:
        for line in process.stdout:
            print(line, end="", flush=True)
            if "| eval |" in line:  # PEBBLE, SAC and QPA: an evaluation (QPA's may follow its tqdm bar)
                wall_times.append(round(time.time() - start, 1))
                write_eval(out, converted_rows(bpref, wall_times))
            if "total_timesteps" in line:  # PrefPPO: the end of a rollout's update
                write_eval(out, training_rows(next(bpref.glob("*/*/*"), bpref)))
        code = process.wait()
    except KeyboardInterrupt:
        process.terminate()
        return 128 + 2
    if code < 0:
        print(f"stopped by signal {-code}; the reference cannot resume: the grid starts this run afresh", file=sys.stderr)
        return 128 - code
    if code:
        print(f"error: the reference exited with code {code}", file=sys.stderr)
        return 1
    import torch

    if args.algorithm == "prefppo":
        log_dir = next(bpref.glob("*/*/*"))  # the reference names it from every setting
        rows = training_rows(log_dir)
        write_eval(out, rows)
        model = prefppo_reward_model(log_dir, args.total_timesteps)
        torch.save(model, out / "final_model.pt")
        print(f"done: {len(rows)} waves of training episodes in {(time.time() - start) / 60:.1f} min; outputs in "
              f"{out}")
        return 0
    model = final_model(next(bpref.glob("RIME/*/mistake_*_seed_*"), bpref), args.total_timesteps + 1)
    if "reward_model" in model:
        rows = converted_rows(bpref, wall_times)
        rows[-1]["reward_correlation"] = final_reward_correlation(model, args)
        write_eval(out, rows)
        print(f"final reward correlation (pebble.py's evaluate, reference's networks): "
              f"{rows[-1]['reward_correlation']:.3f}")
    torch.save(model, out / "final_model.pt")
    print(f"done: {len(wall_times)} evaluations in {(time.time() - start) / 60:.1f} min; outputs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(tyro.cli(Args)))
