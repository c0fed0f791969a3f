"""Attacks on the gated shield in worlds with movers, the movers taken from the simulator's truth
or from the env's scan tracker.

LidarNav-v0 runs unshielded; :func:`fly` applies the shield in the loop, as the companion does,
with the movers and their scan bins from the simulator, or from the tracker as in flight. What it
measures is passive safety: contacts with a mover while the vehicle moves faster than the creep a
stop leaves, apart from those at rest.
``tests/training/test_shield_movers.py`` and ``bench/bench_shield_movers.py`` fly it.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from companion.perception.scan import N_BINS
from companion.perception.tracking import Mover
from companion.safety.shield import SafetyShield, ShieldConfig, command_from_action
from flightsim.envs.env import CONTROL_HZ
from training.attackers import make_attacker
from training.episodes import NAV_ENV_ID, WorldSpec, episode_seed

#: the attackers :func:`fly` knows: :data:`training.attackers.ATTACKERS`' ram and dash, and :class:`MoverRam`
MOVER_ATTACKERS = ("ram", "dash", "mover_ram")
#: where :func:`fly`'s shield learns what moves
MoverSource = Literal["truth", "tracker", "none"]
#: a return this close to a mover's surface is the mover's, m (the lidar's mount error, its noise)
ON_A_MOVER = 0.2
_BEARING = np.radians(np.arange(N_BINS) + 0.5)


def truth_movers(env: Any) -> list[Mover]:
    """Every moving obstacle as the tracker would give it: centre, ground velocity and footprint
    radius, in the body axes now."""
    sim = env.unwrapped
    t, position, yaw = sim.sim_time, sim.true_state.position, sim.shield_heading()
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for obstacle in sim.world.moving:
        centre = obstacle.positions(t)[0]
        velocity = (obstacle.positions(t + 1e-3)[0] - centre) / 1e-3
        d = centre - position[:2]
        out.append(
            Mover(
                (c * d[0] + s * d[1], -s * d[0] + c * d[1]),
                (c * velocity[0] + s * velocity[1], -s * velocity[0] + c * velocity[1]),
                obstacle.footprint_radius,
            )
        )
    return out


def truth_moving_bins(env: Any, scan: np.ndarray) -> np.ndarray:
    """``(360,)`` the bins whose return lies on a moving obstacle now."""
    sim = env.unwrapped
    ranges = np.asarray(scan[:N_BINS], dtype=np.float64) * sim.config.scan.max_range
    position, angle = sim.true_state.position, sim.shield_heading() + _BEARING
    points = np.stack(
        [
            position[0] + ranges * np.cos(angle),
            position[1] + ranges * np.sin(angle),
            np.full(N_BINS, position[2]),
        ],
        axis=1,
    )
    hit = scan[:N_BINS] < 1.0
    out = np.zeros(N_BINS, dtype=bool)
    for obstacle in sim.world.moving:
        out |= hit & (obstacle.clearance(points, sim.sim_time) < ON_A_MOVER)
    return out


class MoverRam:
    """Straight at the nearest mover, at full speed, turning the nose onto it: what a ram at the
    nearest return (:class:`training.attackers.RamAttacker`) does when a walker is the target. It
    reads the simulator's truth.

    :param env: the env it flies (a world with movers)
    """

    def __init__(self, env: Any) -> None:
        self._env = env

    def reset(self, scan: np.ndarray) -> np.ndarray:
        return self.act(scan)

    def act(self, scan: np.ndarray) -> np.ndarray:
        nearest = min(truth_movers(self._env), key=lambda m: math.hypot(*m.position))
        bearing = math.atan2(nearest.position[1], nearest.position[0])
        return np.array(
            [math.cos(bearing), float(np.clip(2.0 * bearing, -1.0, 1.0)), math.sin(bearing)], np.float32
        )


@dataclass
class Flight:
    """One episode.

    :param creep: the speed a stop may leave (the envelope's estimate error), m/s
    :param contacts: the vehicle's true speed at each contact with a mover, m/s
    :param moving_gap: the least gap between the vehicle and a mover's surface while the vehicle
        moved faster than the creep, m (negative: they touched)
    :param static_gap: the least gap to the static world, m
    :param interventions: the shield's counters
    """

    creep: float
    contacts: list[float] = field(default_factory=list)
    moving_gap: float = math.inf
    static_gap: float = math.inf
    interventions: Counter[str] = field(default_factory=Counter)

    @property
    def while_moving(self) -> list[float]:
        """The contacts while the vehicle moved faster than the creep."""
        return [v for v in self.contacts if v > self.creep]


def fly(
    env: Any, world: WorldSpec, attacker: str, movers: MoverSource, config: ShieldConfig | None = None
) -> Flight:
    """``attacker`` (one of :data:`MOVER_ATTACKERS`) on ``world`` until the episode ends, the shield
    between it and the autopilot; ``movers``: where the shield's movers and their bins come from:
    the simulator's truth, the env's tracker (as in flight:
    :meth:`~flightsim.envs.nav_env.LidarNavEnv.shield_movers`), or nowhere (the shield called as
    before movers existed).

    :param env: an unshielded LidarNav-v0 with ``sideways`` (three-part actions)
    :param config: the shield's (default: the gate on, the rest as shipped)
    """
    sim = env.unwrapped
    limits = config if config is not None else ShieldConfig(backup_gate=True)
    config = sim.config
    seed = episode_seed(world, 0, NAV_ENV_ID)
    obs, _ = env.reset(seed=seed, options=world.reset_options())
    shield = SafetyShield(limits, float(config.scan.max_range), config.autopilot_response)
    controller = MoverRam(env) if attacker == "mover_ram" else make_attacker(attacker, seed, 3)
    action = controller.reset(obs)
    flight = Flight(shield.envelope.estimate_error)
    for _ in range(config.max_steps):
        scan = obs[:N_BINS]
        velocity = sim.shield_velocity()
        tracked = (
            {"moving_bins": truth_moving_bins(env, scan), "movers": truth_movers(env)}
            if movers == "truth"
            else sim.shield_movers() if movers == "tracker" else {}
        )
        safe = shield.filter(
            command_from_action(action, config.max_speed, config.max_yaw_rate, config.max_sideways_speed),
            scan, 1.0 / CONTROL_HZ, (float(velocity[0]), float(velocity[1])), sim.shield_drift(),
            sim.shield_heading(), **tracked,
        )  # fmt: skip
        sim.command_lateral(safe.lateral)
        obs, _, terminated, truncated, info = env.step(
            np.array([safe.forward / config.max_speed, safe.yaw_rate / config.max_yaw_rate, 0.0], np.float32)
        )
        position, speed = sim.true_state.position, float(np.hypot(*sim.true_state.velocity[:2]))
        gap = min(float(m.clearance(position[None], sim.sim_time)[0]) for m in sim.world.moving)
        gap -= config.vehicle_radius
        if speed > flight.creep:
            flight.moving_gap = min(flight.moving_gap, gap)
        flight.static_gap = min(flight.static_gap, sim.world.clearance(position) - config.vehicle_radius)
        if info["collision"] and gap < 0.0:
            flight.contacts.append(speed)
        if terminated or truncated:
            break
        action = controller.act(obs)
    flight.interventions = shield.interventions
    return flight
