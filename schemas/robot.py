"""The robot interface: motion commands, action goals and the robot's own state."""

from __future__ import annotations

from typing import Annotated

from msgspec import Meta

from schemas.common import Frozen, Id, Metres, Name, Pose2D, Seconds, Text

JointName = Annotated[str, Meta(min_length=1, max_length=64)]
MetresPerSecond = Annotated[float, Meta(ge=-100.0, le=100.0)]
RadiansPerSecond = Annotated[float, Meta(ge=-100.0, le=100.0)]
MAX_JOINTS = 16
MAX_TRAJECTORY_POINTS = 2000
MAX_PATH_POINTS = 500
# The arm's joint names and the gripper's widest opening (Franka Panda): part of the interface.
ARM_JOINTS: tuple[str, ...] = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS: tuple[str, str] = ("panda_finger_joint1", "panda_finger_joint2")
GRIPPER_MAX_GAP = 0.08


class Twist(Frozen):
    """cmd_vel for the base: forward speed and turn rate in the base frame.

    `stamp` (wall time when sent, 0 if unknown) is carried through safety unchanged, as in ROS's
    TwistStamped, so a stream's latency can be measured end to end.
    """

    linear_x: MetresPerSecond = 0.0
    angular_z: RadiansPerSecond = 0.0
    stamp: float = 0.0


class JointState(Frozen):
    stamp: float
    name: Annotated[list[JointName], Meta(max_length=MAX_JOINTS)]
    position: Annotated[list[float], Meta(max_length=MAX_JOINTS)]
    velocity: Annotated[list[float], Meta(max_length=MAX_JOINTS)] = []


class Odometry(Frozen):
    """Base pose and measured velocity. `stamp` is wall time, `sim_time` the simulator's clock."""

    stamp: float
    sim_time: float
    pose: Pose2D
    linear_x: float
    angular_z: float


# navigate_to_pose


class NavigateToPoseGoal(Frozen):
    """Drive the base to `pose`, following `path` (map-frame waypoints) when one is given.

    `max_speed` (m/s) and `max_turn_rate` (rad/s) are what was asked for; safety refuses one over
    its limit and fills in its limit when none is given, so the robot always receives numbers
    safety approved. `start` is where the route was checked from: safety fills in the pose it
    checked it from, and the robot drives the legs that start gives (services/footprint.py), or
    refuses the goal when it no longer stands there.
    """

    pose: Pose2D
    path: Annotated[list[Pose2D], Meta(max_length=MAX_PATH_POINTS)] = []
    max_speed: Annotated[float, Meta(gt=0.0, le=5.0)] | None = None
    max_turn_rate: Annotated[float, Meta(gt=0.0, le=10.0)] | None = None
    start: Pose2D | None = None


class NavigateToPoseFeedback(Frozen):
    pose: Pose2D
    distance_remaining: Metres


class NavigateToPoseResult(Frozen):
    pose: Pose2D
    message: Text = ""


# follow_joint_trajectory


class TrajectoryPoint(Frozen):
    positions: Annotated[list[float], Meta(max_length=MAX_JOINTS)]
    time_from_start: Seconds


class FollowJointTrajectoryGoal(Frozen):
    """Follow `points` in time. `goal_tolerance` (rad) is how close every joint must end to the last
    point; `path_tolerance` (rad) how far any joint may fall from where the trajectory has it on
    the way: further (blocked, pushed) aborts the goal, as ROS's path_tolerance does."""

    joint_names: Annotated[list[JointName], Meta(min_length=1, max_length=MAX_JOINTS)]
    points: Annotated[list[TrajectoryPoint], Meta(min_length=1, max_length=MAX_TRAJECTORY_POINTS)]
    goal_tolerance: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.02
    path_tolerance: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.1


class FollowJointTrajectoryFeedback(Frozen):
    desired: list[float]
    actual: list[float]
    time_from_start: float


class FollowJointTrajectoryResult(Frozen):
    error: Annotated[float, Meta(ge=0.0)]
    message: Text = ""


# gripper_command


class GripperCommandGoal(Frozen):
    """Open or close the gripper. `position` is the finger gap in metres.

    `object_id` names what a closing gripper is meant to hold, so safety can check the payload.
    `payload_limit` (kg) is the heaviest object the gripper may take hold of: safety fills in its
    limit, and the robot lets anything heavier slip, whatever `object_id` says.
    """

    position: Annotated[float, Meta(ge=0.0, le=GRIPPER_MAX_GAP)]
    max_effort: Annotated[float, Meta(ge=0.0, le=140.0)] = 40.0
    object_id: Id | None = None
    payload_limit: Annotated[float, Meta(gt=0.0, le=1000.0)] | None = None


class GripperCommandFeedback(Frozen):
    position: float


class GripperCommandResult(Frozen):
    position: float
    stalled: bool
    reached_goal: bool
    holding: Name | None = None


# What a backend finds wrong with its robot (optional: robot/diagnostics)

MAX_PROBLEMS = 32


class RobotProblem(Frozen):
    """Something wrong on the robot's side, in words: a report refused (another type hash, bytes
    that do not decode, another frame), a goal it would not take, aborted or did not stop."""

    text: Text
    last_seen: float  # wall time


class RobotDiagnostics(Frozen):
    """A robot backend's problems with its robot: each one seen in the last `window` seconds, the
    latest first; none when all is well."""

    stamp: float
    backend: Name
    window: Seconds
    problems: Annotated[list[RobotProblem], Meta(max_length=MAX_PROBLEMS)] = []
