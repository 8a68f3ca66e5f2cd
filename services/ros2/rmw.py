"""A ROS 2 node on a zenoh session speaking rmw_zenoh's protocol: topics, services and actions."""

from __future__ import annotations

import itertools
import logging
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh
import zenoh.ext

from services.ros2.types import RosDecodeError, RosTypes
from services.ros2.wire import (
    CANCEL_GOAL_TYPE,
    DEFAULT_QOS,
    GOAL_STATUS_ARRAY_TYPE,
    SERVICE_QOS,
    STATUS_QOS,
    Attachment,
    CancelReturn,
    Endpoint,
    EntityKind,
    GoalStatus,
    Naming,
    Qos,
    Style,
    entity_gid,
    liveliness_token,
    mangle,
)

log = logging.getLogger(__name__)

# Node and entity ids come from one counter, as rmw_zenoh's per-context get_next_entity_id().
_ids = itertools.count()
_ids_lock = threading.Lock()

ZERO_UUID = bytes(16)
ERROR_INTERVAL = 1.0  # seconds between two on_error reports about the same endpoint
KEEP_TERMINAL_GOALS = 64  # finished goals still listed in status and answered by get_result
# A goal whose send_goal got no usable answer is watched for this long (seconds) on the status topic:
# a server that takes it after all (a late answer, a lost one) has it canceled.
ABANDONED_WATCH = 60.0
LATE_CANCEL_TIMEOUT = 2.0
# The most a service request or reply or a sample may weigh (bytes), unless its subscription says
# otherwise: far more than any goal, goal status array, feedback or result. A peer sending more (anyone on the robot's
# network can) is dropped before it is decoded, which would cost far more memory and time than its bytes.
MAX_PAYLOAD = 1 << 20
# What a failed service call keeps of the peers' error replies, which anyone on the robot's network
# can send, as many as it likes until the call's timeout: this many, each cut to ERROR_TEXT_MAX
# characters (one over ERROR_REPLY_MAX bytes is not read), the rest counted.
MAX_CALL_ERRORS = 4
ERROR_REPLY_MAX = 4096
ERROR_TEXT_MAX = 300


def _next_id() -> int:
    with _ids_lock:
        return next(_ids)


class RosCallError(Exception):
    """A service or action call that got no usable answer: timeout, wrong type, undecodable reply."""


class RosGoalRejected(RosCallError):
    """The action server answered the goal with accepted = false."""


class RosNodeClosed(RosCallError):
    """A call on a node that was closed: nothing more goes to the robot from it."""


class RosGoalUnknown(RosCallError):
    """The action server answered get_result for a goal it took with status UNKNOWN: it knows no such
    goal now (it restarted, or forgot it), so it runs none."""


def _now_ns() -> int:
    return time.time_ns()


class _ErrorReporter:
    """on_error at most once per endpoint and kind of fault per ERROR_INTERVAL, counting what it held back."""

    def __init__(self, on_error: Callable[[str], None] | None) -> None:
        self._on_error = on_error
        self._last: dict[tuple[str, str], float] = {}
        self._held: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()

    def __call__(self, where: str, message: str, kind: str = "") -> None:
        now = time.monotonic()
        slot = (where, kind)
        with self._lock:
            last = self._last.get(slot)
            if last is not None and now - last < ERROR_INTERVAL:
                self._held[slot] = self._held.get(slot, 0) + 1
                return
            self._last[slot] = now
            held = self._held.pop(slot, 0)
        if held:
            message += f" ({held} more like it since the last report)"
        log.warning("%s", message)
        if self._on_error is not None:
            try:
                self._on_error(message)
            except Exception:
                log.exception("on_error callback failed")


class RosPublisher:
    """Publishes messages of one type on one topic, with rmw_zenoh's attachment."""

    def __init__(self, node: RosNode, endpoint: Endpoint, publisher: Any, gid: bytes) -> None:
        self.endpoint = endpoint
        self._node = node
        self._publisher = publisher
        self._gid = gid
        self._sequence = itertools.count(1)
        self._lock = threading.Lock()

    def put(self, message: object) -> None:
        data = self._node.types.encode(self.endpoint.ros_type, message)
        self.put_raw(data)

    def put_raw(self, data: bytes) -> None:
        """Publish CDR bytes as they are (for relays and tests). A no-op once the node is closed."""
        if self._node.closed:
            return
        if self._node.naming.style is Style.BRIDGE:
            self._publisher.put(data)
            return
        with self._lock:
            attachment = Attachment(next(self._sequence), _now_ns(), self._gid).encode()
            self._publisher.put(data, attachment=attachment)


