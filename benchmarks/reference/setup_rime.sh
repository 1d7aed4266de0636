#!/usr/bin/env bash
# RIME's own code (CJReinforce/RIME_ICML2024, a fork of the reference code) beside rime.py, with compatibility edits
# only, in the reference's virtual environment (benchmarks/reference/README.md, "RIME's own code"). Run setup.sh
# first; nothing of either is committed: both live in reference/ (git-ignored).
#
#   git clone https://github.com/CJReinforce/RIME_ICML2024 /tmp/RIME
#   benchmarks/reference/setup_rime.sh /tmp/RIME        # -> reference/RIME (edited copy), transformers in reference/.venv
set -euo pipefail
clone=${1:?usage: benchmarks/reference/setup_rime.sh RIME_CLONE [TARGET_DIR]}
here=$(cd "$(dirname "$0")" && pwd)
target=${2:-$here/../../reference}
commit=4ad03f4944e9e4a770bb4d8d7b0e07ea960b77f2
python=${PYTHON:-python3}
[ -x "$target/.venv/bin/python" ] || { echo "error: no $target/.venv: run benchmarks/reference/setup.sh first" >&2; exit 2; }

mkdir -p "$target/RIME"
git --git-dir="$( (cd "$clone" && git rev-parse --absolute-git-dir) )" archive "$commit" | tar -x -C "$target/RIME"
"$python" "$here/patch.py" "$target/RIME"
# its reward model's learning-rate warm-up comes from transformers (get_constant_schedule_with_warmup); its dmc2gym
# is the reference's (identical after the reference's np.int edit), already installed
"$target/.venv/bin/pip" install -q transformers==5.24.0
echo "RIME's code ready: $target/RIME with $target/.venv"
