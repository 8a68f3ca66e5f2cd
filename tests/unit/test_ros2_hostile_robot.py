"""A robot, or anyone on its network, telling the ros2 backend's logic something false about motion:
goal statuses that say a goal ended while it runs, stamps from two clocks on one topic."""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import pytest

from schemas.actions import GoalState
from schemas.robot import ARM_JOINTS, FINGER_JOINTS
from services.ros2.backend import JointMerger, RobotCallFailed, Stamps
from services.ros2.goals import TrajectoryRun
from tests.unit.test_ros2_backend import (
    ABORTED,
    CANCELED,
    HOME,
    MESSAGES,
    NOW,
    SUCCEEDED,
    UNWATCHED,
    FakeAction,
    FakeGoal,
    FakeHandle,
    Rig,
    clear,
    header,
    joint_message,
    swing,
    trajectory_result,
    wait_until,
)
from tests.unit.test_ros2_backend import rig as rig  # the fixture, shared


class Holds:
    """The robot's emergency stop as goal runs hold it (RunContext.block_robot)."""

    def __init__(self) -> None:
        self.reasons: list[str] = []
        self.released = threading.Event()

    def __call__(self, reason: str) -> Callable[[], None]:
        self.reasons.append(reason)
        return self.released.set


class SlowResult(FakeGoal):
    """A goal whose get_result is a long query that times out while the goal runs, as on the wire."""

    def result(self, timeout: float) -> tuple[int, Any]:
        if not self._ended.wait(min(timeout, 0.05)):
            raise RobotCallFailed("get_result: no answer within 10 s")
        return self._outcome


class SaysCanceled(SlowResult):
    """A goal the robot runs on when canceled, while its status topic says CANCELED (forged, or a
    robot whose status and action disagree)."""

    def cancel(self, timeout: float) -> bool:
        self.cancels += 1
        self.status = CANCELED
        return False


def test_an_emergency_stop_held_for_a_goal_is_not_released_by_a_status_anyone_can_publish(rig: Rig) -> None:
    # Before, a terminal status on the action's status topic released the robot's emergency stop,
    # held because the robot would not end its goal, while the goal ran on.
    holds = Holds()
    action, handle = FakeAction("arm", ends_on_cancel=False), FakeHandle(swing(10.0))
    rig.clock.once(lambda: bool(action.goals), lambda: setattr(handle, "stop", True))
    ending = TrajectoryRun(
        replace(rig.context, block_robot=holds), action, handle, MESSAGES, joint_states_timeout=UNWATCHED
    ).run()
    assert "emergency stop is held" in ending.message
    [goal] = action.goals
    goal.status = CANCELED  # on the status topic; the robot's action server runs the goal on
    asked = goal.cancels
    assert wait_until(lambda: goal.cancels >= asked + 2), "the cancel is asked again"
    assert not holds.released.is_set(), "held while the goal runs"
    goal.finish(CANCELED)  # its result says it ended
    assert holds.released.wait(5.0)


def test_a_goal_whose_status_says_it_ended_is_held_stopped_until_the_robot_itself_says_so(rig: Rig) -> None:
    # Before, the goal was taken for over once canceled (its status said so): the robot ran on unheld.
    holds = Holds()
    action = FakeAction("arm", make=SlowResult, ends_on_cancel=False)
    rig.clock.once(lambda: bool(action.goals), lambda: setattr(action.goals[0], "status", ABORTED))
    ending = TrajectoryRun(
        replace(rig.context, block_robot=holds),
        action,
        FakeHandle(swing(10.0)),
        MESSAGES,
        joint_states_timeout=UNWATCHED,
    ).run()
    assert ending.state is GoalState.ABORTED
    assert "its result could not be read" in ending.message and "emergency stop is held" in ending.message
    assert len(holds.reasons) == 1 and not holds.released.is_set()
    [goal] = action.goals
    goal.finish(CANCELED)
    assert holds.released.wait(5.0), "released once the robot's result says the goal ended"


