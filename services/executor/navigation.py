"""The base's path planner: OMPL in SE(2) around walls, furniture and people, as the sim drives. Pure logic.

How the sim drives a route, and what safety checks of it, is services/footprint.py's model: the
legs (route_legs), the floor they sweep (route_sweeps) and the clearance rule (clearance_problem).
The planner's motion checks test the same shapes, grown by its clearance; every path is verified
before it is returned with exactly safety's route check (SafetyPolicy.check_route) and, on top,
the planner's own clearance from walls, furniture, people and keep-out zones.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Iterator, Sequence
from functools import cached_property
from typing import NamedTuple

import shapely
from ompl import base as ob
from ompl import geometric as og
from shapely.geometry import LineString, Point, Polygon
from shapely.geometry.base import BaseGeometry

from schemas.common import Pose2D
from schemas.world import KeepOut
from services.executor.errors import PlanningFailed
from services.executor.omplsetup import Guard, solving
from services.footprint import (
    MAX_REVERSE,
    MIN_LEG,
    MIN_TURN,
    TRACKING_TOLERANCE,
    Sweep,
    clearance_problem,
    drive_sweep,
    footprint,
    leg_heading,
    route_legs,
    route_sweeps,
    turn_angle,
    turn_footprints,
)
from services.worldmodel import PRE_GOAL_DISTANCE, PRE_GOAL_MIN_LEG, WorldModel, drive_route

# A person is a disc of this radius (safety's default person_radius), and the base keeps this much
# further from it: safety pauses the robot inside 0.2 m of a person's body (stop_distance), so a
# route nearer would stall; a goal beside a person (the resolver stands 0.8 m from their centre to
# hand something over, the base's front 0.3 m from their body) stays just outside.
PERSON_RADIUS = 0.2
PERSON_COMFORT = 0.2
# RRTConnect's first path takes whichever way round it happens on: the planner asks it for this many
# (seeds seed, seed + 1, ...) and keeps the quickest to drive, shortening each this many rounds.
CANDIDATES = 4
SHORTCUT_ROUNDS = 3
# Tries that find no path (in time_limit each) before planning gives up.
MISSES = 2
# The sim picks driving or backing a leg by the heading and position it actually has, a few degrees
# and centimetres off the plan: a choice this close to a quarter turn or to MAX_REVERSE could go
# either way, so the planner checks both ways or avoids it.
HEADING_MARGIN = 0.15
LENGTH_MARGIN = 0.05
# A plan that fails names the people within this of its start or goal.
PEOPLE_NEARBY = 2.0
# Leaving a spot too tight to turn in, the base tries driving straight out in steps this long, up to
# MAX_REVERSE backwards or this far forwards.
EXIT_STEP = 0.05
MAX_EXIT_FORWARD = 1.0
# Well short of MAX_REVERSE, so the sim backs a leg out this long rather than turning round.
MAX_EXIT_BACK = MAX_REVERSE - LENGTH_MARGIN
# When no straight leg gets there (a base left by teleop beside a wall, nearly along it, can turn
# only a little before a corner comes closer), the way out may be up to EXIT_LEGS legs, each turning
# first by a multiple of EXIT_TURN as far as it keeps clear: a little, a leg away, a little more. The
# ends of each round of legs farthest from everything (EXIT_BEAM of them) are where the next starts.
EXIT_TURN = math.radians(2.0)
# A way out that must turn first (from closer than TRACKING_TOLERANCE: BasePlanner._way_out) may turn
# by these first (radians), then by multiples of EXIT_TURN: a base nearly along a wall can turn only a
# little away from it. Each well over MIN_TURN, so safety draws the turn from the pose it reads.
FIRST_TURNS = (0.005, 0.01, 0.02)
# Turned a little from nearly along a wall, the base gets away from it slowly: such a first leg may go
# this far ahead (metres) to where the margin is kept again.
MAX_TURNED_EXIT_FORWARD = 2.0
EXIT_LEGS = 4
EXIT_BEAM = 8
# When the straight approach is blocked (a room's centre facing furniture) and the base can turn at
# the goal, the path may end this far from the goal instead (within PRE_GOAL_MIN_LEG, so drive_route
# adds no pre-goal point), at one of this many points round it.
NEAR_GOAL_DISTANCE = 0.45
NEAR_GOAL_DIRECTIONS = 16
# Buffers are polygons drawn inside the true rounded outline; this much more keeps a point that is
# outside one truly clear.
ROUND_OFF = 0.005
# Distances equal up to this count as equal (a leg straight away from furniture keeps its distance).
EPSILON = 1e-9
# A leg whose end lies more than this (metres) to the side of the line along the heading held
# driving it is not driven along its own direction (see _Floorplan.drive_shape).
ALONG = 1e-9

State = tuple[float, float, float]

log = logging.getLogger(__name__)


def _at(x: float, y: float) -> str:
    return f"({x:.2f}, {y:.2f})"


def _cm(metres: float) -> str:
    return f"{max(metres, 0.0) * 100:.0f} cm"


def _why(zone: KeepOut) -> str:
    return f" ({zone.reason})" if zone.reason else ""


class _Blocker(NamedTuple):
    """Something the footprint must keep clear of, named for a message ("the kitchen counter"):
    a (name, outline) pair, as footprint.clearance_problem takes them."""

    name: str
    shape: BaseGeometry


class _Exit(NamedTuple):
    """A way out of a tight spot so far: its points, where it ends facing which way (the start when
    it has none) and about how long driving it takes."""

    points: tuple[tuple[float, float], ...]
    end: State
    time: float


class _Floorplan:
    """What the base must keep clear of, prepared for fast tests: walls, furniture and people (by
    the footprint), keep-out zones grown by the base's radius plus `margin` (by its centre), the
    floor (by its centre and its legs). The margin is never below TRACKING_TOLERANCE, what safety
    keeps from walls and furniture: a planner keeping less would find routes safety refuses."""

    def __init__(self, world: WorldModel, margin: float, people: Sequence[tuple[float, float]] = ()) -> None:
        self.world = world
        self.margin = max(margin, TRACKING_TOLERANCE)
        size = world.world.robot.base_size
        self.length, self.width = size.x, size.y
        self.people = [(float(x), float(y)) for x, y in people]
        person = PERSON_RADIUS + PERSON_COMFORT
        # What safety keeps the route's sweeps from (SafetyPolicy.obstacles): walls and furniture.
        self.walls_and_furniture = [_Blocker(f"the {o.name}", o.shape) for o in world.obstacles]
        self.blockers = self.walls_and_furniture + [
            _Blocker(f"a person at {_at(x, y)}", Point(x, y).buffer(person)) for x, y in self.people
        ]
        self.blocked = shapely.union_all([b.shape for b in self.blockers]) if self.blockers else Polygon()
        # Turning in place, the footprint grown by the margin stays within this of its centre.
        self.turn_radius = math.hypot(self.length / 2 + self.margin, self.width / 2 + self.margin)
        cramped = self.blocked.buffer(self.turn_radius + ROUND_OFF) if self.blockers else Polygon()
        self.zone_reach = world.base_radius + self.margin
        self.zones = [(zone, world.keep_out_shapes[zone.id]) for zone in world.world.keep_out]
        # Safety's zones: each grown by the base's radius, as SafetyPolicy grows them.
        self.safety_zones = [(zone, shape.buffer(world.base_radius)) for zone, shape in self.zones]
        self.zones_grown = shapely.union_all([shape.buffer(self.zone_reach) for _, shape in self.zones])
        self.floor = shapely.union_all(list(world.room_shapes.values()))
        # Where the centre may be and turn to any heading: one shape, so one test per point.
        self.turning_room = self.floor.difference(self.zones_grown).difference(cramped)
        for geometry in (self.blocked, self.zones_grown, self.floor, self.turning_room):
            shapely.prepare(geometry)

    # Points, footprints and legs

    def roomy(self, x: float, y: float) -> bool:
        """The base's centre may be at (x, y) and turn there to any heading keeping the margin."""
        return bool(shapely.intersects_xy(self.turning_room, x, y))

    def fits(self, x: float, y: float, yaw: float, margin: float | None = None) -> bool:
        margin = self.margin if margin is None else margin
        return not self.blocked.intersects(footprint(x, y, yaw, self.length, self.width, margin))

    def turn_clear(self, x: float, y: float, yaw_from: float, yaw_to: float) -> bool:
        """Turning in place keeps the margin: the turn's footprints (footprint.turn_footprints), grown
        by it, touch nothing. Each is tested (one call): the turn's sweep is their union, and building
        the union took most of the planner's time (a turn of half a circle is 37 footprints)."""
        if abs(turn_angle(yaw_from, yaw_to)) <= MIN_TURN or self.roomy(x, y):
            return True
        footprints = turn_footprints(x, y, yaw_from, yaw_to, self.length, self.width, self.margin)
        return not shapely.intersects(self.blocked, footprints).any()

    def drive_shape(self, a: tuple[float, float], b: tuple[float, float], heading: float, margin: float) -> Polygon:
        """footprint.drive_sweep(a, b, heading, ..., margin), fast when `heading` is along the leg
        (either way), as the base drives every leg: then the two footprints share their axes and
        one is the other shifted along its length, so their convex hull (drive_sweep) is the same
        rectangle, as wide, longer by the leg, centred halfway: that rectangle is built directly.
        Any other heading gets drive_sweep itself."""
        dx, dy = b[0] - a[0], b[1] - a[1]
        if abs(math.cos(heading) * dy - math.sin(heading) * dx) > ALONG:
            return drive_sweep(a, b, heading, self.length, self.width, margin)
        middle = ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)
        return footprint(middle[0], middle[1], heading, self.length + math.hypot(dx, dy), self.width, margin)

    def leg_clear(self, a: tuple[float, float], b: tuple[float, float], heading: float) -> bool:
        """Driving straight from a to b holding `heading` keeps the margin (the leg's drive_sweep,
        grown by it, touches nothing), and the centre stays on the floor and out of the keep-out
        zones grown by base_radius + margin."""
        if math.dist(a, b) < MIN_LEG:
            return True
        if self.blocked.intersects(self.drive_shape(a, b, heading, self.margin)):
            return False
        line: LineString = shapely.linestrings([a, b])  # LineString([a, b]) in a third of the time
        return not self.zones_grown.intersects(line) and self.floor.covers(line)

    # What is near, for messages

    def nearest(self, shape: BaseGeometry) -> tuple[_Blocker, float] | None:
        found = [(blocker, shape.distance(blocker.shape)) for blocker in self.blockers]
        return min(found, key=lambda item: item[1]) if found else None

    def distance(self, shape: BaseGeometry) -> float:
        return shape.distance(self.blocked) if self.blockers else math.inf

    def hit(self, shape: BaseGeometry) -> _Blocker | None:
        for blocker in self.blockers:
            if shape.intersects(blocker.shape):
                return blocker
        return None

    def zone_near(self, geometry: BaseGeometry, reach: float) -> tuple[KeepOut, float] | None:
        """The keep-out zone within `reach` of the geometry (a point or a leg), and how far it is."""
        for zone, shape in self.zones:
            distance = geometry.distance(shape)
            if distance < reach:
                return zone, distance
        return None

    def where(self, x: float, y: float) -> str:
        """'the kitchen (2.50, 2.50)', or the bare point outside every room."""
        room = self.world.room_of(x, y)
        names = {r.id: r.name for r in self.world.world.rooms}
        return f"the {names[room]} {_at(x, y)}" if room else _at(x, y)

    # A whole route, as the sim drives it

    def route_problem(self, start: Pose2D, path: Sequence[Pose2D], goal: Pose2D) -> str | None:
        """What is wrong with the route drive_route(start, path, goal), in words, or None: what
        safety would refuse (safety_problem), else what breaks the planner's own margin."""
        points = drive_route(start, list(path), goal)
        sweeps = route_sweeps(start, points, goal.yaw, self.length, self.width)
        return self.safety_problem(start, points, sweeps) or self.margin_problem(start, points, sweeps)

    def _safety_zone(self, geometry: BaseGeometry) -> KeepOut | None:
        for zone, grown in self.safety_zones:
            if geometry.intersects(grown):
                return zone
        return None

    def safety_problem(
        self, start: Pose2D, points: Sequence[tuple[float, float]], sweeps: Sequence[Sweep]
    ) -> str | None:
        """Why SafetyPolicy.check_route (services/safety/policy.py, the arm stowed) would refuse the
        route from `start` through `points` (drive_route's) whose sweeps (route_sweeps) are given,
        or None: its tests in its order. Every point in a room and out of the keep-out zones grown
        by the base's radius; every leg, from the start on, on the floor and out of those zones;
        footprint.clearance_problem at TRACKING_TOLERANCE from walls and furniture."""
        for k, (x, y) in enumerate(points, start=1):
            what = "the goal" if k == len(points) else "the route point"
            if self.world.room_of(x, y) is None:
                return f"{what} {_at(x, y)} is outside every room of the map"
            if zone := self._safety_zone(Point(x, y)):
                return f"at {what} {_at(x, y)} the base's footprint would be in keep-out zone '{zone.name}'{_why(zone)}"
        for a, b in itertools.pairwise([(start.x, start.y), *points]):
            leg = LineString([a, b])
            if not self.floor.covers(leg):
                return f"the path from {_at(*a)} to {_at(*b)} leaves the map"
            if zone := self._safety_zone(leg):
                return (
                    f"the path from {_at(*a)} to {_at(*b)} takes the base's footprint into keep-out zone "
                    f"'{zone.name}'{_why(zone)}"
                )
        size = (self.length, self.width)
        if problem := clearance_problem(start, sweeps, self.walls_and_furniture, TRACKING_TOLERANCE, *size):
            return problem[1]
        return None

    def margin_problem(
        self, start: Pose2D, points: Sequence[tuple[float, float]], sweeps: Sequence[Sweep]
    ) -> str | None:
        """What breaks the planner's own margin on the route, or None: every sweep keeps `margin`
        from walls, furniture and people (footprint.clearance_problem: leaving the start no closer
        than it starts), route points and legs keep base_radius + margin from keep-out zones (the
        first leg no closer than the start is)."""
        if problem := clearance_problem(start, sweeps, self.blockers, self.margin, self.length, self.width):
            return problem[1]
        here = (start.x, start.y)
        for k, point in enumerate(points):
            leg = LineString([here, point]) if math.dist(here, point) >= MIN_LEG else Point(point)
            reach = self.zone_reach
            if k == 0 and (start_zone := self.zone_near(Point(here), reach)):
                reach = start_zone[1] - EPSILON
            if found := self.zone_near(leg, reach):
                zone, distance = found
                return (
                    f"the path from {_at(*here)} to {_at(*point)} comes {distance:.2f} m from keep-out zone "
                    f"'{zone.name}'{_why(zone)}; the base's centre must stay {self.zone_reach:.2f} m from it"
                )
            here = point
        return None

    # Which way through, for an unreachable goal

    @cached_property
    def passable(self) -> BaseGeometry:
        """Where the base's centre can be at all: on the floor, half its width plus the margin from
        everything (it cannot be nearer, whichever way it faces), out of the grown keep-out zones."""
        free = self.floor.difference(self.zones_grown)
        if self.blockers:
            free = free.difference(self.blocked.buffer(self.width / 2 + self.margin))
        return free


