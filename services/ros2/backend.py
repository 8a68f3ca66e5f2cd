"""The ros2 backend's logic, no Zenoh: tether <-> ROS 2 messages, the heartbeat's limits, the robot's stop, its reports.

Conversions both ways (odometry, joint states, detections, the camera; cmd_vel, speed limits, goal
messages), ROS status codes in words, the limits the heartbeat sets, the emergency-stop signal,
and what the robot last reported. goals.py carries tether goals out as ROS goals with these.
"""

from __future__ import annotations

import base64
import io
import logging
import math
import re
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar, get_args

import numpy as np

from schemas.common import METRES_MAX, METRES_MIN, Id, Pose2D, Text, Vec3, preview
from schemas.robot import (
    ARM_JOINTS,
    FINGER_JOINTS,
    JointState,
    Odometry,
    Twist,
)
from schemas.world import CameraImage, PerceivedHuman, PerceivedHumans, PerceivedObject, PerceivedObjects, World
from services.robotrules import SafetyNow
from services.ros2.config import Frames
from services.ros2.wire import GoalStatus
from services.worldmodel import WorldModel

log = logging.getLogger(__name__)

# The ROS 2 types the robot speaks.
TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
BOOL = "std_msgs/msg/Bool"
SPEED_LIMIT = "nav2_msgs/msg/SpeedLimit"
ODOMETRY = "nav_msgs/msg/Odometry"
JOINT_STATE = "sensor_msgs/msg/JointState"
DETECTIONS = "vision_msgs/msg/Detection3DArray"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"
NAVIGATE_THROUGH_POSES = "nav2_msgs/action/NavigateThroughPoses"
FOLLOW_JOINT_TRAJECTORY = "control_msgs/action/FollowJointTrajectory"
GRIPPER_COMMAND = "control_msgs/action/GripperCommand"
PARALLEL_GRIPPER_COMMAND = "control_msgs/action/ParallelGripperCommand"
TRIGGER = "std_srvs/srv/Trigger"

TRAJECTORY_ERRORS = {
    -1: "INVALID_GOAL",
    -2: "INVALID_JOINTS",
    -3: "OLD_HEADER_TIMESTAMP",
    -4: "PATH_TOLERANCE_VIOLATED",
    -5: "GOAL_TOLERANCE_VIOLATED",
}
NAV2_ERRORS = {9000: "UNKNOWN", 9001: "FAILED_TO_LOAD_BEHAVIOR_TREE", 9002: "TF_ERROR", 9003: "TIMEOUT"}

R = TypeVar("R")  # a report kept from the robot: odometry, joint states

# A trajectory's goal_time_tolerance: the arm has this long after the last point to settle within
# the goal tolerance (the sim's TRAJECTORY_SETTLE_TIME).
TRAJECTORY_SETTLE = 1.0
# Problems on the way from the robot kept for failure messages: how many, for how long (seconds).
PROBLEMS_KEPT = 32
PROBLEM_MEMORY = 5.0
# The robot's diagnostics (robot/diagnostics): the distinct problems seen in the last
# DIAGNOSTICS_WINDOW seconds, at most DIAGNOSTICS_KEPT of them.
DIAGNOSTICS_WINDOW = 60.0
DIAGNOSTICS_KEPT = 16
# rmw.py's count of the reports it held back: left out, so a problem that goes on is one entry.
_HELD_BACK = re.compile(r" \(\d+ more like it since the last report\)$")
# The arm's joint states must keep up with the gripper's, merged from two publishers: an arm heard
# longer ago than this (seconds; safety's default state_max_age) is not passed on as current.
JOINTS_MAX_LAG = 0.5
# A robot stamp further than this from our wall clock is not believed: the report is stamped on arrival.
CLOCK_TOLERANCE = 1.0
# builtin_interfaces Duration's seconds are an int32: a trajectory re-timed past this cannot be sent.
DURATION_MAX = 2**31 - 1
# emergency_stop goes out this often, `true` or `false` (docs/robot.md: the controller's rate): a
# dead-man signal, so a robot with a watchdog on it stops when the backend goes quiet.
ESTOP_PERIOD = 0.05


# What the schemas let a report hold, read from their own types (safety decodes by them; a Struct
# built here is not checked against them): what a person's id may look like, how long a goal's
# message may be; where the robot, a person or an object may be is schemas.common's METRES_MIN/MAX.
_ID = get_args(Id)[1]
_ID_PATTERN = re.compile(_ID.pattern)
TEXT_MAX = int(get_args(Text)[1].max_length)
# The robot's own words (Nav2's error_msg, a trajectory's error_string) are cut to this, leaving
# the rest of a goal's message (TEXT_MAX) for what tether says around them.
ROBOT_TEXT_MAX = TEXT_MAX // 4


class RobotCallFailed(Exception):
    """The robot gave no usable answer: none in time, another type hash, undecodable bytes."""


class RobotRefused(RobotCallFailed):
    """The robot's action server answered a goal with accepted = false."""


class RobotLinkClosed(RobotCallFailed):
    """The backend left the robot's network (closing): no call reaches the robot any more."""


