"""The Gymnasium environments (``flightsim/LidarAvoid-v0``, ``flightsim/LidarNav-v0``), their batched
twins, the ray-cast lidar, rewards and seed ranges.

Imports vehicle and worlds; never sitl."""
