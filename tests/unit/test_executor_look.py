"""What the executor's robot port (NodeRobot) counts as seen after a motion: a report taken after the
motion ended, by the robot's clock, not one that merely arrived after it.

A camera frame arrives a good while after it was taken: on a loaded machine with the sim ten times
faster than real time, 0.1 to 0.5 s of wall time, seconds of sim time. One taken while the base
still drove into its approach pose has what the hand holds up to 0.4 m from where the hand now is;
combined with the arm's position now, place put the cup down that far from its spot (off the front
of the shelf in CI). The node's topics and goals are handed across in memory instead of Zenoh."""

from __future__ import annotations

import threading
from typing import Any

from schemas import keys
from schemas.actions import GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.common import Pose2D, Vec3
from schemas.robot import ARM_JOINTS, FINGER_JOINTS, JointState, NavigateToPoseGoal, NavigateToPoseResult
from schemas.world import PerceivedObject, PerceivedObjects
from services.executor.config import ExecutorConfig
from services.executor.node import NodeRobot

# Perception's wait in these tests when no report qualifies: the bound of a wait that must come up
# empty, not a pause (one that qualifies answers at once).
EMPTY_WAIT = 0.3
GOAL = Pose2D(x=6.0, y=7.9, yaw=1.5708)


class InMemoryNode:
    """The node as NodeRobot uses it: topics delivered by `deliver`, every navigation goal accepted
    and succeeded at once."""

    def __init__(self) -> None:
        self.subscribers: dict[str, Any] = {}

    def subscribe(self, topic: Any, callback: Any) -> None:
        self.subscribers[topic.path] = callback

    def publisher(self, _topic: Any) -> Any:
        return None

    def call(self, service: Any, request: Any, *, timeout: float = 5.0) -> Any:
        if service is keys.CMD_NAVIGATE.send_goal:
            assert isinstance(request, SendGoal)
            return GoalResponse(goal_id=request.goal_id, accepted=True)
        if service is keys.CMD_NAVIGATE.get_result:
            result = NavigateToPoseResult(pose=GOAL)
            return ResultResponse(goal_id=request.goal_id, state=GoalState.SUCCEEDED, result=result)
        raise AssertionError(f"unexpected call {service.path}")

    def deliver(self, topic: Any, message: Any) -> None:
        self.subscribers[topic.path](message)


def joints(stamp: float) -> JointState:
    names = [*ARM_JOINTS, *FINGER_JOINTS]
    return JointState(stamp=stamp, name=names, position=[0.0] * len(names), velocity=[0.0] * len(names))


def frame(stamp: float, y: float) -> PerceivedObjects:
    """The camera's report taken at `stamp` (the robot's clock): the cup in the hand at map y `y`."""
    cup = PerceivedObject(
        id="blue_cup",
        name="blue cup",
        cls="cup",
        color="blue",
        position=Vec3(x=6.0, y=y, z=1.03),
        on="gripper",
        stamp=stamp,
    )
    return PerceivedObjects(stamp=stamp, objects=[cup])


def cup_y(seen: list[PerceivedObject] | None) -> float | None:
    return None if seen is None else seen[0].position.y


def drive(robot: NodeRobot) -> None:
    result = robot.navigate(NavigateToPoseGoal(pose=GOAL), threading.Event())
    assert result.state is GoalState.SUCCEEDED


def test_a_frame_taken_before_the_motion_ended_is_not_seen_after_it_however_late_it_arrives() -> None:
    node = InMemoryNode()
    robot = NodeRobot(node, ExecutorConfig())  # type: ignore[arg-type]
    node.deliver(keys.JOINT_STATES, joints(100.0))
    node.deliver(keys.OBJECTS, frame(100.0, y=7.4))
    assert cup_y(robot.look(EMPTY_WAIT)) == 7.4  # before any motion: the latest report

    drive(robot)
    # The robot's first state after the drive ended, then a frame taken 0.3 s before that, with the
    # base 0.4 m short of its goal: it arrives after the end, yet shows the past.
    node.deliver(keys.JOINT_STATES, joints(101.0))
    node.deliver(keys.OBJECTS, frame(100.7, y=7.75))
    assert robot.look(EMPTY_WAIT) is None
    assert robot.look(EMPTY_WAIT, new=True) is None

    # Taken once the robot stood still (its clock at or past its first state after the end): seen.
    node.deliver(keys.OBJECTS, frame(101.0, y=8.15))
    assert cup_y(robot.look(EMPTY_WAIT)) == 8.15
    # Asked again with no motion between: the same frame, at once.
    node.deliver(keys.JOINT_STATES, joints(101.5))
    assert cup_y(robot.look(EMPTY_WAIT)) == 8.15


def test_the_motions_end_is_the_robots_first_state_after_it_not_its_latest() -> None:
    node = InMemoryNode()
    robot = NodeRobot(node, ExecutorConfig())  # type: ignore[arg-type]
    drive(robot)
    node.deliver(keys.JOINT_STATES, joints(200.0))
    node.deliver(keys.JOINT_STATES, joints(200.5))
    # Taken after the end (200.0), before the latest joint state: the robot stood still meanwhile.
    node.deliver(keys.OBJECTS, frame(200.2, y=8.15))
    assert cup_y(robot.look(EMPTY_WAIT)) == 8.15
    # A frame of the next motion's start must wait for that motion's own end.
    drive(robot)
    node.deliver(keys.OBJECTS, frame(200.6, y=8.15))
    assert robot.look(EMPTY_WAIT) is None  # no joint state since that end: its time is not known yet
    node.deliver(keys.JOINT_STATES, joints(201.0))
    node.deliver(keys.OBJECTS, frame(201.0, y=8.2))
    assert cup_y(robot.look(EMPTY_WAIT)) == 8.2
