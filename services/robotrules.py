"""What every robot backend does alike (docs/robot.md): fail closed on the heartbeat, check goals, keep out of
keep-out zones on its own. Pure logic."""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import shapely
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from schemas.common import Pose2D
from schemas.robot import ARM_JOINTS, FollowJointTrajectoryGoal, NavigateToPoseGoal
from schemas.safety import SafetyStatus
from schemas.world import World
from services.footprint import MIN_TURN, TRACKING_TOLERANCE, footprint, route_legs, route_sweeps, turn_angle
from services.worldmodel import drive_route

log = logging.getLogger(__name__)

# Action feedback while a goal runs (wall seconds).
FEEDBACK_PERIOD = 0.1
# A goal arriving while the e-stop shows latched waits this long for a newer heartbeat (a reset).
RESET_GRACE = 0.1
# A preempting goal waits this long for the running one to end. With the waits in accepting it
# (RESET_GRACE, twice: before and after), send_goal answers well within safety's forward_timeout
# (5 s), so safety never reports a forward failed that the robot then runs. docs/robot.md, Timing.
PREEMPT_TIMEOUT = 2.0
NO_HEARTBEAT_YET = "no safety heartbeat received yet"
# A heartbeat whose stamp (safety's wall clock) is older than this when it arrives (the robot's wall
# clock) counts for less, and not at all beyond it: a beat held up by a stalled link is no sign of
# life. Covers its transit and the offset between the two hosts' clocks (0 when they share a host).
HEARTBEAT_MAX_AGE = 0.5
# A held cmd_vel's path is drawn as the footprint at this many poses along it.
DRIVE_SAMPLES = 10
# Overlap smaller than this (m^2) is touching, not entering.
TOUCHING = 1e-6
# A base already in a zone is checked at poses this far apart along a route (m, rad): its overlap with
# the zone may not grow.
ROUTE_STEP = 0.05
ROUTE_TURN_STEP = math.radians(5.0)


@dataclass(frozen=True)
class SafetyNow:
    """What safety's heartbeat allows at one moment."""

    blocked: str | None  # why the robot must stay still; None when it may move
    status: SafetyStatus | None  # the latest heartbeat
    stopped: bool = False  # it has just become blocked: stop everything, abort every goal
    released: bool = False  # it has just become clear: it may move again

    @property
    def speed_scale(self) -> float:
        """The fraction of its speed the robot may use: 0 while blocked or paused."""
        if self.blocked is not None or self.status is None:
            return 0.0
        return self.status.speed_scale


