#!/usr/bin/env bash
# The GPU check of real camera data (benchmarks/relabel.md, "Real camera data"): on a machine with torch and a GPU
# but no package index, with the wheels of ../shared/device/wheels.sh in .whl/. Writes an SO-101-shaped recording
# (two 640×480 AV1 cameras, LeRobot's writer), trains a supervised IDM at the default working resolution with
# --policy.device=cuda, scores it on held-out episodes and relabels with the IDM on the GPU, against a plain
# one-thread PyAV decode of the same videos. Logs go to $OUT (default outputs/device-check).
#   bash benchmarks/measure/device_check.sh [frames] [steps]     (DEVICE=cpu HELD=1 for a dry run on a CPU machine)
set -euo pipefail
FRAMES=${1:-2000}
STEPS=${2:-1000}
DEVICE=${DEVICE:-cuda}
HELD=${HELD:-4}
OUT=${OUT:-outputs/device-check}
WORK=${WORK:-/tmp/device-check}
mkdir -p "$OUT" "$WORK"
if ! python3 -c "import lerobot" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site PATH=/tmp/site/bin:$PATH
fi
export HF_LEROBOT_HOME=$WORK/home LEROBOT_IUPE_CACHE=$WORK/frame-cache
(nvidia-smi -L || true) | tee "$OUT/device.txt"
python3 - "$WORK" "$FRAMES" "$HELD" <<'PY' 2>&1 | tail -3 | tee "$OUT/write.txt"
import sys, time
from lerobot_iupe.data.arm_recording import write_arm_recording
work, frames, held = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
start = time.perf_counter()
write_arm_recording(f"{work}/arm", frames // 250, 250, repo_id="local/arm")
write_arm_recording(f"{work}/held", held, 250, seed=1_000_000, repo_id="local/held")
print(f"wrote {frames} + {held * 250} frames in {time.perf_counter() - start:.0f} s")
PY
timed() { python3 - "$@" <<'PY'
import resource, subprocess, sys, time
start = time.perf_counter()
code = subprocess.run(sys.argv[1:]).returncode
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2
print(f"[{sys.argv[1].rsplit('/', 1)[-1]}: exit {code}, {time.perf_counter() - start:.1f} s, peak RSS {peak:.2f} GB]")
sys.exit(code)
PY
}
timed "$(command -v lerobot-train)" --policy.type=iupe --policy.supervised=true --dataset.repo_id=local/arm \
  --dataset.root="$WORK/arm" --dataset.video_backend=pyav --output_dir="$WORK/idm" --steps="$STEPS" \
  --save_freq="$STEPS" --log_freq=100 --policy.device="$DEVICE" --wandb.enable=false \
  --policy.joint_state_columns=[] 2>&1 \
  | grep -E "step:|exit|caching|Error|error" | tail -8 | tee "$OUT/train.txt"
CKPT=$WORK/idm/checkpoints/last/pretrained_model
timed "$(command -v lerobot-iupe-relabel)" --policy.path="$CKPT" --policy.device="$DEVICE" --dataset.repo_id=local/held \
  --dataset.root="$WORK/held" --dataset.video_backend=pyav --dry_run=true 2>&1 | grep -v "frame/s]" | tee "$OUT/held_out.txt"
timed "$(command -v lerobot-iupe-relabel)" --policy.path="$CKPT" --policy.device="$DEVICE" --dataset.repo_id=local/arm \
  --dataset.root="$WORK/arm" --dataset.video_backend=pyav --dry_run=true 2>&1 | grep -v "frame/s]" | tee "$OUT/relabel.txt"
python3 benchmarks/measure/cameras.py --decode "$WORK/arm" --backend pyav | tee "$OUT/decode.txt"
