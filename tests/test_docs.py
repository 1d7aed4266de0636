"""The commands quoted in README.md and docs/ fit the code and their links lead somewhere (tests/doc_commands.py), so
the docs cannot drift from the flags: a wrong flag, value, preset, file or link in a page fails here."""

import subprocess
import sys

from tests.helpers import ENV, ROOT

CHECKER = ROOT / "tests" / "doc_commands.py"


def test_every_quoted_command_fits_the_code():
    result = subprocess.run([sys.executable, str(CHECKER)], capture_output=True, text=True, env=ENV, cwd=ROOT)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]


def test_the_check_finds_each_kind_of_drift(tmp_path):
    (tmp_path / "other.md").write_text("# A heading: `with code`\n")
    page = tmp_path / "page.md"
    page.write_text("""See [it](other.md#a-heading-with-code), [this](other.md#nope) and [that](gone.md).
Run `python pebble.py --env-id walker-walk --teacher oracle` or, over several lines,
`python rime.py --env-id walker-walk
--teacher mistake --teacher-eps-mistake 0.3`.

Last wave of training episodes 595 567 643 565 579 (589.8 ± 28.8, 5 seeds, 32 min per run;
`python experiments/grid.py parity-prefppo --implementations ours`, seeds 4-5 at e311d4a). PPO: 821 869 707 (3 seeds;
`python experiments/grid.py learning-cpu-prefppo`). Two seeds: `python experiments/grid.py rime-reference --seeds 1 2`.

| arm | seeds | final return |
|---|---|---|
| ours | 1 2 3 4 5 | 595 567 643 565 579 |

```bash
python experiments/grid.py parity-prefppo --implementations ours --root runs/other
python experiments/grid.py parity-prefppo --seeds 1 2 3 4 5 --root runs/other   # 5 seeds
python experiments/grid.py mini-bpref --seeds 1 2   # 3 seeds
```

```bash
python pebble.py --env-id walker-walk --teacher nobody          # an unknown teacher
python prefppo.py --env-id walker-walk --segment-len 5000       # out of its range
python rime.py --env-id walker-walk --rime-alpha -1
python pebble.py --env-id walker-walk --no-such-flag 3
python pebble.py --env-id no-such-task
MUJOCO_GL=egl python label_server.py runs/<run> --port 8001 --colour red
python fit_teacher.py --labels RUN_DIR --simulate
python benchmarks/reference/run.py --env-id walker-walk --seed SEED          # --output-dir is required
python experiments/report.py DIR --reps many                                 # --reps takes a number
python experiments/grid.py no-such-preset
python experiments/grid.py mini-bpref --seeds 1 2 && python experiments/report.py runs/mini-bpref --out DIR
python experiments/grid.py custom --pebble-flags='--reward-input-norm'
python benchmarks/reference/edits.py raw-reward-inputs -- pebble.py --env-id walker-walk --max-feedback 0
python benchmarks/reference/edits.py no-such-edit -- pebble.py ...
python benchmarks/gone.py
benchmarks/reference/setup.sh /tmp/BPref
```
""")
    result = subprocess.run([sys.executable, str(CHECKER), str(page)], capture_output=True, text=True, env=ENV,
                            cwd=ROOT)
    assert result.returncode == 1
    found = result.stdout.splitlines()
    expected = ["link (other.md#nope): no such heading in other.md", "link (gone.md): no such file",
                # a preset's seed count against the table above its code block, its comment, the prose before it
                "--root runs/other` runs 3 seeds, beside '1 2 3 4 5 in the seeds column'",
                "mini-bpref --seeds 1 2` runs 2 seeds, beside '3 seeds'",
                "parity-prefppo --implementations ours` runs 3 seeds, beside '5 seeds'",
                "--teacher nobody`: pebble.py refuses its flags: ", "--segment-len 5000`: prefppo.py refuses its flags",
                "--rime-alpha -1`: rime.py refuses its flags", "pebble.py: no flag --no-such-flag",
                "--env-id no-such-task`: pebble.py refuses its flags", "label_server.py: no flag --colour",
                "run.py refuses its command line (placeholders filled in): ",
                "report.py refuses its command line (placeholders filled in): ",
                "grid.py: no preset 'no-such-preset'", "--pebble-flags: no flag --reward-input-norm in pebble.py",
                "--max-feedback 0`: pebble.py refuses its flags", "edits.py: no edit 'no-such-edit'",
                "benchmarks/gone.py: no such file"]
    assert len(found) == len(expected), result.stdout
    for line, part in zip(found, expected):
        assert line.startswith("page.md: ") and part in line, (line, part)
