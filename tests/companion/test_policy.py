"""OnnxPolicy on real ONNX Runtime: loading checks, actions, inference faults."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from companion.common.errors import UserError
from companion.guidance.policy import (
    LEGACY_VALUES,
    METADATA_KEYS,
    InferenceFault,
    OnnxPolicy,
    PolicySpec,
    declared_sideways_speed,
    policy_metadata,
    provider_options,
    select_providers,
)
from companion.perception.observation import ObservationLayout
from companion.perception.scan import BIN_CONVENTION
from tests.onnx_models import COMPANION_SPEC, write_policy

SPEC = PolicySpec()


def stacked(newest: np.ndarray, older: float = 0.0) -> np.ndarray:
    """An observation whose three older scans are ``older`` and whose newest scan is ``newest``."""
    return np.concatenate([np.full(3 * 360, older, np.float32), newest.astype(np.float32)])


def test_metadata_helper_writes_exactly_the_checked_keys() -> None:
    meta = policy_metadata(SPEC, json.dumps({"lr": 3e-4}))
    assert set(meta) == set(METADATA_KEYS)
    assert meta == {
        "lidar_avoid.format": "1",
        "lidar_avoid.obs_size": "1440",
        "lidar_avoid.stack": "4",
        "lidar_avoid.n_bins": "360",
        "lidar_avoid.max_range": "10.0",
        "lidar_avoid.bin_convention": BIN_CONVENTION,
        "lidar_avoid.max_speed": "2.0",
        "lidar_avoid.max_yaw_rate": "1.5",
        "lidar_avoid.max_sideways_speed": "0.0",
        "lidar_avoid.config": '{"lr": 0.0003}',
        "lidar_avoid.obs_layout": "scan360",
    }
    with pytest.raises(ValueError):
        policy_metadata(SPEC, "{not json")


def test_loads_and_logs_the_providers_in_use(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="companion.guidance.policy")
    policy = OnnxPolicy(write_policy(tmp_path / "p.onnx", spec=SPEC), SPEC)
    assert policy.providers == ["CPUExecutionProvider"]  # this machine: no TensorRT/CUDA; Azure never asked
    assert "providers in use: CPUExecutionProvider" in caplog.text


def test_provider_preference_is_filtered_by_availability() -> None:
    assert select_providers() == ["CPUExecutionProvider"]
    with pytest.raises(UserError, match="providers CUDAExecutionProvider is available"):
        select_providers(["CUDAExecutionProvider"])


@pytest.mark.parametrize(
    ("kind", "action"),
    [("forward", (1.0, 0.0)), ("stop", (0.0, 0.0)), ("turn_left", (0.0, 1.0)), ("turn_right", (0.0, -1.0))],
)
def test_constant_policies(tmp_path: Path, kind: str, action: tuple[float, float]) -> None:
    policy = OnnxPolicy(write_policy(tmp_path / "p.onnx", spec=SPEC, kind=kind), SPEC)
    out = policy.act(np.ones(1440, np.float32))
    assert out.dtype == np.float32 and out.shape == (2,)
    assert out.tolist() == list(action)


def test_the_newest_scan_is_the_last_block(tmp_path: Path) -> None:
    policy = OnnxPolicy(write_policy(tmp_path / "p.onnx", spec=SPEC, kind="echo"), SPEC)
    newest = np.ones(360, np.float32)
    newest[0], newest[90] = 0.25, 0.75
    assert policy.act(stacked(newest, older=0.5)).tolist() == [0.25, 0.75]


def test_steer_policy_slows_for_obstacles_and_turns_to_open_side(tmp_path: Path) -> None:
    policy = OnnxPolicy(write_policy(tmp_path / "p.onnx", spec=SPEC, kind="steer"), SPEC)
    assert policy.act(stacked(np.ones(360))).tolist() == pytest.approx([1.0, 0.0])
    blocked = np.ones(360, np.float32)
    blocked[[*range(0, 15), *range(345, 360)]] = 0.1  # 1 m ahead
    blocked[270:330] = 0.2  # right side close: turn left (counter-clockwise, positive)
    a = policy.act(stacked(blocked))
    assert a[0] < 0.0 and a[1] > 0.5


@pytest.mark.parametrize(
    ("nearest", "course_deg", "yaw"),
    [(0, 0.5, 0.5 / 30), (90, 90.5, 1.0), (200, -159.5, -1.0), (350, -9.5, -9.5 / 30)],
)
def test_the_ram_model_asks_full_speed_at_the_nearest_return(
    tmp_path: Path, nearest: int, course_deg: float, yaw: float
) -> None:
    spec = COMPANION_SPEC  # the goal layout, a three-value action (forward, yaw, left)
    policy = OnnxPolicy(write_policy(tmp_path / "ram.onnx", kind="ram"), spec)
    frame = spec.layout.frame_size
    obs = np.full(spec.obs_size, 0.5, np.float32)
    obs[:-frame] = 0.0  # older frames closer everywhere: only the newest scan counts
    obs[-frame + nearest] = 0.1
    a0, a1, a2 = policy.act(obs)
    vx, vy = a0 * spec.max_speed, a2 * spec.max_sideways_speed
    assert np.degrees(np.arctan2(vy, vx)) == pytest.approx(course_deg, abs=1e-3)
    assert max(abs(a0), abs(a2)) == pytest.approx(1.0)  # full scale along that course
    assert a1 == pytest.approx(yaw, abs=1e-5)
    strafe = OnnxPolicy(write_policy(tmp_path / "strafe.onnx", kind="ram_strafe"), spec)
    assert strafe.act(obs).tolist() == pytest.approx([a0, 0.0, a2])
    two = OnnxPolicy(write_policy(tmp_path / "two.onnx", kind="ram", spec=SPEC), SPEC)  # no sideways part
    assert two.act(stacked(obs[-frame:][:360])).tolist() == pytest.approx([1.0, yaw], abs=1e-5)


def test_actions_are_clipped(tmp_path: Path) -> None:
    policy = OnnxPolicy(write_policy(tmp_path / "p.onnx", spec=SPEC, kind="big"), SPEC)
    out = policy.act(np.zeros(1440, np.float32))
    assert out.tolist() == [1.0, -1.0]


@pytest.mark.parametrize(
    ("kind", "match"), [("nan", "non-finite"), ("inf", "non-finite"), ("error", "raised Fail")]
)
def test_inference_faults(tmp_path: Path, kind: str, match: str) -> None:
    policy = OnnxPolicy(write_policy(tmp_path / "p.onnx", spec=SPEC, kind=kind), SPEC)
    with pytest.raises(InferenceFault, match=match):
        policy.act(np.zeros(1440, np.float32))
    # a fault is not fatal: the same policy object can be asked again
    with pytest.raises(InferenceFault):
        policy.act(np.zeros(1440, np.float32))


def test_wrong_observation_length_is_a_programming_error(tmp_path: Path) -> None:
    policy = OnnxPolicy(write_policy(tmp_path / "p.onnx", spec=SPEC), SPEC)
    with pytest.raises(ValueError, match="360 values, the policy takes 1440"):
        policy.act(np.zeros(360, np.float32))


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"^policy model .*nope\.onnx: file not found$"):
        OnnxPolicy(tmp_path / "nope.onnx", SPEC)


@pytest.mark.parametrize("content", [b"", b"this is not a model\n", bytes(range(256)) * 10])
def test_not_onnx(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bad.onnx"
    path.write_bytes(content)
    with pytest.raises(UserError, match=r"bad\.onnx is not a loadable ONNX model: \S"):
        OnnxPolicy(path, SPEC)


def test_input_size_mismatch_names_both(tmp_path: Path) -> None:
    path = write_policy(tmp_path / "p.onnx", spec=SPEC, input_size=720)
    with pytest.raises(UserError, match=r"input shape \(N, 720\) does not match config \(1, 1440\) float32"):
        OnnxPolicy(path, SPEC)


def test_output_size_mismatch(tmp_path: Path) -> None:
    with pytest.raises(
        UserError,
        match=r"model output \(N, 4\) does not match config \(1, 2\) float32 "
        r"\(policy.max_sideways_speed 0\)$",
    ):
        OnnxPolicy(write_policy(tmp_path / "p.onnx", spec=SPEC, output_size=4), SPEC)


SIDEWAYS_SPEC = dataclasses.replace(SPEC, max_sideways_speed=1.0)
AS_THE_MODEL_SAYS = ", as the model's metadata says"


def _refusal(tmp_path: Path, model_spec: PolicySpec, config_spec: PolicySpec) -> str:
    """The companion's message refusing a model exported for ``model_spec`` under ``config_spec``."""
    path = write_policy(tmp_path / "p.onnx", spec=model_spec)
    with pytest.raises(UserError) as err:
        OnnxPolicy(path, config_spec)
    return str(err.value)


