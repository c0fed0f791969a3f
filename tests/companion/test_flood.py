"""The real companion process under 10,000 hostile lidar datagrams a second keeps its setpoint stream.

The real VLP-16 recording plays at the sensor's pace from the sensor's address (127.0.0.1, the
configured ``sensor_ip``) while another process floods the lidar port with one kind of hostile
traffic at a time (tests/companion/lidar_flood.py: garbage, well-formed packets from a foreign address,
the same forged from the sensor's address, the recording replayed). Setpoints are stamped by the
kernel as they reach the autopilot's socket, so the figures are what the companion emitted. Where
this user may (root or CAP_SYS_NICE), the companion runs SCHED_FIFO 20 as its systemd unit runs it,
and the traffic senders and the autopilot's loop run at nice -10 (an autopilot and a sensor are not
starved of the processor by other work; on a shared test machine at a load of 10 on two cores they
would be, and the test would measure the machine instead of the companion). Not real-time: that
would starve the kernel's softirq threads, which deliver loopback datagrams under a flood.

The stream under each flood is judged against the same run's stream without one (a window of the
same length just before): the rate must hold to 95 % of it, and no gap may reach two of its periods,
i.e. no setpoint is lost. A wall-clock bound would measure the machine (it missed 150 ms by 2 ms once
on a loaded two-core machine); the absolute figures and the 150 ms target are bench/bench_flood.py's.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from tests.companion.companion_process import (
    free_udp_port,
    start_companion,
    start_lidar_traffic,
    stop,
    write_config,
)
from tests.companion.lidar_flood import FLOOD_KINDS
from tests.companion.mavlink_peer import SETPOINT, StampingAutopilot
from tests.onnx_models import write_policy

FLOOD_RATE = 10_000
FLOOD_SECONDS = 5.0


def setpoint_figures(autopilot: StampingAutopilot, start: float, end: float) -> tuple[float, float, float]:
    """(setpoints per second, longest gap, median gap in s) within [start, end), the edges included."""
    stamps = [t for t, _ in autopilot.messages(SETPOINT, start, end)]
    gaps = np.diff([start, *stamps, end])
    return len(stamps) / (end - start), float(gaps.max()), float(np.median(gaps))


@pytest.fixture
def rig(tmp_path):
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config = write_config(tmp_path, model, lidar_port, mavlink_port, sensor_ip="127.0.0.1")
    autopilot = StampingAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    log = tmp_path / "companion.log"
    proc = start_companion(config, realtime=True, log=log)  # SCHED_FIFO as the service runs it
    player = start_lidar_traffic(lidar_port, "--play", "1:60", favoured=True)
    yield autopilot, proc, lidar_port
    player.kill()
    player.communicate()
    if proc.poll() is None:
        stop(proc)
    print(log.read_text()[-5000:])  # the companion's log, shown when a test fails
    autopilot.close()


def test_setpoints_keep_their_rate_under_a_flood_of_every_kind(rig):
    autopilot, proc, lidar_port = rig
    autopilot.run(20.0, until=lambda m: m.get_type() == SETPOINT, favoured=True)
    assert autopilot.messages(SETPOINT), "the companion never engaged on the recording"
    autopilot.run(1.0, favoured=True)
    start = time.monotonic()
    autopilot.run(FLOOD_SECONDS, favoured=True)
    reference_rate, reference_gap, period = setpoint_figures(autopilot, start, time.monotonic())
    figures = {}
    for kind in FLOOD_KINDS:
        flood = start_lidar_traffic(lidar_port, "--flood", kind, "--rate", str(FLOOD_RATE),
                                    "--seconds", str(FLOOD_SECONDS), favoured=True)
        autopilot.run_while(flood, favoured=True)
        report = json.loads(flood.communicate(timeout=10)[0])
        start, end = report["start"], report["end"]
        rate, gap, _ = setpoint_figures(autopilot, start, end)
        texts = [m.text for _, m in autopilot.messages("STATUSTEXT", start, end)]
        figures[kind] = (report["sent"] / (end - start), rate, gap, texts)
    print(f"no flood: {reference_rate:.2f} setpoints/s, longest gap {reference_gap * 1e3:.0f} ms", figures)
    assert proc.poll() is None, "the companion died"
    for kind, (sent_rate, rate, gap, _) in figures.items():
        assert sent_rate >= 0.95 * FLOOD_RATE, f"{kind}: the flood reached only {sent_rate:.0f}/s"
        assert rate >= 0.95 * reference_rate and gap < 2 * period, (
            f"{kind}: {rate:.2f} setpoints/s, longest gap {gap * 1e3:.0f} ms; without a flood "
            f"{reference_rate:.2f}/s, period {period * 1e3:.0f} ms"
        )
    # garbage and strangers are dropped: the companion flies on the real scans throughout
    assert not [t for k in ("garbage", "foreign") for t in figures[k][3] if "HOLD" in t]
    # forged packets from the sensor's own address leave no whole turn: it holds (zero setpoints)
    assert any("ACTIVE->HOLD" in t for t in figures["forged"][3])


def test_more_turns_a_second_than_the_sensor_makes_hold_until_the_pace_is_real_again(tmp_path):
    """The real recording replayed at 2.5× (25 whole turns a second, a VLP-16 makes 20 at most)."""
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config = write_config(tmp_path, model, lidar_port, mavlink_port, sensor_ip="127.0.0.1")
    autopilot = StampingAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    proc = start_companion(config, realtime=True, log=tmp_path / "companion.log")
    player = None
    try:
        autopilot.run(3.0, favoured=True)  # the companion starts up and hears the autopilot
        player = start_lidar_traffic(lidar_port, "--play", "1:5,2.5:3,1:6", favoured=True)
        autopilot.run_while(player, favoured=True)
        player.communicate(timeout=10)
    finally:
        if player is not None and player.poll() is None:
            player.kill()
        stop(proc)
        autopilot.close()
    log = (tmp_path / "companion.log").read_text()
    texts = [m.text.removeprefix("avoid ") for _, m in autopilot.messages("STATUSTEXT")]
    changes = [t for t in texts if "->" in t]
    assert "ACTIVE->HOLD: lidar implausible" in changes, (changes, log[-3000:])
    held = changes.index("ACTIVE->HOLD: lidar implausible")
    assert changes[held - 1] == "STANDBY->ACTIVE: engaged"  # on the real pace, before the replay
    after = changes[held + 1 :]  # back at the sensor's pace; a last "lidar stale" once it stops
    assert after[0] == "HOLD->ACTIVE: recovered (5 good scans)"
    assert after[1:] in ([], ["ACTIVE->HOLD: lidar stale"])
    assert "lidar.implausible_revolutions=" in log