class RosClient:
    """Calls one service: a zenoh query with the attachment, answered by one reply."""

    def __init__(self, node: RosNode, endpoint: Endpoint, gid: bytes) -> None:
        self.endpoint = endpoint
        self._node = node
        self._gid = gid
        self._sequence = itertools.count(1)
        self._lock = threading.Lock()

    def wait_for_service(self, timeout: float) -> bool:
        """Wait until a server advertises this service (any type: a wrong one shows in call's error)."""
        return self._node.wait_for(EntityKind.SERVICE, self.endpoint.name, timeout)

    @property
    def request_type(self) -> str:
        return f"{self.endpoint.ros_type}_Request"

    @property
    def response_type(self) -> str:
        return f"{self.endpoint.ros_type}_Response"

    def call(self, request: object, timeout: float) -> Any:
        """The service's response; RosCallError naming the service when there is none in `timeout` s."""
        name = self.endpoint.name
        if self._node.closed:
            raise RosNodeClosed(f"service {name}: the node is closed")
        payload = self._node.types.encode(self.request_type, request)
        with self._lock:
            sequence = next(self._sequence)
        # The node's token: closing it ends a call still waiting (a get_result waits as long as its goal runs).
        options: dict[str, Any] = {"payload": payload, "timeout": timeout, "cancellation_token": self._node.calls}
        if self._node.naming.style is Style.RMW_ZENOH:
            options["attachment"] = Attachment(sequence, _now_ns(), self._gid).encode()
            options["target"] = zenoh.QueryTarget.ALL_COMPLETE
            options["consolidation"] = zenoh.ConsolidationMode.NONE
        errors: list[str] = []
        more = 0  # errors past MAX_CALL_ERRORS, counted only

        def failed(text: str) -> None:
            nonlocal more
            if len(errors) < MAX_CALL_ERRORS:
                errors.append(text)
            else:
                more += 1

        started = time.monotonic()
        try:
            replies = self._node.session.get(self.endpoint.key, **options)
        except zenoh.ZError as exc:  # a closed session, for one
            raise RosCallError(f"service {name}: cannot send the request: {exc}") from exc
        for reply in replies:
            if reply.ok is None:
                text = _error_text(reply.err)
                if text == "Timeout" and time.monotonic() - started >= timeout * 0.9:
                    continue  # zenoh's own error reply for a server that did not answer in time
                failed(text)
                continue
            sample = reply.ok
            if (size := len(sample.payload)) > MAX_PAYLOAD:
                failed(f"a response of {size} bytes, over the {MAX_PAYLOAD} it may take: dropped unread")
                continue
            if self._node.naming.style is Style.RMW_ZENOH:
                problem = self._check_reply_attachment(sample, sequence)
                if problem:
                    failed(problem)
                    continue
            try:
                return self._node.types.decode(self.response_type, sample.payload.to_bytes())
            except RosDecodeError as exc:
                failed(f"undecodable response: {_cut(str(exc))}")
        if self._node.closed:
            raise RosNodeClosed(f"service {name}: the node was closed")
        if errors:
            also = f" (and {more} more failed replies)" if more else ""
            raise RosCallError(f"service {name} ({self.endpoint.ros_type}) failed: {'; '.join(errors)}{also}")
        other = self._node.served_elsewhere(name, EntityKind.SERVICE, self.endpoint)
        if other:
            raise RosCallError(
                f"service {name}: no answer within {timeout:g} s; it is served with another type or hash "
                f"({other}), expected {self.endpoint.ros_type} {self.endpoint.type_hash}"
            )
        raise RosCallError(f"service {name} ({self.endpoint.ros_type}): no answer within {timeout:g} s")

    def _check_reply_attachment(self, sample: zenoh.Sample, sequence: int) -> str:
        if sample.attachment is None:
            return "reply without rmw_zenoh attachment"
        try:
            attachment = Attachment.decode(sample.attachment.to_bytes())
        except ValueError as exc:
            return f"reply with malformed attachment: {exc}"
        if attachment.sequence_number != sequence:
            return f"reply for request {attachment.sequence_number}, expected {sequence}"
        return ""


def _cut(text: str) -> str:
    return text if len(text) <= ERROR_TEXT_MAX else f"{text[:ERROR_TEXT_MAX]}... [{len(text)} characters in all]"


def _error_text(err: zenoh.ReplyError | None) -> str:
    """An error reply's text, cut; one too heavy to read is named by its size."""
    if err is None:
        return "?"
    if (size := len(err.payload)) > ERROR_REPLY_MAX:
        return f"an error reply of {size} bytes, over the {ERROR_REPLY_MAX} it may take: dropped unread"
    return _cut(err.payload.to_bytes().decode("utf-8", "replace"))


@dataclass
class _Request:
    """A service request being answered: the query, and what the reply's attachment echoes."""

    server: _Server
    query: zenoh.Query
    sequence: int
    client_gid: bytes
    done: bool = False

    def respond(self, response: object) -> None:
        self.server.respond(self, response)

    def fail(self, message: str) -> None:
        self.server.fail(self, message)

    def finish(self) -> None:
        """Drop the query, which tells the client no more replies come; once."""
        if self.done:
            return
        self.done = True
        try:
            self.query.drop()
        except Exception:
            log.debug("dropping a query failed", exc_info=True)


