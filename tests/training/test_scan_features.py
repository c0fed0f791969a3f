"""The circular scan extractor: an obstacle reads the same at every bearing, across bin 359 to 0,
and a run trained with it exports to ONNX with parity."""

from __future__ import annotations

import contextlib
import io

import gymnasium as gym
import numpy as np
import onnx
import pytest
import torch

from tests.training.test_nav_pipeline import GOAL, TINY_NAV
from training.__main__ import main
from training.config import load_train_config
from training.scan_features import CircularScanExtractor
from training.train import policy_kwargs

N_STACK, FRAME = 4, 367
#: bins the three default convolutions' strides (3, 2, 2) move the output by one
TOTAL_STRIDE = 12


def _extractor() -> CircularScanExtractor:
    torch.manual_seed(0)
    space = gym.spaces.Box(-1.0, 1.0, (N_STACK * FRAME,), np.float32)
    return CircularScanExtractor(space, N_STACK)


def test_rotating_the_scans_rotates_the_features_and_leaves_the_rest_alone():
    extractor = _extractor()
    frames = np.random.default_rng(1).uniform(0.0, 1.0, (N_STACK, FRAME)).astype(np.float32)
    frames[:, 350:356] = 0.05  # an obstacle that the roll carries across bin 359 to 0
    rolled = frames.copy()
    rolled[:, :360] = np.roll(frames[:, :360], TOTAL_STRIDE, axis=1)
    with torch.no_grad():
        out = extractor(torch.as_tensor(np.stack([frames, rolled]).reshape(2, -1))).numpy()
    assert extractor.features_dim == 16 * 30 + N_STACK * 7 == out.shape[1]
    scans = out[:, : 16 * 30].reshape(2, 16, 30)
    np.testing.assert_allclose(scans[1], np.roll(scans[0], 1, axis=1), atol=1e-5)
    assert not np.allclose(scans[1], scans[0], atol=1e-3)
    np.testing.assert_array_equal(out[0, 16 * 30 :], frames[:, 360:].ravel())
    np.testing.assert_array_equal(out[1, 16 * 30 :], out[0, 16 * 30 :])


def test_an_observation_that_is_not_whole_frames_of_a_scan_is_refused():
    with pytest.raises(ValueError, match=r"observation shape \(1001,\): not 4 frames of at least 360 floats"):
        CircularScanExtractor(gym.spaces.Box(-1.0, 1.0, (1001,), np.float32), 4)
    with pytest.raises(ValueError, match="kernel_size 4: must be odd"):
        CircularScanExtractor(gym.spaces.Box(-1.0, 1.0, (1460,), np.float32), 4, layers=((8, 4, 2),))


def test_the_config_chooses_the_convolutions():
    layers = "ppo.scan_layers=[[16, 5, 2], [32, 3, 3]]"
    config = load_train_config(None, ["ppo.features_extractor=circular_scan", layers])
    kwargs = policy_kwargs(config)
    space = gym.spaces.Box(-1.0, 1.0, (N_STACK * FRAME,), np.float32)
    extractor = kwargs["features_extractor_class"](space, **kwargs["features_extractor_kwargs"])
    convs = [m.conv for m in extractor.convs if hasattr(m, "conv")]
    assert [(c.out_channels, c.kernel_size[0], c.stride[0]) for c in convs] == [(16, 5, 2), (32, 3, 3)]
    assert extractor.features_dim == 32 * 60 + N_STACK * 7  # 360 bins, strides 2 and 3
    default = policy_kwargs(load_train_config(None, ["ppo.features_extractor=circular_scan"]))
    assert "layers" not in default["features_extractor_kwargs"]  # the extractor's own default


def test_a_run_with_the_circular_extractor_trains_and_exports_with_parity(tmp_path):
    config = tmp_path / "tiny-nav.toml"
    config.write_text(TINY_NAV)
    runs = tmp_path / "runs"
    overrides = [f"run_root={runs}", "ppo.features_extractor=circular_scan"]
    assert main(["train", "--config", str(config), *overrides]) == 0
    model = runs / "tiny-nav-s2" / "final_model.zip"
    from stable_baselines3 import PPO

    policy = PPO.load(model, device="cpu").policy
    assert isinstance(policy.pi_features_extractor, CircularScanExtractor)
    assert policy.pi_features_extractor is not policy.vf_features_extractor
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["export", "--model", str(model), "--out", str(tmp_path / "p.onnx"),
                     "--parity-samples", "100"]) == 0  # fmt: skip
    assert "max abs diff" in printed.getvalue()
    meta = {p.key: p.value for p in onnx.load(str(tmp_path / "p.onnx")).metadata_props}
    assert meta["lidar_avoid.obs_layout"] == GOAL.name
