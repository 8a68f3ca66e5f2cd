"""The sim's messages as ROS 2 messages and back, pure: what the stand-in robot says and what it accepts."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import msgspec
import numpy as np

from schemas.actions import GoalState
from schemas.common import Pose2D
from schemas.robot import (
    MAX_JOINTS,
    MAX_PATH_POINTS,
    MAX_TRAJECTORY_POINTS,
    FollowJointTrajectoryFeedback,
    FollowJointTrajectoryGoal,
    GripperCommandFeedback,
    GripperCommandGoal,
    GripperCommandResult,
    JointState,
    NavigateToPoseFeedback,
    NavigateToPoseGoal,
    Odometry,
    Twist,
)
from schemas.world import Extent, PerceivedHumans, PerceivedObjects, RobotSpec
from services.actionlib import Outcome
from services.ros2.types import RosTypes
from services.sim.world import HAND_LINK, HUMAN_HEIGHT, HUMAN_RADIUS

# The stand-in's odom frame is the map frame: its odometry never drifts.
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
CAMERA_FRAME = "camera"
# Goal poses in either name the same frame here; anything else would need a transform the robot lacks.
GOAL_FRAMES = ("odom", "map")
PERSON_CLASS = "person"
HELD = "gripper"  # PerceivedObject.on for the object in the hand

NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"
NAVIGATE_THROUGH_POSES = "nav2_msgs/action/NavigateThroughPoses"
FOLLOW_JOINT_TRAJECTORY = "control_msgs/action/FollowJointTrajectory"
GRIPPER_COMMAND = "control_msgs/action/GripperCommand"

# nav2_msgs NavigateToPose/NavigateThroughPoses result error codes (Jazzy).
NAV_NONE = 0
NAV_UNKNOWN = 9000
# control_msgs FollowJointTrajectory result error codes.
TRAJECTORY_SUCCESSFUL = 0
TRAJECTORY_INVALID_GOAL = -1
PATH_TOLERANCE_VIOLATED = -4
GOAL_TOLERANCE_VIOLATED = -5
# control_msgs JointTolerance: 0 leaves the default, -1 erases the tolerance (no limit).
TOLERANCE_DEFAULT = 0.0
TOLERANCE_ERASED = -1.0
MAX_TOLERANCE = 1.0  # radians; the sim's FollowJointTrajectoryGoal bound
# How much of a name from the network a refusal quotes: a frame_id may be megabytes long.
QUOTED_CHARS = 80


class BadMessage(ValueError):
    """A message from the ROS side this robot will not act on; the text says why."""


def _finite(what: str, *values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise BadMessage(f"{what} is not finite: {', '.join(f'{v:g}' for v in values)}")


def _at_most(what: str, count: int, limit: int) -> None:
    """Before converting item by item: a hostile message may hold millions."""
    if count > limit:
        raise BadMessage(f"{what} has {count} entries; at most {limit}")


def _quoted(text: str) -> str:
    """`text` as a refusal quotes it, cut short when long."""
    if len(text) <= QUOTED_CHARS:
        return repr(text)
    return f"{text[:QUOTED_CHARS]!r}... ({len(text)} characters)"


def _convert(data: Any, cls: type[Any], what: str) -> Any:
    try:
        return msgspec.convert(data, cls)
    except msgspec.ValidationError as exc:
        raise BadMessage(f"{what}: {exc}") from None


# Time


def ros_time(types: RosTypes, stamp: float) -> Any:
    """builtin_interfaces/Time of a wall-clock stamp (Unix seconds)."""
    sec = math.floor(stamp)
    return types.new("builtin_interfaces/msg/Time", sec=sec, nanosec=min(round((stamp - sec) * 1e9), 999_999_999))


def duration(types: RosTypes, seconds: float) -> Any:
    seconds = max(0.0, seconds)
    sec = math.floor(seconds)
    return types.new("builtin_interfaces/msg/Duration", sec=sec, nanosec=min(round((seconds - sec) * 1e9), 999_999_999))


def seconds_of(duration_msg: Any) -> float:
    return float(duration_msg.sec) + float(duration_msg.nanosec) * 1e-9


def header(types: RosTypes, stamp: float, frame: str = "") -> Any:
    return types.new("std_msgs/msg/Header", stamp=ros_time(types, stamp), frame_id=frame)


# Geometry


def quaternion(types: RosTypes, yaw: float = 0.0) -> Any:
    """A rotation about z by `yaw`."""
    return types.new("geometry_msgs/msg/Quaternion", z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def pose(types: RosTypes, x: float, y: float, z: float = 0.0, yaw: float | None = None) -> Any:
    point = types.new("geometry_msgs/msg/Point", x=x, y=y, z=z)
    return types.new("geometry_msgs/msg/Pose", position=point, orientation=quaternion(types, yaw or 0.0))


def yaw_of(q: Any) -> float:
    """The heading of an orientation (its rotation about z); BadMessage for no rotation at all."""
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    _finite("orientation", x, y, z, w)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm < 1e-6:
        raise BadMessage("orientation is the zero quaternion, not a rotation")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def pose2d(stamped: Any, what: str) -> Pose2D:
    """A geometry_msgs/PoseStamped goal as a floor pose in the map frame."""
    frame = stamped.header.frame_id
    if frame.lstrip("/") not in GOAL_FRAMES:
        raise BadMessage(f"{what} is in frame {_quoted(frame)}; this robot takes goals in {' or '.join(GOAL_FRAMES)}")
    position = stamped.pose.position
    x, y = float(position.x), float(position.y)
    _finite(f"{what} position", x, y, float(position.z))
    return _convert({"x": x, "y": y, "yaw": yaw_of(stamped.pose.orientation)}, Pose2D, what)


# Inputs: what the ROS side asks


def navigate_to_pose_goal(goal: Any) -> NavigateToPoseGoal:
    """nav2_msgs NavigateToPose goal -> the sim's, driven from where the base stands, within the speed limit."""
    return NavigateToPoseGoal(pose=pose2d(goal.pose, "pose"))


