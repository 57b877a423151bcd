#!/usr/bin/env bash
# Scores checkpoints on fresh test loops of the synthetic campus for several visit seeds (the demo's
# kind of data: 2 loops of 175 frames per seed; seed 0 trains and seed 11 validates the shipped
# model, so neither may be listed) and prints one markdown table: each seed's metrics and their mean.
# The retrieval baseline (pose of the nearest training image, REFERENCE: the descriptors of the training images)
# is scored on the same frames and printed as the last rows.
# Usage: bash scripts/ablation.sh [LABEL=]CHECKPOINT...
#   env SEEDS (default "101 7 23 42"), LOOPS_DIR (default runs/test-loops), OUT (default runs/ablation),
#   REFERENCE (default models/vlocnetpp_lite.reference.npz), LANE_OFFSET (metres right of the centreline: every
#   test loop drives there instead of a lane; training drives the lanes at +-1.5 m and the sidewalks at +-4.25 m)
# Re-runs reuse the rendered loops and the scores already written (delete OUT to score again).
set -euo pipefail
cd "$(dirname "$0")/.."
V=.venv/bin/vlocnetpp
SEEDS=${SEEDS:-101 7 23 42}
LOOPS_DIR=${LOOPS_DIR:-runs/test-loops}
OUT=${OUT:-runs/ablation}
REFERENCE=${REFERENCE:-models/vlocnetpp_lite.reference.npz}
LANE=${LANE_OFFSET:+-lane$LANE_OFFSET}
[ $# -gt 0 ] || { echo "usage: bash scripts/ablation.sh [LABEL=]CHECKPOINT..." >&2; exit 2; }
mkdir -p "$LOOPS_DIR" "$OUT"
for seed in $SEEDS; do
  case $seed in 0|11) echo "seed $seed trained or validated the shipped model: pick another" >&2; exit 2;; esac
  [ -d "$LOOPS_DIR/seed$seed$LANE" ] || { echo "rendering the test loops of visit seed $seed$LANE" >&2
    $V synth "$LOOPS_DIR/seed$seed$LANE" --scene campus --seed "$seed" --loops 0 --test-loops 2 --frames-per-loop 175 --no-progress \
      ${LANE_OFFSET:+--test-lane-offset "$LANE_OFFSET"}; }
done
rows=()
for arg in "$@"; do
  label=${arg%%=*}; ckpt=${arg#*=}
  [ "$label" != "$arg" ] || label=$ckpt
  [ -f "$ckpt" ] || { echo "no checkpoint $ckpt" >&2; exit 2; }
  # scores are kept per checkpoint file (path, size and time), so a retrained checkpoint is scored again
  slug=$(printf '%s' "$ckpt-$(stat -c %s-%Y "$ckpt")-$(stat -c %s-%Y "$REFERENCE")" | tr -c 'A-Za-z0-9._-' '_')
  for seed in $SEEDS; do
    json="$OUT/$slug.seed$seed$LANE.json"
    if [ ! -f "$json" ]; then
      echo "scoring $label on seed $seed" >&2
      $V evaluate --checkpoint "$ckpt" --data "$LOOPS_DIR/seed$seed$LANE" --reference "$REFERENCE" --json "$json.tmp" --no-progress > /dev/null && mv "$json.tmp" "$json"
    fi
  done
  rows+=("$label" "$OUT/$slug")
done
.venv/bin/python - "$SEEDS" "$LANE" "${rows[@]}" <<'PY'
import json, sys
import numpy as np

seeds, lane, args = sys.argv[1].split(), sys.argv[2], sys.argv[3:]
cols = [("median t [m]", "pose", "median_translation_m", 1, "{:.1f}"), ("median R [deg]", "pose", "median_rotation_deg", 1, "{:.1f}"),
        ("< 0.5 m, 5 deg [%]", "pose", "accuracy_0.5m_5deg", 100, "{:.1f}"),
        ("VO t [%]", "odometry", "translation_error_percent", 1, "{:.1f}"), ("VO R [deg/m]", "odometry", "rotation_error_deg_per_m", 1, "{:.2f}"),
        ("VO scale", "odometry", "step_scale", 1, "{:.2f}"),
        ("mIoU [%]", "segmentation", "miou", 100, "{:.1f}")]
print("| model | seed | " + " | ".join(c[0] for c in cols) + " |")
print("|---|---|" + "---|" * len(cols))
runs = [(label, [json.load(open(f"{prefix}.seed{s}{lane}.json")) for s in seeds]) for label, prefix in zip(args[::2], args[1::2])]
runs.append(("retrieval (nearest training image)", [r["baseline"] for r in runs[0][1]]))
for label, reports in runs:
    per_seed = [r["overall"] for r in reports]
    # nan where a report lacks the number (no such stream; step_scale in a report written before it existed)
    values = [[(m.get(group) or {}).get(key) for _, group, key, _, _ in cols] for m in per_seed]
    values = [[float("nan") if x is None else x * c[3] for c, x in zip(cols, v)] for v in values]
    for seed, v in zip(seeds, values):
        print(f"| {label} | {seed}{lane} | " + " | ".join(c[4].format(x) for c, x in zip(cols, v)) + " |")
    mean = np.mean(values, axis=0)
    print(f"| **{label}** | **mean** | " + " | ".join("**" + c[4].format(x) + "**" for c, x in zip(cols, mean)) + " |")
PY
