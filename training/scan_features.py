"""A features extractor that reads the stacked scans as a ring: 1-D convolutions with circular
padding, so an obstacle looks the same to the network at every bearing.

A flat MLP over 4 × 360 scan bins must learn each bearing's obstacle on its own, from the few
labels near obstacles a DAgger run collects there; a convolution shares what it learns across
bearings, and the padding wraps bin 359 onto bin 0 as the lidar does. The frame's other features
(goal, velocity, drift, command) pass through unchanged beside the convolution's output, and the
policy's MLP (``net_arch``) reads both. The layers are plain ``Conv1d`` over a padding built from
slices, which the ONNX export writes as it writes the MLP.

With movers in the frame, a :class:`MoverRing` draws where each tracked mover will be, at a few
times ahead, into rings of the scan's bins, and the convolution reads them as channels beside the
scans. Six numbers per mover at the end of a frame are a small, easily ignored part of an MLP's
input (a student trained on them flew the same with them zeroed); drawn as a scan, a walker about
to cross the way blocks the same bins a wall there would.
"""

from __future__ import annotations

import gymnasium as gym
import torch
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from companion.perception.observation import (
    MOVER_RADIUS,
    MOVER_RANGE,
    MOVER_SLOT_FEATURES,
    MOVER_SLOTS,
    MOVER_SPEED,
)
from companion.perception.scan import N_BINS

#: (output channels, kernel size, stride) of each convolution: 360 bins become 30 of 16 channels,
#: and a training step costs about what the flat MLP's does
DEFAULT_LAYERS: tuple[tuple[int, int, int], ...] = ((8, 5, 3), (16, 5, 2), (16, 5, 2))


