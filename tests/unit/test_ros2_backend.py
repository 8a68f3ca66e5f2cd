"""The ros2 backend's logic without Zenoh: conversions, status codes, fail-closed decisions, route
tracking, re-timing, and goal runs against a scripted robot on a fake clock."""

from __future__ import annotations

import io
import itertools
import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from PIL import Image

from schemas.actions import GoalState, ResultResponse
from schemas.actions import GoalStatus as TetherGoalStatus
from schemas.common import Pose2D
from schemas.robot import (
    ARM_JOINTS,
    FINGER_JOINTS,
    FollowJointTrajectoryGoal,
    FollowJointTrajectoryResult,
    GripperCommandGoal,
    GripperCommandResult,
    JointState,
    NavigateToPoseGoal,
    NavigateToPoseResult,
    Odometry,
    TrajectoryPoint,
    Twist,
)
from schemas.safety import EstopState, SafetyStatus
from schemas.world import PerceivedHumans
from services.footprint import route_legs
from services.robotrules import NO_HEARTBEAT_YET, HeartbeatGuard, SafetyNow, away_from, check_trajectory
from services.ros2 import backend
from services.ros2.backend import (
    JOINTS_MAX_LAG,
    BaseLimits,
    CmdVelHold,
    EstopSignal,
    JointMerger,
    Messages,
    Perception,
    RateLimit,
    RobotCallFailed,
    RobotGoalUnanswered,
    RobotRefused,
    RobotReportError,
    RobotState,
    Stamps,
    camera_image,
    navigation_error,
    odometry,
    ros_failure,
    trajectory_error,
)
from services.ros2.config import Frames, Ros2Config
from services.ros2.goals import (
    MIN_SEGMENT,
    POLL,
    GripperRun,
    NavigationRun,
    RouteTracker,
    RunContext,
    TrajectoryPlan,
    TrajectoryRun,
)
from services.ros2.types import RosTypes
from services.ros2.wire import GoalStatus
from services.worldmodel import WorldModel, drive_route, load_world

ROOT = Path(__file__).resolve().parents[2]
SUCCEEDED, CANCELED, ABORTED = GoalStatus.SUCCEEDED, GoalStatus.CANCELED, GoalStatus.ABORTED
WORLD = load_world()
MODEL = WorldModel(WORLD)
TYPES = RosTypes()
FRAMES = Frames()
MESSAGES = Messages(TYPES, FRAMES, stamped_cmd_vel=False)
# Trajectories here run on a clock the test moves, without joint states coming in: their age is not
# watched (test_ros2_followups46 tests that it ends a trajectory).
UNWATCHED = math.inf
NOW = 1_700_000_000.0  # a wall-clock time, seconds
HOME = [0.0, -1.3, 0.0, -2.35, 0.0, 1.05, 0.785]
LOWER = [-2.9, -1.8, -2.9, -3.1, -2.9, -0.08, -2.9]
UPPER = [2.9, 1.8, 2.9, 0.0, 2.9, 3.8, 2.9]


def status(
    *, latched: bool = False, scale: float = 1.0, linear: float | None = None, angular: float | None = None
) -> SafetyStatus:
    return SafetyStatus(
        seq=0,
        stamp=NOW,
        estop=EstopState(latched=latched, source="operator", reason="test"),
        speed_scale=scale,
        max_linear_speed=linear,
        max_angular_speed=angular,
    )


def clear(scale: float = 1.0, linear: float | None = None, angular: float | None = None) -> SafetyNow:
    return SafetyNow(None, status(scale=scale, linear=linear, angular=angular))


def as_safety_reads(value: Any, schema: Any) -> Any:
    """`value` through JSON and back, decoded by `schema` as safety and the executor decode it:
    a Struct built in Python is not checked against its bounds, only a decoded one is."""
    return msgspec.json.decode(msgspec.json.encode(value), type=schema)


def header(stamp: float, frame: str) -> Any:
    return MESSAGES.header(stamp, frame)


def ros_pose(
    x: float,
    y: float,
    z: float = 0.0,
    yaw: float | None = None,
    quaternion: tuple[float, float, float, float] | None = None,
) -> Any:
    """`quaternion` (x, y, z, w), when given, is the orientation as it is, whatever `yaw` says."""
    w, qz = (1.0, 0.0) if yaw is None else (math.cos(yaw / 2), math.sin(yaw / 2))
    qx, qy, qz, w = quaternion or (0.0, 0.0, qz, w)
    return TYPES.new(
        "geometry_msgs/msg/Pose",
        position=TYPES.new("geometry_msgs/msg/Point", x=x, y=y, z=z),
        orientation=TYPES.new("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=w),
    )


def ros_odometry(
    x: float,
    y: float,
    yaw: float,
    *,
    frame: str = "odom",
    v: float = 0.0,
    w: float = 0.0,
    quaternion: tuple[float, float, float, float] | None = None,
) -> Any:
    twist = TYPES.new(
        "geometry_msgs/msg/Twist",
        linear=TYPES.new("geometry_msgs/msg/Vector3", x=v),
        angular=TYPES.new("geometry_msgs/msg/Vector3", z=w),
    )
    message = TYPES.new(
        "nav_msgs/msg/Odometry",
        header=header(NOW, frame),
        child_frame_id="base_link",
        pose=TYPES.new("geometry_msgs/msg/PoseWithCovariance", pose=ros_pose(x, y, yaw=yaw, quaternion=quaternion)),
        twist=TYPES.new("geometry_msgs/msg/TwistWithCovariance", twist=twist),
    )
    # As it arrives: through CDR.
    return TYPES.decode("nav_msgs/msg/Odometry", TYPES.encode("nav_msgs/msg/Odometry", message))


def detection(
    ident: str,
    cls: str,
    x: float,
    y: float,
    z: float,
    *,
    frame: str = "odom",
    yaw: float | None = None,
    quaternion: tuple[float, float, float, float] | None = None,
) -> Any:
    hypothesis = TYPES.new(
        "vision_msgs/msg/ObjectHypothesisWithPose",
        hypothesis=TYPES.new("vision_msgs/msg/ObjectHypothesis", class_id=cls, score=1.0),
        pose=TYPES.new("geometry_msgs/msg/PoseWithCovariance", pose=ros_pose(x, y, z, yaw, quaternion)),
    )
    return TYPES.new("vision_msgs/msg/Detection3D", header=header(NOW, frame), results=[hypothesis], id=ident)


def detections(*items: Any) -> Any:
    message = TYPES.new("vision_msgs/msg/Detection3DArray", header=header(NOW, "odom"), detections=list(items))
    return TYPES.decode(backend.DETECTIONS, TYPES.encode(backend.DETECTIONS, message))


def test_the_logic_loads_without_zenoh() -> None:
    code = (
        "import sys, services.ros2.backend, services.ros2.goals, services.robotrules\n"
        "print(any(m.startswith('zenoh') for m in sys.modules))"
    )
    child = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120, check=False
    )
    assert child.returncode == 0, child.stderr[-2000:]
    assert child.stdout.strip() == "False"


# ROS -> tether


def test_odometry_in_the_odom_frame_becomes_tethers() -> None:
    odom = odometry(ros_odometry(6.0, 1.2, 0.5, v=0.3, w=-0.1), "odom", NOW)
    assert odom.pose.x == pytest.approx(6.0) and odom.pose.y == pytest.approx(1.2)
    assert odom.pose.yaw == pytest.approx(0.5)
    assert (odom.linear_x, odom.angular_z) == pytest.approx((0.3, -0.1))
    assert odom.stamp == odom.sim_time == NOW


def test_odometry_in_another_frame_is_refused_naming_both_frames() -> None:
    with pytest.raises(RobotReportError, match=r"'map'.*expected 'odom' \(\[ros2.frames\] odom\)"):
        odometry(ros_odometry(6.0, 1.2, 0.0, frame="map"), "odom", NOW)
    assert odometry(ros_odometry(6.0, 1.2, 0.0, frame="/odom"), "odom", NOW).pose.x == pytest.approx(6.0)


def test_odometry_that_is_not_numbers_is_refused() -> None:
    with pytest.raises(RobotReportError, match="not numbers"):
        odometry(ros_odometry(math.nan, 1.2, 0.0), "odom", NOW)


def turned(yaw: float, length: float) -> tuple[float, float, float, float]:
    """A quaternion (x, y, z, w) of `yaw` about z, `length` long instead of 1."""
    return (0.0, 0.0, length * math.sin(yaw / 2), length * math.cos(yaw / 2))


