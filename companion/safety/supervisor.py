"""The supervisor: decides whether the companion may command the vehicle, and what to send.

A pure state machine with an injected clock (ARCHITECTURE.md, "The supervisor"). The application
feeds it scans (:meth:`Supervisor.on_scan`) and vehicle status (:meth:`Supervisor.on_vehicle`),
calls :meth:`Supervisor.tick` once per loop and sends what it answers. It never changes the
autopilot's mode: the pilot (or the autopilot's own failsafes) own that.

::

    STARTING ─start()→ WAITING_FOR_AUTOPILOT ─heartbeat→ STANDBY ─all engage conditions→ ACTIVE
    ACTIVE ─lidar stale / inference fault / velocity stale→ HOLD ─recover_scans good scans→ ACTIVE
    ACTIVE, HOLD ─mode left GUIDED/OFFBOARD→ PILOT_OVERRIDE ─mode back to GUIDED/OFFBOARD→ STANDBY
    ACTIVE, HOLD ─disarmed / landed / landing→ STANDBY
    any (but STARTING) ─heartbeat lost→ WAITING_FOR_AUTOPILOT

Flapping input (a mode switched back and forth, a link dropping in and out) is debounced: leaving
ACTIVE/HOLD is always immediate (the pilot's override takes effect at the next tick), but once
the companion has stopped commanding it engages again only after every engage condition has held
for ``reengage_delay``. Announcements (log line + STATUSTEXT) are rate-limited to a burst of
``announce_burst`` and one per ``announce_interval`` after it; the ones left out are counted and
summed up in one "N transitions not announced" line that brings the pilot's view up to date.

Engaging needs: armed, guided, airborne (landed_state IN_AIR where the autopilot reports it, never
TAKEOFF), altitude ≥ ``min_engage_altitude``, the climb settled (|climb rate| <
``climb_settled_rate`` for ``climb_settled_time``), the lidar fresh with ``recover_scans``
consecutive good scans, the measured velocity fresh (the shield watches where the vehicle really
goes, so it never flies without it). On ArduPilot a velocity setpoint ends GUIDED's take-off, so engaging
during the climb would freeze the vehicle at whatever height it had reached: hence the settling.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

from companion.autopilot.link import LandedState, VehicleStatus


class SupervisorState(str, Enum):
    """Where the supervisor is; the value is what logs and STATUSTEXT show."""

    STARTING = "STARTING"
    WAITING_FOR_AUTOPILOT = "WAITING_FOR_AUTOPILOT"
    STANDBY = "STANDBY"
    ACTIVE = "ACTIVE"
    HOLD = "HOLD"
    PILOT_OVERRIDE = "PILOT_OVERRIDE"


class CommandKind(Enum):
    """What the application sends this loop, besides HEARTBEAT and OBSTACLE_DISTANCE."""

    NONE = "none"  # no setpoints at all
    POLICY = "policy"  # the shielded policy setpoint
    ZERO = "zero"  # zero-velocity setpoints (hover in place)


_COMMAND_FOR_STATE = {
    SupervisorState.STARTING: CommandKind.NONE,
    SupervisorState.WAITING_FOR_AUTOPILOT: CommandKind.NONE,
    SupervisorState.STANDBY: CommandKind.NONE,
    SupervisorState.ACTIVE: CommandKind.POLICY,
    SupervisorState.HOLD: CommandKind.ZERO,
    SupervisorState.PILOT_OVERRIDE: CommandKind.NONE,
}


@dataclass(frozen=True)
class SupervisorConfig:
    """Timeouts and engage conditions (the ``[supervisor]`` table of the companion config).

    :param lidar_timeout: no scan for longer than this is "lidar stale", s
    :param recover_scans: consecutive good scans needed to engage or to leave HOLD
    :param heartbeat_timeout: no autopilot HEARTBEAT for longer than this is "heartbeat lost", s
    :param min_engage_altitude: metres above home below which the companion never engages
    :param climb_settled_rate: |climb rate| below this counts as settled, m/s
    :param climb_settled_time: the climb must stay settled this long before engaging, s
    :param reengage_delay: after the companion stopped commanding, every engage condition must hold
        this long before it engages again, s (a mode flapping faster never re-engages)
    :param announce_burst: transitions announced back to back before the rate limit applies
    :param announce_interval: one more announcement per this many seconds once the burst is spent
    :param velocity_timeout: a measured velocity older than this (or none) is "velocity stale", s
    """

    lidar_timeout: float = field(default=0.3, metadata={"min": 0.05, "max": 5.0})
    recover_scans: int = field(default=5, metadata={"min": 1, "max": 100})
    heartbeat_timeout: float = field(default=2.0, metadata={"min": 0.5, "max": 30.0})
    min_engage_altitude: float = field(default=1.0, metadata={"min": 0.0, "max": 1000.0})
    climb_settled_rate: float = field(default=0.3, metadata={"min": 0.01, "max": 10.0})
    climb_settled_time: float = field(default=1.0, metadata={"min": 0.0, "max": 60.0})
    reengage_delay: float = field(default=1.0, metadata={"min": 0.0, "max": 60.0})
    announce_burst: int = field(default=10, metadata={"min": 1, "max": 100})
    announce_interval: float = field(default=1.0, metadata={"min": 0.0, "max": 60.0})
    velocity_timeout: float = field(default=0.5, metadata={"min": 0.05, "max": 5.0})


@dataclass(frozen=True)
class Transition:
    """One state change.

    :param time: clock time it happened
    :param old: state before
    :param new: state after
    :param reason: short cause, fits a STATUSTEXT with the state names; its part before any
        " (" is a fixed phrase, counted in :attr:`Supervisor.counters`
    """

    time: float
    old: SupervisorState
    new: SupervisorState
    reason: str

    def __str__(self) -> str:
        return f"{self.old.value}->{self.new.value}: {self.reason}"


class Supervisor:
    """The companion's state machine.

    :param config: timeouts and engage conditions
    :param clock: monotonic time source in seconds (the same clock the links stamp heartbeats with)
    """

    def __init__(self, config: SupervisorConfig, clock: Callable[[], float]) -> None:
        self.config = config
        self._clock = clock
        self.state = SupervisorState.STARTING
        self.counters: collections.Counter[str] = collections.Counter()
        self._transitions: list[Transition] = []
        self._status = VehicleStatus()
        self._last_scan_time: float | None = None
        self._good_scans = 0
        self._scan_problem: str | None = None  # a fault or gap since the last tick, not yet acted on
        self._settled_since: float | None = None
        self._disengaged = False  # stopped commanding at least once: re-engaging is debounced
        self._clear_since: float | None = None  # engage conditions held continuously since
        self._announce_tokens = float(config.announce_burst)
        self._announce_time = clock()
        self._announced_state = self.state
        self._not_announced = 0

    # ---- inputs -------------------------------------------------------------------------------

    def start(self) -> None:
        """The model is loaded and the links are open: start looking for the autopilot."""
        if self.state is SupervisorState.STARTING:
            self._good_scans = 0
            self._go(SupervisorState.WAITING_FOR_AUTOPILOT, "started")

    def on_scan(self, ok: bool, fault: str = "inference fault") -> None:
        """A scan arrived.

        :param ok: False when inference on it faulted (exception, NaN/Inf output), or the lidar
            source judged its input implausible
        :param fault: the HOLD reason when not ``ok``
        """
        now = self._clock()
        last, self._last_scan_time = self._last_scan_time, now
        if last is not None and now - last > self.config.lidar_timeout:
            # a gap, even one no tick saw, restarts the count of good scans
            self._good_scans = 0
            self._scan_problem = "lidar stale"
            self.counters["scan_gaps"] += 1
        if ok:
            self._good_scans += 1
            self.counters["scans_ok"] += 1
        else:
            self._good_scans = 0
            self._scan_problem = fault
            self.counters["scans_faulted"] += 1

    def on_vehicle(self, status: VehicleStatus) -> None:
        """The latest vehicle status from the autopilot link."""
        now = self._clock()
        self._status = status
        rate = status.climb_rate
        if rate is None or not abs(rate) < self.config.climb_settled_rate:
            self._settled_since = None
        elif self._settled_since is None:
            self._settled_since = now

    # ---- decisions ----------------------------------------------------------------------------

    def tick(self) -> CommandKind:
        """Check timeouts and conditions, make at most the transitions they call for, say what to send."""
        now = self._clock()
        problem, self._scan_problem = self._scan_problem, None
        state = self.state
        if state is SupervisorState.STARTING:
            return CommandKind.NONE
        heartbeat_fresh = self._heartbeat_fresh(now)
        if state is SupervisorState.WAITING_FOR_AUTOPILOT:
            if heartbeat_fresh:
                self._go(SupervisorState.STANDBY, "autopilot heartbeat")
                self._try_engage(now)
        elif not heartbeat_fresh:
            self._go(SupervisorState.WAITING_FOR_AUTOPILOT, "autopilot heartbeat lost")
        elif state is SupervisorState.STANDBY:
            self._try_engage(now)
        elif state is SupervisorState.PILOT_OVERRIDE:
            if self._status.guided:
                self._go(SupervisorState.STANDBY, "mode back to guided", self._status.mode)
                self._try_engage(now)
        else:  # ACTIVE or HOLD
            self._while_commanding(now, problem)
        return _COMMAND_FOR_STATE[self.state]

    def drain_transitions(self) -> list[Transition]:
        """Transitions to announce since the last call, oldest first (the app logs and STATUSTEXTs each).

        Rate-limited (a token bucket of ``announce_burst``, refilled one per ``announce_interval``):
        once transitions had to be left out, the next announcement is one summary transition from
        the last announced state to the current one, naming how many were left out.
        """
        now = self._clock()
        cfg = self.config
        if cfg.announce_interval > 0:
            refill = (now - self._announce_time) / cfg.announce_interval
        else:
            refill = math.inf
        self._announce_tokens = min(float(cfg.announce_burst), self._announce_tokens + refill)
        self._announce_time = now
        pending, self._transitions = self._transitions, []
        out: list[Transition] = []
        for transition in pending:
            if self._not_announced == 0 and self._announce_tokens >= 1.0:
                self._announce_tokens -= 1.0
                self._announced_state = transition.new
                out.append(transition)
            else:
                self._not_announced += 1
                self.counters["transitions_not_announced"] += 1
        if self._not_announced and self._announce_tokens >= 1.0:
            self._announce_tokens -= 1.0
            out.append(
                Transition(
                    now, self._announced_state, self.state, f"{self._not_announced} transitions not announced"
                )
            )
            self._announced_state = self.state
            self._not_announced = 0
        return out

    def engage_blockers(self) -> list[str]:
        """Why STANDBY would not engage now (empty: it would); for logs and diagnostics."""
        now = self._clock()
        blockers = self._engage_blockers(now)
        if not blockers and self._reengage_wait(now) > 0:
            blockers.append("re-engage delay")
        return blockers

    # ---- internals ----------------------------------------------------------------------------

    def _heartbeat_fresh(self, now: float) -> bool:
        t = self._status.heartbeat_time
        return t is not None and now - t <= self.config.heartbeat_timeout

    def _lidar_fresh(self, now: float) -> bool:
        t = self._last_scan_time
        return t is not None and now - t <= self.config.lidar_timeout

    def _velocity_fresh(self, now: float) -> bool:
        t = self._status.velocity_time
        return t is not None and now - t <= self.config.velocity_timeout

    def _lidar_ready(self, now: float) -> bool:
        return self._lidar_fresh(now) and self._good_scans >= self.config.recover_scans

    def _engage_blockers(self, now: float) -> list[str]:
        cfg, st = self.config, self._status
        blockers = []
        if not st.armed:
            blockers.append("disarmed")
        if not st.guided:
            blockers.append(f"mode {st.mode}")
        if st.landed_state is not None and st.landed_state is not LandedState.IN_AIR:
            blockers.append(f"landed state {st.landed_state.name}")
        if st.altitude is None or not st.altitude >= cfg.min_engage_altitude:
            blockers.append("below engage altitude")
        if self._settled_since is None or now - self._settled_since < cfg.climb_settled_time:
            blockers.append("climb not settled")
        if not self._lidar_fresh(now):
            blockers.append("lidar stale")
        elif self._good_scans < cfg.recover_scans:
            blockers.append(f"{self._good_scans}/{cfg.recover_scans} good scans")
        if not self._velocity_fresh(now):
            blockers.append("velocity stale")
        return blockers

    def _reengage_wait(self, now: float) -> float:
        """Seconds the engage conditions must still hold before re-engaging (0: may engage)."""
        if not self._disengaged:
            return 0.0
        since = now if self._clear_since is None else self._clear_since
        return max(0.0, self.config.reengage_delay - (now - since))

    def _try_engage(self, now: float) -> None:
        if self._engage_blockers(now):
            if self._clear_since is not None and self._disengaged:
                self.counters["reengage_debounced"] += 1  # conditions broke again within reengage_delay
            self._clear_since = None
            return
        if self._clear_since is None:
            self._clear_since = now
        if self._reengage_wait(now) > 0:
            return
        self._go(SupervisorState.ACTIVE, "engaged")

    def _while_commanding(self, now: float, problem: str | None) -> None:
        st = self._status
        if not st.guided:
            self._go(SupervisorState.PILOT_OVERRIDE, "mode changed", st.mode)
        elif not st.armed:
            self._go(SupervisorState.STANDBY, "disarmed")
        elif st.landed_state in (LandedState.ON_GROUND, LandedState.LANDING):
            self._go(SupervisorState.STANDBY, st.landed_state.name.lower())
        elif self.state is SupervisorState.ACTIVE:
            if not self._lidar_fresh(now):
                self._go(SupervisorState.HOLD, "lidar stale")
            elif problem is not None:
                self._go(SupervisorState.HOLD, problem)
            elif not self._velocity_fresh(now):
                self._go(SupervisorState.HOLD, "velocity stale")
        elif problem is None and self._lidar_ready(now) and self._velocity_fresh(now):  # HOLD, cleared
            self._go(SupervisorState.ACTIVE, "recovered", f"{self._good_scans} good scans")

    def _go(self, new: SupervisorState, reason: str, detail: str = "") -> None:
        """Record a transition; ``reason`` is a fixed phrase (counted), ``detail`` the variable part."""
        old = self.state
        self.state = new
        commanding = (SupervisorState.ACTIVE, SupervisorState.HOLD)
        if old in commanding and new not in commanding:
            self._disengaged = True
            self._clear_since = None
        text = f"{reason} ({detail})" if detail else reason
        self._transitions.append(Transition(self._clock(), old, new, text))
        self.counters[f"{old.value}->{new.value}"] += 1
        self.counters[reason] += 1
