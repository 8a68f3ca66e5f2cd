"""An action server's status stream, memory and goal threads over two real Zenoh sessions in one process:
races made to happen at their worst moment by a status publisher that acts just before a status goes out
(no sleeps)."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from schemas import keys
from schemas.actions import CANCEL_ALL, CancelGoal, GetResult, GoalState, GoalStatus
from schemas.common import Pose2D
from schemas.robot import NavigateToPoseFeedback, NavigateToPoseGoal, NavigateToPoseResult
from services import actionlib
from services.actionlib import ActionClient, ActionServer, GoalHandle, Outcome
from services.errors import CallError
from services.runtime import Node, NodeSettings
from tests.procs import wait_until
from tests.sessions import free_port

WAIT = 5.0  # a deadline for each condition, never a pause
HERE = Pose2D(x=1.0, y=2.0)
PREEMPTS = 0.5  # a goal with this max_speed preempts the running one

Navigation = ActionClient[NavigateToPoseGoal, NavigateToPoseFeedback, NavigateToPoseResult]


class Statuses:
    """The server's status publisher, recording what goes out in order; `before[state](status)` runs
    just before a status in that state goes out (once)."""

    def __init__(self, publisher: Any) -> None:
        self.publisher = publisher
        self.before: dict[GoalState, Callable[[GoalStatus], None]] = {}
        self.sent: list[tuple[str, GoalState]] = []
        self.changed = threading.Condition()

    def put(self, status: GoalStatus) -> None:
        if (hook := self.before.pop(status.state, None)) is not None:
            hook(status)
        self.publisher.put(status)
        with self.changed:
            self.sent.append((status.goal_id, status.state))
            self.changed.notify_all()

    def of(self, goal_id: str) -> list[GoalState]:
        with self.changed:
            return [state for each, state in self.sent if each == goal_id]

    def wait_ended(self, goal_id: str) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: any(s.terminal for s in self.of(goal_id)), WAIT)


@dataclass
class Rig:
    client: Navigation
    node: Node
    statuses: Statuses
    # Every goal runs until this is set; `obeys_cancel` goals end canceled once told to stop.
    release: threading.Event = field(default_factory=threading.Event)
    obeys_cancel: bool = False
    running: threading.Event = field(default_factory=threading.Event)
    # What the client's session heard on the status topic, in order.
    heard: list[tuple[str, GoalState]] = field(default_factory=list)

    def execute(self, handle: GoalHandle[NavigateToPoseGoal, NavigateToPoseFeedback]) -> Outcome[NavigateToPoseResult]:
        self.running.set()
        while not self.release.wait(0.01):
            if self.obeys_cancel and handle.should_stop:
                return Outcome(GoalState.CANCELED, None, "stopped")
        return Outcome(GoalState.SUCCEEDED, NavigateToPoseResult(pose=HERE), "arrived")

    def heard_of(self, goal_id: str) -> list[GoalState]:
        return [state for each, state in list(self.heard) if each == goal_id]


@pytest.fixture
def rig() -> Iterator[Rig]:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    with Node("sim", settings) as server_node, Node("test", settings) as client_node:
        rig = Rig(ActionClient(client_node, keys.ROBOT_NAVIGATE), client_node, Statuses(None))
        client_node.subscribe(keys.ROBOT_NAVIGATE.status, lambda s: rig.heard.append((s.goal_id, s.state)))
        server = ActionServer(
            server_node, keys.ROBOT_NAVIGATE, rig.execute, preempts=lambda goal: goal.max_speed == PREEMPTS
        )
        rig.statuses.publisher = server._status
        server._status = rig.statuses  # type: ignore[assignment]
        server_node.declare_alive()
        assert not client_node.wait_alive({"sim"}, WAIT), "the two sessions did not find each other"
        try:
            yield rig
        finally:
            rig.release.set()


@pytest.mark.parametrize("how", ["cancel", "cancel all", "preempt"])
def test_a_goal_that_ends_as_it_is_canceled_publishes_its_end_last(rig: Rig, how: str) -> None:
    """The cancel found the goal running and said CANCELING, but the goal ended (succeeded) just
    before that went out: the stream ended SUCCEEDED, CANCELING, and a follower took the goal for
    canceling forever."""
    goal = rig.client.send(NavigateToPoseGoal(pose=HERE))
    assert rig.running.wait(WAIT)

    def end_first(status: GoalStatus) -> None:
        assert status.goal_id == goal.goal_id
        rig.release.set()
        assert rig.statuses.wait_ended(goal.goal_id), "the goal did not end"

    rig.statuses.before[GoalState.CANCELING] = end_first
    if how == "preempt":
        rig.client.send(NavigateToPoseGoal(pose=HERE, max_speed=PREEMPTS))
    else:
        which = goal.goal_id if how == "cancel" else CANCEL_ALL
        assert rig.node.call(keys.ROBOT_NAVIGATE.cancel_goal, CancelGoal(goal_id=which), timeout=WAIT).accepted
    assert goal.result(WAIT).state is GoalState.SUCCEEDED
    sent = rig.statuses.of(goal.goal_id)
    assert GoalState.CANCELING in sent, "the race did not happen"
    assert sent[-1] is GoalState.SUCCEEDED, sent
    # What a follower hears: the same stream, its end last.
    assert wait_until(lambda: rig.heard_of(goal.goal_id) == sent, WAIT), (rig.heard_of(goal.goal_id), sent)


def test_a_goal_canceled_as_it_is_accepted_says_canceling_after_executing(rig: Rig) -> None:
    """A cancel that came between the goal's acceptance and its start said CANCELING before the goal
    announced itself ACCEPTED and EXECUTING: a follower saw a canceled goal go back to executing."""
    rig.obeys_cancel = True
    goal_id = uuid.uuid4().hex

    def cancel_first(status: GoalStatus) -> None:
        assert status.goal_id == goal_id
        assert rig.node.call(keys.ROBOT_NAVIGATE.cancel_goal, CancelGoal(goal_id=goal_id), timeout=WAIT).accepted

    rig.statuses.before[GoalState.ACCEPTED] = cancel_first
    goal = rig.client.send(NavigateToPoseGoal(pose=HERE), goal_id=goal_id)
    assert goal.result(WAIT).state is GoalState.CANCELED
    order = [GoalState.ACCEPTED, GoalState.EXECUTING, GoalState.CANCELING, GoalState.CANCELED]
    assert rig.statuses.of(goal_id) == order
    assert wait_until(lambda: rig.heard_of(goal_id) == order, WAIT), rig.heard_of(goal_id)


def status_of(rig: Rig, goal_id: str) -> GoalState | None:
    """The goal's state as get_status answers it; None for a goal the server does not know."""
    try:
        return rig.node.call(keys.ROBOT_NAVIGATE.get_status, GetResult(goal_id=goal_id), timeout=WAIT).state
    except CallError as exc:
        assert "unknown goal" in exc.error.message, exc
        return None


