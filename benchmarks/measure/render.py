"""Rendered steps per second of the SO-101 front camera (--env.image_obs=true) with the MuJoCo model's own render
quality (8x multisampling, 4096-px shadow maps, shadows on) and with the package's (none of them), the scripted
expert acting.

    python benchmarks/measure/render.py [--size 64] [--steps 100]
"""

from __future__ import annotations

import argparse
import time

from lerobot_iupe.envs.so101 import SO101PickPlaceEnv


def steps_per_second(size: int, steps: int, model_quality: bool) -> float:
    env = SO101PickPlaceEnv(image_obs=True, image_size=size)
    if model_quality:  # undo the package's settings
        model = env.env.unwrapped._model
        model.vis.quality.offsamples, model.vis.quality.shadowsize = 8, 4096
        model.light_castshadow[:] = 1
    env.reset(seed=0)
    start = time.perf_counter()
    for _ in range(steps):
        env.step(env.expert_action())
    rate = steps / (time.perf_counter() - start)
    env.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--steps", type=int, default=100)
    args = parser.parse_args()
    for label, quality in (("model's render quality", True), ("package's settings", False)):
        print(f"{label}: {steps_per_second(args.size, args.steps, quality):.1f} steps/s at {args.size} px")


if __name__ == "__main__":
    main()
