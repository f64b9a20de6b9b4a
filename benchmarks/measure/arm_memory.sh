#!/usr/bin/env bash
# One run, same machine: relabel (dry run) and train, the paper's IDM vs the arm IDM, at 3,000 and 30,000 frames.
set -u
cd "$(git rev-parse --show-toplevel)"
# Needs outputs/measure-arm-idm (python benchmarks/measure/arm_idm.py, and --delays 4 --labelled 10 --variant plain) and
# outputs/arm-mem/j3k, j30k (make_arm_recording.py --no_cameras --delay 4 --seed 500, 10 and 100 episodes of 300).
B=.venv/bin
OUT=${OUT:-outputs/arm-mem}
for size in 3k 30k; do
  root=outputs/arm-mem/j$size
  for variant in plain joint; do
    ckpt=outputs/measure-arm-idm/run-d4-n10-$variant/checkpoints/last/pretrained_model
    /usr/bin/time -v $B/lerobot-iupe-relabel --policy.path=$ckpt --dataset.repo_id=local/x --dataset.root=$root \
      --dry_run=true > $OUT/mem-relabel-$size-$variant.out 2> $OUT/mem-relabel-$size-$variant.err
    fps=$(grep -o "([0-9]* frames/s)" $OUT/mem-relabel-$size-$variant.out)
    rss=$(grep "Maximum resident" $OUT/mem-relabel-$size-$variant.err | awk '{print $NF}')
    echo "relabel $size $variant $fps peak_rss_kB=$rss"
    extra=""; [ $variant = plain ] && extra="--policy.joint_state_columns=[]"
    out=outputs/arm-mem/train-$size-$variant; rm -rf $out
    /usr/bin/time -v $B/lerobot-train --policy.type=iupe --policy.supervised=true --dataset.repo_id=local/x \
      --dataset.root=$root --steps=300 --batch_size=64 --save_freq=300 --num_workers=0 --policy.device=cpu \
      --policy.push_to_hub=false --wandb.enable=false --output_dir=$out --log_freq=100 $extra \
      > $OUT/mem-train-$size-$variant.out 2> $OUT/mem-train-$size-$variant.err
    updt=$(grep -o "updt_s:[0-9.]*" $OUT/mem-train-$size-$variant.err | tail -1)
    data=$(grep -o "data_s:[0-9.]*" $OUT/mem-train-$size-$variant.err | tail -1)
    rss=$(grep "Maximum resident" $OUT/mem-train-$size-$variant.err | awk '{print $NF}')
    echo "train $size $variant $updt $data peak_rss_kB=$rss"
  done
done
