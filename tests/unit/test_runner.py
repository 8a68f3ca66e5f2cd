"""The executor's plan runner with scripted planner and robot: stages, failures, cancel."""

from __future__ import annotations

import functools
import math
import re
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest

from schemas.actions import GoalState, ResultResponse
from schemas.common import ErrorKind, Pose2D, ServiceError, Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, FailureKind, PlanStatus, StepStatus
from schemas.plan import (
    Fallback,
    GripperStep,
    GroundedPlan,
    NavigateStep,
    Plan,
    PlanApproved,
    SayStep,
    Step,
    WaitStep,
)
from schemas.robot import (
    GRIPPER_MAX_GAP,
    FollowJointTrajectoryGoal,
    GripperCommandGoal,
    GripperCommandResult,
    NavigateToPoseGoal,
    Twist,
)
from schemas.world import PerceivedObject
from services.errors import CallError, GoalRejected
from services.executor import runner as runner_module
from services.executor.armplanning import ArmPlanner
from services.executor.config import ExecutorConfig, StepRetries, StepTimeouts
from services.executor.manipulation import Manipulator
from services.executor.navigation import BasePlanner
from services.executor.runner import PlanRunner, StepClock
from services.worldmodel import WorldModel, load_world

PLAN = Plan(steps=[Step(action="navigate_to", target="kitchen"), Step(action="say", target="hi")])  # type: ignore[arg-type]
GROUNDED = GroundedPlan(
    steps=[NavigateStep(target="kitchen", goal=Pose2D(x=2.5, y=2.5)), SayStep(text="hi")], source=PLAN
)


class ScriptedPlanServices:
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


# Where the scripted base stands before it moves: in the living room, facing east.
START = Pose2D(x=6.0, y=1.2)
# Where a navigation that succeeds leaves the base, from where it started and its goal pose.
Stop = Callable[[Pose2D, Pose2D], Pose2D]


def at_goal(start: Pose2D, goal: Pose2D) -> Pose2D:
    return goal


def short_of(metres: float) -> Stop:
    """A robot that says it arrived having stopped `metres` short, on the straight line from its start."""

    def stop(start: Pose2D, goal: Pose2D) -> Pose2D:
        way = math.dist((start.x, start.y), (goal.x, goal.y))
        left = min(metres, way) / way if way > 0 else 0.0
        return Pose2D(x=goal.x - (goal.x - start.x) * left, y=goal.y - (goal.y - start.y) * left, yaw=goal.yaw)

    return stop


