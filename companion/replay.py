"""``avoid-companion replay FILE.mcap [--policy OTHER.onnx] [--set shield.KEY=VALUE ...]``: run a recording
through the pipeline again.

The recorded inputs go through the companion's own code, with the recorded configuration: the
clouds (when recorded whole, ``recorder.cloud_decimation = 1``) through :func:`scan_from_points`,
otherwise the recorded scans; then the frame stack, the policy and the shield, with the recorded
time steps and resets. The shield is built as the companion built it: the recorded autopilot type's
limits, with the stopping model the shield assumed (in the metadata; recordings made before it was
recorded: the limits then in force, :data:`STOPPING_BEFORE_RECORDED`), and the yaw cap the companion
read from the autopilot (in the metadata; recordings made before it was recorded: the firmware
default, as when nothing was read).

- Same model (the file's sha256 matches the recording's): every scan, observation, action,
  requested command and shield output must match the recording bit for bit, and so must every
  tracker update (``/tracks``: the tracker run again on its recorded scan, pose and time, from the
  first update with no state before it in the file); the first one that does not is reported
  (exit status 1).
- Another model, or other shield settings (``--set shield.backup_gate=true``): what it would have
  asked for and what the shield would have let through, scan by scan on the recorded scans (open
  loop: the vehicle's path stays the recorded one), as a table and a plot. When the recording holds
  the simulator's ground truth and the flight ended in contact, a line says how the new output
  compared with the recorded one on the way in (:func:`approach_figures`).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.app import companion_shield, policy_spec
from companion.common.errors import UserError
from companion.common.tomlconfig import apply_overrides, from_dict, to_dict
from companion.config import CompanionConfig
from companion.guidance.policy import InferenceFault, OnnxPolicy
from companion.perception.framestack import FrameStack
from companion.perception.scan import N_BINS, scan_from_points
from companion.perception.tracking import Mover, ScanTracker
from companion.recording import schemas
from companion.recording.messages import TRACK_FIELDS, unpack_f32
from companion.recording.reader import Recording, read_recording
from companion.recording.recorder import file_digest, track_rows
from companion.safety.shield import Command, command_from_action, sector_bins

log = logging.getLogger(__name__)


@dataclass
class Step:
    """One shielded setpoint, as recorded and as replayed: (forward, yaw rate, lateral); a recorded
    lateral is NaN in recordings made before /shield had it."""

    t: float
    recorded: tuple[float, float, float]
    replayed: tuple[float, float, float]
    front_clearance: float
    recorded_limits: list[str]
    replayed_limits: list[str]


@dataclass
class ReplayResult:
    """What a replay found.

    :param source: ``clouds`` or ``scans`` (what the pipeline started from)
    :param first_difference: the first thing that did not match bit for bit ("" = none)
    """

    source: str
    policy_steps: int = 0
    shield_steps: int = 0
    skipped_shield: int = 0
    first_difference: str = ""
    track_steps: int = 0
    skipped_tracks: int = 0
    steps: list[Step] = field(default_factory=list)
    first_event_t: float = 0.0  # the recording's clock at the first scan or shield step (steps' t = 0), s


def recorded_config(rec: Recording) -> tuple[CompanionConfig, dict[str, str]]:
    """The companion configuration the recording was made with, and the recording's metadata."""
    meta = rec.metadata.get(schemas.METADATA_NAME)
    if meta is None:
        raise UserError(f"{rec.path}: not a lidar-avoid recording (no {schemas.METADATA_NAME} metadata)")
    if meta.get("format") != schemas.FORMAT_VERSION:
        raise UserError(
            f"{rec.path}: recording format {meta.get('format')!r}, this version reads "
            f"{schemas.FORMAT_VERSION!r}"
        )
    try:
        data = json.loads(meta["config"])
        # recordings made before policy.observation existed fed the model scans alone
        data.setdefault("policy", {}).setdefault("observation", "scan")
        # and before policy.drift existed, no drift features
        data["policy"].setdefault("drift", False)
        # and before policy.command existed, no command features
        data["policy"].setdefault("command", False)
        # the shield's stopping model as flown: [shield] left at 0 took the autopilot's limits of
        # the version that flew, which this one may have changed
        shield = data.setdefault("shield", {})
        try:
            decel, reaction_time = recorded_stopping(meta, data.get("autopilot", {}).get("type", "ardupilot"))
        except UserError as exc:
            raise UserError(f"{rec.path}: {exc}") from None
        if not shield.get("max_decel") and decel is not None:
            shield["max_decel"] = decel
        if not shield.get("reaction_time") and reaction_time is not None:
            shield["reaction_time"] = reaction_time
        return from_dict(CompanionConfig, data, "recorded config: "), meta
    except (KeyError, ValueError) as exc:
        raise UserError(f"{rec.path}: recorded config unreadable: {exc}") from None


