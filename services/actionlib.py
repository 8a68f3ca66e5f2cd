"""Actions over Zenoh on the five ROS 2 action keys: a goal server and a client."""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable
from concurrent import futures
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Generic, NoReturn, TypeVar

from schemas.actions import (
    CANCEL_ALL,
    CancelGoal,
    CancelResponse,
    Feedback,
    GetResult,
    GoalProgress,
    GoalResponse,
    GoalState,
    GoalStatus,
    ResultResponse,
    SendGoal,
)
from schemas.common import ErrorKind, ServiceError
from schemas.keys import ActionKeys
from services.errors import CallError, GoalRejected
from services.runtime import Node, Verify

log = logging.getLogger(__name__)

G = TypeVar("G")
F = TypeVar("F")
R = TypeVar("R")

# How long a finished goal's result stays available to get_result.
RESULT_RETENTION = 300.0
# At most this many finished goals are remembered, however fast goals come (the oldest forgotten first).
MAX_RESULTS = 4096
MAX_RESULT_WAIT = 3600.0
CANCEL_POLL = 0.05
# Cancels of goal ids not (yet) known an action server remembers, so the goal is rejected if it comes.
MAX_EARLY_CANCELS = 1024
# After a client cancels a goal, it waits this long for the server to report it ended; then it
# raises GoalNotStopped: the goal may still be moving the robot. A goal whose end it cannot learn (its
# send_goal or get_result failed) it cancels, and raises GoalUnanswered if no cancel was answered by then.
CANCEL_GRACE = 10.0
# A cancel that did not reach the server (no answer, or the server too busy) is sent again this often
# while the goal's cancel grace lasts.
CANCEL_RESEND = 0.5
# A preempting goal waits this long for the goals it cancels to end before it is accepted.
PREEMPT_TIMEOUT = 10.0
# The goal id of a result for a goal that was never sent.
UNSENT = "unsent"


class GoalNotStopped(CallError):
    """A goal did not end within the grace after its cancel: it may still be moving the robot, and
    whoever sent it must not go on as if it had stopped."""


class GoalUnanswered(GoalNotStopped):
    """A goal whose end could not be learned (its send_goal or get_result failed), and no cancel of it
    reached the server within the grace: it may have been accepted and may still be moving the robot."""


@dataclass(frozen=True)
class Outcome(Generic[R]):
    """What a goal ended as: the terminal state, its result value and a message for people."""

    state: GoalState
    result: R | None = None
    message: str = ""


@dataclass
class GoalHandle(Generic[G, F]):
    """The executing side of one goal: read the goal, publish feedback, watch for cancel or abort."""

    goal_id: str
    goal: G
    _publish_feedback: Callable[[str, F], None]
    cancel_requested: threading.Event = field(default_factory=threading.Event)
    abort_reason: str = ""
    done: threading.Event = field(default_factory=threading.Event)
    outcome: Outcome[Any] | None = None
    finished_at: float = 0.0
    latest_feedback: F | None = None
    # Why the goal is being canceled when someone other than its client asked (a preempting goal).
    cancel_reason: str = ""
    # Whether its ACCEPTED and EXECUTING have gone out: a CANCELING before them would be followed by
    # EXECUTING, and is said after them instead.
    announced: bool = False

    def feedback(self, message: F) -> None:
        self.latest_feedback = message
        self._publish_feedback(self.goal_id, message)

    @property
    def should_stop(self) -> bool:
        return self.cancel_requested.is_set()


def _events() -> tuple[threading.Event, threading.Event]:
    """A goal handle's cancel_requested and done."""
    return threading.Event(), threading.Event()


