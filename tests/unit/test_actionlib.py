"""Actions over two real Zenoh sessions in one process: status without waiting, preemption, cancel grace,
goals decided on Zenoh's callback thread when nothing makes them wait."""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import pytest

from schemas import keys
from schemas.actions import CANCEL_ALL, CancelGoal, GetResult, GoalState
from schemas.common import ErrorKind, Pose2D, Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus
from schemas.keys import Service
from schemas.plan import PlanText
from schemas.robot import NavigateToPoseFeedback, NavigateToPoseGoal, NavigateToPoseResult
from services import actionlib
from services.actionlib import ActionClient, ActionServer, ClientGoal, GoalHandle, Outcome
from services.errors import CallError, GoalRejected
from services.querypool import QueryPool
from services.runtime import Node, NodeSettings
from tests.procs import wait_until
from tests.sessions import free_port
from tether.client import PlanSender

WAIT = 5.0
HERE = Pose2D(x=1.0, y=2.0)
# This test's ways of saying a goal preempts (max_speed) and that it moves nothing (max_turn_rate).
PREEMPTS = 0.5
MOVES_NOTHING = 0.25


@dataclass
class Script:
    """How the served goals behave: each blocks until released or canceled (unless it ignores cancel)."""

    ignore_cancel: bool = False
    # When set, a goal told to stop makes the server refuse new goals with this (an e-stop latching).
    refuse_once_stopped: str = ""
    refusal: str | None = None
    release: threading.Event = field(default_factory=threading.Event)
    started: list[str] = field(default_factory=list)
    ended: list[str] = field(default_factory=list)
    running: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)
    # The threads `accept` ran on, in order: Zenoh's callback thread or a pool worker.
    accepted_on: list[str] = field(default_factory=list)
    # When set, `accept` waits until it is set (a robot slow to decide), at most WAIT.
    decide: threading.Event | None = None

    def accept(self, _goal: NavigateToPoseGoal) -> str | None:
        self.accepted_on.append(threading.current_thread().name)
        if self.decide is not None:
            self.decide.wait(WAIT)
        return self.refusal

    def execute(self, handle: GoalHandle[NavigateToPoseGoal, NavigateToPoseFeedback]) -> Outcome[NavigateToPoseResult]:
        if handle.goal.max_turn_rate == MOVES_NOTHING:
            return Outcome(GoalState.SUCCEEDED, NavigateToPoseResult(pose=HERE), "looked only")
        with self.lock:
            # Two goals never run at once: a preempting one starts only after the other ended.
            assert len(self.started) == len(self.ended), "a goal started while another ran"
            self.started.append(handle.goal_id)
        self.running.set()
        handle.feedback(NavigateToPoseFeedback(pose=HERE, distance_remaining=3.0))
        try:
            while not self.release.wait(0.01):
                if handle.should_stop and not self.ignore_cancel:
                    self.refusal = self.refuse_once_stopped or None
                    return Outcome(GoalState.CANCELED, None, "stopped")
            return Outcome(GoalState.SUCCEEDED, NavigateToPoseResult(pose=HERE), "arrived")
        finally:
            self.running.clear()
            with self.lock:
                self.ended.append(handle.goal_id)


# Holds the server's one quick-query worker until released, so a query handed to a worker finds none.
HOLD: Service[PlanText, PlanText] = Service("test/hold", PlanText, PlanText)


@dataclass
class Rig:
    client: ActionClient[NavigateToPoseGoal, NavigateToPoseFeedback, NavigateToPoseResult]
    node: Node
    script: Script
    held: threading.Event = field(default_factory=threading.Event)
    release_worker: threading.Event = field(default_factory=threading.Event)
    # The server's quick queries' pool (with `accept_waits`).
    pool: QueryPool | None = None
    server: ActionServer[NavigateToPoseGoal, NavigateToPoseFeedback, NavigateToPoseResult] | None = None

    def hold_the_worker(self, callers: ThreadPoolExecutor) -> Future[PlanText]:
        """The server's only worker blocked (the pool has no backlog): a goal sent to a worker is answered busy."""
        holding = callers.submit(self.node.call, HOLD, PlanText(text="hold"), timeout=WAIT)
        assert self.held.wait(WAIT), "the worker was not taken"
        return holding