def route_clearance_problem(
    world: WorldModel,
    start: Pose2D,
    path: Sequence[Pose2D],
    goal: Pose2D,
    margin: float = 0.0,
    people: Sequence[tuple[float, float]] = (),
) -> str | None:
    """What keeps the base from driving `path` then to `goal` from `start` as the sim does
    (worldmodel.drive_route, footprint.route_legs), in words, or None when nothing does: the
    planner's final verification of a path. Safety's route check (TRACKING_TOLERANCE from walls
    and furniture, base_radius from keep-out zones, on the map), and the footprint no closer than
    `margin` (at least TRACKING_TOLERANCE) to a wall, furniture or a person (PERSON_RADIUS +
    PERSON_COMFORT around each of `people`), route points and legs base_radius + `margin` from
    keep-out zones; leaving the start the base may stay as close as it starts, never closer.
    margin=0 is what safety demands.
    """
    return _Floorplan(world, margin, people).route_problem(start, path, goal)


class _RouteChecker:
    """The motion model the planner validates against, exactly as footprint.route_sweeps drives.

    A state's yaw is the base's heading only at the start; at any other waypoint the base turns
    from the heading of the leg it arrived on, which a check of one motion cannot know, so such a
    waypoint must be roomy (any turn there keeps the margin). `goals` are where the path may end,
    each with whether it is the pre-goal point: the base must arrive there knowing its heading
    (from the start, or on a leg clearly longer than MAX_REVERSE, so driven forwards), facing well
    within a quarter turn of the goal's heading so the sim drives the last leg straight in
    forwards. Any other end point is roomy and its last leg to the goal was checked beforehand.
    """

    def __init__(self, plan: _Floorplan, start: State, goals: dict[State, bool]) -> None:
        self.plan = plan
        self.start = start
        self.goals = goals
        # OMPL checks motions from the same tree nodes over and over.
        self.roomy_at: dict[tuple[float, float], bool] = {}
        # The checks run from OMPL: one that raises fails, and is raised after the solve.
        self.guard = Guard()

    def roomy(self, point: tuple[float, float]) -> bool:
        known = self.roomy_at.get(point)
        if known is None:
            known = self.roomy_at[point] = self.plan.roomy(*point)
        return known

    def state_ok(self, state: State) -> bool:
        return state == self.start or state in self.goals or self.roomy((state[0], state[1]))

    def motion_ok(self, a: State, b: State) -> bool:
        plan = self.plan
        here, there = (a[0], a[1]), (b[0], b[1])
        from_start, straight_in = a == self.start, self.goals.get(b, False)
        if not from_start and not self.roomy(here):
            return False
        if not straight_in and b not in self.goals and not self.roomy(there):
            return False
        length = math.dist(here, there)
        if from_start:
            headings = [a[2]] if length < MIN_LEG else _headings(a[2], here, there)
            if not all(plan.turn_clear(here[0], here[1], a[2], heading) for heading in headings):
                return False
        elif straight_in and length <= MAX_REVERSE + LENGTH_MARGIN:
            return False  # the base could arrive facing either way
        else:
            headings = [math.atan2(there[1] - here[1], there[0] - here[0])]
        if not plan.leg_clear(here, there, headings[0]):
            return False
        if straight_in:
            # Arriving facing one known way, within a quarter turn of the goal's heading, so that the
            # sim drives the last leg forwards.
            if len(headings) > 1 or abs(turn_angle(headings[0], b[2])) > math.pi / 2 - HEADING_MARGIN:
                return False
            return plan.turn_clear(there[0], there[1], headings[0], b[2])
        return True


