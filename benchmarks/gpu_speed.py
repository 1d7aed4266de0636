"""Steps per second on one GPU, side by side in one run (issue 48): CleanRL's SAC (eager, a fetched copy),
pebble.py eager and pebble.py --compile, at 256 x 2 / batch 256 and 1024 x 2 / batch 1024, in SAC's learning phase
on Hopper-v4's true reward (5000 random steps first); then a whole PEBBLE run (Hopper-v5, oracle, 1024 x 2:
pre-training, sessions, relabelling) eager and compiled, by phase (rime.py's too with --whole-run-scripts pebble rime).

    python benchmarks/gpu_speed.py --cleanrl reference/cleanrl --steps 4000
    # reference/cleanrl: a copy of vwxyzjn/cleanrl's cleanrl/sac_continuous_action.py and cleanrl_utils/ (git-ignored)

Rates: steps/s from the end of the first 1000 learning steps to the last step; "first 1000" is the time of those
steps, which holds the compilation and the CUDA graphs' recording (compile time, reported apart). CleanRL's networks
are 256 wide in its file: the 1024 run uses a copy with 1024 there.
"""

import argparse
import csv
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RANDOM_STEPS = 5000
WHOLE_RUN = ["--env-id", "Hopper-v5", "--teacher", "oracle", "--total-timesteps", "16000", "--unsup-steps", "3000",
             "--feedback-every", "3000", "--max-feedback", "400", "--feedback-per-session", "100", "--eval-every",
             "1000", "--eval-episodes", "1", "--hidden-dim", "1024", "--num-layers", "2", "--batch-size", "1024"]


def walls(out: Path) -> list[tuple[int, float]]:
    """(step, seconds since the start) at each evaluation of a pebble.py run."""
    with open(out / "eval.csv") as f:
        return [(int(row["step"]), float(row["wall_time"])) for row in csv.DictReader(f)]


def learning_rate_of(points: list[tuple[int, float]]) -> tuple[float, float]:
    """steps/s after the first 1000 learning steps, and those 1000 steps' seconds."""
    start = next((s, t) for s, t in points if s >= RANDOM_STEPS)
    warm = next((s, t) for s, t in points if s >= RANDOM_STEPS + 1000)
    last = points[-1]
    return (last[0] - warm[0]) / (last[1] - warm[1]), warm[1] - start[1]


def pebble_sac(hidden: int, steps: int, compiled: bool, out: Path) -> tuple[float, float]:
    flags = ["--env-id", "Hopper-v4", "--ground-truth-reward", "--seed-steps", str(RANDOM_STEPS), "--unsup-steps",
             "0", "--total-timesteps", str(RANDOM_STEPS + steps), "--eval-every", "1000", "--eval-episodes", "1",
             "--hidden-dim", str(hidden), "--num-layers", "2", "--batch-size", str(hidden), "--checkpoint-every", "0",
             "--output-dir", str(out), *(["--compile"] if compiled else [])]
    subprocess.run([sys.executable, str(ROOT / "pebble.py"), *flags], check=True, stdout=subprocess.DEVNULL)
    return learning_rate_of(walls(out))


def cleanrl_sac(source: Path, hidden: int, steps: int, work: Path) -> tuple[float, float]:
    """CleanRL's SAC, its networks hidden wide; its SPS lines (every 100 learning steps) give the clock."""
    copy = work / f"cleanrl_{hidden}"
    shutil.copytree(source, copy)
    script = copy / "sac_continuous_action.py"
    script.write_text(script.read_text().replace("256", str(hidden)))  # its widths (and batch default) only
    result = subprocess.run([sys.executable, str(script), "--env-id", "Hopper-v4", "--total-timesteps",
                             str(RANDOM_STEPS + steps + 1), "--batch-size", str(hidden), "--learning-starts",
                             str(RANDOM_STEPS)], cwd=copy, capture_output=True, text=True, check=True)
    sps = [int(value) for value in re.findall(r"^SPS: (\d+)$", result.stdout, re.M)]
    points = [(RANDOM_STEPS + 100 * (i + 1), (RANDOM_STEPS + 100 * (i + 1)) / rate) for i, rate in enumerate(sps)]
    return learning_rate_of([(RANDOM_STEPS, points[0][1] - 100 / sps[0])] + points)


def phases(points: list[tuple[int, float]]) -> dict[str, float]:
    """The whole run's steps/s by phase: pre-training (to 4000), with sessions (4000-16000), all."""
    at = dict(points)
    return {"pre-training": 4000 / at[4000], "after pre-training": (16000 - 4000) / (at[16000] - at[4000]),
            "whole run": 16000 / at[16000]}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cleanrl", type=Path, help="a folder with CleanRL's sac_continuous_action.py and "
                                                     "cleanrl_utils/ (left out: no CleanRL rows)")
    parser.add_argument("--steps", type=int, default=4000, help="learning steps per SAC run")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 1024], help="widths (= batch sizes)")
    parser.add_argument("--no-whole-run", action="store_true", help="skip the whole PEBBLE runs")
    parser.add_argument("--whole-run-scripts", nargs="+", default=["pebble"], choices=["pebble", "rime"],
                        help="the scripts of the whole runs")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="gpu_speed_"))
    print("| run | width x 2, batch | steps/s | first 1000 steps (s) | / pebble.py eager |\n|---|---|---:|---:|---:|")
    for hidden in args.sizes:
        eager = pebble_sac(hidden, args.steps, False, work / f"eager_{hidden}")
        runs = {"pebble.py eager": lambda: eager,
                "pebble.py --compile": lambda: pebble_sac(hidden, args.steps, True, work / f"compiled_{hidden}")}
        if args.cleanrl:
            runs["CleanRL SAC eager"] = lambda: cleanrl_sac(args.cleanrl, hidden, args.steps, work)
        for name, run in runs.items():  # each row printed as soon as it is measured
            rate, first = run()
            print(f"| {name} | {hidden}, {hidden} | {rate:.1f} | {first:.1f} | {rate / eager[0]:.2f} |", flush=True)
    if args.no_whole_run:
        return
    for script in args.whole_run_scripts:
        runs = {}
        for name, extra in (("eager", []), ("--compile", ["--compile"])):
            out = work / f"whole_{script}_{name.strip('-')}"
            subprocess.run([sys.executable, str(ROOT / f"{script}.py"), *WHOLE_RUN, "--output-dir", str(out),
                            *extra], check=True, stdout=subprocess.DEVNULL)
            runs[name] = phases(walls(out))
        print(f"\nWhole {script}.py run, Hopper-v5, 1024 x 2, batch 1024 (steps/s):\n")
        print("| phase | eager | --compile | ratio |\n|---|---:|---:|---:|")
        for phase in runs["eager"]:
            eager, compiled = runs["eager"][phase], runs["--compile"][phase]
            print(f"| {phase} | {eager:.1f} | {compiled:.1f} | {compiled / eager:.2f} |")


if __name__ == "__main__":
    main()
