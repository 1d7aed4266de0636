"""Size and write/read time of pebble.py's checkpoint at the card's sizes (the README's first command: quadruped-walk,
1M steps, so a 1M-transition replay buffer; 1024 x 2 SAC networks with their Adam states; the reward ensemble with
its Adam state), with the buffer filled to 1K, 100K and 1M transitions: a checkpoint holds the filled part of the
buffer only. Written as the script writes it (snapshot, serialised in memory, then save_file: a temporary file,
fsync, rename) and read as --resume reads it (torch.load, then each part's load_state_dict).

    python benchmarks/checkpoint_cost.py [--filled 1000 100000 1000000] [--repeats 3]
"""

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import pebble  # noqa: E402

CAPACITY = 1_000_000  # quadruped-walk's --total-timesteps: the buffer's capacity
HIDDEN, LAYERS = 1024, 2

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--filled", type=int, nargs="+", default=[1_000, 100_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    env, _ = pebble.make_env("quadruped-walk")
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    buffer = pebble.ReplayBuffer(CAPACITY, obs_dim, action_dim)
    parts = {"actor": pebble.Actor(obs_dim, action_dim, HIDDEN, LAYERS),
             "critic": pebble.TwinCritic(obs_dim, action_dim, HIDDEN, LAYERS),
             "critic_target": pebble.TwinCritic(obs_dim, action_dim, HIDDEN, LAYERS),
             "reward_model": pebble.RewardEnsemble(obs_dim, action_dim, 3)}
    for name, net in list(parts.items()):  # Adam's two moments per parameter, as after training
        optimizer = pebble.adam(net.parameters(), 1e-4)
        pebble.optimize(optimizer, sum(p.sum() for p in net.parameters()))
        parts[f"{name}_optimizer"] = optimizer
    parts["buffer"] = buffer
    for name in pebble.Batch._fields:  # random contents (zeros would not show what the disk costs)
        getattr(buffer, name).normal_()

    print(f"pebble.py checkpoint, quadruped-walk (obs {obs_dim}, action {action_dim}), {HIDDEN} x {LAYERS} networks, "
          f"a {CAPACITY:,}-transition buffer; best of {args.repeats}\n")
    print("| transitions in the buffer | checkpoint size (MiB) | write (s) | read (s) |")
    print("|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory(dir=".") as folder:
        path = os.path.join(folder, "checkpoint.pt")
        for filled in args.filled:
            buffer.size = filled
            buffer.pos = filled % CAPACITY
            writes, reads = [], []
            for _ in range(args.repeats):
                start = time.perf_counter()
                pebble.save_whole(path, pebble.snapshot(parts))
                writes.append(time.perf_counter() - start)
                start = time.perf_counter()
                state = torch.load(path, weights_only=True)
                for name, part in parts.items():
                    part.load_state_dict(state[name])
                reads.append(time.perf_counter() - start)
                del state
            print(f"| {filled:,} | {os.path.getsize(path) / 2**20:.1f} | {min(writes):.2f} | {min(reads):.2f} |",
                  flush=True)
