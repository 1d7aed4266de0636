"""The B-Pref protocol as a grid of runs: algorithms x tasks x teachers x budgets x samplers x schedules x seeds,
plus the --ground-truth-reward runs that normalise them (one per algorithm x task x seed). Docs: docs/experiments.md

    python experiments/grid.py mini-bpref                                  # the 2-hour CPU preset, 2 workers
    python experiments/grid.py custom --env-ids walker-walk --teachers oracle mistake --seeds 1 2 3 \\
        --budgets 1000/100 500/50 --flags='--total-timesteps 100000 --hidden-dim 256' --workers 4
    python experiments/grid.py custom ... --backend ray --ray-address auto  # each run a task on a Ray cluster
    python experiments/report.py runs/mini-bpref                           # tables and plots

Each run is its own process of pebble.py / prefppo.py with its own output directory <root>/<name>, a name made
from its settings; its output goes to <root>/logs/<name>.log (outside the run directory, which the scripts
want empty at the start). Running the same grid again skips finished runs, resumes the others from their
checkpoint (--resume) and starts afresh those that stopped before one (the partial directory is moved to
<root>/.aside/). <root>/grid.json keeps each run's command and last exit code.
"""

import concurrent.futures
import csv
import importlib
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from samplers import SAMPLERS, SCHEDULES  # noqa: E402
from sim_teacher import TEACHERS  # noqa: E402
from benchmarks.reference.edits import EDITS  # noqa: E402

ALGORITHMS = ("pebble", "prefppo", "rime", "qpa")
IMPLEMENTATIONS = ("ours", "reference")  # reference: BPref (RIME's, QPA's fork) through benchmarks/reference/run.py
REFERENCE_RUNNER = ROOT / "benchmarks" / "reference" / "run.py"
EDITS_RUNNER = ROOT / "benchmarks" / "reference" / "edits.py"
# Flags the grid sets for each run; --flags must not set them too
GRID_FLAGS = ("--env-id", "--seed", "--teacher", "--sampler", "--schedule", "--max-feedback", "--feedback-per-session",
              "--ground-truth-reward", "--output-dir", "--resume")
EXIT_MEANINGS = {0: "ok", 1: "an unexpected error: its log has the traceback", 2: "bad input",
                 3: "non-finite value", 4: "a write failed (a full disk?)"}


@dataclass(frozen=True)
class Grid:
    algorithms: tuple[str, ...] = ("pebble",)
    """pebble, prefppo, rime and/or qpa"""
    implementations: tuple[str, ...] = ("ours",)
    """ours and/or reference (the reference code: PEBBLE, SAC, PrefPPO; RIME's, QPA's own; benchmarks/reference)"""
    env_ids: tuple[str, ...] = ("walker-walk",)
    """tasks (any --env-id of the scripts)"""
    teachers: tuple[str, ...] = tuple(TEACHERS)
    """simulated teachers: oracle, stoc, mistake, skip, equal, myopic"""
    budgets: tuple[str, ...] = ("preset",)
    """max_feedback[/feedback_per_session], e.g. 1000/100 or 500; 'preset' = the task's preset"""
    samplers: tuple[str, ...] = ("disagreement",)
    """query samplers; 'default' = each script's own (pebble, rime, prefppo: disagreement; qpa: uniform)"""
    schedules: tuple[str, ...] = ("uniform",)
    """feedback schedules"""
    seeds: tuple[int, ...] = (1, 2, 3)
    """seeds of every configuration"""
    ground_truth: bool = True
    """also run --ground-truth-reward once per algorithm x task x seed (the normalisation's denominator)"""
    preference_runs: bool = True
    """run the teachers x budgets x samplers x schedules x seeds (--no-preference-runs: ground-truth runs only)"""
    flags: str = ""
    """more flags for every run, as one string: --flags='--total-timesteps 100000 --hidden-dim 256'"""
    pebble_flags: str = ""
    """more flags for pebble.py runs only (one string, as --flags)"""
    prefppo_flags: str = ""
    """more flags for prefppo.py runs only (one string, as --flags)"""
    rime_flags: str = ""
    """more flags for rime.py runs only (one string, as --flags)"""
    qpa_flags: str = ""
    """more flags for qpa.py runs only (one string, as --flags)"""
    edits: tuple[str, ...] = ()
    """the reference code's ways, applied to copies of our scripts (benchmarks/reference/edits.py)"""
    root: str = "runs/grid"
    """folder of the runs (on a Ray cluster: a folder every node sees at the same path)"""
    backend: Literal["local", "ray"] = "local"
    """local: a pool of --workers processes on this machine; ray: each run a Ray task"""
    workers: int = 2
    """runs at once (local backend, and the CPUs of a Ray instance started here)"""
    ray_address: str | None = None
    """address of an existing Ray cluster ('auto' = the one this machine belongs to); none: start one here"""
    cpus_per_run: int = 1
    """CPU cores (and torch threads) per run"""
    gpus_per_run: float = 0.0
    """GPUs per run on Ray (e.g. 0.25: four runs share a GPU; add --flags='--cuda')"""
    dry_run: bool = False
    """print what would run (start, resume or skip, with the commands) and its core-hours, and stop"""
    retry_non_finite: bool = False
    """resume the runs that stopped on a non-finite value (exit code 3), once its cause is fixed"""
    progress_every: float = 60.0
    """seconds between progress lines"""


# Presets: `python experiments/grid.py NAME [overrides]`; `custom` is the bare grid
# The README's CPU scale: 10 sessions of 100 (steps 10001, 19001, ..., 91001) spend 1000 labels within 100K steps
CPU_PEBBLE = ("--total-timesteps 100000 --hidden-dim 256 --num-layers 2 --batch-size 256 --eval-every 10000 "
              "--eval-episodes 10 --feedback-every 9000")
CPU_PREFPPO = "--total-timesteps 1000000 --eval-every 50000 --eval-episodes 10"  # docs/results.md
MINI_BPREF = Grid(
    env_ids=("walker-walk",), budgets=("300/30",), seeds=(1, 2, 3, 4, 5), root="runs/mini-bpref",
    # 40K steps, 128 x 2 networks, pre-training until 5K, 10 sessions of 30 queries every 3500 steps (5001 ... 36501),
    # at most 20 reward epochs per session (paper: 50); the rest as the walker-walk preset (docs/experiments.md)
    flags="--total-timesteps 40000 --hidden-dim 128 --num-layers 2 --batch-size 128 --unsup-steps 4000 "
          "--feedback-every 3500 --reward-epochs 20 --eval-every 5000 --eval-episodes 10 --checkpoint-every 10000")
