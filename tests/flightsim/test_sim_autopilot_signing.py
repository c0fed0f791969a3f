"""MAVLink 2 signing between the companion's ArduPilotLink and the simulated autopilots, over
real loopback sockets: both signed works; either end unsigned, or a wrong key, is dropped and
counted; SETUP_SIGNING installs a key as the firmware does; the unsigned exceptions are the
firmware's own (RADIO_STATUS on ArduPilot; RADIO_STATUS, ADSB_VEHICLE, COLLISION on PX4)."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.autopilot.ardupilot import ArduPilotLink
from companion.autopilot.signing import enable_signing
from flightsim.sitl.sim_autopilot.server import SimAutopilotServer
from flightsim.vehicle.quadrotor import Vehicle, VehicleConfig
from tests.companion.companion_process import wait_until
from tests.companion.mavlink_peer import AutopilotPeer, free_udp_port

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(101, 133))


@pytest.fixture(scope="module")
def vehicle():
    return Vehicle(VehicleConfig())  # loading JSBSim is the slow part: one for the module


def _wait(condition, timeout=5.0, what="condition"):
    return wait_until(condition, timeout, what)


class Rig:
    """A simulated autopilot sending to the companion's udpin port, and the companion's link."""

    def __init__(self, vehicle, personality="ardupilot", sim_key=None, link_key=None, extra_links=()):
        self.port = free_udp_port()
        self.server = SimAutopilotServer(personality, [f"udpout:127.0.0.1:{self.port}", *extra_links],
                                         vehicle=vehicle, signing_key=sim_key).start()
        self.link = ArduPilotLink(f"udpin:127.0.0.1:{self.port}", signing_key=link_key)

    def poll_until(self, condition, timeout=5.0, what="condition"):
        def check():
            status = self.link.poll()
            self.link.send_heartbeat()
            return status if condition(status) else None

        return _wait(check, timeout, what)

    def rx(self, kind: str) -> int:
        return self.server.autopilot.counters.get(f"rx_{kind}", 0)

    def close(self):
        self.link.close()
        self.server.stop()


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_both_signed_talk_and_every_frame_is_signed(vehicle, personality):
    rig = Rig(vehicle, personality, sim_key=KEY, link_key=KEY)
    try:
        status = rig.poll_until(lambda s: s.heartbeat_time is not None, what="the autopilot's heartbeat")
        assert status.mode != "UNKNOWN"
        rig.poll_until(lambda s: rig.rx("HEARTBEAT") >= 1, what="the companion's heartbeat at the autopilot")
        assert rig.server.endpoint.counters.get("signature_rejected", 0) == 0
        assert rig.link.counters["signature_rejected"] == 0
        rig.link.send_velocity(0.0, 0.0)
        _wait(lambda: rig.rx("SET_POSITION_TARGET_LOCAL_NED") >= 1, what="the setpoint at the autopilot")
    finally:
        rig.close()


def test_an_unsigned_companion_is_not_heard_by_a_signing_autopilot(vehicle):
    rig = Rig(vehicle, sim_key=KEY, link_key=None)
    try:
        rig.poll_until(lambda s: s.heartbeat_time is not None)  # it reads signed frames without checking
        rig.link.send_velocity(1.0, 0.0)
        _wait(lambda: rig.server.endpoint.counters.get("signature_rejected", 0) >= 2, what="rejections")
        assert rig.rx("HEARTBEAT") == 0 and rig.rx("SET_POSITION_TARGET_LOCAL_NED") == 0
    finally:
        rig.close()


@pytest.mark.parametrize("sim_key", [None, OTHER_KEY])
def test_a_signing_companion_ignores_an_unsigned_or_wrongly_keyed_autopilot(vehicle, sim_key):
    rig = Rig(vehicle, sim_key=sim_key, link_key=KEY)
    try:
        rig.poll_until(lambda s: rig.link.counters["signature_rejected"] >= 5, what="rejections")
        status = rig.link.poll()
        assert status.heartbeat_time is None and status.altitude is None and rig.link.target is None
    finally:
        rig.close()


def test_setup_signing_installs_the_key_and_unsigned_input_is_then_dropped(vehicle):
    """As with MAVProxy's `signing setup` (over USB): the key arrives in SETUP_SIGNING, after which
    only signed frames (and the firmware's unsigned exceptions) are taken."""
    gcs_port = free_udp_port()
    rig = Rig(vehicle, sim_key=None, link_key=KEY, extra_links=[f"udpin:127.0.0.1:{gcs_port}"])
    gcs = AutopilotPeer(f"udpout:127.0.0.1:{gcs_port}", sysid=255, compid=190)
    try:
        rig.poll_until(lambda s: rig.link.counters["signature_rejected"] >= 2, what="unsigned rejected")

        gcs.mav.setup_signing_send(1, 1, list(KEY), 0)
        _wait(lambda: rig.server.endpoint.counters.get("signing_key_set") == 1, what="key installed")
        status = rig.poll_until(lambda s: s.heartbeat_time is not None, what="signed heartbeat")
        assert status.mode != "UNKNOWN"
        rig.poll_until(lambda s: rig.rx("HEARTBEAT") >= 1, what="the companion heard")

        before = rig.server.endpoint.counters.get("signature_rejected", 0)
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        gcs.mav.radio_status_send(200, 190, 100, 50, 40, 0, 0)  # a telemetry radio's report
        _wait(lambda: rig.rx("RADIO_STATUS") == 1, what="RADIO_STATUS accepted unsigned")
        assert rig.server.endpoint.counters["signature_rejected"] == before + 1
        # the only COMMAND_LONGs taken are the link's own signed stream requests, never the GCS's arm
        _wait(lambda: rig.rx("COMMAND_LONG") == rig.link.counters["stream_requests"], timeout=1.0,
              what="the link's stream requests alone")
        assert not rig.server.autopilot.armed

        enable_signing(gcs.mav, KEY, link_id=3)  # the GCS with the key: heard again
        gcs.mav.setup_signing_send(1, 1, [0] * 32, 0)  # all zero: signing off
        _wait(lambda: rig.server.endpoint.counters.get("signing_disabled") == 1, what="signing off")
    finally:
        gcs.close()
        rig.close()


def test_px4_accepts_only_its_own_unsigned_exceptions(vehicle):
    port = free_udp_port()
    server = SimAutopilotServer("px4", [f"udpin:127.0.0.1:{port}"], vehicle=vehicle, signing_key=KEY).start()
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=255, compid=190)
    try:
        peer.mav.radio_status_send(200, 190, 100, 50, 40, 0, 0)
        peer.mav.collision_send(0, 1, 0, 1, 0.0, 0.0, 0.0)
        peer.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        peer.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        counters = server.autopilot.counters
        _wait(lambda: counters.get("rx_RADIO_STATUS") == 1 and counters.get("rx_COLLISION") == 1)
        _wait(lambda: server.endpoint.counters.get("signature_rejected") == 2)
        assert "rx_HEARTBEAT" not in counters and "rx_COMMAND_LONG" not in counters
    finally:
        peer.close()
        server.stop()


