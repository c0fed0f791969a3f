"""Run a simulated autopilot in real time: MAVLink sockets + personality + the JSBSim vehicle.

One thread owns the vehicle and the sockets: it waits on the sockets until the next physics
chunk is due (so a message is handled as soon as it arrives, and its arrival time is exact),
then flies the chunk with the personality's setpoint and sends whatever the personality emits.
Other threads (the lidar co-simulation, a test) read :attr:`SimAutopilotServer.state` and use the
small control surface (:meth:`set_heartbeat_enabled`, :meth:`call`).

With ``ground_truth`` it also streams the simulator's truth after every physics chunk, as the real
SITLs do: SIMSTATE and SIM_STATE (ArduPilot SITL) or HIL_STATE_QUATERNION (PX4 SIH), so a harness judging
collisions of an external SITL finds the same messages here. ``avoid-sim autopilot`` runs the
server alone as its own process, the way an external SITL runs.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from flightsim.sitl.sim_autopilot.ardupilot import ArduCopterAutopilot
from flightsim.sitl.sim_autopilot.common import SimAutopilot
from flightsim.sitl.sim_autopilot.endpoint import MavlinkEndpoint, mavlink
from flightsim.sitl.sim_autopilot.frames import HOME_ALT_AMSL_M, enu_to_ned, lat_lon, yaw_enu_to_ned
from flightsim.sitl.sim_autopilot.params import default_table
from flightsim.sitl.sim_autopilot.px4 import PX4Autopilot
from flightsim.vehicle.quadrotor import Vehicle, VehicleConfig, VehicleState

log = logging.getLogger(__name__)

#: physics chunk flown per loop iteration: 3 steps of 1/120 s
CHUNK_S = 3 / 120

PERSONALITIES = {"ardupilot": ArduCopterAutopilot, "px4": PX4Autopilot}

MessageHook = Callable[[int, Any, float], None]
StepHook = Callable[[VehicleState], None]


def make_autopilot(
    personality: str, boot_time: float, response: bool = True, position_delay: float = 0.0,
    altitude_drift: float = 0.0,
) -> SimAutopilot:
    """A personality (``"ardupilot"`` or ``"px4"``) with its firmware's default parameter table;
    ``response`` False flies setpoints as given (the ideal autopilot) instead of the firmware's response;
    ``position_delay`` s pass before it reports a position; its altitude estimate drifts
    ``altitude_drift`` m from the truth after arming."""
    return PERSONALITIES[personality](
        default_table(personality), boot_time=boot_time, response=response, position_delay=position_delay,
        altitude_drift=altitude_drift,
    )


def ground_truth_messages(
    personality: str, autopilot: SimAutopilot, state: VehicleState, now: float
) -> list[Any]:
    """The simulator's truth as the real SITL sends it: ArduPilot SITL's SIMSTATE (attitude, gyro,
    lat/lng: no altitude) and SIM_STATE (its altitude, AMSL), or PX4 SIH's HIL_STATE_QUATERNION
    (quaternion, rates, lat/lon/alt, NED velocity)."""
    rel = state.position - autopilot.home
    lat, lon = lat_lon(rel)
    roll, pitch, yaw = state.roll, -state.pitch, yaw_enu_to_ned(state.yaw)  # NED/FRD, as MAVLink
    p, q, r = (float(x) for x in state.angular_rate)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    quaternion = [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                  cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]
    vn, ve, vd = enu_to_ned(state.velocity)
    alt = HOME_ALT_AMSL_M + float(rel[2])
    if personality == "ardupilot":
        return [
            mavlink.MAVLink_simstate_message(roll, pitch, yaw, 0.0, 0.0, -9.81, p, -q, -r, lat, lon),
            mavlink.MAVLink_sim_state_message(*quaternion, roll, pitch, yaw, 0.0, 0.0, -9.81, p, -q, -r,
                                              lat * 1e-7, lon * 1e-7, alt, 0.0, 0.0, vn, ve, vd, lat, lon),
        ]
    return [mavlink.MAVLink_hil_state_quaternion_message(
        int(now * 1e6), quaternion, p, -q, -r, lat, lon, round(alt * 1000),
        round(vn * 100), round(ve * 100), round(vd * 100), 0, 0, 0, 0, -1000
    )]


class SimAutopilotServer:
    """A simulated flight controller flying a :class:`~flightsim.vehicle.quadrotor.Vehicle` in real time.

    :param personality: ``"ardupilot"`` or ``"px4"``
    :param links: endpoint connection strings (see :mod:`flightsim.sitl.sim_autopilot.endpoint`)
    :param start_position: (3,) world ENU where the vehicle rests on the floor
    :param start_yaw: rad, counter-clockwise from East
    :param params: parameter overrides applied before the first message (name -> value)
    :param vehicle: an existing vehicle to reuse (JSBSim load is the slow part); reset here
    :param signing_key: MAVLink 2 signing secret the autopilot starts with (as if installed
        earlier with SETUP_SIGNING); None = unsigned until a SETUP_SIGNING arrives
    :param ground_truth: stream the simulator's truth on every link after each physics chunk
    :param response: fly the firmware's calibrated response (False: the ideal autopilot)
    :param position_delay: seconds before the autopilot reports a position (its EKF origin) and
        lets itself be armed
    :param altitude_drift: the altitude estimate's error after arming, m (it flies its estimate)
    """

    def __init__(
        self,
        personality: str,
        links: list[str],
        start_position: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
        start_yaw: float = 0.0,
        params: dict[str, float] | None = None,
        vehicle: Vehicle | None = None,
        signing_key: bytes | None = None,
        ground_truth: bool = False,
        response: bool = True,
        position_delay: float = 0.0,
        altitude_drift: float = 0.0,
    ) -> None:
        self.endpoint = MavlinkEndpoint(links, signing_key=signing_key,
                                        accept_unsigned=PERSONALITIES[personality].UNSIGNED_ACCEPTED)
        self.personality = personality
        self.ground_truth = ground_truth
        self.t0 = time.monotonic()
        self.autopilot = make_autopilot(personality, boot_time=0.0, response=response,
                                        position_delay=position_delay, altitude_drift=altitude_drift)
        for name, value in (params or {}).items():
            self.autopilot.params.set(name, value)
        self.vehicle = vehicle or Vehicle(VehicleConfig())
        self.state: VehicleState = self.vehicle.reset(start_position, start_yaw, on_ground=True)
        self.autopilot.observe(self.state)
        for link in range(self.endpoint.link_count):
            self.autopilot.add_link(link)
        self.message_hooks: list[MessageHook] = []
        self.step_hooks: list[StepHook] = []
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def now(self) -> float:
        """The autopilot's clock: seconds since this server was created."""
        return time.monotonic() - self.t0

    # ----------------------------------------------------------------- control surface
    def call(self, fn: Callable[[SimAutopilot], Any]) -> Any:
        """Run ``fn(autopilot)`` under the loop's lock and send what it returns (a list of Outgoing)."""
        with self._lock:
            result = fn(self.autopilot)
            if isinstance(result, list):
                self._send(result)
            return result

    def set_heartbeat_enabled(self, enabled: bool) -> None:
        """Stop (or resume) this autopilot's HEARTBEATs, as if its link to the companion died."""
        with self._lock:
            self.autopilot.heartbeat_enabled = enabled

    # ----------------------------------------------------------------- loop
    def start(self) -> SimAutopilotServer:
        self._thread = threading.Thread(target=self._run, name="sim-autopilot", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self.endpoint.close()

    def __enter__(self) -> SimAutopilotServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _send(self, outgoing: list[Any]) -> None:
        for out in outgoing:
            self.endpoint.send(out.link, out.message)

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:  # surfaced to the harness, which reports it
            log.exception("simulated autopilot stopped")
            self.error = exc

    def _loop(self) -> None:
        next_step = self.now()
        with self._lock:
            self._send(self.autopilot.tick(next_step))
        while not self._stop.is_set():
            for link, msg, rx in self.endpoint.poll(next_step - self.now()):
                t = rx - self.t0
                for hook in self.message_hooks:
                    hook(link, msg, t)
                with self._lock:
                    self._send(self.autopilot.handle(msg, link, t))
            now = self.now()
            if now < next_step:
                continue
            with self._lock:
                armed, setpoint = self.autopilot.flight_command(now)
                if armed != self.state.armed:
                    self.vehicle.set_armed(armed)
                self.state = self.vehicle.step(setpoint, CHUNK_S)
                self.autopilot.observe(self.state)
                self._send(self.autopilot.tick(now))
                if self.ground_truth:
                    for truth in ground_truth_messages(self.personality, self.autopilot, self.state, now):
                        for link in range(self.endpoint.link_count):
                            self.endpoint.send(link, truth)
            for hook in self.step_hooks:
                hook(self.state)
            next_step += CHUNK_S
            if now - next_step > 0.5:  # fell far behind (a stalled machine): do not sprint to catch up
                log.warning("simulated autopilot fell %.2f s behind real time", now - next_step)
                self.autopilot.count("overruns")
                next_step = now


# ------------------------------------------------------------------------------------ CLI
def configure_parser(parser: Any) -> None:
    """``avoid-sim autopilot``: a simulated autopilot alone, for a GCS or ``fly --autopilot external``."""
    parser.add_argument(
        "--personality",
        choices=sorted(PERSONALITIES),
        default="ardupilot",
        help="firmware to imitate (ardupilot)",
    )
    parser.add_argument(
        "--link",
        action="append",
        default=[],
        help="udpin:HOST:PORT | udpout:HOST:PORT | tcpin:HOST:PORT; repeatable "
        "(default tcpin:127.0.0.1:5760, like ArduPilot SITL)",
    )
    parser.add_argument("--start-yaw", type=float, default=0.0, metavar="DEG",
                        help="initial heading, degrees counter-clockwise from East (0)")
    parser.add_argument("--no-ground-truth", action="store_true",
                        help="do not stream SIMSTATE / HIL_STATE_QUATERNION (a SITL that sends no truth)")
    parser.add_argument("--position-delay", type=float, default=0.0, metavar="S",
                        help="report no position (no EKF origin: no LOCAL_POSITION_NED, GLOBAL_POSITION_INT, "
                        "HOME_POSITION) and refuse to arm for the first S seconds, as a fresh ArduPilot "
                        "SITL does for about 40 s (0)")
    parser.add_argument("--altitude-drift", type=float, default=0.0, metavar="M",
                        help="the altitude estimate ends up M metres above the truth (negative: below) "
                        "20 s after arming, and the autopilot flies its estimate (0)")
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set a parameter before start, e.g. COM_OBL_RC_ACT=5; repeatable",
    )
    parser.add_argument(
        "--signing-key",
        metavar="FILE",
        help="MAVLink 2 signing key file (64 hex digits, mode 0600, as the companion's "
        "autopilot.signing_key): sign everything, drop unsigned input",
    )
    parser.add_argument(
        "--ideal-response",
        action="store_true",
        help="fly velocity setpoints as given, not with the firmware's calibrated (slower) response",
    )


