"""Goal runs ending as the robot's real servers end them: a gripper that stalls short of its goal
(gripper_action_controller aborts it, saying so only in its result), a Nav2 goal aborted with an
empty result (as Nav2 ends a goal another preempts)."""

from __future__ import annotations

import numpy as np

from schemas.actions import GoalState
from schemas.common import Pose2D
from schemas.robot import GripperCommandGoal, GripperCommandResult, NavigateToPoseGoal, NavigateToPoseResult
from services.ros2 import backend
from services.ros2.backend import Messages
from services.ros2.goals import GripperRun
from services.ros2.wire import GoalStatus
from tests.unit import test_ros2_backend as base
from tests.unit.test_ros2_backend import FRAMES, MESSAGES, TYPES, FakeAction, FakeHandle, Rig, assert_plan_reads

rig = base.rig  # a scripted robot and its clock


def gripper_aborted(rig: Rig, result: object, messages: Messages = MESSAGES) -> str:
    action = FakeAction("gripper")
    rig.clock.once(lambda: bool(action.goals), lambda: action.goals[0].finish(GoalStatus.ABORTED, result))
    ending = GripperRun(rig.context, action, FakeHandle(GripperCommandGoal(position=0.0)), messages, {}, 0.2).run()
    assert ending.state is GoalState.ABORTED
    assert_plan_reads(ending, GripperCommandResult)
    return ending.message


def test_a_gripper_goal_aborted_as_stalled_says_where_the_fingers_stalled(rig: Rig) -> None:
    stalled = TYPES.new(f"{backend.GRIPPER_COMMAND}_Result", position=0.035, stalled=True, reached_goal=False)
    assert gripper_aborted(rig, stalled) == (
        "the robot aborted the gripper_command goal: the fingers stalled at 35 mm, short of the goal"
    )
    finger = TYPES.new(backend.JOINT_STATE, name=["panda_finger_joint1"], position=np.array([0.02]))
    parallel = TYPES.new(f"{backend.PARALLEL_GRIPPER_COMMAND}_Result", state=finger, stalled=True, reached_goal=False)
    messages = Messages(TYPES, FRAMES, stamped_cmd_vel=False, parallel_gripper_joint="panda_finger_joint1")
    assert "stalled at 40 mm" in gripper_aborted(rig, parallel, messages)
    # An empty result (the stand-in's for a goal it could not carry out) says nothing more than that.
    empty = gripper_aborted(rig, TYPES.new(f"{backend.GRIPPER_COMMAND}_Result"))
    assert empty == "the robot aborted the gripper_command goal: no reason given"


def test_a_navigation_nav2_aborts_with_an_empty_result_says_what_nav2_means_by_it(rig: Rig) -> None:
    action = FakeAction("navigate_to_pose")
    empty = TYPES.new(f"{backend.NAVIGATE_TO_POSE}_Result")
    rig.clock.once(lambda: bool(action.goals), lambda: action.goals[0].finish(GoalStatus.ABORTED, empty))
    handle = FakeHandle(NavigateToPoseGoal(pose=Pose2D(x=8.0, y=1.2), start=Pose2D(x=6.0, y=1.2)))
    ending = base.navigation(rig, handle, action).run()
    assert ending.state is GoalState.ABORTED
    assert ending.message.startswith("the robot aborted the navigate_to_pose goal: no reason given (Nav2 gives none")
    assert_plan_reads(ending, NavigateToPoseResult)
    # One with Nav2's code and words says those.
    action = FakeAction("navigate_to_pose")
    timeout = TYPES.new(f"{backend.NAVIGATE_TO_POSE}_Result", error_code=9003, error_msg="took too long")
    rig.clock.once(lambda: bool(action.goals), lambda: action.goals[0].finish(GoalStatus.ABORTED, timeout))
    ending = base.navigation(rig, FakeHandle(handle.goal), action).run()
    assert ending.message == "the robot aborted the navigate_to_pose goal: TIMEOUT: took too long"