class ScriptedRobot:
    """Navigation ends as scripted (per goal pose in `outcomes`, else `state`); waits for cancel
    when told to block. One that succeeds leaves the base where `stops` says (at the goal; a lying
    robot elsewhere), and odometry then reports it unless `odometry_after` is off (none comes after
    a motion, as NodeRobot.base_pose answers then). The gripper succeeds and holds nothing."""

    def __init__(
        self,
        state: GoalState = GoalState.SUCCEEDED,
        block: bool = False,
        outcomes: dict[Pose2D, GoalState | str] | None = None,
        holding: str | None = None,
        stop_reason: str | None = None,
        stops: Stop = at_goal,
        odometry_after: bool = True,
    ) -> None:
        self.pose = START
        self.stops = stops
        self.odometry_after = odometry_after
        self.moved = False
        self.state = state
        self.block = block
        # A GoalState ends the goal so; a string is a rejection by safety with that reason.
        self.outcomes = outcomes or {}
        self.holding = holding
        self.stop_reason = stop_reason
        self.goals: list[NavigateToPoseGoal] = []
        self.grips: list[GripperCommandGoal] = []
        self.started = threading.Event()
        self.scale = 1.0

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        self.started.set()
        if self.block:
            cancel.wait(5.0)
            return ResultResponse(goal_id="g", state=GoalState.CANCELED, message="canceled")
        state = self.outcomes.get(goal.pose, self.state)
        if not isinstance(state, GoalState):
            raise GoalRejected(state, ErrorKind.VETOED)
        return self.ended(goal, state, "stalled" if state is not GoalState.SUCCEEDED else "")

    def ended(self, goal: NavigateToPoseGoal, state: GoalState, message: str = "") -> ResultResponse[Any]:
        """The navigation to `goal` ends in `state`: the base stops as scripted if it succeeded."""
        self.moved = True
        if state is GoalState.SUCCEEDED:
            self.pose = self.stops(self.pose, goal.pose)
        return ResultResponse(goal_id="g", state=state, message=message)

    def trajectory(self, goal: FollowJointTrajectoryGoal, cancel: threading.Event) -> ResultResponse[Any]:
        raise AssertionError("no arm motion in these plans")

    def gripper(self, goal: GripperCommandGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.grips.append(goal)
        result = GripperCommandResult(position=goal.position, stalled=False, reached_goal=True)
        return ResultResponse(goal_id="g", state=GoalState.SUCCEEDED, result=result)

    def cmd_vel(self, twist: Twist) -> None:
        pass

    def base_pose(self) -> Pose2D | None:
        return self.pose if self.odometry_after or not self.moved else None

    def arm_positions(self) -> list[float] | None:
        return list(WORLD.world.robot.home_joints)  # stowed: driving needs no arm motion first

    def held_object(self) -> str | None:
        return self.holding

    def look(self, timeout: float, *, new: bool = False) -> list[PerceivedObject] | None:
        return []

    def safety_stop(self) -> str | None:
        return self.stop_reason

    def speed_scale(self) -> float:
        return self.scale

    def people(self) -> list[Pose2D]:
        return []

    def remembered(self, object_id: str) -> PerceivedObject | None:
        return None


WORLD = WorldModel(load_world())
# The plans here test the runner's order of things: a failed step is not tried again unless a test says so.
NO_RETRIES = ExecutorConfig(
    retries=StepRetries(navigate_to=0, pick=0, place=0, detect=0, gripper=0, say=0, wait=0, stop=0)
)


@functools.cache
def planners() -> tuple[ArmPlanner, BasePlanner]:
    """Real planners, built once: the base's routes are planned for real; these plans move no arm."""
    return ArmPlanner(WORLD), BasePlanner(WORLD)


def runner(planner: ScriptedPlanServices, robot: ScriptedRobot, config: ExecutorConfig = NO_RETRIES) -> PlanRunner:
    arm, base = planners()
    return PlanRunner(planner, robot, Manipulator(robot, arm, base, WORLD, config), config)


def run(
    planner: ScriptedPlanServices,
    robot: ScriptedRobot,
    cancel: threading.Event | None = None,
    config: ExecutorConfig = NO_RETRIES,
) -> Any:
    feedback: list[ExecutePlanFeedback] = []
    result = runner(planner, robot, config).run(
        ExecutePlanGoal(text="..."), cancel or threading.Event(), feedback.append
    )
    return result, feedback


def test_a_plan_runs_every_step_and_reports_each() -> None:
    robot = ScriptedRobot()
    result, feedback = run(ScriptedPlanServices(), robot)
    assert result.status is PlanStatus.SUCCEEDED
    assert [s.status for s in result.steps] == [StepStatus.SUCCEEDED, StepStatus.SUCCEEDED]
    assert robot.goals[0].pose == Pose2D(x=2.5, y=2.5)
    assert [f.stage for f in feedback[:3]] == [Stage.PARSE, Stage.RESOLVE, Stage.SAFETY]


def test_a_refusal_at_any_stage_is_a_rejection_there_and_nothing_moves() -> None:
    refusal = ServiceError(kind=ErrorKind.VETOED, message="inside keep-out zone 'stairs'", stage=Stage.SAFETY)
    for stage, planner in (
        (Stage.PARSE, ScriptedPlanServices(parse=ServiceError(kind=ErrorKind.UNKNOWN_ACTION, message="teleport"))),
        (
            Stage.RESOLVE,
            ScriptedPlanServices(resolve=ServiceError(kind=ErrorKind.AMBIGUOUS_NAME, message="cup", step=0)),
        ),
        (Stage.SAFETY, ScriptedPlanServices(check=refusal)),
    ):
        robot = ScriptedRobot()
        result, _ = run(planner, robot)
        assert (result.status, result.stage) == (PlanStatus.REJECTED, stage)
        assert robot.goals == []
    unreachable = CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message="no reply", stage=Stage.SAFETY))
    result, _ = run(ScriptedPlanServices(check=unreachable), ScriptedRobot())
    assert (result.status, result.stage, result.reason) == (PlanStatus.REJECTED, Stage.SAFETY, "no reply")