def command(args: Any) -> int:
    from companion.common.errors import UserError

    params: dict[str, float] = {}
    for item in args.param:
        name, sep, value = item.partition("=")
        try:
            params[name.strip()] = float(value)
        except ValueError:
            raise UserError(f"--param {item!r}: expected NAME=NUMBER") from None
        if not sep:
            raise UserError(f"--param {item!r}: expected NAME=NUMBER")
    known = set(default_table(args.personality).names())
    for name in params:
        if name not in known:
            raise UserError(f"--param {name}: not a parameter of the {args.personality} table")
    if not (math.isfinite(args.position_delay) and args.position_delay >= 0):
        raise UserError(f"--position-delay must be a non-negative number of seconds, "
                        f"got {args.position_delay}")
    if not (math.isfinite(args.altitude_drift) and abs(args.altitude_drift) <= 10.0):
        raise UserError(f"--altitude-drift must be within ±10 m, got {args.altitude_drift}")
    if not math.isfinite(args.start_yaw):
        raise UserError(f"--start-yaw must be a finite number of degrees, got {args.start_yaw}")

    from companion.autopilot.signing import load_signing_key

    key = load_signing_key(args.signing_key, "--signing-key") if args.signing_key else None
    server = SimAutopilotServer(
        args.personality,
        args.link or ["tcpin:127.0.0.1:5760"],
        start_yaw=math.radians(args.start_yaw),
        params=params,
        signing_key=key,
        ground_truth=not args.no_ground_truth,
        response=not args.ideal_response,
        position_delay=args.position_delay,
        altitude_drift=args.altitude_drift,
    )
    stop = threading.Event()
    # Ctrl-C, or a supervisor's/test's SIGTERM; the caller's handlers come back on return, so a
    # caller in the same process (a test, a script) is not left with a Ctrl-C that does nothing
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with server:
            links = ", ".join(args.link or ["tcpin:127.0.0.1:5760"])
            print(f"simulated {args.personality} running on {links}; Ctrl-C stops it", flush=True)
            while server.error is None and not stop.wait(0.5):
                pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0 if server.error is None else 1
