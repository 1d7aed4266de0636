"""Keep finished runs for the docs: what report.py reads of each, without checkpoints, models and label files.

Per run, into a folder of the same name under --to: config.json and eval.csv; the teacher's answers at every
feedback session (queries, skipped, equal) as labels.csv, one row a session; for a RIME run, its discriminator at
every feedback session (the label files' trusted, flipped, dropped, precision and recall) as discriminator.csv,
one row a session, which report.py --compare reads when the labels are gone; with --events, the TensorBoard files
too (report.py --parity reads their training episodes where the reference's PrefPPO is compared); with --labels,
the label files without the segments' observations and actions (what fit_teacher.py reads: 0.5 MB of a walker-walk
run's 12).
Docs: docs/experiments.md

    python experiments/keep_runs.py runs/rime-eps0.3/rime__* --to docs/rime/data/eps0.3
"""

import csv
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import sim_teacher  # noqa: E402

DISCRIMINATOR_KEYS = ("trusted", "flipped", "dropped", "precision", "recall")


@dataclass
class Args:
    runs: tyro.conf.Positional[list[str]]
    """run folders (each with config.json and eval.csv)"""
    to: str
    """folder to keep them in (docs/.../data/...)"""
    events: bool = False
    """also keep the TensorBoard files (events.out.tfevents.*)"""
    labels: bool = False
    """also keep the label files, without the segments' observations and actions (for fit_teacher.py)"""


def discriminator_rows(labels: Path) -> list[dict]:
    """A row per label file that has RIME's discriminator fields: the session, its step and those fields."""
    rows = []
    for session, file in enumerate(sorted(labels.glob("session_*.npz"))):
        with np.load(file) as data:
            if all(key in data.files for key in DISCRIMINATOR_KEYS):
                rows.append({"session": session, "step": int(data["step"])}
                            | {key: float(data[key]) for key in DISCRIMINATOR_KEYS})
    return rows


def answer_rows(labels: Path) -> list[dict]:
    """A row per label file with the teacher's answers (y, keep): the session, its step, how many queries, how many
    the teacher skipped and how many it called equally preferable (y = 0.5)."""
    rows = []
    for session, file in enumerate(sorted(labels.glob("session_*.npz"))):
        with np.load(file) as data:
            if "y" in data.files and "keep" in data.files:
                keep = data["keep"].astype(bool)
                rows.append({"session": session, "step": int(data["step"]), "queries": len(keep),
                             "skipped": int((~keep).sum()), "equal": int((keep & (data["y"] == 0.5)).sum())})
    return rows


def write_rows(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def keep_label_files(run: Path, target: Path) -> None:
    """Each session's label file under target/labels, less the segments' obs0, actions0, obs1, actions1."""
    for session, arrays in enumerate(sim_teacher.load_labels(str(run))):
        kept = {key: value for key, value in arrays.items() if not key.startswith(("obs", "actions"))}
        if kept["threshold_scale"] is None:  # a label file written before pebble.py saved it
            del kept["threshold_scale"]
        sim_teacher.save_labels(str(target), session, **kept)


def keep(run: Path, target: Path, events: bool, labels: bool) -> None:
    target.mkdir(parents=True, exist_ok=True)
    names = ["config.json", "eval.csv"] + ([path.name for path in run.glob("events.out.tfevents.*")] if events else [])
    for name in names:
        shutil.copy2(run / name, target / name)
    for name, rows in (("labels.csv", answer_rows(run / "labels")),
                       ("discriminator.csv", discriminator_rows(run / "labels"))):
        if rows:
            write_rows(target / name, rows)
    if labels:
        keep_label_files(run, target)


def main(args: Args) -> None:
    runs = [Path(run) for run in args.runs]
    for run in runs:
        missing = [name for name in ("config.json", "eval.csv") if not (run / name).is_file()]
        if missing:
            sys.exit(f"error: {run}: no {' or '.join(missing)}: not a run folder")
        if args.labels and not sim_teacher.label_files(str(run)):
            sys.exit(f"error: {run}: no label files (labels/session_*.npz) to keep with --labels")
    for run in runs:
        try:
            keep(run, Path(args.to) / run.name, args.events, args.labels)
        except ValueError as error:  # a malformed label file (sim_teacher.load_labels names it)
            sys.exit(f"error: {error}")
        print(f"kept {run} -> {Path(args.to) / run.name}")


if __name__ == "__main__":
    main(tyro.cli(Args))
