"""The stand-in's refusals of hostile goals: bounded work before converting, and a bounded reason."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from schemas.robot import MAX_JOINTS
from services.ros2.types import RosTypes
from services.ros2sim import messages
from services.ros2sim.messages import BadMessage

TYPES = RosTypes()
HUGE = 1_000_000  # characters: a frame_id or joint name from a hostile peer, within one request


def trajectory_goal(positions: list[float], **tolerances: list[tuple[str, float]]) -> Any:
    point = TYPES.new(
        "trajectory_msgs/msg/JointTrajectoryPoint",
        positions=np.array(positions, dtype=np.float64),
        time_from_start=messages.duration(TYPES, 1.0),
    )
    fields = {
        field: [TYPES.new("control_msgs/msg/JointTolerance", name=n, position=p) for n, p in given]
        for field, given in tolerances.items()
    }
    trajectory = TYPES.new("trajectory_msgs/msg/JointTrajectory", joint_names=["panda_joint1"], points=[point])
    return TYPES.new(f"{messages.FOLLOW_JOINT_TRAJECTORY}_Goal", trajectory=trajectory, **fields)


def test_a_point_with_more_positions_than_any_arm_has_joints_is_refused_before_reading_them() -> None:
    positions = [0.0] * 100_000
    positions[-1] = math.nan  # read one by one, the refusal would list all 100000
    with pytest.raises(BadMessage, match=rf"points\[0\]\.positions has 100000 entries; at most {MAX_JOINTS}") as info:
        messages.trajectory_goal(trajectory_goal(positions))
    assert len(str(info.value)) < 200


def test_more_tolerances_than_any_arm_has_joints_are_refused() -> None:
    goal = trajectory_goal([0.0], path_tolerance=[("panda_joint1", 0.1)] * 50_000)
    with pytest.raises(BadMessage, match=rf"path_tolerance has 50000 entries; at most {MAX_JOINTS}"):
        messages.trajectory_goal(goal)


def test_a_refusal_quotes_a_huge_frame_or_joint_name_cut_short() -> None:
    stamped = TYPES.new(
        "geometry_msgs/msg/PoseStamped",
        header=messages.header(TYPES, 0.0, "f" * HUGE),
        pose=messages.pose(TYPES, 7.0, 1.5),
    )
    with pytest.raises(BadMessage, match=rf"frame 'f+'\.\.\. \({HUGE} characters\)") as frame:
        messages.navigate_to_pose_goal(TYPES.new(f"{messages.NAVIGATE_TO_POSE}_Goal", pose=stamped))
    goal = trajectory_goal([0.0], goal_tolerance=[("j" * HUGE, 0.1)])
    with pytest.raises(BadMessage, match=rf"names joint 'j+'\.\.\. \({HUGE} characters\)") as joint:
        messages.trajectory_goal(goal)
    assert len(str(frame.value)) < 300 and len(str(joint.value)) < 300
    # A short name is quoted whole, as before.
    with pytest.raises(BadMessage, match="frame 'base_link';"):
        stamped.header.frame_id = "base_link"
        messages.navigate_to_pose_goal(TYPES.new(f"{messages.NAVIGATE_TO_POSE}_Goal", pose=stamped))


def point(positions: list[float], at: float, **fields: list[float]) -> Any:
    arrays = {name: np.array(values, dtype=np.float64) for name, values in fields.items()}
    return TYPES.new(
        "trajectory_msgs/msg/JointTrajectoryPoint",
        positions=np.array(positions, dtype=np.float64),
        time_from_start=messages.duration(TYPES, at),
        **arrays,
    )


def two_joint_goal(*points: Any) -> Any:
    names = ["panda_joint1", "panda_joint2"]
    trajectory = TYPES.new("trajectory_msgs/msg/JointTrajectory", joint_names=names, points=list(points))
    return TYPES.new(f"{messages.FOLLOW_JOINT_TRAJECTORY}_Goal", trajectory=trajectory)


@pytest.mark.parametrize(
    ("points", "reason"),
    [
        # joint_trajectory_controller's validate_trajectory_msg refuses each of these.
        ((point([0.0, 0.0], 1.0), point([0.1, 0.1], 1.0)), r"points\[1\]\.time_from_start is 1 s, not after .*1 s"),
        ((point([0.0, 0.0], 1.0), point([0.1, 0.1], 0.5)), r"points\[1\]\.time_from_start is 0\.5 s"),
        ((point([0.0, 0.0], 1.0, velocities=[0.0]),), r"points\[0\]\.velocities has 1 entries for 2 joints"),
        ((point([0.0, 0.0], 1.0, accelerations=[0.0] * 3),), r"points\[0\]\.accelerations has 3 entries"),
        ((point([0.0, 0.0], 1.0, effort=[1.0, 1.0]),), r"points\[0\]\.effort is given"),
    ],
)
def test_a_trajectory_the_joint_trajectory_controller_refuses_is_refused(points: Any, reason: str) -> None:
    with pytest.raises(BadMessage, match=reason):
        messages.trajectory_goal(two_joint_goal(*points))


def test_a_trajectory_with_velocities_for_every_joint_is_taken() -> None:
    goal = messages.trajectory_goal(
        two_joint_goal(
            point([0.0, 0.0], 0.0), point([0.1, 0.1], 0.5, velocities=[0.2, 0.2]), point([0.2, 0.2], 1.0, velocities=[])
        )
    )
    assert [p.time_from_start for p in goal.points] == [0.0, 0.5, 1.0]
