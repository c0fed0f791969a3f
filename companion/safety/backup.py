"""The backup gate: a command passes only if the vehicle can still be stopped clear after it.

The guarantee (stated in full in ARCHITECTURE.md, "The shield's guarantee"):

*Assumptions.* The world is static. Every obstacle that matters has been seen by the scans within
the memory horizon (:class:`~companion.safety.obstacle_memory.ObstacleMemory`). The autopilot
answers within the firmware envelope (:mod:`companion.safety.envelope`): the delay window, the
acceleration and deceleration bounds, the overshoot, and a velocity-estimate error of at most
``estimate_error``. The heading is known (or the commanded yaw rates are flown).

*Promise.* Whatever commands arrive, every command sent keeps a *backup* available: braking to a
stop (a zero setpoint), after which the envelope's worst-case displacement towards every
direction stays below the clearance of the remembered returns that way less ``body_radius +
margin``. So the true vehicle centre stays at least ``body_radius + margin`` from every remembered
return until the vehicle is stopped. What comes after the stop, the creep of the estimate error
(up to ``estimate_error`` m/s), is not covered. With a position loop (ArduPilot, the envelope's
finite ``position_error``) the worst case up to the stop already holds the creep's capped share:
the stop comes no sooner than ``period + max_delay``. The cap is the real flights' over a few
seconds; held longer, the estimate's own drift carries the vehicle on (the simulated ArduPilot
crept 0.6 m in 19 s of zero setpoints), so it is not covered with ArduPilot either.

*Proof sketch.* Each remembered return with its inflation holds the true one at the step it is
judged. Let S say "from here, the backup keeps the worst case clear of the returns". A command u
passes only if u for one period, then the backup, keeps the worst case clear. When none passes
but the last command sent passed, or is that command's backup sent again since, the backup is sent
again (``gate_backup_kept``): it continues the setpoint sequence verified then, from a state inside
that worst case, so its worst case is a part of the one verified, which was clear of the returns as
they were known then, and so of the true ones. It is not judged again: the memory's inflation
grows with a return's age (even while the same surface is seen again), so a stop verified may not
pass a step later, though nothing has come closer. This holds until the verified worst case has
stopped, which is where the promise ends. By induction, from a first state where S holds
(standstill, clear), every command sent passes or continues a verified backup, and no true
trajectory leaves a verified worst case before its stop.

*Not covered.* Obstacles the scans never saw (below or above the beams, hidden, outside the memory
horizon), anything that moves but is not given as a mover (below), an envelope the firmware leaves
(a gust, a motor failure, a wrong heading), the creep once stopped, and a state where S does not
hold with no verified backup running (a start closer to a return than the creep allows, or a stop
the creep or the memory's growing inflation has left there): there the gate sends the stop or a
candidate as good (``gate_best_effort``), backing away from the nearest return where the envelope
has that truly move away and it raises nothing that decides (:meth:`BackupGate.choose`).

*Movers.* The tracker's moving objects (:class:`~companion.perception.tracking.Mover`: centre,
ground velocity and radius in the body axes at the scan's time, and the age of a mover lost from
sight; :func:`mover_rows`) are not returns: their returns stay out of the memory (the shield's
doing), and each is judged along its motion. The model (:class:`MoverModel`, ``[shield] mover_*``):
a mover moves at up to ``speed`` (``mover_speed``, 1.5 m/s, a walker); when seen, its true velocity
is within ``velocity_error`` of the tracked one, and it changes at up to ``accel`` from then on. So
``τ`` after it was seen (a scan is at most a period old when its command is sent; a mover the
tracker has lost from sight was seen its ``age`` before that scan, and is judged from where it was
then), its speed towards any direction ``-n`` is at most ``min(c_n + velocity_error + accel·τ,
speed)``, ``c_n`` the tracked one's, and every point ``o`` of its body has ``o·n >= p·n - radius -
H_n(τ)``, ``H_n`` the integral of that speed: within ``radius + speed·τ`` of where it was seen in
any case, less towards the vehicle when it walks away. A candidate passes only if, in addition, at
every step of its worst case up to its stop where the vehicle may move faster than the creep
(standing still, it closes on nothing), some direction separates the farthest displacement so far
from that bound over the step, by ``body_radius + margin``, as for a return. The promise then reads:
with movers that keep within the model and are seen, every command sent keeps a backup whose worst
case stays clear of them until the vehicle is stopped (to within the creep). The vehicle never
closes on a mover while it moves; a contact can only come once it is stopped, by the mover's own
motion (passive safety). The induction needs each scan's mover set to lie within the one judged a
period before: true of the speed bound alone (a mover that moved at up to ``speed`` stays in the
disc grown from where it was seen), and of the tracked velocity's narrowing while successive tracked
velocities differ by at most ``accel`` times the period. Not covered: a mover faster than ``speed``
(counted, ``mover_too_fast``, and judged at its tracked speed plus the velocity error), one that
keeps coming after the stop (pursuit), one never seen or never tracked (or lost from sight longer
than the tracker's ``coast_s``), and one first seen inside the reach; where no command keeps clear
of a mover, the gate sends, of those clear of the returns, the one that leaves the movers the most
room (``gate_mover_best_effort``).

Separation makes it cheap: with ``X_m`` the worst displacement towards direction ``m`` over the
horizon, every reachable position ``d`` has ``d·m <= X_m`` for all ``m``; so for a return ``o``,
``|o - d| >= (o - d)·m >= o·m - X_m`` for any one ``m``. A return is clear when some direction
separates it: ``max_m (o·m - X_m) >= body_radius + margin`` (:func:`separation`). The worst case is
bounded towards 72 directions; a wall beside the course is separated by its normal, a return ahead
by its bearing.

*Cost* (``bench/bench_shield.py``; the budget is 5 % of the scan period at the 99th percentile).
Every shortcut gives the rooms of the plain computation (``tests/companion/test_backup_gate.py``
holds it to them). While the gate passes, :meth:`BackupGate.choose` judges the asked command alone
first; once it refuses, the asked and its candidates share one worst case (the asked still judged
on its own horizon). A (candidate, direction) pair whose targets the candidate never raises above
the history's and the backup's shares their worst case. The integration stops where every
direction has stopped (a guess, checked, else the whole horizon); without a jerk limit, the bound
is integrated alone and the displacement summed after it (``envelope.worst_closing``). The
shield's sidesteps (``give_way``) are judged beside the candidates, on the same worst case
(:meth:`BackupGate.choose_beside`), and their movers' room only where the returns leave them room.
:func:`separation` takes the returns by a lower bound of their room and leaves a candidate once no
further return can go below it. Slower is not always safer (of a command away from a return, the
slower one raises the worst case towards it more), so every candidate is judged, none found by
bisection. A mover is first bounded by distances alone (the vehicle within its farthest reach,
the mover within its speed of where it was seen); only a (mover, candidate) pair that bound leaves
short is searched step by step, so its room is exact where it decides (below the clearance) and a
lower bound above.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from companion.safety.envelope import STEP_S, ResponseEnvelope, worst_closing

if TYPE_CHECKING:
    from companion.perception.tracking import Mover

#: the directions the worst case is bounded towards, every 5 degrees
N_DIRECTIONS = 72
_DIR_RAD = np.radians(np.arange(N_DIRECTIONS) * (360.0 / N_DIRECTIONS))
_DIR_UNIT = np.stack([np.cos(_DIR_RAD), np.sin(_DIR_RAD)], axis=1)
#: the longest worst case integrated, s (a backup from the highest speed settles well inside it)
MAX_HORIZON_S = 8.0
#: returns searched at once in :func:`separation`
_CHUNK = 64
#: returns sorted before the search starts (the rest only if it gets that far)
_HEAD = 4 * _CHUNK
#: fractions of the asked velocity tried when it does not pass, fastest first
_SCALES = np.linspace(1.0, 0.0, 11)
#: fractions of ``retreat_speed`` the best effort's retreat is tried at, fastest first
_RETREATS = np.array([1.0, 0.5, 0.2])


def separation(points: np.ndarray, inflation: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """Per candidate, the least over the returns of the best separating direction's room, m.

    :param points: ``(p, 2)`` returns in the body frame (forward, left), m
    :param inflation: ``(p,)`` how far each may truly lie from where it is recorded, m
    :param displacement: ``(m, 72)`` each candidate's worst displacement towards each direction, m
    :return: ``(m,)`` ``min_o max_n (o·n - inflation_o - X_n)``; inf without returns
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    grown = np.asarray(inflation, dtype=np.float64)
    least = np.full(len(displacement), math.inf)
    # each return's own bearing (within half a sector of a direction) separates it by at least
    # |o| cos(half a sector) - inflation - the candidate's farthest reach (less a hair, so rounding
    # never lifts the bound over the room it bounds): take the returns in that order, and leave a
    # candidate where the bound cannot go below what the nearer ones left it
    bound = np.hypot(pts[:, 0], pts[:, 1]) * math.cos(math.pi / N_DIRECTIONS) - grown - 1e-9
    # sorted lazily: the nearest few chunks first (usually all it takes), the rest only if reached
    head = min(len(bound), _HEAD)
    part = np.argpartition(bound, head - 1) if len(bound) > head else np.arange(len(bound))
    order = part[:head][np.argsort(bound[part[:head]])]
    farthest = displacement.max(axis=1, initial=-math.inf)
    for start in range(0, len(bound), _CHUNK):
        if start >= len(order):  # every one left bounds no lower than those taken
            order = np.concatenate([order, part[head:][np.argsort(bound[part[head:]])]])
        chunk = order[start : start + _CHUNK]
        open_ = np.flatnonzero(~(bound[chunk[0]] - farthest >= least))  # a NaN reach stays open
        if len(open_) == 0:
            break
        along = pts[chunk] @ _DIR_UNIT.T - grown[chunk][:, None]  # (c, 72)
        room = (along[None, :, :] - displacement[open_, None, :]).max(axis=2).min(axis=1)
        least[open_] = np.minimum(least[open_], room)
    return least


