"""The circular scan extractor: an obstacle reads the same at every bearing, across bin 359 to 0;
the tracked movers are drawn as scans where their tracks take them; and a run trained with both
exports to ONNX with parity."""

from __future__ import annotations

import contextlib
import io

import gymnasium as gym
import numpy as np
import onnx
import pytest
import torch

from companion.perception.observation import MOVER_SLOT_FEATURES, ObservationLayout
from tests.training.test_nav_pipeline import TINY_NAV
from training.__main__ import main
from training.config import load_train_config
from training.mirror import mirror_for
from training.scan_features import CircularScanExtractor, MoverRing
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


MOVERS = ObservationLayout(goal=True, goal_range=30.0, velocity_scale=2.0, movers=True)


def _slot(forward: float, left: float, v_forward: float, v_left: float, radius: float) -> list[float]:
    """One mover slot's features (metres, m/s), scaled as the frame carries them."""
    return [forward / 10.0, left / 10.0, v_forward / 3.0, v_left / 3.0, radius, 1.0]


def test_the_mover_ring_draws_a_walker_where_its_track_takes_it():
    # a walker (r 0.25 m) 3 m ahead walking left at 1 m/s; the second slot is empty, the third a
    # drone 6 m to the right, coming at the vehicle at 2 m/s
    movers = torch.tensor([_slot(3.0, 0.0, 0.0, 1.0, 0.25) + [0.0] * 6 + _slot(0.0, -6.0, 0.0, 2.0, 0.4)])
    now, later = MoverRing((0.0, 1.5))(movers)[0].numpy()
    # now: the walker dead ahead, asin(0.25 / 3) = 4.8 degrees either side; the drone at 270 degrees,
    # asin(0.4 / 6) = 3.8 either side
    assert np.flatnonzero(now < 1.0).tolist() == [*range(0, 5), *range(266, 274), *range(355, 360)]
    np.testing.assert_allclose(now[[0, 359]], 0.275, atol=1e-6)
    np.testing.assert_allclose(now[[266, 273]], (6.0 - 0.4) / 10.0, atol=1e-6)
    # 1.5 s later: the walker at (3, 1.5), 26.6 degrees left; the drone 3 m to the right
    walker = np.flatnonzero(later[:180] < 1.0)
    assert walker.min() <= 26 <= walker.max() and walker.size < 12
    np.testing.assert_allclose(later[26], (np.hypot(3.0, 1.5) - 0.25) / 10.0, atol=1e-6)
    np.testing.assert_allclose(later[270], (3.0 - 0.4) / 10.0, atol=1e-6)
    assert np.all(later[[0, 359]] == 1.0)  # the walker has left the nose
    absent = movers.clone()
    absent[:, 5::6] = 0.0  # nobody present: open rings whatever the other numbers say
    assert torch.all(MoverRing((0.0, 1.5))(absent) == 1.0)


def test_mirroring_the_frame_mirrors_the_rings():
    # the DAgger fit mirrors half of each batch across the nose: the rings must mirror with it
    frames = np.random.default_rng(3).uniform(0.0, 1.0, (N_STACK, MOVERS.frame_size)).astype(np.float32)
    movers = MOVERS.slices()["movers"]
    slots = _slot(2.0, 1.0, -0.5, -1.0, 0.3) + _slot(4.0, -3.0, 0.0, 2.0, 0.5) + [0.0] * 6
    frames[:, movers] = slots
    mirrored = mirror_for(MOVERS, N_STACK).observations(frames.ravel()[None])[0].reshape(N_STACK, -1)
    ring = MoverRing((0.0, 1.0, 2.0))
    with torch.no_grad():
        rings = ring(torch.as_tensor(frames[-1:, movers])).numpy()[0]
        mirrored_rings = ring(torch.as_tensor(mirrored[-1:, movers])).numpy()[0]
    assert (rings < 1.0).any(axis=1).all()
    np.testing.assert_allclose(mirrored_rings, rings[:, ::-1], atol=1e-6)


def test_the_extractor_reads_the_newest_movers_through_the_convolutions():
    torch.manual_seed(0)
    space = gym.spaces.Box(-1.0, 1.0, (N_STACK * MOVERS.frame_size,), np.float32)
    start = MOVERS.slices()["movers"].start
    extractor = CircularScanExtractor(space, N_STACK, movers_at=start, mover_times=(0.0, 1.0))
    assert extractor.convs[0].conv.in_channels == N_STACK + 2
    assert extractor.features_dim == 16 * 30 + N_STACK * (MOVERS.frame_size - 360)
    frames = np.ones((2, N_STACK, MOVERS.frame_size), dtype=np.float32)
    frames[:, :, 360:] = 0.0
    frames[1, -1, start : start + len(MOVER_SLOT_FEATURES)] = _slot(2.0, 0.0, 0.0, 1.0, 0.3)
    with torch.no_grad():
        out = extractor(torch.as_tensor(frames.reshape(2, -1))).numpy()
    # the walker moves the convolutions' output, not only its own pass-through numbers
    assert not np.allclose(out[0, : 16 * 30], out[1, : 16 * 30], atol=1e-4)
    with pytest.raises(ValueError, match="movers_at 370: 18 mover features do not fit a 383-float frame"):
        CircularScanExtractor(space, N_STACK, movers_at=370)


def test_the_mover_ring_needs_the_circular_extractor_and_the_movers():
    from companion.common.errors import UserError

    with pytest.raises(UserError, match=r"ppo\.mover_ring draws the frame's movers"):
        load_train_config(None, ["ppo.features_extractor=circular_scan", "ppo.mover_ring=[1.0]"])
    with pytest.raises(UserError, match=r"ppo\.mover_ring draws the frame's movers"):
        load_train_config(None, ["env.movers=true", "env.tracking=true", "ppo.mover_ring=[1.0]"])
    goal = ["env_id=flightsim/LidarNav-v0", "eval.first_seed=500000", "env.movers=true"]
    config = load_train_config(None, [*goal, "ppo.features_extractor=circular_scan", "ppo.mover_ring=[0, 2]"])
    kwargs = policy_kwargs(config)["features_extractor_kwargs"]
    assert (kwargs["movers_at"], kwargs["mover_times"]) == (MOVERS.slices()["movers"].start, (0.0, 2.0))


def test_a_run_with_the_circular_extractor_and_the_mover_ring_trains_and_exports_with_parity(tmp_path):
    config = tmp_path / "tiny-nav.toml"
    config.write_text(TINY_NAV.replace('families = ["gaps"]', 'families = ["rooms-dynamic"]\nmovers = true'))
    runs = tmp_path / "runs"
    overrides = [f"run_root={runs}", "ppo.features_extractor=circular_scan", "ppo.mover_ring=[0.0, 1.0]"]
    assert main(["train", "--config", str(config), *overrides]) == 0
    model = runs / "tiny-nav-s2" / "final_model.zip"
    from stable_baselines3 import PPO

    policy = PPO.load(model, device="cpu").policy
    assert isinstance(policy.pi_features_extractor, CircularScanExtractor)
    assert policy.pi_features_extractor.ring is not None
    assert policy.pi_features_extractor is not policy.vf_features_extractor
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["export", "--model", str(model), "--out", str(tmp_path / "p.onnx"),
                     "--parity-samples", "100"]) == 0  # fmt: skip
    assert "max abs diff" in printed.getvalue()
    meta = {p.key: p.value for p in onnx.load(str(tmp_path / "p.onnx")).metadata_props}
    assert meta["lidar_avoid.obs_layout"] == MOVERS.name
