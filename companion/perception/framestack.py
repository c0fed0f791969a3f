"""Stack the last ``n`` scans into the policy's input, exactly as SB3's VecFrameStack does.

Order is oldest first, newest last. After a (re)start the stack is zeros with the first scan in
the last slot; training saw exactly this at every episode start, so flight must too.
"""

from __future__ import annotations

import numpy as np


class FrameStack:
    """Rolling stack of ``n`` observations of ``size`` floats each.

    :param n: stack depth (4 in this project)
    :param size: length of one observation (360 bins)
    """

    def __init__(self, n: int = 4, size: int = 360) -> None:
        if n < 1 or size < 1:
            raise ValueError(f"FrameStack needs n >= 1 and size >= 1, got n={n}, size={size}")
        self.n = n
        self.size = size
        self._stack = np.zeros(n * size, dtype=np.float32)

    def reset(self, scan: np.ndarray) -> np.ndarray:
        """Start over: zeros, then ``scan`` last. Returns a copy of the stacked observation."""
        self._stack[:] = 0.0
        self._stack[-self.size :] = self._checked(scan)
        return self._stack.copy()

    def push(self, scan: np.ndarray) -> np.ndarray:
        """Drop the oldest scan, append ``scan`` last. Returns a copy of the stacked observation."""
        new = self._checked(scan)
        self._stack[: -self.size] = self._stack[self.size :]
        self._stack[-self.size :] = new
        return self._stack.copy()

    def _checked(self, scan: np.ndarray) -> np.ndarray:
        arr = np.asarray(scan, dtype=np.float32).reshape(-1)
        if arr.shape[0] != self.size:
            raise ValueError(f"FrameStack expects {self.size} values per scan, got {arr.shape[0]}")
        return arr
