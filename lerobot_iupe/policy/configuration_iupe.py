"""``--policy.type=iupe``: configuration of the IUPE policy (inverse dynamics model + policy model)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PreTrainedConfig
from lerobot.optim import AdamConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_iupe.policy.action_sources import CAMERA, POSITION, SOURCE_KINDS, max_lag
from lerobot_iupe.policy.action_space import action_space_from_dataset, check_binary_action_dims
from lerobot_iupe.policy.joint_fit import named_columns, sources_of_dataset
from lerobot_iupe.policy.observation_config import ObservationPolicyConfig

# Measured with benchmarks/measure/context.py (10 labelled expert episodes, 50 held out): k = 1 raised MountainCar's
# agreement 0.977 → 0.993 and LunarLander's R² 0.853 → 0.882 (by effect 0.851 → 0.885); it cost Acrobot
# 0.998 → 0.996 and SO-101's R² 0.981 → 0.973 and left CartPole at 1.000. k = 2 was no better on average.
SUPERVISED_IDM_CONTEXT = 1
# How far after t the camera network of a camera dimension looks (t and t + this): a gripper's jaws take a few tenths
# of a second to follow a key press; on a real arm's 10 fps wrist camera frames t and t+5 labelled it best.
CAMERA_REACH_SECONDS = 0.5
IDM_ONLY_CANNOT_ACT = (
    "this checkpoint trained its inverse dynamics model alone (--policy.idm_only=true): it labels datasets "
    "(lerobot-iupe-relabel), but its policy model was never trained; train without --policy.idm_only to act"
)


@PreTrainedConfig.register_subclass("iupe")
@dataclass
class IUPEConfig(ObservationPolicyConfig):
    """IUPE = BCO(α) + sampling + exploration + self-attention. All three off is BCO(α);
    ``supervised=true`` trains the policy (the BC baseline) and the IDM on the dataset's true actions: no env, no
    pre-demonstrations, and a checkpoint ``lerobot-iupe-relabel`` takes."""

    # Random pre-demonstrations (with actions) that train the inverse dynamics model first: their repo id.
    pre_demos_repo_id: str | None = None
    # Local directory of the pre-demonstrations; None = $HF_LEROBOT_HOME/<pre_demos_repo_id> (or the hub).
    pre_demos_root: str | None = None
    # Sampling, the paper's first mechanism: the IDM retrains on a set rebuilt from the successful rollouts.
    sampling: bool = True
    # The largest share of I^s that sampling draws from successful rollouts (the paper: 1.0, so I^s holds no
    # pre-demonstrations once every rollout succeeds). Below 1 the success distribution is scaled down to it and
    # pre-demonstrations keep the rest: on SO-101 the IDM retrained on successful rollouts alone scored R² 0.85–0.92
    # on its held-out transitions in every such cycle (0.94–0.96 otherwise; benchmarks/findings.md).
    max_success_share: float = 1.0
    # Exploration, the second: the policy learns from draws of the IDM's distribution, not its argmax.
    exploration: bool = True
    # Self-attention, the third: in the IDM's and the policy's encoders.
    attention: bool = True
    # Behaviour cloning on the dataset's true actions (BC), the IDM trained on them too: no env, no pre-demos.
    supervised: bool = False
    # With supervised: train the IDM alone, for lerobot-iupe-relabel. The policy model is not trained (on a camera
    # dataset it is about half of a step's cost: benchmarks/action_sources.md), and the checkpoint refuses to act.
    idm_only: bool = False
    # Continuous dimensions that take only their two bounds (a gripper commanded open or shut, e.g. [3] for
    # SO-101's grasp): fitted as a Bernoulli between the bounds and played as one of them, never in between.
    # Measured on SO-101 BC: benchmarks/findings.md.
    binary_action_dims: list[int] = field(default_factory=list)
    # The IDM sees frames t-k … t+1+k to label a_t (k = idm_context; 0 = the pair (s_t, s_{t+1}) of the paper).
    # Edges repeat an episode's first or last frame. In the IUPE cycle the pre-demonstrations, the rollouts and the
    # expert frames the IDM labels are all read as such windows: where an action shows in the state only some steps
    # later (Meta-World's hand lags its command by 3-4 steps), the pair cannot tell it (benchmarks/cycle_context.md).
    # The cycle holds its transitions as windows in memory: k + 1 times the frames of pairs.
    # None = 1 when supervised (best overall in benchmarks/relabel.md), else 0; resolved when training starts, so
    # config.json records it (a checkpoint saved before this option existed reads as 0).
    idm_context: int | None = None
    # The linear-first IDM of continuous actions read from observation.state (supervised; policy/joint_idm.py): an
    # arm's leader (its joints named as the state's, or another arm's), a humanoid's arms and hands. Each action
    # dimension is predicted as its source state column at its own lag, plus a ridge regression's correction and a
    # gated network per joint, from frames t-k … t+reach on observation.state, reach = the largest lag + 1 + k and
    # at least 0.35 s. idm_lag: the largest lag (a value given sets every joint's lag); None = chosen from the data.
    idm_lag: int | None = None
    # Each action dimension's own lag in that model (frames): where a_t best matches its source s_{t+lag}, 0 … 0.35 s.
    # None = chosen from the labelled data. Resolved when training starts, so config.json records them.
    idm_joint_lags: list[int] | None = None
    # The observation.state column of each action dimension in that model: the state of the same name, else the column
    # the action follows most closely (|correlation| at its lag). [] = off (the IDM of the paper's envs and cameras).
    # None = on wherever most action dimensions are named as states or follow a column (|correlation| ≥ 0.8).
    joint_state_columns: list[int] | None = None
    # What each action dimension of that model reads of its column (policy/joint_idm.py, SOURCE_KINDS): "position"
    # (a_t ~ s_{t+lag}: an arm's leader), "difference" (a_t ~ s_{t+lag+1} - s_{t+lag}: measured joint velocities,
    # end-effector deltas) or "camera" (no column follows it: a camera network labels it, with the state's ridge).
    # None = chosen from the labelled data (a checkpoint saved before this option existed reads as all "position").
    idm_source_kinds: list[str] | None = None
    # A linear part under any other continuous IDM (policy/linear_prior.py): a ridge from the window's vector values,
    # the network learning what it leaves. None = on when supervised (fitted on the frames it labels), off in the
    # cycle: there the first IDM labels by it alone, at the ridge, yet IUPE's success on Meta-World went 0.34 -> 0.13
    # on reach, 0.39 -> 0.54 on pick-place (benchmarks/cycle_linear_part.md). Resolved when training starts (a
    # checkpoint saved before this option existed reads as off, fine-tuned too).
    idm_linear_part: bool | None = None
    # The policy model reads the last n observations s_{t-n+1} … s_t (LeRobot's name; before an episode's first
    # frame that frame is repeated). 1 = the current observation only, as in the paper. The IDM is not affected.
    n_obs_steps: int = 1
    # Continuous actions: the sampling rule's action classes are K cells of a k-means partition of the
    # pre-demonstrations' actions (benchmarks/findings.md measures K).
    action_cells: int = 16
    # Fused cameras share one image encoder (the cameras must then have one size); false = one encoder each.
    shared_camera_encoder: bool = False
    # The observations the IDM reads, a subset of observation_keys; None = all of them. An arm's
    # actions show in its own state: an SO-101 IDM trained on play that also read the block and goal labelled the
    # expert with R² < 0 on two dimensions (it never saw a carried block move), on observation.state alone ≥ 0.93.
    idm_observation_keys: list[str] | None = None
    # One cycle = train IDM on I^s, then `cycle_steps` policy steps on IDM labels, then rollouts + sampling.
    cycle_steps: int = 100
    # Episodes the policy plays at the end of every cycle (the rollouts the sampling and selection read).
    rollout_episodes: int = 20
    # The model is selected on episodes played as lerobot-eval plays them (eval_mode). N > 0: N episodes of their
    # own every cycle, from the same start seeds every cycle so that cycles are compared on one set. None: the
    # cycle's rollouts when they already play that way (no exploration), else as many episodes of their own as the
    # rollouts. 0: the rollouts themselves, also when they draw (the paper's rule; not what lerobot-eval plays).
    # Supervised (BC): None or 0 keeps the last step's weights (no env needed); N > 0 plays N episodes every
    # cycle_steps steps and keeps the best policy model, as BCO(α) and IUPE do (it needs the env, as they do); its
    # IDM, which relabelling reads, stays the latest.
    selection_episodes: int | None = None
    # IDM epochs per cycle and batch size; 0 = 2 and 256 for vector states (10 epochs for continuous actions), 5
    # and 64 for images (a CNN needs more, smaller steps: on Maze 5x5, 3 epochs of batch 256 stayed at chance).
    idm_epochs: int = 0
    # The IDM's batch size (see idm_epochs for the default).
    idm_batch_size: int = 0
    # The IDM's Adam learning rate.
    idm_lr: float = 1e-3
    # I^s size; 0 = |I_pre|.
    sampled_set_size: int = 0
    # Width of the encoders' output features (both models).
    hidden_dim: int = 64
    # Size of each state value's token in the vector encoders (where self-attention mixes values).
    token_dim: int = 16
    # Base channel count of the image encoder ("cnn").
    cnn_width: int = 16
    # The policy model's Adam learning rate (LeRobot's optimizer; the IDM has idm_lr).
    optimizer_lr: float = 1e-3
    # The policy acts, is selected and is saved with an exponential moving average of its trained weights
    # (avg ← d·avg + (1−d)·w after every optimizer step; d = ema_decay), while the optimizer goes on with the raw
    # weights; 0 = off (the raw weights, which every committed benchmark row used). SO-101 BC's success over 3 seeds
    # spread 1.00 / 0.14 / 0.66 without it and 0.78 / 0.66 / 0.72 with 0.995 (benchmarks/history.md). A supervised
    # run that does not select keeps no training state, so --resume=true goes on from the saved average.
    ema_decay: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if self.cycle_steps <= 0 or self.rollout_episodes <= 0:
            raise ValueError("--policy.cycle_steps and --policy.rollout_episodes must be positive")
        if self.selection_episodes is not None and self.selection_episodes < 0:
            raise ValueError(
                f"--policy.selection_episodes must be 0 (select on the rollouts) or more, got {self.selection_episodes}"
            )
        if not 0.0 < self.max_success_share <= 1.0:
            raise ValueError(
                f"--policy.max_success_share must be in (0, 1] (1 = the paper's sampling), got {self.max_success_share}"
            )
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"--policy.ema_decay must be in [0, 1) (0 = no weight average), got {self.ema_decay}")
        if self.idm_context is not None and self.idm_context < 0:
            raise ValueError(f"--policy.idm_context must be 0 or more frames, got {self.idm_context}")
        if self.idm_lag is not None and self.idm_lag < 0:
            raise ValueError(f"--policy.idm_lag must be 0 or more frames, got {self.idm_lag}")
        if self.idm_only and (not self.supervised or self.selection_episodes):
            raise ValueError(
                "--policy.idm_only=true trains the IDM alone on labelled frames: it needs --policy.supervised=true, "
                f"and no --policy.selection_episodes (got {self.selection_episodes}), which would play the untrained "
                "policy model"
            )
        if self.joint_state_columns and not self.supervised:
            raise ValueError(
                f"--policy.joint_state_columns={self.joint_state_columns} (the arm IDM) needs "
                "--policy.supervised=true: it learns from labelled windows"
            )
        if self.joint_state_columns and self.idm_observation_keys and self.idm_observation_keys[0] != OBS_STATE:
            raise ValueError(
                f"--policy.joint_state_columns={self.joint_state_columns} makes the IDM read {OBS_STATE} first (its "
                f"sources are its columns), but --policy.idm_observation_keys={self.idm_observation_keys}: put "
                f"{OBS_STATE} first, or pass --policy.joint_state_columns=[] for an IDM of those keys"
            )
        if self.n_obs_steps < 1:
            raise ValueError(f"--policy.n_obs_steps must be 1 or more observations, got {self.n_obs_steps}")
        if self.action_cells < 1:
            raise ValueError(f"--policy.action_cells must be at least 1, got {self.action_cells}")
        if len(set(self.binary_action_dims)) != len(self.binary_action_dims) or any(
            d < 0 for d in self.binary_action_dims
        ):
            raise ValueError(
                f"--policy.binary_action_dims must list distinct action dimensions (0, 1, …), got "
                f"{self.binary_action_dims}"
            )

    @property
    def rollouts_play_eval_mode(self) -> bool:
        """Whether the cycle's rollouts act as lerobot-eval does (draws exactly when eval_mode is "sample")."""
        return self.exploration == (self.eval_mode == "sample")

    @property
    def separate_selection_episodes(self) -> int:
        """Episodes played each cycle only to select the model; 0 = the selection reads the cycle's rollouts (or,
        supervised, that there is no selection)."""
        if self.supervised:
            return self.selection_episodes or 0
        if self.selection_episodes == 0 or (self.selection_episodes is None and self.rollouts_play_eval_mode):
            return 0
        return self.rollout_episodes if self.selection_episodes is None else self.selection_episodes

    @property
    def joint_idm(self) -> bool:
        """The IDM is the position-controlled arm's (``joint_idm.JointIDM``)."""
        return bool(self.joint_state_columns)

    @property
    def source_kinds(self) -> list[str]:
        """Each action dimension's source kind in the linear-first model (``idm_source_kinds``; all positions for
        a checkpoint that predates it)."""
        return list(self.idm_source_kinds or [POSITION] * len(self.joint_state_columns or []))

    @property
    def camera_dims(self) -> list[int]:
        """The action dimensions of the linear-first model that a camera network labels (no state column follows
        them)."""
        return [j for j, kind in enumerate(self.source_kinds) if kind == CAMERA] if self.joint_idm else []

    @property
    def camera_keys(self) -> list[str]:
        """The cameras that network reads: the policy's (none where no dimension needs them)."""
        if not self.camera_dims:
            return []
        return [k for k in self.observation_keys if self.input_features[k].type is FeatureType.VISUAL]

    @property
    def camera_offsets(self) -> list[int]:
        """The frames the camera network reads around t: t, t + 1 (where a commanded change shows first) and
        t + ``CAMERA_REACH_SECONDS`` (where a slow one, a gripper's jaws, has shown; within the window)."""
        reach = min(max(1, round(CAMERA_REACH_SECONDS * (self.fps or 30))), max(self.idm_window))
        return sorted({0, 1, reach})

    @property
    def idm_keys(self) -> list[str]:
        """The observation keys the IDM reads (the linear-first model: observation.state first, then the other vector
        keys it was trained with; observation.state alone for a checkpoint that predates them)."""
        if self.joint_idm:
            return self.idm_observation_keys or [OBS_STATE]
        return self.idm_observation_keys or self.observation_keys

    @property
    def idm_window(self) -> list[int]:
        """Frame offsets the IDM reads around t: -k … k+1; for the linear-first model -k … reach, reach = the largest
        lag + 1 + k and at least 0.35 s (``max_lag``), as far as a ridge's reference window reaches."""
        k, lag = self.idm_context or 0, self.idm_lag or 0
        if self.joint_idm:
            return list(range(-k, max(lag + k + 1, max_lag(self.fps)) + 1))
        return list(range(-k, lag + k + 2))

    @property
    def obs_window(self) -> list[int]:
        """Frame offsets the policy model reads: -(n-1) … 0."""
        return list(range(1 - self.n_obs_steps, 1))

    def get_optimizer_preset(self) -> AdamConfig:
        return AdamConfig(lr=self.optimizer_lr, grad_clip_norm=10.0)

    def validate_features(self) -> None:
        cameras = self.validate_observations()
        if self.idm_observation_keys is not None:
            outside = [k for k in self.idm_observation_keys if k not in self.observation_keys]
            if outside or not self.idm_observation_keys:
                raise ValueError(
                    f"--policy.idm_observation_keys={self.idm_observation_keys} must name one or more of the policy's "
                    f"observation keys {self.observation_keys}"
                )
        if self.joint_state_columns and set(self.idm_observation_keys or []) & set(cameras):
            raise ValueError(
                f"--policy.idm_observation_keys={self.idm_observation_keys}: the linear-first IDM "
                f"(--policy.joint_state_columns={self.joint_state_columns}) reads vectors only; its camera dimensions "
                "read the cameras by themselves"
            )
        if self.shared_camera_encoder and len({self.working_shape(k) for k in cameras}) > 1:
            shapes = {k: self.working_shape(k) for k in cameras}
            raise ValueError(
                f"--policy.shared_camera_encoder=true needs cameras of one size; they are {shapes} "
                "(pass --policy.shared_camera_encoder=false for one encoder per camera)"
            )
        # Defaults that depend on the observation kind, resolved once so that config.json records what ran.
        self.idm_batch_size = self.idm_batch_size or (64 if self.is_image else 256)

    def resolve_dataset(self, dataset_meta) -> None:
        """Fill what the training run tells (the rollout env: lerobot-train's ``--env.*``, else
        ``--policy.env_settings``, else the expert dataset's ``meta/iupe.json``; the action space from that env,
        or, supervised and without an env, from the dataset's own ``action`` feature) and refuse what it cannot
        train.
        ``dataset_meta`` is None when a checkpoint is loaded for evaluation (its config holds all of it) or a policy
        is built from features alone."""
        if dataset_meta is not None:
            if self.idm_context is None:
                self.idm_context = SUPERVISED_IDM_CONTEXT if self.supervised else 0
            if self.idm_linear_part is None:  # a checkpoint from before it (--policy.path) keeps its network alone
                self.idm_linear_part = self.supervised and self.pretrained_path is None
            if self.supervised and ACTION not in dataset_meta.features:
                raise ValueError(
                    f"--policy.supervised=true needs a dataset with actions; {dataset_meta.root} has none "
                    "(collect it with --keep_actions=true)"
                )
            self.resolve_joint_idm(dataset_meta)
        self.resolve_env(dataset_meta)
        if dataset_meta is not None and self.supervised and self.separate_selection_episodes and not self.env_settings:
            raise ValueError(
                f"--policy.selection_episodes={self.selection_episodes} with --policy.supervised=true plays "
                f"episodes in the env to select the model, and the dataset at {dataset_meta.root} records no "
                "env (meta/iupe.json): pass --env.type=<its env>, or --policy.selection_episodes=0"
            )
        self.resolve_action_space(dataset_meta, action_space_from_dataset if self.supervised else None)
        self.check_binary_action_dims()
        # A Gaussian IDM needs more passes than a categorical one: with 2 epochs a cycle LunarLander's held-out R²
        # went 0.07 → 0.29 → 0.60 over three cycles, with 10 epochs 0.78 in the first (40 random episodes).
        self.idm_epochs = self.idm_epochs or (5 if self.is_image else 10 if self.is_continuous else 2)

    def resolve_joint_idm(self, dataset_meta) -> None:
        """The linear-first model's source columns, lags and kinds, from the dataset's names and its labelled frames
        (once: a checkpoint's values stay)."""
        features = dataset_meta.features
        cameras = any(self.input_features[k].type is FeatureType.VISUAL for k in self.observation_keys)
        lowest = -min(1, self.idm_context or 0)  # a difference may end at t (a velocity measured up to t)
        if self.joint_state_columns is None:
            sources = None
            own_keys = self.idm_observation_keys in (None, [OBS_STATE])  # an IDM of other keys was asked for
            float_actions = features.get(ACTION, {}).get("dtype", "").startswith("float")
            if self.supervised and own_keys and float_actions and OBS_STATE in self.observation_keys:
                named = named_columns(dataset_meta)  # unnamed actions: each finds the column it follows
                if not self.binary_action_dims:
                    sources = sources_of_dataset(dataset_meta, named, self.idm_lag, lowest, cameras)
            self.joint_state_columns, self.idm_joint_lags, self.idm_source_kinds = sources or ([], None, None)
            if sources and self.idm_observation_keys is None:
                # Every vector the policy reads, observation.state first: a dimension's correction may read the
                # other keys where that predicts held-out episodes clearly better (joint_idm.fit_linear). On
                # Meta-World push a ridge over the state and environment state labels dx at R² 0.99, over the state
                # alone 0.94 (the puck's motion shows the push the hand's does not).
                vectors = [k for k in self.observation_keys if self.input_features[k].type is not FeatureType.VISUAL]
                self.idm_observation_keys = [OBS_STATE] + [k for k in vectors if k != OBS_STATE]
        elif self.joint_idm and self.idm_joint_lags is None:
            sources = sources_of_dataset(dataset_meta, list(self.joint_state_columns), self.idm_lag, lowest, cameras)
            self.idm_joint_lags = sources[1] if sources else [self.idm_lag or 0] * len(self.joint_state_columns)
            self.idm_source_kinds = sources[2] if sources else None
        if not self.joint_idm:
            self.idm_lag = self.idm_lag or 0
        else:
            self.idm_lag = max(self.idm_joint_lags)
        unknown = [kind for kind in self.source_kinds if kind not in SOURCE_KINDS]
        if unknown or len(self.source_kinds) != len(self.joint_state_columns or []):
            raise ValueError(
                f"--policy.idm_source_kinds={self.idm_source_kinds} must give one of {list(SOURCE_KINDS)} for each "
                f"action dimension ({len(self.joint_state_columns or [])})"
            )
        if self.camera_dims and not cameras:
            raise ValueError(
                f"--policy.idm_source_kinds={self.idm_source_kinds} reads dimensions {self.camera_dims} off a camera, "
                f"and the policy reads none ({self.observation_keys})"
            )

    def check_binary_action_dims(self) -> None:
        """``binary_action_dims`` must name dimensions of a continuous action."""
        check_binary_action_dims(self)
