#!/usr/bin/env bash
# The reference code (rll-research/BPref) with its Meta-World v2 tasks, in a
# virtual environment of its own (reference/.venv-metaworld), beside the DMC one that setup.sh builds. Nothing of
# either clone is committed: both trees live in reference/ (git-ignored).
#
#   git clone https://github.com/rll-research/BPref /tmp/BPref
#   git clone https://github.com/Farama-Foundation/Metaworld /tmp/Metaworld
#   benchmarks/reference/setup_metaworld.sh /tmp/BPref /tmp/Metaworld
#
# What it builds: reference/BPref-metaworld (BPref at setup.sh's commit, patch.py's edits; its guarded metaworld
# import then finds Meta-World) and reference/.venv-metaworld, Python 3.11 with
#   - free-mujoco-py 2.1.6 (mujoco-py 2.1 with the MuJoCo 2.1 binaries inside the wheel; it declares Python < 3.11,
#     so --ignore-requires-python, and --no-deps), which cythonizes and compiles its extension at its first import
#     (Cython 0.29.x, gcc, and Debian's libosmesa6-dev libgl1-mesa-dev libglew-dev patchelf);
#   - Meta-World at 04be337a, the last commit before its move to Gymnasium (RIME's fork pins it too): its setup.py
#     wants gym >= 0.15.4 and mujoco-py >= 2.0, < 2.2; installed --no-deps;
#   - numpy 1.26.4 (mujoco-py needs numpy < 2), gym 0.17.3 (as setup.sh: 4-value step API), torch 2.13.0 (CPU),
#     hydra-core 0.11.3 and what train_SAC.py / train_PEBBLE.py import.
#
# Checked on 2026-11-27 (2 busy cores): mujoco-py's extension builds at its first import (3.3 minutes here, once),
# and benchmarks/reference/run.py --env-id button-press runs the reference's train_SAC.py and train_PEBBLE.py on
# metaworld_button-press-v2 to the end (evaluation success rates, labels, final networks read back).
set -euo pipefail
bpref=${1:?usage: benchmarks/reference/setup_metaworld.sh BPREF_CLONE METAWORLD_CLONE [TARGET_DIR]}
metaworld=${2:?usage: benchmarks/reference/setup_metaworld.sh BPREF_CLONE METAWORLD_CLONE [TARGET_DIR]}
here=$(cd "$(dirname "$0")" && pwd)
target=${3:-$here/../../reference}
commit=f3ece2ecf04b5d11b276d9bbb19b8004c29429d1
metaworld_commit=04be337a
python=${PYTHON:-python3}
gitdir() { (cd "$1" && git rev-parse --absolute-git-dir); }

# Debian's build dependencies of mujoco-py's extension
if [ "$(id -u)" = 0 ]; then
    apt-get install -y -q libosmesa6-dev libgl1-mesa-dev libglew-dev patchelf
else
    echo "note: not root; install libosmesa6-dev libgl1-mesa-dev libglew-dev patchelf with apt-get" >&2
fi

# the reference's tree, as setup.sh takes it, in its own folder
mkdir -p "$target/BPref-metaworld"
git --git-dir="$(gitdir "$bpref")" archive "$commit" | tar -x -C "$target/BPref-metaworld"
"$python" "$here/patch.py" "$target/BPref-metaworld"

# Meta-World's tree at 04be337a. A partial copy of its history (some large files absent) is taken file by file:
# the absent ones seen so far are v1 meshes (.DAE, which MuJoCo does not read) and the textures wood1.png and
# real_door.png, which every v2 scene needs (the table); those two are byte-identical (same git blob) in the
# metaworld 3.1.1 wheel on PyPI, from which they are then taken.
mw="$target/metaworld-$metaworld_commit"
rm -rf "$mw" && mkdir -p "$mw"
mwgit=$(gitdir "$metaworld")
if ! git --git-dir="$mwgit" archive "$metaworld_commit" | tar -x -C "$mw" 2>/dev/null; then
    rm -rf "$mw" && mkdir -p "$mw"
    missing=()
    while IFS=$'\t' read -r meta path; do
        sha=${meta##* }
        if git --git-dir="$mwgit" cat-file -e "$sha" 2>/dev/null; then
            mkdir -p "$mw/$(dirname "$path")"
            git --git-dir="$mwgit" cat-file blob "$sha" > "$mw/$path"
        else
            missing+=("$path:$sha")
        fi
    done < <(git --git-dir="$mwgit" ls-tree -r "$metaworld_commit")
    wheel=$(mktemp -d)
    "$python" -m pip download -q --no-deps -d "$wheel" metaworld==3.1.1
    (cd "$wheel" && "$python" -m zipfile -e ./*.whl x)
    for entry in "${missing[@]}"; do
        path=${entry%:*} sha=${entry##*:}
        case "$path" in *.DAE) echo "absent, unused by MuJoCo: $path"; continue ;; esac
        found=$(find "$wheel/x" -name "$(basename "$path")" | head -1)
        if [ -n "$found" ] && [ "$(git hash-object "$found")" = "$sha" ]; then
            cp "$found" "$mw/$path"
        else
            echo "error: $path is absent from $metaworld and not found identical in metaworld 3.1.1" >&2
            exit 1
        fi
    done
    rm -rf "$wheel"
fi

"$python" -m venv "$target/.venv-metaworld"
pip="$target/.venv-metaworld/bin/pip"
"$pip" install -q torch==2.13.0 numpy==1.26.4 'Cython<0.30' hydra-core==0.11.3 termcolor tqdm scipy scikit-image \
    tensorboard pyyaml cloudpickle glfw imageio fasteners cffi
"$pip" install -q --no-deps gym==0.17.3                                   # as setup.sh
"$pip" install -q --no-deps --ignore-requires-python free-mujoco-py==2.1.6
"$pip" install -q --no-deps "$mw"
"$pip" install -q --no-deps "$target/BPref-metaworld/custom_dmc2gym"     # utils.py imports dmc2gym
# mujoco-py builds its extension at the first import (minutes of one core); do it now, once
"$target/.venv-metaworld/bin/python" -c "import mujoco_py; print('mujoco_py', mujoco_py.__version__)"
"$target/.venv-metaworld/bin/python" -c "
import metaworld.envs.mujoco.env_dict as d
env = d.ALL_V2_ENVIRONMENTS['button-press-v2']()
env._freeze_rand_vec = False; env._set_task_called = True; env.seed(1)
obs = env.reset(); print('button-press-v2', obs.shape, env.step(env.action_space.sample())[1:3])"
echo "reference with Meta-World ready: $target/BPref-metaworld with $target/.venv-metaworld"