# Issue 45: pilots of SAC on the true reward that choose each new task's CPU scale (docs/results.md): the most
# steps that fit about 75 minutes on one core at walker-walk's CPU network sizes; curves read at every 10K
CPU_PILOT = ("--total-timesteps 250000 --hidden-dim 256 --num-layers 2 --batch-size 256 --eval-every 10000 "
             "--eval-episodes 10 --checkpoint-every 25000")
# Meta-World at CPU scale: the pilot's SAC succeeds from 50K steps on button-press (docs/results.md); the preset's
# sessions of 50 every 4950 steps from step 10,001, its learning rate, reward epochs and segment length
CPU_METAWORLD = ("--total-timesteps 100000 --hidden-dim 256 --num-layers 2 --batch-size 256 --eval-every 10000 "
                 "--eval-episodes 10 --checkpoint-every 10000")
# sweep-into: the pilot's SAC succeeds at every evaluation from 110K steps on (docs/results.md), so 150K steps;
# the same sessions of 50 every 4950 steps from step 10,001, 28 of them (1400 labels) as button-press's 18 in 100K
CPU_SWEEP_INTO = CPU_METAWORLD.replace("--total-timesteps 100000", "--total-timesteps 150000")
# sweep-into longer: PEBBLE barely learns by 150K (docs/results.md); 250K steps, 48 sessions of 50 (2400 labels)
CPU_SWEEP_INTO_250K = CPU_METAWORLD.replace("--total-timesteps 100000", "--total-timesteps 250000")
# quadruped-walk: the pilots' 250K steps (2-2.7 h a run on a core here); 10 sessions of 100 every 24K from 10,001
CPU_QUADRUPED = CPU_PILOT + " --feedback-every 24000"
PRESETS = {
    "custom": ("a grid of your own (defaults: PEBBLE, walker-walk, six teachers, the task's budget, 3 seeds)", Grid()),
    "mini-bpref": ("PEBBLE on walker-walk at CPU size: six teachers + ground truth, 5 seeds, about 1.5 h on 2 cores "
                   "(docs/experiments.md)", MINI_BPREF),
    "learning-cpu-pebble": (
        "README's CPU learning benchmark: PEBBLE (oracle, 1000 labels) and SAC on the true reward, walker-walk 100K "
        "steps, 256 x 2, 3 seeds",
        Grid(teachers=("oracle",), budgets=("1000/100",), root="runs/learning-cpu-pebble", flags=CPU_PEBBLE)),
    "pilot-sac": (
        "SAC on the true reward, one seed, 250K steps at 256 x 2, on quadruped-walk, button-press and sweep-into: the "
        "pilots that chose each task's CPU scale",
        Grid(env_ids=("quadruped-walk", "button-press", "sweep-into"), preference_runs=False, seeds=(1,),
             root="runs/pilot-sac", flags=CPU_PILOT)),
    # The paper's other tasks at their CPU scale (issue 45; docs/results.md): PEBBLE and SAC on the true reward
    "button-press-cpu": (
        "PEBBLE (oracle, 900 labels in sessions of 50 every 4950 steps) and SAC on the true reward, button-press, "
        "100K steps, 256 x 2, batch 256, 3 seeds",
        Grid(env_ids=("button-press",), teachers=("oracle",), budgets=("900/50",), root="runs/button-press",
             flags=CPU_METAWORLD)),
    "sweep-into-cpu": (
        "PEBBLE (oracle, 1400 labels in sessions of 50 every 4950 steps) and SAC on the true reward, sweep-into, "
        "150K steps, 256 x 2, batch 256, 3 seeds",
        Grid(env_ids=("sweep-into",), teachers=("oracle",), budgets=("1400/50",), root="runs/sweep-into",
             flags=CPU_SWEEP_INTO)),
    "sweep-into-cpu-250k": (
        "PEBBLE (oracle, 2400 labels in sessions of 50 every 4950 steps) and SAC on the true reward, sweep-into, "
        "250K steps, 256 x 2, batch 256, 3 seeds",
        Grid(env_ids=("sweep-into",), teachers=("oracle",), budgets=("2400/50",), root="runs/sweep-into-250k",
             flags=CPU_SWEEP_INTO_250K)),
    "quadruped-walk-cpu": (
        "PEBBLE (oracle, 1000 labels in sessions of 100 every 24K steps) and SAC on the true reward, quadruped-walk, "
        "250K steps, 256 x 2, batch 256, 3 seeds",
        Grid(env_ids=("quadruped-walk",), teachers=("oracle",), budgets=("1000/100",), root="runs/quadruped-walk",
             flags=CPU_QUADRUPED)),
    "quadruped-walk-myopic-cpu": (
        "PEBBLE with the myopic teacher (the README's first command's) as quadruped-walk-cpu, in its root so that one "
        "report compares it with that preset's SAC runs, 3 seeds",
        Grid(env_ids=("quadruped-walk",), teachers=("myopic",), budgets=("1000/100",), ground_truth=False,
             root="runs/quadruped-walk", flags=CPU_QUADRUPED)),
    "quadruped-walk-cpu-prefppo": (
        "PrefPPO (oracle, 1000 labels in sessions of 100 every 32K steps) and PPO on the true reward, quadruped-walk, "
        "1M steps, the paper's PrefPPO preset, 3 seeds",
        Grid(algorithms=("prefppo",), env_ids=("quadruped-walk",), teachers=("oracle",), budgets=("1000/100",),
             root="runs/quadruped-walk-prefppo", flags=CPU_PREFPPO)),
    "button-press-cpu-prefppo": (
        "PrefPPO (oracle, 6100 labels in sessions of 100 every 16K steps) and PPO on the true reward, button-press, "
        "1M steps, the paper's PrefPPO preset, 3 seeds",
        Grid(algorithms=("prefppo",), env_ids=("button-press",), teachers=("oracle",), budgets=("6100/100",),
             root="runs/button-press-prefppo", flags=CPU_PREFPPO)),
    "sweep-into-cpu-prefppo": (
        "PrefPPO (oracle, 6100 labels in sessions of 100 every 16K steps) and PPO on the true reward, sweep-into, "
        "1M steps, the paper's PrefPPO preset, 3 seeds",
        Grid(algorithms=("prefppo",), env_ids=("sweep-into",), teachers=("oracle",), budgets=("6100/100",),
             root="runs/sweep-into-prefppo", flags=CPU_PREFPPO)),
    # Parity with the reference code (docs/parity.md): one root, so that one report compares every pair
    "parity-pebble": (
        "PEBBLE (oracle, 1000 labels) at the README's CPU scale, ours and the reference code's, 5 seeds each",
        Grid(implementations=IMPLEMENTATIONS, teachers=("oracle",), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5),
             ground_truth=False, root="runs/parity", flags=CPU_PEBBLE)),
    "parity-pebble-mistake": (
        "PEBBLE under the mistake teacher (eps 0.1), as parity-pebble, 3 seeds each",
        Grid(implementations=IMPLEMENTATIONS, teachers=("mistake",), budgets=("1000/100",), ground_truth=False,
             root="runs/parity", flags=CPU_PEBBLE)),
    "parity-pebble-cheetah": (
        "PEBBLE (oracle, 1000 labels) on a second task, cheetah-run, as parity-pebble, 3 seeds each",
        Grid(implementations=IMPLEMENTATIONS, env_ids=("cheetah-run",), teachers=("oracle",), budgets=("1000/100",),
             ground_truth=False, root="runs/parity", flags=CPU_PEBBLE)),
    "parity-sac": (
        "SAC on the true reward (the same pre-training and critic reset) at the README's CPU scale, ours and the "
        "reference code's train_SAC.py, 3 seeds each",
        Grid(implementations=IMPLEMENTATIONS, preference_runs=False, root="runs/parity", flags=CPU_PEBBLE)),
    "parity-prefppo": (
        "PrefPPO (oracle, 1000 labels), walker-walk 1M steps, the paper's preset, ours and the reference code's "
        "train_PrefPPO.py, 3 seeds each, compared on training episodes (the reference evaluates no policy)",
        Grid(algorithms=("prefppo",), implementations=IMPLEMENTATIONS, teachers=("oracle",), budgets=("1000/100",),
             ground_truth=False, root="runs/parity", flags=CPU_PREFPPO)),
    "learning-cpu-prefppo": (
        "README's CPU learning benchmark: PrefPPO (oracle, 1000 labels) and PPO on the true reward, walker-walk 1M "
        "steps, the paper's PrefPPO preset, 3 seeds",
        Grid(algorithms=("prefppo",), teachers=("oracle",), budgets=("1000/100",), root="runs/learning-cpu-prefppo",
             flags=CPU_PREFPPO)),
    # RIME against PEBBLE (docs/rime.md): the same runs of each, README's CPU scale, one root per mistake rate
    "rime-mistake": (
        "RIME and PEBBLE under the mistake teacher (eps 0.1, B-Pref's), walker-walk at the README's CPU scale, 5 seeds",
        Grid(algorithms=("pebble", "rime"), teachers=("mistake",), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5),
             ground_truth=False, root="runs/rime", flags=CPU_PEBBLE + " --checkpoint-every 10000")),
    "rime-mistake-0.3": (
        "RIME and PEBBLE under the mistake teacher at eps 0.3 (RIME's hardest), as rime-mistake",
        Grid(algorithms=("pebble", "rime"), teachers=("mistake",), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5),
             ground_truth=False, root="runs/rime-eps0.3",
             flags=CPU_PEBBLE + " --checkpoint-every 10000 --teacher-eps-mistake 0.3")),
    "rime-oracle": (
        "RIME and PEBBLE with the oracle teacher (what RIME costs when no label is wrong), as rime-mistake, 5 seeds",
        Grid(algorithms=("pebble", "rime"), teachers=("oracle",), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5),
             ground_truth=False, root="runs/rime", flags=CPU_PEBBLE)),
    "rime-reference": (
        "RIME's own code (benchmarks/reference/setup_rime.sh) on rime-mistake-0.3's setting and root, 5 seeds, for "
        "report.py --compare rime reference-rime",
        Grid(algorithms=("rime",), implementations=("reference",), teachers=("mistake",), budgets=("1000/100",),
             seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/rime-eps0.3",
             flags=CPU_PEBBLE + " --teacher-eps-mistake 0.3")),
    # QPA against PEBBLE (docs/qpa.md): each asks its own way (--samplers default: qpa.py uniformly from the last 10
    # episodes, pebble.py and rime.py by disagreement), the rest the same; in the roots of the kept runs of PEBBLE
    "qpa-walker-100": (
        "QPA and PEBBLE (oracle, 100 labels: 10 sessions of 10 within 100K steps), walker-walk at the README's CPU "
        "scale, 5 seeds",
        Grid(algorithms=("pebble", "qpa"), teachers=("oracle",), budgets=("100/10",), samplers=("default",),
             seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/qpa-walker", flags=CPU_PEBBLE)),
    "qpa-reference": (
        "QPA's own code (benchmarks/reference/setup_qpa.sh) on qpa-walker-100's setting and root, 5 seeds, for "
        "report.py --compare qpa reference-qpa",
        Grid(algorithms=("qpa",), implementations=("reference",), teachers=("oracle",), budgets=("100/10",),
             samplers=("default",), seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/qpa-walker",
             flags=CPU_PEBBLE)),
    "qpa-walker-1000": (
        "QPA and PEBBLE (oracle, 1000 labels), walker-walk at the README's CPU scale, 5 seeds; PEBBLE's runs are "
        "parity-pebble's (same root)",
        Grid(algorithms=("pebble", "qpa"), teachers=("oracle",), budgets=("1000/100",), samplers=("default",),
             seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/parity", flags=CPU_PEBBLE)),
    "qpa-button-press": (
        "QPA and PEBBLE (oracle, 900 labels in sessions of 50 every 4950 steps), button-press as button-press-cpu, "
        "5 seeds, beside that preset's runs",
        Grid(algorithms=("pebble", "qpa"), env_ids=("button-press",), teachers=("oracle",), budgets=("900/50",),
             samplers=("default",), seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/button-press",
             flags=CPU_METAWORLD)),
    "qpa-sweep-into": (
        "QPA and PEBBLE (oracle, 1400 labels in sessions of 50 every 4950 steps), sweep-into as sweep-into-cpu, "
        "5 seeds, beside that preset's runs",
        Grid(algorithms=("pebble", "qpa"), env_ids=("sweep-into",), teachers=("oracle",), budgets=("1400/50",),
             samplers=("default",), seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/sweep-into",
             flags=CPU_SWEEP_INTO)),
    "qpa-mistake": (
        "QPA beside PEBBLE and RIME under the mistake teacher (eps 0.1), as rime-mistake (same root and flags: "
        "its runs are that preset's), 5 seeds",
        Grid(algorithms=("pebble", "rime", "qpa"), teachers=("mistake",), budgets=("1000/100",),
             samplers=("default",), seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/rime",
             flags=CPU_PEBBLE + " --checkpoint-every 10000")),
    # B-Pref's findings at CPU scale (docs/bpref.md): each block its own root; the oracle and mistake runs of
    # walker-walk and the oracle runs of the other tasks are the kept runs of the presets above
    "bpref-walker-teachers": (
        "PEBBLE with the stoc, skip, equal and myopic teachers, walker-walk at the README's CPU scale (1000 labels), "
        "5 seeds",
        Grid(teachers=("stoc", "skip", "equal", "myopic"), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5),
             ground_truth=False, root="runs/bpref-walker", flags=CPU_PEBBLE + " --checkpoint-every 10000")),
    "bpref-walker-samplers": (
        "PEBBLE (oracle) with the uniform, entropy, coverage and hybrid samplers, walker-walk at the README's CPU "
        "scale, 5 seeds (disagreement: parity-pebble's runs)",
        Grid(teachers=("oracle",), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5), ground_truth=False,
             samplers=("uniform", "entropy", "coverage", "disagreement-coverage", "entropy-coverage"),
             root="runs/bpref-walker", flags=CPU_PEBBLE)),
    "bpref-walker-samplers-equal": (
        "PEBBLE with the equal teacher and every sampler (the share of equal answers each receives), walker-walk at "
        "the README's CPU scale, 3 seeds",
        Grid(teachers=("equal",), budgets=("1000/100",), seeds=(1, 2, 3), ground_truth=False, samplers=SAMPLERS,
             root="runs/bpref-walker", flags=CPU_PEBBLE)),
    "bpref-walker-schedules": (
        "PEBBLE (oracle) with the increase and decay schedules, walker-walk at the README's CPU scale, 5 seeds",
        Grid(teachers=("oracle",), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5), ground_truth=False,
             schedules=("increase", "decay"), root="runs/bpref-walker", flags=CPU_PEBBLE)),
    "bpref-walker-smoothing": (
        "PEBBLE under the mistake teacher (eps 0.1) with label smoothing 0.1, walker-walk at the README's CPU scale, "
        "5 seeds",
        Grid(teachers=("mistake",), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5), ground_truth=False,
             root="runs/bpref-walker-smoothing", flags=CPU_PEBBLE + " --label-smoothing 0.1")),
    "bpref-walker-prefppo": (
        "PrefPPO with the stoc, mistake, skip, equal and myopic teachers and PPO on the true reward (the "
        "normaliser), walker-walk 1M steps (parity-prefppo's scale), 5 seeds",
        Grid(algorithms=("prefppo",), teachers=("stoc", "mistake", "skip", "equal", "myopic"), budgets=("1000/100",),
             seeds=(1, 2, 3, 4, 5), root="runs/bpref-walker-prefppo", flags=CPU_PREFPPO)),
    "bpref-button-press": (
        "PEBBLE with the stoc, mistake, skip, equal and myopic teachers, button-press at button-press-cpu's scale, "
        "5 seeds",
        Grid(env_ids=("button-press",), teachers=("stoc", "mistake", "skip", "equal", "myopic"), budgets=("900/50",),
             seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/bpref-button-press", flags=CPU_METAWORLD)),
    "bpref-quadruped-walk": (
        "PEBBLE with the stoc, mistake, skip and equal teachers, quadruped-walk at quadruped-walk-cpu's scale, "
        "5 seeds",
        Grid(env_ids=("quadruped-walk",), teachers=("stoc", "mistake", "skip", "equal"), budgets=("1000/100",),
             seeds=(1, 2, 3, 4, 5), ground_truth=False, root="runs/bpref-quadruped-walk", flags=CPU_QUADRUPED)),
    # the skip and equal teachers with the reference's thresholds (eps applied again after the first session,
    # differences.md 1), each in a root of its own: the runs' names do not say their edits
    "bpref-walker-reference-thresholds": (
        "PEBBLE with the skip and equal teachers as the reference's code thresholds them, walker-walk at the "
        "README's CPU scale, 5 seeds",
        Grid(teachers=("skip", "equal"), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5), ground_truth=False,
             edits=("reference-thresholds",), root="runs/bpref-walker-reference-thresholds",
             flags=CPU_PEBBLE + " --checkpoint-every 10000")),
    "bpref-quadruped-reference-thresholds": (
        "PEBBLE with the skip and equal teachers as the reference's code thresholds them, quadruped-walk at "
        "quadruped-walk-cpu's scale, 5 seeds (F2 as the paper's figure met it)",
        Grid(env_ids=("quadruped-walk",), teachers=("skip", "equal"), budgets=("1000/100",), seeds=(1, 2, 3, 4, 5),
             ground_truth=False, edits=("reference-thresholds",), root="runs/bpref-quadruped-reference-thresholds",
             flags=CPU_QUADRUPED)),
    "rime-mini-bpref": (
        "The mini B-Pref (six teachers + ground truth, 5 seeds) for RIME and for PEBBLE's default reward inputs",
        replace(MINI_BPREF, algorithms=("pebble", "rime"), root="runs/mini-bpref-rime")),
}


