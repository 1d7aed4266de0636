"""Reward learning of both implementations on the same labels: pebble.py's RewardEnsemble and train_reward against the
reference's RewardModel.train_reward (in its own environment), trained on the first sessions of a run's labels until
97% accuracy or 50 epochs (as each does in a run), then judged on the run's later sessions: Pearson correlation of
the learned per-step reward with the true one, and the share of later pairs ordered as the teacher ordered them.
Several initialisation seeds a side; a table on stdout.

    python benchmarks/reference/reward_learning.py runs/parity/ours/pebble__walker-walk__oracle__..._s1 --sessions 5

--normalized-inputs adds ours with the scripts' input normaliser (RewardEnsemble.set_input_stats: observations
centred and scaled by the training segments' states, clipped to +-10, as the reference's PrefPPO fed VecNormalize'd
ones to its reward network), to measure that conditioning difference (docs/differences.md, item 17).
"""

import argparse
import glob
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]


def labelled(run_dir: str, sessions: int) -> dict:
    """The run's labels: the first `sessions` sessions to train on, the later ones to judge."""
    saved = [dict(np.load(path)) for path in sorted(glob.glob(f"{run_dir}/labels/session_*.npz"))]
    if len(saved) <= sessions:
        sys.exit(f"error: {run_dir} has {len(saved)} label sessions; --sessions must leave some to judge on")

    def both(part: list[dict], side: int) -> np.ndarray:
        return np.concatenate([np.concatenate([s[f"obs{side}"], s[f"actions{side}"]], -1) for s in part])

    train, later = saved[:sessions], saved[sessions:]
    return {"obs_dim": saved[0]["obs0"].shape[-1], "train0": both(train, 0), "train1": both(train, 1),
            "y": np.concatenate([s["y"] for s in train]).astype(np.float32),
            "later0": both(later, 0), "later1": both(later, 1),
            "later_y": np.concatenate([s["y"] for s in later]),
            "later_rewards": np.concatenate([np.concatenate([s[f"rewards{i}"] for s in later]) for i in (0, 1)])}


def judged(reward_fn, data: dict) -> tuple[float, float]:
    """(correlation with the true per-step reward, share of later pairs in the teacher's order) of reward_fn, which
    maps (N, obs+action) float32 to N rewards."""
    steps = np.concatenate([data["later0"], data["later1"]]).astype(np.float32)
    learned = reward_fn(steps.reshape(-1, steps.shape[-1]))
    correlation = float(np.corrcoef(learned, data["later_rewards"].reshape(-1))[0, 1])
    returns = learned.reshape(2, -1, steps.shape[1]).sum(-1)
    agreement = float(np.mean((returns[1] > returns[0]) == (data["later_y"] > 0.5)))
    return correlation, agreement


def ours(data: dict, seed: int, normalize: bool = False) -> dict:
    """pebble.py's reward learning; normalize: as the scripts do (D's states standardise the observations), else
    raw inputs as the reference PEBBLE's."""
    sys.path.insert(0, str(ROOT))
    import pebble

    torch.manual_seed(seed)
    obs_action = data["train0"].shape[-1]
    model = pebble.RewardEnsemble(obs_action, 0, 3)  # the input is (observation, action) concatenated
    if normalize:
        states = np.concatenate([data["train0"], data["train1"]], 1)[..., : data["obs_dim"]]
        model.set_input_stats(torch.as_tensor(states, dtype=torch.float32).flatten(0, 1))
    optimizer = pebble.adam(model.parameters(), 3e-4)
    preferences = {"inputs0": torch.as_tensor(data["train0"], dtype=torch.float32),
                   "inputs1": torch.as_tensor(data["train1"], dtype=torch.float32), "y": torch.as_tensor(data["y"])}
    one_epoch = pebble.Args(reward_epochs=1)
    for epoch in range(1, 51):
        _, accuracy = pebble.train_reward(model, optimizer, preferences, one_epoch)
        if accuracy > 0.97:
            break
    with torch.no_grad():
        scores = judged(lambda x: model(torch.as_tensor(x)).mean(0)[:, 0].numpy(), data)
    return {"epochs": epoch, "accuracy": accuracy, "correlation": scores[0], "agreement": scores[1]}


def reference(data: dict, seed: int, tree: str) -> dict:
    sys.path.insert(0, tree)
    import reward_model

    torch.manual_seed(seed)
    np.random.seed(seed)
    obs_action = data["train0"].shape[-1]
    model = reward_model.RewardModel(obs_action, 0, ensemble_size=3, size_segment=data["train0"].shape[1],
                                     activation="tanh", lr=3e-4)
    model.put_queries(data["train0"].astype(np.float32), data["train1"].astype(np.float32), data["y"][:, None])
    for epoch in range(1, 51):  # train_PEBBLE.py's learn_reward
        accuracy = float(np.mean(model.train_reward()))
        if accuracy > 0.97:
            break
    scores = judged(lambda x: model.r_hat_batch(x)[:, 0], data)
    return {"epochs": epoch, "accuracy": accuracy, "correlation": scores[0], "agreement": scores[1]}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a run directory of pebble.py with labels/session_*.npz")
    parser.add_argument("--sessions", type=int, default=5, help="sessions to train on; the later ones judge")
    parser.add_argument("--seeds", type=int, default=3, help="initialisation seeds a side")
    parser.add_argument("--reference-dir", default=str(ROOT / "reference"), help="where setup.sh put the reference")
    parser.add_argument("--normalized-inputs", action="store_true",
                        help="also ours on normalised observations (the reference PrefPPO's reward inputs)")
    parser.add_argument("--side", choices=["both", "reference"], default="both", help=argparse.SUPPRESS)
    args = parser.parse_args()
    data = labelled(args.run, args.sessions)
    if args.side == "reference":  # in the reference's environment: one JSON line per seed
        for seed in range(args.seeds):
            print(json.dumps(reference(data, seed, str(Path(args.reference_dir) / "BPref"))))
        return
    python = Path(args.reference_dir) / ".venv" / "bin" / "python"
    if not python.exists():
        sys.exit(f"error: no reference code in {args.reference_dir}: run benchmarks/reference/setup.sh first")
    other = subprocess.run([str(python), __file__, *sys.argv[1:], "--side", "reference"], capture_output=True,
                           text=True, check=True)
    rows = {"ours": [ours(data, seed) for seed in range(args.seeds)],
            "reference": [json.loads(line) for line in other.stdout.splitlines() if line.startswith("{")]}
    if args.normalized_inputs:
        rows["ours, normalised inputs"] = [ours(data, seed, normalize=True) for seed in range(args.seeds)]
    print(f"{len(data['y'])} labels to train on, {len(data['later_y'])} later pairs to judge on ({args.run})")
    print("| implementation | seed | epochs | training accuracy | correlation with the true reward | later pairs "
          "in the teacher's order |")
    print("|---|---|---|---|---|---|")
    for name, results in rows.items():
        for seed, row in enumerate(results):
            print(f"| {name} | {seed} | {row['epochs']} | {row['accuracy']:.3f} | {row['correlation']:.3f} | "
                  f"{row['agreement']:.3f} |")
        print(f"| {name} | mean | {np.mean([r['epochs'] for r in results]):.1f} | "
              f"{np.mean([r['accuracy'] for r in results]):.3f} | {np.mean([r['correlation'] for r in results]):.3f}"
              f" | {np.mean([r['agreement'] for r in results]):.3f} |")


if __name__ == "__main__":
    main()