#: the autopilot limits' (deceleration m/s², reaction time s) the shield assumed in recordings made
#: before ``shield_stopping`` was recorded (ArduPilot's were then tuned, not the firmware envelope's)
STOPPING_BEFORE_RECORDED: dict[str, tuple[float, float]] = {"ardupilot": (2.5, 0.7), "px4": (1.2, 0.8)}


def recorded_stopping(meta: dict[str, str], autopilot: str) -> tuple[float | None, float | None]:
    """The shield's stopping model (deceleration m/s², reaction time s) a recording was flown with:
    its ``shield_stopping`` metadata, or for recordings made before it was recorded the limits then in
    force (:data:`STOPPING_BEFORE_RECORDED`); (None, None) when not known (this version's limits)."""
    text = meta.get("shield_stopping")
    if text is None:
        return STOPPING_BEFORE_RECORDED.get(autopilot, (None, None))
    if not text:
        return None, None
    try:
        decel, reaction_time = (float(v) for v in text.split())
    except ValueError:
        raise UserError(f"recorded shield_stopping {text!r} is not two numbers") from None
    return decel, reaction_time


def recorded_autopilot_yaw_rate(rec: Recording) -> float | None:
    """The yaw cap the companion read from the autopilot, rad/s; None when it read none, or the
    recording was made before it was recorded (the companion then assumed the firmware default)."""
    text = rec.metadata[schemas.METADATA_NAME].get("autopilot_yaw_rate", "")
    try:
        return float(text) if text else None
    except ValueError:
        raise UserError(f"{rec.path}: recorded autopilot_yaw_rate {text!r} is not a number") from None


#: the [config] table ``--set`` may change: the what-if is about the shield; other tables (the policy's
#: layout, the scan) would no longer fit the recorded observations
SETTABLE_TABLE = "shield"
#: a contact, as the SITL harness judges it (flightsim/sitl/flight_recorder.py): the true clearance
#: below the vehicle radius (flightsim.worlds.world.DEFAULT_VEHICLE_RADIUS) above this altitude
CONTACT_RADIUS_M = 0.25
CONTACT_MIN_ALTITUDE_M = 0.3
#: the ground-truth topic the SITL recordings carry (flightsim.sitl.recording.TRUTH_STATE)
TRUTH_STATE_TOPIC = "/truth/state"
#: the stretch before the contact the speeds are compared over, s
APPROACH_S = 3.0
#: less than this, m/s, is float noise, not a lower speed asked
SPEED_TOLERANCE = 1e-3


def with_settings(config: CompanionConfig, settings: list[str]) -> CompanionConfig:
    """``config`` with ``--set`` items (``shield.KEY=VALUE``, the value parsed as TOML) applied and
    checked by the companion's own config loader, so a what-if runs only settings a flight could.

    :raises UserError: naming the key that is malformed, outside [shield], unknown, ill-typed or out of range
    """
    for item in settings:
        key = item.split("=", 1)[0].strip()
        if "=" not in item or not key.startswith(f"{SETTABLE_TABLE}."):
            raise UserError(
                f"--set {item}: expected {SETTABLE_TABLE}.KEY=VALUE (replay changes only "
                f"[{SETTABLE_TABLE}] keys)"
            )
    try:
        return from_dict(CompanionConfig, apply_overrides(to_dict(config), settings))
    except UserError as exc:
        raise UserError(f"--set {exc}") from None


@dataclass(frozen=True)
class Contact:
    """The first ground-truth sample in contact: time (the recording's clock, s) and true clearance, m."""

    t: float
    clearance: float


def first_contact(truth: list[tuple[float, dict[str, Any]]]) -> Contact | None:
    """The first ``/truth/state`` sample closer to geometry than the vehicle radius, in the air (the
    harness's rule, on the recorded 20 Hz truth); None: the flight ended clear."""
    for t, msg in truth:
        clearance = msg.get("clearance")
        if (
            clearance is not None
            and clearance < CONTACT_RADIUS_M
            and msg["position"]["z"] > CONTACT_MIN_ALTITUDE_M
        ):
            return Contact(t, float(clearance))
    return None


