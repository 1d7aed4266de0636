"""CPU-scale PEBBLE result: walker-walk, 100K steps, 256 x 2 networks, batch 256, oracle teacher and
1000 labels, against --ground-truth-reward, several seeds each; then a summary table.

    python benchmarks/pebble_cpu.py                    # run all (2 at a time, 1 thread each) and summarise
    python benchmarks/pebble_cpu.py --summarize-only   # just the table from finished runs

Wall times of runs that share the machine are noisy; PEBBLE's own cost is therefore also measured
inside each run (eval.csv column overhead_seconds: kNN reward, queries, reward learning, relabelling).
"""

import argparse
import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
COMMON = ["--env-id", "walker-walk", "--total-timesteps", "100000", "--hidden-dim", "256", "--num-layers", "2",
          "--batch-size", "256", "--eval-every", "10000", "--eval-episodes", "10"]
METHODS = {
    # 10 sessions of 100 (steps 10001, 19001, ..., 91001) spend the 1000 labels within 100K steps
    "pebble": ["--teacher", "oracle", "--max-feedback", "1000", "--feedback-per-session", "100", "--feedback-every", "9000"],
    "sac_true_reward": ["--ground-truth-reward"],
}


def read_rows(path: Path) -> list[dict]:
    with open(path) as f:
        rows = [{k: float(v) if v not in ("", "nan") else float("nan") for k, v in row.items()} for row in csv.DictReader(f)]
    for row in rows:  # runs made before the column was renamed
        row.setdefault("overhead_seconds", row.get("pebble_seconds", float("nan")))
    return rows


def summarize(out: Path, seeds: list[int]):
    results = {}
    for method in METHODS:
        runs = [read_rows(out / f"{method}_seed{s}" / "eval.csv") for s in seeds if (out / f"{method}_seed{s}" / "eval.csv").exists()]
        runs = [r for r in runs if r and r[-1]["step"] >= 100000]
        results[method] = runs
    print(f"\nwalker-walk, 100K steps, 256 x 2, batch 256, CPU; seeds {seeds}\n")
    print("| method | seeds done | final return (mean ± std) | mean return over evals | final reward_correlation | wall time (min) | overhead_seconds / wall |")
    print("|---|---|---|---|---|---|---|")
    for method, runs in results.items():
        if not runs:
            print(f"| {method} | 0 | - | - | - | - | - |")
            continue
        finals = np.array([r[-1]["episode_return"] for r in runs])
        curves = np.array([np.mean([row["episode_return"] for row in r]) for r in runs])
        corr = np.array([r[-1]["reward_correlation"] for r in runs])
        wall = np.array([r[-1]["wall_time"] for r in runs])
        overhead = np.array([r[-1]["overhead_seconds"] / r[-1]["wall_time"] for r in runs])
        corr_text = "-" if np.isnan(corr).all() else f"{np.nanmean(corr):.3f} ± {np.nanstd(corr):.3f}"
        print(f"| {method} | {len(runs)} | {finals.mean():.1f} ± {finals.std():.1f} | {curves.mean():.1f} | {corr_text} "
              f"| {wall.mean() / 60:.1f} | {overhead.mean():.3f} |")
    if results["pebble"] and results["sac_true_reward"]:
        pebble_final = np.mean([r[-1]["episode_return"] for r in results["pebble"]])
        true_final = np.mean([r[-1]["episode_return"] for r in results["sac_true_reward"]])
        pebble_curve = np.mean([np.mean([row["episode_return"] for row in r]) for r in results["pebble"]])
        true_curve = np.mean([np.mean([row["episode_return"] for row in r]) for r in results["sac_true_reward"]])
        pebble_own = np.mean([r[-1]["overhead_seconds"] for r in results["pebble"]])
        true_knn = np.mean([r[-1]["overhead_seconds"] for r in results["sac_true_reward"]])
        true_wall = np.mean([r[-1]["wall_time"] for r in results["sac_true_reward"]])
        print(f"\nnormalized return (PEBBLE / SAC with true reward): final {pebble_final / true_final:.3f}, "
              f"averaged over evaluations {pebble_curve / true_curve:.3f}")
        print(f"PEBBLE's own cost: {pebble_own:.0f} s (its kNN pre-training included; the true-reward run spends "
              f"{true_knn:.0f} s on the same kNN) = {pebble_own / true_wall:.1%} of the true-reward run's wall time")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--parallel", type=int, default=2, help="runs at once (each gets one thread)")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_pebble_cpu")
    parser.add_argument("--summarize-only", action="store_true")
    args = parser.parse_args()
    if not args.summarize_only:
        jobs = [(m, s) for s in args.seeds for m in METHODS if not (args.out / f"{m}_seed{s}" / "eval.csv").exists()]
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONWARNINGS="ignore")
        running = []
        while jobs or running:
            while jobs and len(running) < args.parallel:
                method, seed = jobs.pop(0)
                run_dir = args.out / f"{method}_seed{seed}"
                cmd = [sys.executable, str(ROOT / "pebble.py"), *COMMON, *METHODS[method], "--seed", str(seed), "--output-dir", str(run_dir)]
                print("running:", " ".join(cmd[1:]), flush=True)
                args.out.mkdir(parents=True, exist_ok=True)
                with open(args.out / f"{method}_seed{seed}.log", "w") as log:
                    running.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env))
            time.sleep(5)
            running = [p for p in running if p.poll() is None]
    summarize(args.out, args.seeds)
