#!/usr/bin/env bash
# docs/parity.md in one command: every parity preset of experiments/grid.py (ours and the reference code's runs,
# benchmarks/reference/README.md), then the report. Finished runs are skipped and stopped runs of ours resume, so
# the same command continues an interrupted side-by-side; the reference cannot resume (its stopped runs restart).
#
#   benchmarks/reference/setup.sh /tmp/BPref     # once: the reference in reference/, its own environment
#   benchmarks/reference/parity.sh               # hours on a CPU: ~30 min per run of ours, ~50 of the reference's
#   benchmarks/reference/parity.sh --dry-run     # what would run; no report
#
# Arguments go to every grid (e.g. --workers 1); PARITY_ROOT is the folder of the runs (runs/parity).
set -euo pipefail
cd "$(dirname "$0")/../.."
root=${PARITY_ROOT:-runs/parity}
python=${PYTHON:-python}
for preset in parity-pebble parity-pebble-mistake parity-pebble-cheetah parity-sac parity-prefppo; do
    "$python" experiments/grid.py "$preset" --root "$root" "$@"
done
for arg in "$@"; do
    [ "$arg" = --dry-run ] && exit 0
done
"$python" experiments/report.py "$root" --out docs/parity --parity docs/parity.md
