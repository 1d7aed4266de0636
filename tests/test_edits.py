"""benchmarks/reference/edits.py: the reference code's ways as text edits applied to a copy of a script. Each edited
copy differs from the script in the edited lines only, and runs; an edit that no longer fits is refused."""

import difflib
import subprocess
import sys

import numpy as np
import pytest
import torch

from benchmarks.reference.edits import EDITS, edited_source
from tests.helpers import ENV, ROOT, run_cli

EDIT_SCRIPT = "benchmarks/reference/edits.py"
CASES = [(name, script) for name, scripts in EDITS.items() for script in scripts]


@pytest.mark.parametrize("name, script", CASES, ids=[f"{n}-{s}" for n, s in CASES])
def test_an_edited_copy_differs_in_the_edited_lines_only(name, script, tmp_path):
    copy = tmp_path / script
    result = subprocess.run([sys.executable, str(ROOT / EDIT_SCRIPT), name, "--write", str(copy), "--", script],
                            capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    original = (ROOT / script).read_text().splitlines(keepends=True)
    removed = [line[1:] for line in difflib.unified_diff(original, copy.read_text().splitlines(keepends=True), n=0)
               if line.startswith("-") and not line.startswith("---")]
    edited_lines = []  # the lines an edit's old text covers: whole lines, or the one line holding it
    for old, _ in EDITS[name][script]:
        if old.count("\n") > 1 or not old.endswith("\n"):
            edited_lines += old.splitlines(keepends=True) if "\n" in old else [l for l in original if old in l]
        else:
            edited_lines.append(old)
    assert removed and sorted(removed) == sorted(edited_lines)  # the edited lines changed, and nothing else


def test_an_edit_that_no_longer_fits_is_refused():
    with pytest.raises(ValueError, match="does not fit"):
        edited_source("pebble.py", ["raw-reward-inputs", "raw-reward-inputs"])  # its text is gone after once
    with pytest.raises(ValueError, match="no edit 'nonsense' for pebble.py"):
        edited_source("pebble.py", ["nonsense"])


@pytest.mark.parametrize("script", ["pebble.py", "rime.py", "qpa.py"])  # rime.py: its warm start's inputs too
def test_raw_reward_inputs_run_pebble_with_the_reference_s_raw_observations(script, tmp_path):
    out = tmp_path / "raw"
    flags = ["--env-id", "Pendulum-v1", "--total-timesteps", "700", "--seed-steps", "200", "--unsup-steps", "200",
             "--feedback-every", "200", "--max-feedback", "20", "--feedback-per-session", "10", "--segment-len", "10",
             "--eval-every", "700", "--hidden-dim", "32", "--batch-size", "32", "--reward-epochs", "3",
             "--reward-batch-size", "32", "--eval-episodes", "1", "--output-dir", str(out)]
    if script == "rime.py":  # one warm-start update a pre-training step, not 5: cheaper
        flags += ["--rime-warm-updates", "1"]
    result = run_cli(EDIT_SCRIPT, "raw-reward-inputs", "--", script, *flags)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("reward model trained on") == 2
    saved = torch.load(out / "final_model.pt", weights_only=True)["reward_model"]
    assert not saved["input_mean"].any() and (saved["input_std"] == 1).all()  # the identity: raw inputs
    assert saved["input_clip"].item() == float("inf")


@pytest.mark.parametrize("edits", [[], ["reference-thresholds"]], ids=["ours", "reference-thresholds"])
def test_reference_thresholds_apply_eps_twice_after_the_first_session(edits, tmp_path):
    """The equal teacher (eps 0.1) ties a pair where its returns differ by less than delta_equal: eps x |scale| in
    every session (ours); eps x |scale| in the first and eps^2 x |scale| after it (the reference's)."""
    out = tmp_path / "run"
    flags = ["--env-id", "Pendulum-v1", "--teacher", "equal", "--total-timesteps", "900", "--seed-steps", "200",
             "--unsup-steps", "200", "--feedback-every", "200", "--max-feedback", "90", "--feedback-per-session", "30",
             "--segment-len", "10", "--eval-every", "900", "--hidden-dim", "32", "--batch-size", "32",
             "--reward-epochs", "1", "--reward-batch-size", "32", "--eval-episodes", "1", "--output-dir", str(out)]
    result = run_cli(EDIT_SCRIPT, *edits, "--", "pebble.py", *flags) if edits else run_cli("pebble.py", *flags)
    assert result.returncode == 0, result.stderr[-3000:]
    from sim_teacher import load_labels

    sessions = load_labels(str(out))
    assert len(sessions) == 3
    between = 0  # pairs tied by ours and not by the reference's, after the first session
    for i, session in enumerate(sessions):
        gap = np.abs(session["rewards0"].sum(1) - session["rewards1"].sum(1))
        eps = 0.1 if i == 0 or not edits else 0.01
        np.testing.assert_array_equal(session["y"] == 0.5, gap < eps * abs(session["threshold_scale"]))
        between += i > 0 and int(((gap >= 0.01 * abs(session["threshold_scale"]))
                                  & (gap < 0.1 * abs(session["threshold_scale"]))).sum())
    assert between > 0  # so the two ways label some pair differently
