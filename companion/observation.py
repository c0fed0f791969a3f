"""The layout of one observation frame, and the pure function that builds its goal/velocity part.

A frame is what the environment returns per step and what the companion pushes into its
:class:`~companion.framestack.FrameStack`; the policy sees ``stack`` frames, oldest first, the whole
frame stacked (SB3's ``VecFrameStack`` does the same in training). Two layouts exist:

* scan only (``LidarAvoid-v0``): ``[0, n_bins)`` the scan, normalised ranges in ``[0, 1]``;
* goal (``LidarNav-v0``): the scan, then :data:`GOAL_FEATURES` — the goal's bearing in the body
  frame as ``cos, sin`` (FLU: x forward, y left, so ``sin > 0`` = goal on the left), its horizontal
  distance ``/ goal_range`` clipped to ``[0, 1]``, and the measured body velocity
  ``forward, left / velocity_scale`` clipped to ``[-1, 1]``.

:attr:`ObservationLayout.name` spells a layout out (sizes and scales included); the training export
writes it into the ONNX metadata and the companion refuses a model whose name differs from its own.
This module imports numpy only: the companion uses it in flight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: the goal/velocity features after the scan, in order
GOAL_FEATURES = ("goal_cos", "goal_sin", "goal_distance", "velocity_forward", "velocity_left")


@dataclass(frozen=True)
class ObservationLayout:
    """One observation frame: ``n_bins`` scan values, then (``goal``) the :data:`GOAL_FEATURES`.

    :param n_bins: scan bins
    :param goal: the frame carries the goal and the measured velocity
    :param goal_range: metres a distance feature of 1.0 stands for (farther goals read 1.0)
    :param velocity_scale: m/s a velocity feature of 1.0 stands for (the env's ``max_speed``)
    """

    n_bins: int = 360
    goal: bool = False
    goal_range: float = 10.0
    velocity_scale: float = 2.0

    def __post_init__(self) -> None:
        if self.n_bins < 1 or not self.goal_range > 0.0 or not self.velocity_scale > 0.0:
            raise ValueError(f"invalid observation layout {self}")

    @property
    def frame_size(self) -> int:
        """Floats per frame."""
        return self.n_bins + (len(GOAL_FEATURES) if self.goal else 0)

    @property
    def name(self) -> str:
        """The layout spelled out, e.g. ``scan360`` or
        ``scan360+goal(cos,sin,distance/10m)+velocity(forward,left/2m/s)``."""
        scan = f"scan{self.n_bins}"
        if not self.goal:
            return scan
        return (
            f"{scan}+goal(cos,sin,distance/{self.goal_range:g}m)"
            f"+velocity(forward,left/{self.velocity_scale:g}m/s)"
        )

    def slices(self) -> dict[str, slice]:
        """Index ranges of each part of a frame (add ``k * frame_size`` for frame ``k`` of a stack)."""
        parts = {"scan": slice(0, self.n_bins)}
        if self.goal:
            n = self.n_bins
            parts |= {"goal_bearing": slice(n, n + 2), "goal_distance": slice(n + 2, n + 3)}
            parts["velocity"] = slice(n + 3, n + 5)
        return parts

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` per frame element, float32 (a Gymnasium ``Box``'s bounds)."""
        low = np.zeros(self.frame_size, dtype=np.float32)
        high = np.ones(self.frame_size, dtype=np.float32)
        if self.goal:
            low[self.n_bins : self.n_bins + 2] = -1.0  # bearing cos, sin
            low[self.n_bins + 3 :] = -1.0  # velocity
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
