"""Safety's transport: keys to the gate and its rulings onto the wire; the only writer of robot/**."""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, Feedback, GetResult, GoalResponse, GoalStatus, SendGoal
from schemas.common import DECODE_ERRORS, TEXT_CHARS, ErrorKind, Pose2D, fmt_point
from schemas.executor import ExecutePlanFeedback
from schemas.incidents import (
    MAX_LISTED,
    ForgetAction,
    ForgetIncident,
    ForgetReply,
    Incident,
    IncidentList,
    IncidentQuery,
    IncidentReport,
)
from schemas.keys import ActionKeys
from schemas.plan import GroundedPlan, PlanCheckReply
from schemas.robot import FollowJointTrajectoryGoal, JointState, Odometry, Twist
from schemas.safety import (
    ApprovalDecision,
    ApprovalReply,
    ApprovalRequest,
    ApprovalState,
    Decision,
    EStop,
    ModeReply,
    ModeRequest,
    PendingPlans,
    PlanApproval,
    ResetReply,
    ResetRequest,
    Rule,
    SafetyEvent,
)
from schemas.world import Empty, PerceivedHumans
from services.actionlib import MAX_RESULT_WAIT
from services.errors import CallError
from services.runtime import Node, decoder, encode
from services.safety.config import SafetyConfig
from services.safety.gate import MOVING, GateEvent, GoalRuling, Ruling, SafetyGate
from services.safety.incidents import (
    MAX_REASON,
    REPORTER,
    Draft,
    IncidentStore,
    IncidentStoreError,
    IncidentWatch,
)
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile
from services.safety.monitor import RateLimit
from services.safety.policy import FRESH_JOINTS_WAIT, SafetyPolicy

log = logging.getLogger(__name__)

# Incidents noticed but not yet recorded, at most (more are dropped with an error in the log).
MAX_NOTED = 1000
# How far from the robot's base a reported incident (a dropped object) may be placed: its reach, and
# then some for a fall and a roll.
REPORT_REACH = 3.0
# The service whose plans the approvals are for (its node's name, so its liveliness token's).
EXECUTOR = "executor"
# On close, incidents noticed are still recorded for at most this long (seconds); the rest are logged.
CLOSE_DRAIN = 2.0
# The recording thread looks at the store when idle this often (seconds): incidents kept in memory
# while its file had a fault are written once it is usable again.
IDLE_POLL = 1.0
# New incidents are published once the caution zones include them: after every batch of at most this
# many (or when no more wait).
PUBLISH_BATCH = 50
# A store holding this many incidents at start has them (and all else safety loaded) left out of the
# garbage collector's full passes (gc.freeze): with 100 000 in memory a full pass takes about 0.2 s, on
# whichever thread sets it off, the heartbeat's too. They live as long as safety anyway.
FREEZE_AT = 10_000
# A report refused is logged at most this often (seconds) for each reporter, however many come.
REPORT_LOG_INTERVAL = 1.0
# safety/incidents answers at most this many queries a second (bursts of a second's worth); the agent
# may ask it, and each goes through the memory.
QUERY_RATE = 20.0
# The recorder's file is asked for at most this often (seconds), and waited for this long.
RECORDING_TTL = 5.0
RECORDER_WAIT = 0.5


@dataclass(frozen=True)
class Noted:
    """An incident as noticed, with what safety knew then: the base pose, the arm's joints, the plan."""

    draft: Draft
    pose: Pose2D | None
    joints: dict[str, float] | None
    goal_id: str
    step: int | None
    label: str


