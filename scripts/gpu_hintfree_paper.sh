#!/usr/bin/env bash
# The paper-size hint-free student in one sitting on one GPU machine (docs/log.md, "The
# paper-size hint-free student on a GPU"): data, training throughput, training, and its level rows.
#
#   scripts/gpu_hintfree_paper.sh OUT_DIR [BUDGET_S]
#
# 1. the privileged expert's data under randomized level5 conditions, nearest+velocity (the same
#    1,200 episodes, seed 0, as the CPU hint-free student's), simulated by nproc-1 worker processes;
# 2. training throughput of configs/formation_diffusion_hintfree_paper.json (U-Net [256, 512, 1024],
#    T_p 64, batch 256) with benchmarks/bench_train_throughput.py;
# 3. lerobot-train on that config for as many steps as the measured rate fits into the time left
#    (the cosine schedule spans them; a checkpoint at half way);
# 4. lerobot-formation-bench, standard sampling, on the first SCENES evaluation scenes of each level,
#    the levels side by side, the network on DEVICE.
#
# Writes OUT_DIR/{gen,throughput,train,bench}.log, OUT_DIR/summary.json and OUT_DIR/results.tar.gz
# (each level's results.json). Every phase has a time limit inside BUDGET_S (default 540 s), so the
# run ends in time with whatever it finished. Environment: EPISODES (1200), SCENES (100), LEVELS
# ("level0 ... level5"), DEVICE (cuda), WORKERS (nproc - 1), EVAL_RESERVE_S (150), PYTHON (python: the
# interpreter that has torch and this project's packages), EXTRA (more --key=value flags for the
# throughput run and lerobot-train, e.g. a smaller network for a dry run). It first checks, within
# 90 s, that the packages import and the device exists, and stops there if not.
set -uo pipefail
cd "$(dirname "$0")/.."
case "${1:-}" in
  -h|--help)
    echo "usage: scripts/gpu_hintfree_paper.sh OUT_DIR [BUDGET_S]"
    echo
    # the comment at the top of this file, up to the first line of code
    awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' scripts/gpu_hintfree_paper.sh
    exit 0
    ;;
  -*) echo "usage: scripts/gpu_hintfree_paper.sh OUT_DIR [BUDGET_S] (--help: what it does)" >&2; exit 2 ;;
esac
OUT=${1:?usage: scripts/gpu_hintfree_paper.sh OUT_DIR [BUDGET_S]}
BUDGET=${2:-540}
T0=$(date +%s)
EPISODES=${EPISODES:-1200}
SCENES=${SCENES:-100}
LEVELS=${LEVELS:-"level0 level1 level2 level3 level4 level5"}
DEVICE=${DEVICE:-cuda}
WORKERS=${WORKERS:-$(($(nproc) - 1))}
EVAL_RESERVE_S=${EVAL_RESERVE_S:-150}
EXTRA=${EXTRA:-}
PYTHON=${PYTHON:-python}
CONFIG=configs/formation_diffusion_hintfree_paper.json
DATA=data/formation_priv_velocity_gpu
RUN=outputs/hintfree_paper
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONUNBUFFERED=1
mkdir -p "$OUT"
left() { echo $((BUDGET - ($(date +%s) - T0))); }
say() { echo "[gpu_hintfree_paper +$(($(date +%s) - T0)) s] $*"; }

say "device $DEVICE, $(nproc) CPUs, $WORKERS simulation workers, budget $BUDGET s"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader

# 0. the packages and the device, before anything long
if ! timeout 90 "$PYTHON" - "$DEVICE" <<'EOF'
import sys
import torch, lerobot, diffusers, gymnasium, datasets  # noqa: E401,F401
import lerobot_formation.plugin  # noqa: F401
from lerobot_formation.bench.cli import check_device
check_device(sys.argv[1])
print(f"torch {torch.__version__}, device {sys.argv[1]} ok", flush=True)
EOF
then
    say "the import and device check failed or took over 90 s: stopping"
    exit 1
fi

