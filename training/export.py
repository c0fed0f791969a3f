"""``avoid-train export``: the trained actor as a self-contained ONNX file the companion can fly.

Only the deterministic actor goes in (feature extractor → policy MLP → action mean → clip to
[-1, 1]); the value head and the Gaussian sampling stay behind. That is exactly what
``model.predict(obs, deterministic=True)`` computes, and the export proves it: on observations
from real rollouts the ONNX Runtime output must match SB3's within ``PARITY_TOLERANCE``.

Several ``--model`` checkpoints of one task export as their ensemble: one file whose action is the
mean of the members' (each clipped, as each predicts), so the companion runs it as any other
model. Students imitating one teacher from different seeds err in different places; their mean
errs less (bagging).

The exporter is torch's TorchScript-based one (``dynamo=False``): for a plain MLP it writes one
self-contained file in well under a second, with parity; the dynamo exporter took ~10 s and
wrote the weights to a side file by default.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from companion.common.errors import UserError

if TYPE_CHECKING:
    import torch
    from stable_baselines3 import PPO

    from training.config import TrainConfig

log = logging.getLogger(__name__)

PARITY_TOLERANCE = 1e-5
PARITY_SAMPLES = 1000
INPUT_NAME = "observation"
OUTPUT_NAME = "action"
OPSET = 17


def actor_module(model: PPO) -> torch.nn.Module:
    """The deterministic actor of an SB3 PPO model as a torch module: ``(B, obs) -> (B, 2)`` in [-1, 1].

    :param model: a PPO model with a Box observation (no image preprocessing) and a Box action space
    """
    import torch

    policy = model.policy
    low = torch.as_tensor(model.action_space.low, dtype=torch.float32)
    high = torch.as_tensor(model.action_space.high, dtype=torch.float32)

    class DeterministicActor(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.features = policy.pi_features_extractor
            self.latent = policy.mlp_extractor.policy_net
            self.mean = policy.action_net
            self.register_buffer("low", low)
            self.register_buffer("high", high)

        def forward(self, obs: torch.Tensor) -> torch.Tensor:
            return torch.clamp(self.mean(self.latent(self.features(obs))), self.low, self.high)

    return DeterministicActor().eval()


def ensemble_module(models: Sequence[PPO]) -> torch.nn.Module:
    """The mean of the models' deterministic actors (:func:`actor_module`); one model: its actor."""
    import torch

    actors = [actor_module(model) for model in models]
    if len(actors) == 1:
        return actors[0]

    class MeanActor(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.members = torch.nn.ModuleList(actors)

        def forward(self, obs: torch.Tensor) -> torch.Tensor:
            return torch.stack([member(obs) for member in self.members]).mean(dim=0)

    return MeanActor().eval()


def export_onnx(models: Sequence[PPO], out: Path, metadata: dict[str, str]) -> None:
    """Write the actor (several models: their mean) to ``out`` with ``metadata`` as ONNX
    metadata_props; ``onnx.checker`` must pass.

    :param models: trained PPO models of one observation and action space (usually one)
    :param out: destination ``.onnx`` file
    :param metadata: key → value strings the companion checks at load time
    """
    import onnx
    import torch

    actor = ensemble_module(models)
    dummy = torch.zeros((1, *models[0].observation_space.shape), dtype=torch.float32)
    out.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        # The TorchScript exporter announces its own deprecation; it is still the right tool here.
        warnings.simplefilter("ignore", category=DeprecationWarning)
        warnings.simplefilter("ignore", category=FutureWarning)
        torch.onnx.export(
            actor,
            (dummy,),
            str(out),
            dynamo=False,
            input_names=[INPUT_NAME],
            output_names=[OUTPUT_NAME],
            dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
            opset_version=OPSET,
        )
    proto = onnx.load(str(out))
    del proto.metadata_props[:]
    for key, value in metadata.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    layout = metadata.get("lidar_avoid.obs_layout", "scan360")
    actors = "actor" if len(models) == 1 else f"actors' mean ({len(models)} members)"
    action = "forward, yaw rate" + (", sideways" if models[0].action_space.shape == (3,) else "")
    proto.doc_string = f"lidar-avoid deterministic PPO {actors} (stacked {layout} frames -> [{action}])"
    onnx.checker.check_model(proto, full_check=True)
    onnx.save(proto, str(out))
    log.info("wrote %s (%d bytes)", out, out.stat().st_size)


def policy_spec_for(config: TrainConfig):
    """The companion's :class:`~companion.guidance.policy.PolicySpec` for what this training run
    fed the policy."""
    from companion.guidance.policy import PolicySpec
    from companion.perception.observation import ObservationLayout
    from companion.perception.scan import BIN_CONVENTION, N_BINS
    from training.config import sideways_scale

    env_config = config.env_config()
    # the goal task's frame layout (scan + goal + velocity); the avoidance task's is the scan alone
    layout = env_config.layout if config.is_goal_task else ObservationLayout(n_bins=N_BINS)
    return PolicySpec(
        stack=config.n_stack,
        n_bins=N_BINS,
        max_range=float(env_config.scan.max_range),
        bin_convention=BIN_CONVENTION,
        max_speed=float(env_config.max_speed),
        max_yaw_rate=float(env_config.max_yaw_rate),
        max_sideways_speed=sideways_scale(env_config),
        layout=layout,
    )


def rollout_observations(model: PPO, config: TrainConfig, n: int, seed: int = 0) -> np.ndarray:
    """``n`` stacked observations the policy met while flying (VecFrameStack over the real simulator).

    Actions are sampled (not deterministic) so the set covers more than one line of flight.
    """
    from training.vec_env import make_vec_env

    venv = make_vec_env(config, n_envs=1, seed=seed, subprocess=False)
    try:
        obs = venv.reset()
        out = np.empty((n, *obs.shape[1:]), dtype=np.float32)
        for i in range(n):
            out[i] = obs[0]
            action, _ = model.predict(obs, deterministic=False)
            obs, _, _, _ = venv.step(action)
    finally:
        venv.close()
    return out


def parity_max_abs_diff(models: Sequence[PPO], onnx_path: Path, observations: np.ndarray) -> float:
    """Max |ONNX Runtime − ``model.predict(obs, deterministic=True)``| over ``observations`` (several
    models: the mean of their predictions)."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = session.run(None, {INPUT_NAME: observations.astype(np.float32)})[0]
    want = np.mean([model.predict(observations, deterministic=True)[0] for model in models], axis=0)
    return float(np.max(np.abs(got - want)))


def find_run_config(checkpoint: Path) -> Path:
    """The ``config.toml`` a checkpoint was trained with: in its run directory (or one level above)."""
    for directory in (checkpoint.parent, checkpoint.parent.parent):
        candidate = directory / "config.toml"
        if candidate.is_file():
            return candidate
    raise UserError(f"no config.toml beside {checkpoint} or in its run directory; pass --config")


def load_model(path: Path) -> PPO:
    """Load an SB3 PPO checkpoint; a missing or foreign file is a :class:`UserError`."""
    from stable_baselines3 import PPO

    if not path.is_file():
        raise UserError(f"model file not found: {path}")
    try:
        return PPO.load(str(path), device="cpu")
    except Exception as exc:  # SB3 raises many types for a file that is not one of its zips
        raise UserError(f"{path} is not a stable-baselines3 PPO checkpoint: {exc}") from None


def export_policy(
    paths: Sequence[Path], out: Path, config_path: Path | None, samples: int = PARITY_SAMPLES
) -> float:
    """Export the checkpoints ``paths`` (several: their ensemble) to ``out`` and return the parity max abs
    difference (raise if too large).

    :param paths: SB3 ``.zip`` checkpoints, usually one
    :param out: ``.onnx`` destination
    :param config_path: the runs' training config (default: found in each run directory; the
        first model's goes into the metadata, and every member's must feed the same observation)
    :param samples: rollout observations for the parity check
    """
    from companion.common.tomlconfig import to_dict
    from companion.guidance.policy import policy_metadata
    from training.config import load_train_config

    models = [load_model(path) for path in paths]
    configs = [load_train_config(config_path or find_run_config(path)) for path in paths]
    config = configs[0]
    spec = policy_spec_for(config)
    expected = (spec.obs_size,)
    for path, model, member_config in zip(paths, models, configs, strict=True):
        if model.observation_space.shape != expected:
            raise UserError(
                f"{path}: observation shape {model.observation_space.shape} does not match the config's "
                f"{config.n_stack} stacked {spec.layout.name} frames {expected}"
            )
        if policy_spec_for(member_config) != spec:
            raise UserError(f"{path}: trained for another observation or action scaling than {paths[0]}")
    config_json = json.dumps(to_dict(config), sort_keys=True)
    export_onnx(models, out, policy_metadata(spec, config_json))
    observations = rollout_observations(models[0], config, samples, seed=config.seed + 12345)
    diff = parity_max_abs_diff(models, out, observations)
    if diff > PARITY_TOLERANCE:
        raise RuntimeError(f"ONNX parity failed: max abs diff {diff:.3g} > {PARITY_TOLERANCE:g}")
    return diff


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--model", type=Path, required=True, action="append",
        help="SB3 PPO checkpoint (.zip); give it again for each member of an ensemble (the mean action)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="ONNX file to write")
    parser.add_argument("--config", type=Path, default=None, help="training config (default: the run's)")
    parser.add_argument(
        "--parity-samples", type=int, default=PARITY_SAMPLES, help="rollout observations for the parity check"
    )


def command(args: argparse.Namespace) -> int:
    if args.parity_samples < 1:
        raise UserError("--parity-samples must be at least 1")
    diff = export_policy(args.model, args.out, args.config, args.parity_samples)
    print(
        f"exported {args.out}: max abs diff vs model.predict over {args.parity_samples} "
        f"rollout observations {diff:.3g}"
    )
    # for the companion config's policy.sha256, which refuses any other file
    print(f"sha256 {hashlib.sha256(args.out.read_bytes()).hexdigest()}  {args.out}")
    return 0
