"""Safety over real processes, what the recording holds of the latch: an e-stop with the longest reason
a peer may send is an event every reader decodes, one asked for while latched is an event naming who
and why (the latch held as it was), and the reset names the operator. And a plan autonomous mode let
run moves nothing once supervised mode is back, until an operator approves one (the test plays the
executor and the robot's odometry)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal, Odometry
from schemas.safety import (
    ApprovalRequest,
    ApprovalState,
    ControlMode,
    Decision,
    EStop,
    EstopSource,
    ModeRequest,
    PlanApproval,
    SafetyEvent,
)
from services.safety.operator import read_token
from tests.integration.conftest import Stack, start_stack, stop_stack
from tests.unit.test_safety_modes import NEAR, PLAN
from tests.watch import Watch
from tether.client import reset_estop

WAIT = 10.0


@pytest.fixture
def safety_alone(tmp_path: Path) -> Iterator[Stack]:
    s = start_stack(tmp_path, realtime_factor=1.0, services=("safety",))
    try:
        yield s
    finally:
        stop_stack(s)


def latch_events(events: Watch[SafetyEvent], after: int) -> SafetyEvent | None:
    return events.wait_for(lambda e: e.decision is Decision.LATCHED, timeout=WAIT, after=after)


def test_every_estop_is_an_event_the_recording_can_read_and_the_reset_names_the_operator(safety_alone: Stack) -> None:
    stack = safety_alone
    beats = Watch(stack.node, keys.HEARTBEAT)
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    assert beats.wait_for(lambda b: not b.estop.latched, timeout=WAIT)

    # The longest reason an EStop may carry: the event ("by agent: " and the reason) was 10 over
    # what a SafetyEvent may hold, so no reader (the recorder, `tether inspect`) could decode it.
    stack.node.publish(keys.ESTOP, EStop(source=EstopSource.AGENT, reason="x" * 4000))
    first = latch_events(events, 0)
    assert first is not None and first.reason.startswith("by agent: xxx") and len(first.reason) == 4000

    n = len(events)
    stack.node.publish(keys.ESTOP, EStop(source=EstopSource.OPERATOR, reason="person on the floor"))
    again = latch_events(events, n)
    assert again is not None and again.values["already_latched"] == 1.0
    assert again.reason.startswith("by operator: person on the floor; already latched by agent: xxx")
    beat = beats.wait_for(lambda _: True, timeout=WAIT, after=len(beats))
    assert beat is not None and (beat.estop.latched, beat.estop.source) == (True, "agent")

    n = len(events)
    assert reset_estop(stack.node, str(stack.token_file)).ok
    reset = events.wait_for(lambda e: e.decision is Decision.RESET, timeout=WAIT, after=n)
    assert reset is not None and reset.reason.startswith("by operator ")


@pytest.fixture
def standing_robot(safety_alone: Stack) -> Iterator[Stack]:
    """Safety hearing a robot stand still at (6.0, 1.2), at 50 Hz, for as long as the test runs."""
    stop = threading.Event()

    def play() -> None:
        while not stop.is_set():
            now = time.time()
            odom = Odometry(stamp=now, sim_time=now, pose=Pose2D(x=6.0, y=1.2), linear_x=0.0, angular_z=0.0)
            safety_alone.node.publish(keys.ODOM, odom)
            stop.wait(0.02)

    player = threading.Thread(target=play, name="odometry", daemon=True)
    player.start()
    try:
        yield safety_alone
    finally:
        stop.set()
        player.join(timeout=WAIT)


def test_a_plan_the_mode_let_run_moves_nothing_once_supervised_is_back(standing_robot: Stack) -> None:
    stack = standing_robot
    events = Watch(stack.node, keys.SAFETY_EVENTS)
    token = read_token(stack.token_file)

    def mode(to: ControlMode) -> None:
        assert stack.node.call(keys.SET_MODE, ModeRequest(operator="test", token=token, mode=to), timeout=WAIT).ok

    def ask() -> PlanApproval:
        reply: PlanApproval = stack.node.call(
            keys.APPROVAL_REQUEST, ApprovalRequest(goal_id="p1", plan=PLAN), timeout=WAIT
        )
        return reply

    mode(ControlMode.SUPERVISED)
    assert ask().state is ApprovalState.PENDING
    mode(ControlMode.AUTONOMOUS)
    assert ask().state is ApprovalState.APPROVED  # the executor's next ask: the mode lets it run
    n = len(events)
    mode(ControlMode.SUPERVISED)
    denied = events.wait_for(lambda e: e.decision is Decision.DENIED and "plan p1" in e.reason, timeout=WAIT, after=n)
    assert denied is not None and "not an operator's" in denied.reason
    assert ask().state is ApprovalState.DENIED
    goal = SendGoal(goal_id="n1", goal=NavigateToPoseGoal(pose=NEAR))
    reply: GoalResponse = stack.node.call(keys.CMD_NAVIGATE.send_goal, goal, timeout=WAIT)
    assert not reply.accepted and "no plan an operator approved is running" in reply.reason