class RobotGoalForgotten(RobotCallFailed):
    """The robot's action server says it knows no such goal (it restarted, or forgot it): it runs none."""


class RobotGoalUnanswered(RobotCallFailed):
    """A goal's send_goal got no usable answer: the robot may still take it, as goal `goal_id`."""

    def __init__(self, message: str, goal_id: bytes) -> None:
        super().__init__(message)
        self.goal_id = goal_id


class UnsendableGoal(ValueError):
    """A goal the robot's messages cannot carry (a time beyond a ROS Duration): nothing was sent."""


class RobotReportError(ValueError):
    """A report from the robot that cannot be taken as it is: another frame, values that are not numbers."""


class Builder(Protocol):
    """Makes ROS messages (types.RosTypes)."""

    def new(self, ros_type: str, **fields: Any) -> Any: ...


# Small conversions


def to_seconds(stamp: Any) -> float:
    """builtin_interfaces Time or Duration as seconds."""
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def yaw_of(q: Any) -> float:
    """The rotation about z of a quaternion (x, y, z, w) of any length, as ROS tools take one that is
    not quite unit (rviz normalises it); RobotReportError when its length is 0 or not a number, as
    then it is no rotation at all."""
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    norm = math.hypot(x, y, z, w)
    if norm == 0.0 or not math.isfinite(norm):
        raise RobotReportError(f"orientation (x, y, z, w) = ({x}, {y}, {z}, {w}) has norm {norm}: it is no rotation")
    # Normalised first: the squares of a very short or very long quaternion would underflow or overflow.
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _in_metres(*values: float) -> bool:
    """Whether every value is a place safety can decode (schemas' Metres); False for NaN too."""
    return all(METRES_MIN <= v <= METRES_MAX for v in values)


def robot_text(text: str) -> str:
    """Text the robot wrote (an error message, a frame id), cut to ROBOT_TEXT_MAX characters on one
    line, saying so, so that the goal's message that carries it still fits tether's Text."""
    if len(text) <= ROBOT_TEXT_MAX:
        return text
    note = f" [cut: {len(text)} characters in all]"
    return preview(text, ROBOT_TEXT_MAX - len(note)) + note


def _frame(frame_id: str) -> str:
    return frame_id.lstrip("/")


class Stamps:
    """Report stamps, one clock per source (a topic): the robot's own while its clock agrees with ours;
    once a source's stamp is not believed (off by more than CLOCK_TOLERANCE, not a number, or none
    at all), the time its reports arrive, from then on. Two clocks taken by turns on one topic made
    its stamps jump back and forth by up to the tolerance, and joint speeds estimated from them 0 or
    a fraction of the real ones."""

    def __init__(self) -> None:
        self._on_arrival: set[str] = set()

    def of(self, header: Any, now: float, source: str = "") -> float:
        stamp = to_seconds(header.stamp)
        if source in self._on_arrival:
            return now
        if math.isfinite(stamp) and abs(stamp - now) <= CLOCK_TOLERANCE:
            return stamp
        self._on_arrival.add(source)
        if stamp != 0.0:  # else not stamped at all
            log.warning(
                "the robot's clock is %.1f s off ours (a report on %s stamped %.3f arrived at %.3f): stamping "
                "its reports there on arrival from now on; synchronise the clocks (chrony) for exact stamps",
                stamp - now,
                source or "a topic",
                stamp,
                now,
            )
        return now


class RateLimit:
    """At most `hz` a second on average (GCRA): a report may come up to half a period early, never more."""

    def __init__(self, hz: float) -> None:
        self.period = 1.0 / hz
        self._next = -math.inf

    def allow(self, now: float) -> bool:
        if now < self._next - self.period / 2:
            return False
        self._next = max(self._next, now - self.period / 2) + self.period
        return True


# tether -> ROS


