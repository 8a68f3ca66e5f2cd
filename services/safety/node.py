"""Safety's transport: keys to the gate and its rulings onto the wire; the only writer of robot/**."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import msgspec

from schemas import keys
from schemas.actions import CancelGoal, CancelResponse, GetResult, GoalResponse, GoalStatus, SendGoal
from schemas.common import DECODE_ERRORS
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
    SafetyEvent,
)
from schemas.world import Empty, PerceivedHumans
from services.actionlib import MAX_RESULT_WAIT
from services.runtime import Node, decoder, encode
from services.safety.config import SafetyConfig
from services.safety.gate import GateEvent, GoalRuling, Ruling, SafetyGate
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile
from services.safety.policy import FRESH_JOINTS_WAIT, SafetyPolicy

log = logging.getLogger(__name__)


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
        # Wakes an executor waiting for a plan's approval when an operator decides (or the mode changes).
        self._approvals_changed = threading.Condition()
        self._seq = 0
        self._beat_lock = threading.Lock()
        self._twist_lock = threading.Lock()
        self._forwarded: dict[str, ActionKeys[Any, Any, Any]] = {}
        self._forwarded_lock = threading.Lock()
        # Counts joint states heard, for a trajectory check that waits for one measured since.
        self._joint_reports = 0
        self._joints_arrived = threading.Condition()
        self._heartbeat = node.publisher(keys.HEARTBEAT)
        self._events = node.publisher(keys.SAFETY_EVENTS)
        self._robot_cmd_vel = node.publisher(keys.ROBOT_CMD_VEL)
        self._stop = threading.Event()
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
        # Waits (up to the request's `wait`) for an operator: on the pool for queries that wait.
        node.serve(keys.APPROVAL_REQUEST, self._on_approval_request, waits=True)
        # The plans' goals ending: an approved plan may move the robot only until it ends.
        node.subscribe(keys.EXECUTE_PLAN.status, self._on_plan_status)
        node.serve(keys.PLAN_CHECK, self._on_check_plan)
        self._proxy(keys.CMD_NAVIGATE, keys.ROBOT_NAVIGATE, self.gate.navigate)
        self._proxy(keys.CMD_TRAJECTORY, keys.ROBOT_TRAJECTORY, self._decide_trajectory)
        self._proxy(keys.CMD_GRIPPER, keys.ROBOT_GRIPPER, self.gate.gripper)
        self._beat_thread = threading.Thread(target=self._beat, name="heartbeat", daemon=True)
        self._beat_thread.start()

    def close(self) -> None:
        self._stop.set()
        self._beat_thread.join(timeout=1.0)

    # Carrying out the gate's rulings

    def _carry_out(self, ruling: Ruling[Any]) -> None:
        if ruling.latched:
            # Out of cycle, so the robot hears it now rather than at the next beat; then written down.
            self._publish_heartbeat()
            # In order with the twists the gate decided (taken after _forward_twist let go of it).
            with self._twist_lock:
                self._robot_cmd_vel.put(Twist())
            self._persist()
        for event in ruling.events:
            self._publish_event(event)
        if ruling.latched or ruling.cancel_goals:
            # Queries take time; not on Zenoh's callback thread. The heartbeat already stops the robot.
            threading.Thread(target=self._cancel_forwarded, name="estop-cancel", daemon=True).start()
        if ruling.approvals_changed:
            with self._approvals_changed:
                self._approvals_changed.notify_all()

    def _publish_event(self, event: GateEvent, logged: bool = False) -> None:
        """Publish `event`; a veto is logged too unless it was (`logged`)."""
        finite = {k: float(v) for k, v in event.values.items() if math.isfinite(v)}
        command = msgspec.Raw(encode(event.command) if event.command is not None else b"null")
        self._events.put(
            SafetyEvent(
                stamp=self.wall_clock(),
                key=event.key,
                decision=event.decision,
                reason=event.reason,
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

    def _cancel_forwarded(self) -> None:
        with self._forwarded_lock:
            goals = list(self._forwarded.items())
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
        ruling = self.gate.request_approval(req)
        self._carry_out(ruling)
        approval = ruling.forward
        if approval.state is not ApprovalState.PENDING or req.wait <= 0.0:
            return approval
        deadline = time.monotonic() + req.wait

        def decided() -> bool:
            now = self.gate.approval(req.goal_id)
            return now is None or now.state is not ApprovalState.PENDING

        with self._approvals_changed:
            while not decided() and (left := deadline - time.monotonic()) > 0:
                self._approvals_changed.wait(left)
        # Asked again: a change of mode while it waited is applied here.
        again = self.gate.request_approval(req)
        self._carry_out(again)
        return again.forward

    def _on_plan_status(self, status: GoalStatus) -> None:
        self._carry_out(self.gate.plan_status(status))

    def _on_odom(self, msg: Odometry) -> None:
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
    ) -> None:
        """Serve `cmd`'s keys: goals as the gate rules, forwarded to `robot`; its feedback and status relayed."""

        def send_goal(req: SendGoal[Any]) -> GoalResponse:
            ruling = decide(req)
            self._carry_out(ruling)
            if isinstance(ruling.forward, GoalResponse):
                return ruling.forward
            response = self.node.call(robot.send_goal, ruling.forward, timeout=self.config.forward_timeout)
            if response.accepted:
                with self._forwarded_lock:
                    self._forwarded[req.goal_id] = robot
            return response

        def cancel_goal(req: CancelGoal) -> CancelResponse:
            return self.node.call(robot.cancel_goal, req, timeout=self.config.forward_timeout)

        def get_result(req: GetResult) -> Any:
            try:
                return self.node.call(robot.get_result, req, timeout=MAX_RESULT_WAIT)
            finally:
                with self._forwarded_lock:
                    self._forwarded.pop(req.goal_id, None)

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
