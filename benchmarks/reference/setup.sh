#!/usr/bin/env bash
# The reference code (rll-research/BPref) beside ours, in its own virtual environment, with compatibility edits only
# (benchmarks/reference/README.md). Nothing of it is committed: it lives in reference/ (git-ignored).
#
#   git clone https://github.com/rll-research/BPref /tmp/BPref
#   benchmarks/reference/setup.sh /tmp/BPref            # -> reference/BPref (edited copy) and reference/.venv
set -euo pipefail
clone=${1:?usage: benchmarks/reference/setup.sh BPREF_CLONE [TARGET_DIR]}
here=$(cd "$(dirname "$0")" && pwd)
target=${2:-$here/../../reference}
commit=f3ece2ecf04b5d11b276d9bbb19b8004c29429d1
python=${PYTHON:-python3}

# the reference's tree at the commit the comparison used, copied out of the clone (a git dir or a work tree)
mkdir -p "$target/BPref"
git --git-dir="$( (cd "$clone" && git rev-parse --absolute-git-dir) )" archive "$commit" | tar -x -C "$target/BPref"
"$python" "$here/patch.py" "$target/BPref"

# its own environment: Python 3.11, torch 2.13.0 (CPU), stock dm-control + mujoco in place of its custom_dmcontrol
"$python" -m venv "$target/.venv"
pip="$target/.venv/bin/pip"
"$pip" install -q torch==2.13.0 mujoco==3.3.0 dm-control==1.0.28 numpy==2.3.5 'setuptools>=77.0.3,<81' \
    hydra-core==0.11.3 termcolor tqdm scipy scikit-image tensorboard pyyaml cloudpickle pandas matplotlib
"$pip" install -q --no-deps gym==0.17.3                    # its dmc2gym needs the 4-value step API
"$pip" install -q --no-deps "$target/BPref/custom_dmc2gym"  # dmc2gym is not on the package index
echo "reference ready: $target/BPref with $target/.venv"