def least_clearance(truth: list[tuple[float, dict[str, Any]]]) -> float | None:
    """The least true clearance in the air, m (None: none recorded)."""
    values = [
        msg["clearance"]
        for _, msg in truth
        if msg.get("clearance") is not None and msg["position"]["z"] > CONTACT_MIN_ALTITUDE_M
    ]
    return min(values) if values else None


def setpoint_speed(command: tuple[float, float, float]) -> float:
    """Horizontal speed of a (forward, yaw rate, lateral) setpoint, m/s; a lateral not recorded
    (NaN, recordings before /shield had it) counts as none."""
    forward, _, lateral = command
    return math.hypot(forward, lateral if math.isfinite(lateral) else 0.0)


@dataclass(frozen=True)
class Approach:
    """How the new shield output compared with the recorded one on the way into a contact.

    :param contact_t: the contact, s since the first scan
    :param first_less_s: seconds before the contact the new output first asked for less speed (None: never)
    :param last_less_s: seconds before the contact it last did (None: never)
    :param less_in_window: setpoints in the last ``window`` s where it asked for less, of ``in_window``
    :param recorded_mean, recorded_max, new_mean, new_max: setpoint speed over the last ``window`` s, m/s
    """

    contact_t: float
    window: float
    first_less_s: float | None
    last_less_s: float | None
    less_in_window: int
    in_window: int
    recorded_mean: float
    recorded_max: float
    new_mean: float
    new_max: float


def approach_figures(steps: list[Step], contact_t: float, window: float = APPROACH_S) -> Approach:
    """The comparison figures of one contact: whether, and how early, the new settings would have
    slowed the vehicle down where the recorded flight hit (open loop: on the recorded path).

    :param steps: the compared setpoints, times in s since the first scan
    :param contact_t: the contact, same clock
    """
    before = [s for s in steps if s.t <= contact_t]
    less = [s.t for s in before if setpoint_speed(s.replayed) < setpoint_speed(s.recorded) - SPEED_TOLERANCE]
    recent = [s for s in before if s.t >= contact_t - window]
    rec = np.array([setpoint_speed(s.recorded) for s in recent])
    new = np.array([setpoint_speed(s.replayed) for s in recent])
    nan = float("nan")
    return Approach(
        contact_t=contact_t,
        window=window,
        first_less_s=contact_t - less[0] if less else None,
        last_less_s=contact_t - less[-1] if less else None,
        less_in_window=int(np.sum(new < rec - SPEED_TOLERANCE)),
        in_window=len(recent),
        recorded_mean=float(rec.mean()) if len(rec) else nan,
        recorded_max=float(rec.max()) if len(rec) else nan,
        new_mean=float(new.mean()) if len(new) else nan,
        new_max=float(new.max()) if len(new) else nan,
    )


def approach_line(a: Approach, contact: Contact, label: str) -> str:
    """One flight's contact figures as the what-if prints them."""
    if a.first_less_s is None or a.last_less_s is None:
        asked = f"the {label} never asked for less speed before it"
    else:
        asked = (
            f"the {label} first asked for less speed {a.first_less_s:.2f} s before it (last "
            f"{a.last_less_s:.2f} s before), in the last {a.window:g} s on {a.less_in_window} of "
            f"{a.in_window} setpoints"
        )
    return (
        f"contact at t={a.contact_t:.2f} s (true clearance {contact.clearance:.3f} m < "
        f"{CONTACT_RADIUS_M} m): {asked}; setpoint speed over the last {a.window:g} s, recorded vs "
        f"{label}: mean {a.recorded_mean:.2f} vs {a.new_mean:.2f} m/s, max {a.recorded_max:.2f} vs "
        f"{a.new_max:.2f} m/s"
    )


def heading_recorded(rec: Recording) -> bool:
    """Whether the shield was given the autopilot's heading in flight: it is then in /shield's
    ``extra`` and the replay passes it on as recorded; otherwise the gate integrates the yaw rates
    it sent, in flight and in the replay alike."""
    # by name, or positionally after velocity and drift (the tap records those as arg3, arg4, arg5)
    steps = rec.topic(schemas.SHIELD.topic)
    return any({"heading", "arg5"} & set(msg.get("extra") or {}) for _, msg in steps)