class _Server:
    """One service's queryable; answers on a worker thread; refuses wrong types, hashes and bytes."""

    def __init__(self, node: RosNode, endpoint: Endpoint, on_request: Callable[[Any, _Request], None]) -> None:
        self.node = node
        self.endpoint = endpoint
        self._on_request = on_request
        naming = node.naming
        if naming.style is Style.RMW_ZENOH:
            # A wildcard on type and hash, so a request with another hash is answered with an error
            # instead of silence; complete=True since rmw_zenoh clients target ALL_COMPLETE.
            prefix = endpoint.key.rsplit("/", 2)[0]
            key = f"{prefix}/*/*"
        else:
            key = endpoint.key
        self.queryable = node.session.declare_queryable(key, self._on_query, complete=True)

    def _on_query(self, query: zenoh.Query) -> None:
        threading.Thread(target=self._answer, args=(query,), name=f"srv:{self.endpoint.name}", daemon=True).start()

    def _answer(self, query: zenoh.Query) -> None:
        where = self.endpoint.name
        pending = _Request(self, query, 0, bytes(16))
        try:
            problem, kind = "", ""
            sequence, gid = 0, bytes(16)
            if self.node.naming.style is Style.RMW_ZENOH:
                problem, kind = self.node.check_key(str(query.key_expr), self.endpoint, "request"), "type"
                if not problem:
                    kind = "attachment"
                    if query.attachment is None:
                        problem = f"request on service {where} without rmw_zenoh attachment"
                    else:
                        try:
                            attachment = Attachment.decode(query.attachment.to_bytes())
                            sequence, gid = attachment.sequence_number, attachment.gid
                        except ValueError as exc:
                            problem = f"request on service {where} with malformed attachment: {exc}"
            request = None
            if not problem and query.payload is not None and (size := len(query.payload)) > MAX_PAYLOAD:
                problem, kind = (
                    f"request on service {where} of {size} bytes, over the {MAX_PAYLOAD} it may take",
                    "size",
                )
            if not problem:
                raw = query.payload.to_bytes() if query.payload is not None else b""
                try:
                    request = self.node.types.decode(f"{self.endpoint.ros_type}_Request", raw)
                except RosDecodeError as exc:
                    problem, kind = f"undecodable request on service {where}: {exc}", "cdr"
            if problem:
                self.node.report(where, problem, kind)
                self.fail(pending, problem)
                return
            pending = _Request(self, query, sequence, gid)
            self._on_request(request, pending)  # answers now, or keeps the request to answer later
        except Exception as exc:
            log.exception("service %s failed", where)
            self.fail(pending, f"service {where} failed: {exc}")  # a no-op if it was answered

    def respond(self, request: _Request, response: object) -> None:
        """Reply to a kept request; the attachment echoes its sequence number and the client's GID."""
        if self.node.closed or request.done:
            request.finish()
            return
        try:
            data = self.node.types.encode(f"{self.endpoint.ros_type}_Response", response)
            if self.node.naming.style is Style.RMW_ZENOH:
                attachment = Attachment(request.sequence, _now_ns(), request.client_gid).encode()
                request.query.reply(request.query.key_expr, data, attachment=attachment)
            else:
                request.query.reply(request.query.key_expr, data)
        except Exception as exc:
            log.exception("reply on service %s failed", self.endpoint.name)
            self.fail(request, f"service {self.endpoint.name} failed: {exc}")
        finally:
            request.finish()

    def fail(self, request: _Request, message: str) -> None:
        """Answer with an error, unless the request was answered already."""
        if request.done:
            return
        try:
            if not self.node.closed:
                request.query.reply_err(message.encode())
        except Exception:
            log.debug("error reply on service %s failed", self.endpoint.name, exc_info=True)
        finally:
            request.finish()


# ---------------------------------------------------------------------------------------------------
# Actions: the server side


class RosServerGoal:
    """One goal on an action server, handed to `execute` on its own thread."""

    def __init__(self, server: RosActionServer, goal_id: bytes, goal: Any, stamp_ns: int) -> None:
        self.goal_id = goal_id
        self.goal = goal
        self.stamp_ns = stamp_ns
        self.cancel_requested = threading.Event()
        self.status = GoalStatus.ACCEPTED
        self.result: Any = None
        self._server = server
        self._waiting: list[_Request] = []

    def publish_feedback(self, feedback: object) -> None:
        self._server._publish_feedback(self, feedback)

    def succeed(self, result: object) -> bool:
        return self._server._finish(self, GoalStatus.SUCCEEDED, result)

    def abort(self, result: object) -> bool:
        return self._server._finish(self, GoalStatus.ABORTED, result)

    def canceled(self, result: object) -> bool:
        return self._server._finish(self, GoalStatus.CANCELED, result)

    @property
    def active(self) -> bool:
        return not self.status.terminal


