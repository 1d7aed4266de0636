"""What the reference PrefPPO's moving reward-input normaliser (defect 7, docs/differences.md item 17) does to reward
learning, measured offline on one of our prefppo.py runs: its labels and its query pool (every episode, in the
checkpoint) are normalised three ways, a reward model is trained on the first sessions and judged on the later ones
(Pearson correlation of the learned with the true per-step reward, share of later pairs in the teacher's order):

- ours: prefppo.py's input normaliser, the labelled states' statistics (RewardEnsemble.set_input_stats);
- moving, as stored (the reference's way): each step normalised by the running statistics of every observation seen
  up to its own step, as the reference stored it in its query pool, while the learned reward is used (and judged) on
  observations normalised by the statistics of the last training session's step;
- moving, current: the same running normaliser, but every input normalised by the statistics at that last session's
  step: the moving normaliser without its stale storage.

    python benchmarks/reference/stale_inputs.py runs/parity/ours/prefppo__walker-walk__oracle__..._s1 --sessions 5

The run must hold its checkpoint.pt (prefppo.py keeps every episode in order there) and labels/. Episodes end in
waves (every env at the same step, DMC's fixed length), so episode e was collected in wave e // num_envs; the running
statistics are exact per step over all envs (without the reset observations, a 1/1000 share).
"""

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
import prefppo  # noqa: E402


