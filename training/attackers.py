"""Controllers that want to crash: what the shield is attacked with.

The shipped policy avoids obstacles by itself, so flying it rarely tests the shield. These do not:
each reads only the scan (as a policy would) and steers into what it sees. Flown behind the shield
(``avoid-train evaluate --baselines ram,dash,held_random --shield``), a collision is the shield's.

Each turns a frame (its first 360 values the normalised scan) into an action in ``[-1, 1]`` of the
env's action size: 2 (forward, yaw) or 3 (forward, yaw, left).

:class:`ReplayAttacker` is the odd one: blind, it replays a sequence of actions found beforehand by
flying candidates on one world and seed (:mod:`training.attack_search`). It is not among
:data:`ATTACKERS`, which fly without a sequence; :data:`REPLAY` names it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from companion.perception.scan import N_BINS

#: the attackers by name
ATTACKERS = ("ram", "dash", "held_random")
#: the sequence replayer's name (:class:`ReplayAttacker`), for a ``ControllerSpec`` carrying ``actions``
REPLAY = "replay"


class RamAttacker:
    """Straight at the nearest return, at full speed: sideways too when the action has a sideways
    part, else forward while turning the nose onto it.

    :param action_size: 2 or 3
    """

    def __init__(self, action_size: int) -> None:
        self._size = action_size

    def reset(self, scan: np.ndarray) -> np.ndarray:
        return self.act(scan)

    def act(self, scan: np.ndarray) -> np.ndarray:
        ranges = np.asarray(scan, dtype=np.float64)[:N_BINS]
        bearing = math.radians(int(np.argmin(ranges)) + 0.5)
        turn = float(np.clip(math.atan2(math.sin(bearing), math.cos(bearing)) * 2.0, -1.0, 1.0))
        if self._size == 3:
            return np.array([math.cos(bearing), turn, math.sin(bearing)], dtype=np.float32)
        return np.array([1.0, turn], dtype=np.float32)


class _Held:
    """An action drawn afresh every 0.5-2 s and held in between (10 steps a second)."""

    def __init__(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._left = 0
        self._action = np.zeros(2, dtype=np.float32)

    def reset(self, scan: np.ndarray) -> np.ndarray:
        self._left = 0
        return self.act(scan)

    def act(self, scan: np.ndarray) -> np.ndarray:
        if self._left <= 0:
            self._action = self._draw()
            self._left = int(self._rng.integers(5, 21))
        self._left -= 1
        return self._action

    def _draw(self) -> np.ndarray:
        raise NotImplementedError


class DashAttacker(_Held):
    """Full speed forward with a random yaw rate, each held 0.5-2 s.

    :param seed: the episode's seed
    :param action_size: 2 or 3 (the sideways part full to a random side)
    """

    def __init__(self, seed: int, action_size: int) -> None:
        super().__init__(seed)
        self._size = action_size

    def _draw(self) -> np.ndarray:
        yaw = float(self._rng.uniform(-1.0, 1.0))
        side = [float(self._rng.choice([-1.0, 0.0, 1.0]))] if self._size == 3 else []
        return np.array([1.0, yaw, *side], dtype=np.float32)


class HeldRandomAttacker(_Held):
    """Uniform random actions, each held 0.5-2 s.

    :param seed: the episode's seed
    :param action_size: 2 or 3
    """

    def __init__(self, seed: int, action_size: int) -> None:
        super().__init__(seed)
        self._size = action_size

    def _draw(self) -> np.ndarray:
        return self._rng.uniform(-1.0, 1.0, self._size).astype(np.float32)


class ReplayAttacker:
    """A fixed action per step, whatever the scans show: an open-loop sequence, so that a search
    over sequences (:mod:`training.attack_search`) scores each candidate by flying exactly it.
    Past its end it holds its last action (keeps pushing where it was going).

    :param actions: one action per step, the first for the reset; each of ``action_size`` values,
        clipped to ``[-1, 1]``
    :param action_size: 2 or 3
    """

    def __init__(self, actions: Sequence[Sequence[float]], action_size: int) -> None:
        steps = np.asarray(actions, dtype=np.float32).reshape(-1, action_size)
        self._actions = np.clip(steps, -1.0, 1.0) if len(steps) else np.zeros((1, action_size), np.float32)
        self._step = 0

    def reset(self, scan: np.ndarray) -> np.ndarray:
        self._step = 0
        return self.act(scan)

    def act(self, scan: np.ndarray) -> np.ndarray:
        action = self._actions[min(self._step, len(self._actions) - 1)]
        self._step += 1
        return action.copy()


def make_attacker(kind: str, seed: int, action_size: int) -> RamAttacker | DashAttacker | HeldRandomAttacker:
    """The attacker ``kind`` names (one of :data:`ATTACKERS`)."""
    if kind == "ram":
        return RamAttacker(action_size)
    if kind == "dash":
        return DashAttacker(seed, action_size)
    if kind == "held_random":
        return HeldRandomAttacker(seed, action_size)
    raise ValueError(f"unknown attacker {kind!r}; known: {', '.join(ATTACKERS)}")
