#!/bin/bash
# --compile on a GPU (issue 48), the correctness checks, in about 6 minutes:
# 1. tests/test_cuda_graph.py on real CUDA graphs (replayed SAC updates, r_hat and actions against eager ones);
# 2. tiny Hopper-v5 runs of pebble.py and rime.py: eager, --compile, and --compile stopped by SIGTERM after its
#    first checkpoint then resumed (its eval.csv must equal the uninterrupted compiled run's);
# 3. two seeds of a short pebble.py run (Hopper-v5, 256 x 2, 16K steps), eager and --compile: the curves side by side.
# Run from the repository root with the requirements installed: OUT=some/dir bash benchmarks/gpu_compile_check.sh
# (A machine without network access takes the packages as .whl/, made here by benchmarks/gpu_wheels.sh.)
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1 PYTHONWARNINGS=ignore
OUT=${OUT:-/tmp/gpu_compile_check}; mkdir -p $OUT
R=/tmp/r; rm -rf $R; mkdir -p $R
nvidia-smi -L; python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
start=$(date +%s)
timeout 150 python3 -m pytest -p no:cacheprovider -n 0 -q -rs tests/test_cuda_graph.py 2>&1 | tail -n 15
echo "tests: $(( $(date +%s) - start )) s"
T="--env-id Hopper-v5 --seed 3 --total-timesteps 3000 --seed-steps 500 --unsup-steps 600 --feedback-every 500 --max-feedback 40 --feedback-per-session 10 --segment-len 10 --eval-every 500 --checkpoint-every 1300 --hidden-dim 32 --num-layers 2 --batch-size 32 --reward-epochs 3 --reward-batch-size 32 --eval-episodes 1"
C="--env-id Hopper-v5 --total-timesteps 16000 --unsup-steps 4000 --feedback-every 4000 --max-feedback 200 --feedback-per-session 50 --eval-every 4000 --eval-episodes 5 --hidden-dim 256 --num-layers 2 --batch-size 256 --checkpoint-every 0"
start=$(date +%s)
for s in pebble rime; do
  timeout 240 python3 $s.py $T --output-dir $R/$s-eager > $OUT/$s-eager.log 2>&1 &
  timeout 240 python3 $s.py $T --compile --output-dir $R/$s-compiled > $OUT/$s-compiled.log 2>&1 &
  (timeout 240 python3 $s.py $T --compile --output-dir $R/$s-resumed > $OUT/$s-resumed.log 2>&1 & pid=$!
   while [ ! -f $R/$s-resumed/checkpoint.pt ] && kill -0 $pid 2>/dev/null; do sleep 0.2; done; sleep 2; kill -TERM $pid
   wait $pid; echo "exit after SIGTERM: $?" >> $OUT/$s-resumed.log
   timeout 240 python3 $s.py --resume $R/$s-resumed >> $OUT/$s-resumed.log 2>&1; echo "exit: $?" >> $OUT/$s-resumed.log) &
done
for seed in 1 2; do
  timeout 330 python3 pebble.py $C --seed $seed --output-dir $R/curve-eager-$seed > $OUT/curve-eager-$seed.log 2>&1 &
  timeout 330 python3 pebble.py $C --seed $seed --compile --output-dir $R/curve-compiled-$seed > $OUT/curve-compiled-$seed.log 2>&1 &
done
wait; echo "runs: $(( $(date +%s) - start )) s"
python3 - <<'PY'
import csv, os
def returns(run):
    path = f"/tmp/r/{run}/eval.csv"
    return {r["step"]: float(r["episode_return"]) for r in csv.DictReader(open(path))} if os.path.exists(path) else {}
for s in ("pebble", "rime"):
    runs = [returns(f"{s}-{kind}") for kind in ("eager", "compiled", "resumed")]
    print(f"\n{s}, tiny: step | eager | --compile | --compile, SIGTERM + --resume")
    for step in runs[0]:
        print(step, *(f"{r.get(step, float('nan')):.4f}" for r in runs), sep=" | ")
    print(f"{s}: resumed == uninterrupted compiled: {runs[1] == runs[2] and len(runs[1]) > 0}")
for seed in (1, 2):
    eager, compiled = returns(f"curve-eager-{seed}"), returns(f"curve-compiled-{seed}")
    print(f"\npebble.py 256 x 2, seed {seed}: step | eager | --compile")
    for step in eager:
        print(step, f"{eager[step]:.1f}", f"{compiled.get(step, float('nan')):.1f}", sep=" | ")
PY
for f in $OUT/*.log; do grep -l -E "Error|error" $f > /dev/null && { echo "== $f"; tail -n 5 $f; }; done