class Messages:
    """The ROS messages tether's commands and goals become."""

    def __init__(
        self,
        types: Builder,
        frames: Frames,
        *,
        stamped_cmd_vel: bool,
        parallel_gripper_joint: str = "",
        gripper_position_per_gap: float = 1.0,
    ) -> None:
        self.types = types
        self.frames = frames
        self.stamped_cmd_vel = stamped_cmd_vel
        self.parallel_gripper_joint = parallel_gripper_joint
        self.gripper_position_per_gap = gripper_position_per_gap

    @property
    def cmd_vel_type(self) -> str:
        return TWIST_STAMPED if self.stamped_cmd_vel else TWIST

    def time(self, seconds: float) -> Any:
        sec = math.floor(seconds)
        nanosec = min(round((seconds - sec) * 1e9), 999_999_999)
        return self.types.new("builtin_interfaces/msg/Time", sec=int(sec), nanosec=nanosec)

    def duration(self, seconds: float) -> Any:
        """UnsendableGoal past DURATION_MAX (a Duration's seconds are an int32), rather than failing to encode."""
        if not 0.0 <= seconds < DURATION_MAX + 1:
            raise UnsendableGoal(f"a duration of {seconds:.3g} s, where a ROS Duration holds 0 to {DURATION_MAX} s")
        sec = math.floor(seconds)
        nanosec = min(round((seconds - sec) * 1e9), 999_999_999)
        return self.types.new("builtin_interfaces/msg/Duration", sec=int(sec), nanosec=nanosec)

    def header(self, stamp: float, frame_id: str) -> Any:
        return self.types.new("std_msgs/msg/Header", stamp=self.time(stamp), frame_id=frame_id)

    def cmd_vel(self, linear_x: float, angular_z: float, stamp: float) -> Any:
        new = self.types.new
        twist = new(
            TWIST,
            linear=new("geometry_msgs/msg/Vector3", x=float(linear_x)),
            angular=new("geometry_msgs/msg/Vector3", z=float(angular_z)),
        )
        if not self.stamped_cmd_vel:
            return twist
        return new(TWIST_STAMPED, header=self.header(stamp, self.frames.base), twist=twist)

    def flag(self, value: bool) -> Any:
        return self.types.new(BOOL, data=value)

    def speed_limit(self, metres_per_second: float, stamp: float) -> Any:
        """Nav2's SpeedLimit in m/s (percentage false); never 0, which Nav2 reads as no limit."""
        return self.types.new(
            SPEED_LIMIT,
            header=self.header(stamp, self.frames.base),
            percentage=False,
            speed_limit=float(metres_per_second),
        )

    def pose(self, pose: Pose2D, stamp: float) -> Any:
        new = self.types.new
        return new(
            "geometry_msgs/msg/PoseStamped",
            header=self.header(stamp, self.frames.odom),
            pose=new(
                "geometry_msgs/msg/Pose",
                position=new("geometry_msgs/msg/Point", x=pose.x, y=pose.y),
                orientation=new("geometry_msgs/msg/Quaternion", z=math.sin(pose.yaw / 2), w=math.cos(pose.yaw / 2)),
            ),
        )

    def navigate(self, poses: Sequence[Pose2D], stamp: float) -> tuple[bool, Any]:
        """NavigateToPose for one pose, NavigateThroughPoses for several; whether it is the latter, and the goal."""
        if len(poses) == 1:
            return False, self.types.new(f"{NAVIGATE_TO_POSE}_Goal", pose=self.pose(poses[0], stamp))
        return True, self.types.new(f"{NAVIGATE_THROUGH_POSES}_Goal", poses=[self.pose(p, stamp) for p in poses])

    def trajectory(
        self,
        joint_names: Sequence[str],
        points: Sequence[tuple[Sequence[float], float]],
        *,
        path_tolerance: float,
        goal_tolerance: float,
    ) -> Any:
        """A FollowJointTrajectory goal: positions only (ros2_control's joint_trajectory_controller then
        interpolates linearly, as tether's protocol does), with the goal's tolerances for every joint."""
        new = self.types.new
        trajectory = new(
            "trajectory_msgs/msg/JointTrajectory",
            joint_names=list(joint_names),
            points=[
                new(
                    "trajectory_msgs/msg/JointTrajectoryPoint",
                    positions=np.asarray(positions, dtype=np.float64),
                    time_from_start=self.duration(t),
                )
                for positions, t in points
            ],
        )

        def tolerances(position: float) -> list[Any]:
            return [new("control_msgs/msg/JointTolerance", name=name, position=position) for name in joint_names]

        return new(
            f"{FOLLOW_JOINT_TRAJECTORY}_Goal",
            trajectory=trajectory,
            path_tolerance=tolerances(path_tolerance),
            goal_tolerance=tolerances(goal_tolerance),
            goal_time_tolerance=self.duration(TRAJECTORY_SETTLE),
        )

    def gripper(self, gap: float, max_effort: float) -> Any:
        new = self.types.new
        if self.parallel_gripper_joint:
            # One finger joint moves half the gap (the Panda's).
            command = new(
                JOINT_STATE,
                name=[self.parallel_gripper_joint],
                position=np.array([gap / 2], dtype=np.float64),
                effort=np.array([max_effort], dtype=np.float64),
            )
            return new(f"{PARALLEL_GRIPPER_COMMAND}_Goal", command=command)
        position = float(gap) * self.gripper_position_per_gap
        command = new("control_msgs/msg/GripperCommand", position=position, max_effort=float(max_effort))
        return new(f"{GRIPPER_COMMAND}_Goal", command=command)


# ROS -> tether


