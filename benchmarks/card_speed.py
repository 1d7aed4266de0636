"""How long the README's first command takes: `python pebble.py --env-id quadruped-walk --teacher myopic` (the paper's
sizes: 1M steps, 1024 x 2, batch 1024, 1000 labels in sessions of 100 every 30K) run as it is for a few minutes,
stopped by SIGTERM, and the whole run projected from the wall time of its 10K-step blocks (from one evaluation to the
next: each holds the command's own evaluation, 10 episodes; docs/results.md, the paper's four tasks).

    python benchmarks/card_speed.py --seconds 480            # on a GPU: about 40K steps in 8 minutes
    python benchmarks/card_speed.py --seconds 120 -- --hidden-dim 64 --batch-size 64   # any extra pebble.py flags

Blocks: the first (steps 1-10K) is pre-training (1000 random steps, then SAC on the kNN reward); the one that holds a
feedback session (step 10,001, then every 30K) pays for the session (query selection, the teacher, reward learning,
relabelling) on top of SAC on r_hat; the others are SAC on r_hat alone. A session's reward learning runs 50 epochs
over every label so far, so the k-th session is taken to cost k times the first one's extra time (an upper estimate:
query selection and relabelling do not grow with the labels).
"""

import argparse
import csv
import json
import math
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_for(seconds: float, out: Path, extra: list[str]) -> int:
    """The card's command for this long, then SIGTERM (it checkpoints and exits); its exit code."""
    command = [sys.executable, str(ROOT / "pebble.py"), "--env-id", "quadruped-walk", "--teacher", "myopic",
               "--output-dir", str(out), *extra]
    print("$", " ".join(command[1:]), flush=True)
    process = subprocess.Popen(command)
    try:
        process.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGTERM)
    return process.wait()


def projection(rows: list[dict], config: dict) -> tuple[list[tuple], float]:
    """Each measured block (steps, kind, seconds, steps/s) and the projected seconds of the whole run."""
    first_session = config["seed_steps"] + config["unsup_steps"] + 1
    sessions = math.ceil(config["max_feedback"] / config["feedback_per_session"])
    session_steps = [first_session + k * config["feedback_every"] for k in range(sessions)]
    blocks, before = [], (0, 0.0)
    for row in rows:
        step, wall = int(row["step"]), float(row["wall_time"])
        holds = [s for s in session_steps if before[0] < s <= step]
        kind = "pre-training" if step <= first_session - 1 else ("session + SAC" if holds else "SAC on r_hat")
        blocks.append((f"{before[0] + 1}-{step}", kind, wall - before[1], (step - before[0]) / (wall - before[1])))
        before = (step, wall)
    times = {kind: [seconds for _, k, seconds, _ in blocks if k == kind] for kind in
             ("pre-training", "session + SAC", "SAC on r_hat")}
    pre_blocks = math.ceil((first_session - 1) / config["eval_every"])
    if len(times["pre-training"]) < pre_blocks or not (times["session + SAC"] and times["SAC on r_hat"]):
        return blocks, math.nan
    sac = statistics.median(times["SAC on r_hat"])
    extra = max(times["session + SAC"][0] - sac, 0.0)  # the first session's
    total_blocks = math.ceil(config["total_timesteps"] / config["eval_every"])
    total = sum(times["pre-training"]) + (total_blocks - pre_blocks) * sac + extra * sessions * (sessions + 1) / 2
    return blocks, total


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=480, help="how long the command runs before SIGTERM")
    parser.add_argument("--out", default=None, help="the run's folder (default: a new temporary one)")
    parser.add_argument("extra", nargs="*", help="pebble.py flags after --")
    args = parser.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="card_speed_")) / "card"
    start = time.time()
    code = run_for(args.seconds, out, args.extra)
    with open(out / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    config = json.loads((out / "config.json").read_text())
    blocks, total = projection(rows, config)
    print(f"\nexit {code} after {time.time() - start:.0f} s; {len(rows)} blocks of {config['eval_every']} steps measured\n")
    print("| steps | phase | seconds | steps/s |\n|---|---|---:|---:|")
    for steps, kind, seconds, rate in blocks:
        print(f"| {steps} | {kind} | {seconds:.0f} | {rate:.1f} |")
    hours = "-" if math.isnan(total) else f"{total / 3600:.1f} h"
    print(f"\nprojected whole run ({config['total_timesteps']} steps): {hours} "
          "(needs one block of each phase)")


if __name__ == "__main__":
    main()