def test_odometry_takes_the_yaw_of_a_quaternion_of_any_length() -> None:
    for length in (0.1, 1.0, 3.0, 1e-200, 1e200):
        odom = odometry(ros_odometry(6.0, 1.2, 0.0, quaternion=turned(1.2, length)), "odom", NOW)
        assert odom.pose.yaw == pytest.approx(1.2), length


@pytest.mark.parametrize(
    "quaternion", [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, math.nan, math.nan), (math.inf, math.inf, 0.0, 0.0)]
)
def test_odometry_whose_quaternion_is_no_rotation_is_refused_naming_it(
    quaternion: tuple[float, float, float, float],
) -> None:
    with pytest.raises(RobotReportError, match=r"^odometry whose orientation \(x, y, z, w\) = .* has norm"):
        odometry(ros_odometry(6.0, 1.2, 0.0, quaternion=quaternion), "odom", NOW)


@pytest.mark.parametrize(("x", "y"), [(5000.0, 1.2), (1e300, 1.2), (6.0, -1000.5)])
def test_odometry_beyond_the_schemas_metres_is_refused_naming_the_bound(x: float, y: float) -> None:
    # Before, it was passed on: safety could not decode it, so its monitors went blind while the
    # backend's own keep-out check used the pose.
    with pytest.raises(RobotReportError, match=r"^odometry at \(.*\): outside -1000 to 1000 m \(tether's Metres\)"):
        odometry(ros_odometry(x, y, 0.0), "odom", NOW)
    edge = odometry(ros_odometry(1000.0, -1000.0, 0.0), "odom", NOW)
    assert as_safety_reads(edge, Odometry) == edge


def test_a_robot_clock_far_from_ours_is_not_believed() -> None:
    stamps = Stamps()
    assert stamps.of(header(NOW - 0.01, "odom"), NOW) == pytest.approx(NOW - 0.01)
    assert stamps.of(header(NOW - 3600.0, "odom"), NOW) == NOW


def joint_message(names: list[str], positions: list[float], velocities: list[float] | None = None) -> Any:
    return TYPES.new(
        backend.JOINT_STATE,
        header=header(NOW, ""),
        name=names,
        position=np.array(positions, dtype=np.float64),
        velocity=np.array(velocities or [], dtype=np.float64),
    )


def test_joint_states_from_arm_and_gripper_apart_merge_into_one_in_tethers_order() -> None:
    merger = JointMerger()
    arm = joint_message(list(reversed(ARM_JOINTS)), list(reversed(HOME)), [0.0] * 7)
    assert merger.update(arm, NOW) is None, "the fingers were not heard yet"
    assert merger.missing() == list(FINGER_JOINTS)
    fingers = joint_message([*FINGER_JOINTS, "other_joint"], [0.04, 0.04, 9.0])
    state = merger.update(fingers, NOW + 0.02)
    assert state is not None
    assert state.name == [*ARM_JOINTS, *FINGER_JOINTS]
    assert state.position == pytest.approx([*HOME, 0.04, 0.04])
    assert len(state.velocity) == len(state.name)
    # Without velocities from the robot, from positions.
    closing = merger.update(joint_message(list(FINGER_JOINTS), [0.03, 0.03]), NOW + 0.12)
    assert closing is not None and closing.velocity[-1] == pytest.approx(-0.1)


def test_joint_states_that_do_not_add_up_are_refused() -> None:
    with pytest.raises(RobotReportError, match="2 names and 1 positions"):
        JointMerger().update(joint_message(list(FINGER_JOINTS), [0.04]), NOW)
    all_joints = [*ARM_JOINTS, *FINGER_JOINTS]
    with pytest.raises(RobotReportError, match="9 names and 7 velocities"):
        JointMerger().update(joint_message(all_joints, [*HOME, 0.04, 0.04], [5.0] * 7), NOW)
    with pytest.raises(RobotReportError, match="naming 'panda_joint1' more than once"):
        JointMerger().update(joint_message([ARM_JOINTS[0], *all_joints], [0.1, *HOME, 0.04, 0.04]), NOW)


def test_joint_states_refused_leave_the_merged_state_as_it_was() -> None:
    all_joints = [*ARM_JOINTS, *FINGER_JOINTS]
    merger = JointMerger()
    merger.update(joint_message(all_joints, [-1.5e308] * 9), NOW)
    # A speed estimated from these positions is not a number: refused, not reported as inf.
    with pytest.raises(RobotReportError, match=r"moving panda_joint1 .* a speed that is not a number"):
        merger.update(joint_message(all_joints, [1.5e308] * 9), NOW + 0.01)
    state = merger.update(joint_message(all_joints, [-1.5e308] * 9), NOW + 0.02)
    assert state is not None and state.velocity == [0.0] * 9


def test_joint_states_naming_none_of_tethers_joints_pass_nothing_on() -> None:
    merger = JointMerger()
    merger.update(joint_message(list(FINGER_JOINTS), [0.04, 0.04]), NOW)
    arm = merger.update(joint_message(list(ARM_JOINTS), HOME, [0.8] * 7), NOW + 0.01)
    assert arm is not None and arm.stamp == NOW + 0.01
    # A message of none of tether's joints (a base's wheels) says nothing new: before, it republished all.
    assert merger.update(joint_message(["wheel_left_joint"], [3.0]), NOW + 11.0) is None
    assert merger.update(joint_message(list(ARM_JOINTS), HOME, [0.0] * 7), NOW + 11.9) is not None
    again = merger.update(joint_message(list(FINGER_JOINTS), [0.03, 0.03]), NOW + 12.0)
    assert again is not None and again.stamp == NOW + 12.0 and again.position[-2:] == [0.03, 0.03]


def test_an_arm_that_stops_reporting_is_not_passed_on_under_the_grippers_fresh_stamps() -> None:
    merger = JointMerger()
    assert merger.update(joint_message(list(ARM_JOINTS), HOME, [0.8] * 7), NOW) is None
    # The gripper's messages complete the state while the arm's are recent.
    assert merger.update(joint_message(list(FINGER_JOINTS), [0.04, 0.04]), NOW + JOINTS_MAX_LAG) is not None
    # The arm's publisher has stopped; the gripper's goes on: its message would carry the arm's last
    # positions, moving at 0.8 rad/s, as measured now. Nothing is passed on, and the arm is named.
    assert merger.update(joint_message(list(FINGER_JOINTS), [0.04, 0.04]), NOW + JOINTS_MAX_LAG + 0.01) is None
    assert merger.lagging() == list(ARM_JOINTS) and merger.missing() == []
    # The arm reports again: passed on at once. Fingers reported only on change may lag.
    back = merger.update(joint_message(list(ARM_JOINTS), HOME, [0.0] * 7), NOW + 5.0)
    assert back is not None and back.stamp == NOW + 5.0 and merger.lagging() == []


def perception(class_map: dict[str, str] | None = None) -> Perception:
    return Perception(WORLD, class_map or {}, "person", FRAMES)


def cup_on_the_counter() -> tuple[float, float, float]:
    cup = MODEL.objects["red_cup"]
    at = MODEL.initial_position(cup)
    return at.x, at.y, at.z


def test_an_object_detected_by_its_world_id_is_named_placed_in_its_room_and_on_its_furniture() -> None:
    seen = perception().read(detections(detection("red_cup", "cup", *cup_on_the_counter())), NOW)
    assert seen.humans is None and not seen.problems
    assert seen.objects is not None
    [cup] = seen.objects.objects
    assert (cup.id, cup.name, cup.color, cup.cls) == ("red_cup", "red cup", "red", "cup")
    assert cup.on == "kitchen_counter" and cup.room == MODEL.room_of(cup.position.x, cup.position.y)
    assert cup.stamp == NOW


def test_the_class_map_names_a_detectors_classes_and_unknown_ones_are_reported() -> None:
    x, y, z = cup_on_the_counter()
    seen = perception({"mug_0": "red_cup"}).read(
        detections(detection("mug_0", "mug", x, y, z), detection("7", "dog", 1.0, 1.0, 0.1)), NOW
    )
    assert seen.objects is not None and [o.id for o in seen.objects.objects] == ["red_cup"]
    assert len(seen.problems) == 1 and "class_map" in seen.problems[0] and "'dog'" in seen.problems[0]


def test_an_object_in_the_gripper_frame_is_on_the_gripper() -> None:
    seen = perception().read(detections(detection("red_cup", "cup", 6.4, 1.2, 0.9, frame="panda_hand")), NOW)
    assert seen.objects is not None and seen.objects.objects[0].on == "gripper"


def test_a_detection_in_a_frame_without_a_transform_is_left_out_with_the_reason() -> None:
    seen = perception().read(detections(detection("red_cup", "cup", 0.1, 0.0, 0.3, frame="camera_link")), NOW)
    assert seen.objects is not None and seen.objects.objects == []
    assert "'camera_link'" in seen.problems[0]