def odometry(message: Any, frame: str, stamp: float) -> Odometry:
    """nav_msgs/Odometry as tether's, or RobotReportError: tether's map frame is the robot's `frame`,
    and there is no tf on tether's side to bring another frame into it."""
    got = _frame(message.header.frame_id)
    if got != _frame(frame):
        raise RobotReportError(
            f"odometry in frame {got!r}, expected {frame!r} ([ros2.frames] odom): refused, as tether has no "
            "transform from it to its map frame"
        )
    position, twist = message.pose.pose.position, message.twist.twist
    try:
        yaw = yaw_of(message.pose.pose.orientation)
    except RobotReportError as exc:
        raise RobotReportError(f"odometry whose {exc}") from None
    x, y = float(position.x), float(position.y)
    linear, angular = float(twist.linear.x), float(twist.angular.z)
    if not _finite(x, y, yaw, linear, angular):
        raise RobotReportError(f"odometry with values that are not numbers: x={x}, y={y}, v={linear}, w={angular}")
    if not _in_metres(x, y):
        raise RobotReportError(
            f"odometry at ({x:g}, {y:g}): outside {METRES_MIN:g} to {METRES_MAX:g} m (tether's Metres), a pose "
            "safety could not read"
        )
    return Odometry(stamp=stamp, sim_time=stamp, pose=Pose2D(x=x, y=y, yaw=yaw), linear_x=linear, angular_z=angular)


class JointMerger:
    """sensor_msgs/JointState messages as tether's JointState: the arm's seven joints then the two
    fingers, merged over messages (a robot may publish its arm and gripper apart), velocities
    estimated from positions when the robot sends none. The merged state carries the stamp of the
    message that completed it; a message naming none of its joints adds nothing and is not passed on.

    The `keeping_up` joints (the arm's) must have been heard within `max_lag` seconds of every
    message merged: when their publisher stops while another (the gripper's) goes on, nothing is
    passed on (`lagging` names them), rather than their last positions under a fresh stamp. Safety
    ages joint states by when they arrive, so it then finds them missing, refuses arm motion and
    trips its watchdog if the arm was moving. The others (fingers) may be reported only on change."""

    def __init__(
        self,
        names: Sequence[str] = (*ARM_JOINTS, *FINGER_JOINTS),
        keeping_up: Sequence[str] = ARM_JOINTS,
        max_lag: float = JOINTS_MAX_LAG,
    ) -> None:
        self.names = tuple(names)
        self.keeping_up = tuple(name for name in keeping_up if name in self.names)
        self.max_lag = max_lag
        self._position: dict[str, float] = {}
        self._velocity: dict[str, float] = {}
        self._heard: dict[str, float] = {}
        self._lagging: list[str] = []

    def update(self, message: Any, stamp: float) -> JointState | None:
        """The joint state with `message` merged in; None until every joint has been heard, and
        None for a message holding none of them (nothing new to say)."""
        names = list(message.name)
        positions = [float(p) for p in message.position]
        velocities = [float(v) for v in message.velocity]
        if len(positions) != len(names):
            raise RobotReportError(f"joint states with {len(names)} names and {len(positions)} positions")
        if velocities and len(velocities) != len(names):
            raise RobotReportError(f"joint states with {len(names)} names and {len(velocities)} velocities")
        if len(set(names)) != len(names):
            twice = [name for name, count in Counter(names).items() if count > 1]
            raise RobotReportError(f"joint states naming {', '.join(map(repr, twice[:3]))} more than once")
        if not _finite(*positions, *velocities):
            raise RobotReportError("joint states with positions or velocities that are not numbers")
        heard: dict[str, tuple[float, float]] = {}  # ours in the message: position, velocity
        for k, name in enumerate(names):
            if name not in self.names:
                continue
            if velocities:
                velocity = velocities[k]
            elif name in self._heard and stamp > self._heard[name]:
                velocity = (positions[k] - self._position[name]) / (stamp - self._heard[name])
            else:
                velocity = 0.0
            if not math.isfinite(velocity):
                raise RobotReportError(
                    f"joint states moving {name} from {self._position[name]} to {positions[k]} in "
                    f"{stamp - self._heard[name]:.3g} s: a speed that is not a number"
                )
            heard[name] = positions[k], velocity
        if not heard:
            return None
        for name, (position, velocity) in heard.items():  # only once the whole message is taken
            self._position[name], self._velocity[name], self._heard[name] = position, velocity, stamp
        if len(self._position) < len(self.names):
            return None
        self._lagging = [name for name in self.keeping_up if stamp - self._heard[name] > self.max_lag]
        if self._lagging:
            return None
        return JointState(
            stamp=stamp,
            name=list(self.names),
            position=[self._position[n] for n in self.names],
            velocity=[self._velocity[n] for n in self.names],
        )

    def missing(self) -> list[str]:
        return [n for n in self.names if n not in self._position]

    def lagging(self) -> list[str]:
        """The `keeping_up` joints not heard within `max_lag` of the last message merged."""
        return list(self._lagging)


@dataclass(frozen=True)
class Perceived:
    """What one Detection3DArray said: objects (None when it was a people tracker's), people (None
    when it held none), and what could not be taken."""

    objects: PerceivedObjects | None
    humans: PerceivedHumans | None
    problems: list[str] = field(default_factory=list)


