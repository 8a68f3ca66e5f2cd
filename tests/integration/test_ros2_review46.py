"""Canceling a goal the robot takes a while to cancel, over real Zenoh: the stand-in's action server
answers as rcl_action does, and the backend waits for the goal's result (review 46)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

from services.ros2.node import _Action
from services.ros2.rmw import RosServerGoal
from services.ros2.wire import CancelReturn, GoalStatus
from tests.integration.test_ros2_rmw import DEADLINE, NAV, Collected, Pair, nav_goal
from tests.integration.test_ros2_rmw import pair as pair  # the fixtures, shared
from tests.integration.test_ros2_rmw import types as types


class SlowToCancel:
    """A NavigateToPose server whose goals, once canceled, end only when the test lets them (a base
    braking to rest)."""

    def __init__(self, pair: Pair) -> None:
        self.types = pair.types
        self.started = Collected()
        self.stopped = threading.Event()
        pair.robot.action_server("navigate_to_pose", NAV, accept=lambda _goal: True, execute=self.execute)

    def execute(self, goal: RosServerGoal) -> None:
        self.started(goal.goal_id)
        goal.cancel_requested.wait(DEADLINE)
        self.stopped.wait(DEADLINE)
        goal.canceled(self.types.new(f"{NAV}_Result", error_msg="canceled"))


@pytest.fixture
def slow(pair: Pair) -> Iterator[SlowToCancel]:
    server = SlowToCancel(pair)
    yield server
    server.stopped.set()


def test_a_goal_being_canceled_is_answered_terminated_as_rcl_action_does(pair: Pair, slow: SlowToCancel) -> None:
    # Before, the stand-in answered ERROR_NONE again, where rcl_action (Nav2, ros2_control) answers
    # ERROR_GOAL_TERMINATED: a goal in CANCELING is no longer cancelable. The backend's handling of
    # that answer was never played against it.
    client = pair.tether.action_client("navigate_to_pose", NAV)
    assert client.wait_for_server(DEADLINE)
    goal = client.send_goal(nav_goal(pair.types, 1.0), timeout=DEADLINE)
    assert slow.started.wait(lambda ids: goal.goal_id in ids)
    assert goal.request_cancel(DEADLINE) is CancelReturn.ERROR_NONE
    assert goal.request_cancel(DEADLINE) is CancelReturn.ERROR_GOAL_TERMINATED
    assert goal.wait_status(lambda status: status is GoalStatus.CANCELING, DEADLINE)


def test_the_backend_takes_a_goal_it_canceled_for_over_only_on_its_result(pair: Pair, slow: SlowToCancel) -> None:
    # Before, the second cancel's ERROR_GOAL_TERMINATED was taken for the robot's word that the goal
    # had ended: a pause taken as done, an emergency stop held for the goal released, while it ran on.
    client = pair.tether.action_client("navigate_to_pose", NAV)
    assert client.wait_for_server(DEADLINE)
    goal: Any = _Action(client).send_goal(nav_goal(pair.types, 1.0), timeout=DEADLINE)
    assert slow.started.wait(lambda ids: goal._goal.goal_id in ids)
    assert not goal.cancel(DEADLINE), "the robot is canceling it: not over yet"
    assert not goal.cancel(DEADLINE), "still canceling, whatever rcl_action's answer says"
    slow.stopped.set()
    status, result = goal.result(DEADLINE)
    assert status == GoalStatus.CANCELED and result.error_msg == "canceled"
