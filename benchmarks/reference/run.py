"""One run of the reference code (rll-research/BPref, set up by benchmarks/reference/setup.sh) from pebble.py's flags,
its results written as pebble.py writes them, so that experiments/grid.py and experiments/report.py treat both
implementations alike (docs/parity.md):

    python benchmarks/reference/run.py --env-id walker-walk --seed 3 --teacher oracle --max-feedback 1000 \\
        --feedback-per-session 100 --feedback-every 9000 --total-timesteps 100000 --hidden-dim 256 --num-layers 2 \\
        --batch-size 256 --output-dir runs/parity/reference__s3
    python benchmarks/reference/run.py ... --ground-truth-reward    # the reference's train_SAC.py

The output directory gets config.json (pebble.py's fields, with "implementation": "reference" and the reference's
command line), bpref/ (the reference's own files), eval.csv in pebble.py's columns (wall_time from this wrapper's
clock at each evaluation line; the reference records no std or overhead: nan) and, at the end, final_model.pt (the
reference's actor, critic and reward models as pebble.py's state dicts) and, in the last row, the final reward
correlation measured by pebble.py's evaluate on those networks. The reference cannot resume: a run stopped part-way
is started afresh by the grid.
"""

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import tyro

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT))

from pebble import DMC_PRESET, PRESETS, eval_csv, save_file  # noqa: E402
from sim_teacher import make_teacher  # noqa: E402

FEED_TYPES = {"uniform": 0, "disagreement": 1, "entropy": 2, "coverage": 3, "disagreement-coverage": 4,
              "entropy-coverage": 5}  # the reference's feed_type
REWARD_SCHEDULES = {"uniform": (0, 1.0), "decay": (1, 2.0), "increase": (2, 0.5)}
"""schedule -> (the reference's reward_schedule, the factor its walker scripts apply to the per-session count)"""


@dataclass
class Args:
    """pebble.py's flags that the reference has a setting for (same names; None = pebble.py's preset of the task);
    anything else is refused."""

    output_dir: str
    """where the run's files go (must be empty or absent)"""
    env_id: str = "walker-walk"
    """a DMC task, domain-task (the reference's Meta-World needs MuJoCo 2.0)"""
    seed: int = 1
    """the reference's seed"""
    teacher: Literal["oracle", "stoc", "mistake", "skip", "equal", "myopic"] = "oracle"
    """simulated teacher: the reference's teacher_* settings of that name"""
    sampler: Literal[
        "uniform", "disagreement", "entropy", "coverage", "disagreement-coverage", "entropy-coverage"
    ] = "disagreement"
    """query selection (feed_type)"""
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
    seed_steps: int = 1000
    """random-action steps (num_seed_steps)"""
    unsup_steps: int = 9000
    """unsupervised pre-training steps (num_unsup_steps)"""
    hidden_dim: int | None = None
    """actor and critic width"""
    num_layers: int | None = None
    """actor and critic depth (hidden_depth)"""
    batch_size: int | None = None
    """SAC batch"""
    learning_rate: float | None = None
    """actor and critic learning rate"""
    reward_epochs: int | None = None
    """most reward epochs per session (reward_update)"""
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


def reference_command(args: Args) -> list[str]:
    """The reference's script and hydra overrides for these flags."""
    domain, task = args.env_id.split("-", 1)
    common = [f"env={domain}_{task.replace('-', '_')}", f"seed={args.seed}", f"device={'cuda' if args.cuda else 'cpu'}",
              "log_save_tb=false", f"num_train_steps={args.total_timesteps + 1}",
              f"num_seed_steps={args.seed_steps}", f"num_unsup_steps={args.unsup_steps}",
              f"agent.params.actor_lr={args.learning_rate}", f"agent.params.critic_lr={args.learning_rate}",
              f"agent.params.batch_size={args.batch_size}",
              *[f"{net}.params.{key}={value}" for net in ("diag_gaussian_actor", "double_q_critic")
                for key, value in (("hidden_dim", args.hidden_dim), ("hidden_depth", args.num_layers))],
              f"eval_frequency={args.eval_every}", f"num_eval_episodes={args.eval_episodes}"]
    if args.ground_truth_reward:
        return ["train_SAC.py", *common]
    teacher = make_teacher(args.teacher)
    schedule, factor = REWARD_SCHEDULES[args.schedule]
    return ["train_PEBBLE.py", *common, f"num_interact={args.feedback_every}", f"max_feedback={args.max_feedback}",
            f"reward_batch={int(args.feedback_per_session * factor)}", f"reward_schedule={schedule}",
            f"reward_update={args.reward_epochs}", f"feed_type={FEED_TYPES[args.sampler]}", f"segment={args.segment_len}",
            f"teacher_beta={-1 if math.isinf(teacher.beta) else teacher.beta}", f"teacher_gamma={teacher.gamma}",
            f"teacher_eps_mistake={teacher.eps_mistake}", f"teacher_eps_skip={teacher.eps_skip}",
            f"teacher_eps_equal={teacher.eps_equal}"]


