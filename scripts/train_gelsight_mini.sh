#!/usr/bin/env bash
# Reproduce the shipped GelSight Mini calibration files from the shared ball presses:
#   models/gelsight_mini.pt         gradient MLP (5-32-32-32-2), with metadata
#   models/gelsight_mini_colour.pt  the simulator's forward colour model
# Labels, overlays, the training curve and the held-out comparison with the SDK's
# reference model land in $OUT (default build/gelsight_mini_calibration).
# Usage: scripts/train_gelsight_mini.sh [CALIB_ROOT]   (default ../shared/data/gelsight_mini)
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-../shared/data/gelsight_mini}
OUT=${OUT:-build/gelsight_mini_calibration}
PY=${PY:-.venv/bin/tactile-slam}
"$PY" calibrate train "$DATA/calibration" --out "$OUT" --seed 0 --restarts 4 \
    --reference "$DATA/reference_model/nnmodel.pth" --colour-model --json "$OUT/summary.json"
mkdir -p models
cp "$OUT/model.pt" models/gelsight_mini.pt
cp "$OUT/colour_model.pt" models/gelsight_mini_colour.pt
echo "wrote models/gelsight_mini.pt and models/gelsight_mini_colour.pt (report: $OUT)"