class RosActionServer:
    """rcl_action's server: send_goal, cancel_goal, get_result services, feedback and status topics."""

    def __init__(
        self,
        node: RosNode,
        name: str,
        action_type: str,
        accept: Callable[[Any], bool],
        execute: Callable[[RosServerGoal], None],
    ) -> None:
        self.node = node
        self.action_type = action_type
        self.keys = node.naming.action(name, action_type, node.types)
        self.name = node.naming.qualify(name)
        self._accept = accept
        self._execute = execute
        self._goals: dict[bytes, RosServerGoal] = {}
        self._lock = threading.RLock()
        self._feedback = node._publisher(self.keys.feedback, DEFAULT_QOS)
        self._status = node._publisher(self.keys.status, STATUS_QOS)
        node._server(self.keys.cancel_goal, self._on_cancel_goal)
        node._server(self.keys.get_result, self._on_get_result)
        # Last, so a client that sees send_goal's token (wait_for_server) finds everything else routed.
        node._server(self.keys.send_goal, self._on_send_goal)

    @property
    def goals(self) -> list[RosServerGoal]:
        with self._lock:
            return list(self._goals.values())

    def _type(self, suffix: str) -> str:
        return f"{self.action_type}_{suffix}"

    def _on_send_goal(self, request: Any, pending: _Request) -> None:
        goal_id = bytes(request.goal_id.uuid)
        types = self.node.types
        with self._lock:
            duplicate = goal_id in self._goals
        accepted = False
        if duplicate:
            self.node.report(self.name, f"action {self.name}: goal id {goal_id.hex()} already used; rejected", "goal")
        else:
            try:
                accepted = bool(self._accept(request.goal))
            except Exception:
                log.exception("accept callback of action %s failed; goal rejected", self.name)
        stamp = _now_ns()
        response = types.new(self._type("SendGoal_Response"), accepted=accepted, stamp=_time(types, stamp))
        if not accepted:
            pending.respond(response)
            return
        goal = RosServerGoal(self, goal_id, request.goal, stamp)
        with self._lock:
            self._goals[goal_id] = goal
            self._forget_old_goals()
        pending.respond(response)
        self._publish_status()
        threading.Thread(target=self._run, args=(goal,), name=f"goal:{self.name}", daemon=True).start()

    def _run(self, goal: RosServerGoal) -> None:
        with self._lock:
            if goal.status is GoalStatus.ACCEPTED:
                goal.status = GoalStatus.EXECUTING
        self._publish_status()
        try:
            self._execute(goal)
        except Exception as exc:
            log.exception("execute of action %s failed", self.name)
            if goal.active:
                self.node.report(self.name, f"action {self.name}: execute failed: {exc}; goal aborted", "execute")
        if goal.active:
            log.error("action %s: execute returned without a result; goal aborted", self.name)
            goal.abort(self.node.types.new(self._type("Result")))

    def _finish(self, goal: RosServerGoal, status: GoalStatus, result: object) -> bool:
        with self._lock:
            if goal.status.terminal:
                return False
            goal.status = status
            goal.result = result
            waiting, goal._waiting = goal._waiting, []
        self._publish_status()
        for pending in waiting:
            self._answer_result(pending, goal.status, result)
        return True

    def _answer_result(self, pending: _Request, status: GoalStatus, result: object) -> None:
        response = self.node.types.new(self._type("GetResult_Response"), status=int(status), result=result)
        pending.respond(response)

    def _on_get_result(self, request: Any, pending: _Request) -> None:
        goal_id = bytes(request.goal_id.uuid)
        with self._lock:
            goal = self._goals.get(goal_id)
            if goal is not None and not goal.status.terminal:
                goal._waiting.append(pending)  # answered when the goal ends
                return
        if goal is None:
            self._answer_result(pending, GoalStatus.UNKNOWN, self.node.types.new(self._type("Result")))
        else:
            self._answer_result(pending, goal.status, goal.result)

    def _on_cancel_goal(self, request: Any, pending: _Request) -> None:
        types = self.node.types
        goal_id = bytes(request.goal_info.goal_id.uuid)
        stamp = request.goal_info.stamp
        stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
        canceling: list[RosServerGoal] = []
        code = CancelReturn.ERROR_NONE
        with self._lock:
            chosen: list[RosServerGoal] = []
            if goal_id != ZERO_UUID:
                goal = self._goals.get(goal_id)
                if goal is None:
                    code = CancelReturn.ERROR_UNKNOWN_GOAL_ID
                elif goal.status.terminal or goal.status is GoalStatus.CANCELING:
                    # As rcl_action: a goal being canceled is no longer cancelable, which it answers
                    # so, as for one that ended (a client must wait for its result).
                    code = CancelReturn.ERROR_GOAL_TERMINATED
                else:
                    chosen.append(goal)
            if goal_id == ZERO_UUID and stamp_ns == 0:
                chosen = list(self._goals.values())
            elif stamp_ns != 0:
                chosen += [g for g in self._goals.values() if g.stamp_ns <= stamp_ns and g not in chosen]
            for goal in chosen:
                if goal.status in (GoalStatus.ACCEPTED, GoalStatus.EXECUTING):
                    goal.status = GoalStatus.CANCELING
                    canceling.append(goal)
            if not canceling and code is CancelReturn.ERROR_NONE:
                code = CancelReturn.ERROR_REJECTED
            elif canceling:
                code = CancelReturn.ERROR_NONE
        for goal in canceling:
            goal.cancel_requested.set()
        infos = [
            types.new(
                "action_msgs/msg/GoalInfo",
                goal_id=_uuid(types, goal.goal_id),
                stamp=_time(types, goal.stamp_ns),
            )
            for goal in canceling
        ]
        response = types.new(f"{CANCEL_GOAL_TYPE}_Response", return_code=int(code), goals_canceling=infos)
        pending.respond(response)
        if canceling:
            self._publish_status()

    def _publish_feedback(self, goal: RosServerGoal, feedback: object) -> None:
        types = self.node.types
        message = types.new(self._type("FeedbackMessage"), goal_id=_uuid(types, goal.goal_id), feedback=feedback)
        self._feedback.put(message)

    def _publish_status(self) -> None:
        types = self.node.types
        with self._lock:
            statuses = [
                types.new(
                    "action_msgs/msg/GoalStatus",
                    goal_info=types.new(
                        "action_msgs/msg/GoalInfo",
                        goal_id=_uuid(types, goal.goal_id),
                        stamp=_time(types, goal.stamp_ns),
                    ),
                    status=int(goal.status),
                )
                for goal in self._goals.values()
            ]
            self._status.put(types.new(GOAL_STATUS_ARRAY_TYPE, status_list=statuses))

    def _forget_old_goals(self) -> None:
        finished = [gid for gid, goal in self._goals.items() if goal.status.terminal]
        for gid in finished[: max(0, len(finished) - KEEP_TERMINAL_GOALS)]:
            del self._goals[gid]


