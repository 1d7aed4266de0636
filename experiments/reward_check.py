"""Does a run's learned reward prefer what the true reward prefers, away from the agent's own behaviour?

A reward model can agree with the teacher on the segments it was taught on (the agent's recent episodes) and still
rank other behaviour wrongly; the agent then settles where r_hat is high and the true reward is not. This plays the
reset seeds of the run's last evaluation with three policies: the run's own final policy, an expert (Meta-World's
scripted policy for the task, or the final policy of another run, such as SAC on the true reward) and a uniformly
random one; and prints, for each, the true return, the success rate (Meta-World), the learned return (r_hat's
ensemble mean summed over the episode, from final_model.pt) and r_hat's per-step correlation with the true reward.
Docs: docs/experiments.md

    python experiments/reward_check.py runs/sweep-into/pebble__sweep-into__oracle__fb1400-50__disagreement__uniform__s2
    python experiments/reward_check.py RUN --expert runs/grid/pebble__walker-walk__ground-truth__s1   # any task
"""

import csv
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))

from report import find_runs, final_evaluation_seeds, is_metaworld, load_final_model  # noqa: E402


@dataclass
class Args:
    run: tyro.conf.Positional[str]
    """a run's folder (config.json, eval.csv and final_model.pt)"""
    expert: str = "scripted"
    """'scripted': Meta-World's scripted policy for the task; else a run's folder whose final policy is the expert"""
    episodes: int = 0
    """episodes per policy, the first of the run's last evaluation (0: all of them)"""
    seed: int = 0
    """seed of the random policy's actions"""
    csv: str = ""
    """also write one row per policy and episode to this CSV file"""


class CheckError(Exception):
    """A problem with the command line or a run's folder, said in one line."""


def load_run(folder: str) -> tuple:
    """load_final_model() of the finished run in folder."""
    path = Path(folder).resolve()
    runs = [run for run in find_runs(path, path / "report") if run.path == path] if path.is_dir() else []
    if not runs:
        raise CheckError(f"{folder!r} is not a run's folder (no config.json there)")
    if not (path / "final_model.pt").is_file() or (path / "final_model.pt").stat().st_size == 0:
        raise CheckError(f"{folder!r} has no final_model.pt (only a finished run has one)")
    return runs[0], *load_final_model(runs[0])


def actor_policy(module, actor, obs_stats):
    """The run's evaluated policy (its mean action), numpy in and out."""
    import torch

    policy = module.mean_policy(actor, "cpu") if obs_stats is None else module.mean_policy(actor, obs_stats, "cpu")

    def act(obs):
        with torch.no_grad():
            return policy(obs).numpy()

    return act


def scripted_policy(env_id: str):
    """Meta-World's scripted policy for the task; it reads the goal, which the agent's observations hide."""
    from metaworld.policies import ENV_POLICY_MAP

    warnings.filterwarnings("ignore", "Constant", module="metaworld")  # its policies' note on their gains
    name = f"{env_id.removesuffix('-v3')}-v3"
    if name not in ENV_POLICY_MAP:
        raise CheckError(f"no scripted policy for {env_id!r} (Meta-World's only): give --expert RUN")
    expert = ENV_POLICY_MAP[name]()
    return lambda obs: np.clip(expert.get_action(obs), -1, 1).astype(np.float32)


def play(env, policy, seed: int, reward_model, sees_goal: bool = False) -> dict:
    """One episode from the reset seed: true return, success, and r_hat at each step on the (obs, action) the agent's
    own observations give (with sees_goal, the policy sees Meta-World's goal; r_hat gets it hidden, as in training)."""
    import torch

    unwrapped = env.unwrapped
    if sees_goal:  # Meta-World clips observations to a cached space: made again, as its set_task() does
        unwrapped._partially_observable = False
        unwrapped.__dict__.pop("sawyer_observation_space", None)
    try:
        obs, _ = env.reset(seed=seed)
        inputs, true_rewards, success, done = [], [], False, False
        while not done:
            action = policy(obs)
            seen = obs.copy()
            if sees_goal:
                seen[-3:] = 0.0  # the goal's entries, zeros in the agent's observations
            inputs.append(np.concatenate([seen, action]))
            obs, reward, terminated, truncated, info = env.step(action)
            true_rewards.append(float(reward))
            success = success or bool(info.get("success"))
            done = terminated or truncated
    finally:
        if sees_goal:
            unwrapped._partially_observable = True
            unwrapped.__dict__.pop("sawyer_observation_space", None)
    with torch.no_grad():
        learned = reward_model(torch.as_tensor(np.array(inputs), dtype=torch.float32)).mean(0).flatten().numpy()
    return {"true": np.array(true_rewards), "learned": learned, "success": success}


