"""What a uniformly random policy scores on a task, on the evaluation episodes a run of seed 1 uses: the floor that
"the agent learned" has to clear (docs/results.md, the paper's four tasks).

    python benchmarks/random_policy.py quadruped-walk button-press sweep-into --episodes 10
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pebble  # noqa: E402


def random_returns(env_id: str, episodes: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Return and success of each episode, reset as the run's first evaluation resets them."""
    env, _ = pebble.make_env(env_id)
    rng = np.random.default_rng(seed)
    returns, successes = [], []
    for episode in range(episodes):
        env.reset(seed=pebble.episode_seed(seed, pebble.EVAL_STREAM, episode))
        total, success, done = 0.0, False, False
        while not done:
            action = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
            _, reward, terminated, truncated, info = env.step(action)
            total += reward
            success = success or bool(info.get("success"))
            done = terminated or truncated
        returns.append(total)
        successes.append(success)
    return np.array(returns), np.array(successes)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("env_ids", nargs="+")
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    print("| task | episodes | return, mean ± std | per episode | success rate |")
    print("|---|---:|---|---|---:|")
    for env_id in args.env_ids:
        returns, successes = random_returns(env_id, args.episodes)
        per_episode = " ".join(f"{r:.0f}" for r in returns)
        print(f"| {env_id} | {args.episodes} | {returns.mean():.1f} ± {returns.std():.1f} | {per_episode} | "
              f"{successes.mean():.2f} |")


if __name__ == "__main__":
    main()
