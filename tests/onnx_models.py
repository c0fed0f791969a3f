"""Small real ONNX policies for tests (companion, app, SITL) until a trained one exists.

Each model is ``Gemm(obs, W, b)`` (optionally followed by ``Clip`` to [-1, 1]) built with
``onnx.helper``, carrying the same metadata the training export writes. Kinds:

- ``forward``: a = (1, 0)                 - ``stop``: a = (0, 0)
- ``turn_left``: a = (0, 1) (CCW)         - ``turn_right``: a = (0, -1)
- ``forward_left``: a = (1, 1), full speed ahead while turning left at full rate (above both
  firmwares' default yaw caps)
- ``slide_left``: a = (0, 0, 1), a sideways model's full speed to the left
- ``steer``: a0 = 2·mean(newest scan, forward ±15°) − 1, a1 = 2·(mean left 30–90° − mean right
  30–90°): slows for what is ahead and turns towards the more open side (a usable toy pilot)
- ``echo``: a = (newest scan bin 0, newest scan bin 90), to prove which values reach the model
- ``echo_goal``: a = (newest goal cos, goal sin) (goal layout): flies toward the goal's bearing
- ``echo_velocity``: a = (0, newest measured velocity left feature) (goal layout)
- ``echo_drift``: a = (newest drift forward feature, drift left feature) (drift layout)
- ``echo_command``: a = (0, 0.4 − newest yaw-rate command feature) (command layout): alternates
  between 0.4 and 0 when the frame carries the last command sent, 0.4 throughout when it does not
- ``echo_firmware``: a = (0.25 + 0.5 × newest firmware feature, 0) (firmware layout): 0.75 for
  ArduPilot, 0.25 for PX4
- ``big``: a = (5, −5) without the Clip node (the companion must clip)
- ``nan`` / ``inf``: non-finite output (an inference fault)
- ``error``: raises inside ONNX Runtime at inference (a Reshape that cannot fit)
- ``ram`` / ``ram_strafe``: an attacker, not a ``Gemm``: ``ArgMin`` over the newest scan finds the
  nearest return and a ``Gather`` looks up that bin's action: full speed along its bearing (the
  forward and sideways parts scaled so the larger is 1; a two-value action flies full forward) and,
  for ``ram``, full yaw rate towards it (proportional within 30°); ``ram_strafe`` keeps the nose
  (:func:`ram_table`)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from companion.app import policy_spec
from companion.config import CompanionConfig
from companion.guidance.policy import PolicySpec, policy_metadata

#: What the default companion config feeds a model (the goal layout): the default of :func:`write_policy`
COMPANION_SPEC = policy_spec(CompanionConfig())
#: A scan-only model's spec (LidarAvoid-v0), for tests of scan-only behaviour
SCAN_SPEC = PolicySpec()

KINDS = (
    "forward",
    "stop",
    "turn_left",
    "turn_right",
    "forward_left",
    "slide_left",
    "steer",
    "echo",
    "echo_goal",
    "echo_velocity",
    "echo_drift",
    "echo_command",
    "echo_firmware",
    "big",
    "nan",
    "inf",
    "error",
    "ram",
    "ram_strafe",
)
#: the attackers' yaw: full rate beyond this bearing of the nearest return, proportional within, rad
RAM_YAW_FULL_RAD = np.radians(30.0)
OPSET = 17
IR_VERSION = 8  # accepted by every onnxruntime the project supports


def _start(kind: str, spec: PolicySpec, part: str, layout: str = "") -> int:
    """Where ``part`` starts in a frame of ``spec``; a ValueError naming the ``layout`` (default:
    ``part``) that ``kind`` needs when the spec's has none."""
    parts = spec.layout.slices()
    if part not in parts:
        raise ValueError(f"{kind} needs a {layout or part} layout, not {spec.layout.name}")
    return parts[part].start