def test_a_book_seen_turned_reports_its_heading_modulo_a_half_turn() -> None:
    seen = perception().read(detections(detection("blue_book", "book", 3.0, 6.0, 0.45, yaw=math.pi - 0.3)), NOW)
    assert seen.objects is not None and seen.objects.objects[0].yaw == pytest.approx(-0.3)


def test_a_book_seen_turned_by_a_quaternion_of_another_length_reports_its_heading() -> None:
    book = detection("blue_book", "book", 3.0, 6.0, 0.45, quaternion=turned(0.5, 3.0))
    seen = perception().read(detections(book), NOW)
    assert seen.objects is not None and seen.objects.objects[0].yaw == pytest.approx(0.5)
    # w = 1 with z = 1 is no detector's "no orientation": a quarter turn.
    book = detection("blue_book", "book", 3.0, 6.0, 0.45, quaternion=(0.0, 0.0, 1.0, 1.0))
    seen = perception().read(detections(book), NOW)
    assert seen.objects is not None and seen.objects.objects[0].yaw == pytest.approx(math.pi / 2)


def test_a_detection_whose_quaternion_is_no_rotation_is_left_out_and_a_persons_kept_with_the_reason() -> None:
    book = detection("blue_book", "book", 3.0, 6.0, 0.45, quaternion=(0.0, 0.0, 0.0, 0.0))
    seen = perception().read(detections(book), NOW)
    assert seen.objects is not None and seen.objects.objects == []
    assert seen.problems == [
        "blue_book detected, but its orientation (x, y, z, w) = (0.0, 0.0, 0.0, 0.0) has norm 0.0: it is no rotation"
    ]
    # A person is kept where it stands: safety keeps its distance from it all the same.
    person = detection("operator", "person", 9.5, 1.5, 0.85, quaternion=(0.0, 0.0, math.nan, math.nan))
    seen = perception().read(detections(person), NOW)
    assert seen.humans is not None and seen.humans.humans[0].pose == Pose2D(x=9.5, y=1.5, yaw=0.0)
    assert len(seen.problems) == 1 and "person operator: its orientation" in seen.problems[0]


def test_a_person_whose_id_is_no_id_of_the_schemas_is_named_so_safety_can_read_the_people() -> None:
    # Letters other than ASCII passed as an id before: the schema's Id refused them, so safety
    # could read none of the people in the message.
    seen = perception().read(detections(detection("café", "person", 9.5, 1.5, 0.85)), NOW)
    assert seen.humans is not None and [h.id for h in seen.humans.humans] == ["person_0"]
    assert as_safety_reads(seen.humans, PerceivedHumans) == seen.humans


def test_a_detection_beyond_the_schemas_metres_is_left_out_with_the_reason() -> None:
    seen = perception().read(detections(detection("operator", "person", 1000.5, 1.5, 0.85)), NOW)
    assert seen.humans is None and seen.problems == [
        "detection 0 (operator) at (1000.5, 1.5, 0.85): not a place in the world"
    ]


def test_an_array_of_people_only_is_the_trackers_and_an_empty_one_the_cameras() -> None:
    seen = perception().read(detections(detection("operator", "person", 9.5, 1.5, 0.85, yaw=math.pi)), NOW)
    assert seen.objects is None, "a people tracker's array says nothing about objects"
    assert seen.humans is not None
    [person] = seen.humans.humans
    assert (person.id, person.name, person.room) == ("operator", "operator", MODEL.room_of(9.5, 1.5))
    assert person.pose.yaw == pytest.approx(math.pi)
    stranger = perception().read(detections(detection("track 12!", "person", 9.0, 1.5, 0.85)), NOW)
    assert stranger.humans is not None and stranger.humans.humans[0].id == "person_0"
    empty = perception().read(detections(), NOW)
    assert empty.objects is not None and empty.objects.objects == [] and empty.humans is None


def test_a_flood_of_detections_is_cut_at_the_cap_with_the_reason() -> None:
    x, y, z = cup_on_the_counter()
    flood = detections(*(detection("red_cup", "cup", x, y, z) for _ in range(backend.MAX_DETECTIONS + 50)))
    seen = perception().read(flood, NOW)
    assert seen.objects is not None and [o.id for o in seen.objects.objects] == ["red_cup"]
    assert f"the first {backend.MAX_DETECTIONS} are read" in seen.problems[0]


def png_bytes(width: int, height: int) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (width, height), (200, 10, 10)).save(buffer, format="PNG")
    return buffer.getvalue()


def test_a_compressed_png_is_passed_on_and_a_jpeg_becomes_a_png() -> None:
    png = TYPES.new(
        backend.COMPRESSED_IMAGE,
        header=header(NOW, "camera"),
        format="png",
        data=np.frombuffer(png_bytes(32, 24), np.uint8),
    )
    image = camera_image(png, NOW)
    assert (image.width, image.height, image.mime_type) == (32, 24, "image/png")
    buffer = io.BytesIO()
    Image.new("RGB", (16, 8)).save(buffer, format="JPEG")
    jpeg = TYPES.new(backend.COMPRESSED_IMAGE, format="jpeg", data=np.frombuffer(buffer.getvalue(), np.uint8))
    assert (camera_image(jpeg, NOW).width, camera_image(jpeg, NOW).height) == (16, 8)
    garbage = TYPES.new(backend.COMPRESSED_IMAGE, format="jpeg", data=np.frombuffer(b"not an image", np.uint8))
    with pytest.raises(RobotReportError, match="does not decode"):
        camera_image(garbage, NOW)


def test_a_huge_picture_is_refused_before_it_is_decoded() -> None:
    # A JPEG header claiming 8000 x 8000 pixels (below PIL's own bomb limit): refused from the header, never decoded.
    buffer = io.BytesIO()
    Image.new("L", (8, 8)).save(buffer, format="JPEG")
    data = bytearray(buffer.getvalue())
    sof = data.index(b"\xff\xc0")  # baseline frame header: length (2), precision (1), height (2), width (2)
    data[sof + 5 : sof + 9] = (8000).to_bytes(2, "big") * 2
    bomb = TYPES.new(backend.COMPRESSED_IMAGE, format="jpeg", data=np.frombuffer(bytes(data), np.uint8))
    with pytest.raises(RobotReportError, match="8000x8000 pixels"):
        camera_image(bomb, NOW)
    raw = TYPES.new(backend.IMAGE, width=20000, height=2, encoding="mono8", step=20000, data=np.zeros(8, np.uint8))
    with pytest.raises(RobotReportError, match="20000x2 pixels"):
        camera_image(raw, NOW)


def test_a_raw_image_becomes_a_png() -> None:
    raw = TYPES.new(backend.IMAGE, width=4, height=2, encoding="bgr8", step=12, data=np.zeros(24, np.uint8))
    assert camera_image(raw, NOW).width == 4
    odd = TYPES.new(backend.IMAGE, width=4, height=2, encoding="32FC1", step=16, data=np.zeros(32, np.uint8))
    with pytest.raises(RobotReportError, match="32FC1"):
        camera_image(odd, NOW)


# tether -> ROS


def test_cmd_vel_is_a_twist_or_a_stamped_one_in_the_base_frame() -> None:
    twist = MESSAGES.cmd_vel(0.2, -0.5, NOW)
    decoded = TYPES.decode(backend.TWIST, TYPES.encode(backend.TWIST, twist))
    assert (decoded.linear.x, decoded.angular.z) == (0.2, -0.5)
    stamped = Messages(TYPES, FRAMES, stamped_cmd_vel=True)
    message = TYPES.decode(backend.TWIST_STAMPED, TYPES.encode(backend.TWIST_STAMPED, stamped.cmd_vel(0.2, 0.0, NOW)))
    assert message.header.frame_id == "base_link" and backend.to_seconds(message.header.stamp) == pytest.approx(NOW)


def test_a_goal_without_a_path_is_navigate_to_pose_and_with_one_navigate_through_poses() -> None:
    goal = Pose2D(x=8.0, y=1.2, yaw=math.pi / 2)
    through, message = MESSAGES.navigate([goal], NOW)
    assert not through
    encoded = TYPES.encode(f"{backend.NAVIGATE_TO_POSE}_Goal", message)
    pose = TYPES.decode(f"{backend.NAVIGATE_TO_POSE}_Goal", encoded).pose
    assert pose.header.frame_id == "odom" and backend.yaw_of(pose.pose.orientation) == pytest.approx(math.pi / 2)
    through, message = MESSAGES.navigate([Pose2D(x=7.0, y=1.2), goal], NOW)
    assert through and [p.pose.position.x for p in message.poses] == [7.0, 8.0]
    TYPES.encode(f"{backend.NAVIGATE_THROUGH_POSES}_Goal", message)