@contextlib.contextmanager
def serving(
    accept_waits: Callable[[NavigateToPoseGoal], bool] | None = None, preempt_timeout: float = 1.0
) -> Iterator[Rig]:
    """A navigation server whose `accept` is the script's, and a client; with `accept_waits`, the
    server's quick queries have one worker and no backlog."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    script = Script()
    with Node("sim", settings) as server_node, Node("test", settings) as client_node:
        rig = Rig(ActionClient(client_node, keys.ROBOT_NAVIGATE, cancel_grace=0.5), client_node, script)
        if accept_waits is not None:
            server_node.queries = rig.pool = QueryPool("q:test", workers=1)

            def hold(request: PlanText) -> PlanText:
                rig.held.set()
                assert rig.release_worker.wait(WAIT), "the worker was never released"
                return request

            server_node.serve(HOLD, hold)
        rig.server = ActionServer(
            server_node,
            keys.ROBOT_NAVIGATE,
            script.execute,
            accept=script.accept,
            preempts=lambda goal: goal.max_speed == PREEMPTS,
            preempt_timeout=preempt_timeout,
            concurrent=lambda goal: goal.max_turn_rate == MOVES_NOTHING,
            accept_waits=accept_waits,
        )
        server_node.declare_alive()
        assert not client_node.wait_alive({"sim"}, WAIT), "the two sessions did not find each other"
        try:
            yield rig
        finally:
            script.release.set()
            rig.release_worker.set()


@pytest.fixture
def rig() -> Iterator[Rig]:
    """Without `accept_waits`: the script's `accept` is taken to wait, every goal is decided on a worker."""
    with serving() as rig:
        yield rig


def placed(goal: NavigateToPoseGoal) -> bool:
    """As the sim's: deciding on a goal without `start` waits (for where the base stands)."""
    return goal.start is None


@pytest.fixture
def quick() -> Iterator[Rig]:
    with serving(accept_waits=placed) as rig:
        yield rig


def from_here(**limits: float) -> NavigateToPoseGoal:
    """A goal whose `accept` does not wait (its start is given)."""
    return NavigateToPoseGoal(pose=HERE, start=HERE, **limits)


def on_a_worker(thread: str) -> bool:
    """Whether `thread` is a worker of a node's query pools (services/querypool.py)."""
    return thread.startswith(("q:", "w:"))


def test_status_answers_at_once_with_the_latest_feedback_and_then_the_result(rig: Rig) -> None:
    goal = rig.client.send(NavigateToPoseGoal(pose=HERE))
    assert rig.script.running.wait(WAIT)
    status = GetResult(goal_id=goal.goal_id)
    progress = rig.node.call(keys.ROBOT_NAVIGATE.get_status, status, timeout=WAIT)
    assert progress.state is GoalState.EXECUTING and progress.result is None
    assert progress.feedback == NavigateToPoseFeedback(pose=HERE, distance_remaining=3.0)
    rig.script.release.set()
    assert goal.result(WAIT).state is GoalState.SUCCEEDED
    done = rig.node.call(keys.ROBOT_NAVIGATE.get_status, status, timeout=WAIT)
    assert (done.state, done.message, done.result) == (GoalState.SUCCEEDED, "arrived", NavigateToPoseResult(pose=HERE))
    with pytest.raises(CallError, match="unknown goal"):
        rig.node.call(keys.ROBOT_NAVIGATE.get_status, GetResult(goal_id="nosuchgoal"), timeout=WAIT)


def test_a_second_goal_is_rejected_while_one_runs_unless_it_preempts(rig: Rig) -> None:
    first = rig.client.send(NavigateToPoseGoal(pose=HERE))
    assert rig.script.running.wait(WAIT)
    with pytest.raises(GoalRejected, match="busy"):
        rig.client.send(NavigateToPoseGoal(pose=HERE))
    second = rig.client.send(NavigateToPoseGoal(pose=HERE, max_speed=PREEMPTS))
    # Accepted only once the first had ended: the script asserts no overlap.
    ended = first.result(WAIT)
    assert ended.state is GoalState.CANCELED
    assert ended.message == f"preempted by goal {second.goal_id}; stopped"
    assert rig.script.ended == [first.goal_id]
    rig.script.release.set()
    assert second.result(WAIT).state is GoalState.SUCCEEDED
    assert rig.script.started == [first.goal_id, second.goal_id]
    # Without `accept_waits`, an `accept` is taken to wait: every goal was decided on a worker.
    assert len(rig.script.accepted_on) == 4 and all(on_a_worker(t) for t in rig.script.accepted_on)


