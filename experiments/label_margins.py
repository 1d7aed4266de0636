"""How far apart were the pairs a teacher was asked about, and how much of the true reward can be learnt from them?

For one run's saved labels: per stretch of sessions, the median |difference| between the two segments' true returns
beside the median segment return, and the share of near-ties (a difference under 10% of the larger |return|). Then
a random fifth of the kept pairs is held out, and pebble.py's reward ensemble (the paper's: 3 members of 3 x 256,
Adam 3e-4, batch 128; the three scripts share it) is trained twice on the rest: on the labels, as reward learning
does (until 97% accuracy or --epochs), and on the true per-step rewards (a regression, the rewards scaled into the
tanh output's range), the most that this network and the observation allow. Both are judged on the held-out pairs:
per-step correlation with the true reward, and the share of pairs they order as the teacher did.
Docs: docs/experiments.md

    python experiments/label_margins.py RUN_DIR
"""

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pebble  # noqa: E402
from sim_teacher import load_labels, load_pairs  # noqa: E402


REGRESSION_EPOCHS = 10  # on the true rewards; the figures in docs/results.md were made with 10


@dataclass
class Args:
    labels: tyro.conf.Positional[str]
    """a run's folder, its labels/ folder or one session_*.npz"""
    stretches: int = 4
    """rows of the margins table: the sessions in this many stretches, in order"""
    seeds: int = 1
    """held-out splits (and initialisations) to fit; 0: the margins table only"""
    epochs: int = 50
    """most epochs of reward learning on the labels (the regression always runs 10)"""


def margins(sessions: list[dict], stretches: int) -> list[dict]:
    """One row per stretch of sessions: pairs, median segment return, median return difference, near-ties."""
    rows = []
    for part in np.array_split(np.arange(len(sessions)), min(stretches, len(sessions))):
        returns0 = np.concatenate([sessions[i]["rewards0"].sum(1) for i in part])
        returns1 = np.concatenate([sessions[i]["rewards1"].sum(1) for i in part])
        difference = np.abs(returns1 - returns0)
        rows.append({"sessions": f"{part[0] + 1}-{part[-1] + 1}", "pairs": len(returns0),
                     "median return": float(np.median(np.concatenate([returns0, returns1]))),
                     "median difference": float(np.median(difference)),
                     "near-ties": float(np.mean(difference < 0.1 * np.maximum(abs(returns0), abs(returns1))))})
    return rows


def judged(model, inputs, rewards, y) -> tuple[float, float]:
    """(per-step correlation of r_hat with the true reward, share of strict labels y that it orders alike)."""
    with torch.no_grad():
        learned = [model(side).mean(0)[..., 0] for side in inputs]
    correlation = np.corrcoef(torch.cat(learned).flatten().numpy(), torch.cat(rewards).flatten().numpy())[0, 1]
    strict = y != 0.5
    agreement = ((learned[1].sum(1) > learned[0].sum(1)) == (y > 0.5))[strict].float().mean()
    return float(correlation), float(agreement)


def fits(path: str, sessions: list[dict], seed: int, epochs: int) -> dict:
    """{"labels": judged(...), "true reward": judged(...)} on a held-out fifth of the kept pairs."""
    obs_dim = sessions[0]["obs0"].shape[-1]
    shape = (sessions[0]["obs0"].shape[1], obs_dim + sessions[0]["actions0"].shape[-1])
    inputs0, inputs1, y, keep = load_pairs(path, shape)
    inputs = [torch.as_tensor(side[keep], dtype=torch.float32) for side in (inputs0, inputs1)]
    y = torch.as_tensor(y[keep], dtype=torch.float32)
    rewards = [torch.as_tensor(np.concatenate([s[f"rewards{i}"] for s in sessions])[keep]) for i in (0, 1)]
    order = torch.randperm(len(y), generator=torch.Generator().manual_seed(seed))
    held_out, train = order[: len(y) // 5], order[len(y) // 5 :]
    results = {}
    for target in ("labels", "true reward"):
        torch.manual_seed(seed)
        model = pebble.RewardEnsemble(shape[1], 0, 3)  # the input is (observation, action) side by side
        model.set_input_stats(torch.cat([side[train] for side in inputs], 1)[..., :obs_dim].flatten(0, 1))
        optimizer = pebble.adam(model.parameters(), 3e-4)
        if target == "labels":
            preferences = {"inputs0": inputs[0][train], "inputs1": inputs[1][train], "y": y[train]}
            pebble.train_reward(model, optimizer, preferences, pebble.Args(reward_epochs=epochs))
        else:
            steps = torch.cat([side[train] for side in inputs]).flatten(0, 1)
            scaled = torch.cat([side[train] for side in rewards]).flatten() / torch.cat(rewards).abs().max()
            for _ in range(REGRESSION_EPOCHS):
                for batch in torch.randperm(len(steps)).split(512):
                    predicted = model(steps[batch])[..., 0]
                    pebble.optimize(optimizer, F.mse_loss(predicted, scaled[batch].expand_as(predicted)))
        results[target] = judged(model, [side[held_out] for side in inputs], [side[held_out] for side in rewards],
                                 y[held_out])
    return results


def fail(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def main(args: Args) -> None:
    if min(args.stretches, args.epochs) < 1 or args.seeds < 0:
        fail("--stretches and --epochs must be at least 1, --seeds at least 0")
    try:
        sessions = load_labels(args.labels)
    except ValueError as error:
        fail(str(error))
    torch.set_num_threads(1)
    print(f"{args.labels}: {len(sessions)} sessions, {sum(len(s['y']) for s in sessions)} pairs")
    print("\n| sessions | pairs | median segment return | median return difference | near-ties (< 10%) |")
    print("|---|---:|---:|---:|---:|")
    for row in margins(sessions, args.stretches):
        print(f"| {row['sessions']} | {row['pairs']} | {row['median return']:.3f} | {row['median difference']:.3f} | "
              f"{row['near-ties']:.2f} |")
    if args.seeds:
        print("\n| seed | trained on | per-step correlation with the true reward | held-out pairs in the teacher's "
              "order |")
        print("|---|---|---:|---:|")
    for seed in range(args.seeds):
        for target, (correlation, agreement) in fits(args.labels, sessions, seed, args.epochs).items():
            print(f"| {seed} | {target} | {correlation:.3f} | {agreement:.3f} |")


if __name__ == "__main__":
    main(tyro.cli(Args, description=__doc__.split("\n\n")[0]))