def _weights(kind: str, spec: PolicySpec, input_size: int, output_size: int) -> tuple[np.ndarray, np.ndarray]:
    w = np.zeros((input_size, output_size), dtype=np.float32)
    b = np.zeros(output_size, dtype=np.float32)
    newest = input_size - spec.layout.frame_size  # first index of the newest frame (its scan first)
    constant = {
        "forward": (1.0, 0.0),
        "stop": (0.0, 0.0),
        "turn_left": (0.0, 1.0),
        "turn_right": (0.0, -1.0),
        "forward_left": (1.0, 1.0),
        "big": (5.0, -5.0),
        "nan": (np.nan, np.nan),
        "inf": (np.inf, -np.inf),
        "error": (0.0, 0.0),
    }
    if kind in constant:
        b[:2] = constant[kind]
    elif kind == "slide_left":
        if output_size != 3:
            raise ValueError(f"{kind} needs a sideways action (3 values), not {output_size}")
        b[2] = 1.0
    elif kind == "steer":
        ahead = [*range(0, 15), *range(345, 360)]
        w[[newest + i for i in ahead], 0] = 2.0 / len(ahead)
        b[0] = -1.0
        w[[newest + i for i in range(30, 90)], 1] = 2.0 / 60
        w[[newest + i for i in range(270, 330)], 1] = -2.0 / 60
    elif kind == "echo":
        w[newest + 0, 0] = 1.0
        w[newest + 90, 1] = 1.0
    elif kind == "echo_goal":
        bearing = newest + _start(kind, spec, "goal_bearing", "goal")
        w[bearing, 0] = 1.0
        w[bearing + 1, 1] = 1.0
    elif kind == "echo_velocity":
        w[newest + _start(kind, spec, "velocity", "goal") + 1, 1] = 1.0
    elif kind == "echo_drift":
        drift = newest + _start(kind, spec, "drift")
        w[drift, 0] = 1.0
        w[drift + 1, 1] = 1.0
    elif kind == "echo_command":
        w[newest + _start(kind, spec, "command") + 1, 1] = -1.0
        b[1] = 0.4
    elif kind == "echo_firmware":
        w[newest + _start(kind, spec, "firmware"), 0] = 0.5
        b[0] = 0.25
    else:
        raise ValueError(f"unknown policy kind {kind!r}; choose from {', '.join(KINDS)}")
    return w, b


def ram_table(spec: PolicySpec, output_size: int, turn: bool = True) -> np.ndarray:
    """``(n_bins, output_size)``: the action the ``ram`` (``turn``) and ``ram_strafe`` models answer
    when bin ``i`` holds the nearest return.

    The bin's centre bearing θ (counter-clockwise from forward) is the course: the velocity
    (max_speed·a0, max_sideways_speed·a2) points along (cos θ, sin θ) at the highest speed the
    action's [-1, 1] box allows (one of a0, a2 is ±1). A two-value action cannot fly sideways: it
    flies full forward (a0 = 1), turning towards the return. ``turn``: a1 = θ / 30°, clipped to
    [-1, 1] (θ wrapped into (-180°, 180°]): full yaw rate towards the return until it is within 30°.
    """
    bearing = np.radians(np.arange(spec.n_bins) + 0.5) * (360.0 / spec.n_bins)
    bearing = np.arctan2(np.sin(bearing), np.cos(bearing))  # (-π, π]
    table = np.zeros((spec.n_bins, output_size), dtype=np.float32)
    if output_size >= 3:
        # the speed along (cos θ, sin θ) at which the larger of a0, a2 reaches 1
        scale = 1.0 / np.maximum(
            np.abs(np.cos(bearing)) / spec.max_speed, np.abs(np.sin(bearing)) / spec.max_sideways_speed
        )
        table[:, 0] = np.cos(bearing) * scale / spec.max_speed
        table[:, 2] = np.sin(bearing) * scale / spec.max_sideways_speed
    else:
        table[:, 0] = 1.0
    if turn:
        table[:, 1] = np.clip(bearing / RAM_YAW_FULL_RAD, -1.0, 1.0)
    return np.clip(table, -1.0, 1.0)


