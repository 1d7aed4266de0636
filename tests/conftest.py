"""Each pytest-xdist worker computes on one thread: the two workers share two cores (and the scripts they start
run with OMP_NUM_THREADS=1, tests/helpers.py). Every interpreter the tests start skips the final searches for
reference cycles at its exit (tests/fast_exit/sitecustomize.py)."""

import os
from pathlib import Path

import torch

torch.set_num_threads(1)
FAST_EXIT = str(Path(__file__).resolve().parent / "fast_exit")
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [FAST_EXIT, os.environ.get("PYTHONPATH")]))

# pytest-xdist hands each worker a file at a time, in collection order (--no-loadscope-reorder, pytest.ini): the
# longest files first (--durations=0, 2026-11-28), so that the two workers end together
LONGEST_FIRST = ["test_resume.py", "test_pebble.py", "test_experiments.py", "test_prefppo.py", "test_fit_teacher.py",
                 "test_reference.py", "test_label_server.py", "test_video.py", "test_human_teacher.py"]


def pytest_collection_modifyitems(items):
    def rank(item):
        return LONGEST_FIRST.index(item.path.name) if item.path.name in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)  # stable: the tests of a file keep their order