def _matches(command: Command, recorded: dict[str, Any]) -> bool:
    """``command`` is what was recorded of it, bit for bit (recordings made before /shield had
    ``lateral``: forward and yaw rate alone)."""
    return all(getattr(command, name) == value for name, value in recorded.items())


def replay(rec: Recording, config: CompanionConfig, policy: OnnxPolicy, *, compare: bool) -> ReplayResult:
    """Run ``rec``'s inputs through scan, frame stack, ``policy`` and shield.

    :param compare: check every intermediate against the recording (same model); otherwise only
        collect the shield outputs side by side (what-if)
    """
    decimation = int(rec.metadata[schemas.METADATA_NAME].get("cloud_decimation", "0"))
    clouds: dict[int, dict[str, Any]] = {}
    if decimation == 1:
        cloud_topic = schemas.CLOUD.topic
        clouds = dict(
            zip(rec.sequences.get(cloud_topic, []), (msg for _, msg in rec.topic(cloud_topic)), strict=True)
        )
    result = ReplayResult(source="clouds" if clouds else "scans")
    layout = config.policy.layout  # a frame: the scan, then (goal layout) the recorded goal/velocity
    size = layout.frame_size
    stack = FrameStack(config.policy.stack, size)
    shield = companion_shield(config, recorded_autopilot_yaw_rate(rec))
    forward_bins = sector_bins(0.0, config.shield.forward_sector_deg)
    scans: dict[int, np.ndarray] = {}
    requested: dict[int, Command] = {}
    seeded_stack = False
    seeded_shield = False
    tracker = ScanTracker(max_range=config.scan.max_range)
    seeded_tracker = False
    cfg = config.policy

    def differ(what: str) -> None:
        if not result.first_difference:
            result.first_difference = what

    events = [(t, 0, msg) for t, msg in rec.topic(schemas.POLICY.topic)]
    events += [(t, 1, msg) for t, msg in rec.topic(schemas.SHIELD.topic)]
    if compare:  # the tracks depend on neither the model nor the shield
        events += [(t, 2, msg) for t, msg in rec.topic(schemas.TRACKS.topic)]
    events.sort(key=lambda e: (e[0], e[1]))
    t0 = result.first_event_t = events[0][0] if events else 0.0
    for t, kind, msg in events:
        when = f"t={t - t0:.3f} s"
        if kind == 0:
            result.policy_steps += 1
            recorded_obs = unpack_f32(msg["observation"])
            frame = recorded_obs[-size:]
            scan = frame[:N_BINS]
            if clouds:
                cloud_msg = clouds.get(msg["cloud_seq"])
                if cloud_msg is None and (msg["cloud_seq"] or 0) < min(clouds):
                    pass  # its cloud was written before this part began: replay the recorded scan
                elif cloud_msg is None:
                    differ(f"{when}: scan {msg['seq']}: its cloud {msg['cloud_seq']} is not in the recording")
                else:
                    points = unpack_f32(cloud_msg["data"]).reshape(-1, 3)
                    replayed_scan = scan_from_points(points, config.scan).astype(np.float32)
                    if compare and not np.array_equal(replayed_scan.view(np.uint32), scan.view(np.uint32)):
                        differ(
                            f"{when}: scan {msg['seq']} from its cloud differs from the recorded scan "
                            f"in {int(np.sum(replayed_scan != scan))} bins"
                        )
                    scan = replayed_scan
                    frame = np.concatenate([scan, frame[N_BINS:]])
            if not msg["reset"] and not seeded_stack:  # the file starts mid-flight: take its stack
                stack.reset(recorded_obs[:size])
                for i in range(1, config.policy.stack - 1):
                    stack.push(recorded_obs[i * size : (i + 1) * size])
            seeded_stack = True
            obs = stack.reset(frame) if msg["reset"] else stack.push(frame)
            if compare and not np.array_equal(obs.view(np.uint32), recorded_obs.view(np.uint32)):
                differ(f"{when}: observation {msg['seq']} differs from the recorded one")
            try:
                action: np.ndarray | None = policy.act(obs)
            except InferenceFault as exc:
                action = None
                fault = str(exc)
            else:
                fault = None
            recorded_action = msg["action"]
            if compare:
                if (action is None) != (recorded_action is None):
                    differ(
                        f"{when}: scan {msg['seq']}: recorded {recorded_action or msg['fault']}, "
                        f"replayed {action.tolist() if action is not None else fault}"
                    )
                elif action is not None and not np.array_equal(
                    action.view(np.uint32), np.asarray(recorded_action, np.float32).view(np.uint32)
                ):
                    differ(
                        f"{when}: action {msg['seq']}: recorded {recorded_action}, replayed "
                        f"{[float(a) for a in action]}"
                    )
            scans[msg["seq"]] = scan
            requested[msg["seq"]] = (
                command_from_action(action, cfg.max_speed, cfg.max_yaw_rate, cfg.sideways_speed)
                if action is not None
                else Command(0.0, 0.0)
            )
        elif kind == 2:
            seeded_tracker = seeded_tracker or msg["fresh"]
            if not seeded_tracker:  # the tracker's state before the file is unknown
                result.skipped_tracks += 1
                continue
            result.track_steps += 1
            where = msg["pose"]
            pose = None if where is None else (where["x"], where["y"], where["yaw"])
            scan = unpack_f32(msg["scan"]) if msg["scan"] is not None else np.ones(N_BINS, np.float32)
            rows, bins = track_rows(tracker.update(scan, pose, msg["time"]))
            recorded = [tuple(row[k] for k in TRACK_FIELDS) for row in msg["tracks"]]
            if rows != recorded or bins != msg["moving_bins"]:
                differ(
                    f"{when}: tracks recorded {recorded} moving in bins {msg['moving_bins']}, "
                    f"replayed {rows} moving in bins {bins}"
                )
        else:
            seq = msg["scan_seq"]
            if msg["reset_before"]:
                shield.reset()
                seeded_shield = True
            if seq not in scans or not seeded_shield:  # the shield's state before the file is unknown
                result.skipped_shield += 1
                continue
            result.shield_steps += 1
            command = requested[seq]
            rec_req = msg["requested"]
            if compare and not _matches(command, rec_req):
                differ(f"{when}: requested command recorded {rec_req}, replayed {asdict(command)}")
            before = dict(shield.interventions)
            out = shield.filter(
                command,
                scans[seq],
                msg["dt"],
                *_extra_args(msg.get("extra")),
                **_extra_kwargs(msg.get("extra")),
            )
            limits = [k for k, v in shield.interventions.items() if v != before.get(k, 0)]
            rec_out = msg["output"]
            if compare and not _matches(out, rec_out):
                differ(f"{when}: shield output recorded {rec_out}, replayed {asdict(out)}")
            front = float(np.min(scans[seq][forward_bins])) * config.scan.max_range
            recorded = (rec_out["forward"], rec_out["yaw_rate"], rec_out.get("lateral", np.nan))
            result.steps.append(
                Step(t - t0, recorded, (out.forward, out.yaw_rate, out.lateral), front, msg["limits"], limits)
            )
    return result