class HeartbeatGuard:
    """The fail-closed rules on safety's heartbeat (docs/robot.md, Fail closed), for any backend.

    `heard` takes each heartbeat; `block` says why the robot must stay still now; `accept` is an
    action server's accept check (waiting, bounded, for the first heartbeat and for a reset);
    `poll`, from the one loop that enforces it, also says when the robot has just become blocked or
    clear. Times come from `clock` (monotonic seconds), so tests can step it.

    A heartbeat counts for `heartbeat_timeout` from its arrival, but never once its stamp is older
    than `max_age` by `wall_clock`: one stamped `age` before it arrived counts for
    min(heartbeat_timeout, max_age - age), so a beat a stalled link held back does not refresh the
    guard when it finally arrives. Freshness never goes back: a late beat's word (its e-stop, its
    speed) is taken, its age does not cut short what an earlier, timely one allowed.
    """

    def __init__(
        self,
        heartbeat_timeout: float,
        first_heartbeat_wait: float,
        clock: Callable[[], float] = time.monotonic,
        *,
        max_age: float = HEARTBEAT_MAX_AGE,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.heartbeat_timeout = heartbeat_timeout
        self.first_heartbeat_wait = first_heartbeat_wait
        self.max_age = max_age
        self._clock = clock
        self._wall_clock = wall_clock
        # Taken alone where nothing waits or is told (C's enter and exit, not the Condition's own in
        # Python): `accept` takes it twice for every goal.
        self._lock = threading.RLock()
        self._beat = threading.Condition(self._lock)
        self._status: SafetyStatus | None = None
        self._heard_at = 0.0  # when the heartbeat counting longest arrived
        self._stale_at = -math.inf  # when it stops counting
        self._late = 0.0  # how old the latest heartbeat's stamp was when it arrived
        self._first = threading.Event()
        self._blocked: str | None = NO_HEARTBEAT_YET  # as of the last poll
        self._scale = 1.0  # as of the last poll

    def heard(self, status: SafetyStatus) -> None:
        now, age = self._clock(), self._wall_clock() - status.stamp
        # How long it counts; not at all with a stamp that is no time.
        counts_for = min(self.heartbeat_timeout, self.max_age - age) if math.isfinite(age) else 0.0
        with self._beat:
            self._status, self._late = status, age
            if counts_for > 0.0 and now + counts_for > self._stale_at:
                self._heard_at, self._stale_at = now, now + counts_for
            self._beat.notify_all()
        self._first.set()

    @property
    def status(self) -> SafetyStatus | None:
        with self._lock:
            return self._status

    def stale_at(self) -> float | None:
        """When the heartbeats heard stop counting (clock seconds); None before the first that counts."""
        with self._lock:
            return None if self._stale_at == -math.inf else self._stale_at

    def block(self) -> str | None:
        """Why the robot must stay still right now, or None when safety says it may move."""
        with self._lock:
            status, at, stale_at, late = self._status, self._heard_at, self._stale_at, self._late
        if status is None:
            return NO_HEARTBEAT_YET
        now = self._clock()
        if now > stale_at:
            if not late <= self.max_age - self.heartbeat_timeout:  # the latest came late (or stamped no time)
                return (
                    f"no fresh safety heartbeat: the latest was stamped {late * 1000:.0f} ms before it arrived "
                    f"(heartbeat_max_age {self.max_age * 1000:.0f} ms)"
                )
            return f"no safety heartbeat for {(now - at) * 1000:.0f} ms"
        if status.estop.latched:
            return f"e-stop latched by {status.estop.source or 'unknown'}: {status.estop.reason or 'no reason given'}"
        return None

    def now(self) -> SafetyNow:
        """What the heartbeat allows now (no transitions: those are `poll`'s)."""
        return SafetyNow(self.block(), self.status)

    def next_heartbeat(self, timeout: float) -> None:
        """Wait (bounded) until a heartbeat newer than the latest arrives."""
        with self._beat:
            latest = self._status
            self._beat.wait_for(lambda: self._status is not latest, timeout)

    def accept(self) -> str | None:
        """None when a goal may be accepted now, else why not. Never moves without a heartbeat: this
        only waits (bounded) for the first one to arrive, and for one more when the e-stop shows latched."""
        if not self._first.is_set():
            self._first.wait(self.first_heartbeat_wait)
        reason = self.block()
        status = self.status
        if status is not None and status.estop.latched:
            # Safety announces a reset with a heartbeat before it approves anything, but a goal it
            # approved right after can overtake that heartbeat on the way here: hear one more.
            self.next_heartbeat(RESET_GRACE)
            reason = self.block()
        return reason

    def poll(self) -> SafetyNow:
        """What the heartbeat allows now, and whether that just changed. Call from one loop only."""
        now = self.now()
        was_blocked = self._blocked is not None
        self._blocked = now.blocked
        if now.blocked is not None:
            self._scale = 0.0  # while blocked nothing moves until a heartbeat says how fast it may
            if not was_blocked:
                log.warning("stopping the robot: %s", now.blocked)
                return SafetyNow(now.blocked, now.status, stopped=True)
            return now
        assert now.status is not None
        scale = now.status.speed_scale
        if was_blocked:
            log.info("safety heartbeat present and e-stop clear: the robot may move at %.2f of full speed", scale)
        else:
            _log_speed_change(self._scale, scale, now.status.speed_reason or "no reason given")
        self._scale = scale
        return SafetyNow(None, now.status, released=was_blocked)


def _log_speed_change(previous: float, scale: float, why: str) -> None:
    if scale == previous:
        return
    if scale == 0.0:
        log.info("pausing motion, goals kept: speed scale 0 (%s)", why)
    elif previous == 0.0:
        log.info("resuming at speed scale %.2f (%s)", scale, why)
    else:
        log.debug("speed scale %.2f (%s)", scale, why)


_ARM_JOINT_SET = frozenset(ARM_JOINTS)
_ARM_JOINT_LIST = list(ARM_JOINTS)


def check_trajectory(goal: FollowJointTrajectoryGoal, lower: Sequence[float], upper: Sequence[float]) -> str | None:
    """Why the arm cannot follow a trajectory goal, or None when it can; `lower` and `upper` are the
    limits of ARM_JOINTS, in order."""
    names = goal.joint_names
    if not _ARM_JOINT_SET.issuperset(names):
        unknown = [n for n in names if n not in _ARM_JOINT_SET]
        return f"unknown joints {unknown}; this arm has {list(ARM_JOINTS)}"
    if len(set(names)) != len(names):
        return f"joint names repeat: {names}"
    # Each joint's limits looked up once for the goal, not per point, and not at all for the arm's
    # joints in their order (what safety sends): the robot checks every goal as it comes, after
    # sleeping between goals, when each call costs many times its warm time.
    lows, highs = lower, upper
    if names != _ARM_JOINT_LIST:
        lows = [lower[ARM_JOINTS.index(name)] for name in names]
        highs = [upper[ARM_JOINTS.index(name)] for name in names]
    previous = -1.0
    for k, point in enumerate(goal.points):
        if len(point.positions) != len(names):
            return f"point {k} has {len(point.positions)} positions for {len(names)} joints"
        if point.time_from_start < previous:
            return f"point {k} goes back in time ({point.time_from_start:g} s after {previous:g} s)"
        if point.time_from_start == previous:
            # Nothing to interpolate between them: the arm would jump (ros2_control's trajectory
            # controller refuses such times too; safety sends only strictly increasing ones).
            return f"point {k} comes at the same time as point {k - 1} ({previous:g} s): the arm would jump"
        previous = point.time_from_start
        for name, value, low, high in zip(names, point.positions, lows, highs, strict=True):
            if not low <= value <= high:
                return f"point {k}: {name} = {value:.3f} rad is outside [{low:.3f}, {high:.3f}]"
    return None


def away_from(here: Pose2D, start: Pose2D, base_radius: float) -> str | None:
    """Why a navigation checked from `start` may not set off with the base at `here` (it would drive
    other legs than those safety checked), or None when the base stands there within TRACKING_TOLERANCE."""
    off = math.dist((here.x, here.y), (start.x, start.y)) + base_radius * abs(turn_angle(here.yaw, start.yaw))
    if off <= TRACKING_TOLERANCE:
        return None
    return (
        f"the route was checked from ({start.x:.2f}, {start.y:.2f}, {start.yaw:.2f} rad) but the base stands at "
        f"({here.x:.2f}, {here.y:.2f}, {here.yaw:.2f} rad)"
    )


class KeepOut:
    """The world's keep-out zones, checked by the robot itself (docs/robot.md, Keep-out zones): a
    navigation goal whose target or route (the legs the robot drives, services/footprint.py) would
    put the base's footprint into a zone, or a cmd_vel that held for its time would, is refused
    before the base moves. Safety checks the same and more (its policy may add zones); this is the
    robot's own line, for a command that came past safety. A base already in a zone (touching is not
    in) may leave it, or move within it, but only so that its footprint's overlap with the zone
    shrinks or stays: never deeper in, nor through it."""

    def __init__(
        self, zones: dict[str, Polygon], length: float, width: float, accelerations: tuple[float, float] = (1.5, 3.0)
    ) -> None:
        self.zones = zones
        self._bounds = [zone.bounds for zone in zones.values()]
        self.length = length
        self.width = width
        # The base's (linear m/s^2, angular rad/s^2): how far it rolls on braking after a cmd_vel's hold.
        self.accelerations = accelerations

    @classmethod
    def of(cls, world: World) -> KeepOut:
        robot = world.robot
        zones = {k.name: Polygon(k.polygon) for k in world.keep_out}
        accelerations = (robot.max_linear_acceleration, robot.max_angular_acceleration)
        return cls(zones, robot.base_size.x, robot.base_size.y, accelerations)

    def _entered(
        self, here: Pose2D, shapes: Sequence[BaseGeometry], poses: Callable[[], Sequence[Pose2D]]
    ) -> str | None:
        """The first zone one of `shapes` (the floor the move covers) enters from outside, or, for a
        zone the footprint at `here` is already in, one that the footprint at any of `poses` (along
        the move) overlaps more than it does at `here`."""
        start = footprint(here.x, here.y, here.yaw, self.length, self.width)
        along: Sequence[Polygon] | None = None
        for name, zone in self.zones.items():
            inside = start.intersection(zone).area
            if inside <= TOUCHING:
                if any(shape.intersection(zone).area > TOUCHING for shape in shapes):
                    return name
                continue
            if along is None:
                along = [footprint(p.x, p.y, p.yaw, self.length, self.width) for p in poses()]
            if any(shape.intersection(zone).area > inside + TOUCHING for shape in along):
                return name
        return None

    def goal(self, goal: NavigateToPoseGoal, here: Pose2D | None) -> str | None:
        """Why the robot refuses `goal` from `here` (its `start` when it carries one), or None."""
        start = goal.start or here
        if start is None:
            return "the robot's pose is unknown: it cannot check the route against keep-out zones"
        route = drive_route(start, goal.path, goal.pose)
        sweeps = route_sweeps(start, route, goal.pose.yaw, self.length, self.width)
        target = goal.pose
        # A sweep whose box meets no zone's box cannot enter one: only the others are made one polygon
        # (a turn's union of footprints costs milliseconds, and most routes pass no zone).
        near = [s for s in sweeps if any(_boxes_meet(s.bounds, bounds) for bounds in self._bounds)]
        shapes = [footprint(target.x, target.y, target.yaw, self.length, self.width), *(s.shape for s in near)]
        zone = self._entered(start, shapes, lambda: _route_poses(start, route, target))
        if zone is None:
            return None
        return f"the route to ({target.x:.2f}, {target.y:.2f}) would take the base into keep-out zone '{zone}'"

    def drive(self, here: Pose2D | None, linear: float, angular: float, seconds: float) -> str | None:
        """Why the robot refuses to hold (`linear` m/s, `angular` rad/s) for `seconds` from `here`, or None."""
        if linear == 0.0 and angular == 0.0:
            return None
        if here is None:
            return "the robot's pose is unknown: it cannot check a cmd_vel against keep-out zones"
        # Braking to rest from v at a takes v / a and covers as much as v / (2 a) at full speed.
        braking = max(abs(linear) / (2 * self.accelerations[0]), abs(angular) / (2 * self.accelerations[1]))
        total = seconds + braking
        # The base's centre travels at most |linear| * total along its arc, and its footprint reaches
        # half its diagonal beyond: a zone whose bounding box is farther than that cannot be entered.
        # Most twists are far from every zone, and this costs microseconds where the sweep costs ~1 ms.
        reach = abs(linear) * total + math.hypot(self.length, self.width) / 2 + TOUCHING
        if all(_box_distance(bounds, here.x, here.y) > reach for bounds in self._bounds):
            return None
        poses = [_arc(here, linear, angular, total * k / DRIVE_SAMPLES) for k in range(DRIVE_SAMPLES + 1)]
        prints = [footprint(p.x, p.y, p.yaw, self.length, self.width) for p in poses]
        shapes = [shapely.union_all([a, b]).convex_hull for a, b in itertools.pairwise(prints)]
        zone = self._entered(here, shapes, lambda: poses)
        if zone is None:
            return None
        twist = f"cmd_vel ({linear:.2f} m/s, {angular:.2f} rad/s)"
        return f"{twist} held {seconds:.2f} s would take the base into keep-out zone '{zone}'"


def _boxes_meet(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    """Whether two boxes (min x, min y, max x, max y) overlap or touch."""
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def _box_distance(bounds: tuple[float, float, float, float], x: float, y: float) -> float:
    """How far (x, y) is from the box `bounds` (min x, min y, max x, max y); 0 inside. Never more
    than the distance to the shape the box bounds."""
    min_x, min_y, max_x, max_y = bounds
    return math.hypot(max(min_x - x, 0.0, x - max_x), max(min_y - y, 0.0, y - max_y))


def _route_poses(start: Pose2D, points: Sequence[tuple[float, float]], target: Pose2D) -> list[Pose2D]:
    """The base's poses along a route (route_legs: turn, then drive each leg; turn to the target's
    heading at the end), at most ROUTE_STEP and ROUTE_TURN_STEP apart."""
    poses = [start]

    def turn(x: float, y: float, yaw_from: float, yaw_to: float) -> None:
        angle = turn_angle(yaw_from, yaw_to)
        if abs(angle) <= MIN_TURN:
            return
        count = math.ceil(abs(angle) / ROUTE_TURN_STEP)
        poses.extend(Pose2D(x=x, y=y, yaw=yaw_from + angle * k / count) for k in range(1, count + 1))

    yaw = start.yaw
    for leg in route_legs(start, points):
        turn(leg.start[0], leg.start[1], yaw, leg.heading)
        count = max(1, math.ceil(leg.length / ROUTE_STEP))
        (x0, y0), (x1, y1) = leg.start, leg.end
        poses.extend(
            Pose2D(x=x0 + (x1 - x0) * k / count, y=y0 + (y1 - y0) * k / count, yaw=leg.heading)
            for k in range(1, count + 1)
        )
        yaw = leg.heading
    last = poses[-1]
    turn(last.x, last.y, yaw, target.yaw)
    return poses


def _arc(start: Pose2D, linear: float, angular: float, t: float) -> Pose2D:
    """Where a base at `start` is after `t` seconds at a constant twist."""
    yaw = start.yaw + angular * t
    if abs(angular) < 1e-9:
        step = linear * t
        return Pose2D(x=start.x + step * math.cos(start.yaw), y=start.y + step * math.sin(start.yaw), yaw=yaw)
    radius = linear / angular
    return Pose2D(
        x=start.x + radius * (math.sin(yaw) - math.sin(start.yaw)),
        y=start.y - radius * (math.cos(yaw) - math.cos(start.yaw)),
        yaw=yaw,
    )
