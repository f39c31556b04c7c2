#!/usr/bin/env bash
# Every number in the README's results table, in order (about an hour on 2 CPU cores after the
# training run). Logs go to outputs/results/.
set -euo pipefail
cd "$(dirname "$0")/.."
export HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1
PY=.venv/bin/python
BIN=.venv/bin
OUT=outputs/results
MODEL=pretrained/formation_diffusion_cpu
mkdir -p "$OUT"

# World / PAC (issue 2)
$BIN/lerobot-formation-bench --controllers pac --scenes random:1000 --out $OUT/pac1000 --no-progress | tee $OUT/pac1000.log
$PY benchmarks/bench_env_step.py | tee $OUT/bench_env_step.log
$PY benchmarks/bench_follower_floor.py | tee $OUT/bench_follower_floor.log

# Dataset (issue 3)
$BIN/lerobot-formation-generate --episodes 1878 --obstacle-encoding grid+list --root data/formation_pac_list \
  --repo-id local/formation_pac_list --overwrite --no-progress | tee $OUT/generate.log
$PY benchmarks/bench_dataset.py | tee $OUT/bench_dataset.log

# Training (issue 4): about 80 min on 2 cores with fast reads (40,000 steps at ~8.7 steps/s)
START=$(date +%H:%M:%S)
$BIN/lerobot-train --config_path=configs/formation_diffusion_cpu.json --dataset.root=data/formation_pac_list \
  --output_dir=outputs/train_cpu 2>&1 | tee $OUT/train.log
$PY scripts/checkpoint_curve.py outputs/train_cpu --dataset.root data/formation_pac_list --start "$START" \
  --out $OUT/checkpoint_curve.json | tee $OUT/checkpoint_curve.log
$PY scripts/export_pretrained.py outputs/train_cpu/checkpoints/last/pretrained_model $MODEL \
  --dataset.root data/formation_pac_list --card $MODEL/README.md
$PY benchmarks/bench_train_throughput.py --dataset.root data/formation_pac_list --batch-size 256 --steps 20 \
  --num-workers 1 --fast-reads | tee $OUT/bench_train_throughput.log

# The paper's experiments (issue 5)
$BIN/lerobot-formation-bench --controllers pac,mppi,diffusion,diffusion-adaptive --policy.path $MODEL \
  --scenes dataset:100 --unseen random:100 --out $OUT/bench --no-progress | tee $OUT/bench.log
for k in 2 5 10 25 100; do
  $BIN/lerobot-formation-bench --controllers diffusion --policy.path $MODEL --scenes dataset:100 \
    --num-inference-steps $k --out $OUT/ddim_$k --no-figures --no-progress | tee $OUT/ddim_$k.log
done
$PY benchmarks/mppi_sweep.py --scenes 40 --confirm 100 --out $OUT/mppi_sweep.json | tee $OUT/mppi_sweep.log
$PY benchmarks/bench_eval_speed.py --policy.path $MODEL --episodes 100 --stock 100:sync --threads 1 \
  --out $OUT/eval_unseen | tee $OUT/bench_eval_speed.log
$PY benchmarks/bench_eval_speed.py --policy.path $MODEL --scenes dataset:100 --stock 100:sync --threads 1 \
  --out $OUT/eval_dataset | tee $OUT/eval_dataset.log
$PY benchmarks/bench_replan_latency.py --policy.path $MODEL --threads 1 | tee $OUT/bench_replan_latency.log
