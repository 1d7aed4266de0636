"""CPU-scale learning results, each method against --ground-truth-reward, several seeds; then a table.

  pebble:  walker-walk, 100K steps, 256 x 2 networks, batch 256, oracle teacher, 1000 labels
  prefppo: walker-walk, 1M steps, the paper's PrefPPO preset (256 x 3, 32 envs), oracle, 1000 labels

    python benchmarks/learning_cpu.py --algo pebble                   # run (2 at a time, 1 thread each), summarise
    python benchmarks/learning_cpu.py --algo pebble --summarize-only  # the table from finished runs

Wall times of runs that share the machine are noisy; the preference-learning cost is therefore also
measured inside each run (eval.csv column overhead_seconds: kNN reward, queries, reward learning,
relabelling).
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
ALGOS = {
    "pebble": dict(
        total=100_000,
        common=["--env-id", "walker-walk", "--total-timesteps", "100000", "--hidden-dim", "256", "--num-layers", "2",
                "--batch-size", "256", "--eval-every", "10000", "--eval-episodes", "10"],
        # 10 sessions of 100 (steps 10001, 19001, ..., 91001) spend the 1000 labels within 100K steps
        methods={"pebble": ["--teacher", "oracle", "--max-feedback", "1000", "--feedback-per-session", "100",
                            "--feedback-every", "9000"],
                 "sac_true_reward": ["--ground-truth-reward"]},
    ),
    "prefppo": dict(
        total=1_000_000,
        common=["--env-id", "walker-walk", "--total-timesteps", "1000000", "--eval-every", "50000", "--eval-episodes", "10"],
        # sessions every 32K steps from the end of pre-training (32K) spend 1000 labels by 320K
        methods={"prefppo": ["--teacher", "oracle", "--max-feedback", "1000", "--feedback-per-session", "100"],
                 "ppo_true_reward": ["--ground-truth-reward"]},
    ),
}


def read_rows(path: Path) -> list[dict]:
    with open(path) as f:
        rows = [{k: float(v) if v not in ("", "nan") else float("nan") for k, v in row.items()} for row in csv.DictReader(f)]
    for row in rows:  # runs made before the column was renamed
        row.setdefault("overhead_seconds", row.get("pebble_seconds", float("nan")))
    return rows


def summarize(algo: str, out: Path, seeds: list[int]):
    results = {}
    for method in ALGOS[algo]["methods"]:
        runs = [read_rows(out / f"{method}_seed{s}" / "eval.csv") for s in seeds if (out / f"{method}_seed{s}" / "eval.csv").exists()]
        results[method] = [r for r in runs if r and r[-1]["step"] >= ALGOS[algo]["total"]]
    print(f"\n{algo}: {' '.join(ALGOS[algo]['common'])}; CPU; seeds {seeds}\n")
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
    preference, true_reward = (results[m] for m in ALGOS[algo]["methods"])
    if preference and true_reward:
        def mean_of(runs, field, last=True):
            return np.mean([r[-1][field] if last else np.mean([row[field] for row in r]) for r in runs])

        print(f"\nnormalized return ({algo} / true reward): final "
              f"{mean_of(preference, 'episode_return') / mean_of(true_reward, 'episode_return'):.3f}, averaged over "
              f"evaluations {mean_of(preference, 'episode_return', False) / mean_of(true_reward, 'episode_return', False):.3f}")
        own, knn, wall = (mean_of(preference, "overhead_seconds"), mean_of(true_reward, "overhead_seconds"),
                          mean_of(true_reward, "wall_time"))
        print(f"{algo}'s own cost: {own:.0f} s (kNN pre-training included; the true-reward run spends {knn:.0f} s "
              f"on the same kNN) = {own / wall:.1%} of the true-reward run's wall time; without the shared kNN "
              f"{(own - knn) / wall:.1%}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=sorted(ALGOS), default="pebble")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--parallel", type=int, default=2, help="runs at once (each gets one thread)")
    parser.add_argument("--out", type=Path, default=None, help="default: runs/bench_<algo>_cpu")
    parser.add_argument("--summarize-only", action="store_true")
    parser.add_argument("--total-timesteps", type=int, default=None, help="a shorter (or longer) run than the preset")
    args = parser.parse_args()
    args.out = args.out or ROOT / "runs" / f"bench_{args.algo}_cpu"
    algo = ALGOS[args.algo]
    if args.total_timesteps:
        algo["total"] = args.total_timesteps
        algo["common"] = [*algo["common"], "--total-timesteps", str(args.total_timesteps)]
    if not args.summarize_only:
        jobs = [(m, s) for s in args.seeds for m in algo["methods"] if not (args.out / f"{m}_seed{s}" / "eval.csv").exists()]
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONWARNINGS="ignore")
        running = []
        while jobs or running:
            while jobs and len(running) < args.parallel:
                method, seed = jobs.pop(0)
                run_dir = args.out / f"{method}_seed{seed}"
                cmd = [sys.executable, str(ROOT / f"{args.algo}.py"), *algo["common"], *algo["methods"][method], "--seed", str(seed), "--output-dir", str(run_dir)]
                print("running:", " ".join(cmd[1:]), flush=True)
                args.out.mkdir(parents=True, exist_ok=True)
                with open(args.out / f"{method}_seed{seed}.log", "w") as log:
                    running.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env))
            time.sleep(5)
            running = [p for p in running if p.poll() is None]
    summarize(args.algo, args.out, args.seeds)