class Perception:
    """vision_msgs/Detection3DArray as world/objects and world/humans, named from the world file.

    A detection is an object of the world when its id is one, or when `class_map` maps its id or its
    class (results[0].hypothesis.class_id) to one; a detection of `person_class` is a person. Poses
    are in the odom frame (tether's map frame); one whose header names the gripper frame is the
    object in the gripper (`on` "gripper", its pose still in odom coordinates). Room and furniture
    (`on`) come from the world file. An array holding only people is a people tracker's (world/humans
    only); any other, also an empty one, is what the camera sees now (world/objects).
    """

    def __init__(self, world: World, class_map: dict[str, str], person_class: str, frames: Frames) -> None:
        self.model = WorldModel(world)
        self.class_map = class_map
        self.person_class = person_class
        self.frames = frames
        self.people = {h.id: h for h in world.humans}

    def read(self, message: Any, stamp: float) -> Perceived:
        objects: dict[str, tuple[float, PerceivedObject]] = {}
        humans: list[PerceivedHuman] = []
        problems: list[str] = []
        detections = message.detections
        if len(detections) > MAX_DETECTIONS:
            problems.append(f"{len(detections)} detections in one message; the first {MAX_DETECTIONS} are read")
            detections = detections[:MAX_DETECTIONS]
        people_only = bool(detections)
        for k, detection in enumerate(detections):
            hypothesis = detection.results[0] if detection.results else None
            class_id = str(hypothesis.hypothesis.class_id) if hypothesis is not None else ""
            score = float(hypothesis.hypothesis.score) if hypothesis is not None else 0.0
            pose = hypothesis.pose.pose if hypothesis is not None else detection.bbox.center
            frame = _frame(detection.header.frame_id or message.header.frame_id)
            ident = str(detection.id)
            x, y, z = float(pose.position.x), float(pose.position.y), float(pose.position.z)
            if not _in_metres(x, y, z):
                problems.append(f"detection {k} ({ident or class_id}) at ({x}, {y}, {z}): not a place in the world")
                continue
            is_person = class_id == self.person_class or ident in self.people
            if is_person:
                if frame != _frame(self.frames.odom):
                    problems.append(f"person {ident or k} in frame {frame!r}, expected {self.frames.odom!r}")
                    continue
                try:
                    yaw = yaw_of(pose.orientation)
                except RobotReportError as exc:
                    # Kept, where it stands: a person left out would be one safety keeps no distance from.
                    problems.append(f"person {ident or k}: its {exc}; taken as facing along x")
                    yaw = 0.0
                humans.append(self._person(ident, k, x, y, yaw, len(humans)))
                continue
            people_only = False
            seen = self._object(ident, class_id, x, y, z, pose.orientation, frame, stamp, problems)
            if seen is not None and (seen.id not in objects or objects[seen.id][0] < score):
                objects[seen.id] = (score, seen)
        perceived_objects = None
        if not people_only:
            perceived_objects = PerceivedObjects(stamp=stamp, objects=[o for _, o in objects.values()])
        perceived_humans = PerceivedHumans(stamp=stamp, humans=humans) if humans else None
        return Perceived(perceived_objects, perceived_humans, problems)

    def _person(self, ident: str, k: int, x: float, y: float, yaw: float, n: int) -> PerceivedHuman:
        known = self.people.get(ident)
        person_id = ident if known is not None or _is_id(ident) else f"person_{n}"
        return PerceivedHuman(
            id=person_id,
            name=known.name if known is not None else "person",
            pose=Pose2D(x=x, y=y, yaw=yaw),
            room=self.model.room_of(x, y),
        )

    def _object(
        self,
        ident: str,
        class_id: str,
        x: float,
        y: float,
        z: float,
        orientation: Any,
        frame: str,
        stamp: float,
        problems: list[str],
    ) -> PerceivedObject | None:
        objects = self.model.objects
        object_id = ident if ident in objects else self.class_map.get(ident) or self.class_map.get(class_id)
        if object_id is None or object_id not in objects:
            problems.append(
                f"detection {ident!r} of class {class_id!r} is no object of the world; map it in [ros2] class_map"
            )
            return None
        held = frame == _frame(self.frames.gripper)
        if not held and frame != _frame(self.frames.odom):
            problems.append(
                f"{object_id} detected in frame {frame!r}, expected {self.frames.odom!r} or {self.frames.gripper!r}"
            )
            return None
        obj = objects[object_id]
        position = Vec3(x=x, y=y, z=z)
        on = "gripper" if held else self.model.support_under(position, obj.size.z / 2)
        yaw = None
        if obj.shape == "box" and abs(obj.size.x - obj.size.y) > 1e-3 and not _identity(orientation):
            try:
                heading = yaw_of(orientation)
            except RobotReportError as exc:
                problems.append(f"{object_id} detected, but its {exc}")
                return None
            # A rectangle looks the same turned half round: its heading modulo a half turn.
            yaw = math.atan(math.tan(heading)) if abs(math.cos(heading)) > 1e-9 else math.pi / 2
        return PerceivedObject(
            id=obj.id,
            name=obj.name,
            cls=obj.cls,
            color=obj.color,
            position=position,
            room=self.model.room_of(x, y),
            on=on,
            stamp=stamp,
            yaw=yaw,
        )


