"""The stand-in's conversions between the sim's messages and ROS 2's, pure: what it accepts and what it says."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from schemas.actions import GoalState
from schemas.common import Pose2D, Vec3
from schemas.robot import (
    FollowJointTrajectoryFeedback,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    GripperCommandResult,
    JointState,
    NavigateToPoseFeedback,
    Odometry,
)
from schemas.world import Extent, PerceivedHuman, PerceivedHumans, PerceivedObject, PerceivedObjects
from services.actionlib import Outcome
from services.ros2.types import RosTypes
from services.ros2sim import messages
from services.ros2sim.messages import BadMessage
from services.worldmodel import load_world

TYPES = RosTypes()
ROBOT = load_world("household").robot


def roundtrip(ros_type: str, message: Any) -> Any:
    """What the other side decodes: the message is valid on the wire."""
    return TYPES.decode(ros_type, TYPES.encode(ros_type, message))


def stamped_pose(x: float, y: float, yaw: float = 0.0, frame: str = "odom") -> Any:
    return TYPES.new(
        "geometry_msgs/msg/PoseStamped",
        header=messages.header(TYPES, 0.0, frame),
        pose=messages.pose(TYPES, x, y, 0.0, yaw),
    )


def trajectory(names: list[str], points: list[tuple[list[float], float]], **tolerances: list[tuple[str, float]]) -> Any:
    ros_points = [
        TYPES.new(
            "trajectory_msgs/msg/JointTrajectoryPoint",
            positions=np.array(positions, dtype=np.float64),
            time_from_start=messages.duration(TYPES, at),
        )
        for positions, at in points
    ]
    fields = {
        field: [TYPES.new("control_msgs/msg/JointTolerance", name=n, position=p) for n, p in given]
        for field, given in tolerances.items()
    }
    return TYPES.new(
        f"{messages.FOLLOW_JOINT_TRAJECTORY}_Goal",
        trajectory=TYPES.new("trajectory_msgs/msg/JointTrajectory", joint_names=names, points=ros_points),
        **fields,
    )


# Time and geometry


@pytest.mark.parametrize("stamp", [0.0, 1.5, 1_764_000_000.25, 1.9999999999])
def test_stamps_become_ros_times_and_durations(stamp: float) -> None:
    time = messages.ros_time(TYPES, stamp)
    assert 0 <= time.nanosec <= 999_999_999
    assert time.sec + time.nanosec * 1e-9 == pytest.approx(stamp, abs=1e-6)
    assert messages.seconds_of(messages.duration(TYPES, stamp)) == pytest.approx(stamp, abs=1e-6)


@pytest.mark.parametrize("yaw", [0.0, 0.5, -1.2, math.pi - 1e-6, -math.pi + 1e-6])
def test_a_heading_survives_the_quaternion(yaw: float) -> None:
    assert messages.yaw_of(messages.quaternion(TYPES, yaw)) == pytest.approx(yaw, abs=1e-9)


def test_an_unnormalised_quaternion_gives_its_heading_and_no_rotation_is_refused() -> None:
    q = TYPES.new("geometry_msgs/msg/Quaternion", z=2.0 * math.sin(0.3), w=2.0 * math.cos(0.3))
    assert messages.yaw_of(q) == pytest.approx(0.6)
    with pytest.raises(BadMessage, match="zero quaternion"):
        messages.yaw_of(TYPES.new("geometry_msgs/msg/Quaternion", w=0.0))
    with pytest.raises(BadMessage, match="not finite"):
        messages.yaw_of(TYPES.new("geometry_msgs/msg/Quaternion", w=math.nan))


# Goals in


@pytest.mark.parametrize("frame", ["odom", "map", "/map"])
def test_a_navigation_goal_in_the_odom_or_map_frame_drives_from_where_the_base_stands(frame: str) -> None:
    goal = messages.navigate_to_pose_goal(
        TYPES.new(f"{messages.NAVIGATE_TO_POSE}_Goal", pose=stamped_pose(7.0, 1.5, 0.4, frame))
    )
    assert (goal.pose.x, goal.pose.y, goal.pose.yaw) == pytest.approx((7.0, 1.5, 0.4))
    assert goal.start is None and goal.path == [] and goal.max_speed is None


@pytest.mark.parametrize(
    ("pose", "reason"),
    [
        (stamped_pose(7.0, 1.5, frame="base_link"), "frame 'base_link'"),
        (stamped_pose(7.0, 1.5, frame=""), "frame ''"),
        (stamped_pose(math.nan, 1.5), "not finite"),
        (stamped_pose(7.0, math.inf), "not finite"),
        (stamped_pose(5000.0, 1.5), r"\$\.x"),
    ],
)
def test_a_navigation_goal_it_cannot_drive_is_refused_saying_why(pose: Any, reason: str) -> None:
    with pytest.raises(BadMessage, match=reason):
        messages.navigate_to_pose_goal(TYPES.new(f"{messages.NAVIGATE_TO_POSE}_Goal", pose=pose))


def test_navigate_through_poses_drives_through_all_but_the_last_to_the_last() -> None:
    poses = [stamped_pose(7.0, 1.2), stamped_pose(8.0, 1.2), stamped_pose(8.0, 2.0, 1.5)]
    goal = messages.navigate_through_poses_goal(TYPES.new(f"{messages.NAVIGATE_THROUGH_POSES}_Goal", poses=poses))
    assert (goal.pose.x, goal.pose.y, goal.pose.yaw) == pytest.approx((8.0, 2.0, 1.5))
    assert [(p.x, p.y) for p in goal.path] == [(7.0, 1.2), (8.0, 1.2)]
    with pytest.raises(BadMessage, match="empty"):
        messages.navigate_through_poses_goal(TYPES.new(f"{messages.NAVIGATE_THROUGH_POSES}_Goal"))
    with pytest.raises(BadMessage, match=r"poses\[1\]"):
        bad = [stamped_pose(7.0, 1.2), stamped_pose(8.0, 1.2, frame="base_link")]
        messages.navigate_through_poses_goal(TYPES.new(f"{messages.NAVIGATE_THROUGH_POSES}_Goal", poses=bad))


def test_a_trajectory_keeps_its_joints_positions_and_times_with_the_sims_tolerances() -> None:
    goal = messages.trajectory_goal(
        trajectory(["panda_joint2", "panda_joint1"], [([0.1, 0.2], 0.5), ([0.3, 0.4], 1.25)])
    )
    assert goal.joint_names == ["panda_joint2", "panda_joint1"]
    assert [(p.positions, p.time_from_start) for p in goal.points] == [([0.1, 0.2], 0.5), ([0.3, 0.4], 1.25)]
    defaults = FollowJointTrajectoryGoal(joint_names=["panda_joint1"], points=goal.points[:1])
    assert (goal.path_tolerance, goal.goal_tolerance) == (defaults.path_tolerance, defaults.goal_tolerance)


def test_per_joint_tolerances_become_the_tightest_given() -> None:
    names = ["panda_joint1", "panda_joint2"]
    goal = messages.trajectory_goal(
        trajectory(
            names,
            [([0.0, 0.0], 1.0)],
            path_tolerance=[("panda_joint1", 0.05), ("panda_joint2", 0.0)],  # 0: the default for that joint
            goal_tolerance=[("panda_joint1", -1.0), ("panda_joint2", 3.0)],  # -1: none; capped at 1 rad
        )
    )
    assert (goal.path_tolerance, goal.goal_tolerance) == (0.05, messages.MAX_TOLERANCE)


@pytest.mark.parametrize(
    ("goal", "reason"),
    [
        (trajectory(["panda_joint1"], [([math.nan], 1.0)]), "not finite"),
        (trajectory(["panda_joint1"], []), r"\$\.points"),
        (trajectory(["panda_joint1"], [([0.0], 1.0)], path_tolerance=[("elbow", 0.1)]), "elbow"),
        (trajectory(["panda_joint1"], [([0.0], 1.0)], goal_tolerance=[("panda_joint1", -2.0)]), "-2"),
        (trajectory(["panda_joint1"], [([0.0], 1.0)], goal_tolerance=[("panda_joint1", math.nan)]), "not finite"),
        (trajectory([f"j{i}" for i in range(20)], [([0.0] * 20, 1.0)]), "20 entries; at most 16"),
        (trajectory(["panda_joint1"], [([0.0], 1.0)] * 2001), "2001 entries; at most 2000"),
    ],
)
def test_a_trajectory_that_is_not_one_is_refused_saying_why(goal: Any, reason: str) -> None:
    with pytest.raises(BadMessage, match=reason):
        messages.trajectory_goal(goal)


def test_a_multi_dof_trajectory_is_refused() -> None:
    goal = trajectory(["panda_joint1"], [([0.0], 1.0)])
    goal.multi_dof_trajectory.joint_names = ["base"]
    with pytest.raises(BadMessage, match="multi-DOF"):
        messages.trajectory_goal(goal)


def gripper(position: float, max_effort: float) -> Any:
    command = TYPES.new("control_msgs/msg/GripperCommand", position=position, max_effort=max_effort)
    return TYPES.new(f"{messages.GRIPPER_COMMAND}_Goal", command=command)


def test_a_gripper_goal_within_the_grippers_range_is_taken_as_it_is() -> None:
    assert messages.gripper_goal(gripper(0.03, 20.0)) == GripperCommandGoal(position=0.03, max_effort=20.0)
    for position, effort, reason in (
        (0.5, 20.0, r"\$\.position"),
        (0.03, -1.0, r"\$\.max_effort"),
        (math.nan, 1, "not finite"),
    ):
        with pytest.raises(BadMessage, match=reason):
            messages.gripper_goal(gripper(position, effort))


# Streams in


def test_cmd_vel_takes_forward_speed_and_turn_rate_stamped_or_not() -> None:
    vector = "geometry_msgs/msg/Vector3"
    body = TYPES.new(
        "geometry_msgs/msg/Twist", linear=TYPES.new(vector, x=0.3, y=5.0), angular=TYPES.new(vector, z=-0.2)
    )
    plain = messages.twist(body, stamped=False)
    assert (plain.linear_x, plain.angular_z, plain.stamp) == (0.3, -0.2, 0.0)
    stamped = messages.twist(
        TYPES.new("geometry_msgs/msg/TwistStamped", header=messages.header(TYPES, 12.5), twist=body), stamped=True
    )
    assert (stamped.linear_x, stamped.angular_z, stamped.stamp) == (0.3, -0.2, 12.5)
    with pytest.raises(BadMessage, match="not finite"):
        messages.twist(TYPES.new("geometry_msgs/msg/Twist", linear=TYPES.new(vector, x=math.nan)), stamped=False)
    with pytest.raises(BadMessage, match=r"\$\.linear_x"):
        messages.twist(TYPES.new("geometry_msgs/msg/Twist", linear=TYPES.new(vector, x=1e9)), stamped=False)


def limit(value: float, percentage: bool = False) -> Any:
    return TYPES.new("nav2_msgs/msg/SpeedLimit", percentage=percentage, speed_limit=value)


def test_speed_limit_as_nav2_reads_it_limits_the_turn_rate_alike() -> None:
    top, turn = ROBOT.max_linear_speed, ROBOT.max_angular_speed
    assert messages.speed_limits(limit(0.0), ROBOT) == (None, None)
    assert messages.speed_limits(limit(0.0, percentage=True), ROBOT) == (None, None)
    assert messages.speed_limits(limit(50.0, percentage=True), ROBOT) == pytest.approx((top / 2, turn / 2))
    assert messages.speed_limits(limit(top / 4), ROBOT) == pytest.approx((top / 4, turn / 4))
    assert messages.speed_limits(limit(top * 10), ROBOT) == pytest.approx((top, turn))
    assert messages.speed_limits(limit(150.0, percentage=True), ROBOT) == pytest.approx((top, turn))
    for bad in (-0.1, math.nan, math.inf):
        with pytest.raises(BadMessage):
            messages.speed_limits(limit(bad), ROBOT)


# Reports out


def test_odometry_is_in_the_odom_frame_with_the_base_as_child() -> None:
    odom = Odometry(stamp=100.25, sim_time=3.0, pose=Pose2D(x=6.0, y=1.2, yaw=0.7), linear_x=0.4, angular_z=-0.1)
    out = roundtrip("nav_msgs/msg/Odometry", messages.odometry(TYPES, odom))
    assert (out.header.frame_id, out.child_frame_id) == ("odom", "base_link")
    assert messages.seconds_of(out.header.stamp) == pytest.approx(100.25)
    position = out.pose.pose.position
    assert (position.x, position.y, position.z) == (6.0, 1.2, 0.0)
    assert messages.yaw_of(out.pose.pose.orientation) == pytest.approx(0.7)
    assert (out.twist.twist.linear.x, out.twist.twist.angular.z) == (0.4, -0.1)


def test_joint_states_keep_names_positions_and_velocities() -> None:
    state = JointState(
        stamp=5.0, name=["panda_joint1", "panda_finger_joint1"], position=[0.1, 0.04], velocity=[0.0, 0.01]
    )
    out = roundtrip("sensor_msgs/msg/JointState", messages.joint_state(TYPES, state))
    assert out.name == state.name
    assert list(out.position) == state.position and list(out.velocity) == state.velocity


def perceived(ident: str, cls: str, on: str | None, yaw: float | None = None) -> PerceivedObject:
    return PerceivedObject(
        id=ident, name=ident, cls=cls, color="red", position=Vec3(x=1.0, y=2.0, z=0.9), on=on, stamp=7.0, yaw=yaw
    )


def test_objects_are_detections_with_their_id_class_pose_and_size_and_the_held_one_in_the_hand() -> None:
    seen = PerceivedObjects(
        stamp=7.0,
        objects=[perceived("blue_book", "book", "coffee_table", yaw=0.3), perceived("red_cup", "cup", "gripper")],
    )
    sizes = {"blue_book": Extent(x=0.2, y=0.15, z=0.03)}
    out = roundtrip("vision_msgs/msg/Detection3DArray", messages.object_detections(TYPES, seen, sizes))
    book, cup = out.detections
    assert (book.id, book.results[0].hypothesis.class_id, book.results[0].hypothesis.score) == (
        "blue_book",
        "book",
        1.0,
    )
    assert book.header.frame_id == "odom" and cup.header.frame_id == "panda_hand"
    where = book.results[0].pose.pose
    assert (where.position.x, where.position.y, where.position.z) == (1.0, 2.0, 0.9)
    assert messages.yaw_of(where.orientation) == pytest.approx(0.3)
    assert book.bbox.center == where and (book.bbox.size.x, book.bbox.size.y, book.bbox.size.z) == (0.2, 0.15, 0.03)
    # No heading known: the identity rotation; no size known: zero.
    assert cup.results[0].pose.pose.orientation.w == 1.0 and cup.bbox.size.x == 0.0


def test_people_are_person_detections_where_they_stand() -> None:
    people = PerceivedHumans(
        stamp=8.0, humans=[PerceivedHuman(id="operator", name="Alex", pose=Pose2D(x=3.0, y=4.0, yaw=1.0))]
    )
    out = roundtrip("vision_msgs/msg/Detection3DArray", messages.people_detections(TYPES, people))
    (person,) = out.detections
    assert (person.id, person.results[0].hypothesis.class_id, person.header.frame_id) == ("operator", "person", "odom")
    where = person.results[0].pose.pose
    assert (where.position.x, where.position.y) == (3.0, 4.0)
    assert messages.yaw_of(where.orientation) == pytest.approx(1.0)
    assert person.bbox.size.z > 1.0


def test_a_picture_is_a_png_compressed_image() -> None:
    out = roundtrip("sensor_msgs/msg/CompressedImage", messages.compressed_image(TYPES, b"\x89PNG\r\n", 9.0))
    assert out.format == "png" and bytes(out.data) == b"\x89PNG\r\n"


# Feedback and results out


def test_navigation_feedback_and_results_as_nav2_gives_them() -> None:
    for action in (messages.NAVIGATE_TO_POSE, messages.NAVIGATE_THROUGH_POSES):
        feedback = NavigateToPoseFeedback(pose=Pose2D(x=6.5, y=1.2, yaw=0.0), distance_remaining=1.5)
        out = roundtrip(f"{action}_Feedback", messages.navigation_feedback(TYPES, action, feedback, 10.0, 2.5))
        assert out.current_pose.pose.position.x == 6.5 and out.current_pose.header.frame_id == "odom"
        assert out.distance_remaining == pytest.approx(1.5)
        assert messages.seconds_of(out.navigation_time) == pytest.approx(2.5)
        done = messages.navigation_result(TYPES, action, Outcome(GoalState.SUCCEEDED, None, "reached"))
        assert (done.error_code, done.error_msg) == (messages.NAV_NONE, "")
        failed = messages.navigation_result(TYPES, action, Outcome(GoalState.ABORTED, None, "stalled"))
        assert (failed.error_code, failed.error_msg) == (messages.NAV_UNKNOWN, "stalled")
        roundtrip(f"{action}_Result", failed)


def test_trajectory_feedback_and_error_codes_as_control_msgs_gives_them() -> None:
    feedback = FollowJointTrajectoryFeedback(desired=[0.5, 0.2], actual=[0.4, 0.2], time_from_start=0.75)
    out = roundtrip(
        f"{messages.FOLLOW_JOINT_TRAJECTORY}_Feedback",
        messages.trajectory_feedback(TYPES, feedback, ["panda_joint1", "panda_joint2"], 3.0),
    )
    assert out.joint_names == ["panda_joint1", "panda_joint2"]
    assert list(out.error.positions) == pytest.approx([0.1, 0.0])
    assert messages.seconds_of(out.desired.time_from_start) == pytest.approx(0.75)
    # The sim's own messages for the two ways a trajectory fails.
    path = "panda_joint2 was 0.150 rad from the trajectory at 0.50 s (path tolerance 0.1 rad): blocked or pushed"
    goal = "final joint error 0.050 rad exceeds the tolerance 0.02 rad"
    codes: dict[Outcome[Any], int] = {
        Outcome(GoalState.SUCCEEDED, None, "reached the last point"): messages.TRAJECTORY_SUCCESSFUL,
        Outcome(GoalState.CANCELED, None, "canceled"): messages.TRAJECTORY_SUCCESSFUL,
        Outcome(GoalState.ABORTED, None, path): messages.PATH_TOLERANCE_VIOLATED,
        Outcome(GoalState.ABORTED, None, goal): messages.GOAL_TOLERANCE_VIOLATED,
        Outcome(GoalState.ABORTED, None, "emergency stop"): messages.GOAL_TOLERANCE_VIOLATED,
    }
    for outcome, code in codes.items():
        result = roundtrip(f"{messages.FOLLOW_JOINT_TRAJECTORY}_Result", messages.trajectory_result(TYPES, outcome))
        assert (result.error_code, result.error_string) == (code, outcome.message)


def test_a_gripper_result_says_where_the_fingers_stopped_and_whether_on_an_object() -> None:
    goal = GripperCommandGoal(position=0.0, max_effort=30.0)
    held = GripperCommandResult(position=0.031, stalled=True, reached_goal=False, holding="red_cup")
    out = roundtrip(
        f"{messages.GRIPPER_COMMAND}_Result",
        messages.gripper_result(TYPES, Outcome(GoalState.SUCCEEDED, held, "holding red_cup"), goal),
    )
    assert (out.position, out.effort, out.stalled, out.reached_goal) == (0.031, 30.0, True, False)
    never = messages.gripper_result(TYPES, Outcome(GoalState.ABORTED, None, "emergency stop"), goal)
    assert (never.position, never.stalled, never.reached_goal) == (0.0, False, False)