def test_a_trajectory_goal_carries_positions_times_and_the_tolerances_for_every_joint() -> None:
    message = MESSAGES.trajectory(
        ["panda_joint1", "panda_joint2"], [([0.1, 0.2], 1.5)], path_tolerance=0.1, goal_tolerance=0.02
    )
    decoded = TYPES.decode(
        f"{backend.FOLLOW_JOINT_TRAJECTORY}_Goal", TYPES.encode(f"{backend.FOLLOW_JOINT_TRAJECTORY}_Goal", message)
    )
    point = decoded.trajectory.points[0]
    assert list(point.positions) == [0.1, 0.2] and backend.to_seconds(point.time_from_start) == pytest.approx(1.5)
    assert len(point.velocities) == 0, "positions only: the controller interpolates linearly"
    assert [t.position for t in decoded.goal_tolerance] == [0.02, 0.02]
    assert [t.name for t in decoded.path_tolerance] == ["panda_joint1", "panda_joint2"]


def test_the_gripper_goal_is_a_gripper_command_or_a_parallel_one() -> None:
    message = MESSAGES.gripper(0.04, 20.0)
    assert (message.command.position, message.command.max_effort) == (0.04, 20.0)
    parallel = Messages(TYPES, FRAMES, stamped_cmd_vel=False, parallel_gripper_joint="panda_finger_joint1")
    command = parallel.gripper(0.04, 20.0).command
    assert command.name == ["panda_finger_joint1"] and list(command.position) == [0.02]


def test_speed_limit_is_absolute_and_never_zero_for_a_pause() -> None:
    message = MESSAGES.speed_limit(0.25, NOW)
    assert message.percentage is False and message.speed_limit == 0.25


# Status codes


def test_ros_goal_endings_in_words() -> None:
    assert ros_failure("navigate_to_pose", ABORTED, "TIMEOUT: no progress") == (
        "the robot aborted the navigate_to_pose goal: TIMEOUT: no progress"
    )
    assert "on its own" in ros_failure("gripper_command", CANCELED, "")
    assert "status UNKNOWN" in ros_failure("gripper_command", 0, "")
    result = TYPES.new(f"{backend.FOLLOW_JOINT_TRAJECTORY}_Result", error_code=-4, error_string="panda_joint2 lagged")
    assert trajectory_error(result) == "PATH_TOLERANCE_VIOLATED: panda_joint2 lagged"
    assert trajectory_error(TYPES.new(f"{backend.FOLLOW_JOINT_TRAJECTORY}_Result")) == ""
    nav = TYPES.new(f"{backend.NAVIGATE_TO_POSE}_Result", error_code=9002, error_msg="no map->odom")
    assert navigation_error(nav) == "TF_ERROR: no map->odom"


# Limits and the stop signal


def test_the_base_keeps_to_the_scaled_maximum_and_to_the_heartbeats_limits_never_raised_by_them() -> None:
    limits = BaseLimits(max_linear=0.6, max_angular=1.2)
    assert limits.caps(clear()) == (0.6, 1.2)
    assert limits.caps(clear(0.5)) == (0.3, 0.6)
    assert limits.caps(clear(0.5, linear=2.0, angular=0.2)) == (0.3, 0.2)
    assert limits.caps(SafetyNow("e-stop latched", status(latched=True))) == (0.0, 0.0)
    assert limits.clamp(Twist(linear_x=-1.0, angular_z=1.0), clear(angular=0.3)) == (-0.6, 0.3)


def test_navigations_speed_limit_also_keeps_the_turn_rate_within_its_limit() -> None:
    limits = BaseLimits(max_linear=0.6, max_angular=1.2)
    assert limits.navigation_limit(clear()) == pytest.approx(0.6)
    assert limits.navigation_limit(clear(), max_speed=0.4) == pytest.approx(0.4)
    # The robot turns at the same fraction of its maximum as it drives: 0.3 rad/s is a quarter.
    assert limits.navigation_limit(clear(angular=0.3)) == pytest.approx(0.15)
    assert limits.navigation_limit(clear(0.0)) == 0.0


def test_reports_never_come_faster_than_their_rate_also_when_the_robot_sends_more() -> None:
    limit = RateLimit(50.0)
    arrivals = [k * 0.01 + (0.003 if k % 3 else 0.0) for k in range(1000)]  # 100 Hz, jittered
    passed = [t for t in arrivals if limit.allow(t)]
    assert 49 * 10 <= len(passed) <= 50 * 10 + 1
    assert min(b - a for a, b in itertools.pairwise(passed)) >= 0.5 / 50.0 - 1e-9


def test_reports_at_their_rate_with_jitter_all_pass() -> None:
    limit = RateLimit(50.0)
    arrivals = [k * 0.02 + (0.004 if k % 2 else -0.004) for k in range(1, 200)]
    assert all(limit.allow(t) for t in arrivals)


def test_the_robots_stop_is_a_dead_man_signal_told_at_once_on_a_change_and_at_20_hz_always() -> None:
    signal = EstopSignal()
    sent = [(t, value) for k in range(200) if (value := signal.due((t := k * 0.01) < 1.0, t)) is not None]
    blocked = [t for t, value in sent if value]
    assert blocked[0] == 0.0 and len(blocked) == pytest.approx(20, abs=1)  # 20 Hz for a second
    released = [t for t, value in sent if not value]
    assert released[0] == pytest.approx(1.0)  # at once
    # `false` goes on at 20 Hz too: a robot's watchdog on it stops the robot when the backend goes quiet.
    assert len(released) == pytest.approx(20, abs=1)
    assert max(b - a for a, b in itertools.pairwise(released)) <= 0.05 + 0.01 + 1e-9  # one tick late at most


# Fail closed (services/robotrules.py, shared with the sim)


@dataclass
class Clock:
    """A fake monotonic clock that the code under test advances by sleeping; what the test scripted
    happens inside those sleeps, on the run's own thread."""

    now: float = 100.0
    events: list[tuple[float, Callable[[], None]]] = field(default_factory=list)
    triggers: list[tuple[Callable[[], bool], Callable[[], None]]] = field(default_factory=list)
    ticks: list[Callable[[], None]] = field(default_factory=list)

    def __call__(self) -> float:
        return self.now

    def at(self, when: float, action: Callable[[], None]) -> None:
        """Do `action` once the clock reaches `when`."""
        self.events.append((when, action))
        self.events.sort(key=lambda e: e[0])

    def once(self, condition: Callable[[], bool], action: Callable[[], None]) -> None:
        """Do `action` at the first sleep after `condition` holds."""
        self.triggers.append((condition, action))

    def sleep(self, seconds: float) -> None:
        self.now += seconds
        while self.events and self.events[0][0] <= self.now:
            self.events.pop(0)[1]()
        for trigger in list(self.triggers):
            if trigger[0]():
                self.triggers.remove(trigger)
                trigger[1]()
        for tick in self.ticks:
            tick()
        # Let the threads fetching ROS results run (the goal runs' own, as on the wire).
        threading.Event().wait(0.0005)


def test_the_robot_stays_still_before_the_first_heartbeat_after_a_late_one_and_while_latched() -> None:
    clock = Clock()
    guard = HeartbeatGuard(0.2, 0.01, clock, wall_clock=lambda: NOW)
    assert guard.block() == NO_HEARTBEAT_YET
    guard.heard(status())
    assert guard.block() is None
    clock.now += 0.25
    assert guard.block() == "no safety heartbeat for 250 ms"
    guard.heard(status(latched=True))
    assert guard.block() == "e-stop latched by operator: test"


def test_poll_says_once_when_the_robot_must_stop_and_once_when_it_may_move() -> None:
    clock = Clock()
    guard = HeartbeatGuard(0.2, 0.01, clock, wall_clock=lambda: NOW)
    first = guard.poll()
    assert first.blocked == NO_HEARTBEAT_YET and not first.stopped, "blocked from the start: nothing to stop"
    guard.heard(status(scale=0.5))
    released = guard.poll()
    assert released.released and released.speed_scale == 0.5
    assert not guard.poll().released
    guard.heard(status(latched=True))
    stopped = guard.poll()
    assert stopped.stopped and stopped.speed_scale == 0.0 and "e-stop" in (stopped.blocked or "")
    assert not guard.poll().stopped


def test_a_goal_before_any_heartbeat_waits_for_one_then_is_refused() -> None:
    guard = HeartbeatGuard(0.2, 0.05, wall_clock=lambda: NOW)
    assert guard.accept() == NO_HEARTBEAT_YET


