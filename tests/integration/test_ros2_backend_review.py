"""The ros2 backend against robots that behave as real ones do: a base controller that holds a
stamped cmd_vel from its stamp, a service peer whose error replies are huge, an action server that
forgets its goals (restarted)."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import zenoh

from schemas import keys
from schemas.actions import GoalState
from schemas.robot import GripperCommandGoal, Twist
from schemas.safety import EstopState, SafetyStatus
from services.robotrules import SafetyNow
from services.ros2.backend import Messages, RobotState
from services.ros2.config import Frames
from services.ros2.goals import Ending, GripperRun, RunContext
from services.ros2.node import _Action
from services.ros2.rmw import RosActionClient, RosCallError, RosNode, RosServerGoal
from services.ros2.types import RosTypes
from services.ros2.wire import Naming, Style
from tests.integration.test_ros2_rmw import ADD, node_pair
from tests.robot_contract.conftest import CONTRACT_SIM, RunningBackend, ros2_backend, running

DEADLINE = 10.0  # every wait ends as soon as its condition holds; generous for a shared machine
FLOOD = 20  # error replies to one call
ERROR_BYTES = 200_000  # each
CLEAR = SafetyNow(None, SafetyStatus(seq=0, stamp=0.0, estop=EstopState(latched=False), speed_scale=1.0))


@pytest.fixture(scope="module")
def types() -> RosTypes:
    return RosTypes("jazzy")


@dataclass
class Handle:
    """The tether goal a goal run carries out (actionlib's GoalHandle, as goals.TetherGoal)."""

    goal: Any
    stop: bool = False
    abort_reason: str = ""

    @property
    def should_stop(self) -> bool:
        return self.stop

    def feedback(self, message: Any) -> None:
        pass


@pytest.fixture(scope="module")
def stamped(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningBackend]:
    """The backend driving the stand-in robot with TwistStamped cmd_vel, as diff_drive_controller takes it."""
    backend = ros2_backend(CONTRACT_SIM)
    config = backend.config.replace("[ros2]\n", "[ros2]\nstamped_cmd_vel = true\n").replace(
        "[ros2sim]\n", "[ros2sim]\nstamped_cmd_vel = true\n"
    )
    with running(dataclasses.replace(backend, config=config), tmp_path_factory.mktemp("stamped"), beating=True) as up:
        yield up


@pytest.mark.realtime
@pytest.mark.alone
def test_a_stamped_cmd_vel_that_took_long_through_the_pipeline_still_drives_the_base(stamped: RunningBackend) -> None:
    # Stamped by whoever asked a second ago, longer than the robot's cmd_vel_timeout (0.5 s): the
    # backend holds it from when it comes, and so must the robot, so it goes out stamped when sent.
    start = len(stamped.odom)
    deadline = time.monotonic() + DEADLINE
    moving = None
    while moving is None and time.monotonic() < deadline:
        stamped.node.publish(keys.ROBOT_CMD_VEL, Twist(linear_x=0.2, stamp=time.time() - 1.0))
        stamped.safety.beats(1)
        moving = stamped.odom.wait_for(lambda o: o.linear_x > 0.1, 0.0, after=start)
    assert moving is not None, "the robot ignored every cmd_vel: it went out with tether's stamp, 1 s old"
    # Ended by the backend's hold and the robot's own timeout: the base comes to rest.
    assert stamped.odom.wait_for(lambda o: abs(o.linear_x) < 0.01, DEADLINE, after=len(stamped.odom))


# A peer on the robot's network answering the backend's calls (send_goal, get_result, cancel_goal)


def test_a_flood_of_huge_error_replies_makes_a_short_error_not_one_the_size_of_the_flood(types: RosTypes) -> None:
    with node_pair(types, Style.RMW_ZENOH) as pair:
        client = pair.tether.client("add_two_ints", ADD)

        def answer(query: zenoh.Query) -> None:
            for _ in range(FLOOD):
                query.reply_err(b"x" * ERROR_BYTES)
            query.reply_err(b"short, but past the ones kept")

        queryable = pair.robot_session.declare_queryable(client.endpoint.key, answer, complete=True)
        # Called before the backend's session knows of it, the call would reach no one: on a busy
        # machine the declaration takes a while to arrive.
        querier = pair.tether.session.declare_querier(client.endpoint.key)
        deadline = time.monotonic() + DEADLINE
        while not querier.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        querier.undeclare()
        try:
            with pytest.raises(RosCallError) as raised:
                client.call(types.new(f"{ADD}_Request", a=1, b=2), timeout=DEADLINE)
        finally:
            queryable.undeclare()
    message = str(raised.value)
    assert len(message) < 2000, f"an error of {len(message)} characters from {FLOOD} replies of {ERROR_BYTES} bytes"
    assert f"an error reply of {ERROR_BYTES} bytes" in message and f"{FLOOD + 1 - 4} more failed replies" in message


def test_a_request_heavier_than_a_service_takes_is_refused_before_it_is_decoded(types: RosTypes) -> None:
    through = "nav2_msgs/action/NavigateThroughPoses"
    with node_pair(types, Style.RMW_ZENOH) as pair:
        decoded: list[Any] = []

        def accept(goal: Any) -> bool:
            decoded.append(goal)
            return True

        pair.robot.action_server("through", through, accept=accept, execute=lambda _goal: None)
        client = pair.tether.action_client("through", through)
        assert client.wait_for_server(DEADLINE)
        pose = types.new("geometry_msgs/msg/PoseStamped")
        goal = types.new(f"{through}_Goal", poses=[pose] * 20_000)  # about 2 MB of CDR
        with pytest.raises(RosCallError, match=r"request on service .*through/_action/send_goal of \d+ bytes, over"):
            client.send_goal(goal, timeout=DEADLINE)
        assert not decoded, "the server decoded the goal and asked whether to take it"
        assert pair.robot_errors.wait(lambda errors: any("bytes, over" in e for e in errors))


def gripper_run(types: RosTypes, client: RosActionClient, handle: Handle, held: list[str]) -> GripperRun:
    def block(reason: str) -> Callable[[], None]:
        held.append(reason)
        return lambda: None

    context = RunContext(
        safety=lambda: CLEAR,
        robot=RobotState(),
        goal_timeout=DEADLINE,
        cancel_timeout=0.3,
        halt_base=lambda: None,
        block_robot=block,
    )
    return GripperRun(context, _Action(client), handle, Messages(types, Frames(), stamped_cmd_vel=False), {}, 0.2)


# An action server that forgets a goal it took: restarted (a lifecycle reset, a crash and respawn)


def test_a_goal_the_robots_action_server_forgot_ends_at_once_and_holds_no_stop(types: RosTypes) -> None:
    gripper = "control_msgs/action/GripperCommand"
    with node_pair(types, Style.RMW_ZENOH) as pair:
        executing = threading.Event()

        def execute(goal: RosServerGoal) -> None:
            executing.set()
            goal.cancel_requested.wait(DEADLINE)  # runs until its server goes

        pair.robot.action_server("gripper", gripper, accept=lambda _goal: True, execute=execute)
        client = pair.tether.action_client("gripper", gripper)
        assert client.wait_for_server(DEADLINE)
        held: list[str] = []
        handle = Handle(GripperCommandGoal(position=0.02))
        run = gripper_run(types, client, handle, held)
        ending: list[Ending] = []
        runner = threading.Thread(target=lambda: ending.append(run.run()), daemon=True)
        runner.start()
        assert executing.wait(DEADLINE), "the robot never ran the goal"
        # The robot's action server restarts: the goal is gone with it, and the new one knows nothing of it.
        pair.robot.close()
        restarted = RosNode(pair.robot_session, types, Naming(Style.RMW_ZENOH, 0), "standin_again")
        try:
            restarted.action_server("gripper", gripper, accept=lambda _goal: True, execute=execute)
            runner.join(3.0)
        finally:
            handle.stop = True  # an old run ends (canceled) rather than outliving the test
            runner.join(DEADLINE)
            restarted.close()
    assert ending, "the goal run did not end"
    assert ending[0].state is GoalState.ABORTED and "knows no such goal" in ending[0].message, ending[0]
    assert not held, f"the robot's emergency stop was held for a goal it no longer has: {held}"


def test_the_threads_following_a_goal_the_robot_would_not_end_stop_when_the_backend_leaves(types: RosTypes) -> None:
    gripper = "control_msgs/action/GripperCommand"
    release = threading.Event()
    with node_pair(types, Style.RMW_ZENOH) as pair:
        executing = threading.Event()

        def execute(goal: RosServerGoal) -> None:
            executing.set()
            release.wait(DEADLINE)  # deaf to cancels
            goal.abort(types.new(f"{gripper}_Result"))

        pair.robot.action_server("gripper", gripper, accept=lambda _goal: True, execute=execute)
        client = pair.tether.action_client("gripper", gripper)
        assert client.wait_for_server(DEADLINE)
        held: list[str] = []
        handle = Handle(GripperCommandGoal(position=0.02))
        ending: list[Ending] = []
        runner = threading.Thread(
            target=lambda: ending.append(gripper_run(types, client, handle, held).run()), daemon=True
        )
        runner.start()
        try:
            assert executing.wait(DEADLINE), "the robot never ran the goal"
            handle.stop = True  # canceled; the robot does not end it
            runner.join(DEADLINE)
            assert ending and held, "the goal run did not hold the robot's emergency stop for the goal"
            following = [t for t in threading.enumerate() if t.name.endswith(":gripper_command")]
            assert following, "no thread follows the goal the robot would not end"
            pair.tether.close()  # the backend leaves the robot's network (Ros2Backend.close)
            for thread in following:
                thread.join(3.0)
            left = [t.name for t in following if t.is_alive()]
            assert not left, f"still asking the robot about the goal after the backend left: {left}"
        finally:
            release.set()
