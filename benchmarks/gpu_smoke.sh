#!/bin/bash
# The scripts on a GPU: tiny walker-walk runs of pebble.py, rime.py and prefppo.py on CUDA, pebble.py and rime.py
# stopped by SIGTERM after their first checkpoint and resumed (their eval.csv against the uninterrupted run's), then
# pebble.py and rime.py with the paper's networks (1024 x 2, batch 1024) one after the other, wall time side by side.
# Run from the repository root with the requirements installed: OUT=some/dir bash benchmarks/gpu_smoke.sh
# (A machine without network access can take the packages as a folder .whl/ of wheels, installed first.)
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD/.whl/stub
fi
export PYTHONUNBUFFERED=1 PYTHONWARNINGS=ignore
OUT=${OUT:-/tmp/gpu_smoke}; mkdir -p $OUT
nvidia-smi -L; python3 -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'numpy', numpy.__version__)"
R=/tmp/r; mkdir -p $R
T="--env-id walker-walk --seed 3 --total-timesteps 3000 --seed-steps 500 --unsup-steps 600 --feedback-every 500 --max-feedback 40 --feedback-per-session 10 --segment-len 10 --eval-every 500 --checkpoint-every 1300 --hidden-dim 32 --num-layers 2 --batch-size 32 --reward-epochs 3 --reward-batch-size 32 --eval-episodes 1"
P="--env-id walker-walk --seed 3 --total-timesteps 5000 --num-envs 2 --num-steps 250 --minibatch-size 250 --unsup-steps 1000 --feedback-every 1000 --max-feedback 40 --feedback-per-session 10 --segment-len 10 --eval-every 1000 --hidden-dim 32 --num-layers 2 --reward-epochs 3 --reward-batch-size 32 --eval-episodes 1 --update-epochs 2 --unsup-update-epochs 2"
start=$(date +%s)
for s in pebble rime; do timeout 200 python3 $s.py $T --output-dir $R/$s-a > $OUT/$s-a.log 2>&1 & done
timeout 200 python3 prefppo.py $P --output-dir $R/prefppo-a > $OUT/prefppo-a.log 2>&1 &
# interrupted by SIGTERM after the first checkpoint, then resumed
for s in pebble rime; do (timeout 200 python3 $s.py $T --output-dir $R/$s-b > $OUT/$s-b.log 2>&1 & pid=$!
  while [ ! -f $R/$s-b/checkpoint.pt ] && kill -0 $pid 2>/dev/null; do sleep 0.2; done; sleep 2; kill -TERM $pid; wait $pid
  echo "exit after SIGTERM: $?" >> $OUT/$s-b.log; timeout 200 python3 $s.py --resume $R/$s-b >> $OUT/$s-b.log 2>&1; echo "exit: $?" >> $OUT/$s-b.log) & done
wait; echo "tiny runs: $(( $(date +%s) - start )) s"
for s in pebble rime prefppo; do echo "== $s"; tail -2 $OUT/$s-a.log; cat $R/$s-a/eval.csv; done
for s in pebble rime; do echo "== $s resumed"; grep -E "SIGTERM|resuming|exit" $OUT/$s-b.log; cat $R/$s-b/eval.csv; done
python3 - <<'PY'
import torch
for s in ("pebble", "rime"):
    st = torch.load(f"/tmp/r/{s}-b/checkpoint.pt", weights_only=True)
    print(s, "step", st["progress"]["global_step"], "cuda rng states", len(st.get("cuda_rng", [])), "buffer on", st["buffer"]["obs"].device)
PY
# paper-size networks (1024 x 2, batch 1024), pre-training then one session: wall time side by side, one at a time
F="--env-id walker-walk --seed 1 --total-timesteps 6000 --unsup-steps 4000 --eval-every 3000 --eval-episodes 1 --checkpoint-every 0"
for s in pebble rime; do t0=$(date +%s); timeout 150 python3 $s.py $F --output-dir $R/$s-paper > $OUT/$s-paper.log 2>&1; echo "$s paper-size: exit $? in $(( $(date +%s) - t0 )) s"; cat $R/$s-paper/eval.csv; done
