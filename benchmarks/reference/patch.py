"""Compatibility edits to a copy of the reference code (rll-research/BPref at REFERENCE_COMMIT), or of RIME's code
(CJReinforce/RIME_ICML2024 at RIME_COMMIT) or QPA's (huxiao09/QPA at QPA_COMMIT), forks of it, so that it runs on
Python 3.11 with today's torch, numpy and MuJoCo. Each edit changes how the code reaches a library or what it records,
never what the algorithm computes; why is in EDITS, RIME_EDITS, QPA_EDITS and in benchmarks/reference/README.md.

    python benchmarks/reference/patch.py reference/BPref     # applies every edit once; a second call changes nothing
    python benchmarks/reference/patch.py reference/RIME      # a tree with train_RIME.py gets RIME_EDITS
    python benchmarks/reference/patch.py reference/QPA       # a tree with train_QPA.py gets QPA_EDITS
"""

import sys
from pathlib import Path

REFERENCE_COMMIT = "f3ece2ecf04b5d11b276d9bbb19b8004c29429d1"
RIME_COMMIT = "4ad03f4944e9e4a770bb4d8d7b0e07ea960b77f2"
QPA_COMMIT = "7e9e49e4291b0af4aaded913a02c15dcd13cce1e"

# (file, text in the reference, replacement, why it changes no algorithm)
EDITS = [
    ("reward_model.py",
     "device = 'cuda'\n",
     "device = 'cuda' if torch.cuda.is_available() else 'cpu'\n",
     "the reward model hard-codes CUDA; the same networks on the CPU when no GPU is present"),
    ("utils.py",
     "import metaworld\nimport metaworld.envs.mujoco.env_dict as _env_dict\n",
     "try:\n    import metaworld\n    import metaworld.envs.mujoco.env_dict as _env_dict\nexcept ImportError:\n"
     "    metaworld = None\n",
     "its Meta-World v2 cannot be installed (MuJoCo 2.0, mujoco-py); DMC runs never use it"),
    ("utils.py",
     "from torch import distributions as pyd\n",
     "from torch import distributions as pyd\npyd.Distribution.set_default_validate_args(False)\n",
     "torch >= 1.8 validates distribution arguments by default and refuses tanh(u) = +-1.0 in float32; torch 1.4, "
     "which the reference was written for, did not validate: the same values"),
    ("stable_baselines3/__init__.py",
     'with open(version_file, "r") as file_handler:\n    __version__ = file_handler.read().strip()',
     '__version__ = open(version_file).read().strip() if os.path.exists(version_file) else "unknown"',
     "its vendored Stable-Baselines3 reads a version.txt that the repository does not contain (PrefPPO only)"),
    ("custom_dmc2gym/dmc2gym/wrappers.py",
     "dim = np.int(np.prod(s.shape))",
     "dim = int(np.prod(s.shape))",
     "np.int was an alias of int, removed in numpy 1.24 (twice in the file)"),
]

# RIME's fork: its reward model takes the device from --device, and its dmc2gym already has int(); the two utils.py
# edits are the same as the reference's
RIME_EDITS = [edit for edit in EDITS if edit[0] == "utils.py"]

# QPA's fork: the same two utils.py edits; it logs to Weights & Biases only, so its evaluations are written to
# eval.csv (the reference's columns) and printed as a line, and its unused wandb import is made optional
OPTIONAL_WANDB = ("import wandb\n", "try:\n    import wandb\nexcept ImportError:\n    wandb = None\n",
                  "it imports wandb at the top and uses it only with wandb=true: runs without W&B need no wandb")
QPA_EDITS = RIME_EDITS + [
    ("train_QPA.py", *OPTIONAL_WANDB),
    ("agent/sac.py", *OPTIONAL_WANDB),
    ("train_QPA.py",
     "class Workspace(object):\n",
     "def record_evaluation(step, true_return, learned_return, success_rate, feedback):\n"
     "    new = not os.path.exists('eval.csv')\n"
     "    with open('eval.csv', 'a') as f:\n"
     "        if new:\n"
     "            f.write('step,episode_reward,true_episode_reward,success_rate,total_feedback\\n')\n"
     "        f.write(f'{step},{learned_return},{true_return},{success_rate},{feedback}\\n')\n"
     "    print(f'| eval | S: {step} | TR: {true_return:.4f} | FB: {feedback}', flush=True)\n\n"
     "class Workspace(object):\n",
     "its evaluations go to W&B only: a function that writes each to eval.csv and prints it (defined here)"),
    ("train_QPA.py",
     "ep_reward, ep_reward_hat, success_rate  = self.evaluate()\n",
     "ep_reward, ep_reward_hat, success_rate  = self.evaluate()\n                        "
     "record_evaluation(self.step, ep_reward, ep_reward_hat, success_rate, self.total_feedback)\n",
     "... called after each evaluation, with the values the evaluation computed"),
]


def apply(tree: Path) -> list[str]:
    """Applies every edit of EDITS (RIME_EDITS where `tree` has train_RIME.py, QPA_EDITS where it has train_QPA.py) to
    `tree`; returns what it did, one line an edit. An edit already applied is left as it is; a file where neither the
    original nor the edited text is
    found is an error."""
    done = []
    edits, source = EDITS, f"BPref at {REFERENCE_COMMIT[:7]}"
    if (tree / "train_RIME.py").is_file():
        edits, source = RIME_EDITS, f"RIME's code at {RIME_COMMIT[:7]}"
    if (tree / "train_QPA.py").is_file():
        edits, source = QPA_EDITS, f"QPA's code at {QPA_COMMIT[:7]}"
    for name, old, new, why in edits:
        path = tree / name
        if not path.is_file():
            raise FileNotFoundError(f"{path}: not found (is {tree} a copy of {source}?)")
        text = path.read_text()
        if new in text:  # first: an edit's new text may contain its old text
            done.append(f"already edited {name}")
        elif old in text:
            path.write_text(text.replace(old, new))
            done.append(f"edited {name}: {why}")
        else:
            raise ValueError(f"{path}: the text to edit is not there: {old.splitlines()[0]!r}")
    return done


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python benchmarks/reference/patch.py REFERENCE_TREE")
    try:
        print("\n".join(apply(Path(sys.argv[1]))))
    except (OSError, ValueError) as error:
        sys.exit(f"error: {error}")