def test_a_sideways_model_loads_under_a_sideways_config_and_acts_with_three_values(tmp_path: Path) -> None:
    path = write_policy(tmp_path / "side.onnx", kind="slide_left", spec=SIDEWAYS_SPEC)
    policy = OnnxPolicy(path, SIDEWAYS_SPEC)
    assert policy.act(np.zeros(SPEC.obs_size, np.float32)).tolist() == [0.0, 0.0, 1.0]


@pytest.mark.parametrize(
    ("model_spec", "config_spec", "message"),
    [
        (
            SIDEWAYS_SPEC,
            SPEC,
            "model output (N, 3) does not match config (1, 2) float32 (policy.max_sideways_"
            f"speed 0; set policy.max_sideways_speed = 1{AS_THE_MODEL_SAYS})",
        ),
        (
            SPEC,
            SIDEWAYS_SPEC,
            "model output (N, 2) does not match config (1, 3) float32 (policy.max_sideways_"
            f"speed 1; set policy.max_sideways_speed = 0{AS_THE_MODEL_SAYS})",
        ),
        (
            dataclasses.replace(SPEC, max_sideways_speed=0.5),
            SIDEWAYS_SPEC,
            "model max_sideways_speed 0.5 does not match config policy.max_sideways_speed 1.0",
        ),
    ],
)
def test_a_model_of_another_action_is_refused_naming_the_fix(
    tmp_path: Path, model_spec: PolicySpec, config_spec: PolicySpec, message: str
) -> None:
    assert _refusal(tmp_path, model_spec, config_spec) == message


