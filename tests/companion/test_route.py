"""The route planner maps what the scans show and sends the policy around what blocks the goal."""

import math

import numpy as np
import pytest

from companion.guidance.route import RouteConfig, RoutePlanner

MAX_RANGE = 10.0


def segment_scan(x, y, heading, segments, n_bins=360):
    """A normalised scan at (x, y) facing ``heading`` (CCW from +x) of line segments ((x0, y0), (x1, y1))."""
    scan = np.ones(n_bins)
    for i in range(n_bins):
        a = heading + math.radians(i + 0.5)
        d = np.array([math.cos(a), math.sin(a)])
        for p, q in segments:
            p, q = np.asarray(p, float), np.asarray(q, float)
            e = q - p
            det = d[0] * -e[1] + d[1] * e[0]
            if abs(det) < 1e-12:
                continue
            rel = p - (x, y)
            t = (rel[0] * -e[1] + rel[1] * e[0]) / det
            u = (d[0] * rel[1] - d[1] * rel[0]) / det
            if 0.0 < t < MAX_RANGE and 0.0 <= u <= 1.0:
                scan[i] = min(scan[i], t / MAX_RANGE)
    return scan


#: a wall across the way from (0, 0) to the goal at (6, 0), open beyond y = 4 and below y = -6
WALL = [((3.0, -6.0), (3.0, 4.0))]


def planner(**changes):
    return RoutePlanner(RouteConfig(**changes), MAX_RANGE)


def test_nothing_seen_sends_the_policy_straight_at_the_goal():
    route = planner()
    sub = route.subgoal(0.0, 0.0, 0.0, 6.0, 0.0)
    assert (sub.forward, sub.left, sub.distance) == pytest.approx((6.0, 0.0, 6.0))


def test_a_goal_in_plain_sight_is_the_subgoal():
    route = planner()
    far_wall = [((9.0, -5.0), (9.0, 5.0))]
    route.observe(segment_scan(0.0, 0.0, 0.0, far_wall), 0.0, 0.0, 0.0)
    sub = route.subgoal(0.0, 0.0, 0.0, 6.0, 1.0)
    assert (sub.forward, sub.left) == pytest.approx((6.0, 1.0), abs=1e-6)


def test_a_wall_in_the_way_sends_the_policy_around_its_nearer_end():
    route = planner()
    route.observe(segment_scan(0.0, 0.0, 0.0, WALL), 0.0, 0.0, 0.0)
    sub = route.subgoal(0.0, 0.0, 0.0, 6.0, 0.0)
    bearing = math.degrees(math.atan2(sub.left, sub.forward))
    assert 30.0 < bearing < 80.0  # to the left, toward the end at y = 4, not into the wall
    # the distance feature is the route's length, around the end: longer than the straight 6 m
    assert sub.distance > 2 * math.hypot(3.0, 4.0) - 0.5
    assert math.hypot(sub.forward, sub.left) == pytest.approx(sub.distance)


def test_the_subgoal_turns_with_the_vehicle():
    """Facing +y, the same route reads as ahead-and-right in the body frame."""
    route = planner()
    route.observe(segment_scan(0.0, 0.0, math.pi / 2, WALL), 0.0, 0.0, math.pi / 2)
    sub = route.subgoal(0.0, 0.0, math.pi / 2, 6.0, 0.0)
    assert sub.forward > 0.0 and sub.left < 0.0


def test_a_route_is_followed_between_plans_and_replanned_when_the_goal_moves():
    route = planner(replan_every=10)
    route.observe(segment_scan(0.0, 0.0, 0.0, WALL), 0.0, 0.0, 0.0)
    route.subgoal(0.0, 0.0, 0.0, 6.0, 0.0)
    route.subgoal(0.5, 1.0, 0.0, 6.0, 0.0)
    assert route.plans == 1
    route.subgoal(0.5, 1.0, 0.0, -6.0, 0.0)
    assert route.plans == 2