def test_dry_run_checks_everything_and_moves_nothing() -> None:
    robot = ScriptedRobot()
    result = runner(ScriptedPlanServices(), robot).run(
        ExecutePlanGoal(text="...", dry_run=True), threading.Event(), list[ExecutePlanFeedback]().append
    )
    assert result.status is PlanStatus.SUCCEEDED and result.stage is Stage.SAFETY
    assert robot.goals == []


def test_a_failed_step_fails_the_plan_and_skips_the_rest() -> None:
    result, _ = run(ScriptedPlanServices(), ScriptedRobot(state=GoalState.ABORTED))
    assert result.status is PlanStatus.FAILED
    assert [s.status for s in result.steps] == [StepStatus.FAILED, StepStatus.SKIPPED]
    assert "stalled" in result.reason


def test_cancel_stops_the_running_step() -> None:
    robot = ScriptedRobot(block=True)
    cancel = threading.Event()
    box: list[Any] = []
    worker = threading.Thread(target=lambda: box.append(run(ScriptedPlanServices(), robot, cancel)))
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
    result, _ = run(ScriptedPlanServices(resolve=plan), ScriptedRobot(), cancel)
    assert result.status is PlanStatus.CANCELED


def test_the_plan_side_knows_no_robot_command_key_and_no_reset() -> None:
    """Invariants 1 and 3 by construction: parser, resolver and executor never name a robot/**
    command key or the e-stop reset, so no plan can reach either."""
    from pathlib import Path

    import services

    # Whole words, so "preset" is not "reset".
    forbidden = ("ROBOT_NAVIGATE", "ROBOT_TRAJECTORY", "ROBOT_GRIPPER", "ROBOT_CMD_VEL", "RESET", "reset")
    for package in ("parser", "resolver", "executor"):
        for path in (Path(services.__file__).parent / package).glob("*.py"):
            source = path.read_text()
            assert '"robot/' not in source, f"{path} names a robot/ key"
            for name in forbidden:
                assert not re.search(rf"\b{name}\b", source), f"{path} names {name}"


# Sub-steps, on_failure alternatives and the gripper

KITCHEN = Pose2D(x=2.5, y=2.5)
HALLWAY = Pose2D(x=10.0, y=7.0)
# Inside the living room's coffee table: no route reaches it.
INSIDE_COFFEE_TABLE = Pose2D(x=8.0, y=2.5)
DOCK = Pose2D(x=11.2, y=0.8)


def go(pose: Pose2D, name: str = "somewhere") -> NavigateStep:
    return NavigateStep(target=name, goal=pose)


def grounded(
    steps: list[Any], labels: list[str] | None = None, fallbacks: list[Fallback] | None = None
) -> GroundedPlan:
    return GroundedPlan(
        steps=steps, source=PLAN, labels=labels or [str(i + 1) for i in range(len(steps))], fallbacks=fallbacks or []
    )


def outcome(plan: GroundedPlan, robot: ScriptedRobot, cancel: threading.Event | None = None) -> Any:
    result, _ = run(ScriptedPlanServices(resolve=plan), robot, cancel)
    return result