def _identity(q: Any) -> bool:
    """The quaternion a detector leaves when it saw no orientation (ROS 2's default)."""
    return float(q.w) == 1.0 and float(q.x) == float(q.y) == float(q.z) == 0.0


def _is_id(text: str) -> bool:
    """Whether `text` is an id as the schemas' Id takes one (ASCII letters and digits, not any letter)."""
    return _ID.min_length <= len(text) <= _ID.max_length and _ID_PATTERN.fullmatch(text) is not None


# A camera picture's largest side, checked before it is decoded.
MAX_IMAGE_SIDE = 4096
# Detections read from one message; a detector's real scenes hold far fewer.
MAX_DETECTIONS = 256
# The most each report from the robot may weigh on the wire (bytes), checked before it is decoded:
# a robot's real ones are far smaller (an odometry about 700 bytes, a picture MAX_IMAGE_SIDE square
# at 4 bytes a pixel), and a peer sending more (a JointState of millions of names, a gigabyte
# picture) would cost the backend far more memory and time to decode than its bytes.
REPORT_MAX_BYTES = {
    ODOMETRY: 1 << 16,
    JOINT_STATE: 1 << 18,  # a thousand joints with long names
    DETECTIONS: 1 << 22,  # thousands of detections, of which MAX_DETECTIONS are read
    IMAGE: MAX_IMAGE_SIDE * MAX_IMAGE_SIDE * 4 + (1 << 16),
    COMPRESSED_IMAGE: MAX_IMAGE_SIDE * MAX_IMAGE_SIDE * 4 + (1 << 16),
}


def camera_image(message: Any, stamp: float) -> CameraImage:
    """sensor_msgs CompressedImage or Image as a PNG CameraImage; RobotReportError when it holds none."""
    from PIL import Image  # only when asked for a picture

    picture: Image.Image
    if hasattr(message, "format"):  # CompressedImage
        data = bytes(message.data)
        if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
            width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
            return _png(data, width, height, stamp)
        try:
            picture = Image.open(io.BytesIO(data))
            _check_size(picture.width, picture.height)  # from the header, before decoding: no bombs
            picture.load()
        except RobotReportError:
            raise
        except Exception as exc:
            raise RobotReportError(
                f"the camera's {message.format or 'compressed'} image does not decode: {exc}"
            ) from exc
    else:  # Image
        modes = {"rgb8": ("RGB", "RGB"), "bgr8": ("RGB", "BGR"), "rgba8": ("RGBA", "RGBA"), "mono8": ("L", "L")}
        if message.encoding not in modes:
            raise RobotReportError(f"camera image encoding {message.encoding!r}; tether reads {', '.join(modes)}")
        mode, raw = modes[message.encoding]
        _check_size(int(message.width), int(message.height))
        try:
            picture = Image.frombuffer(
                mode, (int(message.width), int(message.height)), bytes(message.data), "raw", raw, int(message.step), 1
            )
        except Exception as exc:
            raise RobotReportError(
                f"camera image {message.width}x{message.height} does not fit its data: {exc}"
            ) from exc
    buffer = io.BytesIO()
    picture.save(buffer, format="PNG")
    return _png(buffer.getvalue(), picture.width, picture.height, stamp)


def _check_size(width: int, height: int) -> None:
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        raise RobotReportError(
            f"camera image of {width}x{height} pixels; tether takes up to {MAX_IMAGE_SIDE}x{MAX_IMAGE_SIDE}"
        )


def _png(data: bytes, width: int, height: int, stamp: float) -> CameraImage:
    _check_size(width, height)
    return CameraImage(stamp=stamp, width=width, height=height, data=base64.b64encode(data).decode())


# Limits and the stop signal


@dataclass(frozen=True)
class BaseLimits:
    """The base's own top speeds, and what the heartbeat leaves of them (docs/robot.md: the robot's
    maximum times the scale, and the heartbeat's limits when given; a limit never raises it)."""

    max_linear: float
    max_angular: float

    def caps(self, safety: SafetyNow) -> tuple[float, float]:
        """The forward speed and turn rate the base may use now (0 while blocked)."""
        scale, status = safety.speed_scale, safety.status
        linear, angular = self.max_linear * scale, self.max_angular * scale
        if status is not None and status.max_linear_speed is not None:
            linear = min(linear, status.max_linear_speed)
        if status is not None and status.max_angular_speed is not None:
            angular = min(angular, status.max_angular_speed)
        return max(linear, 0.0), max(angular, 0.0)

    def clamp(self, twist: Twist, safety: SafetyNow) -> tuple[float, float]:
        """cmd_vel within the caps."""
        linear, angular = self.caps(safety)
        return (max(-linear, min(linear, twist.linear_x)), max(-angular, min(angular, twist.angular_z)))

    def navigation_limit(
        self, safety: SafetyNow, max_speed: float | None = None, max_turn_rate: float | None = None
    ) -> float:
        """Nav2's speed limit (m/s) for a navigation at most `max_speed` and `max_turn_rate`: the
        robot scales its turn rate by the same fraction of its top speed, so the fraction is the
        smaller of the two."""
        linear, angular = self.caps(safety)
        if max_speed is not None:
            linear = min(linear, max_speed)
        if max_turn_rate is not None:
            angular = min(angular, max_turn_rate)
        fraction = min(1.0, linear / self.max_linear, angular / self.max_angular)
        return fraction * self.max_linear


