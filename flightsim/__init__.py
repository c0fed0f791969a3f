"""lidar-avoid flight simulator: JSBSim quadrotor, ray-cast VLP-16, worlds, Gymnasium envs, SITL."""

from gymnasium.envs.registration import register, registry

ENV_ID = "flightsim/LidarAvoid-v0"
NAV_ENV_ID = "flightsim/LidarNav-v0"

# The entry points are strings so importing flightsim stays light (no JSBSim, no numba until made);
# the guard keeps a second import (or a reload) from re-registering.
if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="flightsim.envs.env:LidarAvoidEnv")
if NAV_ENV_ID not in registry:
    register(id=NAV_ENV_ID, entry_point="flightsim.envs.nav_env:LidarNavEnv")