def navigate_through_poses_goal(goal: Any) -> NavigateToPoseGoal:
    """nav2_msgs NavigateThroughPoses goal: through every pose but the last, to the last."""
    if not goal.poses:
        raise BadMessage("poses is empty; NavigateThroughPoses needs at least one")
    _at_most("poses", len(goal.poses), MAX_PATH_POINTS + 1)
    poses = [pose2d(p, f"poses[{i}]") for i, p in enumerate(goal.poses)]
    return _convert({"pose": poses[-1], "path": poses[:-1]}, NavigateToPoseGoal, "poses")


def _tolerance(tolerances: Sequence[Any], joints: Sequence[str], what: str) -> float | None:
    """The sim's one tolerance from control_msgs' per-joint ones: the tightest given, capped at
    MAX_TOLERANCE; erased (-1) counts as MAX_TOLERANCE; None when none is given (the sim's default)."""
    _at_most(what, len(tolerances), MAX_JOINTS)
    tightest = math.inf
    for i, tolerance in enumerate(tolerances):
        name, value = str(tolerance.name), float(tolerance.position)
        _finite(f"{what}[{i}].position", value)
        if name not in joints:
            raise BadMessage(f"{what}[{i}] names joint {_quoted(name)}, which the trajectory does not move")
        if value == TOLERANCE_DEFAULT:
            continue
        if value == TOLERANCE_ERASED:
            tightest = min(tightest, MAX_TOLERANCE)
        elif value > 0.0:
            tightest = min(tightest, value, MAX_TOLERANCE)
        else:
            raise BadMessage(f"{what}[{i}].position is {value:g}; a tolerance is > 0, 0 (default) or -1 (none)")
    return None if tightest == math.inf else tightest