@dataclass(frozen=True)
class Run:
    name: str
    """directory name under the root, made from the settings"""
    algorithm: str
    flags: tuple[str, ...]
    """the script's flags, without --output-dir and --resume"""
    implementation: str = "ours"
    edits: tuple[str, ...] = ()
    """benchmarks/reference/edits.py's edits of the script that this run runs"""

    def command(self, run_dir: Path, resume: bool) -> list[str]:
        """The script and its flags (run with the Python of the machine that runs it); the same flags again on resume,
        which the scripts accept as they equal the saved configuration. The reference takes the same flags through
        its runner, which never resumes (it writes no checkpoint.pt: a stopped run is started afresh)."""
        if self.implementation == "reference":  # it writes no checkpoint: --checkpoint-every is ours only
            at = self.flags.index("--checkpoint-every") if "--checkpoint-every" in self.flags else len(self.flags)
            flags = self.flags[:at] + self.flags[at + 2:]
            return [str(REFERENCE_RUNNER), "--algorithm", self.algorithm, *flags, "--output-dir", str(run_dir)]
        # a resumed run takes its directory from --resume (the folder may have moved since)
        script = [str(EDITS_RUNNER), *self.edits, "--"] if self.edits else []
        return [*script, str(ROOT / f"{self.algorithm}.py"), *self.flags, "--resume" if resume else "--output-dir",
                str(run_dir)]


