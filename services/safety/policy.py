"""The checks: every command and every plan against keep-out zones, speed, joint and payload limits."""

from __future__ import annotations

import itertools
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from shapely.geometry import LineString, Point
from shapely.geometry.base import BaseGeometry

from schemas.common import Pose2D
from schemas.plan import (
    Fallback,
    GripperStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    fallback_labels,
    step_kind,
    step_labels,
)
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, Twist
from schemas.world import KeepOut
from services.safety.config import SafetyConfig
from services.safety.errors import Vetoed
from services.worldmodel import WorldModel, drive_route

# Joint positions may not come closer than this to the hard limits.
JOINT_LIMIT_MARGIN = 0.01
# A trajectory's first point, at time zero, may differ this much from the measured position.
START_TOLERANCE = 0.05


@dataclass(frozen=True)
class JointLimit:
    lower: float
    upper: float
    velocity: float


def joint_limits_from_urdf(path: Path) -> dict[str, JointLimit]:
    """Revolute and prismatic joint limits, read from the robot's own URDF."""
    limits: dict[str, JointLimit] = {}
    for joint in ET.parse(path).getroot().iter("joint"):
        limit = joint.find("limit")
        if joint.get("type") in ("revolute", "prismatic") and limit is not None:
            limits[joint.get("name", "")] = JointLimit(
                float(limit.get("lower", "0")), float(limit.get("upper", "0")), float(limit.get("velocity", "0"))
            )
    return limits


def _fmt(x: float) -> str:
    return f"{x:.2f}"


def _why(zone: KeepOut) -> str:
    return f": {zone.reason}" if zone.reason else ""


