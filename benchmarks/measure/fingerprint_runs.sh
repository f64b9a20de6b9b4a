#!/usr/bin/env bash
# Fingerprints of short seeded runs, to prove a refactor changes no behaviour: run it before and after, compare.
#   benchmarks/measure/fingerprint_runs.sh before   # ... change the code ...   benchmarks/measure/fingerprint_runs.sh after
# Prints, per run, the SHA-256 prefix of model.safetensors; cycle records (timings aside) are compared by diffing
# outputs/fingerprints/<tag>/<run>/checkpoints/last/pretrained_model/iupe_cycles.jsonl without the *_s fields.
# Runs: CartPole IUPE, BCO(α), BC (200 steps), Maze 3×3 IUPE (60 steps) and continuous LunarLander IUPE (100 steps),
# one CPU thread, --seed=3.
set -euo pipefail
cd "$(dirname "$0")/../.."
tag=${1:?usage: benchmarks/measure/fingerprint_runs.sh TAG}
bin=.venv/bin
data=outputs/fingerprints/data
out=outputs/fingerprints/$tag
rm -rf "$out"
mkdir -p "$out" "$data"
collect() {
  [ -d "$data/$1" ] || "$bin/lerobot-iupe-collect" --dataset.repo_id="local/$1" --dataset.root="$data/$1" "${@:2}" \
    > "$out/collect-$1.log" 2>&1
}
collect cp-expert --env.type=cartpole --agent=expert --episodes=10
collect cp-expert-a --env.type=cartpole --agent=expert --episodes=10 --keep_actions=true
collect cp-random --env.type=cartpole --agent=random --episodes=200 --seed=1000
collect mz-expert --env.type=maze --env.size=3 --env.image_size=21 --agent=expert --episodes=10 --video=false
collect mz-random --env.type=maze --env.size=3 --env.image_size=21 --agent=random --random_start=true --episodes=40 \
  --seed=1000 --video=false --env.max_steps=15
collect ll-expert --env.type=lunarlander --agent=expert --episodes=5
collect ll-random --env.type=lunarlander --agent=random --episodes=20 --seed=1000
train() {
  local name=$1 expert=$2 pre=$3
  shift 3
  OMP_NUM_THREADS=1 "$bin/lerobot-train" --policy.type=iupe --dataset.repo_id="local/$expert" \
    --dataset.root="$data/$expert" --dataset.video_backend=pyav --policy.pre_demos_repo_id="local/$pre" \
    --policy.pre_demos_root="$data/$pre" --output_dir="$out/$name" --policy.device=cpu --num_workers=0 \
    --wandb.enable=false --save_freq=1000000 --seed=3 "$@" > "$out/$name.log" 2>&1
  echo "$name $(sha256sum "$out/$name/checkpoints/last/pretrained_model/model.safetensors" | cut -c1-16)"
}
short=(--steps=200 --batch_size=64 --policy.cycle_steps=50)
train cp-iupe cp-expert cp-random "${short[@]}"
train cp-bco cp-expert cp-random "${short[@]}" --policy.sampling=false --policy.exploration=false \
  --policy.attention=false
train cp-bc cp-expert-a cp-random "${short[@]}" --policy.supervised=true
train mz-iupe mz-expert mz-random --steps=60 --batch_size=32 --policy.cycle_steps=20 --policy.rollout_episodes=6
train ll-iupe ll-expert ll-random --steps=100 --batch_size=64 --policy.cycle_steps=50 --policy.rollout_episodes=2