def parse_budget(budget: str) -> list[str]:
    """'1000/100' -> the flags; 'preset' -> none. ValueError on anything else."""
    if budget == "preset":
        return []
    match = re.fullmatch(r"(\d+)(?:/(\d+))?", budget)
    if not match or int(match[1]) < 1 or (match[2] and not 1 <= int(match[2]) <= int(match[1])):
        raise ValueError(f"--budgets {budget!r} is not max_feedback[/feedback_per_session] with "
                         "1 <= feedback_per_session <= max_feedback (e.g. 1000/100), nor 'preset'")
    return ["--max-feedback", match[1], *(["--feedback-per-session", match[2]] if match[2] else [])]


def check(grid: Grid) -> str | None:
    """The first problem with the grid as one line, or None."""
    for name, given, known in (("algorithms", grid.algorithms, ALGORITHMS), ("teachers", grid.teachers, TEACHERS),
                               ("implementations", grid.implementations, IMPLEMENTATIONS),
                               ("samplers", grid.samplers, (*SAMPLERS, "default")),
                               ("schedules", grid.schedules, SCHEDULES)):
        unknown = [value for value in given if value not in known]
        if unknown:
            return f"--{name} {unknown[0]!r} is not one of {', '.join(known)}"
    for edit in grid.edits:
        unfit = [algorithm for algorithm in grid.algorithms if f"{algorithm}.py" not in EDITS.get(edit, {})]
        if unfit:
            return f"--edits {edit!r} is not an edit of {unfit[0]}.py (known: {', '.join(EDITS)})"
    for algorithm, what in (("prefppo", "PrefPPO, not PPO"), ("rime", "RIME's code, not SAC"),
                            ("qpa", "QPA's code, not SAC")):
        if "reference" in grid.implementations and algorithm in grid.algorithms and grid.ground_truth:
            return f"--implementations reference runs {what} on the true reward: add --no-ground-truth"
    if "default" in grid.samplers and len(grid.samplers) > 1:
        return "--samplers default (each script's own sampler) stands alone"
    if not (grid.ground_truth or grid.preference_runs):
        return "--no-ground-truth with --no-preference-runs leaves no run"
    for name in ("algorithms", "implementations", "env_ids", "teachers", "budgets", "samplers", "schedules", "seeds"):
        values = getattr(grid, name)
        if not values:
            return f"--{name.replace('_', '-')} needs at least one value"
        if len(set(values)) < len(values):
            return f"--{name.replace('_', '-')} lists a value twice: {' '.join(map(str, values))}"
    for budget in grid.budgets:
        try:
            parse_budget(budget)
        except ValueError as error:
            return str(error)
    for name in ("flags", "pebble_flags", "prefppo_flags", "rime_flags", "qpa_flags"):
        try:
            given = shlex.split(getattr(grid, name))
        except ValueError as error:
            return f"--{name.replace('_', '-')}: {error}"
        clash = [flag for flag in given if flag.split("=")[0] in GRID_FLAGS]
        if clash:
            return f"--{name.replace('_', '-')} sets {clash[0]}, which the grid sets itself for each run"
    if grid.workers < 1 or grid.cpus_per_run < 1 or grid.gpus_per_run < 0:
        return "--workers and --cpus-per-run must be >= 1, --gpus-per-run >= 0"
    if grid.backend == "local" and grid.gpus_per_run:
        return "--gpus-per-run is for --backend ray; locally, give --flags='--cuda' and choose --workers"
    if grid.backend == "ray" and not grid.dry_run:
        try:
            import ray  # noqa: F401
        except ImportError:
            return "--backend ray needs Ray (pip install -r requirements.txt)"
    return None


def safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text)


def expand(grid: Grid) -> list[Run]:
    """Per implementation, algorithm and task: first the ground-truth runs (no teacher, budget, sampler or schedule:
    one per seed), so that a grid stopped part-way can already be normalised, then the cross product. The reference's
    runs are named as ours with the prefix reference__."""
    return [run for implementation in grid.implementations for run in expand_one(grid, implementation)]


def expand_one(grid: Grid, implementation: str) -> list[Run]:
    runs, prefix = [], "" if implementation == "ours" else f"{implementation}__"
    for algorithm in grid.algorithms:
        extra = shlex.split(grid.flags) + shlex.split(getattr(grid, f"{algorithm}_flags"))
        edits = grid.edits if implementation == "ours" else ()
        for env_id in grid.env_ids:
            if grid.ground_truth:
                for seed in grid.seeds:
                    name = safe_name(f"{prefix}{algorithm}__{env_id}__ground-truth__s{seed}")
                    runs.append(Run(name, algorithm, ("--env-id", env_id, "--seed", str(seed), "--ground-truth-reward",
                                                      *extra), implementation, edits))
            for teacher in grid.teachers if grid.preference_runs else ():
                for budget in grid.budgets:
                    for sampler in grid.samplers:
                        if sampler == "default":  # the script's own, named and passed as any other
                            sampler = importlib.import_module(algorithm).Args.sampler
                        for schedule in grid.schedules:
                            for seed in grid.seeds:
                                name = safe_name(f"{prefix}{algorithm}__{env_id}__{teacher}__fb"
                                                 f"{budget.replace('/', '-')}__{sampler}__{schedule}__s{seed}")
                                flags = ["--env-id", env_id, "--seed", str(seed), "--teacher", teacher,
                                         *parse_budget(budget), "--sampler", sampler, "--schedule", schedule, *extra]
                                runs.append(Run(name, algorithm, tuple(flags), implementation, edits))
    return runs