def _as_the_controller_takes(point: Any, what: str, joints: int) -> None:
    """What joint_trajectory_controller refuses in a point besides its positions: velocities or
    accelerations not given for every joint, any effort."""
    for field in ("velocities", "accelerations"):
        given = len(getattr(point, field))
        if given not in (0, joints):
            raise BadMessage(f"{what}.{field} has {given} entries for {joints} joints; one per joint, or none")
    if len(point.effort):
        raise BadMessage(f"{what}.effort is given; this arm's controller takes no efforts")


def trajectory_goal(goal: Any) -> FollowJointTrajectoryGoal:
    """control_msgs FollowJointTrajectory goal -> the sim's (positions and times; velocities and
    accelerations are left to the sim's linear interpolation). The arm's own checks come after."""
    if goal.multi_dof_trajectory.joint_names or goal.multi_dof_trajectory.points:
        raise BadMessage("multi_dof_trajectory is not empty; this arm has no multi-DOF joints")
    trajectory = goal.trajectory
    _at_most("trajectory.joint_names", len(trajectory.joint_names), MAX_JOINTS)
    _at_most("trajectory.points", len(trajectory.points), MAX_TRAJECTORY_POINTS)
    names = [str(n) for n in trajectory.joint_names]
    points = []
    previous = -math.inf
    for k, point in enumerate(trajectory.points):
        what = f"trajectory.points[{k}]"
        _at_most(f"{what}.positions", len(point.positions), MAX_JOINTS)
        _as_the_controller_takes(point, what, len(names))
        positions = [float(v) for v in point.positions]
        _finite(f"{what}.positions", *positions)
        at = seconds_of(point.time_from_start)
        if at <= previous:  # joint_trajectory_controller's rule, stricter than the sim's
            raise BadMessage(f"{what}.time_from_start is {at:g} s, not after the point before it ({previous:g} s)")
        previous = at
        points.append({"positions": positions, "time_from_start": at})
    data: dict[str, Any] = {"joint_names": names, "points": points}
    for field in ("path_tolerance", "goal_tolerance"):
        tolerance = _tolerance(getattr(goal, field), names, field)
        if tolerance is not None:
            data[field] = tolerance
    converted: FollowJointTrajectoryGoal = _convert(data, FollowJointTrajectoryGoal, "trajectory")
    return converted


def gripper_goal(goal: Any) -> GripperCommandGoal:
    """control_msgs GripperCommand goal -> the sim's: the finger gap and the force to close with."""
    position, max_effort = float(goal.command.position), float(goal.command.max_effort)
    _finite("command", position, max_effort)
    converted: GripperCommandGoal = _convert(
        {"position": position, "max_effort": max_effort}, GripperCommandGoal, "command"
    )
    return converted


def twist(message: Any, stamped: bool) -> Twist:
    """geometry_msgs Twist (or TwistStamped) -> the base's command; only linear.x and angular.z
    move a differential drive, the other components are ignored as diff_drive_controller does."""
    body = message.twist if stamped else message
    linear, angular = float(body.linear.x), float(body.angular.z)
    _finite("cmd_vel", linear, angular)
    stamp = float(message.header.stamp.sec) + float(message.header.stamp.nanosec) * 1e-9 if stamped else 0.0
    converted: Twist = _convert({"linear_x": linear, "angular_z": angular, "stamp": stamp}, Twist, "cmd_vel")
    return converted


def speed_limits(message: Any, robot: RobotSpec) -> tuple[float | None, float | None]:
    """nav2_msgs SpeedLimit -> the base's (linear m/s, angular rad/s) limits, (None, None) for none.

    As Nav2's controller_server: 0 is no limit; `percentage` is of the robot's maximum; otherwise
    m/s. The turn rate is limited by the same fraction of its maximum.
    """
    value = float(message.speed_limit)
    _finite("speed_limit", value)
    if value < 0.0:
        raise BadMessage(f"speed_limit is {value:g}; it is > 0, or 0 for no limit")
    if value == 0.0:
        return None, None
    fraction = value / 100.0 if message.percentage else value / robot.max_linear_speed
    fraction = min(fraction, 1.0)
    return fraction * robot.max_linear_speed, fraction * robot.max_angular_speed


