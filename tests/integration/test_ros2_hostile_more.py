"""More of a hostile robot's network against the real ros2 backend: a goal status anyone can publish,
reports too big to decode. Neither makes the backend believe something false about the robot's motion."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from schemas import keys
from schemas.actions import GoalState
from schemas.robot import ARM_JOINTS, FINGER_JOINTS
from schemas.world import Empty
from services.actionlib import ActionClient
from services.ros2.config import Ros2Config
from services.ros2.rmw import RosCallError, RosNode, RosServerGoal
from services.ros2.types import RosTypes
from services.ros2.wire import GOAL_STATUS_ARRAY_TYPE, STATUS_QOS, GoalStatus, Naming, Style
from services.worldmodel import load_world
from tests.integration.test_ros2_hostile import (
    DEADLINE,
    JOINT_STATE,
    Heard,
    HostileRobot,
    Rig,
    ahead,
    backend_toml,
    robot_session,
)
from tests.robot_contract.conftest import CONTRACT_SIM, ros2_backend, running
from tests.sessions import free_port

BOOL = "std_msgs/msg/Bool"
HOME = load_world("household").robot.home_joints


class StubbornRobot(HostileRobot):
    """The hostile robot, which also drives on when a goal is canceled while `stubborn` (until
    `let_go`), and hears what the backend tells its emergency stop."""

    def __init__(self, endpoint: str) -> None:
        self.stubborn = False
        self.let_go = threading.Event()
        self.estop = Heard()  # the values of emergency_stop, as they come
        super().__init__(endpoint)
        try:
            self.ros.subscribe("emergency_stop", BOOL, lambda message: self.estop(bool(message.data)))
        except BaseException:
            self.close()
            raise

    def _executor(self, action: str) -> Callable[[RosServerGoal], None]:
        def execute(goal: RosServerGoal) -> None:
            self.goals(goal)
            if not goal.cancel_requested.wait(60.0):
                return
            self.canceled(goal)
            if self.stubborn:
                self.let_go.wait(60.0)  # the canceled goal runs on
            goal.canceled(self.types.new(f"{action}_Result"))

        return execute

    def close(self) -> None:
        self.let_go.set()
        super().close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    """The ros2 backend as a real process driving the stubborn robot; the test plays safety, clear."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = StubbornRobot(endpoint)
    try:
        backend = dataclasses.replace(ros2_backend(CONTRACT_SIM), config=backend_toml(endpoint), robot_service=None)
        with running(backend, tmp_path_factory.mktemp("hostile-more"), beating=True) as started:
            yield Rig(robot, started, ActionClient(started.node, keys.ROBOT_NAVIGATE))
    finally:
        robot.close()


def stubborn(rig: Rig) -> StubbornRobot:
    assert isinstance(rig.robot, StubbornRobot)
    return rig.robot


def forged_status(robot: HostileRobot, goal: RosServerGoal, status: GoalStatus) -> Any:
    new = robot.types.new
    info = new(
        "action_msgs/msg/GoalInfo",
        goal_id=new("unique_identifier_msgs/msg/UUID", uuid=np.frombuffer(goal.goal_id, dtype=np.uint8).copy()),
        stamp=robot.stamp(),
    )
    return new(GOAL_STATUS_ARRAY_TYPE, status_list=[new("action_msgs/msg/GoalStatus", goal_info=info, status=status)])


def test_an_emergency_stop_held_for_a_goal_the_robot_runs_on_is_not_released_by_a_forged_status(rig: Rig) -> None:
    """The backend holds the robot's emergency stop while a goal it canceled runs on. Anyone on the
    robot's network then says on the action's status topic that the goal ended: the stop is held on
    (before, it was released, the goal still running), until the robot's own action server says so."""
    robot = stubborn(rig)
    robot.stubborn = True
    robot.let_go.clear()
    sent = time.monotonic()
    handle = rig.navigate.send(ahead(), timeout=DEADLINE)
    try:
        driving = robot.goals.since(sent, lambda goal: goal.active)
        assert driving is not None, "the robot never got the goal"
        handle.cancel()
        ended = handle.result(DEADLINE)
        assert ended.state is GoalState.CANCELED and "emergency stop is held" in ended.message, ended
        held = time.monotonic()
        assert robot.estop.since(held, lambda stopped: stopped) is not None, "the robot was not told to stop"

        # Another node on the robot's network (on its session: the backend connects to that peer alone).
        with RosNode(robot.session, robot.types, robot.naming, "anyone") as anyone:
            status = anyone.publisher("navigate_to_pose/_action/status", GOAL_STATUS_ARRAY_TYPE, qos=STATUS_QOS)
            forged = time.monotonic()
            for ending in [GoalStatus.CANCELED, GoalStatus.SUCCEEDED, GoalStatus.ABORTED] * 10:
                status.put(forged_status(robot, driving, ending))
                # One more emergency_stop (20 Hz) between two: the backend's watch has run meanwhile.
                beat = time.monotonic()
                assert robot.estop.since(beat, lambda _: True) is not None, "emergency_stop went quiet"
        told = [stopped for at, stopped in robot.estop.items if at >= forged]
        assert len(told) >= 30 and all(told), "the forged status released the robot's emergency stop"
        assert driving.active, "the robot ran the goal on"
    finally:
        robot.let_go.set()
    released = time.monotonic()
    assert robot.estop.since(released, lambda stopped: not stopped) is not None, (
        "not released once the robot ended the goal"
    )
    robot.stubborn = False


