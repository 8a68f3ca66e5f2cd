"""`tether send` against an executor played by this test: a real action server on real Zenoh, whose
deciding and carrying out of a plan the test holds and lets go of. Short: no stack to start."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import pytest

from schemas import keys
from schemas.actions import GoalState
from schemas.common import Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, PlanStatus
from services.actionlib import ActionServer, GoalHandle, Outcome
from services.runtime import ALL_SERVICES, Node, NodeSettings
from tests.procs import output_of, tether_process
from tests.sessions import free_ports

WAIT = 20.0
PLAN = json.dumps({"plan": [{"action": "navigate_to", "target": "kitchen"}]})


@dataclass
class StandIn:
    """The executor as `tether send` sees it: `deciding` is set while a goal waits for `decide`
    (the send is unanswered meanwhile); a goal runs until canceled, or does `run` when one is set."""

    node: Node
    deciding: threading.Event = field(default_factory=threading.Event)
    decide: threading.Event = field(default_factory=threading.Event)
    running: threading.Event = field(default_factory=threading.Event)
    ended: list[Outcome[ExecutePlanResult]] = field(default_factory=list)
    run: Callable[[GoalHandle[ExecutePlanGoal, ExecutePlanFeedback]], Outcome[ExecutePlanResult]] | None = None

    def accept(self, goal: ExecutePlanGoal) -> str | None:
        self.deciding.set()
        assert self.decide.wait(WAIT), "the test never let the goal be decided"
        return None

    def execute(self, handle: GoalHandle[ExecutePlanGoal, ExecutePlanFeedback]) -> Outcome[ExecutePlanResult]:
        self.running.set()
        if self.run is not None:
            return self.run(handle)
        stopped = handle.cancel_requested.wait(WAIT)
        status = PlanStatus.CANCELED if stopped else PlanStatus.SUCCEEDED
        result = ExecutePlanResult(status=status, stage=Stage.EXECUTE, reason="stopped" if stopped else "")
        outcome = Outcome(GoalState.CANCELED if stopped else GoalState.SUCCEEDED, result, result.reason)
        self.ended.append(outcome)
        return outcome


@pytest.fixture
def executor() -> Iterator[tuple[StandIn, dict[str, str]]]:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    node = Node("executor", settings)
    try:
        stand_in = StandIn(node)
        ActionServer(node, keys.EXECUTE_PLAN, stand_in.execute, accept=stand_in.accept)
        node.declare_alive()
        env = {**os.environ, "TETHER_ROBOT": settings.robot, "TETHER_BASE_PORT": str(settings.base_port)}
        yield stand_in, env
    finally:
        stand_in.decide.set()
        node.close()


def sending(env: dict[str, str], *args: str) -> contextlib.AbstractContextManager[subprocess.Popen[str]]:
    return tether_process(env, "send", PLAN, "--json", *args)


def test_ctrl_c_before_the_executor_answered_the_send_cancels_the_plan(
    executor: tuple[StandIn, dict[str, str]],
) -> None:
    """A Ctrl-C while the executor decided on the plan (a --preempt waits up to 15 s for the plan it
    preempts) ended send with click's 'Aborted!' and no JSON; the plan, accepted a moment later,
    drove on with nobody to cancel it."""
    stand_in, env = executor
    with sending(env, "--wait") as sender:
        assert stand_in.deciding.wait(WAIT), sender.communicate()
        os.kill(sender.pid, signal.SIGINT)
        stand_in.decide.set()
        out, err = output_of(sender, WAIT)
    assert sender.returncode == 1, out + err
    document = json.loads(out)
    assert document["status"] == "canceled", document
    # Accepted after the cancel came, it is rejected for it; or, accepted before, it is canceled.
    assert not stand_in.running.is_set() or [o.state for o in stand_in.ended] == [GoalState.CANCELED], err


def test_a_plan_that_ended_without_a_result_is_no_success(executor: tuple[StandIn, dict[str, str]]) -> None:
    """An executor whose run of the plan raised ends the goal aborted, with no result: send --wait
    printed status 'accepted' and exited 0, as if the plan had gone on moving."""
    stand_in, env = executor
    stand_in.decide.set()

    def breaks(handle: GoalHandle[ExecutePlanGoal, ExecutePlanFeedback]) -> Outcome[ExecutePlanResult]:
        raise RuntimeError("the runner broke")

    stand_in.run = breaks
    with sending(env, "--wait") as sender:
        out, err = output_of(sender, WAIT)
    assert sender.returncode == 1, out + err
    document = json.loads(out)
    assert (document["status"], document["stage"]) == ("failed", "execute"), document
    assert "the runner broke" in document["reason"], document
    # `tether goal` said exit 0, 'running or succeeded', for it too.
    command = [sys.executable, "-m", "tether", "goal", document["goal_id"], "--json"]
    asked = subprocess.run(command, env=env, capture_output=True, text=True, timeout=WAIT, start_new_session=True)
    assert asked.returncode == 1, asked.stdout + asked.stderr
    progress = json.loads(asked.stdout)
    assert progress["state"] == "aborted", asked.stdout
    # Its --json said "result": null with that exit 1; the words said the plan failed.
    assert progress["result"]["status"] == "failed" and "the runner broke" in progress["result"]["reason"], progress


def test_ctrl_c_while_waiting_cancels_the_plan_and_says_so(executor: tuple[StandIn, dict[str, str]]) -> None:
    stand_in, env = executor
    stand_in.decide.set()
    with sending(env, "--wait") as sender:
        assert stand_in.running.wait(WAIT), sender.communicate()
        os.kill(sender.pid, signal.SIGINT)
        out, err = output_of(sender, WAIT)
    assert sender.returncode == 1, out + err
    document = json.loads(out)
    assert (document["status"], document["reason"]) == ("canceled", "stopped"), document
    assert [o.state for o in stand_in.ended] == [GoalState.CANCELED]