class EstopSignal:
    """When to tell the robot its own stop (std_msgs/Bool emergency_stop): the current value at once
    when it changes and every ESTOP_PERIOD always, `true` while safety blocks the robot and `false`
    while it may move: a dead-man signal, whose silence a robot's watchdog takes for a stop."""

    def __init__(self) -> None:
        self._blocked: bool | None = None
        self._next = 0.0

    def due(self, blocked: bool, now: float) -> bool | None:
        """The value to publish now, or None."""
        if blocked != self._blocked or now >= self._next:
            self._blocked = blocked
            self._next = now + ESTOP_PERIOD
            return blocked
        return None

    @property
    def next_at(self) -> float:
        return self._next


class CmdVelHold:
    """The cmd_vel the robot holds: the command asked, what was sent for it, and when it was asked.

    It holds for `timeout` from the command (a re-send, clamped to a lower limit, never extends it);
    then one zero Twist ends it, as the backend's own end of the command rather than the robot's
    (a robot whose controller has no cmd_vel timeout would drive on)."""

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout
        self._held: tuple[Twist, float, float, float] | None = None  # asked, sent linear, angular, when asked

    def sent(self, twist: Twist, linear: float, angular: float, now: float) -> None:
        self._held = (twist, linear, angular, now)

    def clear(self) -> None:
        self._held = None

    @property
    def ends_at(self) -> float | None:
        return None if self._held is None else self._held[3] + self.timeout

    def due(self, clamp: Callable[[Twist], tuple[float, float]], now: float) -> tuple[float, float] | None:
        """The command to send now: zero once the hold is over, the held one clamped when a limit
        dropped below what was sent; else None."""
        if self._held is None:
            return None
        twist, linear, angular, at = self._held
        if now - at >= self.timeout:
            self._held = None
            return 0.0, 0.0
        clamped = clamp(twist)
        if abs(clamped[0]) >= abs(linear) - 1e-9 and abs(clamped[1]) >= abs(angular) - 1e-9:
            return None
        self._held = (twist, clamped[0], clamped[1], at)
        return clamped


# Status codes


def ros_failure(label: str, status: int, error: str) -> str:
    """Why a ROS goal that did not succeed ended, for the tether goal's message."""
    name = GoalStatus(status).name if status in GoalStatus._value2member_map_ else str(status)
    if status == GoalStatus.ABORTED:
        return f"the robot aborted the {label} goal: {error or 'no reason given'}"
    if status == GoalStatus.CANCELED:
        return f"the robot canceled the {label} goal on its own{': ' + error if error else ''}"
    return f"the robot ended the {label} goal with status {name}{': ' + error if error else ''}"


def trajectory_error(result: Any) -> str:
    """A FollowJointTrajectory result's error in words; '' when it has none."""
    if result is None:
        return ""
    code = int(result.error_code)
    if code == 0:
        return ""
    text = robot_text(str(result.error_string))
    name = TRAJECTORY_ERRORS.get(code, f"error {code}")
    return f"{name}: {text}" if text else name


# Nav2's result for a goal it aborted without a code or a word: so its SimpleActionServer ends a goal
# a newer one preempted, on the same navigator or (the navigator muxer) the other one.
NAV2_NO_REASON = "no reason given (Nav2 gives none when another goal on the robot preempts it)"


def navigation_error(result: Any) -> str:
    if result is None:
        return ""
    code = int(getattr(result, "error_code", 0))
    text = robot_text(str(getattr(result, "error_msg", "")))
    if code == 0:
        return text
    name = NAV2_ERRORS.get(code, f"error {code}")
    return f"{name}: {text}" if text else name


def gripper_error(result: Any, position_per_gap: float = 1.0) -> str:
    """A GripperCommand (or ParallelGripperCommand) result that did not succeed, in words; '' when it
    says nothing. gripper_action_controller aborts a goal whose fingers stall short of it (unless
    allow_stalling), saying so only in its result. `position_per_gap`: Messages.gripper_position_per_gap."""
    if result is None or not bool(getattr(result, "stalled", False)):
        return ""
    if hasattr(result, "state"):  # ParallelGripperCommand: one finger joint, half the gap
        position = float(result.state.position[0]) * 2 if len(result.state.position) else math.nan
    else:
        position = float(result.position) / position_per_gap
    where = f" at {position * 1000:.0f} mm" if math.isfinite(position) else ""
    return f"the fingers stalled{where}, short of the goal"


# What the robot reports, as the goal runs read it