def _headings(yaw: float, here: tuple[float, float], there: tuple[float, float]) -> list[float]:
    """The heading the base holds driving from `here`, facing `yaw`, to `there` (footprint.leg_heading);
    both ways round when tracking error could tip the sim's choice between driving and backing."""
    heading, _ = leg_heading(yaw, here, there)
    off = abs(turn_angle(yaw, math.atan2(there[1] - here[1], there[0] - here[0])))
    length = math.dist(here, there)
    near_quarter = abs(off - math.pi / 2) < HEADING_MARGIN
    near_limit = abs(length - MAX_REVERSE) < LENGTH_MARGIN and off > math.pi / 2 - HEADING_MARGIN
    if length <= MAX_REVERSE + LENGTH_MARGIN and (near_quarter or near_limit):
        return [heading, math.remainder(heading + math.pi, math.tau)]
    return [heading]


def _values(state: ob.State) -> State:
    return (state.getX(), state.getY(), state.getYaw())


class _MotionValidator(ob.MotionValidator):
    """OMPL's hook for _RouteChecker.motion_ok (called from C++ for every motion it considers)."""

    def __init__(self, si: ob.SpaceInformation, checker: _RouteChecker) -> None:
        super().__init__(si)
        self.checker = checker

    def checkMotion(self, a: ob.State, b: ob.State, *rest: object) -> bool:
        checker = self.checker
        return checker.guard.check(lambda: checker.motion_ok(_values(a), _values(b)))


