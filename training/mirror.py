"""The task's left-right symmetry: every demonstration mirrored across the nose is another one.

A world reflected across the vehicle's nose is a world of the same families, and the teacher's
label in it is its label here with the yaw rate turned the other way (the airframe, the lidar, the
firmware responses and the teacher's candidates are all symmetric). So each label is two: the fit
(:func:`training.pretrain.fit`) mirrors a random half of every batch. A student fitted afresh on
the 162k labels of a DAgger run (90 % of each iteration; the last 10 % held out) erred more on the
held-out labels than on its own, and the longer it fitted the more (action mean squared error
0.188 against 0.146 after 15 epochs, 0.215 against 0.092 after 45): it learns the worlds it saw
rather than how to fly, and a mirrored label is a world it did not see.

In a frame (:class:`companion.perception.observation.ObservationLayout`) the scan's bin ``i`` covers
``[i°, i+1°)`` counter-clockwise from the nose, so its mirror is bin ``n_bins - 1 - i``; what points
left (the goal's ``sin``, the left velocity, the left drift, the yaw-rate command, each mover's left
position and left velocity) changes sign; the rest stays. The movers stay in their slots: a
mirror leaves each one's distance as it is. This module imports numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.perception.observation import MOVER_SLOT_FEATURES, MOVER_SLOTS, ObservationLayout

#: a mirrored action: forward speed kept, yaw rate reversed
ACTION_SIGNS = np.array([1.0, -1.0], dtype=np.float32)
#: the same with a sideways speed (LidarNav-v0's ``sideways``), reversed too
SIDEWAYS_ACTION_SIGNS = np.array([1.0, -1.0, -1.0], dtype=np.float32)


@dataclass(frozen=True)
class Mirror:
    """How to mirror stacked observations (``obs[..., index] * signs``) and actions (``* action_signs``).
    Its methods take numpy arrays, or torch tensors when its own fields are torch tensors (the fit's).

    :param index: for each element of the mirrored observation, the element it comes from
    :param signs: ``+1`` or ``-1`` per element of the mirrored observation
    :param action_signs: per action element (:data:`ACTION_SIGNS`)
    """

    index: np.ndarray
    signs: np.ndarray
    action_signs: np.ndarray = field(default_factory=ACTION_SIGNS.copy)

    def observations(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` (``(..., n_stack × frame_size)``) mirrored across the nose."""
        return obs[..., self.index] * self.signs

    def actions(self, actions: np.ndarray) -> np.ndarray:
        """``actions`` (``(..., 2)``: forward, yaw rate; ``(..., 3)``: and sideways speed) mirrored
        across the nose."""
        return actions * self.action_signs


def mirror_for(layout: ObservationLayout, n_stack: int, sideways: bool = False) -> Mirror:
    """The mirror of ``n_stack`` stacked frames of ``layout``, and of actions with a sideways part
    when ``sideways``.

    :raises ValueError: ``n_stack`` < 1
    """
    if n_stack < 1:
        raise ValueError(f"n_stack must be at least 1, got {n_stack}")
    n, size = layout.n_bins, layout.frame_size
    frame_index = np.arange(size)
    frame_index[:n] = n - 1 - np.arange(n)
    frame_signs = np.ones(size, dtype=np.float32)
    parts = layout.slices()
    for part in ("goal_bearing", "velocity", "drift", "command"):
        if part in parts:  # the second of each pair points left (sin, left, left, yaw rate)
            frame_signs[parts[part].start + 1] = -1.0
    if "movers" in parts:  # each slot's left position and left velocity
        slots = frame_signs[parts["movers"]].reshape(MOVER_SLOTS, len(MOVER_SLOT_FEATURES))  # a view
        slots[:, [MOVER_SLOT_FEATURES.index("left"), MOVER_SLOT_FEATURES.index("velocity_left")]] = -1.0
    offsets = size * np.arange(n_stack)[:, None]
    return Mirror(
        index=(frame_index[None, :] + offsets).ravel(),
        signs=np.tile(frame_signs, n_stack),
        action_signs=(SIDEWAYS_ACTION_SIGNS if sideways else ACTION_SIGNS).copy(),
    )