# ---------------------------------------------------------------------------------------------------
# Actions: the client side


class RosClientGoal:
    """A goal this client sent: its id, latest status, result and cancel."""

    def __init__(self, client: RosActionClient, goal_id: bytes, stamp_ns: int) -> None:
        self.goal_id = goal_id
        self.stamp_ns = stamp_ns
        self.status = GoalStatus.ACCEPTED
        self._client = client
        self._result: tuple[int, Any] | None = None
        self.changed = threading.Condition()

    def result(self, timeout: float) -> tuple[int, Any]:
        """(GoalStatus code, result) once the goal ends; RosCallError if it has not ended in `timeout` s."""
        if self._result is None:
            types = self._client.node.types
            request = types.new(self._client._type("GetResult_Request"), goal_id=_uuid(types, self.goal_id))
            response = self._client._get_result.call(request, timeout)
            code = int(response.status)
            if code == GoalStatus.UNKNOWN:
                raise RosGoalUnknown(
                    f"action {self._client.name}: get_result answered status UNKNOWN for goal {self.goal_id.hex()}, "
                    "which is not a final one: its server knows no such goal now (it restarted, or forgot it)"
                )
            if code not in (GoalStatus.SUCCEEDED, GoalStatus.CANCELED, GoalStatus.ABORTED):
                raise RosCallError(
                    f"action {self._client.name}: get_result answered status {code} "
                    f"for goal {self.goal_id.hex()}, which is not a final one (unknown goal?)"
                )
            self._result = (code, response.result)
            self._set_status(GoalStatus(code))
        return self._result

    def cancel(self, timeout: float) -> bool:
        """Ask the server to cancel this goal; True when it accepted (the goal is then CANCELING)."""
        return self.request_cancel(timeout) is CancelReturn.ERROR_NONE

    def request_cancel(self, timeout: float) -> CancelReturn:
        """Ask the server to cancel this goal; its answer: ERROR_NONE when it is canceling it,
        ERROR_GOAL_TERMINATED when the goal had ended already, or (rcl_action's way) was being canceled
        already (the server's own word, where its status topic is anyone's), else why not."""
        response = self._client._cancel(self.goal_id, 0, timeout)
        code = int(response.return_code)
        if code == CancelReturn.ERROR_NONE:
            listed = any(bytes(info.goal_id.uuid) == self.goal_id for info in response.goals_canceling)
            return CancelReturn.ERROR_NONE if listed else CancelReturn.ERROR_REJECTED
        if code in CancelReturn._value2member_map_:
            return CancelReturn(code)
        return CancelReturn.ERROR_REJECTED

    def wait_status(self, predicate: Callable[[GoalStatus], bool], timeout: float) -> bool:
        """Wait until the latest status satisfies predicate (from the status topic); False on timeout."""
        with self.changed:
            return self.changed.wait_for(lambda: predicate(self.status), timeout)

    def _set_status(self, status: GoalStatus) -> None:
        with self.changed:
            if self.status.terminal and not status.terminal:
                return  # a late status message never takes back an end
            self.status = status
            self.changed.notify_all()


