"""The checks: every command and every plan against the policy's limits, each decision with its rule.

Pure logic: no zenoh. Each `check_*` returns a Verdict (the command to forward, the rules applied,
the values measured) or raises Vetoed naming the rule, the values and why, in words an LLM can act on.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, TypeVar, assert_never

import msgspec
import numpy as np
import shapely
from shapely.geometry import LineString, Point, Polygon
from shapely.geometry.base import BaseGeometry
from shapely.ops import unary_union

from schemas.common import Pose2D, Vec3
from schemas.plan import (
    DetectStep,
    Fallback,
    GripperStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    SayStep,
    StopStep,
    WaitStep,
    fallback_labels,
    step_kind,
    step_labels,
)
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, Odometry, Twist
from schemas.safety import Rule
from schemas.world import KeepOut, World
from services.footprint import TRACKING_TOLERANCE, clearance_problem, footprint, nearest, route_sweeps
from services.robotmodel import ArmModel, base_to_map, map_to_base
from services.safety.errors import Vetoed
from services.safety.policyfile import JointLimit, Limits, PolicyError, load_policy, parse_policy
from services.worldmodel import WorldModel, drive_route

T = TypeVar("T")

# Up to this many trajectory points, or end effector positions along the arm's path, are checked one
# by one in plain floats; more, all at once (numpy, shapely), then one by one only to name what fails.
# One by one costs less for a few: numpy's calls cost more than a few floats' arithmetic, the more so
# in a check run after idling, as safety's are. check_trajectory in process, back to back and after
# 40 ms asleep (2026-11-29, this machine): a one-point goal whose path has 16 end effector positions
# 61 and 241 us one by one against 74 and 440 at once, 24 positions 85 and 247 against 86 and 447; 12
# points (the joint checks) 97 and 216 against 107 and 386, 16 points 125 and 274 against 124 and 441.
FEW_POINTS = 12
FEW_ARM_POINTS = 16

# Joint positions may not come closer than this to the limits.
JOINT_LIMIT_MARGIN = 0.01
# A trajectory's first point, at time zero, may differ this much from the measured position.
START_TOLERANCE = 0.05
# Trajectories are checked between their points too, in steps no joint moves more than this.
INTERPOLATION_STEP = 0.05
# Slower than this counts as standing still.
STILL = 1e-6
# A held cmd_vel's arc is checked as chords that cut inside it by at most this much (m).
ARC_TOLERANCE = 1e-3

# The arm may start moving while the base is slower than this (m/s, rad/s): a base that just
# arrived is still settling.
STILL_BELOW = 0.1
# How long a trajectory whose start seems to jump waits for a fresher joint state (joint states
# come at 50 Hz).
FRESH_JOINTS_WAIT = 0.1
# In a trajectory decision's values: the stamp of the joint state it was checked from.
JOINTS_STAMP = "joints_stamp_s"
ROUTE_CHECKS = (Rule.POSE_KNOWN, Rule.MAP, Rule.KEEP_OUT, Rule.OBSTACLE)
# What the whole-plan check (check_plan, with the e-stop in the node) applies.
PLAN_RULES = (
    Rule.ESTOP,
    Rule.PLAN,
    Rule.POSE_KNOWN,
    Rule.MAP,
    Rule.KEEP_OUT,
    Rule.OBSTACLE,
    Rule.BASE_SPEED,
    Rule.PAYLOAD,
    Rule.WORKSPACE,
    Rule.ARM_KEEP_OUT,
    Rule.GRIPPER_DROP,
)


@dataclass(frozen=True)
class Verdict(Generic[T]):
    """A command safety lets through: as sent (maybe clamped), the rules applied, the values measured."""

    command: T
    checks: tuple[Rule, ...]
    values: dict[str, float] = field(default_factory=dict)
    # The rule that clamped the command and how, when it was changed.
    clamped_by: Rule | None = None
    note: str = ""


def _fmt(x: float) -> str:
    return f"{x:.2f}"


def _why(zone: KeepOut) -> str:
    return f": {zone.reason}" if zone.reason else ""


def _what(reach: float, radius: float) -> str:
    return "base's footprint" if reach <= radius else f"hand ({reach:.2f} m from the base's centre)"


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _joint_checks_pass(
    goal: FollowJointTrajectoryGoal, start: list[float], limits: list[JointLimit]
) -> tuple[float, np.ndarray] | None:
    """The joint checks of SafetyPolicy._joint_checks over all points at once: when every point
    passes, (the fastest joint speed, the points' positions as rows); None when one may not, for the
    point-by-point checks to find and name the first. The same comparisons of the same doubles."""
    width = len(goal.joint_names)
    if any(len(point.positions) != width for point in goal.points):
        return None
    positions = (
        np.array([point.positions for point in goal.points], dtype=float) if goal.points else np.empty((0, width))
    )
    times = np.array([point.time_from_start for point in goal.points], dtype=float)
    if not (np.isfinite(positions).all() and np.isfinite(times).all()):
        return None
    lower = np.array([lim.lower for lim in limits]) + JOINT_LIMIT_MARGIN
    upper = np.array([lim.upper for lim in limits]) - JOINT_LIMIT_MARGIN
    if not ((lower <= positions) & (positions <= upper)).all():
        return None
    dt = np.diff(times, prepend=0.0)
    # Only the first point may be at time zero, and it where the arm already is.
    if (dt < 0).any() or (dt[1:] == 0).any():
        return None
    moved = np.abs(np.diff(positions, axis=0, prepend=np.array([start], dtype=float)))
    if dt.size and dt[0] == 0 and (moved[0] > START_TOLERANCE).any():
        return None
    timed = dt > 0
    speeds = moved[timed] / dt[timed][:, np.newaxis]
    if (speeds > np.array([lim.velocity for lim in limits]) + STILL).any():
        return None
    return (float(speeds.max()) if speeds.size else 0.0), positions


def _largest_move(q0: list[float], q1: list[float]) -> float:
    """The most any joint moves from q0 to q1: NaN when a move is NaN, as numpy's max has it (max()
    keeps a NaN only when it comes first)."""
    moves = [abs(b - a) for a, b in zip(q0, q1, strict=True)]
    total = sum(moves)
    return max(moves, default=0.0) if math.isfinite(total) else total


def _held_path(pose: Pose2D, linear: float, angular: float, seconds: float) -> list[tuple[float, float]]:
    """The base centre's path holding (`linear`, `angular`) for `seconds` from `pose`: the arc it
    drives, as chords that cut inside it by at most ARC_TOLERANCE (a chord over a turn of theta,
    `length` long, cuts in by at most length * theta / 8); one straight line when `angular` is 0."""
    chords = max(1, math.ceil(seconds * math.sqrt(abs(linear * angular) / (8 * ARC_TOLERANCE))))
    points = [(pose.x, pose.y)]
    for k in range(1, chords + 1):
        t = seconds * k / chords
        if angular == 0.0:
            step = linear * t
            points.append((pose.x + step * math.cos(pose.yaw), pose.y + step * math.sin(pose.yaw)))
            continue
        yaw, radius = pose.yaw + angular * t, linear / angular
        points.append(
            (
                pose.x + radius * (math.sin(yaw) - math.sin(pose.yaw)),
                pose.y - radius * (math.cos(yaw) - math.cos(pose.yaw)),
            )
        )
    return points


def base_moving(odom: Odometry) -> bool:
    """Whether the base moves too fast for the arm to start (it may still be settling)."""
    return abs(odom.linear_x) > STILL_BELOW or abs(odom.angular_z) > STILL_BELOW


class SafetyPolicy:
    """Pure checks against the effective limits (policy tightened within the robot's own)."""

    def __init__(self, world: WorldModel, limits: Limits, arm: ArmModel) -> None:
        self.world = world
        self.limits = limits
        self.policy = limits.policy
        self.arm = arm
        self.joint_limits = limits.joints
        robot = world.world.robot
        base = self.policy.base
        self.max_linear = base.max_linear_speed
        self.max_angular = base.max_angular_speed
        self.mount = robot.arm_mount
        # Zones grown by the base's half-diagonal (plus the margin): the base centre stays that far out.
        self.radius = world.base_radius + base.footprint_margin
        self.zone_shapes: dict[str, BaseGeometry] = {zone.id: Polygon(zone.polygon) for zone in limits.keep_out}
        self.zones = {zone_id: shape.buffer(self.radius) for zone_id, shape in self.zone_shapes.items()}
        # Each zone's bounding box (min x, min y, max x, max y): a point outside it is outside the zone.
        self._zone_boxes = [(zone, self.zone_shapes[zone.id].bounds) for zone in limits.keep_out]
        self.payload = self.policy.payload.max_mass
        self._floor = unary_union(list(world.room_shapes.values()))
        self.base_size = robot.base_size
        self.obstacles = [(f"the {o.name}", o.shape) for o in world.obstacles]

    # Where the hand is

    def hand_in_base(self, joints: dict[str, float] | None) -> tuple[float, float] | None:
        """The end effector over the floor in the base frame; None when a joint position is unknown."""
        names = self.arm.joint_names
        if joints is None or not all(n in joints for n in names):
            return None
        point = self.arm.grasp_point([joints[n] for n in names])
        return float(point[0]) + self.mount.x, float(point[1]) + self.mount.y

    def reach(self, joints: dict[str, float] | None) -> float:
        """How far the hand sticks out from the base's centre (unknown: as far as the arm reaches)."""
        local = self.hand_in_base(joints)
        return math.hypot(*local) if local is not None else self.world.world.robot.reach + 0.3

    # Navigation

    def _zone_hit(self, geometry: BaseGeometry, shapes: dict[str, BaseGeometry] | None = None) -> KeepOut | None:
        """The first zone `geometry` touches, of `shapes` (default: the zones grown by the base's radius)."""
        shapes = shapes or self.zones
        for zone in self.limits.keep_out:
            if geometry.intersects(shapes[zone.id]):
                return zone
        return None

    def _zone_hit_point(self, x: float, y: float) -> KeepOut | None:
        """The first zone (not grown) the point (x, y) is in or on. A Point is built only for a zone whose
        bounding box holds it (GEOS answers False outside the box too): building and testing one after
        idling took some 60 of check_trajectory's 190 us (one position, in process, 2026-11-29)."""
        for zone, (x0, y0, x1, y1) in self._zone_boxes:
            if x0 <= x <= x1 and y0 <= y <= y1 and Point(x, y).intersects(self.zone_shapes[zone.id]):
                return zone
        return None

    def zone_at(self, x: float, y: float) -> KeepOut | None:
        """The keep-out zone the base's centre stands in (not grown), for the monitors."""
        return self._zone_hit_point(x, y)

    def check_spot(self, pose: Pose2D) -> None:
        """Where a plan sends the base: on the map, its footprint out of keep-out zones and as far
        from walls and furniture as the route there must keep (the robot's tracking tolerance). The
        way there is planned later and checked goal by goal (check_route)."""
        if not _finite(pose.x, pose.y, pose.yaw):
            raise Vetoed("the goal is not a finite pose", Rule.MAP)
        if self.world.room_of(pose.x, pose.y) is None:
            raise Vetoed(
                f"the goal ({_fmt(pose.x)}, {_fmt(pose.y)}) is outside every room of the map",
                Rule.MAP,
                x=pose.x,
                y=pose.y,
            )
        if zone := self._zone_hit(Point(pose.x, pose.y)):
            raise Vetoed(
                f"at the goal ({_fmt(pose.x)}, {_fmt(pose.y)}) the base's footprint would be in keep-out zone "
                f"'{zone.name}'{_why(zone)}",
                Rule.KEEP_OUT,
                x=pose.x,
                y=pose.y,
            )
        size = self.base_size
        there = footprint(pose.x, pose.y, pose.yaw, size.x, size.y)
        name, distance = nearest(there, self.obstacles)
        if distance < TRACKING_TOLERANCE:
            where = "in" if distance <= 0.0 else f"{distance * 100:.0f} cm from"
            raise Vetoed(
                f"at the goal ({_fmt(pose.x)}, {_fmt(pose.y)}) the base would stand {where} {name} "
                f"(it keeps {TRACKING_TOLERANCE * 100:g} cm)",
                Rule.OBSTACLE,
                x=pose.x,
                y=pose.y,
            )

    def check_route(self, start: Pose2D | None, path: list[Pose2D], goal: Pose2D, reach: float = 0.0) -> None:
        """The route the base will drive (see worldmodel.drive_route): on the map, its footprint
        clear of every keep-out zone at every point and along every leg, and touching no wall or
        furniture anywhere on the way as the sim drives it (services/footprint.py). `reach` is how
        far the hand sticks out from the base's centre; beyond the footprint it widens what must
        stay clear of keep-out zones."""
        zones = self.zones
        if reach > self.radius:
            zones = {zone_id: shape.buffer(reach) for zone_id, shape in self.zone_shapes.items()}
        if start is None:
            raise Vetoed(
                "the robot's pose is unknown (no recent odometry), so no route can be checked", Rule.POSE_KNOWN
            )
        for pose in (*path, goal):
            if not _finite(pose.x, pose.y, pose.yaw):
                raise Vetoed("a waypoint is not a finite pose", Rule.MAP)
        points = [(start.x, start.y), *drive_route(start, path, goal)]
        for k, (x, y) in enumerate(points[1:], start=1):
            where = "the goal" if k == len(points) - 1 else "the route point"
            if self.world.room_of(x, y) is None:
                raise Vetoed(f"{where} ({_fmt(x)}, {_fmt(y)}) is outside every room of the map", Rule.MAP, x=x, y=y)
            if zone := self._zone_hit(Point(x, y), shapes=zones):
                raise Vetoed(
                    f"at {where} ({_fmt(x)}, {_fmt(y)}) the {_what(reach, self.radius)} would be in keep-out zone "
                    f"'{zone.name}'{_why(zone)}",
                    Rule.KEEP_OUT,
                    x=x,
                    y=y,
                )
        for a, b in itertools.pairwise(points):
            if not self._floor.covers(LineString([a, b])):
                raise Vetoed(
                    f"the path from ({_fmt(a[0])}, {_fmt(a[1])}) to ({_fmt(b[0])}, {_fmt(b[1])}) leaves the map",
                    Rule.MAP,
                    x=b[0],
                    y=b[1],
                )
            if zone := self._zone_hit(LineString([a, b]), shapes=zones):
                raise Vetoed(
                    f"path from ({_fmt(a[0])}, {_fmt(a[1])}) to ({_fmt(b[0])}, {_fmt(b[1])}) "
                    f"takes the {_what(reach, self.radius)} into keep-out zone '{zone.name}'{_why(zone)}",
                    Rule.KEEP_OUT,
                    x=b[0],
                    y=b[1],
                )
        size = self.base_size
        # The sim keeps the footprint within its tracking tolerance of the route's sweeps; a hand
        # sticking out beyond the footprint sweeps further, as far as it reaches.
        hand = max(0.0, reach - min(size.x, size.y) / 2) if reach > self.radius else 0.0
        sweeps = route_sweeps(start, points[1:], goal.yaw, size.x, size.y)
        if problem := clearance_problem(start, sweeps, self.obstacles, TRACKING_TOLERANCE + hand, size.x, size.y):
            sweep, why = problem
            with_hand = f" with the hand {reach:.2f} m from the base's centre (stow the arm to drive)" if hand else ""
            raise Vetoed(f"{why}{with_hand}; plan a path around it", Rule.OBSTACLE, x=sweep.x, y=sweep.y)

    def check_speed(self, speed: float) -> None:
        """A speed a plan asked for: over the limit is refused, never silently lowered."""
        if not _finite(speed) or speed <= 0.0 or speed > self.max_linear + STILL:
            raise Vetoed(
                f"a speed of {speed:g} m/s exceeds the base's limit of {self.max_linear:g} m/s; "
                f"ask for {self.max_linear:g} m/s or less",
                Rule.BASE_SPEED,
                speed_mps=speed,
                limit_mps=self.max_linear,
            )

    def check_turn_rate(self, rate: float) -> None:
        if not _finite(rate) or rate <= 0.0 or rate > self.max_angular + STILL:
            raise Vetoed(
                f"a turn rate of {rate:g} rad/s exceeds the base's limit of {self.max_angular:g} rad/s",
                Rule.BASE_SPEED,
                turn_rps=rate,
                limit_rps=self.max_angular,
            )

    def check_navigation(
        self, goal: NavigateToPoseGoal, start: Pose2D | None, reach: float = 0.0
    ) -> Verdict[NavigateToPoseGoal]:
        """The route (widened when the hand sticks out by `reach`), and the speed and turn rate
        asked for: over a limit refused, none given filled in with the limit."""
        self.check_route(start, goal.path, goal.pose, reach)
        if goal.max_speed is not None:
            self.check_speed(goal.max_speed)
        if goal.max_turn_rate is not None:
            self.check_turn_rate(goal.max_turn_rate)
        goal = msgspec.structs.replace(
            goal,
            max_speed=self.max_linear if goal.max_speed is None else goal.max_speed,
            max_turn_rate=self.max_angular if goal.max_turn_rate is None else goal.max_turn_rate,
            start=start,
        )
        values = {
            "x": goal.pose.x,
            "y": goal.pose.y,
            "speed_mps": goal.max_speed or 0.0,
            "limit_mps": self.max_linear,
            "turn_rps": goal.max_turn_rate or 0.0,
            "limit_rps": self.max_angular,
            "reach_m": reach,
        }
        return Verdict(goal, (*ROUTE_CHECKS, Rule.BASE_SPEED), values)

    # cmd_vel

    def _check_twist_finite(self, twist: Twist) -> None:
        if not _finite(twist.linear_x, twist.angular_z):
            raise Vetoed("cmd_vel is not finite", Rule.BASE_SPEED)

    def check_horizon(self, twist: Twist, pose: Pose2D | None, reach: float = 0.0) -> None:
        """Holding `twist` for the horizon must keep the base on the map and out of keep-out zones
        along the arc it drives (turning, it curves off the line ahead). `reach` is how far the hand
        sticks out from the base's centre: beyond the footprint, zones are kept that far from the
        centre instead, as on a route (check_route), and a turn in place swings the hand round too."""
        hand = reach > self.radius
        turning = abs(twist.angular_z) > STILL
        # A turn in place keeps the base's footprint where it is; without a pose it is let through,
        # as it always was, the hand's swing with it (nothing to check it against).
        if abs(twist.linear_x) <= STILL and not (hand and turning and pose is not None):
            return
        if pose is None:
            raise Vetoed("the robot's pose is unknown (no recent odometry): only a stop is allowed", Rule.POSE_KNOWN)
        horizon = self.policy.base.cmd_vel_horizon
        linear = twist.linear_x if abs(twist.linear_x) > STILL else 0.0
        path = LineString(_held_path(pose, linear, twist.angular_z if turning else 0.0, horizon))
        x, y = path.coords[-1]
        values = {"x": x, "y": y, "speed_mps": twist.linear_x, "horizon_s": horizon}
        what = f"cmd_vel at {twist.linear_x:g} m/s"
        if turning:
            values["turn_rps"] = twist.angular_z
            what += f", {twist.angular_z:g} rad/s"
        if not self._floor.covers(path):
            raise Vetoed(f"{what} would leave the map within {horizon:g} s", Rule.CMD_VEL_HORIZON, **values)
        if zone := self._zone_hit(path):
            raise Vetoed(
                f"{what} would enter keep-out zone '{zone.name}' within {horizon:g} s{_why(zone)}",
                Rule.CMD_VEL_HORIZON,
                **values,
            )
        if hand and (zone := self._zone_within(path, reach)):
            raise Vetoed(
                f"{what} would take the {_what(reach, self.radius)} into keep-out zone '{zone.name}' within "
                f"{horizon:g} s{_why(zone)}; stow the arm first",
                Rule.CMD_VEL_HORIZON,
                **values,
                reach_m=reach,
            )

    def _zone_within(self, geometry: BaseGeometry, distance: float) -> KeepOut | None:
        """The first keep-out zone within `distance` of `geometry` (the zones grown by it, without
        growing them: a hand's reach changes with every joint state)."""
        for zone in self.limits.keep_out:
            if geometry.distance(self.zone_shapes[zone.id]) <= distance:
                return zone
        return None

    def check_cmd_vel(
        self, twist: Twist, pose: Pose2D | None, scale: float = 1.0, reach: float = 0.0
    ) -> Verdict[Twist]:
        """A cmd_vel from a program (plan, agent): a value over a limit is refused, not clamped.
        Near people (`scale` < 1) the robot itself keeps to the lower speed; the verdict says so.
        `reach`: how far the hand sticks out from the base's centre (see check_horizon)."""
        self._check_twist_finite(twist)
        if abs(twist.linear_x) > self.max_linear + STILL:
            raise Vetoed(
                f"linear_x {twist.linear_x:g} m/s exceeds the limit of {self.max_linear:g} m/s",
                Rule.BASE_SPEED,
                speed_mps=twist.linear_x,
                limit_mps=self.max_linear,
            )
        if abs(twist.angular_z) > self.max_angular + STILL:
            raise Vetoed(
                f"angular_z {twist.angular_z:g} rad/s exceeds the limit of {self.max_angular:g} rad/s",
                Rule.BASE_SPEED,
                turn_rps=twist.angular_z,
                limit_rps=self.max_angular,
            )
        self.check_horizon(twist, pose, reach)
        values = {"speed_mps": twist.linear_x, "turn_rps": twist.angular_z, "scale": scale}
        note = ""
        if scale < 1.0:
            note = (
                f"a person is near: the robot moves at most {self.max_linear * scale:.2f} m/s and "
                f"{self.max_angular * scale:.2f} rad/s for now"
            )
        return Verdict(twist, (Rule.BASE_SPEED, Rule.CMD_VEL_HORIZON, Rule.HUMAN_SEPARATION), values, note=note)

    def check_teleop(
        self, twist: Twist, pose: Pose2D | None, previous: Twist, dt: float, scale: float = 1.0, reach: float = 0.0
    ) -> Verdict[Twist]:
        """A cmd_vel from a person: clamped to the speed limits (times the separation `scale`) and
        to the acceleration limits from `previous` (what was last sent, `dt` seconds ago); the
        clamping is reported. Slowing down is never limited. Vetoed only when even the clamped
        value would leave the map or reach a keep-out zone within the horizon, the hand held out
        `reach` from the base's centre included (see check_horizon)."""
        self._check_twist_finite(twist)
        base = self.policy.base
        linear, angular = twist.linear_x, twist.angular_z
        clamps: list[tuple[Rule, str]] = []
        v_max, w_max = self.max_linear * scale, self.max_angular * scale
        if abs(linear) > v_max + STILL or abs(angular) > w_max + STILL:
            linear, angular = max(-v_max, min(v_max, linear)), max(-w_max, min(w_max, angular))
            rule = Rule.HUMAN_SEPARATION if scale < 1.0 else Rule.BASE_SPEED
            clamps.append((rule, f"speed limit {v_max:.2f} m/s, {w_max:.2f} rad/s"))
        dt = max(0.0, dt)
        linear, limited_v = _ramp(previous.linear_x, linear, base.max_linear_acceleration * dt)
        angular, limited_w = _ramp(previous.angular_z, angular, base.max_angular_acceleration * dt)
        if limited_v or limited_w:
            clamps.append(
                (
                    Rule.BASE_ACCELERATION,
                    f"acceleration limit {base.max_linear_acceleration:g} m/s^2, "
                    f"{base.max_angular_acceleration:g} rad/s^2",
                )
            )
        sent = msgspec.structs.replace(twist, linear_x=linear, angular_z=angular)
        self.check_horizon(sent, pose, reach)
        values = {
            "requested_mps": twist.linear_x,
            "requested_rps": twist.angular_z,
            "speed_mps": linear,
            "turn_rps": angular,
            "scale": scale,
        }
        checks = (Rule.BASE_SPEED, Rule.HUMAN_SEPARATION, Rule.BASE_ACCELERATION, Rule.CMD_VEL_HORIZON)
        if not clamps:
            return Verdict(sent, checks, values)
        note = (
            f"clamped from ({twist.linear_x:.2f} m/s, {twist.angular_z:.2f} rad/s) to "
            f"({linear:.2f} m/s, {angular:.2f} rad/s): " + "; ".join(why for _, why in clamps)
        )
        return Verdict(sent, checks, values, clamped_by=clamps[0][0], note=note)

    # Arm

    def check_trajectory(
        self,
        goal: FollowJointTrajectoryGoal,
        current: dict[str, float] | None,
        base: Pose2D | None,
        base_moving: bool = False,
    ) -> Verdict[FollowJointTrajectoryGoal]:
        """Every point inside the joint limits; no joint faster than its limit on any segment, the
        first one from where the arm is now; the end effector, along the whole path, inside the
        workspace box and out of keep-out zones, checked from where the base stands (so the base
        must stand still)."""
        if base_moving:
            raise Vetoed("the base is moving: the arm moves only while the base stands still", Rule.BASE_STILL)
        unknown = [n for n in goal.joint_names if n not in self.joint_limits]
        if unknown:
            raise Vetoed(
                f"unknown joints {unknown}; the arm's joints are {sorted(self.joint_limits)}", Rule.JOINT_LIMITS
            )
        if len(set(goal.joint_names)) != len(goal.joint_names):
            raise Vetoed("a joint is named twice", Rule.JOINT_LIMITS)
        if current is None or not all(n in current for n in self.arm.joint_names):
            raise Vetoed("the arm's joint positions are unknown (no recent joint states)", Rule.POSE_KNOWN)
        if base is None:
            raise Vetoed("the robot's pose is unknown (no recent odometry)", Rule.POSE_KNOWN)
        index = [self.arm.joint_names.index(n) for n in goal.joint_names]
        full = [float(current[n]) for n in self.arm.joint_names]
        if not all(map(math.isfinite, full)):
            broken = [n for n, q in zip(self.arm.joint_names, full, strict=True) if not math.isfinite(q)]
            raise Vetoed(f"the arm's joint states give no position for {', '.join(broken)}", Rule.POSE_KNOWN)
        start = [full[i] for i in index]
        limits = [self.joint_limits[name] for name in goal.joint_names]
        # All points at once; point by point only when that finds something, to name the first.
        passed = _joint_checks_pass(goal, start, limits) if len(goal.points) > FEW_POINTS else None
        path: list[list[float]]
        if passed is None:
            fastest, path = self._joint_checks(goal, start, limits, full, index)
        else:
            fastest, rows = passed
            table = np.tile(full, (len(rows) + 1, 1))
            table[1:, index] = rows
            path = table.tolist()
        reach = self._check_arm_path(path, base)
        values = {"points": float(len(goal.points)), "fastest_rps": fastest, **reach}
        checks = (
            Rule.BASE_STILL,
            Rule.POSE_KNOWN,
            Rule.JOINT_LIMITS,
            Rule.JOINT_SPEED,
            Rule.WORKSPACE,
            Rule.ARM_KEEP_OUT,
        )
        return Verdict(goal, checks, values)

    def _joint_checks(
        self,
        goal: FollowJointTrajectoryGoal,
        start: list[float],
        limits: list[JointLimit],
        full: list[float],
        index: list[int],
    ) -> tuple[float, list[list[float]]]:
        """The joint checks point by point, raising at the first point and joint that fails: the
        fastest joint speed and the joint path (every arm joint, from `full`). In plain floats (a numpy
        scalar's arithmetic costs several times a float's): the same IEEE doubles."""
        previous, previous_time = start, 0.0
        fastest = 0.0
        path = [full]
        for i, point in enumerate(goal.points):
            if len(point.positions) != len(goal.joint_names):
                raise Vetoed(
                    f"point {i}: {len(point.positions)} positions for {len(goal.joint_names)} joints", Rule.JOINT_LIMITS
                )
            positions = [float(q) for q in point.positions]
            if not all(map(math.isfinite, positions)) or not math.isfinite(point.time_from_start):
                raise Vetoed(f"point {i}: a position is not finite", Rule.JOINT_LIMITS)
            for name, q, lim in zip(goal.joint_names, positions, limits, strict=True):
                lower, upper = lim.lower + JOINT_LIMIT_MARGIN, lim.upper - JOINT_LIMIT_MARGIN
                if not lower <= q <= upper:
                    raise Vetoed(
                        f"point {i}: {name} = {q:.4f} rad is outside its limits [{lower:.4f}, {upper:.4f}] rad "
                        f"(the joint's range less {JOINT_LIMIT_MARGIN:g} rad)",
                        Rule.JOINT_LIMITS,
                        position_rad=q,
                        lower_rad=lower,
                        upper_rad=upper,
                    )
            dt = point.time_from_start - previous_time
            if dt < 0 or (dt == 0 and i > 0):
                # Only the first point may be at time zero (where the arm already is): points at
                # equal times would be jumps, however small each one.
                raise Vetoed(
                    f"point {i}: time_from_start {point.time_from_start:g} s does not increase "
                    f"from {previous_time:g} s",
                    Rule.JOINT_SPEED,
                )
            for name, q0, q1, lim in zip(goal.joint_names, previous, positions, limits, strict=True):
                if dt == 0:
                    # A point at the start time must be where the arm already is.
                    if abs(q1 - q0) > START_TOLERANCE:
                        raise Vetoed(
                            f"point {i}: {name} would jump {abs(q1 - q0):.3f} rad at once",
                            Rule.JOINT_SPEED,
                            jump_rad=abs(q1 - q0),
                        )
                    continue
                speed = abs(q1 - q0) / dt
                fastest = max(fastest, speed)
                limit = lim.velocity
                if speed > limit + STILL:
                    raise Vetoed(
                        f"point {i}: {name} would move at {speed:.3f} rad/s, over its limit of {limit:.3f} rad/s; "
                        f"slow the trajectory down",
                        Rule.JOINT_SPEED,
                        speed_rps=speed,
                        limit_rps=limit,
                    )
            row = path[-1].copy()
            for j, q in zip(index, positions, strict=True):
                row[j] = q
            path.append(row)
            previous, previous_time = positions, point.time_from_start
        return fastest, path

    def _check_arm_path(self, path: list[list[float]], base: Pose2D) -> dict[str, float]:
        """Forward kinematics along the joint path, interpolated finely; raises at the first point out.
        Past a few points, the workspace and the zones are checked for every point at once, and point
        by point only when that finds one out, to name the first."""
        segments = list(itertools.pairwise(path))
        steps = [max(1, math.ceil(_largest_move(q0, q1) / INTERPOLATION_STEP)) for q0, q1 in segments]
        if sum(steps) <= FEW_ARM_POINTS:
            return self._arm_path_point_by_point(segments, steps, base)
        # The same configurations, in order, as q0 + (q1 - q0) * k / n for k = 1 .. n on each segment.
        rows = np.array(path, dtype=float)
        configurations = np.concatenate(
            [
                q0 + (q1 - q0) * np.arange(1, n + 1)[:, np.newaxis] / n
                for (q0, q1), n in zip(itertools.pairwise(rows), steps, strict=True)
            ]
        )
        hand = np.array([self.arm.grasp_xyz(q) for q in configurations])
        x, y, z = hand[:, 0] + self.mount.x, hand[:, 1] + self.mount.y, hand[:, 2] + self.mount.z
        low, high = self.policy.workspace.min, self.policy.workspace.max
        inside = (low.x <= x) & (x <= high.x) & (low.y <= y) & (y <= high.y) & (low.z <= z) & (z <= high.z)
        c, s = math.cos(base.yaw), math.sin(base.yaw)  # base_to_map, for every point
        world = shapely.points(base.x + c * x - s * y, base.y + s * x + c * y)
        # The points first, as Point(...).intersects(zone) has them: shapely.intersects_xy would prepare
        # the shared zone in place, and GEOS builds a prepared geometry's index lazily, unlocked, while
        # safety checks from several threads (libgeos/geos#825).
        if not inside.all() or any(
            shapely.intersects(world, self.zone_shapes[zone.id]).any() for zone in self.limits.keep_out
        ):
            self._arm_path_point_by_point(segments, steps, base)
            # Not reached while the two agree (the same points, the same comparisons): refused if not.
            raise Vetoed("the end effector would leave the workspace or reach into a keep-out zone", Rule.WORKSPACE)
        return {"lowest_m": float(z.min()), "farthest_m": max(0.0, float(x.max()))}

    def _arm_path_point_by_point(
        self, segments: list[tuple[list[float], list[float]]], steps: list[int], base: Pose2D
    ) -> dict[str, float]:
        """`_check_arm_path` one point at a time: raises for the first whose end effector leaves the
        workspace or reaches into a keep-out zone. In plain floats, as numpy's q0 + (q1 - q0) * k / n
        would work them out element by element."""
        lowest, farthest = math.inf, 0.0
        for (q0, q1), n in zip(segments, steps, strict=True):
            for k in range(1, n + 1):
                px, py, pz = self.arm.grasp_xyz([a + (b - a) * k / n for a, b in zip(q0, q1, strict=True)])
                x, y, z = px + self.mount.x, py + self.mount.y, pz + self.mount.z
                self.check_in_workspace(x, y, z, "the end effector")
                lowest, farthest = min(lowest, z), max(farthest, x)
                world = base_to_map(base, x, y)
                if zone := self._zone_hit_point(*world):
                    raise Vetoed(
                        f"the end effector would reach into keep-out zone '{zone.name}' at "
                        f"({_fmt(world[0])}, {_fmt(world[1])}){_why(zone)}",
                        Rule.ARM_KEEP_OUT,
                        x=world[0],
                        y=world[1],
                    )
        if not math.isfinite(lowest):
            return {}
        return {"lowest_m": lowest, "farthest_m": farthest}

    def check_in_workspace(self, x: float, y: float, z: float, what: str) -> None:
        """A point in the base frame inside the workspace box."""
        box = self.policy.workspace
        for axis, value, low, high in (
            ("x", x, box.min.x, box.max.x),
            ("y", y, box.min.y, box.max.y),
            ("z", z, box.min.z, box.max.z),
        ):
            if not low <= value <= high:
                raise Vetoed(
                    f"{what} would be at {axis} = {value:.3f} m in the base frame, outside the workspace "
                    f"[{low:g}, {high:g}] m",
                    Rule.WORKSPACE,
                    **{f"{axis}_m": value, "low_m": low, "high_m": high},
                )

    def check_reach(self, approach: Pose2D, position: Vec3, what: str) -> None:
        """The end effector can go to `position` (map frame) from `approach` without leaving the
        workspace or reaching into a keep-out zone."""
        self.check_in_workspace(*map_to_base(approach, position.x, position.y), position.z, what)
        if zone := self._zone_hit_point(position.x, position.y):
            raise Vetoed(
                f"{what} at ({_fmt(position.x)}, {_fmt(position.y)}) is inside keep-out zone '{zone.name}'{_why(zone)}",
                Rule.ARM_KEEP_OUT,
                x=position.x,
                y=position.y,
            )

    def check_gripper(self, goal: GripperCommandGoal) -> Verdict[GripperCommandGoal]:
        limit = self.policy.gripper.max_force
        if goal.max_effort > limit + STILL:
            raise Vetoed(
                f"a gripper force of {goal.max_effort:g} N exceeds the limit of {limit:g} N",
                Rule.GRIPPER_FORCE,
                force_n=goal.max_effort,
                limit_n=limit,
            )
        if goal.payload_limit is not None and goal.payload_limit > self.payload + STILL:
            raise Vetoed(
                f"a payload limit of {goal.payload_limit:g} kg exceeds the arm's payload of {self.payload:g} kg",
                Rule.PAYLOAD,
                mass_kg=goal.payload_limit,
                payload_kg=self.payload,
            )
        # Whatever the command names, the robot lets anything heavier than this slip.
        goal = msgspec.structs.replace(
            goal, payload_limit=self.payload if goal.payload_limit is None else goal.payload_limit
        )
        values = {"force_n": goal.max_effort, "limit_n": limit, "payload_kg": self.payload}
        if goal.object_id is None:
            return Verdict(goal, (Rule.GRIPPER_FORCE, Rule.PAYLOAD), values)
        values["mass_kg"] = self.check_payload(goal.object_id)
        return Verdict(goal, (Rule.GRIPPER_FORCE, Rule.PAYLOAD), values)

    def check_payload(self, object_id: str) -> float:
        """Masses come from the world file, never from the command. Returns the mass."""
        obj = self.world.objects.get(object_id)
        if obj is None:
            raise Vetoed(f"unknown object '{object_id}': its mass cannot be checked", Rule.PAYLOAD)
        if obj.mass > self.payload:
            raise Vetoed(
                f"'{obj.name}' weighs {obj.mass:g} kg, over the arm's payload of {self.payload:g} kg",
                Rule.PAYLOAD,
                mass_kg=obj.mass,
                payload_kg=self.payload,
            )
        return obj.mass

    # Whole plans, before the first motion

    def check_plan(self, plan: GroundedPlan, start: Pose2D | None) -> list[str]:
        """Check every way the plan can go, on_failure alternatives included, before anything moves.

        Each step is checked from every state (base pose, object held) it can start from: the plan's
        own steps in order, each alternative from every state a failure of the steps it covers can
        leave (where each started, and for a pick also holding its object: a lift or stow that fails
        after the grasp leaves it in the hand), and the steps after it from where it ends. Returns
        what was checked; raises Vetoed naming the step by its label ("step 2.1 (pick): ...").
        """
        labels = step_labels(plan)
        self._check_structure(plan)
        checks: dict[str, None] = {}
        # before[i]: the states step i can start from; grasped[i]: those a pick at step i leaves
        # when it grasped its object and then failed.
        before: list[dict[_PlanState, None]] = [{} for _ in range(len(plan.steps) + 1)]
        grasped: list[dict[_PlanState, None]] = [{} for _ in plan.steps]
        before[0][_PlanState.at(start, None)] = None
        # States a failure inside each alternative can leave: an enclosing one may take over there.
        met: dict[int, dict[_PlanState, None]] = {}
        innermost_first = sorted(range(len(plan.fallbacks)), key=lambda k: _span(plan.fallbacks[k]))
        for i, step in enumerate(plan.steps):
            for state in before[i]:
                after = self._check_step(step, labels[i], state, checks)
                before[i + 1][after] = None
                if isinstance(step, PickStep):
                    grasped[i][_grasped(after, labels[i])] = None
            for k in (k for k in innermost_first if plan.fallbacks[k].last == i):
                fallback = plan.fallbacks[k]
                covered = range(fallback.first, fallback.last + 1)
                # The states reached anyway first: of two equal states, a refusal names the first.
                starts: dict[_PlanState, None] = {}
                for j in covered:
                    starts.update(before[j])
                for inner, states in met.items():
                    if _within(plan.fallbacks[inner], fallback):
                        starts.update(states)
                for j in covered:
                    starts.update(grasped[j])
                met[k] = {}
                picks: dict[_PlanState, None] = {}
                alternative_labels = fallback_labels(fallback, labels)
                for state in starts:
                    for step_, label in zip(fallback.steps, alternative_labels, strict=True):
                        met[k][state] = None
                        state = self._check_step(step_, label, state, checks)
                        if isinstance(step_, PickStep):
                            picks[_grasped(state, label)] = None
                    before[i + 1][state] = None
                met[k].update(picks)
        return list(checks)

    def _check_structure(self, plan: GroundedPlan) -> None:
        if plan.labels and len(plan.labels) != len(plan.steps):
            raise Vetoed(f"the plan has {len(plan.steps)} steps but {len(plan.labels)} labels", Rule.PLAN)
        for fallback in plan.fallbacks:
            if not 0 <= fallback.first <= fallback.last < len(plan.steps):
                raise Vetoed(
                    f"an on_failure covers steps {fallback.first + 1}..{fallback.last + 1} "
                    f"of a plan of {len(plan.steps)} steps",
                    Rule.PLAN,
                )
            if not fallback.steps or (fallback.labels and len(fallback.labels) != len(fallback.steps)):
                raise Vetoed(
                    f"the on_failure of steps {fallback.first + 1}..{fallback.last + 1} is malformed", Rule.PLAN
                )

    def _check_step(self, step: GroundedStep, label: str, state: _PlanState, checks: dict[str, None]) -> _PlanState:
        """The state after `step` from `state`, or Vetoed naming the step. Every kind of step has its
        own case: a new kind is a type error here until its checks are written."""
        try:
            if step.spec.moves_base and state.pose is None:
                raise Vetoed(
                    "the robot's pose is unknown (no recent odometry), so it cannot be sent anywhere", Rule.POSE_KNOWN
                )
            match step:
                case NavigateStep():
                    self.check_spot(step.goal)
                    if step.max_speed is not None:
                        self.check_speed(step.max_speed)
                    checks[f"step {label}: {step.target} is on the map, clear of keep-out zones and obstacles"] = None
                    return _PlanState.at(step.goal, state.holding, state.grasped_by)
                case PickStep():
                    self.check_payload(step.object_id)
                    self.check_spot(step.approach)
                    self.check_reach(step.approach, step.position, step.object_name)
                    checks[f"step {label}: {step.object_name} is within payload and reach"] = None
                    return _PlanState.at(step.approach, step.object_id)
                case PlaceStep():
                    self.check_spot(step.approach)
                    self.check_reach(step.approach, step.position, f"the spot on the {step.surface_name}")
                    checks[f"step {label}: the spot on the {step.surface_name} is within reach"] = None
                    return _PlanState.at(step.approach, None)
                case GripperStep():
                    return self._check_gripper_step(step, label, state, checks)
                case DetectStep() | SayStep() | WaitStep() | StopStep():
                    # Looking, speaking, waiting and stopping ask nothing of the map, the payload or reach.
                    return state
                case _:
                    assert_never(step)
        except Vetoed as exc:
            raise Vetoed(f"step {label} ({step_kind(step)}): {exc}", exc.rule, **exc.values) from None

    def _check_gripper_step(
        self, step: GripperStep, label: str, state: _PlanState, checks: dict[str, None]
    ) -> _PlanState:
        held = self.world.objects.get(state.holding) if state.holding else None
        name = held.name if held else state.holding
        if step.open:
            if name is not None:
                # Outside place, the arm is stowed over the base: opening drops the object.
                how = (
                    f" (held if the pick at step {state.grasped_by} grasped it and then failed)"
                    if state.grasped_by
                    else ""
                )
                raise Vetoed(
                    f"opening the gripper would drop {name} from the stowed arm{how}; use place to put it down",
                    Rule.GRIPPER_DROP,
                )
            checks[f"step {label}: the gripper opens with nothing in it"] = None
            return state
        # The arm is stowed after every pick and place, so a closing gripper can only meet what it
        # already holds (checked against the payload when it was picked).
        checks[f"step {label}: the gripper closes on {name or 'nothing'}"] = None
        return state


@dataclass(frozen=True)
class _PlanState:
    """Where the base is predicted to stand and what the gripper holds, at a point of a plan."""

    position: tuple[float, float, float] | None
    holding: str | None
    # The label of the pick whose failure after grasping left `holding` in the hand, for a refusal
    # to say why the hand would hold it; not part of the state (the same state, however reached).
    grasped_by: str | None = field(default=None, compare=False)

    @staticmethod
    def at(pose: Pose2D | None, holding: str | None, grasped_by: str | None = None) -> _PlanState:
        if pose is None:
            return _PlanState(None, holding, grasped_by)
        return _PlanState((round(pose.x, 3), round(pose.y, 3), round(pose.yaw, 3)), holding, grasped_by)

    @property
    def pose(self) -> Pose2D | None:
        return None if self.position is None else Pose2D(x=self.position[0], y=self.position[1], yaw=self.position[2])


def _grasped(picked: _PlanState, label: str) -> _PlanState:
    """Where a pick that grasped its object and then failed (lifting, stowing) leaves the robot:
    as one that succeeded (at its approach pose, holding the object), named as such."""
    return _PlanState(picked.position, picked.holding, label)


def _span(fallback: Fallback) -> tuple[int, int]:
    return fallback.last - fallback.first, -fallback.first


def _within(inner: Fallback, outer: Fallback) -> bool:
    return outer.first <= inner.first and inner.last <= outer.last and inner is not outer


def _ramp(previous: float, wanted: float, step: float) -> tuple[float, bool]:
    """`wanted`, but at most `step` faster than `previous`; slowing down (towards zero) is never
    limited, and reversing brakes to zero freely before speeding up the other way."""
    if previous * wanted < 0:
        previous = 0.0
    if abs(wanted) <= abs(previous) + step + STILL:
        return wanted, False
    return math.copysign(abs(previous) + step, wanted), True


def load_safety_policy(world: World, policy: Path | None, world_label: str, data: bytes | None = None) -> SafetyPolicy:
    """The checks safety runs in `world` under the policy file `policy` (None: the default policy).
    `data` is the policy file's content when it comes from somewhere else (a recording); `policy`
    then only names it. Raises PolicyError naming what is wrong."""
    try:
        arm = ArmModel(world.robot.arm_urdf)
    except (OSError, ValueError, RuntimeError) as exc:
        raise PolicyError(f"{world_label}: robot.arm_urdf {world.robot.arm_urdf!r} cannot be loaded: {exc}") from None
    if data is None:
        limits = load_policy(policy, world.robot, arm, world.keep_out, world.rooms)
    else:
        limits = parse_policy(data, policy or Path("policy.toml"), world.robot, arm, world.keep_out, world.rooms)
    return SafetyPolicy(WorldModel(world), limits, arm)
