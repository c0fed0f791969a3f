"""Hostile MAVLink against the real ``avoid-companion run`` process over loopback: an impostor
system claiming GUIDED and armed, and a sender flapping modes at 20 Hz with the autopilot's ids."""

from __future__ import annotations

import threading
import time

import pytest

from tests.companion.companion_process import LidarSender, free_udp_port, start_companion, stop, write_config
from tests.companion.companion_process import wait_until as _wait
from tests.companion.mavlink_peer import COPTER_GUIDED, COPTER_LOITER, SETPOINT, SimulatedAutopilot
from tests.onnx_models import write_policy


@pytest.fixture
def companion(tmp_path):
    """Start the companion (forward policy, lidar streaming); yields its MAVLink port and a list
    the test appends its simulated vehicles to (closed at the end)."""
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config = write_config(tmp_path, model, lidar_port, mavlink_port)
    proc = start_companion(config)
    lidar = LidarSender(lidar_port)
    lidar.on = True
    vehicles: list[SimulatedAutopilot] = []
    yield mavlink_port, vehicles
    lidar.close()
    _code, _out, err = stop(proc)
    for vehicle in vehicles:
        vehicle.close()
    assert "Traceback" not in err, err[-3000:]


def test_an_impostor_claiming_guided_and_armed_never_gets_a_setpoint(companion):
    port, vehicles = companion
    impostor = SimulatedAutopilot(f"udpout:127.0.0.1:{port}", sysid=42)  # GUIDED, armed, flying
    vehicles.append(impostor)
    time.sleep(3.0)  # lidar streaming, the impostor's heartbeats at 10 Hz: long enough to engage
    assert impostor.messages(SETPOINT) == []
    assert impostor.messages() == [], "nothing at all goes to an address that is not the autopilot's"
    autopilot = SimulatedAutopilot(f"udpout:127.0.0.1:{port}", sysid=1)
    vehicles.append(autopilot)
    first = _wait(lambda: autopilot.wait_for(SETPOINT, timeout=0.1), what="setpoints to the real autopilot")
    assert (first.target_system, first.target_component) == (1, 1)
    time.sleep(0.5)
    assert impostor.messages(SETPOINT) == []


def test_mode_flapping_at_20_hz_is_debounced(companion):
    """With the autopilot's own ids, GUIDED/LOITER every 50 ms for 4 s: a handful of STATUSTEXTs
    (the issue measured 563 in 10 s), no setpoints while it lasts, engaged again once it stops."""
    port, vehicles = companion
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{port}", rate_hz=40.0)
    vehicles.append(vehicle)
    _wait(lambda: vehicle.wait_for(SETPOINT, timeout=0.1), what="engaged")
    stop_flapping = threading.Event()

    def flap() -> None:
        while not stop_flapping.wait(0.05):
            vehicle.custom_mode = COPTER_LOITER if vehicle.custom_mode == COPTER_GUIDED else COPTER_GUIDED

    t0 = time.monotonic()
    flapper = threading.Thread(target=flap, daemon=True)
    flapper.start()
    time.sleep(4.0)
    stop_flapping.set()
    flapper.join()
    vehicle.custom_mode = COPTER_GUIDED
    t_end = time.monotonic()
    # one text per announcement: a MAVLink 2 STATUSTEXT over 50 bytes comes in chunks (chunk_seq 1, 2, ...)
    texts = [m.text for m in vehicle.messages("STATUSTEXT", since=t0) if getattr(m, "chunk_seq", 0) == 0]
    assert 1 <= len(texts) <= 4, texts
    assert any("PILOT_OVERRIDE" in t for t in texts)
    setpoints = vehicle.times(SETPOINT, since=t0 + 0.3)  # the override takes effect within a loop or two
    assert [t for t in setpoints if t < t_end] == []
    _wait(lambda: vehicle.wait_for(SETPOINT, timeout=0.1, since=t_end), what="re-engaged after the flapping")
