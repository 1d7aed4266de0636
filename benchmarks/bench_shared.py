"""Timings of the shared, torch-free parts: SimTeacher.label, select (coverage, hybrid) and
random_pairs, plus a naive reference-style k-center on the same data for a side-by-side speedup.

    python benchmarks/bench_shared.py            # prints a Markdown table
    python benchmarks/bench_shared.py --skip-naive

Each operation: one warm-up call, then the best of 5 timed calls (time.perf_counter).
The naive k-center is slow (tens of seconds), so it is timed once, without warm-up.
"""

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from samplers import random_pairs, select  # noqa: E402
from sim_teacher import make_teacher  # noqa: E402

REPEATS = 5
H = 50  # segment length
STATE_DIM = 78  # quadruped observation size: features are 2 * H * 78 = 7800 wide


def best_ms(fn, repeats=REPEATS, warmup=True):
    if warmup:
        fn()
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best * 1e3


def naive_k_center(features, n_query, labeled_features):
    """Reference-style greedy k-center (B-Pref's KCenterGreedy): at every pick, recompute the
    distance of every remaining candidate to every center (labelled queries + picks so far).
    Distances via ||a||^2 + ||b||^2 - 2ab in chunks (BLAS), which is kinder to it than the
    reference's broadcast subtraction; the work is still O(picks * M * K * D)."""
    remaining = list(range(len(features)))
    chosen = []
    centers = labeled_features
    for _ in range(n_query):
        candidates = features[remaining]
        cand_norms = np.einsum("md,md->m", candidates, candidates)
        nearest = np.full(len(candidates), np.inf, dtype=features.dtype)
        for start in range(0, len(centers), 1024):
            chunk = centers[start : start + 1024]
            squared = cand_norms[:, None] + np.einsum("kd,kd->k", chunk, chunk)[None] - 2 * candidates @ chunk.T
            nearest = np.minimum(nearest, squared.min(axis=1))
        pick = remaining.pop(int(np.argmax(nearest)))
        chosen.append(pick)
        centers = np.concatenate([labeled_features, features[chosen]], axis=0)
    return np.array(chosen)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--skip-naive", action="store_true", help="do not time the naive k-center")
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    rows = []  # (operation, size, best ms, target ms or None)

    # (a) SimTeacher.label: 100,000 pairs of H = 50
    n_pairs = 100_000
    rewards0 = rng.standard_normal((n_pairs, H))
    rewards1 = rng.standard_normal((n_pairs, H))
    for name, teacher in [
        ("oracle", make_teacher("oracle", seed=0)),
        ("stoc", make_teacher("stoc", seed=0)),
        ("myopic+mistake", make_teacher("myopic", seed=0, eps_mistake=0.1)),
    ]:
        ms = best_ms(lambda: teacher.label(rewards0, rewards1))
        rows.append((f"SimTeacher.label ({name})", f"{n_pairs:,} pairs, H={H}", ms, 50.0))

    # (b) coverage and disagreement-coverage: 100 of 1,000 candidates, D = 7800, 2,000 labelled
    n_candidates, n_query, n_labeled, dim = 1_000, 100, 2_000, 2 * H * STATE_DIM
    features = rng.standard_normal((n_candidates, dim), dtype=np.float32)
    labeled = rng.standard_normal((n_labeled, dim), dtype=np.float32)
    probs = rng.random((3, n_candidates))
    size = f"{n_query} of {n_candidates:,}, D={dim}, {n_labeled:,} labelled (float32)"
    chosen_fast = select("coverage", n_query, features=features, labeled_features=labeled)
    ms_cov = best_ms(lambda: select("coverage", n_query, features=features, labeled_features=labeled))
    rows.append(("select coverage (incremental k-center)", size, ms_cov, 2000.0))
    ms = best_ms(
        lambda: select("disagreement-coverage", n_query, probs=probs, features=features, labeled_features=labeled)
    )
    rows.append(("select disagreement-coverage (n_inter=500)", size, ms, 2000.0))

    # (c) naive reference-style k-center on the same data
    notes = []
    if not args.skip_naive:
        start = time.perf_counter()
        chosen_naive = naive_k_center(features, n_query, labeled)
        ms_naive = (time.perf_counter() - start) * 1e3
        rows.append(("naive k-center (recompute all distances each pick; 1 run)", size, ms_naive, None))
        agree = len(set(chosen_naive.tolist()) & set(chosen_fast.tolist()))
        notes.append(f"speedup of select coverage over the naive k-center: {ms_naive / ms_cov:.1f}x")
        notes.append(f"picks in common with the naive k-center: {agree}/{n_query}")

    # (d) random_pairs: 10,000 pairs over 1,000 episodes
    lengths = rng.integers(100, 1001, size=1_000)
    ms = best_ms(lambda: random_pairs(lengths, H, 10_000, np.random.default_rng(1)))
    rows.append(("random_pairs", f"10,000 pairs, 1,000 episodes (100-1000 steps), segment {H}", ms, None))

    print("| operation | size | best ms | target ms | meets target |")
    print("|---|---|---:|---:|---|")
    for operation, size_text, ms, target in rows:
        target_text = "-" if target is None else f"{target:.0f}"
        meets = "-" if target is None else ("yes" if ms <= target else "NO")
        print(f"| {operation} | {size_text} | {ms:.2f} | {target_text} | {meets} |")
    for note in notes:
        print(f"\n{note}")
    print(f"\nnumpy {np.__version__}, Python {sys.version.split()[0]}; best of {REPEATS} after a warm-up")


if __name__ == "__main__":
    main()