class RosActionClient:
    """rcl_action's client: goal, feedback, status, result and cancel for one action."""

    def __init__(self, node: RosNode, name: str, action_type: str) -> None:
        self.node = node
        self.action_type = action_type
        self.name = node.naming.qualify(name)
        self.keys = node.naming.action(name, action_type, node.types)
        self._goals: dict[bytes, RosClientGoal] = {}
        self._feedback_callbacks: dict[bytes, Callable[[Any], None]] = {}
        self._abandoned: dict[bytes, float] = {}  # goal id -> when its send_goal failed (monotonic)
        # Goals whose send_goal is under way -> the latest status heard for them meanwhile (or None): the
        # server publishes EXECUTING as it starts the goal, which may be before the answer is read here,
        # and says nothing more until the goal ends.
        self._sending: dict[bytes, GoalStatus | None] = {}
        self._lock = threading.Lock()
        self._send_goal = node._client(self.keys.send_goal)
        self._cancel_goal = node._client(self.keys.cancel_goal)
        self._get_result = node._client(self.keys.get_result)
        node._subscribe(self.keys.feedback, self._on_feedback, DEFAULT_QOS)
        node._subscribe(self.keys.status, self._on_status, STATUS_QOS)

    def _type(self, suffix: str) -> str:
        return f"{self.action_type}_{suffix}"

    def wait_for_server(self, timeout: float) -> bool:
        """Wait until an action server advertises this action's send_goal service."""
        return self.node.wait_for(EntityKind.SERVICE, self.keys.send_goal.name, timeout)

    def send_goal(
        self,
        goal: object,
        *,
        feedback: Callable[[Any], None] | None = None,
        timeout: float,
        goal_id: bytes | None = None,
    ) -> RosClientGoal:
        """Send a goal (as `goal_id`, else a new one); the accepted goal, or RosGoalRejected / RosCallError."""
        types = self.node.types
        if goal_id is None:
            goal_id = uuid.uuid4().bytes
        elif len(goal_id) != 16:
            raise ValueError(f"a goal id is 16 bytes, not {len(goal_id)}")
        with self._lock:
            if feedback is not None:
                self._feedback_callbacks[goal_id] = feedback
            self._sending[goal_id] = None
        request = types.new(self._type("SendGoal_Request"), goal_id=_uuid(types, goal_id), goal=goal)
        try:
            response = self._send_goal.call(request, timeout)
        except RosCallError:
            self._forget(goal_id)
            self._abandon(goal_id)
            raise
        if not response.accepted:
            self._forget(goal_id)
            raise RosGoalRejected(f"action {self.name}: goal rejected by the server")
        stamp = int(response.stamp.sec) * 1_000_000_000 + int(response.stamp.nanosec)
        handle = RosClientGoal(self, goal_id, stamp)
        with self._lock:
            heard = self._sending.pop(goal_id, None)
            if heard is not None:  # before anyone else sees the handle: a later status always comes after it
                handle._set_status(heard)
            self._goals[goal_id] = handle
        return handle

    def cancel_all(self, timeout: float) -> list[bytes]:
        """Cancel every goal on the server (zero goal id and stamp); the ids now canceling."""
        response = self._cancel(ZERO_UUID, 0, timeout)
        return [bytes(info.goal_id.uuid) for info in response.goals_canceling]

    def cancel_goal(self, goal_id: bytes, timeout: float) -> bool:
        """Cancel the goal of this id (also one whose send_goal went unanswered); True when the server
        is canceling it or it had ended, False when the server knows no such goal or refused."""
        response = self._cancel(goal_id, 0, timeout)
        code = int(response.return_code)
        if code == CancelReturn.ERROR_GOAL_TERMINATED:
            return True
        return code == CancelReturn.ERROR_NONE and any(
            bytes(info.goal_id.uuid) == goal_id for info in response.goals_canceling
        )

    def _cancel(self, goal_id: bytes, stamp_ns: int, timeout: float) -> Any:
        types = self.node.types
        info = types.new("action_msgs/msg/GoalInfo", goal_id=_uuid(types, goal_id), stamp=_time(types, stamp_ns))
        return self._cancel_goal.call(types.new(f"{CANCEL_GOAL_TYPE}_Request", goal_info=info), timeout)

    def forget(self, goal: RosClientGoal) -> None:
        """Stop following a goal (feedback and status) once its result is in."""
        self._forget(goal.goal_id)

    def _forget(self, goal_id: bytes) -> None:
        with self._lock:
            self._feedback_callbacks.pop(goal_id, None)
            self._goals.pop(goal_id, None)
            self._sending.pop(goal_id, None)

    def _on_feedback(self, message: Any) -> None:
        goal_id = bytes(message.goal_id.uuid)
        with self._lock:
            callback = self._feedback_callbacks.get(goal_id)
        if callback is not None:
            callback(message.feedback)

    def _abandon(self, goal_id: bytes) -> None:
        """A goal whose send_goal got no usable answer, which the server may take all the same."""
        now = time.monotonic()
        with self._lock:
            self._abandoned = {g: at for g, at in self._abandoned.items() if now - at < ABANDONED_WATCH}
            self._abandoned[goal_id] = now

    def _cancel_late(self, goal_id: bytes) -> None:
        """Cancel a goal the server took after its send_goal went unanswered: nothing follows it here."""
        what = f"action {self.name}: the server took goal {goal_id.hex()} after its send_goal went unanswered"
        try:
            self._cancel(goal_id, 0, LATE_CANCEL_TIMEOUT)
        except RosCallError as exc:
            self._abandon(goal_id)  # tried again at its next status
            self.node.report(self.name, f"{what}; its cancel failed: {exc}", "late goal")
            return
        self.node.report(self.name, f"{what}; canceled it", "late goal")

    def _on_status(self, message: Any) -> None:
        for status in message.status_list:
            goal_id = bytes(status.goal_info.goal_id.uuid)
            code = int(status.status)
            known = code in GoalStatus._value2member_map_
            with self._lock:  # with send_goal's hand-over from _sending to _goals: no status falls between
                goal = self._goals.get(goal_id)
                sending = goal is None and goal_id in self._sending
                if sending and known:
                    self._sending[goal_id] = GoalStatus(code)
            if sending:
                continue
            if goal is not None and known:
                goal._set_status(GoalStatus(code))
            elif goal is None and code in (GoalStatus.ACCEPTED, GoalStatus.EXECUTING):
                with self._lock:
                    late = self._abandoned.pop(goal_id, None) is not None
                if late:
                    threading.Thread(target=self._cancel_late, args=(goal_id,), name="late-goal", daemon=True).start()


# ---------------------------------------------------------------------------------------------------
# The node


