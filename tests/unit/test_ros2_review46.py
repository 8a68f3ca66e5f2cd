"""The ros2 backend against what a real rcl_action server answers (review 46)."""

from __future__ import annotations

import threading
from dataclasses import replace
from typing import Any

import pytest

from schemas.actions import GoalState
from services.ros2.backend import RobotCallFailed
from services.ros2.goals import TrajectoryRun
from services.ros2.node import _Goal
from services.ros2.rmw import RosCallError
from services.ros2.wire import CancelReturn, GoalStatus
from tests.unit.test_ros2_backend import MESSAGES, UNWATCHED, FakeHandle, Rig, swing, wait_until
from tests.unit.test_ros2_backend import rig as rig  # the fixture, shared
from tests.unit.test_ros2_hostile_robot import Holds


class RclGoal:
    """A goal as rcl_action's server holds it (rmw's RosClientGoal's face): a cancel it takes puts
    the goal in CANCELING, where it is no longer cancelable, so rcl_action_process_cancel_request
    answers any later cancel ERROR_GOAL_TERMINATED while the goal still runs; get_result answers
    only once the goal ends."""

    def __init__(self) -> None:
        self.goal_id = bytes(range(16))
        self.status = GoalStatus.EXECUTING
        self.cancels = 0
        self._ended = threading.Event()

    def request_cancel(self, timeout: float) -> CancelReturn:
        self.cancels += 1
        if self.status in (GoalStatus.ACCEPTED, GoalStatus.EXECUTING):
            self.status = GoalStatus.CANCELING
            return CancelReturn.ERROR_NONE
        return CancelReturn.ERROR_GOAL_TERMINATED  # CANCELING, or over: rcl_action says the same

    def result(self, timeout: float) -> tuple[int, Any]:
        if not self._ended.wait(min(timeout, 0.05)):
            raise RosCallError("service get_result: no answer within 10 s")
        return int(GoalStatus.CANCELED), None

    def finish(self) -> None:
        self.status = GoalStatus.CANCELED
        self._ended.set()


class RclAction:
    """node.py's _Action for an rcl_action server: its goals through node.py's own adapter, _Goal."""

    name = "/arm_controller/follow_joint_trajectory"

    def __init__(self) -> None:
        self.goals: list[RclGoal] = []

    def send_goal(self, goal: Any, *, timeout: float) -> _Goal:
        self.goals.append(RclGoal())
        return _Goal(self.goals[-1], self)  # type: ignore[arg-type]  # rmw's goal and client, faked

    def cancel(self, goal_id: bytes, timeout: float) -> bool:
        raise AssertionError("only unanswered goals are canceled by id")

    def forget(self, goal: Any) -> None:
        pass


def test_an_emergency_stop_held_for_a_goal_still_canceling_is_not_released_by_rcl_answering_terminated(
    rig: Rig,
) -> None:
    # Before, the second cancel of a goal the robot was still canceling settled it: rcl_action answers
    # ERROR_GOAL_TERMINATED for a goal in CANCELING (no longer cancelable), which the backend took
    # for the robot's word that the goal had ended, and released the robot's emergency stop.
    holds = Holds()
    action, handle = RclAction(), FakeHandle(swing(10.0))
    rig.clock.once(lambda: bool(action.goals), lambda: setattr(handle, "stop", True))
    ending = TrajectoryRun(
        replace(rig.context, block_robot=holds), action, handle, MESSAGES, joint_states_timeout=UNWATCHED
    ).run()
    assert ending.state is GoalState.CANCELED and "emergency stop is held" in ending.message, ending.message
    [goal] = action.goals
    assert wait_until(lambda: goal.cancels >= 3 or holds.released.is_set())
    assert not holds.released.is_set(), "released while the robot still cancels the goal"
    assert goal.cancels >= 3, "the cancel is asked again"
    goal.finish()
    assert holds.released.wait(5.0), "released once its result says the goal ended"


def test_a_goal_that_had_ended_before_its_cancel_is_settled_by_rcls_answer() -> None:
    # The answer ERROR_GOAL_TERMINATED to a first cancel is the robot's word that the goal is over.
    goal = RclGoal()
    goal.status = GoalStatus.SUCCEEDED
    assert _Goal(goal, RclAction()).cancel(1.0)  # type: ignore[arg-type]


def test_a_cancel_whose_answer_was_lost_leaves_a_later_terminated_answer_unbelieved() -> None:
    # Before, a cancel the robot took but whose answer was lost, then the next cancel's
    # ERROR_GOAL_TERMINATED (the goal CANCELING), was taken for the goal's end.
    class Lossy(RclGoal):
        def request_cancel(self, timeout: float) -> CancelReturn:
            answer = super().request_cancel(timeout)
            if self.cancels == 1:
                raise RosCallError("service cancel_goal: no answer within 1.5 s")
            return answer

    goal = _Goal(Lossy(), RclAction())  # type: ignore[arg-type]
    with pytest.raises(RobotCallFailed, match="no answer"):
        goal.cancel(1.0)
    assert not goal.cancel(1.0), "the robot may be canceling it: only its result says it ended"
