"""What one epoch of reward learning costs as the labels grow, on one thread: prefppo.train_reward (the same code as
pebble.py's) over N labels of a task's segments, beside this core's plain fp32 matmul of the hidden layer's shape.

    python benchmarks/reward_epoch.py [--env-id sweep-into] [--labels 1000 3000 6100] [--checkpoint RUN_DIR]

A session trains on every label so far until the ensemble's accuracy passes 97% (at most --reward-epochs), so a
session late in a long Meta-World run costs epochs x the last row. --checkpoint RUN_DIR also trains that run's
ensemble again on its own labels, from its checkpoint and optimizer state, and counts the epochs to pass 97%.
Inputs here are random (the cost of an epoch does not depend on their values); docs/prefppo.md has the figures.
"""

import argparse
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import prefppo  # noqa: E402
from benchmarks.pebble_overhead import median_seconds  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="sweep-into", help="the task whose sizes to use (--checkpoint: its run's)")
    parser.add_argument("--labels", type=int, nargs="+", default=[1000, 3000, 6100])
    parser.add_argument("--checkpoint", help="a prefppo.py run directory with checkpoint.pt")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    if args.checkpoint:  # its task's sizes
        args.env_id = json.loads((Path(args.checkpoint) / "config.json").read_text())["env_id"]
    torch.set_num_threads(1)
    torch.manual_seed(0)
    task = prefppo.task_defaults(args.env_id, "oracle")  # the task's preset: segment length, batch size
    segment_len = task.segment_len
    env, _ = prefppo.make_env(args.env_id)
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    config = SimpleNamespace(reward_epochs=1, reward_batch_size=task.reward_batch_size, label_smoothing=0.0)
    width = obs_dim + action_dim
    forward_macs = width * 256 + 2 * 256 * 256 + 256  # RewardEnsemble: 3 x 256, one output
    a, b = torch.randn(config.reward_batch_size * segment_len, 256), torch.randn(256, 256)
    plain = 2 * a.shape[0] * 256 * 256 / median_seconds(lambda: [a @ b for _ in range(200)], args.repeats) * 200 / 1e9
    print(f"{args.env_id}: segments of {segment_len} steps x {width} inputs, 3 members of 3 x 256, batches of "
          f"{config.reward_batch_size}; plain fp32 matmul ({a.shape[0]} x 256 x 256): {plain:.0f} GFLOP/s\n")
    print("| labels | one epoch (s) | GFLOP/s | / plain matmul |")
    print("|---:|---:|---:|---:|")
    for labels in args.labels:
        model = prefppo.RewardEnsemble(obs_dim, action_dim, 3)
        optimizer = prefppo.adam(model.parameters(), 3e-4)
        preferences = {"inputs0": torch.randn(labels, segment_len, width),
                       "inputs1": torch.randn(labels, segment_len, width),
                       "y": torch.randint(0, 2, (labels,)).float()}
        epoch = median_seconds(lambda: prefppo.train_reward(model, optimizer, preferences, config), args.repeats)
        # training a row: forward, input gradient, weight gradient, each about the forward's multiply-adds
        gflops = 2 * 3 * forward_macs * 2 * segment_len * 3 * labels / epoch / 1e9
        print(f"| {labels} | {epoch:.2f} | {gflops:.0f} | {gflops / plain:.0%} |", flush=True)
    if args.checkpoint:  # three shuffles of the labels: the epochs to 97% vary with them
        print(f"\n{args.checkpoint}, its ensemble trained again from its checkpoint on its own labels:")
        state = torch.load(Path(args.checkpoint) / "checkpoint.pt", "cpu", weights_only=True)
        for seed in range(3):
            torch.manual_seed(seed)
            model = prefppo.RewardEnsemble(obs_dim, action_dim, 3)
            model.load_state_dict(state["reward_model"])
            optimizer = prefppo.adam(model.parameters(), 3e-4)
            optimizer.load_state_dict(state["reward_optimizer"])
            start = time.perf_counter()
            for epoch in range(1, task.reward_epochs + 1):
                _, accuracy = prefppo.train_reward(model, optimizer, state["preferences"], config)
                if accuracy > 0.97:
                    break
            print(f"shuffle seed {seed}: {len(state['preferences']['y'])} labels, accuracy {accuracy:.3f} after "
                  f"{epoch} epochs, {time.perf_counter() - start:.0f} s", flush=True)


if __name__ == "__main__":
    main()