class ActionServer(Generic[G, F, R]):
    """Serves one action. Each accepted goal runs `execute` on its own thread, started once the
    goal's acceptance is on its way back; until then it counts as running (it keeps others out, a
    cancel or abort reaches it before it moves).

    `accept` returns None to accept a goal or the reason to reject it. With `exclusive`, a goal
    that arrives while another runs is rejected, unless `preempts(goal)` says it preempts: then the
    running goals are canceled and the new one is accepted only once they have ended, so two goals
    never drive the robot at once; `accept` is asked again after that wait (an e-stop latched
    meanwhile rejects it). Of two goals preempting at once, the later one to finish its wait finds
    the other running and is rejected as busy: the sender retries. A goal `concurrent(goal)` says
    moves nothing (a dry run) is neither kept out nor keeps others out. Besides the five ROS 2 keys
    it answers `get_status`. `verify` checks each goal and cancel before it is read (a robot's
    action: only safety's signed ones, services/robotlink.py).

    A goal that will not wait is answered on Zenoh's callback thread, with no hand-over to a worker:
    one that preempts nothing (no goal running, checked as it arrives), whose `accept` never waits.
    `accept_waits(goal)` says whether `accept` may wait for it (the sim asks its own thread where
    the base is); without it, an `accept` is taken to wait and every goal goes to a worker. A goal
    started between that look and its turn is still preempted, on the callback thread: rare, and
    over once the preempted goal has ended (its motion stops at the next step).

    Canceling every goal (CANCEL_ALL) or aborting them all (`abort_all`) also reaches a goal being
    decided meanwhile (one waiting for the goal it preempts to end): it is rejected with the reason,
    not started after the cancel. A goal still on its way to a worker when the cancel is answered
    (microseconds) is decided as if it came after it.
    """

    def __init__(
        self,
        node: Node,
        action: ActionKeys[G, F, R],
        execute: Callable[[GoalHandle[G, F]], Outcome[R]],
        *,
        accept: Callable[[G], str | None] | None = None,
        exclusive: bool = True,
        preempts: Callable[[G], bool] | None = None,
        preempt_timeout: float = PREEMPT_TIMEOUT,
        concurrent: Callable[[G], bool] | None = None,
        verify: Verify | None = None,
        accept_waits: Callable[[G], bool] | None = None,
    ) -> None:
        self._node = node
        self._action = action
        self._execute = execute
        self._accept = accept
        self._exclusive = exclusive
        self._preempts = preempts
        self._preempt_timeout = preempt_timeout
        # None: every goal moves the robot (no call made to say so, on every goal's path).
        self._concurrent = concurrent
        self._accept_waits = accept_waits or (lambda _goal: accept is not None)
        # Every goal accepted and not yet forgotten, by id; of them, those running (accepted, not yet
        # ended: a goal leaves as its `done` is set, under the lock), and those ended, oldest first
        # (when, id). A goal is decided on by looking at the running ones only: with every result kept
        # RESULT_RETENTION, scanning all of them cost the sim's send_goal some 0.1 ms each time at 24
        # goals a second (bench.gate).
        self._goals: dict[str, GoalHandle[G, F]] = {}
        self._running: dict[str, GoalHandle[G, F]] = {}
        self._ended: deque[tuple[float, str]] = deque()
        self._lock = threading.Lock()
        # How many times every goal was canceled or aborted, and why the last time: a goal decided
        # across one is rejected (see the class's docstring).
        self._sweeps = 0
        self._swept_because = ""
        # Goal ids canceled before any goal of theirs was known, oldest first (at most
        # MAX_EARLY_CANCELS): a client that had no answer to its send_goal cancels the goal by id, and
        # the server may still be deciding on it. Such a goal is rejected when its turn comes.
        self._canceled_early: dict[str, None] = {}
        # The Events of the next accepted goal's handle, made before it comes (again in `_start`, once
        # the reply has gone): made on the reply's path they cost the sim's send_goal some 40 us, as the
        # robot mostly answers a goal after sleeping, when such code takes many times its warm time.
        self._spare_events: tuple[threading.Event, threading.Event] | None = _events()
        self._feedback = node.publisher(action.feedback)
        self._status = node.publisher(action.status)
        # An accepted goal starts once its acceptance has gone back (`_start`): the sender does not
        # wait for a thread to start, nor for the GIL the new thread takes first.
        node.serve(
            action.send_goal, self._on_send_goal, inline=self._answered_at_once, after=self._start, verify=verify
        )
        # Cancel and status never wait: answered on Zenoh's callback thread, with no hand-over.
        node.serve(action.cancel_goal, self._on_cancel, inline=True, verify=verify)
        node.serve(action.get_status, self._on_get_status, inline=True)
        # Waits as long as the goal runs: on the node's pool for such waits, not a quick query's worker.
        node.serve(action.get_result, self._on_get_result, waits=True)

    def active(self) -> list[GoalHandle[G, F]]:
        with self._lock:
            return list(self._running.values())

    def abort_all(self, reason: str) -> None:
        """Stop every running goal (e-stop, lost heartbeat); each ends as aborted with `reason`. A goal
        being decided meanwhile is rejected with it."""
        for handle in self._sweep(reason):
            handle.abort_reason = reason
            handle.cancel_requested.set()

    def wait_ended(self, timeout: float) -> list[str]:
        """Wait up to `timeout` for the running goals to end (after `abort_all`, say); the ids of
        those that did not."""
        deadline = time.monotonic() + timeout
        return [h.goal_id for h in self.active() if not h.done.wait(max(0.0, deadline - time.monotonic()))]

    def _sweep(self, reason: str) -> list[GoalHandle[G, F]]:
        """The running goals, for canceling or aborting all of them; a goal being decided now will be
        rejected with `reason`."""
        with self._lock:
            self._sweeps += 1
            self._swept_because = reason
            return list(self._running.values())

    def _publish_status(self, goal_id: str, state: GoalState, message: str = "") -> None:
        self._status.put(GoalStatus(goal_id=goal_id, state=state, message=message, stamp=time.time()))

    def _answered_at_once(self, request: SendGoal[G]) -> bool:
        """Whether deciding on this goal waits for nothing: its accept does not, it preempts no goal."""
        goal = request.goal
        if self._accept_waits(goal):
            return False
        concurrent = self._concurrent
        if (
            not (self._exclusive and self._preempts is not None)
            or (concurrent and concurrent(goal))
            or not self._preempts(goal)
        ):
            return True
        with self._lock:
            return not self._blocking()

    def _on_send_goal(self, request: SendGoal[G]) -> GoalResponse:
        with self._lock:
            sweeps = self._sweeps
        reason = self._accept(request.goal) if self._accept else None
        with self._lock:
            if reason is None and request.goal_id in self._goals:
                reason = f"goal id {request.goal_id} was already used"
        exclusive = self._exclusive and not (self._concurrent and self._concurrent(request.goal))
        if reason is None and exclusive and self._preempts is not None and self._preempts(request.goal):
            preempted, reason = self._preempt(request.goal_id)
            # Asked again for what may have changed while it waited. With no goal to wait for, the answer
            # just given stands: every goal paid its check twice (the sim's keep-out check of a navigation).
            if reason is None and preempted and self._accept:
                reason = self._accept(request.goal)
        with self._lock:
            self._forget_old()
            if reason is None and request.goal_id in self._goals:
                reason = f"goal id {request.goal_id} was already used"
            if request.goal_id in self._canceled_early:
                del self._canceled_early[request.goal_id]
                reason = reason or f"goal {request.goal_id} was canceled before it was accepted"
            if reason is None and self._sweeps != sweeps:
                reason = f"{self._swept_because} (while this goal was being decided)"
            if reason is None and exclusive and self._blocking():
                reason = f"{self._action.path} is busy with another goal"
            if reason is not None:
                log.info("rejected goal %s on %s: %s", request.goal_id, self._action.path, reason)
                return GoalResponse(goal_id=request.goal_id, accepted=False, reason=reason)
            cancel_requested, done = self._spare_events or _events()
            self._spare_events = None
            handle: GoalHandle[G, F] = GoalHandle(
                request.goal_id, request.goal, self._publish_feedback, cancel_requested=cancel_requested, done=done
            )
            self._goals[request.goal_id] = self._running[request.goal_id] = handle
        return GoalResponse(goal_id=request.goal_id, accepted=True)

    def _start(self, request: SendGoal[G], response: GoalResponse) -> None:
        """After the reply to send_goal: an accepted goal is set running (it announces itself)."""
        if not response.accepted:
            return
        with self._lock:
            handle = self._goals[request.goal_id]
        try:
            threading.Thread(target=self._run, args=(handle,), name=f"goal:{self._action.path}", daemon=True).start()
        except RuntimeError as exc:  # no thread to be had (a process's task limit): the goal must not stay running
            log.error("goal %s on %s could not start: %s", handle.goal_id, self._action.path, exc)
            self._end(handle, Outcome(GoalState.ABORTED, None, f"{self._action.path} could not start the goal: {exc}"))
        spare = _events()  # for the next goal (see __init__)
        with self._lock:
            self._spare_events = self._spare_events or spare

    def _blocking(self) -> list[GoalHandle[G, F]]:
        """The running goals that keep others out (not the concurrent ones). With the lock held."""
        if self._concurrent is None:
            return list(self._running.values())
        return [g for g in self._running.values() if not self._concurrent(g.goal)]

    def _preempt(self, goal_id: str) -> tuple[bool, str | None]:
        """Cancel every running goal for `goal_id` and wait for them to end: (whether there were any,
        the reason to reject the new goal if they do not end in time)."""
        with self._lock:
            running = self._blocking()
        for handle in running:
            handle.cancel_reason = f"preempted by goal {goal_id}"
            handle.cancel_requested.set()
            self._publish_canceling(handle, handle.cancel_reason)
        deadline = time.monotonic() + self._preempt_timeout
        for handle in running:
            if not handle.done.wait(max(0.0, deadline - time.monotonic())):
                return True, f"goal {handle.goal_id} did not stop within {self._preempt_timeout:g} s of being preempted"
        if running:
            log.info("goal %s preempted %s", goal_id, ", ".join(h.goal_id for h in running))
        return bool(running), None

    def _publish_feedback(self, goal_id: str, message: F) -> None:
        self._feedback.put(Feedback(goal_id=goal_id, feedback=message))

    def _publish_canceling(self, handle: GoalHandle[G, F], message: str = "") -> None:
        """Say a goal told to stop is canceling. The last status a goal publishes is its terminal one:
        a goal that ended while CANCELING went out has its end said again after it, and a goal not yet
        announced says CANCELING itself once it is (`_run`)."""
        if handle.done.is_set() or not handle.announced:
            return
        self._publish_status(handle.goal_id, GoalState.CANCELING, message)
        outcome = handle.outcome
        if handle.done.is_set() and outcome is not None:
            self._publish_status(handle.goal_id, outcome.state, outcome.message)

    def _run(self, handle: GoalHandle[G, F]) -> None:
        self._publish_status(handle.goal_id, GoalState.ACCEPTED)
        self._publish_status(handle.goal_id, GoalState.EXECUTING)
        handle.announced = True
        if handle.cancel_requested.is_set():  # canceled as it was accepted, before it was announced
            self._publish_status(handle.goal_id, GoalState.CANCELING, handle.cancel_reason)
        try:
            outcome: Outcome[Any] = self._execute(handle)
        except Exception as exc:
            log.exception("goal %s on %s failed", handle.goal_id, self._action.path)
            outcome = Outcome(GoalState.ABORTED, None, f"{self._action.path} failed: {exc}")
        if handle.abort_reason and outcome.state is not GoalState.SUCCEEDED:
            # A goal whose own words already give the reason (its result says it too) keeps them.
            why = outcome.message if handle.abort_reason in outcome.message else handle.abort_reason
            outcome = Outcome(GoalState.ABORTED, outcome.result, why)
        elif (
            handle.cancel_reason and outcome.state is GoalState.CANCELED and handle.cancel_reason not in outcome.message
        ):
            outcome = Outcome(outcome.state, outcome.result, f"{handle.cancel_reason}; {outcome.message}")
        self._end(handle, outcome)

    def _end(self, handle: GoalHandle[G, F], outcome: Outcome[Any]) -> None:
        """The goal ended as `outcome`: its result kept, it no longer keeps others out, its end said."""
        handle.outcome = outcome
        with self._lock:
            handle.finished_at = time.monotonic()
            handle.done.set()
            self._running.pop(handle.goal_id, None)
            self._ended.append((handle.finished_at, handle.goal_id))
        self._publish_status(handle.goal_id, outcome.state, outcome.message)

    def _on_cancel(self, request: CancelGoal) -> CancelResponse:
        if request.goal_id == CANCEL_ALL:
            running = self._sweep("every goal was canceled")
            for each in running:
                each.cancel_requested.set()
                self._publish_canceling(each)
            return CancelResponse(goal_id=request.goal_id, accepted=bool(running), reason=f"{len(running)} canceled")
        with self._lock:
            handle = self._goals.get(request.goal_id)
            if handle is None:
                self._canceled_early[request.goal_id] = None
                while len(self._canceled_early) > MAX_EARLY_CANCELS:
                    del self._canceled_early[next(iter(self._canceled_early))]
        if handle is None or handle.done.is_set():
            return CancelResponse(goal_id=request.goal_id, accepted=False, reason="no such running goal")
        handle.cancel_requested.set()
        self._publish_canceling(handle)
        return CancelResponse(goal_id=request.goal_id, accepted=True)

    def _on_get_result(self, request: GetResult) -> ResultResponse[R]:
        with self._lock:
            handle = self._goals.get(request.goal_id)
        if handle is None:
            raise CallError(ServiceError(kind=ErrorKind.INVALID_REQUEST, message=f"unknown goal {request.goal_id}"))
        handle.done.wait(MAX_RESULT_WAIT)
        outcome = handle.outcome or Outcome(GoalState.EXECUTING, None, "still running")
        return ResultResponse(
            goal_id=handle.goal_id, state=outcome.state, result=outcome.result, message=outcome.message
        )

    def _on_get_status(self, request: GetResult) -> GoalProgress[F, R]:
        with self._lock:
            handle = self._goals.get(request.goal_id)
        if handle is None:
            raise CallError(ServiceError(kind=ErrorKind.INVALID_REQUEST, message=f"unknown goal {request.goal_id}"))
        outcome = handle.outcome
        if outcome is None:
            state = GoalState.CANCELING if handle.cancel_requested.is_set() else GoalState.EXECUTING
            return GoalProgress(goal_id=handle.goal_id, state=state, feedback=handle.latest_feedback)
        return GoalProgress(
            goal_id=handle.goal_id,
            state=outcome.state,
            message=outcome.message,
            feedback=handle.latest_feedback,
            result=outcome.result,
        )

    def _forget_old(self) -> None:
        """Forget the goals that ended more than RESULT_RETENTION ago, and the oldest beyond MAX_RESULTS.
        With the lock held."""
        cutoff = time.monotonic() - RESULT_RETENTION
        ended = self._ended
        while ended and (ended[0][0] < cutoff or len(ended) > MAX_RESULTS):
            self._goals.pop(ended.popleft()[1], None)


