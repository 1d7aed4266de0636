"""What both implementations do along their runs, side by side: SAC's temperature, the policy's entropy, the
mean reward of the batches (kNN reward in pre-training, r_hat after), the critic loss and the true return of the
training episodes, averaged over the runs of each implementation in windows of steps. Ours from each run's
TensorBoard scalars (losses/*, charts/episodic_return), the reference's from its bpref/train.csv.

    python benchmarks/reference/compare_logs.py runs/parity --window 10000
"""

import csv
import json
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

# quantity -> (our TensorBoard tag, the reference's train.csv column)
QUANTITIES = {"alpha": ("losses/alpha", "alpha_value"), "entropy": ("losses/entropy", "actor_entropy"),
              "batch_reward": ("losses/batch_reward", "batch_reward"), "critic_loss": ("losses/critic_loss",
                                                                                       "critic_loss"),
              "train_return": ("charts/episodic_return", "true_episode_reward")}


@dataclass
class Args:
    root: tyro.conf.Positional[str]
    """folder of runs of both implementations (searched for config.json)"""
    window: int = 10000
    """steps per row"""
    teacher: str = "oracle"
    """compare the runs of this teacher (ground-truth runs: ground-truth)"""


def ours(path: Path) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(path), size_guidance={"scalars": 0})
    events.Reload()
    tags = set(events.Tags()["scalars"])
    return {name: [(e.step, e.value) for e in events.Scalars(tag)] for name, (tag, _) in QUANTITIES.items()
            if tag in tags}


def reference(path: Path) -> dict[str, list[tuple[int, float]]]:
    with open(path / "bpref" / "train.csv") as f:
        rows = list(csv.DictReader(f))
    return {name: [(int(float(row["step"])), float(row[column])) for row in rows if row.get(column)]
            for name, (_, column) in QUANTITIES.items()}


def teacher_of(config: dict) -> str:
    return "ground-truth" if config.get("ground_truth_reward") else config["teacher"]


def main(args: Args):
    series = defaultdict(lambda: defaultdict(list))  # implementation -> quantity -> [(step, value)] of all runs
    counts = defaultdict(int)
    for config_path in sorted(Path(args.root).rglob("config.json")):
        config = json.loads(config_path.read_text())
        if teacher_of(config) != args.teacher:
            continue
        implementation = config.get("implementation", "ours")
        read = reference if implementation == "reference" else ours
        counts[implementation] += 1
        for name, points in read(config_path.parent).items():
            series[implementation][name] += points
    if not counts:
        sys.exit(f"error: no runs of teacher {args.teacher!r} below {args.root}")
    print(f"runs: {dict(counts)}; mean over the runs' logged values in each window of {args.window} steps")
    names = [f"{name} ({implementation})" for name in QUANTITIES for implementation in sorted(series)]
    print("| steps | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    last = max(step for by_name in series.values() for points in by_name.values() for step, _ in points)
    for start in range(0, last, args.window):
        cells = []
        for name in QUANTITIES:
            for implementation in sorted(series):
                values = [v for step, v in series[implementation][name] if start < step <= start + args.window]
                cells.append(f"{np.mean(values):.4g}" if values else "-")
        print(f"| {start + 1}-{start + args.window} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(tyro.cli(Args))