# Outputs: what the robot reports


def odometry(types: RosTypes, odom: Odometry) -> Any:
    """nav_msgs/Odometry in the odom frame (the map's), the measured speeds in the base frame."""
    p = odom.pose
    twist_msg = types.new(
        "geometry_msgs/msg/Twist",
        linear=types.new("geometry_msgs/msg/Vector3", x=odom.linear_x),
        angular=types.new("geometry_msgs/msg/Vector3", z=odom.angular_z),
    )
    return types.new(
        "nav_msgs/msg/Odometry",
        header=header(types, odom.stamp, ODOM_FRAME),
        child_frame_id=BASE_FRAME,
        pose=types.new("geometry_msgs/msg/PoseWithCovariance", pose=pose(types, p.x, p.y, 0.0, p.yaw)),
        twist=types.new("geometry_msgs/msg/TwistWithCovariance", twist=twist_msg),
    )


def joint_state(types: RosTypes, state: JointState) -> Any:
    return types.new(
        "sensor_msgs/msg/JointState",
        header=header(types, state.stamp),
        name=list(state.name),
        position=np.asarray(state.position, dtype=np.float64),
        velocity=np.asarray(state.velocity, dtype=np.float64),
    )


def _detection(types: RosTypes, stamp: float, frame: str, ident: str, cls: str, where: Any, size: Extent | None) -> Any:
    hypothesis = types.new(
        "vision_msgs/msg/ObjectHypothesisWithPose",
        hypothesis=types.new("vision_msgs/msg/ObjectHypothesis", class_id=cls, score=1.0),
        pose=types.new("geometry_msgs/msg/PoseWithCovariance", pose=where),
    )
    extent = types.new("geometry_msgs/msg/Vector3", **({"x": size.x, "y": size.y, "z": size.z} if size else {}))
    return types.new(
        "vision_msgs/msg/Detection3D",
        header=header(types, stamp, frame),
        results=[hypothesis],
        bbox=types.new("vision_msgs/msg/BoundingBox3D", center=where, size=extent),
        id=ident,
    )


def object_detections(types: RosTypes, seen: PerceivedObjects, sizes: Mapping[str, Extent]) -> Any:
    """What the camera sees now, one Detection3D per object: its world-file id and class, its centre
    (and heading when it has one) in the odom frame; the held one's header says the gripper frame."""
    detections = [
        _detection(
            types,
            seen.stamp,
            HAND_LINK if o.on == HELD else ODOM_FRAME,
            o.id,
            o.cls,
            pose(types, o.position.x, o.position.y, o.position.z, o.yaw),
            sizes.get(o.id),
        )
        for o in seen.objects
    ]
    return types.new(
        "vision_msgs/msg/Detection3DArray", header=header(types, seen.stamp, ODOM_FRAME), detections=detections
    )


PERSON_SIZE = Extent(x=2 * HUMAN_RADIUS, y=2 * HUMAN_RADIUS, z=HUMAN_HEIGHT)


def people_detections(types: RosTypes, people: PerceivedHumans) -> Any:
    """Every person where they stand, class "person": centred at half their height, facing their heading."""
    detections = [
        _detection(
            types,
            people.stamp,
            ODOM_FRAME,
            h.id,
            PERSON_CLASS,
            pose(types, h.pose.x, h.pose.y, HUMAN_HEIGHT / 2, h.pose.yaw),
            PERSON_SIZE,
        )
        for h in people.humans
    ]
    return types.new(
        "vision_msgs/msg/Detection3DArray", header=header(types, people.stamp, ODOM_FRAME), detections=detections
    )


def compressed_image(types: RosTypes, png: bytes, stamp: float) -> Any:
    return types.new(
        "sensor_msgs/msg/CompressedImage",
        header=header(types, stamp, CAMERA_FRAME),
        format="png",
        data=np.frombuffer(png, dtype=np.uint8),
    )


# Action feedback and results


