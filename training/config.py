"""The one training config: a strict TOML file (``training/configs/*.toml``) plus ``key=value`` overrides.

Everything a run depends on lives here, so a run directory's saved ``config.toml`` reproduces it.
The ``[env]`` table is the simulator's own :class:`flightsim.envs.env.EnvConfig` — or, with ``env_id =
"flightsim/LidarNav-v0"``, :class:`flightsim.envs.nav_env.NavEnvConfig` — (checked by its strict loader,
keys named ``env.<key>``), which is also where the domain-randomisation switches live.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from companion.common.errors import UserError
from companion.common.tomlconfig import apply_overrides, from_dict, load_toml, to_dict, toml_dumps

#: success needs at least this mean speed over a full episode: 40 m in the default 100 s
SUCCESS_MIN_MEAN_SPEED = 0.4
#: one environment step: LidarAvoidEnv runs its vehicle at a 10 Hz control rate
STEP_SECONDS = 0.1
#: a clearance below this counts as a near miss in evaluation, metres
NEAR_MISS_DISTANCE = 0.5
#: the environments a config can train on: avoidance (no goal) and the goal task
ENV_IDS = ("flightsim/LidarAvoid-v0", "flightsim/LidarNav-v0")
#: the DAgger teachers that pass movers on one side (not left-right symmetric)
HANDED_TEACHERS = ("keep_right_expert", "present_expert")


@dataclass(frozen=True)
class PPOConfig:
    """stable-baselines3 PPO hyperparameters (defaults: the seed tutorial's)."""

    learning_rate: float = field(default=3e-4, metadata={"min": 1e-7, "max": 1.0})
    #: "constant", or "linear": from ``learning_rate`` down to 0 at ``total_timesteps`` (as rl-zoo's
    #: ``lin_`` schedules), so late updates stop shaking a policy that already flies
    learning_rate_schedule: Literal["constant", "linear"] = "constant"
    n_steps: int = field(default=2048, metadata={"min": 8})
    batch_size: int = field(default=64, metadata={"min": 2})
    n_epochs: int = field(default=10, metadata={"min": 1})
    gamma: float = field(default=0.99, metadata={"min": 0.0, "max": 1.0})
    gae_lambda: float = field(default=0.95, metadata={"min": 0.0, "max": 1.0})
    clip_range: float = field(default=0.2, metadata={"min": 0.0, "max": 1.0})
    ent_coef: float = field(default=0.01, metadata={"min": 0.0})
    vf_coef: float = field(default=0.5, metadata={"min": 0.0})
    max_grad_norm: float = field(default=0.5, metadata={"min": 0.0})
    #: hidden layer sizes of the actor and of the critic (separate networks, SB3's default)
    net_arch: list[int] = field(default_factory=lambda: [64, 64])
    #: initial log standard deviation of the Gaussian action noise
    log_std_init: float = field(default=0.0, metadata={"min": -5.0, "max": 2.0})
    #: what reads the observation before ``net_arch``: "flat" (SB3's flatten), or "circular_scan"
    #: (training/scan_features.py: circular 1-D convolutions over the stacked scans, the other
    #: features beside them; the actor and the critic each have their own)
    features_extractor: Literal["flat", "circular_scan"] = "flat"
    #: "circular_scan"'s convolutions, each (output channels, odd kernel size, stride); empty: its
    #: default (training/scan_features.py, ``DEFAULT_LAYERS``)
    scan_layers: list[tuple[int, int, int]] = field(default_factory=list, metadata={"min": 1, "max": 512})
    #: "circular_scan" also reads the newest frame's tracked movers drawn as scans, one ring per
    #: time here, seconds ahead (training/scan_features.py, ``MoverRing``); needs ``env.movers``.
    #: Empty: no rings
    mover_ring: list[float] = field(default_factory=list, metadata={"min": 0.0, "max": 10.0})
    #: stop an update's epochs once the approximate KL divergence from the policy that collected
    #: the rollout passes this (SB3's ``target_kl``; 0: never), so a fine-tune's first updates,
    #: against a critic that has not yet seen the policy fly, cannot tear up what it learnt
    target_kl: float = field(default=0.0, metadata={"min": 0.0, "max": 10.0})
    #: a trained model (.zip) whose actor and critic start PPO: a fine-tune, e.g. of a DAgger
    #: student. The hyperparameters stay this config's, and the action noise restarts at
    #: ``log_std_init``. "": a fresh network
    init_from: str = ""

    def __post_init__(self) -> None:
        for i, (_, kernel, _) in enumerate(self.scan_layers):
            if kernel % 2 != 1:
                raise ValueError(f"ppo.scan_layers[{i}]: kernel size {kernel} must be odd")


@dataclass(frozen=True)
class EvalConfig:
    """Evaluation during training on held-out generated worlds (seeds below the training range).

    The goal task flies ``n_worlds`` per family from ``first_seed`` (which must lie in
    :data:`flightsim.envs.seeds.VALIDATION`) over ``env.difficulty_range``; ``difficulty`` is unused.
    """

    every_steps: int = field(default=50_000, metadata={"min": 1})
    n_worlds: int = field(default=10, metadata={"min": 1})
    #: first world seed of the held-out set; training worlds use seeds >= 1_000_000
    first_seed: int = field(default=0, metadata={"min": 0, "max": 999_999})
    difficulty: float = field(default=0.5, metadata={"min": 0.0, "max": 1.0})
    #: evaluation processes; 0 = one per training environment, 1 = in the training process (no pool)
    workers: int = field(default=0, metadata={"min": 0, "max": 256})


@dataclass(frozen=True)
class CurriculumConfig:
    """Training difficulty rises by ``step`` each time the evaluation success rate reaches ``threshold``."""

    enabled: bool = False
    start_difficulty: float = field(default=0.2, metadata={"min": 0.0, "max": 1.0})
    step: float = field(default=0.1, metadata={"min": 0.0, "max": 1.0})
    threshold: float = field(default=0.8, metadata={"min": 0.0, "max": 1.0})


@dataclass(frozen=True)
class PretrainConfig:
    """Imitation before PPO; ``steps = 0``: none.

    ``method = "bc"``: behaviour cloning of a classical controller (:mod:`training.pretrain`).
    ``method = "dagger"`` (goal task): DAgger from a privileged teacher (:mod:`training.dagger`;
    ``teacher``: :mod:`training.path_expert` or :mod:`training.predictive_expert`), with the
    held-out evaluation after every iteration (``best_model.zip`` is the best of them, and of
    PPO's evaluations after).

    :param method: ``"bc"`` or ``"dagger"``
    :param steps: env steps recorded (all envs together; per iteration for DAgger). Behaviour
        cloning's are not counted in ``total_timesteps``; DAgger's are: with ``total_timesteps``
        set, each iteration collects at most ``total_timesteps / iterations``
    :param demonstrator: the classical controller imitated (``bc`` only)
    :param teacher: DAgger's privileged teacher (``dagger`` only)
    :param iterations: DAgger's collect-and-fit rounds
    :param beta0: DAgger's teacher flies an episode with probability ``beta0 ** iteration``
    :param teacher_noise: DAgger's teacher flies its label plus Gaussian noise of this standard
        deviation (action units; DART): its own last command then does not foretell its next label
    :param epochs: passes over the demonstrations
    :param batch_size: demonstrations per gradient step
    :param learning_rate: Adam's, for the warm start only
    :param learning_rate_schedule: each fit's: ``"constant"``, or ``"cosine"`` (annealed to 0 over
        the fit's epochs)
    :param near_weight: DAgger's labels count ``1 + near_weight × (1 − d / near_distance)`` in each
        fit, where the newest scan's nearest return ``d`` is within ``near_distance`` (0: all alike)
    :param near_distance: where that weighting starts, metres
    :param mirror: each fit mirrors a random half of every batch across the nose
        (:mod:`training.mirror`: the task is left-right symmetric, so each label is two)
    """

    method: Literal["bc", "dagger"] = "bc"
    steps: int = field(default=0, metadata={"min": 0, "max": 10_000_000})
    demonstrator: Literal["goal_follower", "gap_follower"] = "goal_follower"
    teacher: Literal[
        "path_expert", "predictive_expert", "robust_expert", "smooth_expert", "mover_expert",
        "space_time_expert", "keep_right_expert", "present_expert",
    ] = "path_expert"  # fmt: skip
    iterations: int = field(default=1, metadata={"min": 1, "max": 100})
    beta0: float = field(default=0.5, metadata={"min": 0.0, "max": 1.0})
    teacher_noise: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    epochs: int = field(default=10, metadata={"min": 1, "max": 1000})
    batch_size: int = field(default=256, metadata={"min": 1})
    learning_rate: float = field(default=1e-3, metadata={"min": 1e-7, "max": 1.0})
    learning_rate_schedule: Literal["constant", "cosine"] = "constant"
    near_weight: float = field(default=0.0, metadata={"min": 0.0, "max": 100.0})
    near_distance: float = field(default=1.5, metadata={"min": 0.1, "max": 100.0})
    mirror: bool = False


@dataclass(frozen=True)
class TrainConfig:
    """One training run.

    :param name: config name; the run directory is ``<run_root>/<name>-s<seed>``
    :param seed: seeds PPO, the world sequence and the environments
    :param total_timesteps: the run's environment steps (all environments together): PPO's, and
        DAgger's before them (PPO gets what DAgger leaves); 0: imitation only (``[pretrain]``, at
        its full size), no PPO
    :param n_envs: parallel simulator processes; 0 = one per CPU core
    :param n_stack: scans stacked into one observation (the companion's FrameStack depth)
    :param checkpoint_every: save a checkpoint every this many environment steps
    :param run_root: parent directory of run directories
    :param progress_bar: show SB3's progress bar (turn off for background runs with a log file)
    :param difficulty_spread: each training world's difficulty is drawn uniformly within this of
        ``env.difficulty`` (or of the curriculum's current difficulty), clipped to [0, 1]
    :param narrow_room_prob: fraction of training worlds generated as narrow rooms (corridors and
        small rooms like the example worlds, which the generator's default sizes never produce)
    :param narrow_room_widths: range the narrow rooms' width is drawn from, metres
    :param env_id: the environment: ``flightsim/LidarAvoid-v0`` (avoid, no goal) or
        ``flightsim/LidarNav-v0`` (fly to waypoints; ``difficulty_spread``, ``narrow_room_*`` and the
        curriculum do not apply: the env draws its own families and difficulties)
    :param env: the simulator's ``EnvConfig`` table (domain randomisation switches included)
    :param vec_env: how the ``n_envs`` simulators run: ``"batched"`` all in the training process,
        their vehicles and lidars stepped together in compiled batches
        (``training/batched_vec_env.py``, several times the steps per second), or ``"subproc"``
        one process each (SB3's ``SubprocVecEnv``, the earlier path), or ``"sharded"`` batched
        shards in one process per CPU core, a DAgger teacher labelling beside each env
        (``training/sharded_vec_env.py``); the same episodes for the same seeds each way
    :param pretrain: the behaviour cloning warm start (a fresh run only, not on ``--resume``)
    """

    env_id: Literal["flightsim/LidarAvoid-v0", "flightsim/LidarNav-v0"] = "flightsim/LidarAvoid-v0"
    name: str = "default"
    seed: int = field(default=0, metadata={"min": 0})
    total_timesteps: int = field(default=1_000_000, metadata={"min": 0})
    n_envs: int = field(default=0, metadata={"min": 0, "max": 256})
    n_stack: int = field(default=4, metadata={"min": 1, "max": 64})
    checkpoint_every: int = field(default=50_000, metadata={"min": 1})
    run_root: str = "runs"
    progress_bar: bool = True
    vec_env: Literal["batched", "subproc", "sharded"] = "batched"
    difficulty_spread: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    narrow_room_prob: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    narrow_room_widths: tuple[float, float] = (6.0, 9.0)
    env: dict[str, Any] = field(default_factory=dict)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    pretrain: PretrainConfig = field(default_factory=PretrainConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.env, dict):
            raise ValueError("env must be a table")
        if self.ppo.init_from and self.pretrain.steps:
            raise ValueError(
                "ppo.init_from starts PPO from a trained model and [pretrain] steps would train one "
                "first: give one of them"
            )
        if self.total_timesteps == 0 and not self.pretrain.steps:
            raise ValueError("total_timesteps 0 trains nothing: give it steps, or [pretrain] steps")
        if self.pretrain.steps and self.pretrain.method == "dagger":
            if not self.is_goal_task:
                raise ValueError('pretrain.method "dagger" flies the goal task (its teacher plans waypoints)')
        elif self.pretrain.steps and (self.pretrain.demonstrator == "goal_follower") != self.is_goal_task:
            task = "goal" if self.is_goal_task else "avoid"
            raise ValueError(
                f"pretrain.demonstrator {self.pretrain.demonstrator} does not fly the {task} task"
            )
        if self.pretrain.mirror and self.pretrain.teacher in HANDED_TEACHERS:
            raise ValueError(
                f"pretrain.teacher {self.pretrain.teacher} passes movers on one side, which a mirrored "
                "label would turn to the other: set pretrain.mirror = false"
            )
        ring_unread = self.ppo.features_extractor != "circular_scan" or not self.env.get("movers")
        if self.ppo.mover_ring and ring_unread:
            raise ValueError(
                "ppo.mover_ring draws the frame's movers for the \"circular_scan\" extractor: it needs "
                "that extractor and env.movers"
            )
        if not self.name or any(c in self.name for c in "/\\ "):
            raise ValueError(f"name {self.name!r} must be non-empty without spaces or slashes")

    @property
    def resolved_n_envs(self) -> int:
        """``n_envs``, with 0 meaning one per CPU core."""
        return self.n_envs or (os.cpu_count() or 1)

    @property
    def run_dir(self) -> Path:
        """Where this run's checkpoints, logs and models go."""
        return Path(self.run_root) / f"{self.name}-s{self.seed}"

    @property
    def is_goal_task(self) -> bool:
        return self.env_id == ENV_IDS[1]

    def env_config(self, **changes: Any):
        """The simulator's :class:`~flightsim.envs.env.EnvConfig`
        (:class:`~flightsim.envs.nav_env.NavEnvConfig`
        for the goal task) from the ``[env]`` table (+ ``changes``).

        :raises UserError: on an unknown or ill-typed key, named ``env.<key>``
        """
        if self.is_goal_task:
            from flightsim.envs.nav_env import NavEnvConfig

            return from_dict(NavEnvConfig, {**self.env, **changes}, prefix="env.")
        from flightsim.envs.env import EnvConfig  # the simulator is only needed once a run starts

        return from_dict(EnvConfig, {**self.env, **changes}, prefix="env.")


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """Build and fully check a :class:`TrainConfig` (the ``[env]`` table included)."""
    config = from_dict(TrainConfig, data)
    config.env_config()
    if config.is_goal_task:
        from flightsim.envs import seeds

        if config.curriculum.enabled:
            raise UserError(
                "curriculum.enabled: the goal task draws its own difficulties (env.difficulty_range)"
            )
        if config.eval.first_seed not in seeds.VALIDATION:
            raise UserError(
                f"eval.first_seed {config.eval.first_seed}: the goal task validates on seeds "
                f"{seeds.VALIDATION.start}..{seeds.VALIDATION.stop - 1}"
            )
    if config.ppo.batch_size > config.ppo.n_steps * config.resolved_n_envs:
        raise UserError(
            f"ppo.batch_size {config.ppo.batch_size} exceeds one rollout "
            f"(ppo.n_steps {config.ppo.n_steps} x n_envs {config.resolved_n_envs})"
        )
    return config


def load_train_config(path: str | Path | None, overrides: list[str] | None = None) -> TrainConfig:
    """Load ``path`` (or the defaults when ``None``), apply ``a.b=value`` overrides, check everything.

    :param path: TOML file; its stem is the default run name
    :param overrides: command-line ``key=value`` items (values parsed as TOML)
    """
    data: dict[str, Any] = load_toml(path) if path is not None else {}
    if path is not None:
        data.setdefault("name", Path(path).stem)
    return config_from_dict(apply_overrides(data, overrides or []))


#: a goal-task config to name when a goal model meets an avoidance config (and back)
TASK_CONFIGS = {ENV_IDS[0]: "training/configs/shipped.toml", ENV_IDS[1]: "training/configs/nav.toml"}
_TASK_NAMES = {ENV_IDS[0]: "avoidance", ENV_IDS[1]: "goal"}


def model_train_config(model: Path, overrides: list[str] | None = None) -> TrainConfig:
    """The training config an exported model carries in its metadata (``lidar_avoid.config``),
    with ``overrides`` applied: what ``evaluate`` and ``trace`` fly a model in without ``--config``.

    :raises UserError: the model carries none that loads; the message says to give ``--config``
    """
    import json

    from companion.guidance.policy import PREFIX, read_model_metadata

    raw = read_model_metadata(model).get(PREFIX + "config", "")
    try:
        data = json.loads(raw)
    except ValueError:
        data = None
    if not isinstance(data, dict) or "env_id" not in data:
        raise UserError(
            f"{model}: its metadata carries no training config; give the one it was trained with: "
            "--config FILE"
        )
    try:
        return config_from_dict(apply_overrides(data, overrides or []))
    except UserError as exc:
        raise UserError(f"{model}: the training config in its metadata does not load ({exc}); "
                        "give one: --config FILE") from None


def check_model_task(model: Path, config: TrainConfig, config_path: Path) -> None:
    """Refuse, in one line naming the flag, a ``--config`` whose task or observation layout is not
    the model's (read from its metadata).

    :raises UserError: the model was trained for another task or layout than ``config`` flies
    """
    from companion.guidance.policy import LEGACY_LAYOUT, PREFIX, read_model_metadata

    model_layout = read_model_metadata(model).get(PREFIX + "obs_layout", LEGACY_LAYOUT)
    layout = observation_layout(config.env_config()).name
    if model_layout == layout:
        return
    model_task = ENV_IDS[0] if model_layout == LEGACY_LAYOUT else ENV_IDS[1]
    if model_task != config.env_id:
        raise UserError(
            f"{model} flies the {_TASK_NAMES[model_task]} task ({model_task}), --config {config_path} the "
            f"{_TASK_NAMES[config.env_id]} task: drop --config to fly the model's own training config, "
            f"or give a {_TASK_NAMES[model_task]}-task one such as --config {TASK_CONFIGS[model_task]}"
        )
    raise UserError(
        f"{model} takes the observation {model_layout}, --config {config_path} makes {layout}: drop "
        "--config to fly the model's own training config"
    )


def config_to_toml(config: TrainConfig) -> str:
    """The config as TOML text (saved into the run directory and the ONNX metadata)."""
    return toml_dumps(to_dict(config))


def sideways_scale(env_config: Any) -> float:
    """m/s that a third action component stands for in an env of ``env_config`` (0: none)."""
    return float(env_config.max_sideways_speed) if getattr(env_config, "sideways", False) else 0.0


def observation_layout(env_config: Any) -> Any:
    """The observation layout an env config produces (goal configs carry theirs)."""
    from companion.perception.observation import ObservationLayout
    from companion.perception.scan import N_BINS

    return getattr(env_config, "layout", None) or ObservationLayout(n_bins=N_BINS)
