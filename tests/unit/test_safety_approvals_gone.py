"""Safety's approvals and the executor's liveliness: an ask whose executor is not alive is denied, never
held for an operator; an executor that comes back (or was running when safety started) has its asks
held. And a reset decided while a new latch is being written down is published after that latch.
On the Recorder stand-in of test_safety_node, races made to happen every time with events; the
executor's liveliness once over real Zenoh."""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path
from typing import Any

import msgspec

from schemas import keys
from schemas.safety import (
    ApprovalAction,
    ApprovalDecision,
    ApprovalReply,
    ApprovalRequest,
    ApprovalState,
    ControlMode,
    Decision,
    EstopState,
    ModeRequest,
    PendingPlans,
    ResetRequest,
    SafetyEvent,
    SafetyStatus,
)
from schemas.world import Empty
from services.robotmodel import ArmModel
from services.runtime import Node, NodeSettings
from services.safety.config import SafetyConfig
from services.safety.latch import EstopLatch
from services.safety.node import SafetyNode
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel
from tests.sessions import free_port
from tests.unit.test_safety_modes import PLAN
from tests.unit.test_safety_node import ESTOP, WAIT, WORLD, Recorder, Start, odometry
from tests.unit.test_safety_node import start as start  # the fixture, shared

SUPERVISED = ModeRequest(operator="alice", token="token", mode=ControlMode.SUPERVISED)


def supervised(node: Recorder) -> None:
    node.callbacks[keys.ODOM.path](odometry())
    assert node.callbacks[keys.SET_MODE.path](SUPERVISED).ok


def ask(node: Recorder, goal_id: str) -> Any:
    return node.callbacks[keys.APPROVAL_REQUEST.path](ApprovalRequest(goal_id=goal_id, plan=PLAN))


def approve(node: Recorder, goal_id: str) -> ApprovalReply:
    decision = ApprovalDecision(operator="alice", token="token", goal_id=goal_id, action=ApprovalAction.APPROVE)
    reply: ApprovalReply = node.callbacks[keys.APPROVAL_DECIDE.path](decision)
    return reply


def waiting(node: Recorder) -> list[str]:
    pending: PendingPlans = node.callbacks[keys.PENDING_PLANS.path](Empty())
    return [p.goal_id for p in pending.plans]


def test_an_ask_that_comes_after_the_executor_went_away_is_denied_not_held(start: Start) -> None:
    """Queued on safety's worker pool when the executor died, the ask was decided after its
    liveliness ended and held pending: an operator could approve a plan no executor runs, which in
    supervised mode let every program's motion pass while it lasted."""
    node, safety = start()
    supervised(node)
    node.callbacks["alive/executor"](False)

    reply = ask(node, "p1")

    assert reply.state is ApprovalState.DENIED and "executor went away" in reply.reason, reply
    assert waiting(node) == []
    assert not approve(node, "p1").ok
    assert safety.gate._mode_veto() is not None, "no approved plan lets a program's motion pass"
    denied = [m for _, m in node.sent if isinstance(m, SafetyEvent) and m.key == keys.APPROVAL_REQUEST.path]
    assert [e.decision for e in denied] == [Decision.DENIED], denied


def test_an_ask_that_came_while_the_executor_was_away_stays_denied_if_it_comes_back_meanwhile(start: Start) -> None:
    """The executor came back while the ask of the one that went away was checked: it is still not
    the new executor's ask."""
    node, safety = start()
    supervised(node)
    node.callbacks["alive/executor"](False)
    check = safety.gate.check_plan

    def executor_back_while_checking(plan: Any) -> Any:
        node.callbacks["alive/executor"](True)
        return check(plan)

    safety.gate.check_plan = executor_back_while_checking  # type: ignore[method-assign]
    reply = ask(node, "p1")
    assert reply.state is ApprovalState.DENIED and "executor went away" in reply.reason, reply
    assert waiting(node) == []


def test_an_executor_that_comes_back_has_its_new_asks_held_for_an_operator(start: Start) -> None:
    node, _safety = start()
    supervised(node)
    node.callbacks["alive/executor"](True)
    assert ask(node, "p1").state is ApprovalState.PENDING
    node.callbacks["alive/executor"](False)
    assert ask(node, "p2").state is ApprovalState.DENIED
    node.callbacks["alive/executor"](True)

    reply = ask(node, "p3")

    assert reply.state is ApprovalState.PENDING, reply
    assert waiting(node) == ["p3"]
    assert approve(node, "p3").ok
    assert ask(node, "p1").state is ApprovalState.DENIED, "the plan of the executor that went away stays ended"


