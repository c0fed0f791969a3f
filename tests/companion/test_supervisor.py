"""Supervisor: every transition driven with a fake clock."""

from __future__ import annotations

import dataclasses

import pytest

from companion.autopilot.link import LandedState, VehicleStatus
from companion.common.errors import UserError
from companion.common.tomlconfig import from_dict
from companion.safety.supervisor import CommandKind, Supervisor, SupervisorConfig, SupervisorState, Transition

S = SupervisorState
DT = 0.1  # a 10 Hz lidar


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class Rig:
    """A supervisor plus the world it watches: a clock, the vehicle, the lidar."""

    def __init__(self, config: SupervisorConfig | None = None, **vehicle: object) -> None:
        self.clock = FakeClock()
        self.sup = Supervisor(config or SupervisorConfig(), self.clock)
        self.vehicle = VehicleStatus(
            armed=True, guided=True, mode="GUIDED", landed_state=LandedState.IN_AIR, altitude=5.0
        )
        self.set(climb_rate=0.0)
        self.set(**vehicle)
        self.heartbeat = True
        self.velocity = True  # the link measures the velocity every loop

    def set(self, **changes: object) -> None:
        self.vehicle = dataclasses.replace(self.vehicle, **changes)

    def step(self, *, scan: bool = True, ok: bool = True, dt: float = DT) -> CommandKind:
        """One loop of the app: time passes, the link is polled, maybe a scan arrives, then tick."""
        self.clock.now += dt
        if self.heartbeat:
            self.set(heartbeat_time=self.clock.now)
        if self.velocity:
            self.set(velocity_body=(0.0, 0.0), velocity_time=self.clock.now)
        self.sup.on_vehicle(self.vehicle)
        if scan:
            self.sup.on_scan(ok)
        return self.sup.tick()

    def steps(self, n: int, **kw: object) -> CommandKind:
        kind = CommandKind.NONE
        for _ in range(n):
            kind = self.step(**kw)  # type: ignore[arg-type]
        return kind

    def to_active(self) -> None:
        self.sup.start()
        self.steps(12)  # 1.2 s: climb settled for 1 s, well over 5 good scans
        assert self.sup.state is S.ACTIVE
        self.sup.drain_transitions()

    def transitions(self) -> list[tuple[S, S, str]]:
        return [(t.old, t.new, t.reason) for t in self.sup.drain_transitions()]


def test_starting_sends_nothing_until_started() -> None:
    rig = Rig()
    assert rig.steps(20) is CommandKind.NONE
    assert rig.sup.state is S.STARTING and rig.transitions() == []
    rig.sup.start()
    assert rig.transitions() == [(S.STARTING, S.WAITING_FOR_AUTOPILOT, "started")]


def test_waiting_until_a_fresh_heartbeat() -> None:
    rig = Rig()
    rig.heartbeat = False
    rig.sup.start()
    rig.set(heartbeat_time=rig.clock.now - 5.0)  # an old heartbeat does not count
    assert rig.steps(10) is CommandKind.NONE
    assert rig.sup.state is S.WAITING_FOR_AUTOPILOT
    rig.set(armed=False)  # on the ground: heartbeat → STANDBY and no further
    rig.heartbeat = True
    rig.sup.drain_transitions()
    assert rig.step() is CommandKind.NONE
    assert rig.transitions() == [(S.WAITING_FOR_AUTOPILOT, S.STANDBY, "autopilot heartbeat")]


def test_engages_when_all_conditions_hold() -> None:
    rig = Rig()
    rig.sup.start()
    rig.steps(9)  # 0.9 s: climb settled for 0.8 s only
    assert rig.sup.state is S.STANDBY
    assert rig.sup.engage_blockers() == ["climb not settled"]
    assert rig.steps(3) is CommandKind.POLICY
    assert rig.sup.state is S.ACTIVE
    assert rig.transitions()[-1] == (S.STANDBY, S.ACTIVE, "engaged")


