"""Each pytest-xdist worker computes on one thread: the two workers share two cores (and the scripts they start
run with OMP_NUM_THREADS=1, tests/helpers.py)."""

import torch

torch.set_num_threads(1)
