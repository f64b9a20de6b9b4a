#!/bin/bash
# Peak resident memory of a camera-IDM training (30 steps, default flags, --policy.joint_state_columns=[]) and of a
# dry-run relabel, on recordings of two 640x480 AV1 cameras of 500 and 5,000 frames (10x), written by LeRobot's
# writer through scripts/make_arm_recording.py.
#     bash benchmarks/measure/camera_memory.sh [WORK=outputs/speed]
set -euo pipefail
REPO=$(cd "$(dirname "$0")/../.." && pwd)
WORK=$(realpath -m "${1:-outputs/speed}")
B=$REPO/.venv/bin
export LEROBOT_IUPE_CACHE=$WORK/frame-cache
for n in 500 5000; do
  root=$WORK/arm-$n out=$WORK/memory-$n
  [ -f "$root/meta/info.json" ] || "$B/python" "$REPO/scripts/make_arm_recording.py" --root "$root" \
    --repo_id "local/arm-$n" --episodes $((n / 250)) > "$WORK/make-$n.log" 2>&1
  rm -rf "$out"
  /usr/bin/time -v "$B/lerobot-train" --policy.type=iupe --policy.supervised=true --dataset.repo_id="local/arm-$n" \
    --dataset.root="$root" --output_dir="$out" --steps=30 --save_freq=30 --log_freq=10 --policy.device=cpu \
    --wandb.enable=false --policy.joint_state_columns=[] > "$out.train.log" 2>&1
  /usr/bin/time -v "$B/lerobot-iupe-relabel" --policy.path="$out/checkpoints/last/pretrained_model" \
    --dataset.repo_id="local/arm-$n" --dataset.root="$root" --dry_run=true > "$out.relabel.log" 2>&1
  echo "$n frames: training peak $(grep 'Maximum resident' "$out.train.log" | awk '{print $NF}') KB," \
       "relabel peak $(grep 'Maximum resident' "$out.relabel.log" | awk '{print $NF}') KB"
done