def our_config(args: Args, command: list[str]) -> dict:
    """config.json as pebble.py would write it for these flags, marked as the reference's run."""
    config = {key: value for key, value in asdict(args).items() if key != "reference_dir"}
    teacher = make_teacher(args.teacher)
    config |= {f"teacher_{name}": getattr(teacher, name) for name in ("beta", "gamma", "eps_mistake", "eps_skip",
                                                                      "eps_equal")}
    return config | {"implementation": "reference", "reference_command": command}


def converted_rows(bpref_dir: Path, wall_times: list[float]) -> list[dict]:
    """The reference's eval.csv in pebble.py's eval.csv columns; the i-th evaluation gets wall_times[i] (nan where
    unknown)."""
    def read(name):
        try:
            with open(bpref_dir / name) as f:
                return list(csv.DictReader(f))
        except OSError:
            return []

    # train.csv's total_feedback at step S is what was asked before the episode that ended at S began: the labels
    # at an evaluation are on the first train row after it (the last row for the final evaluation)
    feedback = [(int(float(row["step"])), float(row.get("total_feedback") or 0)) for row in read("train.csv")]
    rows = []
    for i, row in enumerate(read("eval.csv")):
        step = int(float(row["step"]))
        later = [value for at, value in feedback if at > step] or [value for _, value in feedback[-1:]] or [0.0]
        returns = row.get("true_episode_reward") or row["episode_reward"]
        rows.append({"step": step, "episode_return": float(returns), "episode_return_std": math.nan,
                     "success_rate": math.nan, "feedback": later[0],
                     "reward_correlation": math.nan, "wall_time": wall_times[i] if i < len(wall_times) else math.nan,
                     "overhead_seconds": math.nan})
    return rows


def write_eval(out: Path, rows: list[dict]):
    """eval.csv as pebble.py writes it (its columns, written whole and atomically)."""
    save_file(str(out / "eval.csv"), eval_csv(rows))


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
        model["reward_model"] = {f"members.{i}.0.{key}": value for i, path in enumerate(members)
                                 for key, value in load(path.name).items()}
    return model


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
    reward_model = pebble.RewardEnsemble(obs_dim, action_dim, len({key.split(".")[1] for key in model["reward_model"]}))
    reward_model.load_state_dict(model["reward_model"])
    seeds = [pebble.episode_seed(args.seed, pebble.EVAL_STREAM, j) for j in range(args.eval_episodes)]
    policy = pebble.mean_policy(actor, torch.device("cpu"))
    return pebble.evaluate(policy, reward_model, env, seeds, torch.device("cpu"))["reward_correlation"]


def main(args: Args) -> int:
    for key, value in PRESETS.get(args.env_id, DMC_PRESET).items():  # pebble.py's resolve(), for a DMC task
        if getattr(args, key) is None:
            setattr(args, key, value)
    out, reference = Path(args.output_dir), Path(args.reference_dir)
    python, tree = reference / ".venv" / "bin" / "python", reference / "BPref"
    if not (python.exists() and (tree / "train_PEBBLE.py").exists()):
        print(f"error: no reference code in {reference}: run benchmarks/reference/setup.sh first", file=sys.stderr)
        return 2
    with warnings.catch_warnings(action="ignore"):  # GLFW's "failed to open display" on a headless machine
        from dm_control import suite
    if tuple(args.env_id.split("-", 1)) not in suite.ALL_TASKS:
        print(f"error: --env-id {args.env_id!r}: the reference runs DMC tasks only here", file=sys.stderr)
        return 2
    if out.exists() and any(out.iterdir()):
        print(f"error: --output-dir {out} is not empty (the reference cannot resume)", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    command = reference_command(args)
    (out / "config.json").write_text(json.dumps(our_config(args, command), indent=2))
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONWARNINGS="ignore")
    start, wall_times = time.time(), []
    print(f"reference: {python} {' '.join(command)} hydra.run.dir={out / 'bpref'}", flush=True)
    process = subprocess.Popen([str(python), *command, f"hydra.run.dir={(out / 'bpref').resolve()}"], cwd=tree,
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    signal.signal(signal.SIGTERM, lambda signum, frame: process.terminate())  # a grid's stop: end the reference too
    try:
        for line in process.stdout:
            print(line, end="", flush=True)
            if line.startswith("| eval"):
                wall_times.append(round(time.time() - start, 1))
                write_eval(out, converted_rows(out / "bpref", wall_times))
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

    model = final_model(out / "bpref", args.total_timesteps + 1)
    if "reward_model" in model:
        rows = converted_rows(out / "bpref", wall_times)
        rows[-1]["reward_correlation"] = final_reward_correlation(model, args)
        write_eval(out, rows)
        print(f"final reward correlation (pebble.py's evaluate, reference's networks): "
              f"{rows[-1]['reward_correlation']:.3f}")
    torch.save(model, out / "final_model.pt")
    print(f"done: {len(wall_times)} evaluations in {(time.time() - start) / 60:.1f} min; outputs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(tyro.cli(Args)))