def navigation_feedback(
    types: RosTypes, action_type: str, feedback: NavigateToPoseFeedback, stamp: float, elapsed: float
) -> Any:
    """Nav2's feedback for either navigation action: where the base is, the distance still to go."""
    p = feedback.pose
    fields: dict[str, Any] = {
        "current_pose": types.new(
            "geometry_msgs/msg/PoseStamped",
            header=header(types, stamp, ODOM_FRAME),
            pose=pose(types, p.x, p.y, 0.0, p.yaw),
        ),
        "navigation_time": duration(types, elapsed),
        "distance_remaining": feedback.distance_remaining,
    }
    return types.new(f"{action_type}_Feedback", **fields)


def navigation_result(types: RosTypes, action_type: str, outcome: Outcome[Any]) -> Any:
    """Nav2's result: no error code on success or cancel, UNKNOWN with the sim's reason on an abort."""
    aborted = outcome.state is GoalState.ABORTED
    return types.new(
        f"{action_type}_Result",
        error_code=NAV_UNKNOWN if aborted else NAV_NONE,
        error_msg=outcome.message if aborted else "",
    )


def _point(types: RosTypes, positions: np.ndarray, at: float) -> Any:
    return types.new(
        "trajectory_msgs/msg/JointTrajectoryPoint",
        positions=np.asarray(positions, dtype=np.float64),
        time_from_start=duration(types, at),
    )


def trajectory_feedback(
    types: RosTypes, feedback: FollowJointTrajectoryFeedback, joint_names: Sequence[str], stamp: float
) -> Any:
    desired, actual = np.asarray(feedback.desired), np.asarray(feedback.actual)
    at = feedback.time_from_start
    return types.new(
        f"{FOLLOW_JOINT_TRAJECTORY}_Feedback",
        header=header(types, stamp),
        joint_names=list(joint_names),
        desired=_point(types, desired, at),
        actual=_point(types, actual, at),
        error=_point(types, desired - actual, at),
    )


def trajectory_error_code(outcome: Outcome[Any]) -> int:
    """control_msgs' code for how a trajectory ended. The sim tells a path violation only in its
    message ("... (path tolerance ...)"); any other abort (the final error over the goal tolerance,
    an emergency stop) did not reach the goal."""
    if outcome.state is not GoalState.ABORTED:
        return TRAJECTORY_SUCCESSFUL  # canceled too, as joint_trajectory_controller reports it
    return PATH_TOLERANCE_VIOLATED if "path tolerance" in outcome.message else GOAL_TOLERANCE_VIOLATED


# What joint_trajectory_controller says of the goal a new one preempted (it ends canceled).
TRAJECTORY_PREEMPTED = "Current goal cancelled due to new incoming action."


def trajectory_preempted(types: RosTypes) -> Any:
    return types.new(
        f"{FOLLOW_JOINT_TRAJECTORY}_Result", error_code=TRAJECTORY_INVALID_GOAL, error_string=TRAJECTORY_PREEMPTED
    )


def trajectory_result(types: RosTypes, outcome: Outcome[Any]) -> Any:
    return types.new(
        f"{FOLLOW_JOINT_TRAJECTORY}_Result",
        error_code=trajectory_error_code(outcome),
        error_string=outcome.message,
    )


def gripper_feedback(types: RosTypes, feedback: GripperCommandFeedback) -> Any:
    return types.new(f"{GRIPPER_COMMAND}_Feedback", position=feedback.position)


def gripper_result(types: RosTypes, outcome: Outcome[Any], goal: GripperCommandGoal) -> Any:
    """The gap where the fingers stopped; stalled (on an object) pushing with the goal's effort."""
    result: GripperCommandResult | None = outcome.result
    if result is None:  # ended before it started: nothing moved, nothing known here
        return types.new(f"{GRIPPER_COMMAND}_Result")
    return types.new(
        f"{GRIPPER_COMMAND}_Result",
        position=result.position,
        effort=goal.max_effort if result.stalled else 0.0,
        stalled=result.stalled,
        reached_goal=result.reached_goal,
    )