def table(result: Any) -> list[tuple[str | None, StepStatus]]:
    return [(s.label, s.status) for s in result.steps]


def test_results_and_feedback_carry_the_label_of_each_step() -> None:
    plan = grounded([go(KITCHEN), SayStep(text="a"), SayStep(text="b")], labels=["1", "2.1", "2.2"])
    result, feedback = run(ScriptedPlanServices(resolve=plan), ScriptedRobot())
    assert table(result) == [("1", StepStatus.SUCCEEDED), ("2.1", StepStatus.SUCCEEDED), ("2.2", StepStatus.SUCCEEDED)]
    assert [f.label for f in feedback if f.status is StepStatus.SUCCEEDED] == ["1", "2.1", "2.2"]


def test_gripper_steps_use_the_gripper_action() -> None:
    robot = ScriptedRobot()
    result = outcome(grounded([GripperStep(open=False), GripperStep(open=True)]), robot)
    assert result.status is PlanStatus.SUCCEEDED
    assert [g.position for g in robot.grips] == [0.0, GRIPPER_MAX_GAP]
    assert all(g.object_id is None for g in robot.grips)
    assert "holding nothing" in result.steps[0].message


def test_opening_the_gripper_never_drops_what_it_holds() -> None:
    robot = ScriptedRobot(holding="red_cup")
    result = outcome(grounded([GripperStep(open=True)]), robot)
    assert result.status is PlanStatus.FAILED and "would drop red cup" in result.reason
    assert robot.grips == []
    # Closing on what it holds sends nothing: it is closed already.
    result = outcome(grounded([GripperStep(open=False)]), robot)
    assert result.status is PlanStatus.SUCCEEDED and robot.grips == []


def test_the_plan_speed_limit_reaches_the_navigation_goal() -> None:
    robot = ScriptedRobot()
    outcome(grounded([NavigateStep(target="1.00 m forward", goal=KITCHEN, max_speed=0.2), go(DOCK)]), robot)
    assert [g.max_speed for g in robot.goals] == [0.2, NavigateToPoseGoal(pose=DOCK).max_speed]


def test_a_failed_step_runs_its_on_failure_and_the_plan_goes_on_after_it() -> None:
    # Step 1 is a group (1.1, 1.2); 1.1 fails, so 1.2 is skipped, the alternative runs, then step 2.
    alternative = Fallback(
        first=0, last=1, steps=[go(DOCK), SayStep(text="sorry")], labels=["1 on_failure 1", "1 on_failure 2"]
    )
    plan = grounded([go(KITCHEN), SayStep(text="there"), go(HALLWAY)], ["1.1", "1.2", "2"], [alternative])
    robot = ScriptedRobot(outcomes={KITCHEN: GoalState.ABORTED})
    result = outcome(plan, robot)
    assert result.status is PlanStatus.SUCCEEDED
    assert table(result) == [
        ("1.1", StepStatus.FAILED),
        ("1 on_failure 1", StepStatus.SUCCEEDED),
        ("1 on_failure 2", StepStatus.SUCCEEDED),
        ("1.2", StepStatus.SKIPPED),
        ("2", StepStatus.SUCCEEDED),
    ]
    assert [g.pose for g in robot.goals] == [KITCHEN, DOCK, HALLWAY]
    assert "step 1.1 (navigate_to) failed (execution): navigation aborted: stalled" in result.reason
    assert "on_failure ran instead" in result.reason


