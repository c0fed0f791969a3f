"""Taps: thin wrappers around the loop's parts that tell the recorder what went in and came out.

The loop keeps calling its parts exactly as before (``self.policy.act(obs)``,
``self.shield.filter(...)``, ``self.link.send_velocity(...)``); each tap calls the real part,
reports to the :class:`FlightRecorder` and returns the real answer unchanged. So the loop needs no
recording calls of its own, what is recorded is what the parts really did (the setpoint the link
really sent, the limits the shield really counted), and a part whose interface grows (another
argument to ``filter``) is still recorded: unknown arguments pass through and are recorded as
``extra``. Anything a tap does not define is the real part's own attribute.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from companion.recording.recorder import WARNING, FlightRecorder


class _Tap:
    def __init__(self, inner: Any, recorder: FlightRecorder) -> None:
        self._inner = inner
        self._recorder = recorder

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class LidarTap(_Tap):
    def read_available(self) -> list[np.ndarray]:
        clouds = self._inner.read_available()
        self._recorder.on_clouds(clouds)
        return clouds


class FrameStackTap(_Tap):
    def reset(self, scan: np.ndarray) -> np.ndarray:
        obs = self._inner.reset(scan)
        self._recorder.on_stacked(scan, obs, reset=True)
        return obs

    def push(self, scan: np.ndarray) -> np.ndarray:
        obs = self._inner.push(scan)
        self._recorder.on_stacked(scan, obs, reset=False)
        return obs


class PolicyTap(_Tap):
    def act(self, obs: np.ndarray) -> np.ndarray:
        try:
            action = self._inner.act(obs)
        except Exception as exc:
            self._recorder.on_action(None, f"{type(exc).__name__}: {exc}")
            raise
        self._recorder.on_action(action)
        return action


class ShieldTap(_Tap):
    def reset(self) -> None:
        self._inner.reset()
        self._recorder.on_shield_reset()

    def filter(self, requested: Any, scan: np.ndarray, dt: float, *args: Any, **kwargs: Any) -> Any:
        before = dict(self._inner.interventions)
        out = self._inner.filter(requested, scan, dt, *args, **kwargs)
        after = self._inner.interventions
        limits = [k for k, v in after.items() if v != before.get(k, 0)]
        extra = {**{f"arg{i}": a for i, a in enumerate(args, start=3)}, **kwargs} or None
        self._recorder.on_shield(requested, scan, dt, out, limits, extra)
        return out


class LinkTap(_Tap):
    """Also where the pilot hears about the recorder: its notices go out as STATUSTEXT once the
    autopilot is there (this runs in the loop thread, the only one that may use the link)."""

    def poll(self) -> Any:
        status = self._inner.poll()
        self._recorder.on_status(status)
        self._recorder.flush_if_stale()
        if getattr(status, "heartbeat_time", None) is not None:
            for line in self._recorder.take_notices():
                self._inner.send_statustext(line, WARNING)
        return status

    # After each of these the iteration's time-critical part is over: the writer may have the records.
    def send_velocity(self, forward: float, yaw_rate: float, lateral: float = 0.0,
                      vertical: float = 0.0) -> None:
        self._inner.send_velocity(forward, yaw_rate, lateral, vertical)
        self._recorder.on_setpoint(forward, yaw_rate, lateral, vertical)
        self._recorder.flush()

    def send_obstacle_distance(self, sectors_cm: np.ndarray) -> None:
        self._inner.send_obstacle_distance(sectors_cm)
        self._recorder.flush()

    def send_heartbeat(self) -> None:
        self._inner.send_heartbeat()
        self._recorder.flush()

    def send_statustext(self, text: str, severity: int) -> None:
        self._inner.send_statustext(text, severity)
        self._recorder.on_statustext(text, severity)


class TrackerTap(_Tap):
    def update(self, scan: np.ndarray, pose: tuple[float, float, float] | None, time: float) -> Any:
        fresh = self._inner.fresh
        out = self._inner.update(scan, pose, time)
        self._recorder.on_tracks(scan, pose, time, fresh, out)
        return out


class SupervisorTap(_Tap):
    def drain_transitions(self) -> list[Any]:
        transitions = self._inner.drain_transitions()
        for transition in transitions:
            self._recorder.on_transition(transition, self._inner.counters)
        return transitions


def tap_parts(recorder: FlightRecorder, **parts: Any) -> dict[str, Any]:
    """Wrap the named parts (lidar, stack, policy, shield, link, supervisor, tracker) in their taps."""
    kinds = {"lidar": LidarTap, "stack": FrameStackTap, "policy": PolicyTap, "shield": ShieldTap,
             "link": LinkTap, "supervisor": SupervisorTap, "tracker": TrackerTap}
    return {name: kinds[name](part, recorder) for name, part in parts.items()}