@dataclass
class _Sent:
    """Setpoints sent so far (world frame by the heading at sending), newest last."""

    times: list[float]
    vectors: list[np.ndarray]


@dataclass
class _WorstCase:
    """A batch's worst case: what :meth:`BackupGate.passes` would find with any horizon up to ``steps``.

    Integrated per column: the 72 directions without the candidates (the history and the backup
    alone), then each (candidate, direction) pair the candidate raises above them."""

    reached: np.ndarray  # (n + 1, c) the farthest displacement so far at each step, per column
    settled: np.ndarray  # (c,) the step each column stops at (``steps`` when it does not)
    column: np.ndarray  # (m, 72) each pair's column
    steps: int  # the horizon's steps for the whole batch
    base_peak: float  # the highest closing speed without the candidates: now, or set by what was sent
    cand_peak: np.ndarray  # (m,) each candidate's highest target
    fast: np.ndarray  # (n + 1, c) where the closing speed may exceed the creep, per column

    def reach(self, steps: int | np.ndarray, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """``(m, 72)`` the worst displacement towards each direction up to the stop, with the horizon cut
        at ``steps`` (the stop a shorter horizon never reaches is its end; ``(m, 1)``: one per row), for
        the candidates ``rows``."""
        column = self.column[rows]
        return self.reached[np.minimum(self.settled[column], steps), column]


@dataclass(frozen=True)
class MoverModel:
    """What the gate assumes of a mover's motion (the module doc, "Movers").

    :param speed: the highest ground speed of a mover, m/s: any motion up to it stays inside the
        disc ``radius + speed·t`` round where it was seen
    :param accel: how fast a mover's velocity may change, m/s²
    :param velocity_error: how far a mover's true velocity may be from the tracked one when seen, m/s
    """

    speed: float = 1.5
    accel: float = 3.0
    velocity_error: float = 0.3


class BackupGate:
    """Passes the command closest to the asked one whose backup stays clear (see the module doc).

    :param envelope: the firmware envelope
    :param clearance: how far the vehicle centre must stay from every return: body radius + margin, m
    :param period: the control period: how long a command is flown before the next can be the backup,
        and how old a scan may be when its command is sent, s
    :param unknown_speed: the speed assumed in every direction when the velocity is not known, m/s
    :param movers: what the gate assumes of the movers' motion
    :param retreat_speed: the speed of the best effort's retreat from the nearest return, m/s
    """

    def __init__(
        self,
        envelope: ResponseEnvelope,
        clearance: float,
        period: float = 0.1,
        unknown_speed: float = 2.0,
        movers: MoverModel | None = None,
        retreat_speed: float = 0.5,
    ) -> None:
        self.envelope = envelope
        self.clearance = float(clearance)
        self.period = float(period)
        self.unknown_speed = float(unknown_speed)
        self.movers = movers if movers is not None else MoverModel()
        self.retreat_speed = float(retreat_speed)
        # a retreat counts only where the envelope has it truly move away (its target below 0)
        self._retreats = envelope.target(-self.retreat_speed * _RETREATS) < 0.0
        self._sent = _Sent([], [])
        self._time = 0.0
        self._heading = 0.0
        # whether the last command was refused: then the next likely is too, and the asked is judged
        # with its candidates in one batch rather than alone first (the same choice, sooner)
        self._intervening = False
        # until when (gate clock, s) the worst case of the last verified command runs to its stop: up
        # to then, sending that command's backup again keeps the promise (``gate_backup_kept``)
        self._kept_until = -math.inf
        # what :meth:`choose` offered last, and the ``_kept_until`` it sets when sent (None: unchanged)
        self._offered: tuple[np.ndarray, float | None] | None = None

    def reset(self) -> None:
        """Forget the setpoints sent (a new engagement starts from a zero setpoint held long)."""
        self._sent = _Sent([], [])
        self._intervening = False
        self._kept_until = -math.inf
        self._offered = None

    def advance(self, dt: float, heading: float | None, yaw_rate: float) -> None:
        """Move the gate's clock by ``dt`` and its heading to ``heading`` (rad, counter-clockwise),
        or by ``yaw_rate`` flown for ``dt`` when the heading is not known."""
        step = dt if math.isfinite(dt) and dt > 0.0 else 0.0
        self._time += step
        self._heading = (
            float(heading)
            if heading is not None and math.isfinite(heading)
            else (self._heading + yaw_rate * step)
        )
        keep = self._time - self.envelope.max_delay - self.period
        while len(self._sent.times) > 1 and self._sent.times[1] <= keep:
            del self._sent.times[0]
            del self._sent.vectors[0]

    def record(self, body: tuple[float, float]) -> None:
        """The setpoint (body forward, left, m/s) that was sent now: it keeps a verified backup only
        if it is what :meth:`choose` offered as one."""
        offered, self._offered = self._offered, None
        if offered is None or not np.array_equal(offered[0], body):
            self._kept_until = -math.inf
        elif offered[1] is not None:
            self._kept_until = offered[1]
        c, s = math.cos(self._heading), math.sin(self._heading)
        self._sent.times.append(self._time)
        self._sent.vectors.append(np.array([c * body[0] - s * body[1], s * body[0] + c * body[1]]))

    def passes(
        self,
        candidates: np.ndarray,
        velocity: tuple[float, float] | None,
        points: np.ndarray,
        inflation: np.ndarray,
        movers: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Which candidate body setpoints keep their backup clear, and by how much.

        :param candidates: ``(m, 2)`` body setpoints (forward, left), m/s
        :param velocity: the measured body velocity less the drift estimate, m/s (None: not known)
        :param points: ``(p, 2)`` the remembered returns, body frame, m
        :param inflation: ``(p,)`` their inflation, m
        :param movers: ``(k, 6)`` the movers (:func:`mover_rows`); None: none
        :return: ``(m,)`` bools and ``(m,)`` the least room left (from the returns and the movers), m
        """
        least, _ = self._judge(np.atleast_2d(np.asarray(candidates, dtype=np.float64)), velocity, points,
                               inflation, movers)  # fmt: skip
        return least >= 0.0, least

    def _judge(
        self,
        candidates: np.ndarray,
        velocity: tuple[float, float] | None,
        points: np.ndarray,
        inflation: np.ndarray,
        movers: np.ndarray | None,
    ) -> tuple[np.ndarray, _WorstCase]:
        """:meth:`passes`' rooms (the least from the returns and the movers), and the worst case they
        were found on."""
        worst = self._worst_case(candidates, velocity)
        least = separation(points, inflation, worst.reach(worst.steps)) - self.clearance
        if movers is not None and len(movers):
            rows = np.arange(len(worst.column))
            least = np.minimum(least, self._mover_room(worst, rows, worst.steps, np.asarray(movers)))
        return least, worst

    def _stop_time(self, worst: _WorstCase, row: int, steps: int) -> float:
        """The gate-clock time by which candidate ``row``'s worst case (horizon cut at ``steps``) has
        stopped in every direction, s."""
        return self._time + STEP_S * float(np.minimum(worst.settled[worst.column[row]], steps).max())

    def mover_caps(self, movers: np.ndarray) -> np.ndarray:
        """``(k,)`` the speed each mover is assumed to keep within, m/s: the model's, or for a mover
        tracked faster than that (outside the promise), its tracked speed plus the velocity error."""
        model = self.movers
        speed = np.hypot(movers[:, 2], movers[:, 3])
        return np.where(speed > model.speed, speed + model.velocity_error, model.speed)

    def _mover_bounds(self, movers: np.ndarray, steps: int) -> np.ndarray:
        """``(k, steps, 72)``: for each mover and each step ``[t_j, t_j+1]`` of the worst case, a lower
        bound of ``o·n`` over every point ``o`` of the mover's body then, towards each direction ``n``, m.

        The mover was seen up to a period and its age before now (where it was then: its centre less
        its velocity times its age), so at ``t`` it has moved for ``τ = age + period + t``.
        Its velocity towards ``-n`` (towards the vehicle, for the returns beyond it along ``n``) is at
        most its speed cap and at most the tracked one's plus ``e + a·τ`` (the velocity error when
        seen, then the acceleration): its body lies at least ``o·n >= p·n - radius - H(τ)`` with ``H``
        the integral of the lower of the two. ``H`` is convex (its rate only grows), so the higher of
        a step's two ends bounds the step.
        """
        model = self.movers
        tau = movers[:, 5:6] + self.period + STEP_S * np.arange(steps + 1)  # (k, steps + 1)
        closing = -(movers[:, 2:4] @ _DIR_UNIT.T) + model.velocity_error  # (k, 72): the rate at τ = 0
        cap = self.mover_caps(movers)[:, None]
        # the rate meets the cap at τ = (cap - closing) / a: H is closing·τ + a·τ²/2 before, cap·τ after
        if model.accel > 0.0:
            meet = np.maximum(cap - closing, 0.0) / model.accel
        else:
            meet = np.where(closing < cap, math.inf, 0.0)
        ramp = np.minimum(meet[:, None, :], tau[:, :, None])  # (k, steps + 1, 72)
        extent = closing[:, None, :] * ramp + 0.5 * model.accel * ramp * ramp
        extent += cap[:, :, None] * (tau[:, :, None] - ramp)
        reach = np.maximum(extent[:, :-1], extent[:, 1:])
        return (_where_seen(movers) @ _DIR_UNIT.T - movers[:, 4:5])[:, None, :] - reach

    def _mover_room(
        self, worst: _WorstCase, rows: np.ndarray, steps: np.ndarray | int, movers: np.ndarray
    ) -> np.ndarray:
        """``(len(rows),)`` per candidate, the least room to any mover over every step up to its stop
        where the vehicle may move faster than the creep, less the clearance, m: exact where it is
        below 0 (where it decides), a lower bound above.

        Each step's vehicle bound is the farthest displacement so far towards each direction (up to
        that direction's stop: beyond it, what moves is the creep, as for the returns), separated
        from the mover's bound over that step by the best direction, as :func:`separation` does.
        A (mover, candidate) pair is first bounded by distances alone: the vehicle stays within its
        farthest reach over ``cos(half a sector)``, the mover within its speed cap of where it was seen.

        :param rows: the candidates (rows of ``worst.column``)
        :param steps: the horizon cut per candidate (or one for all), as :meth:`_WorstCase.reach` takes it
        :param movers: ``(k, 6)`` :func:`mover_rows`
        """
        column = worst.column[rows]  # (m, 72)
        stop = np.minimum(worst.settled[column], np.reshape(steps, (-1, 1)))  # (m, 72)
        last = stop.max(axis=1)  # the step by which every direction has stopped
        farthest = worst.reached[stop, column].max(axis=1) / math.cos(math.pi / N_DIRECTIONS)  # (m,)
        seen = np.hypot(*_where_seen(movers).T) - movers[:, 4]  # (k,)
        tau = movers[:, 5:6] + self.period + STEP_S * last  # (k, m)
        room = seen[:, None] - self.mover_caps(movers)[:, None] * tau - farthest[None] - self.clearance
        near = np.flatnonzero((room < 0.0).any(axis=1))  # movers some candidate must be searched for
        open_ = np.flatnonzero((room[near] < 0.0).any(axis=0))  # and those candidates
        if len(open_) == 0:
            return room.min(axis=0)
        n = int(last[open_].max())
        j = np.arange(1, n + 1)
        cols = column[open_]
        # the farthest so far up to each direction's stop: the columns only grow until every one has
        # stopped, so the lower of the step's and the stop's
        reach = np.minimum(worst.reached[1 : n + 1][:, cols], worst.reached[stop[open_], cols])  # (n, m', 72)
        bounds = self._mover_bounds(movers[near], n)  # (k', n, 72)
        exact = (bounds[:, :, None] - reach[None]).max(axis=3)  # (k', n, m')
        # the steps up to the stop where the vehicle may move faster than the creep at either end
        # (the closing bound changes linearly within a step): at rest, a contact is the mover's
        fast = worst.fast[: n + 1][:, cols].any(axis=2)  # (n + 1, m')
        judged = (j[:, None] <= last[open_]) & (fast[:-1] | fast[1:])
        exact = np.where(judged[None], exact, math.inf).min(axis=1)
        room[np.ix_(near, open_)] = exact - self.clearance
        return room.min(axis=0)

    def _worst_case(self, cand: np.ndarray, velocity: tuple[float, float] | None) -> _WorstCase:
        """The worst case of every candidate in ``cand`` (``(m, 2)``, body), integrated once for all."""
        env = self.envelope
        heading = self._heading
        c, s = math.cos(heading), math.sin(heading)
        units_world = _DIR_UNIT @ np.array([[c, s], [-s, c]])  # body directions turned into the world
        cand_world = np.stack([c * cand[:, 0] - s * cand[:, 1], s * cand[:, 0] + c * cand[:, 1]], axis=1)
        cand_comp = cand_world @ units_world.T  # (m, 72)
        if velocity is None:
            closing = np.full(N_DIRECTIONS, self.unknown_speed)
        else:
            closing = _DIR_UNIT @ np.asarray(velocity, dtype=np.float64)
        now_peak = float(np.max(closing)) + env.estimate_error
        base_peak = max(now_peak, self._history_peak())
        cand_peak = env.target(cand_comp).max(axis=1)  # (m,): each candidate's own horizon
        steps = self._steps(max(base_peak, float(cand_peak.max())))
        times = STEP_S * np.arange(steps)
        # the history's highest component in force at each future time, and the candidate's window
        history = self._history_components(units_world, times)  # (k, 72), -inf where none in force
        # a setpoint counts over every step its span touches (see envelope.window_targets)
        cand_on = (times + STEP_S > env.min_delay) & (times <= self.period + env.max_delay)
        backup_on = times + STEP_S > self.period + env.min_delay
        # the targets without the candidate (the history and the backup), and with it in its window
        shared = env.target(np.where(backup_on[:, None], np.maximum(history, 0.0), history))  # (k, 72)
        own = np.maximum(history[cand_on][:, None, :], cand_comp[None])
        own = env.target(np.where(backup_on[cand_on][:, None, None], np.maximum(own, 0.0), own))  # (w, m, 72)
        # a pair whose targets the candidate never raises has the shared worst case: integrate the
        # 72 shared columns and the raised pairs only (each column's arithmetic is the same as alone)
        raised = np.flatnonzero((own != shared[cand_on][:, None, :]).any(axis=0))  # into (m * 72)
        direction = raised % N_DIRECTIONS
        column = np.tile(np.arange(N_DIRECTIONS), (len(cand), 1))
        column.flat[raised] = N_DIRECTIONS + np.arange(len(raised))
        targets = np.concatenate([shared, shared[:, direction]], axis=1)  # (k, c)
        targets[cand_on, N_DIRECTIONS:] = own.reshape(len(own), -1)[:, raised]
        closing_now = np.concatenate([closing, closing[direction]])
        floor = float(env.target(np.zeros(())))
        busy = np.flatnonzero(cand_on | (shared > floor).any(axis=1))  # steps beyond the backup's alone
        guess = self._settling_steps(targets, int(busy[-1]) + 1 if len(busy) else 0, now_peak, floor)
        # up to the stop: once only the backup is flown and the worst case has come down to its
        # creep, the gate's promise is kept (what creeps on is the keep-out's, see the module doc)
        first = int(np.searchsorted(np.append(0.0, times + STEP_S) >= self.period + env.max_delay, True))
        # integrate as far as the worst case settles by the estimate, and the whole horizon only
        # when some column has not settled by then (each column's result is the same either way)
        for length in (guess, steps) if guess < steps else (steps,):
            closing_bound, displacement = worst_closing(closing_now, targets[:length], env)
            stopped = closing_bound[first:] <= floor + 1e-9
            done = stopped.any(axis=0)
            if length == steps or done.all():
                break
        settled = np.where(done, first + stopped.argmax(axis=0), steps)
        # the farthest so far: the displacement itself where the bound never goes below 0 (each
        # step then adds a non-negative length), a running maximum in the few other columns
        back = np.flatnonzero((closing_bound[: int(settled.max()) + 1] < 0.0).any(axis=0))
        if len(back):
            displacement[:, back] = np.maximum.accumulate(displacement[:, back], axis=0)
        fast = closing_bound > floor + 1e-9
        return _WorstCase(displacement, settled, column, steps, base_peak, cand_peak, fast)

    def _settling_steps(self, targets: np.ndarray, end: int, now_peak: float, floor: float) -> int:
        """A guess of the step by which every column has stopped (after the step ``end`` the targets
        are the backup's alone): the closing speed is at most the highest target or what braking
        leaves of the one now, and then falls at ``decel`` once braking is built up. Only the time
        depends on it, not the result: :meth:`_worst_case` integrates further when it falls short."""
        env = self.envelope
        peak = float(targets[:end].max()) if end else -math.inf
        if math.isinf(env.jerk):  # braking at decel from the start
            peak = max(peak, now_peak - env.decel * STEP_S * end)
        else:
            peak = max(peak, now_peak)
            end += math.ceil(env.decel / (env.jerk * STEP_S))
        if not math.isfinite(peak):  # an undefined target (a setpoint not yet in force): no guess
            return len(targets)
        return min(len(targets), end + math.ceil(max(peak - floor, 0.0) / (env.decel * STEP_S)) + 2)

    def _history_peak(self) -> float:
        """The highest target the setpoints sent may still set, m/s (from their speed: no component
        is larger): the horizon must cover braking from them, not only from the candidate."""
        speeds = [float(np.hypot(*v)) for v in self._sent.vectors]
        return float(self.envelope.target(np.array(max(speeds)))) if speeds else -math.inf

    def _steps(self, peak: float) -> int:
        """The integration steps of the horizon for a worst case whose highest closing speed is ``peak``."""
        env = self.envelope
        horizon = min(self.period + env.max_delay + max(peak, 0.0) / env.decel + STEP_S, MAX_HORIZON_S)
        return math.ceil(horizon / STEP_S)

    def _history_components(self, units_world: np.ndarray, times: np.ndarray) -> np.ndarray:
        """``(k, 72)``: the highest component of the setpoints sent before now that may still be
        flown at each future time (``-inf`` when none: only the candidate and the backup)."""
        env = self.envelope
        sent_times = np.asarray(self._sent.times) - self._time  # <= 0
        if len(sent_times) == 0:
            return np.zeros((len(times), N_DIRECTIONS))  # a fresh gate: the vehicle was held still
        comps = np.stack(self._sent.vectors) @ units_world.T
        # setpoint j is flown over [t_j + min_delay, t_{j+1} + max_delay]; the newest until the candidate
        ends = np.append(sent_times[1:], 0.0) + env.max_delay
        on = (times + STEP_S > (sent_times + env.min_delay)[:, None]) & (times <= ends[:, None])  # (j, k)
        out = np.where(on[:, :, None], comps[:, None, :], -np.inf).max(axis=0)
        # what came before the first one kept (the hold before the engagement's first setpoint, or
        # one dropped by advance) may be flown until max_delay after it: a zero at most there (a
        # dropped one's span has ended by then), so no step is left with nothing in force
        before = times <= sent_times[0] + env.max_delay
        out[before] = np.maximum(out[before], 0.0)
        return out

    def choose(
        self,
        asked: tuple[float, float],
        velocity: tuple[float, float] | None,
        points: np.ndarray,
        inflation: np.ndarray,
        movers: np.ndarray | None = None,
    ) -> tuple[tuple[float, float], str | None]:
        """The setpoint to send: ``asked`` when it passes; else the passing candidate closest to it
        (scaled down, or with its part towards the nearest return or mover removed, then scaled).

        When none passes but the last setpoint sent keeps a backup an earlier step verified, that
        backup, the stop, is sent again (``"gate_backup_kept"``): its worst case is a part of the one
        verified then, which the returns known then kept clear (the module doc's proof sketch). This
        is what keeps the promise while the memory's inflation grows (a return's drift bound grows
        with its age even while the same surface is seen again).

        Otherwise (the assumptions were left: a start closer than the creep allows, a return seen
        late; a mover seen late, or outside its model): of those that keep clear of the returns, the
        one that leaves a mover the most room (``"gate_mover_best_effort"``); and when none does,
        the one that leaves the most room (``"gate_best_effort"``). That is the stop or one as good
        (no command sent now lowers the worst case below the stop's); a retreat from the nearest
        return at up to ``retreat_speed`` is as good when it raises no bound that decides, and is then
        sent (the fastest of a few that the envelope has truly move away: none for PX4's, whose
        estimate error outweighs the retreat), as it is what can bring the vehicle back to where a
        stop is verified.

        The reason is None, ``"gate_slowed"``, ``"gate_backup"`` (the stop, verified now),
        ``"gate_backup_kept"``, ``"gate_mover_best_effort"`` or ``"gate_best_effort"``.

        :param movers: ``(k, 6)`` :func:`mover_rows`; None: none
        """
        setpoint, reason, _ = self._choose(asked, velocity, points, inflation, movers, None)
        return setpoint, reason

    def choose_beside(
        self,
        asked: tuple[float, float],
        velocity: tuple[float, float] | None,
        points: np.ndarray,
        inflation: np.ndarray,
        movers: np.ndarray,
        alternatives: np.ndarray,
    ) -> tuple[tuple[float, float], str | None, np.ndarray, np.ndarray]:
        """:meth:`choose`, and which of ``alternatives`` may stand in for the stop, judged with it on
        the same worst case (one integration for both: the shield's sidesteps, ``give_way``).

        :param alternatives: ``(a, 2)`` body setpoints (forward, left), m/s
        :return: :meth:`choose`'s setpoint and reason; then ``(a,)`` ``ok``: its backup keeps clear
            of the returns, or where the stop's does not (the best effort), leaves them as much
            room; and ``(a,)`` ``verified``: ok and clear of the movers too (the whole promise).
            The movers' room is searched for the ok ones only
        """
        beside = np.asarray(alternatives, dtype=np.float64).reshape(-1, 2)
        setpoint, reason, judged = self._choose(asked, velocity, points, inflation, movers, beside)
        assert judged is not None
        return setpoint, reason, *judged

    def _choose(
        self,
        asked: tuple[float, float],
        velocity: tuple[float, float] | None,
        points: np.ndarray,
        inflation: np.ndarray,
        movers: np.ndarray | None,
        beside: np.ndarray | None,
    ) -> tuple[tuple[float, float], str | None, tuple[np.ndarray, np.ndarray] | None]:
        """:meth:`choose`; with ``beside``, :meth:`choose_beside`'s judgement of them as well."""
        want = np.asarray(asked, dtype=np.float64)
        moving = np.zeros((0, 6)) if movers is None else np.asarray(movers, dtype=np.float64)
        pending = self._intervening or beside is not None  # the asked judged in the batch, not alone first
        if beside is None and (not self._intervening or len(points) + len(moving) == 0):  # as the last did
            least, alone = self._judge(want[None], velocity, points, inflation, moving)
            if least[0] >= 0.0:
                self._intervening = False
                return (*self._offer(want, self._stop_time(alone, 0, alone.steps), None), None)
        centres = np.concatenate([points, moving[:, :2]])
        gaps = np.hypot(centres[:, 0], centres[:, 1]) - np.concatenate([inflation, moving[:, 4]])
        nearest = centres[int(np.argmin(gaps))]
        towards = nearest / max(float(np.hypot(*nearest)), 1e-9)
        slide = want - max(float(want @ towards), 0.0) * towards
        candidates = np.concatenate([want[None], _SCALES[1:, None] * want, _SCALES[:-1, None] * slide])
        # one worst case for every candidate (the slide is the asked itself when it does not close
        # on the nearest return: then the scaled ones only), and for the stop and ``beside`` after them
        index = np.arange(len(candidates))
        if np.array_equal(slide, want):
            index[len(_SCALES) :] = np.arange(len(_SCALES) - 1)
        n = int(index.max()) + 1
        others = np.zeros((0, 2)) if beside is None else np.vstack([np.zeros((1, 2)), beside])
        worst = self._worst_case(np.concatenate([candidates[:n], others]), velocity)
        steps = self._steps(max(worst.base_peak, float(worst.cand_peak[:n].max())))  # the candidates' own
        rows, horizons = np.arange(n), np.full(n, steps)
        if pending:  # the asked not judged yet: on its own horizon, as if alone
            own = self._steps(max(worst.base_peak, float(worst.cand_peak[0])))
            rows, horizons = np.append(rows, 0), np.append(horizons, own)
        judged = np.concatenate([rows, n + np.arange(len(others))])
        cut = np.concatenate([horizons, np.full(len(others), worst.steps)])
        rooms = separation(points, inflation, worst.reach(cut[:, None], judged)) - self.clearance
        least = rooms[: len(rows)]
        clear = self._mover_room(worst, rows, horizons, moving) if len(moving) else np.full(len(rows), np.inf)
        beside_judged = None if beside is None else self._beside(worst, n, rooms[len(rows) :], moving)
        if pending and min(least[-1], clear[-1]) >= 0.0:
            self._intervening = False
            return (*self._offer(want, self._stop_time(worst, 0, int(horizons[-1])), None), beside_judged)
        self._intervening = True
        room, mover_room = least[index], clear[index]
        ok = (room >= 0.0) & (mover_room >= 0.0)
        until: float | None = -math.inf  # a best effort ends what was kept
        if ok.any():
            pick = int(np.argmin(np.where(ok, np.hypot(*(candidates - want).T), np.inf)))
            setpoint, until = candidates[pick], self._stop_time(worst, int(index[pick]), steps)
            reason = "gate_slowed" if np.any(setpoint) else "gate_backup"
        elif self._time < self._kept_until:
            setpoint, until, reason = candidates[len(_SCALES) - 1], None, "gate_backup_kept"  # the stop
        elif (room >= 0.0).any():
            setpoint = candidates[int(np.argmax(np.where(room >= 0.0, mover_room, -np.inf)))]
            reason = "gate_mover_best_effort"
        else:
            retreat = self._retreat(towards, velocity, points, inflation, moving)
            most = candidates[int(np.argmax(np.minimum(room, mover_room)))]
            setpoint = retreat if retreat is not None else most
            reason = "gate_best_effort"
        return (*self._offer(setpoint, until, reason), beside_judged)

    def _beside(
        self, worst: _WorstCase, n: int, rooms: np.ndarray, movers: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`choose_beside`'s ``ok`` and ``verified``, from the rooms from the returns of the stop
        and the alternatives after it (rows ``n``, ``n + 1``, ... of ``worst``)."""
        ok = rooms[1:] >= min(rooms[0], 0.0)
        verified = ok.copy()
        if ok.any() and len(movers):
            verified[ok] = self._mover_room(worst, n + 1 + np.flatnonzero(ok), worst.steps, movers) >= 0.0
        return ok, verified

    def _retreat(
        self,
        towards: np.ndarray,
        velocity: tuple[float, float] | None,
        points: np.ndarray,
        inflation: np.ndarray,
        movers: np.ndarray,
    ) -> np.ndarray | None:
        """The fastest retreat from ``towards`` (a unit vector, body) that the envelope has truly move
        away and that leaves as much room as the stop, judged with it in one worst case; None: none."""
        speeds = self.retreat_speed * _RETREATS[self._retreats]
        if len(speeds) == 0:
            return None
        candidates = np.concatenate([np.zeros((1, 2)), -speeds[:, None] * towards])
        least, _ = self._judge(candidates, velocity, points, inflation, movers)
        backing = np.flatnonzero(least[1:] >= least[0])
        return candidates[1 + backing[0]] if len(backing) else None

    def _offer(
        self, setpoint: np.ndarray, kept_until: float | None, reason: str | None
    ) -> tuple[tuple[float, float], str | None]:
        """Remember what is offered, and the ``_kept_until`` it sets when sent, for :meth:`record`."""
        body = (float(setpoint[0]), float(setpoint[1]))
        self._offered = (np.array(body), kept_until)
        return body, reason


def mover_rows(movers: Sequence[Mover]) -> np.ndarray:
    """``(k, 6)`` the movers as the gate takes them: position (forward, left), velocity (forward,
    left), radius and age, body axes at the scan's time, m, m/s and s."""
    rows = [(*m.position, *m.velocity, m.radius, m.age) for m in movers]
    return np.array(rows, dtype=np.float64).reshape(-1, 6)


def _where_seen(movers: np.ndarray) -> np.ndarray:
    """``(k, 2)`` where each mover was last seen: its centre carried back along its velocity by its age, m."""
    return movers[:, :2] - movers[:, 5:6] * movers[:, 2:4]
