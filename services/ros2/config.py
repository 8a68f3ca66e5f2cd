"""The ros2 backend's frozen config, `[ros2]`: where the robot is, its names and frames, timing and limits."""

from __future__ import annotations

import os
from typing import Annotated, Literal

import msgspec
from msgspec import Meta

from services.ros2.wire import Style

Hz = Annotated[float, Meta(gt=0.0, le=1000.0)]
WallSeconds = Annotated[float, Meta(gt=0.0, le=60.0)]
# A ROS 2 topic, service or action name, relative (to [ros2] namespace) or absolute.
RosName = Annotated[
    str, Meta(min_length=1, max_length=256, pattern=r"^~?/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")
]
FrameId = Annotated[str, Meta(min_length=1, max_length=256, pattern=r"^[A-Za-z0-9_./-]+$")]
ClassName = Annotated[str, Meta(min_length=1, max_length=200)]
ObjectId = Annotated[str, Meta(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:-]+$")]
# rmw_zenoh's router listens here on the robot.
ROBOT_ROUTER = "tcp/127.0.0.1:7447"
# The bundled nav2_msgs and control_msgs interfaces (services/ros2/interfaces) are Jazzy's: another
# distribution's differ on the wire, in either style (CDR), and rmw_zenoh also checks their hashes.
SUPPORTED_DISTROS = ("jazzy",)
UNSUPPORTED_DISTROS = {
    "humble": "Humble's rmw_zenoh has no RIHS01 type hashes in its keys, and its nav2 action results "
    "have no error_code (not the bundled Jazzy interfaces)",
    "iron": "Iron is end of life and its nav2 action results have no error_code (not the bundled Jazzy interfaces)",
    "kilted": "Kilted's nav2 NavigateThroughPoses takes nav_msgs/Goals (not the bundled Jazzy interfaces)",
}


class Names(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """`[ros2.names]`: the robot's topics, actions and services, as remapped on the robot."""

    cmd_vel: RosName = "cmd_vel"
    speed_limit: RosName = "speed_limit"
    emergency_stop: RosName = "emergency_stop"
    odom: RosName = "odom"
    joint_states: RosName = "joint_states"
    detections: RosName = "detections"
    camera: RosName = "camera/image/compressed"
    navigate_to_pose: RosName = "navigate_to_pose"
    navigate_through_poses: RosName = "navigate_through_poses"
    follow_joint_trajectory: RosName = "arm_controller/follow_joint_trajectory"
    gripper: RosName = "gripper_controller/gripper_cmd"
    # The robot's own stop, called when safety stops the robot (with `stop_service = true`).
    stop: RosName = "stop"


class Frames(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """`[ros2.frames]`: the robot's frames. tether's map frame is the robot's `odom` frame: odometry
    in any other frame is refused (there is no tf on tether's side)."""

    odom: FrameId = "odom"
    base: FrameId = "base_link"
    # A detection in this frame is the object in the gripper.
    gripper: FrameId = "panda_hand"


class Ros2Config(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """`[ros2]` in the config file. Timeouts are wall seconds; rates are per wall second, at most."""

    # The robot's Zenoh router (rmw_zenoh's listens on 7447), or zenoh-bridge-ros2dds's.
    endpoint: Annotated[str, Meta(pattern=r"^(tcp|udp|tls|quic|ws|unixsock-stream)/.+$", max_length=300)] = ROBOT_ROUTER
    # A Zenoh config file (JSON5) for the robot's side instead of `endpoint` (TLS, access control).
    zenoh_config: Annotated[str, Meta(max_length=1000)] = ""
    # None: ROS_DOMAIN_ID from the environment, else 0.
    domain_id: Annotated[int, Meta(ge=0, le=232)] | None = None
    namespace: Annotated[str, Meta(max_length=256, pattern=r"^(/?[A-Za-z_][A-Za-z0-9_]*)*/?$")] = ""
    # rmw_zenoh's keys (domain/name/type/hash) or zenoh-bridge-ros2dds's plain names.
    style: Style = Style.RMW_ZENOH
    # Only "jazzy" is supported (SUPPORTED_DISTROS); the others are named so the refusal can say why.
    distro: Literal["humble", "iron", "jazzy", "kilted"] = "jazzy"
    node_name: Annotated[str, Meta(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$", max_length=100)] = "tether"
    # geometry_msgs/msg/TwistStamped on cmd_vel (recent Nav2 and ros2_control), else Twist.
    stamped_cmd_vel: bool = False
    # control_msgs GripperCommand, or ParallelGripperCommand naming `gripper_joint`.
    gripper_action: Literal["gripper_command", "parallel_gripper_command"] = "gripper_command"
    gripper_joint: Annotated[str, Meta(min_length=1, max_length=64)] = "panda_finger_joint1"
    # GripperCommand's position per metre of finger gap, both ways: 1.0 when it is the gap, 0.5 when
    # it is one finger joint's travel (a Panda's gripper_action_controller on panda_finger_joint1).
    gripper_position_per_gap: Annotated[float, Meta(gt=0.0, le=100.0)] = 1.0
    # The camera on `names.camera`: sensor_msgs CompressedImage, or Image (rgb8, bgr8, rgba8, mono8).
    camera_format: Literal["compressed", "raw"] = "compressed"
    # Call the robot's std_srvs/srv/Trigger `names.stop` when safety stops it (besides emergency_stop).
    stop_service: bool = False
    names: Names = Names()
    frames: Frames = Frames()
    # A detection's class (results[0].hypothesis.class_id) or id -> the world file's object id.
    # A detection whose id is already an object id in the world needs no entry.
    class_map: dict[ClassName, ObjectId] = {}
    # Detections of this class are people (world/humans).
    person_class: ClassName = "person"
    # The world file: object names, classes and colours, rooms, the furniture objects stand on, the robot.
    world: Annotated[str, Meta(min_length=1, max_length=1000)] = "household"
    heartbeat_timeout: WallSeconds = 0.2
    first_heartbeat_wait: WallSeconds = 3.0
    # A heartbeat stamped longer ago than this (by this host's clock) counts for less, not at all past
    # it (services/robotrules.py): as the sim's [sim] heartbeat_max_age.
    heartbeat_max_age: WallSeconds = 0.5
    # The base's own top speeds; None: the world file's robot.
    max_linear_speed: Annotated[float, Meta(gt=0.0, le=10.0)] | None = None
    max_angular_speed: Annotated[float, Meta(gt=0.0, le=20.0)] | None = None
    # Reports on tether's side, at most this often (as they arrive from the robot).
    odom_hz: Hz = 50.0
    joint_states_hz: Hz = 50.0
    objects_hz: Hz = 5.0
    humans_hz: Hz = 5.0
    # How long the robot may take to answer a goal, a cancel (and end the goal), a service call.
    goal_timeout: WallSeconds = 2.0
    cancel_timeout: WallSeconds = 1.5
    # A cmd_vel holds this long from the command, then the backend sends one zero Twist (at most
    # 1 s: diff_drive_controller's own cmd_vel_timeout is 0.5 s).
    cmd_vel_timeout: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.5
    # A navigation aborts when odometry is older than this (safety's watchdog latches at 0.5 s).
    odom_timeout: WallSeconds = 0.5
    # A trajectory aborts when joint states are older than this (safety's state_max_age is 0.5 s).
    joint_states_timeout: WallSeconds = 0.5
    # ... or when the base makes no progress for this long (seconds of scaled time; a pause never counts).
    stall_timeout: WallSeconds = 10.0
    # The key safety signs robot commands and heartbeats with (services/robotlink.py); None:
    # $TETHER_ROBOT_KEY_FILE, else robot-<robot>.key beside the operator token. Made if missing.
    robot_key_file: Annotated[str, Meta(min_length=1, max_length=4096)] | None = None

    def __post_init__(self) -> None:
        if self.distro not in SUPPORTED_DISTROS:
            raise ValueError(
                f"distro {self.distro!r} is not supported: {UNSUPPORTED_DISTROS[self.distro]}; "
                f"supported: {', '.join(SUPPORTED_DISTROS)} (style rmw_zenoh or bridge)"
            )
        if self.gripper_action == "parallel_gripper_command" and self.gripper_position_per_gap != 1.0:
            raise ValueError(
                f"gripper_position_per_gap = {self.gripper_position_per_gap:g} is for gripper_action = "
                "'gripper_command': a ParallelGripperCommand names gripper_joint and gets half the gap"
            )

    def ros_domain(self) -> int:
        """ROS_DOMAIN_ID from the environment when set, else `domain_id`, else 0."""
        if (env := os.environ.get("ROS_DOMAIN_ID", "").strip()) != "":
            try:
                value = int(env)
            except ValueError:
                raise ValueError(f"ROS_DOMAIN_ID={env!r} is not a number") from None
            if not 0 <= value <= 232:
                raise ValueError(f"ROS_DOMAIN_ID={value} must be 0..232")
            return value
        return self.domain_id if self.domain_id is not None else 0
