"""Motions that make up the steps: driving to a pose, picking from a surface, placing onto one."""

from __future__ import annotations

import math
import threading
from typing import Any

from schemas.actions import GoalState, ResultResponse
from schemas.common import Pose2D, Vec3
from schemas.plan import PickStep, PlaceStep
from schemas.robot import (
    ARM_JOINTS,
    GRIPPER_MAX_GAP,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    NavigateToPoseGoal,
    TrajectoryPoint,
)
from services.actionlib import GoalRejected
from services.executor.config import ExecutorConfig
from services.executor.errors import (
    Canceled,
    ExecutionError,
    Interrupted,
    PostconditionFailed,
    PreconditionFailed,
    Vetoed,
)
from services.executor.kinematics import ArmKinematics, waypoint_trajectory
from services.executor.ports import Robot
from services.worldmodel import WorldModel

GRIPPER_OPEN = GRIPPER_MAX_GAP
GRIPPER_CLOSED = 0.0
# Perception publishes a few times a second; wait at most this for its next report.
PERCEPTION_TIMEOUT = 2.0
# Half the height of a held object the world file does not know.
DEFAULT_HALF_HEIGHT = 0.05


def check_outcome(what: str, result: ResultResponse[Any], cancel: threading.Event) -> Any:
    if result.state is GoalState.SUCCEEDED:
        return result.result
    if result.state is GoalState.CANCELED:
        if cancel.is_set():
            raise Canceled(f"{what} canceled")
        # Not canceled here: safety cancels every goal it forwarded when the e-stop latches.
        raise Interrupted(f"{what} canceled by the robot side: {result.message or 'no reason given'}")
    raise ExecutionError(f"{what} {result.state}: {result.message}")