def read_eval(run_dir: Path) -> list[dict]:
    """The rows of a run's eval.csv as floats ([] if there is none)."""
    try:
        with open(run_dir / "eval.csv") as f:
            return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(f)]
    except (OSError, ValueError):
        return []


def run_state(run_dir: Path) -> tuple[str, str]:
    """('finished' | 'resumable' | 'partial' | 'new', a few words). Finished: final_model.pt written and the last
    evaluation at (prefppo: past) the configured total steps; the reference's PrefPPO (rows of training episodes,
    the last before the last step): final_model.pt written."""
    if not run_dir.is_dir() or not any(run_dir.iterdir()):
        return "new", "not started"
    try:
        config = json.loads((run_dir / "config.json").read_text())
        total = config["total_timesteps"]
    except (OSError, ValueError, KeyError):
        config, total = {}, None
    rows = read_eval(run_dir)
    step = int(rows[-1]["step"]) if rows else 0
    training = config.get("episode_returns") == "training"
    if total is not None and (run_dir / "final_model.pt").exists() and (step >= total or training):
        return "finished", f"{step} steps"
    where = f"last evaluation at step {step} of {total}" if total is not None else "no config.json"
    if (run_dir / "checkpoint.pt").exists():
        return "resumable", where
    return "partial", f"{where}, no checkpoint"


# What sets a run's wall time, as (config.json key, flag): a kept run is alike when it agrees on every one the run sets
COST_SETTINGS = (("env_id", "--env-id"), ("total_timesteps", "--total-timesteps"), ("hidden_dim", "--hidden-dim"),
                 ("num_layers", "--num-layers"), ("batch_size", "--batch-size"),
                 ("ground_truth_reward", "--ground-truth-reward"))


def kept_wall_times(docs: Path) -> list[tuple[str, dict, float]]:
    """(algorithm with the implementation's prefix, config, final wall time in seconds) of every run kept below
    docs that reached its last step."""
    kept = []
    for config_path in sorted(docs.rglob("config.json")):
        try:
            config = json.loads(config_path.read_text())
        except (OSError, ValueError):
            continue
        rows = read_eval(config_path.parent)
        if not rows or rows[-1].get("wall_time") is None or rows[-1]["step"] < config.get("total_timesteps", 1):
            continue
        prefix = "reference__" if config.get("implementation") == "reference" else ""
        algorithm = config.get("exp_name") or config_path.parent.name.removeprefix(prefix).split("__")[0]
        kept.append((prefix + algorithm, config, rows[-1]["wall_time"]))
    return kept


def minutes_alike(run: Run, kept: list[tuple[str, dict, float]]) -> tuple[float, int] | None:
    """(median wall minutes, how many) of the kept runs alike to this run, or None where none is."""
    prefix = "" if run.implementation == "ours" else f"{run.implementation}__"
    wanted = {}
    for key, flag in COST_SETTINGS:
        if flag == "--ground-truth-reward":
            wanted[key] = flag in run.flags
        elif flag in run.flags:
            wanted[key] = type_of(run.flags[run.flags.index(flag) + 1])
    walls = [wall for algorithm, config, wall in kept if algorithm == prefix + run.algorithm
             and all(config.get(key, False) == value for key, value in wanted.items())]
    return (float(np.median(walls)) / 60, len(walls)) if walls else None


def type_of(text: str):
    """A flag's value as the config.json holds it: an int where it is one, else the text."""
    return int(text) if text.isdigit() else text


def dry_run_cost(todo: list[tuple[Run, bool]], root: Path, cpus_per_run: int, docs: Path) -> list[str]:
    """Lines that say what the runs to do will cost in core-hours, from the wall times of alike runs kept under
    docs (a resumed run only its steps left)."""
    kept = kept_wall_times(docs)
    hours = 0.0
    unknown = []
    for run, resume in todo:
        alike = minutes_alike(run, kept)
        if alike is None:
            unknown.append(run.name)
            continue
        left = 1.0
        if resume:
            rows = read_eval(root / run.name)
            config = json.loads((root / run.name / "config.json").read_text())
            left = 1 - (rows[-1]["step"] if rows else 0) / config["total_timesteps"]
        hours += alike[0] * left * cpus_per_run / 60
    lines = [f"# about {hours:.1f} core-hours for {len(todo) - len(unknown)} runs, from the median wall time of the "
             f"kept runs alike under {docs.relative_to(ROOT) if docs.is_relative_to(ROOT) else docs}"]
    if unknown:
        lines.append(f"# no kept run alike, so no estimate, for {len(unknown)} runs: {', '.join(unknown)}")
    return lines


def load_spec(root: Path) -> dict:
    try:
        return json.loads((root / "grid.json").read_text())["runs"]
    except (OSError, ValueError, KeyError):
        return {}


def save_spec(root: Path, spec: dict):
    tmp = root / "grid.json.tmp"  # one run a line
    lines = ",\n".join(f"  {json.dumps(name)}: {json.dumps(entry)}" for name, entry in spec.items())
    tmp.write_text(f'{{"runs": {{\n{lines}\n}}}}\n')
    os.replace(tmp, root / "grid.json")