# 1. data (the generator refuses to overwrite what it did not write; a leftover of this script is its own)
say "data: $EPISODES episodes"
timeout $(($(left) - EVAL_RESERVE_S - 120)) "$PYTHON" -m datasets_scripts.generate_pac_dataset \
    --episodes "$EPISODES" --root "$DATA" --repo-id local/formation_priv_velocity_gpu \
    --obstacle-encoding nearest+velocity --scene-preset paper,wide,mixed-hard,structures \
    --expert privileged --conditions-randomize level5 --seed 0 --workers "$WORKERS" --batch-size 16 \
    --threads 1 --no-progress --overwrite >"$OUT/gen.log" 2>&1
say "data: rc $? $(tail -n 1 "$OUT/gen.log")"

# 2. throughput: lerobot-train's objects, pure compute and with the loader (fast reads)
say "throughput"
timeout 120 "$PYTHON" benchmarks/bench_train_throughput.py --dataset.root "$DATA" \
    --dataset.repo_id local/formation_priv_velocity_gpu --config "$CONFIG" --batch-size 256 \
    --steps 10 --warmup 3 --num-workers 8 "--policy.device=$DEVICE" $EXTRA >"$OUT/throughput.log" 2>&1
say "throughput: rc $? $(grep -E '^pure compute' "$OUT/throughput.log")"
RATE=$("$PYTHON" - "$OUT/throughput.log" <<'EOF'
import re, sys
text = open(sys.argv[1]).read()
m = re.search(r"^pure compute \(same batches, in memory\): ([0-9.]+) samples/s", text, re.M)
b = re.search(r"batch (\d+);", text)
print(f"{float(m.group(1)) / int(b.group(1)):.3f}" if m and b else "0")
EOF
)

[ "$RATE" = "0" ] && RATE=10  # no measurement: a guess; the time limit below still holds

# 3. training: the steps the rate fits into the time left (80 % of it: start-up, saving, the loader)
TRAIN_S=$(($(left) - EVAL_RESERVE_S - 60))
STEPS=$("$PYTHON" -c "print(max(20, int(0.8 * $RATE * $TRAIN_S) // 20 * 20))")
say "train: $STEPS steps at ~$RATE steps/s measured, $TRAIN_S s left for it"
rm -rf "$RUN"  # this script's own output folder (outputs/ is ignored)
timeout $(($(left) - EVAL_RESERVE_S + 30)) "$PYTHON" -m lerobot_formation.with_plugin lerobot-train \
    --config_path="$CONFIG" --dataset.root="$DATA" --dataset.repo_id=local/formation_priv_velocity_gpu \
    "--policy.device=$DEVICE" --steps="$STEPS" --save_freq=$((STEPS / 2)) --log_freq=50 \
    --wandb.enable=false --output_dir="$RUN" $EXTRA >"$OUT/train.log" 2>&1
say "train: rc $? $(grep -E 'step:' "$OUT/train.log" | tail -n 1)"
MODEL=$RUN/checkpoints/last/pretrained_model

# 4. the level rows, side by side
say "bench: $LEVELS, $SCENES scenes each"
pids=()
for level in $LEVELS; do
    timeout $(($(left) - 10)) "$PYTHON" -m lerobot_formation.bench.cli --overwrite --controllers diffusion \
        --policy.path "$MODEL" --scenes "$level:$SCENES" --device "$DEVICE" --threads 1 --no-figures \
        --no-progress --out "outputs/hintfree_paper_bench/$level" >"outputs/bench_$level.log" 2>&1 &
    pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
for level in $LEVELS; do cat "outputs/bench_$level.log"; done >"$OUT/bench.log" 2>&1
"$PYTHON" - "$OUT" "$RATE" "$STEPS" $LEVELS <<'EOF'
import json, sys
from pathlib import Path
out, rate, steps, levels = Path(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), sys.argv[4:]
summary = {"measured_pure_compute_steps_per_s": rate, "train_steps": steps, "levels": {}}
for level in levels:
    f = Path("outputs/hintfree_paper_bench") / level / "results.json"
    if f.is_file():
        r = json.loads(f.read_text())["diffusion"]
        summary["levels"][level] = {k: v for k, v in r.items() if k != "episodes"}
(out / "summary.json").write_text(json.dumps(summary, indent=1))
print(json.dumps(summary, indent=1))
EOF
tar czf "$OUT/results.tar.gz" -C outputs hintfree_paper_bench
say "done"