def test_a_model_without_a_sideways_key_has_two_action_values(tmp_path: Path) -> None:
    """Models exported before the key existed (the shipped one) fly forward and yaw rate only."""
    key = "lidar_avoid.max_sideways_speed"
    path = write_policy(tmp_path / "old.onnx", spec=SPEC, metadata_overrides={key: None})
    OnnxPolicy(path, SPEC)
    with pytest.raises(UserError, match=r"^model output \(N, 2\) does not match config \(1, 3\)"):
        OnnxPolicy(path, SIDEWAYS_SPEC)


@pytest.mark.parametrize(
    ("value", "declared"),
    [(None, 0.0), ("1.0", 1.0), ("0.0", 0.0), ("nan", None), ("-1.0", None), ("inf", None), ("fast", None)],
)
def test_the_declared_sideways_speed_is_a_finite_speed_or_none(
    value: str | None, declared: float | None
) -> None:
    """What the refusal's hint and the inference bench read: an absent key is a two-part model."""
    meta = {} if value is None else {"lidar_avoid.max_sideways_speed": value}
    assert declared_sideways_speed(meta) == declared


def test_input_type_mismatch(tmp_path: Path) -> None:
    graph = helper.make_graph(
        [
            helper.make_node("Cast", ["obs"], ["obs_f"], to=TensorProto.FLOAT),
            helper.make_node("Gemm", ["obs_f", "W", "B"], ["action"]),
        ],
        "double-input",
        [helper.make_tensor_value_info("obs", TensorProto.DOUBLE, ["N", 1440])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["N", 2])],
        initializer=[
            numpy_helper.from_array(np.zeros((1440, 2), np.float32), "W"),
            numpy_helper.from_array(np.zeros(2, np.float32), "B"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, policy_metadata(SPEC, "{}"))
    onnx.save(model, str(tmp_path / "d.onnx"))
    with pytest.raises(UserError, match=r"input is tensor\(double\), expected \(1, 1440\) float32"):
        OnnxPolicy(tmp_path / "d.onnx", SPEC)


def test_a_model_for_another_stack_depth_loads_with_the_matching_spec(tmp_path: Path) -> None:
    spec = PolicySpec(stack=2)
    policy = OnnxPolicy(write_policy(tmp_path / "p.onnx", kind="echo", spec=spec), spec)
    newest = np.ones(360, np.float32)
    newest[0] = 0.5
    assert policy.act(np.concatenate([np.zeros(360, np.float32), newest])).tolist() == [0.5, 1.0]
    with pytest.raises(UserError, match=r"input shape \(N, 720\) does not match config \(1, 1440\)"):
        OnnxPolicy(tmp_path / "p.onnx", SPEC)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("max_range", "8.0", "model max_range 8.0 does not match config scan.max_range 10.0"),
        ("stack", "3", "model stack 3 does not match config policy.stack 4"),
        ("n_bins", "720", "model n_bins 720 does not match config scan bins 360"),
        ("obs_size", "1441", "model obs_size 1441 does not match config observation size 1440"),
        (
            "bin_convention",
            "cw-1deg",
            f"model bin_convention cw-1deg does not match config scan bin convention {BIN_CONVENTION}",
        ),
        ("max_speed", "3.0", "model max_speed 3.0 does not match config policy.max_speed 2.0"),
        ("max_yaw_rate", "1.0", "model max_yaw_rate 1.0 does not match config policy.max_yaw_rate 1.5"),
        ("format", "2", "model metadata format '2' is not the supported '1'"),
        ("config", "{oops", "model metadata lidar_avoid.config is not valid JSON"),
        ("max_range", "ten", "model metadata lidar_avoid.max_range = 'ten' is not a number"),
    ],
)
def test_metadata_contradicting_the_config_refuses_to_start(
    tmp_path: Path, key: str, value: str, message: str
) -> None:
    path = write_policy(tmp_path / "p.onnx", spec=SPEC, metadata_overrides={f"lidar_avoid.{key}": value})
    with pytest.raises(UserError) as err:
        OnnxPolicy(path, SPEC)
    assert message in str(err.value)