def test_a_free_ray_clears_a_cell_once_seen_occupied():
    route = planner()
    post = [((2.0, -0.2), (2.0, 0.2))]
    route.observe(segment_scan(0.0, 0.0, 0.0, post), 0.0, 0.0, 0.0)
    assert route.occupied.sum() > 0
    for _ in range(12):  # the post is gone: every ray now passes where it stood
        route.observe(np.ones(360), 0.0, 0.0, 0.0)
    assert route.occupied.sum() == 0


def test_a_goal_walled_in_all_round_falls_back_to_the_goal_itself():
    route = planner()
    corners = [(5.0, -1.0), (7.0, -1.0), (7.0, 1.0), (5.0, 1.0)]
    box = list(zip(corners, corners[1:] + corners[:1], strict=True))
    for x, y in ((0.0, 0.0), (8.5, 0.0), (6.0, 3.5), (6.0, -3.5)):  # every wall seen face on
        route.observe(segment_scan(x, y, 0.0, box), x, y, 0.0)
    sub = route.subgoal(0.0, 0.0, 0.0, 6.0, 0.0)
    assert (sub.forward, sub.left) == pytest.approx((6.0, 0.0), abs=1e-6)


@pytest.mark.parametrize(
    "scan, pose",
    [
        (np.full(360, np.nan), (0.0, 0.0, 0.0)),
        (np.ones(360), (math.nan, 0.0, 0.0)),
        (np.ones(360), (0.0, 0.0, math.inf)),
    ],
)
def test_a_false_picture_is_refused(scan, pose):
    with pytest.raises(ValueError, match="finite"):
        planner().observe(scan, *pose)


def test_preferred_clearance_below_the_blocked_one_is_refused():
    with pytest.raises(ValueError, match="preferred_clearance"):
        RouteConfig(blocked_clearance=0.5, preferred_clearance=0.3)


def test_reset_forgets_the_map():
    route = planner()
    route.observe(segment_scan(0.0, 0.0, 0.0, WALL), 0.0, 0.0, 0.0)
    route.reset()
    assert route.occupied.sum() == 0
    sub = route.subgoal(0.0, 0.0, 0.0, 6.0, 0.0)
    assert (sub.forward, sub.left) == pytest.approx((6.0, 0.0))


def test_a_gap_the_vehicle_barely_fits_is_passed_up_for_a_way_round_a_little_longer():
    """A 0.9 m gap straight ahead (it keeps ``blocked_clearance``, just) and the wall's end 2 m to the
    side: the default route goes round the end, 2.4 m longer; at proximity_cost 2 (the default
    before) it threads the gap."""
    walls = [((3.0, -6.0), (3.0, -0.45)), ((3.0, 0.45), (3.0, 2.0))]
    for route, through_the_gap in ((planner(), False), (planner(proximity_cost=2.0), True)):
        route.observe(segment_scan(0.0, 0.0, 0.0, walls), 0.0, 0.0, 0.0)
        sub = route.subgoal(0.0, 0.0, 0.0, 6.0, 0.0)
        bearing = math.degrees(math.atan2(sub.left, sub.forward))
        assert (abs(bearing) < 1.0) == through_the_gap, bearing
        assert (sub.distance < 6.01) == through_the_gap, sub.distance


def test_an_unseen_cost_takes_the_door_seen_over_a_shorter_way_through_what_no_scan_reached():
    """A wall across the way with a door 2.2-3.8 m to the left; a short wall near the vehicle hides
    the wall's stretch to the right of the line, so no scan shows it. Planning through the unknown
    as if free (the default), the route heads on past the short wall's end, for the hidden
    stretch, 1.2 m shorter than through the door; with the unknown costing twice the seen, it
    takes the door."""
    walls = [((5.0, -8.0), (5.0, 2.2)), ((5.0, 3.8), (5.0, 8.0)), ((1.0, -1.0), (1.0, -0.2))]
    bearings = {}
    for unseen_cost in (1.0, 2.0):
        route = planner(unseen_cost=unseen_cost)
        route.observe(segment_scan(0.0, 0.0, 0.0, walls), 0.0, 0.0, 0.0)
        sub = route.subgoal(0.0, 0.0, 0.0, 10.0, 0.0)
        bearings[unseen_cost] = math.degrees(math.atan2(sub.left, sub.forward))
    assert bearings[1.0] < 10.0, bearings
    assert 20.0 < bearings[2.0] < 45.0, bearings  # the door's middle lies 31° to the left