class RosNode:
    """One ROS 2 node on a zenoh session: its liveliness token and those of each endpoint it declares.

    Samples and requests with another type hash, a missing or malformed attachment, or undecodable
    CDR, and samples, requests and replies over their size (MAX_PAYLOAD, or the subscription's), are never
    delivered: on_error gets a sentence naming the endpoint and what was wrong (at most once per
    endpoint and kind per second, counting the rest). Callbacks run on zenoh's threads; service
    handlers and action `execute` on threads of their own.
    """

    def __init__(
        self,
        session: zenoh.Session,
        types: RosTypes,
        naming: Naming,
        name: str,
        *,
        on_error: Callable[[str], None] | None = None,
        enclave: str = "/",
    ) -> None:
        self.session = session
        self.types = types
        self.naming = naming
        self.name = name
        self.namespace = "/" + naming.namespace.strip("/") if naming.namespace.strip("/") else "/"
        self.enclave = enclave
        self.report = _ErrorReporter(on_error)
        self.zid = str(session.info.zid())
        self.node_id = _next_id()
        self._declared: list[Any] = []
        self._action_servers: list[RosActionServer] = []
        self.calls = zenoh.CancellationToken()  # every service call's: canceled on close
        self._closed = False
        self._lock = threading.Lock()
        self._declare_token(self._token_key(EntityKind.NODE, self.node_id))

    # -- liveliness and ids

    def _token_key(
        self, kind: EntityKind, entity_id: int, endpoint: Endpoint | None = None, qos: Qos = DEFAULT_QOS
    ) -> str:
        return liveliness_token(
            kind,
            domain_id=self.naming.domain_id,
            zid=self.zid,
            node_id=self.node_id,
            entity_id=entity_id,
            node_name=self.name,
            namespace=self.namespace,
            enclave=self.enclave,
            name=endpoint.name if endpoint else None,
            ros_type=endpoint.ros_type if endpoint else None,
            type_hash=endpoint.type_hash if endpoint else None,
            qos=qos,
        )

    def _declare_token(self, key: str) -> None:
        """Declared after its entity, so a peer that sees the token also routes to the entity."""
        if self.naming.style is Style.RMW_ZENOH:
            self._declared.append(self.session.liveliness().declare_token(key))

    def wait_for(self, kind: EntityKind, name: str, timeout: float) -> bool:
        """Wait until some node advertises `name` (e.g. "/cmd_vel") as kind; False after timeout.

        In bridge style there are no rmw_zenoh tokens to wait on, so this returns True at once.
        """
        if self.naming.style is not Style.RMW_ZENOH:
            return True
        found = threading.Event()
        selector = f"@ros2_lv/{self.naming.domain_id}/*/*/*/{kind.value}/*/*/*/{mangle(self.naming.qualify(name))}/**"
        subscriber = self.session.liveliness().declare_subscriber(
            selector, lambda sample: found.set() if sample.kind == zenoh.SampleKind.PUT else None, history=True
        )
        try:
            return found.wait(timeout)
        finally:
            subscriber.undeclare()

    def served_elsewhere(self, name: str, kind: EntityKind, endpoint: Endpoint) -> str:
        """Types and hashes other nodes advertise for `name` as `kind`, other than ours ('' if none)."""
        if self.naming.style is not Style.RMW_ZENOH:
            return ""
        found: set[str] = set()
        selector = f"@ros2_lv/{self.naming.domain_id}/*/*/*/{kind.value}/*/*/*/{mangle(name)}/*/*/*"
        try:
            for reply in self.session.liveliness().get(selector, timeout=0.5):
                if reply.ok is None:
                    continue
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) >= 13:
                    dds, digest = parts[10].replace("%", "/"), parts[11]
                    if digest != endpoint.type_hash:
                        found.add(f"{dds} {digest}")
        except Exception:
            log.debug("liveliness query for %s failed", name, exc_info=True)
        return ", ".join(sorted(found))

    def check_key(self, key: str, endpoint: Endpoint, what: str) -> str:
        """'' when key is endpoint's exact key, else a sentence saying what differs."""
        if key == endpoint.key:
            return ""
        parsed = self.naming.parse(key)
        if parsed is None:
            return f"{what} on {endpoint.name} with a key that is not rmw_zenoh's: {key}"
        _, ros_type, type_hash = parsed
        if ros_type != endpoint.ros_type:
            return f"{what} on {endpoint.name} has type {ros_type} ({type_hash}), expected {endpoint.ros_type}"
        return (
            f"{what} on {endpoint.name} has type hash {type_hash}, expected {endpoint.type_hash} "
            f"for {endpoint.ros_type} ({self.types.distro}): the two sides use different definitions"
        )

    # -- low level, shared by topics, services and actions

    def _publisher(self, endpoint: Endpoint, qos: Qos) -> RosPublisher:
        token = self._token_key(EntityKind.PUBLISHER, _next_id(), endpoint, qos)
        reliability = zenoh.Reliability.RELIABLE if qos.reliable else zenoh.Reliability.BEST_EFFORT
        publisher: Any
        if qos.transient_local and self.naming.style is Style.RMW_ZENOH:
            # As rmw_zenoh: a cache of `depth` samples late-joining transient-local subscribers query,
            # publisher detection, and for reliable ones sporadic heartbeats (last-sample recovery).
            publisher = zenoh.ext.declare_advanced_publisher(
                self.session,
                endpoint.key,
                reliability=reliability,
                cache=zenoh.ext.CacheConfig(max_samples=max(1, qos.depth)),
                publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5)
                if qos.reliable
                else None,
            )
        else:
            publisher = self.session.declare_publisher(endpoint.key, reliability=reliability)
        self._declared.append(publisher)
        self._declare_token(token)
        return RosPublisher(self, endpoint, publisher, entity_gid(token))

    def _subscribe(
        self, endpoint: Endpoint, callback: Callable[[Any], None], qos: Qos, max_bytes: int = MAX_PAYLOAD
    ) -> None:
        token = self._token_key(EntityKind.SUBSCRIPTION, _next_id(), endpoint, qos)
        rmw = self.naming.style is Style.RMW_ZENOH
        key = endpoint.key.rsplit("/", 2)[0] + "/*/*" if rmw else endpoint.key
        where = endpoint.name

        def on_sample(sample: zenoh.Sample) -> None:
            if rmw:
                problem, kind = self.check_key(str(sample.key_expr), endpoint, "sample"), "type"
                if not problem:
                    kind = "attachment"
                    if sample.attachment is None:
                        problem = f"sample on {where} without rmw_zenoh attachment"
                    else:
                        try:
                            Attachment.decode(sample.attachment.to_bytes())
                        except ValueError as exc:
                            problem = f"sample on {where} with malformed attachment: {exc}"
                if problem:
                    self.report(where, problem, kind)
                    return
            if (size := len(sample.payload)) > max_bytes:
                self.report(
                    where,
                    f"sample on {where} of {size} bytes, over the {max_bytes} a {endpoint.ros_type} may take here: "
                    "dropped unread",
                    "size",
                )
                return
            try:
                message = self.types.decode(endpoint.ros_type, sample.payload.to_bytes())
            except RosDecodeError as exc:
                self.report(where, f"undecodable sample on {where}: {exc}", "cdr")
                return
            try:
                callback(message)
            except Exception:
                log.exception("subscriber callback for %s failed", where)

        self._declared.append(self.session.declare_subscriber(key, on_sample))
        self._declare_token(token)

    def _server(self, endpoint: Endpoint, on_request: Callable[[Any, _Request], None]) -> _Server:
        token = self._token_key(EntityKind.SERVICE, _next_id(), endpoint, SERVICE_QOS)
        server = _Server(self, endpoint, on_request)
        self._declared.append(server.queryable)
        self._declare_token(token)
        return server

    def _client(self, endpoint: Endpoint) -> RosClient:
        token = self._token_key(EntityKind.CLIENT, _next_id(), endpoint, SERVICE_QOS)
        self._declare_token(token)
        return RosClient(self, endpoint, entity_gid(token))

    # -- the API

    def publisher(self, topic: str, ros_type: str, *, qos: Qos = DEFAULT_QOS) -> RosPublisher:
        return self._publisher(self.naming.endpoint(topic, ros_type, self.types), qos)

    def subscribe(
        self,
        topic: str,
        ros_type: str,
        callback: Callable[[Any], None],
        *,
        qos: Qos = DEFAULT_QOS,
        max_bytes: int = MAX_PAYLOAD,
    ) -> None:
        """Deliver the topic's messages to `callback`; a sample over `max_bytes` is dropped unread (on_error)."""
        self._subscribe(self.naming.endpoint(topic, ros_type, self.types), callback, qos, max_bytes)

    def serve(self, service: str, srv_type: str, handler: Callable[[Any], Any]) -> None:
        """Answer a service: handler(request) -> response, on a thread per request."""
        endpoint = self.naming.endpoint(service, srv_type, self.types)

        def on_request(request: Any, pending: _Request) -> None:
            try:
                response = handler(request)
            except Exception as exc:
                log.exception("handler of service %s failed", endpoint.name)
                pending.fail(f"service {endpoint.name} failed: {exc}")
                return
            pending.respond(response)

        self._server(endpoint, on_request)

    def client(self, service: str, srv_type: str) -> RosClient:
        return self._client(self.naming.endpoint(service, srv_type, self.types))

    def action_server(
        self,
        name: str,
        action_type: str,
        *,
        accept: Callable[[Any], bool],
        execute: Callable[[RosServerGoal], None],
    ) -> RosActionServer:
        server = RosActionServer(self, name, action_type, accept, execute)
        self._action_servers.append(server)
        return server

    def action_client(self, name: str, action_type: str) -> RosActionClient:
        return RosActionClient(self, name, action_type)

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Undeclare every token, publisher, subscriber and queryable (the session stays open).

        Goals still executing see their cancel_requested set; what they publish afterwards is dropped.
        Service calls still waiting end, and later ones fail at once (RosNodeClosed): nothing more goes out.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            declared, self._declared = self._declared, []
        self.calls.cancel()
        for server in self._action_servers:
            for goal in server.goals:
                goal.cancel_requested.set()
        for entity in reversed(declared):
            try:
                entity.undeclare()
            except Exception:
                log.debug("undeclare failed", exc_info=True)

    def __enter__(self) -> RosNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _uuid(types: RosTypes, goal_id: bytes) -> Any:
    import numpy as np

    return types.new("unique_identifier_msgs/msg/UUID", uuid=np.frombuffer(goal_id, dtype=np.uint8).copy())


def _time(types: RosTypes, ns: int) -> Any:
    return types.new("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
