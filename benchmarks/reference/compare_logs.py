"""What both implementations do along their runs, side by side, averaged over the runs of each implementation in
windows of steps. PEBBLE: SAC's temperature, the policy's entropy, the mean reward of the batches (kNN reward in
pre-training, r_hat after), the critic loss and the true return of the training episodes; ours from each run's
TensorBoard scalars (losses/*, charts/episodic_return), the reference's from its bpref/train.csv. PrefPPO
(--algorithm prefppo): the true return of the training episodes and the correlation of r_hat with the true reward
over each rollout; ours from TensorBoard (charts/episodic_return, reward/rollout_correlation), the reference's from
its eval.csv (waves of training episodes) and rollouts.csv (run.py records it through trace_prefppo.py).

    python benchmarks/reference/compare_logs.py runs/parity --window 10000
    python benchmarks/reference/compare_logs.py runs/parity --algorithm prefppo --window 64000
"""

import csv
import json
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import tyro

# algorithm -> quantity -> (our TensorBoard tag, (the reference's file in its run directory, its column))
QUANTITIES = {
    "pebble": {"alpha": ("losses/alpha", ("bpref/train.csv", "alpha_value")),
               "entropy": ("losses/entropy", ("bpref/train.csv", "actor_entropy")),
               "batch_reward": ("losses/batch_reward", ("bpref/train.csv", "batch_reward")),
               "critic_loss": ("losses/critic_loss", ("bpref/train.csv", "critic_loss")),
               "train_return": ("charts/episodic_return", ("bpref/train.csv", "true_episode_reward"))},
    "prefppo": {"train_return": ("charts/episodic_return", ("eval.csv", "episode_return")),
                "rollout_correlation": ("reward/rollout_correlation", ("rollouts.csv", "correlation"))},
}


@dataclass
class Args:
    root: tyro.conf.Positional[str]
    """folder of runs of both implementations (searched for config.json)"""
    window: int = 10000
    """steps per row"""
    teacher: str = "oracle"
    """compare the runs of this teacher (ground-truth runs: ground-truth)"""
    algorithm: Literal["pebble", "prefppo"] = "pebble"
    """compare the runs of this algorithm"""


def ours(path: Path, quantities: dict) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(path), size_guidance={"scalars": 0})
    events.Reload()
    tags = set(events.Tags()["scalars"])
    return {name: [(e.step, e.value) for e in events.Scalars(tag)] for name, (tag, _) in quantities.items()
            if tag in tags}


def reference(path: Path, quantities: dict) -> dict[str, list[tuple[int, float]]]:
    series = {}
    for name, (_, (file, column)) in quantities.items():
        if (path / file).exists():
            with open(path / file) as f:
                rows = list(csv.DictReader(f))
            series[name] = [(int(float(row["step"])), float(row[column])) for row in rows if row.get(column)]
    return series


def algorithm_of(config: dict) -> str:
    """prefppo for prefppo.py's runs and the reference's train_PrefPPO.py runs (returns of training episodes)."""
    training_returns = config.get("episode_returns") == "training"  # the reference's PrefPPO
    return "prefppo" if config.get("exp_name") == "prefppo" or training_returns else "pebble"


def teacher_of(config: dict) -> str:
    return "ground-truth" if config.get("ground_truth_reward") else config["teacher"]


def main(args: Args):
    series = defaultdict(lambda: defaultdict(list))  # implementation -> quantity -> [(step, value)] of all runs
    counts = defaultdict(int)
    quantities = QUANTITIES[args.algorithm]
    for config_path in sorted(Path(args.root).rglob("config.json")):
        config = json.loads(config_path.read_text())
        if teacher_of(config) != args.teacher or algorithm_of(config) != args.algorithm:
            continue
        implementation = config.get("implementation", "ours")
        read = reference if implementation == "reference" else ours
        counts[implementation] += 1
        for name, points in read(config_path.parent, quantities).items():
            series[implementation][name] += points
    if not counts:
        sys.exit(f"error: no {args.algorithm} runs of teacher {args.teacher!r} below {args.root}")
    print(f"runs: {dict(counts)}; mean over the runs' logged values in each window of {args.window} steps")
    names = [f"{name} ({implementation})" for name in quantities for implementation in sorted(series)]
    print("| steps | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    last = max(step for by_name in series.values() for points in by_name.values() for step, _ in points)
    for start in range(0, last, args.window):
        cells = []
        for name in quantities:
            for implementation in sorted(series):
                values = [v for step, v in series[implementation][name] if start < step <= start + args.window]
                cells.append(f"{np.mean(values):.4g}" if values else "-")
        print(f"| {start + 1}-{start + args.window} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(tyro.cli(Args))