def joint_states(robot: HostileRobot, names: list[str], positions: list[float]) -> Any:
    new = robot.types.new
    return new(
        JOINT_STATE,
        header=new("std_msgs/msg/Header", stamp=robot.stamp()),
        name=names,
        position=np.array(positions, dtype=np.float64),
        velocity=np.zeros(len(names)),
    )


def test_joint_states_too_big_to_decode_are_dropped_unread_said_and_the_backend_reports_on(rig: Rig) -> None:
    """Tether's joints, the arm far from where it is, among a hundred thousand others: before, the
    backend decoded every name and passed the arm's false position on to safety."""
    robot, backend = stubborn(rig), rig.backend
    names = [*ARM_JOINTS, *FINGER_JOINTS, *(f"wheel_{k}" for k in range(100_000))]
    positions = [1.0, *HOME[1:], 0.04, 0.04, *([0.0] * 100_000)]
    flood = joint_states(robot, names, positions)
    assert len(robot.types.encode(JOINT_STATE, flood)) > 1 << 20  # more than a robot's joint states ever weigh
    since, after = time.time(), len(backend.joint_states)
    with RosNode(robot.session, robot.types, robot.naming, "anyone") as anyone:
        publisher = anyone.publisher("joint_states", JOINT_STATE)
        text = ""
        deadline = time.monotonic() + DEADLINE
        while not text:
            publisher.put(flood)  # again until it is heard: a new publisher's first samples may find no route yet
            assert time.monotonic() < deadline, "the backend never said it dropped the joint states"
            problems = backend.node.call(keys.ROBOT_DIAGNOSTICS, Empty(), timeout=5.0).problems
            text = next((p.text for p in problems if p.last_seen >= since and "/joint_states of" in p.text), "")
    assert "bytes, over the" in text and "sensor_msgs/msg/JointState" in text and "dropped unread" in text, text
    # The robot's own joint states go on being passed on, and the flood's never was.
    assert backend.joint_states.wait_for(lambda _: True, DEADLINE, after=len(backend.joint_states))
    passed = backend.joint_states.messages[after:]
    assert passed and all(state.position[0] == pytest.approx(HOME[0]) for state in passed), passed[-1]


FOLLOW_JOINT_TRAJECTORY = "control_msgs/action/FollowJointTrajectory"


def test_a_reply_too_big_to_decode_is_dropped_unread_naming_its_size() -> None:
    """A trajectory's result with an error_string of 2 MB, as a hostile action server answers
    get_result: before, decoded whole; now refused like any reply that does not decode."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    types = RosTypes()
    naming = Naming(Style.RMW_ZENOH, Ros2Config().ros_domain())
    huge = types.new(f"{FOLLOW_JOINT_TRAJECTORY}_Result", error_code=-4, error_string="x" * (2 << 20))

    def execute(goal: RosServerGoal) -> None:
        goal.abort(huge)

    with (
        robot_session(endpoint) as robot_side,
        robot_session(endpoint, listen=False) as tether_side,
        RosNode(robot_side, types, naming, "hostile_arm") as robot,
        RosNode(tether_side, types, naming, "tether") as tether,
    ):
        robot.action_server("follow_joint_trajectory", FOLLOW_JOINT_TRAJECTORY, accept=lambda _: True, execute=execute)
        client = tether.action_client("follow_joint_trajectory", FOLLOW_JOINT_TRAJECTORY)
        assert client.wait_for_server(DEADLINE)
        goal = client.send_goal(types.new(f"{FOLLOW_JOINT_TRAJECTORY}_Goal"), timeout=DEADLINE)
        with pytest.raises(RosCallError, match=r"a response of \d+ bytes, over the \d+ it may take"):
            goal.result(DEADLINE)
