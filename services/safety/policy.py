"""The checks: every command and every plan against keep-out zones, speed, joint and payload limits."""

from __future__ import annotations

import itertools
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from shapely.geometry import LineString, Point

from schemas.common import Pose2D
from schemas.plan import GroundedPlan, NavigateStep, PickStep, PlaceStep
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, Twist
from services.safety.config import SafetyConfig
from services.safety.errors import Vetoed
from services.worldmodel import WorldModel

# Joint positions may not come closer than this to the hard limits.
JOINT_LIMIT_MARGIN = 0.01


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


class SafetyPolicy:
    """Pure checks. Each `check_*` returns the command to forward, or raises Vetoed naming why."""

    def __init__(self, world: WorldModel, config: SafetyConfig, joint_limits: dict[str, JointLimit]) -> None:
        self.world = world
        self.config = config
        self.joint_limits = joint_limits
        robot = world.world.robot
        self.max_linear = min(config.max_linear_speed or robot.max_linear_speed, robot.max_linear_speed)
        self.max_angular = min(config.max_angular_speed or robot.max_angular_speed, robot.max_angular_speed)

    # Navigation

    def check_route(self, start: Pose2D | None, waypoints: list[Pose2D]) -> None:
        """Every waypoint on the map and out of keep-out zones; every leg clear of them too."""
        for i, pose in enumerate(waypoints):
            point = Point(pose.x, pose.y)
            if not (math.isfinite(pose.x) and math.isfinite(pose.y) and math.isfinite(pose.yaw)):
                raise Vetoed(f"waypoint {i + 1} is not a finite pose")
            if self.world.room_of(pose.x, pose.y) is None:
                raise Vetoed(f"({_fmt(pose.x)}, {_fmt(pose.y)}) is outside every room of the map")
            for zone in self.world.world.keep_out:
                if self.world.keep_out_shapes[zone.id].covers(point):
                    raise Vetoed(
                        f"goal ({_fmt(pose.x)}, {_fmt(pose.y)}) is inside keep-out zone '{zone.name}'"
                        + (f": {zone.reason}" if zone.reason else "")
                    )
        points = ([start] if start is not None else []) + waypoints
        for a, b in itertools.pairwise(points):
            leg = LineString([(a.x, a.y), (b.x, b.y)])
            for zone in self.world.world.keep_out:
                if leg.intersects(self.world.keep_out_shapes[zone.id]):
                    raise Vetoed(
                        f"path from ({_fmt(a.x)}, {_fmt(a.y)}) to ({_fmt(b.x)}, {_fmt(b.y)}) "
                        f"crosses keep-out zone '{zone.name}'"
                    )

    def check_navigation(self, goal: NavigateToPoseGoal, start: Pose2D | None) -> NavigateToPoseGoal:
        self.check_route(start, [*goal.path, goal.pose])
        if goal.max_speed > self.max_linear:
            # Clamp rather than refuse: a slower arrival is always safe.
            return NavigateToPoseGoal(pose=goal.pose, path=goal.path, max_speed=self.max_linear)
        return goal

    def check_cmd_vel(self, twist: Twist) -> Twist:
        if not (math.isfinite(twist.linear_x) and math.isfinite(twist.angular_z)):
            raise Vetoed("cmd_vel is not finite")
        return Twist(
            linear_x=max(-self.max_linear, min(self.max_linear, twist.linear_x)),
            angular_z=max(-self.max_angular, min(self.max_angular, twist.angular_z)),
        )

    # Arm

    def check_trajectory(self, goal: FollowJointTrajectoryGoal) -> FollowJointTrajectoryGoal:
        unknown = [n for n in goal.joint_names if n not in self.joint_limits]
        if unknown:
            raise Vetoed(f"unknown joints {unknown}")
        if len(set(goal.joint_names)) != len(goal.joint_names):
            raise Vetoed("a joint is named twice")
        previous: list[float] | None = None
        previous_time = 0.0
        for i, point in enumerate(goal.points):
            if len(point.positions) != len(goal.joint_names):
                raise Vetoed(f"point {i}: {len(point.positions)} positions for {len(goal.joint_names)} joints")
            for name, q in zip(goal.joint_names, point.positions, strict=True):
                lim = self.joint_limits[name]
                if not (lim.lower + JOINT_LIMIT_MARGIN <= q <= lim.upper - JOINT_LIMIT_MARGIN):
                    raise Vetoed(f"point {i}: {name} = {q:.3f} rad is outside [{lim.lower:.3f}, {lim.upper:.3f}]")
            if previous is not None:
                dt = point.time_from_start - previous_time
                if dt <= 0:
                    raise Vetoed(f"point {i}: time_from_start does not increase")
                for name, q0, q1 in zip(goal.joint_names, previous, point.positions, strict=True):
                    speed = abs(q1 - q0) / dt
                    if speed > self.config.max_joint_speed + 1e-6:
                        raise Vetoed(
                            f"point {i}: {name} would move at {speed:.2f} rad/s, "
                            f"limit {self.config.max_joint_speed:.2f} rad/s"
                        )
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
        """Check every step in order; returns what was checked, raises Vetoed naming the step."""
        checks: list[str] = []
        position = start
        for i, step in enumerate(plan.steps):
            try:
                if isinstance(step, NavigateStep):
                    self.check_route(position, [step.goal])
                    position = step.goal
                    checks.append(f"step {i + 1}: route to {step.target} is clear of keep-out zones")
                elif isinstance(step, PickStep):
                    self.check_payload(step.object_id)
                    self.check_route(position, [step.approach])
                    position = step.approach
                    checks.append(f"step {i + 1}: {step.object_name} is within payload")
                elif isinstance(step, PlaceStep):
                    self.check_route(position, [step.approach])
                    position = step.approach
                    checks.append(f"step {i + 1}: route to {step.surface_name} is clear")
            except Vetoed as exc:
                raise Vetoed(f"step {i + 1} ({step_name(step)}): {exc}") from None
        return checks


def step_name(step: object) -> str:
    tag = type(step).__struct_config__.tag  # type: ignore[attr-defined]
    return str(tag)
