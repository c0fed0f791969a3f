"""What the evaluation flies: the learned policy (ONNX through the companion's own
:class:`~companion.guidance.policy.OnnxPolicy`, or an SB3 checkpoint), the baselines and the privileged
teachers, each turning one scan per step into an action, optionally behind the companion's
:class:`~companion.safety.shield.SafetyShield` as in flight.

:class:`ControllerSpec` describes one picklably (tasks cross process boundaries);
:func:`build_controller` builds it in the worker that flies it.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from companion.common.errors import UserError
from companion.perception.framestack import FrameStack
from companion.perception.scan import N_BINS
from companion.safety.give_way import GiveWayConfig
from companion.safety.shield import Command, SafetyShield, ShieldConfig, command_from_action
from training.attackers import ATTACKERS, REPLAY, ReplayAttacker, make_attacker
from training.config import STEP_SECONDS, observation_layout, sideways_scale
from training.path_expert import ExpertController, PathExpert
from training.predictive_expert import PredictiveExpert, mover_expert, robust_expert, smooth_expert
from training.space_time_expert import keep_right_expert, present_expert, space_time_expert

BASELINES = ("gap_follower", "random")
GOAL_BASELINES = ("goal_follower", "straight_line")
#: flown only when named: baselines for worlds with movers (they need the env's tracker)
TRACK_BASELINES = ("goal_follower_tracks",)
#: ``[env]`` keys a controller flies with, whatever the config says: the straight line gauges how
#: hard a world is by flying at the waypoint itself, blind; with the route its goal features would
#: point along a route planned round what the scans showed
ENV_OVERRIDES: dict[str, dict[str, Any]] = {"straight_line": {"route": False}}
#: flown only when named: not a baseline a drone could fly, it reads the simulator's truth (the
#: DAgger teachers, :mod:`training.path_expert`, :mod:`training.predictive_expert`): what
#: imitation can reach
PRIVILEGED_GOAL_CONTROLLERS = (
    "path_expert",
    "predictive_expert",
    "robust_expert",
    "smooth_expert",
    "mover_expert",
    "space_time_expert",
    "keep_right_expert",
    "present_expert",
)
#: the DAgger teachers by name, each built from the env whose truth it reads
TEACHERS: dict[str, Callable[[Any], Any]] = {
    "path_expert": PathExpert,
    "predictive_expert": PredictiveExpert,
    "robust_expert": robust_expert,
    "smooth_expert": smooth_expert,
    "mover_expert": mover_expert,
    "space_time_expert": space_time_expert,
    "keep_right_expert": keep_right_expert,
    "present_expert": present_expert,
}


class Controller(Protocol):
    """Anything that turns one scan per step into an action in ``[-1, 1]²`` (``[-1, 1]³`` in an env
    with a sideways part)."""

    def reset(self, scan: np.ndarray) -> np.ndarray: ...

    def act(self, scan: np.ndarray) -> np.ndarray: ...


class StackedPolicyController:
    """A stacked-scan policy behind the companion's :class:`FrameStack` (as on the drone).

    :param act_stacked: maps one ``(n_stack * frame_size,)`` observation to a ``(2,)`` action
    :param n_stack: stack depth
    :param frame_size: floats per frame (360 scan bins, 365 with the goal features)
    """

    def __init__(
        self, act_stacked: Callable[[np.ndarray], np.ndarray], n_stack: int, frame_size: int = N_BINS
    ) -> None:
        self._act = act_stacked
        self._stack = FrameStack(n_stack, frame_size)

    def reset(self, scan: np.ndarray) -> np.ndarray:
        return np.asarray(self._act(self._stack.reset(scan)), dtype=np.float32)

    def act(self, scan: np.ndarray) -> np.ndarray:
        return np.asarray(self._act(self._stack.push(scan)), dtype=np.float32)


class ShieldedController:
    """Another controller's actions filtered by the companion's safety shield, as in flight.

    :param inner: the controller whose actions are filtered
    :param shield: the companion's shield (its limits are the flight configuration's)
    :param max_speed: m/s that an action of 1 stands for (the env's action scaling)
    :param max_yaw_rate: rad/s that an action of 1 stands for
    :param velocity: the measured body velocity (forward, left) now, less the drift estimate (the
        true motion as the scans show it), as the companion gives its shield (the env's
        :meth:`~flightsim.envs.env.LidarAvoidEnv.shield_velocity`)
    :param lateral: where the shield's sideways brake goes (the env's
        :meth:`~flightsim.envs.env.LidarAvoidEnv.command_lateral`), since an action carries none
    :param drift: the drift estimate now (body forward, left, m/s), as the companion tracks it (the
        env's :meth:`~flightsim.envs.env.LidarAvoidEnv.shield_drift`), or None where it is not tracked
    :param max_sideways_speed: m/s that a third action component stands for (a goal env with
        ``sideways``); 0: actions have two. The sideways part the shield sends goes to ``lateral``
        with its brake, and the action returned asks none
    :param heading: the heading now, rad counter-clockwise (the env's
        :meth:`~flightsim.envs.env.LidarAvoidEnv.shield_heading`), for the shield's memory and gate
    :param movers: what moves in the scan now, as the companion's tracker gives it (the env's
        :meth:`~flightsim.envs.env.LidarAvoidEnv.shield_movers`): the shield's ``moving_bins`` and
        ``movers`` keywords
    """

    def __init__(
        self,
        inner: Controller,
        shield: SafetyShield,
        max_speed: float,
        max_yaw_rate: float,
        velocity: Callable[[], np.ndarray] | None = None,
        lateral: Callable[[float], None] | None = None,
        drift: Callable[[], tuple[float, float] | None] | None = None,
        max_sideways_speed: float = 0.0,
        heading: Callable[[], float] | None = None,
        movers: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        self._inner = inner
        self.shield = shield
        self._scale = (max_speed, max_yaw_rate)
        self._sideways = max_sideways_speed
        self._velocity = velocity
        self._lateral = lateral
        self._drift = drift
        self._heading = heading
        self._movers = movers
        #: the last (requested, sent) commands, for a trace (``avoid-train trace``)
        self.last: tuple[Command, Command] | None = None

    def reset(self, scan: np.ndarray) -> np.ndarray:
        self.shield.reset()
        return self._filter(self._inner.reset(scan), scan)

    def act(self, scan: np.ndarray) -> np.ndarray:
        return self._filter(self._inner.act(scan), scan)

    def _filter(self, action: np.ndarray, scan: np.ndarray) -> np.ndarray:
        max_speed, max_yaw_rate = self._scale
        scan = scan[:N_BINS]  # a goal frame's scan part
        measured = None
        if self._velocity is not None:
            v = self._velocity()
            measured = (float(v[0]), float(v[1]))
        drift = self._drift() if self._drift is not None else None
        requested = command_from_action(action, max_speed, max_yaw_rate, self._sideways)
        heading = self._heading() if self._heading is not None else None
        moving = self._movers() if self._movers is not None else {}
        safe = self.shield.filter(requested, scan, STEP_SECONDS, measured, drift, heading, **moving)
        self.last = (requested, safe)
        if self._lateral is not None:
            self._lateral(safe.lateral)
        sent = [safe.forward / max_speed, safe.yaw_rate / max_yaw_rate] + ([0.0] if self._sideways else [])
        return np.array(sent, dtype=np.float32)


class NoSidewaysController:
    """A two-part controller (the baselines) in an env whose action has a sideways part: it asks
    none (a2 = 0), which flies exactly what its two parts fly in the two-part env."""

    def __init__(self, inner: Controller) -> None:
        self._inner = inner

    def reset(self, scan: np.ndarray) -> np.ndarray:
        return self._widen(self._inner.reset(scan))

    def act(self, scan: np.ndarray) -> np.ndarray:
        return self._widen(self._inner.act(scan))

    @staticmethod
    def _widen(action: np.ndarray) -> np.ndarray:
        return np.append(np.asarray(action, dtype=np.float32), np.float32(0.0))


def sb3_controller(model: Any, n_stack: int, frame_size: int = N_BINS) -> StackedPolicyController:
    """An SB3 model acting deterministically (what ``model.predict(..., deterministic=True)`` gives)."""

    def act(obs: np.ndarray) -> np.ndarray:
        action, _ = model.predict(obs[None, :], deterministic=True)
        return action[0]

    return StackedPolicyController(act, n_stack, frame_size)


@dataclass(frozen=True)
class ControllerSpec:
    """What to build in a worker: ``kind`` is ``policy`` (``path``) or one of :data:`BASELINES` /
    :data:`GOAL_BASELINES` / :data:`PRIVILEGED_GOAL_CONTROLLERS` / :data:`~training.attackers.ATTACKERS`,
    or :data:`~training.attackers.REPLAY` (replaying ``actions``, one per step);
    ``shield``: behind the
    companion's safety shield, with ``shield_config``'s limits (None: the defaults)."""

    kind: str
    path: str = ""
    name: str = ""
    shield: bool = False
    shield_config: ShieldConfig | None = None
    #: what a :data:`~training.attackers.REPLAY` controller replays (a tuple: the spec stays hashable)
    actions: tuple[tuple[float, ...], ...] = ()

    @property
    def label(self) -> str:
        return (self.name or self.kind) + ("+shield" if self.shield else "")


#: policies loaded in this process (one at a time), so each episode does not load its own
_POLICIES: dict[Any, Any] = {}


def build_controller(
    spec: ControllerSpec,
    env_config: Any,
    seed: int,
    n_stack: int = 4,
    velocity: Callable[[], np.ndarray] | None = None,
    lateral: Callable[[float], None] | None = None,
    env: Any = None,
    drift: Callable[[], tuple[float, float] | None] | None = None,
    heading: Callable[[], float] | None = None,
    movers: Callable[[], dict[str, Any]] | None = None,
) -> Controller:
    """Build the controller ``spec`` describes, behind the shield if it says so (the shield braking
    and capping yaw as the env's autopilot response does, watching ``velocity`` and carrying
    ``drift`` as in flight).

    :param env: the unwrapped env the controller flies, for a privileged one
        (:data:`PRIVILEGED_GOAL_CONTROLLERS`)
    :param movers: what moves in the scan now, as the tracker gives it (the env's
        :meth:`~flightsim.envs.nav_env.LidarNavEnv.shield_movers`): the shield's, and
        ``goal_follower_tracks``'s
    """
    controller = _bare_controller(spec, env_config, seed, n_stack, env, movers)
    if not spec.shield:
        return controller
    limits = spec.shield_config or ShieldConfig()
    shield = SafetyShield(limits, float(env_config.scan.max_range), env_config.autopilot_response)
    return ShieldedController(
        controller, shield, float(env_config.max_speed), float(env_config.max_yaw_rate), velocity, lateral,
        drift, sideways_scale(env_config), heading, movers,
    )  # fmt: skip


def _teacher_controller(kind: str, env: Any) -> Controller:
    """A privileged teacher flying ``env``."""
    return ExpertController(TEACHERS[kind](env))


def _bare_controller(
    spec: ControllerSpec,
    env_config: Any,
    seed: int,
    n_stack: int,
    env: Any = None,
    movers: Callable[[], dict[str, Any]] | None = None,
) -> Controller:
    """The controller itself (policies are loaded once per process)."""
    if spec.kind in ATTACKERS:
        return make_attacker(spec.kind, seed, 3 if sideways_scale(env_config) else 2)
    if spec.kind == REPLAY:
        return ReplayAttacker(spec.actions, 3 if sideways_scale(env_config) else 2)
    if spec.kind == "goal_follower_tracks":  # its sidesteps fly the sideways part itself
        return _goal_follower_tracks(env_config, movers)
    baseline = _baseline(spec, env_config, seed)
    if baseline is not None:
        return NoSidewaysController(baseline) if sideways_scale(env_config) else baseline
    if spec.kind in PRIVILEGED_GOAL_CONTROLLERS:
        if env is None:
            raise ValueError(f"{spec.kind} reads the env it flies: pass env")
        return _teacher_controller(spec.kind, env)
    if spec.kind != "policy":
        raise ValueError(f"unknown controller kind {spec.kind!r}")
    # keyed by modification time too: training re-saves its evaluation model under one name
    key = ("policy", spec.path, os.stat(spec.path).st_mtime_ns, env_config.scan.max_range)
    if key not in _POLICIES:
        _POLICIES.clear()
        _POLICIES[key] = load_policy(Path(spec.path), env_config, n_stack)
    act, stack = _POLICIES[key]
    return StackedPolicyController(act, stack, observation_layout(env_config).frame_size)


def _baseline(spec: ControllerSpec, env_config: Any, seed: int) -> Controller | None:
    """The classical controller ``spec`` names (two action parts), or None for any other kind."""
    from training.baselines import (
        GapFollower,
        GapFollowerConfig,
        GoalFollower,
        GoalFollowerConfig,
        RandomController,
        StraightLine,
    )

    if spec.kind == "random":
        return RandomController(seed)
    if spec.kind == "gap_follower":
        return GapFollower(GapFollowerConfig(max_range=float(env_config.scan.max_range)))
    if spec.kind == "goal_follower":
        hold = env_config.drift_hold_limits if env_config.drift_hold else None
        config = GoalFollowerConfig(max_range=float(env_config.scan.max_range))
        return GoalFollower(env_config.layout, config, hold=hold)
    if spec.kind == "straight_line":
        return StraightLine(env_config.layout)
    return None


def _goal_follower_tracks(env_config: Any, movers: Callable[[], dict[str, Any]] | None) -> Controller:
    """The goal follower giving way to the tracker's movers (the env's, as the shield gets them).

    :raises UserError: the env does not track what moves
    :raises ValueError: no ``movers`` to read them from
    """
    from training.baselines import GoalFollowerConfig, GoalFollowerTracks

    if not getattr(env_config, "tracking", False):
        raise UserError("goal_follower_tracks gives way to the tracker's movers: set env.tracking = true")
    if movers is None:
        raise ValueError("goal_follower_tracks reads the tracker's movers: pass movers")
    hold = env_config.drift_hold_limits if env_config.drift_hold else None
    config = GoalFollowerConfig(max_range=float(env_config.scan.max_range))
    give_way = GiveWayConfig(vehicle_radius=float(env_config.vehicle_radius))

    def tracked() -> Any:
        """The tracker's movers now, as the shield gets them."""
        return movers().get("movers", [])

    return GoalFollowerTracks(env_config.layout, tracked, config, hold, give_way, sideways_scale(env_config))


