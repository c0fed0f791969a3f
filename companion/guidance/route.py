"""A route to the goal on a map of what the scans have shown: the goal features then point along it.

A reactive policy sees one scan slice and a goal bearing. Where the goal lies behind a wall (the
next room of an office, the far end of an aisle) the bearing points into the wall, and the policy
slides along it until the time runs out. :class:`RoutePlanner` keeps an occupancy grid of every
scan (returns mark cells occupied, the free ray before them clears cells), plans the cheapest
8-connected route from the goal to the vehicle over it (cells near what was seen cost more, cells
too near cost far more, unseen cells are free) and hands the policy a subgoal instead of the goal:
the farthest point of the route, at most ``lookahead`` along it, that the vehicle can see in a
straight line. Its distance feature is the route's length, so the policy does not slow for a
subgoal that is not the end. With the goal in plain sight the subgoal is the goal itself, and
nothing changes.

Coordinates are planar metres in a right-handed frame with the heading counter-clockwise from +x:
the environment's world frame (ENU) as is; the companion turns local NED into it with
:func:`enu_pose`, so both build the same grid from the same flight. The map is fixed in that
frame, so it trusts the pose it is given: the environment's true pose, or the autopilot's estimate
in flight. Pure numpy and scipy (the
distance transform and Dijkstra): the companion runs it in flight and the environment in
training and evaluation, the same code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from companion.perception.observation import goal_in_body

#: A cell nearer than ``blocked_clearance`` costs this many times a free one (the route may still
#: leave such a cell, or squeeze through when nothing else joins vehicle and goal).
BLOCKED_COST = 200.0
_SQRT2 = math.sqrt(2.0)
# the 4 edges each cell owns (the other 4 are its neighbours'): right, up, up-right, down-right
_EDGES = ((1, 0, 1.0), (0, 1, 1.0), (1, 1, _SQRT2), (1, -1, _SQRT2))


@dataclass(frozen=True)
class RouteConfig:
    """Tuning of :class:`RoutePlanner` (strict-loadable: every bound is checked).

    :param resolution: map cell size, metres
    :param extent: side of the square map, metres, centred where the first scan was taken
    :param blocked_clearance: cells nearer a seen obstacle than this are (nearly) blocked, metres:
        the vehicle's radius and a margin
    :param preferred_clearance: cells nearer than this cost more, in proportion, metres
    :param proximity_cost: extra cost of a cell next to a seen obstacle, in free cells (falling
        linearly to 0 at ``preferred_clearance``): how far the route goes round for a wider way.
        8 (2 before): the shipped policy reached more validation worlds behind the shield with 8,
        though not more test worlds (docs/goal-policy.md)
    :param unseen_cost: cost factor of a cell no scan has reached, against 1 for one seen free: 1
        (the default) plans through the unknown as if it were free; above 1 the route keeps to what
        the scans have shown where that is not much longer, and enters the unknown nearer the goal
        (2 flew worse on the validation worlds: docs/goal-policy.md)
    :param lookahead: the subgoal lies at most this far along the route, metres
    :param replan_every: scans between two plans; in between the subgoal moves along the last route
    :param switch_margin: a replan for the same goal plans with the cells within
        ``preferred_clearance`` of the route flown (ahead of the vehicle) costing ``1 +
        switch_margin`` times less: it keeps to that way unless another costs less by about this
        fraction. Two ways of nearly the same cost (through a pillar grid, or out through a wall not
        yet seen) otherwise swap as single cells of the map flicker with the scan's noise, and the
        subgoal and the distance feature swap with them (7 m in one replan in pillars-900057). 0
        (the default, what the shipped policy was trained and chosen with): always the cheapest; 1
        failed 4 of the 900 validation episodes behind the shield against 5, one a collision the
        shield let through (docs/goal-policy.md, "The route held to the way flown")
    :param hit: evidence a return adds to its cell
    :param miss: evidence a ray passing through a cell takes away
    :param evidence_max: evidence saturates here (a cell seen occupied this often needs as many
        misses to clear)
    """

    resolution: float = field(default=0.2, metadata={"min": 0.05, "max": 1.0})
    extent: float = field(default=100.0, metadata={"min": 10.0, "max": 1000.0})
    blocked_clearance: float = field(default=0.4, metadata={"min": 0.05, "max": 5.0})
    preferred_clearance: float = field(default=1.0, metadata={"min": 0.05, "max": 10.0})
    proximity_cost: float = field(default=8.0, metadata={"min": 0.0, "max": 100.0})
    unseen_cost: float = field(default=1.0, metadata={"min": 1.0, "max": 100.0})
    lookahead: float = field(default=5.0, metadata={"min": 0.5, "max": 50.0})
    replan_every: int = field(default=5, metadata={"min": 1, "max": 100})
    switch_margin: float = field(default=0.0, metadata={"min": 0.0, "max": 10.0})
    hit: float = field(default=3.0, metadata={"min": 0.1, "max": 100.0})
    miss: float = field(default=1.0, metadata={"min": 0.0, "max": 100.0})
    evidence_max: float = field(default=9.0, metadata={"min": 0.1, "max": 1000.0})

    def __post_init__(self) -> None:
        if self.preferred_clearance < self.blocked_clearance:
            raise ValueError(
                f"preferred_clearance {self.preferred_clearance} must be at least "
                f"blocked_clearance {self.blocked_clearance}"
            )


@dataclass(frozen=True)
class Subgoal:
    """Where the policy is sent: ``(forward, left)`` metres in the body frame (FLU), stretched so
    that their length is the route's to the goal (the straight distance when no route was needed
    or found)."""

    forward: float
    left: float

    @property
    def distance(self) -> float:
        """The route's length to the goal, metres (what the distance feature reads)."""
        return math.hypot(self.forward, self.left)