def test_a_goal_finding_the_estop_latched_hears_one_more_heartbeat_a_reset() -> None:
    guard = HeartbeatGuard(0.2, 0.05, wall_clock=lambda: NOW)
    guard.heard(status(latched=True))
    threading.Timer(0.01, guard.heard, args=(status(),)).start()
    assert guard.accept() is None


def test_the_arms_checks_and_the_start_check_name_what_is_wrong() -> None:
    unknown = FollowJointTrajectoryGoal(
        joint_names=["panda_joint9"], points=[TrajectoryPoint(positions=[0.0], time_from_start=1.0)]
    )
    assert "panda_joint9" in (check_trajectory(unknown, LOWER, UPPER) or "")
    beyond = FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS), points=[TrajectoryPoint(positions=[5.0, *HOME[1:]], time_from_start=1.0)]
    )
    assert "panda_joint1 = 5.000 rad is outside" in (check_trajectory(beyond, LOWER, UPPER) or "")
    here = Pose2D(x=6.0, y=1.2)
    assert away_from(here, Pose2D(x=6.01, y=1.2), 0.39) is None
    assert "checked from (7.00, 1.20" in (away_from(here, Pose2D(x=7.0, y=1.2), 0.39) or "")


# The route, from odometry


def tracker(start: Pose2D, goal: Pose2D, path: list[Pose2D] | None = None) -> RouteTracker:
    legs = route_legs(start, drive_route(start, path or [], goal))
    return RouteTracker(legs, start, goal, MODEL.base_radius)


def driven(route: RouteTracker, steps: int = 20) -> list[Pose2D]:
    """The poses of a base driving `route` as the sim does: turn in place, drive the leg, turn to the goal's yaw."""
    poses: list[Pose2D] = []
    yaw = route.start.yaw
    for leg in route.legs:
        (ax, ay), (bx, by) = leg.start, leg.end
        poses += [Pose2D(x=ax, y=ay, yaw=yaw + (leg.heading - yaw) * k / steps) for k in range(steps + 1)]
        poses += [
            Pose2D(x=ax + (bx - ax) * k / steps, y=ay + (by - ay) * k / steps, yaw=leg.heading)
            for k in range(steps + 1)
        ]
        yaw = leg.heading
    end = poses[-1]
    poses += [Pose2D(x=end.x, y=end.y, yaw=yaw + (route.goal.yaw - yaw) * k / steps) for k in range(steps + 1)]
    return poses


def test_driving_the_legs_as_the_sim_does_stays_on_the_route_to_the_end() -> None:
    route = tracker(Pose2D(x=6.0, y=1.2), Pose2D(x=7.0, y=2.2, yaw=math.pi / 2))
    remaining = []
    for pose in driven(route):
        assert route.update(pose) < 0.005
        remaining.append(route.remaining(pose))
    assert remaining[0] == pytest.approx(sum(leg.length for leg in route.legs))
    assert remaining[-1] == 0.0 and all(b <= a + 1e-9 for a, b in itertools.pairwise(remaining))


def test_a_base_off_its_leg_or_turned_off_its_heading_strays() -> None:
    start, goal = Pose2D(x=6.0, y=1.2), Pose2D(x=8.0, y=1.2)
    route = tracker(start, goal)
    assert route.update(Pose2D(x=6.5, y=1.2)) < 0.001
    assert route.update(Pose2D(x=6.6, y=1.25)) == pytest.approx(0.05)
    assert route.update(Pose2D(x=6.7, y=1.2, yaw=0.2)) == pytest.approx(MODEL.base_radius * 0.2)


def test_the_rest_of_a_paused_route_is_its_remaining_leg_ends_then_the_goal() -> None:
    start, goal = Pose2D(x=6.0, y=1.2), Pose2D(x=9.0, y=1.2)
    route = tracker(start, goal, [Pose2D(x=7.0, y=1.2)])
    assert [(p.x, p.y) for p in route.rest()] == [(7.0, 1.2), (8.6, 1.2), (9.0, 1.2)]
    route.update(Pose2D(x=6.5, y=1.2))
    route.update(Pose2D(x=7.5, y=1.2))
    rest = route.rest()
    assert [(round(p.x, 3), p.y) for p in rest] == [(8.6, 1.2), (9.0, 1.2)] and rest[-1] == goal


# Re-timing trajectories


def swing(seconds: float = 2.0) -> FollowJointTrajectoryGoal:
    return FollowJointTrajectoryGoal(
        joint_names=list(ARM_JOINTS),
        points=[
            TrajectoryPoint(positions=[0.3, *HOME[1:]], time_from_start=seconds / 2),
            TrajectoryPoint(positions=[0.6, *HOME[1:]], time_from_start=seconds),
        ],
    )


def test_a_trajectory_is_interpolated_from_where_the_arm_is_and_the_rest_re_timed_by_the_scale() -> None:
    plan = TrajectoryPlan(swing(2.0), HOME)
    assert plan.desired(0.5)[0] == pytest.approx(0.15)
    assert plan.first(0.5) == [([0.3, *HOME[1:]], 2.0), ([0.6, *HOME[1:]], 4.0)]
    rest = plan.rest(0.5, 0.25)
    assert [(p[0][0], t) for p, t in [(r, r[1]) for r in rest]] == [(0.3, 2.0), (0.6, 6.0)]
    assert plan.rest(5.0, 1.0) == [([0.6, *HOME[1:]], MIN_SEGMENT)]


# Goal runs against a scripted robot


class FakeGoal:
    """A ROS goal as the robot holds it; the test ends it."""

    def __init__(self, goal: Any, *, ends_on_cancel: bool = True) -> None:
        self.goal = goal
        self.ends_on_cancel = ends_on_cancel
        self.status = 2
        self.cancels = 0
        self.forgotten = False
        self._ended = threading.Event()
        self._outcome: tuple[int, Any] = (0, None)

    def finish(self, code: int, result: Any = None) -> None:
        self._outcome, self.status = (code, result), code
        self._ended.set()

    def result(self, timeout: float) -> tuple[int, Any]:
        if not self._ended.wait(timeout):
            raise RobotCallFailed("get_result: no answer")
        return self._outcome

    def cancel(self, timeout: float) -> bool:
        self.cancels += 1
        if self.ends_on_cancel:
            self.finish(CANCELED)
        return self.ends_on_cancel

    def forget(self) -> None:
        self.forgotten = True


class FakeAction:
    def __init__(
        self,
        name: str,
        *,
        refuse: Exception | None = None,
        ends_on_cancel: bool = True,
        make: type[FakeGoal] = FakeGoal,
        during_send: Callable[[], None] | None = None,
    ) -> None:
        self.name = name
        self.refuse = refuse
        self.ends_on_cancel = ends_on_cancel
        self.make = make
        self.during_send = during_send  # what happens while the goal is on its way, once
        self.goals: list[FakeGoal] = []
        self.canceled: list[bytes] = []  # ids, in the order their cancels came

    def send_goal(self, goal: Any, *, timeout: float) -> FakeGoal:
        if self.refuse is not None:
            raise self.refuse
        self.goals.append(self.make(goal, ends_on_cancel=self.ends_on_cancel))
        if self.during_send is not None:
            self.during_send, during = None, self.during_send
            during()
        return self.goals[-1]

    def cancel(self, goal_id: bytes, timeout: float) -> bool:
        self.canceled.append(goal_id)
        return len(self.canceled) >= 2  # the robot takes the unanswered goal late: the second cancel finds it


@dataclass
class FakeHandle:
    goal: Any
    abort_reason: str = ""
    stop: bool = False
    feedbacks: list[Any] = field(default_factory=list)

    @property
    def should_stop(self) -> bool:
        return self.stop

    def feedback(self, message: Any) -> None:
        self.feedbacks.append(message)


@dataclass
class Rig:
    clock: Clock
    robot: RobotState
    safety: list[SafetyNow]
    halts: list[float]
    context: RunContext
    base: tuple[Pose2D, float] = (Pose2D(x=6.0, y=1.2), 0.0)

    def set(self, safety: SafetyNow) -> None:
        self.safety[0] = safety

    def odometry(self, pose: Pose2D, v: float = 0.0) -> None:
        self.base = (pose, v)
        self.robot.heard_odometry(Odometry(stamp=NOW, sim_time=NOW, pose=pose, linear_x=v, angular_z=0.0))

    def joints(self, arm: list[float], gap: float = 0.08) -> None:
        names = [*ARM_JOINTS, *FINGER_JOINTS]
        self.robot.heard_joints(
            JointState(stamp=NOW, name=names, position=[*arm, gap / 2, gap / 2], velocity=[0.0] * 9)
        )


