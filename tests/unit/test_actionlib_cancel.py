"""An action client against servers that do not end their goals as asked, over two real Zenoh sessions
in one process: a goal that drives on past its cancel, results that are not this goal's end."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, GetResult, GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.common import ErrorKind, Pose2D, ServiceError
from schemas.robot import NavigateToPoseFeedback, NavigateToPoseGoal, NavigateToPoseResult
from services import actionlib
from services.actionlib import ActionClient, ActionServer, GoalHandle, Outcome
from services.errors import CallError
from services.runtime import Node, NodeSettings
from tests.sessions import free_port

WAIT = 5.0
GRACE = 0.5
HERE = Pose2D(x=1.0, y=2.0)

Navigation = ActionClient[NavigateToPoseGoal, NavigateToPoseFeedback, NavigateToPoseResult]


@dataclass
class Peers:
    """Two sessions that found each other: `server` serves, `client` sends through `navigation`."""

    server: Node
    client: Node
    navigation: Navigation


@pytest.fixture
def peers() -> Iterator[Peers]:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    with Node("sim", settings) as server, Node("test", settings) as client:
        yield Peers(server, client, ActionClient(client, keys.ROBOT_NAVIGATE, cancel_grace=GRACE))


def found(peers: Peers) -> None:
    peers.server.declare_alive()
    assert not peers.client.wait_alive({"sim"}, WAIT), "the two sessions did not find each other"


def test_a_goal_that_drives_on_past_its_cancel_is_told_apart_from_other_call_errors(peers: Peers) -> None:
    """Its sender must not take it for stopped: the error says so by its type (the executor latches
    the e-stop on it), not only in words."""
    release, running = threading.Event(), threading.Event()

    def stubborn(_handle: GoalHandle[NavigateToPoseGoal, NavigateToPoseFeedback]) -> Outcome[NavigateToPoseResult]:
        running.set()
        release.wait(WAIT)  # canceled or not
        return Outcome(GoalState.SUCCEEDED, NavigateToPoseResult(pose=HERE), "arrived")

    ActionServer(peers.server, keys.ROBOT_NAVIGATE, stubborn)
    found(peers)
    cancel = threading.Event()

    def cancel_once_running() -> None:
        if running.wait(WAIT):
            cancel.set()

    canceling = threading.Thread(target=cancel_once_running)
    canceling.start()
    try:
        with pytest.raises(actionlib.GoalNotStopped, match=rf"did not end within {GRACE:g} s of its cancel"):
            peers.navigation.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT, cancel=cancel)
    finally:
        release.set()
        canceling.join()


@dataclass
class Hostile:
    """A navigation server that accepts every goal and answers get_result with `state`, naming the goal
    asked about or, when given, `other`."""

    state: GoalState
    other: str = ""
    canceled: list[str] = field(default_factory=list)

    def serve(self, node: Node) -> None:
        action = keys.ROBOT_NAVIGATE
        node.serve(action.send_goal, self.send_goal)
        node.serve(action.cancel_goal, self.cancel_goal)
        node.serve(action.get_result, self.get_result)

    def send_goal(self, request: SendGoal[NavigateToPoseGoal]) -> GoalResponse:
        return GoalResponse(goal_id=request.goal_id, accepted=True)

    def cancel_goal(self, request: CancelGoal) -> CancelResponse:
        self.canceled.append(request.goal_id)
        return CancelResponse(goal_id=request.goal_id, accepted=True)

    def get_result(self, request: GetResult) -> ResultResponse[NavigateToPoseResult]:
        result = NavigateToPoseResult(pose=HERE) if self.state is GoalState.SUCCEEDED else None
        return ResultResponse(goal_id=self.other or request.goal_id, state=self.state, result=result)


@pytest.mark.parametrize("watched", [True, False], ids=["with a cancel to watch", "without"])
@pytest.mark.parametrize(
    ("state", "other", "why"),
    [
        (GoalState.SUCCEEDED, "another", "result with goal another's"),
        (GoalState.EXECUTING, "", "is no end: state executing"),
        (GoalState.CANCELING, "", "is no end: state canceling"),
    ],
    ids=["another goal's result", "still executing", "still canceling"],
)
def test_a_result_that_is_not_this_goals_end_is_not_taken_for_it(
    peers: Peers, state: GoalState, other: str, why: str, watched: bool
) -> None:
    """Taken for the goal's end, another goal's success would pass for this one's, and a state the
    goal goes on from for a failure a retry may follow while the goal still moves the robot. Neither
    is: the call fails and the goal is canceled."""
    hostile = Hostile(state, other)
    hostile.serve(peers.server)
    found(peers)
    cancel = threading.Event() if watched else None
    with pytest.raises(CallError, match=why):
        peers.navigation.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT, cancel=cancel)
    assert len(hostile.canceled) == 1, "the goal was not canceled"


def test_a_cancel_that_did_not_reach_the_server_is_sent_again_within_the_grace(peers: Peers) -> None:
    """The first cancel answered "too busy" (or lost): sent once, the goal drove on to the end of its
    grace and the e-stop latched, where a second cancel would have stopped it."""
    ended = threading.Event()
    asked: list[str] = []
    action = keys.ROBOT_NAVIGATE

    def cancel_goal(request: CancelGoal) -> CancelResponse:
        asked.append(request.goal_id)
        if len(asked) == 1:
            raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message="too busy to answer; try again"))
        ended.set()
        return CancelResponse(goal_id=request.goal_id, accepted=True)

    def get_result(request: GetResult) -> ResultResponse[NavigateToPoseResult]:
        ended.wait(WAIT)
        state = GoalState.CANCELED if ended.is_set() else GoalState.ABORTED
        return ResultResponse(goal_id=request.goal_id, state=state)

    peers.server.serve(action.send_goal, lambda r: GoalResponse(goal_id=r.goal_id, accepted=True))
    peers.server.serve(action.cancel_goal, cancel_goal)
    peers.server.serve(action.get_result, get_result, waits=True)
    found(peers)
    patient = ActionClient(peers.client, action, cancel_grace=3.0)
    cancel = threading.Event()
    timer = threading.Timer(0.2, cancel.set)  # once the goal is sent and running
    timer.start()
    try:
        ending = patient.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT, cancel=cancel)
    finally:
        timer.cancel()
    assert ending.state is GoalState.CANCELED, ending
    assert len(asked) == 2, asked