def test_a_preempting_goal_is_checked_again_once_the_old_one_ended(rig: Rig) -> None:
    rig.script.refuse_once_stopped = "e-stop latched by test"
    rig.client.send(NavigateToPoseGoal(pose=HERE))
    assert rig.script.running.wait(WAIT)
    with pytest.raises(GoalRejected, match="e-stop latched by test"):
        rig.client.send(NavigateToPoseGoal(pose=HERE, max_speed=PREEMPTS), timeout=WAIT)
    assert len(rig.script.started) == 1


def test_a_goal_that_will_not_stop_keeps_a_preempting_one_out(rig: Rig) -> None:
    rig.script.ignore_cancel = True
    first = rig.client.send(NavigateToPoseGoal(pose=HERE))
    assert rig.script.running.wait(WAIT)
    with pytest.raises(GoalRejected, match=rf"goal {first.goal_id} did not stop within 1 s of being preempted"):
        rig.client.send(NavigateToPoseGoal(pose=HERE, max_speed=PREEMPTS), timeout=WAIT)
    assert rig.script.started == [first.goal_id]


@pytest.mark.parametrize("sweep", ["cancel all", "abort all"])
def test_a_goal_waiting_for_the_one_it_preempts_is_rejected_when_every_goal_is_canceled(sweep: str) -> None:
    """`tether cancel` (every goal) or an e-stop (abort_all) while a preempting goal waits for the
    running one to end: the waiting goal is rejected, not started once the old one has ended."""
    with serving(preempt_timeout=WAIT) as rig, ThreadPoolExecutor(1) as callers:
        assert rig.server is not None
        rig.script.ignore_cancel = True  # the first goal ends only once released: the second waits for it
        first = rig.client.send(NavigateToPoseGoal(pose=HERE))
        assert rig.script.running.wait(WAIT)
        second = callers.submit(rig.client.send, NavigateToPoseGoal(pose=HERE, max_speed=PREEMPTS), timeout=WAIT)
        status = GetResult(goal_id=first.goal_id)

        def preempting() -> bool:  # the second has asked the first to stop, and waits for it to end
            return rig.node.call(keys.ROBOT_NAVIGATE.get_status, status, timeout=WAIT).state is GoalState.CANCELING

        assert wait_until(preempting, WAIT), "the second goal never asked the first to stop"
        if sweep == "cancel all":
            canceled = rig.node.call(keys.ROBOT_NAVIGATE.cancel_goal, CancelGoal(goal_id=CANCEL_ALL), timeout=WAIT)
            assert (canceled.accepted, canceled.reason) == (True, "1 canceled")
            why = "every goal was canceled"
        else:
            rig.server.abort_all("e-stop latched by test")
            why = "e-stop latched by test"
        assert not second.done(), "the second goal was decided before the first ended"
        rig.script.release.set()
        with pytest.raises(GoalRejected, match=rf"{why} \(while this goal was being decided\)"):
            second.result(WAIT)
        assert first.result(WAIT).state is GoalState.SUCCEEDED  # it ignored every cancel
        assert rig.script.started == [first.goal_id], "a goal started after every goal was canceled"


def test_a_goal_whose_send_goal_went_unanswered_is_canceled_and_never_runs(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    """The client gives up waiting for send_goal's answer while the server still decides: it cancels the
    goal by id, and the server, once decided, rejects it instead of running a goal no one follows."""
    caplog.set_level(logging.INFO, logger=actionlib.__name__)  # where the server says it rejected a goal
    rig.script.decide = threading.Event()
    sent = rig.client.send
    rig.client.send = functools.partial(sent, timeout=0.3)  # type: ignore[method-assign]
    with pytest.raises(CallError):  # no answer in time
        rig.client.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT)
    assert rig.script.accepted_on, "the goal reached the server"
    rig.script.decide.set()

    def rejected() -> bool:
        return any("was canceled before it was accepted" in r.getMessage() for r in caplog.records)

    assert wait_until(rejected, WAIT), "the server did not reject the goal canceled while it decided"
    assert rig.script.started == [], "a goal whose sender gave up on it ran"


def test_a_client_gives_up_on_a_goal_that_ignores_its_cancel(rig: Rig) -> None:
    rig.script.ignore_cancel = True
    cancel = threading.Event()
    canceling = threading.Thread(target=lambda: rig.script.running.wait(WAIT) and cancel.set())
    canceling.start()
    with pytest.raises(CallError, match=r"did not end within 0\.5 s of its cancel"):
        rig.client.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT, cancel=cancel)
    canceling.join()


