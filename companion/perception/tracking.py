"""Tracking what moves, from the scans alone: segment each scan into objects, follow them across
revolutions with a constant-velocity Kalman filter each, and say which of them move.

The drift estimate, the route map and the shield's obstacle memory assume that returns do not
move. :class:`ScanTracker` tells them which do: :attr:`TrackerOutput.moving_bins` marks the scan
bins whose returns belong to a moving track. No ground truth goes in: the scan and the vehicle's own
pose (the autopilot's estimate, in any frame fixed to the ground) only.

- Segments: consecutive scan bins with returns, each within ``join_distance`` of the previous
  (one empty bin may lie between), in the ground frame. A segment's width is the farthest any of
  its returns lies from either end; segments wider than ``max_extent`` (walls, racks, a room's
  walls all round) are never tracked: a person, a drone or a forklift is narrower. A round object
  seen from one side shows its near arc, whose centroid lies about 0.64 of its radius in front of
  its centre; the segment's centre is put that far behind the centroid, seen from the sensor, so
  that a pillar the vehicle flies past stays still. A segment that may go on beyond the range, or
  whose end may not be the object's (a nearer return beside it hides part of it, or one not
  clearly behind it continues the surface), is not measured in that scan: its seen centre is not
  its centre. So an object within ``background_gap`` of a wall is not tracked while it is there.
- Association: each track's predicted position against each segment's centre, the cheapest
  one-to-one assignment within ``gate`` metres (``scipy.optimize.linear_sum_assignment``).
- Filter: state (x, y, vx, vy), white-noise acceleration of ``accel_std``, centre measured to
  ``measurement_std``. A segment more than ``extent_jump`` wider or narrower than the track's last
  shows another part of the object (a box's second face comes into view as the vehicle flies
  past): it places the track without changing its velocity. A segment no track takes starts a
  tentative track; ``confirm_hits`` hits confirm it; ``max_misses`` revolutions in a row without
  one end it.
- Moving: a confirmed track, seen this revolution, faster than ``fast_speed``, or faster than
  ``moving_speed`` after ``moving_hits`` hits and in each of its last ``moving_streak``
  revolutions. Three hits measure the speed only to about 0.5 m/s (a pillar's edge bins flicker
  with the noise): a fast mover is told at once, a slow one a revolution later, and a still pillar
  not at all; a large still object whose seen centre slides as the vehicle passes may read above
  ``moving_speed`` for a revolution, not for ``moving_streak`` in a row.
- Kept moving: a moving track stays moving while it is seen faster than ``keep_speed``. A walker
  at 0.5 m/s reads 0.4-0.6 m/s from revolution to revolution: without the lower bar it dropped in
  and out of the moving tracks, and with it out of the policy's frame and the shield's movers.
- Lost from sight: a track that moved within the last ``coast_s`` and is not moving now, unseen
  since (a miss, or ended by ``max_misses``) or seen again faster than ``keep_speed`` but not yet
  moving again by the rules above, is still given to the shield (:meth:`TrackerOutput.shield_inputs`,
  not to the policy), carried on at its velocity and with its age, up to ``coast_s`` after it was
  last seen. A walker's track drops out of the moving ones for a revolution or two when a scan
  misses it (beside a wall, behind a pillar); the shield then judged its returns as standing ones.
- No pose (the autopilot's position not known): the tracker forgets everything and nothing moves.

Pure: arrays and times in, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from companion.perception.scan import N_BINS

#: a round object's visible-arc centroid lies this share of its seen width in front of its centre
_ARC_OFFSET = 2.0 / math.pi / 2.0


@dataclass(frozen=True)
class TrackerConfig:
    """How scans become tracks.

    :param join_distance: consecutive returns at most this far apart are one object, metres
    :param max_extent: wider segments (walls) are not tracked, metres
    :param min_points: fewer returns are noise, not an object
    :param gate: a track takes a segment at most this far from its prediction, metres
    :param accel_std: the filter's process noise: how hard a target accelerates, m/s²
    :param measurement_std: how well a segment's centre is measured, metres
    :param confirm_hits: hits before a track counts
    :param max_misses: revolutions in a row without a hit before a track ends
    :param moving_speed: a confirmed track faster than this after ``moving_hits`` hits, and for
        ``moving_streak`` revolutions in a row, moves, m/s
    :param moving_hits: hits before a speed above ``moving_speed`` says a track moves
    :param moving_streak: revolutions in a row above ``moving_speed`` before a track moves
    :param fast_speed: a confirmed track faster than this moves whatever its hits, m/s
    :param keep_speed: a moving track stays moving while it is seen faster than this, m/s
    :param edge_margin: a segment with an end within this of the maximum range may go on beyond
        it (a wall cut off by the range slides along with the vehicle): not tracked, metres
    :param background_gap: a segment is an object only where the returns beside it are at least
        this much farther (or none): else its end may be the sampling's, not the object's, metres
    :param coast_s: how long after it was last seen a track that moved is still given to the
        shield once lost from sight, s
    :param extent_jump: a segment this much wider or narrower than the track's last one shows
        another part of the object (a box's second face comes into view, a part goes behind
        something): its centre moved with what is seen, not with the object, so it places the track
        without changing its velocity, metres
    """

    join_distance: float = 0.35
    max_extent: float = 1.6
    min_points: int = 2
    gate: float = 1.0
    accel_std: float = 3.0
    measurement_std: float = 0.08
    confirm_hits: int = 3
    max_misses: int = 3
    moving_speed: float = 0.45
    moving_hits: int = 4
    moving_streak: int = 2
    fast_speed: float = 1.0
    keep_speed: float = 0.35
    edge_margin: float = 1.0
    background_gap: float = 1.0
    extent_jump: float = 0.2
    coast_s: float = 1.0


@dataclass
class Segment:
    """One object in one scan.

    :param centre: (x, y) in the ground frame, metres
    :param extent: its width as seen, metres
    :param bins: the scan bins its returns are in
    """

    centre: np.ndarray
    extent: float
    bins: np.ndarray


@dataclass
class Track:
    """One object followed across revolutions.

    :param track_id: unique while the tracker lives
    :param state: (x, y, vx, vy) in the ground frame, metres and m/s
    :param covariance: the state's 4 × 4 covariance
    :param first_seen: time of its first segment, seconds
    :param hits: segments it took
    :param misses: revolutions in a row it took none
    :param bins: the scan bins of its last segment
    :param extent: the width of its last segment, metres
    :param widest: the widest it was seen, metres: a round object shows up to its diameter
    :param streak: revolutions in a row it was seen faster than ``moving_speed``
    :param moving: whether it moves (:class:`ScanTracker`'s rules)
    :param seen_at: time of its last segment, seconds
    :param moved_at: the last time it moved, seconds (-inf: never)
    """

    track_id: int
    state: np.ndarray
    covariance: np.ndarray
    first_seen: float
    hits: int = 1
    misses: int = 0
    bins: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    extent: float = 0.0
    widest: float = 0.0
    streak: int = 0
    moving: bool = False
    seen_at: float = 0.0
    moved_at: float = -math.inf

    @property
    def position(self) -> np.ndarray:
        return self.state[:2]

    @property
    def velocity(self) -> np.ndarray:
        return self.state[2:]

    @property
    def speed(self) -> float:
        return float(np.hypot(*self.state[2:]))


@dataclass(frozen=True)
class Mover:
    """A moving object as the shield judges it, in the vehicle's body axes at the scan's time.

    :param position: its centre from the vehicle (forward, left), m
    :param velocity: its ground velocity along the body axes (forward, left), m/s
    :param radius: how far its surface may lie from ``position``, m
    :param age: seconds since it was last seen (a mover lost from sight): ``position`` is carried on
        at ``velocity`` from where it was then
    """

    position: tuple[float, float]
    velocity: tuple[float, float]
    radius: float
    age: float = 0.0


@dataclass
class TrackerOutput:
    """What one scan's update says.

    :param tracks: the confirmed tracks
    :param moving: the confirmed tracks that move
    :param moving_bins: ``(360,)`` bool: bins whose return this scan belongs to a moving track
    :param pose: the vehicle's (x, y, yaw) the scan was tracked at (None: not known, nothing tracked)
    :param lost: the tracks lost from sight that the shield still judges (:class:`ScanTracker`)
    :param time: the scan's time, seconds
    """

    tracks: list[Track]
    moving: list[Track]
    moving_bins: np.ndarray
    pose: tuple[float, float, float] | None = None
    lost: list[Track] = field(default_factory=list)
    time: float = 0.0

    def movers(self) -> list[Mover]:
        """The moving tracks in the body axes (:func:`movers_in_body`), as the policy takes them;
        none without a pose."""
        return [] if self.pose is None else movers_in_body(self.moving, self.pose)

    def shield_inputs(self) -> dict[str, Any]:
        """What :meth:`companion.safety.shield.SafetyShield.filter` takes of this update: its
        ``moving_bins`` and ``movers`` keywords, the movers with those lost from sight and their ages."""
        if self.pose is None:
            return {"moving_bins": self.moving_bins, "movers": []}
        movers = movers_in_body(self.moving + self.lost, self.pose, self.time)
        return {"moving_bins": self.moving_bins, "movers": movers}


class ScanTracker:
    """Tracks objects across scans (one instance per flight).

    :param config: the tracker's settings
    :param max_range: metres a scan value of 1.0 stands for (nothing returned)
    """

    def __init__(self, config: TrackerConfig | None = None, max_range: float = 10.0) -> None:
        self.config = config or TrackerConfig()
        self.max_range = float(max_range)
        angles = np.radians(np.arange(N_BINS) + 0.5)  # bin centres, counter-clockwise from the nose
        self._cos, self._sin = np.cos(angles), np.sin(angles)
        self.reset()

    def reset(self) -> None:
        """Forget every track (a new flight, or a scan without a pose: the next cannot be placed
        against the last)."""
        self.tracks: list[Track] = []
        self._ended: list[Track] = []  # tracks ended while lost from sight, carried on for the shield
        self._next_id = 0
        self._time: float | None = None

    @property
    def fresh(self) -> bool:
        """No scan taken since it was made or reset: the next update depends on nothing before it
        (a replay can check the updates from here on)."""
        return self._time is None

    def update(self, scan: np.ndarray, pose: tuple[float, float, float] | None, time: float) -> TrackerOutput:
        """Take one scan.

        :param scan: ``(360,)`` normalised ranges (:func:`companion.perception.scan.scan_from_points`)
        :param pose: the vehicle's (x, y, yaw) in a frame fixed to the ground, metres and radians CCW;
            None (not known): the tracker resets and says nothing moves
        :param time: the scan's time, seconds (any clock that only goes forward)
        """
        if pose is None:
            self.reset()
            return TrackerOutput([], [], np.zeros(N_BINS, dtype=bool))
        cfg = self.config
        dt = 0.0 if self._time is None else max(float(time) - self._time, 0.0)
        self._time = float(time)
        now = self._time
        for track in self.tracks + self._ended:
            _predict(track, dt, cfg.accel_std)
        segments = self.segments(scan, pose)
        taken = self._associate(segments)
        for track in self.tracks:
            if track.track_id not in taken:
                track.misses += 1
            else:
                track.seen_at = now
            fast = track.track_id in taken and track.speed > cfg.moving_speed
            track.streak = track.streak + 1 if fast else 0
        gone = [t for t in self.tracks if t.misses > cfg.max_misses]
        self._ended += [t for t in gone if now - t.moved_at <= cfg.coast_s]
        self.tracks = [t for t in self.tracks if t.misses <= cfg.max_misses]
        confirmed = [t for t in self.tracks if t.hits >= cfg.confirm_hits]
        for t in confirmed:
            starts = t.speed > cfg.fast_speed or (t.speed > cfg.moving_speed and self._settled(t))
            t.moving = t.misses == 0 and (starts or (t.moving and t.speed > cfg.keep_speed))
            if t.moving:
                t.moved_at = now
        moving = [t for t in confirmed if t.moving]
        mask = np.zeros(N_BINS, dtype=bool)
        for track in moving:
            mask[track.bins] = True
        return TrackerOutput(confirmed, moving, mask, tuple(pose), self._lost(now), now)

    def _lost(self, now: float) -> list[Track]:
        """The tracks lost from sight that the shield still judges (the module doc); an ended one is
        forgotten once ``coast_s`` has passed since it was seen, or a track the shield judges lies
        within ``gate`` of it (the same object, found again)."""
        cfg = self.config
        alive = [
            t
            for t in self.tracks
            if not t.moving
            and now - t.moved_at <= cfg.coast_s
            and (t.misses > 0 or t.speed > cfg.keep_speed)
            and now - t.seen_at <= cfg.coast_s
        ]
        judged = [t.position for t in self.tracks if t.moving] + [t.position for t in alive]
        self._ended = [
            t
            for t in self._ended
            if now - t.seen_at <= cfg.coast_s
            and all(float(np.hypot(*(t.position - p))) > cfg.gate for p in judged)
        ]
        return alive + self._ended

    def _settled(self, track: Track) -> bool:
        """Whether a slow track's speed says it moves: enough hits, and fast for long enough in a row."""
        return track.hits >= self.config.moving_hits and track.streak >= self.config.moving_streak

    def segments(self, scan: np.ndarray, pose: tuple[float, float, float]) -> list[Segment]:
        """The scan's objects narrow enough to track, in the ground frame."""
        cfg = self.config
        values = np.asarray(scan, dtype=np.float64).reshape(N_BINS)
        hit = values < 1.0
        if not hit.any():
            return []
        r = values * self.max_range
        x, y, yaw = pose
        c, s = math.cos(yaw), math.sin(yaw)
        bx, by = r * self._cos, r * self._sin
        wx, wy = x + c * bx - s * by, y + s * bx + c * by
        # start the walk where a run starts (no return within two bins before, or one too far), so
        # that no segment is cut where the bins wrap: not after an empty bin, as a room's walls all
        # round leave none
        index = np.arange(N_BINS)
        one, two = np.roll(index, 1), np.roll(index, 2)
        before = np.where(hit[one], one, two)
        joined = (hit[one] | hit[two]) & (np.hypot(wx - wx[before], wy - wy[before]) <= cfg.join_distance)
        starts = np.flatnonzero(hit & ~joined)
        order = np.roll(index, -int(starts[0])) if starts.size else index
        runs: list[list[int]] = []
        gap = 0
        for i in order:
            if not hit[i]:
                gap += 1
                continue
            if (
                runs
                and gap <= 1
                and math.hypot(wx[i] - wx[runs[-1][-1]], wy[i] - wy[runs[-1][-1]]) <= cfg.join_distance
            ):
                runs[-1].append(int(i))
            else:
                runs.append([int(i)])
            gap = 0
        out = []
        for run in runs:
            idx = np.asarray(run)
            if idx.size < cfg.min_points:
                continue
            px, py = wx[idx], wy[idx]
            # its width: the farthest any return lies from either end (not the ends' distance alone,
            # which a run curling round the vehicle, a room's walls, brings close together)
            extent = float(
                max(np.hypot(px - px[0], py - py[0]).max(), np.hypot(px - px[-1], py - py[-1]).max())
            )
            if extent > cfg.max_extent or max(r[idx[0]], r[idx[-1]]) > self.max_range - cfg.edge_margin:
                continue
            if self._occluded(hit, r, idx[0], -1) or self._occluded(hit, r, idx[-1], 1):
                continue
            cx, cy = float(px.mean()), float(py.mean())
            away = np.array([cx - x, cy - y])
            away /= max(float(np.hypot(*away)), 1e-9)
            centre = np.array([cx, cy]) + away * _ARC_OFFSET * extent
            out.append(Segment(centre, extent, idx))
        return out

    def _occluded(self, hit: np.ndarray, r: np.ndarray, end: int, side: int) -> bool:
        """Whether a segment's end may not be the object's: next to it is a nearer return
        (something in front hides part of it) or one not clearly behind it (the surface goes on,
        its points only too far apart at a grazing angle, as along a wall)."""
        for step in (1, 2):
            k = (end + side * step) % N_BINS
            if hit[k]:
                return bool(r[k] < r[end] + self.config.background_gap)
        return False

    def _associate(self, segments: list[Segment]) -> set[int]:
        """Update the tracks with the segments they take; new tracks for the rest. Returns the ids
        of the tracks that took one."""
        cfg = self.config
        taken: set[int] = set()
        used = np.zeros(len(segments), dtype=bool)
        if self.tracks and segments:
            predicted = np.array([t.position for t in self.tracks])
            centres = np.array([seg.centre for seg in segments])
            cost = np.hypot(
                predicted[:, None, 0] - centres[None, :, 0], predicted[:, None, 1] - centres[None, :, 1]
            )
            rows, cols = linear_sum_assignment(np.where(cost <= cfg.gate, cost, 1e6))
            for i, j in zip(rows, cols, strict=True):
                if cost[i, j] > cfg.gate:
                    continue
                track, seg = self.tracks[i], segments[j]
                if abs(seg.extent - track.extent) > cfg.extent_jump:
                    _place(track, seg.centre, cfg.measurement_std)
                else:
                    _correct(track, seg.centre, cfg.measurement_std)
                track.hits += 1
                track.misses = 0
                track.bins = seg.bins
                track.extent = seg.extent
                track.widest = max(track.widest, seg.extent)
                taken.add(track.track_id)
                used[j] = True
        for seg, was_used in zip(segments, used, strict=True):
            if not was_used:
                self.tracks.append(self._new_track(seg))
        return taken

    def _new_track(self, seg: Segment) -> Track:
        self._next_id += 1
        state = np.array([seg.centre[0], seg.centre[1], 0.0, 0.0])
        covariance = np.diag([self.config.measurement_std**2] * 2 + [2.0**2] * 2)
        return Track(
            self._next_id,
            state,
            covariance,
            self._time or 0.0,
            bins=seg.bins,
            extent=seg.extent,
            widest=seg.extent,
            seen_at=self._time or 0.0,
        )


def _predict(track: Track, dt: float, accel_std: float) -> None:
    """Constant velocity over ``dt``, white-noise acceleration."""
    if dt <= 0.0:
        return
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt
    g = np.array([[dt * dt / 2.0, 0.0], [0.0, dt * dt / 2.0], [dt, 0.0], [0.0, dt]])
    track.state = f @ track.state
    track.covariance = f @ track.covariance @ f.T + accel_std**2 * (g @ g.T)


def _correct(track: Track, centre: np.ndarray, measurement_std: float) -> None:
    """The Kalman update with a measured position."""
    h = np.zeros((2, 4))
    h[0, 0] = h[1, 1] = 1.0
    innovation = centre - h @ track.state
    s = h @ track.covariance @ h.T + measurement_std**2 * np.eye(2)
    gain = track.covariance @ h.T @ np.linalg.inv(s)
    track.state = track.state + gain @ innovation
    track.covariance = (np.eye(4) - gain @ h) @ track.covariance


def _place(track: Track, centre: np.ndarray, measurement_std: float) -> None:
    """The track put at a measured position that says nothing of its motion: the velocity and its
    uncertainty stay, the position is the measurement's."""
    track.state = np.concatenate([centre, track.state[2:]])
    covariance = track.covariance.copy()
    covariance[:2, :] = 0.0
    covariance[:, :2] = 0.0
    covariance[:2, :2] = measurement_std**2 * np.eye(2)
    track.covariance = covariance


def without_movers(scan: np.ndarray, moving_bins: np.ndarray) -> np.ndarray:
    """``scan`` with the bins of moving returns read as nothing returned (1.0): what the drift
    estimate matches, so that a mover's motion is not taken for the vehicle's own.

    :param scan: ``(360,)`` normalised ranges
    :param moving_bins: ``(360,)`` bool, :attr:`TrackerOutput.moving_bins`
    :returns: a copy (``scan`` itself when nothing moves)
    """
    if not moving_bins.any():
        return scan
    return np.where(moving_bins, np.asarray(1.0, dtype=scan.dtype), scan)


def movers_in_body(
    tracks: list[Track], pose: tuple[float, float, float], now: float | None = None
) -> list[Mover]:
    """Tracks as the shield takes them: in the body axes of the vehicle at ``pose`` (the pose the
    scan was tracked at), the velocity turned into those axes, the radius half the widest the track
    was seen, and the age since it was last seen.

    :param tracks: :attr:`TrackerOutput.moving` (and :attr:`TrackerOutput.lost`)
    :param pose: the vehicle's (x, y, yaw) in the tracker's ground frame, metres and radians CCW
    :param now: the scan's time, seconds (None: every track seen in it, age 0)
    """
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for track in tracks:
        dx, dy = float(track.state[0]) - x, float(track.state[1]) - y
        vx, vy = float(track.state[2]), float(track.state[3])
        age = 0.0 if now is None else max(now - track.seen_at, 0.0)
        position, velocity = (c * dx + s * dy, -s * dx + c * dy), (c * vx + s * vy, -s * vx + c * vy)
        out.append(Mover(position, velocity, track.widest / 2.0, age))
    return out