def _solve(
    checker: _RouteChecker, bounds: tuple[float, float, float, float], seed: int, time_limit: float
) -> list[State]:
    """RRTConnect from checker.start to one of checker.goals, fewest vertices; [] when none was
    found in time. OMPL's objects live only in _rrt_connect, so they are gone when the solve ends
    and none is left for nanobind to report at exit."""
    with solving(seed):
        states = _rrt_connect(checker, bounds, time_limit)
    checker.guard.raise_failure("a check of the base planner")
    return states


def _rrt_connect(checker: _RouteChecker, bounds: tuple[float, float, float, float], time_limit: float) -> list[State]:
    space = ob.SE2StateSpace()
    limits = ob.RealVectorBounds(2)
    limits.setLow(0, bounds[0])
    limits.setLow(1, bounds[1])
    limits.setHigh(0, bounds[2])
    limits.setHigh(1, bounds[3])
    space.setBounds(limits)
    setup = og.SimpleSetup(space)
    setup.setStateValidityChecker(lambda s: checker.guard.check(lambda: checker.state_ok(_values(s))))
    si = setup.getSpaceInformation()
    si.setMotionValidator(_MotionValidator(si, checker))

    def state(values: State) -> ob.State:
        made = space.allocState()
        made.setX(values[0])
        made.setY(values[1])
        made.setYaw(values[2])
        return made

    setup.setStartState(state(checker.start))
    goals = ob.GoalStates(si)
    for values in checker.goals:
        goals.addState(state(values))
    setup.setGoal(goals)
    setup.setPlanner(og.RRTConnect(si))
    setup.solve(time_limit)
    if not setup.haveExactSolutionPath():
        return []
    path = setup.getSolutionPath()
    simplifier = setup.getPathSimplifier()
    while simplifier.reduceVertices(path, 0, 0, 1.0):
        pass
    states = [_values(s) for s in path.getStates()]
    for _ in range(SHORTCUT_ROUNDS):
        # Shortcutting assumes part of a valid motion is valid, which turning at a new waypoint
        # in a tight spot is not: a round that leaves a motion invalid is dropped.
        simplifier.partialShortcutPath(path)
        simplifier.reduceVertices(path, 0, 0, 1.0)
        shorter = [_values(s) for s in path.getStates()]
        if not all(checker.guard.check(checker.motion_ok, a, b) for a, b in itertools.pairwise(shorter)):
            break
        states = shorter
    return states