def _extra_args(extra: dict[str, Any] | None) -> list[Any]:
    if not extra:
        return []
    return [extra[k] for k in sorted((k for k in extra if k.startswith("arg")), key=lambda k: int(k[3:]))]


def _extra_kwargs(extra: dict[str, Any] | None) -> dict[str, Any]:
    """The keywords the shield was called with, as it takes them (the tracker's bins and movers
    come back from JSON as lists and objects, a non-finite number as null)."""
    kwargs = {k: v for k, v in (extra or {}).items() if not k.startswith("arg")}
    if kwargs.get("moving_bins") is not None:
        kwargs["moving_bins"] = np.asarray(kwargs["moving_bins"], dtype=bool)
    if "movers" in kwargs:
        kwargs["movers"] = [_mover(m) for m in kwargs["movers"]]
    return kwargs


def _mover(plain: dict[str, Any]) -> Mover:
    """A recorded :class:`Mover` (its null numbers not finite; age 0 in recordings made before movers
    lost from sight were given to the shield)."""
    age = _number(plain.get("age", 0.0))
    return Mover(_pair(plain["position"]), _pair(plain["velocity"]), _number(plain["radius"]), age)


def _pair(values: list[float | None]) -> tuple[float, float]:
    return _number(values[0]), _number(values[1])


def _number(value: float | None) -> float:
    return math.nan if value is None else float(value)


# ---- what-if output ----------------------------------------------------------------------------


