"""A features extractor that reads the stacked scans as a ring: 1-D convolutions with circular
padding, so an obstacle looks the same to the network at every bearing.

A flat MLP over 4 × 360 scan bins must learn each bearing's obstacle on its own, from the few
labels near obstacles a DAgger run collects there; a convolution shares what it learns across
bearings, and the padding wraps bin 359 onto bin 0 as the lidar does. The frame's other features
(goal, velocity, drift, command) pass through unchanged beside the convolution's output, and the
policy's MLP (``net_arch``) reads both. The layers are plain ``Conv1d`` over a padding built from
slices, which the ONNX export writes as it writes the MLP.
"""

from __future__ import annotations

import gymnasium as gym
import torch
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

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


class CircularScanExtractor(BaseFeaturesExtractor):
    """Circular convolutions over the scans of ``n_stack`` frames, the other features beside them.

    The observation is ``n_stack`` frames side by side (SB3's ``VecFrameStack``, oldest first); each
    frame starts with ``n_bins`` scan values
    (:class:`companion.perception.observation.ObservationLayout`). The
    frames' scans are the convolution's input channels.

    :param observation_space: a flat Box of ``n_stack`` × frame floats
    :param n_stack: frames per observation
    :param n_bins: scan bins at the start of each frame
    :param layers: (output channels, kernel size, stride) of each convolution
    """

    def __init__(
        self,
        observation_space: gym.spaces.Box,
        n_stack: int,
        n_bins: int = N_BINS,
        layers: tuple[tuple[int, int, int], ...] = DEFAULT_LAYERS,
    ) -> None:
        size = int(observation_space.shape[0])
        if len(observation_space.shape) != 1 or size % n_stack or size // n_stack < n_bins:
            shape = observation_space.shape
            raise ValueError(f"observation shape {shape}: not {n_stack} frames of at least {n_bins} floats")
        frame = size // n_stack
        convs: list[nn.Module] = []
        channels, bins = n_stack, n_bins
        for out_channels, kernel_size, stride in layers:
            convs += [CircularConv1d(channels, out_channels, kernel_size, stride), nn.ReLU()]
            channels, bins = out_channels, -(-bins // stride)
        super().__init__(observation_space, channels * bins + n_stack * (frame - n_bins))
        self.n_stack, self.n_bins, self.frame = n_stack, n_bins, frame
        self.convs = nn.Sequential(*convs, nn.Flatten())

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        frames = observations.reshape(-1, self.n_stack, self.frame)
        scans = self.convs(frames[..., : self.n_bins])
        return torch.cat([scans, frames[..., self.n_bins :].flatten(1)], dim=1)