def test_a_goal_canceled_before_it_is_sent_is_never_sent(rig: Rig) -> None:
    cancel = threading.Event()
    cancel.set()
    result = rig.client.run(NavigateToPoseGoal(pose=HERE), timeout=WAIT, cancel=cancel)
    assert (result.state, result.message) == (GoalState.CANCELED, "canceled before it was sent")
    assert rig.script.started == [], "nothing started moving after the cancel"


def test_a_goal_that_moves_nothing_runs_beside_the_running_one_and_preempts_nothing(rig: Rig) -> None:
    first = rig.client.send(NavigateToPoseGoal(pose=HERE))
    assert rig.script.running.wait(WAIT)
    # Moving nothing (a dry run), asking to preempt does not stop the running goal.
    beside = rig.client.send(NavigateToPoseGoal(pose=HERE, max_speed=PREEMPTS, max_turn_rate=MOVES_NOTHING))
    assert rig.script.ended == [], "the running goal was not preempted"
    rig.script.release.set()
    assert first.result(WAIT).state is GoalState.SUCCEEDED
    assert beside.result(WAIT).state is GoalState.SUCCEEDED


def test_a_result_is_kept_for_the_retention_then_forgotten_and_a_running_goal_never(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    looked = NavigateToPoseGoal(pose=HERE, max_turn_rate=MOVES_NOTHING)  # ends at once, keeps nobody out
    ended = rig.client.send(looked)
    assert ended.result(WAIT).state is GoalState.SUCCEEDED
    running = rig.client.send(NavigateToPoseGoal(pose=HERE))
    assert rig.script.running.wait(WAIT)

    def status(goal_id: str) -> GoalState | None:
        try:
            return rig.node.call(keys.ROBOT_NAVIGATE.get_status, GetResult(goal_id=goal_id), timeout=WAIT).state
        except CallError:
            return None

    # Within the retention (five minutes): its result is there, and its id is not taken again.
    assert status(ended.goal_id) is GoalState.SUCCEEDED
    with pytest.raises(GoalRejected, match="already used"):
        rig.client.send(looked, goal_id=ended.goal_id)
    # Past it: forgotten as the next goal comes.
    monkeypatch.setattr(actionlib, "RESULT_RETENTION", 0.0)
    rig.client.send(looked).result(WAIT)
    assert status(ended.goal_id) is None, "a result outlived its retention"
    # The goal running all along is not forgotten, and still keeps others out; the old id is free.
    assert status(running.goal_id) is GoalState.EXECUTING
    with pytest.raises(GoalRejected, match="busy"):
        rig.client.send(NavigateToPoseGoal(pose=HERE))
    again = rig.client.send(looked, goal_id=ended.goal_id)
    assert again.result(WAIT).state is GoalState.SUCCEEDED
    rig.script.release.set()
    assert running.result(WAIT).state is GoalState.SUCCEEDED


def test_a_goal_that_waits_for_nothing_is_decided_on_zenohs_thread_with_no_worker_free(quick: Rig) -> None:
    with ThreadPoolExecutor(1, thread_name_prefix="caller") as callers:
        holding = quick.hold_the_worker(callers)
        try:
            # Nothing running, `accept` does not wait: accepted although no worker could have taken it.
            first = quick.client.send(from_here())
            assert quick.script.running.wait(WAIT)
            assert len(quick.script.accepted_on) == 1
            assert not on_a_worker(quick.script.accepted_on[0]) and not quick.script.accepted_on[0].startswith("caller")
            # Neither does one that does not preempt: rejected at once as busy; nor one that moves nothing.
            with pytest.raises(GoalRejected, match="busy with another goal"):
                quick.client.send(from_here())
            beside = quick.client.send(from_here(max_speed=PREEMPTS, max_turn_rate=MOVES_NOTHING))
            assert beside.result(WAIT).state is GoalState.SUCCEEDED
            # One that would preempt the running goal waits for it to end: that is a worker's, and none is free.
            with pytest.raises(CallError, match="too busy to answer") as busy:
                quick.client.send(from_here(max_speed=PREEMPTS))
            assert busy.value.error.kind is ErrorKind.UNAVAILABLE
            assert quick.script.ended == [], "a goal answered busy preempted the running one"
            # Cancel never waits either.
            assert first.cancel().accepted
            ended = first.result(WAIT)
            assert (ended.state, quick.script.ended) == (GoalState.CANCELED, [first.goal_id])
            # Nothing runs now, but this goal's `accept` waits (no start): a worker's, and none is free.
            with pytest.raises(CallError, match="too busy to answer"):
                quick.client.send(NavigateToPoseGoal(pose=HERE))
            assert not any(on_a_worker(t) for t in quick.script.accepted_on)
            assert quick.script.started == [first.goal_id]
        finally:
            quick.release_worker.set()
        assert holding.result(WAIT) == PlanText(text="hold")


def test_a_goal_that_preempts_or_whose_accept_waits_is_decided_on_a_worker(quick: Rig) -> None:
    first = quick.client.send(from_here())
    assert quick.script.running.wait(WAIT)
    assert not on_a_worker(quick.script.accepted_on[-1])
    second = quick.client.send(from_here(max_speed=PREEMPTS))
    # Accepted on a worker only once the preempted goal had ended (the script asserts no overlap);
    # `accept` asked before the wait and again after it.
    ended = first.result(WAIT)
    assert (ended.state, ended.message) == (GoalState.CANCELED, f"preempted by goal {second.goal_id}; stopped")
    assert quick.script.accepted_on[1:] == [quick.script.accepted_on[1]] * 2
    assert on_a_worker(quick.script.accepted_on[1])
    quick.script.release.set()
    assert second.result(WAIT).state is GoalState.SUCCEEDED
    # The worker that accepted the second goal is free once its task has returned, which on a loaded
    # machine may be after the goal itself ended (the pool has no backlog: a goal sent now is busy).
    pool = quick.pool
    assert pool is not None and wait_until(lambda: pool.busy == 0, WAIT), "the worker never came free"
    # Nothing running, but its `accept` waits: on a worker too.
    third = quick.client.send(NavigateToPoseGoal(pose=HERE))
    assert third.result(WAIT).state is GoalState.SUCCEEDED
    assert len(quick.script.accepted_on) == 4 and on_a_worker(quick.script.accepted_on[3])
    assert quick.script.started == [first.goal_id, second.goal_id, third.goal_id]


def test_a_plan_sender_hears_only_its_own_plans_and_keeps_nothing_once_they_end() -> None:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    release = threading.Event()

    def execute(handle: GoalHandle[ExecutePlanGoal, ExecutePlanFeedback]) -> Outcome[ExecutePlanResult]:
        handle.feedback(ExecutePlanFeedback(stage=Stage.EXECUTE, message=handle.goal.text))
        release.wait(WAIT)
        return Outcome(GoalState.SUCCEEDED, ExecutePlanResult(status=PlanStatus.SUCCEEDED, stage=Stage.EXECUTE))

    with Node("executor", settings) as server_node, Node("test", settings) as client_node:
        ActionServer(server_node, keys.EXECUTE_PLAN, execute, concurrent=lambda goal: True)
        server_node.declare_alive()
        assert not client_node.wait_alive({"executor"}, WAIT), "the two sessions did not find each other"
        heard: dict[str, list[ExecutePlanFeedback]] = {"a": [], "b": []}
        senders = {name: PlanSender(client_node, heard[name].append) for name in heard}
        handles = {name: sender.send(ExecutePlanGoal(text=name)) for name, sender in senders.items()}
        for name, sender in senders.items():
            started = sender.wait(handles[name], WAIT, until_started=True)
            assert started.result is None and started.latest is not None and started.latest.message == name
            assert sender.following() == [handles[name].goal_id]
        release.set()
        for name, sender in senders.items():
            ended = sender.wait(handles[name], WAIT)
            assert ended.result is not None and ended.result.status is PlanStatus.SUCCEEDED
            assert sender.following() == [], "a sender kept a plan that ended"
        assert {name: [fb.message for fb in fbs] for name, fbs in heard.items()} == {"a": ["a"], "b": ["b"]}


def test_a_result_future_whose_node_closes_fails_with_the_reason_instead_of_raising_on_its_thread() -> None:
    node = Node("test", NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port()))
    client = ActionClient(node, keys.ROBOT_NAVIGATE)
    node.close()
    future = ClientGoal(client, "nosuchgoal").result_future(WAIT)
    error = future.exception(WAIT)
    assert error is not None and "closed" in str(error), error