def _ram_graph(kind: str, spec: PolicySpec, n_in: int, output_size: int) -> tuple[list, list]:
    """Nodes and initialisers of the ``ram`` models: Slice (the newest scan) → ArgMin → Gather."""
    newest = n_in - spec.layout.frame_size
    scan = spec.layout.slices()["scan"]
    nodes = [
        helper.make_node("Slice", ["obs", "scan_start", "scan_end", "scan_axis"], ["scan"]),
        helper.make_node("ArgMin", ["scan"], ["nearest"], axis=1, keepdims=0),
        helper.make_node("Gather", ["table", "nearest"], ["action"], axis=0),
    ]
    inits = [
        numpy_helper.from_array(np.array([newest + scan.start], dtype=np.int64), "scan_start"),
        numpy_helper.from_array(np.array([newest + scan.stop], dtype=np.int64), "scan_end"),
        numpy_helper.from_array(np.array([1], dtype=np.int64), "scan_axis"),
        numpy_helper.from_array(ram_table(spec, output_size, turn=kind == "ram"), "table"),
    ]
    return nodes, inits


def write_policy(
    path: str | Path,
    *,
    kind: str = "forward",
    spec: PolicySpec = COMPANION_SPEC,
    metadata_overrides: dict[str, str | None] | None = None,
    input_size: int | None = None,
    output_size: int | None = None,
) -> Path:
    """Write a small ONNX policy and return its path.

    :param path: destination file
    :param kind: behaviour, one of :data:`KINDS`
    :param spec: written into the metadata (and sets the default input size); by default what the
        default companion config feeds (the goal layout)
    :param metadata_overrides: full metadata keys to change; ``None`` as a value removes the key
    :param input_size: observation length (default ``spec.obs_size``)
    :param output_size: action length (default ``spec.action_size``)
    """
    path = Path(path)
    n_in = spec.obs_size if input_size is None else input_size
    output_size = spec.action_size if output_size is None else output_size
    clipped = kind not in ("big", "inf", "ram", "ram_strafe")  # (a ram's table is within [-1, 1])
    if kind in ("ram", "ram_strafe"):
        nodes, inits = _ram_graph(kind, spec, n_in, output_size)
    else:
        w, b = _weights(kind, spec, n_in, output_size)
        nodes = [helper.make_node("Gemm", ["obs", "W", "B"], ["raw" if clipped else "action"])]
        inits = [numpy_helper.from_array(w, "W"), numpy_helper.from_array(b, "B")]
    if clipped:
        clip_out = "clipped" if kind == "error" else "action"
        nodes.append(helper.make_node("Clip", ["raw", "lo", "hi"], [clip_out]))
        inits += [numpy_helper.from_array(np.float32(v), name) for v, name in ((-1.0, "lo"), (1.0, "hi"))]
    if kind == "error":
        # Reshape (N, 2) to (N + 2, -1), computed from the input's shape so that no load-time shape
        # inference can see it: ONNX Runtime raises at run time.
        nodes += [
            helper.make_node("Shape", ["obs"], ["obs_shape"]),
            helper.make_node("Add", ["obs_shape", "shape_delta"], ["bad_shape"]),
            helper.make_node("Reshape", ["clipped", "bad_shape"], ["action"]),
        ]
        inits.append(numpy_helper.from_array(np.array([2, -1 - n_in], dtype=np.int64), "shape_delta"))
    graph = helper.make_graph(
        nodes,
        f"test-policy-{kind}",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["N", n_in])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["N", output_size])],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="tests")
    model.ir_version = IR_VERSION
    meta = policy_metadata(spec, json.dumps({"test_policy": kind}))
    for key, value in (metadata_overrides or {}).items():
        if value is None:
            meta.pop(key, None)
        else:
            meta[key] = value
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model, full_check=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path