def _fewest(checker: _RouteChecker, states: list[State]) -> list[State]:
    """The path with every waypoint dropped that a straight motion past it makes unnecessary,
    greedily from the start."""
    if not states:
        return []
    kept = [states[0]]
    k = 0
    while k < len(states) - 1:
        far = next((j for j in range(len(states) - 1, k, -1) if checker.motion_ok(states[k], states[j])), k + 1)
        kept.append(states[far])
        k = far
    return kept


class BasePlanner:
    """Plans the waypoints of NavigateToPoseGoal.path: OMPL's RRTConnect in SE(2) with the base's
    footprint against walls and furniture (and people, for planning only), each motion checked as
    the sim drives it (footprint.route_legs: turn in place, straight legs, short legs behind
    backwards). The footprint keeps `clearance` (at least TRACKING_TOLERANCE, what safety keeps)
    from everything; the start may be closer (parked at a counter, left by a wall by teleop), and
    the base then first drives out, straight or by a few legs turning a little before each, never
    getting closer. The route ends with a straight approach along the goal's
    heading from PRE_GOAL_DISTANCE behind it or, when that is blocked or out of reach and the base
    can turn freely at the goal, with a short last leg from any side. Plans are reproducible: the
    same seed gives the same path.
    """

    def __init__(self, world: WorldModel, *, clearance: float = 0.03, time_limit: float = 1.0, seed: int = 1) -> None:
        if not clearance >= 0.0 or not time_limit > 0.0:
            raise ValueError(f"clearance must be >= 0 and time_limit > 0, not {clearance!r} and {time_limit!r}")
        _check_seed(seed)
        self.world = world
        self.clearance = clearance
        self.time_limit = time_limit
        # The seed of plans that are given none (the executor gives each retry its own).
        self.seed = seed
        self._floorplan = _Floorplan(world, clearance)
        minx, miny, maxx, maxy = self._floorplan.floor.bounds
        self._bounds = (minx, miny, maxx, maxy)

    def plan(
        self,
        start: Pose2D,
        goal: Pose2D,
        people: Sequence[tuple[float, float]] = (),
        *,
        seed: int | None = None,
    ) -> list[Pose2D]:
        """The waypoints from `start` to `goal` (the goal itself not included) such that the route
        drive_route(start, path, goal), driven as footprint.route_legs, passes safety's route check
        and keeps `clearance` from walls, furniture and the comfort zone of each of `people`, and
        base_radius + clearance from keep-out zones; verified as driven before it is returned.
        OMPL is seeded with `seed` (None: the planner's own), seed + 1, ... for its tries. Raises
        PlanningFailed with a reason an LLM can act on."""
        seed = self.seed if seed is None else _check_seed(seed)
        plan = self._floorplan if not people else _Floorplan(self.world, self.clearance, people)
        self._check_start(plan, start)
        self._check_goal(plan, goal)
        if math.dist((start.x, start.y), (goal.x, goal.y)) <= PRE_GOAL_MIN_LEG and not plan.route_problem(
            start, [], goal
        ):
            return []
        ends, fallback = self._ends(plan, goal)
        exit_point, origin = self._way_out(plan, start)
        self._check_connected(plan, start, origin, goal)
        # With ends to fall back on, the first search gives up sooner: the misses are shared.
        misses = 1 if fallback else MISSES
        checker = _RouteChecker(plan, origin, ends)
        path, tries, problem = self._search(plan, start, goal, exit_point, checker, seed, misses)
        if path is None and fallback:
            checker = _RouteChecker(plan, origin, fallback)
            path, more, problem = self._search(plan, start, goal, exit_point, checker, seed + tries, MISSES - misses)
            tries += more
        if path is not None:
            return path
        tried = f"{tries} tries of {self.time_limit:g} s" if tries > 1 else f"{self.time_limit:g} s"
        if problem:
            reason = f"the path found did not check out ({problem})"
        else:
            reason = f"the way may be too tight for the base to turn (it needs {2 * plan.turn_radius:.2f} m across)"
            nearby = [p for p in plan.people if min(math.dist(p, (s.x, s.y)) for s in (start, goal)) < PEOPLE_NEARBY]
            if nearby:
                reason += (
                    f", or people near the start or the goal are in the way (at {', '.join(_at(*p) for p in nearby)}; "
                    f"the base keeps {PERSON_RADIUS + PERSON_COMFORT:.1f} m from a person's centre)"
                )
        raise PlanningFailed(
            f"no collision-free path from {plan.where(start.x, start.y)} to {plan.where(goal.x, goal.y)} "
            f"found in {tried}: {reason}"
        )

    def _search(
        self,
        plan: _Floorplan,
        start: Pose2D,
        goal: Pose2D,
        exit_point: list[tuple[float, float]],
        checker: _RouteChecker,
        seed: int,
        misses: int,
    ) -> tuple[list[Pose2D] | None, int, str]:
        """Up to CANDIDATES paths from OMPL (seeds seed, seed + 1, ...), giving up after `misses`
        tries that find none; the quickest to drive that verifies as driven (route_problem), or
        None. Also returns the tries made and, when no path found verified, why the last did not."""
        found: list[tuple[float, int, list[Pose2D]]] = []
        tries = 0
        while len(found) < CANDIDATES and tries - len(found) < misses:
            states = _solve(checker, self._bounds, seed + tries, self.time_limit)
            tries += 1
            if states:
                fewest = _fewest(checker, states)
                path = self._poses(start, [*exit_point, *((x, y) for x, y, _ in fewest[1:])])
                found.append((self._drive_time(start, path, goal), tries, path))
                if len(fewest) == 2:
                    break  # one straight motion: no other way round is quicker
        problem = ""
        for drive_time, _, path in sorted(found):
            # What safety checks, and the planner's own clearance, as driven.
            problem = plan.route_problem(start, path, goal) or ""
            if not problem:
                log.debug(
                    "path from %s to %s: %d waypoints, about %.0f s to drive, best of %d found in %d tries",
                    _at(start.x, start.y),
                    _at(goal.x, goal.y),
                    len(path),
                    drive_time,
                    len(found),
                    tries,
                )
                return path, tries, ""
            log.warning("a planned path did not check out, trying the next: %s", problem)
        return None, tries, problem

    def _drive_time(self, start: Pose2D, path: list[Pose2D], goal: Pose2D) -> float:
        """About how long the sim takes to drive the route's legs: turning and driving at full
        speed, plus speeding up and slowing down for every turn and leg."""
        robot = self.world.world.robot
        speed, rate = robot.max_linear_speed, robot.max_angular_speed
        speed_up, turn_up = speed / robot.max_linear_acceleration, rate / robot.max_angular_acceleration

        def turning(yaw_from: float, yaw_to: float) -> float:
            turn = abs(turn_angle(yaw_from, yaw_to))
            return turn / rate + turn_up if turn > MIN_TURN else 0.0

        total, yaw = 0.0, start.yaw
        for leg in route_legs(start, drive_route(start, path, goal)):
            total += turning(yaw, leg.heading) + leg.length / speed + speed_up
            yaw = leg.heading
        return total + turning(yaw, goal.yaw)

    # Start and goal

    def _check_start(self, plan: _Floorplan, start: Pose2D) -> None:
        at = _at(start.x, start.y)
        if not all(math.isfinite(v) for v in (start.x, start.y, start.yaw)):
            raise PlanningFailed("the robot's pose is not finite, so no path can be planned from it")
        if self.world.room_of(start.x, start.y) is None:
            raise PlanningFailed(f"the robot at {at} is outside every room of the map")
        if blocker := plan.hit(footprint(start.x, start.y, start.yaw, plan.length, plan.width)):
            raise PlanningFailed(f"the robot at {at} overlaps {blocker.name}, so no path can be planned from there")
        if near := plan.zone_near(Point(start.x, start.y), self.world.base_radius):
            zone, distance = near
            raise PlanningFailed(
                f"the robot at {at} is {distance:.2f} m from keep-out zone '{zone.name}'{_why(zone)}; safety "
                f"refuses any route whose points come within {self.world.base_radius:.2f} m of it"
            )

    def _check_goal(self, plan: _Floorplan, goal: Pose2D) -> None:
        at = _at(goal.x, goal.y)
        if not all(math.isfinite(v) for v in (goal.x, goal.y, goal.yaw)):
            raise PlanningFailed("the goal is not a finite pose")
        if self.world.room_of(goal.x, goal.y) is None:
            raise PlanningFailed(f"the goal {at} is outside every room of the map")
        centre = Point(goal.x, goal.y)
        for blocker in plan.blockers:
            if blocker.shape.intersects(centre):
                inside = "is where" if blocker.name.startswith("a person") else "is inside"
                raise PlanningFailed(f"the goal {at} {inside} {blocker.name}")
        for zone, shape in plan.zones:
            if shape.intersects(centre):
                raise PlanningFailed(f"the goal {at} is in keep-out zone '{zone.name}'{_why(zone)}")
        if near := plan.zone_near(centre, plan.zone_reach):
            zone, distance = near
            raise PlanningFailed(
                f"the goal {at} is {distance:.2f} m from keep-out zone '{zone.name}'{_why(zone)}; the base's "
                f"centre must stay {plan.zone_reach:.2f} m from it"
            )
        self._check_fits(plan, goal, f"the base does not fit at the goal {at}")

    def _check_fits(self, plan: _Floorplan, pose: Pose2D, what: str) -> None:
        shape = footprint(pose.x, pose.y, pose.yaw, plan.length, plan.width)
        if blocker := plan.hit(shape):
            raise PlanningFailed(f"{what}: it would overlap {blocker.name}")
        if not plan.fits(pose.x, pose.y, pose.yaw) and (near := plan.nearest(shape)):
            raise PlanningFailed(
                f"{what}: it would be {_cm(near[1])} from {near[0].name} (it keeps {_cm(plan.margin)} clear)"
            )

    def _ends(self, plan: _Floorplan, goal: Pose2D) -> tuple[dict[State, bool], dict[State, bool]]:
        """Where the path may end, each with whether it is the pre-goal point, and where it may end
        should it not reach those. The pre-goal, when the base can drive straight in from there;
        where the base can turn freely at the goal, also points NEAR_GOAL_DISTANCE round it with a
        clear last leg: instead of the pre-goal when that is blocked, else should it be out of reach."""
        yaw = math.remainder(goal.yaw, math.tau)
        near: dict[State, bool] = {}
        for k in range(NEAR_GOAL_DIRECTIONS if plan.roomy(goal.x, goal.y) else 0):
            # From behind the goal first, then further round either way.
            side = (k + 1) // 2 * (1 if k % 2 else -1)
            direction = yaw + math.pi + side * math.tau / NEAR_GOAL_DIRECTIONS
            x = goal.x + NEAR_GOAL_DISTANCE * math.cos(direction)
            y = goal.y + NEAR_GOAL_DISTANCE * math.sin(direction)
            heading = math.remainder(direction + math.pi, math.tau)
            if plan.roomy(x, y) and plan.leg_clear((x, y), (goal.x, goal.y), heading):
                near[(x, y, heading)] = False
        try:
            return {self._check_approach(plan, goal, yaw): True}, near
        except PlanningFailed:
            if not near:
                raise
            return near, {}

    def _check_approach(self, plan: _Floorplan, goal: Pose2D, yaw: float) -> State:
        """The pre-goal state, when the base can drive straight in from there along the goal's heading."""
        x, y = goal.x - PRE_GOAL_DISTANCE * math.cos(yaw), goal.y - PRE_GOAL_DISTANCE * math.sin(yaw)
        what = f"the base cannot drive straight in to the goal {_at(goal.x, goal.y)} facing {goal.yaw:.2f} rad"
        if self.world.room_of(x, y) is None:
            raise PlanningFailed(f"{what}: it would start at {_at(x, y)}, outside every room of the map")
        before = f"{what}: at {_at(x, y)}, {PRE_GOAL_DISTANCE:g} m before it"
        self._check_fits(plan, Pose2D(x=x, y=y, yaw=yaw), before)
        if found := plan.zone_near(Point(x, y), plan.zone_reach):
            raise PlanningFailed(f"{before}, it would be {found[1]:.2f} m from keep-out zone '{found[0].name}'")
        if not plan.leg_clear((x, y), (goal.x, goal.y), yaw):
            near = plan.nearest(plan.drive_shape((x, y), (goal.x, goal.y), yaw, 0.0))
            detail = f"it would come {_cm(near[1])} from {near[0].name}" if near else "it would leave the map"
            raise PlanningFailed(f"{what}: from {_at(x, y)} {detail}")
        return (x, y, yaw)

    def _way_out(self, plan: _Floorplan, start: Pose2D) -> tuple[list[tuple[float, float]], State]:
        """Where planning starts: the start itself when the base can turn there, else the nearest
        point straight behind (less than MAX_REVERSE) or ahead of it where it can or, when there is
        none, the end of the quickest few legs there (_legs_out), driven to keeping the margin or,
        when the start is closer than that, getting no closer to anything than the start is
        (footprint.clearance_problem). Returns the way out's points (if any) and the state planning
        starts from."""
        yaw = math.remainder(start.yaw, math.tau)
        origin = (start.x, start.y, yaw)
        if plan.roomy(start.x, start.y):
            return [], origin
        size = (plan.length, plan.width)
        tight = not plan.fits(start.x, start.y, yaw)
        reach = plan.zone_reach
        if near := plan.zone_near(Point(start.x, start.y), reach):
            reach = near[1] - EPSILON
        start_footprint = footprint(start.x, start.y, yaw, *size)
        # Closer than TRACKING_TOLERANCE, safety lets the base leave only as close as it starts, as it
        # reads the pose a moment after this: a leg straight out ties with that exactly, and a start read
        # a hair off (a standing base creeps, a teleop turn dies out) had it refused. A turn first is
        # drawn by safety from its own start, beginning with exactly the footprint it measures there.
        facing = Pose2D(x=start.x, y=start.y, yaw=yaw)  # the start, its yaw in [-pi, pi]
        if plan.distance(start_footprint) < TRACKING_TOLERANCE and (
            legs := self._legs_out(plan, facing, reach, turn_first=True)
        ):
            return legs
        steps = [EXIT_STEP * k for k in range(1, round(MAX_EXIT_FORWARD / EXIT_STEP) + 1)]
        candidates = sorted([-d for d in steps if d <= MAX_EXIT_BACK + EPSILON] + steps, key=abs)
        fallback: tuple[list[tuple[float, float]], State] | None = None
        for d in candidates:
            point = (start.x + d * math.cos(yaw), start.y + d * math.sin(yaw))
            line = LineString([(start.x, start.y), point])
            if not plan.floor.covers(line) or plan.zone_near(line, reach):
                continue
            sweeps = route_sweeps(start, [point], yaw, *size)
            if clearance_problem(start, sweeps, plan.blockers, plan.margin, *size):
                continue
            if plan.roomy(*point):
                return [point], (*point, yaw)
            if fallback is None and plan.fits(*point, yaw):
                fallback = ([point], (*point, yaw))
        if legs := self._legs_out(plan, facing, reach):
            return legs
        if not tight:
            return [], origin
        if fallback is not None:
            return fallback
        near_blocker = plan.nearest(start_footprint)
        name = near_blocker[0].name if near_blocker else "something"
        raise PlanningFailed(
            f"the robot at {_at(start.x, start.y)} is {_cm(plan.distance(start_footprint))} from {name} and cannot "
            f"drive out of there, in up to {EXIT_LEGS} legs coming no closer to anything, to where it could turn"
        )

    def _legs_out(
        self, plan: _Floorplan, start: Pose2D, reach: float, turn_first: bool = False
    ) -> tuple[list[tuple[float, float]], State] | None:
        """The quickest way out of up to EXIT_LEGS legs that ends where the base can turn, fewest
        legs first, or None: its points and where it ends facing which way. Each round of legs
        starts from the ends of the last farthest from everything. The first leg leaves the start
        keeping the margin or getting no closer than the start is, its line `reach` from keep-out
        zones (footprint.clearance_problem, as the route is checked); later legs keep the margin.
        `turn_first`: the first leg turns before it drives (see _exit_legs)."""
        size = (plan.length, plan.width)
        ends = [_Exit((), (start.x, start.y, start.yaw), 0.0)]
        for _ in range(EXIT_LEGS):
            found = [way for end in ends for way in self._exit_legs(plan, end, reach, turn_first)]
            for way in sorted((way for way in found if plan.roomy(way.end[0], way.end[1])), key=lambda way: way.time):
                sweeps = route_sweeps(start, way.points, way.end[2], *size)
                if not clearance_problem(start, sweeps, plan.blockers, plan.margin, *size):
                    return list(way.points), way.end
            found.sort(key=lambda way: -plan.distance(Point(way.end[0], way.end[1])))
            ends = found[:EXIT_BEAM]
        return None

    def _exit_legs(self, plan: _Floorplan, way: _Exit, reach: float, turn_first: bool = False) -> Iterator[_Exit]:
        """`way` and one more leg, every one that keeps clear: turning by a multiple of EXIT_TURN either
        way (no further than the turn keeps clear), then forwards up to MAX_EXIT_FORWARD or backwards
        up to MAX_EXIT_BACK in steps of EXIT_STEP (no further than the leg keeps clear). The first leg
        is measured as footprint.clearance_problem measures leaving the start; later ones keep the
        margin as every motion of the planner does. With `turn_first` the first leg turns by one of
        FIRST_TURNS or a multiple of EXIT_TURN, never not at all, and may go MAX_TURNED_EXIT_FORWARD ahead."""
        x, y, yaw = way.end
        here = (x, y)
        first = not way.points
        # Leaving the start, the base may stay as close as it starts (later legs: plan.turn_clear, leg_clear).
        required = (
            min(plan.margin, plan.distance(footprint(x, y, yaw, plan.length, plan.width))) - EPSILON if first else 0.0
        )
        robot = self.world.world.robot
        turns = [k * EXIT_TURN for k in range(round(math.pi / EXIT_TURN))]
        ahead = MAX_EXIT_FORWARD
        if first and turn_first:
            turns, ahead = [*FIRST_TURNS, *turns[1:]], MAX_TURNED_EXIT_FORWARD
        for sense in (1.0, -1.0):
            for angle in turns if sense > 0 else [a for a in turns if a]:
                heading = math.remainder(yaw + sense * angle, math.tau)
                if first and angle:
                    turn = turn_footprints(x, y, yaw, heading, plan.length, plan.width, 0.0)
                    if shapely.distance(turn, plan.blocked).min() < required:
                        break
                elif not first and not plan.turn_clear(x, y, yaw, heading):
                    break
                turning = angle / robot.max_angular_speed
                for direction, farthest in ((1.0, ahead), (-1.0, MAX_EXIT_BACK)):
                    for step in range(1, round(farthest / EXIT_STEP) + 1):
                        length = step * EXIT_STEP
                        point = (x + direction * length * math.cos(heading), y + direction * length * math.sin(heading))
                        held = _headings(yaw, here, point)
                        if len(held) > 1 or abs(turn_angle(held[0], heading)) > MIN_TURN:
                            continue  # the sim would not drive it holding this heading
                        if first:
                            line: LineString = shapely.linestrings([here, point])
                            if not plan.floor.covers(line) or plan.zone_near(line, reach):
                                break
                            if plan.distance(plan.drive_shape(here, point, heading, 0.0)) < required:
                                break
                        elif not plan.leg_clear(here, point, heading):
                            break
                        time = way.time + turning + length / robot.max_linear_speed
                        yield _Exit((*way.points, point), (*point, heading), time)

    def _check_connected(self, plan: _Floorplan, start: Pose2D, origin: State, goal: Pose2D) -> None:
        """Fail fast, naming why, when no opening as wide as the base leads from start to goal."""
        parts = _parts(plan.passable)
        source, target = _part_of(parts, origin), _part_of(parts, (goal.x, goal.y, 0.0))
        if source is None or target is None or source == target:
            return
        way = f"no collision-free path from {plan.where(start.x, start.y)} to {plan.where(goal.x, goal.y)}"
        if plan.people:
            open_parts = _parts(self._floorplan.passable)
            if _part_of(open_parts, origin) == _part_of(open_parts, (goal.x, goal.y, 0.0)):
                people = ", ".join(_at(x, y) for x, y in plan.people)
                raise PlanningFailed(
                    f"{way}: people block the way (at {people}; the base keeps "
                    f"{PERSON_RADIUS + PERSON_COMFORT:.1f} m from a person's centre); ask them to step aside or wait"
                )
        needed = plan.width + 2 * plan.margin
        raise PlanningFailed(
            f"{way}: no opening at least {needed:.2f} m wide (the base's width and {_cm(plan.margin)} "
            f"each side) leads there"
        )

    @staticmethod
    def _poses(start: Pose2D, points: list[tuple[float, float]]) -> list[Pose2D]:
        """Waypoints as poses, each facing the way the base faces arriving there (the heading of the
        route_legs leg ending there; a point the base does not move for keeps the one before)."""
        legs = iter(route_legs(start, points))
        leg = next(legs, None)
        poses = []
        yaw = start.yaw
        for x, y in points:
            if leg is not None and leg.end == (float(x), float(y)):
                yaw = leg.heading
                leg = next(legs, None)
            poses.append(Pose2D(x=x, y=y, yaw=math.remainder(yaw, math.tau)))
        return poses


def _check_seed(seed: int) -> int:
    if not isinstance(seed, int) or seed <= 0:
        raise ValueError(f"an OMPL seed must be a positive integer (0 makes OMPL pick one at random), not {seed!r}")
    return seed


def _parts(region: BaseGeometry) -> list[BaseGeometry]:
    return list(getattr(region, "geoms", [region]))


def _part_of(parts: list[BaseGeometry], state: State) -> int | None:
    point = Point(state[0], state[1])
    distances = [part.distance(point) for part in parts]
    if not distances:
        return None
    best = min(range(len(parts)), key=distances.__getitem__)
    return best if distances[best] < 1e-6 else None