def what_if_table(result: ReplayResult, top: int = 10, label: str = "other model") -> str:
    """Summary of recorded vs the what-if (``label``: another model, other shield settings), then the
    scans where they differ most."""
    steps = result.steps
    if not steps:
        return "no shielded setpoints in the recording: nothing to compare"
    rec = np.array([s.recorded for s in steps], dtype=np.float64)
    alt = np.array([s.replayed for s in steps], dtype=np.float64)
    d = np.abs(alt - rec)
    lateral_recorded = not np.isnan(rec[:, 2]).all()
    short = "oth" if label == "other model" else "new"

    def count(limits: list[list[str]]) -> str:
        c: dict[str, int] = {}
        for names in limits:
            for n in names:
                c[n] = c.get(n, 0) + 1
        return ", ".join(f"{k} {v}" for k, v in sorted(c.items())) or "-"

    def number(value: float, width: int = 9) -> str:
        return f"{'-':>{width}}" if np.isnan(value) else f"{value:{width}.3f}"

    recorded_lateral = np.abs(rec[:, 2]).mean() if lateral_recorded else np.nan
    lines = [
        f"{len(steps)} shielded setpoints compared ({result.source}; open loop: the recorded path)",
        f"{'':34}{'recorded':>14}{label:>14}",
        f"{'mean forward speed, m/s':34}{rec[:, 0].mean():14.3f}{alt[:, 0].mean():14.3f}",
        f"{'mean |yaw rate|, rad/s':34}{np.abs(rec[:, 1]).mean():14.3f}{np.abs(alt[:, 1]).mean():14.3f}",
        f"{'mean |lateral|, m/s':34}{number(recorded_lateral, 14)}{np.abs(alt[:, 2]).mean():14.3f}",
        f"{'setpoints with a shield limit':34}{sum(bool(s.recorded_limits) for s in steps):14d}"
        f"{sum(bool(s.replayed_limits) for s in steps):14d}",
        f"shield limits, recorded: {count([s.recorded_limits for s in steps])}",
        f"shield limits, {label}: {count([s.replayed_limits for s in steps])}",
        f"|Δ forward| mean {d[:, 0].mean():.3f} max {d[:, 0].max():.3f} m/s; "
        f"|Δ yaw rate| mean {d[:, 1].mean():.3f} max {d[:, 1].max():.3f} rad/s; "
        + (
            f"|Δ lateral| mean {d[:, 2].mean():.3f} max {d[:, 2].max():.3f} m/s"
            if lateral_recorded
            else "lateral not recorded"
        ),
        "",
        f"largest differences{'':4}{'t s':>8}{'front m':>9}"
        + "".join(f"{name + ' rec':>9}{name + ' ' + short:>9}" for name in ("fwd", "yaw", "lat")),
    ]
    order = np.argsort(-np.nansum(d, axis=1))[:top]
    for i in sorted(order, key=lambda i: steps[i].t):
        s = steps[i]
        lines.append(
            f"{'':23}{s.t:8.2f}{s.front_clearance:9.2f}"
            + "".join(number(rec[i, k]) + number(alt[i, k]) for k in range(3))
        )
    return "\n".join(lines)


def what_if_plot(result: ReplayResult, path: Path, title: str, label: str = "other model") -> None:
    """Forward speed, yaw rate, lateral speed and forward clearance over time: recorded vs the
    what-if (a recording without the lateral speed draws only the what-if's)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    steps = result.steps
    t = np.array([s.t for s in steps])
    rec = np.array([s.recorded for s in steps], dtype=np.float64).reshape(-1, 3)
    alt = np.array([s.replayed for s in steps], dtype=np.float64).reshape(-1, 3)
    fig = Figure(figsize=(9, 9))
    FigureCanvasAgg(fig)
    axes = fig.subplots(4, 1, sharex=True)
    for col, label in enumerate(("forward speed, m/s", "yaw rate, rad/s", "lateral speed, m/s")):
        axes[col].plot(t, rec[:, col], label="recorded", color="tab:blue")
        axes[col].plot(t, alt[:, col], label=label, color="tab:orange", alpha=0.85)
        axes[col].set_ylabel(label)
        axes[col].grid(alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[3].plot(t, [s.front_clearance for s in steps], color="tab:gray")
    axes[3].set_ylabel("front clearance, m")
    axes[3].set_xlabel("time since the first scan, s")
    axes[3].grid(alpha=0.3)
    axes[0].set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


# ---- CLI -----------------------------------------------------------------------------------------


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``replay FILE.mcap [--policy OTHER.onnx] [--set shield.KEY=VALUE ...] [--plot OUT.png]``."""
    parser.add_argument("recording", metavar="FILE.mcap", help="a recording of the companion ([recorder])")
    parser.add_argument(
        "--policy", metavar="OTHER.onnx", help="run this model instead of the recorded one (what-if)"
    )
    parser.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="shield.KEY=VALUE",
        help="run the shield with this [shield] key changed, e.g. shield.backup_gate=true "
        "(what-if; repeatable; the value is TOML, checked as the companion's config is)",
    )
    parser.add_argument(
        "--plot", metavar="OUT.png", help="what-if plot (default: next to the recording, <name>.whatif.png)"
    )


