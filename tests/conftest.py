"""Each pytest-xdist worker computes on one thread: the two workers share two cores (and the scripts they start
run with OMP_NUM_THREADS=1, tests/helpers.py). Every interpreter the tests start skips the final searches for
reference cycles at its exit (tests/fast_exit/sitecustomize.py)."""

import os
from pathlib import Path

import torch

torch.set_num_threads(1)
FAST_EXIT = str(Path(__file__).resolve().parent / "fast_exit")
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [FAST_EXIT, os.environ.get("PYTHONPATH")]))