def test_when_the_on_failure_fails_too_the_plan_fails_with_both_reasons() -> None:
    alternative = Fallback(
        first=0, last=0, steps=[go(DOCK), SayStep(text="never")], labels=["1 on_failure 1", "1 on_failure 2"]
    )
    plan = grounded([go(KITCHEN), go(HALLWAY)], fallbacks=[alternative])
    robot = ScriptedRobot(outcomes={KITCHEN: GoalState.ABORTED, DOCK: GoalState.ABORTED})
    result = outcome(plan, robot)
    assert result.status is PlanStatus.FAILED
    assert result.reason == (
        "step 1 (navigate_to) failed (execution): navigation aborted: stalled; "
        "then step 1 on_failure 1 (navigate_to) failed (execution): navigation aborted: stalled"
    )
    assert table(result) == [
        ("1", StepStatus.FAILED),
        ("1 on_failure 1", StepStatus.FAILED),
        ("1 on_failure 2", StepStatus.SKIPPED),
        ("2", StepStatus.SKIPPED),
    ]
    assert [g.pose for g in robot.goals] == [KITCHEN, DOCK]


def test_an_enclosing_on_failure_takes_over_when_the_inner_one_fails() -> None:
    # Step 1 is a group whose sub-step 1.1 has its own on_failure; both alternatives are tried.
    inner = Fallback(first=0, last=0, steps=[go(DOCK)], labels=["1.1 on_failure 1"])
    outer = Fallback(first=0, last=1, steps=[SayStep(text="gave up")], labels=["1 on_failure 1"])
    plan = grounded([go(KITCHEN), SayStep(text="x"), go(HALLWAY)], ["1.1", "1.2", "2"], [inner, outer])
    robot = ScriptedRobot(outcomes={KITCHEN: GoalState.ABORTED, DOCK: GoalState.ABORTED})
    result = outcome(plan, robot)
    assert result.status is PlanStatus.SUCCEEDED
    assert table(result) == [
        ("1.1", StepStatus.FAILED),
        ("1.1 on_failure 1", StepStatus.FAILED),
        ("1 on_failure 1", StepStatus.SUCCEEDED),
        ("1.2", StepStatus.SKIPPED),
        ("2", StepStatus.SUCCEEDED),
    ]
    # When the inner one works, the group goes on with 1.2.
    robot = ScriptedRobot(outcomes={KITCHEN: GoalState.ABORTED})
    result = outcome(plan, robot)
    assert [label for label, status in table(result) if status is StepStatus.SUCCEEDED] == [
        "1.1 on_failure 1",
        "1.2",
        "2",
    ]


def test_no_on_failure_runs_after_a_veto_an_estop_or_an_interruption() -> None:
    alternative = Fallback(first=0, last=0, steps=[SayStep(text="should not be said")], labels=["1 on_failure 1"])
    plan = grounded([go(KITCHEN), go(HALLWAY)], fallbacks=[alternative])
    for robot, why in (
        (ScriptedRobot(outcomes={KITCHEN: "vetoed by safety: inside keep-out zone"}), "safety refused the motion"),
        (ScriptedRobot(state=GoalState.ABORTED, stop_reason="e-stop latched by operator: test"), "e-stop latched"),
        (ScriptedRobot(outcomes={KITCHEN: GoalState.CANCELED}), "the robot side ended the motion"),
    ):
        result = outcome(plan, robot)
        assert result.status is PlanStatus.FAILED, why
        assert f"no on_failure runs: {why}" in result.reason
        assert table(result) == [("1", StepStatus.FAILED), ("2", StepStatus.SKIPPED)]
        assert [g.pose for g in robot.goals] == [KITCHEN]


def test_no_on_failure_runs_after_a_cancel() -> None:
    alternative = Fallback(first=0, last=0, steps=[SayStep(text="should not be said")], labels=["1 on_failure 1"])
    robot = ScriptedRobot(block=True)
    cancel = threading.Event()
    box: list[Any] = []
    plan = grounded([go(KITCHEN), go(HALLWAY)], fallbacks=[alternative])
    worker = threading.Thread(target=lambda: box.append(outcome(plan, robot, cancel)))
    worker.start()
    assert robot.started.wait(5.0)
    cancel.set()
    worker.join(5.0)
    result = box[0]
    assert result.status is PlanStatus.CANCELED
    assert table(result) == [("1", StepStatus.CANCELED), ("2", StepStatus.SKIPPED)]