@pytest.mark.parametrize(
    ("change", "blocker"),
    [
        ({"armed": False}, "disarmed"),
        ({"guided": False, "mode": "LOITER"}, "mode LOITER"),
        ({"landed_state": LandedState.TAKEOFF}, "landed state TAKEOFF"),
        ({"landed_state": LandedState.ON_GROUND}, "landed state ON_GROUND"),
        ({"landed_state": LandedState.UNDEFINED}, "landed state UNDEFINED"),
        ({"altitude": 0.9}, "below engage altitude"),
        ({"altitude": None}, "below engage altitude"),
        ({"climb_rate": 0.5}, "climb not settled"),
        ({"climb_rate": -0.5}, "climb not settled"),
        ({"climb_rate": None}, "climb not settled"),
    ],
)
def test_each_engage_condition_alone_keeps_standby(change: dict[str, object], blocker: str) -> None:
    rig = Rig(**change)
    rig.sup.start()
    assert rig.steps(50) is CommandKind.NONE
    assert rig.sup.state is S.STANDBY
    assert rig.sup.engage_blockers() == [blocker]


def test_lidar_must_be_fresh_and_have_enough_good_scans_to_engage() -> None:
    rig = Rig()
    rig.sup.start()
    rig.steps(20, scan=False)
    assert rig.sup.state is S.STANDBY and rig.sup.engage_blockers() == ["lidar stale"]
    rig.steps(4)
    assert rig.sup.state is S.STANDBY and rig.sup.engage_blockers() == ["4/5 good scans"]
    rig.step(ok=False)  # a fault restarts the count
    rig.steps(4)
    assert rig.sup.state is S.STANDBY
    assert rig.step() is CommandKind.POLICY


def test_engages_without_extended_sys_state() -> None:
    rig = Rig(landed_state=None)
    rig.sup.start()
    rig.steps(12)
    assert rig.sup.state is S.ACTIVE


@pytest.mark.parametrize("reports_landed_state", [True, False])
def test_guided_takeoff_is_never_interrupted(reports_landed_state: bool) -> None:
    """Arm and take off to 5 m in GUIDED at 1 m/s: the companion engages only after the climb."""
    rig = Rig(altitude=0.0, climb_rate=0.0, armed=False, landed_state=LandedState.ON_GROUND)
    rig.sup.start()
    rig.steps(20)
    rig.set(armed=True)
    rig.steps(10)
    altitude, engaged_at = 0.0, None
    for _ in range(100):
        climbing = altitude < 5.0
        altitude = min(5.0, altitude + 1.0 * DT)
        state = LandedState.TAKEOFF if climbing else LandedState.IN_AIR
        rig.set(
            altitude=altitude,
            climb_rate=1.0 if climbing else 0.0,
            landed_state=state if reports_landed_state else None,
        )
        rig.step()
        if rig.sup.state is S.ACTIVE and engaged_at is None:
            engaged_at = rig.clock.now
        if climbing:
            assert rig.sup.state is S.STANDBY, f"engaged during the climb at {altitude:.1f} m"
    assert engaged_at is not None


def test_lidar_stale_holds_then_recovers_after_recover_scans() -> None:
    rig = Rig()
    rig.to_active()
    rig.step(scan=False, dt=0.29)  # just under lidar_timeout: still fresh
    assert rig.sup.state is S.ACTIVE
    assert rig.step(scan=False, dt=0.02) is CommandKind.ZERO
    assert rig.transitions() == [(S.ACTIVE, S.HOLD, "lidar stale")]
    assert rig.steps(4) is CommandKind.ZERO
    assert rig.sup.state is S.HOLD
    assert rig.step() is CommandKind.POLICY
    assert rig.transitions() == [(S.HOLD, S.ACTIVE, "recovered (5 good scans)")]


def test_a_scan_gap_no_tick_saw_still_holds() -> None:
    rig = Rig()
    rig.to_active()
    rig.clock.now += 0.5  # the loop stalled: no tick during the gap
    assert rig.step() is CommandKind.ZERO
    assert rig.transitions() == [(S.ACTIVE, S.HOLD, "lidar stale")]


