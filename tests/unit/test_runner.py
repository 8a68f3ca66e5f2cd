"""The executor's plan runner with scripted planner and robot: stages, failures, cancel."""

from __future__ import annotations

import threading
from typing import Any, cast

from schemas.actions import GoalState, ResultResponse
from schemas.common import ErrorKind, Pose2D, ServiceError, Stage, Vec3
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, PlanStatus, StepStatus
from schemas.plan import GroundedPlan, NavigateStep, Plan, PlanApproved, SayStep, Step, WaitStep
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, Twist
from schemas.world import PerceivedObject
from services.executor.config import ExecutorConfig
from services.executor.kinematics import ArmKinematics
from services.executor.manipulation import Manipulator
from services.executor.runner import PlanRunner
from services.runtime import CallError
from services.worldmodel import WorldModel, load_world

PLAN = Plan(steps=[Step(action="navigate_to", target="kitchen"), Step(action="say", target="hi")])  # type: ignore[arg-type]
GROUNDED = GroundedPlan(
    steps=[NavigateStep(target="kitchen", goal=Pose2D(x=2.5, y=2.5)), SayStep(text="hi")], source=PLAN
)


class ScriptedPlanner:
    def __init__(self, parse: Any = PLAN, resolve: Any = GROUNDED, check: Any = None) -> None:
        self.replies = {"parse": parse, "resolve": resolve, "check": check or PlanApproved()}
        self.asked: list[str] = []

    def _reply(self, stage: str) -> Any:
        self.asked.append(stage)
        reply = self.replies[stage]
        if isinstance(reply, CallError):
            raise reply
        return reply

    def parse(self, text: str, fmt: str) -> Any:
        return self._reply("parse")

    def resolve(self, plan: Plan) -> Any:
        return self._reply("resolve")

    def check(self, plan: GroundedPlan) -> Any:
        return self._reply("check")


class ScriptedRobot:
    """Navigation ends as scripted; waits for cancel when told to block."""

    def __init__(self, state: GoalState = GoalState.SUCCEEDED, block: bool = False) -> None:
        self.state = state
        self.block = block
        self.goals: list[NavigateToPoseGoal] = []
        self.started = threading.Event()

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        self.started.set()
        if self.block:
            cancel.wait(5.0)
            return ResultResponse(goal_id="g", state=GoalState.CANCELED, message="canceled")
        return ResultResponse(
            goal_id="g", state=self.state, message="stalled" if self.state is not GoalState.SUCCEEDED else ""
        )

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]:
        raise AssertionError("no arm motion in these plans")

    def gripper(self, goal: GripperCommandGoal, cancel: threading.Event) -> ResultResponse[Any]:
        raise AssertionError("no gripper motion in these plans")

    def cmd_vel(self, twist: Twist) -> None:
        pass

    def base_pose(self) -> Pose2D | None:
        return Pose2D(x=6.0, y=1.2)

    def arm_positions(self) -> list[float] | None:
        return None

    def object_position(self, object_id: str) -> Vec3 | None:
        return None

    def held_object(self) -> str | None:
        return None

    def next_perception(self, object_id: str, timeout: float) -> PerceivedObject | None:
        return None


def runner(planner: ScriptedPlanner, robot: ScriptedRobot) -> PlanRunner:
    world = WorldModel(load_world())
    # These plans never move the arm, so the kinematics are never asked.
    manipulator = Manipulator(robot, cast(ArmKinematics, None), world, ExecutorConfig())
    return PlanRunner(planner, robot, manipulator)


def run(planner: ScriptedPlanner, robot: ScriptedRobot, cancel: threading.Event | None = None) -> Any:
    feedback: list[ExecutePlanFeedback] = []
    result = runner(planner, robot).run(ExecutePlanGoal(text="..."), cancel or threading.Event(), feedback.append)
    return result, feedback