class RoutePlanner:
    """Occupancy grid of the scans, and the subgoal along the cheapest route to the goal.

    :param config: tuning
    :param max_range: the scan's range, metres (a bin of 1.0 saw nothing within it)
    """

    def __init__(self, config: RouteConfig, max_range: float) -> None:
        self.config = config
        self.max_range = float(max_range)
        n = math.ceil(config.extent / config.resolution)
        self._evidence = np.zeros((n, n), np.float32)
        self._seen = np.zeros((n, n), bool)  # cells a ray has reached (with an unseen_cost)
        self._origin: np.ndarray | None = None  # world (x, y) of cell (0, 0)'s corner
        self._route: np.ndarray | None = None  # (N, 2) world points, vehicle end first
        self._route_goal: tuple[float, float] | None = None
        self._since_plan = 0
        self._window: tuple[int, int, np.ndarray] = (0, 0, np.zeros((0, 0)))  # the last plan's clearance
        self.plans = 0  # plans made so far (benches and tests read it)

    def reset(self) -> None:
        """Forget the map and the route (a new episode, a new flight)."""
        self._evidence[:] = 0.0
        self._seen[:] = False
        self._origin = None
        self._route = None
        self._route_goal = None
        self._since_plan = 0

    @property
    def occupied(self) -> np.ndarray:
        """(n, n) bool: cells the scans say are occupied (index ``[i, j]`` = x, y)."""
        return self._evidence > 0.0

    # ------------------------------------------------------------------ the map
    def observe(
        self, scan: np.ndarray, x: float, y: float, heading: float, moving: np.ndarray | None = None
    ) -> None:
        """Add one scan taken at ``(x, y)`` facing ``heading`` (rad, CCW from +x).

        :param scan: the normalised scan (bin i covers [i°, i+1°) CCW from the nose; 1.0 = nothing)
        :param moving: ``(n,)`` bool, bins whose return is a moving object
            (:attr:`companion.perception.tracking.TrackerOutput.moving_bins`): the ray up to it is
            free, the return is not stamped, and what lies behind it stays as it was (it was not seen)
        :raises ValueError: a non-finite pose or scan (the map must not take a false picture)
        """
        scan = np.asarray(scan, dtype=np.float64).reshape(-1)
        pose_ok = all(math.isfinite(v) for v in (x, y, heading))
        if not pose_ok or not np.isfinite(scan).all():
            raise ValueError("the route map takes finite scans and poses only")
        cfg = self.config
        if self._origin is None:
            self._origin = np.array([x, y]) - cfg.extent / 2.0
        angles = heading + (np.arange(scan.size) + 0.5) * (2.0 * math.pi / scan.size)
        ranges = np.clip(scan, 0.0, 1.0) * self.max_range
        hit = scan < 1.0
        # free space: samples every half cell, up to a cell short of each return
        steps = np.arange(0.5, self.max_range / (0.5 * cfg.resolution)) * 0.5 * cfg.resolution
        free_to = np.where(hit, ranges - cfg.resolution, self.max_range)
        rr = steps[None, :]
        keep = rr < free_to[:, None]
        fx = (x + rr * np.cos(angles)[:, None])[keep]
        fy = (y + rr * np.sin(angles)[:, None])[keep]
        fi, fj, inside = self._cells(fx, fy)
        fi, fj = fi[inside], fj[inside]
        self._evidence[fi, fj] -= cfg.miss
        if moving is not None:
            hit = hit & ~np.asarray(moving, dtype=bool).reshape(-1)
        hx = x + ranges[hit] * np.cos(angles[hit])
        hy = y + ranges[hit] * np.sin(angles[hit])
        hi, hj, inside = self._cells(hx, hy)
        hi, hj = hi[inside], hj[inside]
        self._evidence[hi, hj] += cfg.hit
        # only the cells this scan touched can have left the bounds
        touched = (np.concatenate([fi, hi]), np.concatenate([fj, hj]))
        self._evidence[touched] = np.clip(self._evidence[touched], -cfg.evidence_max, cfg.evidence_max)
        if cfg.unseen_cost != 1.0:  # read only then: the default pays nothing for it
            self._seen[touched] = True

    def _cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        assert self._origin is not None
        n = self._evidence.shape[0]
        i = np.floor((x - self._origin[0]) / self.config.resolution).astype(np.int64)
        j = np.floor((y - self._origin[1]) / self.config.resolution).astype(np.int64)
        inside = (i >= 0) & (j >= 0) & (i < n) & (j < n)
        return i, j, inside

    # ------------------------------------------------------------------ the route
    def subgoal(self, x: float, y: float, heading: float, goal_x: float, goal_y: float) -> Subgoal:
        """Where to send the policy from ``(x, y)``, facing ``heading``, for the goal ``(goal_x, goal_y)``.

        Replans every ``replan_every`` calls and whenever the goal moves; in between the subgoal
        moves along the last route. The goal itself when nothing has been seen yet, when the goal or
        the vehicle lies off the map, or when no route joins them.
        """
        cfg = self.config
        goal = (float(goal_x), float(goal_y))
        position = np.array([x, y], dtype=np.float64)
        if self._route is None or goal != self._route_goal or self._since_plan >= cfg.replan_every:
            flown = None
            if self._route is not None and goal == self._route_goal and cfg.switch_margin > 0.0:
                flown = np.concatenate([position[None, :], self._ahead(position)])
            self._route = self._plan(position, np.array(goal), flown)
            self._route_goal = goal
            self._since_plan = 0
            self.plans += 1
        self._since_plan += 1
        if self._route is None:
            return _in_body(goal[0] - x, goal[1] - y, heading, math.hypot(goal[0] - x, goal[1] - y))
        target, length = self._along_route(position)
        return _in_body(target[0] - x, target[1] - y, heading, length)

    def _plan(
        self, start: np.ndarray, goal: np.ndarray, flown: np.ndarray | None = None
    ) -> np.ndarray | None:
        """The cheapest route ``(N, 2)``, world points from ``start`` to ``goal``, or None; cells
        within ``preferred_clearance`` of the route ``flown`` (world points) cost ``1 +
        switch_margin`` times less."""
        if self._origin is None:
            return None
        cfg, res = self.config, self.config.resolution
        occupied = self.occupied
        (si, gi), (sj, gj), inside = self._cells(np.array([start[0], goal[0]]), np.array([start[1], goal[1]]))
        if not inside.all() or not occupied.any():
            return None
        # outside the box around every occupied cell, the vehicle and the goal (and every seen one,
        # when the unseen cost more), all costs the same: the cheapest route never leaves it by
        # more than the clearance it prefers
        boxed = occupied | self._seen if cfg.unseen_cost != 1.0 else occupied
        rows, cols = np.flatnonzero(boxed.any(axis=1)), np.flatnonzero(boxed.any(axis=0))
        n = occupied.shape[0]
        margin = math.ceil(cfg.preferred_clearance / res) + 2
        i0, i1 = max(min(rows[0], si, gi) - margin, 0), min(max(rows[-1], si, gi) + margin + 1, n)
        j0, j1 = max(min(cols[0], sj, gj) - margin, 0), min(max(cols[-1], sj, gj) + margin + 1, n)
        window = occupied[i0:i1, j0:j1]
        clearance = ndimage.distance_transform_edt(~window) * res
        nearness = np.clip((cfg.preferred_clearance - clearance) / cfg.preferred_clearance, 0.0, 1.0)
        cost = 1.0 + cfg.proximity_cost * nearness
        if cfg.unseen_cost != 1.0:
            cost[~self._seen[i0:i1, j0:j1]] *= cfg.unseen_cost
        cost[clearance < cfg.blocked_clearance] = BLOCKED_COST
        if flown is not None:
            cost[self._near(flown, (i0, j0), window.shape)] /= 1.0 + cfg.switch_margin
        cost[window] = np.inf
        a, b = (si - i0, sj - j0), (gi - i0, gj - j0)
        cost[a] = min(cost[a], BLOCKED_COST)  # the vehicle and the goal may sit in a cell seen occupied
        cost[b] = min(cost[b], BLOCKED_COST)
        self._window = (i0, j0, clearance)
        cells = _cheapest_cells(cost, a, b)
        if cells is None:
            return None
        points = (cells + np.array([i0, j0]) + 0.5) * res + self._origin
        points[0], points[-1] = start, goal
        return self._pull_taut(points)

    def _near(self, route: np.ndarray, corner: tuple[int, int], shape: tuple[int, ...]) -> np.ndarray:
        """Which cells of the window at ``corner`` (cells) of ``shape`` lie within
        ``preferred_clearance`` of ``route`` (world points), ``shape`` bool."""
        res = self.config.resolution
        legs = np.diff(route, axis=0)
        counts = np.ceil(np.hypot(*legs.T) / (0.5 * res)).astype(np.int64) + 1
        leg = np.repeat(np.arange(len(legs)), counts)
        t = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        points = route[leg] + (t / np.maximum(counts[leg] - 1, 1))[:, None] * legs[leg]
        i, j, _ = self._cells(points[:, 0], points[:, 1])
        i, j = i - corner[0], j - corner[1]
        on = (i >= 0) & (j >= 0) & (i < shape[0]) & (j < shape[1])
        along = np.ones(shape, bool)
        along[i[on], j[on]] = False
        if along.all():  # the route lies outside the window
            return np.zeros(shape, bool)
        return ndimage.distance_transform_edt(along) * res <= self.config.preferred_clearance

    def _pull_taut(self, points: np.ndarray) -> np.ndarray:
        """Drop the corners a straight leg can skip while keeping ``blocked_clearance`` (the cell
        path's staircase would read longer than the route is)."""
        keep, anchor = [0], 0
        while anchor < len(points) - 1:
            nxt = anchor + 1
            while nxt + 1 < len(points) and self._visible(points[anchor], points[nxt + 1]):
                nxt += 1
            keep.append(nxt)
            anchor = nxt
        return points[keep]

    def _ahead(self, position: np.ndarray) -> np.ndarray:
        """The current route from the point on it nearest ``position`` to its end, ``(N, 2)``."""
        route = self._route
        assert route is not None
        a, b = route[:-1], route[1:]
        seg = b - a
        along = np.einsum("ij,ij->i", position - a, seg) / np.maximum(np.einsum("ij,ij->i", seg, seg), 1e-12)
        foot = a + np.clip(along, 0.0, 1.0)[:, None] * seg
        k = int(np.argmin(np.hypot(*(foot - position).T)))
        return np.concatenate([foot[k : k + 1], route[k + 1 :]])

    def _along_route(self, position: np.ndarray) -> tuple[np.ndarray, float]:
        """The subgoal on the current route, seen from ``position``, and the route's length from there.

        The vehicle is placed on the route where it is nearest to it; the candidates are the corners
        ahead within ``lookahead`` and the point ``lookahead`` along, the farthest one in sight wins.
        """
        ahead = self._ahead(position)
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ahead, axis=0).T))])
        arc += float(np.hypot(*(ahead[0] - position)))
        lookahead = self.config.lookahead
        inside = int(np.searchsorted(arc, lookahead, side="right"))
        candidates = list(ahead[: max(inside, 1)])  # the foot of the route at least
        if 0 < inside < len(ahead):  # the point lookahead along, on the leg that crosses it
            frac = (lookahead - arc[inside - 1]) / max(arc[inside] - arc[inside - 1], 1e-12)
            candidates.append(ahead[inside - 1] + frac * (ahead[inside] - ahead[inside - 1]))
        for target in candidates[::-1]:
            if self._visible(position, target):
                return target, float(arc[-1])
        return ahead[min(1, len(ahead) - 1)], float(arc[-1])

    def _visible(self, a: np.ndarray, b: np.ndarray) -> bool:
        """True if the segment a-b keeps ``blocked_clearance`` from what was seen (the part within
        that distance of ``a`` excepted: the vehicle may already be that near a wall)."""
        cfg = self.config
        i0, j0, clearance = self._window
        length = float(np.hypot(*(b - a)))
        t = np.arange(0.0, length + 1e-9, 0.5 * cfg.resolution)
        t = t[t >= cfg.blocked_clearance]
        if t.size == 0:
            return True
        points = a + (b - a) * (t / max(length, 1e-9))[:, None]
        i, j, inside = self._cells(points[:, 0], points[:, 1])
        i, j = i - i0, j - j0
        h, w = clearance.shape
        on = inside & (i >= 0) & (j >= 0) & (i < h) & (j < w)
        return bool((clearance[i[on], j[on]] >= cfg.blocked_clearance).all())


