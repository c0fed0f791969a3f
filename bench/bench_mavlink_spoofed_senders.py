"""What thousands of spoofed UDP source addresses cost each setpoint, companion link vs plain pymavlink.

pymavlink's ``udpin`` connection writes every frame to every address that ever sent it a datagram
and never forgets one; the issue measured the companion's setpoint rate falling to 7.1 Hz after
20,000 spoofed addresses. ``ArduPilotLink`` replies only to the address of the autopilot's
heartbeats. This script sends one 6-byte datagram from each of ``--senders`` source addresses
(127.0.x.y, all loopback on Linux) to each of two listeners:

- reference: a plain ``mavutil.mavlink_connection("udpin:...")``, as the link used to be;
- the companion's ``ArduPilotLink`` (udpin), with an autopilot peer that has sent a heartbeat;

then times ``--sends`` SET_POSITION_TARGET_LOCAL_NED sends on each (best of 5), before and after.
Prints setpoints/s and the ratio after/before for both (1.0 = the flood costs nothing).

    python bench/bench_mavlink_spoofed_senders.py [--senders 20000] [--sends 2000]
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pymavlink import mavutil  # noqa: E402

from companion.autopilot.ardupilot import ArduPilotLink  # noqa: E402
from companion.autopilot.mavlink_adapter import mavlink  # noqa: E402
from tests.companion.mavlink_peer import AutopilotPeer, free_udp_port  # noqa: E402


def flood(port: int, senders: int, drain) -> None:
    """One tiny datagram from each of ``senders`` addresses; ``drain()`` reads them as they come."""
    for i in range(senders):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind((f"127.{1 + i // 62500}.{(i // 250) % 250 + 1}.{i % 250 + 1}", 0))
            s.sendto(b"\xfd\x00\x00\x00\x00\x00", ("127.0.0.1", port))
        if i % 100 == 99:
            drain()
    drain()


def rate(send, n: int, repeats: int = 5) -> float:
    """Sends per second: the best of ``repeats`` runs of ``n`` (the machine is shared)."""
    best = 0.0
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            send()
        best = max(best, n / (time.perf_counter() - t0))
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--senders", type=int, default=20000)
    parser.add_argument("--sends", type=int, default=2000)
    args = parser.parse_args()

    # reference: plain pymavlink udpin
    port = free_udp_port()
    plain = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191)
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}")
    peer.heartbeat()
    time.sleep(0.05)
    while plain.recv_msg() is not None:
        pass

    def plain_send() -> None:
        plain.mav.set_position_target_local_ned_send(0, 1, 1, mavlink.MAV_FRAME_BODY_OFFSET_NED, 0x05C7,
                                                     0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0)

    def plain_drain() -> None:
        while plain.recv():  # every datagram: pymavlink adds its source to the reply list
            pass

    plain_before = rate(plain_send, args.sends)
    flood(port, args.senders, plain_drain)
    plain_after = rate(plain_send, max(1, args.sends // 200))  # thousands of sendto each: fewer sends
    clients = len(plain.clients)
    plain.close()
    peer.close()

    # the companion's link
    port = free_udp_port()
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}")
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}")
    peer.heartbeat()
    deadline = time.monotonic() + 3
    while link.poll().heartbeat_time is None and time.monotonic() < deadline:
        time.sleep(0.01)

    def link_send() -> None:
        link.send_velocity(1.0, 0.0)

    link_before = rate(link_send, args.sends)
    flood(port, args.senders, link.poll)
    link_after = rate(link_send, args.sends)
    garbage = link.counters["bad_data"]
    link.close()
    peer.close()

    print(f"{args.senders} spoofed source addresses, one 6-byte datagram each")
    print(f"  plain pymavlink udpin: {plain_before:9.0f} setpoints/s before, {plain_after:9.1f} after "
          f"({clients} addresses written to per frame): ratio {plain_after / plain_before:.4f}")
    print(f"  ArduPilotLink        : {link_before:9.0f} setpoints/s before, {link_after:9.0f} after "
          f"({garbage} datagrams counted as bad_data): ratio {link_after / link_before:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