def test_a_pause_the_robot_did_not_carry_out_is_not_taken_for_one_on_its_status(rig: Rig) -> None:
    # Before, the pause was taken as done on the status alone and the rest sent on resume, while
    # the first goal ran on: two trajectories on the arm at once.
    holds = Holds()
    action = FakeAction("arm", make=SaysCanceled)
    rig.clock.at(100.5, lambda: rig.set(clear(0.0)))
    rig.clock.at(103.0, lambda: rig.set(clear(1.0)))
    rig.clock.once(lambda: len(action.goals) == 2, lambda: action.goals[1].finish(SUCCEEDED, trajectory_result()))
    ending = TrajectoryRun(
        replace(rig.context, block_robot=holds),
        action,
        FakeHandle(swing(2.0)),
        MESSAGES,
        joint_states_timeout=UNWATCHED,
    ).run()
    assert ending.state is GoalState.ABORTED and "emergency stop is held" in ending.message, ending.message
    assert len(action.goals) == 1, "nothing more sent while the first goal may run"
    assert len(holds.reasons) == 1


def test_a_cancel_the_robot_answers_with_the_goal_already_ended_settles_it(rig: Rig) -> None:
    # The server's own answer (CancelGoal's ERROR_GOAL_TERMINATED) is as good as its result.
    holds = Holds()

    class Ended(SlowResult):
        def cancel(self, timeout: float) -> bool:
            self.cancels += 1
            return True

    action, handle = FakeAction("arm", make=Ended), FakeHandle(swing(10.0))
    rig.clock.once(lambda: bool(action.goals), lambda: setattr(handle, "stop", True))
    ending = TrajectoryRun(
        replace(rig.context, block_robot=holds), action, handle, MESSAGES, joint_states_timeout=UNWATCHED
    ).run()
    assert ending.state is GoalState.CANCELED and ending.message == "canceled"
    assert holds.reasons == [] and action.goals[0].cancels == 1


# Stamps


@pytest.mark.parametrize("offsets", [(-0.99, -1.01), (0.99, 1.01)], ids=["behind", "ahead"])
def test_a_robot_clock_about_the_tolerance_off_never_sends_stamps_back_nor_joint_speeds_wrong(
    offsets: tuple[float, float],
) -> None:
    # Before, stamps of the robot's clock and of arrival came by turns as jitter took the robot's
    # clock across CLOCK_TOLERANCE: stamps jumped back and forth by a second, and the arm's speed,
    # estimated from them, was 0 or a twentieth of the real one.
    stamps, merger = Stamps(), JointMerger()
    speed, period = 0.5, 0.05  # panda_joint1 turning at 0.5 rad/s, reported at 20 Hz without velocities
    states = []
    for k in range(20):
        now = NOW + k * period
        message = joint_message([*ARM_JOINTS, *FINGER_JOINTS], [speed * k * period, *HOME[1:], 0.04, 0.04])
        message.header = header(now + offsets[k % 2], "")
        states.append(merger.update(message, stamps.of(message.header, now, "/joint_states")))
    # The first is the robot's clock, the second ours (the one step from one clock to the other), and
    # from then on ours alone.
    times = [state.stamp for state in states[1:] if state is not None]
    assert len(times) == 19 and all(later > earlier for earlier, later in itertools.pairwise(times))
    speeds = [state.velocity[0] for state in states[2:] if state is not None]
    assert speeds == pytest.approx([speed] * 18, rel=1e-4)


def test_each_topic_keeps_to_its_own_clock() -> None:
    stamps = Stamps()
    assert stamps.of(header(NOW - 0.2, "odom"), NOW, "/odom") == pytest.approx(NOW - 0.2)
    assert stamps.of(header(0.0, ""), NOW, "/joint_states") == NOW  # not stamped: on arrival
    assert stamps.of(header(NOW + 0.2, ""), NOW + 0.1, "/joint_states") == NOW + 0.1, "and so on"
    assert stamps.of(header(NOW - 0.1, "odom"), NOW + 0.1, "/odom") == pytest.approx(NOW - 0.1)