def test_metadata_equal_within_float_tolerance_is_accepted(tmp_path: Path) -> None:
    path = write_policy(tmp_path / "p.onnx", spec=SPEC, metadata_overrides={"lidar_avoid.max_range": "10"})
    OnnxPolicy(path, SPEC)


@pytest.mark.parametrize("key", sorted(set(METADATA_KEYS) - set(LEGACY_VALUES)))
def test_missing_metadata_is_named(tmp_path: Path, key: str) -> None:
    path = write_policy(tmp_path / "p.onnx", spec=SPEC, metadata_overrides={key: None})
    with pytest.raises(UserError, match=f"lacks metadata {key} "):
        OnnxPolicy(path, SPEC)


GOAL_SPEC = PolicySpec(layout=ObservationLayout(goal=True))
GOAL_NAME = "scan360+goal(cos,sin,distance/10m)+velocity(forward,left/2m/s)"


def test_a_goal_model_loads_with_a_goal_config_and_takes_its_frames(tmp_path: Path) -> None:
    path = write_policy(tmp_path / "goal.onnx", spec=GOAL_SPEC)
    policy = OnnxPolicy(path, GOAL_SPEC)
    assert policy.act(np.zeros(4 * 365, np.float32)).tolist() == [1.0, 0.0]
    with pytest.raises(ValueError, match="1440 values, the policy takes 1460"):
        policy.act(np.zeros(1440, np.float32))


