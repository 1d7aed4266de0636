"""Size and write/read time of a paper-scale pebble.py checkpoint: walker-walk's full 1M-transition replay
buffer, 1024 x 2 SAC networks with their Adam states, the reward ensemble; written as the script writes it
(serialised in memory, then save_file: a temporary file, fsync, rename).

    python benchmarks/checkpoint_cost.py [--transitions 1000000] [--repeats 3]
"""

import argparse
import io
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import pebble  # noqa: E402
import sim_teacher  # noqa: E402

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--transitions", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    env, _ = pebble.make_env("walker-walk")
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    buffer = pebble.ReplayBuffer(args.transitions, obs_dim, action_dim)
    for name in pebble.Batch._fields:
        getattr(buffer, name).normal_()
    buffer.size = args.transitions
    networks = {"actor": pebble.Actor(obs_dim, action_dim, 1024, 2),
                "critic": pebble.TwinCritic(obs_dim, action_dim, 1024, 2),
                "critic_target": pebble.TwinCritic(obs_dim, action_dim, 1024, 2),
                "reward_model": pebble.RewardEnsemble(obs_dim, action_dim, 3)}
    optimizers = {}
    for name, net in networks.items():  # Adam's two moments per parameter, as after training
        optimizers[f"{name}_optimizer"] = torch.optim.Adam(net.parameters())
        sum(p.sum() for p in net.parameters()).backward()
        optimizers[f"{name}_optimizer"].step()
    checkpoint = {**{k: v.state_dict() for k, v in {**networks, **optimizers}.items()},
                  "buffer": buffer.state_dict()}

    with tempfile.TemporaryDirectory(dir=".") as folder:
        path = os.path.join(folder, "checkpoint.pt")
        writes, reads = [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            data = io.BytesIO()
            torch.save(checkpoint, data)
            sim_teacher.save_file(path, data.getvalue())
            writes.append(time.perf_counter() - start)
            start = time.perf_counter()
            torch.load(path, weights_only=True)
            reads.append(time.perf_counter() - start)
        size = os.path.getsize(path)
    print(f"| transitions | checkpoint size (MiB) | write, best of {args.repeats} (s) | read, best of {args.repeats} (s) |")
    print("|---|---|---|---|")
    print(f"| {args.transitions:,} | {size / 2**20:.0f} | {min(writes):.2f} | {min(reads):.2f} |")