class RobotState:
    """The latest odometry, joint states and objects the robot reported, and what went wrong on the
    way: the problems with its reports (for the messages of the failures they explain), and those
    and the goals it failed (for its diagnostics)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, odom_topic: str = "odom") -> None:
        self.clock = clock
        self.odom_topic = odom_topic
        self._changed = threading.Condition()
        self._odom: Odometry | None = None
        self._odom_at = -math.inf
        self._joints: JointState | None = None
        self._joints_at = -math.inf
        self._objects: PerceivedObjects | None = None
        self._objects_at = -math.inf
        self._problems: deque[tuple[float, str]] = deque(maxlen=PROBLEMS_KEPT)
        self._seen: dict[str, float] = {}  # problem -> when last seen, the latest last

    def heard_odometry(self, odom: Odometry) -> None:
        with self._changed:
            self._odom, self._odom_at = odom, self.clock()
            self._changed.notify_all()

    def refused_odometry(self, why: str) -> None:
        self.problem(f"it sends {why}")

    def heard_joints(self, joints: JointState) -> None:
        with self._changed:
            self._joints, self._joints_at = joints, self.clock()
            self._changed.notify_all()

    def heard_objects(self, objects: PerceivedObjects) -> None:
        with self._changed:
            self._objects, self._objects_at = objects, self.clock()
            self._changed.notify_all()

    def problem(self, text: str) -> None:
        """Something refused on the way (another type hash, undecodable bytes, another frame), for the
        message of the next failure it explains."""
        with self._changed:
            now = self.clock()
            self._problems.append((now, text))
            self._saw(text, now)

    def goal_failed(self, text: str) -> None:
        """A goal that failed by the robot's doing (refused, unanswered, aborted, not stopped), for the diagnostics."""
        with self._changed:
            self._saw(text, self.clock())

    def _saw(self, text: str, now: float) -> None:
        problem = _HELD_BACK.sub("", text)
        self._seen.pop(problem, None)
        self._seen[problem] = now
        if len(self._seen) > DIAGNOSTICS_KEPT:
            del self._seen[next(iter(self._seen))]

    def diagnostics(self, within: float = DIAGNOSTICS_WINDOW) -> list[tuple[str, float]]:
        """Each problem seen in the last `within` seconds and when it was last seen (clock), the latest first."""
        with self._changed:
            since = self.clock() - within
            return [(text, at) for text, at in reversed(self._seen.items()) if at >= since]

    def recent_problem(self, within: float = PROBLEM_MEMORY, about: tuple[str, ...] = ("",)) -> str:
        """The latest problem in the last `within` seconds whose text names one of `about`; '' if none."""
        with self._changed:
            since = self.clock() - within
            for at, text in reversed(self._problems):
                if at >= since and any(word in text for word in about):
                    return text
        return ""

    def odometry(self, max_age: float) -> Odometry | str:
        """The latest odometry if it is at most `max_age` old; else why there is none."""
        with self._changed:
            odom, at = self._odom, self._odom_at
        return self._fresh(odom, at, max_age, "odometry", ("odometry", self.odom_topic.strip("/")))

    def joint_states(self, max_age: float) -> JointState | str:
        """The latest joint states if they are at most `max_age` old; else why there are none."""
        with self._changed:
            joints, at = self._joints, self._joints_at
        return self._fresh(joints, at, max_age, "joint states", ("joint states",))

    def _fresh(self, latest: R | None, at: float, max_age: float, what: str, about: tuple[str, ...]) -> R | str:
        """`latest`, received at `at`, if it is at most `max_age` old; else why there is none, with the
        robot's latest problem `about` it."""
        age = self.clock() - at
        if latest is not None and age <= max_age:
            return latest
        why = f"no {what} from the robot yet" if latest is None else f"no {what} from the robot for {age:.1f} s"
        if problem := self.recent_problem(about=about):
            why += f"; {robot_text(problem)}"  # it may quote the robot (a frame id) at any length
        return why

    @property
    def latest_odometry(self) -> Odometry | None:
        with self._changed:
            return self._odom

    @property
    def joints(self) -> JointState | None:
        with self._changed:
            return self._joints

    def fresh_joints(self, since: float, timeout: float) -> JointState | None:
        """The first joint state heard after `since` (clock seconds), waiting up to `timeout`; else the latest."""
        with self._changed:
            self._changed.wait_for(lambda: self._joints_at > since, timeout)
            return self._joints

    def fresh_odometry(self, since: float, timeout: float) -> Odometry | None:
        with self._changed:
            self._changed.wait_for(lambda: self._odom_at > since, timeout)
            return self._odom

    def fresh_objects(self, since: float, timeout: float) -> PerceivedObjects | None:
        """The first objects report after `since`, waiting up to `timeout`; None if none came."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._objects_at > since, timeout):
                return None
            return self._objects

    def ready(self) -> list[str]:
        """What has not been heard from the robot yet (odometry, joint states)."""
        with self._changed:
            return [name for name, value in (("odometry", self._odom), ("joint states", self._joints)) if value is None]


def gripper_gap(joints: JointState | None) -> float | None:
    """The finger gap: the two finger joints' positions added (each finger moves half of it)."""
    if joints is None or not all(n in joints.name for n in FINGER_JOINTS):
        return None
    return sum(joints.position[joints.name.index(n)] for n in FINGER_JOINTS)
