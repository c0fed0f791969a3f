"""Shared helpers for the simulated-autopilot tests: MAVLink wire round-trips and a fake-clock flight loop."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.sim_autopilot.common import SimAutopilot
from flightsim.sitl.sim_autopilot.snapshot import VehicleSnapshot
from flightsim.worlds.world import World

GCS = (255, 190)
COMPANION = (1, 191)
BODY_VEL_YAWRATE_MASK = 0x05C7


def wire(msg: Any, source: tuple[int, int] = GCS) -> Any:
    """Pack ``msg`` as ``source`` would and decode it again, so it carries real header fields."""
    mav = mavlink.MAVLink(None, *source)
    return mav.decode(bytearray(msg.pack(mav)))


def command(cmd: int, *params: float, source: tuple[int, int] = GCS) -> Any:
    p = [*params, *([0.0] * (7 - len(params)))]
    return wire(mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *p), source)


def body_velocity(
    forward: float,
    yaw_rate_frd: float = 0.0,
    frame: int = mavlink.MAV_FRAME_BODY_OFFSET_NED,
    mask: int = BODY_VEL_YAWRATE_MASK,
) -> Any:
    return wire(
        mavlink.MAVLink_set_position_target_local_ned_message(
            0, 1, 1, frame, mask, 0, 0, 0, forward, 0, 0, 0, 0, 0, 0, yaw_rate_frd
        ),
        COMPANION,
    )


def acks(out: list[Any]) -> list[tuple[int, int]]:
    return [(o.message.command, o.message.result) for o in out if o.message.get_type() == "COMMAND_ACK"]


def airborne(x: float = 0.0, y: float = 0.0, z: float = 1.5, yaw: float = 0.0) -> VehicleSnapshot:
    """A hovering vehicle (world ENU) for logic tests that need no physics."""
    return VehicleSnapshot(time=0.0, position=np.array([x, y, z]), yaw=yaw, on_ground=False)


def on_ground() -> VehicleSnapshot:
    return VehicleSnapshot(time=0.0, position=np.array([0.0, 0.0, 0.08]), on_ground=True)


def fly(
    ap: SimAutopilot, vehicle: Any, t: float, duration: float, dt: float = 3 / 120, each: Any = None
) -> float:
    """Fly the real vehicle under ``ap`` for ``duration`` s of sim time from ``t``; returns the end time."""
    for _ in range(math.ceil(duration / dt)):
        t += dt
        if each is not None:
            each(t)
        armed, setpoint = ap.flight_command(t)
        if armed != vehicle.state.armed:
            vehicle.set_armed(armed)
        ap.observe(vehicle.step(setpoint, dt))
        ap.tick(t)
    return t


# ------------------------------------------------------------------------------------ SITL flights
OPEN_ROOM = World(
    name="open-room",
    room_size=(16.0, 16.0),
    room_height=3.0,
    obstacles=(),
    start_position=(0.0, -1.7, 1.5),
    start_yaw_deg=0.0,
)


def write_constant_policy(path: Path, forward: float, turn: float) -> Path:
    """A real ONNX policy that always answers ``(forward, turn)`` (a0, a1 in [-1, 1]; no sideways
    part, a2 = 0, in the default config's three-part action).

    (0.5, 0.4) flies a circle of about 1.7 m radius at 1 m/s: the vehicle keeps moving without
    ever meeting a wall of :data:`OPEN_ROOM`, so stopping it is always the system's doing.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from companion.guidance.policy import policy_metadata
    from tests.onnx_models import COMPANION_SPEC

    spec = COMPANION_SPEC  # what the default companion config feeds (the answer ignores it)
    w = np.zeros((spec.obs_size, spec.action_size), dtype=np.float32)
    b = np.zeros(spec.action_size, dtype=np.float32)
    b[:2] = forward, turn
    graph = helper.make_graph(
        [helper.make_node("Gemm", ["obs", "W", "B"], ["action"])],
        "constant-policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["N", spec.obs_size])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["N", spec.action_size])],
        initializer=[numpy_helper.from_array(w, "W"), numpy_helper.from_array(b, "B")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="tests")
    model.ir_version = 8
    helper.set_model_props(model, policy_metadata(spec, '{"test_policy": "constant"}'))
    onnx.save(model, str(path))
    return path


def wait_for(predicate: Callable[[], Any], timeout: float, what: str, poll: float = 0.02) -> Any:
    """Poll until ``predicate()`` is truthy and return it; AssertionError naming ``what`` on timeout."""
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(poll)


def said(flight: Any, mark: str) -> bool:
    """The companion sent a STATUSTEXT containing ``mark``."""
    return any(mark in t for t in flight.recorder.texts())


def engage_mission(flight: Any) -> None:
    """Companion up, the world's waypoints uploaded as a mission, take-off, the companion engaged."""
    flight.wait_companion_up()
    flight.upload_mission()
    flight.take_off()
    assert flight.wait_engaged(25.0), flight.companion_log()


def speed(flight: Any) -> float:
    """Horizontal speed of the simulated vehicle, m/s."""
    return float(np.linalg.norm(flight.server.state.velocity[:2]))


def estimated_speed(flight: Any) -> float:
    """Horizontal speed as the simulated autopilot's estimator reports it, m/s: the speed its
    velocity loop closes on. PX4's calibrated estimate error (0.25 m/s per axis) makes the true speed
    of a commanded 1 m/s circle swing between about 0.1 and 1.4 m/s; this one does not."""
    return float(np.linalg.norm(flight.server.call(lambda a: a.reported_velocity())[:2]))


def stopped_at(flight: Any, since: float, threshold: float = 0.1) -> float | None:
    """First trajectory time after ``since`` from which the speed stays below ``threshold``."""
    rec = flight.recorder
    with rec.lock:
        rows = [(t, v) for t, *_, v in rec.trajectory if t >= since]
    first = None
    for t, v in rows:
        if v >= threshold:
            first = None
        elif first is None:
            first = t
    return first


def estimated_stop_at(
    flight: Any,
    since: float,
    threshold: float = 0.1,
    settle: float = 0.5,
    settled_below: float = 0.2,
    timeout: float = 5.0,
) -> float:
    """Poll the autopilot's velocity estimate and return the first time after ``since`` it fell below
    ``threshold`` and then stayed below ``settled_below`` for ``settle`` s: the stop the autopilot
    flies when told to hold.

    The true speed is the wrong judge: a held vehicle drifts at its estimate's error (ArduPilot's
    calibrated sigma 0.03 m/s, up to 0.1 m/s at the tails), so the true speed can hover around
    ``threshold`` for seconds after the autopilot has stopped. Once stopped, ArduPilot's position
    loop also flies the vehicle back over its overshoot at about 0.1 m/s (``PSC_POSXY_P`` 1/s times
    a 0.1 m overshoot); that return is not braking, so it is judged against ``settled_below``.
    """
    first: float | None = None
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        now = time.monotonic()
        estimate = estimated_speed(flight)
        if estimate >= settled_below or (first is None and estimate >= threshold):
            first = None
        elif first is None:
            first = max(now, since)
        elif now - first >= settle:
            return first
        time.sleep(0.02)
    raise AssertionError(
        f"the autopilot's estimate did not fall under {threshold} m/s and stay under {settled_below} m/s"
        f" within {timeout} s"
    )


def companion_counters(flight: Any) -> str:
    """The companion's last counters log line."""
    lines = [line for line in flight.companion_log().splitlines() if " state=" in line]
    return lines[-1] if lines else ""


# ---- the companion's setpoints as the autopilot received them: (t, vx body m/s, yaw rate FRD rad/s)
Setpoint = tuple[float, float, float]
#: a setpoint equals a command within this, m/s and rad/s
COMMAND_TOLERANCE = 0.05
#: dt of the shield's first filter after an engagement (no previous one: companion.app._send), s
FIRST_FILTER_DT = 0.1
#: arrival jitter allowed when a ramp is judged on arrival times (a loaded autopilot loop reads late), s
ARRIVAL_JITTER = 0.05


def is_command(setpoint: Setpoint, command: tuple[float, float]) -> bool:
    """``setpoint`` is ``command`` (forward m/s, yaw rate FRD rad/s) within :data:`COMMAND_TOLERANCE`."""
    _, vx, yr = setpoint
    return abs(vx - command[0]) < COMMAND_TOLERANCE and abs(yr - command[1]) < COMMAND_TOLERANCE


def recorded_setpoints(flight: Any) -> list[Setpoint]:
    """A copy of every setpoint the autopilot received from the companion so far."""
    with flight.recorder.lock:
        return list(flight.recorder.setpoints)


def engagement_ramp(
    setpoints: list[Setpoint], command: tuple[float, float]
) -> tuple[list[Setpoint], Setpoint]:
    """The shield's ramp from standstill up to ``command`` after the companion engaged, and the
    first setpoint that is the command.

    Engaging (or leaving HOLD) starts the shield from standstill (``SafetyShield.reset``), and the
    command then grows no faster than ``max_accel`` / ``max_yaw_accel``: 0.2-0.3 s of setpoints
    that are not yet the command. The ramp is what came after the last full-zero setpoint (the
    pre-OFFBOARD stream or a HOLD) before the first command setpoint.

    :raises AssertionError: no setpoint is the command
    """
    first = next((i for i, s in enumerate(setpoints) if is_command(s, command)), None)
    assert first is not None, f"no setpoint is the command {command}: {setpoints[-10:]}"
    zeros = [i for i, (_, vx, yr) in enumerate(setpoints[:first]) if vx == 0.0 and yr == 0.0]
    start = zeros[-1] + 1 if zeros else 0
    return setpoints[start:first], setpoints[first]


def ramp_problem(
    ramp: list[Setpoint], first_command: Setpoint, command: tuple[float, float], max_accel: float,
    max_yaw_accel: float,
) -> str | None:
    """What makes ``ramp`` (then ``first_command``) more than the shield's acceleration ramp, or None.

    Each axis moves from zero monotonically toward its command without passing it, and no faster
    than the shield's limit: at arrival time t, |value| <= limit x (FIRST_FILTER_DT + t - t_first +
    ARRIVAL_JITTER), t_first the arrival of the ramp's first setpoint.
    """
    steps = [*ramp, first_command]
    t_first = steps[0][0]
    previous = (0.0, 0.0)
    for t, *values in steps:
        for axis, (value, target, last, limit) in enumerate(
            zip(values, command, previous, (max_accel, max_yaw_accel), strict=True)
        ):
            progress, last_progress = value / target, last / target
            if not -1e-6 <= progress <= 1.0 + COMMAND_TOLERANCE / abs(target):
                return f"setpoint {(t, *values)}: axis {axis} is not between standstill and {target}"
            if progress < last_progress - 1e-6:
                return f"setpoint {(t, *values)}: axis {axis} went back from {last} (not monotonic)"
            bound = limit * (FIRST_FILTER_DT + t - t_first + ARRIVAL_JITTER)
            if abs(value) > bound:
                return f"setpoint {(t, *values)}: axis {axis} grew faster than {limit}/s² (> {bound:.2f})"
        previous = (values[0], values[1])
    return None
