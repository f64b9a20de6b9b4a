"""What every policy of the plugin (``iupe``, ``ilpo``) configures alike: the observations it reads and how, the
action space, the env of its online phase, acting and threads. Each policy's configuration adds its own
algorithm's settings to this one."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.configs import FeatureType, NormalizationMode, PolicyFeature, PreTrainedConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_iupe.data.observation import ObservationLayout
from lerobot_iupe.data.storage import read_iupe_meta
from lerobot_iupe.data.video import working_shape
from lerobot_iupe.envs.configs import (
    IUPEEnvConfig,
    action_names,
    action_space_of,
    env_config_from_settings,
    env_settings,
)
from lerobot_iupe.policy.train_run import lerobot_train_config

EVAL_MODES = ("argmax", "sample")
IMAGE_BACKBONES = ("cnn", "resnet18")
# The default working resolution's longer side (--policy.resize_shape): see docs/policy.md.
DEFAULT_LONGEST_SIDE = 96


@dataclass
class ObservationPolicyConfig(PreTrainedConfig):
    """Settings shared by the plugin's policies (not a policy type of its own)."""

    # How select_action (lerobot-eval) acts: "argmax" (the most likely action) or "sample" (a draw from the
    # policy's distribution). Exploration during training is the algorithm's own.
    eval_mode: str = "argmax"
    # Number of discrete actions; 0 = read from the env (0 also for a continuous env).
    n_actions: int = 0
    # Continuous (Box) actions: bounds and names per dimension; None = read from the env's action space.
    action_low: list[float] | None = None
    action_high: list[float] | None = None
    action_names: list[str] | None = None
    # Frames per second of the data the model was trained on (filled from the dataset; checked when relabelling).
    fps: int | None = None
    # The observations the policy reads, in this order (config.json records it); None = every camera of the dataset,
    # then observation.state, observation.environment_state and any other vector key. Vectors alone are
    # concatenated; a camera with other keys is fused: one image encoder per camera, one for the vectors, their
    # features mixed by a linear layer (as LeRobot's ACT and Diffusion take cameras and state together).
    observation_keys: list[str] | None = None
    # Environment of the online phase (rollouts, action remapping), as {type: …, <env config fields>}.
    # lerobot-train's --env.* win when given (also over the env a --policy.path checkpoint recorded); else this; else
    # the expert dataset's meta/iupe.json. From Python, set it here: the policy never reads the process's command line.
    env_settings: dict | None = None
    # Mazes: the online phase (IUPE's rollouts, ILPO's remapping) and the model selection play only the expert
    # dataset's last K layouts; 0 = all of them. An evaluation on the other layouts then never plays a layout the
    # selection saw.
    rollout_layouts: int = 0
    # Every camera is resized to [height, width] before the encoders — in training, rollouts, select_action
    # (lerobot-eval) and relabelling — so that a dataset or env of another camera size is read at the size the
    # checkpoint learned (LeRobot's name, as in its Diffusion policy). None = cameras as they are when none is over
    # 96 px on its longer side, else the largest one scaled to 96 px on its longer side, aspect ratio kept
    # (640×480 → [72, 96]; docs/policy.md says how the choice was measured). Resolved when the policy is built, so
    # config.json records what ran.
    resize_shape: list[int] | None = None
    # Image encoder: "cnn" (compact residual CNN, CPU-sized at 64 px) or "resnet18" (torchvision, for GPU runs).
    image_backbone: str = "cnn"
    # CPU threads for torch while training (set when training starts, not when a policy is built, so evaluation
    # and relabelling in the same process keep theirs) and while the policy acts (then the caller's count is
    # restored); 0 = 1 thread for vector states (tiny networks run several times faster without intra-op
    # threading, and far faster beside LeRobot's env workers) and torch's default for images.
    torch_threads: int = 0
    # Seed of the algorithm's own random streams (env seeds, draws); None = lerobot-train's --seed.
    seed: int | None = None
    # Push the trained policy to the hub at the end of lerobot-train (needs --policy.repo_id).
    push_to_hub: bool = False

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            # States are normalised inside the model (its buffers), because the policy also feeds itself
            # transitions of its own that never pass through LeRobot's processors.
            "STATE": NormalizationMode.IDENTITY,
            "VISUAL": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )

    def __post_init__(self):
        super().__post_init__()
        if self.eval_mode not in EVAL_MODES:
            raise ValueError(f"--policy.eval_mode must be one of {list(EVAL_MODES)}, got {self.eval_mode!r}")
        if (self.action_low is None) != (self.action_high is None) or (
            self.action_low is not None and len(self.action_low) != len(self.action_high)
        ):
            raise ValueError("--policy.action_low and --policy.action_high must be given together, one per dimension")
        if self.rollout_layouts < 0:
            raise ValueError(f"--policy.rollout_layouts must be 0 (all layouts) or more, got {self.rollout_layouts}")
        if self.resize_shape is not None and (len(self.resize_shape) != 2 or min(self.resize_shape) < 8):
            raise ValueError(
                f"--policy.resize_shape must be [height, width] of at least 8 pixels each (e.g. [72,96] for "
                f"640×480 cameras), got {self.resize_shape}"
            )
        if self.image_backbone not in IMAGE_BACKBONES:
            raise ValueError(
                f"--policy.image_backbone must be one of {list(IMAGE_BACKBONES)}, got {self.image_backbone!r}"
            )

    # No delta_timestamps: the policy reads s_{t+1} from its in-memory copy of the expert dataset by each batch
    # frame's index — LeRobot's per-item delta queries cost 12× more.
    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    @property
    def drop_n_last_frames(self) -> int:
        return 1  # the last frame of an episode has no successor

    def get_scheduler_preset(self) -> None:
        return None

    @property
    def threads(self) -> int:
        """The torch thread count this policy trains and acts with; 0 = torch's own (``torch_threads``)."""
        return self.torch_threads or (0 if self.is_image else 1)

    @property
    def observation_key(self) -> str:
        """The first observation key (single-key tools: relabelling, hub cards)."""
        return self.observation_keys[0]

    def layout_of(self, keys: list[str]) -> ObservationLayout:
        """How these observation keys are joined into one array per frame (``data.observation``); cameras at the
        working resolution (``resize_shape``)."""
        return ObservationLayout(tuple(self.working_shape(k) for k in keys))

    def working_shape(self, key: str) -> tuple[int, ...]:
        """The shape the networks see of ``key``: a camera (C, *resize_shape), a vector as it is."""
        feature = self.input_features[key]
        if feature.type is FeatureType.VISUAL and self.resize_shape:
            return (int(feature.shape[0]), *(int(v) for v in self.resize_shape))
        return tuple(feature.shape)

    @property
    def layout(self) -> ObservationLayout:
        return self.layout_of(self.observation_keys)

    @property
    def is_image(self) -> bool:
        """The policy reads a camera (alone or fused with other keys)."""
        return any(self.input_features[k].type is FeatureType.VISUAL for k in self.observation_keys)

    @property
    def is_continuous(self) -> bool:
        return self.action_low is not None

    @property
    def action_dim(self) -> int:
        return len(self.action_low) if self.is_continuous else 1

    def validate_observations(self) -> list[str]:
        """Choose and check the observation keys and the working resolution; returns the cameras read."""
        features = self.input_features
        images = [k for k, f in features.items() if f.type is FeatureType.VISUAL]
        order = {OBS_STATE: 0, OBS_ENV_STATE: 1}
        vectors = sorted(
            (k for k, f in features.items() if f.type in (FeatureType.STATE, FeatureType.ENV)),
            key=lambda k: order.get(k, 2),
        )
        if not self.observation_keys:
            if not images and not vectors:
                raise ValueError(
                    f"the expert dataset has no observation {self.type.upper()} can read (features: {sorted(features)})"
                )
            self.observation_keys = images + vectors
        unknown = [k for k in self.observation_keys if k not in features]
        if unknown:
            raise ValueError(
                f"--policy.observation_keys names {unknown}, which the dataset does not have "
                f"(it has {images + vectors})"
            )
        cameras = [k for k in self.observation_keys if k in images]
        if self.resize_shape is None and cameras:
            largest = max((tuple(features[k].shape[1:]) for k in cameras), key=lambda hw: hw[0] * hw[1])
            if max(largest) > DEFAULT_LONGEST_SIDE:
                self.resize_shape = list(working_shape(*largest, DEFAULT_LONGEST_SIDE))
        return cameras

    def resolve_env(self, dataset_meta) -> None:
        """The env of the online phase: lerobot-train's ``--env.*``, else ``--policy.env_settings``, else the
        expert dataset's ``meta/iupe.json``; and the data's fps."""
        if dataset_meta is None:
            return
        self.fps = self.fps or int(dataset_meta.fps)
        train_cfg = lerobot_train_config()
        if train_cfg is not None and train_cfg.env is not None:  # the flags given now beat a checkpoint's env
            self.env_settings = env_settings(train_cfg.env)
        elif self.env_settings is None:
            self.env_settings = read_iupe_meta(Path(dataset_meta.root)).get("env")

    def resolve_action_space(self, dataset_meta, from_dataset=None) -> None:
        """Fill the action space from the env (or ``from_dataset(config, dataset_meta)`` where the algorithm can
        read it from labelled data); a policy built from features alone (no dataset, no env) takes the action
        feature it was given as a box of [-1, 1] per dimension, as LeRobot's own policies act in normalised units
        until trained."""
        if self.n_actions or self.is_continuous:
            pass
        elif self.env_settings is None and dataset_meta is not None and from_dataset is not None:
            from_dataset(self, dataset_meta)
        elif self.env_settings is None and dataset_meta is None and ACTION in self.output_features:
            dim = int(self.output_features[ACTION].shape[0])
            self.action_low, self.action_high = [-1.0] * dim, [1.0] * dim
            self.action_names = [f"a{i}" for i in range(dim)]
        elif self.env_settings is None:
            raise ValueError(
                "cannot tell the action space: no --env.type, no --policy.env_settings and the expert dataset "
                "has no meta/iupe.json; pass --env.type=<the env of the demonstrations> (from Python: "
                "env_settings={'type': …}, or output_features with the action's shape)"
            )
        else:
            env_cfg = env_config_from_settings(self.env_settings)
            if isinstance(env_cfg, IUPEEnvConfig) and env_cfg.n_actions:
                self.n_actions = env_cfg.n_actions
            else:
                space = action_space_of(env_cfg)
                self.action_low = [float(x) for x in space.low]
                self.action_high = [float(x) for x in space.high]
                self.action_names = action_names(env_cfg)
        self.output_features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(self.action_dim,))}