class Manipulator:
    """Turns grounded steps into goals for the robot (through safety) and checks each outcome."""

    def __init__(self, robot: Robot, kinematics: ArmKinematics, world: WorldModel, config: ExecutorConfig) -> None:
        self.robot = robot
        self.kin = kinematics
        self.world = world
        self.config = config

    # Base

    def drive_to(self, pose: Pose2D, cancel: threading.Event, max_speed: float | None = None) -> None:
        goal = NavigateToPoseGoal(pose=pose, max_speed=max_speed)
        try:
            result = self.robot.navigate(goal, cancel)
        except GoalRejected as exc:
            raise Vetoed(exc.reason) from None
        check_outcome("navigation", result, cancel)

    def ensure_at(self, approach: Pose2D, cancel: threading.Event) -> None:
        """Drive to `approach` unless the base already stands there."""
        here = self.robot.base_pose()
        if here is not None:
            distance = math.hypot(here.x - approach.x, here.y - approach.y)
            yaw_error = abs(math.remainder(here.yaw - approach.yaw, math.tau))
            if distance <= self.config.approach_tolerance and yaw_error <= self.config.approach_yaw_tolerance:
                return
        self.drive_to(approach, cancel)

    # Arm and gripper

    def _base(self) -> Pose2D:
        base = self.robot.base_pose()
        if base is None:
            raise PreconditionFailed("no odometry from the robot: its pose is unknown")
        return base

    def _arm_now(self) -> list[float]:
        q = self.robot.arm_positions()
        if q is None:
            raise PreconditionFailed("no joint states from the robot")
        return q

    def move_arm_to(self, q_target: list[float], what: str, cancel: threading.Event) -> None:
        points = self.kin.joint_trajectory(self._arm_now(), q_target, self.config.max_joint_speed)
        self._run_trajectory(points, what, cancel)

    def _run_trajectory(self, points: list[TrajectoryPoint], what: str, cancel: threading.Event) -> None:
        goal = FollowJointTrajectoryGoal(joint_names=list(ARM_JOINTS), points=points)
        try:
            result = self.robot.trajectory(goal, cancel)
        except GoalRejected as exc:
            raise Vetoed(f"{what}: {exc.reason}") from None
        check_outcome(what, result, cancel)

    def reach(self, point: Vec3, what: str, cancel: threading.Event) -> None:
        """Bring the fingertips to `point` (map frame), hand pointing down, through free space."""
        mount = self.world.world.robot.arm_mount
        target = self.kin.world_to_arm(self._base(), mount, point)
        q = self.kin.solve_top_down(target, self._arm_now())
        self.move_arm_to([float(x) for x in q], what, cancel)

    def slide(self, point: Vec3, what: str, cancel: threading.Event) -> None:
        """Move the fingertips in a straight line to `point`: the descent to and lift from an object."""
        mount = self.world.world.robot.arm_mount
        target = self.kin.world_to_arm(self._base(), mount, point)
        path = self.kin.straight_line(self._arm_now(), target)
        self._run_trajectory(waypoint_trajectory(path, self.config.max_joint_speed), what, cancel)

    def stow(self, cancel: threading.Event) -> None:
        self.move_arm_to(list(self.world.world.robot.home_joints), "stowing the arm", cancel)

    def gripper(self, position: float, cancel: threading.Event, object_id: str | None = None) -> Any:
        try:
            result = self.robot.gripper(GripperCommandGoal(position=position, object_id=object_id), cancel)
        except GoalRejected as exc:
            raise Vetoed(exc.reason) from None
        return check_outcome("gripper", result, cancel)

    def operate_gripper(self, open_: bool, cancel: threading.Event) -> str:
        """open_gripper / close_gripper on their own. Opening never drops what the hand holds (that
        is place's job); closing on what it already holds leaves it as it is."""
        held_id = self.robot.held_object()
        held = self.world.objects.get(held_id) if held_id else None
        held_name = held.name if held else held_id
        if open_:
            if held_name is not None:
                raise PreconditionFailed(f"opening the gripper would drop {held_name}; use place to put it down")
            self.gripper(GRIPPER_OPEN, cancel)
            return "gripper open"
        if held_name is not None:
            return f"gripper already closed on {held_name}"
        result = self.gripper(GRIPPER_CLOSED, cancel)
        holding = None if result is None else result.holding
        return f"gripper closed on {holding}" if holding else "gripper closed, holding nothing"

    # Steps

    def _grasp_height(self, height: float) -> float:
        """How far above its centre the fingertips close on an object `height` tall: at most
        grasp_depth below its top, so the palm stays clear of its rim."""
        return max(0.0, height / 2 - self.config.grasp_depth)

    def pick(self, step: PickStep, cancel: threading.Event) -> None:
        # What the hand holds comes from perception, never from bookkeeping that a failed step
        # could have left stale.
        if (held_now := self.robot.held_object()) is not None:
            raise PreconditionFailed(f"the gripper already holds {held_now}")
        self.ensure_at(step.approach, cancel)
        # Where perception sees it now, not where it was when the plan was resolved.
        centre = self.robot.object_position(step.object_id) or step.position
        obj = self.world.objects.get(step.object_id)
        grasp_height = self._grasp_height(obj.size.z if obj else 2 * DEFAULT_HALF_HEIGHT)
        position = Vec3(x=centre.x, y=centre.y, z=centre.z + grasp_height)
        above = Vec3(x=position.x, y=position.y, z=position.z + self.config.pregrasp_height)
        self.gripper(GRIPPER_OPEN, cancel)
        self.reach(above, f"moving above {step.object_name}", cancel)
        self.slide(position, f"reaching {step.object_name}", cancel)
        result = self.gripper(GRIPPER_CLOSED, cancel, object_id=step.object_id)
        if result is None or result.holding != step.object_id:
            held = None if result is None else result.holding
            self.gripper(GRIPPER_OPEN, cancel)
            raise ExecutionError(f"gripper closed on {held or 'nothing'}, not {step.object_name}")
        self.slide(above, f"lifting {step.object_name}", cancel)
        self.stow(cancel)

    def place(self, step: PlaceStep, cancel: threading.Event) -> str:
        held_id = self.robot.held_object()
        if held_id is None:
            raise PreconditionFailed("the gripper holds nothing to place")
        held = self.world.objects.get(held_id)
        name = held.name if held else held_id
        half_height = held.size.z / 2 if held else DEFAULT_HALF_HEIGHT
        self.ensure_at(step.approach, cancel)
        # The fingertips, with the object's bottom place_clearance above the top, as pick held it.
        bottom_to_fingertips = half_height + self._grasp_height(2 * half_height)
        at = Vec3(
            x=step.position.x, y=step.position.y, z=step.position.z + bottom_to_fingertips + self.config.place_clearance
        )
        above = Vec3(x=at.x, y=at.y, z=at.z + self.config.pregrasp_height)
        self.reach(above, f"moving {name} above {step.surface_name}", cancel)
        self.slide(at, f"lowering {name} onto {step.surface_name}", cancel)
        self.gripper(GRIPPER_OPEN, cancel)
        self.slide(above, "lifting the hand", cancel)
        self.stow(cancel)
        # Done means perception sees it on the surface, not that the motions went through.
        seen = self.robot.next_perception(held_id, PERCEPTION_TIMEOUT)
        if seen is None or seen.on != step.surface_id:
            where = "nowhere" if seen is None else (seen.on or "the floor")
            raise PostconditionFailed(f"after placing, perception has {name} on {where}, not on {step.surface_name}")
        return name
