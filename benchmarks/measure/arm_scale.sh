#!/usr/bin/env bash
# The linear-first IDM at 100,000 frames of a 26-joint humanoid (two arms, two hands), beside the code of another
# checkout (OLD=path: its sources shadow this one's through PYTHONPATH, same venv): fit and training step
# (lerobot-train on the 100,000 labelled frames, 300 steps), and relabelling a state-only copy in place, each with its
# peak RSS. One run, same machine. Data (python - <<<… or the generator):
#   write_arm_recording(<root>, 200, 500, seed=7000, cameras=False, body=HUMANOID, with_actions=…)
# into outputs/arm-scale/h100k-labelled and outputs/arm-scale/h100k-state-only.
#   OLD=/tmp/old-src bash benchmarks/measure/arm_scale.sh
set -u
cd "$(git rev-parse --show-toplevel)"
B=$PWD/.venv/bin
OUT=${OUT:-outputs/arm-scale}
for variant in ${VARIANTS:-old new}; do
  path=""; [ "$variant" = old ] && path=${OLD:?set OLD to the other checkout}
  run=$OUT/train-$variant; rm -rf "$run"
  PYTHONPATH=$path /usr/bin/time -v $B/lerobot-train --policy.type=iupe --policy.supervised=true \
    --dataset.repo_id=local/h100k --dataset.root=$OUT/h100k-labelled --steps=300 --batch_size=64 --save_freq=300 \
    --num_workers=0 --policy.device=cpu --policy.push_to_hub=false --wandb.enable=false --output_dir=$run \
    --log_freq=100 > $OUT/train-$variant.out 2> $OUT/train-$variant.err
  updt=$(grep -o "updt_s:[0-9.]*" $OUT/train-$variant.err | tail -1)
  wall=$(grep "Elapsed (wall" $OUT/train-$variant.err | awk '{print $NF}')
  rss=$(grep "Maximum resident" $OUT/train-$variant.err | awk '{print $NF}')
  echo "train 100k $variant $updt wall=$wall peak_rss_kB=$rss"
  root=$OUT/relabel-$variant; rm -rf "$root"; cp -r $OUT/h100k-state-only "$root"
  PYTHONPATH=$path /usr/bin/time -v $B/lerobot-iupe-relabel --policy.path=$run/checkpoints/last/pretrained_model \
    --dataset.repo_id=local/h100k --dataset.root=$root > $OUT/relabel-$variant.out 2> $OUT/relabel-$variant.err
  line=$(grep -o "wrote .* frames/s)" $OUT/relabel-$variant.out)
  wall=$(grep "Elapsed (wall" $OUT/relabel-$variant.err | awk '{print $NF}')
  rss=$(grep "Maximum resident" $OUT/relabel-$variant.err | awk '{print $NF}')
  echo "relabel 100k $variant: $line; wall=$wall peak_rss_kB=$rss"
done