def test_inference_fault_holds_and_recovery_needs_consecutive_good_scans() -> None:
    rig = Rig()
    rig.to_active()
    assert rig.step(ok=False) is CommandKind.ZERO
    assert rig.transitions() == [(S.ACTIVE, S.HOLD, "inference fault")]
    rig.steps(3)
    rig.step(ok=False)  # a second fault restarts the count
    rig.steps(4)
    assert rig.sup.state is S.HOLD
    rig.step()
    assert rig.sup.state is S.ACTIVE
    assert rig.sup.counters["scans_faulted"] == 2


def test_hold_stays_while_lidar_stays_stale() -> None:
    rig = Rig()
    rig.to_active()
    rig.steps(50, scan=False)
    assert rig.sup.state is S.HOLD
    assert [t[:2] for t in rig.transitions()] == [(S.ACTIVE, S.HOLD)]


@pytest.mark.parametrize("from_hold", [False, True])
def test_pilot_mode_change_is_pilot_override_until_guided_again(from_hold: bool) -> None:
    rig = Rig()
    rig.to_active()
    if from_hold:
        rig.step(ok=False)
        assert rig.sup.state is S.HOLD
        rig.sup.drain_transitions()
    rig.set(guided=False, mode="LOITER")
    assert rig.step() is CommandKind.NONE
    old = S.HOLD if from_hold else S.ACTIVE
    assert rig.transitions() == [(old, S.PILOT_OVERRIDE, "mode changed (LOITER)")]
    # everything else fine for a long time: the companion never takes over again by itself
    assert rig.steps(100) is CommandKind.NONE
    assert rig.sup.state is S.PILOT_OVERRIDE
    rig.set(guided=True, mode="GUIDED")
    assert rig.step() is CommandKind.NONE
    assert rig.transitions() == [(S.PILOT_OVERRIDE, S.STANDBY, "mode back to guided (GUIDED)")]
    assert rig.sup.engage_blockers() == ["re-engage delay"]
    assert rig.steps(9) is CommandKind.NONE  # guided for 0.9 s: not yet
    assert rig.steps(2) is CommandKind.POLICY  # reengage_delay (1 s) passed
    assert rig.transitions() == [(S.STANDBY, S.ACTIVE, "engaged")]


def test_back_to_guided_on_the_ground_waits_in_standby() -> None:
    rig = Rig()
    rig.to_active()
    rig.set(guided=False, mode="LAND")
    rig.step()
    rig.set(landed_state=LandedState.ON_GROUND, altitude=0.0, armed=False)
    rig.steps(10)
    rig.set(guided=True, mode="GUIDED")
    assert rig.steps(10) is CommandKind.NONE
    assert rig.sup.state is S.STANDBY


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"armed": False}, "disarmed"),
        ({"landed_state": LandedState.ON_GROUND}, "on_ground"),
        ({"landed_state": LandedState.LANDING}, "landing"),
    ],
)
@pytest.mark.parametrize("from_hold", [False, True])
def test_disarmed_or_landed_goes_to_standby(change: dict[str, object], reason: str, from_hold: bool) -> None:
    rig = Rig()
    rig.to_active()
    if from_hold:
        rig.step(ok=False)
        rig.sup.drain_transitions()
    rig.set(**change)
    assert rig.step() is CommandKind.NONE
    assert rig.transitions() == [(S.HOLD if from_hold else S.ACTIVE, S.STANDBY, reason)]


@pytest.mark.parametrize("state", [S.STANDBY, S.ACTIVE, S.HOLD, S.PILOT_OVERRIDE])
def test_heartbeat_lost_from_any_state_stops_commanding(state: S) -> None:
    rig = Rig()
    if state is S.STANDBY:
        rig.set(armed=False)
        rig.sup.start()
        rig.steps(3)
    else:
        rig.to_active()
        if state is S.HOLD:
            rig.step(ok=False)
        elif state is S.PILOT_OVERRIDE:
            rig.set(guided=False, mode="ALT_HOLD")
            rig.step()
    assert rig.sup.state is state
    rig.sup.drain_transitions()
    rig.heartbeat = False
    rig.steps(19, ok=state is not S.HOLD)  # 1.9 s: under heartbeat_timeout, still fresh
    assert rig.sup.state is state
    assert rig.step(dt=0.2) is CommandKind.NONE
    assert rig.transitions() == [(state, S.WAITING_FOR_AUTOPILOT, "autopilot heartbeat lost")]
    rig.steps(20)
    assert rig.sup.state is S.WAITING_FOR_AUTOPILOT
    # heartbeat back: STANDBY, then the normal engage rules (not in guided: stays in STANDBY)
    rig.set(guided=False, mode="LOITER")
    rig.heartbeat = True
    rig.step()
    assert rig.transitions() == [(S.WAITING_FOR_AUTOPILOT, S.STANDBY, "autopilot heartbeat")]
    assert rig.steps(10) is CommandKind.NONE