def test_the_finished_goals_remembered_are_bounded_however_fast_goals_come(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every finished goal was kept for the retention (five minutes) however many came: a peer ending
    goals as fast as it sends them grew the server without bound."""
    monkeypatch.setattr(actionlib, "MAX_RESULTS", 2, raising=False)
    rig.release.set()  # every goal ends at once
    ended = []
    for _ in range(4):  # one at a time: the action is exclusive
        ended.append(rig.client.send(NavigateToPoseGoal(pose=HERE)))
        assert ended[-1].result(WAIT).state is GoalState.SUCCEEDED
    rig.client.send(NavigateToPoseGoal(pose=HERE)).result(WAIT)  # the server forgets as a goal comes
    assert [status_of(rig, goal.goal_id) for goal in ended] == [None, None, GoalState.SUCCEEDED, GoalState.SUCCEEDED]


def test_a_goal_that_gets_no_thread_ends_aborted_instead_of_keeping_the_action_busy(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With no thread to be had (a service's task limit reached), the accepted goal never started nor
    ended: every later goal was rejected as busy, and its result waited on for an hour."""
    start = threading.Thread.start

    def no_goal_threads(thread: threading.Thread) -> None:
        if thread.name.startswith("goal:"):
            raise RuntimeError("can't start new thread")
        start(thread)

    monkeypatch.setattr(threading.Thread, "start", no_goal_threads)
    stuck = rig.client.send(NavigateToPoseGoal(pose=HERE))
    ended = stuck.result(WAIT)
    assert (ended.state, ended.message) == (
        GoalState.ABORTED,
        "robot/navigate_to_pose could not start the goal: can't start new thread",
    )
    monkeypatch.setattr(threading.Thread, "start", start)
    rig.release.set()
    assert rig.client.send(NavigateToPoseGoal(pose=HERE)).result(WAIT).state is GoalState.SUCCEEDED