@pytest.fixture
def rig() -> Rig:
    clock = Clock()
    robot = RobotState(clock)
    safety = [clear()]
    halts: list[float] = []
    context = RunContext(
        safety=lambda: safety[0],
        robot=robot,
        goal_timeout=2.0,
        cancel_timeout=0.5,
        halt_base=lambda: halts.append(clock.now),
        clock=clock,
        sleep=clock.sleep,
    )
    rig = Rig(clock, robot, safety, halts, context)
    rig.joints(HOME)
    rig.odometry(Pose2D(x=6.0, y=1.2))
    # Odometry keeps coming, where the base last was.
    clock.ticks.append(lambda: rig.odometry(*rig.base))
    return rig


def trajectory_result(code: int = 0, text: str = "") -> Any:
    return TYPES.new(f"{backend.FOLLOW_JOINT_TRAJECTORY}_Result", error_code=code, error_string=text)


def test_a_trajectory_runs_as_one_ros_goal_and_succeeds_with_the_error_the_joints_show(rig: Rig) -> None:
    action, handle = FakeAction("arm"), FakeHandle(swing(2.0))
    run = TrajectoryRun(rig.context, action, handle, MESSAGES, joint_states_timeout=UNWATCHED)
    rig.clock.at(101.0, lambda: rig.joints([0.6, *HOME[1:]]))
    rig.clock.at(101.0, lambda: action.goals[0].finish(SUCCEEDED, trajectory_result()))
    ending = run.run()
    assert ending.state is GoalState.SUCCEEDED, ending.message
    assert ending.result.error == pytest.approx(0.0)
    [sent] = action.goals
    assert [backend.to_seconds(p.time_from_start) for p in sent.goal.trajectory.points] == [1.0, 2.0]
    assert handle.feedbacks and handle.feedbacks[-1].time_from_start > 0.0


def test_a_trajectory_paused_at_scale_zero_is_canceled_and_the_rest_sent_re_timed_on_resume(rig: Rig) -> None:
    action, handle = FakeAction("arm"), FakeHandle(swing(2.0))
    run = TrajectoryRun(rig.context, action, handle, MESSAGES, joint_states_timeout=UNWATCHED)
    rig.clock.at(100.5, lambda: rig.set(clear(0.0)))  # paused half a second in
    rig.clock.at(103.0, lambda: rig.set(clear(0.5)))  # resumed at half speed
    rig.clock.once(lambda: len(action.goals) == 2, lambda: action.goals[1].finish(SUCCEEDED, trajectory_result()))
    ending = run.run()
    assert ending.state is GoalState.SUCCEEDED, ending.message
    first, rest = action.goals
    assert first.cancels == 1, "paused by canceling: the arm holds"
    times = [backend.to_seconds(p.time_from_start) for p in rest.goal.trajectory.points]
    # 0.5 s of trajectory time had passed: the rest (0.5 s to the first point, 1.5 s to the last) takes twice as long.
    assert times == pytest.approx([1.0, 3.0], abs=0.05)


def test_a_trajectory_the_robot_refuses_or_aborts_ends_aborted_with_what_it_said(rig: Rig) -> None:
    refused = TrajectoryRun(
        rig.context,
        FakeAction("arm", refuse=RobotRefused("goal rejected by the server")),
        FakeHandle(swing()),
        MESSAGES,
        joint_states_timeout=UNWATCHED,
    ).run()
    assert (
        refused.state is GoalState.ABORTED
        and "refused" in refused.message
        and "rejected by the server" in refused.message
    )
    action = FakeAction("arm")
    rig.clock.once(
        lambda: bool(action.goals),
        lambda: action.goals[0].finish(ABORTED, trajectory_result(-4, "panda_joint2 blocked")),
    )
    aborted = TrajectoryRun(rig.context, action, FakeHandle(swing()), MESSAGES, joint_states_timeout=UNWATCHED).run()
    assert aborted.state is GoalState.ABORTED
    assert (
        aborted.message
        == "the robot aborted the follow_joint_trajectory goal: PATH_TOLERANCE_VIOLATED: panda_joint2 blocked"
    )
    action = FakeAction("arm")
    rig.clock.once(
        lambda: bool(action.goals), lambda: action.goals[0].finish(SUCCEEDED, trajectory_result(-5, "off by 0.1"))
    )
    failed = TrajectoryRun(rig.context, action, FakeHandle(swing()), MESSAGES, joint_states_timeout=UNWATCHED).run()
    assert failed.state is GoalState.ABORTED and "GOAL_TOLERANCE_VIOLATED" in failed.message


def assert_plan_reads(ending: Any, result_type: Any) -> None:
    """The goal's ending as the executor reads it: its result and its status both decode."""
    wire = ResultResponse(goal_id="g1", state=ending.state, result=ending.result, message=ending.message)
    as_safety_reads(wire, ResultResponse[result_type])
    as_safety_reads(TetherGoalStatus(goal_id="g1", state=ending.state, message=ending.message), TetherGoalStatus)


def test_the_robots_words_too_long_for_a_message_are_cut_saying_so(rig: Rig) -> None:
    # Before, a 10 000-character reason made the goal's ending undecodable: the robot's words were lost.
    action = FakeAction("arm")
    rig.clock.once(
        lambda: bool(action.goals),
        lambda: action.goals[0].finish(ABORTED, trajectory_result(-4, "panda_joint2 blocked " + "x" * 10_000)),
    )
    arm = TrajectoryRun(rig.context, action, FakeHandle(swing()), MESSAGES, joint_states_timeout=UNWATCHED).run()
    assert arm.state is GoalState.ABORTED
    assert arm.message.startswith(
        "the robot aborted the follow_joint_trajectory goal: PATH_TOLERANCE_VIOLATED: panda_joint2 blocked xxx"
    )
    assert arm.message.endswith("… [cut: 10021 characters in all]")
    assert len(arm.message) < backend.TEXT_MAX // 2
    assert_plan_reads(arm, FollowJointTrajectoryResult)

    to_pose = FakeAction("navigate_to_pose")
    failed = TYPES.new(f"{backend.NAVIGATE_TO_POSE}_Result", error_code=9003, error_msg="y" * 10_000)
    rig.clock.once(lambda: bool(to_pose.goals), lambda: to_pose.goals[0].finish(ABORTED, failed))
    nav = navigation(rig, FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=6.5, y=1.2))), to_pose).run()
    assert nav.state is GoalState.ABORTED and nav.message.startswith(
        "the robot aborted the navigate_to_pose goal: TIMEOUT: yyy"
    )
    assert nav.message.endswith("… [cut: 10000 characters in all]")
    assert_plan_reads(nav, NavigateToPoseResult)


@pytest.mark.parametrize("position", [math.nan, math.inf, -math.inf])
def test_a_gripper_result_whose_position_is_not_a_number_ends_the_goal_aborted(rig: Rig, position: float) -> None:
    # Before, the goal succeeded with a result no one could decode (JSON has no NaN).
    action = FakeAction("gripper")
    run = GripperRun(rig.context, action, FakeHandle(GripperCommandGoal(position=0.08)), MESSAGES, {}, 0.2)
    result = TYPES.new(f"{backend.GRIPPER_COMMAND}_Result", position=position, stalled=False, reached_goal=True)
    rig.clock.once(lambda: bool(action.goals), lambda: action.goals[0].finish(SUCCEEDED, result))
    ending = run.run()
    assert ending.state is GoalState.ABORTED
    assert ending.message == (
        f"the robot reports the gripper_command goal succeeded, but with the gripper at {position}: not a gap"
    )
    assert ending.result.position == pytest.approx(0.08), "the gap the joint states show"
    assert_plan_reads(ending, GripperCommandResult)


