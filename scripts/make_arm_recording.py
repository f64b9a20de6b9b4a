"""Write an SO-101-shaped recording with LeRobot's own writer: two cameras (640×480 by default) that show a six-joint
arm, six joint positions, the leader arm's joint positions as actions, 30 fps (``lerobot_iupe.data.arm_recording``).
The follower behaves as a real SO-101 measured: a transport delay, a servo's first-order response with a dead band,
gravity on shoulder and elbow, jaws stopped by grasped objects, 12-bit encoder readings. Data to try relabelling and
camera training on without a robot; the tests, ``benchmarks/measure/cameras.py`` and
``benchmarks/measure/arm_idm.py`` use it.

    python scripts/make_arm_recording.py --root data/arm --episodes 40 [--frames 250] [--state_only] [--delay 4]
    python scripts/make_arm_recording.py --root data/humanoid --no_cameras --body humanoid --idle left_arm

``--body`` records other arms (a leader of another arm, a humanoid's arms and hands, a miscalibrated SO-101;
docs/relabelling.md); they are written without cameras. ``--body velocity_arm`` records a hand-guided arm at 10 fps:
measured joint velocities and a keyboard gripper that only its wrist camera shows, with cameras:

    python scripts/make_arm_recording.py --root data/velocity-arm --body velocity_arm --idle joint_4
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lerobot_iupe.data.arm_recording import HUMANOID_LEFT_ARM, ArmDynamics
from lerobot_iupe.data.arm_writer import BODIES, write_arm_recording


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, required=True, help="where to write the dataset (must not exist)")
    parser.add_argument("--repo_id", default="local/arm-recording", help="the dataset's repo id")
    parser.add_argument("--episodes", type=int, default=10, help="episodes to record")
    parser.add_argument("--frames", type=int, default=250, help="frames per episode")
    parser.add_argument("--height", type=int, default=480, help="camera height in pixels")
    parser.add_argument("--width", type=int, default=640, help="camera width in pixels")
    parser.add_argument("--seed", type=int, default=0, help="episode i is drawn from seed + i")
    parser.add_argument("--vcodec", default="libsvtav1", help="video codec (LeRobot's default AV1, or h264)")
    parser.add_argument("--state_only", action="store_true", help="leave the actions out (a state-only recording)")
    parser.add_argument("--no_cameras", action="store_true", help="write the joints alone, no camera")
    parser.add_argument(
        "--body", choices=sorted(BODIES), default="so101",
        help="which arms record: so101; so101_miscalibrated (an offset wrist_roll that barely follows); "
        "other_leader (an SO-101 leader driving a 7-value follower of other names); humanoid (2 arms, 2 hands); "
        "velocity_arm (hand-guided, 10 fps: measured joint velocities, a keyboard gripper only its camera shows)",
    )  # fmt: skip
    parser.add_argument(
        "--idle", nargs="+", default=[], metavar="JOINT",
        help="leader joints that stay at rest (action names; 'left_arm' = the humanoid's left arm)",
    )  # fmt: skip
    default = ArmDynamics()
    arm = parser.add_argument_group(
        "how the follower follows the leader (defaults: a real SO-101, docs/relabelling.md)"
    )
    arm.add_argument("--delay", type=int, default=default.delay, help="transport delay in frames before a servo moves")
    arm.add_argument(
        "--response", type=float, default=default.response, help="share of its error a servo closes a frame"
    )
    arm.add_argument(
        "--dead_band", type=float, default=default.dead_band, help="error (degrees) below which a servo rests"
    )
    arm.add_argument("--gravity", type=float, nargs=2, default=default.gravity, metavar=("LIFT", "ELBOW"),
                     help="degrees gravity holds shoulder_lift and elbow_flex below their targets at most")  # fmt: skip
    arm.add_argument("--wrist_gravity", type=float, default=default.wrist_gravity,
                     help="degrees gravity holds wrist_flex below its target at most, by the arm's pose")  # fmt: skip
    arm.add_argument("--grasp_probability", type=float, default=default.grasp_probability,
                     help="probability that closing the gripper grasps an object, which stops the jaws")  # fmt: skip
    arm.add_argument("--reading_noise", type=float, default=default.reading_noise, help="noise of a joint reading")
    arm.add_argument("--tremor", type=float, default=default.tremor, help="the operator's hand tremor (degrees)")
    arm.add_argument("--no_quantise", action="store_true", help="exact readings instead of 12-bit encoder steps")
    args = parser.parse_args()
    try:
        dynamics = ArmDynamics(
            delay=args.delay, response=args.response, dead_band=args.dead_band, gravity=tuple(args.gravity),
            wrist_gravity=args.wrist_gravity,
            grasp_probability=args.grasp_probability, quantise=not args.no_quantise,
            reading_noise=args.reading_noise, tremor=args.tremor,
        )  # fmt: skip
    except ValueError as error:
        parser.error(f"--delay/--response: {error}")
    if args.root.exists():
        parser.error(f"--root={args.root} already exists; choose a new folder")
    body = BODIES[args.body]
    idle = tuple(j for name in args.idle for j in (HUMANOID_LEFT_ARM if name == "left_arm" else (name,)))
    known = set(body.action_names) | (set(body.state_names) if args.body == "velocity_arm" else set())
    unknown = sorted(set(idle) - known)
    if unknown:
        parser.error(f"--idle: {unknown} are not joints of --body={args.body}: {', '.join(body.action_names)}")
    if args.body not in ("so101", "velocity_arm") and not args.no_cameras:
        parser.error(f"--body={args.body}: the cameras draw an SO-101; add --no_cameras")
    dataset = write_arm_recording(
        args.root, args.episodes, args.frames, args.height, args.width, fps=10 if args.body == "velocity_arm" else 30,
        seed=args.seed, repo_id=args.repo_id,
        vcodec=args.vcodec, with_actions=not args.state_only, progress=True, dynamics=dynamics,
        cameras=not args.no_cameras, body=body, idle=idle,
    )  # fmt: skip
    print(f"wrote {dataset.meta.total_frames} frames in {dataset.meta.total_episodes} episodes to {args.root}")


if __name__ == "__main__":
    main()