@pytest.mark.parametrize("sim_key", [KEY, None])
def test_px4_link_signs_mavsdk_frames_and_drops_unsigned_ones(vehicle, sim_key):
    """MAVSDK cannot sign; the PX4 link carries its frames through the companion's endpoint, which
    signs them on the way out and checks signatures on the way in."""
    from companion.autopilot.px4 import Px4Link

    port = free_udp_port()
    server = SimAutopilotServer("px4", [f"udpout:127.0.0.1:{port}"], vehicle=vehicle,
                                signing_key=sim_key).start()
    link = Px4Link(f"udpin://127.0.0.1:{port}", signing_key=KEY)
    try:
        if sim_key is None:
            _wait(lambda: link.poll() and link.counters["signature_rejected"] >= 10, what="rejections")
            assert link.poll().heartbeat_time is None and not link.connected
            return
        _wait(lambda: link.poll().heartbeat_time is not None and link.poll().mode != "UNKNOWN",
              what="PX4's status through MAVSDK")
        _wait(lambda: server.autopilot.counters.get("rx_HEARTBEAT", 0) >= 1, what="MAVSDK's heartbeat at PX4")
        link.send_velocity(0.0, 0.0)
        _wait(lambda: server.autopilot.counters.get("rx_SET_POSITION_TARGET_LOCAL_NED", 0) >= 1,
              what="a signed setpoint at PX4")
        assert server.endpoint.counters.get("signature_rejected", 0) == 0
        assert link.counters["signature_rejected"] == 0 and link.counters["unsignable_frames"] == 0
    finally:
        link.close()
        server.stop()


@pytest.mark.parametrize("signed_check", [True, False])
def test_start_up_parameter_check_signs_too(vehicle, tmp_path, signed_check):
    """[params_check] at start-up talks to a signing autopilot with the companion's key: it reads
    the real value (and refuses, naming it); unsigned, the autopilot never answers."""
    from tests.companion.companion_process import run_to_exit, write_config
    from tests.onnx_models import write_policy

    port = free_udp_port()
    key_file = tmp_path / "signing.key"
    key_file.write_text(KEY.hex())
    key_file.chmod(0o600)
    (tmp_path / "copter.parm").write_text("PRX1_TYPE 2\n")
    config = write_config(tmp_path, write_policy(tmp_path / "m.onnx"), free_udp_port(), port,
                          extra='[params_check]\nmode = "refuse"\nfile = "copter.parm"\ntimeout = 3.0\n')
    if signed_check:
        text = config.read_text().replace("[autopilot]\n", '[autopilot]\nsigning_key = "signing.key"\n')
        config.write_text(text)
    server = SimAutopilotServer("ardupilot", [f"udpout:127.0.0.1:{port}"], vehicle=vehicle,
                                signing_key=KEY).start()
    try:
        result = run_to_exit(["run", "--config", str(config)])
    finally:
        server.stop()
    assert result.returncode == 2, result.stderr[-2000:]
    last = result.stderr.strip().splitlines()[-1]
    if signed_check:
        assert "PRX1_TYPE: wanted 2, autopilot 0" in last
        assert server.endpoint.counters.get("signature_rejected", 0) == 0
    else:  # the requests were dropped: no value was read
        assert "autopilot 0" not in last
        assert server.endpoint.counters.get("signature_rejected", 0) > 0