def test_a_plan_runs_every_step_and_reports_each() -> None:
    robot = ScriptedRobot()
    result, feedback = run(ScriptedPlanner(), robot)
    assert result.status is PlanStatus.SUCCEEDED
    assert [s.status for s in result.steps] == [StepStatus.SUCCEEDED, StepStatus.SUCCEEDED]
    assert robot.goals[0].pose == Pose2D(x=2.5, y=2.5)
    assert [f.stage for f in feedback[:3]] == [Stage.PARSE, Stage.RESOLVE, Stage.SAFETY]


def test_a_refusal_at_any_stage_is_a_rejection_there_and_nothing_moves() -> None:
    refusal = ServiceError(kind=ErrorKind.VETOED, message="inside keep-out zone 'stairs'", stage=Stage.SAFETY)
    for stage, planner in (
        (Stage.PARSE, ScriptedPlanner(parse=ServiceError(kind=ErrorKind.UNKNOWN_ACTION, message="teleport"))),
        (Stage.RESOLVE, ScriptedPlanner(resolve=ServiceError(kind=ErrorKind.AMBIGUOUS_NAME, message="cup", step=0))),
        (Stage.SAFETY, ScriptedPlanner(check=refusal)),
    ):
        robot = ScriptedRobot()
        result, _ = run(planner, robot)
        assert (result.status, result.stage) == (PlanStatus.REJECTED, stage)
        assert robot.goals == []
    unreachable = CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message="no reply", stage=Stage.SAFETY))
    result, _ = run(ScriptedPlanner(check=unreachable), ScriptedRobot())
    assert (result.status, result.stage, result.reason) == (PlanStatus.REJECTED, Stage.SAFETY, "no reply")


def test_dry_run_checks_everything_and_moves_nothing() -> None:
    robot = ScriptedRobot()
    result = runner(ScriptedPlanner(), robot).run(
        ExecutePlanGoal(text="...", dry_run=True), threading.Event(), list().append
    )
    assert result.status is PlanStatus.SUCCEEDED and result.stage is Stage.SAFETY
    assert robot.goals == []


def test_a_failed_step_fails_the_plan_and_skips_the_rest() -> None:
    result, _ = run(ScriptedPlanner(), ScriptedRobot(state=GoalState.ABORTED))
    assert result.status is PlanStatus.FAILED
    assert [s.status for s in result.steps] == [StepStatus.FAILED, StepStatus.SKIPPED]
    assert "stalled" in result.reason


def test_cancel_stops_the_running_step() -> None:
    robot = ScriptedRobot(block=True)
    cancel = threading.Event()
    box: list[Any] = []
    worker = threading.Thread(target=lambda: box.append(run(ScriptedPlanner(), robot, cancel)))
    worker.start()
    assert robot.started.wait(5.0)
    cancel.set()
    worker.join(5.0)
    result, _ = box[0]
    assert result.status is PlanStatus.CANCELED
    assert [s.status for s in result.steps] == [StepStatus.CANCELED, StepStatus.SKIPPED]


def test_a_wait_step_ends_early_on_cancel() -> None:
    plan = GroundedPlan(steps=[WaitStep(duration=30.0)], source=PLAN)
    cancel = threading.Event()
    cancel.set()
    result, _ = run(ScriptedPlanner(resolve=plan), ScriptedRobot(), cancel)
    assert result.status is PlanStatus.CANCELED


def test_the_plan_side_knows_no_robot_command_key_and_no_reset() -> None:
    """Invariants 1 and 3 by construction: parser, resolver and executor never name a robot/**
    command key or the e-stop reset, so no plan can reach either."""
    from pathlib import Path

    import services

    forbidden = ("ROBOT_NAVIGATE", "ROBOT_TRAJECTORY", "ROBOT_GRIPPER", "ROBOT_CMD_VEL", '"robot/', "RESET", "reset")
    for package in ("parser", "resolver", "executor"):
        for path in (Path(services.__file__).parent / package).glob("*.py"):
            source = path.read_text()
            for name in forbidden:
                assert name not in source, f"{path} names {name}"