def test_safety_started_while_the_executor_runs_holds_its_asks_and_those_of_the_next_one(tmp_path: Path) -> None:
    """Over real Zenoh: the executor's token, held before safety started, reaches safety after it has
    started (on Zenoh's thread); an ask decided before that is the executor's all the same. An
    executor started again after one went away has its asks held."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    arm = ArmModel(WORLD.robot.arm_urdf)
    policy = SafetyPolicy(WorldModel(WORLD), load_policy(None, WORLD.robot, arm, WORLD.keep_out), arm)
    (tmp_path / "estop.json").write_bytes(msgspec.json.encode(EstopState(latched=False)))

    def held(executor: Node, goal_id: str) -> ApprovalState:
        request = ApprovalRequest(goal_id=goal_id, plan=PLAN)
        return executor.call(keys.APPROVAL_REQUEST, request, timeout=WAIT).state

    def gone(goal_id: str) -> bool:
        approval = safety.gate.approval(goal_id)
        return approval is not None and "executor went away" in approval.reason

    with Node("executor", settings) as executor:
        executor.declare_alive()
        with Node("safety", settings) as session:
            safety = SafetyNode(session, policy, EstopLatch("token", tmp_path / "estop.json"), SafetyConfig())
            session.declare_alive()
            try:
                assert not executor.wait_alive({"safety"}, WAIT), "the two sessions did not find each other"
                assert executor.call(keys.SET_MODE, SUPERVISED, timeout=WAIT).ok
                executor.publish(keys.ODOM, odometry())
                deadline = time.monotonic() + WAIT
                while safety.gate.pose() is None:
                    assert time.monotonic() < deadline, "safety never heard the odometry"
                    time.sleep(0.005)
                assert held(executor, "p1") is ApprovalState.PENDING
                executor.close()
                deadline = time.monotonic() + WAIT
                while not gone("p1"):
                    assert time.monotonic() < deadline, "safety never saw the executor go away"
                    time.sleep(0.01)
                with Node("executor", settings) as again:
                    again.declare_alive()
                    assert not again.wait_alive({"safety"}, WAIT)
                    deadline = time.monotonic() + WAIT
                    while safety.gate._executor_away:
                        assert time.monotonic() < deadline, "safety never saw the executor come back"
                        time.sleep(0.01)
                    assert held(again, "p2") is ApprovalState.PENDING
            finally:
                safety.close()


def timeline(node: Recorder) -> tuple[list[Decision], list[bool]]:
    """The latch's events (latched, reset) and whether each heartbeat said latched, in the order sent."""
    with node.changed:
        latch = (keys.ESTOP.path, keys.RESET.path)
        events = [m.decision for _, m in node.sent if isinstance(m, SafetyEvent) and m.key in latch]
        beats = [m.estop.latched for _, m in node.sent if isinstance(m, SafetyStatus)]
    return events, beats


def test_a_reset_decided_while_a_latch_is_written_down_is_published_after_the_latch(
    start: Start, tmp_path: Path
) -> None:
    """The latch's event goes out once its state file is written; a reset decided meanwhile sent its
    own event first, so the recording's timeline showed the robot latched after the reset, when it
    was not (the heartbeats and the state file were right)."""
    node, safety = start()
    estop_key = keys.ESTOP.key(node.robot)
    estop = threading.Thread(target=node.callbacks[estop_key], args=(estop_key, ESTOP))
    reset = ResetRequest(operator="alice", token="token")
    resetting = threading.Thread(target=lambda: replies.append(node.callbacks[keys.RESET.path](reset)))
    replies: list[Any] = []
    save = safety.latch.save

    def reset_while_writing() -> None:
        if threading.current_thread() is estop and resetting.ident is None:
            # The latch's heartbeat is out; its state file is about to be written.
            resetting.start()
            resetting.join(WAIT)
        save()

    safety.latch.save = reset_while_writing  # type: ignore[method-assign]
    estop.start()
    estop.join(WAIT)
    assert not estop.is_alive() and [r.ok for r in replies] == [True], replies

    events, beats = timeline(node)
    assert events == [Decision.LATCHED, Decision.RESET], events
    assert True in beats and not beats[-1], beats
    assert not safety.latch.state.latched
    assert b'"latched":false' in (tmp_path / "estop.json").read_bytes()


def test_a_latch_decided_while_a_reset_is_written_down_is_published_after_the_reset(
    start: Start, tmp_path: Path
) -> None:
    """The other way round: a new latch published while the reset before it was written down came
    out first, and the timeline showed the robot free when it was latched."""
    node, safety = start()
    estop_key = keys.ESTOP.key(node.robot)
    node.callbacks[estop_key](estop_key, ESTOP)
    resetting = threading.current_thread()
    estop = threading.Thread(target=node.callbacks[estop_key], args=(estop_key, ESTOP))
    save = safety.latch.save

    def latch_while_writing() -> None:
        if threading.current_thread() is resetting and estop.ident is None:
            # The reset's heartbeat is out; its state file is about to be written.
            estop.start()
            estop.join(WAIT)
        save()

    safety.latch.save = latch_while_writing  # type: ignore[method-assign]
    assert node.callbacks[keys.RESET.path](ResetRequest(operator="alice", token="token")).ok
    assert estop.ident is not None and not estop.is_alive()

    events, beats = timeline(node)
    assert events == [Decision.LATCHED, Decision.RESET, Decision.LATCHED], events
    assert False in beats and beats[-1], beats
    assert safety.latch.state.latched
    assert b'"latched":true' in (tmp_path / "estop.json").read_bytes()