def contact_report(rec: Recording, result: ReplayResult, label: str) -> list[str]:
    """The what-if's ground-truth lines: the contact figures, or why there are none."""
    truth = rec.topic(TRUTH_STATE_TOPIC)
    if not truth:
        return [f"no ground truth ({TRUTH_STATE_TOPIC}) in the recording: contact not judged"]
    contact = first_contact(truth)
    if contact is None:
        least = least_clearance(truth)
        return [
            "ground truth: no contact"
            + (f" (least true clearance {least:.3f} m)" if least is not None else "")
        ]
    t0 = result.first_event_t
    return [approach_line(approach_figures(result.steps, contact.t - t0), contact, label)]


def command(args: argparse.Namespace) -> int:
    path = Path(args.recording)
    rec = read_recording(path)
    config, meta = recorded_config(rec)
    settings: list[str] = list(args.settings)
    if settings:
        config = with_settings(config, settings)
    model = Path(args.policy) if args.policy else Path(config.policy.model)
    if not model.is_file():
        raise UserError(
            f"model {model} not found"
            + ("" if args.policy else " (the recorded one): pass --policy FILE.onnx")
        )
    same = file_digest(model) == meta.get("model_sha256")
    policy = OnnxPolicy(model, policy_spec(config), config.policy.providers or None)
    if rec.truncated:
        print(f"note: {path} ends early (not closed); replaying what it holds")
    result = replay(rec, config, policy, compare=same and not settings)
    if result.policy_steps == 0:
        raise UserError(f"{path}: no policy steps recorded (the companion saw no scan)")
    counts = f"{result.policy_steps} scans, {result.shield_steps} shielded setpoints" + (
        f" ({result.skipped_shield} before the file's first shield reset not checked)"
        if result.skipped_shield
        else ""
    )
    if result.track_steps or result.skipped_tracks:
        counts += f", {result.track_steps} tracker updates" + (
            f" ({result.skipped_tracks} before the file's first fresh tracker not checked)"
            if result.skipped_tracks
            else ""
        )
    if same and not settings:
        if result.first_difference:
            print(f"replay of {path} from the recorded {result.source} with {model.name}: {counts}")
            print(f"DIFFERENT: first difference at {result.first_difference}")
            return 1
        print(
            f"replay of {path} from the recorded {result.source} with {model.name}: {counts}; "
            "every scan, observation, action, shield output and track matches bit for bit"
        )
        return 0
    what = [] if same else [f"{model.name} instead of the recorded model"]
    if settings:
        what.append(" ".join(settings))
    label = "new shield" if same else ("other model" if not settings else "what-if")
    print(f"what-if: {', '.join(what)}, {counts}")
    if config.shield.backup_gate and not heading_recorded(rec):
        print(
            "heading: not in the recording (the companion gives the shield none; /vehicle/status holds "
            "no attitude): the gate integrates the yaw rates it sent, as in flight"
        )
    print(what_if_table(result, label=label))
    for line in contact_report(rec, result, label):
        print(line)
    plot = Path(args.plot) if args.plot else path.with_suffix(".whatif.png")
    title = f"{path.name}: recorded vs {', '.join(what)}"
    try:
        what_if_plot(result, plot, title, label)
    except ImportError:
        print("plot skipped: matplotlib is not installed (pip install 'lidar-avoid[sim]')")
    except OSError as exc:
        print(f"plot skipped: cannot write {plot} ({exc.strerror or exc}): pass --plot OUT.png")
    else:
        print(f"plot: {plot}")
    return 0