@pytest.mark.parametrize(
    ("model_spec", "config_spec", "message"),
    [
        (GOAL_SPEC, SPEC, f"model obs_layout {GOAL_NAME} does not match config observation layout scan360"),
        (SPEC, GOAL_SPEC, f"model obs_layout scan360 does not match config observation layout {GOAL_NAME}"),
        (
            PolicySpec(layout=ObservationLayout(goal=True, goal_range=20.0)),
            GOAL_SPEC,
            "model obs_layout scan360+goal(cos,sin,distance/20m)+velocity(forward,left/2m/s) does not match "
            f"config observation layout {GOAL_NAME}",
        ),
    ],
)
def test_a_model_of_another_observation_layout_is_refused_naming_both(
    tmp_path: Path, model_spec: PolicySpec, config_spec: PolicySpec, message: str
) -> None:
    assert message in _refusal(tmp_path, model_spec, config_spec)


def test_a_model_without_a_layout_key_is_a_scan_only_model(tmp_path: Path) -> None:
    """Models exported before the key existed (the shipped one) were trained on scans alone."""
    path = write_policy(tmp_path / "old.onnx", spec=SPEC, metadata_overrides={"lidar_avoid.obs_layout": None})
    OnnxPolicy(path, SPEC)
    with pytest.raises(UserError, match=r"model obs_layout scan360 does not match config observation layout"):
        OnnxPolicy(path, GOAL_SPEC)


def test_the_shipped_model_loads_under_the_default_config() -> None:
    """The shipped goal policy, as the default companion config feeds it (swapping it is one copy)."""
    from companion.app import policy_spec
    from companion.config import CompanionConfig

    OnnxPolicy(Path(__file__).resolve().parents[2] / "models" / "policy.onnx", policy_spec(CompanionConfig()))


def test_tensorrt_gets_the_engine_cache_and_others_are_left_alone() -> None:
    providers = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    with_cache = provider_options(providers, "/var/lib/lidar-avoid/trt")
    assert with_cache[0] == (
        "TensorrtExecutionProvider",
        {"trt_engine_cache_enable": "True", "trt_engine_cache_path": "/var/lib/lidar-avoid/trt"},
    )
    assert with_cache[1:] == providers[1:]
    assert provider_options(providers, None) == providers


def test_a_goal_model_without_drift_features_is_refused_with_the_fix(tmp_path: Path) -> None:
    """Goal models exported before the drift features (the previous shipped one) under today's
    default config: one line, naming both layouts and the key to set."""
    from companion.app import policy_spec
    from companion.config import CompanionConfig

    default = policy_spec(CompanionConfig())
    assert default.layout.drift
    old = PolicySpec(layout=dataclasses.replace(default.layout, drift=False))
    path = write_policy(tmp_path / "old-goal.onnx", spec=old)
    with pytest.raises(UserError) as err:
        OnnxPolicy(path, default)
    assert str(err.value).endswith("(drift features: the model has none: policy.drift = false)")
    assert old.layout.name in str(err.value) and default.layout.name in str(err.value)


def test_a_firmware_model_under_a_config_without_the_feature_is_refused_with_the_fix(tmp_path: Path) -> None:
    from companion.app import policy_spec
    from companion.config import CompanionConfig

    default = policy_spec(CompanionConfig())
    assert not default.layout.firmware
    firmware = PolicySpec(layout=dataclasses.replace(default.layout, firmware=True))
    path = write_policy(tmp_path / "firmware.onnx", spec=firmware)
    with pytest.raises(UserError) as err:
        OnnxPolicy(path, default)
    assert str(err.value).endswith("(firmware features: set policy.firmware = true)")


def test_a_movers_model_and_a_movers_config_each_refuse_the_other_with_the_fix(tmp_path: Path) -> None:
    from companion.app import policy_spec
    from companion.config import CompanionConfig

    default = policy_spec(CompanionConfig())
    movers = PolicySpec(layout=dataclasses.replace(default.layout, movers=True))
    with pytest.raises(UserError) as err:
        OnnxPolicy(write_policy(tmp_path / "movers.onnx", spec=movers), default)
    assert str(err.value).endswith("(movers features: set policy.movers = true)")
    assert movers.layout.name in str(err.value)
    with pytest.raises(UserError) as err:
        OnnxPolicy(write_policy(tmp_path / "plain.onnx", spec=default), movers)
    assert str(err.value).endswith("(movers features: the model has none: policy.movers = false)")