def running_stats(episodes: list, num_envs: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) of every observation seen up to and including each step, shape (waves, episode_len, obs_dim):
    VecNormalize's statistics after its update with that step's observations of all envs."""
    obs = np.stack([np.asarray(episode[0], np.float64) for episode in episodes])  # (episodes, len, obs_dim)
    waves = obs.reshape(-1, num_envs, *obs.shape[1:])  # episode e is env e % num_envs of wave e // num_envs
    step_sums = waves.sum(1).reshape(-1, obs.shape[-1])  # in collection order: wave by wave, step by step
    step_squares = (waves**2).sum(1).reshape(-1, obs.shape[-1])
    count = num_envs * np.arange(1, len(step_sums) + 1)[:, None]
    mean = np.cumsum(step_sums, 0) / count
    var = np.maximum(np.cumsum(step_squares, 0) / count - mean**2, 0)
    shape = (len(waves), obs.shape[1], obs.shape[-1])
    return mean.reshape(shape), np.sqrt(var + 1e-8).reshape(shape)


def normalized(x: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    return np.clip((x - mean) / std, -10, 10)


def sessions_of(run: Path) -> list[dict]:
    return [dict(np.load(path)) for path in sorted(glob.glob(str(run / "labels" / "session_*.npz")))]


def inputs(sessions: list[dict], side: int, obs_fn) -> np.ndarray:
    """(pairs, segment_len, obs+action) of one side, the observations passed through obs_fn(obs, session, side)."""
    parts = [np.concatenate([obs_fn(s[f"obs{side}"], s, side), s[f"actions{side}"]], -1) for s in sessions]
    return np.concatenate(parts).astype(np.float32)


def learn_and_judge(train: tuple, later: tuple, y: np.ndarray, later_y: np.ndarray, later_rewards: np.ndarray,
                    seed: int, epochs: int, obs_dim: int | None = None) -> dict:
    """prefppo.py's reward learning on train (inputs0, inputs1) until 97% accuracy; obs_dim: set its input
    statistics from the training states first (as prefppo.py does)."""
    torch.manual_seed(seed)
    model = prefppo.RewardEnsemble(train[0].shape[-1], 0, 3)
    preferences = {"inputs0": torch.as_tensor(train[0]), "inputs1": torch.as_tensor(train[1]),
                   "y": torch.as_tensor(y, dtype=torch.float32)}
    if obs_dim:
        states = torch.cat([preferences["inputs0"], preferences["inputs1"]], 1)[..., :obs_dim]
        model.set_input_stats(states.flatten(0, 1))
    optimizer = prefppo.adam(model.parameters(), 3e-4)
    one_epoch = prefppo.Args(reward_epochs=1)
    for epoch in range(1, epochs + 1):
        _, accuracy = prefppo.train_reward(model, optimizer, preferences, one_epoch)
        if accuracy > 0.97:
            break
    with torch.no_grad():
        returns = [model(torch.as_tensor(side)).mean(0)[..., 0].numpy() for side in later]
    correlation = float(np.corrcoef(np.concatenate(returns).reshape(-1), later_rewards.reshape(-1))[0, 1])
    agreement = float(np.mean((returns[1].sum(1) > returns[0].sum(1)) == (later_y > 0.5)))
    return {"epochs": epoch, "correlation": correlation, "agreement": agreement}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a prefppo.py run directory with checkpoint.pt and labels/")
    parser.add_argument("--sessions", type=int, default=5, help="sessions to train on; the later ones judge")
    parser.add_argument("--seeds", type=int, default=3, help="initialisation seeds of each way")
    args = parser.parse_args()
    run = Path(args.run)
    config = json.loads((run / "config.json").read_text())
    state = torch.load(run / "checkpoint.pt", "cpu", weights_only=True)
    mean, std = running_stats(state["episodes"], config["num_envs"])
    saved = [s for s in sessions_of(run) if s["keep"].all()]  # the oracle: every query labelled
    if len(saved) <= args.sessions:
        sys.exit(f"error: {run} has {len(saved)} label sessions; --sessions must leave some to judge on")
    train, later = saved[: args.sessions], saved[args.sessions :]
    steps_per_wave = config["num_envs"] * mean.shape[1]
    last = int(train[-1]["step"]) - 1  # the last training session's step, 0-based in collection order
    now = (mean[last // steps_per_wave, last % steps_per_wave // config["num_envs"]],
           std[last // steps_per_wave, last % steps_per_wave // config["num_envs"]])

    def as_stored(obs, session, side):
        waves = session[f"episode{side}"] // config["num_envs"]
        steps = session[f"start{side}"][:, None] + np.arange(obs.shape[1])
        return normalized(obs, mean[waves[:, None], steps], std[waves[:, None], steps])

    def current(obs, session, side):
        return normalized(obs, *now)

    def raw(obs, session, side):
        return obs

    y = np.concatenate([s["y"] for s in train])
    later_y = np.concatenate([s["y"] for s in later])
    later_rewards = np.stack([np.concatenate([s[f"rewards{i}"] for s in later]) for i in (0, 1)])
    obs_dim = saved[0]["obs0"].shape[-1]
    ways = {"ours (labelled states' statistics)": (raw, raw, obs_dim),
            "moving, as stored (the reference's)": (as_stored, current, None),
            "moving, current": (current, current, None)}
    print(f"{len(y)} labels to train on, {len(later_y)} later pairs to judge on ({run})")
    print("| inputs | seed | epochs | correlation with the true reward | later pairs in the teacher's order |")
    print("|---|---|---|---|---|")
    for name, (train_fn, judge_fn, stats_dim) in ways.items():
        rows = [learn_and_judge((inputs(train, 0, train_fn), inputs(train, 1, train_fn)),
                                (inputs(later, 0, judge_fn), inputs(later, 1, judge_fn)), y, later_y, later_rewards,
                                seed, config["reward_epochs"], stats_dim) for seed in range(args.seeds)]
        for seed, row in enumerate(rows):
            print(f"| {name} | {seed} | {row['epochs']} | {row['correlation']:.3f} | {row['agreement']:.3f} |")
        print(f"| {name} | mean | {np.mean([r['epochs'] for r in rows]):.1f} | "
              f"{np.mean([r['correlation'] for r in rows]):.3f} | {np.mean([r['agreement'] for r in rows]):.3f} |")


if __name__ == "__main__":
    main()
