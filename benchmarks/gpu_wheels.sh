#!/bin/bash
# The packages a lent GPU machine lacks for the GPU checks (it has torch, numpy, tensorboard and pytest, and no
# network): wheels for its Python 3.12 into .whl/ (git-ignored, about 11 MB), for `carry`; gpu_compile_check.sh
# and gpu_smoke.sh install them first. The checks run Gymnasium's MuJoCo tasks (Hopper), so dm-control (a 56 MB
# wheel) and metaworld stay behind. Run here, from the repository root: bash benchmarks/gpu_wheels.sh
set -e
rm -rf .whl; mkdir .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
  mujoco==3.3.0 gymnasium==1.4.0 tyro==1.0.17 farama-notifications glfw pyopengl docstring-parser typeguard shtab \
  "typing-extensions>=4.14" stable-baselines3  # the last: CleanRL's SAC (gpu_speed.py --cleanrl) uses its buffer
du -sh .whl
