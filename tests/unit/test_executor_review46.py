"""Review 46 of the executor: a step's failure says what went wrong, with the kind it is; an object
that left the hand is not put down as if it were still held; what perception said long ago is not
what is seen now; an operator's pause that came with the approval is waited out, not a rejection."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import pytest

from schemas import keys
from schemas.actions import GoalResponse, GoalState, ResultResponse, SendGoal
from schemas.common import Pose2D, Vec3
from schemas.executor import FailureKind, PlanStatus, StepStatus
from schemas.plan import PickStep, Plan, Step, WaitStep
from schemas.robot import FollowJointTrajectoryGoal, NavigateToPoseGoal
from schemas.safety import ApprovalAction, ApprovalRequest, PlanApproval
from schemas.world import FaultInjected, FaultKind, InjectFault
from services.errors import GoalRejected
from services.executor import node as executor_node
from services.executor.armplanning import ArmPlanner
from services.executor.config import ExecutorConfig, StepRetries, StepTimeouts
from services.executor.errors import PreconditionFailed
from services.executor.navigation import BasePlanner
from services.resolver.resolver import Resolver
from services.safety.gate import SafetyGate
from services.sim.simulation import Simulation
from services.worldmodel import WorldModel, load_world
from tests.fastsim import FAST_PHYSICS_HZ
from tests.unit.test_executor_look import EMPTY_WAIT, InMemoryNode, cup_y, frame, joints
from tests.unit.test_executor_pause import WAIT, RobotBehindSafety, Run, SafetyInMemory
from tests.unit.test_executor_pause import gate as gate  # fixture
from tests.unit.test_manipulation import SimRobot, manipulator_for
from tests.unit.test_manipulation import planners as planners  # fixture
from tests.unit.test_runner import ScriptedPlanServices, ScriptedRobot, grounded, run
from tests.unit.test_safety_gate import policy as policy  # fixture

__all__ = ["gate", "planners", "policy"]  # fixtures


def test_a_plan_canceled_while_paused_ends_with_the_kind_canceled(gate: SafetyGate) -> None:
    """Every other cancel gives the plan's result the kind `canceled`; one while an operator's pause
    was waited out gave none."""
    paused = Run(gate)
    try:
        paused.approved_and_driving()
        assert paused.safety.decide("p1", ApprovalAction.PAUSE, "someone in the hall")
        paused.wait_feedback(StepStatus.AWAITING_APPROVAL, 0)
        paused.cancel.set()
        result = paused.ended()
    finally:
        paused.cancel.set()
        paused.thread.join(10.0)
    assert result.status is PlanStatus.CANCELED, result
    assert result.failure is FailureKind.CANCELED, result
    assert (result.steps[0].status, result.steps[0].failure) == (StepStatus.CANCELED, FailureKind.CANCELED)


class ApprovedThenPaused(SafetyInMemory):
    """The operator approves the plan and pauses it at once, both before safety answers the
    executor's next ask (a script's `tether approve` then `tether pause`, a loaded safety)."""

    def __init__(self, gate: SafetyGate) -> None:
        super().__init__(gate)
        self.asked = 0

    def call(self, key: Any, request: ApprovalRequest, timeout: float) -> PlanApproval:
        self.asked += 1
        if self.asked == 2:
            assert self.decide(request.goal_id, ApprovalAction.APPROVE)
            assert self.decide(request.goal_id, ApprovalAction.PAUSE, "hold on")
        return super().call(key, request, timeout)


class ArrivesAtOnce(RobotBehindSafety):
    """Every navigation safety forwards arrives at once."""

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        ruled = self.gate.navigate(SendGoal(goal_id=f"n{len(self.goals)}", goal=goal)).forward
        if isinstance(ruled, GoalResponse):
            raise GoalRejected(ruled.reason, ruled.kind)
        self.forwarded += 1
        return self.ended(goal, GoalState.SUCCEEDED)


def test_a_plan_paused_as_soon_as_it_is_approved_waits_for_the_resume(gate: SafetyGate) -> None:
    """An approved plan paused before the executor heard of the approval was rejected ("paused by
    operator ..."), though the operator only paused it: the resume found no plan to hand back to."""
    paused = Run(gate, robot=ArrivesAtOnce)
    paused.safety = paused.robot.safety = paused.supervision.node = ApprovedThenPaused(gate)  # type: ignore[assignment]
    try:
        paused.thread.start()
        with paused.heard:
            ended_or_waiting = paused.heard.wait_for(
                lambda: (
                    not paused.thread.is_alive()
                    or any(f.status is StepStatus.AWAITING_APPROVAL and f.step == 0 for f in paused.feedback)
                ),
                WAIT,
            )
        assert ended_or_waiting and paused.thread.is_alive(), paused.result
        assert paused.robot.forwarded == 0, "nothing moves while paused"
        assert paused.safety.decide("p1", ApprovalAction.RESUME)
        result = paused.ended()
    finally:
        paused.cancel.set()
        paused.thread.join(WAIT)
    assert result.status is PlanStatus.SUCCEEDED, result
    assert paused.robot.forwarded == 1


def test_a_pick_of_an_object_the_executors_world_does_not_know_fails_naming_it() -> None:
    """A resolver grounded against another world file (or a hostile one) names an object id the
    executor has no model of: no fault of the executor's, a precondition failure saying which."""
    pick = PickStep(
        object_id="unicorn_mug",
        object_name="unicorn mug",
        position=Vec3(x=2.5, y=3.7, z=0.8),
        mass=0.3,
        support_id="kitchen_table",
        approach=Pose2D(x=2.5, y=3.0, yaw=1.57),
    )
    robot = ScriptedRobot()
    result, _ = run(ScriptedPlanServices(resolve=grounded([pick])), robot)
    step = result.steps[0]
    assert (step.status, step.failure) == (StepStatus.FAILED, FailureKind.PRECONDITION), step
    assert "unicorn_mug" in step.message and "world" in step.message, step.message
    assert "executor failed" not in step.message
    assert robot.goals == [], "nothing moves for an object it cannot model"


def test_a_wait_over_its_time_says_it_timed_out_waiting() -> None:
    config = ExecutorConfig(
        timeouts=StepTimeouts(wait=0.2), retries=StepRetries(navigate_to=0, pick=0, place=0, detect=0)
    )
    result, _ = run(ScriptedPlanServices(resolve=grounded([WaitStep(duration=30.0)])), ScriptedRobot(), config=config)
    step = result.steps[0]
    assert (step.status, step.failure) == (StepStatus.FAILED, FailureKind.EXECUTION), step
    assert "timed out after 0.2 s of motion" in step.message, step.message
    assert "canceled" not in step.message, step.message


class CountingSim(SimRobot):
    def __init__(self, sim: Simulation) -> None:
        super().__init__(sim)
        self.trajectories = 0

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> Any:
        self.trajectories += 1
        return super().trajectory(goal, cancel)


@pytest.fixture
def sim() -> Iterator[Simulation]:
    simulation = Simulation(load_world(), physics_hz=FAST_PHYSICS_HZ)
    yield simulation
    simulation.close()


def test_a_place_whose_object_slipped_out_on_the_way_fails_before_the_arm_moves(
    sim: Simulation, planners: tuple[ArmPlanner, BasePlanner]
) -> None:
    """The cup slips out of the gripper while the place's approach drives (the sim's slip fault):
    perception has it on the floor (or a top) after the drive. It was taken for held there, the arm
    went through the place's motions with nothing in the hand."""
    world = WorldModel(sim.world)
    plan = Plan(
        steps=[
            Step(action="navigate_to", target="kitchen counter"),  # type: ignore[arg-type]
            Step(action="pick", target="red cup"),  # type: ignore[arg-type]
            Step(action="place", location="coffee table"),  # type: ignore[arg-type]
        ]
    )
    grounded_plan = Resolver(world).resolve(plan, sim.sensors.perceived_objects(0.0), sim.robot.base_pose())
    robot = CountingSim(sim)
    manipulator = manipulator_for(robot, planners)
    cancel = threading.Event()
    go, pick, place = grounded_plan.steps
    manipulator.drive_to(go.goal, cancel)  # type: ignore[union-attr]
    manipulator.pick(pick, cancel)  # type: ignore[arg-type]
    assert sim.scene.ground_truth().holding == "red_cup"
    assert isinstance(sim.faults.inject(InjectFault(kind=FaultKind.SLIP, target="red_cup")), FaultInjected)
    arm_moves = robot.trajectories
    with pytest.raises(PreconditionFailed) as failed:
        manipulator.place(place, cancel)  # type: ignore[arg-type]
    assert sim.scene.ground_truth().holding is None, "the slip happened on the way"
    assert "red cup" in str(failed.value) and "no longer in the gripper" in str(failed.value), failed.value
    assert robot.trajectories == arm_moves, "the arm must not go through a place with nothing in the hand"


def test_a_report_from_a_perception_that_stopped_long_ago_is_not_what_is_seen_now(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before the executor's first motion (or long after its last) any report counted, however old:
    with perception stopped a minute ago, a detect saw the cup where it stood then, and a pick planned
    its grasp and its arm's way among the objects as they stood then."""
    node = InMemoryNode()
    robot = executor_node.NodeRobot(node, ExecutorConfig())  # type: ignore[arg-type]
    node.deliver(keys.JOINT_STATES, joints(100.0))
    minute_ago = time.monotonic() - 60.0
    with monkeypatch.context() as past:  # received a minute ago: perception has said nothing since
        past.setattr(executor_node, "time", SimpleNamespace(monotonic=lambda: minute_ago))
        node.deliver(keys.OBJECTS, frame(100.0, y=7.4))
    assert robot.look(EMPTY_WAIT) is None
    node.deliver(keys.OBJECTS, frame(160.0, y=7.5))  # perception back: its report is seen at once
    assert cup_y(robot.look(EMPTY_WAIT)) == 7.5
