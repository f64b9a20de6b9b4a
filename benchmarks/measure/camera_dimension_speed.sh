#!/bin/bash
# Seconds per training step of a camera dimension (the default IDM on the velocity arm) and of the IDM of cameras and
# state (--policy.joint_state_columns=[]), this tree against a baseline revision, on the same machine in one run; and
# the default trained alone (--policy.idm_only=true: no policy model, what a relabelling run needs).
#     bash benchmarks/measure/camera_dimension_speed.sh [BASELINE=5a43bd2] [WORK=outputs/camera-dimension-speed]
# Writes the velocity arm at 480x640 (two AV1 cameras, 5 episodes of 150 frames) once; prints one line per run:
# seconds per step at steps 40 and 60 (batch 64), wall time with the fits, peak RSS (KB).
set -euo pipefail
REPO=$(cd "$(dirname "$0")/../.." && pwd)
BASELINE=${1:-5a43bd2}
WORK=$(realpath -m "${2:-outputs/camera-dimension-speed}")
B=$REPO/.venv/bin
mkdir -p "$WORK"
export LEROBOT_IUPE_CACHE=$WORK/frame-cache
[ -d "$WORK/code-$BASELINE" ] || git -C "$REPO" worktree add --detach "$WORK/code-$BASELINE" "$BASELINE"
[ -f "$WORK/arm/meta/info.json" ] || "$B/python" -c "
from lerobot_iupe.data.arm_writer import write_arm_recording
from lerobot_iupe.data.hand_guided_arm import VELOCITY_ARM
write_arm_recording('$WORK/arm', 5, 150, 480, 640, fps=10, seed=0, repo_id='local/arm', body=VELOCITY_ARM)"
train() { # output code extra...
  local out=$1 code=$2; shift 2
  rm -rf "$out"
  PYTHONPATH=$code /usr/bin/time -v "$B/lerobot-train" --policy.type=iupe --policy.supervised=true "$@" \
    --num_workers=0 --policy.device=cpu --dataset.repo_id=local/arm --dataset.root="$WORK/arm" \
    --output_dir="$out" --wandb.enable=false > "$out.log" 2>&1
}
train "$WORK/warm" "$REPO" --batch_size=8 --steps=1  # builds the frame cache outside the timed runs
for run in "now default $REPO" "now alone $REPO --policy.idm_only=true" "before default $WORK/code-$BASELINE" \
           "now fused $REPO --policy.joint_state_columns=[]" "before fused $WORK/code-$BASELINE --policy.joint_state_columns=[]"; do
  set -- $run
  name=$1-$2 code=$3; shift 3
  train "$WORK/$name" "$code" --batch_size=64 --steps=60 --log_freq=20 "$@"
  echo "$name $(grep -o 'updt_s:[0-9.]*' "$WORK/$name.log" | tail -2 | tr '\n' ' ')" \
       "wall $(grep Elapsed "$WORK/$name.log" | awk '{print $NF}')" \
       "peak_kb $(grep 'Maximum resident' "$WORK/$name.log" | awk '{print $NF}')"
done