def test_restarted_mid_flight_resumes_only_after_fresh_scans() -> None:
    """The service restarts while the vehicle hovers in GUIDED: no setpoint before 5 new scans."""
    rig = Rig()
    rig.sup.start()
    kinds = [rig.step(scan=False) for _ in range(15)]  # autopilot and vehicle fine, lidar not yet up
    assert set(kinds) == {CommandKind.NONE}
    assert rig.sup.state is S.STANDBY
    for n in range(1, 5):
        assert rig.step() is CommandKind.NONE, f"commanded after {n} scans"
    assert rig.step() is CommandKind.POLICY
    assert [t[1] for t in rig.transitions()] == [S.WAITING_FOR_AUTOPILOT, S.STANDBY, S.ACTIVE]


def test_an_implausible_lidar_holds_with_its_own_reason() -> None:
    rig = Rig()
    rig.to_active()
    rig.clock.now += DT
    rig.sup.on_scan(False, "lidar implausible")  # the source saw more turns than the sensor makes
    assert rig.sup.tick() is CommandKind.ZERO
    assert rig.transitions() == [(S.ACTIVE, S.HOLD, "lidar implausible")]
    assert rig.sup.counters["lidar implausible"] == 1


def test_every_transition_is_recorded_and_counted() -> None:
    rig = Rig()
    rig.to_active()
    rig.step(ok=False)
    rig.steps(5)
    rig.step(ok=False)
    transitions = rig.sup.drain_transitions()
    assert all(isinstance(t, Transition) for t in transitions)
    assert [t.time for t in transitions] == pytest.approx([101.3, 101.8, 101.9])
    assert str(transitions[0]) == "ACTIVE->HOLD: inference fault"
    assert rig.sup.drain_transitions() == []
    c = rig.sup.counters
    assert c["ACTIVE->HOLD"] == 2 and c["HOLD->ACTIVE"] == 1 and c["STANDBY->ACTIVE"] == 1
    assert c["inference fault"] == 2 and c["recovered"] == 1 and c["engaged"] == 1
    assert c["STARTING->WAITING_FOR_AUTOPILOT"] == 1 and c["started"] == 1


def test_command_kind_per_state() -> None:
    rig = Rig()
    rig.to_active()
    assert rig.step() is CommandKind.POLICY
    assert rig.step(ok=False) is CommandKind.ZERO


def test_config_from_toml_with_ranges() -> None:
    cfg = from_dict(SupervisorConfig, {"lidar_timeout": 0.5, "recover_scans": 3})
    assert cfg == SupervisorConfig(lidar_timeout=0.5, recover_scans=3)
    with pytest.raises(UserError, match=r"supervisor\.recover_scans: 0 is below the minimum 1"):
        from_dict(SupervisorConfig, {"recover_scans": 0}, prefix="supervisor.")
    with pytest.raises(UserError, match=r"supervisor\.recover_scans: expected an integer"):
        from_dict(SupervisorConfig, {"recover_scans": 2.5}, prefix="supervisor.")


