"""A robot that ignores a cancel, over real processes: the parser, the resolver and the executor run
as they deploy; this test plays safety and the robot behind it (plan check, approval, heartbeat,
odometry, joint states, and a navigation server that keeps driving after its cancel)."""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from schemas import keys
from schemas.actions import CANCEL_ALL, CancelGoal, GoalState
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult, FailureKind, PlanStatus
from schemas.plan import GroundedPlan, PlanApproved, PlanCheckReply
from schemas.robot import (
    ARM_JOINTS,
    JointState,
    NavigateToPoseFeedback,
    NavigateToPoseGoal,
    NavigateToPoseResult,
    Odometry,
)
from schemas.safety import (
    ApprovalRequest,
    ApprovalState,
    EStop,
    EstopSource,
    EstopState,
    PlanApproval,
    SafetyStatus,
)
from services.actionlib import ActionClient, ActionServer, GoalHandle, Outcome
from services.runtime import ALL_SERVICES, Node, NodeSettings
from services.worldmodel import load_world
from tests.integration.conftest import dump_logs, write_config
from tests.procs import wait_until
from tests.sessions import free_ports
from tether.supervisor import Supervisor

WORLD = load_world()
START = WORLD.robot.start
STARTUP_TIMEOUT = 90.0
WAIT = 10.0
# The executor's cancel grace here ([executor] cancel_grace; 10 s by default): the test waits it out.
CANCEL_GRACE = 2.0
# The plan's whole run: the cancel's grace and a margin for a loaded machine.
PLAN_TIMEOUT = CANCEL_GRACE + 30.0
STATE_PERIOD = 0.05


@dataclass
class StubbornRobot:
    """Safety and the robot as the executor sees them, the robot driving on after its cancel."""

    node: Node
    supervisor: Supervisor
    # False: a goal ends canceled at its cancel, as a robot should.
    stubborn: bool = True
    estops: list[EStop] = field(default_factory=list)
    goals: list[str] = field(default_factory=list)
    canceled: list[str] = field(default_factory=list)
    release: threading.Event = field(default_factory=threading.Event)
    stop: threading.Event = field(default_factory=threading.Event)

    def serve(self) -> threading.Thread:
        node = self.node
        node.serve(keys.PLAN_CHECK, self.check)
        node.serve(keys.APPROVAL_REQUEST, self.approval)
        node.subscribe(keys.ESTOP, self.estops.append)
        ActionServer(node, keys.CMD_NAVIGATE, self.drive)
        beat = threading.Thread(target=self.publish_state, name="robot-state", daemon=True)
        beat.start()
        return beat

    def check(self, _plan: GroundedPlan) -> PlanCheckReply:
        return PlanApproved(checks=["stub"])

    def approval(self, request: ApprovalRequest) -> PlanApproval:
        return PlanApproval(goal_id=request.goal_id, state=ApprovalState.NOT_NEEDED)

    def drive(self, handle: GoalHandle[NavigateToPoseGoal, NavigateToPoseFeedback]) -> Outcome[NavigateToPoseResult]:
        self.goals.append(handle.goal_id)
        handle.feedback(NavigateToPoseFeedback(pose=START, distance_remaining=3.0))
        # Stubborn, it drives on until the test ends, canceled or not.
        while not self.release.wait(STATE_PERIOD):
            if handle.should_stop and not self.stubborn:
                self.canceled.append(handle.goal_id)
                return Outcome(GoalState.CANCELED, NavigateToPoseResult(pose=START), "stopped")
        return Outcome(GoalState.SUCCEEDED, NavigateToPoseResult(pose=START), "arrived")

    def publish_state(self) -> None:
        heartbeat = self.node.publisher(keys.HEARTBEAT)
        odom = self.node.publisher(keys.ODOM)
        joints = self.node.publisher(keys.JOINT_STATES)
        seq = 0
        while not self.stop.wait(STATE_PERIOD):
            now = time.time()
            latched = bool(self.estops)
            reason = self.estops[0].reason if latched else ""
            estop = EstopState(latched=latched, source=self.estops[0].source if latched else "", reason=reason)
            heartbeat.put(SafetyStatus(seq=seq, stamp=now, estop=estop))
            odom.put(Odometry(stamp=now, sim_time=now, pose=START, linear_x=0.0, angular_z=0.0))
            joints.put(JointState(stamp=now, name=list(ARM_JOINTS), position=list(WORLD.robot.home_joints)))
            seq += 1


