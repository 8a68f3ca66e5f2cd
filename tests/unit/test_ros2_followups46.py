"""Follow-ups to review 46: GripperCommand's position on a Panda, a trajectory whose joint states stop,
a speed scale too small for a ROS Duration."""

from __future__ import annotations

import math
import re
from typing import Any

import msgspec
import pytest

from schemas.actions import GoalState
from schemas.robot import GripperCommandGoal
from services.ros2 import backend
from services.ros2.backend import Messages
from services.ros2.config import Ros2Config
from services.ros2.goals import GripperRun, TrajectoryRun
from tests.unit.test_ros2_backend import (
    ABORTED,
    FRAMES,
    HOME,
    MESSAGES,
    SUCCEEDED,
    TYPES,
    UNWATCHED,
    FakeAction,
    FakeGoal,
    FakeHandle,
    Rig,
    clear,
    swing,
    trajectory_result,
)
from tests.unit.test_ros2_backend import rig as rig  # the fixture, shared


def panda_messages() -> Messages:
    """docs/ros2.md's Panda: gripper_action_controller on panda_finger_joint1, one finger's travel (0 to 0.04 m)."""
    panda = msgspec.convert({"gripper_position_per_gap": 0.5}, Ros2Config)
    return Messages(TYPES, FRAMES, stamped_cmd_vel=False, gripper_position_per_gap=panda.gripper_position_per_gap)


# 1. What GripperCommand.position is on the robot


def test_a_gripper_command_on_a_pandas_finger_joint_asks_for_half_the_gap() -> None:
    # Before, a Panda's finger joint was asked for the whole gap: open (0.08 m) twice its 0.04 m range.
    assert MESSAGES.gripper(0.08, 20.0).command.position == pytest.approx(0.08), "by default the gap"
    panda = panda_messages()
    command = panda.gripper(0.08, 20.0).command
    assert command.position == pytest.approx(0.04) and command.max_effort == pytest.approx(20.0)
    assert panda.gripper(0.03, 20.0).command.position == pytest.approx(0.015)


def gripper_result(position: float, *, stalled: bool = False, reached: bool = True) -> Any:
    return TYPES.new(f"{backend.GRIPPER_COMMAND}_Result", position=position, stalled=stalled, reached_goal=reached)


def test_a_pandas_gripper_result_is_read_back_as_the_gap(rig: Rig) -> None:
    action = FakeAction("gripper")
    run = GripperRun(rig.context, action, FakeHandle(GripperCommandGoal(position=0.04)), panda_messages(), {}, 0.2)
    rig.clock.once(lambda: bool(action.goals), lambda: action.goals[0].finish(SUCCEEDED, gripper_result(0.02)))
    ending = run.run()
    assert ending.state is GoalState.SUCCEEDED, ending.message
    assert ending.result.position == pytest.approx(0.04) and ending.message == "gripper at 40 mm"


def test_a_pandas_fingers_stalled_are_named_at_the_gap(rig: Rig) -> None:
    action = FakeAction("gripper")
    run = GripperRun(rig.context, action, FakeHandle(GripperCommandGoal(position=0.0)), panda_messages(), {}, 0.2)
    stalled = gripper_result(0.0175, stalled=True, reached=False)
    rig.clock.once(lambda: bool(action.goals), lambda: action.goals[0].finish(ABORTED, stalled))
    ending = run.run()
    assert ending.state is GoalState.ABORTED
    assert (
        ending.message == "the robot aborted the gripper_command goal: the fingers stalled at 35 mm, short of the goal"
    )


@pytest.mark.parametrize(
    ("value", "why"),
    [(0.0, "> 0.0"), (-0.5, "> 0.0"), (math.nan, "> 0.0"), (math.inf, "<= 100.0"), (1000.0, "<= 100.0")],
)
def test_a_gripper_position_per_gap_that_is_no_factor_is_refused_naming_it(value: float, why: str) -> None:
    with pytest.raises(msgspec.ValidationError, match=rf"Expected `float` {why} - at `\$.gripper_position_per_gap`"):
        msgspec.convert({"gripper_position_per_gap": value}, Ros2Config)


def test_a_gripper_position_per_gap_for_a_parallel_gripper_command_is_refused_saying_why() -> None:
    # A ParallelGripperCommand names its finger joint and gets half the gap: a factor would be ignored.
    with pytest.raises(msgspec.ValidationError, match=r"gripper_position_per_gap = 0.5 is for gripper_action"):
        msgspec.convert({"gripper_action": "parallel_gripper_command", "gripper_position_per_gap": 0.5}, Ros2Config)


# 2. A trajectory whose joint states stop