def wait_until(condition: Callable[[], bool], timeout: float = 5.0) -> bool:
    """For what the goal runs' own threads do in wall time."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        threading.Event().wait(0.01)
    return True


def test_a_robot_that_never_answers_a_goal_ends_it_aborted_and_is_left_still(rig: Rig) -> None:
    goal_id = bytes(range(16))
    silent = FakeAction(
        "navigate_to_pose",
        refuse=RobotGoalUnanswered("service navigate_to_pose/_action/send_goal: no answer within 2 s", goal_id),
    )
    run = navigation(rig, FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=7.0, y=1.2))), silent)
    ending = run.run()
    assert ending.state is GoalState.ABORTED and "no answer within 2 s" in ending.message
    assert rig.halts, "the base was told to stop"
    assert ending.result is not None and ending.result.message == ending.message
    # The robot may take it late: that goal is canceled by its own id (never every goal on the
    # server, which may be other clients'), again until the robot has it canceling.
    assert wait_until(lambda: len(silent.canceled) >= 2)
    assert set(silent.canceled) == {goal_id}


def test_a_canceled_goal_cancels_its_ros_goal_and_ends_canceled(rig: Rig) -> None:
    action, handle = FakeAction("arm"), FakeHandle(swing(10.0))
    rig.clock.once(lambda: bool(action.goals), lambda: setattr(handle, "stop", True))
    ending = TrajectoryRun(rig.context, action, handle, MESSAGES, joint_states_timeout=UNWATCHED).run()
    assert ending.state is GoalState.CANCELED and ending.message == "canceled"
    assert action.goals[0].cancels == 1


def test_a_goal_safety_aborts_ends_aborted_with_the_reason(rig: Rig) -> None:
    action, handle = FakeAction("gripper"), FakeHandle(GripperCommandGoal(position=0.0))
    run = GripperRun(rig.context, action, handle, MESSAGES, {}, 0.2)

    def latch() -> None:
        rig.set(SafetyNow("e-stop latched by operator: test", status(latched=True)))
        handle.abort_reason, handle.stop = "e-stop latched by operator: test", True

    rig.clock.once(lambda: bool(action.goals), latch)
    ending = run.run()
    assert ending.state is GoalState.ABORTED and ending.message == "e-stop latched by operator: test"
    assert action.goals[0].cancels == 1


def test_a_cancel_the_robot_never_confirms_halts_the_base_and_says_so(rig: Rig) -> None:
    action = FakeAction("navigate_to_pose", ends_on_cancel=False)
    handle = FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=7.0, y=1.2)))
    rig.clock.once(lambda: bool(action.goals), lambda: setattr(handle, "stop", True))
    ending = navigation(rig, handle, action).run()
    assert "did not confirm" in ending.message and rig.halts


def test_a_cancel_the_robot_never_confirms_holds_its_emergency_stop_and_is_asked_again_until_the_goal_ends(
    rig: Rig,
) -> None:
    blocks: list[str] = []
    released = threading.Event()

    def block_robot(reason: str) -> Callable[[], None]:
        blocks.append(reason)
        return released.set

    action, handle = FakeAction("arm", ends_on_cancel=False), FakeHandle(swing(10.0))
    rig.clock.once(lambda: bool(action.goals), lambda: setattr(handle, "stop", True))
    ending = TrajectoryRun(
        replace(rig.context, block_robot=block_robot), action, handle, MESSAGES, joint_states_timeout=UNWATCHED
    ).run()
    assert "did not confirm" in ending.message and "emergency stop is held" in ending.message
    assert blocks == [
        "the robot did not end its follow_joint_trajectory goal when canceled: its emergency stop is "
        "held until the goal ends"
    ]
    assert any(blocks[0] in text for text, _ in rig.robot.diagnostics()), "an operator sees why"
    [goal] = action.goals
    assert wait_until(lambda: goal.cancels >= 3), "the goal's cancel is asked again"
    assert not released.is_set(), "held while the goal runs"
    goal.finish(CANCELED)
    assert released.wait(5.0), "released once the robot ended it"


def test_a_goal_stopped_while_it_is_made_is_never_sent(rig: Rig) -> None:
    action, handle = FakeAction("arm"), FakeHandle(swing())
    run = TrajectoryRun(rig.context, action, handle, MESSAGES, joint_states_timeout=UNWATCHED)
    made = run.next_goal

    def next_goal(scale: float) -> Any:
        handle.abort_reason, handle.stop = "e-stop latched by operator: test", True
        return made(scale)

    run.next_goal = next_goal  # type: ignore[method-assign]
    ending = run.run()
    assert ending.state is GoalState.ABORTED and ending.message == "e-stop latched by operator: test"
    assert action.goals == []


def test_a_goal_sent_while_safety_stopped_the_robot_is_canceled_at_once_and_sent_again(rig: Rig) -> None:
    epoch = [0]
    action = FakeAction("arm", during_send=lambda: epoch.__setitem__(0, 1))  # a stop, then a release
    rig.clock.once(lambda: len(action.goals) == 2, lambda: action.goals[1].finish(SUCCEEDED, trajectory_result()))
    context = replace(rig.context, motion_epoch=lambda: epoch[0])
    ending = TrajectoryRun(context, action, FakeHandle(swing()), MESSAGES, joint_states_timeout=UNWATCHED).run()
    assert ending.state is GoalState.SUCCEEDED, ending.message
    first, _again = action.goals
    assert first.cancels == 1


def test_a_goal_run_that_fails_cancels_its_ros_goal_and_leaves_the_base_still(rig: Rig) -> None:
    action, handle = FakeAction("navigate_to_pose"), FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=7.0, y=1.2)))
    run = navigation(rig, handle, action)

    def broken(now: float, moving: bool, scale: float) -> str | None:
        raise RuntimeError("a bug")

    rig.clock.once(lambda: bool(action.goals), lambda: setattr(run, "check", broken))
    ending = run.run()
    assert ending.state is GoalState.ABORTED and "a bug" in ending.message
    assert action.goals[0].cancels == 1 and rig.halts


class BrokenResult(FakeGoal):
    def result(self, timeout: float) -> tuple[int, Any]:
        raise TypeError("a decoder bug")


def test_a_result_that_fails_unexpectedly_ends_the_goal_and_cancels_it_on_the_robot(rig: Rig) -> None:
    action = FakeAction("arm", make=BrokenResult)
    ending = TrajectoryRun(rig.context, action, FakeHandle(swing(10.0)), MESSAGES, joint_states_timeout=UNWATCHED).run()
    assert ending.state is GoalState.ABORTED and "a decoder bug" in ending.message
    assert action.goals[0].cancels == 1


class ResultNeverComes(FakeGoal):
    """A goal whose get_result never answers: it may run on whatever its status says."""

    def result(self, timeout: float) -> tuple[int, Any]:
        raise RobotCallFailed("get_result: no answer within 10 s")


def test_a_goal_whose_status_says_it_ended_but_whose_result_never_comes_is_canceled_on_the_robot(
    rig: Rig,
) -> None:
    action = FakeAction("arm", make=ResultNeverComes)
    # A terminal status on the action's status topic, as anyone on the robot's network could publish.
    rig.clock.once(lambda: bool(action.goals), lambda: setattr(action.goals[0], "status", ABORTED))
    ending = TrajectoryRun(rig.context, action, FakeHandle(swing(4.0)), MESSAGES, joint_states_timeout=UNWATCHED).run()
    assert ending.state is GoalState.ABORTED and "its result could not be read" in ending.message
    assert action.goals[0].cancels == 1


def test_a_finished_goal_is_forgotten_by_the_action_client(rig: Rig) -> None:
    action = FakeAction("arm")
    rig.clock.once(lambda: bool(action.goals), lambda: action.goals[0].finish(SUCCEEDED, trajectory_result()))
    assert (
        TrajectoryRun(rig.context, action, FakeHandle(swing()), MESSAGES, joint_states_timeout=UNWATCHED).run().state
        is GoalState.SUCCEEDED
    )
    assert wait_until(lambda: action.goals[0].forgotten)


def test_a_cmd_vel_ends_with_one_zero_after_its_hold_and_a_clamped_resend_never_extends_it() -> None:
    hold, cap = CmdVelHold(0.5), [0.6]

    def clamp(twist: Twist) -> tuple[float, float]:
        return min(twist.linear_x, cap[0]), twist.angular_z

    hold.sent(Twist(linear_x=0.5, angular_z=0.1), 0.5, 0.1, 10.0)
    assert hold.due(clamp, 10.1) is None
    cap[0] = 0.2
    assert hold.due(clamp, 10.2) == (0.2, 0.1)  # a lower limit: sent again, clamped
    assert hold.due(clamp, 10.3) is None and hold.ends_at == pytest.approx(10.5)
    assert hold.due(clamp, 10.5) == (0.0, 0.0)  # the hold is over: one zero ends it
    assert hold.due(clamp, 10.6) is None and hold.ends_at is None


@pytest.mark.parametrize("distro", ["humble", "iron", "kilted"])
def test_a_distro_other_than_the_bundled_interfaces_is_refused_saying_why(distro: str) -> None:
    with pytest.raises(msgspec.ValidationError, match=f"distro '{distro}' is not supported: .*; supported: jazzy"):
        msgspec.convert({"distro": distro}, Ros2Config)
    assert msgspec.convert({"style": "bridge"}, Ros2Config).distro == "jazzy"
    with pytest.raises(msgspec.ValidationError, match="cmd_vel_timeout"):
        msgspec.convert({"cmd_vel_timeout": 2.0}, Ros2Config)


def navigation(rig: Rig, handle: FakeHandle, to_pose: Any, through: Any | None = None) -> NavigationRun:
    return NavigationRun(
        rig.context,
        handle,
        to_pose=to_pose,
        through_poses=through or FakeAction("navigate_through_poses"),
        messages=MESSAGES,
        limits=BaseLimits(0.6, 1.2),
        publish_speed_limit=lambda _limit: None,
        base_radius=MODEL.base_radius,
        odom_timeout=0.5,
        stall_timeout=10.0,
    )


def test_a_navigation_checked_from_elsewhere_is_refused_and_nothing_is_sent(rig: Rig) -> None:
    action = FakeAction("navigate_to_pose")
    goal = NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2), start=Pose2D(x=7.0, y=1.2))
    ending = navigation(rig, FakeHandle(goal), action).run()
    assert ending.state is GoalState.ABORTED and "checked from" in ending.message
    assert action.goals == []


def test_a_navigation_with_odometry_in_the_wrong_frame_is_refused_with_the_reason(rig: Rig) -> None:
    rig.clock.now += 1.0  # the good odometry is old
    rig.robot.refused_odometry("odometry in frame 'map', expected 'odom' ([ros2.frames] odom)")
    ending = navigation(rig, FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2))), FakeAction("nav")).run()
    assert ending.state is GoalState.ABORTED and "frame 'map'" in ending.message


def test_a_navigation_refused_for_odometry_in_a_frame_of_any_length_says_so_in_a_message_that_fits(
    rig: Rig,
) -> None:
    rig.clock.now += 1.0
    rig.robot.refused_odometry(f"odometry in frame {'m' * 10_000!r}, expected 'odom' ([ros2.frames] odom)")
    ending = navigation(rig, FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2))), FakeAction("nav")).run()
    assert ending.state is GoalState.ABORTED and "odometry in frame 'mmm" in ending.message
    assert ending.message.endswith("… [cut: 10067 characters in all]") and len(ending.message) < backend.TEXT_MAX // 2
    assert_plan_reads(ending, NavigateToPoseResult)


def test_a_base_pushed_off_its_route_is_stopped_and_the_goal_aborted(rig: Rig) -> None:
    action = FakeAction("navigate_to_pose")
    handle = FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2), start=Pose2D(x=6.0, y=1.2)))
    rig.clock.once(lambda: bool(action.goals), lambda: rig.odometry(Pose2D(x=6.5, y=1.26), v=0.3))
    ending = navigation(rig, handle, action).run()
    assert ending.state is GoalState.ABORTED and "off its route" in ending.message
    assert action.goals[0].cancels == 1 and rig.halts


def test_a_paused_navigation_is_canceled_and_the_rest_sent_through_its_remaining_poses(rig: Rig) -> None:
    to_pose, through = FakeAction("navigate_to_pose"), FakeAction("navigate_through_poses")
    handle = FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2), start=Pose2D(x=6.0, y=1.2)))

    def drive_then_pause() -> None:
        rig.odometry(Pose2D(x=6.8, y=1.2))
        rig.set(clear(0.0))
        rig.clock.at(rig.clock.now + 1.0, lambda: rig.set(clear()))

    rig.clock.once(lambda: bool(to_pose.goals), drive_then_pause)
    rig.clock.once(lambda: bool(through.goals), lambda: arrive(rig, through, Pose2D(x=8.0, y=1.2)))
    ending = navigation(rig, handle, to_pose, through).run()
    assert ending.state is GoalState.SUCCEEDED, ending.message
    assert to_pose.goals[0].cancels == 1
    poses = [(round(p.pose.position.x, 3), p.pose.position.y) for p in through.goals[0].goal.poses]
    assert poses == [(7.6, 1.2), (8.0, 1.2)], "the rest of the legs: to the pre-goal point, then the goal"
    feedback = [f for f in handle.feedbacks if f is not None]
    assert feedback[0].distance_remaining > feedback[-1].distance_remaining


def test_the_config_has_every_ros_name_and_takes_the_domain_from_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    config = Ros2Config(domain_id=7)
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert config.ros_domain() == 7
    monkeypatch.setenv("ROS_DOMAIN_ID", "3")
    assert config.ros_domain() == 3
    monkeypatch.setenv("ROS_DOMAIN_ID", "x")
    with pytest.raises(ValueError, match="ROS_DOMAIN_ID"):
        config.ros_domain()


def test_a_navigation_tells_nav2_its_speed_limit_as_the_heartbeat_changes_it_and_lifts_it_after(rig: Rig) -> None:
    action = FakeAction("navigate_to_pose")
    limits: list[float] = []
    run = navigation(rig, FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=7.0, y=1.2), max_speed=0.4)), action)
    run.publish_speed_limit = limits.append
    rig.clock.once(lambda: bool(action.goals), lambda: rig.set(clear(0.5)))
    rig.clock.once(lambda: len(limits) == 2, lambda: arrive(rig, action, Pose2D(x=7.0, y=1.2)))
    assert run.run().state is GoalState.SUCCEEDED
    assert limits == pytest.approx([0.4, 0.3, 0.6]), "the goal's, then the scaled maximum, then lifted"


def arrive(rig: Rig, action: Any, where: Pose2D) -> None:
    """The base driven to `where` in 2 cm steps, one each POLL of the run's clock, then Nav2's goal
    ends succeeded. A jump there at once may be checked first as a base off its route: the tracker
    follows the legs at most two phases ahead."""
    (here, _), step = rig.base, 0.02
    count = max(1, math.ceil(math.hypot(where.x - here.x, where.y - here.y) / step))
    for k in range(1, count + 1):
        f = k / count
        pose = Pose2D(x=here.x + (where.x - here.x) * f, y=here.y + (where.y - here.y) * f, yaw=here.yaw)
        rig.clock.at(rig.clock.now + k * POLL, lambda pose=pose: rig.odometry(pose))  # type: ignore[misc]
    rig.clock.at(rig.clock.now + (count + 1) * POLL, lambda: rig.odometry(where))
    rig.clock.at(rig.clock.now + (count + 2) * POLL, lambda: action.goals[0].finish(SUCCEEDED))


@pytest.mark.parametrize(
    ("where", "off"),
    [(Pose2D(x=6.0, y=1.2), "2.00 m and 0.00 rad"), (Pose2D(x=8.0, y=1.2, yaw=0.1), "0.00 m and 0.10 rad")],
    ids=["short of it", "facing elsewhere"],
)
def test_a_navigation_nav2_says_arrived_but_odometry_does_not_is_aborted(rig: Rig, where: Pose2D, off: str) -> None:
    """Nav2's word is not taken for it: a goal checker looser than tether's, or a robot that is wrong."""
    action = FakeAction("navigate_to_pose")
    handle = FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2), start=Pose2D(x=6.0, y=1.2)))
    rig.clock.once(lambda: bool(action.goals), lambda: arrive(rig, action, where))
    ending = navigation(rig, handle, action).run()
    assert ending.state is GoalState.ABORTED, ending.message
    assert "the robot says it reached the goal pose, but odometry has the base at" in ending.message
    assert off in ending.message and "set Nav2's goal checker within these" in ending.message
    assert rig.halts, "the base is stopped"


def test_a_navigation_that_ends_within_the_arrival_tolerance_succeeded(rig: Rig) -> None:
    action = FakeAction("navigate_to_pose")
    handle = FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2), start=Pose2D(x=6.0, y=1.2)))
    rig.clock.once(lambda: bool(action.goals), lambda: arrive(rig, action, Pose2D(x=7.97, y=1.21, yaw=0.04)))
    ending = navigation(rig, handle, action).run()
    assert (ending.state, ending.message) == (GoalState.SUCCEEDED, "reached the goal pose")


def test_why_there_is_no_odometry_names_the_latest_problem_with_it() -> None:
    clock = Clock()
    robot = RobotState(clock, odom_topic="odom")
    assert robot.odometry(0.5) == "no odometry from the robot yet"
    robot.refused_odometry("odometry in frame 'map', expected 'odom'")
    robot.problem("undecodable sample on /joint_states: ...")
    clock.now += 1.0
    robot.problem("undecodable sample on /odom: nav_msgs/msg/Odometry: undecodable CDR")
    assert (
        robot.odometry(0.5)
        == "no odometry from the robot yet; undecodable sample on /odom: nav_msgs/msg/Odometry: undecodable CDR"
    )
    clock.now += 10.0
    assert robot.odometry(0.5) == "no odometry from the robot yet", "old problems are forgotten"