class CircularConv1d(nn.Module):
    """``Conv1d`` over a ring of bins: the input wraps around by half the kernel on each side.

    :param in_channels: input channels
    :param out_channels: output channels
    :param kernel_size: an odd kernel size
    :param stride: the stride (the output has ``ceil(bins / stride)`` bins)
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int) -> None:
        super().__init__()
        if kernel_size % 2 != 1:
            raise ValueError(f"kernel_size {kernel_size}: must be odd")
        self.pad = kernel_size // 2
        self.conv = nn.Conv1d(in_channels, out_channels, kernel_size, stride=stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.pad
        return self.conv(torch.cat([x[..., -p:], x, x[..., :p]], dim=-1) if p else x)


class MoverRing(nn.Module):
    """The tracked movers drawn as scans: per prediction time, each bin holds the range to the
    nearest mover surface there (constant velocity from its track) ``/``
    :data:`~companion.perception.observation.MOVER_RANGE`, as a scan bin holds a return's, and 1.0
    where no mover is.

    A mover covers the bins whose centre bearing lies within ``asin(radius / distance)`` of its
    centre's (all bins within 90 degrees, once the vehicle would be inside it).

    :param times: seconds ahead of the frame, one ring each
    :param n_bins: bins of a ring, bin ``i`` centred ``i + 0.5`` bin widths counter-clockwise from
        the nose, as the scan's (:mod:`companion.perception.scan`)
    """

    def __init__(self, times: tuple[float, ...], n_bins: int = N_BINS) -> None:
        super().__init__()
        if not times or min(times) < 0.0:
            raise ValueError(f"mover ring times {times}: need at least one, none negative")
        bearing = (torch.arange(n_bins, dtype=torch.float32) + 0.5) * (2.0 * torch.pi / n_bins)
        self.register_buffer("directions", torch.stack([torch.cos(bearing), torch.sin(bearing)], dim=1))
        self.register_buffer("times", torch.tensor(times, dtype=torch.float32).view(1, -1, 1, 1))

    def forward(self, movers: torch.Tensor) -> torch.Tensor:
        """One frame's :data:`~companion.perception.observation.MOVER_FEATURES`, ``(B, 18)``, as
        rings ``(B, len(times), n_bins)``."""
        slots = movers.reshape(-1, MOVER_SLOTS, len(MOVER_SLOT_FEATURES))
        position, velocity = slots[..., 0:2] * MOVER_RANGE, slots[..., 2:4] * MOVER_SPEED
        radius, present = slots[..., 4] * MOVER_RADIUS, slots[..., 5] > 0.5
        centre = position[:, None] + velocity[:, None] * self.times  # (B, times, slots, 2)
        distance = torch.sqrt((centre * centre).sum(dim=-1)).clamp_min(1e-3)
        radius = radius[:, None].expand_as(distance)
        cos_off_centre = (centre @ self.directions.T) / distance[..., None]  # (B, times, slots, bins)
        sin_half = torch.clamp(radius / distance, max=1.0)
        cos_half = torch.sqrt(1.0 - sin_half * sin_half)
        covered = (cos_off_centre >= cos_half[..., None]) & present[:, None, :, None]
        surface = torch.clamp((distance - radius) / MOVER_RANGE, 0.0, 1.0)
        ring = torch.where(covered, surface[..., None], torch.ones_like(cos_off_centre))
        return ring.amin(dim=2)


class CircularScanExtractor(BaseFeaturesExtractor):
    """Circular convolutions over the scans of ``n_stack`` frames, the other features beside them.

    The observation is ``n_stack`` frames side by side (SB3's ``VecFrameStack``, oldest first); each
    frame starts with ``n_bins`` scan values
    (:class:`companion.perception.observation.ObservationLayout`). The
    frames' scans are the convolution's input channels, then (``movers_at``) the newest frame's
    :class:`MoverRing`.

    :param observation_space: a flat Box of ``n_stack`` × frame floats
    :param n_stack: frames per observation
    :param n_bins: scan bins at the start of each frame
    :param layers: (output channels, kernel size, stride) of each convolution
    :param movers_at: where a frame's :data:`~companion.perception.observation.MOVER_FEATURES`
        start; ``None``: no mover ring
    :param mover_times: the mover ring's prediction times, seconds
    """

    def __init__(
        self,
        observation_space: gym.spaces.Box,
        n_stack: int,
        n_bins: int = N_BINS,
        layers: tuple[tuple[int, int, int], ...] = DEFAULT_LAYERS,
        movers_at: int | None = None,
        mover_times: tuple[float, ...] = (0.0, 0.5, 1.0, 1.5, 2.0),
    ) -> None:
        size = int(observation_space.shape[0])
        if len(observation_space.shape) != 1 or size % n_stack or size // n_stack < n_bins:
            shape = observation_space.shape
            raise ValueError(f"observation shape {shape}: not {n_stack} frames of at least {n_bins} floats")
        frame = size // n_stack
        n_movers = MOVER_SLOTS * len(MOVER_SLOT_FEATURES)
        if movers_at is not None and not n_bins <= movers_at <= frame - n_movers:
            fits = f"{n_movers} mover features do not fit a {frame}-float frame"
            raise ValueError(f"movers_at {movers_at}: {fits}")
        ring = None if movers_at is None else MoverRing(tuple(mover_times), n_bins)
        convs: list[nn.Module] = []
        channels, bins = n_stack + (0 if ring is None else len(mover_times)), n_bins
        for out_channels, kernel_size, stride in layers:
            convs += [CircularConv1d(channels, out_channels, kernel_size, stride), nn.ReLU()]
            channels, bins = out_channels, -(-bins // stride)
        super().__init__(observation_space, channels * bins + n_stack * (frame - n_bins))
        self.n_stack, self.n_bins, self.frame = n_stack, n_bins, frame
        self.movers = None if movers_at is None else slice(movers_at, movers_at + n_movers)
        self.ring = ring
        self.convs = nn.Sequential(*convs, nn.Flatten())

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        frames = observations.reshape(-1, self.n_stack, self.frame)
        channels = frames[..., : self.n_bins]
        if self.ring is not None:
            channels = torch.cat([channels, self.ring(frames[:, -1, self.movers])], dim=1)
        return torch.cat([self.convs(channels), frames[..., self.n_bins :].flatten(1)], dim=1)
