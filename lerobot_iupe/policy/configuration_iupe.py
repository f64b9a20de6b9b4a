"""``--policy.type=iupe``: configuration of the IUPE policy (inverse dynamics model + policy model)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.configs import FeatureType, NormalizationMode, PolicyFeature, PreTrainedConfig
from lerobot.optim import AdamConfig
from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

from lerobot_iupe.data.storage import read_iupe_meta
from lerobot_iupe.envs.configs import env_config_from_settings

EVAL_MODES = ("argmax", "sample")
IMAGE_BACKBONES = ("cnn", "resnet18")


@PreTrainedConfig.register_subclass("iupe")
@dataclass
class IUPEConfig(PreTrainedConfig):
    """IUPE = BCO(α) + sampling + exploration + self-attention. All three off is BCO(α);
    ``supervised=true`` trains the policy on the dataset's true actions (the BC baseline)."""

    # Random pre-demonstrations (with actions) that train the inverse dynamics model first.
    pre_demos_repo_id: str | None = None
    pre_demos_root: str | None = None
    # The three mechanisms of the paper.
    sampling: bool = True
    exploration: bool = True
    attention: bool = True
    supervised: bool = False
    # How select_action (lerobot-eval) acts, whatever the training switches: "argmax" (the policy's most likely
    # action) or "sample" (a draw from its softmax). Exploration is a training mechanism only.
    eval_mode: str = "argmax"
    # Number of discrete actions; 0 = read from the pre-demonstrations (or the env).
    n_actions: int = 0
    # Environment of the rollouts; None = the one recorded in the expert dataset's meta/iupe.json.
    env_settings: dict | None = None
    # One cycle = train IDM on I^s, then `cycle_steps` policy steps on IDM labels, then rollouts + sampling.
    cycle_steps: int = 100
    rollout_episodes: int = 20
    # IDM epochs per cycle and batch size; 0 = 2 and 256 for vector states, 5 and 64 for images (a CNN needs
    # more, smaller steps: measured on Maze 5x5, 3 epochs of batch 256 stayed at chance level).
    idm_epochs: int = 0
    idm_batch_size: int = 0
    idm_lr: float = 1e-3
    # I^s size; 0 = |I_pre|.
    sampled_set_size: int = 0
    # Network sizes.
    hidden_dim: int = 64
    token_dim: int = 16
    cnn_width: int = 16
    # Image encoder: "cnn" (compact residual CNN, CPU-sized at 64 px) or "resnet18" (torchvision, for GPU runs).
    image_backbone: str = "cnn"
    # CPU threads for torch while training (set when training starts, not when a policy is built, so evaluation
    # and relabelling in the same process keep theirs); 0 = 1 thread for vector states (tiny networks run several
    # times faster without intra-op threading) and torch's default for images.
    torch_threads: int = 0
    optimizer_lr: float = 1e-3
    # Seed of IUPE's own random streams (rollout seeds, I^s draws, label draws); None = lerobot-train's --seed.
    seed: int | None = None
    push_to_hub: bool = False

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            # States are normalised inside the model (its buffers), because the policy also feeds itself
            # pre-demonstrations and rollouts that never pass through LeRobot's processors.
            "STATE": NormalizationMode.IDENTITY,
            "VISUAL": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )

    def __post_init__(self):
        super().__post_init__()
        if self.cycle_steps <= 0 or self.rollout_episodes <= 0:
            raise ValueError("--policy.cycle_steps and --policy.rollout_episodes must be positive")
        if self.eval_mode not in EVAL_MODES:
            raise ValueError(f"--policy.eval_mode must be one of {list(EVAL_MODES)}, got {self.eval_mode!r}")
        if self.image_backbone not in IMAGE_BACKBONES:
            raise ValueError(
                f"--policy.image_backbone must be one of {list(IMAGE_BACKBONES)}, got {self.image_backbone!r}"
            )

    # No delta_timestamps: the policy reads s_{t+1} (and, supervised, the action) from its in-memory copy of the
    # expert dataset by each batch frame's index — LeRobot's per-item delta queries cost 12× more.
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

    @property
    def observation_key(self) -> str:
        return OBS_IMAGE if OBS_IMAGE in self.input_features else OBS_STATE

    @property
    def is_image(self) -> bool:
        return self.observation_key == OBS_IMAGE

    def get_optimizer_preset(self) -> AdamConfig:
        return AdamConfig(lr=self.optimizer_lr, grad_clip_norm=10.0)

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        keys = set(self.input_features)
        if OBS_STATE not in keys and OBS_IMAGE not in keys:
            raise ValueError(
                f"the expert dataset has neither '{OBS_STATE}' nor '{OBS_IMAGE}' (features: {sorted(keys)}); "
                "IUPE needs one of them"
            )
        # make_policy sets output_features from the dataset's actions: {} for state-only data.
        self.output_features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(1,))}
        # Defaults that depend on the observation kind, resolved once so that config.json records what ran.
        self.idm_epochs = self.idm_epochs or (5 if self.is_image else 2)
        self.idm_batch_size = self.idm_batch_size or (64 if self.is_image else 256)

    def resolve_dataset(self, dataset_meta) -> None:
        """Fill what the training dataset tells (the rollout env from its ``meta/iupe.json`` unless
        ``--policy.env_settings`` is given; the action count from that env) and refuse what it cannot train.
        ``dataset_meta`` is None when a checkpoint is loaded for evaluation: its config holds all of it."""
        if dataset_meta is not None and self.env_settings is None:
            self.env_settings = read_iupe_meta(Path(dataset_meta.root)).get("env")
        if self.n_actions == 0:
            if self.env_settings is None:
                raise ValueError(
                    "cannot tell the number of actions: the expert dataset has no meta/iupe.json; "
                    "pass --policy.n_actions and --policy.env_settings"
                )
            self.n_actions = env_config_from_settings(self.env_settings).n_actions
        if dataset_meta is not None and self.supervised and ACTION not in dataset_meta.features:
            raise ValueError(
                f"--policy.supervised=true needs a dataset with actions; {dataset_meta.root} has none "
                "(collect it with --keep_actions=true)"
            )