def enu_pose(north: float, east: float, yaw: float) -> tuple[float, float, float]:
    """A local NED position and heading (clockwise from north, rad) as the planner's ENU ``(x, y,
    heading)``: x east, y north, heading counter-clockwise from east."""
    return east, north, math.pi / 2.0 - yaw


def _in_body(dx: float, dy: float, heading: float, length: float) -> Subgoal:
    """The offset (dx, dy) turned into the body frame and stretched to ``length`` metres (never
    shorter than the offset itself)."""
    forward, left = goal_in_body(dx, dy, heading)
    norm = math.hypot(forward, left)
    if norm < 1e-9:
        return Subgoal(0.0, 0.0)
    scale = max(length, norm) / norm
    return Subgoal(float(forward * scale), float(left * scale))


def _cheapest_cells(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> np.ndarray | None:
    """The cheapest 8-connected cell path ``(N, 2)`` from ``start`` to ``goal`` over per-cell cost
    factors (``inf``: impassable; a step costs its length times the mean of its two cells' factors;
    no diagonal past an impassable corner), or None when none joins them. Dijkstra from the goal."""
    h, w = cost.shape
    index = np.arange(h * w).reshape(h, w)
    finite = np.isfinite(cost)
    rows, cols, weights = [], [], []
    for di, dj, length in _EDGES:
        # cells (i, j) and (i + di, j + dj), both inside
        a = (slice(0, h - di), slice(max(-dj, 0), w - max(dj, 0)))
        b = (slice(di, h), slice(max(dj, 0), w + min(dj, 0)))
        ok = finite[a] & finite[b]
        if di and dj:  # the two cells the diagonal passes between
            ok &= finite[(slice(di, h), a[1])] & finite[(a[0], b[1])]
        rows.append(index[a][ok])
        cols.append(index[b][ok])
        weights.append(length * 0.5 * (cost[a][ok] + cost[b][ok]))
    n = h * w
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    source, target = index[goal], index[start]
    _, predecessors = dijkstra(graph.tocsr(), directed=False, indices=source, return_predecessors=True)
    if target != source and predecessors[target] < 0:
        return None
    path = [target]
    while path[-1] != source:
        path.append(int(predecessors[path[-1]]))
    return np.stack(np.divmod(np.array(path), w), axis=1)
