"""The layout of one observation frame, and the pure function that builds its goal/velocity part.

A frame is what the environment returns per step and what the companion pushes into its
:class:`~companion.perception.framestack.FrameStack`; the policy sees ``stack`` frames, oldest
first, the whole
frame stacked (SB3's ``VecFrameStack`` does the same in training). A frame's parts, in order (the
scan alone is a layout; drift, commands, firmware and movers each come on top of the goal part, any
subset):

* scan only (``LidarAvoid-v0``): ``[0, n_bins)`` the scan, normalised ranges in ``[0, 1]``;
* goal (``LidarNav-v0``): the scan, then :data:`GOAL_FEATURES` — the goal's bearing in the body
  frame as ``cos, sin`` (FLU: x forward, y left, so ``sin > 0`` = goal on the left), its horizontal
  distance ``/ goal_range`` clipped to ``[0, 1]``, and the measured body velocity
  ``forward, left / velocity_scale`` clipped to ``[-1, 1]``;
* goal with drift: the goal layout, then :data:`DRIFT_FEATURES` — the velocity estimate's error
  (reported minus true, body FLU) that :class:`companion.perception.drift.DriftEstimator` tracks from the
  scans, ``/ velocity_scale`` clipped to ``[-1, 1]``. The autopilot flies its estimate, so a policy
  that cannot see the error cannot see the drift it causes;
* goal with commands: then :data:`COMMAND_FEATURES` — the last command sent to the autopilot (after
  the shield), forward ``/ velocity_scale`` and yaw rate ``/ yaw_rate_scale``, clipped to
  ``[-1, 1]``. A real autopilot answers a command late and slowly, so what the vehicle does next
  depends on the commands still in flight, which the measured velocity does not show yet;
* goal with firmware: then :data:`FIRMWARE_FEATURES` — 1.0 when the autopilot is ArduPilot, 0.0
  when it is PX4 (the companion's ``autopilot.type``; in simulation, the structure of the drawn
  response). ArduPilot shapes a velocity setpoint (jerk- and acceleration-limited) before it flies
  it, PX4's offboard mode does not, so the same command stops sooner on one than on the other;
* goal with movers: last, :data:`MOVER_FEATURES` — the :data:`MOVER_SLOTS` (3) nearest moving
  objects the tracker reports (:meth:`companion.perception.tracking.TrackerOutput.movers`), nearest
  surface first (centre distance less radius), each as :data:`MOVER_SLOT_FEATURES`: its centre
  (forward, left) ``/`` :data:`MOVER_RANGE` (10 m, the scan's range) clipped to ``[-1, 1]``, its ground
  velocity in the body axes (forward, left) ``/`` :data:`MOVER_SPEED` (3 m/s, the fastest drone of
  the dynamic worlds) clipped to ``[-1, 1]``, its radius ``/`` :data:`MOVER_RADIUS` (1 m; the tracker
  tracks nothing wider than 1.6 m) clipped to ``[0, 1]``, and 1.0 for a mover present. A slot no
  mover fills is six zeros. In the scan a walker is a return like a wall's: only the tracks say
  that it moves, where, and how fast.

:attr:`ObservationLayout.name` spells a layout out (sizes and scales included); the training export
writes it into the ONNX metadata and the companion refuses a model whose name differs from its own.
This module imports numpy only: the companion uses it in flight.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the type only: the tracker (scipy) is not imported with the layout
    from companion.perception.tracking import Mover

#: the goal/velocity features after the scan, in order
GOAL_FEATURES = ("goal_cos", "goal_sin", "goal_distance", "velocity_forward", "velocity_left")
#: the drift features after the goal features (``drift`` layouts), in order
DRIFT_FEATURES = ("drift_forward", "drift_left")
#: the last command sent, after the goal (and drift) features (``command`` layouts), in order
COMMAND_FEATURES = ("command_forward", "command_yaw_rate")
#: the autopilot's firmware, last in the frame (``firmware`` layouts)
FIRMWARE_FEATURES = ("firmware_ardupilot",)
#: movers in a frame (``movers`` layouts), nearest first
MOVER_SLOTS = 3
#: one mover slot's features, in order
MOVER_SLOT_FEATURES = ("forward", "left", "velocity_forward", "velocity_left", "radius", "present")
#: the movers' features, last in the frame (``movers`` layouts), slot by slot
MOVER_FEATURES = tuple(f"mover{k}_{name}" for k in range(MOVER_SLOTS) for name in MOVER_SLOT_FEATURES)
#: metres a mover's position feature of 1.0 stands for (the scan's default range)
MOVER_RANGE = 10.0
#: m/s a mover's velocity feature of 1.0 stands for (the dynamic worlds' fastest drone)
MOVER_SPEED = 3.0
#: metres a mover's radius feature of 1.0 stands for (the tracker's widest object is 1.6 m across)
MOVER_RADIUS = 1.0


@dataclass(frozen=True)
class ObservationLayout:
    """One observation frame: ``n_bins`` scan values, then (``goal``) the :data:`GOAL_FEATURES`,
    then (``drift``) the :data:`DRIFT_FEATURES`, then (``command``) the :data:`COMMAND_FEATURES`,
    then (``firmware``) the :data:`FIRMWARE_FEATURES`, then (``movers``) the :data:`MOVER_FEATURES`.

    :param n_bins: scan bins
    :param goal: the frame carries the goal and the measured velocity
    :param drift: the frame also carries the drift estimate (a goal layout only)
    :param goal_range: metres a distance feature of 1.0 stands for (farther goals read 1.0)
    :param velocity_scale: m/s a velocity feature of 1.0 stands for (the env's ``max_speed``)
    :param command: the frame also carries the last command sent (a goal layout only)
    :param yaw_rate_scale: rad/s a yaw-rate command feature of 1.0 stands for (``max_yaw_rate``)
    :param firmware: the frame also says which firmware flies the setpoints (a goal layout only)
    :param movers: the frame also carries the nearest tracked movers (a goal layout only)
    """

    n_bins: int = 360
    goal: bool = False
    goal_range: float = 10.0
    velocity_scale: float = 2.0
    drift: bool = False
    command: bool = False
    yaw_rate_scale: float = 1.5
    firmware: bool = False
    movers: bool = False

    def __post_init__(self) -> None:
        scales = (self.goal_range, self.velocity_scale, self.yaw_rate_scale)
        if self.n_bins < 1 or not all(scale > 0.0 for scale in scales):
            raise ValueError(f"invalid observation layout {self}")
        for part in ("drift", "command", "firmware", "movers"):
            if getattr(self, part) and not self.goal:
                raise ValueError(f"the {part} features come after the goal features: {part} needs goal")

    @property
    def frame_size(self) -> int:
        """Floats per frame."""
        return self.n_bins + sum(len(names) for _, names in self._parts())

    def _parts(self) -> list[tuple[str, tuple[str, ...]]]:
        """The feature groups after the scan this layout has, in frame order, by name."""
        groups = (
            ("goal", GOAL_FEATURES),
            ("drift", DRIFT_FEATURES),
            ("command", COMMAND_FEATURES),
            ("firmware", FIRMWARE_FEATURES),
            ("movers", MOVER_FEATURES),
        )
        return [(part, names) for part, names in groups if getattr(self, part)]

    @property
    def name(self) -> str:
        """The layout spelled out, e.g. ``scan360`` or
        ``scan360+goal(cos,sin,distance/10m)+velocity(forward,left/2m/s)[+drift(forward,left/2m/s)]``
        ``[+command(forward/2m/s,yaw/1.5rad/s)][+firmware(ardupilot=1,px4=0)]``
        ``[+movers(3x(forward,left/10m,velocity/3m/s,radius/1m,present))]``."""
        scan = f"scan{self.n_bins}"
        if not self.goal:
            return scan
        drift = f"+drift(forward,left/{self.velocity_scale:g}m/s)" if self.drift else ""
        command = (
            f"+command(forward/{self.velocity_scale:g}m/s,yaw/{self.yaw_rate_scale:g}rad/s)"
            if self.command
            else ""
        )
        firmware = "+firmware(ardupilot=1,px4=0)" if self.firmware else ""
        movers = (
            f"+movers({MOVER_SLOTS}x(forward,left/{MOVER_RANGE:g}m,velocity/{MOVER_SPEED:g}m/s,"
            f"radius/{MOVER_RADIUS:g}m,present))"
            if self.movers
            else ""
        )
        return (
            f"{scan}+goal(cos,sin,distance/{self.goal_range:g}m)"
            f"+velocity(forward,left/{self.velocity_scale:g}m/s){drift}{command}{firmware}{movers}"
        )

    def slices(self) -> dict[str, slice]:
        """Index ranges of each part of a frame (add ``k * frame_size`` for frame ``k`` of a stack)."""
        parts = {"scan": slice(0, self.n_bins)}
        if self.goal:
            n = self.n_bins
            parts |= {"goal_bearing": slice(n, n + 2), "goal_distance": slice(n + 2, n + 3)}
            parts["velocity"] = slice(n + 3, n + 5)
        start = self.n_bins + len(GOAL_FEATURES)
        for part, names in self._parts()[1:]:
            parts[part] = slice(start, start + len(names))
            start += len(names)
        return parts

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` per frame element, float32 (a Gymnasium ``Box``'s bounds)."""
        low = np.zeros(self.frame_size, dtype=np.float32)
        high = np.ones(self.frame_size, dtype=np.float32)
        if self.goal:
            low[self.n_bins : self.n_bins + 2] = -1.0  # bearing cos, sin
            low[self.n_bins + 3 :] = -1.0  # velocity (and drift, command)
        if self.firmware:
            low[self.slices()["firmware"]] = 0.0
        if self.movers:  # per slot: position and velocity in [-1, 1], radius and presence in [0, 1]
            slot_low = np.array([-1.0, -1.0, -1.0, -1.0, 0.0, 0.0], dtype=np.float32)
            low[self.slices()["movers"]] = np.tile(slot_low, MOVER_SLOTS)
        return low, high


def goal_in_body(dx: float, dy: float, yaw: float) -> tuple[float, float]:
    """A horizontal offset (x, y) in a frame whose ``yaw`` runs counter-clockwise from +x (ENU), as
    ``(forward, left)`` metres in the body frame (FLU)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return c * dx + s * dy, -s * dx + c * dy


def goal_features(
    goal_forward: float,
    goal_left: float,
    velocity_forward: float,
    velocity_left: float,
    layout: ObservationLayout,
) -> np.ndarray:
    """The :data:`GOAL_FEATURES` of a frame (float32), scaled and clipped as ``layout`` says.

    :param goal_forward: the goal ahead of the vehicle, metres (body frame, FLU)
    :param goal_left: the goal to the left of the vehicle, metres
    :param velocity_forward: measured body velocity along the nose, m/s
    :param velocity_left: measured body velocity to the left, m/s
    :param layout: a goal layout
    :raises ValueError: a non-finite input (a false picture must not reach the policy) or a
        scan-only layout
    """
    if not layout.goal:
        raise ValueError(f"layout {layout.name} has no goal features")
    values = (goal_forward, goal_left, velocity_forward, velocity_left)
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"goal/velocity inputs must be finite, got {values}")
    distance = math.hypot(goal_forward, goal_left)
    cos, sin = (goal_forward / distance, goal_left / distance) if distance > 1e-9 else (1.0, 0.0)
    scale = layout.velocity_scale
    return np.array(
        [
            cos,
            sin,
            min(distance / layout.goal_range, 1.0),
            min(max(velocity_forward / scale, -1.0), 1.0),
            min(max(velocity_left / scale, -1.0), 1.0),
        ],
        dtype=np.float32,
    )


def drift_features(bias: np.ndarray, layout: ObservationLayout) -> np.ndarray:
    """The :data:`DRIFT_FEATURES` of a frame (float32): the drift estimate (forward, left m/s, body
    FLU) ``/ velocity_scale``, clipped to ``[-1, 1]``.

    :raises ValueError: a non-finite estimate or a layout without drift
    """
    if not layout.drift:
        raise ValueError(f"layout {layout.name} has no drift features")
    bias = np.asarray(bias, dtype=np.float64).reshape(-1)
    if bias.shape != (2,) or not np.isfinite(bias).all():
        raise ValueError(f"the drift estimate must be 2 finite values, got {bias}")
    return np.clip(bias / layout.velocity_scale, -1.0, 1.0).astype(np.float32)


def command_features(forward: float, yaw_rate: float, layout: ObservationLayout) -> np.ndarray:
    """The :data:`COMMAND_FEATURES` of a frame (float32): the last command sent, forward m/s
    ``/ velocity_scale`` and yaw rate rad/s ``/ yaw_rate_scale``, clipped to ``[-1, 1]``.

    :raises ValueError: a non-finite command or a layout without command features
    """
    if not layout.command:
        raise ValueError(f"layout {layout.name} has no command features")
    if not (math.isfinite(forward) and math.isfinite(yaw_rate)):
        raise ValueError(f"the last command must be finite, got {(forward, yaw_rate)}")
    values = (forward / layout.velocity_scale, yaw_rate / layout.yaw_rate_scale)
    return np.clip(np.array(values, dtype=np.float32), -1.0, 1.0)


def firmware_features(ardupilot: bool, layout: ObservationLayout) -> np.ndarray:
    """The :data:`FIRMWARE_FEATURES` of a frame (float32): 1.0 for ArduPilot, 0.0 for PX4.

    :raises ValueError: a layout without the firmware feature
    """
    if not layout.firmware:
        raise ValueError(f"layout {layout.name} has no firmware feature")
    return np.array([1.0 if ardupilot else 0.0], dtype=np.float32)


def mover_features(movers: Sequence[Mover], layout: ObservationLayout) -> np.ndarray:
    """The :data:`MOVER_FEATURES` of a frame (float32): the :data:`MOVER_SLOTS` movers whose surface
    is nearest (centre distance less radius; of equals, the first given), nearest first, each scaled
    and clipped as the module says; slots no mover fills are zeros, their presence 0.

    :param movers: the tracker's movers in the body axes at the scan's time
        (:meth:`companion.perception.tracking.TrackerOutput.movers`)
    :param layout: a movers layout
    :raises ValueError: a non-finite mover (a false picture must not reach the policy) or a layout
        without movers
    """
    if not layout.movers:
        raise ValueError(f"layout {layout.name} has no mover features")
    rows = []
    for mover in movers:
        row = (*mover.position, *mover.velocity, mover.radius)
        if len(row) != 5 or not all(math.isfinite(v) for v in row):
            raise ValueError(f"a mover's position, velocity and radius must be finite, got {mover}")
        rows.append(row)
    rows.sort(key=lambda r: math.hypot(r[0], r[1]) - r[4])  # stable: equals keep their order
    out = np.zeros((MOVER_SLOTS, len(MOVER_SLOT_FEATURES)), dtype=np.float32)
    for slot, (forward, left, v_forward, v_left, radius) in enumerate(rows[:MOVER_SLOTS]):
        position = np.clip(np.array([forward, left]) / MOVER_RANGE, -1.0, 1.0)
        velocity = np.clip(np.array([v_forward, v_left]) / MOVER_SPEED, -1.0, 1.0)
        out[slot] = (*position, *velocity, min(max(radius / MOVER_RADIUS, 0.0), 1.0), 1.0)
    return out.reshape(-1)


def build_frame(scan: np.ndarray, features: np.ndarray | None, layout: ObservationLayout) -> np.ndarray:
    """One frame: the scan, then ``features`` (from :func:`goal_features`; None for scan only).

    :raises ValueError: sizes that do not match ``layout``
    """
    scan = np.asarray(scan, dtype=np.float32).reshape(-1)
    extra = np.zeros(0, np.float32) if features is None else np.asarray(features, np.float32).reshape(-1)
    if scan.size != layout.n_bins or scan.size + extra.size != layout.frame_size:
        got = f"{scan.size} scan + {extra.size} features"
        raise ValueError(f"a {layout.name} frame is {layout.frame_size} floats, got {got}")
    return np.concatenate([scan, extra])