def load_policy(
    path: Path, env_config: Any, n_stack: int = 4
) -> tuple[Callable[[np.ndarray], np.ndarray], int]:
    """``(act_stacked, n_stack)`` for an ``.onnx`` file (companion OnnxPolicy) or an SB3 ``.zip``."""
    if not path.is_file():
        raise UserError(f"policy file not found: {path}")
    if path.suffix == ".onnx":
        from companion.guidance.policy import OnnxPolicy, PolicySpec
        from companion.perception.scan import BIN_CONVENTION

        spec = PolicySpec(
            stack=n_stack,
            n_bins=N_BINS,
            max_range=float(env_config.scan.max_range),
            bin_convention=BIN_CONVENTION,
            max_speed=float(env_config.max_speed),
            max_yaw_rate=float(env_config.max_yaw_rate),
            max_sideways_speed=sideways_scale(env_config),
            layout=observation_layout(env_config),
        )
        try:
            policy = OnnxPolicy(path, spec)
        except UserError:
            raise
        except Exception as exc:
            raise UserError(f"{path}: cannot load the ONNX policy: {exc}") from None
        return policy.act, n_stack
    if path.suffix == ".zip":
        import torch

        from training.export import load_model

        torch.set_num_threads(1)  # one episode per process: more threads only contend for the cores
        model = load_model(path)
        frame = observation_layout(env_config).frame_size
        size = int(model.observation_space.shape[0])
        if size % frame:
            raise UserError(f"{path}: observation of {size} floats is not a stack of {frame}-float frames")
        return sb3_controller(model, size // frame, frame)._act, size // frame
    raise UserError(f"{path}: a policy is an .onnx or a stable-baselines3 .zip file")
