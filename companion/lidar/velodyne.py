"""Velodyne VLP-16: packet validation, decoding, revolution assembly, encoding and a UDP source."""

from __future__ import annotations

import numpy as np

#: Elevation ω of each laser in degrees, indexed by laser id (the order within a firing sequence).
#: From the VLP-16 manual: even ids point down (−15° … −1°), odd ids up (+1° … +15°), interleaved.
VLP16_ELEVATIONS_DEG: np.ndarray = np.array(
    [-15.0, 1.0, -13.0, 3.0, -11.0, 5.0, -9.0, 7.0, -7.0, 9.0, -5.0, 11.0, -3.0, 13.0, -1.0, 15.0],
    dtype=np.float64,
)
VLP16_ELEVATIONS_DEG.setflags(write=False)
