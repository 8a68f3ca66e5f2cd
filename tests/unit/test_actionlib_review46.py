"""A goal whose end its sender cannot learn (send_goal or get_result failed) and whose cancel is not
answered either may have been accepted and still be moving the robot: the action client asks the
cancel again within the grace and, with none answered, says so by its error's type; the executor's
robot port latches the e-stop on it. Over real Zenoh sessions in one process, against a stand-in
server such as safety is when the robot behind it took a goal and its replies are lost."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, GetResult, GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.common import ErrorKind, Pose2D, ServiceError
from schemas.keys import ActionKeys
from schemas.robot import NavigateToPoseFeedback, NavigateToPoseGoal, NavigateToPoseResult
from schemas.safety import EStop, EstopSource
from services import actionlib
from services.actionlib import ActionClient
from services.errors import CallError
from services.executor.config import ExecutorConfig
from services.executor.errors import MotionNotStopped
from services.executor.node import NodeRobot
from services.runtime import Node, NodeSettings
from tests.sessions import free_port

WAIT = 5.0
GRACE = 1.0
HERE = Pose2D(x=1.0, y=2.0)

Navigation = ActionClient[NavigateToPoseGoal, NavigateToPoseFeedback, NavigateToPoseResult]


def unanswered(what: str) -> CallError:
    """What safety answers when the robot it forwards to did not answer in time."""
    return CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=f"no reply from the robot's {what}"))


@dataclass
class Standin:
    """A navigation server whose robot took every goal sent (`sent`, moving from then on) while the
    replies are lost as told: send_goal's (`send_lost`), get_result's (`result_lost`, or a result that
    is no end with `result_state`), and the first `cancels_lost` cancels (-1: every one). A cancel
    answered may be answered for `cancel_answers_for` instead of the goal asked about."""

    send_lost: bool = False
    result_lost: bool = False
    result_state: GoalState = GoalState.SUCCEEDED
    cancels_lost: int = -1
    cancel_answers_for: str = ""
    sent: list[str] = field(default_factory=list)
    canceled: list[str] = field(default_factory=list)

    def serve(self, node: Node, action: ActionKeys[Any, Any, Any] = keys.CMD_NAVIGATE) -> None:
        node.serve(action.send_goal, self.send_goal)
        node.serve(action.cancel_goal, self.cancel_goal)
        node.serve(action.get_result, self.get_result)

    def send_goal(self, request: SendGoal[NavigateToPoseGoal]) -> GoalResponse:
        self.sent.append(request.goal_id)
        if self.send_lost:
            raise unanswered("send_goal")
        return GoalResponse(goal_id=request.goal_id, accepted=True)

    def cancel_goal(self, request: CancelGoal) -> CancelResponse:
        self.canceled.append(request.goal_id)
        if self.cancels_lost < 0 or len(self.canceled) <= self.cancels_lost:
            raise unanswered("cancel_goal")
        return CancelResponse(goal_id=self.cancel_answers_for or request.goal_id, accepted=True)

    def get_result(self, request: GetResult) -> ResultResponse[NavigateToPoseResult]:
        if self.result_lost:
            raise unanswered("get_result")
        return ResultResponse(goal_id=request.goal_id, state=self.result_state)


@dataclass
class Peers:
    """Two sessions that found each other: `server` serves, `client` sends."""

    server: Node
    client: Node

    def navigation(self, standin: Standin, grace: float = GRACE) -> Navigation:
        standin.serve(self.server, keys.ROBOT_NAVIGATE)
        self.found()
        return ActionClient(self.client, keys.ROBOT_NAVIGATE, cancel_grace=grace)

    def found(self) -> None:
        self.server.declare_alive()
        assert not self.client.wait_alive({"sim"}, WAIT), "the two sessions did not find each other"


@pytest.fixture
def peers() -> Iterator[Peers]:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    with Node("sim", settings) as server, Node("executor", settings) as client:
        yield Peers(server, client)


def test_a_goal_whose_send_goal_and_every_cancel_went_unanswered_is_not_taken_for_stopped(peers: Peers) -> None:
    """One cancel was sent, whether it arrived or not, and a plain error raised: the executor took the
    goal for never started while the robot drove it."""
    standin = Standin(send_lost=True)
    navigation = peers.navigation(standin)
    with pytest.raises(actionlib.GoalNotStopped) as raised:
        navigation.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT)
    assert isinstance(raised.value, actionlib.GoalUnanswered)
    [goal_id] = standin.sent
    message = raised.value.error.message
    assert f"goal {goal_id}: its send_goal failed (no reply from the robot's send_goal)" in message, message
    assert f"no cancel of it was answered within {GRACE:g} s" in message, message
    # Asked again within the grace: test_a_cancel_answered_at_a_later_ask_is_enough (how many asks fit
    # in this one's 1 s depends on the CPU it gets: a loaded CI run's unit tests fitted one).
    assert standin.canceled and set(standin.canceled) == {goal_id}, standin.canceled


@pytest.mark.parametrize("watched", [True, False], ids=["with a cancel to watch", "without"])
@pytest.mark.parametrize(
    ("lost", "state", "why"),
    [
        (True, GoalState.SUCCEEDED, "no reply from the robot's get_result"),
        (False, GoalState.EXECUTING, "result is no end: state executing"),
    ],
    ids=["get_result unanswered", "a result that is no end"],
)
def test_a_goal_whose_result_and_every_cancel_went_unanswered_is_not_taken_for_stopped(
    peers: Peers, lost: bool, state: GoalState, why: str, watched: bool
) -> None:
    standin = Standin(result_lost=lost, result_state=state)
    navigation = peers.navigation(standin)
    cancel = threading.Event() if watched else None
    with pytest.raises(actionlib.GoalNotStopped) as raised:
        navigation.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT, cancel=cancel)
    assert isinstance(raised.value, actionlib.GoalUnanswered)
    message = raised.value.error.message
    assert f"goal {standin.sent[0]}: its get_result failed" in message and why in message, message
    assert standin.canceled, "no cancel was asked"


def test_a_cancel_answered_at_a_later_ask_is_enough(peers: Peers) -> None:
    """The goal is known to be stopping (or never to start): the call fails as it did, with no e-stop's
    worth of error, once the second cancel is answered."""
    standin = Standin(send_lost=True, cancels_lost=1)
    # A grace long enough for a second ask on a loaded machine: it ends as soon as that is answered.
    navigation = peers.navigation(standin, grace=10.0)
    with pytest.raises(CallError) as raised:
        navigation.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT)
    assert not isinstance(raised.value, actionlib.GoalNotStopped), raised.value
    assert "no reply from the robot's send_goal" in raised.value.error.message
    assert len(standin.canceled) == 2, standin.canceled


def test_a_cancel_answered_for_another_goal_is_no_answer(peers: Peers) -> None:
    standin = Standin(result_lost=True, cancels_lost=0, cancel_answers_for="another")
    navigation = peers.navigation(standin)
    with pytest.raises(actionlib.GoalNotStopped, match="no cancel of it was answered"):
        navigation.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT)


def test_the_executor_latches_the_e_stop_naming_the_goal_and_what_went_unanswered(peers: Peers) -> None:
    """NodeRobot latched the e-stop only for a goal that did not stop within its cancel's grace: one
    whose send_goal and cancel both went unanswered failed the step as 'the robot side did not
    answer' with the robot free to drive on."""
    standin = Standin(send_lost=True)
    standin.serve(peers.server)
    latched: list[EStop] = []
    heard = threading.Event()

    def on_estop(estop: EStop) -> None:
        latched.append(estop)
        heard.set()

    peers.server.subscribe(keys.ESTOP, on_estop)
    peers.found()
    robot = NodeRobot(peers.client, ExecutorConfig(cancel_grace=GRACE))
    with pytest.raises(MotionNotStopped) as raised:
        robot.navigate(NavigateToPoseGoal(pose=HERE), threading.Event())
    [goal_id] = standin.sent
    message = str(raised.value)
    assert message.startswith("the robot side did not answer: "), message
    assert f"goal {goal_id}: its send_goal failed" in message, message
    # No safety beats here: the e-stop is sent, and the words do not claim it latched.
    assert message.endswith(
        "it may still be moving the robot; the executor sent safety an e-stop, which no heartbeat showed "
        "latched (no safety heartbeat received)"
    ), message
    assert heard.wait(WAIT), "no e-stop was published"
    [estop] = latched
    assert estop.source is EstopSource.EXECUTOR, estop
    assert f"goal {goal_id}: its send_goal failed" in estop.reason, estop.reason
    assert "no cancel of it was answered" in estop.reason, estop.reason


def test_a_goal_whose_cancel_is_answered_latches_nothing(peers: Peers) -> None:
    """The robot side took the cancel: the step fails as the robot side not answering, no e-stop."""
    standin = Standin(result_lost=True, cancels_lost=0)
    standin.serve(peers.server)
    latched: list[EStop] = []
    peers.server.subscribe(keys.ESTOP, latched.append)
    peers.found()
    robot = NodeRobot(peers.client, ExecutorConfig(cancel_grace=GRACE))
    with pytest.raises(CallError) as raised:
        robot.navigate(NavigateToPoseGoal(pose=HERE), threading.Event())
    assert not isinstance(raised.value, actionlib.GoalNotStopped), raised.value
    assert standin.canceled == standin.sent, standin.canceled
    assert not latched, latched