def test_a_dry_run_lists_the_alternatives_after_the_steps_they_cover() -> None:
    alternative = Fallback(first=0, last=1, steps=[SayStep(text="sorry")], labels=["1 on_failure 1"])
    plan = grounded([go(KITCHEN), SayStep(text="x"), go(HALLWAY)], ["1.1", "1.2", "2"], [alternative])
    robot = ScriptedRobot()
    result = runner(ScriptedPlanServices(resolve=plan), robot).run(
        ExecutePlanGoal(text="...", dry_run=True), threading.Event(), list[ExecutePlanFeedback]().append
    )
    assert [s.label for s in result.steps] == ["1.1", "1.2", "1 on_failure 1", "2"]
    assert robot.goals == []


# Retries, the step's clock and failure kinds


class FlakyRobot(ScriptedRobot):
    """Navigation aborts the first `failures` times, then arrives."""

    def __init__(self, failures: int) -> None:
        super().__init__()
        self.failures = failures

    def navigate(self, goal: NavigateToPoseGoal, cancel: threading.Event) -> ResultResponse[Any]:
        self.goals.append(goal)
        state = GoalState.ABORTED if len(self.goals) <= self.failures else GoalState.SUCCEEDED
        return self.ended(goal, state, "stalled: is the way blocked?")


def retrying(navigate_to: int) -> ExecutorConfig:
    return ExecutorConfig(retries=StepRetries(navigate_to=navigate_to))


def test_a_failed_motion_is_planned_anew_and_tried_again_up_to_the_configured_retries() -> None:
    robot = FlakyRobot(failures=2)
    result, feedback = run(ScriptedPlanServices(resolve=grounded([go(KITCHEN)])), robot, config=retrying(2))
    assert result.status is PlanStatus.SUCCEEDED
    assert (result.steps[0].status, result.steps[0].attempts) == (StepStatus.SUCCEEDED, 3)
    assert len(robot.goals) == 3, "each try a new navigation goal, each with a freshly planned route"
    retries = [f for f in feedback if f.attempt > 1 and f.status is StepStatus.RUNNING and f.failure]
    assert [f.attempt for f in retries] == [2, 3]
    assert retries[0].failure is FailureKind.EXECUTION
    assert "attempt 1 failed (execution): navigation aborted: stalled" in retries[0].message
    # One retry too few: the step fails, saying how often it was tried and what kind of failure it was.
    result, _ = run(ScriptedPlanServices(resolve=grounded([go(KITCHEN)])), FlakyRobot(failures=2), config=retrying(1))
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.EXECUTION)
    assert (result.steps[0].failure, result.steps[0].attempts) == (FailureKind.EXECUTION, 2)
    assert result.reason.startswith("step 1 (navigate_to) failed after 2 attempts (execution): navigation aborted")


def test_a_veto_is_never_retried_and_says_so() -> None:
    robot = ScriptedRobot(outcomes={KITCHEN: "inside keep-out zone 'stairs'"})
    result, _ = run(ScriptedPlanServices(resolve=grounded([go(KITCHEN)])), robot, config=retrying(2))
    assert (result.status, result.failure, result.steps[0].attempts) == (PlanStatus.FAILED, FailureKind.VETOED, 1)
    assert len(robot.goals) == 1


