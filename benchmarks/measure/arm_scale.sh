#!/usr/bin/env bash
# The linear-first IDM on SIZE frames (100k by default, 10k for a tenth) of a 26-joint humanoid (two arms, two
# hands), beside the code of another checkout (OLD=path: its sources shadow this one's through PYTHONPATH, same venv):
# fit and training step (lerobot-train on all the labelled frames, 300 steps), and relabelling a state-only copy in
# place, each with its peak RSS. One run, same machine. Data (python - <<<… or the generator):
#   write_arm_recording(<root>, 200, 500, seed=7000, cameras=False, body=HUMANOID, with_actions=…)
# into outputs/arm-scale/h100k-labelled and outputs/arm-scale/h100k-state-only (h10k-…: 20 episodes).
#   OLD=/tmp/old-src bash benchmarks/measure/arm_scale.sh
#   SIZE=10k VARIANTS=new bash benchmarks/measure/arm_scale.sh
set -u
cd "$(git rev-parse --show-toplevel)"
B=$PWD/.venv/bin
OUT=${OUT:-outputs/arm-scale}
SIZE=${SIZE:-100k}
for variant in ${VARIANTS:-old new}; do
  path=""; [ "$variant" = old ] && path=${OLD:?set OLD to the other checkout}
  run=$OUT/train-$SIZE-$variant; rm -rf "$run"
  PYTHONPATH=$path /usr/bin/time -v $B/lerobot-train --policy.type=iupe --policy.supervised=true \
    --dataset.repo_id=local/h$SIZE --dataset.root=$OUT/h$SIZE-labelled --steps=300 --batch_size=64 --save_freq=300 \
    --num_workers=0 --policy.device=cpu --policy.push_to_hub=false --wandb.enable=false --output_dir=$run \
    --log_freq=100 > $OUT/train-$SIZE-$variant.out 2> $OUT/train-$SIZE-$variant.err
  updt=$(grep -o "updt_s:[0-9.]*" $OUT/train-$SIZE-$variant.err | tail -1)
  wall=$(grep "Elapsed (wall" $OUT/train-$SIZE-$variant.err | awk '{print $NF}')
  rss=$(grep "Maximum resident" $OUT/train-$SIZE-$variant.err | awk '{print $NF}')
  echo "train $SIZE $variant $updt wall=$wall peak_rss_kB=$rss"
  root=$OUT/relabel-$SIZE-$variant; rm -rf "$root"; cp -r $OUT/h$SIZE-state-only "$root"
  PYTHONPATH=$path /usr/bin/time -v $B/lerobot-iupe-relabel --policy.path=$run/checkpoints/last/pretrained_model \
    --dataset.repo_id=local/h$SIZE --dataset.root=$root > $OUT/relabel-$SIZE-$variant.out 2> $OUT/relabel-$SIZE-$variant.err
  line=$(grep -o "wrote .* frames/s)" $OUT/relabel-$SIZE-$variant.out)
  wall=$(grep "Elapsed (wall" $OUT/relabel-$SIZE-$variant.err | awk '{print $NF}')
  rss=$(grep "Maximum resident" $OUT/relabel-$SIZE-$variant.err | awk '{print $NF}')
  echo "relabel $SIZE $variant: $line; wall=$wall peak_rss_kB=$rss"
done