def execute(command: list[str], log_path: str, threads: int, started=None) -> int:
    """One run as a child process, its output appended to log_path; returns its exit code (-N: killed by signal N).
    `started(process)` is called once it runs. An interrupt of this function (Ray's cancel) is passed on to the run
    as SIGTERM, so that it writes a checkpoint before it ends."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads), PYTHONWARNINGS="ignore")
    with open(log_path, "a") as log:
        log.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} on {os.uname().nodename}: {shlex.join(command)}\n")
        log.flush()
        start = time.time()
        process = subprocess.Popen([sys.executable, *command], stdout=log, stderr=subprocess.STDOUT, env=env,
                                   stdin=subprocess.DEVNULL)
        if started:
            started(process)
        try:
            while (code := process.poll()) is None:  # not wait(): Ray's cancel arrives between bytecodes only
                time.sleep(0.5)
        except BaseException:
            process.send_signal(signal.SIGTERM)
            log.write(f"=== interrupted: exit code {process.wait()} after {(time.time() - start) / 60:.1f} min\n")
            raise
        log.write(f"=== exit code {code} after {(time.time() - start) / 60:.1f} min\n")
    return code


def execute_ray_task(command: list[str], log_path: str, threads: int) -> int:
    """execute() as a Ray task. Ray cancels a running task with a SIGINT to its worker, which a worker started from a
    background shell would ignore (it inherits SIG_IGN): restore Python's handler."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    return execute(command, log_path, threads)


class Progress:
    """Counts and a time-left estimate for the whole grid, printed every progress_every seconds and at each end."""

    def __init__(self, waiting: int, finished_before: int, refused: list[str], concurrency: int, every: float,
                 logs: dict[str, Path]):
        self.waiting, self.skipped, self.failed = waiting, finished_before, list(refused)
        self.total = waiting + finished_before + len(refused)
        self.concurrency, self.every, self.logs = concurrency, every, logs
        self.started_at, self.running, self.done, self.durations, self.interrupted = time.time(), {}, 0, [], []
        self.lock, self.last_print, self.cancelled = threading.Lock(), 0.0, False

    def start(self, name: str):
        with self.lock:
            self.waiting -= 1
            self.running[name] = time.time()

    def end(self, name: str, failure: str | None, interrupted: bool = False):
        """A run ended: finished (no failure), failed, or stopped because the grid was interrupted."""
        with self.lock:
            duration = time.time() - self.running.pop(name)
            if interrupted and failure:
                self.interrupted.append(name)
                print(f"interrupted: {name}: {failure}; the same grid command continues it", flush=True)
            elif failure:
                self.failed.append(name)
                print(f"failed: {name}: {failure}; log {self.logs[name]}", flush=True)
            else:
                self.done += 1
                self.durations.append(duration)
                print(f"finished: {name} ({duration / 60:.1f} min)", flush=True)
        self.show(force=True)

    def fraction(self, name: str) -> float | None:
        """How far a running run is, from the last 'step N/T' line of its log."""
        try:
            with open(self.logs[name], "rb") as f:
                f.seek(max(0, f.seek(0, 2) - 4096))
                found = re.findall(rb"step (\d+)/(\d+) \|", f.read())
        except OSError:
            return None
        return int(found[-1][0]) / int(found[-1][1]) if found else None

    def time_left(self) -> float | None:
        """Seconds: runs finished here and the extrapolated running ones give a run's duration; the remaining work
        is shared by the workers."""
        now, estimates = time.time(), list(self.durations)
        fractions = {name: self.fraction(name) for name in self.running}
        for name, began in self.running.items():
            if fractions[name] and fractions[name] > 0.02:
                estimates.append((now - began) / fractions[name])
        if not estimates:
            return None
        duration = sum(estimates) / len(estimates)
        left = sum(max(duration - (now - began), 0.0) for began in self.running.values()) + self.waiting * duration
        return left / max(1, min(self.concurrency, len(self.running) + self.waiting))

    def show(self, force: bool = False):
        if not force and time.time() - self.last_print < self.every:
            return
        with self.lock:
            self.last_print = time.time()
            left = self.time_left()
            left_text = ("-" if left is None else f"{left / 3600:.1f} h" if left > 5400 else f"{left / 60:.0f} min"
                         if left > 90 else f"{left:.0f} s")
            print(f"[grid {time.strftime('%H:%M:%S')}] {self.done + self.skipped}/{self.total} done "
                  f"({self.skipped} before), {len(self.running)} running, {len(self.failed)} failed, {self.waiting} "
                  f"waiting | {(time.time() - self.started_at) / 60:.1f} min | time left ~{left_text}", flush=True)


def failure_of(code: int) -> str | None:
    if code == 0:
        return None
    if code < 0:
        return f"killed by signal {-code}"
    if code > 128:
        return f"stopped by signal {code - 128} after a checkpoint (exit code {code})"
    return f"exit code {code} ({EXIT_MEANINGS.get(code, 'error')})"


def plan(runs: list[Run], root: Path, spec: dict, retry_non_finite: bool = False
         ) -> tuple[list[tuple[Run, bool]], list[tuple[Run, str]], list[str]]:
    """(runs to do with their resume flag, runs refused with the reason, names of finished runs)."""
    todo, refused, finished = [], [], []
    for run in runs:
        run_dir, recorded = root / run.name, spec.get(run.name)
        state, detail = run_state(run_dir)
        if state != "new" and recorded and recorded["command"] != list(run.flags):
            refused.append((run, f"{run_dir} holds a run of other flags ({shlex.join(recorded['command'])}); choose "
                                 "another --root or move it away"))
        elif state != "new" and recorded and recorded.get("edits", []) != list(run.edits):
            refused.append((run, f"{run_dir} holds a run with edits {recorded.get('edits', [])} (this grid's: "
                                 f"{list(run.edits)}); choose another --root or move it away"))
        elif state == "finished":
            finished.append(run.name)
        elif state == "resumable" and recorded and recorded.get("exit_code") == 3 and not retry_non_finite:
            refused.append((run, f"it stopped on a non-finite value (exit code 3), which a resume would meet again; "
                                 f"once its cause is fixed, --retry-non-finite resumes it; remove {run_dir} to "
                                 "start it afresh"))
        else:
            todo.append((run, state == "resumable"))
    return todo, refused, finished