def correlation(episodes: list[dict]) -> float:
    """Pearson correlation of r_hat with the true reward over every step of the episodes (evaluate()'s)."""
    true = np.concatenate([e["true"] for e in episodes])
    learned = np.concatenate([e["learned"] for e in episodes])
    if min(true.std(), learned.std()) == 0:
        return float("nan")
    return float(np.corrcoef(learned, true)[0, 1])


def check(args: Args) -> list[str]:
    """The table's lines (Markdown) and the ranking line."""
    run, module, env, actor, reward_model, obs_stats = load_run(args.run)
    if run.is_ground_truth:
        raise CheckError(f"{args.run!r} learned from the true reward: it has no learned reward to check")
    seeds = final_evaluation_seeds(module, run)
    if not 0 <= args.episodes <= len(seeds):
        raise CheckError(f"--episodes must be in [0, {len(seeds)}] (the run's evaluation episodes)")
    seeds = seeds[: args.episodes or len(seeds)]
    env_id = run.config["env_id"]
    if args.expert == "scripted":
        expert, expert_name, sees_goal = scripted_policy(env_id), "scripted expert", True
    else:
        expert_run, expert_module, expert_env, expert_actor, _, expert_stats = load_run(args.expert)
        expert_env.close()
        if expert_run.config["env_id"] != env_id:
            raise CheckError(f"--expert {args.expert!r} ran {expert_run.config['env_id']}, the run {env_id}")
        expert, expert_name, sees_goal = actor_policy(expert_module, expert_actor, expert_stats), "expert run", False
    rng = np.random.default_rng(args.seed)
    low, high = env.action_space.low, env.action_space.high
    policies = {"own policy": (actor_policy(module, actor, obs_stats), False), expert_name: (expert, sees_goal),
                "random policy": (lambda obs: rng.uniform(low, high).astype(np.float32), False)}
    played = {name: [play(env, policy, seed, reward_model, sees) for seed in seeds]
              for name, (policy, sees) in policies.items()}
    env.close()
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["policy", "seed", "true_return", "success", "learned_return"])
            for name, episodes in played.items():
                writer.writerows([name, seed, e["true"].sum(), int(e["success"]), e["learned"].sum()]
                                 for seed, e in zip(seeds, episodes))
    lines = [f"{run.path} ({env_id}, {len(seeds)} episodes on the reset seeds of its last evaluation)", "",
             "| policy | true return | success | learned return | r_hat-true correlation (per step) |",
             "|---|---:|---:|---:|---:|"]
    for name, episodes in played.items():
        true = np.array([e["true"].sum() for e in episodes])
        learned = np.array([e["learned"].sum() for e in episodes])
        successes = f"{np.mean([e['success'] for e in episodes]):.2f}" if is_metaworld(env_id) else "-"
        lines.append(f"| {name} | {true.mean():.1f} ± {true.std():.1f} | {successes} | "
                     f"{learned.mean():.1f} ± {learned.std():.1f} | {correlation(episodes):.3f} |")
    pairs = list(zip(played[expert_name], played["own policy"]))
    by_learned = sum(e["learned"].sum() > o["learned"].sum() for e, o in pairs)
    by_true = sum(e["true"].sum() > o["true"].sum() for e, o in pairs)
    agree = sum((e["learned"].sum() > o["learned"].sum()) == (e["true"].sum() > o["true"].sum()) for e, o in pairs)
    lines += ["", f"the {expert_name}'s episode above the own policy's on the same seed: by the learned reward in "
                  f"{by_learned} of {len(pairs)}, by the true reward in {by_true} of {len(pairs)}; the two agree on "
                  f"{agree} of {len(pairs)}"]
    return lines


if __name__ == "__main__":
    args = tyro.cli(Args, description=__doc__.split("\n\n")[0])
    try:
        print("\n".join(check(args)))
    except CheckError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
