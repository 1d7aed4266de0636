"""PEBBLE's own cost (reward learning, relabelling, per-step r_hat, query selection) as a share of the
SAC run it serves, at the CPU benchmark's sizes and at the paper's walker-walk sizes, on this machine.

    python benchmarks/pebble_overhead.py [--paper-updates 100] [--cpu-updates 500]

A paper-scale run takes days on a CPU, so the share is projected from unit costs measured here, one
thread, one after another in this process:
  - a SAC step: pebble.py --ground-truth-reward, N random steps then N steps with updates, evaluated
    after each half; (wall at 2N - 2 x wall at N) / N is one environment step plus one SAC update;
  - one epoch of pebble.train_reward over n labels of 50-step segments (walker: 24 + 6 inputs);
  - pebble.relabel per transition, one r_hat per environment step as the main loop computes it,
    disagreement selection (the ensemble on 10 x the session's pairs).
Projected PEBBLE cost = sum over sessions of (50 epochs over the labels so far + relabelling the
buffer at that step + the session's selection) + r_hat for every step after the first session. 50
epochs is the most a DMC session runs (the 97% early stop ends most sessions sooner), so the share
is an upper bound. The kNN reward of pre-training is left out: the --ground-truth-reward run pays it too.
It also prints how close reward training comes to this core's plain fp32 matmul throughput.
"""

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import pebble  # noqa: E402

OBS_DIM, ACTION_DIM, SEGMENT_LEN, ENSEMBLE, MAX_EPOCHS = 24, 6, 50, 3, 50

# (name, SAC hidden x layers, SAC batch, total steps, first session step, feedback every, sessions, labels per session)
SETTINGS = [
    ("CPU benchmark: 256 x 2, batch 256, 100K steps", 256, 2, 256, 100_000, 10_001, 9_000, 10, 100),
    ("paper walker-walk: 1024 x 2, batch 1024, 500K steps", 1024, 2, 1024, 500_000, 10_001, 20_000, 10, 100),
]


def median_seconds(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def sac_step_seconds(hidden, layers, batch, updates) -> float:
    """One environment step + one SAC update of pebble.py at these sizes (true reward, no teacher)."""
    with tempfile.TemporaryDirectory() as folder:
        out = os.path.join(folder, "run")
        cmd = [sys.executable, str(ROOT / "pebble.py"), "--ground-truth-reward", "--output-dir", out,
               "--hidden-dim", str(hidden), "--num-layers", str(layers), "--batch-size", str(batch),
               "--seed-steps", str(updates), "--unsup-steps", "0", "--total-timesteps", str(2 * updates),
               "--eval-every", str(updates), "--eval-episodes", "1", "--critic-reset-updates", "0",
               "--checkpoint-every", "0", "--buffer-size", str(max(2 * updates, batch, 1000))]
        run = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
        if run.returncode:
            sys.exit(f"pebble.py failed: {run.stderr.strip().splitlines()[-1]}")
        with open(os.path.join(out, "eval.csv")) as f:
            first, second = (float(row["wall_time"]) for row in csv.DictReader(f))
    return (second - 2 * first) / updates


def reward_unit_costs(repeats) -> dict:
    model = pebble.RewardEnsemble(OBS_DIM, ACTION_DIM, ENSEMBLE)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-4)
    config = SimpleNamespace(reward_batch_size=128, label_smoothing=0.0, reward_epochs=1)
    width = OBS_DIM + ACTION_DIM
    costs = {}
    labels = 500
    inputs0, inputs1 = torch.randn(labels, SEGMENT_LEN, width), torch.randn(labels, SEGMENT_LEN, width)
    y = torch.randint(0, 2, (labels,)).float()
    costs["epoch_per_label"] = median_seconds(
        lambda: pebble.train_reward(model, optimizer, {"inputs0": inputs0, "inputs1": inputs1, "y": y}, config),
        repeats) / labels
    transitions = 100_000
    buffer = pebble.ReplayBuffer(transitions, OBS_DIM, ACTION_DIM)
    buffer.obs.normal_(), buffer.actions.uniform_(-1, 1)
    buffer.size = transitions
    costs["relabel_per_transition"] = median_seconds(lambda: pebble.relabel(buffer, model), repeats) / transitions
    obs, action = np.random.randn(OBS_DIM).astype(np.float32), np.random.uniform(-1, 1, ACTION_DIM).astype(np.float32)

    def one_r_hat():
        with torch.no_grad():
            model(torch.as_tensor(np.concatenate([obs, action]))).mean().item()

    costs["r_hat_per_step"] = median_seconds(lambda: [one_r_hat() for _ in range(1000)], repeats) / 1000
    candidates = torch.randn(1000, SEGMENT_LEN, width)

    def disagreement():
        with torch.no_grad():
            torch.sigmoid(model(candidates).sum(2) - model(candidates).sum(2))

    costs["selection_per_session"] = median_seconds(disagreement, repeats)
    return costs


def gemm_efficiency(epoch_per_label, repeats) -> tuple[float, float]:
    """(reward training's GFLOP/s, this core's GFLOP/s on one plain fp32 matmul of the hidden layer's shape).
    Training a row costs ~3x its forward multiply-adds (forward, input gradient, weight gradient)."""
    forward_macs = (OBS_DIM + ACTION_DIM) * 256 + 2 * 256 * 256 + 256
    rows_per_label = 2 * SEGMENT_LEN * ENSEMBLE
    training = 2 * 3 * forward_macs * rows_per_label / epoch_per_label / 1e9
    a, b = torch.randn(128 * SEGMENT_LEN, 256), torch.randn(256, 256)
    plain = 2 * a.shape[0] * 256 * 256 / median_seconds(lambda: [a @ b for _ in range(20)], repeats) * 20 / 1e9
    return training, plain


def projected_overhead(costs, total, first_session, every, sessions, per_session) -> float:
    seconds = 0.0
    for k in range(sessions):
        step = first_session + k * every
        seconds += MAX_EPOCHS * (k + 1) * per_session * costs["epoch_per_label"]
        seconds += step * costs["relabel_per_transition"] + costs["selection_per_session"]
    return seconds + (total - first_session) * costs["r_hat_per_step"]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cpu-updates", type=int, default=500, help="SAC updates timed at the CPU benchmark's sizes")
    parser.add_argument("--paper-updates", type=int, default=100, help="SAC updates timed at the paper's sizes")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)

    costs = reward_unit_costs(args.repeats)
    print("unit costs (one thread): " + ", ".join(f"{k} {v * 1e3:.3g} ms" for k, v in costs.items()))
    training_gflops, plain_gflops = gemm_efficiency(costs["epoch_per_label"], args.repeats)
    print(f"reward training: {training_gflops:.0f} GFLOP/s = {training_gflops / plain_gflops:.0%} of one plain fp32 "
          f"matmul of its hidden-layer shape ({plain_gflops:.0f} GFLOP/s): it is bound by the matrix products")
    print()
    print("| setting | SAC step (env + update) | SAC run | PEBBLE's own cost (at most) | share |")
    print("|---|---|---|---|---|")
    for (name, hidden, layers, batch, total, first, every, sessions, per_session), updates in zip(
            SETTINGS, (args.cpu_updates, args.paper_updates)):
        step = sac_step_seconds(hidden, layers, batch, updates)
        run_seconds = step * total
        overhead = projected_overhead(costs, total, first, every, sessions, per_session)
        print(f"| {name} | {step * 1e3:.1f} ms | {run_seconds / 3600:.1f} h | {overhead / 60:.1f} min "
              f"| {100 * overhead / run_seconds:.1f}% |", flush=True)