def run_grid(grid: Grid) -> int:
    """Plans, prints and runs the grid; returns the exit code (0: all finished, 1: a run failed)."""
    root = Path(grid.root).resolve()
    runs, spec = expand(grid), load_spec(root)
    todo, refused, finished = plan(runs, root, spec, grid.retry_non_finite)
    logs = {run.name: root / "logs" / f"{run.name}.log" for run in runs}
    print(f"grid: {len(runs)} runs in {root}: {len(finished)} finished, {sum(r for _, r in todo)} to resume, "
          f"{sum(not r for _, r in todo)} to start, {len(refused)} refused", flush=True)
    for run, reason in refused:
        print(f"refused: {run.name}: {reason}", flush=True)
    threads = grid.cpus_per_run
    if grid.dry_run:
        for name in finished:
            print(f"# skip (finished): {name}")
        for run, resume in todo:
            state, detail = run_state(root / run.name)
            note = {"resumable": f"resume ({detail})", "partial": f"start afresh, moving the partial run aside "
                    f"({detail})", "new": "start"}[state]
            command = shlex.join(["python", *run.command(root / run.name, resume)])
            log = shlex.quote(str(logs[run.name]))
            print(f"# {note}: {run.name}\nOMP_NUM_THREADS={threads} {command} >> {log} 2>&1")
        print("\n".join(dry_run_cost(todo, root, threads, ROOT / "docs")))
        return 0

    (root / "logs").mkdir(parents=True, exist_ok=True)
    for run, resume in todo:
        if not resume and run_state(root / run.name)[0] == "partial":  # stopped before its first checkpoint
            aside = root / ".aside" / f"{run.name}.{time.strftime('%Y%m%d-%H%M%S')}"
            aside.parent.mkdir(exist_ok=True)
            shutil.move(root / run.name, aside)
            print(f"{run.name}: stopped before a checkpoint; moved to {aside}, starting afresh", flush=True)
        spec[run.name] = {"command": list(run.flags), "edits": list(run.edits), "exit_code": None}
    save_spec(root, spec)
    spec_lock = threading.Lock()

    def record(run: Run, code: int):
        with spec_lock:
            spec[run.name]["exit_code"] = code
            save_spec(root, spec)

    progress = Progress(len(todo), len(finished), [run.name for run, _ in refused], grid.workers, grid.progress_every,
                        logs)
    progress.show(force=True)
    if grid.backend == "local":
        stopped = run_local(todo, root, logs, grid, progress, record)
    else:
        stopped = run_ray(todo, root, logs, grid, progress, record)
    progress.show(force=True)
    for name in progress.failed:
        print(f"failed: {name}; log {logs[name]}")
    if stopped:
        print(f"grid stopped by signal {stopped} ({len(progress.interrupted)} runs interrupted, the ones past their "
              "first checkpoint with a checkpoint of their last step); the same command continues it", flush=True)
        return 128 + stopped
    return 1 if progress.failed else 0


def run_local(todo, root, logs, grid, progress, record) -> int | None:
    """A pool of grid.workers runs at once on this machine. SIGINT / SIGTERM: every run checkpoints and stops,
    waiting runs are not started; returns the signal number."""
    live, stop = set(), []

    def one(run: Run, resume: bool):
        if stop:
            return
        progress.start(run.name)
        code = execute(run.command(root / run.name, resume), str(logs[run.name]), grid.cpus_per_run, live.add)
        record(run, code)
        progress.end(run.name, failure_of(code), interrupted=bool(stop))

    def request_stop(signum, frame):
        stop.append(signum)
        for process in list(live):
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)  # the run checkpoints and exits with 128 + 15

    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with concurrent.futures.ThreadPoolExecutor(grid.workers) as pool:
            futures = [pool.submit(one, run, resume) for run, resume in todo]
            while concurrent.futures.wait(futures, timeout=min(grid.progress_every, 5.0)).not_done:
                progress.show()
            for future in futures:
                future.result()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    return stop[0] if stop else None


def run_ray(todo, root, logs, grid, progress, record) -> int | None:
    """Each run a Ray task with grid.cpus_per_run CPUs and grid.gpus_per_run GPUs, on the cluster at
    grid.ray_address or on a Ray instance started here with grid.workers x grid.cpus_per_run CPUs. SIGINT / SIGTERM:
    the running tasks are cancelled (their runs checkpoint and stop), waiting runs are not submitted."""
    import ray

    if grid.ray_address:
        ray.init(address=grid.ray_address)
    else:
        ray.init(num_cpus=grid.workers * grid.cpus_per_run, include_dashboard=False)
    ray.cloudpickle.register_pickle_by_value(sys.modules[execute.__module__])  # the workers need not import this file
    task = ray.remote(num_cpus=grid.cpus_per_run, num_gpus=grid.gpus_per_run, max_retries=0)(execute_ray_task)

    def capacity() -> int:
        """Runs the cluster has resources for now: only that many are submitted, so that 'running' means running."""
        resources = ray.cluster_resources()
        fits = [resources.get("CPU", 0) // grid.cpus_per_run]
        if grid.gpus_per_run:
            fits.append(resources.get("GPU", 0) // grid.gpus_per_run)
        return max(1, int(min(fits)))

    waiting, submitted, stop = list(todo), {}, []
    previous = {s: signal.signal(s, lambda signum, frame: stop.append(signum)) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        while waiting or submitted:
            progress.concurrency = capacity()
            while waiting and len(submitted) < progress.concurrency and not stop:
                run, resume = waiting.pop(0)
                progress.start(run.name)
                command = run.command(root / run.name, resume)
                submitted[task.remote(command, str(logs[run.name]), grid.cpus_per_run)] = run
            if stop and (waiting or not progress.cancelled):
                progress.waiting -= len(waiting)
                waiting, progress.cancelled = [], True
                for ref in submitted:
                    ray.cancel(ref)  # a KeyboardInterrupt in the task: its run gets SIGTERM and checkpoints
            ready, _ = ray.wait(list(submitted), num_returns=1, timeout=min(grid.progress_every, 5.0))
            for ref in ready:
                run = submitted.pop(ref)
                try:
                    code = ray.get(ref)
                except ray.exceptions.TaskCancelledError:
                    progress.end(run.name, "its Ray task was cancelled", interrupted=True)
                except ray.exceptions.RayError as error:
                    progress.end(run.name, f"the Ray task failed ({type(error).__name__}: {str(error)[:300]})")
                else:
                    record(run, code)
                    progress.end(run.name, failure_of(code), interrupted=bool(stop))
            progress.show()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        ray.shutdown()
    return stop[0] if stop else None


if __name__ == "__main__":
    grid = tyro.extras.overridable_config_cli(PRESETS)
    problem = check(grid)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        sys.exit(2)
    sys.exit(run_grid(grid))
