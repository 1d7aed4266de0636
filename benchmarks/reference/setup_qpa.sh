#!/usr/bin/env bash
# QPA's own code (huxiao09/QPA, a fork of the reference code) beside qpa.py, with compatibility edits only, in the
# reference's virtual environment (benchmarks/reference/README.md, "QPA's own code"). Run setup.sh first; nothing of
# either is committed: both live in reference/ (git-ignored).
#
#   git clone https://github.com/huxiao09/QPA /tmp/QPA
#   benchmarks/reference/setup_qpa.sh /tmp/QPA          # -> reference/QPA (edited copy), run by reference/.venv
set -euo pipefail
clone=${1:?usage: benchmarks/reference/setup_qpa.sh QPA_CLONE [TARGET_DIR]}
here=$(cd "$(dirname "$0")" && pwd)
target=${2:-$here/../../reference}
commit=7e9e49e4291b0af4aaded913a02c15dcd13cce1e
python=${PYTHON:-python3}
[ -x "$target/.venv/bin/python" ] || { echo "error: no $target/.venv: run benchmarks/reference/setup.sh first" >&2; exit 2; }

mkdir -p "$target/QPA"
git --git-dir="$( (cd "$clone" && git rev-parse --absolute-git-dir) )" archive "$commit" | tar -x -C "$target/QPA"
"$python" "$here/patch.py" "$target/QPA"
# its dmc2gym is the reference's (the same file before the reference's np.int edit), already installed; everything
# else it imports for DMC runs (hydra-core 0.11, gym, scipy, scikit-image, tqdm) is in the reference's environment
echo "QPA's code ready: $target/QPA with $target/.venv"
