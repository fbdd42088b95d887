#!/usr/bin/env bash
# Train the matcher within a fixed wall-clock budget on a lent GPU machine (issue 17's matcher_v3).
#
#   BUDGET_S=540 OUT=out/gpu scripts/train_on_gpu.sh config/train_real.yaml
#
# 1. A 200-step probe run builds both training stores (all cores) and measures steps per second.
# 2. The real run trains from the config with --steps fitted to what is left of the budget.
# The `liver-p2p train ... --steps N` line it prints (and the model card) reproduces the run on
# any device, the CPU included (same config, same data stream; only float rounding differs).
# Real livers: $LIVER_P2P_REAL_LIVERS (default ../shared/data/livers). PYTHON: the interpreter.
set -euo pipefail
CONFIG=${1:-config/train_real.yaml}
BUDGET_S=${BUDGET_S:-540}
OUT=${OUT:-out/gpu}
PYTHON=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda}
export PYTHONUNBUFFERED=1
start=$(date +%s)
mkdir -p "$OUT"
"$PYTHON" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')"
nproc
probe=$(mktemp -d)
"$PYTHON" -m liver_p2p_reg train --config "$CONFIG" --device "$DEVICE" --out "$probe" --steps 200 --no-progress
cp "$probe/log.csv" "$OUT/probe_log.csv"
now=$(date +%s)
steps=$("$PYTHON" - "$probe/log.csv" "$BUDGET_S" "$((now - start))" <<'PY'
import csv, sys
rows = [r for r in csv.DictReader(open(sys.argv[1])) if r["step"]]
a = next(r for r in rows if int(r["step"]) >= 60)
b = [r for r in rows if not r["val_score_mm"]][-1]  # last training row before the final validation
rate = (int(b["step"]) - int(a["step"])) / max(1e-6, float(b["elapsed_s"]) - float(a["elapsed_s"]))
left = float(sys.argv[2]) - float(sys.argv[3]) - 75.0  # start-up, validations, export
print(max(200, int(rate * left)), file=sys.stdout)
print(f"probe: {rate:.1f} steps/s; {left:.0f} s left for training", file=sys.stderr)
PY
)
now=$(date +%s)
max_min=$(awk -v b="$BUDGET_S" -v e="$((now - start))" 'BEGIN { printf "%.2f", (b - e - 30) / 60 }')
echo "reproduce: liver-p2p train --config $CONFIG --steps $steps --device $DEVICE --out RUN"
"$PYTHON" -m liver_p2p_reg train --config "$CONFIG" --device "$DEVICE" --out "$OUT/run" --steps "$steps" \
  --max-minutes "$max_min" --no-progress
echo "done in $(( $(date +%s) - start )) s"