class ClientGoal(Generic[G, F, R]):
    def __init__(self, client: ActionClient[G, F, R], goal_id: str) -> None:
        self._client = client
        self.goal_id = goal_id

    def result(self, timeout: float) -> ResultResponse[R]:
        """Wait for the goal to end; raises CallError if no result comes within `timeout`."""
        return self._client._node.call(
            self._client._action.get_result, GetResult(goal_id=self.goal_id), timeout=timeout
        )

    def result_future(self, timeout: float) -> Future[ResultResponse[R]]:
        """The result, fetched on a thread of its own; the future fails with CallError if none comes, or with
        whatever else ended the call (the node closed meanwhile)."""
        future: Future[ResultResponse[R]] = Future()

        def fetch() -> None:
            try:
                future.set_result(self.result(timeout))
            except Exception as exc:  # CallError, or the node closed under the call: the waiter learns which
                future.set_exception(exc)

        threading.Thread(target=fetch, name=f"result:{self.goal_id}", daemon=True).start()
        return future

    def cancel(self, timeout: float = 2.0) -> CancelResponse:
        return self._client._node.call(
            self._client._action.cancel_goal, CancelGoal(goal_id=self.goal_id), timeout=timeout
        )


class ActionClient(Generic[G, F, R]):
    """Sends goals on an action's keys; `on_feedback(goal_id, feedback)` hears every goal's feedback."""

    def __init__(
        self,
        node: Node,
        action: ActionKeys[G, F, R],
        on_feedback: Callable[[str, F], None] | None = None,
        *,
        cancel_grace: float = CANCEL_GRACE,
    ) -> None:
        self._node = node
        self._action = action
        self._cancel_grace = cancel_grace
        if on_feedback is not None:
            callback = on_feedback
            node.subscribe(action.feedback, lambda fb: callback(fb.goal_id, fb.feedback))

    def send(self, goal: G, *, timeout: float = 5.0, goal_id: str | None = None) -> ClientGoal[G, F, R]:
        """`goal_id` lets the caller know the id before the goal's first feedback (default: a new uuid)."""
        goal_id = goal_id or uuid.uuid4().hex
        response = self._node.call(self._action.send_goal, SendGoal(goal_id=goal_id, goal=goal), timeout=timeout)
        if not response.accepted:
            raise GoalRejected(response.reason, response.kind)
        return ClientGoal(self, goal_id)

    def run(self, goal: G, *, timeout: float, cancel: threading.Event | None = None) -> ResultResponse[R]:
        """Send `goal` and wait for its result; cancel it if `cancel` is set meanwhile. Already
        canceled, the goal is not sent at all: nothing may start moving after a cancel. CallError when
        the goal's end could not be learned but a cancel of it was answered; GoalNotStopped when it
        did not end within the grace of its cancel, or GoalUnanswered when no cancel was answered."""
        if cancel is not None and cancel.is_set():
            return ResultResponse(goal_id=UNSENT, state=GoalState.CANCELED, message="canceled before it was sent")
        goal_id = uuid.uuid4().hex
        try:
            handle = self.send(goal, goal_id=goal_id)
        except CallError as exc:
            # No answer, or an error instead of one: the goal may have been accepted all the same and
            # move the robot. Canceled by its id; a server still deciding on it rejects it then.
            self._give_up(ClientGoal(self, goal_id), "send_goal", exc)
        if cancel is None:
            try:
                return self._ended(handle, handle.result(timeout))
            except CallError as exc:
                self._give_up(handle, "get_result", exc)
        future = handle.result_future(timeout)
        canceled_at: float | None = None
        answered, asked = False, 0.0  # whether the server took a cancel of it, and when one was last sent
        # Two things to wait for: check the cancel flag between short waits for the result.
        while not futures.wait([future], CANCEL_POLL).done:
            if cancel.is_set() and canceled_at is None:
                canceled_at = asked = time.monotonic()
                answered = self._cancel_reached(handle, canceled_at + self._cancel_grace)
            elif canceled_at is not None and not answered and time.monotonic() - asked >= CANCEL_RESEND:
                # A cancel lost on the way, or the server too busy: asked again, within the grace.
                asked = time.monotonic()
                answered = self._cancel_reached(handle, canceled_at + self._cancel_grace)
            if canceled_at is not None and time.monotonic() - canceled_at > self._cancel_grace:
                unanswered = "" if answered else " (no cancel of it was answered)"
                message = (
                    f"{self._action.path} goal {handle.goal_id} did not end within {self._cancel_grace:g} s "
                    f"of its cancel{unanswered}"
                )
                raise GoalNotStopped(ServiceError(kind=ErrorKind.TIMEOUT, message=message))
        try:
            return self._ended(handle, future.result())
        except CallError as exc:
            # No result in time: the goal must not go on moving the robot behind our back.
            self._give_up(handle, "get_result", exc)

    def _ended(self, handle: ClientGoal[G, F, R], response: ResultResponse[R]) -> ResultResponse[R]:
        """`response` as this goal's end; CallError when it is not one (a peer answering with another
        goal's result, or with a state the goal goes on from): the goal may still be running."""
        if response.goal_id != handle.goal_id:
            message = f"{self._action.path} answered goal {handle.goal_id}'s result with goal {response.goal_id}'s"
        elif not response.state.terminal:
            message = f"{self._action.path} goal {handle.goal_id}'s result is no end: state {response.state}"
        else:
            return response
        raise CallError(ServiceError(kind=ErrorKind.INTERNAL, message=message))

    def _give_up(self, handle: ClientGoal[G, F, R], call: str, failure: CallError) -> NoReturn:
        """The goal's end cannot be learned (`call` failed with `failure`): cancel it, asking again every
        CANCEL_RESEND within the grace while no cancel reaches the server. Raises `failure` once one has;
        GoalUnanswered when none did: the goal may have been accepted and still be moving the robot."""
        deadline = time.monotonic() + self._cancel_grace
        while not self._cancel_reached(handle, deadline):
            left = deadline - time.monotonic()
            if left <= 0 or self._node.closed:  # a closed node reaches no one: no use waiting out the grace
                message = (
                    f"{self._action.path} goal {handle.goal_id}: its {call} failed ({failure.error.message}), "
                    f"and no cancel of it was answered within {self._cancel_grace:g} s"
                )
                raise GoalUnanswered(ServiceError(kind=ErrorKind.TIMEOUT, message=message)) from failure
            time.sleep(min(CANCEL_RESEND, left))
        raise failure

    @staticmethod
    def _cancel_reached(handle: ClientGoal[G, F, R], deadline: float) -> bool:
        """Ask the server to cancel, waiting until `deadline` at most; whether it answered the cancel of
        this goal. An answer that it knows no such running goal is an answer (it rejects the goal should
        it come yet); an error in its stead (no answer, too busy, a robot behind it that did not answer)
        is not: worth asking again."""
        try:
            response = handle.cancel(max(CANCEL_POLL, min(2.0, deadline - time.monotonic())))
        except CallError as exc:
            log.warning("cancel of %s failed: %s", handle.goal_id, exc)
            return False
        if response.goal_id != handle.goal_id:
            log.warning("cancel of %s was answered for goal %s", handle.goal_id, response.goal_id)
            return False
        return True