def _side(sub):
    """+1 when the subgoal lies to the left (round the wall's upper end), -1 to the right."""
    return 1 if math.atan2(sub.left, sub.forward) > 0.0 else -1


def test_a_replan_keeps_the_way_flown_unless_another_is_cheaper_by_the_margin():
    """A wall across the way, its upper end 0.1 m nearer the line to the goal. From y = 0.5 the
    route goes round the upper end; from y = -0.5 the lower way is 4 % shorter. Always the cheapest
    (margin 0), the route swaps ends; with a margin it keeps the end it took. Once a wall shows the
    upper way closed, it goes round the lower end, margin or not."""
    wall = [((3.0, -4.1), (3.0, 4.0))]
    closed = [*wall, ((3.0, 4.0), (3.0, 9.5)), ((-6.0, 9.5), (9.0, 9.5))]
    for margin, sides in ((0.0, [1, -1, -1]), (0.3, [1, 1, -1])):
        route = planner(switch_margin=margin, replan_every=1)
        seen = []
        for y, walls in ((0.5, wall), (-0.5, wall), (-0.5, closed)):
            route.observe(segment_scan(0.0, y, 0.0, walls), 0.0, y, 0.0)
            seen.append(_side(route.subgoal(0.0, y, 0.0, 6.0, 0.0)))
        assert seen == sides, (margin, seen)


def test_a_new_goal_is_planned_afresh_whatever_the_margin():
    """The margin favours the way flown to the same goal only: a route to a new goal is the cheapest."""
    wall = [((3.0, -4.4), (3.0, 4.0))]
    route = planner(switch_margin=10.0, replan_every=1)
    route.observe(segment_scan(0.0, 0.5, 0.0, wall), 0.0, 0.5, 0.0)
    assert _side(route.subgoal(0.0, 0.5, 0.0, 6.0, 0.0)) == 1
    assert _side(route.subgoal(0.0, 0.5, 0.0, 6.0, -2.0)) == -1


def test_a_moving_return_is_not_stamped_and_what_it_hides_is_kept():
    """A wall 6 m ahead is on the map; then a walker 2 m ahead hides part of it for many scans. Its
    bins, marked moving, clear the ray up to it but stamp nothing, and the wall behind it keeps its
    evidence (read as nothing returned, the ray would have been cleared through the wall)."""
    route = planner()
    far_wall = [((6.0, -3.0), (6.0, 3.0))]
    route.observe(segment_scan(0.0, 0.0, 0.0, far_wall), 0.0, 0.0, 0.0)
    wall_cell = route._cells(np.array([6.05]), np.array([0.0]))[:2]
    walker_cell = route._cells(np.array([2.05]), np.array([0.0]))[:2]
    walker = [((2.0, -0.3), (2.0, 0.3))]
    hidden = segment_scan(0.0, 0.0, 0.0, far_wall + walker)
    moving = np.abs(hidden * MAX_RANGE - 2.0) < 0.1
    assert moving.sum() >= 10
    for _ in range(20):
        route.observe(hidden, 0.0, 0.0, 0.0, moving)
    assert route.occupied[wall_cell].all() and not route.occupied[walker_cell].any()
    masked = hidden.copy()
    masked[moving] = 1.0
    for _ in range(20):
        route.observe(masked, 0.0, 0.0, 0.0)
    assert not route.occupied[wall_cell].any()  # what the mask alone would have done