def test_mode_flapping_at_20_hz_never_reengages_and_barely_announces() -> None:
    """A sender flapping GUIDED/LOITER at 20 Hz for 10 s made 340 transitions; now: three."""
    rig = Rig()
    rig.to_active()
    kinds = []
    for i in range(200):  # 10 s of 50 ms loops, the mode changing every loop
        rig.set(guided=i % 2 == 1, mode="GUIDED" if i % 2 else "LOITER")
        kinds.append(rig.step(dt=0.05, scan=i % 2 == 0))
        if i == 0:
            assert kinds[0] is CommandKind.NONE, "the override must take effect at once"
    assert set(kinds) == {CommandKind.NONE}
    assert [t[:2] for t in rig.transitions()] == [(S.ACTIVE, S.PILOT_OVERRIDE), (S.PILOT_OVERRIDE, S.STANDBY)]
    assert rig.sup.counters["engaged"] == 1
    assert rig.sup.counters["reengage_debounced"] >= 95  # every GUIDED spell cut short, counted
    # the flapping stops in GUIDED: engaged again once it has held for reengage_delay
    rig.set(guided=True, mode="GUIDED")
    assert rig.steps(8) is CommandKind.NONE
    assert rig.steps(4) is CommandKind.POLICY


@pytest.mark.parametrize(
    "change", [{"armed": False}, {"landed_state": LandedState.LANDING}, {"guided": False, "mode": "BRAKE"}]
)
def test_any_disengage_then_reengage_is_debounced(change: dict[str, object]) -> None:
    rig = Rig()
    rig.to_active()
    normal = dataclasses.replace(rig.vehicle)
    for _ in range(20):  # the condition flips every loop for 2 s
        rig.set(**change)
        rig.step()
        rig.vehicle = dataclasses.replace(normal)
        assert rig.step() is CommandKind.NONE
    assert rig.sup.counters["engaged"] == 1
    assert len(rig.transitions()) <= 2


def test_announcements_are_rate_limited_and_summed_up() -> None:
    """Inference faults every other scan with reengage/recover at the minimum: many transitions,
    a burst of announcements, then one a second, and a summary that ends in the current state."""
    rig = Rig(SupervisorConfig(recover_scans=1, reengage_delay=0.0, announce_burst=4, announce_interval=1.0))
    rig.sup.start()
    rig.steps(12)
    announced = rig.sup.drain_transitions()  # start, standby, engaged: 3 of the burst of 4
    for i in range(100):  # 10 s: HOLD and back every two scans
        rig.step(ok=i % 2 == 1)
        announced += rig.sup.drain_transitions()
    made = rig.sup.counters["ACTIVE->HOLD"] + rig.sup.counters["HOLD->ACTIVE"]
    assert made >= 99
    assert len(announced) <= 4 + 11  # the burst, then one per second
    assert rig.sup.counters["transitions_not_announced"] >= made - len(announced)
    summaries = [t for t in announced if t.reason.endswith("transitions not announced")]
    assert summaries and all(int(t.reason.split()[0]) >= 1 for t in summaries)
    rig.steps(20)  # quiet again: one last summary brings the announced state up to date
    last = rig.sup.drain_transitions()
    assert last == [] or last[-1].new is rig.sup.state
    shown = (announced + last)[-1]
    assert shown.new is rig.sup.state is S.ACTIVE


def test_stale_velocity_holds_and_fresh_velocity_recovers() -> None:
    rig = Rig()
    rig.to_active()
    rig.velocity = False
    assert rig.steps(5) is CommandKind.POLICY  # 0.5 s old: still fresh
    assert rig.step() is CommandKind.ZERO  # 0.6 s: the shield cannot see where the vehicle goes
    assert rig.transitions() == [(S.ACTIVE, S.HOLD, "velocity stale")]
    assert rig.steps(10) is CommandKind.ZERO  # good scans alone do not recover
    rig.velocity = True
    assert rig.step() is CommandKind.POLICY
    assert rig.transitions() == [(S.HOLD, S.ACTIVE, "recovered (29 good scans)")]


def test_never_engages_without_a_measured_velocity() -> None:
    rig = Rig()
    rig.velocity = False
    rig.sup.start()
    assert rig.steps(30) is CommandKind.NONE
    assert rig.sup.engage_blockers() == ["velocity stale"]
    rig.velocity = True
    assert rig.step() is CommandKind.POLICY
