"""lidar-avoid flight simulator: JSBSim quadrotor, ray-cast VLP-16, worlds, Gymnasium env, SITL."""
