"""``--policy.type=ilpo``: configuration of ILPO (Imitating Latent Policies from Observation, Edwards et al., ICML
2019), the paper's other baseline. Defaults follow the authors' code (docs/ilpo.md lists every deviation)."""

from dataclasses import dataclass

from lerobot.configs import PreTrainedConfig
from lerobot.optim import AdamConfig

from lerobot_iupe.policy.observation_config import ObservationPolicyConfig


@PreTrainedConfig.register_subclass("ilpo")
@dataclass
class ILPOConfig(ObservationPolicyConfig):
    """ILPO in two phases. Offline, every lerobot-train step trains the latent policy network (LPN: a latent policy
    π(z|s) and one generator G(s, z) of s_{t+1} − s_t) on the expert's state pairs, with LeRobot's optimizer. After
    the last step, online, the frozen LPN labels each of the agent's own transitions with the z* that explains it
    best, and an action remapping network (ARN) learns the real action from (s, z*), one step per env step."""

    # |Z|, the number of latent actions; 0 = the env's number of actions (the authors' CartPole 2, Acrobot 3), or,
    # for continuous actions, two per action dimension.
    latent_actions: int = 0
    # Width of the vector encoders (Linear d→w→2w); the generator, the z embedding and image encoders read 2w.
    embedding_width: int = 128
    # Image encoders' base channel count (the package's residual CNN; --policy.image_backbone picks it).
    cnn_width: int = 16
    # The LPN's Adam learning rate (LeRobot's optimizer; the authors' 2e-4).
    optimizer_lr: float = 2e-4
    # The LPN's Adam β1 (the authors' 0.5).
    optimizer_beta1: float = 0.5
    # A deviation from the authors' code, off by default: the networks read vector states normalised by the
    # dataset's mean and std, and the generator predicts each value's difference divided by its std over the
    # expert's pairs (z* is then chosen in that scaled space). Raw, a value that changes little per step (a
    # velocity) weighs nothing in the summed squared error (docs/ilpo.md measures it).
    normalize: bool = False
    # Env steps of the online remapping, each followed by one ARN step once the buffer holds a batch.
    remap_steps: int = 1000
    # Share of uniformly random real actions while remapping (the authors' 0.2, constant).
    remap_epsilon: float = 0.2
    # The ARN's Adam learning rate.
    remap_lr: float = 2e-3
    # The ARN's batch, drawn uniformly from the replay buffer.
    remap_batch_size: int = 32
    # The replay buffer's size (first in, first out).
    remap_buffer_size: int = 50_000
    # Keep the ARN that played best: every selection_every remapping steps, play selection_episodes episodes as
    # lerobot-eval plays them (eval_mode) from the same start seeds, keep the best by the env's success, then the
    # goal (as the IUPE cycle selects). 0 = the final ARN, as the authors' code keeps it.
    selection_episodes: int = 0
    # Remapping steps between two selections (with selection_episodes > 0).
    selection_every: int = 100

    def __post_init__(self):
        super().__post_init__()
        if self.latent_actions < 0 or self.latent_actions == 1:
            raise ValueError(
                f"--policy.latent_actions must be 0 (as many as the env's actions) or at least 2, got "
                f"{self.latent_actions}"
            )
        if self.remap_steps < 1 or self.remap_batch_size < 1 or self.remap_buffer_size < self.remap_batch_size:
            raise ValueError(
                "--policy.remap_steps and --policy.remap_batch_size must be positive and --policy.remap_buffer_size "
                f"at least the batch (got {self.remap_steps}, {self.remap_batch_size}, {self.remap_buffer_size})"
            )
        if not 0.0 <= self.remap_epsilon <= 1.0:
            raise ValueError(f"--policy.remap_epsilon must be in [0, 1], got {self.remap_epsilon}")
        if self.n_obs_steps != 1:
            raise ValueError(
                f"ILPO reads the current observation only: --policy.n_obs_steps must be 1, got {self.n_obs_steps}"
            )
        if self.selection_episodes < 0 or self.selection_every < 1:
            raise ValueError(
                "--policy.selection_episodes must be 0 (keep the final ARN) or more, and --policy.selection_every "
                f"positive (got {self.selection_episodes}, {self.selection_every})"
            )

    # What the package's shared encoders (FusedEncoder, the image CNN) and action heads read of a config.
    @property
    def hidden_dim(self) -> int:
        return 2 * self.embedding_width

    @property
    def token_dim(self) -> int:
        return 16

    @property
    def attention(self) -> bool:
        return False

    @property
    def shared_camera_encoder(self) -> bool:
        return False

    @property
    def binary_action_dims(self) -> list[int]:
        return []

    @property
    def n_latent(self) -> int:
        """|Z|, resolved (``latent_actions``)."""
        if self.latent_actions:
            return self.latent_actions
        return 2 * self.action_dim if self.is_continuous else self.n_actions

    def get_optimizer_preset(self) -> AdamConfig:
        # grad_clip_norm so large it never clips: the authors' Adam does not clip.
        return AdamConfig(lr=self.optimizer_lr, betas=(self.optimizer_beta1, 0.999), grad_clip_norm=1e12)

    def validate_features(self) -> None:
        self.validate_observations()

    def resolve_dataset(self, dataset_meta) -> None:
        """The env of the remapping phase and the action space from it (see ``ObservationPolicyConfig``)."""
        self.resolve_env(dataset_meta)
        self.resolve_action_space(dataset_meta)