def test_a_trajectory_whose_joint_states_stop_is_canceled_and_aborted_naming_their_age(rig: Rig) -> None:
    # Before, it ran to the trajectory's end plus 6 s, its feedback repeating the last positions.
    assert Ros2Config().joint_states_timeout == 0.5
    action, handle = FakeAction("arm"), FakeHandle(swing(10.0))
    rig.clock.ticks.append(lambda: rig.joints(HOME) if rig.clock.now < 101.0 else None)  # the robot vanishes
    ending = TrajectoryRun(rig.context, action, handle, MESSAGES, joint_states_timeout=0.5).run()
    assert ending.state is GoalState.ABORTED
    assert ending.message == "no joint states from the robot for 0.5 s", ending.message
    [goal] = action.goals
    assert goal.cancels == 1, "the arm's goal canceled"
    assert rig.clock.now < 101.6, "aborted once joint states were stale, not at the trajectory's end"


def test_a_trajectory_whose_arm_lags_names_why_there_are_no_joint_states(rig: Rig) -> None:
    # node.py's problem when the arm's publisher stops while the gripper's goes on.
    action, handle = FakeAction("arm"), FakeHandle(swing(10.0))
    lagging = "joint states on joint_states: joints ['panda_joint1'] not heard for over 0.5 s while others were"
    rig.clock.at(100.5, lambda: rig.robot.problem(lagging))
    ending = TrajectoryRun(rig.context, action, handle, MESSAGES, joint_states_timeout=0.5).run()
    assert ending.state is GoalState.ABORTED and ending.message.endswith(f"; {lagging}"), ending.message
    assert ending.message.startswith("no joint states from the robot for 0.5 s")


def test_a_trajectory_from_stale_joint_states_is_refused_and_nothing_is_sent(rig: Rig) -> None:
    rig.clock.now += 2.0  # the joint states heard are 2 s old: the arm may be anywhere
    action = FakeAction("arm")
    ending = TrajectoryRun(rig.context, action, FakeHandle(swing()), MESSAGES, joint_states_timeout=0.5).run()
    assert ending.state is GoalState.ABORTED and ending.message == "no joint states from the robot for 2.0 s"
    assert action.goals == []


# 3. A speed scale too small for a ROS Duration


class EncodingGoal(FakeGoal):
    """A goal encoded as rmw.py sends it: what the wire cannot carry fails there."""

    def __init__(self, goal: Any, *, ends_on_cancel: bool = True) -> None:
        TYPES.encode(f"{backend.FOLLOW_JOINT_TRAJECTORY}_Goal", goal)
        super().__init__(goal, ends_on_cancel=ends_on_cancel)


def test_a_trajectory_at_a_speed_scale_too_small_for_a_ros_duration_is_refused_naming_the_duration(rig: Rig) -> None:
    # Before, it aborted with "RosTypeError(... 'i' format requires ...)": nothing said what was wrong.
    rig.set(clear(1e-6))  # an hour's trajectory takes 3.6e9 s: a Duration's int32 seconds hold 2.1e9
    action = FakeAction("arm", make=EncodingGoal)
    ending = TrajectoryRun(
        rig.context, action, FakeHandle(swing(3600.0)), MESSAGES, joint_states_timeout=UNWATCHED
    ).run()
    assert ending.state is GoalState.ABORTED and action.goals == []
    assert ending.message == (
        "the follow_joint_trajectory goal cannot be sent at speed scale 1e-06: a duration of 3.6e+09 s, "
        "where a ROS Duration holds 0 to 2147483647 s"
    )


def test_a_trajectory_re_timed_for_a_speed_scale_too_small_holds_and_ends_saying_why(rig: Rig) -> None:
    action, handle = FakeAction("arm", make=EncodingGoal), FakeHandle(swing(3600.0))
    rig.clock.at(101.0, lambda: rig.set(clear(1e-7)))
    ending = TrajectoryRun(rig.context, action, handle, MESSAGES, joint_states_timeout=UNWATCHED).run()
    assert ending.state is GoalState.ABORTED
    assert ending.message.startswith("the follow_joint_trajectory goal cannot be sent at speed scale 1e-07: ")
    assert "where a ROS Duration holds 0 to 2147483647 s" in ending.message
    [first] = action.goals
    assert first.cancels == 1, "the arm holds: its goal canceled for the re-timing, nothing more sent"


@pytest.mark.parametrize("seconds", [2.0**31, math.inf, math.nan, -1.0])
def test_a_duration_a_ros_duration_cannot_hold_is_refused_naming_it(seconds: float) -> None:
    with pytest.raises(backend.UnsendableGoal, match=re.escape(f"a duration of {seconds:.3g} s, where a ROS Duration")):
        MESSAGES.duration(seconds)
    assert backend.to_seconds(MESSAGES.duration(2.0**31 - 1)) == 2.0**31 - 1


def test_a_trajectory_whose_joint_states_keep_coming_runs_to_its_end(rig: Rig) -> None:
    # Fresh joint states and a speed scale a Duration holds: nothing above ends it.
    action, handle = FakeAction("arm", make=EncodingGoal), FakeHandle(swing(2.0))
    rig.clock.ticks.append(lambda: rig.joints(HOME))
    rig.clock.at(101.0, lambda: action.goals[0].finish(SUCCEEDED, trajectory_result()))
    ending = TrajectoryRun(rig.context, action, handle, MESSAGES, joint_states_timeout=0.5).run()
    assert ending.state is GoalState.SUCCEEDED, ending.message
