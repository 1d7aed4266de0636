"""Seconds a feedback session spends choosing its queries, per sampler, at walker-walk's CPU scale (the
README's: 100 queries a session from 10 x 100 candidate pairs of 50-step segments, a pool of the last 100
episodes, an ensemble of 3 reward models), at the first session after pre-training with uncertainty (100
labels so far) and at the last (900 labels so far: the coverage samplers' k-center starts from all of them).

    python benchmarks/sampler_speed.py [--repeats 5]

It calls pebble.sample_queries, as a run's feedback session does, on random episodes of walker-walk's shapes
(24-d observations, 6-d actions, 1000 steps), one thread, every sampler in turn in each repeat so that the
machine's load falls on all alike; the table gives the median seconds and the ratio to disagreement sampling (the default). The
rest of a session (the teacher's labels, up to 50 epochs of reward learning) does not depend on the sampler.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import pebble  # noqa: E402
from samplers import SAMPLERS  # noqa: E402

OBS_DIM, ACTION_DIM, EPISODE_LEN, EPISODES, SEGMENT_LEN, QUERIES = 24, 6, 1000, 100, 50, 100


def query_pool(rng):
    """The last 100 episodes, as a run keeps them: (observations, actions, true rewards) tensors."""
    return [tuple(torch.as_tensor(rng.standard_normal(shape), dtype=torch.float32)
                  for shape in ((EPISODE_LEN, OBS_DIM), (EPISODE_LEN, ACTION_DIM), (EPISODE_LEN,)))
            for _ in range(EPISODES)]


def labelled(n, rng):
    """D with n labelled pairs of (obs, action) segments."""
    inputs = [torch.as_tensor(rng.standard_normal((n, SEGMENT_LEN, OBS_DIM + ACTION_DIM)), dtype=torch.float32)
              for _ in range(2)]
    return {"inputs0": inputs[0], "inputs1": inputs[1], "y": torch.ones(n)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed sessions per sampler and size of D")
    repeats = parser.parse_args().repeats
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    episodes = query_pool(rng)
    model = pebble.RewardEnsemble(OBS_DIM, ACTION_DIM, 3)
    args = SimpleNamespace(segment_len=SEGMENT_LEN, candidate_multiplier=10)
    sizes = (100, 900)
    seconds = {(sampler, n): [] for sampler in SAMPLERS for n in sizes}
    for _ in range(repeats):
        for n in sizes:
            preferences = labelled(n, rng)
            for sampler in SAMPLERS:
                start = time.perf_counter()
                pebble.sample_queries(sampler, QUERIES, episodes, model, preferences, args, rng)
                seconds[sampler, n].append(time.perf_counter() - start)
    print(f"query selection of one feedback session, walker-walk CPU scale, median of {repeats}, one thread\n")
    print("| sampler | s, 100 labelled | x disagreement | s, 900 labelled | x disagreement |")
    print("|---|---:|---:|---:|---:|")
    default = {n: statistics.median(seconds["disagreement", n]) for n in sizes}
    for sampler in SAMPLERS:
        cells = []
        for n in sizes:
            median = statistics.median(seconds[sampler, n])
            cells += [f"{median:.3f}", f"{median / default[n]:.2f}"]
        print(f"| {sampler} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
