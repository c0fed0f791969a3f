"""From lidar returns to what the policy sees: the 360-bin scan, scan matching and the drift estimate,
the frame stack and the observation layout.

Pure logic: imports only :mod:`companion.common`."""