class SafetyPolicy:
    """Pure checks. Each `check_*` returns the command to forward, or raises Vetoed naming why."""

    def __init__(self, world: WorldModel, config: SafetyConfig, joint_limits: dict[str, JointLimit]) -> None:
        self.world = world
        self.config = config
        self.joint_limits = joint_limits
        robot = world.world.robot
        self.max_linear = min(config.max_linear_speed or robot.max_linear_speed, robot.max_linear_speed)
        self.max_angular = min(config.max_angular_speed or robot.max_angular_speed, robot.max_angular_speed)
        # Zones grown by the base's half-diagonal: the base centre must stay that far out.
        radius = math.hypot(robot.base_size.x, robot.base_size.y) / 2
        self.zones = {zone_id: shape.buffer(radius) for zone_id, shape in world.keep_out_shapes.items()}

    # Navigation

    def _zone_hit(self, geometry: BaseGeometry) -> KeepOut | None:
        for zone in self.world.world.keep_out:
            if geometry.intersects(self.zones[zone.id]):
                return zone
        return None

    def check_route(self, start: Pose2D | None, path: list[Pose2D], goal: Pose2D) -> None:
        """The route the base will drive (see worldmodel.drive_route): on the map, its footprint
        clear of every keep-out zone at every point and along every leg."""
        if start is None:
            raise Vetoed("the robot's pose is unknown (no recent odometry), so no route can be checked")
        for pose in (*path, goal):
            if not all(math.isfinite(v) for v in (pose.x, pose.y, pose.yaw)):
                raise Vetoed("a waypoint is not a finite pose")
        points = [(start.x, start.y), *drive_route(start, path, goal)]
        for x, y in points[1:]:
            if self.world.room_of(x, y) is None:
                raise Vetoed(f"({_fmt(x)}, {_fmt(y)}) is outside every room of the map")
            if zone := self._zone_hit(Point(x, y)):
                raise Vetoed(f"goal ({_fmt(x)}, {_fmt(y)}) is inside keep-out zone '{zone.name}'{_why(zone)}")
        for a, b in itertools.pairwise(points):
            if zone := self._zone_hit(LineString([a, b])):
                raise Vetoed(
                    f"path from ({_fmt(a[0])}, {_fmt(a[1])}) to ({_fmt(b[0])}, {_fmt(b[1])}) "
                    f"crosses keep-out zone '{zone.name}'{_why(zone)}"
                )

    def check_navigation(self, goal: NavigateToPoseGoal, start: Pose2D | None) -> NavigateToPoseGoal:
        self.check_route(start, goal.path, goal.pose)
        if goal.max_speed > self.max_linear:
            # Clamp rather than refuse: a slower arrival is always safe.
            return NavigateToPoseGoal(pose=goal.pose, path=goal.path, max_speed=self.max_linear)
        return goal

    def check_cmd_vel(self, twist: Twist, pose: Pose2D | None) -> Twist:
        """Clamp to the speed limits; veto a twist that would carry the base off the map or into a
        keep-out zone within the horizon. Stopping is always allowed."""
        if not (math.isfinite(twist.linear_x) and math.isfinite(twist.angular_z)):
            raise Vetoed("cmd_vel is not finite")
        sent = Twist(
            linear_x=max(-self.max_linear, min(self.max_linear, twist.linear_x)),
            angular_z=max(-self.max_angular, min(self.max_angular, twist.angular_z)),
        )
        if sent.linear_x == 0.0:
            return sent
        if pose is None:
            raise Vetoed("the robot's pose is unknown (no recent odometry): only a stop is allowed")
        reach = sent.linear_x * self.config.cmd_vel_horizon
        ahead = (pose.x + reach * math.cos(pose.yaw), pose.y + reach * math.sin(pose.yaw))
        if self.world.room_of(*ahead) is None:
            raise Vetoed(f"cmd_vel would leave the map within {self.config.cmd_vel_horizon:g} s")
        if zone := self._zone_hit(LineString([(pose.x, pose.y), ahead])):
            raise Vetoed(f"cmd_vel would enter keep-out zone '{zone.name}' within {self.config.cmd_vel_horizon:g} s")
        return sent

    # Arm

    def check_trajectory(
        self, goal: FollowJointTrajectoryGoal, current: dict[str, float] | None
    ) -> FollowJointTrajectoryGoal:
        """Known joints inside their limits, and no joint faster than the limit on any segment,
        the first one starting from where the arm is now."""
        unknown = [n for n in goal.joint_names if n not in self.joint_limits]
        if unknown:
            raise Vetoed(f"unknown joints {unknown}")
        if len(set(goal.joint_names)) != len(goal.joint_names):
            raise Vetoed("a joint is named twice")
        if current is None or not all(n in current for n in goal.joint_names):
            raise Vetoed("the arm's joint positions are unknown (no recent joint states)")
        previous = [current[n] for n in goal.joint_names]
        previous_time = 0.0
        for i, point in enumerate(goal.points):
            if len(point.positions) != len(goal.joint_names):
                raise Vetoed(f"point {i}: {len(point.positions)} positions for {len(goal.joint_names)} joints")
            for name, q in zip(goal.joint_names, point.positions, strict=True):
                lim = self.joint_limits[name]
                if not (lim.lower + JOINT_LIMIT_MARGIN <= q <= lim.upper - JOINT_LIMIT_MARGIN):
                    raise Vetoed(f"point {i}: {name} = {q:.3f} rad is outside [{lim.lower:.3f}, {lim.upper:.3f}]")
            dt = point.time_from_start - previous_time
            for name, q0, q1 in zip(goal.joint_names, previous, point.positions, strict=True):
                if dt <= 0:
                    # A point at the start time must be where the arm already is.
                    if abs(q1 - q0) > START_TOLERANCE:
                        raise Vetoed(f"point {i}: {name} would jump {abs(q1 - q0):.3f} rad at once")
                    continue
                speed = abs(q1 - q0) / dt
                if speed > self.config.max_joint_speed + 1e-6:
                    raise Vetoed(
                        f"point {i}: {name} would move at {speed:.2f} rad/s, "
                        f"limit {self.config.max_joint_speed:.2f} rad/s"
                    )
            if dt < 0:
                raise Vetoed(f"point {i}: time_from_start goes backwards")
            previous, previous_time = list(point.positions), point.time_from_start
        return goal

    def check_gripper(self, goal: GripperCommandGoal) -> GripperCommandGoal:
        if goal.object_id is not None:
            self.check_payload(goal.object_id)
        return goal

    def check_payload(self, object_id: str) -> None:
        """Masses come from the world file, never from the command."""
        obj = self.world.objects.get(object_id)
        if obj is None:
            raise Vetoed(f"unknown object '{object_id}': its mass cannot be checked")
        payload = self.world.world.robot.payload
        if obj.mass > payload:
            raise Vetoed(f"'{obj.name}' weighs {obj.mass:g} kg, over the arm's payload of {payload:g} kg")

    # Whole plans, before the first motion

    def check_plan(self, plan: GroundedPlan, start: Pose2D | None) -> list[str]:
        """Check every way the plan can go, on_failure alternatives included, before anything moves.

        Each step is checked from every state (base pose, object held) it can start from: the plan's
        own steps in order, each alternative from every state the steps it covers start from (a
        failure can come at any of them), and the steps after it from where it ends. Returns what
        was checked; raises Vetoed naming the step by its label ("step 2.1 (pick): ...").
        """
        labels = step_labels(plan)
        self._check_structure(plan)
        checks: dict[str, None] = {}
        # before[i]: the states step i can start from.
        before: list[dict[_PlanState, None]] = [{} for _ in range(len(plan.steps) + 1)]
        before[0][_PlanState.at(start, None)] = None
        # States met inside each alternative: an enclosing one may take over from any of them.
        met: dict[int, dict[_PlanState, None]] = {}
        innermost_first = sorted(range(len(plan.fallbacks)), key=lambda k: _span(plan.fallbacks[k]))
        for i, step in enumerate(plan.steps):
            for state in before[i]:
                before[i + 1][self._check_step(step, labels[i], state, checks)] = None
            for k in (k for k in innermost_first if plan.fallbacks[k].last == i):
                fallback = plan.fallbacks[k]
                starts: dict[_PlanState, None] = {}
                for j in range(fallback.first, fallback.last + 1):
                    starts.update(before[j])
                for inner, states in met.items():
                    if _within(plan.fallbacks[inner], fallback):
                        starts.update(states)
                met[k] = {}
                alternative_labels = fallback_labels(fallback, labels)
                for state in starts:
                    for step_, label in zip(fallback.steps, alternative_labels, strict=True):
                        met[k][state] = None
                        state = self._check_step(step_, label, state, checks)
                    before[i + 1][state] = None
        return list(checks)

    def _check_structure(self, plan: GroundedPlan) -> None:
        if plan.labels and len(plan.labels) != len(plan.steps):
            raise Vetoed(f"the plan has {len(plan.steps)} steps but {len(plan.labels)} labels")
        for fallback in plan.fallbacks:
            if not 0 <= fallback.first <= fallback.last < len(plan.steps):
                raise Vetoed(
                    f"an on_failure covers steps {fallback.first + 1}..{fallback.last + 1} "
                    f"of a plan of {len(plan.steps)} steps"
                )
            if not fallback.steps or (fallback.labels and len(fallback.labels) != len(fallback.steps)):
                raise Vetoed(f"the on_failure of steps {fallback.first + 1}..{fallback.last + 1} is malformed")

    def _check_step(self, step: GroundedStep, label: str, state: _PlanState, checks: dict[str, None]) -> _PlanState:
        """The state after `step` from `state`, or Vetoed naming the step."""
        try:
            if isinstance(step, NavigateStep):
                self.check_route(state.pose, [], step.goal)
                checks[f"step {label}: route to {step.target} is clear of keep-out zones"] = None
                return _PlanState.at(step.goal, state.holding)
            if isinstance(step, PickStep):
                self.check_payload(step.object_id)
                self.check_route(state.pose, [], step.approach)
                checks[f"step {label}: {step.object_name} is within payload"] = None
                return _PlanState.at(step.approach, step.object_id)
            if isinstance(step, PlaceStep):
                self.check_route(state.pose, [], step.approach)
                checks[f"step {label}: route to {step.surface_name} is clear"] = None
                return _PlanState.at(step.approach, None)
            if isinstance(step, GripperStep):
                return self._check_gripper_step(step, label, state, checks)
        except Vetoed as exc:
            raise Vetoed(f"step {label} ({step_kind(step)}): {exc}") from None
        return state

    def _check_gripper_step(
        self, step: GripperStep, label: str, state: _PlanState, checks: dict[str, None]
    ) -> _PlanState:
        held = self.world.objects.get(state.holding) if state.holding else None
        name = held.name if held else state.holding
        if step.open:
            if name is not None:
                # Outside place, the arm is stowed over the base: opening drops the object.
                raise Vetoed(f"opening the gripper would drop {name} from the stowed arm; use place to put it down")
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

    @staticmethod
    def at(pose: Pose2D | None, holding: str | None) -> _PlanState:
        if pose is None:
            return _PlanState(None, holding)
        return _PlanState((round(pose.x, 3), round(pose.y, 3), round(pose.yaw, 3)), holding)

    @property
    def pose(self) -> Pose2D | None:
        return None if self.position is None else Pose2D(x=self.position[0], y=self.position[1], yaw=self.position[2])


def _span(fallback: Fallback) -> tuple[int, int]:
    return fallback.last - fallback.first, -fallback.first


def _within(inner: Fallback, outer: Fallback) -> bool:
    return outer.first <= inner.first and inner.last <= outer.last and inner is not outer