class SafetyNode:
    """Every input goes to the gate, which reads `clock` (the time it decides on) and `wall_clock`
    (the latch's stamps); what it rules is published here, stamped with `wall_clock`. The heartbeat is
    paced by time.monotonic whatever `clock` is.

    Locks, each for an order on the wire: `_beat_lock` so a heartbeat read before a latch is never
    sent after the latched one; `_twist_lock` so twists reach robot/cmd_vel in the order the gate
    decided them (teleop ramps from the last one); `_forwarded_lock` for the goals to cancel on an
    e-stop. The gate guards its own state."""

    def __init__(
        self,
        node: Node,
        policy: SafetyPolicy,
        latch: EstopLatch,
        config: SafetyConfig,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        keepalive: Callable[[], None] = lambda: None,
        modes: ModeFile | None = None,
        incidents: IncidentStore | None = None,
    ) -> None:
        self.node = node
        # Called after every beat that ticked and published (systemd's watchdog): if the checking loop
        # hangs, or fails beat after beat, the service is restarted.
        self._keepalive = keepalive
        self.config = config
        self.latch = latch
        self.policy_hash = policy.limits.hash
        self.wall_clock = wall_clock
        self.gate = SafetyGate(policy, latch, clock, wall_clock, config.max_resets_per_minute, modes)
        self.gate.running = self._running
        self.gate.noted = self._forwarded_to
        # Wakes an executor waiting for a plan's approval when an operator decides (or the mode changes).
        self._approvals_changed = threading.Condition()
        self._seq = 0
        self._beat_lock = threading.Lock()
        self._twist_lock = threading.Lock()
        # The goals forwarded that may still run: by goal id, each robot action it went to (a client
        # may send one id on several; noted by id alone, a gripper goal took a navigation's place),
        # with the count of sends the robot had answered once it answered this one (inf while it is
        # on its way): the robot's "no such goal" is believed only of one it had answered before.
        self._forwarded: dict[str, dict[ActionKeys[Any, Any, Any], float]] = {}
        self._answered = 0
        self._forwarded_lock = threading.Lock()
        # A navigation and a trajectory are decided and forwarded one at a time (one_motion): decided
        # together, each asked the robot about the other before it had reached the robot, heard "no
        # such goal", and both went.
        self._motion_lock = threading.Lock()
        # Counts joint states heard, for a trajectory check that waits for one measured since.
        self._joint_reports = 0
        self._joints_arrived = threading.Condition()
        self._heartbeat = node.publisher(keys.HEARTBEAT)
        self._events = node.publisher(keys.SAFETY_EVENTS)
        # Events are decided on several threads (Zenoh's, the query workers'); one stamps and sends at a
        # time, so every subscriber (the recorder, a viewer, a test) gets them in the order of their stamps.
        # Re-entrant: a latch's events are claimed from the gate and published in one hold of it.
        self._events_lock = threading.RLock()
        self._robot_cmd_vel = node.publisher(keys.ROBOT_CMD_VEL)
        self._stop = threading.Event()
        # Safety's memory of incidents (incidents.py): the watch says what is one; each is recorded on
        # a thread of its own (the store's file, the recorder's name, the caution zones), never on the
        # heartbeat's, a command's or Zenoh's. None in the queue: compute the zones again (a forget).
        self.incidents = incidents
        self._incident_rules = policy.policy.incidents
        self.watch = IncidentWatch(self._incident_rules.near_miss_distance)
        self._noted: queue.Queue[Noted | None] = queue.Queue(maxsize=MAX_NOTED)
        self._closing = threading.Event()
        self._drain_until = math.inf
        self._new_incident = node.publisher(keys.NEW_INCIDENT)
        self._recording: tuple[float, str] = (-math.inf, "")
        self._report_warned: dict[str, float] = {}  # by reporter (incidents.REPORTER)
        self._queries = RateLimit(QUERY_RATE, 1.0)
        if incidents is not None:
            self._refresh_zones()
            # The caution zones and the plan check's warnings.
            self.gate.set_incidents(incidents)
            if incidents.size >= FREEZE_AT:
                gc.freeze()
        self._incident_thread = threading.Thread(target=self._record_incidents, name="incidents", daemon=True)
        self._incident_thread.start()
        # A flood of garbage on safety's inputs: one event, then one with the count every few seconds.
        node.on_undecodable = self._on_undecodable

        node.subscribe(keys.ODOM, self._on_odom)
        node.subscribe(keys.JOINT_STATES, self._on_joints)
        node.subscribe(keys.HUMANS, self._on_humans)
        # Raw: an e-stop that does not decode still stops the robot.
        self._estop_decoder = decoder(EStop)
        node.subscribe_raw(keys.ESTOP.key(node.robot), self._on_estop_raw)
        node.subscribe(keys.CMD_VEL, self._on_cmd_vel)
        node.subscribe(keys.TELEOP_CMD_VEL, self._on_teleop)
        node.serve(keys.RESET, self._on_reset)
        node.serve(keys.SET_MODE, self._on_set_mode)
        node.serve(keys.APPROVAL_DECIDE, self._on_decide)
        node.serve(keys.PENDING_PLANS, self._on_pending)
        # The plans' goals ending: an approved plan may move the robot only until it ends, or until
        # its executor goes away (it would never report the end). Watched before asks are served: an
        # executor that can ask was alive when it was first watched, so its end is heard.
        node.subscribe(keys.EXECUTE_PLAN.status, self._on_plan_status)
        node.watch_alive(EXECUTOR, self._on_executor_alive)
        # Waits (up to the request's `wait`) for an operator: on the pool for queries that wait.
        node.serve(keys.APPROVAL_REQUEST, self._on_approval_request, waits=True)
        # The plan and step running, for the incidents.
        node.subscribe(keys.EXECUTE_PLAN.feedback, self._on_plan_feedback)
        node.subscribe(keys.INCIDENT_REPORT, self._on_incident_report)
        # On the pool of queries that may take a while, never a worker of the plan checks and goals'.
        node.serve(keys.INCIDENTS, self._on_incidents, waits=True)
        node.serve(keys.FORGET_INCIDENT, self._on_forget)
        node.serve(keys.PLAN_CHECK, self._on_check_plan)
        self._proxy(keys.CMD_NAVIGATE, keys.ROBOT_NAVIGATE, self.gate.navigate, self._motion_lock)
        self._proxy(keys.CMD_TRAJECTORY, keys.ROBOT_TRAJECTORY, self._decide_trajectory, self._motion_lock)
        # Gripper goals one at a time too: two sent at once under one id, the one the robot refused
        # (an id already used) forgot the one it runs.
        self._proxy(keys.CMD_GRIPPER, keys.ROBOT_GRIPPER, self.gate.gripper, threading.Lock())
        self._beat_thread = threading.Thread(target=self._beat, name="heartbeat", daemon=True)
        self._beat_thread.start()

    def close(self, drain: float = CLOSE_DRAIN) -> None:
        self._stop.set()
        self._beat_thread.join(timeout=1.0)
        # The incidents noticed so far are recorded first, for at most `drain` seconds (a store whose
        # file is locked may take a while for each): never waits on a full queue.
        self._drain_until = time.monotonic() + drain
        self._closing.set()
        with contextlib.suppress(queue.Full):
            self._noted.put_nowait(None)
        self._incident_thread.join(timeout=drain + IDLE_POLL)
        if self._incident_thread.is_alive() or not self._noted.empty():
            log.error("closing: about %d incidents noticed were not recorded in time", self._noted.qsize())

    # Carrying out the gate's rulings

    def _carry_out(self, ruling: Ruling[Any]) -> None:
        events = ruling.events
        if ruling.latched:
            # Out of cycle, so the robot hears it now rather than at the next beat; then written down.
            self._publish_heartbeat()
            # In order with the twists the gate decided (taken after _forward_twist let go of it).
            self._stop_base()
            self._persist()
        elif ruling.cancel_goals:
            # A pause or a mode that stops programs: a program's twist stops now, not when the robot's
            # hold of the last one runs out (0.5 s). Teleop, if it may drive, sends its next one.
            self._stop_base()
        if ruling.latched or ruling.reset:
            # Written down (a reset by _on_reset), and published in the order the gate decided the
            # latch's changes: taken from the gate and sent in one hold of the events' lock.
            with self._events_lock:
                events = self.gate.latch_told(events)
                for event in events:
                    self._publish_event(event)
        else:
            for event in events:
                self._publish_event(event)
        if events:
            self._note_decided(events)
        if ruling.latched or ruling.cancel_goals:
            # Queries take time; not on Zenoh's callback thread. The heartbeat already stops the robot.
            threading.Thread(target=self._cancel_forwarded, name="estop-cancel", daemon=True).start()
        if ruling.approvals_changed:
            with self._approvals_changed:
                self._approvals_changed.notify_all()

    def _stop_base(self) -> None:
        with self._twist_lock:
            self._robot_cmd_vel.put(Twist())
            # Noted as the last twist sent, after any twist decided before it: teleop ramps up from
            # the stop. Unnoted, it went on from the program's twist the stop had cut off.
            self.gate.stopped()

    def _publish_event(self, event: GateEvent, logged: bool = False) -> None:
        """Publish `event`; a veto is logged too unless it was (`logged`)."""
        finite = {k: float(v) for k, v in event.values.items() if math.isfinite(v)}
        command = msgspec.Raw(encode(event.command) if event.command is not None else b"null")
        with self._events_lock:
            self._events.put(
                SafetyEvent(
                    stamp=self.wall_clock(),
                    key=event.key,
                    decision=event.decision,
                    # Within what every reader decodes (Text): a 4,000-character e-stop reason made a
                    # latch event of 4,010 that none could read, the recording's included.
                    reason=event.reason[:TEXT_CHARS],
                    rule=event.rule,
                    checks=list(event.checks),
                    values=finite,
                    policy_hash=self.policy_hash,
                    command=command,
                )
            )
        if event.decision is Decision.VETOED and not logged:
            log.warning("vetoed %s: %s", event.key, event.reason)

    def _on_undecodable(self, key: str, line: str, count: int) -> None:
        path = key.split("/", 2)[-1]
        self._publish_event(GateEvent(path, Decision.VETOED, line, values={"count": float(count)}), logged=True)

    def _publish_heartbeat(self) -> None:
        with self._beat_lock:
            self._seq += 1
            self._heartbeat.put(self.gate.status(self._seq, self.wall_clock()))

    def _beat(self) -> None:
        # Paced by the monotonic clock, not the gate's: the beat must go on whatever the gate's time does.
        period = 1.0 / self.config.heartbeat_hz
        next_beat = time.monotonic()
        while not self._stop.is_set():
            # Nothing may end this thread: without heartbeats the robot stops and takes no goal.
            ok = True
            try:
                self._carry_out(self.gate.tick())
            except Exception:
                ok = False
                log.exception("carrying out the heartbeat's tick failed")
            self._note_separation()
            try:
                self._publish_heartbeat()
            except Exception:
                ok = False
                log.exception("the heartbeat could not be published")
            # Fed only after a beat that did its work: one that fails every time is restarted.
            if ok:
                self._keepalive()
            next_beat += period
            self._stop.wait(max(0.0, next_beat - time.monotonic()))

    def _persist(self) -> bool:
        try:
            self.latch.save()
        except OSError as exc:
            log.error("the e-stop state could not be written (%s): a restart may not remember it", exc)
            return False
        return True

    def _running(self, robot: ActionKeys[Any, Any, Any]) -> str | None:
        """A goal forwarded on `robot` that may still run, or None. The robot's action server says
        whether each one noted has ended (one whose end was fetched, or that it said ended, is no longer
        noted); a goal it cannot answer for may run. One it knows nothing of is being decided or never reached it:
        not running, and left noted (a goal on its way must still be canceled by an e-stop)."""
        with self._forwarded_lock:
            noted = [goal_id for goal_id, actions in self._forwarded.items() if robot in actions]
        for goal_id in noted:
            try:
                progress = self.node.call(
                    robot.get_status, GetResult(goal_id=goal_id), timeout=self.config.forward_timeout
                )
            except CallError as exc:
                if exc.error.kind is ErrorKind.INVALID_REQUEST:
                    continue
                return goal_id
            if not progress.state.terminal:
                return goal_id
            # Ended, the robot says: nothing left to cancel or to ask about.
            self._forget_forwarded(goal_id, robot)
        return None

    def _forwarded_to(self, robot: ActionKeys[Any, Any, Any]) -> str | None:
        """A goal forwarded on `robot` (or being decided) not known to have ended; the robot is not
        asked (see _running)."""
        with self._forwarded_lock:
            return next((goal_id for goal_id, actions in self._forwarded.items() if robot in actions), None)

    def _note_forwarded(self, goal_id: str, robot: ActionKeys[Any, Any, Any]) -> bool:
        """Note `goal_id` as on its way to `robot`; whether it was noted already."""
        with self._forwarded_lock:
            actions = self._forwarded.setdefault(goal_id, {})
            if robot in actions:
                return True
            actions[robot] = math.inf
            return False

    def _answered_now(self) -> int:
        with self._forwarded_lock:
            return self._answered

    def _sent_forwarded(self, goal_id: str, robot: ActionKeys[Any, Any, Any]) -> None:
        """The robot answered the send of `goal_id` (or the call failed): no longer on its way."""
        with self._forwarded_lock:
            self._answered += 1
            actions = self._forwarded.get(goal_id, {})
            if actions.get(robot) == math.inf:
                actions[robot] = self._answered

    def _forget_forwarded(self, goal_id: str, robot: ActionKeys[Any, Any, Any], answered_by: float = math.inf) -> None:
        """Forget `goal_id` on `robot`; with `answered_by`, only if its send was answered by then."""
        with self._forwarded_lock:
            actions = self._forwarded.get(goal_id, {})
            if actions.get(robot, -math.inf) <= answered_by:
                actions.pop(robot, None)
            if not actions:
                self._forwarded.pop(goal_id, None)

    def _cancel_forwarded(self) -> None:
        with self._forwarded_lock:
            goals = [(goal_id, action) for goal_id, actions in self._forwarded.items() for action in actions]
        for goal_id, action in goals:
            try:
                self.node.call(action.cancel_goal, CancelGoal(goal_id=goal_id), timeout=1.0)
            except Exception as exc:  # the heartbeat stops the robot anyway
                log.warning("cancel of %s on e-stop failed: %s", goal_id, exc)

    # Inputs

    def _on_estop_raw(self, _key: str, payload: bytes) -> None:
        try:
            msg: EStop = self._estop_decoder.decode(payload)
        except DECODE_ERRORS as exc:
            self._carry_out(self.gate.unreadable_estop(len(payload), str(exc)))
            return
        self._carry_out(self.gate.estop(msg))

    def _on_reset(self, req: ResetRequest) -> ResetReply:
        ruling = self.gate.reset(req)
        saved = True
        if ruling.reset:
            self._publish_heartbeat()
            saved = self._persist()
        self._carry_out(ruling)
        if saved:
            return ruling.forward
        note = " (the state file could not be written: a restart of safety may come up latched)"
        return msgspec.structs.replace(ruling.forward, message=ruling.forward.message + note)

    def _on_set_mode(self, req: ModeRequest) -> ModeReply:
        ruling = self.gate.set_mode(req)
        saved = True
        if ruling.mode_changed:
            self._publish_heartbeat()
            try:
                self.gate.modes.save()
            except OSError as exc:
                log.error("the mode could not be written (%s): a restart may not remember it", exc)
                saved = False
        self._carry_out(ruling)
        if saved:
            return ruling.forward
        note = " (the mode state file could not be written: a restart of safety may come up in another mode)"
        return msgspec.structs.replace(ruling.forward, message=ruling.forward.message + note)

    def _on_decide(self, req: ApprovalDecision) -> ApprovalReply:
        ruling = self.gate.decide(req)
        self._carry_out(ruling)
        return ruling.forward

    def _on_pending(self, _req: Empty) -> PendingPlans:
        return self.gate.pending()

    def _on_approval_request(self, req: ApprovalRequest) -> PlanApproval:
        # Read before the ask is decided: a change after it ends the wait, however soon it comes.
        mode = self.gate.mode
        ruling = self.gate.request_approval(req)
        self._carry_out(ruling)
        approval = ruling.forward
        # Pending (before the first motion) or paused (while it ran): waits for an operator.
        waiting = (ApprovalState.PENDING, ApprovalState.PAUSED)
        if approval.state not in waiting or req.wait <= 0.0:
            return approval
        deadline = time.monotonic() + req.wait

        def decided() -> bool:
            # A new mode leaves the book as it was (it is applied to the plan when asked again below):
            # waited on for the plan's state alone, it held the executor until its wait ran out.
            if self.gate.mode is not mode:
                return True
            now = self.gate.approval(req.goal_id)
            return now is None or now.state is not approval.state

        with self._approvals_changed:
            while not decided() and (left := deadline - time.monotonic()) > 0:
                self._approvals_changed.wait(left)
        # Asked again: a change of mode while it waited is applied here.
        again = self.gate.request_approval(req)
        self._carry_out(again)
        return again.forward

    def _on_plan_status(self, status: GoalStatus) -> None:
        self.watch.plan_status(status)
        self._carry_out(self.gate.plan_status(status))

    def _on_executor_alive(self, alive: bool) -> None:
        if alive:
            self.gate.executor_alive()
        else:
            self._carry_out(self.gate.executor_gone())

    def _on_plan_feedback(self, feedback: Feedback[ExecutePlanFeedback]) -> None:
        self.watch.plan_feedback(feedback)

    def _on_odom(self, msg: Odometry) -> None:
        self.watch.base_moved(abs(msg.linear_x) > MOVING or abs(msg.angular_z) > MOVING)
        self._carry_out(self.gate.odometry(msg))

    def _on_joints(self, msg: JointState) -> None:
        try:
            ruling = self.gate.joint_state(msg)
        finally:
            # Counted even if the gate failed on it: a trajectory waiting for a fresh one goes on.
            with self._joints_arrived:
                self._joint_reports += 1
                self._joints_arrived.notify_all()
        self._carry_out(ruling)

    def _on_humans(self, msg: PerceivedHumans) -> None:
        self.gate.humans(msg)

    def _on_cmd_vel(self, twist: Twist) -> None:
        self._forward_twist(lambda: self.gate.cmd_vel(twist))

    def _on_teleop(self, twist: Twist) -> None:
        self._forward_twist(lambda: self.gate.teleop(twist))

    def _forward_twist(self, decide: Callable[[], Ruling[Twist | None]]) -> None:
        with self._twist_lock:
            ruling = decide()
            if ruling.forward is not None:
                self._robot_cmd_vel.put(ruling.forward)
        self._carry_out(ruling)

    def _on_check_plan(self, plan: GroundedPlan) -> PlanCheckReply:
        ruling = self.gate.check_plan(plan)
        self._carry_out(ruling)
        return ruling.forward

    def _decide_trajectory(self, req: SendGoal[FollowJointTrajectoryGoal]) -> Ruling[GoalRuling]:
        with self._joints_arrived:
            seen = self._joint_reports
        ruling = self.gate.trajectory(req)
        if ruling.fresh_joints_may_pass and self._joints_since(seen, FRESH_JOINTS_WAIT):
            ruling = self.gate.trajectory(req, again=True)
        return ruling

    def _joints_since(self, seen: int, timeout: float) -> bool:
        """Wait for a joint state after the `seen`th; whether one came."""
        with self._joints_arrived:
            return self._joints_arrived.wait_for(lambda: self._joint_reports != seen, timeout)

    def _proxy(
        self,
        cmd: ActionKeys[Any, Any, Any],
        robot: ActionKeys[Any, Any, Any],
        decide: Callable[[Any], Ruling[GoalRuling]],
        one_at_a_time: threading.Lock,
    ) -> None:
        """Serve `cmd`'s keys: goals as the gate rules, forwarded to `robot`; its feedback and status
        relayed. A goal holds `one_at_a_time` from its decision until the robot has answered it."""

        def send_goal(req: SendGoal[Any]) -> GoalResponse:
            with one_at_a_time:
                return decided(req)

        def decided(req: SendGoal[Any]) -> GoalResponse:
            # Noted as forwarded before it is decided on: an e-stop, pause or mode change decided after
            # this goal's check cancels it, also while it is on its way (the robot rejects a goal
            # canceled before it knew it). Noted only once accepted, such a goal ran on, uncanceled.
            noted_before = self._note_forwarded(req.goal_id, robot)  # a goal id sent twice: the first's stays
            ruling = decide(req)
            self._carry_out(ruling)
            if isinstance(ruling.forward, GoalResponse):
                response = ruling.forward
            else:
                # A call that fails leaves the goal noted: it may run, and a later sweep cancels it.
                try:
                    response = self.node.call(robot.send_goal, ruling.forward, timeout=self.config.forward_timeout)
                finally:
                    self._sent_forwarded(req.goal_id, robot)
            if not response.accepted and not noted_before:
                self._forget_forwarded(req.goal_id, robot)
            return response

        def cancel_goal(req: CancelGoal) -> CancelResponse:
            return self.node.call(robot.cancel_goal, req, timeout=self.config.forward_timeout)

        def get_result(req: GetResult) -> Any:
            # Forgotten once it ended, or once the robot says it knows no such goal, unless it was
            # still on its way when the robot was asked (then it knew none yet). A get_result that
            # failed on the way (no reply, the link down) leaves it noted: it may run on, and a pause
            # or e-stop must still cancel it.
            asked = self._answered_now()
            try:
                result = self.node.call(robot.get_result, req, timeout=MAX_RESULT_WAIT)
            except CallError as exc:
                if exc.error.kind is ErrorKind.INVALID_REQUEST:
                    self._forget_forwarded(req.goal_id, robot, answered_by=asked)
                raise
            if result.state.terminal:
                self._forget_forwarded(req.goal_id, robot)
            return result

        def get_status(req: GetResult) -> Any:
            return self.node.call(robot.get_status, req, timeout=self.config.forward_timeout)

        self.node.serve(cmd.send_goal, send_goal)
        self.node.serve(cmd.cancel_goal, cancel_goal)
        # Waits as long as the goal runs: on the node's pool for such waits (services/runtime.py).
        self.node.serve(cmd.get_result, get_result, waits=True)
        self.node.serve(cmd.get_status, get_status)
        feedback = self.node.publisher(cmd.feedback)
        status = self.node.publisher(cmd.status)
        self.node.subscribe(robot.feedback, feedback.put)
        self.node.subscribe(robot.status, status.put)

    # Safety's memory of incidents

    def _note(self, draft: Draft) -> None:
        """Hand an incident to the recording thread with the pose, joints and plan known now."""
        if self.incidents is None:
            return
        goal_id, step, label = self.watch.context()
        if draft.goal_id:
            goal_id, step, label = draft.goal_id, draft.step, draft.label
        noted = Noted(draft, self.gate.pose(), self.gate.joint_positions(), goal_id, step, label)
        try:
            self._noted.put_nowait(noted)
        except queue.Full:
            log.error("incident not recorded (%d wait already): %s: %s", MAX_NOTED, draft.kind, draft.reason)

    def _note_decided(self, events: tuple[GateEvent, ...]) -> None:
        try:
            for draft in self.watch.decided(events, self.latch.state):
                self._note(draft)
        except Exception:  # never in the way of carrying out a ruling
            log.exception("noting an incident failed")

    def _note_separation(self) -> None:
        try:
            if (draft := self.watch.separation(self.gate.separation)) is not None:
                self._note(draft)
        except Exception:
            log.exception("noting a near-miss failed")

    def _on_incident_report(self, report: IncidentReport) -> None:
        taken = self.watch.report(report, source="reported")
        if isinstance(taken, str):
            # Logged per reporter: one's flood of warnings must not hide another's.
            who, now = REPORTER.get(report.kind, ""), time.monotonic()
            if now - self._report_warned.get(who, -math.inf) >= REPORT_LOG_INTERVAL:
                self._report_warned[who] = now
                log.warning("%s", taken)
            return
        self._note(taken)

    def _record_incidents(self) -> None:
        """The recording thread: each incident into the store, then (with no more waiting, or every
        PUBLISH_BATCH) the caution zones computed again and the incidents published, so whoever hears
        of one finds the zones counting it. Idle, it lets the store write what it kept in memory. On
        close it drains the queue until close's deadline has passed."""
        recorded: list[Incident] = []
        rezone = False
        while True:
            if self._closing.is_set() and (self._noted.empty() or time.monotonic() > self._drain_until):
                break
            try:
                noted = self._noted.get(timeout=IDLE_POLL)
            except queue.Empty:
                self._retry_store()
                continue
            rezone = True
            if noted is not None:
                try:
                    recorded.append(self._record(noted))
                except Exception:
                    log.exception("recording an incident failed")
            if self._noted.empty() or len(recorded) >= PUBLISH_BATCH:
                self._refresh_zones()
                rezone = False
                for incident in recorded:
                    self._new_incident.put(incident)
                recorded.clear()
        if rezone:
            self._refresh_zones()
        for incident in recorded:
            self._new_incident.put(incident)

    def _retry_store(self) -> None:
        store = self.incidents
        if store is None or not (store.fault or store.pending):
            return
        try:
            store.flush()
        except Exception:
            log.exception("writing the incidents kept in memory failed")

    def _record(self, noted: Noted) -> Incident:
        store = self.incidents
        assert store is not None
        draft, pose = noted.draft, noted.pose
        x, y = (draft.x, draft.y) if draft.x is not None and draft.y is not None else (None, None)
        reason = draft.reason
        if x is not None and y is not None and pose is not None and math.dist((x, y), (pose.x, pose.y)) > REPORT_REACH:
            # Nothing the robot dropped or hit lands that far from it: a report placed there (a broken
            # or hostile reporter) would make caution zones anywhere. Where the robot was stands instead.
            note = f" (reported at {fmt_point(x, y)}, over {REPORT_REACH:g} m from the robot: placed where it was)"
            reason = reason[: MAX_REASON - len(note)] + note
            x = y = None
        if x is None and pose is not None:
            x, y = pose.x, pose.y
        incident = store.add(
            draft.kind,
            reason,
            x=x,
            y=y,
            yaw=pose.yaw if pose is not None else None,
            hand=self.gate.hand_on_map(pose, noted.joints) if pose is not None else None,
            source=draft.source,
            rule=draft.rule,
            goal_id=noted.goal_id,
            step=noted.step,
            label=noted.label,
            objects=draft.objects,
            people=draft.people,
            recording=self._recording_now(),
        )
        x, y = incident.x, incident.y
        where = "where unknown" if x is None or y is None else f"at {fmt_point(x, y)}"
        kept = f" (kept in memory: {store.fault})" if store.fault else ""
        log.warning("incident %d, %s %s: %s%s", incident.id, incident.kind, where, incident.reason, kept)
        return incident

    def _recording_now(self) -> str:
        """The recorder's file now ("" with no recorder), asked at most every RECORDING_TTL seconds."""
        at, name = self._recording
        if time.monotonic() - at < RECORDING_TTL:
            return name
        try:
            name = self.node.call(keys.RECORDER_STATUS, Empty(), timeout=RECORDER_WAIT).path
        except Exception:
            name = ""
        self._recording = (time.monotonic(), name)
        return name

    def _refresh_zones(self) -> None:
        """Compute the caution zones again (the store's writer: on this thread or, at start, before
        the gate takes the store); the gate reads them as they are swapped in."""
        if self.incidents is None:
            return
        rules = self._incident_rules
        try:
            self.incidents.refresh_zones(rules.caution_count, rules.caution_radius, rules.caution_speed_scale)
        except Exception:
            log.exception("the caution zones could not be computed; those computed last stay in force")

    def _on_incidents(self, query: IncidentQuery) -> IncidentList:
        if not self._queries.allow(time.monotonic()):
            return IncidentList(
                store=f"too many queries of safety's incident memory (at most {QUERY_RATE:g} a second): ask again"
            )
        if self.incidents is None:
            return IncidentList(store="safety runs without an incident store")
        return self.incidents.query(query)

    def _on_forget(self, req: ForgetIncident) -> ForgetReply:
        """Forget an incident or clear its caution zone: the operator's token only (counted against
        the same limit on wrong attempts as the reset), recorded as a safety event."""
        key = keys.FORGET_INCIDENT.path
        redacted = msgspec.structs.replace(req, token="***")
        forget = req.action is ForgetAction.FORGET
        what = f"forgetting incident {req.id}" if forget else f"clearing the caution zone of incident {req.id}"
        refusal = self.gate.operator_refusal(key, what, req.operator, req.token, redacted)
        if refusal is not None:
            self._publish_event(refusal)
            return ForgetReply(ok=False, message=refusal.reason)
        if self.incidents is None:
            return ForgetReply(ok=False, message="safety runs without an incident store")
        try:
            changed = self.incidents.forget(
                req.id, req.action, req.operator, req.reason, self._incident_rules.caution_radius
            )
        except KeyError as exc:
            return ForgetReply(ok=False, message=str(exc.args[0]) if exc.args else str(exc))
        except IncidentStoreError as exc:
            return ForgetReply(ok=False, message=f"{what} failed: {exc}")
        # The zones again, on the recording thread (a full queue computes them after its batch anyway).
        with contextlib.suppress(queue.Full):
            self._noted.put_nowait(None)
        if forget:
            why = f"incident {req.id} forgotten by operator {req.operator}: {req.reason}"
        elif changed:
            zone = f"caution zone of incident {req.id} ({len(changed)} incidents)"
            why = f"{zone} cleared by operator {req.operator}: {req.reason}"
        else:
            why = f"incident {req.id} counts towards no caution zone now: nothing to clear"
        if changed:
            log.warning("%s", why)
            decision = Decision.FORGOTTEN if forget else Decision.CLEARED
            values = {"incidents": float(len(changed))}
            self._publish_event(GateEvent(key, decision, why, redacted, Rule.OPERATOR, (Rule.OPERATOR,), values))
        # The message counts them all; a reply lists at most MAX_LISTED (more, and no tether could read it).
        return ForgetReply(ok=True, message=why, changed=changed[:MAX_LISTED])