@pytest.fixture
def stubborn(tmp_path: Path) -> Iterator[StubbornRobot]:
    services = ("parser", "resolver", "executor")
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    config = write_config(
        tmp_path / "tether.toml", realtime_factor=1.0, extra=f"[executor]\ncancel_grace = {CANCEL_GRACE}\n"
    )
    supervisor = Supervisor(settings, tmp_path / "logs", config)
    node = Node("safety", settings)
    robot = StubbornRobot(node, supervisor)
    beat: threading.Thread | None = None
    try:
        beat = robot.serve()
        node.declare_alive()
        supervisor.start_all(services)
        missing = node.wait_alive(services, STARTUP_TIMEOUT)
        assert not missing, f"services not up: {missing}"
        yield robot
    finally:
        robot.release.set()
        robot.stop.set()
        if beat is not None:
            beat.join(WAIT)
        node.close()
        supervisor.stop_all()
        dump_logs(supervisor, services)


def test_a_canceled_plan_whose_motion_does_not_stop_fails_and_latches_the_estop(stubborn: StubbornRobot) -> None:
    """The plan is canceled; its navigation goal drives on. The executor must not end the plan as
    canceled (as if the robot had stopped) and take the next plan: it fails naming the motion that
    did not stop and latches the e-stop (source executor), so nothing moves until an operator looks."""
    node = stubborn.node
    feedback: list[ExecutePlanFeedback] = []
    plans = ActionClient(node, keys.EXECUTE_PLAN, lambda _id, fb: feedback.append(fb))
    text = json.dumps({"plan": [{"action": "navigate_to", "target": "kitchen"}]})
    plan = plans.send(ExecutePlanGoal(text=text), timeout=WAIT)
    assert wait_until(lambda: bool(stubborn.goals), WAIT * 3), f"no navigation goal came: {feedback}"
    canceled = node.call(keys.EXECUTE_PLAN.cancel_goal, CancelGoal(goal_id=CANCEL_ALL), timeout=WAIT)
    assert canceled.accepted, canceled
    ended = plan.result(PLAN_TIMEOUT)
    result = ended.result
    assert isinstance(result, ExecutePlanResult), ended
    assert result.status is PlanStatus.FAILED, result
    assert result.failure is FailureKind.EXECUTION, result
    assert f"did not end within {CANCEL_GRACE:g} s of its cancel" in result.reason, result.reason
    assert "e-stop" in result.reason, result.reason
    assert wait_until(lambda: bool(stubborn.estops), WAIT), "the executor did not latch the e-stop"
    assert stubborn.estops[0].source is EstopSource.EXECUTOR
    assert stubborn.goals[0] in stubborn.estops[0].reason, stubborn.estops[0]


def test_an_executor_shutting_down_cancels_the_motion_under_way(stubborn: StubbornRobot) -> None:
    """Stopped (SIGTERM) while a plan drives the base, the executor cancels the plan, and the plan's
    motion on the robot with it: its session must not close before the cancel has gone out."""
    stubborn.stubborn = False
    plans = ActionClient(stubborn.node, keys.EXECUTE_PLAN)
    text = json.dumps({"plan": [{"action": "navigate_to", "target": "kitchen"}]})
    plans.send(ExecutePlanGoal(text=text), timeout=WAIT)
    assert wait_until(lambda: bool(stubborn.goals), WAIT * 3), "no navigation goal came"
    stubborn.supervisor.stop("executor")
    assert wait_until(lambda: stubborn.canceled == stubborn.goals, WAIT), "the motion drives on without its plan"