def test_failure_kinds_name_what_went_wrong() -> None:
    inside_the_table = Pose2D(x=8.0, y=2.5)  # the coffee table's centre: no route can end there
    result, _ = run(ScriptedPlanServices(resolve=grounded([go(inside_the_table)])), ScriptedRobot())
    assert result.failure is FailureKind.PLANNING and "coffee table" in result.reason
    result, _ = run(ScriptedPlanServices(resolve=grounded([GripperStep(open=True)])), ScriptedRobot(holding="red_cup"))
    assert result.failure is FailureKind.PRECONDITION
    robot = ScriptedRobot(block=True)
    cancel = threading.Event()
    cancel.set()
    result, _ = run(ScriptedPlanServices(resolve=grounded([go(KITCHEN)])), robot, cancel)
    assert (result.status, result.steps[0].failure) == (PlanStatus.CANCELED, FailureKind.CANCELED)


def timed(navigate_to: float) -> ExecutorConfig:
    return ExecutorConfig(timeouts=StepTimeouts(navigate_to=navigate_to), retries=NO_RETRIES.retries)


def test_a_step_over_its_time_is_canceled_and_fails() -> None:
    robot = ScriptedRobot(block=True)
    started = time.monotonic()
    result, _ = run(ScriptedPlanServices(resolve=grounded([go(KITCHEN)])), robot, config=timed(0.3))
    assert time.monotonic() - started < 3.0
    assert (result.status, result.failure) == (PlanStatus.FAILED, FailureKind.EXECUTION)
    assert "timed out after 0.3 s of motion" in result.reason


def test_time_paused_for_a_person_does_not_count() -> None:
    robot = ScriptedRobot(block=True)
    robot.scale = 0.0  # safety holds the robot still: a person is too close
    cancel = threading.Event()
    box: list[Any] = []
    worker = threading.Thread(
        target=lambda: box.append(run(ScriptedPlanServices(resolve=grounded([go(KITCHEN)])), robot, cancel, timed(0.3)))
    )
    worker.start()
    assert robot.started.wait(5.0)
    worker.join(1.0)
    assert worker.is_alive(), "paused, the step is still waiting after three times its time"
    robot.scale = 1.0
    worker.join(5.0)
    result, _ = box[0]
    assert result.failure is FailureKind.EXECUTION and "timed out" in result.reason


class CanceledWhilePlanning(ScriptedRobot):
    """The plan's cancel lands as the step plans its route (people are asked for just before)."""

    def __init__(self, cancel: threading.Event) -> None:
        super().__init__()
        self.cancel = cancel

    def people(self) -> list[Pose2D]:
        self.cancel.set()
        return []


@pytest.mark.parametrize("retries", [0, 2])
def test_a_plan_canceled_while_a_try_fails_ends_canceled_not_failed(retries: int) -> None:
    """A cancel, then the try fails on its own (no route into a table): the plan ends canceled, with
    no retry, so nothing (the planner's recovery) takes it for a failure to mend after the cancel."""
    cancel = threading.Event()
    robot = CanceledWhilePlanning(cancel)
    plan = grounded([go(INSIDE_COFFEE_TABLE, "coffee table"), go(KITCHEN)])
    result, _ = run(ScriptedPlanServices(resolve=plan), robot, cancel, retrying(retries))
    assert (result.status, result.failure) == (PlanStatus.CANCELED, FailureKind.CANCELED), result.reason
    assert [s.status for s in result.steps] == [StepStatus.CANCELED, StepStatus.SKIPPED]
    assert "the try had failed" in result.steps[0].message and result.steps[0].attempts == 1
    assert robot.goals == [], "nothing was sent to the robot"


def test_a_steps_cancel_is_set_the_moment_the_goal_is_canceled(monkeypatch: pytest.MonkeyPatch) -> None:
    """A motion is sent only if the step's cancel is not set: it must not wait for the clock's round."""
    monkeypatch.setattr(runner_module, "CLOCK_PERIOD", 60.0)  # no round of the clock comes in this test
    goal_cancel = threading.Event()
    clock = StepClock(10.0, goal_cancel, lambda: 1.0)
    with clock.running() as step_cancel:
        assert not step_cancel.is_set()
        goal_cancel.set()
        assert step_cancel.is_set(), "a motion sent now would go out after the cancel"
        assert not clock.expired
