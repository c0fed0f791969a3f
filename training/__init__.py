"""lidar-avoid training: PPO on stacked lidar scans, evaluation against baselines, ONNX export."""
